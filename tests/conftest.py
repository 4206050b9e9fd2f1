"""Shared fixtures: run the installed CLI in a subprocess, compose configs in-process."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def cobel_exe() -> list[str]:
    exe = shutil.which("cobel", path=str(Path(sys.executable).parent)) or shutil.which("cobel")
    return [exe] if exe else [sys.executable, "-m", "cobelrun.cli"]


def start_cobel_run(args: list[str], out: Path, results: Path) -> subprocess.Popen:
    """``cobel run ARGS hydra.run.dir=OUT --quiet`` as a real process (signals and exit codes
    are what a test of it checks), its results under ``results``, pipes for stdout/stderr."""
    env = {**os.environ, "COBEL_RESULTS": str(results)}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.Popen([*cobel_exe(), "run", *args, f"hydra.run.dir={out}", "--quiet"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


def stop_on_call(
    monkeypatch: pytest.MonkeyPatch, cls: type, name: str, n: int, exc: type[BaseException]
) -> None:
    """Make ``cls.name`` raise ``exc("stopped")`` on its ``n``-th call (a Ctrl-C or an error
    in the middle of a run); the calls before it run as usual."""
    original = getattr(cls, name)
    calls = {"n": 0}

    def stopping(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise exc("stopped")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, stopping)


@pytest.fixture
def cobel(tmp_path: Path):
    """Run ``cobel ARGS`` in a temporary working directory; return the CompletedProcess."""

    def _run(*args: str, cwd: Path | None = None, env: dict | None = None, timeout: float = 300):
        full_env = {**os.environ, "COBEL_RESULTS": str(tmp_path / "results"), **(env or {})}
        full_env.pop("HYDRA_FULL_ERROR", None)
        return subprocess.run(
            [*cobel_exe(), *args],
            cwd=cwd or tmp_path,
            env=full_env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    return _run
