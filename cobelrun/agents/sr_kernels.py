"""Compiled kernels of SR-TD and SR-Dyna (Russek et al. 2017), numba.

The building blocks (:func:`sr_q`, :func:`greedy`, :func:`sr_learn`, :func:`sr_replay`) are
what the agents' Python step loop calls (the opt-in path for per-step callbacks);
:func:`run_sr_trials` runs whole trials with the same blocks in the same order, so both paths
give identical trial tables and learned arrays for the same seeds (tested). Every draw goes
through the ``numpy.random.Generator`` passed in. Imported when an SR agent first runs trials;
SR-MB's kernel (which needs LAPACK) lives apart in :mod:`cobelrun.agents.srmb_kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from cobelrun.agents import kernels as _kernels  # noqa: F401  (numba import without scipy probe)
from cobelrun.agents.kernels import draw_next, draw_start, randint, select_action


@njit(cache=True, inline="always")
def sr_q(M, w, s, q):
    """``q[b] = M(s, b, :) . w`` (summed in state order)."""
    n = w.shape[0]
    for b in range(M.shape[1]):
        v = 0.0
        for k in range(n):
            v += M[s, b, k] * w[k]
        q[b] = v


@njit(cache=True, inline="always")
def greedy(rng, q):
    """``argmax_b q[b]`` with a uniform random tie-break (no draw when one action is best, as
    ``rng.integers(1)`` draws nothing)."""
    best = -np.inf
    m = 0
    a = 0
    for b in range(q.shape[0]):
        if q[b] > best:
            best = q[b]
            m = 1
            a = b
        elif q[b] == best:
            m += 1
    if m > 1:
        j = randint(rng, m)
        for b in range(q.shape[0]):
            if q[b] == best:
                if j == 0:
                    return b
                j -= 1
    return a


@njit(cache=True, inline="always")
def sr_td(M, s, a, s2, terminal, a2, gamma, lr):
    """``M(s,a,:) += lr (1_{s'} + gamma M(s', a2, :) - M(s,a,:))`` (no bootstrap if
    ``terminal``)."""
    n = M.shape[2]
    for k in range(n):
        t = 0.0 if terminal else gamma * M[s2, a2, k]
        if k == s2:
            t += 1.0
        M[s, a, k] += lr * (t - M[s, a, k])


@njit(cache=True, inline="always")
def sr_learn(rng, M, w, s, a, r, s2, terminal, gamma, lr, reward_rate, q):
    """One SR-TD step: ``w(s') += lr_w (r - w(s'))``, then the TD update of ``M(s, a)`` towards
    ``1_{s'} + gamma M(s', a*)``, ``a* = argmax_b M(s', b) . w`` (random tie-break; drawn even
    when ``s'`` is terminal). ``q`` is scratch space of length A."""
    w[s2] += reward_rate * (r - w[s2])
    sr_q(M, w, s2, q)
    a2 = greedy(rng, q)
    sr_td(M, s, a, s2, terminal, a2, gamma, lr)


@njit(cache=True, inline="always")
def add_pair(pairs, n_pairs, i):
    """Insert the flat pair ``i`` into the sorted first ``n_pairs[0]`` entries of ``pairs``."""
    n = n_pairs[0]
    j = n
    while j > 0 and pairs[j - 1] > i:
        pairs[j] = pairs[j - 1]
        j -= 1
    pairs[j] = i
    n_pairs[0] = n + 1


@njit(cache=True, inline="always")
def sr_replay(rng, M, w, model_next, model_reward, pairs, n_pairs, terminal, n, gamma, lr,
              reward_rate, replay_reward, q):  # fmt: skip
    """SR-Dyna's replay after a step: ``n`` experiences drawn uniformly (with replacement) from
    the ``n_pairs`` experienced pairs ``pairs`` (sorted flat ``s * A + a``), each replaying the
    pair's last outcome ``s'`` (and reward ``r``): with ``replay_reward`` first
    ``w(s') += lr_w (r - w(s'))``, then the TD update of ``M(s, a)`` with
    ``a* = argmax_b M(s', b) . w`` (random tie-break; no bootstrap from a terminal ``s'``)."""
    A = model_next.shape[1]
    for _ in range(n):
        i = pairs[randint(rng, n_pairs)]
        ps = i // A
        pa = i - ps * A
        ps2 = model_next[ps, pa]
        if replay_reward:
            w[ps2] += reward_rate * (model_reward[ps, pa] - w[ps2])
        sr_q(M, w, ps2, q)
        a2 = greedy(rng, q)
        sr_td(M, ps, pa, ps2, terminal[ps2], a2, gamma, lr)


@njit(cache=True, nogil=True)
def run_sr_trials(
    rng, env_rng, M, w, dyna, model_next, model_reward, pairs, n_pairs,
    deterministic, next_state, T_cum, R, terminal, starts,
    policy, epsilon, beta, gamma, lr, reward_rate, replay_batch, replay_reward,
    n_trials, max_steps, learn,
    out_state, out_action, out_next, out_reward,
    out_steps, out_term, out_start, out_end, out_rsum, out_offsets,
):  # fmt: skip
    """Run ``n_trials`` SR-TD (``dyna`` False) or SR-Dyna trials; fill the step and trial
    buffers (as :func:`cobelrun.agents.kernels.run_trials`); return the number of steps.

    Per step: ``a`` from the policy over ``M(s) . w``, the world's transition and arrival
    reward, then (learning) :func:`sr_learn` and, for SR-Dyna, the model update
    (``model_next``, ``model_reward``, the sorted pair list) and :func:`sr_replay`.
    Makes exactly the draws of the Python step loop, in the same order.
    """
    n_actions = M.shape[1]
    q = np.empty(n_actions)
    q2 = np.empty(n_actions)
    nomask = np.ones(1, np.bool_)
    k = 0
    for trial in range(n_trials):
        s = draw_start(env_rng, starts)
        out_start[trial] = s
        done = False
        n = 0
        rsum = 0.0
        while n < max_steps:
            sr_q(M, w, s, q)
            a = select_action(rng, q, nomask, False, policy, epsilon, beta)
            s2 = draw_next(env_rng, deterministic, next_state, T_cum, s, a)
            r = R[s2]
            done = terminal[s2]
            if learn:
                sr_learn(rng, M, w, s, a, r, s2, done, gamma, lr, reward_rate, q2)
                if dyna:
                    if model_next[s, a] < 0:
                        add_pair(pairs, n_pairs, s * n_actions + a)
                    model_next[s, a] = s2
                    model_reward[s, a] = r
                    if replay_batch > 0:
                        sr_replay(rng, M, w, model_next, model_reward, pairs, n_pairs[0],
                                  terminal, replay_batch, gamma, lr, reward_rate, replay_reward,
                                  q2)  # fmt: skip
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


@njit(cache=True)
def sr_act(rng, M, w, s, policy, epsilon, beta):
    """The behaviour policy's action in ``s`` (the Python loop's :meth:`act`)."""
    q = np.empty(M.shape[1])
    sr_q(M, w, s, q)
    return select_action(rng, q, np.ones(1, np.bool_), False, policy, epsilon, beta)


@njit(cache=True)
def sr_step(rng, M, w, s, a, r, s2, terminal, gamma, lr, reward_rate):
    """:func:`sr_learn` (the Python loop's SR-TD learning step)."""
    sr_learn(rng, M, w, s, a, r, s2, terminal, gamma, lr, reward_rate, np.empty(M.shape[1]))


@njit(cache=True)
def sr_replay_step(rng, M, w, model_next, model_reward, pairs, n_pairs, terminal, n, gamma, lr,
                   reward_rate, replay_reward):  # fmt: skip
    """:func:`sr_replay` (the Python loop's SR-Dyna replay)."""
    sr_replay(rng, M, w, model_next, model_reward, pairs, n_pairs, terminal, n, gamma, lr,
              reward_rate, replay_reward, np.empty(M.shape[1]))  # fmt: skip


@njit(cache=True)
def sr_values(M, w):
    """(S, A) action values ``M @ w`` summed as in :func:`sr_q`."""
    out = np.empty((M.shape[0], M.shape[1]))
    for s in range(M.shape[0]):
        sr_q(M, w, s, out[s])
    return out
