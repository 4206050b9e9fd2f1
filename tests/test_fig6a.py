"""Fig. 6A: DQN on rendered T-maze images: the figure spec (quick) and the learning shape (slow)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest


def _deep_and_render() -> None:
    pytest.importorskip("stable_baselines3")
    pytest.importorskip("pybullet")


def test_figure_fig6a_quick_writes_png_pdf_csv(cobel, tmp_path):
    _deep_and_render()
    proc = cobel("figure", "fig6a", "--quick", env={"COBEL_CACHE": str(tmp_path / "cache")})
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    for suffix in ("png", "pdf", "csv"):
        f = out / f"fig6a_quick.{suffix}"
        assert f.is_file() and f.stat().st_size > 500, f
    assert (out / "fig6a_quick.pdf").read_bytes().startswith(b"%PDF")
    table = pd.read_csv(out / "fig6a_quick.csv")
    dqn, dyna = table[table["agent"] == "dqn"], table[table["agent"] == "dyna_q"]
    assert len(dqn) == 10 and dqn["runs"].eq(1).all()
    assert len(dyna) == 200 and dyna["runs"].eq(5).all()
    assert {"trial", "phase", "response_rate", "cumulative_response_mean", "latency_mean",
            "trials_to_extinction"} <= set(table.columns)  # fmt: skip
    assert list(dqn["phase"]) == ["acquisition"] * 5 + ["extinction"] * 5
    # Dyna-Q (Fig. 6B) switches arms within a few trials of the switch
    assert dyna["trials_to_extinction"].iloc[0] <= 5


def test_trials_to_extinction_counts_from_the_switch():
    from cobelrun.figures.extinction import trials_to_extinction

    rates = [1, 1, 1, 1, 0.8, 0.6, 0.4, 0.2]  # trials 1-4 acquisition, 5-8 extinction
    rows = [{"run": r, "trial": t + 1, "phase": "acquisition" if t < 4 else "extinction",
             "response": int(r < 10 * p)} for t, p in enumerate(rates) for r in range(10)]  # fmt: skip
    assert trials_to_extinction(pd.DataFrame(rows)) == 3  # trial 7 is the 3rd after the switch
    flat = pd.DataFrame([{**row, "response": 1} for row in rows])
    assert np.isnan(trials_to_extinction(flat))


def test_response_monitor_first_choice_codes_the_first_arm_reached():
    from types import SimpleNamespace

    from cobelrun.envs import TopologyEnv
    from cobelrun.monitors import ResponseMonitor
    from cobelrun.records import TrialBatch

    env = TopologyEnv()  # the paper's T-maze: start 11, junction 3, arm ends 0 (left), 6 (right)
    trials = [
        [11, 3, 4, 5, 6],  # right arm end
        [11, 3, 2, 1, 0],  # left arm end
        [11, 3, 4, 5, 6, 5, 4, 3, 2, 1, 0],  # right first, then left: a right choice
        [11, 3, 2, 1, 0, 1, 2, 3, 4, 5, 6],  # left first: not a right choice
        [11, 10, 3, 4],  # neither (time-out)
    ]
    batch = TrialBatch.from_trials(
        [{"states": t, "actions": [0] * (len(t) - 1), "rewards": [0.0] * (len(t) - 1),
          "terminated": False} for t in trials]
    )  # fmt: skip
    first = ResponseMonitor(states=["right_arm"], before=["left_arm"])
    end = ResponseMonitor(states=["right_arm"])
    for m in (first, end):
        m.setup(SimpleNamespace(unwrapped=env))
        m.start_run(0)
    cols = first.columns(batch, env)
    assert cols["response"].tolist() == [1, 0, 1, 0, 0]
    assert cols["cumulative_response"].tolist() == [1, 1, 2, 2, 2]
    assert end.columns(batch, env)["response"].tolist() == [1, 0, 0, 1, 0]


def _trials(cobel, tmp_path, *overrides: str) -> pd.DataFrame:
    out = cobel("run", *overrides, "task.record.steps=false", "task.record.mcap=false",
                env={"COBEL_CACHE": str(tmp_path / "cache")}, timeout=1800)  # fmt: skip
    assert out.returncode == 0, out.stderr
    return pd.read_parquet(f"{out.stdout.strip().splitlines()[-1]}/trials.parquet")


@pytest.mark.slow
def test_fig6a_dqn_learns_the_right_arm_then_extinguishes_slower_than_dyna_q(cobel, tmp_path):
    """The default CPU budget (36 x 36 images), 4 seeded runs, offline renders (~6 min alone).

    The original's rules: only the rewarded arm end ends a trial, a response is a trial ending on
    the right arm end. Measured (docs/rendering.md): right-arm rate 1.0 in trials 81-100, 0.55 in
    101-110, 0.36 in 181-200; Dyna-Q (Fig. 6B, 100 runs) 0.17 in trials 101-110, 0.0 in 181-200.
    """
    _deep_and_render()
    cache = {"COBEL_CACHE": str(tmp_path / "cache")}
    task = ["task=tmaze_extinction_3d", "task.runs=4", "seed=0", "env.observation.render=offline"]
    assert cobel("render-cache", *task, env=cache).returncode == 0
    dqn = _trials(cobel, tmp_path, *task)
    rate = dqn.groupby("trial")["response"].mean()
    # acquisition: reliable right-arm choice on short paths (the shortest is 8 steps)
    assert rate.loc[81:100].mean() >= 0.9
    assert dqn[dqn["trial"].between(81, 100)]["steps"].median() <= 15
    # extinction: the old goal is a dead end; fewer and fewer trials end there
    assert rate.loc[181:200].mean() <= 0.5
    assert rate.loc[161:200].mean() < rate.loc[101:140].mean()
    # ... more slowly than tabular Dyna-Q (Fig. 6B), which switches within a few trials
    dyna = _trials(cobel, tmp_path, "task=tmaze_extinction", "task.runs=20", "seed=0")
    dyna_rate = dyna.groupby("trial")["response"].mean()
    assert rate.loc[101:110].mean() >= dyna_rate.loc[101:110].mean() + 0.2


def test_fig6a_paper_plans_one_job_per_seed(tmp_path):
    """fig6a_paper: 50 DQN jobs (seeds 0-49, 84 x 84 offline images, one run each) beside
    the Dyna-Q task; --quick plans one DQN job with Fig. 6A's CI budget."""
    from cobelrun.figures.registry import get, plan_runs

    planned = plan_runs(get("fig6a_paper"), root=tmp_path)
    dqn = [p for p in planned if p.label == "dqn"]
    assert [p.params["seed"] for p in dqn] == list(range(50))
    assert {p.cfg.task.name for p in dqn} == {"tmaze_extinction_3d_paper"}
    assert all(p.cfg.task.runs == 1 and p.cfg.env.observation.height == 84 for p in dqn)
    assert len({p.config_hash for p in dqn}) == 50
    assert [p.label for p in planned if p.label != "dqn"] == ["dyna_q"]
    quick = [p for p in plan_runs(get("fig6a_paper"), quick=True, root=tmp_path)
             if p.label == "dqn"]  # fmt: skip
    assert len(quick) == 1 and quick[0].params["seed"] == 0
    assert quick[0].cfg.task.protocol.phases[0].trials == 5


def test_fig6a_draws_a_seed_sweep_with_one_run_per_job():
    """A seed sweep gives every job a run 0 (fig6a_paper: 50 jobs): the figure's table keeps one
    row per trial and counts every job's run, and the phase boundary is drawn once."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    from cobelrun.figures.extinction import first_run, phase_boundaries
    from cobelrun.figures.registry import get

    rows = []
    for job in range(3):
        cum = 0
        for trial in range(1, 7):
            response = int(trial <= 3 or job == 0)
            cum += response
            phase = "acquisition" if trial <= 3 else "extinction"
            rows.append(dict(job=job, run=0, trial=trial, phase=phase, response=response,
                             cumulative_response=cum, steps=10 + trial))  # fmt: skip
    trials = pd.DataFrame(rows)

    class Data:
        def trials(self, label):
            return trials.copy()

    assert first_run(trials)["job"].unique().tolist() == [0]
    assert phase_boundaries(trials) == [(3.5, "extinction")]
    _fig, table = get("fig6a").draw(Data())
    dqn = table[table["agent"] == "dqn"]
    assert dqn["trial"].tolist() == [1, 2, 3, 4, 5, 6]
    assert set(dqn["runs"]) == {3}
    assert dqn["response_rate"].round(3).tolist() == [1, 1, 1, 0.333, 0.333, 0.333]
    assert dqn["phase"].tolist() == ["acquisition"] * 3 + ["extinction"] * 3
