"""Replay events: sequences in the ``replays`` table, their direction, length and distance.

A replay *bout* is every backup an agent made at one moment (one ``run, trial, when``). Inside a
bout, consecutive replayed experiences ``e_i = (s_i, a_i, s'_i)`` and ``e_{i+1}`` are matched
(Mattar & Daw 2018, ``genFig_FvsR_openMaze.m``):

* forward if ``s'_i == s_{i+1}`` (the next experience continues where this one ends);
* reverse if ``s'_{i+1} == s_i`` (the next experience ends where this one starts);
* otherwise the sequence breaks.

An *event* is a maximal run of matched experiences. Its direction is ``forward`` or
``reverse`` if all its pairs agree, ``mixed`` if both kinds occur (a single experience is
``none``). Events are usually counted from a minimum length on (the authors: 5 experiences).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

BOUT_KEYS = ["run", "trial", "when"]


def _pair_codes(state: np.ndarray, next_state: np.ndarray) -> np.ndarray:
    """Code of each consecutive pair: 1 forward, -1 reverse, 0 neither (forward wins ties)."""
    fwd = next_state[:-1] == state[1:]
    rev = next_state[1:] == state[:-1]
    return np.where(fwd, 1, np.where(rev, -1, 0))


def split_events(state: np.ndarray, next_state: np.ndarray) -> list[tuple[int, int, str]]:
    """The events of one bout: ``(first, last, direction)`` per maximal run of matched
    consecutive experiences (positions inclusive), direction ``forward``, ``reverse``,
    ``mixed`` or ``none`` (a single experience)."""
    s, s2 = np.asarray(state), np.asarray(next_state)
    codes = _pair_codes(s, s2)
    out, start = [], 0
    for i in range(len(s)):
        if i == len(s) - 1 or codes[i] == 0:
            seg = codes[start:i]
            nf, nr = int((seg == 1).sum()), int((seg == -1).sum())
            direction = (
                "none" if nf + nr == 0 else "forward" if nr == 0 else "reverse" if nf == 0
                else "mixed"
            )  # fmt: skip
            out.append((start, i, direction))
            start = i + 1
    return out


def event_path(state: np.ndarray, next_state: np.ndarray, direction: str) -> list[np.ndarray]:
    """The states an event runs through, in the order they were replayed: a forward event
    ``s_1, s'_1, s'_2, ...``, a reverse one ``s'_1, s_1, s_2, ...``; a mixed (or single)
    event gives one ``[s_k, s'_k]`` pair per experience."""
    s, s2 = np.asarray(state, np.int64), np.asarray(next_state, np.int64)
    if direction == "forward":
        return [np.concatenate([s[:1], s2])]
    if direction == "reverse":
        return [np.concatenate([s2[:1], s])]
    return [np.array([a, b], np.int64) for a, b in zip(s.tolist(), s2.tolist(), strict=True)]


def replay_events(replays: pd.DataFrame, distances: np.ndarray | None = None) -> pd.DataFrame:
    """One row per replay event (a maximal sequence of matched consecutive experiences).

    Parameters
    ----------
    replays
        The ``replays`` table (columns ``run, trial, when, index, agent_state, state,
        next_state``), in the order the backups were made.
    distances
        Optional (S, S) matrix of path distances (steps) between states; given, each event gets
        ``distance``: steps from the agent's state to the nearest state the event visits.

    Returns
    -------
    pandas.DataFrame
        ``run, trial, when, agent_state, first, start_state, end_state, length`` (experiences),
        ``n_forward, n_reverse`` (matched pairs), ``direction`` (``forward``, ``reverse``,
        ``mixed``, ``none``) and ``distance`` (if ``distances`` is given). ``first`` is the
        event's first position in its bout.
    """
    cols = ["run", "trial", "when", "agent_state", "first", "start_state", "end_state",
            "length", "n_forward", "n_reverse", "direction"]  # fmt: skip
    if distances is not None:
        cols.append("distance")
    if replays.empty:
        return pd.DataFrame({c: [] for c in cols})
    df = replays.sort_values([*BOUT_KEYS, "index"], kind="stable")
    rows = []
    for (run, trial, when), bout in df.groupby(BOUT_KEYS, sort=False):
        s = bout["state"].to_numpy()
        s2 = bout["next_state"].to_numpy()
        agent = int(bout["agent_state"].iloc[0])
        codes = _pair_codes(s, s2)
        for start, i, direction in split_events(s, s2):
            seg = codes[start:i]
            nf, nr = int((seg == 1).sum()), int((seg == -1).sum())
            row = [int(run), int(trial), str(when), agent, start, int(s[start]),
                   int(s2[i]), i - start + 1, nf, nr, direction]  # fmt: skip
            if distances is not None:
                visited = np.concatenate([s[start : i + 1], s2[start : i + 1]])
                row.append(int(distances[agent, visited].min()))
            rows.append(row)
    return pd.DataFrame(rows, columns=cols)


def direction_counts(events: pd.DataFrame, min_length: int = 5) -> pd.DataFrame:
    """Events of at least ``min_length`` experiences per ``when`` x ``direction``.

    Returns a table indexed by ``when`` (``start``, ``end``) with one column per direction
    (``forward``, ``reverse``, ``mixed``), zeros where none occurred.
    """
    long = events[events["length"] >= min_length]
    table = long.groupby(["when", "direction"]).size().unstack(fill_value=0)
    return table.reindex(
        index=["start", "end"], columns=["forward", "reverse", "mixed"], fill_value=0
    )


def state_distances(next_state: np.ndarray) -> np.ndarray:
    """(S, S) shortest-path steps between states of a deterministic (S, A) successor table
    (``world.next_state``); -1 where unreachable."""
    n = next_state.shape[0]
    dist = np.full((n, n), -1, np.int64)
    for src in range(n):
        dist[src, src] = 0
        frontier = [src]
        d = 0
        while frontier:
            d += 1
            nxt = []
            for u in frontier:
                for v in next_state[u]:
                    if dist[src, v] < 0:
                        dist[src, v] = d
                        nxt.append(int(v))
            frontier = nxt
    return dist
