"""Bad input and hostile places: one line, non-zero exit, nothing written (issue 15, items 1-3).

Most checks run in-process against ``cobel run``'s up-front validation
(:func:`cobelrun.compose.validate`, the same code the CLI runs before Hydra creates a folder);
a few go through the real CLI to see the one line and the exit code.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pytest

from cobelrun.compose import composer, validate
from cobelrun.errors import CobelError, ConfigError
from cobelrun.safety import check_inside, check_memory, estimate_memory, results_root
from cobelrun.schema import validate_run

TINY = ["task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.phases.1.trials=3"]  # fmt: skip


def one_line_error(proc) -> str:
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    return lines[0]


# -- nulls ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "override, message",
    [
        ("agent.epsilon=null", "agent.epsilon must not be null"),
        ("agent.gamma=null", "agent.gamma must not be null"),
        ("env=null", "env must name a config, got null"),
        ("agent=null", "agent must name a config, got null"),
        ("protocol=null", "protocol must name a config, got null"),
        ("task.protocol=null", "has no protocol"),
        ("task.protocol.max_steps=null", "task.protocol.max_steps must not be null"),
        ("hydra/launcher=null", "cannot compose the config"),
    ],
)
def test_null_values_are_one_line(override, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        validate([*TINY, override], multirun=False)


def test_null_in_a_sweep_is_one_line():
    with pytest.raises(ConfigError, match="unknown agent 'null'; allowed: 'actor_critic', 'dqn'"):
        validate([*TINY, "agent=dyna_q,null"], multirun=True)


# -- YAML syntax errors in a user's own conf/ ------------------------------------------------
@pytest.mark.parametrize(
    "text, where",
    [
        ("task:\n  name: mine\n  runs: [1, 2\n", "line 5, column 1"),
        ("task:\n  name: mine\n\truns: 2\n", "line 4, column 1"),
        ("task: {name: mine\n", "line 3, column 1"),
    ],
)
def test_yaml_error_names_file_line_and_column(tmp_path, monkeypatch, text, where):
    conf = tmp_path / "conf" / "task"
    conf.mkdir(parents=True)
    (conf / "mine.yaml").write_text("# @package _global_\n" + text)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as err:
        validate(["task=mine"], multirun=False)
    msg = str(err.value)
    assert msg.startswith("YAML syntax error in ") and str(conf / "mine.yaml") in msg, msg
    assert where in msg and "\n" not in msg


# -- sizes ------------------------------------------------------------------------------------
def test_absurd_run_count_is_refused():
    with pytest.raises(ConfigError, match=r"task.runs must be an integer <= 2147483647"):
        validate([*TINY, f"task.runs={10**12}"], multirun=False)


def test_memory_estimate_refuses_with_the_estimate_and_the_limit():
    overrides = [*TINY, "task.protocol.phases.0.trials=1000000", "task.protocol.max_steps=2000000"]
    with pytest.raises(ConfigError) as err:
        validate(overrides, multirun=False)
    msg = str(err.value)
    assert "would allocate about 232.8 TiB" in msg and "available" in msg, msg
    assert "task.protocol.phases[0]" in msg


def test_memory_estimate_is_what_the_phase_allocates():
    with composer() as compose:
        cfg = compose([*TINY, "task.protocol.phases.0.trials=1000", "task.protocol.max_steps=50"])
    proto = validate_run(cfg).task.protocol
    need, what = estimate_memory(proto)
    assert need == 1000 * 50 * 128 and "phases[0]" in what
    check_memory(proto, limit=10 * need)  # fits
    with pytest.raises(
        ConfigError, match=r"6.1 MiB .* more than the 4.0 MiB .* \(80% of 5.0 MiB available\)"
    ):
        check_memory(proto, limit=5 * 2**20)


def test_memory_limit_from_the_environment(monkeypatch):
    monkeypatch.setenv("COBEL_MEMORY_LIMIT", "1M")
    with pytest.raises(ConfigError, match=r"more than the 819\.2 KiB"):
        validate([*TINY, "task.protocol.phases.0.trials=1000"], multirun=False)


def test_memory_limit_set_between_two_checks_applies_at_once(monkeypatch):
    """/proc/meminfo is read at most once a second, COBEL_MEMORY_LIMIT at every check."""
    from cobelrun import safety
    from cobelrun.safety import available_memory

    monkeypatch.setattr(safety, "MEMORY_READ_TTL", 3600.0)  # no second read during the test
    monkeypatch.setattr(safety, "_MEMORY_READ", [-float("inf"), []])
    monkeypatch.delenv("COBEL_MEMORY_LIMIT", raising=False)
    free = available_memory()
    monkeypatch.setenv("COBEL_MEMORY_LIMIT", "1M")
    assert available_memory() == 2**20
    monkeypatch.delenv("COBEL_MEMORY_LIMIT")
    assert available_memory() == free  # the system's reading of the first call, reused


# -- names and paths ------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../x", "/etc", "a/b", ".hidden", "", "x" * 101, "ü ber"])
def test_unsafe_task_names_are_refused(name):
    with pytest.raises(ConfigError, match=r"task\.name must be a (name of letters|non-empty)"):
        validate([*TINY, f"task.name='{name}'"], multirun=False)


def test_empty_results_root_is_refused():
    with pytest.raises(CobelError, match="COBEL_RESULTS is set but empty"):
        results_root({"COBEL_RESULTS": ""})
    with pytest.raises(CobelError, match="COBEL_RESULTS is set but empty"):
        results_root({"COBEL_RESULTS": "  "})
    assert results_root({}).is_absolute()


def test_symlink_escape_is_refused(tmp_path):
    root, outside = tmp_path / "results", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    (root / "task").symlink_to(outside)
    with pytest.raises(CobelError, match="outside the results root"):
        check_inside(root / "task" / "run", root)
    with pytest.raises(CobelError, match="outside the results root"):
        check_inside(root / ".." / "outside" / "run", root)
    assert check_inside(root / "task2" / "run", root) == (root / "task2" / "run").resolve()


def test_cli_empty_results_root_and_escapes_write_nothing(cobel, tmp_path):
    line = one_line_error(cobel("run", *TINY, env={"COBEL_RESULTS": ""}))
    assert "COBEL_RESULTS is set but empty" in line
    line = one_line_error(cobel("run", *TINY, "task.name=../../x"))
    assert "task.name must be a name" in line
    results = tmp_path / "results"
    results.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (results / "tmaze_extinction").symlink_to(tmp_path / "elsewhere")
    line = one_line_error(cobel("run", *TINY))
    assert "outside the results root" in line
    line = one_line_error(cobel("run", "-m", *TINY, "seed=1,2"))
    assert "the sweep folder" in line and "outside the results root" in line
    assert list((tmp_path / "elsewhere").iterdir()) == []
    assert not (tmp_path / "x").exists() and not (tmp_path.parent / "x").exists()


# -- full disk and read-only folders ---------------------------------------------------------
def test_full_disk_in_process(tmp_path, monkeypatch):
    """The third table part hits ENOSPC: one CobelError line, manifest failed, parts kept."""
    import cobelrun.io.parquet as parquet
    from cobelrun.runner import run

    real, calls = parquet._write_part, []

    def failing(table: pa.Table, path: Path) -> None:
        calls.append(path)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real(table, path)

    monkeypatch.setattr(parquet, "_write_part", failing)
    with composer() as compose:
        cfg = compose(["task=tmaze_extinction", "task.runs=30", "task.record.flush_seconds=0.001",
                       "task.save_agents=false"])  # fmt: skip
    out = tmp_path / "run"
    with pytest.raises(CobelError) as err:
        run(cfg, out, background_writes=False)
    msg = str(err.value)
    assert "the disk is full (no space left on device)" in msg and "\n" not in msg, msg
    assert "kept: tables steps, trials" in msg  # the two parts written were merged at close
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "failed" and "disk is full" in manifest["error"]
    assert not (out / ".done").exists() and not (out / ".parts").exists()
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    trials = pd.read_parquet(out / "trials.parquet")
    steps = pd.read_parquet(out / "steps.parquet")
    # what was written is whole: a prefix of runs and trials, with each trial's steps
    assert len(trials) > 0 and not trials.duplicated(["run", "trial"]).any()
    assert steps.groupby(["run", "trial"]).size().sum() == trials["steps"].sum()


def test_full_disk_while_merging_keeps_the_parts(tmp_path, monkeypatch):
    """The disk fills while the parts are merged: the parts stay, `cobel status` merges them."""
    import cobelrun.io.parquet as parquet
    from cobelrun.io.repair import repair_run
    from cobelrun.runner import run

    real = parquet.pq.ParquetWriter

    class Full(real):
        def write_table(self, *args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(parquet.pq, "ParquetWriter", Full)
    with composer() as compose:
        cfg = compose([*TINY, "task.save_agents=false"])
    out = tmp_path / "run"
    with pytest.raises(CobelError, match=r"disk is full.*kept: parts of steps, trials"):
        run(cfg, out, background_writes=False)
    monkeypatch.undo()
    assert json.loads((out / "manifest.json").read_text())["status"] == "failed"
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    repaired = repair_run(out)
    assert repaired["tables"] == {"steps": repaired["tables"]["steps"], "trials": 6}
    assert len(pd.read_parquet(out / "trials.parquet")) == 6


def test_full_disk_cli(cobel, small_disk):
    """A real run on a 1 MiB tmpfs: one line, exit 2, manifest failed, then `cobel status` (after
    the disk grew) merges what was written."""
    import subprocess

    import pandas as pd

    out = small_disk / "run"
    proc = cobel("run", "task=tmaze_extinction", "task.runs=400", "task.record.flush_seconds=0.1",
                 f"hydra.run.dir={out}")  # fmt: skip
    line = one_line_error(proc)
    assert proc.returncode == 2 and "the disk is full" in line, line
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "failed"
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    # where the disk fills depends on timing: on a loaded machine the trials table can be
    # complete already and only the last files (the MCAP, the agents) were cut short
    trials_complete = (out / "trials.parquet").is_file()
    left_in_parts = [p for p in (out / ".parts").rglob("*") if p.is_file()]
    status = cobel("status", str(out))
    if left_in_parts:  # (when the disk filled only after both tables were whole: nothing to merge)
        assert "repaired" in status.stdout, status.stdout + status.stderr
    if not trials_complete:
        assert "repaired trials.parquet" in status.stdout, status.stdout + status.stderr
    trials = pd.read_parquet(out / "trials.parquet")
    assert len(trials) > 0 and not trials.duplicated(["run", "trial"]).any()


def test_read_only_folder_is_one_line_and_writes_nothing(cobel, read_only_dir):
    line = one_line_error(cobel("run", *TINY, f"hydra.run.dir={read_only_dir}/run"))
    assert "not writable" in line
    line = one_line_error(cobel("run", *TINY, env={"COBEL_RESULTS": str(read_only_dir)}))
    assert "not writable" in line
    assert list(read_only_dir.iterdir()) == []


def test_disk_error_messages():
    from cobelrun.io.atomic import disk_error, is_disk_error

    full = OSError(errno.ENOSPC, "No space left on device")
    wrapped = RuntimeError("write failed")
    wrapped.__cause__ = full
    assert is_disk_error(full) and is_disk_error(wrapped)
    assert not is_disk_error(ValueError("x"))
    assert (
        disk_error(wrapped, "/x")
        == "cannot write to /x: the disk is full (no space left on device)"
    )
    assert "read-only" in disk_error(OSError(errno.EROFS, "Read-only file system"), "/x")


def test_manifest_on_a_full_disk_is_rewritten_in_place(tmp_path, monkeypatch):
    """No room for the temporary copy: the manifest is overwritten in place, never lost."""
    import builtins

    from cobelrun.io.manifest import _write_json_atomic

    path = tmp_path / "manifest.json"
    _write_json_atomic(path, {"status": "running", "pad": "x" * 100})
    real_open = builtins.open

    def no_new_files(file, mode="r", *args, **kwargs):
        if "w" in mode and str(file).endswith(".tmp"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", no_new_files)
    _write_json_atomic(path, {"status": "failed", "error": "disk full"})
    monkeypatch.undo()
    assert json.loads(path.read_text()) == {"status": "failed", "error": "disk full"}
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.json"]


def test_validation_happens_before_any_folder(tmp_path, monkeypatch):
    """A config error found only when the agent is built still leaves no folder behind."""
    monkeypatch.setenv("COBEL_RESULTS", str(tmp_path / "results"))
    with pytest.raises(ConfigError):
        validate([*TINY, "agent.epsilon=null"], multirun=False)
    assert not (tmp_path / "results").exists()


# -- atomic writes ----------------------------------------------------------------------------
def test_atomic_path_keeps_the_old_file_on_failure(tmp_path):
    from cobelrun.io.atomic import atomic_path, atomic_write_text

    target = tmp_path / "fig.csv"
    atomic_write_text(target, "old\n")
    with pytest.raises(OSError), atomic_path(target) as tmp:
        assert tmp.suffix == ".csv" and tmp.parent == tmp_path and tmp.name.startswith(".")
        tmp.write_text("half a fi")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["fig.csv"]


def test_figure_files_are_written_atomically(tmp_path, monkeypatch):
    """A figure whose CSV cannot be written leaves the previous CSV whole and says why."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.figures import save_figure

    out = tmp_path / "plot.png"
    fig, _ = plt.subplots()
    save_figure(fig, out)
    first = out.read_bytes()

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    fig, _ = plt.subplots()
    monkeypatch.setattr(type(fig), "savefig", full)
    with pytest.raises(CobelError, match="the disk is full"):
        save_figure(fig, out)
    assert out.read_bytes() == first and len(list(tmp_path.iterdir())) == 1


# -- what the parts of a run allocate -----------------------------------------------------------
COMPONENT_SIZES = [
    # key=value that makes a part allocate too much, the line's start, what it names
    (["task=gridworld", "env=open_field", "env.world.width=100000"],
     "env.world would allocate about", "grid world (1,000,000 states"),
    (["task=gridworld", "env=open_field", "env.world.width=400", "env.world.height=400"],
     "env.world would allocate about", "transition matrix"),
    (["task=tmaze_extinction", "agent.replay_batch=1000000000"],
     "agent.replay_batch would allocate about 59.6 GiB", "replayed experiences"),
    (["task=tmaze_extinction", "agent=dyna_dqn", "agent.hidden=[1000000000]"],
     "agent.hidden would allocate about", "a network of"),
    (["task=tmaze_extinction", "agent=dyna_dqn", "agent.replay_batch=100000000"],
     "agent.replay_batch would allocate about", "replayed experiences"),
    (["task=morris_water_maze", "env.observation.0.n=1000000000"],
     "env.observation (place_cells.n) would allocate about", "1,000,000,000 cells"),
    (["task=morris_water_maze", "env.n_directions=1000000000"],
     "env.n_directions would allocate about", "movement directions"),
    (["task=gridworld", "env=tmaze", "env.world.stem_length=100000"],
     "env.world would allocate about", "grid world"),
    (["task=two_afc", "agent.buffer_size=1000000000"],
     "agent.buffer_size would allocate about", "a replay memory of 1,000,000,000 transitions"),
]  # fmt: skip


@pytest.mark.parametrize("overrides", [
    ["task=tmaze_extinction", "agent=dyna_dqn", "agent.hidden=[0]"],
    ["task=tmaze_extinction", "agent=dyna_dqn", "agent.hidden=[64,-3]"],
    ["task=tmaze_extinction", "agent=dyna_dsr", "agent.hidden=[0]"],
    ["task=two_afc", "agent.net_arch=[64,0]"],
    ["task=two_afc", "agent.net_arch=7"],
])  # fmt: skip
def test_layer_sizes_must_be_positive(overrides):
    """A layer of 0 (or fewer) units is refused in one line naming the key (it used to pass
    with a runtime warning and a network that cannot learn)."""
    key = next(o.split("=")[0] for o in overrides if o.startswith("agent."))
    with pytest.raises(
        ConfigError, match=rf"^{key.replace('.', '[.]')} must be a list of layer sizes"
    ):
        validate([*overrides, "task.runs=1"], multirun=False)


@pytest.mark.parametrize(("overrides", "start", "names"), COMPONENT_SIZES,
                         ids=[o[-1] for o, _, _ in COMPONENT_SIZES])  # fmt: skip
def test_component_memory_is_estimated_before_it_is_allocated(monkeypatch, overrides, start,
                                                               names):  # fmt: skip
    """A size that makes an env, agent or monitor allocate more than the memory available is
    refused by its estimate, before the allocation: one line with the estimate and the limit
    (not a MemoryError from the allocation, nor the kernel's OOM killer)."""
    monkeypatch.setenv("COBEL_MEMORY_LIMIT", "4G")
    with pytest.raises(ConfigError) as err:
        validate([*overrides, "task.runs=1"], multirun=False)
    msg = str(err.value)
    assert msg.startswith(start) and names in msg, msg
    assert "more than the 3.2 GiB this run may use (80% of 4.0 GiB available)" in msg, msg
    assert "\n" not in msg and "MemoryError" not in msg and "Unable to allocate" not in msg


def test_component_estimates_add_up():
    """The run's parts count together: each fits alone, both together do not."""
    from cobelrun.safety import check_allocation, memory_plan

    check_allocation("a", 600, "a thing", limit=1000)
    with memory_plan(), pytest.raises(ConfigError, match=r"with the 600 B planned before it"):
        check_allocation("a", 600, "a thing", limit=1000)
        check_allocation("b", 600, "another thing", limit=1000)


@pytest.mark.parametrize("target", ["..", "/.", ".", ".x", "x.", "a..b"])
def test_target_that_is_no_dotted_path_is_one_line(target):
    """Found by the 2,000-example fuzz: ``_target_`` values like ``..`` made importlib raise
    TypeError/ValueError (a traceback) instead of a config error."""
    from omegaconf import OmegaConf

    from cobelrun.runner import build_task

    with composer() as compose:
        cfg = compose(TINY)
    OmegaConf.update(cfg, "env._target_", target, merge=False)
    with pytest.raises(
        ConfigError, match=r"env._target_ must name a class or function as a dotted"
    ):
        build_task(cfg, probe_agent=True)
