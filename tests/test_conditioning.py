"""Conditioning paradigms (issue 36): each task's expected pattern, which model shows it and
which does not (stated in the task's YAML)."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

import cobelrun
from cobelrun.envs import SequenceEnv
from cobelrun.errors import ConfigError

RW, TD, RW_CTX = ["agent=rescorla_wagner"], ["agent=td_conditioning"], [
    "agent=rescorla_wagner", "agent.context_cues=true"]  # fmt: skip


def _test_v(task: str, agent: list[str], tmp_path, phase: str = "test") -> dict[str, float]:
    r = cobelrun.run(task, [*agent, "task.runs=3"], out=tmp_path / f"{task}-{'-'.join(agent)}")
    t = r.trials
    assert {"trial_type", "cues", "V", "responded"} <= set(t.columns)
    part = t[t["phase"] == phase]
    return part.groupby("trial_type")["V"].mean().to_dict()


@pytest.mark.parametrize("agent", [RW, TD], ids=["rescorla_wagner", "td_conditioning"])
def test_acquisition_extinction(agent, tmp_path):
    r = cobelrun.run("acquisition_extinction", [*agent, "task.runs=3"], out=tmp_path / "r")
    t = r.trials
    end = t.groupby(["run", "phase"])["V"].last().groupby("phase").mean()
    assert end["acquisition"] > 0.7 and end["extinction"] < 0.2
    # responding follows V through the logistic response model
    acq = t[t["phase"] == "acquisition"]
    assert acq[acq["trial_in_phase"] > 30]["responded"].mean() > 0.7
    assert set(t["cues"]) == {"A"}


@pytest.mark.parametrize("agent", [RW, TD], ids=["rescorla_wagner", "td_conditioning"])
def test_blocking(agent, tmp_path):
    v = _test_v("blocking", agent, tmp_path)
    assert v["B"] < 0.5 * v["D"] and v["D"] > 0.3


@pytest.mark.parametrize("agent", [RW, TD], ids=["rescorla_wagner", "td_conditioning"])
def test_overshadowing(agent, tmp_path):
    v = _test_v("overshadowing", agent, tmp_path)
    assert v["B"] < 0.75 * v["C"] and v["B"] > 0.1


@pytest.mark.parametrize("agent", [RW, TD], ids=["rescorla_wagner", "td_conditioning"])
def test_conditioned_inhibition(agent, tmp_path):
    v = _test_v("conditioned_inhibition", agent, tmp_path)
    assert v["X"] < -0.2 and v["AX"] < 0.5 * v["A"]


def test_second_order_td_shows_it_rw_does_not(tmp_path):
    assert _test_v("second_order", TD, tmp_path)["B"] > 0.1
    assert _test_v("second_order", RW, tmp_path)["B"] <= 0.0


def test_renewal_needs_context(tmp_path):
    rw = _test_v("renewal", RW, tmp_path)
    assert rw["A_in_ctx_A"] == pytest.approx(rw["A_in_ctx_B"]) and rw["A_in_ctx_A"] < 0.2
    for agent in (RW_CTX, TD):
        v = _test_v("renewal", agent, tmp_path)
        assert v["A_in_ctx_A"] > v["A_in_ctx_B"] + 0.2, (agent, v)


def test_sequence_env_observation_and_checks():
    from gymnasium.utils.env_checker import check_env

    env = SequenceEnv(["A", "B"], {"BA": {"cues": {"B": [0, 2], "A": [2, 4]}, "outcome": 1.0,
                                          "us": 3, "context": "ctx"}}, contexts=["ctx"],
                      length=5, csc=True)  # fmt: skip
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert info["cues"] == "ctx+A+B" and obs.shape == (3 + 2 * 5,)
    rewards, seen = [], [obs]
    done = False
    while not done:
        obs, r, done, _, _ = env.step(0)
        rewards.append(r)
        seen.append(obs)
    assert rewards == [0, 0, 0, 1.0, 0] and len(rewards) == 5
    presence = np.array(seen)[:5, :3]
    np.testing.assert_array_equal(presence[:, 2], 1)  # context on throughout
    np.testing.assert_array_equal(presence[:, 1], [1, 1, 0, 0, 0])  # B on at 0..1
    csc = np.array(seen)[:5, 3:].reshape(5, 2, 5)
    assert csc[3, 0, 1] == 1 and csc[1, 1, 1] == 1 and csc[3, 1].sum() == 0
    env.apply_changes(rewards={"BA": 0.0})
    assert env.outcome.tolist() == [0.0]
    env.reset_world()
    assert env.outcome.tolist() == [1.0]
    for kwargs, message in [
        ({"trial_types": {"T": {"cues": {"Z": [0, 1]}}}}, "unknown cue 'Z'"),
        ({"trial_types": {"T": {"cues": {"A": [3, 2]}}}}, "on < off"),
        ({"trial_types": {"T": {"us": 9}}}, "us must lie in"),
        ({"trial_types": {"T": {"outcme": 1}}}, "unknown key"),
    ]:
        with pytest.raises(ConfigError, match=message):
            SequenceEnv(["A"], length=4, **kwargs)
    with pytest.raises(ConfigError, match="unknown trial type 'Q'"):
        env.apply_changes(starts=["Q"])


def test_td_needs_the_serial_compound(tmp_path):
    with pytest.raises(ConfigError, match=r"env\.csc=true"):
        cobelrun.run("blocking", [*TD, "env.csc=false", "task.runs=1"], out=tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_fit_recovers_rescorla_wagner_from_responses(tmp_path, monkeypatch):
    """`cobel fit task=acquisition_extinction agent=rescorla_wagner` on the responses of 20
    simulated RW agents (learning rate 0.3, response_beta 8): the intervals hold both."""
    import json

    from typer.testing import CliRunner

    from cobelrun.cli import app

    r = cobelrun.run("acquisition_extinction", [*RW, "task.runs=20", "agent.learning_rate=0.3",
                                                "agent.response_beta=8"], out=tmp_path / "r")  # fmt: skip
    t = r.trials
    data = t.rename(columns={"run": "session", "start_state": "state", "response": "choice"})
    data[["session", "trial", "state", "choice", "reward"]].to_csv(tmp_path / "c.csv", index=False)
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["fit", "task=acquisition_extinction", "agent=rescorla_wagner",
                                   "data=c.csv"], catch_exceptions=False)  # fmt: skip
    assert out.exit_code == 0, out.stderr
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert fit["model"] == "rw_response"
    assert fit["fixed"] == {"agent.response_threshold": 0.5, "agent.asymptote": 1.0}
    for key, truth in (("agent.learning_rate", 0.3), ("agent.response_beta", 8.0)):
        lo, hi = fit["ci95"][key]
        assert lo <= truth <= hi, (key, fit["params"][key], lo, hi)
    bad = CliRunner().invoke(app, ["fit", "task=acquisition_extinction", "agent=sarsa",
                                   "data=c.csv", "--out", "x.json"])  # fmt: skip
    assert bad.exit_code != 0
    assert ("agent Sarsa has no choice likelihood; fittable agents: agent=q_learning, "
            "agent=dyna_q, agent=rescorla_wagner, agent=td_conditioning, agent=pearce_hall"
            in bad.stderr)  # fmt: skip
    assert not (tmp_path / "x.json").exists()


PH = ["agent=pearce_hall"]


def test_latent_inhibition_pearce_hall_shows_it_rw_does_not(tmp_path):
    """Latent inhibition (Lubow & Moore 1959): the preexposed A conditions more slowly than the
    novel B. Compared by the k-th reinforced trial of each cue: Pearce-Hall's V(A) lags V(B)
    (A's associability fell during preexposure); Rescorla-Wagner's are equal, trial by trial."""

    def kth(agent: list[str]) -> pd.DataFrame:
        r = cobelrun.run("latent_inhibition", [*agent, "task.runs=3"],
                         out=tmp_path / agent[0].replace("=", "-"))  # fmt: skip
        c = r.trials[r.trials["phase"] == "conditioning"].copy()
        c["k"] = c.groupby(["run", "trial_type"]).cumcount()
        return c[c["k"].between(1, 5)].pivot_table(index=["run", "k"], columns="trial_type",
                                                   values="V")  # fmt: skip

    ph = kth(PH)
    assert (ph["A"] < ph["B"] - 0.1).all(), ph
    assert ph["A"].mean() < 0.6 * ph["B"].mean()
    rw = kth(RW)
    np.testing.assert_allclose(rw["A"], rw["B"], rtol=1e-12)
    assert rw["A"].min() > 0.15


LIKELIHOOD_CASES = [
    ("second_order", "td_conditioning", "td_response"),
    ("renewal", "td_conditioning", "td_response"),
    ("blocking", "rescorla_wagner", "rw_response"),
    ("blocking", "pearce_hall", "ph_response"),
    ("latent_inhibition", "pearce_hall", "ph_response"),
]


def _responses(trials: pd.DataFrame, cfg) -> pd.DataFrame:
    """A run's trials table as choice data (the response at the cue's onset; learn 0 in
    phases with learning off)."""
    learning = {p["name"]: p.get("learning", True) for p in cfg.task.protocol.phases}
    return pd.DataFrame({"session": trials["run"], "trial": trials["trial"],
                         "state": trials["start_state"], "choice": trials["response"],
                         "reward": trials["reward"],
                         "learn": trials["phase"].map(learning).astype(int)})  # fmt: skip


def _config(task: str, agent: str, *extra: str):
    from cobelrun.config import register_resolvers
    from cobelrun.hydra_app import composer

    register_resolvers()
    with composer() as compose:
        return compose([f"task={task}", f"agent={agent}", *extra])


@pytest.mark.parametrize("task, agent, model", LIKELIHOOD_CASES)
def test_likelihood_replays_the_agent_exactly(task, agent, model, tmp_path):
    """The conditioning models' likelihood runs the agent's own update: on the agent's
    simulated trials (test phases with learning off included) the predictions it responds on
    equal the agents' V column exactly, and each response's log-probability is that of the
    logistic response on it."""
    from omegaconf import OmegaConf

    from cobelrun.choice_models import MODELS, model_logp
    from cobelrun.config import instantiate
    from cobelrun.fit import ChoiceData, task_features

    cfg = _config(task, agent)
    r = cobelrun.run(task, [f"agent={agent}", "task.runs=2"], out=tmp_path / "r")
    t = r.trials
    script = task_features(instantiate("env", cfg.env))
    table = ChoiceData.from_table(_responses(t, cfg), 2, script.n_states)
    spec = MODELS[model]
    theta = np.array([float(OmegaConf.select(cfg, k)) for k in spec.keys])
    values = np.zeros(len(t))
    logp = model_logp(spec, theta, table.choices, table.rewards, table.states, table.sessions,
                      script.n_states, 2, script, table.learns, values)  # fmt: skip
    np.testing.assert_array_equal(values, t["V"].to_numpy())
    threshold = float(cfg.agent.response_threshold)
    p1 = 1 / (1 + np.exp(-float(cfg.agent.response_beta) * (values - threshold)))
    np.testing.assert_allclose(logp, np.log(np.where(t["response"] == 1, p1, 1 - p1)))


@pytest.mark.parametrize(
    "task, agent, truth, extra",
    [
        ("acquisition_extinction", "td_conditioning",
         {"agent.learning_rate": 0.15, "agent.response_beta": 8.0}, []),
        pytest.param("latent_inhibition", "pearce_hall",
                     {"agent.learning_rate": 0.3, "agent.response_beta": 8.0},
                     ["params=[agent.learning_rate,agent.response_beta]"],
                     marks=pytest.mark.slow),
    ],
    ids=["td_conditioning", "pearce_hall"],
)  # fmt: skip
def test_cli_fit_recovers_conditioning_agents(tmp_path, monkeypatch, task, agent, truth, extra):
    """`cobel fit task=... agent=td_conditioning|pearce_hall` on the responses of 20 simulated
    agents of cobel's own class: the 95 % intervals hold the generating values."""
    import json

    from typer.testing import CliRunner

    from cobelrun.cli import app

    sets = [f"{k}={v}" for k, v in truth.items()]
    r = cobelrun.run(task, [f"agent={agent}", "task.runs=20", *sets], out=tmp_path / "r")
    _responses(r.trials, _config(task, agent)).to_csv(tmp_path / "c.csv", index=False)
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["fit", f"task={task}", f"agent={agent}", "data=c.csv",
                                   *extra], catch_exceptions=False)  # fmt: skip
    assert out.exit_code == 0, out.stderr
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert fit["model"] == {"td_conditioning": "td_response", "pearce_hall": "ph_response"}[agent]
    for key, value in truth.items():
        lo, hi = fit["ci95"][key]
        assert lo <= value <= hi, (key, fit["params"][key], lo, hi)


def test_pearce_hall_agent_checks_and_saves(tmp_path):
    with pytest.raises(ConfigError, match="associability_rate"):
        cobelrun.run("latent_inhibition", ["agent.associability_rate=1.5"], out=tmp_path / "x")
    assert not (tmp_path / "x").exists()
    from cobelrun.agents.conditioning import PearceHall

    env = SequenceEnv(["A", "B"], {"AB": {"cues": {"A": [0, 2], "B": [0, 2]}, "outcome": 1.0}},
                      length=2)  # fmt: skip
    agent = PearceHall(env, learning_rate=0.5, associability_rate=0.5, seed=0)
    agent.begin_trial(*env.reset(seed=0), learn=True)
    agent._us = 1.0
    agent.end_trial(learn=True)
    # delta 1: w = 0.5 * 1 * 1 each; alpha = 0.5 * 1 + 0.5 * 1 = 1
    np.testing.assert_allclose(agent.get_state()["w"], [0.5, 0.5])
    agent.begin_trial(*env.reset(), learn=True)
    agent._us = 1.0
    agent.end_trial(learn=True)
    # V 1, delta 0: weights stay, associabilities halve
    np.testing.assert_allclose(agent.get_state()["alpha"], [0.5, 0.5])


@pytest.mark.parametrize(
    "args, rows, message",
    [
        (["task=second_order", "agent=td_conditioning", "task.protocol.max_steps=6"],
         {"choice": [1, 0], "reward": [1.0, 0.0]},
         "protocol stops trials after 6 steps, but its trials last 10"),
        (["task=second_order", "agent=td_conditioning"],
         {"choice": [1, 0], "reward": [1.0, 0.0], "learn": [1, 2]},
         r"learn must lie in 0..1, got 2 in row 1"),
        (["task=second_order", "agent=td_conditioning"],
         {"choice": [1, 0], "reward": [1.0, float("nan")]},
         "reward must be a finite number, got nan in row 1"),
        (["task=second_order", "agent=td_conditioning"],
         {"choice": [1, 0], "reward": [1.0, 0.0], "state": [0, 3]},
         "state must lie in 0..2, got 3 in row 1"),
        (["task=latent_inhibition", "agent=pearce_hall"],
         {"choice": [1, 2], "reward": [1.0, 0.0]},
         "choices 0..2 (3 actions) but task latent_inhibition's env has 2 actions"),
        (["task=reversal_bandit", "model=td_response"],
         {"choice": [1, 0], "reward": [1.0, 0.0]},
         "model td_response needs the cues of every trial type: fit it with a conditioning task"),
    ],
    ids=["short_trials", "learn_value", "non_finite", "state", "action_set", "no_trial_types"],
)  # fmt: skip
def test_conditioning_fit_bad_input_is_one_line(tmp_path, monkeypatch, args, rows, message):
    from typer.testing import CliRunner

    from cobelrun.cli import app

    pd.DataFrame(rows).to_csv(tmp_path / "c.csv", index=False)
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["fit", *args, "data=c.csv"])
    lines = [line for line in out.stderr.strip().splitlines() if line]
    assert out.exit_code != 0 and len(lines) == 1, out.stderr
    assert re.search(message, lines[0]) or message in lines[0], lines[0]
    assert not (tmp_path / "fit.json").exists()
