"""Compiled kernels of the tabular TD-control family (numba): SARSA, Q(lambda), SARSA(lambda),
Monte-Carlo control, the tabular actor-critic and its Dyna variant.

One learning step per algorithm (:func:`td_step`), the Monte-Carlo backup at trial end
(:func:`mc_update`), the actor-critic's model replay (:func:`ac_replay`) and a whole-trial loop
(:func:`run_td_trials`) that calls them in the order the agents' Python step loop does, so both
paths give identical tables for the same seeds (tested). Every draw goes through the
``numpy.random.Generator`` passed in. Imported when such an agent first runs trials.

Algorithm codes (:data:`SARSA` ...) and trace kinds are in :mod:`cobelrun.agents.td_control`,
which mirrors them without importing numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from cobelrun.agents import kernels as _kernels  # noqa: F401  (numba import without scipy probe)
from cobelrun.agents.kernels import draw_next, draw_start, randint, select_action
from cobelrun.agents.sr_kernels import add_pair

SARSA = 0
Q_LAMBDA = 1
SARSA_LAMBDA = 2
MC = 3
AC = 4
ACCUMULATING = 0
REPLACING = 1


@njit(cache=True, inline="always")
def _row_max(Q, s):
    best = Q[s, 0]
    for b in range(1, Q.shape[1]):
        if Q[s, b] > best:
            best = Q[s, b]
    return best


@njit(cache=True, inline="always")
def _traced_update(Q, E, s, a, delta, lr, trace):
    """``E(s,a) += 1`` (accumulating) or ``= 1`` (replacing), then ``Q += lr delta E``."""
    if trace == REPLACING:
        E[s, a] = 1.0
    else:
        E[s, a] += 1.0
    step = lr * delta
    for i in range(Q.shape[0]):
        for j in range(Q.shape[1]):
            if E[i, j] != 0.0:
                Q[i, j] += step * E[i, j]


@njit(cache=True, inline="always")
def td_step(alg, Q, V, E, s, a, r, s2, done, a2, lr, lr2, gamma, lam, trace):
    """One learning step of algorithm ``alg`` on ``(s, a, r, s')`` with the next action ``a2``
    (already chosen by the behaviour policy; -1 when ``s'`` is terminal).

    * SARSA: ``Q(s,a) += lr (r + gamma Q(s',a') - Q(s,a))``;
    * Q(lambda) (Watkins): ``delta = r + gamma max Q(s') - Q(s,a)``, trace of ``(s,a)``,
      ``Q += lr delta E``, then ``E *= gamma lambda`` if ``a'`` is greedy in ``s'`` (before the
      update), else ``E = 0``;
    * SARSA(lambda): ``delta = r + gamma Q(s',a') - Q(s,a)``, trace, ``Q += lr delta E``,
      ``E *= gamma lambda``;
    * actor-critic: ``delta = r + gamma V(s') - V(s)``; ``V(s) += lr2 delta`` (critic),
      ``H(s,a) += lr delta`` (actor; ``Q`` holds the preferences ``H``);
    * Monte-Carlo control learns at trial end (:func:`mc_update`): nothing here.

    No bootstrap from a terminal ``s'``.
    """
    if alg == SARSA:
        target = r if done else r + gamma * Q[s2, a2]
        Q[s, a] += lr * (target - Q[s, a])
    elif alg == Q_LAMBDA:
        best = 0.0 if done else _row_max(Q, s2)
        greedy_next = (not done) and Q[s2, a2] == best
        delta = r + gamma * best - Q[s, a]
        _traced_update(Q, E, s, a, delta, lr, trace)
        if greedy_next:
            decay = gamma * lam
            for i in range(E.shape[0]):
                for j in range(E.shape[1]):
                    E[i, j] *= decay
        else:
            E[:, :] = 0.0
    elif alg == SARSA_LAMBDA:
        nxt = 0.0 if done else gamma * Q[s2, a2]
        delta = r + nxt - Q[s, a]
        _traced_update(Q, E, s, a, delta, lr, trace)
        decay = gamma * lam
        for i in range(E.shape[0]):
            for j in range(E.shape[1]):
                E[i, j] *= decay
    elif alg == AC:
        nxt = 0.0 if done else gamma * V[s2]
        delta = r + nxt - V[s]
        V[s] += lr2 * delta
        Q[s, a] += lr * delta


@njit(cache=True)
def mc_update(Q, states, actions, rewards, gamma, lr, seen, G):
    """First-visit constant-alpha Monte-Carlo backup of one trial (Sutton & Barto 2018, §5.4
    with the update of eq. 6.1): ``Q(s,a) += lr (G_t - Q(s,a))`` at the first visit ``t`` of
    each pair, ``G_t = r_{t+1} + gamma G_{t+1}``. ``seen`` (S, A) bool is all False on entry
    and on return; ``G`` is scratch space of at least the trial's length."""
    n = states.shape[0]
    g = 0.0
    for i in range(n - 1, -1, -1):
        g = rewards[i] + gamma * g
        G[i] = g
    for i in range(n):
        s = states[i]
        a = actions[i]
        if not seen[s, a]:
            seen[s, a] = True
            Q[s, a] += lr * (G[i] - Q[s, a])
    for i in range(n):
        seen[states[i], actions[i]] = False


@njit(cache=True, inline="always")
def ac_replay(rng, Q, V, model_next, model_reward, model_terminal, pairs, n_pairs, n, lr, lr2,
              gamma):  # fmt: skip
    """Dyna actor-critic replay: ``n`` pairs drawn uniformly (with replacement) from the
    ``n_pairs`` experienced ones (sorted flat ``s * A + a``), each replaying its last outcome
    with the actor-critic update of :func:`td_step`."""
    A = Q.shape[1]
    for _ in range(n):
        i = pairs[randint(rng, n_pairs)]
        s = i // A
        a = i - s * A
        s2 = model_next[s, a]
        nxt = 0.0 if model_terminal[s, a] else gamma * V[s2]
        delta = model_reward[s, a] + nxt - V[s]
        V[s] += lr2 * delta
        Q[s, a] += lr * delta


@njit(cache=True)
def td_act(rng, Q, s, policy, epsilon, beta):
    """The behaviour policy's action in ``s`` over ``Q(s)`` (or the actor's preferences)."""
    return select_action(rng, Q[s], np.ones(1, np.bool_), False, policy, epsilon, beta)


@njit(cache=True)
def td_learn(rng, alg, Q, V, E, s, a, r, s2, done, a2, lr, lr2, gamma, lam, trace,
             model_next, model_reward, model_terminal, pairs, n_pairs, replay_batch):  # fmt: skip
    """:func:`td_step`, then for the Dyna actor-critic (``replay_batch > 0``) the model update
    and :func:`ac_replay` (the Python loop's learning step)."""
    td_step(alg, Q, V, E, s, a, r, s2, done, a2, lr, lr2, gamma, lam, trace)
    if replay_batch > 0:
        if model_next[s, a] < 0:
            add_pair(pairs, n_pairs, s * Q.shape[1] + a)
        model_next[s, a] = s2
        model_reward[s, a] = r
        model_terminal[s, a] = done
        ac_replay(rng, Q, V, model_next, model_reward, model_terminal, pairs, n_pairs[0],
                  replay_batch, lr, lr2, gamma)  # fmt: skip


@njit(cache=True, nogil=True)
def run_td_trials(
    rng, env_rng, alg, Q, V, E, model_next, model_reward, model_terminal, pairs, n_pairs,
    replay_batch, deterministic, next_state, T_cum, R, terminal, starts,
    policy, epsilon, beta, lr, lr2, gamma, lam, trace,
    n_trials, max_steps, learn,
    out_state, out_action, out_next, out_reward,
    out_steps, out_term, out_start, out_end, out_rsum, out_offsets,
):  # fmt: skip
    """Run ``n_trials`` trials of algorithm ``alg``; fill the step and trial buffers (as
    :func:`cobelrun.agents.kernels.run_trials`); return the number of steps.

    Per trial: traces cleared, ``a`` chosen in the start state; per step: the world's
    transition and arrival reward, the next action ``a'`` chosen in ``s'`` (unless terminal),
    then (learning) :func:`td_step` and the Dyna replay; Monte-Carlo control backs the trial
    up at its end (:func:`mc_update`).
    """
    seen = np.zeros(Q.shape, np.bool_)
    G = np.empty(max_steps)
    k = 0
    for trial in range(n_trials):
        s = draw_start(env_rng, starts)
        out_start[trial] = s
        E[:, :] = 0.0
        k0 = k
        done = False
        n = 0
        rsum = 0.0
        a = td_act(rng, Q, s, policy, epsilon, beta)
        while n < max_steps:
            s2 = draw_next(env_rng, deterministic, next_state, T_cum, s, a)
            r = R[s2]
            done = terminal[s2]
            a2 = -1 if done else td_act(rng, Q, s2, policy, epsilon, beta)
            if learn:
                td_learn(rng, alg, Q, V, E, s, a, r, s2, done, a2, lr, lr2, gamma, lam, trace,
                         model_next, model_reward, model_terminal, pairs, n_pairs,
                         replay_batch)  # fmt: skip
            out_state[k] = s
            out_action[k] = a
            out_next[k] = s2
            out_reward[k] = r
            rsum += r
            k += 1
            n += 1
            s = s2
            a = a2
            if done:
                break
        if learn and alg == MC:
            mc_update(Q, out_state[k0:k], out_action[k0:k], out_reward[k0:k], gamma, lr, seen, G)
        out_steps[trial] = n
        out_term[trial] = done
        out_end[trial] = s
        out_rsum[trial] = rsum
        out_offsets[trial + 1] = k
    return k
