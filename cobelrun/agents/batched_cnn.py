"""R runs of the image DQN (``CnnPolicy``: Fig. 6A's and Fig. 8's networks) as one computation.

:class:`BatchedCNNDQN` is :class:`~cobelrun.agents.batched_dqn.BatchedDQN` (the same lock-step
loop, replay memories per run, target updates, masked Adam per run, clipping per run) with
cobel's :class:`~cobelrun.agents.conv.ConvFeatures` network in place of the MLP:

- each run's parameters are the sequential ``q_net``'s parameters in their order and shapes
  (``features_extractor.cnn.*``, ``features_extractor.linear.0``, the Q head), one row of the
  ``(R, P)`` parameter tensor;
- on the CPU (``conv="loop"``) each run's network is computed with the sequential ``q_net``'s
  own operations (``conv2d``, ``relu``, ``linear``), each run's loss as SB3's, clipping as
  ``clip_grad_norm_`` and Adam as torch's single-tensor Adam, so a batched run is bit for bit
  its sequential twin (tested): what batching saves is SB3's per-step Python, not arithmetic
  (oneDNN's grouped convolutions measured slower per image than plain ones);
  ``conv="grouped"`` (the CUDA default) computes R runs' convolutions as one grouped
  convolution (``groups=R``) and the dense layers as batched matrix products
  (``torch.baddbmm``): equal within float32 rounding;
- observations are stored as the sequential replay memory stores them (uint8, channels first)
  and scaled by ``/ 255`` as SB3's ``preprocess_obs`` does;
- dropout (Fig. 8: 0.35 after the dense "analysis" layer, while learning only) draws each
  run's masks from the run's own ``torch.Generator``, whose state is the sequential run's
  global torch stream after its weight initialisation, with the operations ``F.dropout`` uses
  on the CPU (``bernoulli_(1 - p)``, ``div_(1 - p)``, a product), so a batched run's masks
  are bit for bit its sequential twin's (only runs that learn in a step draw, as only they
  run the online network in training mode);
- monitors (greedy probes, activity maps of the ``analysis`` layer) see run r through
  :class:`CNNRunView`, which loads run r's weights into the template agent's own network and
  asks it: the same layer names, eval mode and preprocessing as a sequential agent.

Where the time goes and whether it pays: ``docs/speed.md`` ("CNN agents") and
``benchmarks/bench_cnn_runs.py``; :func:`auto_declines` says when ``task.batch_runs=auto``
keeps CNN runs sequential.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.vec_env import VecTransposeImage

from cobelrun.agents.base import ArraySpec
from cobelrun.agents.batched_dqn import BatchedDQN, DQNRunView, resolve_device
from cobelrun.agents.batched_ops import ACTIVATION_NAMES, activation
from cobelrun.agents.conv import ACTIVATIONS
from cobelrun.agents.torch_init import INITS

__all__ = [
    "CONV_MODES",
    "CPU_MACS_LIMIT",
    "BatchedCNNDQN",
    "CNNRunView",
    "auto_declines",
    "cnn_unsupported",
    "macs_per_image",
]

#: how R runs' convolutions are computed: one grouped convolution, or one per run
CONV_MODES = ("grouped", "loop")


def cnn_unsupported(agent: Any) -> str | None:
    """Why a ``CnnPolicy`` :class:`~cobelrun.agents.dqn.DQNAgent` cannot be batched, or None."""
    from cobelrun.agents.conv import ConvFeatures

    m = agent.model
    q_net = m.q_net
    if not isinstance(q_net.features_extractor, ConvFeatures):
        return "a CNN other than cobel's ConvFeatures"
    if int(m.train_freq.frequency) != 1 or m.train_freq.unit.value != "step":
        return "agent.train_freq other than 1 step"
    if not is_image_space(m.observation_space) or not q_net.normalize_images:
        return "image observations that are not uint8 images scaled by 1/255"
    if agent.hyper["activation"] not in ACTIVATION_NAMES:
        return f"agent.activation {agent.hyper['activation']}"
    if agent.prioritized:
        return "prioritized replay with a CNN"
    group = m.policy.optimizer.param_groups[0]
    if group.get("weight_decay", 0) or group.get("amsgrad") or group.get("maximize"):
        return "an Adam optimizer with weight decay, amsgrad or maximize"
    return None


#: multiply-adds per image of a CNN up to which batched runs pay on a CPU, measured on the
#: 2-core benchmark VM (docs/speed.md, "CNN agents"; process CPU time, 8 runs): Fig. 6A's
#: network on 36 x 36 images (0.35 M) trains 1.5x faster batched; Fig. 8's (3.3 M) 1.04x, its
#: step arithmetic-bound either way
CPU_MACS_LIMIT = 1_000_000


def macs_per_image(q_net: torch.nn.Module, shape: Sequence[int]) -> int:
    """Multiply-adds of one forward pass of ``q_net`` (convolutions and dense layers) on one
    channel-first image of ``shape``."""
    total = 0

    def count(mod: torch.nn.Module, _inp: Any, out: torch.Tensor) -> None:
        nonlocal total
        if isinstance(mod, torch.nn.Conv2d):
            k = int(np.prod(mod.kernel_size)) * mod.in_channels // mod.groups
            total += int(out[0].numel()) * k
        elif isinstance(mod, torch.nn.Linear):
            total += mod.in_features * mod.out_features

    hooks = [mod.register_forward_hook(count) for mod in q_net.modules()
             if isinstance(mod, torch.nn.Conv2d | torch.nn.Linear)]  # fmt: skip
    was_training = q_net.training
    q_net.train(False)
    try:
        with torch.no_grad():
            q_net(torch.zeros((1, *shape), dtype=torch.uint8, device=q_net.device))
    finally:
        q_net.train(was_training)
        for h in hooks:
            h.remove()
    return total


def auto_declines(agent: Any) -> str | None:
    """Why ``task.batch_runs=auto`` keeps this (batchable) CNN agent's runs one after another,
    or None. Measured (``docs/speed.md``, "CNN agents"): on a CPU batching pays only where a
    step is per-call overhead, i.e. for small networks (:data:`CPU_MACS_LIMIT` multiply-adds
    per image); a larger CNN's step is arithmetic that batching does not reduce, and a
    sequential run checkpoints inside itself. On a GPU ``auto`` does not batch CNNs (not
    measured there yet). ``task.batch_runs=true`` forces batching."""
    if agent.hyper.get("policy") != "CnnPolicy":
        return None
    if resolve_device(agent.device).type != "cpu":
        return (
            "a CNN agent on a GPU: batched CNN runs are not measured on a GPU yet; "
            "task.batch_runs=true batches them"
        )
    m = agent.model
    macs = macs_per_image(m.q_net, m.observation_space.shape)
    if macs <= CPU_MACS_LIMIT:
        return None
    return (
        f"a CNN of {macs / 1e6:.1f} M multiply-adds per image on the CPU, where batched runs "
        f"pay only up to {CPU_MACS_LIMIT / 1e6:.0f} M (docs/speed.md); task.batch_runs=true "
        "batches it anyway"
    )


class BatchedCNNDQN(BatchedDQN):
    """R image-DQN runs with stacked parameters (see the module docstring).

    Parameters
    ----------
    template, seeds, capacity, device
        As :class:`~cobelrun.agents.batched_dqn.BatchedDQN`.
    conv
        ``"grouped"`` (one grouped convolution for all runs), ``"loop"`` (a convolution per
        run) or ``"auto"`` (grouped on CUDA, loop on the CPU, where oneDNN's grouped
        convolutions measured slower per image than its plain ones).
    """

    def __init__(
        self,
        template: Any,
        seeds: Sequence[np.random.SeedSequence],
        capacity: int,
        device: str = "cpu",
        conv: str = "auto",
    ) -> None:
        if conv not in (*CONV_MODES, "auto"):
            raise ValueError(f"conv must be one of {CONV_MODES} or 'auto', got {conv!r}")
        self._conv_setting = conv
        # on the CPU the sequential agents' own (single-tensor) Adam: updates bit for bit theirs
        self.fused_adam = False if resolve_device(device).type == "cpu" else None
        super().__init__(template, seeds, capacity, device)
        self.conv = (
            conv if conv != "auto" else ("grouped" if self.device.type == "cuda" else "loop")
        )
        #: how acting (one image per run) batches its convolutions
        self.act_conv = self.conv
        self._probe_key: tuple[int, int] | None = None

    @staticmethod
    def unsupported(template: Any) -> str | None:
        return cnn_unsupported(template)

    # -- the network's structure and initial weights -------------------------------------------
    def _setup_networks(self, template: Any) -> None:
        m = template.model
        q_net = m.q_net
        space = m.observation_space  # channels first, as SB3's VecTransposeImage gives it
        self.obs_shape = tuple(int(v) for v in space.shape)
        self.obs_dtype = np.dtype(space.dtype)
        self.obs_dim = int(np.prod(self.obs_shape))
        self.transpose = tuple(template.env.observation_space.shape) != self.obs_shape
        self.init = template.hyper.get("init", "torch")
        self.q_init = template.hyper.get("q_init")
        feats = q_net.features_extractor
        # convolutions: (stride, padding before it or None), in order
        self.conv_plan: list[tuple[int, tuple[int, ...] | None]] = []
        pad: tuple[int, ...] | None = None
        for mod in feats.cnn:
            if isinstance(mod, torch.nn.ZeroPad2d):
                pad = tuple(int(v) for v in mod.padding)
            elif isinstance(mod, torch.nn.Conv2d):
                self.conv_plan.append((int(mod.stride[0]), pad))
                pad = None
        drop = [mod for mod in feats.linear if isinstance(mod, torch.nn.Dropout)]
        self.dropout = float(drop[0].p) if drop else 0.0
        self.n_head = sum(isinstance(mod, torch.nn.Linear) for mod in q_net.q_net)
        self.head_act = activation(template.hyper["activation"])
        self.head_module = ACTIVATIONS[template.hyper["activation"]]()  # the sequential head's
        self.torch_gens: list[torch.Generator] = []  # each run's dropout stream

    def _initial_params(self, torch_seed: int) -> list[torch.Tensor]:
        """Run's initial ``q_net`` parameters (``q_net.parameters()`` order and shapes), built
        as the sequential agent builds them: SB3's policy (online and target networks) from
        the run's torch seed, then ``agent.init`` and ``agent.q_init``. The torch stream's
        state after that is the run's dropout generator."""
        m = self.template.model
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(torch_seed)
            policy = type(m.policy)(m.observation_space, m.action_space, m.lr_schedule,
                                    **m.policy_kwargs)  # fmt: skip
            q_net = policy.q_net
            INITS[self.init](q_net)
            if self.q_init is not None:
                out = [mod for mod in q_net.q_net.modules() if isinstance(mod, torch.nn.Linear)][-1]
                with torch.no_grad():
                    out.bias.fill_(float(self.q_init))
            gen = torch.Generator()
            gen.set_state(torch.get_rng_state())
        self.torch_gens.append(gen)
        return [p.detach().clone() for p in q_net.parameters()]

    def view(self, run: int) -> CNNRunView:
        return CNNRunView(self, run)

    # -- checkpoints: BatchedDQN's, plus each run's dropout generator ----------------------------
    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        schema = super().checkpoint_schema()
        size = int(self.torch_gens[0].get_state().numel())
        schema["rng.dropout"] = ArraySpec((self.R, size), "u")
        return schema

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, meta = super().checkpoint_state()
        arrays["rng.dropout"] = np.stack([g.get_state().numpy() for g in self.torch_gens])
        return arrays, meta

    def restore_checkpoint(self, arrays: Any, meta: Any) -> None:
        states = [torch.as_tensor(np.asarray(row, np.uint8)) for row in arrays["rng.dropout"]]
        for r, state in enumerate(states):  # checked before anything changes
            try:
                torch.Generator().set_state(state)
            except (RuntimeError, ValueError) as exc:
                raise ValueError(f"run {r}: dropout generator: {exc}") from None
        super().restore_checkpoint(arrays, meta)
        for gen, state in zip(self.torch_gens, states, strict=True):
            gen.set_state(state)
        self._probe_key = None

    # -- forward -------------------------------------------------------------------------------
    def _obs_array(self, obs: Any) -> np.ndarray:
        arr = np.asarray(obs, self.obs_dtype)
        return VecTransposeImage.transpose_image(arr) if self.transpose else arr

    def _dropout_noise(self, runs: np.ndarray, shape: tuple[int, int]) -> torch.Tensor:
        """Dropout's multipliers ``(len(runs), n, F)``, run r's drawn from its generator as
        ``F.dropout`` draws them from torch's on the CPU (``bernoulli_(1 - p)``, then
        ``div_(1 - p)``)."""
        p = self.dropout
        rows = [torch.empty(shape).bernoulli_(1 - p, generator=self.torch_gens[r]).div_(1 - p)
                for r in runs]  # fmt: skip
        return torch.stack(rows).to(self.device)

    def forward(  # type: ignore[override]
        self,
        params: Sequence[torch.Tensor],
        x: torch.Tensor,
        keep: list[torch.Tensor] | None = None,
        runs: np.ndarray | None = None,
        dropout: bool = False,
        conv: str | None = None,
    ) -> torch.Tensor:
        """Q values ``(R', n, A)`` of images ``x`` ``(R', n, C, H, W)`` (uint8) through the
        networks of the runs ``runs`` (``R'`` of them; None: every run, ``R' = R``) of the
        stacked ``params``. ``dropout``: those networks are in training mode (their dropout
        masks are drawn), else in eval mode. ``conv``: how the convolutions are batched
        (``"grouped"`` or ``"loop"``; None: :attr:`conv`)."""
        if runs is None:
            runs = np.arange(int(params[0].shape[0]))
        Rp, n = int(x.shape[0]), int(x.shape[1])
        h = x.float() / 255.0  # SB3's preprocess_obs for uint8 images
        nc = len(self.conv_plan)
        if (conv or self.conv) == "grouped":
            if Rp != int(params[0].shape[0]):
                idx = torch.as_tensor(runs, device=x.device)
                params = [p[idx] for p in params]
            h = h.transpose(0, 1).reshape(n, Rp * self.obs_shape[0], *self.obs_shape[1:])
            for j, (stride, pad) in enumerate(self.conv_plan):
                w, b = params[2 * j], params[2 * j + 1]
                if pad is not None:
                    h = F.pad(h, pad)
                h = F.conv2d(h, w.reshape(-1, *w.shape[2:]), b.reshape(-1), stride, groups=Rp)
                h = torch.relu(h)
            h = h.reshape(n, Rp, -1).transpose(0, 1)
            dense = params[2 * nc :]
        else:
            return torch.stack(self._per_run(params, h, runs, dropout))
        w, b = dense[0], dense[1]
        h = torch.relu(torch.baddbmm(b[:, None], h, w.transpose(1, 2)))  # the analysis layer
        if dropout and self.dropout > 0:
            h = h * self._dropout_noise(runs, (n, int(h.shape[2])))
        for i in range(self.n_head):
            w, b = dense[2 + 2 * i], dense[3 + 2 * i]
            h = torch.baddbmm(b[:, None], h, w.transpose(1, 2))
            if i < self.n_head - 1:
                h = self.head_act(h)
        return h

    def _per_run(
        self, params: Sequence[torch.Tensor], h: torch.Tensor, runs: np.ndarray, dropout: bool
    ) -> list[torch.Tensor]:
        """``conv="loop"``: each run's network on its images ``h[i]`` (scaled floats) with the
        very operations the sequential ``q_net`` performs (``conv2d``, ``relu``, ``linear``,
        dropout's product, the head's activation module), so its outputs and gradients are
        bit for bit the sequential network's. Returns each run's Q values ``(n, A)``."""
        nc = len(self.conv_plan)
        per = [p.unbind(0) for p in params]  # one backward node per stacked tensor
        n = int(h.shape[1])
        out = []
        for i, r in enumerate(runs):
            hr = h[i]
            for j, (stride, pad) in enumerate(self.conv_plan):
                if pad is not None:
                    hr = F.pad(hr, pad)
                hr = torch.relu(F.conv2d(hr, per[2 * j][r], per[2 * j + 1][r], stride))
            hr = torch.relu(F.linear(hr.reshape(n, -1), per[2 * nc][r], per[2 * nc + 1][r]))
            if dropout and self.dropout > 0:
                hr = hr * self._dropout_noise([r], (n, int(hr.shape[1])))[0]
            for k in range(self.n_head):
                first = 2 * (nc + 1 + k)
                hr = F.linear(hr, per[first][r], per[first + 1][r])
                if k < self.n_head - 1:
                    hr = self.head_module(hr)
            out.append(hr)
        return out

    def _greedy(self, obs: np.ndarray, runs: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(obs[runs], device=self.device)[:, None]
        with torch.no_grad():
            q = self.forward(self.params, x, runs=runs, conv=self.act_conv)
        return q[:, 0].argmax(dim=1).cpu().numpy()

    def _gradient_step(self, train: np.ndarray) -> None:
        """One Adam step of every run with ``train[r]``: SB3's ``DQN.train`` for one gradient
        step, per run, computed for those runs only (the others are left exactly as they
        are, and cost nothing)."""
        B, dev = self.batch_size, self.device
        runs = np.flatnonzero(train)
        idx = np.empty((len(runs), B), np.int64)
        for j, r in enumerate(runs):  # SB3: np.random.randint(0, upper_bound, size=batch_size)
            upper = self.capacity if self.full[r] else self.pos[r]
            idx[j] = self.np_rngs[r].randint(0, upper, size=B)
        rt = torch.as_tensor(runs, device=dev)
        rows, ii = rt[:, None], torch.as_tensor(idx, device=dev)
        obs, nxt = self.buf_obs[rows, ii], self.buf_next[rows, ii]
        act, rew, done = (
            self.buf_action[rows, ii],
            self.buf_reward[rows, ii],
            self.buf_done[rows, ii],
        )
        with torch.no_grad():
            if bool((done == 1).all()):
                target = rew  # every sampled transition ends its trial: no bootstrap term
            else:
                next_q = self.forward(self.layers(self.flat_target), nxt, runs=runs)
                target = rew + (1 - done) * self.gamma * next_q.max(dim=2).values
        q = self.forward(self.params, obs, runs=runs, dropout=True)
        current = q.gather(2, act[..., None])[..., 0]
        loss_fn = F.smooth_l1_loss if self.huber else F.mse_loss
        # each run's loss as SB3 computes it ((B, 1) columns, mean), summed: each run's
        # gradient is its sequential twin's
        loss = torch.stack([loss_fn(c[:, None], t[:, None])
                            for c, t in zip(current, target, strict=True)]).sum()  # fmt: skip
        grads = torch.autograd.grad(loss, self._leaves)
        with torch.no_grad():
            full = len(runs) == self.R
            grad = torch.cat([(g if full else g[rt]).reshape(len(runs), -1) for g in grads], dim=1)
            if self.max_grad_norm is not None:  # clip_grad_norm_: the norm of tensor norms
                norms = [torch.linalg.vector_norm(piece.reshape(len(runs), -1), dim=1)
                         for piece in self.layers(grad)]  # fmt: skip
                total = torch.linalg.vector_norm(torch.stack(norms, dim=1), dim=1, keepdim=True)
                grad.mul_(torch.clamp(self.max_grad_norm / (total + 1e-6), max=1.0))
            self.version += 1
            self.adam.step([grad], runs)

    # -- one run's network as a module (monitors, saving) --------------------------------------
    def probe(self, run: int) -> torch.nn.Module:
        """The template agent's ``q_net`` holding run ``run``'s current online weights."""
        key = (self.version, run)
        q_net = self.template.model.q_net
        if self._probe_key != key:
            with torch.no_grad():
                for p, t in zip(q_net.parameters(), self.layers(self.flat[run : run + 1]),
                                strict=True):  # fmt: skip
                    p.copy_(t[0])
            self._probe_key = key
        return q_net

    def run_forward(
        self, run: int, x: np.ndarray, keep: list[torch.Tensor] | None = None
    ) -> np.ndarray:
        self.probe(run)
        return self.template.predict(x)


class CNNRunView(DQNRunView):
    """Run ``run`` of a :class:`BatchedCNNDQN`, seen as one CNN DQN agent: ``predict``,
    ``layer_names`` and ``activations`` (``analysis`` included) are the template agent's, asked
    with run ``run``'s weights loaded; ``get_state`` writes a sequential ``DQNAgent``'s file."""

    batch: BatchedCNNDQN

    def predict(self, observations: np.ndarray) -> np.ndarray:
        self.batch.probe(self.run)
        return self._template.predict(observations)

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        self.batch.probe(self.run)
        return self._template.activations(observations, layers)

    def get_state(self) -> dict[str, np.ndarray]:
        b, r = self.batch, self.run
        names = [name for name, _ in self._template.model.q_net.named_parameters()]
        arrays: dict[str, np.ndarray] = {}
        for prefix, flat in (("policy.q_net", b.flat), ("policy.q_net_target", b.flat_target)):
            for name, t in zip(names, b.layers(flat[r : r + 1]), strict=True):
                arrays[f"{prefix}.{name}"] = t[0].detach().cpu().numpy().copy()
        return self._optimizer_and_counters(arrays, lambda _j, t: t, "batched CNN")
