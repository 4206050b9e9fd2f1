"""Pieces shared by cobel's environments: protocol-changeable worlds and action checking."""

from __future__ import annotations

import operator
from collections.abc import Iterable, Mapping, Sequence
from typing import Any


class ChangeableWorld:
    """Mixin for environments whose ``world`` a protocol changes between phases.

    The environment keeps ``_world`` (live) and ``_base_world`` (as built); the world object
    offers ``set_rewards``, ``set_terminal``, ``set_starts`` and ``copy``.
    """

    _world: Any
    _base_world: Any

    @property
    def world(self) -> Any:
        """The live world (changed by :meth:`apply_changes`)."""
        return self._world

    @property
    def base_world(self) -> Any:
        """The world as it was at construction (a copy; do not modify)."""
        return self._base_world

    def reset_world(self) -> None:
        """Restore the world to :attr:`base_world` (undo every :meth:`apply_changes`)."""
        self._world = self._base_world.copy()

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """Change rewards, terminal flags or start states in place (a protocol phase starts).

        Parameters
        ----------
        rewards : mapping state -> float, optional
            New arrival rewards.
        terminals : mapping state -> bool, optional
            Terminal flags to set.
        starts : list of states, optional
            New start states.
        """
        if rewards is not None:
            self._world.set_rewards(rewards)
        if terminals is not None:
            self._world.set_terminal(terminals)
        if starts is not None:
            self._world.set_starts(starts)


def check_action(action: Any, n_actions: int, names: Sequence[str]) -> int:
    """Return ``action`` as an int in ``[0, n_actions)`` or raise a ValueError naming the actions."""
    listed = ", ".join(f"{i}={name}" for i, name in enumerate(names))
    try:
        if hasattr(action, "reshape") and hasattr(
            action, "size"
        ):  # numpy scalar or 1-element array
            if action.size != 1:
                raise TypeError
            action = action.reshape(()).item()
        if isinstance(action, bool) or type(action).__name__ == "bool_":
            raise TypeError
        a = operator.index(action)
    except TypeError:
        raise ValueError(
            f"invalid action {action!r}; allowed: integers 0..{n_actions - 1} ({listed})"
        ) from None
    if not 0 <= a < n_actions:
        raise ValueError(f"invalid action {a}; allowed: 0..{n_actions - 1} ({listed})")
    return a
