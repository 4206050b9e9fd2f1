"""Agents: one small base class, tabular agents with compiled trial loops, deep agents (lazy)."""

from cobelrun.agents.base import Agent, TrialCallback
from cobelrun.agents.dyna_q import DynaQ
from cobelrun.agents.memory import TabularMemory

__all__ = ["Agent", "DynaQ", "TabularMemory", "TrialCallback"]
