"""Agents: one small base class, tabular agents with compiled trial loops, deep agents (lazy)."""

import importlib
from typing import Any

from cobelrun.agents.base import Agent, ArraySpec, Transition, TrialCallback
from cobelrun.agents.conditioning import RescorlaWagner, TDConditioning
from cobelrun.agents.dyna_q import DynaQ
from cobelrun.agents.memory import TabularMemory
from cobelrun.agents.pma import PMA
from cobelrun.agents.sfma import SFMA
from cobelrun.agents.successor import SRMB, SRTD, SRDyna, SuccessorCore, ValueIteration
from cobelrun.agents.td_control import (
    DynaActorCritic,
    MCControl,
    QLambda,
    Sarsa,
    SarsaLambda,
    TabularActorCritic,
)
from cobelrun.errors import CobelError

#: deep and episodic agents, imported on first use (torch / stable-baselines3 / scipy stay lazy)
_LAZY = {
    "DQNAgent": "cobelrun.agents.dqn",
    "DynaDQN": "cobelrun.agents.dyna_dqn",
    "DynaDSR": "cobelrun.agents.dyna_dsr",
    "MFEC": "cobelrun.agents.mfec",
}

__all__ = [
    "PMA",
    "SFMA",
    "SRMB",
    "SRTD",
    "SRDyna",
    "RescorlaWagner",
    "TDConditioning",
    "SuccessorCore",
    "ValueIteration",
    "DynaActorCritic",
    "MCControl",
    "QLambda",
    "Sarsa",
    "SarsaLambda",
    "TabularActorCritic",
    "Agent",
    "ArraySpec",
    "DynaQ",
    "TabularMemory",
    "Transition",
    "TrialCallback",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'cobelrun.agents' has no attribute {name!r}")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("torch", "stable_baselines3"):
            raise CobelError(
                f"agent {name} needs {exc.name}; install the deep extra: pip install 'cobelrun[deep]'"
            ) from None
        raise
    return getattr(mod, name)
