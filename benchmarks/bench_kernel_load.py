"""What loading the compiled tabular kernels costs a process, and a short ``cobel run``.

Run on demand (not a test)::

    python benchmarks/bench_kernel_load.py [--repeats 5] [--baseline /path/to/other/checkout]

Fresh processes, interleaved round by round, medians (wall seconds; CPU = user + system of the
child from ``os.wait4``):

* ``import numba``; the numba floor: ``import numba`` and the first call of one cached
  ``@njit(cache=True)`` function (numba's once-per-process start: its typing and lowering
  registries, LLVM);
* per kernel family, in one process: the import of its kernel module and the first trial of
  its agent (the first one pays the numba floor), then the first trial of each further family
  (what one more kernel costs: loading its machine code from numba's cache);
* ``cobel run task=tmaze_extinction task.runs=1`` with recording off, whole process, and the
  manifest's phase time (the run loop); with ``--baseline`` the same command against another
  checkout (``PYTHONPATH`` set to it), interleaved.

Every kernel is compiled once beforehand (``cache=True``) so only cache loads are timed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

NUMBA_FLOOR = """
import numba
@numba.njit(cache=True)
def f(x):
    return x + 1
f(1)
"""

FAMILIES = """
import json, sys, time
t = time.perf_counter()
import numpy as np
from cobelrun.agents import DynaQ, SRMB, SRTD, Sarsa
from cobelrun.envs import GridWorldEnv, open_field
out = {"import cobelrun.agents": time.perf_counter() - t}
mods = {"DynaQ": "kernels", "SRTD": "sr_kernels", "SRMB": "srmb_kernels", "Sarsa": "td_kernels"}
order = sys.argv[1].split(",")
import importlib
for name in order:
    cls = {"DynaQ": DynaQ, "SRTD": SRTD, "SRMB": SRMB, "Sarsa": Sarsa}[name]
    t = time.perf_counter()
    importlib.import_module("cobelrun.agents." + mods[name])
    out[name + " module import"] = time.perf_counter() - t
    env = GridWorldEnv(open_field(9, 9, starts=[0], goal=80))
    agent = cls(env, seed=0)
    t = time.perf_counter()
    agent.train(1, 20)
    out[name + " first trial"] = time.perf_counter() - t
print(json.dumps(out))
"""


def timed_cpu(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """Wall and CPU seconds (``os.wait4``) of a child process, and its stdout."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as fout, tempfile.TemporaryFile("w+") as ferr:
        proc = subprocess.Popen(cmd, stdout=fout, stderr=ferr, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        fout.seek(0)
        ferr.seek(0)
        out, err = fout.read(), ferr.read()
    if os.waitstatus_to_exitcode(status):
        raise SystemExit(f"{' '.join(cmd[:4])} failed: {err.strip()[-400:]}")
    return wall, usage.ru_utime + usage.ru_stime, out


def env_for(path: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(path)
    return env


def cobel_run(path: Path, tmp: Path, tag: str) -> dict[str, float]:
    out = tmp / f"run_{tag}_{time.monotonic_ns()}"
    cmd = [sys.executable, "-m", "cobelrun.cli", "run", "task=tmaze_extinction", "task.runs=1",
           "task.record.steps=false", "task.record.mcap=false", "task.save_agents=none",
           f"hydra.run.dir={out}"]  # fmt: skip
    wall, cpu, _ = timed_cpu(cmd, env_for(path))
    manifest = json.loads((out / "manifest.json").read_text())
    return {"wall": wall, "cpu": cpu, "loop": sum(manifest["phase_wall_time_s"].values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", type=Path, help="another checkout to compare cobel run with")
    args = ap.parse_args()
    here = env_for(ROOT)
    order = "DynaQ,SRTD,Sarsa,SRMB"
    scripts = Path(tempfile.mkdtemp(prefix="cobel_kernel_load_"))  # numba caches a file's code
    floor, families = scripts / "numba_floor.py", scripts / "families.py"
    floor.write_text(NUMBA_FLOOR)
    families.write_text(FAMILIES)
    # compile everything once (cache=True), so that only cache loads are timed
    timed_cpu([sys.executable, str(families), order], here)
    timed_cpu([sys.executable, str(floor)], here)
    rows: dict[str, list[float]] = {}

    def add(key: str, value: float) -> None:
        rows.setdefault(key, []).append(value)

    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        if args.baseline:
            cobel_run(args.baseline, tmp, "base")  # its kernels compiled once
        cobel_run(ROOT, tmp, "this")
        for rep in range(args.repeats):
            w, c, _ = timed_cpu([sys.executable, "-c", "import numba"], here)
            add("import numba: wall", w)
            add("import numba: CPU", c)
            w, c, _ = timed_cpu([sys.executable, str(floor)], here)
            add("numba floor (import + first cached call): wall", w)
            add("numba floor: CPU", c)
            _, _, out = timed_cpu([sys.executable, str(families), order], here)
            for k, v in json.loads(out).items():
                add(k, v)
            for tag, path in (("this", ROOT), ("baseline", args.baseline)):
                if path is None:
                    continue
                r = cobel_run(path, tmp, tag)
                for k, v in r.items():
                    add(f"cobel run task=tmaze_extinction task.runs=1 ({tag}): {k}", v)
            print(f"round {rep + 1}/{args.repeats}", file=sys.stderr, flush=True)
    shutil.rmtree(scripts, ignore_errors=True)
    print("| measurement | median s | min s |\n|---|---:|---:|")
    for k, v in rows.items():
        print(f"| {k} | {statistics.median(v):.3f} | {min(v):.3f} |")


if __name__ == "__main__":
    main()
