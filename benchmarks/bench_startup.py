"""Start-up: ``cobel run task=tmaze_extinction`` end to end against the floors it stands on.

Run on demand (not a test)::

    python benchmarks/bench_startup.py [--repeats 10] [--baseline CHECKOUT]

Whole processes, interleaved round by round (so machine load hits all alike), median wall time
and median CPU time (user + system of the child, from ``os.wait4``) of

* ``python -c pass`` (the interpreter), ``python -c "import cobelrun"``;
* the numba floor: ``import numba`` and one call of a cached ``@njit(cache=True)`` function
  (what any process that runs compiled code pays; the function is compiled once beforehand);
* the Hydra floor: ``import cobelrun.hydra_app`` and one composition of the task's config;
* ``cobel --help``; ``cobel run task=tmaze_extinction`` (100 runs, everything recorded);
  with ``--baseline CHECKOUT`` the same run from another checkout of cobel (``PYTHONPATH``).

cobel's bytecode is compiled first (``compileall``), as an installed package has it (a shell
with ``PYTHONDONTWRITEBYTECODE=1`` would otherwise compile a checkout in every process).

Then one run of the task split into stages: imports by top-level package (``python -X
importtime``, the modules' own times), and, in a process that imported those modules first,
the time of Hydra's composition (and how often it runs), building and checking the task,
numba's cache load, the run loop (the manifest's ``wall_time_s``: simulation, recording and
the final writes), the end-of-run summary and the rest.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

NUMBA_FLOOR = """
import numba
@numba.njit(cache=True)
def f(x):
    return x + 1
f(1)
"""

HYDRA_FLOOR = """
from cobelrun.hydra_app import composer
with composer() as compose:
    compose(["task=tmaze_extinction"], return_hydra_config=True)
"""

# runs `cobel run ARGS` in this process after importing the modules of a previous run (so
# that the stages below exclude imports), timing a few functions of Hydra, numba and cobel
STAGES = """
import collections, functools, importlib, json, sys, time
mods, args = json.loads(sys.argv[1]), json.loads(sys.argv[2])
for m in mods:
    try:
        importlib.import_module(m)
    except Exception:
        pass
stats = collections.defaultdict(lambda: [0, 0.0])
def wrap(spec):
    modname, qual, label = spec.split(":")
    owner = importlib.import_module(modname)
    *path, name = qual.split(".")
    for p in path:
        owner = getattr(owner, p)
    fn = getattr(owner, name)
    @functools.wraps(fn)
    def timed(*a, **k):
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            stats[label][0] += 1
            stats[label][1] += time.perf_counter() - t
    setattr(owner, name, timed)
for spec in json.loads(sys.argv[3]):
    wrap(spec)
sys.argv = ["cobel", "run", *args]
from cobelrun.cli import main
t0 = time.perf_counter()
try:
    main()
except SystemExit:
    pass
stats["main"] = [1, time.perf_counter() - t0]
print("STAGES " + json.dumps(stats))
"""

WRAPPED = [
    "hydra._internal.hydra:Hydra.compose_config:compose",
    "cobelrun.runner:build_task:build task",
    "cobelrun.hydra_app:validate:validate",
    "numba.core.caching:Cache.load_overload:numba cache load",
    "cobelrun.runner:run:runner.run",
    "cobelrun.runner:execute:execute",
    "cobelrun.recorder:RunRecorder.close:recorder close",
    "cobelrun.hydra_app:log_end:log end",
    "cobelrun.commands.summary:print_run_summary:summary",
]


def cobel_cmd() -> list[str]:
    exe = shutil.which("cobel", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "cobelrun.cli"]


def timed_child(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall and CPU (user + system) seconds of one child process."""
    with tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            err.seek(0)
            raise SystemExit(f"{' '.join(cmd)} failed:\n{err.read().decode()[-2000:]}")
    return wall, usage.ru_utime + usage.ru_stime


#: the run whose start-up this measures
RUN = "cobel run task=tmaze_extinction"


def compile_bytecode(checkout: Path) -> None:
    """Compile ``checkout``'s ``cobelrun`` to bytecode (as ``pip install`` does)."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(checkout / "cobelrun")],
                   check=True, stdout=subprocess.DEVNULL)  # fmt: skip


def commands(tmp: Path, baseline: Path | None = None) -> dict[str, list[str]]:
    py = sys.executable
    floor = tmp / "numba_floor.py"
    floor.write_text(NUMBA_FLOOR)
    run = [*cobel_cmd(), "run", "task=tmaze_extinction", f"hydra.run.dir={tmp / 'run'}"]
    extra = {f"{RUN} (baseline)": ["env", f"PYTHONPATH={baseline}", *run]} if baseline else {}
    return {
        "python -c pass": [py, "-c", "pass"],
        "import cobelrun": [py, "-c", "import cobelrun"],
        "numba floor": [py, str(floor)],
        "hydra floor": [py, "-c", HYDRA_FLOOR],
        "cobel --help": [*cobel_cmd(), "--help"],
        RUN: run,
        **extra,
    }


def whole_processes(
    repeats: int, tmp: Path, baseline: Path | None = None
) -> dict[str, dict[str, float]]:
    cmds = commands(tmp, baseline)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp / "numba_cache")}
    for cmd in cmds.values():  # warm-up: compile the floor's function, fill the file cache
        shutil.rmtree(tmp / "run", ignore_errors=True)
        timed_child(cmd, env)
    samples: dict[str, list[tuple[float, float]]] = {k: [] for k in cmds}
    for _ in range(repeats):
        for name, cmd in cmds.items():
            shutil.rmtree(tmp / "run", ignore_errors=True)
            samples[name].append(timed_child(cmd, env))
    return {
        name: {"wall_s": statistics.median(w for w, _ in s),
               "cpu_s": statistics.median(c for _, c in s),
               "min_wall_s": min(w for w, _ in s)}
        for name, s in samples.items()
    }  # fmt: skip


def import_breakdown(tmp: Path) -> tuple[dict[str, float], list[str]]:
    """Seconds of import per top-level package (their modules' own times) and the modules."""
    out = tmp / "imports"
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-X", "importtime", "-m", "cobelrun.cli", "run",
           "task=tmaze_extinction", f"hydra.run.dir={out}"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    per_pkg: collections.Counter[str] = collections.Counter()
    modules = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "self [us]" in line:
            continue
        own, _, name = line.split("|")
        name = name.strip()
        modules.append(name)
        per_pkg[name.split(".")[0]] += int(own.split(":")[1]) / 1e6
    return dict(per_pkg.most_common()), modules


def stage_breakdown(tmp: Path, modules: list[str]) -> dict[str, list[float]]:
    out = tmp / "stages"
    shutil.rmtree(out, ignore_errors=True)
    args = ["task=tmaze_extinction", f"hydra.run.dir={out}"]
    # the probe reads the stages after main() returns: keep the teardown (no fast exit)
    env = {**os.environ, "COBEL_FAST_EXIT": "0"}
    proc = subprocess.run([sys.executable, "-c", STAGES, json.dumps(modules), json.dumps(args),
                           json.dumps(WRAPPED)], capture_output=True, text=True, check=True,
                          env=env)  # fmt: skip
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("STAGES "))
    stats = json.loads(line.removeprefix("STAGES "))
    manifest = json.loads((out / "manifest.json").read_text())
    stats["run loop (manifest wall_time_s)"] = [1, float(manifest["wall_time_s"])]
    return stats


def measure(repeats: int = 10, baseline: Path | None = None) -> dict:
    compile_bytecode(HERE.parent)
    if baseline is not None:
        compile_bytecode(baseline)
    with tempfile.TemporaryDirectory(prefix="cobel-startup-") as name:
        tmp = Path(name)
        procs = whole_processes(repeats, tmp, baseline)
        imports, modules = import_breakdown(tmp)
        stages = stage_breakdown(tmp, modules)
    run = procs["cobel run task=tmaze_extinction"]
    return {
        "repeats": repeats,
        "processes": procs,
        "imports_s": imports,
        "stages": stages,
        "run_over_floors": {k: run["wall_s"] / v["wall_s"] for k, v in procs.items()},
        "goal_s": 0.8,
    }


def report(res: dict) -> None:
    print(f"whole processes, median of {res['repeats']} (wall / CPU user+sys, seconds):")
    for name, r in res["processes"].items():
        print(
            f"  {name:34s} {r['wall_s']:6.3f} / {r['cpu_s']:6.3f}   (fastest wall {r['min_wall_s']:.3f})"
        )
    run = res["processes"]["cobel run task=tmaze_extinction"]
    print(f"  goal: cobel run <= {res['goal_s']} s; measured {run['wall_s']:.3f} s wall, "
          f"{run['cpu_s']:.3f} s CPU")  # fmt: skip
    imports = res["imports_s"]
    top = ", ".join(f"{k} {v:.3f}" for k, v in list(imports.items())[:12])
    print(f"imports, own time per package (total {sum(imports.values()):.3f} s): {top}")
    st = res["stages"]
    print("stages of one run (s; imports done beforehand; nested: execute is in runner.run):")
    for k, (n, s) in st.items():
        print(f"  {k:34s} {s:7.3f}" + (f"   x{n}" if n != 1 else ""))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--baseline", type=Path, metavar="CHECKOUT",
                    help="also time the run from this checkout of cobel (interleaved)")  # fmt: skip
    args = ap.parse_args(argv)
    res = measure(args.repeats, args.baseline)
    report(res)
    out = HERE / "results" / "startup.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
