"""Trial-sequence environment for classical (Pavlovian) conditioning."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.envs.base import check_action
from cobelrun.errors import ConfigError, allowed_list


class SequenceEnv(gym.Env[np.ndarray, int]):
    """Scripted conditioning trials: cues on and off in time, an outcome (US) at a set step.

    Description
    -----------
    A trial lasts ``length`` time steps. Each trial type names the cues it shows and when
    (``cues: {A: [on, off]}``: cue A is present at steps ``on <= t < off``), the outcome it
    delivers (``outcome``: the US magnitude, 0 for none) at step ``us``, and optionally a
    context (a cue present at every step of the trial). A protocol phase picks the trial
    types it presents with ``starts: [A+, AB+]`` (each trial draws one of them uniformly from
    ``np_random``) and may change outcomes with ``rewards: {A+: 0.0}`` (extinction). Actions
    are responses (conditioned responding); they do not change what happens.

    Action Space
    ------------
    ``Discrete(2)``: 0 = no response, 1 = respond.

    Observation Space
    -----------------
    ``Box(0, 1, (n_cues + csc * n_cues * length,), float32)``: first the presence (0/1) of
    every cue (``cues`` then ``contexts``) at the current step, then, with ``csc: true``, a
    complete serial compound: for each cue a one-hot code of the time since its onset
    (Sutton & Barto 1990; Moore et al. 1989), zero when the cue is off. Contexts have no
    time code.

    Rewards
    -------
    The trial's ``outcome`` on the step taken at ``t == us``, else 0.

    Starting State
    --------------
    Step 0 of a trial type drawn uniformly from the current phase's types.

    Episode End
    -----------
    Terminated after ``length`` steps (the last observation is all zeros: the trial is over).

    Arguments
    ---------
    cues : list of str
        Conditioned stimuli (e.g. ``[A, B, X]``; default ``[A]``).
    trial_types : mapping name -> {cues: {cue: [on, off]}, outcome: float, us: int, context: str}
        The trial types (``us`` default ``length - 1``, ``context`` optional; default: the first
        cue on for the whole trial, outcome 1).
    contexts : list of str
        Context cues (e.g. ``[ctx_A, ctx_B]``); default none.
    length : int
        Time steps per trial.
    csc : bool
        Append the complete-serial-compound code to the observation.
    start_types : list of str
        Trial types before any phase picks them (default: all).

    ``info`` holds ``trial_type``, ``cues`` (the trial's cue names joined by ``+``, context
    included, e.g. ``ctx_A+A+B``), ``t`` (the step) and ``state`` (the index of the trial
    type). :attr:`cue_names` lists the observation's cue order.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self,
        cues: Sequence[str] = ("A",),
        trial_types: Mapping[str, Mapping[str, Any]] | None = None,
        contexts: Sequence[str] = (),
        length: int = 10,
        csc: bool = False,
        start_types: Sequence[str] | None = None,
    ) -> None:
        self.cue_names = [str(c) for c in cues] + [str(c) for c in contexts]
        if len(set(self.cue_names)) != len(self.cue_names) or not cues:
            raise ConfigError(f"cues and contexts must be distinct names, got {self.cue_names}")
        if int(length) < 1:
            raise ConfigError(f"length must be >= 1 step, got {length}")
        self.length, self.csc = int(length), bool(csc)
        if trial_types is None:  # one delay-conditioning trial of the first cue
            trial_types = {str(cues[0]): {"cues": {str(cues[0]): [0, self.length]},
                                          "outcome": 1.0}}  # fmt: skip
        self.n_cs, self.n_cues = len(cues), len(self.cue_names)
        if not trial_types:
            raise ConfigError("trial_types must name at least one trial type")
        self.type_names = [str(k) for k in trial_types]
        self._presence = np.zeros((len(self.type_names), self.length, self.n_cues), np.float32)
        self._onset = np.full((len(self.type_names), self.n_cs), -1, np.int64)
        self._us = np.zeros(len(self.type_names), np.int64)
        self._base_outcome = np.zeros(len(self.type_names))
        for i, name in enumerate(self.type_names):
            self._build(i, name, dict(trial_types[name]))
        self.outcome = self._base_outcome.copy()
        self._base_starts = self._types(start_types or self.type_names, "start_types")
        self.starts = list(self._base_starts)
        size = self.n_cues + (self.n_cs * self.length if self.csc else 0)
        self.observation_space = spaces.Box(0.0, 1.0, (size,), np.float32)
        self.action_space = spaces.Discrete(2)
        self._type, self._t = 0, 0

    def _build(self, i: int, name: str, spec: dict[str, Any]) -> None:
        unknown = sorted(set(spec) - {"cues", "outcome", "us", "context"})
        if unknown:
            raise ConfigError(f"trial type {name}: unknown key(s) {unknown}; allowed: "
                              f"cues, outcome, us, context")  # fmt: skip
        for cue, span in dict(spec.get("cues") or {}).items():
            if cue not in self.cue_names[: self.n_cs]:
                raise ConfigError(f"trial type {name}: unknown cue {cue!r}; cues: "
                                  f"{allowed_list(self.cue_names[: self.n_cs])}")  # fmt: skip
            on, off = (int(v) for v in span)
            if not 0 <= on < off <= self.length:
                raise ConfigError(f"trial type {name}: cue {cue} span [{on}, {off}] must lie in "
                                  f"0..{self.length} with on < off")  # fmt: skip
            j = self.cue_names.index(cue)
            self._presence[i, on:off, j] = 1.0
            self._onset[i, j] = on
        context = spec.get("context")
        if context is not None:
            if context not in self.cue_names[self.n_cs :]:
                raise ConfigError(f"trial type {name}: unknown context {context!r}; contexts: "
                                  f"{allowed_list(self.cue_names[self.n_cs :])}")  # fmt: skip
            self._presence[i, :, self.cue_names.index(context)] = 1.0
        us = int(spec.get("us", self.length - 1))
        if not 0 <= us < self.length:
            raise ConfigError(f"trial type {name}: us must lie in 0..{self.length - 1}, got {us}")
        outcome = float(spec.get("outcome", 0.0))
        if not np.isfinite(outcome):
            raise ConfigError(f"trial type {name}: outcome must be finite, got {outcome}")
        self._us[i], self._base_outcome[i] = us, outcome

    def _types(self, names: Iterable[Any], where: str) -> list[int]:
        out = []
        for n in names:
            if str(n) not in self.type_names:
                raise ConfigError(f"{where}: unknown trial type {n!r}; trial types: "
                                  f"{allowed_list(self.type_names)}")  # fmt: skip
            out.append(self.type_names.index(str(n)))
        if not out:
            raise ConfigError(f"{where}: name at least one trial type")
        return out

    # -- phases (the 'changeable' contract) ------------------------------------------------------
    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """``starts``: the trial types presented from now on; ``rewards``: new outcomes by trial
        type. Trials have no terminal states to change."""
        if terminals:
            raise ConfigError("a sequence phase changes trial types (starts) and outcomes "
                              "(rewards), not terminals")  # fmt: skip
        if starts is not None:
            self.starts = self._types(starts, "phase starts")
        for name, value in (rewards or {}).items():
            i = self._types([name], "phase rewards")[0]
            if not np.isfinite(float(value)):
                raise ConfigError(f"phase rewards: outcome of {name} must be finite, got {value}")
            self.outcome[i] = float(value)

    def reset_world(self) -> None:
        """Restore the outcomes and trial types as built."""
        self.outcome = self._base_outcome.copy()
        self.starts = list(self._base_starts)

    # -- gymnasium ---------------------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        """One state per trial type."""
        return len(self.type_names)

    def trial_cues(self, trial_type: int | None = None) -> np.ndarray:
        """``(n_cues,)`` 0/1: which cues (and context) a trial type shows at any step."""
        i = self._type if trial_type is None else trial_type
        return self._presence[i].max(axis=0)

    def _obs(self, i: int | None = None, t: int | None = None) -> np.ndarray:
        i = self._type if i is None else i
        t = self._t if t is None else t
        x = self._presence[i, t]
        if not self.csc:
            return x.copy()
        code = np.zeros((self.n_cs, self.length), np.float32)
        for j in range(self.n_cs):
            on = self._onset[i, j]
            if on >= 0 and x[j] > 0:
                code[j, t - on] = 1.0
        return np.concatenate([x, code.ravel()])

    @property
    def observations(self) -> np.ndarray:
        """``(n_trial_types, d)``: each trial type's observation at its first cue onset (the
        probes of activity monitors and agents' predictions)."""
        rows = []
        for i in range(len(self.type_names)):
            onsets = self._onset[i][self._onset[i] >= 0]
            rows.append(self._obs(i, int(onsets.min()) if len(onsets) else 0))
        return np.array(rows, np.float32)

    def first_onset(self, trial_type: int | None = None) -> int:
        """The step at which a trial type's first cue comes on (0 without cues)."""
        i = self._type if trial_type is None else trial_type
        onsets = self._onset[i][self._onset[i] >= 0]
        return int(onsets.min()) if len(onsets) else 0

    def trial_info(self) -> dict[str, Any]:
        """``trial_type``, ``cues``, ``t`` and ``state`` of the current trial (as ``info``)."""
        return self._info()

    def _info(self) -> dict[str, Any]:
        shown = self.trial_cues() > 0
        names = [n for n, s in zip(self.cue_names, shown, strict=True) if s]
        ctx = [n for n in names if n in self.cue_names[self.n_cs :]]
        cs = [n for n in names if n not in ctx]
        return {"trial_type": self.type_names[self._type], "cues": "+".join(ctx + cs),
                "t": self._t, "state": self._type}  # fmt: skip

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._type = self.starts[int(self.np_random.integers(0, len(self.starts)))]
        self._t = 0
        return self._obs(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        check_action(action, 2, ("no response", "respond"))
        reward = float(self.outcome[self._type]) if self._t == self._us[self._type] else 0.0
        self._t += 1
        done = self._t >= self.length
        obs = np.zeros(self.observation_space.shape, np.float32) if done else self._obs()
        return obs, reward, done, False, self._info()
