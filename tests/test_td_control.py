"""The tabular TD-control family: SARSA, Q(lambda), SARSA(lambda), Monte-Carlo control, the
tabular actor-critic and Dyna actor-critic (cobelrun.agents.td_control, td_kernels)."""

from __future__ import annotations

import numpy as np
import pytest

from cobelrun.agents import (
    DynaActorCritic,
    MCControl,
    QLambda,
    Sarsa,
    SarsaLambda,
    TabularActorCritic,
)
from cobelrun.agents.base import TrialCallback
from cobelrun.envs import GridWorldEnv, from_layout, open_field
from cobelrun.errors import ConfigError

VARIANTS = [
    (Sarsa, {}),
    (QLambda, {}),
    (QLambda, {"trace": "accumulating"}),
    (SarsaLambda, {}),
    (SarsaLambda, {"trace": "accumulating", "learning_rate": 0.3}),  # accumulating: a smaller step
    (MCControl, {}),
    (TabularActorCritic, {}),
    (DynaActorCritic, {"replay_batch": 2}),
]
IDS = ["sarsa", "q_lambda", "q_lambda_acc", "sarsa_lambda", "sarsa_lambda_acc", "mc",
       "actor_critic", "dyna_ac"]  # fmt: skip


def _run(cls, kw, engine, callbacks=()):
    world = from_layout("S....\n.#.#.\n....G", slip=0.2)
    world.starts = np.array([0, 1, 5])
    env = GridWorldEnv(world)
    env.unwrapped.np_random = np.random.default_rng(7)
    agent = cls(env, seed=11, engine=engine, **kw)
    return agent, [agent.train(15, 40, callbacks), agent.test(3, 40, callbacks)]


class _Steps(TrialCallback):
    def __init__(self):
        self.n = 0

    def _on_step(self, agent, trial, step, transition):
        self.n += 1


@pytest.mark.parametrize("policy", ["epsilon_greedy", "softmax"])
@pytest.mark.parametrize(("cls", "kw"), VARIANTS, ids=IDS)
def test_compiled_and_python_paths_give_identical_tables(cls, kw, policy):
    """Same seeds, stochastic world, several starts: the compiled trial loop and the Python
    step loop (as with per-step hooks) give the same steps and learned arrays."""
    kw = {**kw, "policy": policy, "beta": 3.0}
    a, fast = _run(cls, kw, "compiled")
    steps = _Steps()
    b, slow = _run(cls, kw, "auto", [steps])
    assert steps.n == sum(int(x.steps.sum()) for x in slow)
    for x, y in zip(fast, slow, strict=True):
        for field in ("start_state", "steps", "terminated", "step_state", "step_action",
                      "step_next_state", "step_reward"):  # fmt: skip
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field), err_msg=field)
    assert fast[0].terminated.sum() >= 1
    for key, arr in a.get_state().items():
        np.testing.assert_array_equal(arr, b.get_state()[key], err_msg=key)
    assert np.abs(a.predict(np.arange(15))).sum() > 0  # it learned something


def _greedy_path(agent, world, start=0, cap=100):
    s = start
    for n in range(1, cap + 1):
        s = int(world.next_state[s, int(np.argmax(agent.predict(np.array([s]))[0]))])
        if world.terminal[s]:
            return n
    return cap


@pytest.mark.parametrize(("cls", "kw"), VARIANTS, ids=IDS)
def test_learns_the_open_field_within_20_percent_of_the_shortest_path(cls, kw):
    """9 x 9 open field, corner to corner (16 steps), 200 episodes with the agent's default
    parameters: the greedy path of the learned values is within 20 % of 16 steps (mean of
    three seeds)."""
    lengths = []
    for seed in range(3):
        env = GridWorldEnv(open_field(9, 9, starts=[0], goal=80))
        env.unwrapped.np_random = np.random.default_rng(seed)
        agent = cls(env, seed=seed, **kw)
        batch = agent.train(200, 500)
        assert batch.steps[:5].mean() > 30  # it starts far from the shortest path
        lengths.append(_greedy_path(agent, env.unwrapped.world))
    assert np.mean(lengths) <= 1.2 * 16, lengths


def test_mc_update_backs_up_first_visit_returns():
    from cobelrun.agents.td_kernels import mc_update

    Q = np.zeros((3, 2))
    states = np.array([0, 1, 0, 2])
    actions = np.array([1, 0, 1, 1])
    rewards = np.array([0.0, 0.0, 0.0, 1.0])
    seen = np.zeros((3, 2), bool)
    mc_update(Q, states, actions, rewards, 0.5, 1.0, seen, np.empty(4))
    # first visit of (0, 1) at t = 0: G_0 = 0.5^3; (1, 0): 0.5^2; (2, 1): 1
    np.testing.assert_allclose(Q, [[0, 0.125], [0.25, 0], [0, 1.0]])
    assert not seen.any()


def test_watkins_q_lambda_cuts_traces_after_an_exploratory_action():
    from cobelrun.agents.td_kernels import Q_LAMBDA, REPLACING, td_step

    Q = np.zeros((3, 2))
    Q[1] = [1.0, 0.0]  # in state 1 action 0 is greedy
    E = np.zeros((3, 2))
    V = np.zeros(3)
    td_step(Q_LAMBDA, Q, V, E, 0, 0, 0.0, 1, False, 0, 0.5, 0.0, 0.9, 0.8, REPLACING)
    assert E[0, 0] == pytest.approx(0.9 * 0.8)  # greedy next action: decayed
    assert Q[0, 0] == pytest.approx(0.5 * 0.9)
    Q[2] = [1.0, 0.0]
    td_step(Q_LAMBDA, Q, V, E, 1, 1, 0.0, 2, False, 1, 0.5, 0.0, 0.9, 0.8, REPLACING)
    assert not E.any()  # a' = 1 is not greedy in state 2: traces cut
    # the backup itself used max Q(2) = 1 (off-policy) through both traces
    assert Q[1, 1] == pytest.approx(0.5 * 0.9)
    assert Q[0, 0] == pytest.approx(0.45 + 0.5 * 0.9 * 0.72)


@pytest.mark.parametrize(
    ("cls", "kw", "match"),
    [
        (Sarsa, {"learning_rate": 1.5}, r"agent.learning_rate must be a number in \[0, 1.0\]"),
        (
            QLambda,
            {"trace": "replace"},
            r"agent.trace 'replace' is not known \(did you mean 'replacing'\?\)",
        ),
        (SarsaLambda, {"lam": -0.1}, r"agent.lam must be a number in \[0, 1.0\]"),
        (MCControl, {"policy": "greedy"}, r"agent.policy 'greedy' is not known"),
        (TabularActorCritic, {"learning_rate": 0.1}, r"use agent.actor_lr and agent.critic_lr"),
        (DynaActorCritic, {"replay_batch": 0}, r"agent.replay_batch must be an integer >= 1"),
        (Sarsa, {"engine": "jit"}, r"agent.engine 'jit' is not known"),
    ],
)
def test_bad_parameters_are_one_line_config_errors(cls, kw, match):
    env = GridWorldEnv(open_field(3, 3, starts=[0], goal=8))
    with pytest.raises(ConfigError, match=match):
        cls(env, **kw)
