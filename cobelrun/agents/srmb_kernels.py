"""Compiled kernels of SR-MB (Russek et al. 2017), numba.

SR-MB values actions as ``Q(s, :) = T(s, :, :) v`` with ``v = (I - gamma T_pi)^-1 w``: one
linear solve (LAPACK's ``gesv`` through ``np.linalg.solve``) after each change of the model,
``w`` or the cached policy. The building blocks (:func:`mb_values`, :func:`mb_q`,
:func:`mb_learn`) serve the agent's Python step loop; :func:`run_srmb_trials` runs whole trials
with the same blocks in the same order (identical results for the same seeds, tested).
Kept apart from :mod:`cobelrun.agents.sr_kernels` because numba's linear algebra loads
LAPACK (scipy) when the kernel is loaded, which SR-TD and SR-Dyna runs do not need.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from cobelrun.agents import kernels as _kernels  # noqa: F401  (numba import without scipy probe)
from cobelrun.agents.kernels import draw_next, draw_start, select_action


@njit(cache=True)
def mb_values(T, cached_policy, terminal, w, gamma):
    """``v = (I - gamma T_pi)^-1 w`` with ``T_pi(s) = sum_a pi(s, a) T(s, a)`` and the terminal
    rows of ``T_pi`` zero, by one linear solve."""
    S, A = cached_policy.shape
    lhs = np.empty((S, S))
    for s in range(S):
        for t in range(S):
            v = 0.0
            if not terminal[s]:
                for a in range(A):
                    v += cached_policy[s, a] * T[s, a, t]
            lhs[s, t] = (1.0 if s == t else 0.0) - gamma * v
    return np.linalg.solve(lhs, w)


@njit(cache=True, inline="always")
def mb_q(T, v, s, q):
    """``q[b] = T(s, b, :) . v``."""
    n = v.shape[0]
    for b in range(T.shape[1]):
        x = 0.0
        for k in range(n):
            x += T[s, b, k] * v[k]
        q[b] = x


@njit(cache=True)
def mb_learn(T, cached_policy, terminal, w, s, a, r, s2, done, gamma, rate, reward_rate, q):
    """One SR-MB learning step; returns ``(v, valid)``.

    ``w(s') += lr_w (r - w(s'))``; the model row ``T(s, a) *= 1 - rate``,
    ``T(s, a, s') += rate``; ``s'`` marked terminal if it was; then the cached policy of ``s``
    becomes the greedy one under the new values (ties split evenly). ``v`` are the values
    with the new model and ``w``; ``valid`` says whether the cached policy kept its row (so
    ``v`` needs no second solve).
    """
    w[s2] += reward_rate * (r - w[s2])
    keep = 1.0 - rate
    for t in range(T.shape[2]):
        T[s, a, t] *= keep
    T[s, a, s2] += rate
    if done:
        terminal[s2] = True
    v = mb_values(T, cached_policy, terminal, w, gamma)
    mb_q(T, v, s, q)
    best = q[0]
    for b in range(1, q.shape[0]):
        if q[b] > best:
            best = q[b]
    m = 0
    for b in range(q.shape[0]):
        if q[b] == best:
            m += 1
    valid = True
    for b in range(q.shape[0]):
        p = 1.0 / m if q[b] == best else 0.0
        if cached_policy[s, b] != p:
            valid = False
            cached_policy[s, b] = p
    return v, valid


@njit(cache=True)
def mb_act(rng, T, v, s, policy, epsilon, beta):
    """The behaviour policy's action in ``s`` over ``T(s) v`` (the Python loop's act)."""
    q = np.empty(T.shape[1])
    mb_q(T, v, s, q)
    return select_action(rng, q, np.ones(1, np.bool_), False, policy, epsilon, beta)


@njit(cache=True, nogil=True)
def run_srmb_trials(
    rng, env_rng, T, cached_policy, agent_terminal, w,
    deterministic, next_state, T_cum, R, terminal, starts,
    policy, epsilon, beta, gamma, rate, reward_rate,
    n_trials, max_steps, learn,
    out_state, out_action, out_next, out_reward,
    out_steps, out_term, out_start, out_end, out_rsum, out_offsets,
):  # fmt: skip
    """Run ``n_trials`` SR-MB trials; fill the step and trial buffers (as
    :func:`cobelrun.agents.kernels.run_trials`); return the number of steps.

    ``T``, ``cached_policy``, ``agent_terminal`` (the terminal states the agent knows) and
    ``w`` are the agent's and are updated in place; ``terminal`` is the world's.
    """
    n_actions = T.shape[1]
    q = np.empty(n_actions)
    q2 = np.empty(n_actions)
    nomask = np.ones(1, np.bool_)
    v = mb_values(T, cached_policy, agent_terminal, w, gamma)
    k = 0
    for trial in range(n_trials):
        s = draw_start(env_rng, starts)
        out_start[trial] = s
        done = False
        n = 0
        rsum = 0.0
        while n < max_steps:
            mb_q(T, v, s, q)
            a = select_action(rng, q, nomask, False, policy, epsilon, beta)
            s2 = draw_next(env_rng, deterministic, next_state, T_cum, s, a)
            r = R[s2]
            done = terminal[s2]
            if learn:
                v, valid = mb_learn(T, cached_policy, agent_terminal, w, s, a, r, s2, done,
                                    gamma, rate, reward_rate, q2)  # fmt: skip
                if not valid:
                    v = mb_values(T, cached_policy, agent_terminal, w, gamma)
            out_state[k] = s
            out_action[k] = a
            out_next[k] = s2
            out_reward[k] = r
            rsum += r
            k += 1
            n += 1
            s = s2
            if done:
                break
        out_steps[trial] = n
        out_term[trial] = done
        out_end[trial] = s
        out_rsum[trial] = rsum
        out_offsets[trial + 1] = k
    return k
