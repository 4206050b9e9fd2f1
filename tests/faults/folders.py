"""A real run folder and a real sweep folder, made once per test session by tiny runs of the
installed CLI, and a way to run cobel's commands in-process on copies of them.

``invoke(args)`` runs ``cobel ARGS`` through typer's test runner and returns
``(exit code, output, exception)``: the exception is the one that escaped the command (a
traceback the user would have seen), None when it ended with a clean exit.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import cobel_exe

#: the tiny task of issue 31's cases (T = cobel run task=tmaze_extinction ...)
TINY = ("task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.phases.1.trials=3")  # fmt: skip


def _cobel(root: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "COBEL_RESULTS": str(root / "results")}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run([*cobel_exe(), *args], cwd=root, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip


def make_run(root: Path, *extra: str) -> Path:
    """A completed run folder of the tiny task under ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    proc = _cobel(root, "run", "--quiet", *TINY, *extra, f"hydra.run.dir={root / 'run'}")
    assert proc.returncode == 0, proc.stderr
    return root / "run"


def make_sweep(root: Path) -> Path:
    """A completed sweep folder of the tiny task (two jobs: seed 0, 1) under ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    proc = _cobel(root, "run", "-m", "--quiet", *TINY, "seed=0,1",
                  f"hydra.sweep.dir={root / 'sweep'}", "hydra/launcher=basic")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root / "sweep"


@pytest.fixture(scope="session")
def real_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run(tmp_path_factory.mktemp("real-run"))


@pytest.fixture(scope="session")
def real_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_sweep(tmp_path_factory.mktemp("real-sweep"))


def copy_folder(src: Path, dst: Path) -> Path:
    """A copy of a run or sweep folder (symlinks kept as links)."""
    shutil.copytree(src, dst, symlinks=True)
    return dst


def invoke(*args: str) -> tuple[int, str, BaseException | None]:
    """``cobel ARGS`` in-process: (exit code, output, escaped exception or None)."""
    from typer.testing import CliRunner

    from cobelrun.cli import app

    result = CliRunner().invoke(app, list(args))
    exc = result.exception
    if isinstance(exc, SystemExit):
        exc = None
    return result.exit_code, result.output, exc
