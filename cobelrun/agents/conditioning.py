"""Classical conditioning agents for :class:`cobelrun.envs.sequence.SequenceEnv`.

:class:`RescorlaWagner` (Rescorla & Wagner 1972) learns once per trial from the summed
prediction of the trial's cues::

    V      = sum_i w_i x_i                    x_i = 1 if cue i is shown in the trial
    delta  = asymptote * US - V               US: the trial's outcome
    w_i   += salience_i * learning_rate * delta * x_i

:class:`TDConditioning` is Sutton & Barto's (1990) TD model of conditioning: TD(lambda) over a
complete serial compound (every cue's time since onset is its own feature, contexts are
presence features)::

    V_t    = w . x_t
    delta  = r_t + gamma V_{t+1} - V_t        (V after the trial's last step = 0)
    e      = gamma lambda e + x_t
    w     += learning_rate * delta * e

:class:`PearceHall` is the hybrid Rescorla-Wagner / Pearce-Hall attention model (Pearce & Hall
1980; Pearce, Kaye & Hall 1982; Le Pelley 2004): a cue's associability ``alpha_i`` follows the
recent size of the prediction error, so a cue that predicted its outcome well (or predicted
nothing, and nothing came: latent inhibition) becomes slow to learn about::

    delta    = asymptote * US - V
    w_i     += learning_rate * alpha_i * delta * x_i
    alpha_i  = associability_rate * |delta| + (1 - associability_rate) * alpha_i   (x_i = 1)

All three respond with the logistic response model ``P(respond) = 1 / (1 + exp(-response_beta
(V - response_threshold)))`` on the current prediction, and keep the prediction a trial's cues
evoke (:attr:`prediction`: ``V`` of the trial's cues for Rescorla-Wagner, ``V`` at the first
cue's onset for TD) for :class:`cobelrun.monitors.conditioning.ConditioningMonitor`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import Agent, ArraySpec, SeedLike, Transition
from cobelrun.agents.schema import AgentArgs, interval, number_at_least, validate_args
from cobelrun.errors import ConfigError

__all__ = ["PearceHall", "RescorlaWagner", "TDConditioning"]


class ResponseArgs(AgentArgs):
    """The ranges of the logistic response's arguments (every conditioning agent)."""

    response_beta: Annotated[Any, number_at_least(0.0)]
    response_threshold: Annotated[Any, number_at_least(-1e9)]


class RescorlaWagnerArgs(AgentArgs):
    """The ranges of :class:`RescorlaWagner`'s own arguments (per-cue saliences, whose keys
    are the env's cue names, are checked by the agent with :func:`_number`)."""

    learning_rate: Annotated[Any, interval(0.0, 1.0)]
    asymptote: Annotated[Any, number_at_least(0.0)]


class PearceHallArgs(AgentArgs):
    """The ranges of :class:`PearceHall`'s own arguments."""

    learning_rate: Annotated[Any, interval(0.0, 1.0)]
    associability_rate: Annotated[Any, interval(0.0, 1.0)]
    initial_associability: Annotated[Any, interval(0.0, 1.0)]
    asymptote: Annotated[Any, number_at_least(0.0)]


class TDConditioningArgs(AgentArgs):
    """The ranges of :class:`TDConditioning`'s own arguments."""

    learning_rate: Annotated[Any, interval(0.0, 1.0)]
    gamma: Annotated[Any, interval(0.0, 1.0)]
    trace_decay: Annotated[Any, interval(0.0, 1.0)]


def _number(name: str, value: Any, low: float, high: float | None = None) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < low or (high is not None and value > high):
        bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise ConfigError(f"agent.{name} must be a number {bound}, got {value!r}")
    return float(value)


class _Conditioning(Agent):
    """Shared parts: the sequence env, the logistic response, the recorded prediction."""

    observation_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Box,)
    action_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Discrete,)
    requires: ClassVar[tuple[str, ...]] = ("trial_script",)

    def __init__(self, env: gym.Env, *, response_beta: float, response_threshold: float,
                 seed: SeedLike) -> None:  # fmt: skip
        super().__init__(env, seed=seed)  # checks the trial_script contract (env=sequence)
        self.seq = env.unwrapped
        validate_args(ResponseArgs, locals())
        self.response_beta = float(response_beta)
        self.response_threshold = float(response_threshold)
        self.prediction = 0.0

    def respond(self, v: float) -> int:
        """Logistic response on the prediction ``v``."""
        z = self.response_beta * (v - self.response_threshold)
        p = 1.0 / (1.0 + math.exp(-max(min(z, 700.0), -700.0)))
        return int(self.rng.random() < p)

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """``[0, V]`` per observation (no-response and response preference)."""
        v = self.value(observations)
        return np.stack([np.zeros_like(v), v], axis=1)


class _SummedCues(_Conditioning):
    """Trial-level models whose prediction is the summed strength ``w`` of the trial's cues
    (Rescorla-Wagner, Pearce-Hall): ``V`` is read at the trial's start, the outcome summed over
    its steps, the update made at its end (``end_trial``). ``w`` covers the first ``len(w)``
    cues; :meth:`_counted` says which of them enter the compound."""

    w: np.ndarray
    _x: np.ndarray
    _us: float

    def _counted(self, x: np.ndarray) -> np.ndarray:
        return x

    def value(self, cues: np.ndarray) -> np.ndarray:
        """``V`` of cue vectors (n, n_cues): the summed strengths of the cues in the compound."""
        return self._counted(np.atleast_2d(np.asarray(cues, np.float64))[:, : len(self.w)]) @ self.w

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        self._x = self._counted(self.seq.trial_cues()[: len(self.w)].astype(np.float64))
        self.prediction = float(self._x @ self.w)
        self._us = 0.0

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        return self.respond(self.prediction if np.any(obs[: self.seq.n_cs]) else 0.0)

    def observe(self, transition: Transition, learn: bool) -> None:
        self._us += transition.reward


class RescorlaWagner(_SummedCues):
    """Rescorla-Wagner (1972): trial-level learning from the summed prediction of a compound.

    Parameters
    ----------
    env
        A :class:`~cobelrun.envs.sequence.SequenceEnv`.
    learning_rate
        ``beta`` of the rule (the US's learning-rate parameter), in [0, 1].
    salience
        ``alpha_i``: one number for every cue, or a mapping cue -> salience (others 1), in [0, 1].
    asymptote
        ``lambda`` per unit of outcome (the US supports ``asymptote * outcome``).
    context_cues
        Whether contexts enter the compound like cues (False: classic CS-only Rescorla-Wagner,
        which cannot show ABA renewal; True: contexts summate with the CS).
    response_beta, response_threshold
        Logistic response model on ``V``.
    seed
        Seed of the response draws.
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        learning_rate: float = 0.2,
        salience: float | Mapping[str, float] = 1.0,
        asymptote: float = 1.0,
        context_cues: bool = False,
        response_beta: float = 10.0,
        response_threshold: float = 0.5,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, response_beta=response_beta,
                         response_threshold=response_threshold, seed=seed)  # fmt: skip
        validate_args(RescorlaWagnerArgs, locals())
        self.learning_rate, self.asymptote = float(learning_rate), float(asymptote)
        self.context_cues = bool(context_cues)
        names = self.seq.cue_names
        self.alpha = np.ones(len(names))
        if isinstance(salience, Mapping):
            for cue, value in salience.items():
                if cue not in names:
                    raise ConfigError(f"agent.salience: unknown cue {cue!r}; cues: {names}")
                self.alpha[names.index(cue)] = _number(f"salience.{cue}", value, 0.0, 1.0)
        else:
            self.alpha[:] = _number("salience", salience, 0.0, 1.0)
        if not self.context_cues:
            self.alpha[self.seq.n_cs :] = 0.0
        self.w = np.zeros(len(names))
        self._x = np.zeros(len(names))
        self._us = 0.0

    def hyperparameters(self) -> dict[str, Any]:
        return {"learning_rate": self.learning_rate, "asymptote": self.asymptote,
                "context_cues": self.context_cues, "salience": self.alpha.tolist()}  # fmt: skip

    def _counted(self, x: np.ndarray) -> np.ndarray:
        """The cues of ``x`` that enter the compound: the contexts only with ``context_cues``."""
        if self.context_cues:
            return x
        x = x.copy()
        x[..., self.seq.n_cs :] = 0.0
        return x

    def end_trial(self, learn: bool) -> None:
        if learn:
            delta = self.asymptote * self._us - self.prediction
            self.w += self.alpha * self.learning_rate * delta * self._x

    def state_schema(self) -> dict[str, ArraySpec]:
        return {"w": ArraySpec((len(self.w),))}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"w": self.w.copy()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.w[...] = arrays["w"]


class PearceHall(_SummedCues):
    """The hybrid Rescorla-Wagner / Pearce-Hall model of attention in conditioning.

    The prediction is the summed strength of the trial's conditioned stimuli, as in
    Rescorla-Wagner, but each cue learns at its own associability ``alpha_i``, which tracks the
    recent absolute prediction error on its trials (Pearce & Hall 1980, Psychol. Rev.
    87:532; the running average of Pearce, Kaye & Hall 1982; the hybrid form of Le Pelley
    2004, Q. J. Exp. Psychol. 57B:193, and Li et al. 2011, Nat. Neurosci. 14:1250). A cue
    shown without consequence loses associability and is later slow to condition (latent
    inhibition, Lubow & Moore 1959), which Rescorla-Wagner cannot show. Contexts are not cues.

    Parameters
    ----------
    env
        A :class:`~cobelrun.envs.sequence.SequenceEnv`.
    learning_rate
        ``kappa`` (Pearce & Hall's salience ``S``) in [0, 1]: the step size, scaled by the
        cue's associability.
    associability_rate
        ``eta`` (``gamma`` of Pearce, Kaye & Hall 1982) in [0, 1]: the weight of the last
        trial's ``|delta|`` in the associability (1: Pearce & Hall 1980's original rule,
        ``alpha = |delta|`` of the last trial).
    initial_associability
        ``alpha_0`` of every cue, in [0, 1]: a novel cue is fully associable (Pearce & Hall
        1980), default 1.
    asymptote
        ``lambda`` per unit of outcome.
    response_beta, response_threshold
        Logistic response model on ``V``.
    seed
        Seed of the response draws.
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        learning_rate: float = 0.3,
        associability_rate: float = 0.3,
        initial_associability: float = 1.0,
        asymptote: float = 1.0,
        response_beta: float = 10.0,
        response_threshold: float = 0.5,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, response_beta=response_beta,
                         response_threshold=response_threshold, seed=seed)  # fmt: skip
        validate_args(PearceHallArgs, locals())
        self.learning_rate, self.asymptote = float(learning_rate), float(asymptote)
        self.associability_rate = float(associability_rate)
        self.initial_associability = float(initial_associability)
        n = self.seq.n_cs
        self.w = np.zeros(n)
        self.alpha = np.full(n, self.initial_associability)
        self._x = np.zeros(n)
        self._us = 0.0

    def hyperparameters(self) -> dict[str, Any]:
        return {"learning_rate": self.learning_rate, "asymptote": self.asymptote,
                "associability_rate": self.associability_rate,
                "initial_associability": self.initial_associability}  # fmt: skip

    def end_trial(self, learn: bool) -> None:
        if not learn:
            return
        delta = self.asymptote * self._us - self.prediction
        shown = self._x != 0.0
        self.w += self.learning_rate * self.alpha * delta * self._x
        eta = self.associability_rate
        self.alpha[shown] = eta * abs(delta) + (1.0 - eta) * self.alpha[shown]

    def state_schema(self) -> dict[str, ArraySpec]:
        return {"w": ArraySpec((len(self.w),)), "alpha": ArraySpec((len(self.w),))}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"w": self.w.copy(), "alpha": self.alpha.copy()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.w[...] = arrays["w"]
        self.alpha[...] = arrays["alpha"]


class TDConditioning(_Conditioning):
    """TD(lambda) model of conditioning over a complete serial compound (Sutton & Barto 1990).

    Parameters
    ----------
    env
        A :class:`~cobelrun.envs.sequence.SequenceEnv` with ``csc: true``.
    learning_rate
        Step size ``alpha`` of the weights.
    gamma
        Discount per time step.
    trace_decay
        ``lambda`` of the eligibility traces.
    response_beta, response_threshold
        Logistic response model on ``V_t``.
    seed
        Seed of the response draws.
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        learning_rate: float = 0.1,
        gamma: float = 0.95,
        trace_decay: float = 0.8,
        response_beta: float = 10.0,
        response_threshold: float = 0.5,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, response_beta=response_beta,
                         response_threshold=response_threshold, seed=seed)  # fmt: skip
        if not self.seq.csc:
            raise ConfigError("agent TDConditioning needs the complete serial compound: "
                              "env.csc=true")  # fmt: skip
        validate_args(TDConditioningArgs, locals())
        self.learning_rate, self.gamma = float(learning_rate), float(gamma)
        self.trace_decay = float(trace_decay)
        n = int(env.observation_space.shape[0])  # type: ignore[index]
        self.w = np.zeros(n)
        self._e = np.zeros(n)
        self._seen = False

    def hyperparameters(self) -> dict[str, Any]:
        return {"learning_rate": self.learning_rate, "gamma": self.gamma,
                "trace_decay": self.trace_decay}  # fmt: skip

    def _features(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, np.float64).copy()
        x[: self.seq.n_cs] = 0.0  # cues enter through their serial compound, contexts as presence
        return x

    def value(self, observations: np.ndarray) -> np.ndarray:
        """``V`` of observations (n, d)."""
        x = np.atleast_2d(np.asarray(observations, np.float64)).copy()
        x[:, : self.seq.n_cs] = 0.0
        return x @ self.w

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        self._e[:] = 0.0
        self._seen = False
        self.prediction = 0.0

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        v = float(self._features(obs) @ self.w)
        if not self._seen and np.any(obs[: self.seq.n_cs]):
            self.prediction, self._seen = v, True
        return self.respond(v if np.any(obs[: self.seq.n_cs]) else 0.0)

    def observe(self, transition: Transition, learn: bool) -> None:
        if not learn:
            return
        x = self._features(transition.obs)
        v2 = 0.0 if transition.terminated else float(self._features(transition.next_obs) @ self.w)
        delta = transition.reward + self.gamma * v2 - float(x @ self.w)
        self._e *= self.gamma * self.trace_decay
        self._e += x
        self.w += self.learning_rate * delta * self._e

    def state_schema(self) -> dict[str, ArraySpec]:
        return {"w": ArraySpec((len(self.w),))}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"w": self.w.copy()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.w[...] = arrays["w"]
