"""Function approximators for the deep Dyna agents, behind a small backend-neutral interface.

CoBeL-RL kept the network of its hybrid agents behind an abstract class so that a Tensorflow or
a PyTorch model could be plugged in (paper, section 2.1.3). :class:`Network` is that interface;
:class:`TorchMLP` the PyTorch implementation. A network has ``n_heads`` independent heads of the
same shape (Dyna-DSR keeps one successor-feature network per action); all heads are evaluated
together with batched matrix products, so four "separate" networks cost one forward pass.

Another backend implements :class:`Network` and registers a factory in :data:`BACKENDS`.
"""

from __future__ import annotations

import abc
import itertools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from cobelrun.agents.base import layer_sizes
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.safety import check_allocation

ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "tanh": torch.tanh,
    "relu": torch.relu,
    "sigmoid": torch.sigmoid,
    "elu": torch.nn.functional.elu,
    "linear": lambda x: x,
}


#: float32 copies a trained weight has: itself, its gradient, Adam's two moments, and the
#: temporary of its initialisation
BYTES_PER_PARAMETER_COPY = 5


def set_torch_threads(n: int | None) -> None:
    """Use ``n`` intra-op threads (None: leave torch's setting). cobel's default is 1."""
    if n is not None:
        if n < 1:
            raise ConfigError(f"agent.torch_threads must be >= 1 or null, got {n}")
        torch.set_num_threads(int(n))


class Network(abc.ABC):
    """A (multi-head) regression network trained with MSE.

    Shapes: inputs ``x`` are ``(n, input_dim)``; outputs are ``(n_heads, n, output_dim)``.
    """

    n_heads: int
    input_dim: int
    output_dim: int

    @abc.abstractmethod
    def predict(self, x: np.ndarray) -> np.ndarray:
        """Outputs of every head, ``(n_heads, n, output_dim)``."""

    @abc.abstractmethod
    def train_step(
        self,
        x: np.ndarray,
        targets: np.ndarray,
        heads: np.ndarray | None = None,
        columns: np.ndarray | None = None,
    ) -> float:
        """One gradient step on the mean squared error; returns the loss.

        Sample ``i`` trains head ``heads[i]`` (default 0). ``targets`` is ``(n, output_dim)``, or
        ``(n,)`` with ``columns`` naming the one output of each sample that is trained (the
        others keep their prediction as target, as keras-style Q updates do).
        """

    @abc.abstractmethod
    def clone(self) -> Network:
        """An independent copy (e.g. the target network)."""

    @abc.abstractmethod
    def blend_from(self, other: Network, tau: float) -> None:
        """Soft update ``self <- tau * other + (1 - tau) * self``."""

    @abc.abstractmethod
    def get_weights(self) -> dict[str, np.ndarray]:
        """All parameters as named arrays."""

    @abc.abstractmethod
    def set_weights(self, weights: dict[str, np.ndarray]) -> None:
        """Restore parameters written by :meth:`get_weights`."""

    def optimizer_state(self) -> dict[str, np.ndarray]:
        """The optimiser's state as named arrays (checkpoints; default: none)."""
        return {}

    def optimizer_schema(self) -> dict[str, tuple[tuple[int, ...], bool]]:
        """Shape and non-negativity of every array of :meth:`optimizer_state`."""
        return {}

    def set_optimizer_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore :meth:`optimizer_state` (shapes already checked)."""
        return None  # a hook: nothing by default

    @abc.abstractmethod
    def layer_names(self) -> list[str]:
        """Names accepted by :meth:`activations`."""

    @abc.abstractmethod
    def activations(self, x: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        """Layer outputs ``(n, n_heads * units)`` for the named layers."""


class TorchMLP(Network):
    """Dense network ``input -> hidden... -> output`` per head, Adam, MSE (PyTorch).

    Parameters
    ----------
    input_dim, output_dim
        Sizes of the input and output vectors.
    hidden
        Hidden layer sizes (Fig. 7: [64, 64]); ``[]`` gives a linear model.
    activation
        Hidden-layer activation (tanh, relu, sigmoid, elu, linear).
    n_heads
        Number of independent networks of this shape.
    learning_rate
        Adam learning rate.
    bias
        Whether layers have biases.
    seed
        Seed of the weight initialisation (PyTorch's default init, from a private generator).
    """

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        hidden: Sequence[int] = (64, 64),
        activation: str = "tanh",
        n_heads: int = 1,
        learning_rate: float = 1e-3,
        bias: bool = True,
        seed: int | None = None,
    ) -> None:
        if activation not in ACTIVATIONS:
            raise ConfigError(
                f"activation {activation!r} is not known{suggest(activation, list(ACTIVATIONS))}; "
                f"allowed: {allowed_list(list(ACTIVATIONS))}"
            )
        self.input_dim, self.output_dim, self.n_heads = int(input_dim), int(output_dim), n_heads
        self.hidden = layer_sizes("agent.hidden", hidden)
        self.activation = activation
        self.act = ACTIVATIONS[activation]
        self.learning_rate = float(learning_rate)
        self.bias = bool(bias)
        sizes = [self.input_dim, *self.hidden, self.output_dim]
        n_params = n_heads * sum((a + 1) * b for a, b in itertools.pairwise(sizes))
        check_allocation("agent.hidden", n_params * 4 * BYTES_PER_PARAMETER_COPY,
                         f"a network of {n_params:,} weights ({' x '.join(map(str, sizes))}, "
                         "with gradients and Adam's moments)", "use smaller agent.hidden layers")  # fmt: skip
        gen = torch.Generator().manual_seed(int(seed) if seed is not None else 0)
        self.weights: list[torch.Tensor] = []
        self.biases: list[torch.Tensor | None] = []
        for fan_in, fan_out in itertools.pairwise(sizes):
            bound = 1.0 / np.sqrt(fan_in)  # torch.nn.Linear's default (Kaiming-uniform, a=sqrt 5)
            w = (torch.rand(n_heads, fan_in, fan_out, generator=gen) * 2 - 1) * bound
            self.weights.append(w.requires_grad_())
            if bias:
                b = (torch.rand(n_heads, 1, fan_out, generator=gen) * 2 - 1) * bound
                self.biases.append(b.requires_grad_())
            else:
                self.biases.append(None)
        self.optimizer = torch.optim.Adam(self.parameters(), lr=self.learning_rate, foreach=True)

    def parameters(self) -> list[torch.Tensor]:
        return [*self.weights, *(b for b in self.biases if b is not None)]

    # -- forward -------------------------------------------------------------------------
    def _forward(
        self, x: torch.Tensor, keep: dict[str, torch.Tensor] | None = None
    ) -> torch.Tensor:
        h = x.unsqueeze(0).expand(self.n_heads, -1, -1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.bmm(h, w) if b is None else torch.baddbmm(b, h, w)
            if i < last:
                h = self.act(h)
                if keep is not None:
                    keep[f"layer{i + 1}"] = h
        if keep is not None:
            keep["output"] = h
        return h

    @staticmethod
    def _tensor(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.array(x, dtype=np.float32))  # a writable copy

    def predict(self, x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self._forward(self._tensor(x)).numpy()

    def train_step(
        self,
        x: np.ndarray,
        targets: np.ndarray,
        heads: np.ndarray | None = None,
        columns: np.ndarray | None = None,
    ) -> float:
        xt = self._tensor(x)
        out = self._forward(xt)  # (H, n, out)
        n = xt.shape[0]
        rows = torch.arange(n)
        pred = out[0] if heads is None else out[torch.as_tensor(heads, dtype=torch.long), rows]
        target = self._tensor(targets)
        if columns is not None:
            pred = pred[rows, torch.as_tensor(columns, dtype=torch.long)]
            # keras-style full-vector MSE: the untrained outputs contribute zero error
            loss = ((pred - target) ** 2).sum() / (n * self.output_dim)
        else:
            loss = ((pred - target) ** 2).mean()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())

    # -- copies and weights ---------------------------------------------------------------
    def clone(self) -> TorchMLP:
        new = TorchMLP(self.input_dim, self.output_dim, self.hidden, self.activation,
                       self.n_heads, self.learning_rate, self.bias)  # fmt: skip
        new.set_weights(self.get_weights())
        return new

    def blend_from(self, other: Network, tau: float) -> None:
        assert isinstance(other, TorchMLP)
        with torch.no_grad():
            torch._foreach_lerp_(self.parameters(), other.parameters(), float(tau))

    def get_weights(self) -> dict[str, np.ndarray]:
        out = {f"w{i}": w.detach().numpy().copy() for i, w in enumerate(self.weights)}
        for i, b in enumerate(self.biases):
            if b is not None:
                out[f"b{i}"] = b.detach().numpy().copy()
        return out

    def set_weights(self, weights: dict[str, np.ndarray]) -> None:
        mine = self.get_weights()
        for key, arr in mine.items():
            if key not in weights or np.shape(weights[key]) != arr.shape:
                got = np.shape(weights[key]) if key in weights else "missing"
                raise ConfigError(f"network weight {key}: expected shape {arr.shape}, got {got}")
        with torch.no_grad():
            for i, w in enumerate(self.weights):
                w.copy_(torch.as_tensor(weights[f"w{i}"]))
            for i, b in enumerate(self.biases):
                if b is not None:
                    b.copy_(torch.as_tensor(weights[f"b{i}"]))

    # -- optimiser state (checkpoints) ----------------------------------------------------
    # Adam's step count and moments per parameter, in parameters() order. A parameter Adam has
    # not stepped yet is saved as step 0 with zero moments: the state Adam starts from.
    def optimizer_schema(self) -> dict[str, tuple[tuple[int, ...], bool]]:
        out: dict[str, tuple[tuple[int, ...], bool]] = {}
        for i, p in enumerate(self.parameters()):
            out[f"{i}.step"] = ((), True)
            out[f"{i}.exp_avg"] = (tuple(p.shape), False)
            out[f"{i}.exp_avg_sq"] = (tuple(p.shape), True)
        return out

    def optimizer_state(self) -> dict[str, np.ndarray]:
        state = self.optimizer.state_dict()["state"]
        out: dict[str, np.ndarray] = {}
        for i, p in enumerate(self.parameters()):
            st = state.get(i, {})
            out[f"{i}.step"] = np.array(float(st.get("step", 0.0)), np.float32)
            for key in ("exp_avg", "exp_avg_sq"):
                value = st.get(key)
                out[f"{i}.{key}"] = (
                    np.zeros(tuple(p.shape), np.float32)
                    if value is None
                    else value.detach().numpy().copy()
                )
        return out

    def set_optimizer_state(self, arrays: dict[str, np.ndarray]) -> None:
        state = {
            i: {
                "step": torch.tensor(float(arrays[f"{i}.step"]), dtype=torch.float32),
                "exp_avg": torch.tensor(np.asarray(arrays[f"{i}.exp_avg"], np.float32)),
                "exp_avg_sq": torch.tensor(np.asarray(arrays[f"{i}.exp_avg_sq"], np.float32)),
            }
            for i in range(len(self.parameters()))
        }
        groups = self.optimizer.state_dict()["param_groups"]
        self.optimizer.load_state_dict({"state": state, "param_groups": groups})

    # -- introspection --------------------------------------------------------------------
    def layer_names(self) -> list[str]:
        return [*(f"layer{i + 1}" for i in range(len(self.hidden))), "output"]

    def activations(self, x: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        unknown = [name for name in layers if name not in self.layer_names()]
        if unknown:
            raise ConfigError(f"unknown layer(s) {unknown}; allowed: {self.layer_names()}")
        keep: dict[str, torch.Tensor] = {}
        with torch.no_grad():
            self._forward(self._tensor(x), keep)
        out = {}
        for name in layers:
            h = keep[name]  # (H, n, units) -> (n, H * units)
            out[name] = h.permute(1, 0, 2).reshape(h.shape[1], -1).numpy()
        return out


#: network backends by config name: factory(input_dim, output_dim, **kwargs) -> Network
BACKENDS: dict[str, Callable[..., Network]] = {"torch": TorchMLP}


def build_network(backend: str, input_dim: int, output_dim: int, **kwargs: Any) -> Network:
    """Build a network of the named backend."""
    if backend not in BACKENDS:
        raise ConfigError(
            f"agent.backend {backend!r} is not known{suggest(backend, list(BACKENDS))}; "
            f"allowed: {allowed_list(list(BACKENDS))}"
        )
    return BACKENDS[backend](input_dim, output_dim, **kwargs)
