"""Which batched learner a DQN's runs get (:mod:`cobelrun.agents.batched_dqn` for MLPs,
:mod:`cobelrun.agents.batched_cnn` for image DQNs), whether they can be batched at all, and
whether ``task.batch_runs=auto`` declines: the entry points :class:`~cobelrun.agents.dqn.DQNAgent`
calls (a module of its own so that neither learner imports the other or the agent).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cobelrun.agents.batched_cnn import BatchedCNNDQN, cnn_unsupported
from cobelrun.agents.batched_cnn import auto_declines as cnn_auto_declines
from cobelrun.agents.batched_dqn import BatchedDQN, mlp_unsupported

__all__ = ["auto_declines", "make_batched", "unsupported"]


def unsupported(agent: Any) -> str | None:
    """Why ``agent`` (a built :class:`~cobelrun.agents.dqn.DQNAgent`) cannot be batched, or
    None (image DQNs: :func:`cobelrun.agents.batched_cnn.cnn_unsupported`)."""
    if agent.hyper["policy"] == "CnnPolicy":
        return cnn_unsupported(agent)
    return mlp_unsupported(agent)


def make_batched(
    template: Any, seeds: Sequence[np.random.SeedSequence], capacity: int, device: str = "cpu"
) -> BatchedDQN:
    """The batched learner of ``template``'s network: :class:`BatchedDQN` (MLP) or
    :class:`~cobelrun.agents.batched_cnn.BatchedCNNDQN` (``CnnPolicy``)."""
    if template.hyper["policy"] == "CnnPolicy":
        return BatchedCNNDQN(template, seeds, capacity=capacity, device=device)
    return BatchedDQN(template, seeds, capacity=capacity, device=device)


def auto_declines(agent: Any) -> str | None:
    """Why ``task.batch_runs=auto`` keeps a batchable DQN's runs sequential (measured not to
    pay: :func:`cobelrun.agents.batched_cnn.auto_declines`), or None."""
    if agent.hyper["policy"] == "CnnPolicy":
        return cnn_auto_declines(agent)
    return None
