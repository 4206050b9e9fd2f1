"""Choice models with a likelihood: what ``cobel fit`` and ``cobel recover`` fit.

Each model turns a trial's state into choice probabilities and learns from the trial's
outcome. One compiled kernel (numba) runs every model, so the likelihood that is fitted and
the simulator that generates synthetic agents share the same update rules
(:func:`model_probs`, :func:`model_update`).

Models (Wilson & Collins 2019, eLife 8:e49547, box 1; Daw 2011, "Trial-by-trial data analysis
using computational models"):

``q_learning``
    Softmax Q-learning of the chosen action's value, ``Q[s, a] += alpha (r - Q[s, a])``,
    ``P(a | s) ∝ exp(beta Q[s, a])`` (Sutton & Barto 2018, ch. 2 and 6; cobel's ``DynaQ``
    agent without replay on one-step trials).
``rescorla_wagner``
    Rescorla-Wagner (1972) over compound cues: each trial's cue is the context of state ``s``
    plus the chosen option; both share one prediction error
    ``delta = r - (V_ctx[s] + V[s, a])`` and learn with the same rate ``alpha``; choices are a
    softmax over the options' associative strengths ``V[s, a]`` (the context cancels).
``dyna_q``
    Tabular Dyna-Q (Sutton 1990; Sutton & Barto 2018, sec. 8.2) as cobel's agent keeps it:
    Q-learning plus replay from a model memory that holds a running average of each visited
    option's reward (rate 0.9, cobel's ``memory_reward_rate``); after every trial each
    visited option of every state is replayed once, ``Q[s', b] += alpha (M[s', b] - Q[s', b])``
    (the expected effect of replay spread evenly over the memory).
``wsls``
    Noisy win-stay / lose-shift: after a reward repeat the last action, after none switch to
    one of the others (uniformly); with probability ``epsilon`` choose at random instead
    (Wilson & Collins 2019, model 2). The first trial of a session is random.
``rw_response``
    Classical conditioning (``agent=rescorla_wagner`` on ``env=sequence``): the state is the
    trial type, ``features[s]`` its conditioned stimuli; ``V = w . features[s]``, the choice is
    the response at the cue's onset, ``P(respond) = 1 / (1 + exp(-response_beta (V -
    response_threshold)))``, and ``w += alpha (asymptote * US - V) features[s]`` (saliences 1).

Values restart at 0 at every session.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["MODELS", "ChoiceModel", "ParamSpec", "model_logp", "model_probs", "model_update"]

#: reward rate of the Dyna-Q model's memory (cobel's ``memory_reward_rate``)
DYNA_MEMORY_RATE = 0.9


@dataclass(frozen=True)
class ParamSpec:
    """One fitted parameter.

    Attributes
    ----------
    key
        Config key (``agent.learning_rate``).
    bounds
        Allowed range (inclusive); the fit searches a transformed, unbounded space.
    transform
        ``logit`` (a rate or probability on ``bounds``) or ``log`` (a positive scale).
    default
        Value when neither the config nor the caller gives one (None: the middle of a logit
        range, 1 on a log scale).
    """

    key: str
    bounds: tuple[float, float]
    transform: str = "logit"
    default: float | None = None


@dataclass(frozen=True)
class ChoiceModel:
    """A choice model with a likelihood.

    Attributes
    ----------
    name
        Registry name (``q_learning``).
    code
        Kernel branch (see :func:`model_probs`).
    params
        Its parameters in kernel order.
    n_memory
        Rows of the ``(n_memory, n_states, n_actions)`` memory array.
    description
        One line for listings.
    fitted
        How many of the first parameters are fitted by default (None: all).
    """

    name: str
    code: int
    params: tuple[ParamSpec, ...]
    n_memory: int
    description: str
    fitted: int | None = None

    @property
    def keys(self) -> list[str]:
        """Config keys of the parameters, in kernel order."""
        return [p.key for p in self.params]

    @property
    def default_keys(self) -> list[str]:
        """The parameters fitted unless told otherwise (the first ``fitted``; the rest are
        fixed at the config's values)."""
        return self.keys[: self.fitted] if self.fitted else self.keys


LR = ParamSpec("agent.learning_rate", (0.0, 1.0), "logit")
BETA = ParamSpec("agent.beta", (1e-3, 50.0), "log")
EPSILON = ParamSpec("agent.epsilon", (0.0, 1.0), "logit")
RESPONSE_BETA = ParamSpec("agent.response_beta", (1e-3, 50.0), "log")
THRESHOLD = ParamSpec("agent.response_threshold", (-10.0, 10.0), "logit", 0.5)
ASYMPTOTE = ParamSpec("agent.asymptote", (1e-3, 10.0), "log")

#: every model with a likelihood, by name
MODELS: dict[str, ChoiceModel] = {
    m.name: m
    for m in (
        ChoiceModel("q_learning", 0, (LR, BETA), 1, "softmax Q-learning (alpha, beta)"),
        ChoiceModel(
            "rescorla_wagner",
            1,
            (LR, BETA),
            2,
            "Rescorla-Wagner over context + option cues, softmax (alpha, beta)",
        ),
        ChoiceModel(
            "dyna_q",
            2,
            (LR, BETA),
            3,
            "Q-learning + replay of a tabular model memory, softmax (alpha, beta)",
        ),
        ChoiceModel("wsls", 3, (EPSILON,), 1, "noisy win-stay / lose-shift (epsilon)"),
        ChoiceModel(
            "rw_response",
            4,
            (LR, RESPONSE_BETA, THRESHOLD, ASYMPTOTE),
            1,
            "Rescorla-Wagner conditioning, logistic response on V (alpha, "
            "response_beta; threshold and asymptote fixed)",
            fitted=2,
        ),
    )
}


@numba.njit(cache=True)
def model_probs(code, theta, mem, w, features, s, n_actions, out):  # pragma: no cover
    """Choice probabilities of state ``s`` into ``out`` (length ``n_actions``); ``w`` and
    ``features`` (n_states, n_features) are the cue weights and cues of ``rw_response``."""
    if code == 4:  # rw_response: theta = lr, response_beta, threshold, asymptote
        v = 0.0
        for j in range(features.shape[1]):
            v += w[j] * features[s, j]
        z = theta[1] * (v - theta[2])
        z = min(max(z, -700.0), 700.0)
        out[1] = 1.0 / (1.0 + math.exp(-z))
        out[0] = 1.0 - out[1]
        return
    if code == 3:  # wsls: mem[0, 0, 0] last action (-1: none), mem[0, 0, 1] last reward > 0
        eps = theta[0]
        last = int(mem[0, 0, 0])
        if last < 0 or n_actions == 1:
            for b in range(n_actions):
                out[b] = 1.0 / n_actions
            return
        for b in range(n_actions):
            out[b] = eps / n_actions
        if mem[0, 0, 1] > 0.5:
            out[last] += 1.0 - eps
        else:
            for b in range(n_actions):
                if b != last:
                    out[b] += (1.0 - eps) / (n_actions - 1)
        return
    beta = theta[1]
    m = beta * mem[0, s, 0]
    for b in range(1, n_actions):
        m = max(m, beta * mem[0, s, b])
    total = 0.0
    for b in range(n_actions):
        out[b] = math.exp(beta * mem[0, s, b] - m)
        total += out[b]
    for b in range(n_actions):
        out[b] /= total


@numba.njit(cache=True)
def model_choose(code, theta, mem, w, features, s, n_actions, out, u):  # pragma: no cover
    """Sample a choice in state ``s`` from a uniform draw ``u`` (probabilities into ``out``)."""
    model_probs(code, theta, mem, w, features, s, n_actions, out)
    acc = 0.0
    for b in range(n_actions):
        acc += out[b]
        if u < acc:
            return b
    return n_actions - 1


@numba.njit(cache=True)
def model_update(code, theta, mem, w, features, s, a, r):  # pragma: no cover
    """Learn from choosing ``a`` in state ``s`` and receiving ``r``."""
    if code == 4:
        v = 0.0
        for j in range(features.shape[1]):
            v += w[j] * features[s, j]
        delta = theta[3] * r - v
        for j in range(features.shape[1]):
            w[j] += theta[0] * delta * features[s, j]
        return
    if code == 3:
        mem[0, 0, 0] = a
        mem[0, 0, 1] = 1.0 if r > 0 else 0.0
        return
    lr = theta[0]
    if code == 0:
        mem[0, s, a] += lr * (r - mem[0, s, a])
    elif code == 1:  # mem[0]: option strengths, mem[1, s, 0]: context strength
        delta = r - (mem[1, s, 0] + mem[0, s, a])
        mem[1, s, 0] += lr * delta
        mem[0, s, a] += lr * delta
    else:  # dyna_q: mem[1] the model's reward, mem[2] visited
        mem[0, s, a] += lr * (r - mem[0, s, a])
        if mem[2, s, a] > 0:
            mem[1, s, a] += DYNA_MEMORY_RATE * (r - mem[1, s, a])
        else:
            mem[1, s, a] = r
            mem[2, s, a] = 1.0
        for s2 in range(mem.shape[1]):  # one replay of every visited option
            for b in range(mem.shape[2]):
                if mem[2, s2, b] > 0:
                    mem[0, s2, b] += lr * (mem[1, s2, b] - mem[0, s2, b])


@numba.njit(cache=True)
def _logp_kernel(
    code, theta, n_memory, choices, rewards, states, sessions, n_states, n_actions, features
):  # pragma: no cover
    n = choices.shape[0]
    out = np.empty(n)
    mem = np.zeros((n_memory, n_states, n_actions))
    if code == 3:
        mem[0, 0, 0] = -1.0
    p = np.empty(n_actions)
    w = np.zeros(features.shape[1])
    for t in range(n):
        if t > 0 and sessions[t] != sessions[t - 1]:
            mem[:, :, :] = 0.0
            w[:] = 0.0
            if code == 3:
                mem[0, 0, 0] = -1.0
        s, a = states[t], choices[t]
        model_probs(code, theta, mem, w, features, s, n_actions, p)
        out[t] = math.log(max(p[a], 1e-300))
        model_update(code, theta, mem, w, features, s, a, rewards[t])
    return out


def model_logp(
    model: ChoiceModel,
    theta: np.ndarray,
    choices: np.ndarray,
    rewards: np.ndarray,
    states: np.ndarray,
    sessions: np.ndarray,
    n_states: int,
    n_actions: int,
    features: np.ndarray | None = None,
) -> np.ndarray:
    """Log-probability of each observed choice given the history before it (compiled).

    Parameters
    ----------
    model
        The model (:data:`MODELS`).
    theta
        Its parameters in :attr:`ChoiceModel.keys` order, on their natural scale.
    choices, rewards, states, sessions
        Per-trial arrays (int64, float64, int64, int64) in trial order; memory restarts when
        ``sessions`` changes.
    n_states, n_actions
        Table size.
    features
        ``(n_states, n_features)`` cues of every state (``rw_response``: which conditioned
        stimuli a trial type shows); default none.
    """
    return _logp_kernel(model.code, np.asarray(theta, np.float64), model.n_memory, choices,
                        rewards, states, sessions, int(n_states), int(n_actions),
                        as_features(features, n_states))  # fmt: skip


def as_features(features: np.ndarray | None, n_states: int) -> np.ndarray:
    """``features`` as a C-contiguous float64 (n_states, k) array (``(n_states, 0)`` for none)."""
    if features is None:
        return np.zeros((int(n_states), 0))
    return np.ascontiguousarray(features, np.float64)


class ModelAgent:
    """A model as a synthetic subject: :meth:`act` samples a choice, :meth:`learn` updates.

    Parameters
    ----------
    model, theta
        The model and its parameters.
    n_states, n_actions
        Table size.
    rng
        Random generator of the choices.
    """

    def __init__(self, model: ChoiceModel, theta: np.ndarray, n_states: int, n_actions: int,
                 rng: np.random.Generator, features: np.ndarray | None = None) -> None:  # fmt: skip
        self.model, self.theta = model, np.asarray(theta, np.float64)
        self.features = as_features(features, n_states)
        self.w = np.zeros(self.features.shape[1])
        self.n_actions, self.rng = int(n_actions), rng
        self.mem = np.zeros((model.n_memory, n_states, n_actions))
        if model.code == 3:
            self.mem[0, 0, 0] = -1.0
        self._p = np.empty(self.n_actions)

    def act(self, state: int) -> int:
        """Sample a choice in ``state``."""
        return int(model_choose(self.model.code, self.theta, self.mem, self.w, self.features,
                                int(state), self.n_actions, self._p, self.rng.random()))  # fmt: skip

    def learn(self, state: int, action: int, reward: float) -> None:
        """Update after the outcome."""
        model_update(self.model.code, self.theta, self.mem, self.w, self.features, int(state),
                     int(action), float(reward))  # fmt: skip


# ------------------------------------------------------------ compiled objective and optimiser
@numba.njit(cache=True)
def _theta(phi, idx, base, lo, hi, islog):  # pragma: no cover
    theta = base.copy()
    for j in range(phi.shape[0]):
        if islog[j]:
            theta[idx[j]] = math.exp(phi[j])
        else:
            theta[idx[j]] = lo[j] + (hi[j] - lo[j]) / (1.0 + math.exp(-phi[j]))
    return theta


@numba.njit(cache=True)
def _objective(code, phi, idx, base, lo, hi, islog, weights, n_memory, choices, rewards,
               states, sessions, n_states, n_actions, features):  # pragma: no cover  # fmt: skip
    theta = _theta(phi, idx, base, lo, hi, islog)
    lp = _logp_kernel(code, theta, n_memory, choices, rewards, states, sessions, n_states,
                      n_actions, features)  # fmt: skip
    total = 0.0
    for t in range(lp.shape[0]):
        total -= weights[t] * lp[t]
    return total


@numba.njit(cache=True)
def _positive_definite(A):  # pragma: no cover
    """Whether the symmetric matrix ``A`` has a Cholesky factor."""
    k = A.shape[0]
    L = np.zeros((k, k))
    for i in range(k):
        for j in range(i + 1):
            s = A[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m]
            if i == j:
                if s <= 0.0 or not np.isfinite(s):
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@numba.njit(cache=True)
def newton_fit(code, phi0, phi_lo, phi_hi, idx, base, lo, hi, islog, weights, n_memory,
               choices, rewards, states, sessions, n_states, n_actions, features, max_iter):  # pragma: no cover  # fmt: skip
    """Minimise the weighted negative log-likelihood over ``phi`` (the transformed fitted
    parameters) inside the box ``[phi_lo, phi_hi]`` by Levenberg-Marquardt-damped Newton
    steps with central-difference derivatives; returns ``(phi, value, iterations)``."""
    k = phi0.shape[0]
    phi = np.minimum(np.maximum(phi0.copy(), phi_lo), phi_hi)
    args = (idx, base, lo, hi, islog, weights, n_memory, choices, rewards, states, sessions,
            n_states, n_actions, features)  # fmt: skip
    f = _objective(code, phi, *args)
    lam = 1e-3
    h = 1e-4
    it = 0
    change = 0.0
    step = 0.0
    for it in range(max_iter):  # noqa: B007 (returned)
        g = np.zeros(k)
        H = np.zeros((k, k))
        fp = np.zeros(k)
        fm = np.zeros(k)
        for i in range(k):
            x = phi.copy()
            x[i] += h
            fp[i] = _objective(code, x, *args)
            x[i] -= 2 * h
            fm[i] = _objective(code, x, *args)
            g[i] = (fp[i] - fm[i]) / (2 * h)
            H[i, i] = (fp[i] - 2 * f + fm[i]) / (h * h)
        for i in range(k):
            for j in range(i):
                x = phi.copy()
                x[i] += h
                x[j] += h
                fpp = _objective(code, x, *args)
                H[i, j] = H[j, i] = (fpp - fp[i] - fp[j] + f) / (h * h)
        # a component on its bound whose gradient points outward stays there
        free = np.ones(k, np.bool_)
        for i in range(k):
            if (phi[i] <= phi_lo[i] and g[i] > 0) or (phi[i] >= phi_hi[i] and g[i] < 0):
                free[i] = False
        gmax = 0.0
        for i in range(k):
            if free[i]:
                gmax = max(gmax, abs(g[i]))
        if gmax < 1e-5:
            break
        improved = False
        for _ in range(30):
            A = H.copy()
            for i in range(k):
                A[i, i] += lam * (1.0 + abs(H[i, i]))
                if not free[i]:
                    for j in range(k):
                        A[i, j] = 0.0
                        A[j, i] = 0.0
                    A[i, i] = 1.0
            rhs = -g.copy()
            for i in range(k):
                if not free[i]:
                    rhs[i] = 0.0
            if _positive_definite(A):  # else damp more
                d = np.linalg.solve(A, rhs)
                new = np.minimum(np.maximum(phi + d, phi_lo), phi_hi)
                fn = _objective(code, new, *args)
                if fn < f:
                    step = np.max(np.abs(new - phi))
                    phi, change, f = new, f - fn, fn
                    lam = max(lam / 10.0, 1e-9)
                    improved = True
                    break
            lam *= 10.0
        if not improved or (change < 1e-10 and step < 1e-8):
            break
    return phi, f, it
