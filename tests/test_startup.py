"""What ``cobel`` loads before it works: `cobel --help` and a tabular run import no deep
learning, rendering or analysis package, and a single run composes its config once."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

HEAVY = ("torch", "stable_baselines3", "pybullet", "pandas", "matplotlib")

# counts Hydra's compositions (each ~0.1 s; `cobel run` only) and lists the heavy packages
# imported after ``cobel ARGS``
PROBE = """
import json, sys
count = [0]
if json.loads(sys.argv[1])[0] == "run":
    from hydra._internal.hydra import Hydra
    compose = Hydra.compose_config
    def counted(self, *args, **kwargs):
        count[0] += 1
        return compose(self, *args, **kwargs)
    Hydra.compose_config = counted
heavy = json.loads(sys.argv[2])
sys.argv = ["cobel", *json.loads(sys.argv[1])]
from cobelrun.cli import main
code = 0
try:
    main()
except SystemExit as exc:
    code = exc.code or 0
heavy = [m for m in heavy if m in sys.modules]
print(json.dumps({"code": code, "composed": count[0], "heavy": heavy}))
"""


def _probe(args: list[str], heavy: tuple[str, ...] = HEAVY) -> dict:
    # the probe looks at sys.modules after main(): keep the process (no fast exit)
    env = {**os.environ, "COBEL_FAST_EXIT": "0"}
    proc = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args), json.dumps(heavy)],
                          capture_output=True, text=True, env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_tabular_run_composes_once_and_imports_nothing_heavy(tmp_path) -> None:
    out = tmp_path / "run"
    got = _probe(["run", "task=tmaze_extinction", "task.runs=2", f"hydra.run.dir={out}"])
    assert got == {"code": 0, "composed": 1, "heavy": []}
    assert (out / ".done").is_file()  # completed
    assert (out / ".hydra" / "hydra.yaml").is_file()
    hydra_yaml = (out / ".hydra" / "hydra.yaml").read_text()
    assert f"hydra.run.dir='{out}'" in hydra_yaml and "hydra.mode=RUN" in hydra_yaml


def test_help_imports_no_engine() -> None:
    got = _probe(["--help"], (*HEAVY, "numba", "hydra", "pyarrow", "gymnasium"))
    assert got == {"code": 0, "composed": 0, "heavy": []}


# ---------------------------------------------------------------------- leaving the process
def test_exit_status_reads_codes_as_sys_exit_does() -> None:
    from cobelrun.cli import _exit_status

    assert _exit_status(None) == (0, None)
    assert _exit_status(0) == (0, None)
    assert _exit_status(2) == (2, None)
    assert _exit_status(130) == (130, None)
    assert _exit_status(-1) == (255, None)
    assert _exit_status("bad") == (1, "bad")


TEARDOWN = """
import sys, threading
from cobelrun.cli import _teardown_needed
case = sys.argv[1]
if case == "thread":
    stop = threading.Event()
    threading.Thread(target=stop.wait).start()  # a non-daemon thread still running
if case == "pool":
    import joblib
print(_teardown_needed())
if case == "thread":
    stop.set()
"""


@pytest.mark.parametrize(("case", "env", "needed"), [
    ("plain", {}, False), ("plain", {"COBEL_FAST_EXIT": "0"}, True), ("thread", {}, True),
    ("pool", {}, True),
])  # fmt: skip
def test_the_teardown_is_kept_when_something_may_need_it(case, env, needed) -> None:
    base = {k: v for k, v in os.environ.items() if k != "COBEL_FAST_EXIT"}
    proc = subprocess.run([sys.executable, "-c", TEARDOWN, case], capture_output=True,
                          text=True, env={**base, **env})  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(needed)


FAST_EXIT = """
import sys, threading
sys.argv = ["cobel", *sys.argv[1:]]
from cobelrun.cli import main
import atexit
atexit.register(lambda: print("TEARDOWN", flush=True))  # runs only with the teardown
main()
"""


def test_a_finished_command_leaves_without_the_teardown_and_loses_no_output(tmp_path) -> None:
    out = tmp_path / "run"
    args = ["run", "task=tmaze_extinction", "task.runs=2", f"hydra.run.dir={out}"]
    env = {k: v for k, v in os.environ.items() if k != "COBEL_FAST_EXIT"}
    fast = subprocess.run([sys.executable, "-c", FAST_EXIT, *args], capture_output=True,
                          text=True, env=env)  # fmt: skip
    assert fast.returncode == 0, fast.stderr
    assert "TEARDOWN" not in fast.stdout
    assert fast.stdout.strip() == str(out)  # the folder, for pipes
    assert "done in" in fast.stderr and fast.stderr.rstrip().endswith("status and tables")
    assert (out / ".done").is_file()
    assert "phase extinction" in (out / "cobel.log").read_text()  # the log is complete
    # a bad config: the one-line error on stderr and exit code 2, still without the teardown
    bad = subprocess.run([sys.executable, "-c", FAST_EXIT, "run", "task=no_such_task"],
                         capture_output=True, text=True, env=env)  # fmt: skip
    assert bad.returncode == 2 and "TEARDOWN" not in bad.stdout
    assert bad.stderr.startswith("cobel: error:") and "no_such_task" in bad.stderr
    # COBEL_FAST_EXIT=0: the normal teardown, the same exit code
    kept = subprocess.run([sys.executable, "-c", FAST_EXIT, "run", "task=no_such_task"],
                          capture_output=True, text=True, env={**env, "COBEL_FAST_EXIT": "0"})  # fmt: skip
    assert kept.returncode == 2 and "TEARDOWN" in kept.stdout
