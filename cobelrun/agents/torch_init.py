"""Initial weights of torch networks by config name (``agent.init``), shared by the DQN agent
and its batched twin (:mod:`cobelrun.agents.batched_dqn`), which must draw the same."""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["INITS", "keras_init"]


def keras_init(net: torch.nn.Module) -> None:
    """Keras' layer defaults in place: Glorot-uniform weights, zero biases (dense and conv).

    The weights are drawn on the CPU (the generator the agent seeds) and copied to the
    network's device, so a network on CUDA starts from the same weights as on the CPU.
    """
    with torch.no_grad():
        for layer in net.modules():
            if isinstance(layer, torch.nn.Linear | torch.nn.Conv2d):
                w = torch.empty(layer.weight.shape, dtype=layer.weight.dtype)
                torch.nn.init.xavier_uniform_(w)
                layer.weight.copy_(w)
                if layer.bias is not None:
                    torch.nn.init.zeros_(layer.bias)


#: Q-network initialisations by config name: PyTorch's layer defaults (as built) or Keras'
INITS: dict[str, Callable[[torch.nn.Module], None]] = {
    "torch": lambda net: None,
    "keras": keras_init,
}
