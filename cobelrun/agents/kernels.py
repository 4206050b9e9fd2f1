"""Compiled building blocks shared by the tabular agents (numba, cached on disk).

Every random draw goes through an explicit ``numpy.random.Generator`` passed in as an argument
(numba draws the same numbers from a Generator as numpy does), so a compiled trial loop and a
step-by-step Python loop that call these same functions in the same order give identical
results for the same seed. No global RNG state is used.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Policies
EPSILON_GREEDY = 0
SOFTMAX = 1
POLICIES = {"epsilon_greedy": EPSILON_GREEDY, "softmax": SOFTMAX}

# Replay modes
REPLAY_OFF = 0
REPLAY_STEP = 1
REPLAY_TRIAL_END = 2
REPLAY_MODES = {"off": REPLAY_OFF, "step": REPLAY_STEP, "trial_end": REPLAY_TRIAL_END}

# Model memory sampling
SAMPLE_ALL = 0
SAMPLE_VISITED = 1
SAMPLING = {"all": SAMPLE_ALL, "visited": SAMPLE_VISITED}


@njit(cache=True)
def select_action(rng, q_row, mask_row, use_mask, policy, epsilon, beta):
    """Pick an action for one state's action values ``q_row``.

    epsilon-greedy: with probability ``epsilon`` a uniformly random (allowed) action, otherwise
    the greedy action with ties broken at random. softmax: P(a) proportional to
    exp(beta * q[a]) over allowed actions.
    """
    n = q_row.shape[0]
    allowed = np.empty(n, np.int64)
    k = 0
    for a in range(n):
        if (not use_mask) or mask_row[a]:
            allowed[k] = a
            k += 1
    if k == 0:  # a state with no moving action: fall back to all actions
        for a in range(n):
            allowed[a] = a
        k = n
    if policy == EPSILON_GREEDY:
        if rng.random() < epsilon:
            return allowed[rng.integers(0, k)]
        best = -np.inf
        for i in range(k):
            if q_row[allowed[i]] > best:
                best = q_row[allowed[i]]
        ties = np.empty(k, np.int64)
        m = 0
        for i in range(k):
            if q_row[allowed[i]] == best:
                ties[m] = allowed[i]
                m += 1
        if m == 1:
            return ties[0]
        return ties[rng.integers(0, m)]
    # softmax
    qmax = -np.inf
    for i in range(k):
        if q_row[allowed[i]] > qmax:
            qmax = q_row[allowed[i]]
    p = np.empty(k)
    total = 0.0
    for i in range(k):
        p[i] = np.exp(beta * (q_row[allowed[i]] - qmax))
        total += p[i]
    u = rng.random() * total
    c = 0.0
    for i in range(k):
        c += p[i]
        if u < c:
            return allowed[i]
    return allowed[k - 1]


@njit(cache=True)
def max_value(q_row, mask_row, use_mask):
    """max_a q[a] over allowed actions (all actions if none is allowed)."""
    best = -np.inf
    for a in range(q_row.shape[0]):
        if ((not use_mask) or mask_row[a]) and q_row[a] > best:
            best = q_row[a]
    if best == -np.inf:
        best = q_row.max()
    return best


@njit(cache=True)
def q_update(Q, mask, use_mask, s, a, r, s2, terminal, lr, gamma):
    """One Q-learning update: Q[s,a] += lr * (r + gamma * max Q[s2] * (1 - terminal) - Q[s,a])."""
    target = r
    if not terminal:
        target += gamma * max_value(Q[s2], mask[s2], use_mask)
    Q[s, a] += lr * (target - Q[s, a])


@njit(cache=True)
def start_state(env_rng, starts):
    """Draw a start state exactly as ``GridWorldEnv.reset`` does."""
    return starts[env_rng.integers(0, starts.shape[0])]


@njit(cache=True)
def transition(env_rng, deterministic, next_state, T_cum, s, a):
    """Next state exactly as ``GridWorldEnv.step`` does (a draw only if T is stochastic)."""
    if deterministic:
        return next_state[s, a]
    u = env_rng.random()
    s2 = np.searchsorted(T_cum[s, a], u, side="right")
    n = T_cum.shape[2]
    return s2 if s2 < n else n - 1
