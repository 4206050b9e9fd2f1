"""``cobel`` in the test's own process (typer's CliRunner), for CLI tests that need no separate
process: no interpreter start-up, no imports paid again. Tests of signals, start-up and a real
process's exit codes keep the ``cobel`` fixture (tests/conftest.py), which starts one."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


@pytest.fixture
def cli(tmp_path, monkeypatch):
    """``cobel ARGS`` in this process in a temporary working directory, results under
    ``tmp_path/results``: a CompletedProcess (returncode, stdout, stderr) like ``cobel``'s."""
    from typer.testing import CliRunner

    from cobelrun.cli import app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COBEL_RESULTS", str(tmp_path / "results"))
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)

    def _run(
        *args: str, env: dict[str, str] | None = None, cwd: Path | None = None
    ) -> subprocess.CompletedProcess:
        """``env``: variables set for this call only; ``cwd``: its working directory."""
        with monkeypatch.context() as m:
            for key, value in (env or {}).items():
                m.setenv(key, value)
            if cwd is not None:
                m.chdir(cwd)
            # the command line a run's manifest records (and NWB export reads back)
            m.setattr(sys, "argv", ["cobel", *args])
            result = CliRunner().invoke(app, list(args))
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise result.exception
        return subprocess.CompletedProcess(
            ["cobel", *args], result.exit_code, result.stdout, result.stderr
        )

    return _run
