"""Replay plots (Mattar & Daw 2018 style): steps per trial, replay direction, replays on the maze.

Functions take tables (``trials``, ``replays``, events from
:func:`cobelrun.analysis.replay.replay_events`) and a matplotlib ``ax``, never live objects.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from cobelrun.analysis.replay import direction_counts


def plot_steps_per_trial(trials: pd.DataFrame, ax: Any, label: str, color: str) -> pd.Series:
    """Median steps per trial across runs (interquartile range shaded); returns the medians."""
    g = trials.groupby("trial")["steps"]
    med, q25, q75 = g.median(), g.quantile(0.25), g.quantile(0.75)
    ax.plot(med.index, med.to_numpy(), color=color, label=label)
    ax.fill_between(med.index, q25.to_numpy(), q75.to_numpy(), color=color, alpha=0.2, lw=0)
    ax.set_yscale("log")
    ax.set_xlabel("trial")
    ax.set_ylabel("steps to goal")
    return med


def plot_direction(
    events: pd.DataFrame, n_trials: int, ax: Any, min_length: int = 5
) -> pd.DataFrame:
    """Forward and reverse events (>= ``min_length`` experiences) per trial, at trial start vs
    end (the authors' 'preplay' vs 'replay'); returns the counts per trial."""
    rate = direction_counts(events, min_length)[["forward", "reverse"]] / max(n_trials, 1)
    x = np.arange(2)
    ax.bar(x - 0.18, rate["forward"], 0.36, color="white", edgecolor="k", label="forward")
    ax.bar(x + 0.18, rate["reverse"], 0.36, color="k", edgecolor="k", label="reverse")
    ax.set_xticks(x, ["trial start", "trial end"])
    ax.set_ylabel("events per trial")
    ax.legend()
    return rate


def plot_replay_on_maze(world: Any, bout: pd.DataFrame, ax: Any, color: str = "tab:red") -> None:
    """The maze (walls grey), the agent (circle) and one bout's replayed experiences as arrows,
    shaded from light (first) to dark (last)."""
    grid = world.blocked.reshape(world.height, world.width).astype(float)
    ax.imshow(grid, cmap="Greys", vmin=0, vmax=1.6, origin="upper")
    rows, cols = np.divmod(np.arange(world.n_states), world.width)
    goal = np.flatnonzero(world.terminal & ~world.blocked)
    ax.scatter(cols[goal], rows[goal], marker="*", s=60, color="gold", zorder=3)
    n = len(bout)
    for k, (s, s2) in enumerate(zip(bout["state"], bout["next_state"], strict=True)):
        alpha = 0.3 + 0.7 * k / max(n - 1, 1)
        ax.annotate("", xy=(cols[s2], rows[s2]), xytext=(cols[s], rows[s]),
                    arrowprops={"arrowstyle": "->", "color": color, "alpha": alpha, "lw": 1.2})  # fmt: skip
    agent = int(bout["agent_state"].iloc[0])
    ax.scatter([cols[agent]], [rows[agent]], s=40, facecolor="none", edgecolor="b", zorder=3)
    ax.set_xticks([])
    ax.set_yticks([])


def plot_revaluation(scores: pd.DataFrame, design: str, ax: Any) -> pd.DataFrame:
    """Revaluation score per agent (and replay budget) for one design, as bars in [-1, 1]."""
    rows = scores[scores["design"] == design].copy()
    rows["label"] = [
        a if b < 0 else f"{a} ({b})"
        for a, b in zip(rows["agent"], rows["replay_budget"], strict=True)
    ]
    agents = list(dict.fromkeys(rows["agent"]))
    palette = {a: f"C{i}" for i, a in enumerate(agents)}
    x = np.arange(len(rows))
    ax.bar(x, rows["score"], color=[palette[a] for a in rows["agent"]])
    ax.set_xticks(x, rows["label"], rotation=70, ha="right")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_ylim(-0.1, 1.05)
    ax.set_title(f"{design} revaluation")
    return rows
