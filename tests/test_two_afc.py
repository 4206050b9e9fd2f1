"""Probabilistic rewards of the two-alternative task (``env.reward_probs``) and its use by
``cobel recover`` (issue 36): rates, seeding, validation, reversal phases, observed outcomes."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf
from typer.testing import CliRunner

from cobelrun.choice_models import MODELS, model_logp
from cobelrun.cli import app
from cobelrun.config import instantiate, register_resolvers
from cobelrun.envs.choice import TwoAFCEnv
from cobelrun.errors import ConfigError
from cobelrun.fit import ChoiceData, fit_choices
from cobelrun.hydra_app import composer
from cobelrun.protocol import Protocol
from cobelrun.recover import ChoiceTask, recover


def _compose(*overrides: str):
    register_resolvers()
    with composer() as compose:
        return compose(list(overrides))


def _rewards(env: TwoAFCEnv, n: int, seed: int, pick_correct: bool) -> np.ndarray:
    """``n`` trials of always picking the correct (or always the incorrect) stimulus."""
    out = np.zeros(n)
    for t in range(n):
        _, info = env.reset(seed=seed if t == 0 else None)
        action = info["correct"] if pick_correct else 1 - info["correct"]
        out[t] = env.step(action)[1]
    return out


def _within_binomial(rewards: np.ndarray, p: float, reward: float = 1.0) -> None:
    n, hits = len(rewards), float(np.sum(rewards == reward))
    assert set(np.unique(rewards)) <= {0.0, reward}
    sd = np.sqrt(n * p * (1 - p))
    assert abs(hits - n * p) <= 4 * sd, (hits / n, p)


@pytest.mark.parametrize("probs", [(0.8, 0.2), (0.65, 0.35), (0.3, 0.9)])
def test_rewards_come_at_the_stated_rates(probs):
    env = TwoAFCEnv(reward_probs=list(probs), reward=2.5)
    _within_binomial(_rewards(env, 2000, 3, True), probs[0], 2.5)
    _within_binomial(_rewards(env, 2000, 4, False), probs[1], 2.5)


def test_default_is_the_deterministic_task_and_draws_nothing_more():
    """reward_probs [1, 0] (the default): 1 for correct, 0 otherwise, and no Bernoulli draw, so
    the env's stream (the displays) is that of the task before the feature existed."""
    env, explicit = TwoAFCEnv(), TwoAFCEnv(reward_probs=[1.0, 0.0])
    assert env.reward_probs.tolist() == [1.0, 0.0]
    env.reset(seed=5)
    actions = np.random.default_rng(0)  # the agent's own stream
    for _ in range(50):
        before = env.np_random.bit_generator.state
        _, info = env.reset()
        after_reset = env.np_random.bit_generator.state
        assert after_reset != before
        a = int(actions.integers(0, 2))
        _, r, *_ = env.step(a)
        assert env.np_random.bit_generator.state == after_reset  # the step drew nothing
        assert r == (1.0 if a == info["correct"] else 0.0)
    assert np.array_equal(_rewards(explicit, 30, 1, True), np.ones(30))
    assert np.array_equal(_rewards(explicit, 30, 1, False), np.zeros(30))


def test_same_seed_same_draws_other_seed_others():
    a = _rewards(TwoAFCEnv(reward_probs=[0.5, 0.5]), 200, 7, True)
    b = _rewards(TwoAFCEnv(reward_probs=[0.5, 0.5]), 200, 7, True)
    c = _rewards(TwoAFCEnv(reward_probs=[0.5, 0.5]), 200, 8, True)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.fixture(scope="module")
def env_config() -> dict:
    """env=two_afc_probabilistic as cobel run composes it."""
    return OmegaConf.to_container(_compose("task=two_afc_probabilistic").env)


@pytest.mark.parametrize(
    "value",
    [[0.8], [0.8, 0.2, 0.1], [1.2, 0.2], [0.8, -0.1], [float("nan"), 0.2], "abc", 0.5,
     [True, False], ["a", "b"], None],
)  # fmt: skip
def test_bad_reward_probs_are_one_line(env_config, value):
    with pytest.raises(ConfigError) as err:
        instantiate("env", OmegaConf.create({**env_config, "reward_probs": value}))
    text = str(err.value)
    expected = "must not be null" if value is None else "must be two probabilities in [0, 1]"
    assert f"env.reward_probs {expected}" in text and "\n" not in text


def test_cli_refuses_bad_reward_probs_before_writing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(app, ["recover", "task=two_afc_probabilistic", "models=[q_learning]",
                                 "n=2", "env.reward_probs=[0.8,1.5]", "--out", "rec"],
                           catch_exceptions=False)  # fmt: skip
    assert r.exit_code != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "env.reward_probs must be two probabilities" in lines[0], r.stderr
    assert not (tmp_path / "rec").exists()


def test_phases_reverse_the_probabilities_and_a_new_run_restores_them():
    env = TwoAFCEnv(reward_probs=[0.8, 0.2])
    env.apply_changes(rewards={"correct": 0.2, "incorrect": 0.8})
    assert env.reward_probs.tolist() == [0.2, 0.8]
    _within_binomial(_rewards(env, 1500, 2, True), 0.2)
    env.apply_changes(rewards={0: 0.9, "1": 0.0})
    assert env.reward_probs.tolist() == [0.9, 0.0]
    env.reset_world()
    assert env.reward_probs.tolist() == [0.8, 0.2]
    with pytest.raises(ConfigError, match="unknown two_afc reward key 'left'; allowed: correct"):
        env.apply_changes(rewards={"left": 0.5})
    with pytest.raises(ConfigError, match="must be a number in"):
        env.apply_changes(rewards={"correct": 1.5})
    with pytest.raises(ConfigError, match="changes only rewards"):
        env.apply_changes(starts=[0])
    cfg = _compose("task=two_afc_reversal")
    protocol = Protocol.from_config(OmegaConf.to_container(cfg.task.protocol, resolve=True))
    bad = Protocol.from_config({"max_steps": 1, "phases": [
        {"name": "b1", "trials": 5, "rewards": {"wrong": 0.5}}]})  # fmt: skip
    env = instantiate("env", cfg.env)
    protocol.check(env)
    with pytest.raises(ConfigError, match="unknown two_afc reward key 'wrong'"):
        bad.check(env)


def test_a_phase_naming_one_side_twice_is_refused_and_changes_nothing():
    """``correct`` and ``0`` are the same side: a phase giving both (e.g. a ``+...rewards.0``
    override added to the reversal's ``correct``) is refused, and a refused change sets none
    of its probabilities."""
    env = TwoAFCEnv(reward_probs=[0.8, 0.2])
    with pytest.raises(ConfigError, match="name one side twice: 'correct' and '0'"):
        env.apply_changes(rewards={"correct": 0.2, "incorrect": 0.8, 0: 0.5})
    with pytest.raises(ConfigError, match="must be a number in"):
        env.apply_changes(rewards={"correct": 0.3, "incorrect": 2.0})
    assert env.reward_probs.tolist() == [0.8, 0.2]


def test_recovery_simulates_and_fits_the_drawn_outcomes():
    """cobel recover's synthetic agents choose in the env itself: the table's rewards are the
    drawn outcomes (0 or 1, at the stated rates per phase), and the fit's likelihood is that of
    the observed rewards, not of the expected ones."""
    task = ChoiceTask.from_config(_compose("task=two_afc_reversal"))
    assert task.n_trials == 200 and task.sizes == (4, 2)
    model, theta = MODELS["q_learning"], np.array([0.4, 3.0])
    data = pd.concat([task.simulate(model, theta, s) for s in range(5)], ignore_index=True)
    assert set(np.unique(data["reward"])) == {0.0, 1.0}
    correct = (data["choice"] == data["state"] % 2).to_numpy()
    first = ((data["trial"] - 1) // 50 % 2 == 0).to_numpy()  # blocks 1 and 3: correct pays 0.8
    better = correct == first
    _within_binomial(data["reward"].to_numpy()[better], 0.8)
    _within_binomial(data["reward"].to_numpy()[~better], 0.2)

    one = task.simulate(model, theta, 0)
    table = ChoiceData.from_table(one, 2, 4)
    fit = fit_choices(table, model="q_learning", n_starts=2, heldout=False, uncertainty=False)
    est = np.array([fit.params["agent.learning_rate"], fit.params["agent.beta"]])
    zeros = np.zeros(len(one), np.int64)

    def nll(rewards: np.ndarray) -> float:
        return -float(model_logp(model, est, one["choice"].to_numpy(np.int64), rewards,
                                 one["state"].to_numpy(np.int64), zeros, 4, 2).sum())  # fmt: skip

    observed = one["reward"].to_numpy(np.float64)
    p_better = np.where((one["choice"] == one["state"] % 2) == ((one["trial"] - 1) // 50 % 2 == 0),
                        0.8, 0.2)  # fmt: skip
    assert nll(observed) == pytest.approx(fit.nll, abs=1e-6)
    assert abs(nll(p_better) - fit.nll) > 1.0

    rows = recover(task, ["q_learning", "wsls"], 1, n_starts=1)
    assert len(rows) == 4 and np.isfinite(rows["bic"]).all()


@pytest.mark.slow
def test_cli_recover_on_the_probabilistic_task(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(app, ["recover", "task=two_afc_probabilistic", "models=[q_learning]",
                                 "n=3", "jobs=1", "--out", "rec"], catch_exceptions=False)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    summary = json.loads((tmp_path / "rec" / "recover.json").read_text())
    assert summary["n_trials"] == 200 and summary["models"] == ["q_learning"]
    table = pd.read_parquet(tmp_path / "rec" / "recovery.parquet")
    assert len(table) == 3 and table["fit:agent.learning_rate"].between(0, 1).all()


@pytest.mark.slow
def test_trials_table_records_the_drawn_rewards(tmp_path):
    """`cobel run task=two_afc_probabilistic`: the trials table's reward is each trial's drawn
    outcome (0 or 1, at the stated rate for correct and incorrect choices), with the choice."""
    import cobelrun

    r = cobelrun.run("two_afc_probabilistic", ["task.runs=2", "env.reward_probs=[0.7,0.3]",
                                               "task.protocol.phases.0.trials=150"],
                     out=tmp_path / "run")  # fmt: skip
    t = r.trials
    assert len(t) == 300 and set(np.unique(t["reward"])) <= {0.0, 1.0}
    correct = (t["choice"] == t["start_state"] % 2).to_numpy()
    assert 0 < (~correct).sum() and 0 < correct.sum()
    _within_binomial(t["reward"].to_numpy()[correct], 0.7)
    _within_binomial(t["reward"].to_numpy()[~correct], 0.3)


def test_the_docs_fit_example_is_what_its_recipe_gives(tmp_path, monkeypatch):
    """docs/two_afc.md's recipe (the python block) makes afc.csv; `cobel fit` on it prints the
    console block shown there, line for line."""
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "two_afc.md").read_text()
    recipe = re.search(r"```python\n(.*?)```", doc, re.S).group(1)
    shown = re.search(r"```console\n\$ cobel fit (.*?)\n(.*?)```", doc, re.S)
    monkeypatch.chdir(tmp_path)
    exec(compile(recipe, "two_afc.md", "exec"), {})  # the docs' own code, as a reader runs it
    assert (tmp_path / "afc.csv").is_file()
    result = CliRunner().invoke(app, ["fit", *shown.group(1).split()])
    assert result.exit_code == 0, result.output
    assert result.output.splitlines() == shown.group(2).strip().splitlines()
