"""The convolutional feature extractor of cobel's image DQNs (Fig. 6A, Fig. 8) and the
activation functions by config name, shared by the sequential agent
(:mod:`cobelrun.agents.dqn`) and the batched CNN learner (:mod:`cobelrun.agents.batched_cnn`).

Importing this module imports torch and stable-baselines3 (the ``deep`` extra).
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

__all__ = ["ACTIVATIONS", "DEFAULT_CONVS", "ConvFeatures"]

#: activation functions by config name
ACTIVATIONS: dict[str, type[torch.nn.Module]] = {
    "tanh": torch.nn.Tanh,
    "relu": torch.nn.ReLU,
    "elu": torch.nn.ELU,
    "sigmoid": torch.nn.Sigmoid,
    "linear": torch.nn.Identity,
}

#: Fig. 6A's convolutional stack: [channels, kernel, stride] per layer, then dense 256
DEFAULT_CONVS = ((16, 8, 4), (32, 4, 2))


class ConvFeatures(BaseFeaturesExtractor):
    """Convolutions ``[channels, kernel, stride]`` (ReLU), flattened, then a dense ReLU layer.

    Default: Fig. 6A's conv 16@8x8/4 -> conv 32@4x4/2 -> dense 256 (docs/paper-settings.md). ``padding``:
    ``"valid"`` (none, default) or ``"same"`` (Keras': zero padding so that a layer's output is
    ``ceil(input / stride)``; the original's Fig. 4 network, which also takes 16 x 16 images).
    ``dropout > 0`` adds dropout after the dense layer (Fig. 8: dense 50 ReLU -> dropout 0.35);
    the dense ReLU output is the ``analysis`` layer of :meth:`DQNAgent.activations`.
    """

    def __init__(
        self,
        observation_space: gym.spaces.Box,
        convs: Sequence[Sequence[int]] = DEFAULT_CONVS,
        features_dim: int = 256,
        padding: str = "valid",
        dropout: float = 0.0,
    ) -> None:
        super().__init__(observation_space, features_dim)
        layers: list[torch.nn.Module] = []
        channels, h, w = observation_space.shape
        for out, kernel, stride in convs:
            k, st = int(kernel), int(stride)
            if padding == "same":  # Keras/TensorFlow "same": extra padding goes right/bottom
                ph = max((-(-h // st) - 1) * st + k - h, 0)
                pw = max((-(-w // st) - 1) * st + k - w, 0)
                layers.append(torch.nn.ZeroPad2d((pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)))
                h, w = -(-h // st), -(-w // st)
            else:
                h, w = (h - k) // st + 1, (w - k) // st + 1
            layers += [torch.nn.Conv2d(channels, int(out), k, st), torch.nn.ReLU()]
            channels = int(out)
        layers.append(torch.nn.Flatten())
        self.cnn = torch.nn.Sequential(*layers)
        with torch.no_grad():
            n_flat = self.cnn(torch.zeros(1, *observation_space.shape)).shape[1]
        dense: list[torch.nn.Module] = [torch.nn.Linear(n_flat, features_dim), torch.nn.ReLU()]
        if dropout > 0:
            dense.append(torch.nn.Dropout(float(dropout)))
        self.linear = torch.nn.Sequential(*dense)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.linear(self.cnn(observations))
