"""Sweeps end to end: joblib and submitit_local launchers, resume, failures (``cobel run -m``
in a subprocess: the launchers start processes), ``cobel status`` and ``cobel collect``
(in-process)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest

from cobelrun.results import load_collected, load_jobs, load_sweep
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process

TINY = ["task.runs=2", "task.protocol.phases.0.trials=8", "task.protocol.phases.1.trials=8"]


def sweep_dir_of(proc) -> Path:
    assert proc.returncode == 0, proc.stderr
    return Path(proc.stdout.strip().splitlines()[-1])


def mtimes(sweep: Path) -> dict[int, float]:
    return {int(d.name): (d / "trials.parquet").stat().st_mtime_ns for d in sweep.glob("[0-9]*")}


def test_joblib_sweep_resumes_and_collects(cobel, cli, tmp_path):
    args = ["run", "-m", "task=tmaze_extinction", "seed=1,2,3", *TINY, "hydra.launcher.n_jobs=2"]
    proc = cobel(*args)
    sweep = sweep_dir_of(proc)
    assert "Joblib" in proc.stdout + proc.stderr
    assert sweep.parent == tmp_path / "results" / "tmaze_extinction" / "sweeps"
    for job in range(3):
        assert (sweep / str(job) / ".done").is_file()
        assert json.loads((sweep / str(job) / "job.json").read_text())["status"] == "completed"
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["job"]) == [0, 1, 2] and list(index["seed"]) == [1, 2, 3]
    assert set(index["status"]) == {"done"}
    assert "3 of 3 jobs done" in proc.stderr

    # the same command again: same folder, nothing re-run (the launcher setting does not matter)
    before = mtimes(sweep)
    again = cobel(*args[:-1], "hydra.launcher.n_jobs=1")
    assert sweep_dir_of(again) == sweep
    assert "3 of 3 jobs already done" in again.stdout + again.stderr
    assert mtimes(sweep) == before

    # an unfinished job (no done marker) is run again, the others are not
    (sweep / "1" / ".done").unlink()
    status = cli("status", str(sweep))
    assert status.returncode == 1 and "running" in status.stdout
    third = cobel(*args)
    assert sweep_dir_of(third) == sweep
    after = mtimes(sweep)
    assert after[0] == before[0] and after[2] == before[2] and after[1] != before[1]
    assert cli("status", str(sweep)).returncode == 0

    # collect: one file per table, job + swept params first, all rows of all jobs
    out = cli("collect", str(sweep))
    assert out.returncode == 0, out.stderr
    trials_file = sweep / "collected" / "trials.parquet"
    assert trials_file.is_file() and (sweep / "collected" / "steps.parquet").is_file()
    schema = pq.read_schema(trials_file)
    assert schema.names[:3] == ["job", "seed", "run"]
    assert str(schema.field("seed").type) == "int64" and str(schema.field("job").type) == "int32"
    trials = pd.read_parquet(trials_file)
    assert len(trials) == 3 * 2 * 16
    assert trials.groupby("job")["seed"].first().tolist() == [1, 2, 3]
    one = pd.read_parquet(sweep / "0" / "trials.parquet")
    pd.testing.assert_frame_equal(
        trials[trials["job"] == 0].drop(columns=["job", "seed"]).reset_index(drop=True), one
    )
    steps = load_collected(sweep, "steps", filters=[("seed", "==", 2)])
    assert set(steps["job"]) == {1} and len(steps) == trials.loc[trials.job == 1, "steps"].sum()
    assert len(load_sweep(sweep)) == len(trials)
    assert list(load_jobs(sweep)["status"]) == ["done"] * 3


def test_failing_job_is_recorded_and_the_others_complete(cobel, cli, tmp_path):
    # 'greedy' passes composition (validate builds only the first combination) but the
    # agent's constructor refuses it in job 1
    proc = cobel(
        "run", "-m", "task=tmaze_extinction", "agent.policy=epsilon_greedy,greedy,softmax", *TINY
    )
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("cobel: error: 1 of 3 jobs failed; see cobel status ")
    sweep = Path(last.rsplit(" ", 1)[-1])
    assert (sweep / "0" / ".done").is_file() and (sweep / "2" / ".done").is_file()
    job = json.loads((sweep / "1" / "job.json").read_text())
    assert job["status"] == "failed" and "agent.policy 'greedy' is not known" in job["error"]
    assert "Traceback" in job["traceback"]
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["status"]) == ["done", "failed", "done"]
    assert "not known" in index.loc[1, "error"]
    status = cli("status", str(sweep))
    assert status.returncode == 1
    assert "failed" in status.stdout and "greedy" in status.stdout and "2 done" in status.stdout
    # the rerun only tries the failed job again (and it fails again)
    before = mtimes(sweep)
    again = cobel(
        "run", "-m", "task=tmaze_extinction", "agent.policy=epsilon_greedy,greedy,softmax", *TINY
    )
    assert again.returncode == 1 and "2 of 3 jobs already done" in again.stdout + again.stderr
    assert {k: v for k, v in mtimes(sweep).items() if k != 1} == {0: before[0], 2: before[2]}


def test_submitit_local_sweep(cobel, tmp_path):
    proc = cobel(
        "run", "-m", "hydra/launcher=submitit_local", "task=tmaze_extinction", "seed=4,5", *TINY,
        "hydra.launcher.timeout_min=5",
    )  # fmt: skip
    sweep = sweep_dir_of(proc)
    assert (sweep / ".submitit").is_dir()
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["status"]) == ["done", "done"] and list(index["seed"]) == [4, 5]
    a = pd.read_parquet(sweep / "0" / "trials.parquet")
    assert len(a) == 2 * 16


def test_slurm_launcher_against_stand_in_slurm_commands(cobel, cli, tmp_path):
    """hydra/launcher=slurm end to end with stand-ins for sbatch, srun and sacct
    (tests/fake_slurm): submitit writes one array script from conf/hydra/launcher/slurm.yaml,
    each task runs cobel's job with the environment SLURM gives it, and the sweep ends done and
    indexed, with the same tables as a single run of the same config."""
    import os

    fake = Path(__file__).parent / "fake_slurm"
    state = tmp_path / "slurm_state"
    env = {"PATH": f"{fake}{os.pathsep}{os.environ['PATH']}", "FAKE_SLURM_DIR": str(state)}
    proc = cobel("run", "-m", "hydra/launcher=slurm", "hydra.launcher.partition=testpart",
                 "hydra.launcher.timeout_min=5", "task=tmaze_extinction", "seed=4,5", *TINY,
                 env=env)  # fmt: skip
    sweep = sweep_dir_of(proc)
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["status"]) == ["done", "done"] and list(index["seed"]) == [4, 5]
    (script,) = state.glob("sbatch_*.sh")  # one array for both jobs
    text = script.read_text()
    for line in ("#SBATCH --partition=testpart", "#SBATCH --time=5", "#SBATCH --cpus-per-task=1",
                 "#SBATCH --mem=4GB", "#SBATCH --array=0-1%2",  # parallelism min(64, jobs)
                 "#SBATCH --job-name=cobel-tmaze_extinction",
                 "export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1"):  # fmt: skip
        assert line in text, line
    assert "srun --unbuffered" in text and "submitit.core._submit" in text
    array_id = script.stem.split("_")[1]
    assert sorted(p.name for p in state.glob("state_*")) == [
        f"state_{array_id}_0",
        f"state_{array_id}_1",
    ]
    # submitit reads a task's result as soon as it is written; the stand-in marks the task
    # COMPLETED only once its script has exited (as SLURM does), a moment later
    deadline = time.monotonic() + 60
    while {p.read_text() for p in state.glob("state_*")} != {"COMPLETED"}:
        assert time.monotonic() < deadline, {p.name: p.read_text() for p in state.glob("state_*")}
        time.sleep(0.2)
    single = cli("run", "task=tmaze_extinction", "seed=4", *TINY, "--quiet",
                   f"hydra.run.dir={tmp_path / 'single'}")  # fmt: skip
    assert single.returncode == 0, single.stderr
    pd.testing.assert_frame_equal(pd.read_parquet(sweep / "0" / "trials.parquet"),
                                  pd.read_parquet(tmp_path / "single" / "trials.parquet"))  # fmt: skip


def test_status_of_a_folder_that_is_no_sweep(cli, tmp_path):
    proc = cli("status", str(tmp_path))
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f"cobel: error: {tmp_path} is neither a run folder (no manifest.json; made by `cobel "
        "run`) nor a sweep folder (no sweep.json; made by `cobel run -m`)"
    )
    missing = cli("status", str(tmp_path / "nowhere"))
    assert missing.returncode == 2 and "does not exist" in missing.stderr


@pytest.mark.parametrize("order", [["seed=1,2", "task.runs=2"], ["task.runs=2", "seed=1,2"]])
def test_sweep_id_ignores_order_of_fixed_overrides_and_launcher(order):
    from cobelrun.sweep_plan import plan, sweep_id

    _, jobs = plan(["task=tmaze_extinction", *order])
    _, ref = plan(["task=tmaze_extinction", "seed=1,2", "task.runs=2", "hydra/launcher=joblib"])
    assert sweep_id(jobs) == sweep_id(ref)
    _, other = plan(["task=tmaze_extinction", "seed=1,2,3", "task.runs=2"])
    assert sweep_id(other) != sweep_id(ref)


@pytest.mark.parametrize(
    "overrides",
    [
        ["seed=1,2,3", "agent=q_learning,dyna_q", "task.runs=2"],
        ["seed=range(0,4)", "agent.epsilon=0.1,0.2", "seed=5,6"],  # a key given twice
        ["+extra=choice(a,'b c')", "agent.epsilon=0.3", "hydra/launcher=joblib", "~task.x"],
        ["lst=[1,2],[3]", "d={a:1},{a:2}", "task=tmaze_extinction"],
    ],
)
def test_jobs_come_in_hydras_basic_sweeper_order(overrides):
    """cobel expands sweeps with Hydra's public override API; the jobs and their order are
    those of Hydra's own basic sweeper (imported here, in a test only, to compare)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from cobelrun.sweep_plan import cartesian, plan

    parsed = OverridesParser.create().parse_overrides(overrides)
    (hydra_jobs,) = BasicSweeper.split_arguments(parsed, None)
    assert cartesian(parsed) == hydra_jobs
    _, jobs = plan(overrides)
    assert [j["overrides"] for j in jobs] == hydra_jobs and len(jobs) > 1


def test_an_interval_sweep_is_refused_in_one_line(cli, tmp_path):
    proc = cli("run", "-m", "task=tmaze_extinction", "agent.epsilon=interval(0.1,0.5)")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "interval needs a sampling sweeper" in lines[0], proc.stderr
    assert not (tmp_path / "results").exists()
