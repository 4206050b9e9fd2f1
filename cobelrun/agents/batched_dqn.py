"""R runs of :class:`~cobelrun.agents.dqn.DQNAgent` trained as one batched computation.

A run of the sequential DQN agent is stable-baselines3's ``DQN`` on one environment: per
environment step an epsilon-greedy action, one transition into the replay buffer, a soft (or
hard) target update and ``gradient_steps`` Adam steps on a batch drawn from the buffer (plus
``trial_end_updates`` when a trial ended). On a CPU each of these is a handful of tiny tensor
operations, so a run spends most of its time in per-call overhead. :class:`BatchedDQN` keeps
the R runs' networks as stacked tensors with a leading run axis (``W[l]``: ``(R, in, out)``)
and performs every step of every run at once with batched matrix products
(``torch.baddbmm``), one backward pass and one fused Adam step of the stacked parameters
(:class:`~cobelrun.agents.batched_ops.RowAdam`: a step count per run).

Each run is still its own agent, with the sequential agent's update rule read top to bottom
in :meth:`BatchedDQN._gradient_step`:

- the same random streams as a sequential run of the same seed: the agent's seed sequence
  gives the numpy stream of exploration and replay sampling (``np.random.RandomState``, which
  SB3 draws from through numpy's global generator), the torch stream of the weight
  initialisation and the private action space's sampler, so that run ``r`` draws exactly what
  a sequential run ``r`` draws, in the same order;
- its own replay buffer (``(R, capacity, ...)`` tensors with a write position per run), its
  own step and update counters, learning start, target updates and Adam step count;
- gradient clipping per run (each run's gradient norm over all its parameters, as
  ``torch.nn.utils.clip_grad_norm_`` computes it for one run);
- runs whose trial (or phase) is over wait: their parameters, Adam moments and counters are
  masked out of the update, so trials of different lengths work and run ``r``'s learning does
  not depend on the other runs in the batch.

The arithmetic differs from the sequential path only in how floating-point sums are ordered
(batched instead of single matrix products), so a batched run follows its sequential twin
until a rounding difference first flips a greedy choice (``tests/test_batched.py`` measures
how often that happens and checks the learning curves statistically).

Prioritized replay (``agent.prioritized``, :mod:`cobelrun.agents.per`) is batched too: one
:class:`~cobelrun.agents.per.BatchedSumTree` holds every run's priorities, and each run samples
from its own ``numpy.random.Generator`` (seeded as the sequential buffer's), with its own
maximum priority and beta schedule (see :meth:`BatchedDQN._sample_prioritized`).

Supported: vector (``Box``) or ``Discrete`` observations with the MLP policy, uniform or
prioritized replay, ``train_freq`` 1; image observations with ``CnnPolicy`` (dropout included)
through the subclass :class:`~cobelrun.agents.batched_cnn.BatchedCNNDQN`
(:func:`cobelrun.agents.batched_pick.make_batched` picks). Other settings (Dict observations, other ``train_freq``s) run
sequentially; :func:`unsupported` says why.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F

from cobelrun.agents.base import ArraySpec, TrialCallback, state_of
from cobelrun.agents.batched_ops import ACTIVATION_NAMES, RowAdam, activation
from cobelrun.agents.per import BatchedSumTree
from cobelrun.agents.torch_init import INITS
from cobelrun.envs.base import Posed
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation

__all__ = [
    "BatchedDQN",
    "DQNRunView",
    "mlp_unsupported",
    "resolve_device",
]


def resolve_device(device: str) -> torch.device:
    """``"auto"``: CUDA when present, else the CPU; any other name as torch reads it."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def mlp_unsupported(agent: Any) -> str | None:
    """Why the MLP path (:class:`BatchedDQN`) cannot batch ``agent``, or None."""
    m = agent.model
    hyper = agent.hyper
    if hyper["policy"] != "MlpPolicy":
        return f"agent.policy {hyper['policy']} (batched runs support MlpPolicy networks)"
    if int(m.train_freq.frequency) != 1 or m.train_freq.unit.value != "step":
        return "agent.train_freq other than 1 step"
    space = m.observation_space
    if isinstance(space, gym.spaces.Box) and len(space.shape) != 1:
        return f"observations of shape {space.shape} (batched runs take vectors)"
    if not isinstance(space, gym.spaces.Box | gym.spaces.Discrete):
        return f"{type(space).__name__} observations"
    if hyper["activation"] not in ACTIVATION_NAMES:
        return f"agent.activation {hyper['activation']}"
    group = m.policy.optimizer.param_groups[0]
    if group.get("weight_decay", 0) or group.get("amsgrad") or group.get("maximize"):
        return "an Adam optimizer with weight decay, amsgrad or maximize"
    return None


class BatchedDQN:
    """R DQN runs with stacked parameters (see the module docstring).

    Parameters
    ----------
    template
        A :class:`~cobelrun.agents.dqn.DQNAgent` built with the task's agent settings (run
        0's): its validated hyperparameters, layer names and save-file layout are used.
    seeds
        Each run's agent seed sequence (:func:`cobelrun.runner.run_seed`).
    capacity
        Replay slots per run: ``min(buffer_size, steps the run can take)`` (a ring buffer of
        ``buffer_size`` behaves the same as long as it never wraps).
    device
        torch device (``"auto"``: CUDA when present).
    """

    #: Adam's fused kernel (None: on CPU and CUDA); False: the sequential agents' own Adam
    fused_adam: bool | None = None

    def __init__(
        self,
        template: Any,
        seeds: Sequence[np.random.SeedSequence],
        capacity: int,
        device: str = "cpu",
    ) -> None:
        why = self.unsupported(template)
        if why is not None:
            raise ConfigError(f"task.batch_runs: cannot batch this DQN: {why}")
        m = template.model
        self.template = template
        self.R = R = len(seeds)
        self.device = resolve_device(device)
        self.n_actions = int(template.n_actions)
        space = m.observation_space
        self.discrete_obs = isinstance(space, gym.spaces.Discrete)
        self.obs_dim = int(space.n) if self.discrete_obs else int(np.prod(space.shape))
        #: one observation as the replay memory holds it (vectors: float32)
        self.obs_shape: tuple[int, ...] = (self.obs_dim,)
        self.obs_dtype: np.dtype = np.dtype(np.float32)
        self.gamma, self.tau = float(m.gamma), float(m.tau)
        self.batch_size, self.learning_starts = int(m.batch_size), int(m.learning_starts)
        self.target_update_interval = max(int(m.target_update_interval), 1)
        self.gradient_steps = int(m.gradient_steps)
        self.trial_end_updates = int(m.trial_end_updates)
        self.max_grad_norm = None if m.max_grad_norm is None else float(m.max_grad_norm)
        self.huber = m.td_loss is F.smooth_l1_loss
        self.epsilon, self.test_epsilon = float(template.epsilon), float(template.test_epsilon)
        group = m.policy.optimizer.param_groups[0]
        self.lr = float(group["lr"])
        self.betas = (float(group["betas"][0]), float(group["betas"][1]))
        self.adam_eps = float(group["eps"])
        self.act = activation(template.hyper["activation"])
        self.capacity = max(1, min(int(m.buffer_size), int(capacity)))

        self._setup_networks(template)
        # -- per-run streams, exactly those of a sequential DQNAgent with the same seed
        self.np_rngs: list[np.random.RandomState] = []
        self.per_rngs: list[np.random.Generator] = []  # prioritized replay's sampling streams
        self.spaces: list[gym.spaces.Discrete] = []
        per_run: list[list[torch.Tensor]] = []  # each run's initial parameters, in layout order
        for seq in seeds:
            np_seed, torch_seed, space_seed, per_seed = seq.generate_state(4)
            self.np_rngs.append(np.random.RandomState(int(np_seed)))
            self.per_rngs.append(np.random.default_rng(int(per_seed)))
            sp = gym.spaces.Discrete(self.n_actions)
            sp.seed(int(space_seed))
            self.spaces.append(sp)
            per_run.append(self._initial_params(int(torch_seed)))
        dev = self.device
        # every run's parameters in one (R, P) tensor; the layers are leaf views into it (the
        # backward pass fills one gradient per layer), clipping and Adam work on it whole
        self.shapes = [tuple(t.shape) for t in per_run[0]]
        self.flat = torch.stack([torch.cat([t.reshape(-1) for t in ts]) for ts in per_run]).to(dev)
        self.flat_target = self.flat.clone()
        self._leaves = [v.requires_grad_() for v in self.layers(self.flat)]
        # Adam with a step count per run (a waiting run does not step)
        self.adam = RowAdam([self.flat], self.lr, self.betas, self.adam_eps, fused=self.fused_adam)
        self.version = 0  # bumped at every parameter change (caches of predictions)
        self._cache: tuple[int, bytes, np.ndarray] | None = None
        self.num_timesteps = np.zeros(R, np.int64)
        self.n_calls = np.zeros(R, np.int64)
        # replay buffers: (R, capacity, ...) with a write position per run
        cap = self.capacity
        obs_dtype = torch.from_numpy(np.zeros(0, self.obs_dtype)).dtype
        per_obs = int(np.prod(self.obs_shape)) * self.obs_dtype.itemsize
        check_allocation("task.batch_runs", R * cap * (2 * per_obs + 8 + 4 + 4),
                         f"{R} runs' replay memories of {cap:,} transitions",
                         "lower task.batch_runs (runs at once) or agent.buffer_size")  # fmt: skip
        self.buf_obs = torch.zeros((R, cap, *self.obs_shape), dtype=obs_dtype, device=dev)
        self.buf_next = torch.zeros_like(self.buf_obs)
        self.buf_action = torch.zeros((R, cap), dtype=torch.long, device=dev)
        self.buf_reward = torch.zeros((R, cap), dtype=torch.float32, device=dev)
        self.buf_done = torch.zeros((R, cap), dtype=torch.float32, device=dev)
        self.pos = np.zeros(R, np.int64)
        self.full = np.zeros(R, bool)
        self._rows = torch.arange(R, device=dev)
        # prioritized replay (PrioritizedReplayBuffer's state, one entry per run)
        self.prioritized = bool(template.prioritized)
        if self.prioritized:
            per = m.replay_buffer
            self.alpha, self.beta0 = float(per.alpha), float(per.beta0)
            self.beta_steps, self.per_epsilon = int(per.beta_steps), float(per.epsilon)
            self.tree = BatchedSumTree(R, cap)
            self.max_priority = np.ones(R)
            # max_priority ** alpha, the priority of a new transition (a Python float power,
            # as PrioritizedReplayBuffer.add computes it)
            self.new_priority = np.full(R, 1.0**self.alpha)
            self.n_sampled = np.zeros(R, np.int64)

    def view(self, run: int) -> DQNRunView:
        """Run ``run`` seen as one agent (for monitors and saving)."""
        return DQNRunView(self, run)

    # -- networks ----------------------------------------------------------------------------
    @staticmethod
    def unsupported(template: Any) -> str | None:
        """Why this class cannot batch ``template``, or None."""
        return mlp_unsupported(template)

    def _setup_networks(self, template: Any) -> None:
        """Read the network's settings off the template (the MLP's layer sizes)."""
        self.sizes = [self.obs_dim, *template.hyper["net_arch"], self.n_actions]
        self.init = template.hyper.get("init", "torch")
        self.q_init = template.hyper.get("q_init")

    def _initial_params(self, torch_seed: int) -> list[torch.Tensor]:
        """One run's initial parameters ``[W0, b0, W1, b1, ...]`` (``W`` ``(in, out)``, ``b``
        ``(1, out)``), drawn from the torch stream a sequential agent of this seed draws them
        from."""
        sizes, init, q_init = self.sizes, self.init, self.q_init
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(torch_seed)
            # SB3's q_net: Linear layers created in order with torch's default init
            layers = [torch.nn.Linear(a, b) for a, b in itertools.pairwise(sizes)]
            if init != "torch" or q_init is not None:
                # SB3 builds the target network next; DQNAgent re-initialises after it
                _target = [torch.nn.Linear(a, b) for a, b in itertools.pairwise(sizes)]
                INITS[init](torch.nn.Sequential(*layers))
                if q_init is not None:
                    with torch.no_grad():
                        layers[-1].bias.fill_(float(q_init))
        out: list[torch.Tensor] = []
        for layer in layers:
            out += [layer.weight.detach().T, layer.bias.detach()[None]]
        return out

    def _online_q(self, obs: torch.Tensor, train: np.ndarray) -> torch.Tensor:
        """Q values ``(R, B, A)`` of the online networks in a gradient step (``train``: the
        runs that learn in it)."""
        return self.forward(self.params, obs)

    def _greedy(self, obs: np.ndarray, runs: np.ndarray) -> np.ndarray:
        """Greedy actions of the runs ``runs`` at their current observations ``obs[runs]``
        (``obs``: every run's; the MLPs of all runs are evaluated, it costs no more)."""
        with torch.no_grad():
            q = self.forward(self.params, torch.as_tensor(obs, device=self.device)[:, None])
        return q[:, 0].argmax(dim=1).cpu().numpy()[runs]

    def _obs_array(self, obs: Any) -> np.ndarray:
        if self.discrete_obs:
            v = np.zeros(self.obs_dim, np.float32)
            v[int(np.asarray(obs).reshape(-1)[0])] = 1.0
            return v
        return np.asarray(obs, np.float32).reshape(self.obs_dim)

    def layers(self, flat: torch.Tensor) -> list[torch.Tensor]:
        """``[W0, b0, W1, b1, ...]`` as views of a ``(R', P)`` parameter tensor: ``W`` is
        ``(R', in, out)`` (``nn.Linear``'s weight transposed), ``b`` is ``(R', 1, out)``."""
        out, start = [], 0
        for shape in self.shapes:
            size = math.prod(shape)
            out.append(flat[:, start : start + size].view(flat.shape[0], *shape))
            start += size
        return out

    @property
    def params(self) -> list[torch.Tensor]:
        """The online networks' layers (leaf views of :attr:`flat`)."""
        return self._leaves

    def forward(
        self,
        params: Sequence[torch.Tensor],
        x: torch.Tensor,
        keep: list[torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Q values ``(R, n, A)`` of inputs ``x`` ``(R, n, obs_dim)`` for every run at once."""
        h = x
        last = len(params) // 2 - 1
        for i in range(last + 1):
            h = torch.baddbmm(params[2 * i + 1], h, params[2 * i])
            if keep is not None:
                keep.append(h)
            if i < last:
                h = self.act(h)
                if keep is not None:
                    keep.append(h)
        return h

    def run_forward(
        self, run: int, x: np.ndarray, keep: list[torch.Tensor] | None = None
    ) -> np.ndarray:
        """Q values ``(n, A)`` of run ``run`` for observation vectors ``x`` ``(n, obs_dim)``."""
        x = np.ascontiguousarray(x, np.float32)
        if keep is None:  # every run's values at once, kept until the parameters change
            key = x.tobytes()
            if self._cache is None or self._cache[0] != self.version or self._cache[1] != key:
                xt = torch.as_tensor(x, device=self.device)[None].expand(self.R, -1, -1)
                with torch.no_grad():
                    q = self.forward(self.params, xt).cpu().numpy()
                self._cache = (self.version, key, q)
            return self._cache[2][run].copy()
        xt = torch.as_tensor(x, device=self.device)[None]
        with torch.no_grad():
            return self.forward(self.layers(self.flat[run : run + 1]), xt, keep)[0].cpu().numpy()

    # -- learning ----------------------------------------------------------------------------
    def _store(self, runs: np.ndarray, obs: np.ndarray, nxt: np.ndarray, actions: np.ndarray,
               rewards: np.ndarray, dones: np.ndarray) -> None:  # fmt: skip
        """One transition per run in ``runs`` into its buffer (SB3's ReplayBuffer.add)."""
        pos = self.pos[runs]
        if self.prioritized:  # PrioritizedReplayBuffer.add: the run's largest priority so far
            self.tree.update(runs, pos, self.new_priority[runs])
        r_t = torch.as_tensor(runs, device=self.device)
        p_t = torch.as_tensor(pos, device=self.device)
        dev = self.device
        self.buf_obs[r_t, p_t] = torch.as_tensor(obs, device=dev)
        self.buf_next[r_t, p_t] = torch.as_tensor(nxt, device=dev)
        self.buf_action[r_t, p_t] = torch.as_tensor(actions, device=dev)
        self.buf_reward[r_t, p_t] = torch.as_tensor(rewards.astype(np.float32), device=dev)
        self.buf_done[r_t, p_t] = torch.as_tensor(dones.astype(np.float32), device=dev)
        pos = pos + 1
        wrapped = pos == self.capacity
        self.full[runs[wrapped]] = True
        pos[wrapped] = 0
        self.pos[runs] = pos

    def _target_update(self, runs: np.ndarray) -> None:
        """Polyak update ``target <- (1 - tau) target + tau online`` of the runs in ``runs``."""
        t, p = self.flat_target, self.flat
        with torch.no_grad():
            if len(runs) == self.R:
                t.mul_(1 - self.tau).add_(p, alpha=self.tau)
                return
            # the same two operations as for all runs (SB3's polyak_update: mul_, add_ with
            # alpha), so a run's target does not depend on which runs wait (tested)
            idx = torch.as_tensor(runs, device=self.device)
            sub = t[idx].mul_(1 - self.tau)
            sub.add_(p[idx], alpha=self.tau)
            t[idx] = sub

    def _gradient_step(self, train: np.ndarray) -> None:
        """One Adam step of every run with ``train[r]`` (the others are left exactly as they
        are): SB3's ``DQN.train`` for one gradient step, per run."""
        R, B = self.R, self.batch_size
        runs = np.flatnonzero(train)
        idx = np.zeros((R, B), np.int64)
        weights = None
        if self.prioritized:
            idx[runs], w = self._sample_prioritized(runs)
            weights = torch.zeros((R, B), dtype=torch.float32)
            weights[torch.as_tensor(runs)] = torch.as_tensor(w)
            weights = weights.to(self.device)
        else:
            for r in runs:  # SB3: np.random.randint(0, upper_bound, size=batch_size)
                upper = self.capacity if self.full[r] else self.pos[r]
                idx[r] = self.np_rngs[r].randint(0, upper, size=B)
        ii = torch.as_tensor(idx, device=self.device)
        rows = self._rows[:, None]
        obs, nxt = self.buf_obs[rows, ii], self.buf_next[rows, ii]
        act, rew, done = (
            self.buf_action[rows, ii],
            self.buf_reward[rows, ii],
            self.buf_done[rows, ii],
        )
        with torch.no_grad():
            if bool((done[torch.as_tensor(train, device=self.device)] == 1).all()):
                target = rew  # every sampled transition ends its trial: no bootstrap term
            else:
                next_q = self.forward(self.layers(self.flat_target), nxt).max(dim=2).values
                target = rew + (1 - done) * self.gamma * next_q
        current = self._online_q(obs, train).gather(2, act[..., None])[..., 0]
        if self.huber:
            per = F.smooth_l1_loss(current, target, reduction="none")
        else:
            per = F.mse_loss(current, target, reduction="none")
        if weights is not None:  # PrioritizedDQN: importance weights on each sample's loss
            per = weights * per
        mask = torch.as_tensor(train, device=self.device)
        loss = (per.mean(dim=1) * mask).sum()  # each run's mean loss; runs are independent
        grads = torch.autograd.grad(loss, self._leaves)
        if self.prioritized:  # p_i = |TD error_i| + epsilon, after the step's gradient
            td = (target - current).detach()[torch.as_tensor(runs, device=self.device)]
            self._update_priorities(runs, idx[runs], td.cpu().numpy())
        with torch.no_grad():
            grad = torch.cat([g.reshape(R, -1) for g in grads], dim=1)
            if self.max_grad_norm is not None:  # clip_grad_norm_ over all of a run's gradients
                total = torch.linalg.vector_norm(grad, dim=1, keepdim=True)
                grad.mul_(torch.clamp(self.max_grad_norm / (total + 1e-6), max=1.0))
            self._adam(grad, train)

    def _sample_prioritized(self, runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Buffer indices ``(len(runs), B)`` and importance weights (float32) of one
        :meth:`PrioritizedReplayBuffer.sample <cobelrun.agents.per.PrioritizedReplayBuffer.sample>`
        per run in ``runs``: stratified proportional draws (one uniform per equal slice of the
        run's total, from the run's own generator), ``w_i = (N P(i))^-beta / max_j w_j`` with
        the run's beta, which then moves one step along its schedule."""
        B = self.batch_size
        tree = self.tree
        n = np.where(self.full[runs], self.capacity, self.pos[runs])
        total, low = tree.total()[runs], tree.min()[runs]
        rand = np.empty((len(runs), B))
        for j, r in enumerate(runs):  # each run's generator, in the sequential buffer's order
            rand[j] = self.per_rngs[r].random(B)
        u = (np.arange(B) + rand) * (total / B)[:, None]
        idx = tree.find(np.minimum(u, np.nextafter(total, 0.0)[:, None]), runs)
        idx = np.minimum(idx, (n - 1)[:, None])
        frac = np.minimum(1.0, self.n_sampled[runs] / self.beta_steps)
        beta = self.beta0 + frac * (1.0 - self.beta0)
        probs = tree.get(runs[:, None], idx) / total[:, None]
        # the largest weight, from the smallest priority: a Python float power per run, as in
        # the sequential buffer (numpy's vectorised power may round differently)
        max_weight = np.array([(int(k) * float(lo) / float(t)) ** -float(b)
                               for k, lo, t, b in zip(n, low, total, beta, strict=True)])  # fmt: skip
        scaled = n[:, None] * probs
        powered = scaled ** -beta[:, None]
        one = beta == 1.0  # numpy computes an array ** -1.0 (scalar) as a reciprocal
        if one.any():
            powered[one] = 1.0 / scaled[one]
        weights = powered / max_weight[:, None]
        self.n_sampled[runs] += 1
        return idx, weights.astype(np.float32)

    def _update_priorities(self, runs: np.ndarray, idx: np.ndarray, td: np.ndarray) -> None:
        """:meth:`PrioritizedReplayBuffer.update_priorities
        <cobelrun.agents.per.PrioritizedReplayBuffer.update_priorities>` for each run in
        ``runs``: ``p_i = |delta_i| + epsilon``, the run's largest priority so far, and the
        sampled leaves set to ``p_i^alpha`` (a leaf sampled twice takes its last value)."""
        p = np.abs(np.asarray(td, dtype=np.float64)) + self.per_epsilon
        top = p.max(axis=1)
        grew = top > self.max_priority[runs]
        if grew.any():
            for r, v in zip(runs[grew], top[grew], strict=True):
                self.max_priority[r] = v
                self.new_priority[r] = float(v) ** self.alpha
        self.tree.update(runs[:, None], idx, p**self.alpha)

    def _adam(self, grad: torch.Tensor, train: np.ndarray) -> None:
        """torch.optim.Adam's update with a step count per run (:class:`RowAdam`); runs not
        in ``train`` keep their parameters and moments exactly."""
        self.version += 1
        runs = np.flatnonzero(train)
        self.adam.step([grad if len(runs) == self.R else grad[torch.as_tensor(runs)]], runs)

    @property
    def adam_steps(self) -> np.ndarray:
        """Adam steps taken by each run."""
        return self.adam.steps

    # -- checkpoints (:mod:`cobelrun.checkpoint`, between pieces of a phase) --------------------
    def _replay_kept(self, pos: np.ndarray, full: np.ndarray) -> int:
        """Replay slots a checkpoint keeps: those the fullest run has filled."""
        return int(self.capacity if full.any() else pos.max(initial=0))

    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        """Every array of :meth:`checkpoint_state` and what it must look like (the run axis
        first; the replay memories' slot axis free: a checkpoint keeps the filled slots)."""
        R, P = (int(n) for n in self.flat.shape)
        obs_kind = self.obs_dtype.kind
        schema = {
            "params": ArraySpec((R, P)),
            "target": ArraySpec((R, P)),
            "num_timesteps": ArraySpec((R,), "i", low=0),
            "n_calls": ArraySpec((R,), "i", low=0),
            "replay.pos": ArraySpec((R,), "i", low=0, high=self.capacity),
            "replay.full": ArraySpec((R,), "b"),
            "replay.obs": ArraySpec((R, None, *self.obs_shape), obs_kind),
            "replay.next_obs": ArraySpec((R, None, *self.obs_shape), obs_kind),
            "replay.action": ArraySpec((R, None), "i", low=0, high=self.n_actions),
            "replay.reward": ArraySpec((R, None)),
            "replay.done": ArraySpec((R, None), low=0, high=2),
            "rng.numpy_keys": ArraySpec((R, 624), "u"),
        }
        for key, (shape, kind) in self.adam.checkpoint_shapes().items():
            schema[f"adam.{key}"] = ArraySpec(shape, kind, low=0 if "sq" in key or kind == "i"
                                              else None)  # fmt: skip
        if self.prioritized:
            schema["per.sums"] = ArraySpec(self.tree.sums.shape, "f", low=0)
            schema["per.mins"] = ArraySpec(self.tree.mins.shape, "f", low=0, finite=False)
            schema["per.max_priority"] = ArraySpec((R,), "f", low=0)
            schema["per.new_priority"] = ArraySpec((R,), "f", low=0)
            schema["per.n_sampled"] = ArraySpec((R,), "i", low=0)
        return schema

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Every run's state between pieces: parameters, target networks, Adam moments and
        step counts, counters, the filled part of the replay memories (and PER's sum trees),
        and the generators each run draws from (numpy's legacy stream of exploration and
        replay sampling, the action space's, PER's)."""
        from cobelrun.checkpoint import generator_state

        n = self._replay_kept(self.pos, self.full)
        arrays: dict[str, np.ndarray] = {
            "params": self.flat.detach().cpu().numpy().copy(),
            "target": self.flat_target.detach().cpu().numpy().copy(),
            "num_timesteps": self.num_timesteps.copy(),
            "n_calls": self.n_calls.copy(),
            "replay.pos": self.pos.copy(),
            "replay.full": self.full.copy(),
            "replay.obs": self.buf_obs[:, :n].cpu().numpy(),
            "replay.next_obs": self.buf_next[:, :n].cpu().numpy(),
            "replay.action": self.buf_action[:, :n].cpu().numpy(),
            "replay.reward": self.buf_reward[:, :n].cpu().numpy(),
            "replay.done": self.buf_done[:, :n].cpu().numpy(),
        }
        arrays.update({f"adam.{k}": v for k, v in self.adam.checkpoint_arrays().items()})
        numpy, keys = [], []
        for rs in self.np_rngs:
            _, key, pos, has_gauss, gauss = rs.get_state(legacy=True)
            keys.append(np.asarray(key, np.uint32))
            numpy.append({"pos": int(pos), "has_gauss": int(has_gauss),
                          "cached_gaussian": float(gauss)})  # fmt: skip
        arrays["rng.numpy_keys"] = np.stack(keys)
        meta: dict[str, Any] = {
            "numpy": numpy,
            "action_space": [generator_state(sp.np_random) for sp in self.spaces],
            "per_rngs": [generator_state(g) for g in self.per_rngs],
        }
        if self.prioritized:
            arrays["per.sums"] = self.tree.sums.copy()
            arrays["per.mins"] = self.tree.mins.copy()
            arrays["per.max_priority"] = self.max_priority.copy()
            arrays["per.new_priority"] = self.new_priority.copy()
            arrays["per.n_sampled"] = self.n_sampled.copy()
        return arrays, meta

    def restore_checkpoint(self, arrays: Any, meta: Any) -> None:
        """Restore :meth:`checkpoint_state` (arrays already checked against
        :meth:`checkpoint_schema`); ValueError, with nothing changed, if the rest does not
        fit."""
        from cobelrun.checkpoint import set_generator_state

        R = self.R
        pos = np.asarray(arrays["replay.pos"], np.int64)
        full = np.asarray(arrays["replay.full"], bool)
        n = self._replay_kept(pos, full)
        for key in ("obs", "next_obs", "action", "reward", "done"):
            if arrays[f"replay.{key}"].shape[1] != n:
                raise ValueError(f"replay.{key}: expected {n} slots, got "
                                 f"{arrays[f'replay.{key}'].shape[1]}")  # fmt: skip
        numpy = meta.get("numpy") if isinstance(meta, dict) else None
        lists = [meta.get(k) for k in ("action_space", "per_rngs")] if numpy else []
        if not isinstance(numpy, list) or any(not isinstance(v, list) or len(v) != R
                                              for v in [numpy, *lists]):  # fmt: skip
            raise ValueError(f"expected the generators of {R} runs")
        states = []
        for r, st in enumerate(numpy):
            if not isinstance(st, dict):
                raise ValueError(f"run {r}: numpy: expected an MT19937 state")
            state = ("MT19937", np.asarray(arrays["rng.numpy_keys"][r], np.uint32),
                     int(st.get("pos", -1)), int(st.get("has_gauss", 0)),
                     float(st.get("cached_gaussian", 0.0)))  # fmt: skip
            try:
                np.random.RandomState().set_state(state)
            except (ValueError, TypeError) as exc:
                raise ValueError(f"run {r}: numpy: not a valid MT19937 state ({exc})") from None
            states.append(state)
        for what, gens in (("action_space", [sp.np_random for sp in self.spaces]),
                           ("per_rngs", self.per_rngs)):  # fmt: skip
            for r, (g, st) in enumerate(zip(gens, meta[what], strict=True)):
                probe = np.random.Generator(type(g.bit_generator)())
                set_generator_state(probe, st, f"run {r}: {what}")
        # everything checked: restore
        dev = self.device
        with torch.no_grad():
            self.flat.copy_(torch.as_tensor(np.asarray(arrays["params"], np.float32)))
            self.flat_target.copy_(torch.as_tensor(np.asarray(arrays["target"], np.float32)))
            obs_dtype = self.buf_obs.dtype
            for buf, key in ((self.buf_obs, "obs"), (self.buf_next, "next_obs")):
                buf.zero_()
                buf[:, :n] = torch.as_tensor(arrays[f"replay.{key}"]).to(dev, obs_dtype)
            for buf, key in ((self.buf_action, "action"), (self.buf_reward, "reward"),
                             (self.buf_done, "done")):  # fmt: skip
                buf.zero_()
                buf[:, :n] = torch.as_tensor(arrays[f"replay.{key}"]).to(dev, buf.dtype)
        self.adam.restore_arrays({k[len("adam.") :]: v for k, v in arrays.items()
                                  if k.startswith("adam.")})  # fmt: skip
        self.num_timesteps = np.asarray(arrays["num_timesteps"], np.int64).copy()
        self.n_calls = np.asarray(arrays["n_calls"], np.int64).copy()
        self.pos, self.full = pos.copy(), full.copy()
        for rs, state in zip(self.np_rngs, states, strict=True):
            rs.set_state(state)
        for sp, st in zip(self.spaces, meta["action_space"], strict=True):
            set_generator_state(sp.np_random, st, "action space")
        for g, st in zip(self.per_rngs, meta["per_rngs"], strict=True):
            set_generator_state(g, st, "PER generator")
        if self.prioritized:
            self.tree.sums[:] = arrays["per.sums"]
            self.tree.mins[:] = arrays["per.mins"]
            self.max_priority = np.asarray(arrays["per.max_priority"], np.float64).copy()
            self.new_priority = np.asarray(arrays["per.new_priority"], np.float64).copy()
            self.n_sampled = np.asarray(arrays["per.n_sampled"], np.int64).copy()
        self.version += 1  # cached predictions are stale
        self._cache = None

    # -- trials ----------------------------------------------------------------------------
    def run_phase(
        self,
        envs: Sequence[gym.Env],
        n_trials: int,
        max_steps: int,
        learn: bool,
        callbacks: Sequence[Sequence[TrialCallback]],
        views: Sequence[Any],
    ) -> list[TrialBatch]:
        """``n_trials`` trials (at most ``max_steps`` steps each) of every run in lock-step;
        one :class:`TrialBatch` per run. ``callbacks[r]`` (trial-end hooks) see ``views[r]``.

        Learning follows the sequential agent's SB3 loop: the phase starts with a reset, after
        every step come the target update and the gradient steps, an ended trial's env is
        reset at once (as SB3's vectorised env does) and a run stops after its last trial
        (without the reset after it, as the sequential agent's TrialRecorder).
        Without learning it is the base loop: greedy or ``test_epsilon``-greedy actions.
        """
        R = self.R
        posed = [isinstance(e.unwrapped, Posed) for e in envs]
        finished: list[list[dict[str, Any]]] = [[] for _ in range(R)]
        current: list[dict[str, Any] | None] = [None] * R
        obs = np.zeros((R, *self.obs_shape), self.obs_dtype)
        active = np.full(R, n_trials > 0)
        eps = self.epsilon if learn else self.test_epsilon

        def begin(r: int) -> None:
            o, info = envs[r].reset()
            obs[r] = self._obs_array(o)
            s = state_of(o, info)
            pose = [np.array(envs[r].unwrapped.agent_pose(), np.float64)] if posed[r] else None
            current[r] = {"states": [s], "actions": [], "rewards": [], "terminated": False,
                          "poses": pose}  # fmt: skip
            for cb in callbacks[r]:
                cb.on_trial_start(views[r], len(finished[r]), s)

        for r in np.flatnonzero(active):
            begin(r)
        while active.any():
            runs = np.flatnonzero(active)
            actions = np.zeros(R, np.int64)
            greedy_runs = []
            for r in runs:
                # SB3's DQN holds exploration_rate 0.0 until its first step ends, so a run's very
                # first learning step is greedy (its uniform is still drawn)
                run_eps = eps if not learn or self.n_calls[r] > 0 else 0.0
                if learn and self.num_timesteps[r] < self.learning_starts:
                    actions[r] = self.spaces[r].sample()
                elif (learn or eps > 0) and self.np_rngs[r].rand() < run_eps:
                    actions[r] = self.spaces[r].sample()
                else:
                    greedy_runs.append(r)
            if greedy_runs:  # the networks' choices (no random draws: after them is the same)
                greedy = np.asarray(greedy_runs)
                actions[greedy] = self._greedy(obs, greedy)
            nxt = obs.copy()
            rewards = np.zeros(R)
            dones = np.zeros(R, bool)
            ended = np.zeros(R, bool)
            for r in runs:
                o2, rew, term, trunc, info = envs[r].step(int(actions[r]))
                cur = current[r]
                assert cur is not None
                cur["states"].append(state_of(o2, info))
                cur["actions"].append(int(actions[r]))
                cur["rewards"].append(float(rew))
                if cur["poses"] is not None:
                    cur["poses"].append(np.array(envs[r].unwrapped.agent_pose(), np.float64))
                trunc = bool(trunc) or len(cur["actions"]) >= max_steps
                nxt[r] = self._obs_array(o2)
                rewards[r], dones[r] = float(rew), bool(term)  # SB3: done and not a timeout
                if term or trunc:
                    ended[r] = True
                    cur["terminated"] = bool(term)
                    finished[r].append(cur)
                    current[r] = None
                    for cb in callbacks[r]:  # before this step's update, as in SB3's loop
                        cb.on_trial_end(views[r], len(finished[r]) - 1, cur)
            if learn:
                self.num_timesteps[runs] += 1
                self._store(runs, obs[runs], nxt[runs], actions[runs], rewards[runs], dones[runs])
                self.n_calls[runs] += 1
                due = runs[self.n_calls[runs] % self.target_update_interval == 0]
                if len(due):
                    self._target_update(due)
                train = np.zeros(R, bool)
                train[runs] = self.num_timesteps[runs] > self.learning_starts
                n_steps = np.where(train, self.gradient_steps + self.trial_end_updates * ended, 0)
                for k in range(int(n_steps.max(initial=0))):
                    self._gradient_step(n_steps > k)
            obs = np.where(ended.reshape(-1, *([1] * len(self.obs_shape))), obs, nxt)
            for r in np.flatnonzero(ended):
                last = len(finished[r]) >= n_trials
                if last:  # no reset after the call's last trial (as the sequential agent)
                    active[r] = False
                else:
                    begin(r)
        return [TrialBatch.from_trials(f) for f in finished]


class DQNRunView:
    """Run ``run`` of a :class:`BatchedDQN`, seen as one DQN agent: what monitors ask of an
    agent (``predict``, ``layer_names``, ``activations``) and what the recorder saves
    (``get_state`` / ``saved_meta``: the same file a sequential ``DQNAgent`` writes, so
    ``agent.load_from`` continues a batched run with either path)."""

    def __init__(self, batch: BatchedDQN, run: int) -> None:
        self.batch, self.run = batch, run
        self._template = batch.template

    def _x(self, observations: Any) -> np.ndarray:
        b = self.batch
        obs = np.asarray(observations)
        if b.discrete_obs:
            idx = obs.reshape(-1).astype(np.int64)
            return np.eye(b.obs_dim, dtype=np.float32)[idx]
        return obs.astype(np.float32).reshape(-1, b.obs_dim)

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Q values ``(n, n_actions)`` of a batch of observations."""
        return self.batch.run_forward(self.run, self._x(observations))

    def layer_names(self) -> list[str]:
        return self._template.layer_names()

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        """Outputs of the named layers (``DQNAgent``'s names: ``q_net.K``, the flattened input
        ``features_extractor.flatten`` and ``q``)."""
        known = self.layer_names()
        unknown = [name for name in layers if name not in known]
        if unknown:
            raise ConfigError(f"unknown layer(s) {unknown}; this agent has: {', '.join(known)}")
        x = self._x(observations)
        keep: list[torch.Tensor] = []
        q = self.batch.run_forward(self.run, x, keep)
        out: dict[str, np.ndarray] = {}
        for name in layers:
            if name == "q":
                out[name] = q
            elif name.startswith("q_net."):
                out[name] = keep[int(name.split(".")[1])][0].cpu().numpy()
            else:  # the flatten extractor: the input itself
                out[name] = x.reshape(len(x), -1)
        return out

    # -- saving: DQNAgent's file layout --------------------------------------------------------
    def state_schema(self) -> dict[str, ArraySpec]:
        return self._template.state_schema()

    def get_state(self) -> dict[str, np.ndarray]:
        b, r = self.batch, self.run
        arrays: dict[str, np.ndarray] = {}
        for prefix, params in (("policy.q_net.q_net", b.params),
                               ("policy.q_net_target.q_net", b.layers(b.flat_target))):  # fmt: skip
            for i in range(len(params) // 2):
                w = params[2 * i][r].detach().cpu().numpy().T.copy()
                arrays[f"{prefix}.{2 * i}.weight"] = w
                arrays[f"{prefix}.{2 * i}.bias"] = (
                    params[2 * i + 1][r, 0].detach().cpu().numpy().copy()
                )
        # stacked (in, out) weights and (1, out) biases -> torch.nn.Linear's (out, in) and (out,)
        return self._optimizer_and_counters(
            arrays, lambda j, t: t.T if j % 2 == 0 else t[0], "batched DQN"
        )

    def _optimizer_and_counters(
        self,
        arrays: dict[str, np.ndarray],
        layout: Callable[[int, np.ndarray], np.ndarray],
        what: str,
    ) -> dict[str, np.ndarray]:
        """``arrays`` (the run's weights) completed with the run's Adam step count and moments
        per parameter (``layout(j, moment)``: parameter ``j``'s moment in ``DQNAgent``'s
        shape) and counters, checked against ``DQNAgent``'s file layout."""
        b, r = self.batch, self.run
        ((exp_avg, exp_avg_sq),) = b.adam.moments(r)
        moments = zip(b.layers(exp_avg[None]), b.layers(exp_avg_sq[None]), strict=True)
        for j, (m, v) in enumerate(moments):
            arrays[f"optimizer.{j}.step"] = np.array(float(b.adam_steps[r]), np.float32)
            arrays[f"optimizer.{j}.exp_avg"] = layout(j, m[0].detach().cpu().numpy()).copy()
            arrays[f"optimizer.{j}.exp_avg_sq"] = layout(j, v[0].detach().cpu().numpy()).copy()
        arrays["num_timesteps"] = np.array(b.num_timesteps[r], np.int64)
        arrays["n_calls"] = np.array(b.n_calls[r], np.int64)
        schema = self.state_schema()
        if set(arrays) != set(schema):  # the SB3 policy's layout changed under us
            raise RuntimeError(
                f"{what} state keys differ from DQNAgent's: {sorted(set(schema) ^ set(arrays))}"
            )
        return arrays

    def hyperparameters(self) -> dict[str, Any]:
        return self._template.hyperparameters()

    def saved_meta(self) -> dict[str, Any]:
        return self._template.saved_meta()


def steps_budget(phases: Sequence[Any], default_max_steps: int) -> int:
    """Environment steps a run can take in the learning phases (replay slots it can fill)."""
    return sum(int(p.trials) * int(p.max_steps or default_max_steps) for p in phases if p.learning)
