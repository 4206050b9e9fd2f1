"""R runs of Dyna-DQN or Dyna-DSR (:mod:`cobelrun.agents.dyna_dqn`) as one batched computation.

Each run is a real agent built from its own seed (:class:`~cobelrun.agents.dyna_dqn.DynaDQN`
or :class:`~cobelrun.agents.dyna_dsr.DynaDSR`): it keeps its random generator, its tabular
model memory and its observation matrix, and draws exactly what a sequential run draws, in
the same order (action selection, replay sampling, Dyna-DSR's tie-break noise). Only the
networks are stacked: :class:`StackedMLP` holds every run's multi-head MLP as one
contiguous ``(R, heads, in, out)`` tensor per layer (viewed as ``(R * heads, in, out)``), so
one ``torch.baddbmm`` per layer evaluates all runs and heads, one backward pass gives every
run's gradient and one fused Adam step (:class:`~cobelrun.agents.batched_ops.RowAdam`: a step
count per run) trains them all. A step computes only the runs that learn in it; runs whose
trial or phase is over are left exactly as they are. The update rules are those of
``DynaDQN.update`` / ``DynaDSR.update``, per run; the loss of each run is its own mean squared
error, so runs do not interact. With one-hot observations the networks run on every state
once instead of on every replayed sample (:meth:`BatchedDyna.update`).

The per-run agents double as what monitors and the recorder see
(:class:`DynaRunView`): before an agent is asked for activations, predictions or its saved
state, its networks get the run's current weights.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from cobelrun.agents.base import ArraySpec, TrialCallback, state_of
from cobelrun.agents.batched_ops import RowAdam, activation
from cobelrun.agents.networks import TorchMLP
from cobelrun.agents.policy import allowed_next, select
from cobelrun.envs.base import Posed
from cobelrun.records import TrialBatch

__all__ = ["BatchedDyna", "DynaRunView", "StackedMLP", "unsupported"]


def unsupported(agent: Any) -> str | None:
    """Why a built Dyna agent cannot be batched, or None."""
    nets = agent._all_networks()
    if not all(isinstance(n, TorchMLP) for n in nets.values()):
        return f"agent.backend {agent.backend!r} (batched runs use the torch MLP)"
    return None


def group_by_head(actions: np.ndarray, heads: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices grouped by head: ``idx[r, h, m]`` is the ``m``-th sample of run ``r``
    with ``actions[r, i] == h`` (padded with index 0 where ``valid`` is False), ``M`` the
    largest group."""
    R, _n = actions.shape
    order = np.argsort(actions, axis=1, kind="stable")
    counts = (actions[:, :, None] == np.arange(heads)).sum(axis=1)  # (R, H)
    m = max(int(counts.max()), 1)
    starts = np.cumsum(counts, axis=1) - counts
    j = np.arange(m)
    valid = j < counts[:, :, None]
    pos = np.where(valid, starts[:, :, None] + j, 0)
    idx = order[np.arange(R)[:, None, None], pos]
    return idx, valid.astype(np.float32)


class StackedMLP:
    """The same :class:`~cobelrun.agents.networks.TorchMLP` shape for R runs, stacked.

    :attr:`leaves` are ``[w0, b0, w1, b1, ...]`` with ``w`` ``(R, H, in, out)`` and ``b``
    ``(R, H, 1, out)`` (H heads per run), each one contiguous tensor (so that ``(R * H, in,
    out)`` is a view, not a copy), :attr:`target` the target networks alike. Adam is
    ``torch.optim.Adam`` with a step count per run (:class:`RowAdam`).
    """

    def __init__(self, nets: Sequence[TorchMLP], device: torch.device) -> None:
        first = nets[0]
        self.R, self.H = len(nets), first.n_heads
        self.act = activation(first.activation)
        self.lr = first.learning_rate
        group = first.optimizer.param_groups[0]
        self.betas = (float(group["betas"][0]), float(group["betas"][1]))
        self.eps = float(group["eps"])
        self.has_bias = first.bias
        self.keys = list(first.get_weights())  # w0, w1, ..., b0, b1, ...
        self.n_layers = len(first.weights)
        weights = [n.get_weights() for n in nets]
        self.leaves = [
            torch.stack([torch.as_tensor(w[k]) for w in weights]).to(device).requires_grad_()
            for k in self._order()
        ]  # (R, H, in, out) / (R, H, 1, out)
        self.target = [t.detach().clone() for t in self.leaves]
        self.optimizer = RowAdam([t.detach() for t in self.leaves], self.lr, self.betas, self.eps)
        self.device = device

    def _order(self) -> list[str]:
        out = []
        for i in range(self.n_layers):
            out.append(f"w{i}")
            if self.has_bias:
                out.append(f"b{i}")
        return out

    def forward(self, layers: Sequence[torch.Tensor], x: torch.Tensor | None,
                keep: dict[str, torch.Tensor] | None = None, *,
                states: bool = False) -> torch.Tensor:  # fmt: skip
        """Outputs ``(R', H, n, out)`` of inputs ``x`` ``(R', n, in)`` (every head sees every
        input) or ``(R', H, n, in)`` (each head its own inputs). With ``states``, ``x`` holds
        indices ``(R', n)`` or ``(R', H, n)`` of one-hot inputs: the first layer is then a row
        lookup, which equals the matrix product with a one-hot vector exactly; ``x=None``
        with ``states``: every one-hot input in order (``n = in``; the first layer's
        pre-activations are its weights)."""
        step = 2 if self.has_bias else 1
        first = 0
        if states:
            w0 = layers[0]  # (R', H, in, out)
            if x is None:
                rows, h = w0.shape[0], w0
            else:
                rows = x.shape[0]
                r_i = torch.arange(rows, device=x.device)[:, None, None]
                h_i = torch.arange(self.H, device=x.device)[None, :, None]
                h = w0[r_i, h_i, x if x.dim() == 3 else x[:, None, :]]  # (R', H, n, out)
            if self.has_bias:
                h = h + layers[1]
            n = h.shape[2]
            h = h.reshape(rows * self.H, n, h.shape[-1])
            first = 1
            if self.n_layers > 1:
                h = self.act(h)
                if keep is not None:
                    keep["layer1"] = h
        else:
            assert x is not None
            rows = x.shape[0]
            n = x.shape[2] if x.dim() == 4 else x.shape[1]
            if x.dim() == 4:  # each head its own inputs
                h = x.reshape(rows * self.H, n, x.shape[3])
            else:
                h = x[:, None].expand(rows, self.H, n, x.shape[2])
                h = h.reshape(rows * self.H, n, x.shape[2])
        for i in range(first, self.n_layers):
            w = layers[step * i].reshape(rows * self.H, *layers[step * i].shape[2:])
            if self.has_bias:
                b = layers[step * i + 1].reshape(rows * self.H, 1, -1)
                h = torch.baddbmm(b, h, w)
            else:
                h = torch.bmm(h, w)
            if i < self.n_layers - 1:
                h = self.act(h)
                if keep is not None:
                    keep[f"layer{i + 1}"] = h
        h = h.reshape(rows, self.H, n, h.shape[-1])
        if keep is not None:
            keep["output"] = h
        return h

    def weights_of(self, run: int, *, target: bool = False) -> dict[str, np.ndarray]:
        """Run ``run``'s weights (or its target network's) as ``TorchMLP.get_weights`` names
        them."""
        src = self.target if target else self.leaves
        return {k: v[run].detach().cpu().numpy().copy()
                for k, v in zip(self._order(), src, strict=True)}  # fmt: skip

    # -- checkpoints --------------------------------------------------------------------------
    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        """Stacked online and target layers and the optimizer's arrays (:class:`RowAdam`)."""
        schema: dict[str, ArraySpec] = {}
        for k, t in zip(self._order(), self.leaves, strict=True):
            schema[f"online.{k}"] = ArraySpec(tuple(t.shape))
            schema[f"target.{k}"] = ArraySpec(tuple(t.shape))
        for key, (shape, kind) in self.optimizer.checkpoint_shapes().items():
            schema[f"adam.{key}"] = ArraySpec(shape, kind, low=0 if "sq" in key or kind == "i"
                                              else None)  # fmt: skip
        return schema

    def checkpoint_state(self) -> dict[str, np.ndarray]:
        arrays = {}
        for k, t, g in zip(self._order(), self.leaves, self.target, strict=True):
            arrays[f"online.{k}"] = t.detach().cpu().numpy().copy()
            arrays[f"target.{k}"] = g.detach().cpu().numpy().copy()
        arrays.update({f"adam.{k}": v for k, v in self.optimizer.checkpoint_arrays().items()})
        return arrays

    def restore_checkpoint(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore :meth:`checkpoint_state` (shapes already checked)."""
        with torch.no_grad():
            for k, t, g in zip(self._order(), self.leaves, self.target, strict=True):
                t.copy_(torch.as_tensor(np.asarray(arrays[f"online.{k}"], np.float32)))
                g.copy_(torch.as_tensor(np.asarray(arrays[f"target.{k}"], np.float32)))
        self.optimizer.restore_arrays({k[len("adam.") :]: v for k, v in arrays.items()
                                       if k.startswith("adam.")})  # fmt: skip

    def adam(self, grads: Sequence[torch.Tensor], runs: np.ndarray) -> None:
        """One Adam step of the runs ``runs`` (``grads[k][i]``: run ``runs[i]``'s gradient of
        layer ``k``; the other runs keep parameters and moments)."""
        self.optimizer.step(grads, runs)

    def blend_target(self, tau: float, train: np.ndarray) -> None:
        """``target <- target + tau (online - target)`` (``TorchMLP.blend_from``) per run."""
        with torch.no_grad():
            if train.all():
                for t, p in zip(self.target, self.leaves, strict=True):
                    t.lerp_(p, tau)
                return
            idx = torch.as_tensor(np.flatnonzero(train), device=self.device)
            for t, p in zip(self.target, self.leaves, strict=True):
                t[idx] = torch.lerp(t[idx], p[idx], tau)


class BatchedDyna:
    """R Dyna-DQN or Dyna-DSR runs: per-run agents for draws and memory, stacked networks.

    Parameters
    ----------
    agents
        One :class:`~cobelrun.agents.dyna_dqn.DynaDeepAgent` per run, each built from its
        run's seed.
    successor
        Dyna-DSR's successor features and reward model (else Dyna-DQN's Q network).
    """

    def __init__(self, agents: Sequence[Any], *, successor: bool) -> None:
        self.agents = list(agents)
        self.R = len(agents)
        self.dsr = bool(successor)
        a0 = agents[0]
        self.device = torch.device("cpu")
        self.version = 0
        self._synced = [-1] * self.R
        if self.dsr:
            self.net = StackedMLP([a.sr for a in agents], self.device)
            self.reward = StackedMLP([a.reward_model for a in agents], self.device)
        else:
            self.net = StackedMLP([a.q_net for a in agents], self.device)
            self.reward = None
        self.gamma, self.tau = a0.gamma, a0.target_tau
        self.obs = torch.as_tensor(
            np.stack([a.obs for a in agents]), device=self.device
        )  # (R, S, d)
        # one-hot observations (Fig. 7's): first layers are row lookups by state index
        eye = np.eye(a0.n_states, dtype=np.float32)
        self.onehot = all(a.obs.shape == eye.shape and np.array_equal(a.obs, eye) for a in agents)

    def view(self, run: int) -> DynaRunView:
        return DynaRunView(self, run)

    # -- checkpoints (:mod:`cobelrun.checkpoint`, between pieces of a phase) --------------------
    def _stacks(self) -> dict[str, StackedMLP]:
        return {"net": self.net} if self.reward is None else {"net": self.net,
                                                              "reward": self.reward}  # fmt: skip

    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        """Each run's agent (``run<r>.<key>``: its generator, model memory, ... as a sequential
        checkpoint holds them) and the stacked networks with their Adam state."""
        schema: dict[str, ArraySpec] = {}
        for r, agent in enumerate(self.agents):
            schema.update({f"run{r}.{k}": v for k, v in agent.checkpoint_schema().items()})
        for name, stack in self._stacks().items():
            schema.update({f"{name}.{k}": v for k, v in stack.checkpoint_schema().items()})
        return schema

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays: dict[str, np.ndarray] = {}
        metas = []
        for r in range(self.R):
            own, meta = self.sync(r).checkpoint_state()
            arrays.update({f"run{r}.{k}": v for k, v in own.items()})
            metas.append(meta)
        for name, stack in self._stacks().items():
            arrays.update({f"{name}.{k}": v for k, v in stack.checkpoint_state().items()})
        return arrays, {"runs": metas}

    def restore_checkpoint(self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
        """Restore :meth:`checkpoint_state`; ValueError if a run's agent state does not fit
        (the runs before it are then restored already: the caller drops the learner)."""
        metas = meta.get("runs") if isinstance(meta, Mapping) else None
        if not isinstance(metas, list) or len(metas) != self.R:
            raise ValueError(f"expected the states of {self.R} runs")
        for r, agent in enumerate(self.agents):
            prefix = f"run{r}."
            own = {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}
            agent.restore_checkpoint(own, metas[r] if isinstance(metas[r], Mapping) else {})
        for name, stack in self._stacks().items():
            prefix = f"{name}."
            stack.restore_checkpoint({k[len(prefix) :]: v for k, v in arrays.items()
                                      if k.startswith(prefix)})  # fmt: skip
        self.version += 1
        self._synced = [-1] * self.R

    # -- weights back into the per-run agents -------------------------------------------------
    def sync(self, run: int) -> Any:
        """Run ``run``'s agent with the run's current weights."""
        agent = self.agents[run]
        if self._synced[run] != self.version:
            if self.dsr:
                agent.sr.set_weights(self.net.weights_of(run))
                agent.sr_target.set_weights(self.net.weights_of(run, target=True))
                agent.reward_model.set_weights(self.reward.weights_of(run))  # type: ignore[union-attr]
            else:
                agent.q_net.set_weights(self.net.weights_of(run))
                agent.q_target.set_weights(self.net.weights_of(run, target=True))
            self._synced[run] = self.version
        return agent

    # -- values --------------------------------------------------------------------------------
    def _w(self, layers: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        """Dyna-DSR's reward weights ``(R', d)`` (of ``layers``, default every run's)."""
        assert self.reward is not None and not self.reward.has_bias
        w = (self.reward.leaves if layers is None else layers)[0].detach()
        return w.reshape(w.shape[0], -1)

    def q_of_states(self, states: np.ndarray) -> np.ndarray:
        """Action values ``(R, A)`` of one state per run."""
        with torch.no_grad():
            out = self._net(self.net, self.net.leaves, states[:, None])  # (R, H, 1, out)
            if self.dsr:
                return torch.einsum("rhd,rd->rh", out[:, :, 0], self._w()).numpy()
            return out[:, 0, 0].numpy()

    def _net(self, net: StackedMLP, layers: Sequence[torch.Tensor], states: np.ndarray,
             obs: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
        """``net`` on the observations of ``states`` ``(R', n)`` or ``(R', H, n)`` (``obs``:
        the runs' observation matrices, default every run's)."""
        s_t = torch.as_tensor(states, device=self.device)
        if self.onehot:
            return net.forward(layers, s_t, states=True)
        obs = self.obs if obs is None else obs
        rows = torch.arange(obs.shape[0])
        x = obs[rows[:, None], s_t] if s_t.dim() == 2 else obs[rows[:, None, None], s_t]
        return net.forward(layers, x)

    # -- learning ------------------------------------------------------------------------------
    def update(self, S: np.ndarray, A: np.ndarray, rew: np.ndarray, S2: np.ndarray,
               term: np.ndarray, train: np.ndarray) -> None:  # fmt: skip
        """One replay update of every run in ``train`` on its ``(n,)`` experiences (rows of
        ``S, A, ...``; rows of other runs are ignored)."""
        net, rw = self.net, self.reward
        runs = np.flatnonzero(train)
        if len(runs) == 0:
            return
        # only the runs that learn this step are computed: the others' rows are left out
        # (their trials or phases are over; runs wait for the slowest in lock-step)
        if len(runs) == self.R:
            online, target_net, obs = net.leaves, net.target, self.obs
            rw_online = None if rw is None else rw.leaves
        else:
            sel = torch.as_tensor(runs)
            S, A, rew, S2, term = (v[runs] for v in (S, A, rew, S2, term))
            online = [t.detach()[sel].requires_grad_() for t in net.leaves]
            target_net = [t[sel] for t in net.target]
            obs = self.obs[sel]
            rw_online = (
                None if rw is None else [t.detach()[sel].requires_grad_() for t in rw.leaves]
            )
        R = len(runs)
        rows = torch.arange(R)[:, None]
        ar = np.arange(R)[:, None]
        s2_t = torch.as_tensor(S2)
        x2 = obs[rows, s2_t]  # (R, n, d)
        a_t = torch.as_tensor(A)
        n = S.shape[1]
        agents = [self.agents[r] for r in runs]
        # one-hot observations: every state's outputs once (n_states rows per head) instead
        # of every sample's (n rows); a sample's values are its state's row
        table = self.onehot
        with torch.no_grad():
            if table:
                nxt = net.forward(target_net, None, states=True)  # (R, H, S, out)
            else:
                nxt = self._net(net, target_net, S2, obs)  # (R, H, n, out)
        if self.dsr:
            w = self._w(rw_online)
            q_next = torch.einsum("rhnd,rd->rnh", nxt, w).numpy()
        else:
            q_next = nxt[:, 0].numpy()  # (R, n or S, A)
        if table:
            q_next = q_next[ar, S2]  # (R, n, A)
        best = np.zeros((R, n), np.int64)
        y = np.zeros((R, n), np.float32)
        for r, ag in enumerate(agents):
            qn = q_next[r]
            if ag.use_mask:
                qn = np.where(allowed_next(ag._loop_mask, S2[r]), qn, -np.inf)
            if self.dsr:  # greedy next action, ties broken at random (DynaDSR.update's draw)
                noise = ag.rng.random(qn.shape) * 1e-9
                best[r] = np.argmax(np.where(np.isfinite(qn), qn + noise, -np.inf), axis=1)
            else:
                cont = np.ones_like(rew[r]) if ag.always_bootstrap else 1.0 - term[r]
                y[r] = rew[r] + self.gamma * qn.max(axis=1) * cont
        if self.dsr:
            cont = np.stack([np.ones(n) if agents[r].always_bootstrap else 1.0 - term[r]
                             for r in range(R)])  # fmt: skip
            b_t = torch.as_tensor(best)
            m_best = nxt[rows, b_t, s2_t if table else torch.arange(n)[None]]  # (R, n, d)
            target = (
                x2 + self.gamma * torch.as_tensor(cont, dtype=torch.float32)[..., None] * m_best
            )
            d = target.shape[-1]
            if table:
                # only the taken action's head is trained on a sample; the squared error
                # summed over samples is, per (head, state) row with c samples whose targets
                # sum to T, c |out|^2 - 2 out.T (+ a constant): the same gradient
                out = net.forward(online, None, states=True)  # (R, H, S, d)
                n_states = out.shape[2]
                key = torch.as_tensor(A * n_states + S)  # (R, n): row (head, state)
                count = torch.zeros(R, net.H * n_states).scatter_add_(1, key, torch.ones(R, n))
                tsum = torch.zeros(R, net.H * n_states, d).scatter_add_(
                    1, key[..., None].expand(R, n, d), target
                )
                o = out.reshape(R, net.H * n_states, d)
                loss_sr = ((count[..., None] * o - 2 * tsum) * o).sum(dim=(1, 2)) / (n * d)
            else:
                # each head runs on its own samples (padded to the largest group) instead of
                # all heads on all samples
                idx, valid = group_by_head(A, net.H)  # (R, H, M)
                rows3 = torch.arange(R)[:, None, None]
                idx_t = torch.as_tensor(idx)
                out = self._net(net, online, S[ar[..., None], idx], obs)  # (R, H, M, d)
                err = ((out - target[rows3, idx_t]) ** 2).sum(dim=3) * torch.as_tensor(valid)
                loss_sr = err.sum(dim=(1, 2)) / (n * d)
            assert rw is not None and rw_online is not None
            pr = self._net(rw, rw_online, S2, obs)[:, 0, :, 0]  # (R, n)
            loss_r = ((pr - torch.as_tensor(rew, dtype=torch.float32)) ** 2).mean(dim=1)
            grads = torch.autograd.grad((loss_sr + loss_r).sum(), [*online, *rw_online])
            net.adam(grads[: len(online)], runs)
            rw.adam(grads[len(online) :], runs)
        elif table:  # the same identity per (state, action) entry of the Q table
            out = net.forward(online, None, states=True)[:, 0]  # (R, S, A)
            n_states, d_out = out.shape[1], out.shape[2]
            key = torch.as_tensor(S * d_out + A)
            count = torch.zeros(R, n_states * d_out).scatter_add_(1, key, torch.ones(R, n))
            ysum = torch.zeros(R, n_states * d_out).scatter_add_(1, key, torch.as_tensor(y))
            o = out.reshape(R, n_states * d_out)
            loss = ((count * o - 2 * ysum) * o).sum(dim=1) / (n * d_out)
            grads = torch.autograd.grad(loss.sum(), online)
            net.adam(grads, runs)
        else:
            out = self._net(net, online, S, obs)[:, 0]  # (R, n, A)
            pred = out.gather(2, a_t[..., None])[..., 0]
            d_out = out.shape[-1]
            loss = ((pred - torch.as_tensor(y)) ** 2).sum(dim=1) / (n * d_out)
            grads = torch.autograd.grad(loss.sum(), online)
            net.adam(grads, runs)
        net.blend_target(self.tau, train)
        self.version += 1

    # -- trials ----------------------------------------------------------------------------------
    def run_phase(
        self,
        envs: Sequence[gym.Env],
        n_trials: int,
        max_steps: int,
        learn: bool,
        callbacks: Sequence[Sequence[TrialCallback]],
        views: Sequence[Any],
    ) -> list[TrialBatch]:
        """The base agent loop (``Agent._run``) for every run in lock-step: per trial a reset,
        then act, step, store and replay until the trial ends; finished runs wait."""
        R, agents = self.R, self.agents
        for ag, env in zip(agents, envs, strict=True):
            ag.env = env
            ag._loop_mask = ag._mask()
        posed = [isinstance(e.unwrapped, Posed) for e in envs]
        finished: list[list[dict[str, Any]]] = [[] for _ in range(R)]
        current: list[dict[str, Any] | None] = [None] * R
        obs: list[Any] = [None] * R
        infos: list[dict[str, Any]] = [{}] * R
        states = np.zeros(R, np.int64)
        active = np.full(R, n_trials > 0)
        need_reset = active.copy()
        n = agents[0].replay_batch + 1
        while active.any():
            for r in np.flatnonzero(need_reset & active):
                o, info = envs[r].reset()
                obs[r], infos[r] = o, info
                states[r] = state_of(o, info)
                pose = [np.array(envs[r].unwrapped.agent_pose(), np.float64)] if posed[r] else None
                current[r] = {"states": [int(states[r])], "actions": [], "rewards": [],
                              "terminated": False, "poses": pose}  # fmt: skip
                for cb in callbacks[r]:
                    cb.on_trial_start(views[r], len(finished[r]), int(states[r]))
                need_reset[r] = False
            runs = np.flatnonzero(active)
            q = self.q_of_states(states)
            S = np.zeros((R, n), np.int64)
            A = np.zeros((R, n), np.int64)
            rew = np.zeros((R, n))
            S2 = np.zeros((R, n), np.int64)
            term = np.zeros((R, n))
            ended = np.zeros(R, bool)
            for r in runs:
                ag = agents[r]
                s = int(states[r])
                allowed = ag._loop_mask[s] if ag.use_mask else None
                a = select(ag.rng, q[r], ag.policy, ag.epsilon, ag.beta, allowed)
                o2, rr, terminated, truncated, info2 = envs[r].step(a)
                s2, rr = state_of(o2, info2), float(rr)
                if learn:  # Any.observe: store, then replay the step + a sample
                    mem = ag.memory
                    mem.store(s, a, rr, s2, bool(terminated))
                    rs, ra = mem.sample(ag.rng, ag.replay_batch)
                    S[r] = np.concatenate([[s], rs])
                    A[r] = np.concatenate([[a], ra])
                    rew[r] = mem.reward[S[r], A[r]]
                    S2[r] = mem.next_state[S[r], A[r]]
                    term[r] = mem.terminal[S[r], A[r]]
                cur = current[r]
                assert cur is not None
                cur["states"].append(s2)
                cur["actions"].append(a)
                cur["rewards"].append(rr)
                if cur["poses"] is not None:
                    cur["poses"].append(np.array(envs[r].unwrapped.agent_pose(), np.float64))
                obs[r], infos[r], states[r] = o2, info2, s2
                if terminated or truncated or len(cur["actions"]) >= max_steps:
                    ended[r] = True
                    cur["terminated"] = bool(terminated)
            if learn:
                train = np.zeros(R, bool)
                train[runs] = True
                # each run's generator sees act -> sample -> (Dyna-DSR) tie-break noise, as
                # in the sequential agent, whatever the other runs do
                self.update(S, A, rew, S2, term, train)
            for r in np.flatnonzero(ended):
                cur = current[r]
                assert cur is not None
                finished[r].append(cur)
                current[r] = None
                for cb in callbacks[r]:
                    cb.on_trial_end(views[r], len(finished[r]) - 1, cur)
                if len(finished[r]) >= n_trials:
                    active[r] = False
                else:
                    need_reset[r] = True
        return [TrialBatch.from_trials(f) for f in finished]


class DynaRunView:
    """Run ``run`` of a :class:`BatchedDyna` as one agent (its per-run agent, synced)."""

    def __init__(self, batch: BatchedDyna, run: int) -> None:
        self.batch, self.run = batch, run

    def _agent(self) -> Any:
        return self.batch.sync(self.run)

    def predict(self, observations: np.ndarray) -> np.ndarray:
        return self._agent().predict(observations)

    def layer_names(self) -> list[str]:
        return self._agent().layer_names()

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        return self._agent().activations(observations, layers)

    def state_schema(self) -> Any:
        return self._agent().state_schema()

    def get_state(self) -> dict[str, np.ndarray]:
        return self._agent().get_state()

    def saved_meta(self) -> dict[str, Any]:
        return self._agent().saved_meta()
