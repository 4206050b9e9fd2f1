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
``td_response``
    Classical conditioning (``agent=td_conditioning``): Sutton & Barto's (1990) TD(lambda) over
    the complete serial compound, step by step through the trial exactly as the agent learns
    (``V_t = w . x_t``, ``delta = r_t + gamma V_{t+1} - V_t``, ``e = gamma lambda e + x_t``,
    ``w += alpha delta e``, traces cleared at each trial's start); the choice is the response
    at the first cue's onset on ``V`` there (after the trial's earlier steps' learning), with
    the same logistic response; ``gamma`` and ``lambda`` fixed from the config.
``ph_response``
    Classical conditioning (``agent=pearce_hall``): the hybrid Rescorla-Wagner / Pearce-Hall
    model (Pearce & Hall 1980; Pearce, Kaye & Hall 1982; Le Pelley 2004): ``w_i += kappa
    alpha_i delta``, then each shown cue's associability ``alpha_i = eta |delta| + (1 - eta)
    alpha_i``; logistic response on ``V``; threshold, asymptote and the initial
    associability fixed from the config.

Values restart at 0 at every session. Trials with ``learns`` 0 (a test phase with learning
off) are predicted but teach nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = [
    "MODELS",
    "ChoiceModel",
    "ModelAgent",
    "ParamSpec",
    "ScriptArrays",
    "model_logp",
    "model_probs",
    "model_update",
]

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
ASYMPTOTE = ParamSpec("agent.asymptote", (1e-3, 10.0), "log", 1.0)
GAMMA = ParamSpec("agent.gamma", (0.0, 1.0), "logit", 0.95)
TRACE = ParamSpec("agent.trace_decay", (0.0, 1.0), "logit", 0.8)
ASSOC_RATE = ParamSpec("agent.associability_rate", (0.0, 1.0), "logit")
ASSOC0 = ParamSpec("agent.initial_associability", (0.0, 1.0), "logit", 1.0)

#: kernel codes of the conditioning models (trial type, cue script, one response per trial)
RW_RESPONSE, TD_RESPONSE, PH_RESPONSE = 4, 5, 6

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
        ChoiceModel(
            "td_response",
            TD_RESPONSE,
            (LR, RESPONSE_BETA, THRESHOLD, GAMMA, TRACE),
            1,
            "TD(lambda) over the complete serial compound, logistic response at the cue's "
            "onset (alpha, response_beta; threshold, gamma and lambda fixed)",
            fitted=2,
        ),
        ChoiceModel(
            "ph_response",
            PH_RESPONSE,
            (LR, RESPONSE_BETA, ASSOC_RATE, THRESHOLD, ASYMPTOTE, ASSOC0),
            1,
            "Pearce-Hall hybrid attention model, logistic response on V (kappa, response_beta, "
            "eta; threshold, asymptote and initial associability fixed)",
            fitted=3,
        ),
    )
}

#: the models of classical conditioning (``env=sequence``), by kernel code
CONDITIONING = (RW_RESPONSE, TD_RESPONSE, PH_RESPONSE)


@dataclass(frozen=True)
class ScriptArrays:
    """What a conditioning model needs of the task's trial types (:func:`script_arrays`).

    Attributes
    ----------
    cues
        ``(n_types, n_cs)``: 1 where a trial type shows a conditioned stimulus (RW, PH).
    steps
        ``(n_types, length, d)``: the TD agent's features at every step of a trial type (the
        observation with the cues' presence cleared: serial compound and contexts).
    onset
        ``(n_types,)``: the step of the first cue's onset (-1: a trial type without cues).
    us
        ``(n_types,)``: the step at which the outcome arrives.
    """

    cues: np.ndarray
    steps: np.ndarray
    onset: np.ndarray
    us: np.ndarray

    @property
    def n_states(self) -> int:
        return int(self.cues.shape[0])

    def as_tuple(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The arrays as the compiled kernels take them."""
        return (np.ascontiguousarray(self.cues, np.float64),
                np.ascontiguousarray(self.steps, np.float64),
                np.ascontiguousarray(self.onset, np.int64),
                np.ascontiguousarray(self.us, np.int64))  # fmt: skip


def as_script(features: ScriptArrays | np.ndarray | None, n_states: int) -> tuple:
    """``features`` as the kernels' tuple: a :class:`ScriptArrays`, an ``(n_states, k)`` cue
    array (the other arrays empty) or None (all empty)."""
    if isinstance(features, ScriptArrays):
        return features.as_tuple()
    cues = (np.zeros((int(n_states), 0)) if features is None
            else np.ascontiguousarray(features, np.float64))  # fmt: skip
    n = cues.shape[0]
    return (cues, np.zeros((n, 0, 0)), np.full(n, -1, np.int64), np.zeros(n, np.int64))


@numba.njit(cache=True)
def model_probs(code, theta, mem, s, n_actions, out):  # pragma: no cover
    """Choice probabilities of state ``s`` into ``out`` (length ``n_actions``) for the choice
    models (codes 0-3)."""
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
def model_choose(code, theta, mem, s, n_actions, out, u):  # pragma: no cover
    """Sample a choice in state ``s`` from a uniform draw ``u`` (probabilities into ``out``)."""
    model_probs(code, theta, mem, s, n_actions, out)
    acc = 0.0
    for b in range(n_actions):
        acc += out[b]
        if u < acc:
            return b
    return n_actions - 1


@numba.njit(cache=True)
def model_update(code, theta, mem, s, a, r):  # pragma: no cover
    """Learn from choosing ``a`` in state ``s`` and receiving ``r`` (choice models)."""
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


def state_size(code: int, script: tuple) -> int:
    """Length of the conditioning models' state vector ``w`` (weights, then traces or
    associabilities)."""
    return 2 * max(script[0].shape[1], script[1].shape[2])


@numba.njit(cache=True)
def reset_state(code, theta, w, script):  # pragma: no cover
    """A session's start: weights 0, traces 0, associabilities at their initial value."""
    w[:] = 0.0
    if code == 6:
        k = script[0].shape[1]
        for j in range(k):
            w[k + j] = theta[5]


@numba.njit(cache=True)
def cond_trial(code, theta, w, script, s, r, learn):  # pragma: no cover
    """One conditioning trial of type ``s`` with outcome ``r``: returns the prediction the
    response is made on and, if ``learn``, learns from the trial (codes 4-6)."""
    cues, steps, onset, us = script
    if code == 5:  # td_response: theta = lr, response_beta, threshold, gamma, lambda
        lr, gamma, lam = theta[0], theta[3], theta[4]
        length, d = steps.shape[1], steps.shape[2]
        for j in range(d):
            w[d + j] = 0.0  # traces cleared at the trial's start
        v_on = 0.0
        for t in range(length):
            v = 0.0
            for j in range(d):
                v += w[j] * steps[s, t, j]
            if t == onset[s]:
                v_on = v
            if not learn:
                continue
            v2 = 0.0
            if t + 1 < length:
                for j in range(d):
                    v2 += w[j] * steps[s, t + 1, j]
            delta = (r if t == us[s] else 0.0) + gamma * v2 - v
            for j in range(d):
                w[d + j] = gamma * lam * w[d + j] + steps[s, t, j]
                w[j] += lr * delta * w[d + j]
        return v_on
    k = cues.shape[1]
    v = 0.0
    for j in range(k):
        v += w[j] * cues[s, j]
    if learn:
        if code == 4:  # rw_response: theta = lr, response_beta, threshold, asymptote
            delta = theta[3] * r - v
            for j in range(k):
                w[j] += theta[0] * delta * cues[s, j]
        else:  # ph_response: theta = kappa, response_beta, eta, threshold, asymptote, alpha0
            delta = theta[4] * r - v
            for j in range(k):
                if cues[s, j] != 0.0:
                    w[j] += theta[0] * w[k + j] * delta * cues[s, j]
                    w[k + j] = theta[2] * abs(delta) + (1.0 - theta[2]) * w[k + j]
    return v


@numba.njit(cache=True)
def response_prob(code, theta, v):  # pragma: no cover
    """``P(respond)`` of a conditioning model on the prediction ``v``."""
    z = theta[1] * (v - theta[3 if code == 6 else 2])
    z = min(max(z, -700.0), 700.0)
    return 1.0 / (1.0 + math.exp(-z))


@numba.njit(cache=True)
def _logp_kernel(
    code,
    theta,
    n_memory,
    choices,
    rewards,
    states,
    sessions,
    learns,
    n_states,
    n_actions,
    script,
    values,
):  # pragma: no cover
    """Per-trial log-probabilities; ``values`` (length n, or 0 for none) receives the
    conditioning models' predictions the responses were made on."""
    n = choices.shape[0]
    out = np.empty(n)
    mem = np.zeros((n_memory, n_states, n_actions))
    if code == 3:
        mem[0, 0, 0] = -1.0
    p = np.empty(n_actions)
    w = np.zeros(2 * max(script[0].shape[1], script[1].shape[2]))
    reset_state(code, theta, w, script)
    for t in range(n):
        if t > 0 and sessions[t] != sessions[t - 1]:
            mem[:, :, :] = 0.0
            reset_state(code, theta, w, script)
            if code == 3:
                mem[0, 0, 0] = -1.0
        s, a = states[t], choices[t]
        if code >= 4:
            v = cond_trial(code, theta, w, script, s, rewards[t], learns[t])
            if code == 5 and script[2][s] < 0:
                v = 0.0  # no cue: the TD agent responds on 0
            if values.shape[0] > 0:
                values[t] = v
            p1 = response_prob(code, theta, v)
            out[t] = math.log(max(p1 if a == 1 else 1.0 - p1, 1e-300))
            continue
        model_probs(code, theta, mem, s, n_actions, p)
        out[t] = math.log(max(p[a], 1e-300))
        if learns[t]:
            model_update(code, theta, mem, s, a, rewards[t])
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
    features: ScriptArrays | np.ndarray | None = None,
    learns: np.ndarray | None = None,
    values: np.ndarray | None = None,
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
        The trial types' cues of the conditioning models: a :class:`ScriptArrays`
        (:func:`cobelrun.fit.task_features`), or an ``(n_states, n_cs)`` cue array
        (``rw_response``, ``ph_response``); default none.
    learns
        Per trial, whether the subject learns from it (default: every trial).
    values
        A float64 array of one item per trial that receives the prediction ``V`` each
        response of a conditioning model was made on (what the agent's trials table calls
        ``V``; 0 on trials without a cue); default none.
    """
    learn = (np.ones(len(choices), np.bool_) if learns is None
             else np.ascontiguousarray(learns, np.bool_))  # fmt: skip
    out = np.empty(0) if values is None else values
    if values is not None and (values.shape != (len(choices),) or values.dtype != np.float64):
        raise ValueError(f"values must be a float64 array of {len(choices)} items")
    return _logp_kernel(model.code, np.asarray(theta, np.float64), model.n_memory, choices,
                        rewards, states, sessions, learn, int(n_states), int(n_actions),
                        as_script(features, n_states), out)  # fmt: skip


class ModelAgent:
    """A model as a synthetic subject: :meth:`act` samples a choice, :meth:`learn` updates
    (choice models); :meth:`trial` runs a whole conditioning trial (conditioning models).

    Parameters
    ----------
    model, theta
        The model and its parameters.
    n_states, n_actions
        Table size.
    rng
        Random generator of the choices.
    features
        The trial types' cues (conditioning models; see :func:`model_logp`).
    """

    def __init__(self, model: ChoiceModel, theta: np.ndarray, n_states: int, n_actions: int,
                 rng: np.random.Generator,
                 features: ScriptArrays | np.ndarray | None = None) -> None:  # fmt: skip
        self.model, self.theta = model, np.asarray(theta, np.float64)
        self.script = as_script(features, n_states)
        self.w = np.zeros(state_size(model.code, self.script))
        reset_state(model.code, self.theta, self.w, self.script)
        self.n_actions, self.rng = int(n_actions), rng
        self.mem = np.zeros((model.n_memory, n_states, n_actions))
        if model.code == 3:
            self.mem[0, 0, 0] = -1.0
        self._p = np.empty(self.n_actions)

    @property
    def conditioning(self) -> bool:
        """Whether the model is a conditioning model (one response per scripted trial)."""
        return self.model.code in CONDITIONING

    def act(self, state: int) -> int:
        """Sample a choice in ``state`` (choice models)."""
        return int(model_choose(self.model.code, self.theta, self.mem, int(state),
                                self.n_actions, self._p, self.rng.random()))  # fmt: skip

    def learn(self, state: int, action: int, reward: float) -> None:
        """Update after the outcome (choice models)."""
        model_update(self.model.code, self.theta, self.mem, int(state), int(action),
                     float(reward))  # fmt: skip

    def trial(self, state: int, outcome: float, learn: bool = True) -> int:
        """A conditioning trial of type ``state`` with its ``outcome``: the sampled response
        (0/1) at the cue's onset; learns from the trial if ``learn`` (the response does not
        change the trial, so the order is the agent's)."""
        code = self.model.code
        v = cond_trial(code, self.theta, self.w, self.script, int(state), float(outcome),
                       bool(learn))  # fmt: skip
        if code == TD_RESPONSE and self.script[2][int(state)] < 0:
            v = 0.0
        return int(self.rng.random() < response_prob(code, self.theta, v))


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
               states, sessions, learns, n_states, n_actions, script):  # pragma: no cover  # fmt: skip
    theta = _theta(phi, idx, base, lo, hi, islog)
    lp = _logp_kernel(code, theta, n_memory, choices, rewards, states, sessions, learns,
                      n_states, n_actions, script, np.empty(0))  # fmt: skip
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
               choices, rewards, states, sessions, learns, n_states, n_actions, script, max_iter):  # pragma: no cover  # fmt: skip
    """Minimise the weighted negative log-likelihood over ``phi`` (the transformed fitted
    parameters) inside the box ``[phi_lo, phi_hi]`` by Levenberg-Marquardt-damped Newton
    steps with central-difference derivatives; returns ``(phi, value, iterations)``."""
    k = phi0.shape[0]
    phi = np.minimum(np.maximum(phi0.copy(), phi_lo), phi_hi)
    args = (idx, base, lo, hi, islog, weights, n_memory, choices, rewards, states, sessions,
            learns, n_states, n_actions, script)  # fmt: skip
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
