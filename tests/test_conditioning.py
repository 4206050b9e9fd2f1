"""Conditioning paradigms (issue 36): each task's expected pattern, which model shows it and
which does not (stated in the task's YAML)."""

from __future__ import annotations

import numpy as np
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
    bad = CliRunner().invoke(app, ["fit", "task=acquisition_extinction", "agent=td_conditioning",
                                   "data=c.csv", "--out", "x.json"])  # fmt: skip
    assert bad.exit_code != 0 and "agent TDConditioning has no choice likelihood" in bad.stderr
