"""Agent base class: the trial loop, batch prediction, checked save/load, declared needs.

An agent is trial based: :meth:`Agent.train` and :meth:`Agent.test` run whole trials and return
a :class:`~cobelrun.records.TrialBatch`. The base owns the Python step loop (:meth:`Agent._run`);
an agent supplies

- :meth:`Agent.act` (pick an action) and, to learn, :meth:`Agent.observe` (called after every
  step with a :class:`Transition`) and/or :meth:`Agent.end_trial`;
- :meth:`Agent.predict` (action values of a batch of observations);
- its learned state as named arrays: :meth:`Agent.state_schema`, :meth:`Agent.get_state`,
  :meth:`Agent.set_state`. :meth:`Agent.save` / :meth:`Agent.load` are written once, here: an
  ``.npz`` without pickle plus a JSON ``__meta__``, checked against the schema before anything
  is loaded (a crafted index would otherwise crash a compiled kernel).

Agents with a compiled trial loop (Dyna-Q) override :meth:`Agent._run` and fall back to the
base loop when per-step callbacks are given. What an agent needs from its environment is
declared in :attr:`Agent.requires` (names of :data:`cobelrun.envs.base.CONTRACTS`) and checked
when the agent is built.
"""

from __future__ import annotations

import abc
import json
import os
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, ClassVar

import gymnasium as gym
import numpy as np

from cobelrun.envs.base import Posed, require
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch

__all__ = [
    "META_KEY",
    "Agent",
    "ArraySpec",
    "SeedLike",
    "Transition",
    "TrialCallback",
    "as_seed_sequence",
    "check_budget",
    "pose_of",
    "state_of",
]

SeedLike = int | np.random.SeedSequence | None

#: name of the JSON metadata entry in a saved agent's npz
META_KEY = "__meta__"
#: version of the save-file layout (the ``__meta__`` keys), independent of agents' schemas
FILE_FORMAT = 1


def as_seed_sequence(seed: SeedLike) -> np.random.SeedSequence:
    """Turn ``seed`` (int, SeedSequence or None) into a SeedSequence."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    return np.random.SeedSequence(seed)


def check_budget(n_trials: int, max_steps: int) -> None:
    """Raise ConfigError unless ``n_trials >= 0`` and ``max_steps >= 1``."""
    if n_trials < 0 or max_steps < 1:
        raise ConfigError(f"need n_trials >= 0 and max_steps >= 1, got {n_trials}, {max_steps}")


def state_indices(observations: Any, n_states: int) -> np.ndarray:
    """Observations of a tabular agent's ``predict`` as a flat int64 array of state indices,
    checked to lie in ``[0, n_states)``."""
    obs = np.asarray(observations, dtype=np.int64).reshape(-1)
    if obs.size and (obs.min() < 0 or obs.max() >= n_states):
        raise ValueError(f"observations must be state indices in [0, {n_states})")
    return obs


def layer_sizes(key: str, values: Any) -> list[int]:
    """Layer sizes from a config (``agent.hidden``, ``agent.net_arch``): a list of integers
    >= 1, else a one-line ConfigError naming ``key`` (a 0-unit layer used to pass with a
    runtime warning and NaN-free but meaningless outputs)."""
    if isinstance(values, str | bytes) or not isinstance(values, Sequence):
        raise ConfigError(f"{key} must be a list of layer sizes (integers >= 1), got {values!r}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ConfigError(
                f"{key} must be a list of layer sizes (integers >= 1), got {list(values)!r}"
            )
    return [int(v) for v in values]


def state_of(obs: Any, info: Mapping[str, Any]) -> int:
    """The discrete state of a step: ``info["state"]`` if given, else the observation if it is
    an integer, else -1 (continuous worlds have no state index)."""
    s = info.get("state") if info else None
    if s is not None:
        return int(s)
    if isinstance(obs, int | np.integer) and not isinstance(obs, bool):
        return int(obs)
    if isinstance(obs, np.ndarray) and obs.ndim == 0 and obs.dtype.kind in "iu":
        return int(obs)
    return -1


def pose_of(env: gym.Env) -> np.ndarray | None:
    """The agent's pose ``(x, y, heading)`` (float64, a copy) if the env is
    :class:`~cobelrun.envs.base.Posed`, else None."""
    base = env.unwrapped
    if isinstance(base, Posed):
        return np.array(base.agent_pose(), dtype=np.float64).reshape(3)
    return None


@dataclass(slots=True)
class Transition:
    """One step of the loop, handed to :meth:`Agent.observe` and to callbacks.

    ``state``/``next_state`` are :func:`state_of` the observations (-1 where there is none).
    For callbacks written against the earlier dict, ``transition["state"]`` etc. still work.
    """

    obs: Any
    action: int
    reward: float
    next_obs: Any
    terminated: bool
    truncated: bool
    info: dict[str, Any]
    next_info: dict[str, Any]
    state: int = -1
    next_state: int = -1

    def __getitem__(self, key: str) -> Any:
        try:
            return getattr(self, key)
        except AttributeError:
            raise KeyError(key) from None


class TrialCallback:
    """Per-step hooks for the opt-in slow path (template-method style, as SB3's callbacks).

    Passing any callback to :meth:`Agent.train` or :meth:`Agent.test` runs trials step by step
    in Python so that the hooks can look at (and change) the agent and environment inside a
    trial. Override the underscore methods; return ``False`` from :meth:`_on_step` to end the
    current trial early.
    """

    def on_trial_start(self, agent: Agent, trial: int, state: int) -> None:
        self._on_trial_start(agent, trial, state)

    def on_step(self, agent: Agent, trial: int, step: int, transition: Transition) -> bool:
        return self._on_step(agent, trial, step, transition) is not False

    def on_trial_end(self, agent: Agent, trial: int, record: dict[str, Any]) -> None:
        self._on_trial_end(agent, trial, record)

    def _on_trial_start(self, agent: Agent, trial: int, state: int) -> None:
        """Called after the environment was reset for ``trial`` (0-based within the call)."""

    def _on_step(self, agent: Agent, trial: int, step: int, transition: Transition) -> bool | None:
        """Called after every step (``step`` is 1-based) with the step's :class:`Transition`."""
        return True

    def _on_trial_end(self, agent: Agent, trial: int, record: dict[str, Any]) -> None:
        """Called at trial end with ``states, actions, rewards, terminated`` (and ``poses``)."""

    @classmethod
    def trial_end_only(cls) -> bool:
        """True if only the trial-end hook is overridden: compiled agents may then run each
        trial in compiled code and call the hook between trials (same results)."""
        base = TrialCallback
        return all(getattr(cls, name) is getattr(base, name) for name in
                   ("on_trial_start", "on_step", "_on_trial_start", "_on_step"))  # fmt: skip


@dataclass(frozen=True)
class ArraySpec:
    """What one array of a saved agent must look like.

    Attributes
    ----------
    shape
        Expected shape; ``None`` entries accept any size on that axis.
    kind
        numpy dtype kind: ``"f"`` float, ``"i"`` signed integer, ``"u"`` unsigned, ``"b"`` bool.
    low, high
        Values must lie in ``[low, high)`` (e.g. state indices in ``[0, S)``); None: no bound.
    finite
        Float values must be finite (no NaN or inf).
    """

    shape: tuple[int | None, ...]
    kind: str = "f"
    low: float | None = None
    high: float | None = None
    finite: bool = True

    def header_problem(self, shape: tuple[int, ...], dtype: np.dtype) -> str | None:
        """What is wrong with an array of ``shape`` and ``dtype`` (as an ``.npy`` header gives
        them, before anything is read), or None if they fit."""
        want = "(" + ", ".join("*" if d is None else str(d) for d in self.shape) + ")"
        if len(shape) != len(self.shape) or any(
            d is not None and d != n for d, n in zip(self.shape, shape, strict=True)
        ):
            return f"expected shape {want}, got {tuple(shape)}"
        if np.dtype(dtype).kind != self.kind:
            return f"expected dtype kind '{self.kind}', got {dtype}"
        return None

    def problem(self, arr: np.ndarray) -> str | None:
        """What is wrong with ``arr`` (one phrase), or None if it fits."""
        found = self.header_problem(tuple(arr.shape), arr.dtype)
        if found:
            return found
        if arr.size == 0:
            return None
        if self.finite and self.kind == "f" and not np.isfinite(arr).all():
            return "expected finite values, found NaN or inf"
        if self.low is not None and arr.min() < self.low:
            return f"expected values in [{_num(self.low)}, {_num(self.high)}), found {arr.min()}"
        if self.high is not None and arr.max() >= self.high:
            return f"expected values in [{_num(self.low)}, {_num(self.high)}), found {arr.max()}"
        return None


def _num(x: float | None) -> str:
    if x is None:
        return "inf"
    return str(int(x)) if float(x).is_integer() else str(x)


class Agent(abc.ABC):
    """Base class of all cobel agents.

    Agents are trial based: :meth:`train` and :meth:`test` run ``n_trials`` whole trials of at
    most ``max_steps`` steps in the agent's environment and return a :class:`TrialBatch`.
    Subclasses declare which observation and action spaces they support and which environment
    contracts they need (:attr:`requires`); constructing an agent on anything else raises
    :class:`~cobelrun.errors.ConfigError` naming what is allowed.

    Parameters
    ----------
    env
        The gymnasium environment the agent acts in.
    seed
        Seed of the agent's own random draws (exploration, replay sampling, initialisation).
    """

    #: Gymnasium space classes the agent accepts as observation / action space.
    observation_spaces: ClassVar[tuple[type[gym.Space], ...]] = ()
    action_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Discrete,)
    #: Environment contracts the agent needs (names of :data:`cobelrun.envs.base.CONTRACTS`).
    requires: ClassVar[tuple[str, ...]] = ()
    #: Version of the agent's :meth:`state_schema`; a saved file of another version is refused.
    state_version: ClassVar[int] = 1
    #: Whether the agent can train many runs as one batched computation (``task.batch_runs``,
    #: :mod:`cobelrun.batched`): it then implements :meth:`batch_learner`.
    batchable: ClassVar[bool] = False
    #: Whether ``task.checkpoint`` ``auto`` writes checkpoints of this agent's runs
    #: (:mod:`cobelrun.checkpoint`): the deep and episodic agents, whose runs take minutes to
    #: hours; tabular runs are cheaper to run again.
    checkpoint_by_default: ClassVar[bool] = False

    def __init__(self, env: gym.Env, *, seed: SeedLike = None) -> None:
        self.check_spaces(env)
        require(env, self.requires, f"agent {type(self).__name__}")
        self.env = env
        self.seed_sequence = as_seed_sequence(seed)
        self.rng = np.random.default_rng(self.seed_sequence)

    @classmethod
    def check_spaces(cls, env: gym.Env) -> None:
        """Raise ConfigError if ``env``'s spaces are not supported by this agent."""
        for kind, space, allowed in (
            ("observation", env.observation_space, cls.observation_spaces),
            ("action", env.action_space, cls.action_spaces),
        ):
            if allowed and not isinstance(space, allowed):
                names = ", ".join(a.__name__ for a in allowed)
                raise ConfigError(
                    f"agent {cls.__name__} does not support {kind} space "
                    f"{type(space).__name__}; allowed: {names}"
                )

    # -- trials --------------------------------------------------------------------------------
    def train(
        self, n_trials: int, max_steps: int, callbacks: Sequence[TrialCallback] = ()
    ) -> TrialBatch:
        """Run ``n_trials`` trials of at most ``max_steps`` steps with learning on."""
        check_budget(n_trials, max_steps)
        return self._run(n_trials, max_steps, True, callbacks)

    def test(
        self, n_trials: int, max_steps: int, callbacks: Sequence[TrialCallback] = ()
    ) -> TrialBatch:
        """Run ``n_trials`` trials with learning off (the same policy, no updates)."""
        check_budget(n_trials, max_steps)
        return self._run(n_trials, max_steps, False, callbacks)

    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        """The step loop (arguments already checked).

        Per trial: ``env.reset()``, :meth:`begin_trial`, then per step :meth:`act`,
        ``env.step``, :meth:`observe` and the callbacks' ``on_step``; the trial ends when the
        env terminates or truncates, after ``max_steps`` steps, or when a callback returns
        False; then :meth:`end_trial` and the callbacks' ``on_trial_end``. States, actions,
        rewards and (for :class:`~cobelrun.envs.base.Posed` envs) poses are recorded.
        """
        env = self.env
        base = env.unwrapped
        posed = isinstance(base, Posed)
        trials = []
        for trial in range(n_trials):
            obs, info = env.reset()
            s = state_of(obs, info)
            self.begin_trial(obs, info, learn)
            for cb in callbacks:
                cb.on_trial_start(self, trial, s)
            states, actions, rewards = [s], [], []
            poses = [np.array(base.agent_pose(), np.float64)] if posed else None
            terminated = False
            for step in range(1, max_steps + 1):
                a = int(self.act(obs, info, learn))
                next_obs, r, terminated, truncated, next_info = env.step(a)
                s2, r = state_of(next_obs, next_info), float(r)
                t = Transition(obs, a, r, next_obs, bool(terminated), bool(truncated), info,
                               next_info, s, s2)  # fmt: skip
                self.observe(t, learn)
                states.append(s2)
                actions.append(a)
                rewards.append(r)
                if poses is not None:
                    poses.append(np.array(base.agent_pose(), np.float64))
                keep = all([cb.on_step(self, trial, step, t) for cb in callbacks])
                obs, info, s = next_obs, next_info, s2
                if terminated or truncated or not keep:
                    break
            self.end_trial(learn)
            record = {"states": states, "actions": actions, "rewards": rewards,
                      "terminated": bool(terminated), "poses": poses}  # fmt: skip
            for cb in callbacks:
                cb.on_trial_end(self, trial, record)
            trials.append(record)
        return TrialBatch.from_trials(trials)

    def prepare(self) -> None:
        """Load what this agent's trials will need, before its first trial (default: nothing).

        Agents with compiled trials load their trial kernel here (numba's once-per-process
        start included, ~0.5-1 s of CPU), so a run's set-up pays for it rather than its first
        phase. Meant for the runner, after it builds a run's agent; building an agent loads
        nothing (validation and a sweep's launcher build agents they never run). Trials run
        the same, and draw the same, with or without it.
        """
        return None  # a hook: nothing by default

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        """Called after each ``env.reset()`` (default: nothing)."""
        return None  # a hook: nothing by default

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """The action to take on ``obs``; agents that use the base loop implement this."""
        raise NotImplementedError(f"agent {type(self).__name__} does not implement act()")

    def observe(self, transition: Transition, learn: bool) -> None:
        """Called after every step; agents learn here when ``learn`` (default: nothing)."""
        return None  # a hook: nothing by default

    def end_trial(self, learn: bool) -> None:
        """Called when a trial ends, before the callbacks' ``on_trial_end`` (default: nothing)."""
        return None  # a hook: nothing by default

    # -- batched runs ----------------------------------------------------------------------------
    def batch_unsupported(self) -> str | None:
        """Why this agent's settings cannot be batched (one phrase), or None."""
        return None if self.batchable else f"agent {type(self).__name__} is not batchable"

    def batch_learner(
        self, seeds: Sequence[np.random.SeedSequence], steps: int, make: Any = None
    ) -> Any:
        """A learner training one run per seed in ``seeds`` at once with this agent's settings
        (``run_phase(envs, n_trials, max_steps, learn, callbacks, views)`` and ``view(i)``, see
        :mod:`cobelrun.batched`); ``steps`` bounds the environment steps of a run's learning
        phases and ``make(seed=...)`` builds another agent with these settings. Only
        :attr:`batchable` agents implement it."""
        raise NotImplementedError(f"agent {type(self).__name__} is not batchable")

    # -- inference -------------------------------------------------------------------------------
    @abc.abstractmethod
    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Action values for a batch of observations, shape (n, n_actions)."""

    # -- persistence -----------------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        """The agent's settings, written to the saved file's metadata (not read back)."""
        return {}

    def state_schema(self) -> dict[str, ArraySpec]:
        """Every array of :meth:`get_state` and what it must look like (checked on load)."""
        raise NotImplementedError(f"agent {type(self).__name__} declares no state schema")

    def get_state(self) -> dict[str, np.ndarray]:
        """The learned state as named arrays (the keys of :meth:`state_schema`)."""
        raise NotImplementedError(f"agent {type(self).__name__} cannot save its state")

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore arrays from :meth:`get_state` (already checked against the schema)."""
        raise NotImplementedError(f"agent {type(self).__name__} cannot load a state")

    def check_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Checks across arrays beyond the schema; raise ValueError with what is wrong."""
        return None  # a hook: nothing by default

    def migrate_state(self, arrays: dict[str, np.ndarray], version: int) -> bool:
        """Bring arrays saved under an older schema ``version`` up to :attr:`state_version`,
        in place (add, rename or convert arrays), before the usual checks; return True if
        this agent knows how. Default: it does not (such a file is refused in one line)."""
        return False

    def state_meta(self) -> dict[str, Any]:
        """JSON-ready state that is not an array (saved in ``__meta__["state"]``)."""
        return {}

    def set_state_meta(self, meta: Mapping[str, Any]) -> None:
        """Check (ValueError) and keep :meth:`state_meta` of a file; called by :meth:`load`
        before :meth:`set_state`, and it must not change the agent yet."""
        return None  # a hook: nothing by default

    # -- checkpoints (cobelrun.checkpoint) ---------------------------------------------------
    # Everything the agent needs to go on as if it had never stopped: the learned state of
    # get_state (checked against state_schema) plus the agent's generator. Agents that carry
    # more between train/test calls (replay memories, optimiser moments, counters, generators
    # of a library) extend these three methods.
    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        """Every array of :meth:`checkpoint_state` and what it must look like."""
        return dict(self.state_schema())

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The agent's arrays and JSON state at a trial boundary (between ``train``/``test``
        calls): :meth:`get_state`, :meth:`state_meta` and the generator's state."""
        from cobelrun.checkpoint import generator_state

        return dict(self.get_state()), {"state": self.state_meta(),
                                        "rng": generator_state(self.rng)}  # fmt: skip

    def restore_checkpoint(self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
        """Restore :meth:`checkpoint_state` (arrays already checked against
        :meth:`checkpoint_schema`); ValueError, with nothing changed, if the rest does not fit."""
        from cobelrun.checkpoint import set_generator_state

        self.check_state(arrays)
        self.set_state_meta(meta.get("state") or {})
        probe = np.random.Generator(type(self.rng.bit_generator)())
        set_generator_state(probe, meta.get("rng"), "agent generator")
        self.set_state(arrays)
        set_generator_state(self.rng, meta.get("rng"), "agent generator")

    @classmethod
    def agent_name(cls) -> str:
        """The name a saved file records: ``module.Class``."""
        return f"{cls.__module__}.{cls.__qualname__}"

    def dump(self, fh: BinaryIO, *, compress: bool = False) -> None:
        """Write the learned state as an npz archive to an open binary file: the arrays of
        :meth:`get_state` and ``__meta__`` (JSON with the agent class, schema version,
        hyperparameters and :meth:`state_meta`). No pickle."""
        meta = self.saved_meta()
        arrays = self.get_state()
        if META_KEY in arrays:
            raise ValueError(f"state key {META_KEY!r} is reserved")
        write = np.savez_compressed if compress else np.savez
        write(fh, **{META_KEY: np.array(json.dumps(meta))}, **arrays)

    def saved_meta(self) -> dict[str, Any]:
        """The JSON metadata saved with the state: file format, agent class, schema version,
        hyperparameters and :meth:`state_meta`."""
        return {"format": FILE_FORMAT, "agent": self.agent_name(),
                "schema_version": self.state_version, "hyperparameters": self.hyperparameters(),
                "state": self.state_meta()}  # fmt: skip

    def save(self, path: str | Path) -> Path:
        """Write the learned state to ``PATH.npz`` (see :meth:`dump`) and return the file.

        Written to a temporary file first, then renamed, so a crash never leaves a
        half-written agent.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            self.dump(fh)
        os.replace(tmp, path)
        return path

    def load(self, path: str | Path | BinaryIO, *, source: str | None = None) -> None:
        """Restore a state written by :meth:`save` (a path, or an open binary file such as a
        member of an agents archive, named ``source`` in errors), after checking it whole.

        Raises a one-line :class:`~cobelrun.errors.ConfigError` naming the file, the key and
        what was expected if the file is not an npz (or needs pickle), was written by another
        agent or schema version, lacks a key or has an unknown one, or an array has the wrong
        shape, dtype kind, an index out of range or a non-finite value. Nothing is changed
        unless every check passes.
        """
        target = path if hasattr(path, "read") else Path(path)  # type: ignore[arg-type]
        arrays, _meta = self._read_checked(target, source)  # type: ignore[arg-type]
        self.set_state(arrays)

    def _read_checked(
        self, path: Path | BinaryIO, source: str | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        name = source or path

        def fail(what: str) -> ConfigError:
            return ConfigError(f"cannot load agent from {name}: {what}")

        try:
            raw = self._read_npz(path, name)
        except ConfigError:
            raise
        except FileNotFoundError:
            raise fail("no such file") from None
        except zipfile.BadZipFile as exc:
            if _starts_with(path, b"\x93NUMPY"):
                raise fail("not an .npz archive of arrays (a single .npy array)") from None
            raise fail(f"not a readable .npz archive without pickle ({exc})") from None
        except Exception as exc:  # pickle refused, truncated, a bad header, ...
            raise fail(f"not a readable .npz archive without pickle ({exc})") from None
        if META_KEY not in raw:
            raise fail(f"no {META_KEY!r} entry (not a cobel agent file)")
        try:
            meta = json.loads(str(raw.pop(META_KEY)))
            if not isinstance(meta, dict):
                raise ValueError
        except ValueError:
            raise fail(f"{META_KEY!r} is not a JSON object") from None
        self._check_loaded(raw, meta, fail)
        return raw, meta

    def _read_npz(self, path: Path | BinaryIO, name: Any) -> dict[str, np.ndarray]:
        """The arrays of a single agent file, each checked from its ``.npy`` header (the
        declared schema's shape and dtype kind, and the memory available) before it is read:
        a small file that would decompress to gigabytes is refused with nothing allocated."""
        from cobelrun.io.validate import nbytes_of, read_npy_header
        from cobelrun.safety import check_allocation

        schema = self.state_schema()
        raw: dict[str, np.ndarray] = {}
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
            bad = [n for n in names if not n.endswith(".npy")]
            if bad:
                raise ConfigError(f"cannot load agent from {name}: member {bad[0]!r} is not "
                                  "an .npy array")  # fmt: skip
            headers = {}
            for member in names:
                key = member[: -len(".npy")]
                with zf.open(member) as fh:
                    shape, dtype = read_npy_header(fh)
                spec = schema.get(key)
                problem = spec.header_problem(shape, dtype) if spec is not None else None
                if key == META_KEY and (dtype.kind != "U" or shape != ()):
                    problem = f"expected a JSON string, got {dtype} with shape {shape}"
                if problem:
                    raise ConfigError(f"cannot load agent from {name}: key {key!r}: {problem}")
                headers[member] = (shape, dtype)
            need = sum(nbytes_of(*h) for h in headers.values())
            check_allocation(str(name), need, "the saved agent's arrays",
                             "the file was not written for this agent or is damaged")  # fmt: skip
            for member, (shape, dtype) in headers.items():
                with zf.open(member) as fh:
                    read_npy_header(fh)
                    data = fh.read(nbytes_of(shape, dtype))
                if len(data) != nbytes_of(shape, dtype):
                    raise ValueError(f"member {member!r} is cut short")
                raw[member[: -len(".npy")]] = np.frombuffer(bytearray(data), dtype).reshape(shape)
        return raw

    def load_state(self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any],
                   source: str) -> None:  # fmt: skip
        """Restore a state from arrays and metadata read elsewhere (a job's agents archive),
        with the same checks as :meth:`load`; errors name ``source``."""

        def fail(what: str) -> ConfigError:
            return ConfigError(f"cannot load agent from {source}: {what}")

        raw = dict(arrays)
        self._check_loaded(raw, dict(meta), fail)
        self.set_state(raw)

    def _check_loaded(self, raw: dict[str, np.ndarray], meta: dict[str, Any], fail: Any) -> None:
        """Every check of a saved state; raises ``fail(what)`` (a ConfigError)."""
        if meta.get("agent") != self.agent_name():
            raise fail(f"it holds agent {meta.get('agent')!r}, expected {self.agent_name()!r}")
        version = meta.get("schema_version")
        if version != self.state_version:
            older = isinstance(version, int) and not isinstance(version, bool)
            older = older and version < self.state_version
            if not (older and self.migrate_state(raw, version)):
                raise fail(f"schema version {version!r}, expected {self.state_version}")
        schema = self.state_schema()
        missing = [k for k in schema if k not in raw]
        if missing:
            raise fail(f"key {missing[0]!r} is missing ({len(missing)} missing)")
        unknown = sorted(set(raw) - set(schema))
        if unknown:
            raise fail(f"unknown key {unknown[0]!r}; expected only {', '.join(schema)}")
        for key, spec in schema.items():
            problem = spec.problem(raw[key])
            if problem:
                raise fail(f"key {key!r}: {problem}")
        try:
            self.check_state(raw)
            self.set_state_meta(meta.get("state") or {})
        except ValueError as exc:
            raise fail(str(exc)) from None


def check_load_from(agent: Agent, load_from: str, runs: int) -> None:
    """Check every saved agent ``agent.load_from`` names for runs ``0 .. runs-1`` before any
    output folder exists: the file is there, is an npz without pickle, holds this agent and
    schema version, and every array fits the declared schema (shapes and dtypes from the
    ``.npy`` headers first, so nothing oversized is read) and its value checks. ``load_from``
    is a file (``{run}`` replaced by the run index) or a run folder (its ``agents.npz`` or an
    older layout's agent files). One ConfigError line naming the file and what is wrong."""
    runs = int(runs)
    if "{run}" not in load_from and Path(load_from).is_dir():
        _check_saved_folder(agent, Path(load_from), range(runs))
        return
    for run in range(runs):
        path = Path(load_from.replace("{run}", str(run)))
        if path.is_dir():
            _check_saved_folder(agent, path, [run])
        elif not path.is_file():
            raise ConfigError(f"agent.load_from: {path} does not exist")
        else:
            agent._read_checked(path)


def _check_saved_folder(agent: Agent, path: Path, runs: Sequence[int] | range) -> None:
    """Check the saved agents of ``runs`` in run folder ``path``: its ``agents.npz`` in one
    pass (shapes and dtypes from the headers, then values), an older layout's files for the
    runs the archive lacks."""
    from cobelrun.io.agents_archive import iter_agents, runs_in
    from cobelrun.io.run_folder import RunFolder

    schema = agent.state_schema()

    def header_check(key: str, shape: tuple[int, ...], dtype: np.dtype) -> str | None:
        spec = schema.get(key)
        return None if spec is None else spec.header_problem(shape, dtype)

    folder = RunFolder(path)
    archive = folder.agents_archive
    have: set[int] = set()
    if archive.is_file():
        try:
            have = set(runs_in(archive))
            for run, arrays, meta in iter_agents(archive, runs, header_check):

                def fail(what: str, run: int = run) -> ConfigError:
                    return ConfigError(f"cannot load agent from {archive} (run {run}): {what}")

                agent._check_loaded(dict(arrays), dict(meta), fail)
        except ConfigError as exc:
            if str(exc).startswith("cannot load agent"):
                raise
            raise ConfigError(f"cannot load agent from {archive}: {exc}") from None
        except Exception as exc:  # a damaged archive: zip, npy header, layout
            raise ConfigError(f"cannot load agent from {archive}: {exc}") from None
    for run in runs:
        if run in have:
            continue
        legacy = folder.legacy_agent(run)
        if legacy is None:
            raise ConfigError(
                f"agent.load_from: {folder.path} has no saved agent for run {run} "
                "(task.save_agents decides which runs are saved)"
            )
        agent._read_checked(legacy)


def _starts_with(path: Path | BinaryIO, magic: bytes) -> bool:
    """True if the file ``path`` (a path or an open binary file) starts with ``magic``."""
    try:
        if hasattr(path, "read"):
            path.seek(0)  # type: ignore[union-attr]
            return path.read(len(magic)) == magic  # type: ignore[union-attr]
        with open(path, "rb") as f:
            return f.read(len(magic)) == magic
    except (OSError, ValueError):
        return False
