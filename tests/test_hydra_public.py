"""cobel uses only Hydra's public API (the project's rule: no library's private internals).

Hydra 1.3 keeps some of what a runner needs in private modules (``hydra._internal``); cobel
has its own equivalents of those, each checked here against Hydra's (imported in these tests
only, to compare).
"""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: cobel's own code that Hydra runs: the package and its Hydra plugins
SOURCES = [ROOT / "cobelrun", ROOT / "hydra_plugins"]


def private_hydra_uses(source: str) -> list[str]:
    """The private Hydra names ``source`` uses: imports of ``hydra._internal`` (or any module
    or name with a leading underscore under ``hydra``), and ``hydra._internal`` in any text
    (``importlib``, strings)."""
    found = [f"text {m.group(0)}" for m in re.finditer(r"hydra\._internal[\w.]*", source)]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
            names: list[str] = []
        elif isinstance(node, ast.ImportFrom) and not node.level:
            mods, names = [node.module or ""], [a.name for a in node.names]
        else:
            continue
        for mod in mods:
            parts = mod.split(".")
            if parts[0] != "hydra":
                continue
            if any(p.startswith("_") for p in parts[1:]):
                found.append(f"import {mod}")
            found += [f"from {mod} import {n}" for n in names if n.startswith("_")]
    return found


def test_the_check_finds_private_uses():
    assert private_hydra_uses("from hydra._internal.utils import _run_hydra\n")
    assert private_hydra_uses("def f():\n    import hydra._internal.hydra as h\n")
    assert private_hydra_uses("from hydra.main import _get_rerun_conf\n")
    assert private_hydra_uses("spec = 'hydra._internal.core_plugins'\n")
    assert not private_hydra_uses("from hydra.core.utils import run_job\nimport hydra\n")
    assert not private_hydra_uses("from joblib import _private  # not Hydra\n")


def test_no_private_hydra_in_cobel():
    uses = {
        str(f.relative_to(ROOT)): private_hydra_uses(f.read_text())
        for src in SOURCES
        for f in sorted(src.rglob("*.py"))
    }
    assert len(uses) > 50  # the package was found
    assert {f: u for f, u in uses.items() if u} == {}


def test_cli_parser_has_hydras_flags():
    """`cobel run` reads Hydra's flags itself before Hydra runs: the same flags as Hydra's."""
    from hydra._internal.utils import get_args_parser

    from cobelrun.hydra_app import cli_parser

    def flags(parser):
        return {
            (tuple(sorted(a.option_strings)), a.dest, a.nargs, tuple(a.choices or ()), a.const)
            for a in parser._actions
        }

    ours, theirs = cli_parser(), get_args_parser()
    assert flags(ours) == flags(theirs)
    theirs.prog = ours.prog
    assert ours.format_usage() == theirs.format_usage()
    for args in (
        ["-m", "-cd", "x", "--cfg", "job", "-i", "plugins", "a=1", "b=2"],
        ["--config-name=c", "-cp", "y", "--resolve", "-p", "agent", "-sc"],
        ["-i"],
    ):
        assert vars(ours.parse_args(args)) == vars(theirs.parse_args(args))


def _run_job() -> None:
    raise ValueError("boom") from KeyError("cause")


def run_job() -> None:  # named as Hydra's, whose frames the report starts after
    _run_job()


def _top() -> None:
    run_job()


def _compact() -> None:
    from hydra.errors import ConfigCompositionException
    from omegaconf.errors import ValidationError

    raise ConfigCompositionException("boom") from ValidationError("Value 'cause' is not an int")


@pytest.mark.parametrize("func", [_top, _run_job, _compact])
def test_unexpected_errors_are_reported_as_hydra_does(func, capsys, monkeypatch):
    from hydra._internal.utils import run_and_report

    from cobelrun.hydra_app import report_unexpected

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "gettrace", lambda: None)  # (Hydra raises under a tracer)
    with pytest.raises(SystemExit) as ours:
        report_unexpected(func)
    got = capsys.readouterr().err
    with pytest.raises(SystemExit) as theirs:
        run_and_report(func)
    assert ours.value.code == theirs.value.code == 1

    def same(text: str) -> str:  # the reporter's own frame (a whole traceback) has its name
        return re.sub(r'File "[^"]+", line \d+, in (run_and_report|report_unexpected)',
                      "REPORTER", text)  # fmt: skip

    assert same(got) == same(capsys.readouterr().err)
    assert "boom" in got and "cause" in got
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(Exception, match="boom"):
        report_unexpected(func)


CALLBACK = """
import json, os
from hydra.experimental.callback import Callback

class Record(Callback):
    def __init__(self, name):
        self.name = name
    def _log(self, event):
        with open(os.environ["CB_LOG"], "a") as f:
            f.write(json.dumps([self.name, event]) + "\\n")
    def on_run_start(self, config, **kw): self._log("run_start")
    def on_job_start(self, config, **kw): self._log("job_start")
    def on_job_end(self, config, job_return, **kw): self._log(f"job_end {job_return.status.name}")
    def on_run_end(self, config, **kw): self._log("run_end")
"""


def test_a_single_run_calls_hydras_callbacks(cobel, tmp_path):
    (tmp_path / "cbmod.py").write_text(CALLBACK)
    log = tmp_path / "cb.jsonl"
    out = tmp_path / "run"
    proc = cobel("run", "task=tmaze_extinction", "task.runs=1", f"hydra.run.dir={out}", "--quiet",
                 "--allow-target", "cbmod.Record",  # the user's own class: allowed by name
                 "+hydra.callbacks.a._target_=cbmod.Record", "+hydra.callbacks.a.name=a",
                 "+hydra.callbacks.b._target_=cbmod.Record", "+hydra.callbacks.b.name=b",
                 env={"PYTHONPATH": str(tmp_path), "CB_LOG": str(log)})  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    events = [tuple(json.loads(line)) for line in log.read_text().splitlines()]
    assert events == [("a", "run_start"), ("b", "run_start"), ("a", "job_start"),
                      ("b", "job_start"), ("b", "job_end COMPLETED"), ("a", "job_end COMPLETED"),
                      ("b", "run_end"), ("a", "run_end")]  # fmt: skip
    assert (out / ".done").is_file()
