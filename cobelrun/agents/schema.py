"""Agents' argument schemas: an agent's keyword arguments and the values each allows, declared
once as a pydantic model and checked before anything is built.

An agent declares its arguments as a subclass of :class:`AgentArgs`, each field annotated with
one rule (:func:`interval`, :func:`at_least`, :func:`positive`, :func:`one_of`, ...), and
calls :func:`validate_args` at the top of ``__init__``. The first broken rule becomes one
:class:`~cobelrun.errors.ConfigError` line naming the key (``agent.<name>``), what is allowed and
the value given, e.g. ``agent.epsilon must be a number in [0.0, 1.0], got 1.5``.

The rules check values as they are (fields are ``Any``: nothing is coerced), so the agent builds
from the arguments it was given; the model is the one place for their ranges.

Examples
--------
>>> class Args(AgentArgs):
...     epsilon: Annotated[Any, interval(0.0, 1.0)]
>>> validate_args(Args, {"epsilon": 1.5})
Traceback (most recent call last):
...
cobelrun.errors.ConfigError: agent.epsilon must be a number in [0.0, 1.0], got 1.5
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo
from pydantic.functional_validators import BeforeValidator
from pydantic_core import PydanticCustomError

from cobelrun.errors import ConfigError, allowed_list, suggest

__all__ = [
    "AgentArgs",
    "at_least",
    "boolean",
    "finite_or_none",
    "int_at_least_or_none",
    "interval",
    "number_above",
    "number_at_least",
    "one_of",
    "positive",
    "positive_or_none",
    "validate_args",
]

#: the key prefix of agent arguments in configs and messages
PREFIX = "agent"


class AgentArgs(BaseModel):
    """Base of agents' argument models: values kept as given; keys the model does not declare
    (``self``, ``env``, ``seed``, ...) ignored."""

    model_config = ConfigDict(extra="ignore", frozen=True)


def _rule(check: Callable[[str, Any], str | None]) -> BeforeValidator:
    """A pydantic validator from ``check(key, value)``, which returns the message of a broken
    rule (or None)."""

    def validate(value: Any, info: ValidationInfo) -> Any:
        message = check(f"{PREFIX}.{info.field_name}", value)
        if message is not None:
            raise PydanticCustomError("cobel_agent_arg", "{message}", {"message": message})
        return value

    return BeforeValidator(validate)


def _real(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def interval(lo: float, hi: float) -> BeforeValidator:
    """A number in ``[lo, hi]``."""

    def check(key: str, value: Any) -> str | None:
        if _real(value) and lo <= value <= hi:
            return None
        return f"{key} must be a number in [{lo}, {hi}], got {value!r}"

    return _rule(check)


def number_at_least(lo: float) -> BeforeValidator:
    """A finite number ``>= lo``."""

    def check(key: str, value: Any) -> str | None:
        if _real(value) and math.isfinite(value) and value >= lo:
            return None
        return f"{key} must be a number >= {lo}, got {value!r}"

    return _rule(check)


def number_above(lo: float) -> BeforeValidator:
    """A finite number ``> lo``."""

    def check(key: str, value: Any) -> str | None:
        if _real(value) and math.isfinite(value) and value > lo:
            return None
        return f"{key} must be a number > {lo}, got {value!r}"

    return _rule(check)


def boolean() -> BeforeValidator:
    """``true`` or ``false`` (not 0/1, not a string)."""

    def check(key: str, value: Any) -> str | None:
        return None if isinstance(value, bool) else f"{key} must be true or false, got {value!r}"

    return _rule(check)


def int_at_least_or_none(lo: int) -> BeforeValidator:
    """None (null) or an integer (not a bool) ``>= lo``."""

    def check(key: str, value: Any) -> str | None:
        if value is None or (
            isinstance(value, int) and not isinstance(value, bool) and value >= lo
        ):
            return None
        return f"{key} must be null or an integer >= {lo}, got {value!r}"

    return _rule(check)


def at_least(lo: int) -> BeforeValidator:
    """An integer (not a bool) ``>= lo``."""

    def check(key: str, value: Any) -> str | None:
        if isinstance(value, int) and not isinstance(value, bool) and value >= lo:
            return None
        return f"{key} must be an integer >= {lo}, got {value!r}"

    return _rule(check)


def positive() -> BeforeValidator:
    """A number ``> 0``."""

    def check(key: str, value: Any) -> str | None:
        return None if _real(value) and value > 0 else f"{key} must be > 0, got {value}"

    return _rule(check)


def positive_or_none() -> BeforeValidator:
    """A number ``> 0`` or None (null)."""

    def check(key: str, value: Any) -> str | None:
        if value is None or (_real(value) and value > 0):
            return None
        return f"{key} must be > 0 or null, got {value}"

    return _rule(check)


def finite_or_none() -> BeforeValidator:
    """A finite number or None (null)."""

    def check(key: str, value: Any) -> str | None:
        if value is None or (_real(value) and math.isfinite(value)):
            return None
        return f"{key} must be a finite number or null, got {value!r}"

    return _rule(check)


def one_of(choices: Collection[str], hint: bool = True) -> BeforeValidator:
    """One of ``choices`` (names); ``hint`` adds the closest name to the message."""
    names = list(choices)

    def check(key: str, value: Any) -> str | None:
        if isinstance(value, str) and value in names:
            return None
        near = suggest(str(value), names) if hint else ""
        return f"{key} {value!r} is not known{near}; allowed: {allowed_list(names)}"

    return _rule(check)


def validate_args(model: type[AgentArgs], values: Mapping[str, Any]) -> AgentArgs:
    """``values`` (an agent's arguments, e.g. its ``locals()``) checked against ``model``.

    Raises
    ------
    cobelrun.errors.ConfigError
        One line: the first broken rule, in the model's field order.
    """
    try:
        return model.model_validate(dict(values))
    except ValidationError as error:
        first = error.errors(include_url=False)[0]
        if first["type"] == "missing":
            raise TypeError(f"{model.__name__}: argument {first['loc'][0]!r} not given") from None
        raise ConfigError(first["msg"]) from None
