"""Compiled kernels of prioritized memory access (Mattar & Daw 2018), numba.

One call of :func:`pma_bout` runs a whole replay bout: up to ``n_backups`` backups, each chosen
as the experience (a 1-step backup, or the current sequence extended by one greedy step) with the
highest expected value of backup, EVB = need x gain. Every random draw (tie-breaks) goes through
the ``numpy.random.Generator`` passed in. Imported on first use (numba), like
:mod:`cobelrun.agents.kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from cobelrun.agents import kernels as _kernels  # noqa: F401  (numba import without scipy probe)
from cobelrun.agents.kernels import randint


@njit(cache=True, inline="always")
def _state_value(Q, s, terminal):
    """max_a Q[s, a], 0 for terminal states."""
    if terminal[s]:
        return 0.0
    best = Q[s, 0]
    for b in range(1, Q.shape[1]):
        if Q[s, b] > best:
            best = Q[s, b]
    return best


@njit(cache=True)
def backup_gain(Q, s, a, target, alpha, beta, qbuf):
    """Gain of the backup ``Q[s, a] += alpha * (target - Q[s, a])`` under a softmax(beta) policy.

    ``gain = sum_b pi_new(b) q_new(b) - sum_b pi_old(b) q_new(b)``: how much the policy change
    improves the expected value in ``s``, both valued with the updated Q (Mattar & Daw 2018,
    eq. 6; ``gainTerm.m``). ``qbuf`` is scratch space of length n_actions.
    """
    n = Q.shape[1]
    for b in range(n):
        qbuf[b] = Q[s, b]
    qbuf[a] += alpha * (target - qbuf[a])
    # old policy (from Q[s]) and new policy (from qbuf), both dotted with qbuf
    old_max = Q[s, 0]
    new_max = qbuf[0]
    for b in range(1, n):
        if Q[s, b] > old_max:
            old_max = Q[s, b]
        if qbuf[b] > new_max:
            new_max = qbuf[b]
    z_old = 0.0
    z_new = 0.0
    ev_old = 0.0
    ev_new = 0.0
    for b in range(n):
        w_old = np.exp(beta * (Q[s, b] - old_max))
        w_new = np.exp(beta * (qbuf[b] - new_max))
        z_old += w_old
        z_new += w_new
        ev_old += w_old * qbuf[b]
        ev_new += w_new * qbuf[b]
    return ev_new / z_new - ev_old / z_old


@njit(cache=True)
def _sequence_gain(Q, seq_s, seq_a, seq_r, n, final_next, terminal, gamma, alpha, beta, min_gain,
                   qbuf):  # fmt: skip
    """Summed gain (each step's gain floored at ``min_gain``) of the n-step backups along a
    sequence of ``n`` experiences: step ``j`` backs up ``sum_{k>=j} gamma^(k-j) r_k +
    gamma^(n-j) max Q[final_next]`` (``gainTerm.m``; each step valued with the current Q)."""
    v_end = _state_value(Q, final_next, terminal)
    total = 0.0
    ret = v_end
    for j in range(n - 1, -1, -1):
        ret = seq_r[j] + gamma * ret
        g = backup_gain(Q, seq_s[j], seq_a[j], ret, alpha, beta, qbuf)
        total += g if g > min_gain else min_gain
    return total


@njit(cache=True)
def _greedy_action(rng, q_row):
    """argmax with random tie-break (the greedy extension of ``replaySim.m``)."""
    best = q_row[0]
    for b in range(1, q_row.shape[0]):
        if q_row[b] > best:
            best = q_row[b]
    m = 0
    for b in range(q_row.shape[0]):
        if q_row[b] == best:
            m += 1
    j = randint(rng, m)
    for b in range(q_row.shape[0]):
        if q_row[b] == best:
            if j == 0:
                return b
            j -= 1
    return 0


@njit(cache=True, nogil=True)
def pma_bout(
    rng, Q, model_next, model_reward, candidate, terminal, need,
    gamma, alpha, beta, min_gain, n_backups, extend,
    out_state, out_action, out_next, out_reward, out_gain, out_need, out_length,
):  # fmt: skip
    """Run one replay bout of prioritized memory access; return the number of backups made.

    Parameters
    ----------
    rng : numpy.random.Generator
        Tie-breaks (equal EVB, equal greedy actions).
    Q : (S, A) float64
        Action values, updated in place.
    model_next, model_reward : (S, A)
        The last experienced next state and reward of each state-action pair.
    candidate : (S, A) bool
        Pairs that are 1-step candidates (experienced, and not leading back into the same state).
    terminal : (S,) bool
        Terminal states (no bootstrap from them, no extension past them).
    need : (S,) float64
        Need of each state (SR row of the agent's state, or the stationary distribution).
    gamma, alpha, beta, min_gain
        Discount, backup learning rate, softmax inverse temperature of the policy the gain is
        measured under, floor of each backup's gain.
    n_backups : int
        Budget of backups in this bout.
    extend : bool
        Offer the current sequence extended by one greedy step as a candidate (n-step backups).
    out_* : (n_backups,) arrays
        Per backup: the last experience of the chosen (sequence) backup, its summed gain, the
        need of that experience's state and the sequence length.
    """
    S, A = Q.shape
    qbuf = np.empty(A)
    gains = np.empty(S * A)
    seq_s = np.empty(n_backups + 1, np.int64)
    seq_a = np.empty(n_backups + 1, np.int64)
    seq_r = np.empty(n_backups + 1)
    seq_len = 0
    ext_s = np.empty(n_backups + 1, np.int64)
    ext_a = np.empty(n_backups + 1, np.int64)
    ext_r = np.empty(n_backups + 1)
    done = 0
    # gains of all 1-step candidates, then after each backup only of the pairs it can change
    # (those leaving from or leading into a state whose Q row changed)
    changed = np.ones(S, np.bool_)
    for p in range(n_backups):
        best = -np.inf
        for s in range(S):
            ns = need[s]
            for a in range(A):
                i = s * A + a
                if not candidate[s, a]:
                    gains[i] = -np.inf
                    continue
                nxt = model_next[s, a]
                if changed[s] or changed[nxt]:
                    target = model_reward[s, a] + gamma * _state_value(Q, nxt, terminal)
                    g = backup_gain(Q, s, a, target, alpha, beta, qbuf)
                    gains[i] = g if g > min_gain else min_gain
                evb = ns * gains[i]
                if evb > best:
                    best = evb
        for s in range(S):
            changed[s] = False
        # the current sequence extended by one greedy step
        ext_len = 0
        ext_evb = -np.inf
        ext_gain = 0.0
        if extend and seq_len > 0:
            sn = model_next[seq_s[seq_len - 1], seq_a[seq_len - 1]]
            if not terminal[sn]:
                an = _greedy_action(rng, Q[sn])
                snp1 = model_next[sn, an]
                if snp1 >= 0:  # experienced
                    # no loops: the appended next state must not appear in the sequence
                    loop = snp1 == sn
                    for j in range(seq_len):
                        if seq_s[j] == snp1:
                            loop = True
                    if not loop:
                        for j in range(seq_len):
                            ext_s[j] = seq_s[j]
                            ext_a[j] = seq_a[j]
                            ext_r[j] = seq_r[j]
                        ext_s[seq_len] = sn
                        ext_a[seq_len] = an
                        ext_r[seq_len] = model_reward[sn, an]
                        ext_len = seq_len + 1
                        ext_gain = _sequence_gain(
                            Q, ext_s, ext_a, ext_r, ext_len, snp1, terminal,
                            gamma, alpha, beta, min_gain, qbuf,
                        )  # fmt: skip
                        ext_evb = need[sn] * ext_gain
        top = best if best > ext_evb else ext_evb
        if not top > 0.0:
            break
        # ties prefer the shortest backup (tieBreak 'min'), then a uniformly random one
        n_ties = 0
        for s in range(S):
            for a in range(A):
                i = s * A + a
                if gains[i] > -np.inf and need[s] * gains[i] == top:
                    n_ties += 1
        if n_ties > 0:
            j = randint(rng, n_ties)
            chosen = -1
            for s in range(S):
                for a in range(A):
                    i = s * A + a
                    if gains[i] > -np.inf and need[s] * gains[i] == top:
                        if j == 0 and chosen < 0:
                            chosen = i
                        j -= 1
            s0, a0 = chosen // A, chosen % A
            seq_s[0], seq_a[0], seq_r[0] = s0, a0, model_reward[s0, a0]
            seq_len = 1
            gain_out = gains[chosen]
        else:
            for j in range(ext_len):
                seq_s[j], seq_a[j], seq_r[j] = ext_s[j], ext_a[j], ext_r[j]
            seq_len = ext_len
            gain_out = ext_gain
        # n-step backups along the chosen sequence, each towards the sequence's end
        last_s, last_a = seq_s[seq_len - 1], seq_a[seq_len - 1]
        final = model_next[last_s, last_a]
        v_end = _state_value(Q, final, terminal)
        ret = v_end
        for j in range(seq_len - 1, -1, -1):
            ret = seq_r[j] + gamma * ret
            sj, aj = seq_s[j], seq_a[j]
            Q[sj, aj] += alpha * (ret - Q[sj, aj])
            changed[sj] = True
        out_state[p] = last_s
        out_action[p] = last_a
        out_next[p] = final
        out_reward[p] = seq_r[seq_len - 1]
        out_gain[p] = gain_out
        out_need[p] = need[last_s]
        out_length[p] = seq_len
        done += 1
    return done


@njit(cache=True)
def sr_row(T, gamma, i):
    """Row ``i`` of the successor representation ``(I - gamma T)^-1``.

    Solves ``(I - gamma T)^T m = e_i`` by Gaussian elimination with partial pivoting (one row
    instead of the whole inverse).
    """
    n = T.shape[0]
    M = np.empty((n, n))
    for r in range(n):
        for c in range(n):
            M[r, c] = -gamma * T[c, r]
        M[r, r] += 1.0
    b = np.zeros(n)
    b[i] = 1.0
    for k in range(n):
        piv = k
        big = abs(M[k, k])
        for r in range(k + 1, n):
            if abs(M[r, k]) > big:
                big = abs(M[r, k])
                piv = r
        if piv != k:
            for c in range(n):
                M[k, c], M[piv, c] = M[piv, c], M[k, c]
            b[k], b[piv] = b[piv], b[k]
        inv = 1.0 / M[k, k]
        for r in range(k + 1, n):
            f = M[r, k] * inv
            if f != 0.0:
                for c in range(k, n):
                    M[r, c] -= f * M[k, c]
                b[r] -= f * b[k]
    x = np.empty(n)
    for k in range(n - 1, -1, -1):
        acc = b[k]
        for c in range(k + 1, n):
            acc -= M[k, c] * x[c]
        x[k] = acc / M[k, k]
    return x


@njit(cache=True, nogil=True)
def sfma_bout(
    rng, Q, model_next, model_reward, terminal, strength, similarity, start_state,
    reverse, beta_replay, decay_inhibition, threshold, deterministic, n_backups, alpha, gamma,
    out_state, out_action, out_next, out_reward, out_priority,
):  # fmt: skip
    """One replay bout of SFMA (Diekmann & Cheng 2023); returns the number of reactivations.

    Priority of experience ``e = (s, a)`` given the last reactivated ``(s_c, s'_c)``:
    ``R(e) = C(e) * D(s_c, x(e)) * (1 - I(s))`` with ``x(e) = s`` (default mode) or
    ``x(e) = s'(e)`` (reverse mode: experiences that end where the current one starts);
    ``C`` the experience strength (frequency), ``D`` the similarity of states, ``I`` the
    inhibition of return (reset per bout; after each reactivation ``I *= decay``,
    ``I(s) = min(I(s) + 1, 1)``). ``R`` is normalised by its maximum, thresholded and turned
    into reactivation probabilities ``P(e) ~ exp(beta_replay * R(e)) - 1`` (CoBeL-RL v3's
    softmax with offset -1) over the experiences with ``R >= threshold`` (or the argmax if
    ``deterministic``). Every reactivated experience is a Q-learning backup with rate
    ``alpha``.
    """
    S, A = Q.shape
    inhibition = np.zeros(S)
    prio = np.empty(S * A)
    cur_s = start_state
    done = 0
    for p in range(n_backups):
        best = 0.0
        for s in range(S):
            for a in range(A):
                i = s * A + a
                prio[i] = 0.0
                nxt = model_next[s, a]
                if nxt < 0 or strength[s, a] <= 0.0:
                    continue
                x = nxt if reverse else s
                r = strength[s, a] * similarity[cur_s, x] * (1.0 - inhibition[s])
                prio[i] = r
                if r > best:
                    best = r
        if best <= 0.0:
            break
        total = 0.0
        chosen = -1
        for i in range(S * A):
            r = prio[i] / best
            if r < threshold:
                prio[i] = 0.0
            else:  # CoBeL-RL v3's softmax with offset -1: exp(beta r) - 1, scaled by exp(-beta)
                prio[i] = np.exp(beta_replay * (r - 1.0)) - np.exp(-beta_replay)
                total += prio[i]
                if deterministic and chosen < 0 and r == 1.0:
                    chosen = i
        if not deterministic:
            u = rng.random() * total
            c = 0.0
            for i in range(S * A):
                if prio[i] > 0.0:
                    c += prio[i]
                    chosen = i
                    if u < c:
                        break
        s, a = chosen // A, chosen % A
        nxt = model_next[s, a]
        # backup and inhibition of return
        target = model_reward[s, a]
        if not terminal[nxt]:
            v = Q[nxt, 0]
            for b in range(1, A):
                if Q[nxt, b] > v:
                    v = Q[nxt, b]
            target += gamma * v
        Q[s, a] += alpha * (target - Q[s, a])
        for k in range(S):
            inhibition[k] *= decay_inhibition
        inhibition[s] = min(inhibition[s] + 1.0, 1.0)
        out_state[p] = s
        out_action[p] = a
        out_next[p] = nxt
        out_reward[p] = model_reward[s, a]
        out_priority[p] = prio[chosen] / total
        cur_s = s
        done += 1
    return done
