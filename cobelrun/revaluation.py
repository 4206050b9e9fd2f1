"""Revaluation tasks of Russek et al. (2017), in the two-stage graph form of Momennejad et al. (2017).

One small tabular world (:func:`revaluation_world`), drawn as a graph::

    start --a0--> A --up--> end_A                 phase 1 rewards: end_A 10, end_B1 1, end_B2 0
          --a2--> B --up--> end_B1
                    --down--> pre_B2 --up--> end_B2

Phase 1 (training) starts each trial in a uniformly drawn non-terminal state (``start``, ``A``,
``B`` or ``pre_B2``), so that every branch is experienced; the agent learns to choose ``a0`` at
``start`` (towards ``end_A``). Phase 2 (revaluation) never starts at ``start``, so a changed preference there has to
come from the agent's representation or from replay:

* ``reward`` (latent learning): trials start at ``A`` or ``B``; rewards become end_A 1, end_B1 10;
* ``transition`` (detour): trials start at ``A`` or ``B``; ``A`` now leads to ``end_B1`` and
  ``B`` to ``end_A``;
* ``policy``: trials start at ``pre_B2``; ``end_B2`` pays 20, so the best policy at ``B`` changes
  from ``up`` to ``down``.

In all three the newly best first choice is ``a2``. **Revaluation score** (per agent): the
fraction of runs whose greedy choice at ``start`` (between ``a0`` and ``a2``, ties count 1/2) is
``a2`` after phase 2, minus the same fraction after phase 1. 1: every run revalues; 0: none does.

**Grid versions** (``maze: grid``, :data:`GRID_DESIGNS`), the gridworld designs of Russek et al.
(2017): the decisive choice lies several steps before the change, and the score is whether the
greedy path from the start reaches the new goal (:func:`greedy_reaches`):

* ``reward`` (latent learning): phase 1 explores a 7 x 7 maze without reward (random starts);
  phase 2 puts a reward of 10 on ``R`` (terminal) and starts next to it;
* ``transition`` (detour): phase 1 learns the short middle corridor to ``G`` (random starts; an
  upper corridor, entered from the start through a one-way door, also leads there); phase 2 walls
  the middle corridor off in front of ``B`` and starts the agent at ``B`` for one step;
* ``policy``: a 3 x 11 strip with ``A`` (10) at one end and ``B`` (5) at the other, the start
  nearer ``A``; phase 2 raises ``B`` to 20 and starts next to it for one step: the states between
  the start and ``B`` still point towards ``A``.

Score: per run, the share of greedy rollouts (ties broken at random) from the start in the
phase-2 world that reach the new goal within 1.5 x its shortest path, after phase 2 minus the
same before phase 2 (after phase 1).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.envs.world import World, from_layout
from cobelrun.errors import ConfigError, allowed_list

DESIGNS = ("reward", "transition", "policy")
MAZES = ("graph", "grid")
PLACES = {"start": 0, "A": 1, "B": 2, "end_A": 3, "end_B1": 4, "pre_B2": 5, "end_B2": 6}
OLD_BEST, NEW_BEST = 0, 2  # actions at start: a0 -> A, a2 -> B
LEFT, UP, RIGHT, DOWN = 0, 1, 2, 3


def _edges(swap: bool) -> dict[tuple[int, int], int]:
    p = PLACES
    return {
        (p["start"], LEFT): p["A"],
        (p["start"], RIGHT): p["B"],
        (p["A"], UP): p["end_B1"] if swap else p["end_A"],
        (p["B"], UP): p["end_A"] if swap else p["end_B1"],
        (p["B"], DOWN): p["pre_B2"],
        (p["pre_B2"], UP): p["end_B2"],
    }


def transitions(swap: bool = False) -> np.ndarray:
    """(7, 4, 7) transition table; actions without an edge leave the agent in place."""
    n = len(PLACES)
    T = np.zeros((n, 4, n))
    for s in range(n):
        for a in range(4):
            T[s, a, _edges(swap).get((s, a), s)] = 1.0
    return T


def revaluation_world() -> World:
    """The phase-1 world: start -> {A, B} -> ends, rewards end_A 10, end_B1 1, end_B2 0; trials
    start in any non-terminal state."""
    p = PLACES
    n = len(p)
    rewards = np.zeros(n)
    rewards[p["end_A"]], rewards[p["end_B1"]] = 10.0, 1.0
    terminal = np.zeros(n, bool)
    terminal[[p["end_A"], p["end_B1"], p["end_B2"]]] = True
    coords = np.array([[0, 1], [1, 2], [1, 0], [2, 2], [2, 1], [2, -1], [3, -1]], float)
    return World(width=n, height=1, T=transitions(), rewards=rewards, terminal=terminal,
                 starts=[p["start"], p["A"], p["B"], p["pre_B2"]], coords=coords, blocked=np.zeros(n, bool),
                 places=dict(p))  # fmt: skip


def apply_revaluation(env: Any, design: str) -> None:
    """Phase 2's changes to a :func:`revaluation_world` environment."""
    base = env.unwrapped
    if design == "reward":
        base.apply_changes(rewards={"end_A": 1.0, "end_B1": 10.0}, starts=["A", "B"])
    elif design == "transition":
        base.world.T = transitions(swap=True)
        base.apply_changes(starts=["A", "B"])
    elif design == "policy":
        base.apply_changes(rewards={"end_B2": 20.0}, starts=["pre_B2"])
    else:
        raise ConfigError(
            f"revaluation design {design!r} is not known; allowed: {allowed_list(DESIGNS)}"
        )


def start_choice(agent: Any) -> float:
    """1 if the agent's greedy choice at start is the new best (a2), 0 if a0, 0.5 on a tie."""
    q = np.asarray(agent.predict(np.array([PLACES["start"]])))[0]
    if q[NEW_BEST] == q[OLD_BEST]:
        return 0.5
    return float(q[NEW_BEST] > q[OLD_BEST])


# ---------------------------------------------------------------------------- grid designs
@dataclass(frozen=True)
class GridDesign:
    """A revaluation in a gridworld: the phase-1 world, the phase-2 changes, the test.

    Attributes
    ----------
    layout, places, rewards, terminals, one_way
        The phase-1 world (:func:`~cobelrun.envs.world.from_layout`).
    start_share
        Share of phase-1 trials that begin at ``start`` (the others: every free non-terminal
        cell alike), so that the route from the start is learned.
    rewards_2, terminals_2, starts_2, walls_2
        Phase 2: new rewards, terminal flags, starts and walls.
    trials, max_steps
        ``(phase 1, phase 2)`` trial counts and step limits.
    start, goal
        The test: greedy rollouts from ``start`` must reach ``goal``.
    """

    layout: str
    places: dict[str, tuple[int, int]]
    trials: tuple[int, int]
    max_steps: tuple[int, int]
    start: str
    goal: str
    rewards: dict[str, float] = field(default_factory=dict)
    terminals: tuple[str, ...] = ()
    one_way: tuple[tuple[str, str], ...] = ()
    start_share: float = 0.0
    rewards_2: dict[str, float] = field(default_factory=dict)
    terminals_2: dict[str, bool] = field(default_factory=dict)
    starts_2: tuple[str, ...] = ()
    walls_2: tuple[tuple[str, str], ...] = ()

    def world(self, phase: int = 1) -> World:
        """The world of phase 1 (or, with ``phase=2``, with phase 2's walls)."""
        places = {k: list(v) for k, v in self.places.items()}
        w = from_layout(self.layout, places=places, goal_reward=0.0, rewards=self.rewards,
                        terminals=list(self.terminals) or None,
                        one_way=[list(p) for p in self.one_way],
                        walls=[list(p) for p in self.walls_2] if phase == 2 else ())  # fmt: skip
        cells = np.flatnonzero(~w.blocked & ~w.terminal).tolist()
        extra = round(self.start_share / (1.0 - self.start_share) * len(cells))
        w.set_starts(cells + [w.state(self.start)] * extra)  # reset draws uniformly over these
        return w

    def apply(self, env: Any) -> None:
        """Phase 2's changes to an environment built on :meth:`world`."""
        base = env.unwrapped
        if self.walls_2:
            base.world.T = self.world(2).T
        base.apply_changes(starts=list(self.starts_2))  # first: a new terminal may be a start
        base.apply_changes(rewards=self.rewards_2 or None, terminals=self.terminals_2 or None)


#: Russek et al. (2017)'s three revaluations as gridworlds (see the module docstring)
GRID_DESIGNS: dict[str, GridDesign] = {
    "reward": GridDesign(
        layout="""
            S.....#
            .####.#
            .#....#
            .#.####
            .#.....
            .####..
            .......
        """,
        places={"start": (0, 0), "R": (6, 6), "R_up": (5, 6), "R_left": (6, 5)},
        trials=(100, 20),
        max_steps=(50, 5),
        start="start",
        goal="R",
        rewards_2={"R": 10.0},
        terminals_2={"R": True},
        starts_2=("R_up", "R_left"),
    ),
    "transition": GridDesign(
        layout="""
            .........
            .#######.
            S.......G
        """,
        places={"start": (2, 0), "goal": (2, 8), "B": (2, 4), "C": (2, 5), "door": (1, 0)},
        rewards={"goal": 10.0},
        one_way=(("door", "start"),),
        start_share=0.5,
        trials=(400, 20),
        max_steps=(30, 1),
        start="start",
        goal="goal",
        starts_2=("B",),
        walls_2=(("B", "C"),),
    ),
    "policy": GridDesign(
        layout="""
            ...........
            ....S......
            ...........
        """,
        places={"start": (1, 4), "A": (1, 0), "B": (1, 10), "B_left": (1, 9)},
        rewards={"A": 10.0, "B": 5.0},
        terminals=("A", "B"),
        start_share=0.5,
        trials=(400, 20),
        max_steps=(30, 1),
        start="start",
        goal="B",
        rewards_2={"B": 20.0},
        starts_2=("B_left",),
    ),
}


def greedy_reaches(
    agent: Any, world: World, start: int, goal: int, rng: np.random.Generator, rollouts: int = 10
) -> float:
    """Share of ``rollouts`` greedy walks (ties broken at random by ``rng``) from ``start``
    that reach ``goal`` within 1.5 x its shortest path in ``world``; a walk stops at any
    terminal state. The agent is only asked for its values (``predict``)."""
    nxt = world.next_state
    if nxt is None:
        raise ConfigError("revaluation: the grid designs need a deterministic world")
    shortest = int(world.distances([start])[goal])
    limit = int(np.ceil(1.5 * shortest))
    Q = np.asarray(agent.predict(np.arange(world.n_states)))
    hits = 0
    for _ in range(rollouts):
        s = start
        for _ in range(limit):
            best = np.flatnonzero(Q[s] == Q[s].max())
            s = int(nxt[s, best[rng.integers(best.size)] if best.size > 1 else best[0]])
            if world.terminal[s]:
                break
        hits += int(s == goal)
    return hits / rollouts


class RevaluationJob:
    """``task.job`` of the revaluation tasks: every agent x replay budget x run, one table.

    Parameters
    ----------
    design
        ``reward``, ``transition`` or ``policy``.
    agents
        Label -> agent config (``_target_`` node; ``env`` and ``seed`` are provided).
    runs
        Independent runs per agent and budget (seeds derived from the one ``seed``).
    training_trials, revaluation_trials, max_steps
        Trials of phase 1 and phase 2 and the per-trial step limit.
    replay_budgets
        Values of ``replay_batch`` tried for agents that replay (Dyna-Q, SR-Dyna).
    maze
        ``graph`` (the two-stage graph; the trial counts and step limit above apply) or
        ``grid`` (Russek et al.'s gridworld designs, :data:`GRID_DESIGNS`, with their own trial
        counts and step limits).
    """

    def __init__(
        self,
        design: str,
        agents: Mapping[str, Any],
        runs: int = 20,
        training_trials: int = 200,
        revaluation_trials: int = 20,
        max_steps: int = 10,
        replay_budgets: list[int] | tuple[int, ...] = (10,),
        maze: str = "graph",
    ) -> None:
        from omegaconf import OmegaConf

        from cobelrun.config import validate_node

        if design not in DESIGNS:
            raise ConfigError(
                f"task.job.design {design!r} is not known; allowed: {allowed_list(DESIGNS)}"
            )
        self.design = design
        if maze not in MAZES:
            raise ConfigError(
                f"task.job.maze {maze!r} is not known; allowed: {allowed_list(MAZES)}"
            )
        self.maze = maze
        if OmegaConf.is_config(agents):
            agents = OmegaConf.to_container(agents, resolve=True)
        self.agents = {str(k): dict(v) for k, v in (agents or {}).items() if v is not None}
        if not self.agents:
            raise ConfigError("task.job.agents is empty; give at least one agent config")
        for label, node in self.agents.items():
            node.pop("load_from", None)
            validate_node(f"task.job.agents.{label}", node, provided=["env", "seed"])
        for name, value in (("runs", runs), ("training_trials", training_trials),
                            ("revaluation_trials", revaluation_trials), ("max_steps", max_steps)):  # fmt: skip
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"task.job.{name} must be an integer >= 1, got {value!r}")
        budgets = list(OmegaConf.to_container(replay_budgets) if OmegaConf.is_config(replay_budgets)
                       else replay_budgets)  # fmt: skip
        if not budgets or any(
            isinstance(b, bool) or not isinstance(b, int) or b < 0 for b in budgets
        ):
            raise ConfigError(f"task.job.replay_budgets must be integers >= 0, got {budgets!r}")
        self.runs, self.budgets = runs, budgets
        self.training_trials, self.revaluation_trials = training_trials, revaluation_trials
        self.max_steps = max_steps

    def variants(self) -> list[tuple[str, dict[str, Any], int | None]]:
        """(agent label, config, replay budget or None) for every agent and budget."""
        out = []
        for label, node in self.agents.items():
            if "replay_batch" in node and node.get("replay", "step") != "off":
                out += [(label, {**node, "replay_batch": b}, b) for b in self.budgets]
            else:
                out.append((label, node, None))
        return out

    def run_one(self, node: dict[str, Any], seed: int, run: int) -> tuple[float, float]:
        """The test after phase 1 and after phase 2 of one run: the greedy choice at the start
        (graph; 1 = new best) or the share of greedy paths reaching the new goal (grid)."""
        from cobelrun.config import instantiate
        from cobelrun.envs import GridWorldEnv

        agent_seed, env_seed = np.random.SeedSequence(seed, spawn_key=(run,)).spawn(2)
        if self.maze == "grid":
            grid = GRID_DESIGNS[self.design]
            env = GridWorldEnv(grid.world())
            test_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(run, 1)))
        else:
            env = GridWorldEnv(revaluation_world())
        env.unwrapped.np_random = np.random.default_rng(env_seed)
        agent = instantiate("agent", node, env=env, seed=agent_seed)
        if self.maze == "graph":
            agent.train(self.training_trials, self.max_steps)
            before = start_choice(agent)
            apply_revaluation(env, self.design)
            agent.train(self.revaluation_trials, self.max_steps)
            return before, start_choice(agent)
        agent.train(grid.trials[0], grid.max_steps[0])
        grid.apply(env)
        world = env.unwrapped.world
        start, goal = world.state(grid.start), world.state(grid.goal)
        before = greedy_reaches(agent, world, start, goal, test_rng)
        agent.train(grid.trials[1], grid.max_steps[1])
        return before, greedy_reaches(agent, world, start, goal, test_rng)

    def table(self, seed: int, progress: Callable[..., None] | None = None) -> pd.DataFrame:
        """One row per (agent, budget, run): choices before and after the revaluation."""
        rows = []
        variants = self.variants()
        for i, (label, node, budget) in enumerate(variants):
            for run in range(self.runs):
                before, after = self.run_one(node, seed, run)
                rows.append({"design": self.design, "maze": self.maze, "agent": label,
                             "replay_budget": budget, "run": run, "choice_before": before,
                             "choice_after": after})  # fmt: skip
            if progress is not None:
                progress(i + 1, len(variants))
        return pd.DataFrame(rows)

    def __call__(
        self, cfg: Any, run_dir: Path, progress: Callable[..., None] | None = None
    ) -> dict:
        from cobelrun.analysis.revaluation import revaluation_scores

        table = self.table(int(cfg.seed), progress)
        table.to_csv(Path(run_dir) / "revaluation.csv", index=False)
        scores = revaluation_scores(table)
        scores.to_csv(Path(run_dir) / "revaluation_scores.csv", index=False)
        return {"design": self.design, "maze": self.maze,
                "scores": {f"{r.agent}@{r.replay_budget}": round(float(r.score), 3)
                           for r in scores.itertuples()}}  # fmt: skip
