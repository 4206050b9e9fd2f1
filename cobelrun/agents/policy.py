"""Action-selection policies over one state's action values, shared by every numpy-side agent.

All draws come from the ``numpy.random.Generator`` passed in, so an agent's choices depend only
on its own seed. ``allowed`` (a boolean row, e.g. an action mask) restricts the choice; a row
with no allowed action falls back to all actions (a wall cell), as everywhere in cobel.

The compiled tabular kernels use their numba twin, :func:`cobelrun.agents.kernels.select_action`:
the same semantics (epsilon-greedy with a uniform random tie-break among the greedy actions;
softmax by inverse CDF on one uniform draw) written allocation-free for numba.
"""

from __future__ import annotations

import numpy as np

from cobelrun.errors import ConfigError, allowed_list, suggest

__all__ = ["POLICIES", "check_policy", "epsilon_greedy", "select", "softmax"]

#: policy names accepted by :func:`select` (and by agents' ``policy`` parameter)
POLICIES = ("epsilon_greedy", "softmax")


def check_policy(policy: str, key: str = "agent.policy") -> str:
    """Return ``policy`` if it is known, else raise a one-line ConfigError naming ``key``."""
    if policy not in POLICIES:
        raise ConfigError(
            f"{key} {policy!r} is not known{suggest(policy, POLICIES)}; "
            f"allowed: {allowed_list(POLICIES)}"
        )
    return policy


def _candidates(n: int, allowed: np.ndarray | None) -> np.ndarray | None:
    """Indices of the allowed actions, or None for "all of them"."""
    if allowed is None:
        return None
    allowed = np.asarray(allowed, dtype=bool)
    if allowed.all() or not allowed.any():
        return None
    return np.flatnonzero(allowed)


def epsilon_greedy(
    rng: np.random.Generator, q: np.ndarray, epsilon: float, allowed: np.ndarray | None = None
) -> int:
    """With probability ``epsilon`` a uniformly random (allowed) action, else a greedy one.

    Ties among the greedy actions are broken uniformly at random (not "first index wins",
    which would bias an untrained agent towards action 0).

    Draws: one ``rng.random()``, then one ``rng.integers(k)`` (numpy draws nothing for k = 1).
    """
    q = np.asarray(q)
    idx = _candidates(q.shape[0], allowed)
    qa = q if idx is None else q[idx]
    if rng.random() < epsilon:
        j = int(rng.integers(qa.shape[0]))
    else:
        best = np.flatnonzero(qa == qa.max())
        j = int(best[rng.integers(best.size)])
    return j if idx is None else int(idx[j])


def softmax(
    rng: np.random.Generator, q: np.ndarray, beta: float, allowed: np.ndarray | None = None
) -> int:
    """An (allowed) action with probability proportional to ``exp(beta * q[a])``.

    Computed stably (``q - max q``) and drawn by inverse CDF with one ``rng.random()``.
    """
    q = np.asarray(q, dtype=np.float64)
    idx = _candidates(q.shape[0], allowed)
    qa = q if idx is None else q[idx]
    cdf = np.cumsum(np.exp(beta * (qa - qa.max())))
    j = int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right"))
    j = min(j, qa.shape[0] - 1)
    return j if idx is None else int(idx[j])


def select(
    rng: np.random.Generator,
    q: np.ndarray,
    policy: str,
    epsilon: float,
    beta: float,
    allowed: np.ndarray | None = None,
) -> int:
    """:func:`epsilon_greedy` (``policy="epsilon_greedy"``) or :func:`softmax` (``"softmax"``)."""
    if policy == "epsilon_greedy":
        return epsilon_greedy(rng, q, epsilon, allowed)
    if policy == "softmax":
        return softmax(rng, q, beta, allowed)
    raise ValueError(f"unknown policy {policy!r}; allowed: {', '.join(POLICIES)}")


def allowed_next(mask: np.ndarray, states: np.ndarray) -> np.ndarray:
    """Allowed actions of ``states`` for the max; a state with none (a wall cell) allows all."""
    rows = mask[states]
    return rows | ~rows.any(axis=1, keepdims=True)
