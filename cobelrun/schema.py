"""The task-level config schema: one pydantic model per config node, and one error format.

``cobel run`` composes a config with Hydra; :func:`validate_run` then checks its task-level part
(``seed``, ``task.*``: runs, save_agents, record, protocol and its phases) against the models
below, and :func:`to_config_error` turns the first problem into the one-line
:class:`~cobelrun.errors.ConfigError` the CLI prints::

    unknown key 'task.record.flush_secs' (did you mean 'flush_seconds'?); allowed: 'steps', ...
    task.runs must be an integer >= 1, got -3
    task.runs must not be null

The runtime objects (:class:`~cobelrun.protocol.Protocol`, :class:`~cobelrun.protocol.Phase`,
:class:`~cobelrun.recorder.RecordConfig`) are built from the validated models. Components with a
``_target_`` (env, agent, monitors, job) are not modelled here: :func:`cobelrun.config.instantiate`
checks their keys and types against the target's signature, and the classes check their own
arguments.

Models are strict (no ``"3"`` -> 3, no ``1`` -> ``True``; an integer is accepted where a number
is expected) and forbid unknown keys. Each field's :class:`Expect` phrase says what is allowed,
so every error names the key, the bad value and what is allowed.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from cobelrun.errors import ConfigError, allowed_list, suggest

__all__ = [
    "CheckpointSpec",
    "PhaseSpec",
    "ProtocolSpec",
    "RecordSpec",
    "RunSpec",
    "TaskSpec",
    "to_config_error",
    "validate",
    "validate_run",
]

#: largest run, trial and step index: the tables store them as int32
INT32_MAX = 2**31 - 1
#: largest seed: sweep tables store it as int64
INT64_MAX = 2**63 - 1


@dataclass(frozen=True)
class Expect:
    """What a field allows, as the error message phrases it (``an integer >= 1``)."""

    text: str


PositiveInt = Annotated[int, Field(ge=1, le=INT32_MAX), Expect("an integer >= 1")]
Count = Annotated[int, Field(ge=0, le=INT32_MAX), Expect("an integer >= 0")]
Seed = Annotated[int, Field(ge=0, le=INT64_MAX), Expect("an integer >= 0")]
Flag = Annotated[bool, Expect("true or false")]
#: a monitor's ``_target_`` node (its keys are checked by :func:`cobelrun.config.instantiate`)
MonitorNode = Annotated[
    dict[str, Any], Expect("a monitor config (a mapping with a _target_) or null")
]
#: a state: an index, a place name of the environment or ``[row, col]``; the env resolves it
State = Any


def _error(message: str) -> PydanticCustomError:
    """A model validator's one-line message; ``{where}`` in it becomes the model's key path."""
    return PydanticCustomError("cobel", "{message}", {"message": message})


class Spec(BaseModel):
    """Strict, closed, immutable: every node of the schema."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class _ChangesSpec(Spec):
    """What a phase and a trial of its ``cycle`` share: ``rewards: null`` (or ``terminals``) in
    YAML means "no change", like an empty mapping."""

    @model_validator(mode="before")
    @classmethod
    def _nulls_are_empty(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            data = {k: ({} if k in ("rewards", "terminals") and v is None else v)
                    for k, v in data.items()}  # fmt: skip
        return data


class TrialChangesSpec(_ChangesSpec):
    """The changes one trial of a phase's ``cycle`` makes (see :class:`cobelrun.protocol.Changes`)."""

    rewards: Annotated[dict[State, float], Expect("a mapping state -> number")] = {}
    terminals: Annotated[dict[State, bool], Expect("a mapping state -> true/false")] = {}
    starts: Annotated[list[State] | None, Expect("a list of states")] = None


class PhaseSpec(_ChangesSpec):
    """One phase of a protocol (see :class:`cobelrun.protocol.Phase`)."""

    name: Annotated[str, Field(min_length=1), Expect("a non-empty string")]
    trials: Count
    learning: Flag = True
    max_steps: PositiveInt | None = None
    rewards: Annotated[dict[State, float], Expect("a mapping state -> number")] = {}
    terminals: Annotated[dict[State, bool], Expect("a mapping state -> true/false")] = {}
    starts: Annotated[list[State] | None, Expect("a list of states")] = None
    cycle: Annotated[
        list[TrialChangesSpec] | None,
        Field(min_length=1),
        Expect("a non-empty list of per-trial changes {rewards, terminals, starts}"),
    ] = None


class ProtocolSpec(Spec):
    """A task's protocol (``task.protocol``): phases and the default per-trial step limit."""

    max_steps: PositiveInt
    phases: Annotated[list[PhaseSpec], Field(min_length=1), Expect("a non-empty list of phases")]

    @model_validator(mode="after")
    def _check_phases(self) -> ProtocolSpec:
        names = [p.name for p in self.phases]
        if len(set(names)) != len(names):
            raise _error(f"{{where}}.phases have duplicate names: {names}")
        total = sum(p.trials for p in self.phases)
        if total > INT32_MAX:
            raise _error(f"{{where}}.phases have {total} trials in all; at most {INT32_MAX}")
        return self


class RecordSpec(Spec):
    """What a run writes besides the trials table (``task.record``; see
    :class:`cobelrun.recorder.RecordConfig`)."""

    steps: Flag = True
    mcap: Flag = True
    runs: Annotated[
        Literal["all"] | list[Annotated[int, Field(ge=0, le=INT32_MAX)]],
        Expect("'all' or a list of run indices (integers >= 0)"),
    ] = "all"
    trial_every: PositiveInt = 1
    mcap_runs: Annotated[
        Literal["all"] | Annotated[int, Field(ge=0, le=INT32_MAX)],
        Expect(f"'all' or an integer from 0 to {INT32_MAX}"),
    ] = 10
    flush_seconds: Annotated[float, Field(gt=0, allow_inf_nan=False), Expect("a number > 0")] = 2.0
    images: Flag = False
    training_log: Flag = False
    #: who builds and writes the per-step tables: thread or process (cobelrun.recorder)
    step_writer: Annotated[Literal["thread", "process"], Expect("thread or process")] = "thread"
    #: run.mcap's log clock: runs one after another, or each run from the file's start
    mcap_timeline: Annotated[Literal["sequential", "per_run"], Expect("sequential or per_run")] = (
        "sequential"
    )
    #: stream to a live view (foxglove-sdk's WebSocket server; cobelrun.io.live)
    live: Flag = False
    live_port: Annotated[
        int, Field(ge=0, le=65535), Expect("a port from 0 (any free one) to 65535")
    ] = 8765
    live_host: Annotated[str, Field(min_length=1), Expect("a host name or address")] = "127.0.0.1"
    #: seconds to wait for a live client before the first trial (0: do not wait)
    live_wait: Annotated[
        float, Field(ge=0, le=86400, allow_inf_nan=False), Expect("seconds from 0 to 86400")
    ] = 0.0


class CheckpointSpec(Spec):
    """When a run writes checkpoints (``task.checkpoint``; see
    :class:`cobelrun.checkpoint.CheckpointConfig`)."""

    every_trials: Annotated[
        Literal["auto"] | Annotated[int, Field(ge=1, le=INT32_MAX)] | None,
        Expect("auto, null or an integer >= 1"),
    ] = "auto"
    every_minutes: Annotated[
        Literal["auto"] | Annotated[float, Field(gt=0, allow_inf_nan=False)] | None,
        Expect("auto, null or a number > 0"),
    ] = "auto"
    keep: Flag = False


class TaskSpec(Spec):
    """A task (``task.*``): name, runs, protocol, monitors, record, save_agents, job."""

    name: Annotated[str, Field(min_length=1), Expect("a non-empty string")]
    description: Annotated[str | None, Expect("a string")] = None
    runs: PositiveInt = 1
    protocol: ProtocolSpec | None = None
    #: ``_target_`` nodes, checked by :func:`cobelrun.config.instantiate`; null switches one off
    monitors: Annotated[
        dict[str, MonitorNode | None] | None, Expect("a mapping name -> monitor")
    ] = None
    record: RecordSpec = RecordSpec()
    #: runs whose trained agents go into ``agents.zip``: all (true), last, none (false, null)
    save_agents: Annotated[
        Literal["all", "last", "none"] | bool | list[Annotated[int, Field(ge=0)]] | None,
        Expect("all, last, none or a list of run indices"),
    ] = "all"
    #: train the runs of a batchable deep agent as one batched computation (cobelrun.batched):
    #: auto (when the agent and task allow it), true, false, or N runs at a time
    batch_runs: Annotated[
        Literal["auto"] | bool | Annotated[int, Field(ge=1, le=INT32_MAX)],
        Expect("auto, true, false or a number of runs >= 1"),
    ] = "auto"
    #: checkpoints inside a run (cobelrun.checkpoint): every N trials and/or M minutes
    checkpoint: CheckpointSpec = CheckpointSpec()
    #: a custom job (``_target_`` node) that replaces the protocol loop
    job: Annotated[dict[str, Any] | None, Expect("a config node with a _target_")] = None
    #: the run's objective (``_target_`` node, see :mod:`cobelrun.objectives`), in the manifest
    objective: Annotated[dict[str, Any] | None, Expect("a config node with a _target_")] = None

    @model_validator(mode="after")
    def _check_task(self) -> TaskSpec:
        if self.job is None and self.protocol is None:
            raise _error(f"task {self.name!r} has no protocol; pick one with protocol=NAME")
        if isinstance(self.record.runs, list) and any(r >= self.runs for r in self.record.runs):
            raise _error(
                "{where}.record.runs must be 'all' or a list of run indices in "
                f"0..{self.runs - 1} (task.runs is {self.runs}), got {list(self.record.runs)!r}"
            )
        if isinstance(self.save_agents, list) and any(r >= self.runs for r in self.save_agents):
            raise _error(
                "{where}.save_agents must be all, last, none or a list of run indices in "
                f"0..{self.runs - 1}, got {self.save_agents!r}"
            )
        return self


class RunSpec(BaseModel):
    """A composed run config: the seed and the task; env and agent are ``_target_`` nodes.

    Other top-level keys (e.g. ``hydra``) are allowed: Hydra's struct mode guards them.
    """

    model_config = ConfigDict(extra="allow", strict=True, frozen=True)

    seed: Seed
    task: TaskSpec
    env: Annotated[dict[str, Any], Expect("a config node; pick one with env=NAME")]
    agent: Annotated[dict[str, Any], Expect("a config node; pick one with agent=NAME")]


# ------------------------------------------------------------------------------- errors
M = TypeVar("M", bound=BaseModel)

#: where each model sits in a composed config (for the key paths in messages)
ROOTS: dict[type[BaseModel], str] = {
    RunSpec: "", TaskSpec: "task", ProtocolSpec: "task.protocol", RecordSpec: "task.record",
}  # fmt: skip


def validate(model: type[M], data: Any, where: str | None = None) -> M:
    """``model`` validated from plain ``data`` (YAML values); a problem becomes one ConfigError.

    ``where`` is the key path of ``data`` in the composed config (default: the model's usual
    place, e.g. ``task.record``).
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise to_config_error(
            exc, model, data, ROOTS.get(model, "") if where is None else where
        ) from None


def validate_run(cfg: Any) -> RunSpec:
    """Validate a composed config (a DictConfig or plain mapping) against :class:`RunSpec`."""
    from omegaconf import DictConfig, OmegaConf

    data = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    if isinstance(data, Mapping):
        for key in ("task", "env", "agent", "seed"):
            if key not in data:
                how = "set it with seed=N" if key == "seed" else f"pick one with {key}=NAME"
                raise ConfigError(f"the config has no '{key}'; {how}")
    return validate(RunSpec, data, "")


def _join(path: str, key: Any) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The models an annotation holds (``X``, ``X | None``, ``list[X]``, ``dict[str, X]``)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def _expect(field: Any) -> str | None:
    """The field's :class:`Expect` phrase (also inside ``X | None``), or the keys of its model."""
    found = [m for m in field.metadata if isinstance(m, Expect)]
    if not found and typing.get_origin(field.annotation) in (typing.Union, types.UnionType):
        for arg in typing.get_args(field.annotation):
            found += [m for m in getattr(arg, "__metadata__", ()) if isinstance(m, Expect)]
    if found:
        return found[0].text
    models = _models_in(field.annotation)
    if models:
        return f"a mapping with keys {allowed_list(models[0].model_fields)}"
    return None


def _item_expect(field: Any, key: Any, data: Any, loc: Sequence[Any]) -> str | None:
    """The :class:`Expect` phrase of the items of a ``dict[str, X]`` field, where ``key`` is one
    of the field's keys in ``data`` (so that a message can name the item)."""
    found, value = _value_at(data, loc)
    if not (found and isinstance(value, Mapping) and key in value):
        return None
    for arg in typing.get_args(field.annotation) or (field.annotation,):
        if typing.get_origin(arg) is dict:
            items = typing.get_args(arg)[1]
            for option in typing.get_args(items) or (items,):
                for meta in getattr(option, "__metadata__", ()):
                    if isinstance(meta, Expect):
                        return meta.text
    return None


def _value_at(data: Any, loc: Sequence[Any]) -> tuple[bool, Any]:
    for key in loc:
        if isinstance(data, Mapping) and key in data:
            data = data[key]
        elif isinstance(data, Sequence) and not isinstance(data, str) and isinstance(key, int) \
                and -len(data) <= key < len(data):  # fmt: skip
            data = data[key]
        else:
            return False, None
    return True, data


def _shown(value: Any, limit: int = 80) -> str:
    """``repr(value)``, shortened to ``limit`` characters (a whole config node can be long)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def to_config_error(
    exc: ValidationError, model: type[BaseModel], data: Any, root: str = ""
) -> ConfigError:
    """The first error of ``exc`` as a one-line ConfigError naming key, value and what is allowed.

    The error's location is walked through the model's fields; the message is about the
    deepest field on that path (inner list indices and union branches belong to it).
    """
    errors = exc.errors(include_url=False)
    # an unknown key first: a typo explains the "missing" error of the key it misspells
    err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    kind, loc = err["type"], list(err["loc"])
    current: type[BaseModel] | None = model
    path, field, consumed, item = root, None, 0, None
    for key in loc:
        if current is not None and isinstance(key, str) and key in current.model_fields:
            field = current.model_fields[key]
            models = _models_in(field.annotation)
            current = models[0] if models else None
            path = _join(path, key)
        elif current is not None and isinstance(key, int) and field is not None:
            path = _join(path, key)  # an item of a list of models
            field = None
        elif (
            current is None and field is not None and _item_expect(field, key, data, loc[:consumed])
        ):
            path = _join(path, key)  # an item of a mapping whose items say what they allow
            item = _item_expect(field, key, data, loc[:consumed])
            consumed += 1
            break
        else:
            break
        consumed += 1
    if kind == "cobel":  # a model validator's message
        return ConfigError(str(err["msg"]).replace("{where}", path))
    if kind == "extra_forbidden" and current is not None and consumed == len(loc) - 1:
        key = loc[-1]
        allowed = list(current.model_fields)
        return ConfigError(
            f"unknown key '{_join(path, key)}'{suggest(str(key), allowed)}; "
            f"allowed: {allowed_list(allowed)}"
        )
    found, value = _value_at(data, loc[:consumed])
    if kind == "missing" or not found:
        return ConfigError(f"{path} is missing")
    if value is None:
        return ConfigError(f"{path} must not be null")
    if item is not None:
        expect: str | None = item
    elif field is None:  # an item of a list of models that is not a mapping
        expect = f"a mapping with keys {allowed_list(current.model_fields)}" if current else None
    else:
        expect = _expect(field)
    if kind in ("less_than_equal", "less_than") and consumed == len(loc):
        bound = err.get("ctx", {}).get("le", err.get("ctx", {}).get("lt"))
        noun = "an integer" if isinstance(value, int) else "a number"
        return ConfigError(f"{path} must be {noun} <= {bound}, got {_shown(value)}")
    if expect is None:
        return ConfigError(f"{path}: {err['msg']}, got {_shown(value)}")
    return ConfigError(f"{path} must be {expect}, got {_shown(value)}")
