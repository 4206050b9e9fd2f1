"""Building blocks of the batched learners (:mod:`cobelrun.agents.batched_dqn`,
:mod:`cobelrun.agents.batched_dyna`): Adam with one step count per run, and the activation
functions of stacked networks.

Measured on the 2-core benchmark machine (torch 2.13, CPU, one thread; ``docs/speed.md``):

- torch's unfused Adam formula on a ``(100, 13250)`` parameter tensor (Fig. 9's 100 DQN
  networks) costs ~6 ms per step, memory-bound; torch's fused Adam kernel (one pass over
  parameters, gradients and moments) ~2 ms. :class:`RowAdam` uses the fused kernel with one
  parameter per run, so every run keeps its own step count, and a run that waits (no
  gradient this step) is skipped by the optimizer itself, its parameters and moments left
  exactly as they are.
- ``torch.tanh`` on this CPU costs ~2.7 ns per element, numpy's ``np.tanh`` ~0.35 ns:
  :func:`activation` computes tanh with numpy on CPU tensors (the backward pass is torch's
  ``grad * (1 - y**2)``) and with torch elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["RowAdam", "activation"]


class _NumpyTanh(torch.autograd.Function):
    """tanh of a CPU tensor through ``np.tanh``; backward ``grad * (1 - y * y)``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        y = torch.from_numpy(np.tanh(x.detach().numpy()))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        (y,) = ctx.saved_tensors
        return grad * (1 - y * y)


def _tanh(x: torch.Tensor) -> torch.Tensor:
    if x.device.type == "cpu" and x.dtype == torch.float32:
        return _NumpyTanh.apply(x)
    return torch.tanh(x)


_ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "tanh": _tanh,
    "relu": torch.relu,
    "elu": F.elu,
    "sigmoid": torch.sigmoid,
    "linear": lambda x: x,
}


def activation(name: str) -> Callable[[torch.Tensor], torch.Tensor]:
    """The activation function ``name`` (tanh, relu, elu, sigmoid, linear) for stacked nets."""
    return _ACTIVATIONS[name]


ACTIVATION_NAMES = tuple(_ACTIVATIONS)


class RowAdam:
    """``torch.optim.Adam`` over stacked parameters ``(R, ...)``, one run per row.

    Each run's slice of each tensor is its own optimizer parameter (a leaf tensor sharing
    that memory), so each run has its own step count and moments, exactly as a sequential
    run's optimizer has; a run whose gradients are not given in a step is skipped by the
    optimizer (parameters, moments and step count unchanged). The fused kernel does one pass
    over all of them.

    Parameters
    ----------
    tensors
        Stacked parameters, each ``(R, ...)``, contiguous; updated in place.
    lr, betas, eps
        Adam's settings (those of the sequential agent's optimizer).
    """

    def __init__(
        self,
        tensors: Sequence[torch.Tensor],
        lr: float,
        betas: tuple[float, float],
        eps: float,
        fused: bool | None = None,
    ) -> None:
        self.tensors = list(tensors)
        self.R = int(self.tensors[0].shape[0])
        # params[r][k]: run r's slice of tensor k
        self.params = [[t[r].detach().requires_grad_() for t in self.tensors]
                       for r in range(self.R)]  # fmt: skip
        if fused is None:
            fused = self.tensors[0].device.type in ("cpu", "cuda")
        flat = [p for row in self.params for p in row]
        # not fused: torch's single-tensor Adam, the sequential agents' on the CPU (bit for bit)
        self.opt = torch.optim.Adam(flat, lr=lr, betas=betas, eps=eps, fused=fused or None,
                                    foreach=None if fused else False)  # fmt: skip
        self.steps = np.zeros(self.R, np.int64)

    def step(self, grads: Sequence[torch.Tensor], runs: np.ndarray) -> None:
        """One Adam step of the runs ``runs`` (indices, increasing); ``grads[k][i]`` is run
        ``runs[i]``'s gradient of tensor ``k``. The other runs are left exactly as they are."""
        for i, r in enumerate(runs):
            for p, g in zip(self.params[r], grads, strict=True):
                p.grad = g[i]
        self.opt.step()
        for r in runs:
            for p in self.params[r]:
                p.grad = None
        self.steps[runs] += 1

    def moments(self, run: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Run ``run``'s first and second moments of each tensor (zeros before its first
        step)."""
        out = []
        for p in self.params[run]:
            state = self.opt.state.get(p, {})
            if "exp_avg" not in state:
                zeros = torch.zeros_like(p)
                out.append((zeros, zeros))
            else:
                out.append((state["exp_avg"], state["exp_avg_sq"]))
        return out

    # -- checkpoints (:mod:`cobelrun.checkpoint`) ---------------------------------------------
    def checkpoint_shapes(self) -> dict[str, tuple[tuple[int, ...], str]]:
        """Shape and dtype kind of every array of :meth:`checkpoint_arrays`."""
        out: dict[str, tuple[tuple[int, ...], str]] = {"steps": ((self.R,), "i")}
        for k, t in enumerate(self.tensors):
            out[f"exp_avg.{k}"] = (tuple(t.shape), "f")
            out[f"exp_avg_sq.{k}"] = (tuple(t.shape), "f")
        return out

    def checkpoint_arrays(self) -> dict[str, np.ndarray]:
        """Every run's step count and moments, stacked like the parameters (zeros for a run
        that has not stepped yet)."""
        out: dict[str, np.ndarray] = {"steps": self.steps.copy()}
        per_run = [self.moments(r) for r in range(self.R)]
        for k in range(len(self.tensors)):
            for j, name in enumerate(("exp_avg", "exp_avg_sq")):
                out[f"{name}.{k}"] = (
                    torch.stack([per_run[r][k][j].detach() for r in range(self.R)]).cpu().numpy()
                )
        return out

    def restore_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore :meth:`checkpoint_arrays` (shapes already checked) through the optimizer's
        ``load_state_dict``: a run that has stepped gets its step count and moments, one that
        has not gets no state, as a fresh optimizer (its first step then starts them)."""
        steps = np.asarray(arrays["steps"], np.int64)
        state: dict[int, dict[str, torch.Tensor]] = {}
        K = len(self.tensors)
        for r in range(self.R):
            if steps[r] <= 0:
                continue
            for k in range(K):
                state[r * K + k] = {
                    "step": torch.tensor(float(steps[r]), dtype=torch.float32),
                    "exp_avg": torch.as_tensor(np.asarray(arrays[f"exp_avg.{k}"][r], np.float32)),
                    "exp_avg_sq": torch.as_tensor(
                        np.asarray(arrays[f"exp_avg_sq.{k}"][r], np.float32)
                    ),
                }
        groups = self.opt.state_dict()["param_groups"]
        self.opt.load_state_dict({"state": state, "param_groups": groups})
        self.steps = steps.copy()
