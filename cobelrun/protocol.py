"""Protocols: a task's phases (acquisition, extinction, renewal, probe, ...).

A phase has a name, a number of trials and the changes it makes to the environment when it
starts: reward placement, terminal states, start states, and whether the agent learns.
Changes persist into later phases unless a later phase changes them again.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

from cobelrun.errors import ConfigError, allowed_list, suggest


@dataclass(frozen=True)
class Phase:
    """One phase of a protocol.

    Attributes
    ----------
    name
        Label written to the ``phase`` column (e.g. ``acquisition``).
    trials
        Number of trials in the phase.
    learning
        If false the agent is tested (same policy, no updates).
    max_steps
        Per-trial step limit for this phase (default: the protocol's).
    rewards
        ``{state: reward}`` set when the phase starts; a state is an index, a place name of the
        environment (``right_arm``) or ``[row, col]``.
    terminals
        ``{state: bool}`` set when the phase starts.
    starts
        Start states from this phase on.
    """

    name: str
    trials: int
    learning: bool = True
    max_steps: int | None = None
    rewards: Mapping[Any, float] = field(default_factory=dict)
    terminals: Mapping[Any, bool] = field(default_factory=dict)
    starts: Sequence[Any] | None = None


@dataclass(frozen=True)
class Protocol:
    """A list of phases and the default per-trial step limit."""

    phases: tuple[Phase, ...]
    max_steps: int

    @property
    def n_trials(self) -> int:
        return sum(p.trials for p in self.phases)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Protocol:
        """Build from a plain mapping ``{max_steps: int, phases: [ {name, trials, ...}, ... ]}``."""
        _check_keys("task.protocol", cfg, ("max_steps", "phases"))
        max_steps = _positive_int("task.protocol.max_steps", cfg.get("max_steps"))
        raw = cfg.get("phases")
        if not isinstance(raw, Sequence) or isinstance(raw, str) or not raw:
            raise ConfigError("task.protocol.phases must be a non-empty list of phases")
        allowed = [f.name for f in fields(Phase)]
        phases = []
        for i, p in enumerate(raw):
            where = f"task.protocol.phases[{i}]"
            if not isinstance(p, Mapping):
                raise ConfigError(f"{where} must be a mapping with keys {allowed_list(allowed)}")
            _check_keys(where, p, allowed)
            if "name" not in p or "trials" not in p:
                raise ConfigError(f"{where} needs 'name' and 'trials'")
            if not isinstance(p.get("learning", True), bool):
                raise ConfigError(f"{where}.learning must be true or false, got {p['learning']!r}")
            for key, kind in (("rewards", Mapping), ("terminals", Mapping)):
                if not isinstance(p.get(key, {}) or {}, kind):
                    raise ConfigError(f"{where}.{key} must be a mapping state -> value")
            starts = p.get("starts")
            if starts is not None and (isinstance(starts, str) or not isinstance(starts, Sequence)):
                raise ConfigError(f"{where}.starts must be a list of states")
            phases.append(
                Phase(
                    name=str(p["name"]),
                    trials=_positive_int(f"{where}.trials", p["trials"], allow_zero=True),
                    learning=p.get("learning", True),
                    max_steps=(
                        None
                        if p.get("max_steps") is None
                        else _positive_int(f"{where}.max_steps", p["max_steps"])
                    ),
                    rewards=dict(p.get("rewards") or {}),
                    terminals=dict(p.get("terminals") or {}),
                    starts=None if starts is None else list(starts),
                )
            )
        names = [ph.name for ph in phases]
        if len(set(names)) != len(names):
            raise ConfigError(f"task.protocol.phases have duplicate names: {names}")
        return cls(phases=tuple(phases), max_steps=max_steps)

    def apply(self, phase: Phase, env: Any) -> None:
        """Apply a phase's changes to ``env`` (which must offer ``apply_changes``)."""
        if not (phase.rewards or phase.terminals or phase.starts is not None):
            return
        from cobelrun.envs.base import Changeable, supports

        base = env.unwrapped
        if not supports(base, Changeable):
            raise ConfigError(
                f"phase {phase.name!r} changes the environment, but {type(base).__name__} "
                "does not support changes (no 'changeable' contract)"
            )
        base.apply_changes(
            rewards=phase.rewards or None, terminals=phase.terminals or None, starts=phase.starts
        )


def _check_keys(where: str, cfg: Mapping[str, Any], allowed: Sequence[str]) -> None:
    for key in cfg:
        if key not in allowed:
            raise ConfigError(
                f"unknown key '{where}.{key}'{suggest(key, allowed)}; allowed: {allowed_list(allowed)}"
            )


def _positive_int(where: str, value: Any, *, allow_zero: bool = False) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < (0 if allow_zero else 1):
        bound = ">= 0" if allow_zero else ">= 1"
        raise ConfigError(f"{where} must be an integer {bound}, got {value!r}")
    return int(value)
