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
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.envs.world import World
from cobelrun.errors import ConfigError, allowed_list

DESIGNS = ("reward", "transition", "policy")
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
    ) -> None:
        from omegaconf import OmegaConf

        from cobelrun.config import validate_node

        if design not in DESIGNS:
            raise ConfigError(
                f"task.job.design {design!r} is not known; allowed: {allowed_list(DESIGNS)}"
            )
        self.design = design
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
        """Greedy start choice (1 = new best) after phase 1 and after phase 2 of one run."""
        from cobelrun.config import instantiate
        from cobelrun.envs import GridWorldEnv

        agent_seed, env_seed = np.random.SeedSequence(seed, spawn_key=(run,)).spawn(2)
        env = GridWorldEnv(revaluation_world())
        env.unwrapped.np_random = np.random.default_rng(env_seed)
        agent = instantiate("agent", node, env=env, seed=agent_seed)
        agent.train(self.training_trials, self.max_steps)
        before = start_choice(agent)
        apply_revaluation(env, self.design)
        agent.train(self.revaluation_trials, self.max_steps)
        return before, start_choice(agent)

    def table(self, seed: int, progress: Callable[..., None] | None = None) -> pd.DataFrame:
        """One row per (agent, budget, run): choices before and after the revaluation."""
        rows = []
        variants = self.variants()
        for i, (label, node, budget) in enumerate(variants):
            for run in range(self.runs):
                before, after = self.run_one(node, seed, run)
                rows.append({"design": self.design, "agent": label, "replay_budget": budget,
                             "run": run, "choice_before": before, "choice_after": after})  # fmt: skip
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
        return {"design": self.design,
                "scores": {f"{r.agent}@{r.replay_budget}": round(float(r.score), 3)
                           for r in scores.itertuples()}}  # fmt: skip
