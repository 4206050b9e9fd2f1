"""Gymnasium environments and tabular worlds.

Importing this package registers the environment ids ``cobel/GridWorld-v0`` and
``cobel/DiscreteGridWorld-v0``, ``cobel/Topology-v0``, ``cobel/TwoAFC-v0``,
``cobel/Continuous2D-v0`` (string entry points, registered once).
Without importing anything first,
``gymnasium.make("cobelrun.envs:cobel/GridWorld-v0")`` imports this package and makes the env.
:func:`register_envs` is also the package's ``gymnasium.envs`` entry point, which gymnasium
0.26-0.29 loaded at import; gymnasium >= 1.0 removed that loader, so there a bare
``cobel/...`` id needs this import. A task's env with its ``max_episode_steps`` from the
config: ``cobelrun.api.make_env("tmaze_extinction")``.
See docs/envs.md.
"""

from __future__ import annotations

from typing import Any

from cobelrun.envs.bandit import BanditEnv
from cobelrun.envs.choice import TwoAFCEnv
from cobelrun.envs.gridworld import DiscreteGridWorldEnv, GridWorldEnv
from cobelrun.envs.sequence import SequenceEnv
from cobelrun.envs.topology_env import TopologyEnv
from cobelrun.envs.world import (
    World,
    blodgett,
    from_layout,
    open_field,
    t_maze,
    tmaze_paper,
)

#: Environment ids registered by cobel, with their entry points.
ENV_IDS: dict[str, str] = {
    "cobel/GridWorld-v0": "cobelrun.envs.gridworld:GridWorldEnv",
    "cobel/DiscreteGridWorld-v0": "cobelrun.envs.gridworld:DiscreteGridWorldEnv",
    "cobel/Topology-v0": "cobelrun.envs.topology_env:TopologyEnv",
    "cobel/TwoAFC-v0": "cobelrun.envs.choice:TwoAFCEnv",
    "cobel/Bandit-v0": "cobelrun.envs.bandit:BanditEnv",
    "cobel/Sequence-v0": "cobelrun.envs.sequence:SequenceEnv",
    "cobel/Continuous2D-v0": "cobelrun.envs.continuous:Continuous2DEnv",
}


def register_envs() -> None:
    """Register cobel's environments with gymnasium (safe to call more than once).

    This is also the ``gymnasium.envs`` entry point of the package (``pyproject.toml``), which
    gymnasium 0.26-0.29 call while ``gymnasium`` itself is still being imported: hence the
    names come from ``gymnasium.envs.registration`` rather than the half-initialised
    ``gymnasium`` module.
    """
    from gymnasium.envs.registration import register, registry

    for env_id, entry_point in ENV_IDS.items():
        if env_id not in registry:
            register(id=env_id, entry_point=entry_point)


register_envs()


def __getattr__(name: str) -> Any:
    # the continuous arena imports numba and shapely: loaded on first use, so that building a
    # tabular agent (a sweep's launcher, config validation) stays free of the numba import
    if name == "Continuous2DEnv":
        from cobelrun.envs.continuous import Continuous2DEnv

        return Continuous2DEnv
    raise AttributeError(f"module 'cobelrun.envs' has no attribute {name!r}")


__all__ = [
    "ENV_IDS",
    "BanditEnv",
    "Continuous2DEnv",
    "DiscreteGridWorldEnv",
    "GridWorldEnv",
    "SequenceEnv",
    "TopologyEnv",
    "TwoAFCEnv",
    "World",
    "blodgett",
    "from_layout",
    "open_field",
    "register_envs",
    "t_maze",
    "tmaze_paper",
]
