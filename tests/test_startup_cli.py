"""A short ``cobel run``'s fixed cost (issue 38): the plain ``cobel run`` read without typer
reads what typer reads, the garbage collector waits for the job and comes back, and what a
tabular run with recording off does not need is not imported."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pytest

from cobelrun import startup
from cobelrun.commands import run as run_command


# ------------------------------------------------------------ the plain `cobel run`, no typer
def _typer_reads(argv: list[str], monkeypatch) -> dict:
    """What typer's ``run`` command hands to :func:`launch_run` for ``cobel ARGV``."""
    from cobelrun.cli import app

    seen: dict = {}

    def launch_run(args, *, debug=False, quiet=False, live=False, port=None):
        seen.update(args=list(args), debug=debug, quiet=quiet, live=live, port=port)
        return 0

    monkeypatch.setattr(run_command, "launch_run", launch_run)
    app(args=argv, standalone_mode=False)
    return seen


@pytest.mark.parametrize(
    "argv",
    [
        ["run"],
        ["run", "task=tmaze_extinction", "seed=3", "task.runs=2"],
        ["run", "--quiet", "task=gridworld", "agent=sr_td"],
        ["run", "task=gridworld", "--debug", "agent.beta=50", "--quiet"],
        ["run", "--live", "task=gridworld"],
        ["run", "-m", "task=tmaze_extinction", "seed=1,2,3"],
        ["run", "--cfg", "job", "task=tmaze_extinction"],
        ["run", "-cd", "some/dir", "-cn", "config", "hydra.run.dir=out/x"],
        ["run", "+env.world.starts=[0]", "~task.monitors.reward", "agent.name=--x"],
        ["run", "-h"],
        ["run", "--info", "defaults"],
        ["run", "--multirun", "task=tmaze_extinction", "seed=1,2"],
    ],
)
def test_a_plain_run_is_read_as_typer_reads_it(argv, monkeypatch) -> None:
    plain = run_command.plain_run(argv)
    assert plain is not None
    assert _typer_reads(argv, monkeypatch) == {
        "args": plain.args,
        "debug": plain.debug,
        "quiet": plain.quiet,
        "live": plain.live,
        "port": None,
    }


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["list"],
        ["--version"],
        ["--allow-target", "mypkg.*", "run", "task=x"],
        ["run", "--help"],
        ["run", "--port", "0", "task=x"],
        ["run", "--port=0", "task=x"],
        ["run", "--allow-target", "mypkg.*", "task=x"],
        ["run", "--quiet=1", "task=x"],
        ["run", "task=x", "--", "seed=1"],
        ["status", "run"],
    ],
)
def test_everything_else_goes_through_typer(argv) -> None:
    assert run_command.plain_run(argv) is None


# ------------------------------------------------------------------ the garbage collector
@pytest.fixture
def collector():
    """Leave the collector as it was: on, not paused here, nothing frozen by the test."""
    was_enabled, frozen = gc.isenabled(), gc.get_freeze_count()
    yield
    startup.resume_gc()
    if gc.get_freeze_count() != frozen:
        gc.unfreeze()
    if was_enabled:
        gc.enable()


def test_the_collector_waits_for_the_job_then_freezes_the_start_up(collector) -> None:
    gc.enable()
    before = gc.get_freeze_count()
    assert startup.pause_gc() is True
    assert not gc.isenabled() and startup.gc_paused()
    assert startup.pause_gc() is False  # paused already: nothing more to do
    made = [[k] for k in range(1000)]  # what a start-up makes (tracked containers)
    startup.resume_gc()
    assert gc.isenabled() and not startup.gc_paused()
    assert gc.get_freeze_count() >= before + len(made)  # moved to the permanent generation
    startup.resume_gc()  # a second resume does nothing
    assert gc.isenabled()


def test_a_collector_turned_off_elsewhere_stays_off(collector) -> None:
    gc.disable()
    frozen = gc.get_freeze_count()
    assert startup.pause_gc() is False
    startup.resume_gc()
    assert not gc.isenabled() and gc.get_freeze_count() == frozen


def test_a_run_that_ends_before_its_job_turns_the_collector_back_on(
    collector, monkeypatch, capsys
) -> None:
    """A bad config fails in validation (before the job): main() resumes the collector."""
    from cobelrun.cli import main

    gc.enable()
    monkeypatch.setenv("COBEL_FAST_EXIT", "0")  # sys.exit: the test goes on
    monkeypatch.setattr(sys, "argv", ["cobel", "run", "task=no_such_task"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("cobel: error: unknown task 'no_such_task'") and err.count("\n") == 1
    assert gc.isenabled() and not startup.gc_paused()


# ------------------------------------------------------------ what a short run imports
NOT_NEEDED = (
    "typer",
    "click",
    "cobelrun.commands.app",
    "foxglove",
    "cobelrun.io.mcap",
    "pyarrow.compute",
    "pandas",
    "torch",
    "matplotlib",
)

PROBE = """
import gc, json, sys
args, watched_modules = json.loads(sys.argv[1]), json.loads(sys.argv[2])
paused = []
import cobelrun.hydra_app as hydra_app
job = hydra_app.job
def watched(*args, **kwargs):
    paused.append(not gc.isenabled())  # the collector is off until the job starts
    return job(*args, **kwargs)
hydra_app.job = watched
sys.argv = ["cobel", *args]
from cobelrun.cli import main
code = 0
try:
    main()
except SystemExit as exc:
    code = exc.code or 0
print(json.dumps({"code": code, "paused_at_job": paused, "enabled": gc.isenabled(),
                  "frozen": gc.get_freeze_count(),
                  "loaded": [m for m in watched_modules if m in sys.modules]}))
"""


def test_a_run_with_recording_off_loads_only_what_it_needs(tmp_path) -> None:
    out = tmp_path / "run"
    # a task whose agent needs no numba: this checks the start-up, not numba's kernel cache
    args = ["run", "task=acquisition_extinction", "task.runs=1", "task.record.steps=false",
            "task.record.mcap=false", "task.save_agents=none", f"hydra.run.dir={out}"]  # fmt: skip
    env = {**os.environ, "COBEL_FAST_EXIT": "0"}  # the probe reads the process after main()
    proc = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args),
                           json.dumps(NOT_NEEDED)], capture_output=True, text=True,
                          env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["code"] == 0 and got["loaded"] == []
    assert got["paused_at_job"] == [True]  # paused for the start-up ...
    assert got["enabled"] and got["frozen"] > 10_000  # ... then the start-up frozen, on again
    assert (out / ".done").is_file() and (out / "trials.parquet").is_file()


# --------------------------------------------------------------------- lazy modules
def test_the_entry_point_and_the_io_package_import_lazily() -> None:
    code = (
        "import sys\n"
        "from cobelrun.cli import main\n"
        "import cobelrun.io.lock\n"
        "assert 'typer' not in sys.modules and 'cobelrun.commands.app' not in sys.modules\n"
        "assert 'foxglove' not in sys.modules and 'cobelrun.io.mcap' not in sys.modules\n"
        "from cobelrun.io import McapRecorder, ParquetStreamWriter, config_hash\n"
        "from cobelrun.cli import app\n"
        "import typer\n"
        "assert isinstance(app, typer.Typer) and McapRecorder.__name__ == 'McapRecorder'\n"
        "import cobelrun.cli, cobelrun.io\n"
        "for mod, name in ((cobelrun.cli, 'no_such_name'), (cobelrun.io, 'nothing')):\n"
        "    try:\n"
        "        getattr(mod, name)\n"
        "    except AttributeError:\n"
        "        pass\n"
        "    else:\n"
        "        raise SystemExit(f'{mod.__name__}.{name} exists')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize(
    "values", [["acquisition", "extinction"], ["a", "", "bb"], ["é€", "x"], [""], ["one"]]
)
@pytest.mark.parametrize("n", [0, 1, 7, 1000])
def test_string_columns_by_index_equal_arrows_own(values, n) -> None:
    from cobelrun.io.parquet import _take_strings

    index = np.random.default_rng(n).integers(0, len(values), n).astype(np.int32)
    got = _take_strings(values, index)
    assert got is not None
    got.validate(full=True)
    assert got.equals(pa.array([values[i] for i in index], pa.string()))
