"""``Agent.prepare``: compiled tabular agents load their trial kernel before the first trial,
without changing a draw; building an agent still loads nothing (issue 38, item 4)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from cobelrun.agents import SRMB, SRTD, DynaActorCritic, DynaQ, QLambda, Sarsa, SRDyna
from cobelrun.envs import GridWorldEnv, from_layout

AGENTS = [
    (SRTD, {}),
    (SRDyna, {"replay_batch": 2, "replay_reward": True}),
    (SRMB, {}),
    (Sarsa, {}),
    (QLambda, {}),
    (DynaActorCritic, {"replay_batch": 2}),
    (DynaQ, {"replay_batch": 2}),
]


def _run(cls, kw, prepare):
    world = from_layout("S....\n.#.#.\n....G", slip=0.2)
    world.starts = np.array([0, 1, 5])
    env = GridWorldEnv(world)
    env.unwrapped.np_random = np.random.default_rng(7)
    agent = cls(env, seed=11, **kw)
    if prepare:
        agent.prepare()
    return agent, [agent.train(10, 40), agent.test(2, 40)]


@pytest.mark.parametrize(("cls", "kw"), AGENTS, ids=[c.__name__ for c, _ in AGENTS])
def test_prepare_changes_no_draw(cls, kw):
    """Zero trials run by prepare() make no draw: the same tables and learned arrays."""
    a, with_prepare = _run(cls, kw, True)
    b, without = _run(cls, kw, False)
    for x, y in zip(with_prepare, without, strict=True):
        for field in ("start_state", "steps", "step_action", "step_next_state", "step_reward"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field), err_msg=field)
    assert with_prepare[0].steps.sum() > 20
    for key, arr in a.get_state().items():
        np.testing.assert_array_equal(arr, b.get_state()[key], err_msg=key)


@pytest.mark.slow  # a fresh interpreter: ~1.5 s
def test_building_loads_nothing_and_prepare_loads_the_kernel():
    """Building SR-TD or SARSA imports no numba (validation and a sweep's launcher build agents
    they never run); prepare() loads the agent's trial kernel (one signature), and the python
    engine's prepare loads nothing."""
    code = (
        "import sys\n"
        "from cobelrun.agents import SRTD, Sarsa\n"
        "from cobelrun.envs import GridWorldEnv, open_field\n"
        "env = GridWorldEnv(open_field(4, 4, starts=[0], goal=15))\n"
        "agents = [SRTD(env, seed=0), Sarsa(env, seed=0)]\n"
        "assert 'numba' not in sys.modules, 'numba imported by building an agent'\n"
        "SRTD(env, seed=0, engine='python').prepare()\n"
        "assert 'numba' not in sys.modules, 'numba imported by the python engine'\n"
        "agents[0].prepare()\n"
        "from cobelrun.agents.sr_kernels import run_sr_trials\n"
        "assert len(run_sr_trials.signatures) == 1\n"
        "assert 'cobelrun.agents.td_kernels' not in sys.modules\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
