"""Plumbing shared by tabular agents whose trials run in compiled code (numba).

An agent with a compiled trial kernel (SR-TD, SR-Dyna, SR-MB, SARSA, ...) chooses its engine
with :func:`use_compiled`, reads the world's tables with :func:`world_tables`, hands the kernel
the output buffers of :class:`TrialBuffers`, and runs trial-end callbacks between compiled
trials with :func:`run_trial_by_trial`. The kernels themselves live in their own modules
(imported on first use, so a run loads only the kernels it calls).

Importing this module does not import numba.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import TrialCallback
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.records import TrialBatch

#: values of an agent's ``engine`` parameter
ENGINES = ("auto", "compiled", "python")

# placeholders for the table a kernel does not read (deterministic or stochastic worlds)
_NO_NEXT_STATE = np.zeros((1, 1), np.int64)
_NO_T_CUM = np.zeros((1, 1, 1))


def check_engine(engine: str) -> str:
    """Return ``engine`` if known, else a one-line ConfigError naming ``agent.engine``."""
    if engine not in ENGINES:
        raise ConfigError(
            f"agent.engine {engine!r} is not known{suggest(engine, ENGINES)}; "
            f"allowed: {allowed_list(ENGINES)}"
        )
    return engine


def use_compiled(engine: str, callbacks: Sequence[TrialCallback], env: gym.Env) -> bool:
    """Whether trials run in compiled code: not with ``engine="python"``, per-step callbacks
    or noisy rewards (the kernels read exact rewards); ``engine="compiled"`` refuses those
    with a one-line ConfigError. The env must be a tabular gridworld (checked by the agent)."""
    if engine == "python":
        return False
    if callbacks and not all(cb.trial_end_only() for cb in callbacks):
        if engine == "compiled":
            raise ConfigError("agent.engine 'compiled' cannot run per-step callbacks")
        return False
    if env.unwrapped.world.reward_sd > 0.0:
        if engine == "compiled":
            raise ConfigError(
                "agent.engine 'compiled' needs exact rewards (env.world.reward_sd = 0); "
                "use 'auto' or 'python'"
            )
        return False
    return True


def may_compile(engine: str, env: gym.Env) -> bool:
    """Whether this agent's trials can run in compiled code at all (not ``engine="python"``,
    exact rewards of a tabular world): then :meth:`prepare` has a kernel to load."""
    return engine != "python" and env.unwrapped.world.reward_sd == 0.0


def load_kernel(run_compiled: Callable[[int, int, bool], Any]) -> None:
    """Load a compiled trial kernel now (an agent's :meth:`~cobelrun.agents.base.Agent.prepare`)
    by running zero trials with it: the argument types of the agent's next trials, so numba
    loads that signature's cached machine code.

    The first call of the first numba kernel in a process pays numba's once-per-process start
    (its import, ~0.3-0.5 s, and its first dispatch, ~0.2-0.4 s: typing and lowering
    registries, LLVM), then ~10-30 ms for the kernel's cached machine code. Zero trials make
    no draw and change nothing.
    """
    run_compiled(0, 1, True)


class WorldTables:
    """The world's tables as a compiled kernel takes them, cached per agent.

    ``deterministic, next_state, T_cum, R, terminal, starts, env_rng``: a deterministic world
    hands its next-state table, a stochastic one its cumulative transition probabilities;
    ``env_rng`` is None when the world draws nothing (deterministic, one start state), since
    handing a Generator to compiled code costs ~10-30 us per call.
    """

    def __init__(self) -> None:
        self._T: np.ndarray | None = None
        self._T_cum: np.ndarray | None = None

    def args(self, env: gym.Env) -> tuple[Any, ...]:
        base = env.unwrapped
        world = base.world
        det_table = world.next_state
        deterministic = det_table is not None
        starts = np.ascontiguousarray(world.starts, np.int64)
        if deterministic:
            next_state, T_cum = det_table, _NO_T_CUM
        else:
            if self._T is not world.T:  # the cumulative table, kept while T is the same array
                self._T, self._T_cum = world.T, np.cumsum(world.T, axis=2)
            next_state, T_cum = _NO_NEXT_STATE, self._T_cum
        env_rng = None if deterministic and starts.shape[0] <= 1 else base.np_random
        return (
            deterministic,
            next_state,
            T_cum,
            np.ascontiguousarray(world.rewards, np.float64),
            np.ascontiguousarray(world.terminal, np.bool_),
            starts,
            env_rng,
        )


class TrialBuffers:
    """Output buffers of a compiled trial kernel for ``n_trials`` of at most ``max_steps``.

    :meth:`args` are, in this order: per step state, action, next state, reward; per trial
    steps, terminated, start state, end state, reward sum, offsets (``n_trials + 1``).
    """

    def __init__(self, n_trials: int, max_steps: int) -> None:
        cap = n_trials * max_steps
        self.step_ints = np.empty((3, cap), np.int64)
        self.step_reward = np.empty(cap, np.float64)
        self.trial_ints = np.empty((3, n_trials), np.int64)
        self.reward = np.empty(n_trials, np.float64)
        self.term = np.empty(n_trials, np.bool_)
        self.offsets = np.zeros(n_trials + 1, np.int64)

    def args(self) -> tuple[np.ndarray, ...]:
        si, ti = self.step_ints, self.trial_ints
        return (si[0], si[1], si[2], self.step_reward,
                ti[0], self.term, ti[1], ti[2], self.reward, self.offsets)  # fmt: skip

    def batch(self, total: int) -> TrialBatch:
        """The :class:`TrialBatch` of the first ``total`` steps."""
        steps = self.step_ints[:, :total].copy()
        return TrialBatch(
            start_state=self.trial_ints[1],
            end_state=self.trial_ints[2],
            steps=self.trial_ints[0],
            reward=self.reward,
            terminated=self.term,
            offsets=self.offsets,
            step_state=steps[0],
            step_action=steps[1],
            step_next_state=steps[2],
            step_reward=self.step_reward[:total].copy(),
        )


def run_trial_by_trial(
    agent: Any,
    run_compiled: Callable[[int, int, bool], TrialBatch],
    n_trials: int,
    max_steps: int,
    learn: bool,
    callbacks: Sequence[TrialCallback],
) -> TrialBatch:
    """``run_compiled`` for all trials at once, or, with (trial-end-only) callbacks, one
    compiled trial at a time with the callbacks between trials: the same draws in the same
    order, so the same results."""
    if not callbacks:
        return run_compiled(n_trials, max_steps, learn)
    batches = []
    for trial in range(n_trials):
        b = run_compiled(1, max_steps, learn)
        record = {"states": [int(b.start_state[0]), *b.step_next_state.tolist()],
                  "actions": b.step_action.tolist(), "rewards": b.step_reward.tolist(),
                  "terminated": bool(b.terminated[0])}  # fmt: skip
        for cb in callbacks:
            cb.on_trial_end(agent, trial, record)
        batches.append(b)
    return TrialBatch.concat(batches)
