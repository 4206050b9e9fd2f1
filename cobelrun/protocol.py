"""Protocols: a task's phases (acquisition, extinction, renewal, probe, ...).

A phase has a name, a number of trials and the changes it makes to the environment when it
starts: reward placement, terminal states, start states, and whether the agent learns.
Changes persist into later phases unless a later phase changes them again.

A phase may also change the environment trial by trial: its ``cycle`` is a list of changes,
and trial ``k`` of the phase (0-based) starts with ``cycle[k % len(cycle)]`` applied (after the
phase's own changes). Laps on a linear track alternate their start that way.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from cobelrun.errors import CobelError, ConfigError
from cobelrun.schema import ProtocolSpec, validate


@dataclass(frozen=True)
class Changes:
    """Changes to the environment: ``{state: reward}``, ``{state: terminal}`` and start states
    (``None``: unchanged); states as in :class:`Phase`."""

    rewards: Mapping[Any, float] = field(default_factory=dict)
    terminals: Mapping[Any, bool] = field(default_factory=dict)
    starts: Sequence[Any] | None = None

    def __bool__(self) -> bool:
        return bool(self.rewards or self.terminals or self.starts is not None)


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
    cycle
        Per-trial changes: trial ``k`` of the phase starts with ``cycle[k % len(cycle)]``
        applied (empty: none). The agent then runs one trial per ``train``/``test`` call.
    """

    name: str
    trials: int
    learning: bool = True
    max_steps: int | None = None
    rewards: Mapping[Any, float] = field(default_factory=dict)
    terminals: Mapping[Any, bool] = field(default_factory=dict)
    starts: Sequence[Any] | None = None
    cycle: tuple[Changes, ...] = ()


@dataclass(frozen=True)
class Protocol:
    """A list of phases and the default per-trial step limit."""

    phases: tuple[Phase, ...]
    max_steps: int

    @property
    def n_trials(self) -> int:
        return sum(p.trials for p in self.phases)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], where: str = "task.protocol") -> Protocol:
        """Build from a plain mapping ``{max_steps: int, phases: [ {name, trials, ...}, ... ]}``,
        validated by :class:`cobelrun.schema.ProtocolSpec` (errors are one-line ConfigErrors)."""
        return cls.from_spec(validate(ProtocolSpec, cfg, where))

    @classmethod
    def from_spec(cls, spec: ProtocolSpec) -> Protocol:
        """Build from a validated :class:`cobelrun.schema.ProtocolSpec`."""
        phases = tuple(
            Phase(
                name=p.name,
                trials=p.trials,
                learning=p.learning,
                max_steps=p.max_steps,
                rewards=dict(p.rewards),
                terminals=dict(p.terminals),
                starts=None if p.starts is None else list(p.starts),
                cycle=tuple(
                    Changes(
                        rewards=dict(c.rewards),
                        terminals=dict(c.terminals),
                        starts=None if c.starts is None else list(c.starts),
                    )
                    for c in (p.cycle or ())
                ),
            )
            for p in spec.phases
        )
        return cls(phases=phases, max_steps=spec.max_steps)

    def apply(self, phase: Phase, env: Any) -> None:
        """Apply a phase's changes to ``env`` (which must offer ``apply_changes``)."""
        self._change(phase, Changes(phase.rewards, phase.terminals, phase.starts), env)

    def apply_trial(self, phase: Phase, k: int, env: Any) -> None:
        """Apply the changes of trial ``k`` (0-based) of ``phase``'s cycle (if it has one)."""
        if phase.cycle:
            self._change(phase, phase.cycle[k % len(phase.cycle)], env)

    @staticmethod
    def _change(phase: Phase, changes: Changes, env: Any) -> None:
        if not changes:
            return
        from cobelrun.envs.base import Changeable, supports

        base = env.unwrapped
        if not supports(base, Changeable):
            raise ConfigError(
                f"phase {phase.name!r} changes the environment, but {type(base).__name__} "
                "does not support changes (no 'changeable' contract)"
            )
        base.apply_changes(
            rewards=changes.rewards or None, terminals=changes.terminals or None,
            starts=changes.starts,
        )  # fmt: skip

    def check(self, env: Any) -> None:
        """Apply every phase's changes once, in order, then restore the world: a bad state name,
        terminal or start fails here, before anything runs (a ConfigError naming the phase).

        An env's own checks may raise ``ValueError``/``KeyError``/``TypeError``; they become a
        ConfigError too, so a user's env module still gives the one-line error.
        """
        changing = [p for p in self.phases
                    if p.rewards or p.terminals or p.starts is not None or p.cycle]  # fmt: skip
        if not changing:
            return
        try:
            for phase in changing:
                try:
                    self.apply(phase, env)
                    for k in range(len(phase.cycle or ())):  # each entry of a per-trial cycle
                        self.apply_trial(phase, k, env)
                except CobelError:
                    raise
                except (ValueError, KeyError, TypeError) as exc:
                    raise ConfigError(f"task.protocol phase {phase.name!r}: {exc}") from exc
        finally:
            reset = getattr(env.unwrapped, "reset_world", None)
            if callable(reset):
                reset()
