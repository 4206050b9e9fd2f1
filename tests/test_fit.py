"""Objectives (task.objective, Optuna sweeps) and `cobel fit` (parameter recovery)."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pandas as pd
import pytest

from cobelrun.errors import CobelError, ConfigError
from cobelrun.fit import fit_choices, q_learning_nll, simulate_choices
from cobelrun.objectives import ChoiceNLL, TrialMean

TRUE_LR, TRUE_BETA = 0.3, 4.0


def test_objective_mean_of_last_trials():
    trials = pd.DataFrame({"run": [0, 0, 0, 1, 1, 1], "trial": [1, 2, 3, 1, 2, 3],
                           "phase": ["a", "a", "b"] * 2, "reward": [0, 1, 1, 0, 0, 1.0]})  # fmt: skip
    assert TrialMean("reward", last=2)(trials) == 0.75
    assert TrialMean("reward", last=None, phase="a")(trials) == 0.25
    assert TrialMean("reward", last=2).name == "mean reward, last 2 trials"
    with pytest.raises(ConfigError, match="not a trials column"):
        TrialMean("rewrd")(trials)
    with pytest.raises(ConfigError, match="last must be"):
        TrialMean(last=0)


def test_run_stores_the_objective(tmp_path):
    import cobelrun

    r = cobelrun.run("tmaze_extinction", ["task.runs=2", "task.protocol.phases.0.trials=6",
                     "task.protocol.phases.1.trials=6", "task.record.mcap=false",
                     "task.save_agents=false",
                     "+task.objective={_target_:cobelrun.objectives.TrialMean,last:4}"],
                     out=tmp_path / "r")  # fmt: skip
    t = r.trials
    assert r.objective == pytest.approx(t[t["trial"] > 8]["reward"].mean())
    with pytest.raises(ConfigError, match=r"task\.objective"):
        cobelrun.run("tmaze_extinction", ["+task.objective={_target_:cobelrun.objectives.TrialMean,"
                                          "lst:4}"], out=tmp_path / "bad")  # fmt: skip


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("optuna") is None, reason="needs cobelrun[fit]")
def test_optuna_sweeper_optimises_the_objective(cobel, tmp_path):
    proc = cobel("run", "-m", "hydra/sweeper=optuna", "hydra/launcher=basic",
                 "task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=5",
                 "task.protocol.phases.1.trials=5", "task.record.mcap=false",
                 "task.save_agents=false",
                 "+task.objective={_target_:cobelrun.objectives.TrialMean,last:5}",
                 "agent.epsilon=interval(0.01,0.5)", "hydra.sweeper.n_trials=2",
                 "hydra.sweeper.direction=maximize", f"hydra.sweep.dir={tmp_path / 'opt'}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "best_value" in proc.stderr
    assert (tmp_path / "opt" / "optimization_results.yaml").is_file()
    values = [json.loads((tmp_path / "opt" / str(j) / "manifest.json").read_text())["objective"]
              for j in (0, 1)]  # fmt: skip
    assert all(0.0 <= v <= 1.0 for v in values)


NLL_OBJECTIVE = (
    "+task.objective={_target_:cobelrun.objectives.ChoiceNLL,data:%s,"
    "learning_rate:${agent.learning_rate},beta:${agent.beta}}"
)
TINY_RUN = ["task.runs=1", "task.protocol.phases.0.trials=3", "task.protocol.phases.1.trials=3",
            "task.record.mcap=false", "task.record.steps=false", "task.save_agents=false"]  # fmt: skip


def test_choice_nll_objective_shares_the_fit_likelihood(tmp_path):
    """ChoiceNLL evaluates the same likelihood that `cobel fit` minimises: at the fitted
    parameters it equals the fit's nll, and the generating parameters score better than far
    ones."""
    data = tmp_path / "choices.parquet"
    d = simulate_choices(500, TRUE_LR, TRUE_BETA, seed=4)
    d.to_parquet(data)
    fit = fit_choices(d, ["agent.learning_rate", "agent.beta"])
    lr, beta = fit.params["agent.learning_rate"], fit.params["agent.beta"]
    assert ChoiceNLL(str(data), lr, beta)(None) == pytest.approx(fit.nll, rel=1e-12)
    direct = q_learning_nll(TRUE_LR, TRUE_BETA, d["choice"], d["reward"], d["state"],
                            np.zeros(500), 1, 2)  # fmt: skip
    assert ChoiceNLL(str(data), TRUE_LR, TRUE_BETA)(None) == pytest.approx(direct)
    assert ChoiceNLL(str(data), 0.95, 0.5)(None) > direct + 10
    assert ChoiceNLL(str(data), 0.3, 4.0).name == "nll of choices.parquet (500 trials)"
    with pytest.raises(ConfigError, match=r"task\.objective\.data: .*does not exist"):
        ChoiceNLL(str(tmp_path / "none.parquet"), 0.3, 4.0)
    with pytest.raises(ConfigError, match=r"learning_rate must lie in \[0.0, 1.0\]"):
        ChoiceNLL(str(data), 1.5, 4.0)
    with pytest.raises(ConfigError, match="beta must be a number"):
        ChoiceNLL(str(data), 0.3, "high")


def test_run_returns_the_nll_of_choices_at_its_agent_parameters(tmp_path):
    """task.objective=ChoiceNLL takes the agent's parameters by interpolation: the run's
    manifest holds the data's nll at exactly the composed learning rate and beta."""
    import cobelrun

    data = tmp_path / "choices.parquet"
    d = simulate_choices(300, TRUE_LR, TRUE_BETA, seed=5)
    d.to_parquet(data)
    r = cobelrun.run("tmaze_extinction", [*TINY_RUN, "agent.learning_rate=0.45", "agent.beta=3.5",
                                          NLL_OBJECTIVE % data], out=tmp_path / "r")  # fmt: skip
    expected = q_learning_nll(0.45, 3.5, d["choice"], d["reward"], d["state"], np.zeros(300), 1, 2)
    assert r.objective == pytest.approx(expected)
    assert r.manifest["objective_name"] == "nll of choices.parquet (300 trials)"
    with pytest.raises(ConfigError, match=r"task\.objective\.data"):
        cobelrun.run("tmaze_extinction", [*TINY_RUN, NLL_OBJECTIVE % (tmp_path / "none.csv")],
                     out=tmp_path / "bad")  # fmt: skip
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("optuna") is None, reason="needs cobelrun[fit]")
def test_optuna_sweeper_minimises_the_choice_nll(cobel, tmp_path):
    """`cobel run -m hydra/sweeper=optuna` with a ChoiceNLL objective: every job returns the
    data's nll at its sampled parameters, and Optuna reports the smallest as best."""
    import yaml

    data = tmp_path / "choices.parquet"
    d = simulate_choices(300, TRUE_LR, TRUE_BETA, seed=6)
    d.to_parquet(data)
    proc = cobel("run", "-m", "hydra/sweeper=optuna", "hydra/launcher=basic",
                 "task=tmaze_extinction", *TINY_RUN, NLL_OBJECTIVE % data,
                 "agent.learning_rate=interval(0.05,0.95)", "agent.beta=interval(0.5,10.0)",
                 "hydra.sweeper.n_trials=4", "hydra.sweeper.direction=minimize",
                 "hydra.sweeper.sampler.seed=1", f"hydra.sweep.dir={tmp_path / 'opt'}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    values = []
    for job in range(4):
        manifest = json.loads((tmp_path / "opt" / str(job) / "manifest.json").read_text())
        cfg = yaml.safe_load((tmp_path / "opt" / str(job) / "config.yaml").read_text())
        lr, beta = cfg["agent"]["learning_rate"], cfg["agent"]["beta"]
        expected = q_learning_nll(lr, beta, d["choice"], d["reward"], d["state"], np.zeros(300),
                                  1, 2)  # fmt: skip
        assert manifest["objective"] == pytest.approx(expected)
        values.append(expected)
    best = yaml.safe_load((tmp_path / "opt" / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(min(values))


def test_nll_matches_a_direct_computation():
    d = simulate_choices(50, 0.4, 2.0, seed=1)
    q = np.zeros(2)
    nll = 0.0
    for a, r in zip(d["choice"], d["reward"], strict=True):
        p = np.exp(2.0 * q) / np.exp(2.0 * q).sum()
        nll -= np.log(p[a])
        q[a] += 0.4 * (r - q[a])
    got = q_learning_nll(0.4, 2.0, d["choice"], d["reward"], d["state"], np.zeros(50), 1, 2)
    assert got == pytest.approx(nll)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_recovers_generating_parameters(seed):
    """500 synthetic Q-learning choice trials: learning rate within 0.1, beta within 25%."""
    d = simulate_choices(500, TRUE_LR, TRUE_BETA, seed=seed)
    r = fit_choices(d, ["agent.learning_rate", "agent.beta"])
    assert abs(r.params["agent.learning_rate"] - TRUE_LR) < 0.1
    assert abs(r.params["agent.beta"] - TRUE_BETA) / TRUE_BETA < 0.25
    assert r.nll <= q_learning_nll(TRUE_LR, TRUE_BETA, d["choice"], d["reward"], d["state"],
                                   np.zeros(500), 1, 2) + 1e-6  # fmt: skip


def test_cli_fit(cobel, tmp_path):
    data = tmp_path / "choices.parquet"
    simulate_choices(500, TRUE_LR, TRUE_BETA, seed=3).to_parquet(data)
    out = tmp_path / "fit.json"
    proc = cobel("fit", "task=two_afc", "agent=q_learning", f"data={data}",
                 "params=[agent.learning_rate,agent.beta]", "--out", str(out))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    est = json.loads(out.read_text())["params"]
    assert abs(est["agent.learning_rate"] - TRUE_LR) < 0.1
    assert abs(est["agent.beta"] - TRUE_BETA) / TRUE_BETA < 0.25
    # beta fixed at the config's value, only the learning rate fitted
    proc = cobel("fit", "task=two_afc", "agent=q_learning", "agent.beta=4.0", f"data={data}",
                 "params=[agent.learning_rate]", "--out", str(out))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert json.loads(out.read_text())["fixed"]["agent.beta"] == 4.0
    bad = cobel("fit", "task=two_afc", "agent=q_learning", f"data={tmp_path / 'no.parquet'}")
    assert bad.returncode == 2 and "does not exist" in bad.stderr
    bad = cobel("fit", "task=two_afc", "agent=q_learning", f"data={data}", "params=[agent.gamma]")
    assert bad.returncode == 2 and "fittable" in bad.stderr


def test_fit_checks_its_input():
    d = simulate_choices(20, 0.3, 4.0)
    with pytest.raises(ConfigError, match="method"):
        fit_choices(d, ["agent.beta"], method="grid")
    with pytest.raises(CobelError, match=r"choice must lie in 0..1, got 5"):
        fit_choices(d.assign(choice=5), ["agent.beta"], n_actions=2)
