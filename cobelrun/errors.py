"""Errors that the CLI reports as one clear line (no traceback unless ``--debug``)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class CobelError(Exception):
    """A user-facing error: bad config, layout, name or file.

    The message must name the problem and what is allowed; the CLI prints it as one line.
    """


class ConfigError(CobelError):
    """A config value or key is invalid."""


class LayoutError(CobelError):
    """A maze layout is invalid (unknown symbol, no start, unreachable goal, ...)."""


def suggest(name: str, allowed: Iterable[str]) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest match of ``name`` in ``allowed``, or ``""``."""
    close = difflib.get_close_matches(str(name), [str(a) for a in allowed], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def allowed_list(allowed: Iterable[object]) -> str:
    """Format allowed values for an error message."""
    return ", ".join(repr(a) if isinstance(a, str) else str(a) for a in allowed)


def check_choice(kind: str, value: object, allowed: Iterable[str]) -> str:
    """Return ``value`` if it is one of ``allowed``, else raise a one-line ConfigError naming
    ``kind`` (e.g. ``agent.policy``), the closest match and what is allowed."""
    allowed = list(allowed)
    if value not in allowed:
        raise ConfigError(
            f"{kind} {value!r} is not known{suggest(str(value), allowed)}; "
            f"allowed: {allowed_list(allowed)}"
        )
    return str(value)
