"""What ``cobel`` loads before it works: `cobel --help` and a tabular run import no deep
learning, rendering or analysis package, and a single run composes its config once."""

from __future__ import annotations

import json
import subprocess
import sys

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
    proc = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args), json.dumps(heavy)],
                          capture_output=True, text=True)  # fmt: skip
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
