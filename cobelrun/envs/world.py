"""Tabular worlds: transition table, rewards, terminals and start states of a gridworld.

A :class:`World` is the one description of a tabular maze that every environment, agent kernel
and analysis reads. States are numbered row-major from the top-left corner
(``state = row * width + col``, row 0 = top) and actions are 0 = left, 1 = up, 2 = right,
3 = down, as in the original CoBeL-RL (``docs/paper-settings.md``, "Conventions").

Builders (:func:`from_layout`, :func:`open_field`, :func:`t_maze`, :func:`tmaze_paper`,
:func:`blodgett`) take plain keyword arguments so Hydra configs can point ``_target_`` at them.
"""

from __future__ import annotations

import json
import textwrap
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from cobelrun.errors import ConfigError, LayoutError, allowed_list, suggest

#: Actions as (name, d_row, d_col); index = action id.
ACTIONS: tuple[tuple[str, int, int], ...] = (
    ("left", 0, -1),
    ("up", -1, 0),
    ("right", 0, 1),
    ("down", 1, 0),
)
N_ACTIONS = len(ACTIONS)

#: Layout symbols and their meaning.
SYMBOLS: dict[str, str] = {
    "#": "wall cell",
    ".": "free cell",
    "S": "start",
    "G": "goal (terminal, reward = goal_reward)",
    "E": "terminal without reward",
}

#: A reference to a state: index, place name, or ``[row, col]``.
StateRef = int | str | Sequence[int]


@dataclass(eq=False)
class World:
    """A tabular world (gridworld with a transition table).

    Attributes
    ----------
    width, height : int
        Grid size in cells. ``state = row * width + col`` with row 0 at the top.
    T : (S, A, S) float64
        Transition probabilities ``T[s, a, s']``; every row sums to 1. ``A = 4`` with actions
        0 = left, 1 = up, 2 = right, 3 = down. Stored read-only: assign a new array to change it.
    rewards : (S,) float64
        Reward received on *arriving* in a state.
    terminal : (S,) bool
        Terminal states (a trial ends on arriving there).
    starts : (k,) int64
        Start states; ``reset`` picks one uniformly.
    coords : (S, 2) float64
        Cell coordinates ``(x, y)`` with ``x = col`` and ``y = height - 1 - row`` ("up" = +y).
    blocked : (S,) bool
        Wall cells: numbered like every other cell, but never reachable.
    places : dict[str, int]
        Named states, e.g. ``{"start": 38, "left_arm": 0, "right_arm": 6}``.
    reward_sd : float
        Standard deviation of Gaussian noise added to every non-zero reward on arrival (0: the
        rewards are exact). Positive rewards plus noise are truncated at 0, as Mattar & Daw's
        ``rewOnlyPositive``; the noise is drawn from the environment's ``np_random``.
    """

    width: int
    height: int
    T: np.ndarray
    rewards: np.ndarray
    terminal: np.ndarray
    starts: np.ndarray
    coords: np.ndarray
    blocked: np.ndarray
    places: dict[str, int] = field(default_factory=dict)
    reward_sd: float = 0.0
    _next_state: np.ndarray | None = field(default=None, init=False, repr=False)
    _next_state_known: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width < 1 or self.height < 1:
            raise LayoutError(
                f"world size must be at least 1 x 1, got {self.width} x {self.height}"
            )
        n = self.width * self.height
        self.T = np.array(self.T, dtype=np.float64)  # setter validates and freezes
        self.rewards = _vector(self.rewards, n, np.float64, "rewards")
        self.terminal = _vector(self.terminal, n, np.bool_, "terminal")
        self.blocked = _vector(self.blocked, n, np.bool_, "blocked")
        coords = np.asarray(self.coords, dtype=np.float64)
        if coords.shape != (n, 2):
            raise LayoutError(f"coords must have shape ({n}, 2), got {coords.shape}")
        self.coords = coords.copy()
        if not np.all(np.isfinite(self.rewards)):
            raise LayoutError("rewards must be finite numbers")
        sd = _finite(self.reward_sd, "reward_sd")
        if sd < 0:
            raise LayoutError(f"reward_sd must be a number >= 0, got {sd}")
        self.reward_sd = sd
        self.places = {str(k): self._index(v, f"place '{k}'") for k, v in dict(self.places).items()}
        self.set_starts(np.asarray(self.starts).reshape(-1).tolist())

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "T":
            value = np.array(value, dtype=np.float64)
            n = int(self.width) * int(self.height)
            if value.shape != (n, N_ACTIONS, n):
                raise LayoutError(f"T must have shape ({n}, {N_ACTIONS}, {n}), got {value.shape}")
            if np.any(value < 0) or not np.allclose(value.sum(axis=2), 1.0, atol=1e-9):
                raise LayoutError("T must hold probabilities: non-negative, each T[s, a] sums to 1")
            value.setflags(write=False)
            object.__setattr__(self, "_next_state_known", False)
            object.__setattr__(self, "_next_state", None)
        object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ basic properties
    @property
    def n_states(self) -> int:
        """Number of states ``S = width * height`` (wall cells included)."""
        return self.width * self.height

    @property
    def n_actions(self) -> int:
        """Number of actions (4: left, up, right, down)."""
        return N_ACTIONS

    @property
    def next_state(self) -> np.ndarray | None:
        """(S, A) int64 successor table if ``T`` is deterministic (one-hot rows), else None.

        Computed once and cached; assigning a new ``T`` clears the cache.
        """
        if not self._next_state_known:
            ns = None
            if np.all(self.T.max(axis=2) == 1.0):
                ns = self.T.argmax(axis=2).astype(np.int64)
                ns.setflags(write=False)
            object.__setattr__(self, "_next_state", ns)
            object.__setattr__(self, "_next_state_known", True)
        return self._next_state

    # ------------------------------------------------------------------ state references
    def state(self, ref: StateRef) -> int:
        """Resolve a state reference to a state index.

        Parameters
        ----------
        ref : int, str or [row, col]
            A state index, a place name (see :attr:`places`; a string of digits is read as an
            index), or a ``[row, col]`` pair.

        Returns
        -------
        int
            The state index in ``[0, n_states)``.
        """
        return self._index(ref, "state")

    def _index(self, ref: Any, what: str) -> int:
        if isinstance(ref, bool | np.bool_):
            raise ConfigError(
                f"{what}: {ref!r} is not a state; use an index, a place name or [row, col]"
            )
        if isinstance(ref, int | np.integer):
            s = int(ref)
            if not 0 <= s < self.n_states:
                raise LayoutError(
                    f"{what}: state {s} is out of range; allowed 0..{self.n_states - 1}"
                )
            return s
        if isinstance(ref, str):
            places = getattr(self, "places", {}) or {}
            if ref in places:
                return int(places[ref])
            if ref.strip().lstrip("-").isdigit():
                return self._index(int(ref), what)
            allowed = allowed_list(sorted(places)) if places else "none defined"
            raise LayoutError(
                f"{what}: unknown place '{ref}'{suggest(ref, places)}; places: {allowed}"
            )
        if isinstance(ref, Sequence | np.ndarray) and not isinstance(ref, str | bytes):
            items = list(ref)
            if len(items) == 2 and all(
                isinstance(v, int | np.integer) and not isinstance(v, bool) for v in items
            ):
                r, c = int(items[0]), int(items[1])
                if not (0 <= r < self.height and 0 <= c < self.width):
                    raise LayoutError(
                        f"{what}: cell [row {r}, col {c}] is outside the {self.height} x "
                        f"{self.width} grid; rows 0..{self.height - 1}, cols 0..{self.width - 1}"
                    )
                return r * self.width + c
        raise ConfigError(
            f"{what}: {ref!r} is not a state reference; use an int index, a place name or [row, col]"
        )

    def describe(self, s: int) -> str:
        """Return ``"state s (row r, col c)"`` for messages."""
        r, c = divmod(int(s), self.width)
        return f"state {int(s)} (row {r}, col {c})"

    # ------------------------------------------------------------------ changes (in place)
    def copy(self) -> World:
        """Return a copy whose changeable arrays are independent of this world's.

        ``T`` is read-only (replacing it re-validates), so the copy shares it and its cached
        ``next_state`` table; everything else is copied. Nothing is re-validated: the source
        is a valid world, which keeps :meth:`copy` cheap (it runs once per run).
        """
        _ = self.next_state  # computed once here, so that every copy shares it
        new = object.__new__(World)
        state = dict(self.__dict__)
        for name in ("rewards", "terminal", "starts", "coords", "blocked"):
            state[name] = state[name].copy()
        state["places"] = dict(self.places)
        new.__dict__.update(state)
        return new

    def set_rewards(self, mapping: Mapping[Any, float]) -> None:
        """Set the arrival reward of some states, in place.

        Parameters
        ----------
        mapping : mapping of state reference to float
            E.g. ``{"right_arm": 0.0, "left_arm": 1.0}``. A list of ``[ref, value]`` pairs
            is accepted too (YAML cannot use ``[row, col]`` as a key).
        """
        items = _pairs(mapping, "rewards")
        new = self.rewards.copy()
        for ref, value in items:
            s = self._index(ref, "rewards")
            v = _finite(value, f"rewards[{ref!r}]")
            if self.blocked[s] and v != 0.0:
                raise LayoutError(
                    f"rewards: {self.describe(s)} is a wall cell; rewards must be on free cells"
                )
            new[s] = v
        self.rewards = new

    def set_terminal(self, mapping: Mapping[Any, bool]) -> None:
        """Mark states terminal (True) or not (False), in place.

        Parameters
        ----------
        mapping : mapping of state reference to bool
            E.g. ``{"left_arm": True}``. A list of ``[ref, flag]`` pairs is accepted too.
        """
        items = _pairs(mapping, "terminals")
        new = self.terminal.copy()
        for ref, flag in items:
            s = self._index(ref, "terminals")
            if not isinstance(flag, bool | np.bool_):
                raise ConfigError(f"terminals[{ref!r}] must be true or false, got {flag!r}")
            if flag and s in set(self.starts.tolist()):
                raise LayoutError(
                    f"terminals: {self.describe(s)} is a start state; it cannot be terminal"
                )
            new[s] = bool(flag)
        self.terminal = new

    def set_starts(self, refs: Iterable[StateRef] | StateRef) -> None:
        """Replace the start states, in place.

        Parameters
        ----------
        refs : state reference or list of them
            ``reset`` picks uniformly among these. Must be free, non-terminal cells. A list is
            always a list of references: write ``[[row, col]]`` for a single cell.
        """
        if isinstance(refs, int | np.integer | str):
            refs = [refs]
        starts = [self._index(r, "starts") for r in refs]  # type: ignore[union-attr]
        if not starts:
            raise LayoutError("starts: at least one start state is needed")
        for s in starts:
            if self.blocked[s]:
                raise LayoutError(
                    f"starts: {self.describe(s)} is a wall cell; starts must be free cells"
                )
            if self.terminal[s]:
                raise LayoutError(
                    f"starts: {self.describe(s)} is terminal; starts must be non-terminal"
                )
        self.starts = np.asarray(starts, dtype=np.int64)

    # ------------------------------------------------------------------ graph queries
    def distances(self, from_states: Iterable[StateRef] | None = None) -> np.ndarray:
        """Breadth-first step distances over ``T > 0``.

        Parameters
        ----------
        from_states : list of state references, optional
            Sources (default: the start states).

        Returns
        -------
        (S,) int64
            Minimal number of steps from the nearest source; -1 where unreachable.
        """
        src = self.starts.tolist() if from_states is None else [self.state(r) for r in from_states]
        adj = self.T > 0
        dist = np.full(self.n_states, -1, dtype=np.int64)
        queue: deque[int] = deque()
        for s in src:
            if dist[s] < 0:
                dist[s] = 0
                queue.append(s)
        while queue:
            s = queue.popleft()
            for nxt in np.flatnonzero(adj[s].any(axis=0)):
                if dist[nxt] < 0:
                    dist[nxt] = dist[s] + 1
                    queue.append(int(nxt))
        return dist

    def reachable(self, from_states: Iterable[StateRef] | None = None) -> np.ndarray:
        """(S,) bool: states reachable from ``from_states`` (default: the start states)."""
        return self.distances(from_states) >= 0

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | PathLike[str]) -> Path:
        """Save to an ``.npz`` file (no pickle; places stored as a JSON string).

        Returns
        -------
        Path
            The file written (``.npz`` appended if missing).
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        np.savez(
            path,
            width=np.int64(self.width),
            height=np.int64(self.height),
            T=self.T,
            rewards=self.rewards,
            terminal=self.terminal,
            starts=self.starts,
            coords=self.coords,
            blocked=self.blocked,
            places=np.str_(json.dumps(self.places, sort_keys=True)),
            reward_sd=np.float64(self.reward_sd),
        )
        return path

    @classmethod
    def load(cls, path: str | PathLike[str]) -> World:
        """Load a world written by :meth:`save` (``allow_pickle=False``)."""
        with np.load(Path(path), allow_pickle=False) as z:
            return cls(
                width=int(z["width"]),
                height=int(z["height"]),
                T=z["T"],
                rewards=z["rewards"],
                terminal=z["terminal"],
                starts=z["starts"],
                coords=z["coords"],
                blocked=z["blocked"],
                places=json.loads(str(z["places"])),
                reward_sd=float(z["reward_sd"]) if "reward_sd" in z.files else 0.0,
            )


# ---------------------------------------------------------------------- helpers
def _vector(value: Any, n: int, dtype: Any, name: str) -> np.ndarray:
    arr = np.array(value, dtype=dtype).reshape(-1) if np.ndim(value) else np.full(n, value, dtype)
    if arr.shape != (n,):
        raise LayoutError(f"{name} must have one entry per state ({n}), got {arr.shape[0]}")
    return arr


def _finite(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ConfigError(f"{what} must be a finite number, got {value!r}")
    return v


def _pairs(mapping: Any, what: str) -> list[tuple[Any, Any]]:
    if mapping is None:
        return []
    if isinstance(mapping, Mapping):
        return list(mapping.items())
    if isinstance(mapping, Iterable) and not isinstance(mapping, str):
        items = list(mapping)
        if all(isinstance(p, Sequence) and not isinstance(p, str) and len(p) == 2 for p in items):
            return [(p[0], p[1]) for p in items]
    raise ConfigError(
        f"{what} must be a mapping of state -> value or a list of [state, value] pairs, got {mapping!r}"
    )


def world_bytes(width: int, height: int, slip: float = 0.0) -> int:
    """Bytes a ``width x height`` world allocates: its dense (S, 4, S) float64 transition
    matrix (three of them while a slip is mixed in), and per-cell arrays."""
    n = int(width) * int(height)
    return n * N_ACTIONS * n * 8 * (3 if slip > 0 else 1) + n * 256


def check_world_memory(where: str, width: int, height: int, slip: float = 0.0) -> None:
    """Refuse a grid world too large for memory before any of it is allocated."""
    from cobelrun.safety import check_allocation

    n = int(width) * int(height)
    check_allocation(where, world_bytes(width, height, slip),
                     f"a {width:,} x {height:,} grid world ({n:,} states: a {n:,} x {N_ACTIONS} x "
                     f"{n:,} transition matrix)", "use a smaller grid")  # fmt: skip


def _coords(width: int, height: int) -> np.ndarray:
    rows, cols = np.divmod(np.arange(width * height), width)
    return np.stack([cols, height - 1 - rows], axis=1).astype(np.float64)


def _parse_layout(layout: str) -> list[str]:
    if not isinstance(layout, str):
        raise ConfigError(f"layout must be a string of rows, got {type(layout).__name__}")
    lines = textwrap.dedent(layout.expandtabs()).split("\n")
    lines = [line.rstrip() for line in lines]
    while lines and not lines[0].strip():
        lines.pop(0)
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise LayoutError("layout is empty; give rows of cells using " + allowed_list(SYMBOLS))
    width = len(lines[0])
    for r, line in enumerate(lines):
        if len(line) != width:
            raise LayoutError(
                f"layout row {r} has {len(line)} cells but row 0 has {width}; all rows must have the same length (ragged rows)"
            )
        for c, ch in enumerate(line):
            if ch not in SYMBOLS:
                raise LayoutError(
                    f"unknown layout symbol {ch!r} at row {r}, col {c}; allowed symbols: {allowed_list(SYMBOLS)}"
                )
    return lines


def _check_warps(world: World, warps: Any, blocked: np.ndarray, goal: np.ndarray,
                 starts: list[int]) -> dict[int, int]:  # fmt: skip
    """``{entry: exit}`` of ``warps`` (a mapping of state references), checked."""
    out: dict[int, int] = {}
    for k, v in _pairs(warps or {}, "warps"):
        entry, exit_ = world._index(k, "warps"), world._index(v, "warps")
        for what, s in (("entry", entry), ("exit", exit_)):
            if blocked[s]:
                raise LayoutError(f"warp {what} {world.describe(s)} is a wall cell; "
                                  "warps join free cells")  # fmt: skip
        if entry == exit_:
            raise LayoutError(f"warp {world.describe(entry)} leads to itself")
        if entry in starts:
            raise LayoutError(f"warp entry {world.describe(entry)} is a start; an entry is "
                              "never occupied")  # fmt: skip
        if goal[entry]:
            raise LayoutError(f"warp entry {world.describe(entry)} is a goal or terminal; an "
                              "entry is never occupied (reward its exit instead)")  # fmt: skip
        out[entry] = exit_
    for entry, exit_ in out.items():
        if exit_ in out:
            raise LayoutError(f"warp exit {world.describe(exit_)} is another warp's entry "
                              f"(from {world.describe(entry)}); warps do not chain")  # fmt: skip
    return out


def _check_pairs(world: World, pairs: Any, what: str) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for pair in pairs or ():
        if isinstance(pair, str) or not isinstance(pair, Sequence) or len(pair) != 2:
            raise ConfigError(f"{what}: each entry must be a pair [a, b] of states, got {pair!r}")
        a, b = world._index(pair[0], what), world._index(pair[1], what)
        (ra, ca), (rb, cb) = divmod(a, world.width), divmod(b, world.width)
        if abs(ra - rb) + abs(ca - cb) != 1:
            raise LayoutError(
                f"{what}: states {a} and {b} are not adjacent cells; a pair must share an edge"
            )
        out.append((a, b))
    return out


def from_layout(
    layout: str,
    *,
    walls: Iterable[Sequence[StateRef]] = (),
    one_way: Iterable[Sequence[StateRef]] = (),
    rewards: Mapping[Any, float] | None = None,
    terminals: Iterable[StateRef] | None = None,
    starts: Iterable[StateRef] | None = None,
    places: Mapping[str, StateRef] | None = None,
    goal_reward: float = 1.0,
    slip: float = 0.0,
    reward_sd: float = 0.0,
    warps: Mapping[Any, StateRef] | None = None,
) -> World:
    """Build a world from an ASCII layout.

    Parameters
    ----------
    layout : str
        One character per cell, rows separated by newlines (common indentation and blank
        leading/trailing lines are stripped): ``#`` wall cell, ``.`` free, ``S`` start,
        ``G`` goal (terminal, reward ``goal_reward``), ``E`` terminal without reward.
    walls : list of [a, b]
        Two-way walls between adjacent states ``a`` and ``b``.
    one_way : list of [a, b]
        One-way doors: the move ``a -> b`` is blocked, ``b -> a`` stays allowed.
    rewards : mapping state -> float, optional
        Arrival rewards, applied after the ``G`` cells (so they can override them).
    terminals : list of states, optional
        Additional terminal states.
    starts : list of states, optional
        Start states; overrides the ``S`` cells.
    places : mapping name -> state, optional
        Named states. Without it, ``start`` and ``goal`` are named when the layout has exactly
        one ``S`` / ``G`` cell.
    goal_reward : float
        Reward of the ``G`` cells (default 1.0).
    slip : float
        Probability in [0, 1) that a move goes in a uniformly random *other* direction.
        0 gives a deterministic world.
    reward_sd : float
        Gaussian noise (standard deviation) on every non-zero reward (see :class:`World`).
    warps : mapping entry -> exit, optional
        Teleport cells (as neuro-nav's warps): a move that would arrive in ``entry`` arrives
        in ``exit`` instead, so ``entry`` is never occupied. Each pair whose entry has no place
        name yet is named ``warp_N`` (entry) and ``warp_N_exit`` (``cobel show`` draws places).
        Entries must be free, not starts, not rewarded or terminal, and not another warp's
        exit.

    Returns
    -------
    World

    Raises
    ------
    LayoutError
        Unknown symbol, ragged rows, no start, start on a wall, a rewarded or terminal state
        unreachable from every start, bad wall / door pairs.
    """
    rows = _parse_layout(layout)
    height, width = len(rows), len(rows[0])
    n = width * height
    slip = _finite(slip, "slip")
    if not 0.0 <= slip < 1.0:
        raise LayoutError(f"slip must be in [0, 1), got {slip}")
    check_world_memory("env.world", width, height, slip)
    cells = "".join(rows)
    goal_reward = _finite(goal_reward, "goal_reward")

    blocked = np.array([ch == "#" for ch in cells])
    terminal = np.array([ch in "GE" for ch in cells])
    reward = np.where([ch == "G" for ch in cells], goal_reward, 0.0)
    start_cells = [i for i, ch in enumerate(cells) if ch == "S"]

    # A provisional world (identity T) to resolve references before the real T exists.
    auto_places: dict[str, int] = {}
    goals = [i for i, ch in enumerate(cells) if ch == "G"]
    if places is None and len(start_cells) == 1:
        auto_places["start"] = start_cells[0]
    if places is None and len(goals) == 1:
        auto_places["goal"] = goals[0]
    world = World.__new__(World)
    object.__setattr__(world, "width", width)
    object.__setattr__(world, "height", height)
    object.__setattr__(world, "places", auto_places)
    user_places = {str(k): world._index(v, f"place '{k}'") for k, v in dict(places or {}).items()}
    all_places = {**auto_places, **user_places}
    object.__setattr__(world, "places", all_places)

    if starts is not None:
        if isinstance(starts, int | str):
            starts = [starts]
        start_states = [world._index(r, "starts") for r in starts]
    else:
        start_states = start_cells
    if not start_states:
        raise LayoutError("layout has no start: mark a cell 'S' or pass starts=[...]")
    for s in start_states:
        if blocked[s]:
            raise LayoutError(
                f"start {world.describe(s)} is a wall cell; starts must be free cells"
            )

    warp_to = _check_warps(world, warps, blocked, terminal | (reward != 0), start_states)
    for i, (entry, exit_) in enumerate(warp_to.items()):
        if entry in all_places.values():  # named already (e.g. a key)
            continue
        for name, state in ((f"warp_{i}", entry), (f"warp_{i}_exit", exit_)):
            all_places.setdefault(name, state)

    wall_pairs = _check_pairs(world, walls, "walls")
    door_pairs = _check_pairs(world, one_way, "one_way")
    cut = set()
    for a, b in wall_pairs:
        cut.add((a, b))
        cut.add((b, a))
    cut.update(door_pairs)

    # Deterministic successor table, then slip mixing.
    succ = np.empty((n, N_ACTIONS), dtype=np.int64)
    for s in range(n):
        r, c = divmod(s, width)
        for a, (_, dr, dc) in enumerate(ACTIONS):
            rr, cc = r + dr, c + dc
            nxt = rr * width + cc
            ok = (
                not blocked[s]
                and 0 <= rr < height
                and 0 <= cc < width
                and not blocked[nxt]
                and (s, nxt) not in cut
            )
            succ[s, a] = warp_to.get(nxt, nxt) if ok else s
    det = np.zeros((n, N_ACTIONS, n))
    det[np.arange(n)[:, None], np.arange(N_ACTIONS)[None, :], succ] = 1.0
    if slip > 0.0:
        others = det.sum(axis=1, keepdims=True) - det
        T = (1.0 - slip) * det + (slip / (N_ACTIONS - 1)) * others
        T /= T.sum(axis=2, keepdims=True)
    else:
        T = det

    for s in start_states:
        if terminal[s]:
            raise LayoutError(
                f"start {world.describe(s)} is terminal; starts must be non-terminal cells"
            )
    world = World(
        width=width,
        height=height,
        T=T,
        rewards=reward,
        terminal=terminal,
        starts=start_states,
        coords=_coords(width, height),
        blocked=blocked,
        places=all_places,
        reward_sd=reward_sd,
    )
    world.set_rewards(rewards or {})
    if terminals is not None:
        if isinstance(terminals, int | str):
            terminals = [terminals]
        world.set_terminal({world._index(r, "terminals"): True for r in terminals})
    for entry in warp_to:
        if world.terminal[entry] or world.rewards[entry] != 0:
            raise LayoutError(f"warp entry {world.describe(entry)} is rewarded or terminal; "
                              "an entry is never occupied (reward its exit instead)")  # fmt: skip

    reach = world.reachable()
    for s in np.flatnonzero((world.rewards != 0) | world.terminal):
        if not reach[s]:
            kind = "terminal" if world.terminal[s] else "rewarded"
            if world.terminal[s] and world.rewards[s] != 0:
                kind = "goal"
            raise LayoutError(
                f"{kind} {world.describe(s)} is unreachable from every start "
                f"({allowed_list(world.starts.tolist())}); open a path or move it"
            )
    return world


def keys_and_doors(
    layout: str,
    *,
    goal_reward: float = 1.0,
    slip: float = 0.0,
    reward_sd: float = 0.0,
) -> World:
    """A maze with doors that a key opens, as a tabular world (the state includes the key).

    The layout takes two more symbols: ``K`` a key, ``D`` a door (a wall cell until the agent
    has picked up a key; any key opens every door). The world stacks two copies of the maze,
    separated by a wall row: the top one without the key (doors are walls; the agent starts
    here) and the bottom one with it (doors are free cells). Stepping onto a key in the top
    copy lands on the same cell of the bottom copy (a warp, see :func:`from_layout`), so
    ``state = layer * (height + 1) * width + row * width + col``. Keys are named ``key_N``
    (top) and ``key_N_held`` (bottom), goals ``goal`` / ``goal_with_key`` where there is one,
    so ``cobel show`` draws them; a goal is kept in each copy where it can be reached.

    Parameters
    ----------
    layout : str
        As :func:`from_layout`, plus ``K`` (key) and ``D`` (door).
    goal_reward, slip, reward_sd
        As :func:`from_layout`.

    Raises
    ------
    LayoutError
        As :func:`from_layout`; a layout with doors but no key.
    """
    raw = _parse_layout(layout.replace("K", ".").replace("D", "#"))  # validates the rest
    rows = textwrap.dedent(layout.expandtabs()).split("\n")
    rows = [r.rstrip() for r in rows]
    while rows and not rows[0].strip():
        rows.pop(0)
    while rows and not rows[-1].strip():
        rows.pop()
    h, w = len(raw), len(raw[0])
    keys = [(r, c) for r in range(h) for c in range(w) if rows[r][c] == "K"]
    if any("D" in r for r in rows) and not keys:
        raise LayoutError("layout has doors ('D') but no key ('K') to open them")
    top = [r.replace("K", ".").replace("D", "#") for r in rows]
    bottom = [r.replace("K", ".").replace("D", ".").replace("S", ".") for r in rows]
    off = h + 1  # the bottom copy starts below the separating wall row
    warps = [[[r, c], [off + r, c]] for r, c in keys]
    places = {}
    for i, (r, c) in enumerate(keys):
        places[f"key_{i}"] = [r, c]
        places[f"key_{i}_held"] = [off + r, c]

    def build(top_rows: list[str], bottom_rows: list[str]) -> World:
        return from_layout("\n".join([*top_rows, "#" * w, *bottom_rows]), warps=warps,
                           places=places, goal_reward=goal_reward, slip=slip,
                           reward_sd=reward_sd)  # fmt: skip

    # goals only where they can be reached (a goal behind a door is not, without the key)
    no_goals = build([r.replace("G", ".") for r in top], [r.replace("G", ".") for r in bottom])
    reach = no_goals.reachable()
    goals = [(r, c) for r in range(h) for c in range(w) if rows[r][c] == "G"]
    top = ["".join("." if ch == "G" and not reach[r * w + c] else ch for c, ch in enumerate(row))
           for r, row in enumerate(top)]  # fmt: skip
    bottom = ["".join("." if ch == "G" and not reach[(off + r) * w + c] else ch
                      for c, ch in enumerate(row)) for r, row in enumerate(bottom)]  # fmt: skip
    if len(goals) == 1:
        r, c = goals[0]
        if reach[r * w + c]:
            places["goal"] = [r, c]
        if reach[(off + r) * w + c]:
            places["goal_with_key"] = [off + r, c]
    starts = [(r, c) for r in range(h) for c in range(w) if rows[r][c] == "S"]
    if len(starts) == 1:
        places["start"] = list(starts[0])
    return build(top, bottom)


def open_field(
    width: int,
    height: int,
    *,
    starts: Iterable[StateRef] | None = None,
    goal: StateRef | None = None,
    goal_reward: float = 1.0,
) -> World:
    """An open rectangular field without inner walls.

    Parameters
    ----------
    width, height : int
        Grid size in cells.
    starts : list of states, optional
        Start states (default: every free, non-goal cell). Besides indices, place names and
        ``[row, col]``, the corners ``top_left``, ``top_right``, ``bottom_left`` and
        ``bottom_right`` name states here (so a config keeps its corners when the size is
        overridden).
    goal : state, optional
        Goal state (terminal, reward ``goal_reward``; a corner name as for ``starts``); none
        by default.
    goal_reward : float
        Reward on arriving at the goal.
    """
    width, height = int(width), int(height)
    if width < 1 or height < 1 or width * height < 2:
        raise LayoutError(f"open_field needs at least 2 cells, got {width} x {height}")
    check_world_memory("env.world", width, height, 0.0)
    corners = {"top_left": 0, "top_right": width - 1, "bottom_left": (height - 1) * width,
               "bottom_right": width * height - 1}  # fmt: skip

    def corner(ref: Any) -> Any:
        return corners.get(ref, ref) if isinstance(ref, str) else ref

    goal = corner(goal)
    if starts is not None and not isinstance(starts, str | int):
        starts = [corner(s) for s in starts]
    layout = "\n".join("." * width for _ in range(height))
    world = from_layout(layout, starts=[0], goal_reward=goal_reward)
    if goal is not None:
        g = world.state(goal)
        world.places["goal"] = g
        world.set_starts([s for s in range(world.n_states) if s != g] if starts is None else starts)
        world.set_rewards({g: goal_reward})
        world.set_terminal({g: True})
    else:
        world.set_starts(range(world.n_states) if starts is None else starts)
    return world


def t_maze(
    stem_length: int,
    arm_length: int,
    *,
    goal: str | None = "right",
    goal_reward: float = 1.0,
) -> World:
    """A T-maze: arms along the top row, stem down the middle column.

    The grid is ``(2 * arm_length + 1)`` wide and ``stem_length + 1`` high. The start is the
    bottom of the stem; both arm ends are terminal.

    Parameters
    ----------
    stem_length : int
        Stem cells below the junction (start included).
    arm_length : int
        Cells of each arm beside the junction.
    goal : {"right", "left", None}
        Arm end that pays ``goal_reward`` (None: neither).
    goal_reward : float
        Reward on arriving at the goal arm end.

    Returns
    -------
    World
        Places ``start``, ``junction``, ``left_arm``, ``right_arm``.
    """
    stem_length, arm_length = int(stem_length), int(arm_length)
    if stem_length < 1 or arm_length < 1:
        raise LayoutError(
            f"t_maze needs stem_length >= 1 and arm_length >= 1, got {stem_length}, {arm_length}"
        )
    if goal not in ("left", "right", None):
        raise ConfigError(
            f"t_maze goal must be one of 'left', 'right', None, got {goal!r}{suggest(str(goal), ['left', 'right'])}"
        )
    width = 2 * arm_length + 1
    side = "#" * arm_length
    rows = ["E" + "." * (width - 2) + "E"]
    rows += [side + "." + side for _ in range(stem_length - 1)]
    rows += [side + "S" + side]
    mid = arm_length
    start = stem_length * width + mid
    places = {"start": start, "junction": mid, "left_arm": 0, "right_arm": width - 1}
    rewards = {} if goal is None else {f"{goal}_arm": goal_reward}
    world = from_layout("\n".join(rows), places=places)
    world.set_rewards(rewards)
    return world


def tmaze_paper() -> World:
    """The 7 x 7 T-maze of the paper's Fig. 6B (``docs/paper-settings.md``).

    49 states, 12 reachable. Start 38; stem 38, 31, 24, 17, 10 up to the junction 3; arms
    0..6 along the top row. States 0 and 6 are terminal; reward 1 at state 6 (acquisition).
    Shortest path start -> arm end: 8 steps.
    """
    layout = """
        E.....G
        ###.###
        ###.###
        ###.###
        ###.###
        ###S###
        #######
    """
    return from_layout(
        layout,
        places={"start": 38, "junction": 3, "left_arm": 0, "right_arm": 6},
        goal_reward=1.0,
    )


#: Path of the Blodgett maze from start to goal (docs/paper-settings.md, Fig. 7).
BLODGETT_PATH: tuple[int, ...] = (24, 25, 17, 9, 10, 11, 19, 27, 28, 29, 21, 13, 14, 15)
#: Blind alleys: one dead-end cell at each of the six choice points (cell, its path cell).
BLODGETT_DEAD_ENDS: tuple[tuple[int, int], ...] = (
    (33, 25),
    (1, 9),
    (3, 11),
    (35, 27),
    (37, 29),
    (5, 13),
)
#: One-way doors: the move a -> b is blocked.
BLODGETT_DOORS: tuple[tuple[int, int], ...] = (
    (25, 24),
    (9, 17),
    (11, 10),
    (27, 19),
    (29, 28),
    (13, 21),
)


def _blodgett_walls() -> list[list[int]]:
    """Walls around every reachable cell except along the path and into the blind alleys."""
    width, height = 8, 5
    open_edges = {frozenset(p) for p in pairwise(BLODGETT_PATH)}
    open_edges |= {frozenset(p) for p in BLODGETT_DEAD_ENDS}
    inside = set(BLODGETT_PATH) | {d for d, _ in BLODGETT_DEAD_ENDS}
    walls: set[tuple[int, int]] = set()
    for s in inside:
        r, c = divmod(s, width)
        for _, dr, dc in ACTIONS:
            rr, cc = r + dr, c + dc
            if 0 <= rr < height and 0 <= cc < width:
                nxt = rr * width + cc
                if frozenset((s, nxt)) not in open_edges:
                    walls.add((min(s, nxt), max(s, nxt)))
    return [list(w) for w in sorted(walls)]


def blodgett(goal_reward: float = 0.0) -> World:
    """The Blodgett maze of the paper's Fig. 7 (``docs/paper-settings.md``).

    5 rows x 8 columns (40 states), start 24, goal 15 (terminal; reward ``goal_reward``,
    0 by default because the latent-learning protocol sets it). Six T-shaped units, each with
    a blind alley and a one-way door behind the choice point (blocked 25->24, 9->17, 11->10,
    27->19, 29->28, 13->21). 34 two-way walls leave 20 reachable states; the unique shortest
    path is 24, 25, 17, 9, 10, 11, 19, 27, 28, 29, 21, 13, 14, 15 (13 steps).

    Parameters
    ----------
    goal_reward : float
        Reward on arriving at the goal (default 0).
    """
    layout = "\n".join("." * 8 for _ in range(5))
    return from_layout(
        layout,
        walls=_blodgett_walls(),
        one_way=[list(d) for d in BLODGETT_DOORS],
        starts=[24],
        terminals=[15],
        rewards={15: goal_reward},
        places={"start": 24, "goal": 15},
    )
