"""Compiled building blocks shared by the tabular agents, and the Dyna-Q trial loop (numba).

Every random draw goes through an explicit ``numpy.random.Generator`` passed in as an argument
(numba draws the same numbers from a Generator as numpy does), so a compiled trial loop and a
step-by-step Python loop that call these same functions in the same order give identical
results for the same seed. No global RNG state is used.
"""

from __future__ import annotations

import sys

import numpy as np


def _import_numba_arraymath_without_scipy() -> None:
    """Import ``numba.np.arraymath`` without its BLAS probe importing scipy.linalg (~0.35 s).

    The first call of any compiled (or cache-loaded) function makes numba import
    ``numba.np.arraymath``, which checks once whether BLAS is available by importing
    ``scipy.linalg``. The only thing that check decides is whether ``np.convolve`` /
    ``np.correlate`` inner products in numba code use BLAS; nothing in cobel needs that, so
    when scipy is not imported yet we let the probe fail (plain-loop fallback) and restore
    the import system right after. Set ``COBEL_NUMBA_BLAS=1`` to keep numba's default.
    """
    import os

    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    if os.environ.get("COBEL_NUMBA_BLAS") == "1":
        return
    sys.modules["scipy.linalg"] = None  # type: ignore[assignment]  # -> ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        if sys.modules.get("scipy.linalg", 0) is None:
            del sys.modules["scipy.linalg"]


_import_numba_arraymath_without_scipy()

from numba import njit  # noqa: E402

from cobelrun.agents.codes import EPSILON_GREEDY, REPLAY_STEP, REPLAY_TRIAL_END, SAMPLE_ALL  # noqa: E402

try:  # numba's own bounded-integer routine behind Generator.integers (same draws as numpy)
    from numba.np.random.random_methods import (
        buffered_bounded_lemire_uint32 as _lemire_uint32,
    )
except ImportError:  # pragma: no cover - other numba layouts: use the public (slower) call
    _lemire_uint32 = None

if _lemire_uint32 is not None:

    @njit(cache=True, inline="always")
    def randint(rng, n):
        """``rng.integers(0, n)`` for ``1 <= n < 2**32``: the same draw, without allocation.

        numba's ``Generator.integers`` fills a fresh 1-element array per call (~50 ns here);
        this calls the routine it uses (Lemire's bounded draw on the bit generator's
        ``next_uint32``) directly. Like numpy, ``n == 1`` draws nothing.
        """
        if n <= 1:
            return 0
        return np.int64(_lemire_uint32(rng.bit_generator, np.int64(n - 1)))

else:  # pragma: no cover

    @njit(cache=True, inline="always")
    def randint(rng, n):
        """``rng.integers(0, n)``."""
        return rng.integers(0, n)


@njit(cache=True, inline="always")
def draw_start(env_rng, starts):
    """A trial's start state, as the env's ``reset`` draws it:
    ``starts[env_rng.integers(0, len(starts))]``; ``starts[0]`` without drawing when
    ``env_rng`` is None (a deterministic world with one start state). Shared by every trial
    kernel."""
    if env_rng is None:
        return starts[0]
    return starts[randint(env_rng, starts.shape[0])]


@njit(cache=True, inline="always")
def draw_next(env_rng, deterministic, next_state, T_cum, s, a):
    """The state after action ``a`` in ``s``, as the env's ``step`` draws it: the next-state
    table of a deterministic world (no draw), else the first ``s'`` whose cumulative
    probability ``T_cum[s, a, s']`` exceeds one uniform draw (the last state if rounding
    leaves the draw above them all). Shared by every trial kernel."""
    if env_rng is None or deterministic:
        return next_state[s, a]
    n = T_cum.shape[2]
    s2 = np.searchsorted(T_cum[s, a], env_rng.random(), side="right")
    return s2 if s2 < n else n - 1


@njit(cache=True, inline="always")
def _nth_allowed(mask_row, masked, j):
    """The ``j``-th allowed action (all actions allowed unless ``masked``)."""
    if not masked:
        return j
    for a in range(mask_row.shape[0]):
        if mask_row[a]:
            if j == 0:
                return a
            j -= 1
    return mask_row.shape[0] - 1


@njit(cache=True, inline="always")
def select_action(rng, q_row, mask_row, use_mask, policy, epsilon, beta):
    """Pick an action for one state's action values ``q_row``.

    epsilon-greedy: with probability ``epsilon`` a uniformly random (allowed) action, otherwise
    the greedy action with ties broken at random. softmax: P(a) proportional to
    exp(beta * q[a]) over allowed actions. A state with no allowed action falls back to all
    actions. Allocation-free (counting passes instead of index arrays).

    The numba twin of :func:`cobelrun.agents.policy.select` (used by the numpy-side agents):
    same semantics and, from the same generator, the same draws (tested).
    """
    n = q_row.shape[0]
    k = n
    if use_mask:
        k = 0
        for a in range(n):
            if mask_row[a]:
                k += 1
    masked = use_mask and k > 0
    if not masked:
        k = n
    if policy == EPSILON_GREEDY:
        if rng.random() < epsilon:
            return _nth_allowed(mask_row, masked, randint(rng, k))
        best = -np.inf
        for a in range(n):
            if ((not masked) or mask_row[a]) and q_row[a] > best:
                best = q_row[a]
        m = 0
        first = -1
        for a in range(n):
            if ((not masked) or mask_row[a]) and q_row[a] == best:
                if m == 0:
                    first = a
                m += 1
        if m == 1:
            return first
        j = randint(rng, m)
        for a in range(n):
            if ((not masked) or mask_row[a]) and q_row[a] == best:
                if j == 0:
                    return a
                j -= 1
        return first
    # softmax
    qmax = -np.inf
    for a in range(n):
        if ((not masked) or mask_row[a]) and q_row[a] > qmax:
            qmax = q_row[a]
    total = 0.0
    last = 0
    for a in range(n):
        if (not masked) or mask_row[a]:
            total += np.exp(beta * (q_row[a] - qmax))
            last = a
    u = rng.random() * total
    c = 0.0
    for a in range(n):
        if (not masked) or mask_row[a]:
            c += np.exp(beta * (q_row[a] - qmax))
            if u < c:
                return a
    return last


@njit(cache=True, inline="always")
def q_update(Q, mask, use_mask, s, a, r, s2, terminal, lr, gamma):
    """One Q-learning update: Q[s,a] += lr * (r + gamma * max Q[s2] * (1 - terminal) - Q[s,a])."""
    target = r
    if not terminal:
        best = -np.inf
        for b in range(Q.shape[1]):
            if ((not use_mask) or mask[s2, b]) and Q[s2, b] > best:
                best = Q[s2, b]
        if best == -np.inf:
            for b in range(Q.shape[1]):
                if Q[s2, b] > best or b == 0:
                    best = Q[s2, b]
        target += gamma * best
    Q[s, a] += lr * (target - Q[s, a])


# -- model memory (TabularMemory's arrays) ------------------------------------------------
@njit(cache=True, inline="always")
def memory_store(
    m_next, m_reward, m_terminal, visited, visited_list, n_visited, rate, s, a, r, s2, terminal
):
    m_next[s, a] = s2
    m_reward[s, a] += rate * (r - m_reward[s, a])
    m_terminal[s, a] = terminal
    if not visited[s, a]:
        visited[s, a] = True
        visited_list[n_visited[0]] = s * m_next.shape[1] + a
        n_visited[0] += 1


@njit(cache=True, inline="always")
def memory_sample(rng, visited_list, n_visited, n_pairs, sampling):
    if sampling == SAMPLE_ALL or n_visited[0] == 0:
        return randint(rng, n_pairs)
    return visited_list[randint(rng, n_visited[0])]


@njit(cache=True, inline="always")
def memory_sample_batch(rng, visited_list, n_visited, n_pairs, sampling, n):
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = memory_sample(rng, visited_list, n_visited, n_pairs, sampling)
    return out


@njit(cache=True, inline="always")
def replay(
    rng,
    Q,
    mask,
    use_mask,
    m_next,
    m_reward,
    m_terminal,
    visited_list,
    n_visited,
    sampling,
    n,
    lr,
    gamma,
):
    """``n`` sequential Q updates from experiences sampled out of the model memory."""
    n_actions = Q.shape[1]
    n_pairs = Q.shape[0] * n_actions
    for _ in range(n):
        idx = memory_sample(rng, visited_list, n_visited, n_pairs, sampling)
        s = idx // n_actions
        a = idx % n_actions
        q_update(Q, mask, use_mask, s, a, m_reward[s, a], m_next[s, a], m_terminal[s, a], lr, gamma)


# -- whole trials ---------------------------------------------------------------------------
# ``run_trials`` spells out select_action / q_update / memory_store / replay inline instead of
# calling them: each call of a compiled helper that takes arrays costs ~10-30 ns of reference
# counting here (numba's inline="always" did not remove it), which made the replay loop ~4x
# slower. The helpers above remain the reference for the Python step-by-step path; the tests
# check that both paths give exactly the same trajectories and Q tables.
@njit(cache=True)
def _replay_inline(
    rng, Q, mask, use_mask, m_next, m_reward, m_terminal, visited_list, n_visited, sampling,
    n, lr, gamma, n_actions, n_pairs,
):  # fmt: skip
    """:func:`replay` with memory_sample and q_update spelled out (see the note above)."""
    for _ in range(n):
        if sampling == SAMPLE_ALL or n_visited[0] == 0:
            idx = randint(rng, n_pairs)
        else:
            idx = visited_list[randint(rng, n_visited[0])]
        s = idx // n_actions
        a = idx - s * n_actions
        s2 = m_next[s, a]
        target = m_reward[s, a]
        if not m_terminal[s, a]:
            best = -np.inf
            for b in range(n_actions):
                if ((not use_mask) or mask[s2, b]) and Q[s2, b] > best:
                    best = Q[s2, b]
            if best == -np.inf:
                for b in range(n_actions):
                    if b == 0 or Q[s2, b] > best:
                        best = Q[s2, b]
            target += gamma * best
        Q[s, a] += lr * (target - Q[s, a])


@njit(cache=True, nogil=True)
def run_trials(
    rng, env_rng, Q, mask, use_mask,
    m_next, m_reward, m_terminal, visited, visited_list, n_visited, reward_rate,
    deterministic, next_state, T_cum, R, terminal, starts,
    policy, epsilon, beta, lr, gamma, replay_mode, replay_batch, sampling,
    n_trials, max_steps, learn,
    out_state, out_action, out_next, out_reward,
    out_steps, out_term, out_start, out_end, out_rsum, out_offsets,
):  # fmt: skip
    """Run ``n_trials`` Dyna-Q trials; fill the step and trial buffers; return the total
    number of steps.

    Per step: ``out_state``, ``out_action``, ``out_next``, ``out_reward``. Per trial:
    ``out_steps``, ``out_term``, ``out_start``, ``out_end`` (the last state), ``out_rsum`` (the
    reward sum) and ``out_offsets[trial + 1]`` (the end of its steps; ``out_offsets[0]`` is
    left as given).

    Makes exactly the draws of the Python engine (agent draws from ``rng``, start states and
    stochastic transitions from the environment's ``env_rng``) in the same order. ``env_rng``
    may be None when the world is deterministic with one start state: it then draws nothing
    (and passing a Generator into compiled code costs ~10-30 us per call).
    """
    n_actions = Q.shape[1]
    n_pairs = Q.shape[0] * n_actions
    k = 0
    for trial in range(n_trials):
        s = draw_start(env_rng, starts)
        out_start[trial] = s
        done = False
        n = 0
        rsum = 0.0
        while n < max_steps:
            # -- select_action(rng, Q[s], mask[s], ...)
            n_allowed = n_actions
            if use_mask:
                n_allowed = 0
                for b in range(n_actions):
                    if mask[s, b]:
                        n_allowed += 1
            masked = use_mask and n_allowed > 0
            if not masked:
                n_allowed = n_actions
            a = -1
            if policy == EPSILON_GREEDY:
                if rng.random() < epsilon:
                    j = randint(rng, n_allowed)
                    for b in range(n_actions):
                        if (not masked) or mask[s, b]:
                            if j == 0:
                                a = b
                                break
                            j -= 1
                else:  # one pass: the best value, its first action and how many tie
                    best = -np.inf
                    m = 0
                    for b in range(n_actions):
                        if masked and not mask[s, b]:
                            continue
                        q = Q[s, b]
                        if q > best:
                            best = q
                            m = 1
                            a = b
                        elif q == best:
                            if m == 0:
                                a = b
                            m += 1
                    if m > 1:
                        j = randint(rng, m)
                        for b in range(n_actions):
                            if ((not masked) or mask[s, b]) and Q[s, b] == best:
                                if j == 0:
                                    a = b
                                    break
                                j -= 1
            else:  # softmax
                qmax = -np.inf
                for b in range(n_actions):
                    if ((not masked) or mask[s, b]) and Q[s, b] > qmax:
                        qmax = Q[s, b]
                total = 0.0
                for b in range(n_actions):
                    if (not masked) or mask[s, b]:
                        total += np.exp(beta * (Q[s, b] - qmax))
                        a = b
                u = rng.random() * total
                c = 0.0
                for b in range(n_actions):
                    if (not masked) or mask[s, b]:
                        c += np.exp(beta * (Q[s, b] - qmax))
                        if u < c:
                            a = b
                            break
            if a < 0:
                a = n_actions - 1
            # -- transition(env_rng, ...)
            s2 = draw_next(env_rng, deterministic, next_state, T_cum, s, a)
            r = R[s2]
            done = terminal[s2]
            if learn:
                # -- q_update(Q, mask, use_mask, s, a, r, s2, done, lr, gamma)
                target = r
                if not done:
                    if use_mask:
                        best = -np.inf
                        for b in range(n_actions):
                            if mask[s2, b] and Q[s2, b] > best:
                                best = Q[s2, b]
                        if best == -np.inf:
                            for b in range(n_actions):
                                if b == 0 or Q[s2, b] > best:
                                    best = Q[s2, b]
                    else:
                        best = Q[s2, 0]
                        for b in range(1, n_actions):
                            best = max(best, Q[s2, b])
                    target += gamma * best
                Q[s, a] += lr * (target - Q[s, a])
                # -- memory_store(...)
                m_next[s, a] = s2
                m_reward[s, a] += reward_rate * (r - m_reward[s, a])
                m_terminal[s, a] = done
                if not visited[s, a]:
                    visited[s, a] = True
                    visited_list[n_visited[0]] = s * n_actions + a
                    n_visited[0] += 1
                if replay_mode == REPLAY_STEP:  # _replay_inline, spelled out (see above)
                    for _ in range(replay_batch):
                        if sampling == SAMPLE_ALL or n_visited[0] == 0:
                            idx = randint(rng, n_pairs)
                        else:
                            idx = visited_list[randint(rng, n_visited[0])]
                        rs = idx // n_actions
                        ra = idx - rs * n_actions
                        target = m_reward[rs, ra]
                        if not m_terminal[rs, ra]:
                            rs2 = m_next[rs, ra]
                            if use_mask:
                                best = -np.inf
                                for b in range(n_actions):
                                    if mask[rs2, b] and Q[rs2, b] > best:
                                        best = Q[rs2, b]
                                if best == -np.inf:
                                    for b in range(n_actions):
                                        if b == 0 or Q[rs2, b] > best:
                                            best = Q[rs2, b]
                            else:  # the plain max (branch-free; Q values are finite)
                                best = Q[rs2, 0]
                                for b in range(1, n_actions):
                                    best = max(best, Q[rs2, b])
                            target += gamma * best
                        Q[rs, ra] += lr * (target - Q[rs, ra])
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
        if learn and replay_mode == REPLAY_TRIAL_END:
            _replay_inline(rng, Q, mask, use_mask, m_next, m_reward, m_terminal,
                           visited_list, n_visited, sampling, replay_batch, lr, gamma,
                           n_actions, n_pairs)  # fmt: skip
        out_steps[trial] = n
        out_term[trial] = done
        out_end[trial] = s
        out_rsum[trial] = rsum
        out_offsets[trial + 1] = k
    return k
