"""The CLI end to end: runs, listing, plotting, bad input (in-process, through typer's runner),
start-up, exit codes of a real process and interruption by signals (subprocess)."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest
from mcap.reader import make_reader

from tests import inprocess
from tests.conftest import cobel_exe
from tests.test_mcap import read as read_mcap

cli = inprocess.cli  # fixture: cobel in this process

TINY = ["task.runs=3", "task.protocol.phases.0.trials=10", "task.protocol.phases.1.trials=10"]


def run_dir_of(proc: subprocess.CompletedProcess) -> Path:
    assert proc.returncode == 0, proc.stderr
    return Path(proc.stdout.strip().splitlines()[-1])


def test_run_tmaze_extinction_writes_a_complete_run_folder(cli, tmp_path):
    proc = cli("run", "task=tmaze_extinction", *TINY)
    run = run_dir_of(proc)
    assert run.parent.parent == tmp_path / "results" / "tmaze_extinction"
    for name in (
        "config.yaml",
        "manifest.json",
        "trials.parquet",
        "steps.parquet",
        "run.mcap",
        ".done",
    ):
        assert (run / name).is_file(), name
    trials = pd.read_parquet(run / "trials.parquet")
    for col in (
        "run",
        "trial",
        "phase",
        "trial_in_phase",
        "steps",
        "reward",
        "response",
        "end_state",
    ):
        assert col in trials
    assert len(trials) == 3 * 20
    assert trials["trial"].min() == 1 and trials["trial"].max() == 20
    assert set(trials["phase"]) == {"acquisition", "extinction"}
    steps = pd.read_parquet(run / "steps.parquet")
    assert list(steps.columns[:9]) == [
        "run",
        "trial",
        "step",
        "state",
        "x",
        "y",
        "heading",
        "action",
        "reward",
    ]
    assert len(steps) == trials["steps"].sum()
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["status"] == "completed" and manifest["seed"] == 0
    assert "numpy" in manifest["versions"]
    messages = read_mcap(run / "run.mcap")
    topics = {m[0] for m in messages}
    assert topics == {"/maze", "/trial", "/trials", "/run_0000/pose", "/run_0001/pose",
                      "/run_0002/pose"}  # fmt: skip
    poses = [m for m in messages if m[0].endswith("/pose")]
    assert len(poses) == len(steps) + len(trials)  # each trial's start, then every step
    assert {m[1] for m in poses} == {"foxglove.PoseInFrame"}
    ends = [m[3] for m in messages if m[0] == "/trial" and m[3]["event"] == "end"]
    assert sorted((e["run"], e["trial"]) for e in ends) == sorted(
        zip(trials["run"], trials["trial"], strict=True)
    )  # 1-based trials, every one of them
    by_key = trials.set_index(["run", "trial"])["response"]
    assert all(e["response"] == by_key[(e["run"], e["trial"])] for e in ends)
    start = json.loads((run / "manifest.json").read_text())["started_at"]
    assert min(m[2] for m in messages) > 1_700_000_000 * 10**9, start  # real time, not 1970

    plot = cli("plot", str(run))
    assert plot.returncode == 0, plot.stderr
    assert (run / "plot.png").stat().st_size > 10_000


def test_same_seed_gives_identical_trials_table(cli):
    a = run_dir_of(cli("run", "task=tmaze_extinction", "seed=7", *TINY))
    b = run_dir_of(cli("run", "task=tmaze_extinction", "seed=7", *TINY))
    c = run_dir_of(cli("run", "task=tmaze_extinction", "seed=8", *TINY))
    assert a != b
    ta, tb, tc = (pd.read_parquet(p / "trials.parquet") for p in (a, b, c))
    pd.testing.assert_frame_equal(ta, tb)
    assert not ta.equals(tc)


def test_user_conf_folder_is_searched_first(cli, tmp_path):
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "conf" / "task" / "my_tmaze.yaml").write_text(
        "# @package _global_\n"
        "# My own task on top of the built-in T-maze.\n"
        "defaults:\n  - tmaze_extinction\n"
        "task:\n  name: my_tmaze\n  runs: 2\n"
        "agent:\n  epsilon: 0.2\n"
    )
    listing = cli("list", "task")
    assert (
        listing.returncode == 0
        and "my_tmaze" in listing.stdout
        and "tmaze_extinction" in listing.stdout
    )
    run = run_dir_of(cli("run", "task=my_tmaze", "task.protocol.phases.0.trials=5"))
    assert "my_tmaze" in str(run)
    cfg = (run / "config.yaml").read_text()
    assert "epsilon: 0.2" in cfg


def test_list_shows_descriptions(cli):
    out = cli("list")
    assert out.returncode == 0
    assert "tmaze_extinction" in out.stdout and "Fig. 6B" in out.stdout
    assert "dyna_q" in out.stdout and "tmaze_paper" in out.stdout


def test_version(cobel):
    from cobelrun import __version__

    out = cobel("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"cobel {__version__}"


def test_help_is_useful(cobel):
    top = cobel("--help")
    assert top.returncode == 0 and "run" in top.stdout and "list" in top.stdout
    run_help = cobel("run", "--help")
    assert run_help.returncode == 0 and "task=" in run_help.stdout


def test_multirun_basic_launcher(cobel, tmp_path):
    proc = cobel("run", "-m", "hydra/launcher=basic", "task=tmaze_extinction", "seed=1,2", *TINY)
    assert proc.returncode == 0, proc.stderr
    done = list((tmp_path / "results" / "tmaze_extinction" / "sweeps").rglob(".done"))
    assert len(done) == 2


LAYOUT_UNKNOWN = "env.world.layout='#####\n#S.X#\n#####'"


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["task=tmaze_extintion"],
            "unknown task 'tmaze_extintion' (did you mean 'tmaze_extinction'?)",
        ),
        (["agent=dynaq"], "unknown agent 'dynaq' (did you mean 'dyna_q'?)"),
        (["env=tmaze_papr"], "unknown env 'tmaze_papr' (did you mean 'tmaze_paper'?)"),
        (["agent.epsilonn=0.2"], "unknown key 'agent.epsilonn' (did you mean 'epsilon'?)"),
        (  # the task's DQN settings under another agent: all of them, and how to drop them
            ["task=two_afc", "agent=q_learning"],
            "unknown keys 'agent.batch_size', 'agent.learning_starts'; allowed: 'epsilon', ",
        ),
        (
            ["task=two_afc", "agent=q_learning"],
            "drop them with ~agent.batch_size ~agent.learning_starts",
        ),
        (  # one key: with the suggestion
            ["task=two_afc", "agent=q_learning", "~agent.batch_size"],
            "unknown key 'agent.learning_starts' (did you mean 'learning_rate'?); allowed: ",
        ),
        (
            ["task.monitors.respons.states=[left]"],
            "unknown key 'task.monitors.respons.states': task.monitors has no 'respons' "
            "(did you mean 'response'?); allowed: ",
        ),
        (["agent.epsilon=abc"], "agent.epsilon must be a number, got 'abc'"),
        (["agent.policy=greedy"], "agent.policy 'greedy' is not known"),
        (["task.runs=0"], "task.runs must be an integer >= 1"),
        (["task.runs=null"], "task.runs must not be null"),
        (
            ["+task.record.flush_secs=1"],
            "unknown key 'task.record.flush_secs' (did you mean 'flush_seconds'?)",
        ),
        (["task.protocol.phases.0.trials=-1"], "task.protocol.phases[0].trials must be an integer"),
        (["task.monitors.response.states=[nowhere]"], "unknown place 'nowhere'"),
        (["env=gridworld_layout", LAYOUT_UNKNOWN], "unknown layout symbol 'X' at row 1, col 3"),
        (["env=gridworld_layout", "env.world.layout='#####\n#..G#\n#####'"], "no start"),
        (
            ["env=gridworld_layout", "env.world.layout='#######\n#S.#.G#\n#######'"],
            "unreachable from every start",
        ),
    ],
)
def test_bad_input_one_clear_line(cli, tmp_path, args, message):
    proc = cli("run", "task=tmaze_extinction", *args)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("cobel: error:")
    assert message in lines[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "results").exists()  # nothing was written


def test_unwritable_output_folder(cli, tmp_path):
    (tmp_path / "blocker").write_text("a file, not a folder")
    proc = cli("run", "task=tmaze_extinction", f"hydra.run.dir={tmp_path}/blocker/run")
    assert proc.returncode == 2
    assert "is not a folder" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert (tmp_path / "blocker").read_text() == "a file, not a folder"


def test_debug_shows_traceback(cobel):
    proc = cobel("run", "--debug", "task=tmaze_extinction", "agent.policy=greedy")
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_plot_bad_folder(cli, tmp_path):
    proc = cli("plot", str(tmp_path / "nope"))
    assert proc.returncode == 2 and "does not exist" in proc.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_run_leaves_readable_files(tmp_path, sig):
    import os

    out = tmp_path / "run"
    env = {**os.environ, "COBEL_RESULTS": str(tmp_path)}
    proc = subprocess.Popen(
        [*cobel_exe(), "run", "task=tmaze_extinction", "task.runs=200000", f"hydra.run.dir={out}"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.time() + 120
    while time.time() < deadline:  # until the first rows were handed to disk
        if (out / ".parts" / "trials").is_dir():
            break
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted"
    trials = pd.read_parquet(out / "trials.parquet")
    assert len(trials) > 0
    pd.read_parquet(out / "steps.parquet")
    with open(out / "run.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f, validate_crcs=True).iter_messages()) > 0
    assert not (out / ".done").exists()
