"""Deep Q-network agent: stable-baselines3's DQN, trained and tested in trials.

CoBeL-RL's DQN agent wrapped keras-rl2 and used callbacks to train "for N trials" instead of
"for N steps" (paper, section 2.1.1). We wrap SB3's :class:`~stable_baselines3.DQN` the same way:

- every trial is an episode, capped at ``max_steps`` by
  :class:`~cobelrun.agents.sb3.TrialRecorder`, a thin gymnasium wrapper that also records each
  trial (states, actions, rewards, poses of ``Posed`` envs) as the base class's loop does, so
  monitors get the same :class:`~cobelrun.records.TrialBatch` as from every other agent;
- :meth:`DQNAgent.train` calls ``model.learn(total_timesteps=n_trials * max_steps,
  reset_num_timesteps=False)`` and :class:`TrialDQN` ends the rollout loop once ``n_trials``
  trials are finished. (Stopping from an SB3 ``BaseCallback._on_step`` would be the textbook
  way, but SB3 checks the callback *before* it stores the step's transition, so the last,
  usually rewarded, transition of the last trial would be lost; checking at the start of the
  next rollout keeps it and its gradient step.)
- the model acts with fixed exploration (``exploration_initial_eps = exploration_final_eps =
  epsilon``), as the original's ``EpsGreedyQPolicy``; tests run without learning through the
  base class's step loop (:meth:`DQNAgent.act` asks the model), greedy by default (keras-rl's
  ``test_policy``) or with ``test_epsilon``.
- :meth:`~cobelrun.agents.base.Agent.save` writes the policy's weights and the Adam state as
  plain arrays (no ``torch.save``, no pickle), checked on load like every agent's.

SB3 draws from numpy's and torch's *global* generators (exploration, replay sampling, weight
initialisation). The agent keeps its own copies of both states and swaps them in around every
call into SB3, so agents built from the same seed give identical trials, independent of what
ran before or in between, and no global state leaks out.

Importing this module imports torch and stable-baselines3 (the ``deep`` extra).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from cobelrun.agents.base import Agent, ArraySpec, SeedLike, TrialCallback
from cobelrun.agents.networks import set_torch_threads
from cobelrun.agents.per import PrioritizedDQN, PrioritizedReplayBuffer
from cobelrun.agents.sb3 import TrialDQN, TrialRecorder
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.records import TrialBatch

#: activation functions by config name
ACTIVATIONS: dict[str, type[torch.nn.Module]] = {
    "tanh": torch.nn.Tanh,
    "relu": torch.nn.ReLU,
    "elu": torch.nn.ELU,
    "sigmoid": torch.nn.Sigmoid,
    "linear": torch.nn.Identity,
}
POLICIES = ("auto", "MlpPolicy", "CnnPolicy", "MultiInputPolicy")
#: Fig. 6A's convolutional stack: [channels, kernel, stride] per layer, then dense 256
DEFAULT_CONVS = ((16, 8, 4), (32, 4, 2))


class ConvFeatures(BaseFeaturesExtractor):
    """Convolutions ``[channels, kernel, stride]`` (ReLU), flattened, then a dense ReLU layer.

    Default: Fig. 6A's conv 16@8x8/4 -> conv 32@4x4/2 -> dense 256 (FACTS.md).
    """

    def __init__(
        self,
        observation_space: gym.spaces.Box,
        convs: Sequence[Sequence[int]] = DEFAULT_CONVS,
        features_dim: int = 256,
    ) -> None:
        super().__init__(observation_space, features_dim)
        layers: list[torch.nn.Module] = []
        channels = observation_space.shape[0]
        for out, kernel, stride in convs:
            layers += [
                torch.nn.Conv2d(channels, int(out), int(kernel), int(stride)),
                torch.nn.ReLU(),
            ]
            channels = int(out)
        layers.append(torch.nn.Flatten())
        self.cnn = torch.nn.Sequential(*layers)
        with torch.no_grad():
            n_flat = self.cnn(torch.zeros(1, *observation_space.shape)).shape[1]
        self.linear = torch.nn.Sequential(torch.nn.Linear(n_flat, features_dim), torch.nn.ReLU())

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.linear(self.cnn(observations))


class DQNAgent(Agent):
    """DQN (Mnih et al. 2015) through stable-baselines3, trained in trials.

    Defaults are CoBeL-RL's DQN defaults (FACTS.md): 4 x dense 64 tanh, epsilon 0.3,
    gamma 0.8, batch 32, Adam 1e-3, soft target update 0.01, warm-up 100 steps.

    Parameters
    ----------
    env
        Environment with a ``Discrete`` action space and a ``Box`` (vector or image),
        ``Discrete`` or ``Dict`` observation space.
    epsilon
        Fixed exploration rate of the epsilon-greedy policy while training.
    test_epsilon
        Exploration rate in :meth:`test` (default 0: greedy, keras-rl's test policy).
    gamma
        Discount factor.
    learning_rate
        Adam learning rate.
    batch_size
        Transitions per gradient step.
    buffer_size
        Replay memory capacity (1: no memory, learn from the latest transition only).
    learning_starts
        Steps of random actions before learning starts (0: learn from the first step).
    train_freq, gradient_steps
        Gradient steps every ``train_freq`` environment steps (default 1 and 1: keras-rl's).
    tau, target_update_interval
        Target network update ``target <- tau * online + (1 - tau) * target`` every
        ``target_update_interval`` steps: soft (0.01 every step, default) or hard
        (``tau=1``, interval N).
    max_grad_norm
        Gradient-norm clipping (SB3's default 10).
    policy
        ``"auto"`` (``MultiInputPolicy`` for Dict, ``CnnPolicy`` for images, else
        ``MlpPolicy``) or one of those names.
    net_arch
        Hidden layer sizes of the Q head (default: [64, 64, 64, 64] on vectors, [] after a CNN).
    activation
        Hidden-layer activation: tanh (default), relu, elu, sigmoid, linear.
    convs, features_dim
        CNN layers ``[[channels, kernel, stride], ...]`` and the dense features after them
        (Fig. 6A's by default); used with ``CnnPolicy``.
    prioritized
        Use proportional prioritized experience replay (:mod:`cobelrun.agents.per`).
    per_alpha, per_beta, per_beta_steps, per_epsilon
        PER priority exponent, initial importance-sampling exponent (annealed linearly to 1
        over ``per_beta_steps`` gradient steps) and priority offset (Schaul et al. 2016).
    torch_threads
        torch intra-op threads set at construction (default 1; None: leave as is).
    device
        torch device (default ``"cpu"``).
    seed
        Seed of the agent's draws (network init, exploration, replay sampling).
    """

    observation_spaces = (gym.spaces.Box, gym.spaces.Discrete, gym.spaces.Dict)
    action_spaces = (gym.spaces.Discrete,)

    def __init__(
        self,
        env: gym.Env,
        *,
        epsilon: float = 0.3,
        test_epsilon: float = 0.0,
        gamma: float = 0.8,
        learning_rate: float = 1e-3,
        batch_size: int = 32,
        buffer_size: int = 10_000,
        learning_starts: int = 100,
        train_freq: int = 1,
        gradient_steps: int = 1,
        tau: float = 0.01,
        target_update_interval: int = 1,
        max_grad_norm: float = 10.0,
        policy: str = "auto",
        net_arch: Sequence[int] | None = None,
        activation: str = "tanh",
        convs: Sequence[Sequence[int]] | None = None,
        features_dim: int = 256,
        prioritized: bool = False,
        per_alpha: float = 0.6,
        per_beta: float = 0.4,
        per_beta_steps: int = 10_000,
        per_epsilon: float = 1e-6,
        torch_threads: int | None = 1,
        device: str = "cpu",
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        for name, value, lo, hi in (
            ("epsilon", epsilon, 0.0, 1.0),
            ("test_epsilon", test_epsilon, 0.0, 1.0),
            ("gamma", gamma, 0.0, 1.0),
            ("tau", tau, 0.0, 1.0),
            ("per_alpha", per_alpha, 0.0, 1.0),
            ("per_beta", per_beta, 0.0, 1.0),
        ):
            if not lo <= value <= hi:
                raise ConfigError(f"agent.{name} must be in [{lo}, {hi}], got {value}")
        for name, value, lo in (
            ("batch_size", batch_size, 1),
            ("buffer_size", buffer_size, 1),
            ("learning_starts", learning_starts, 0),
            ("train_freq", train_freq, 1),
            ("gradient_steps", gradient_steps, 1),
            ("target_update_interval", target_update_interval, 1),
            ("per_beta_steps", per_beta_steps, 1),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < lo:
                raise ConfigError(f"agent.{name} must be an integer >= {lo}, got {value!r}")
        if learning_rate <= 0:
            raise ConfigError(f"agent.learning_rate must be > 0, got {learning_rate}")
        if activation not in ACTIVATIONS:
            raise ConfigError(
                f"agent.activation {activation!r} is not known{suggest(activation, list(ACTIVATIONS))}; "
                f"allowed: {allowed_list(list(ACTIVATIONS))}"
            )
        if policy not in POLICIES:
            raise ConfigError(
                f"agent.policy {policy!r} is not known{suggest(policy, POLICIES)}; "
                f"allowed: {allowed_list(POLICIES)}"
            )
        set_torch_threads(torch_threads)
        self.epsilon, self.test_epsilon = float(epsilon), float(test_epsilon)
        self.prioritized = bool(prioritized)
        obs_space = env.observation_space
        image = is_image_space(obs_space)
        if policy == "auto":
            policy = (
                "MultiInputPolicy"
                if isinstance(obs_space, gym.spaces.Dict)
                else "CnnPolicy"
                if image
                else "MlpPolicy"
            )
        if policy == "CnnPolicy" and not image:
            raise ConfigError(
                "agent.policy CnnPolicy needs image observations (uint8 Box, H x W x C); "
                f"got {obs_space}"
            )
        if self.prioritized and isinstance(obs_space, gym.spaces.Dict):
            raise ConfigError("agent.prioritized replay does not support Dict observations")
        if net_arch is None:
            net_arch = [] if policy == "CnnPolicy" else [64, 64, 64, 64]
        policy_kwargs: dict[str, Any] = {
            "net_arch": [int(n) for n in net_arch],
            "activation_fn": ACTIVATIONS[activation],
        }
        if policy == "CnnPolicy":
            policy_kwargs["features_extractor_class"] = ConvFeatures
            policy_kwargs["features_extractor_kwargs"] = {
                "convs": [list(map(int, c)) for c in (convs or DEFAULT_CONVS)],
                "features_dim": int(features_dim),
            }
        self.hyper = {
            "epsilon": self.epsilon, "test_epsilon": self.test_epsilon, "gamma": gamma,
            "learning_rate": learning_rate, "batch_size": batch_size, "buffer_size": buffer_size,
            "learning_starts": learning_starts, "tau": tau,
            "target_update_interval": target_update_interval, "policy": policy,
            "net_arch": policy_kwargs["net_arch"], "activation": activation,
            "prioritized": self.prioritized,
        }  # fmt: skip

        np_seed, torch_seed, space_seed, per_seed = self.seed_sequence.generate_state(4)
        self._np_state = np.random.RandomState(int(np_seed)).get_state()
        self._torch_state = torch.Generator().manual_seed(int(torch_seed)).get_state()
        self.recorder = TrialRecorder(env)
        self._pending_groups: list[dict[str, Any]] | None = None  # from a file being loaded
        algo: type[TrialDQN] = TrialDQN
        kwargs: dict[str, Any] = {}
        if self.prioritized:
            algo = PrioritizedDQN
            kwargs["replay_buffer_class"] = PrioritizedReplayBuffer
            kwargs["replay_buffer_kwargs"] = {
                "alpha": per_alpha, "beta": per_beta, "beta_steps": per_beta_steps,
                "epsilon": per_epsilon, "seed": int(per_seed),
            }  # fmt: skip
        with self._rng_scope():
            self.model = algo(
                policy,
                Monitor(self.recorder),
                learning_rate=learning_rate,
                buffer_size=buffer_size,
                learning_starts=learning_starts,
                batch_size=batch_size,
                tau=tau,
                gamma=gamma,
                train_freq=train_freq,
                gradient_steps=gradient_steps,
                target_update_interval=target_update_interval,
                exploration_fraction=1.0,
                exploration_initial_eps=epsilon,
                exploration_final_eps=epsilon,
                max_grad_norm=max_grad_norm,
                policy_kwargs=policy_kwargs,
                device=device,
                verbose=0,
                seed=None,  # seeded through _rng_scope; SB3's seed= would also reseed the env
                **kwargs,
            )
        # a private action space: its sampler is the agent's, not the environment's
        self.model.action_space = gym.spaces.Discrete(int(env.action_space.n))
        self.model.action_space.seed(int(space_seed))
        self.n_actions = int(env.action_space.n)

    # -- rng bookkeeping -----------------------------------------------------------------
    @contextlib.contextmanager
    def _rng_scope(self) -> Iterator[None]:
        """Swap the agent's numpy/torch global generator states in for the duration."""
        outer_np, outer_torch = np.random.get_state(), torch.get_rng_state()  # noqa: NPY002
        np.random.set_state(self._np_state)  # noqa: NPY002
        torch.set_rng_state(self._torch_state)
        try:
            yield
        finally:
            self._np_state, self._torch_state = np.random.get_state(), torch.get_rng_state()  # noqa: NPY002
            np.random.set_state(outer_np)  # noqa: NPY002
            torch.set_rng_state(outer_torch)

    # -- trials ----------------------------------------------------------------------------
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        if learn:
            return self._learn_trials(n_trials, max_steps, callbacks)
        m = self.model
        m.policy.set_training_mode(False)
        eps = m.exploration_rate
        m.exploration_rate = self.test_epsilon
        try:
            with self._rng_scope():
                return super()._run(n_trials, max_steps, learn, callbacks)  # the base loop
        finally:
            m.exploration_rate = eps

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """The model's action (test trials): greedy, or epsilon-greedy with ``test_epsilon``."""
        action, _ = self.model.predict(obs, deterministic=self.test_epsilon == 0.0)
        return int(np.asarray(action).reshape(-1)[0])

    def _learn_trials(
        self, n_trials: int, max_steps: int, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        rec = self.recorder
        rec.begin(max_steps, callbacks, self)
        if n_trials == 0:
            return rec.batch()
        m = self.model
        m.stop_when = lambda: len(rec.finished) >= n_trials
        with self._rng_scope():
            # a fresh trial: phase changes (start states, rewards) apply from here
            m._last_obs = m.env.reset()
            m._last_episode_starts = np.ones((1,), dtype=bool)
            m.learn(total_timesteps=n_trials * max_steps, reset_num_timesteps=False,
                    log_interval=None)  # fmt: skip
        m.stop_when = None
        rec.finished = rec.finished[:n_trials]
        return rec.batch()

    # -- inference ---------------------------------------------------------------------------
    def _obs_tensor(self, observations: Any) -> torch.Tensor:
        obs = observations
        if not isinstance(obs, dict):
            obs = np.asarray(obs)
            space = self.model.observation_space
            if isinstance(space, gym.spaces.Discrete):
                obs = obs.reshape(-1)
            elif obs.shape == space.shape:
                obs = obs[None]
        tensor, _ = self.model.policy.obs_to_tensor(obs)
        return tensor

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Q values, shape (n, n_actions), of a batch of observations."""
        with torch.no_grad():
            return self.model.q_net(self._obs_tensor(observations)).cpu().numpy()

    def layer_names(self) -> list[str]:
        """Names of the Q network's layers usable with :meth:`activations` (plus ``"q"``)."""
        names = [n for n, mod in self.model.q_net.named_modules() if n and not list(mod.children())]
        return [*names, "q"]

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        """Outputs of the named layers of the online Q network for a batch of observations."""
        net = self.model.q_net
        modules = dict(net.named_modules())
        unknown = [name for name in layers if name != "q" and name not in modules]
        if unknown:
            raise ConfigError(
                f"unknown layer(s) {unknown}; this agent has: {', '.join(self.layer_names())}"
            )
        out: dict[str, np.ndarray] = {}
        hooks = []
        for name in layers:
            if name == "q":
                continue

            def hook(_mod: Any, _inp: Any, output: torch.Tensor, name: str = name) -> None:
                out[name] = output.detach().reshape(output.shape[0], -1).cpu().numpy()

            hooks.append(modules[name].register_forward_hook(hook))
        try:
            with torch.no_grad():
                q = net(self._obs_tensor(observations)).cpu().numpy()
        finally:
            for h in hooks:
                h.remove()
        if "q" in layers:
            out["q"] = q
        return {name: out[name] for name in layers}

    # -- persistence ---------------------------------------------------------------------------
    # The policy's tensors (online and target Q networks) and the Adam state, as plain arrays;
    # Adam's param_groups (learning rate, betas, ...) go to the JSON metadata. Parameters that
    # the optimizer has not stepped yet are saved as step 0 with zero moments, which is exactly
    # the state Adam starts from, so the schema does not depend on whether the agent learned.
    # The replay memory is not saved: a continued agent starts with an empty one.
    def hyperparameters(self) -> dict[str, Any]:
        return dict(self.hyper)

    def _adam_params(self) -> list[torch.Tensor]:
        return [p for g in self.model.policy.optimizer.param_groups for p in g["params"]]

    def state_schema(self) -> dict[str, ArraySpec]:
        schema = {
            f"policy.{k}": ArraySpec(tuple(v.shape), "f")
            for k, v in self.model.policy.state_dict().items()
        }
        for i, p in enumerate(self._adam_params()):
            shape = tuple(p.shape)
            schema[f"optimizer.{i}.step"] = ArraySpec((), "f", low=0)
            schema[f"optimizer.{i}.exp_avg"] = ArraySpec(shape, "f")
            schema[f"optimizer.{i}.exp_avg_sq"] = ArraySpec(shape, "f", low=0)
        schema["num_timesteps"] = ArraySpec((), "i", low=0)
        schema["n_calls"] = ArraySpec((), "i", low=0)
        return schema

    def get_state(self) -> dict[str, np.ndarray]:
        m = self.model
        arrays = {f"policy.{k}": v.detach().cpu().numpy()
                  for k, v in m.policy.state_dict().items()}  # fmt: skip
        state = m.policy.optimizer.state_dict()["state"]
        for i, p in enumerate(self._adam_params()):
            st = state.get(i, {})
            zeros = np.zeros(tuple(p.shape), np.float32)
            arrays[f"optimizer.{i}.step"] = np.array(float(st.get("step", 0.0)), np.float32)
            for key in ("exp_avg", "exp_avg_sq"):
                value = st.get(key)
                arrays[f"optimizer.{i}.{key}"] = (
                    zeros if value is None else value.detach().cpu().numpy()
                )
        arrays["num_timesteps"] = np.array(m.num_timesteps, np.int64)
        arrays["n_calls"] = np.array(m._n_calls, np.int64)
        return arrays

    def state_meta(self) -> dict[str, Any]:
        groups = self.model.policy.optimizer.state_dict()["param_groups"]
        return {"param_groups": [{k: (list(v) if isinstance(v, tuple) else v)
                                  for k, v in g.items()} for g in groups]}  # fmt: skip

    def set_state_meta(self, meta: Mapping[str, Any]) -> None:
        mine = self.model.policy.optimizer.state_dict()["param_groups"]
        groups = meta.get("param_groups")
        if not isinstance(groups, list) or len(groups) != len(mine):
            raise ValueError(f"__meta__ state.param_groups: expected a list of {len(mine)}")
        for g, own in zip(groups, mine, strict=True):
            if not isinstance(g, dict) or set(g) != set(own) or g["params"] != own["params"]:
                raise ValueError(
                    "__meta__ state.param_groups: expected the keys and params of "
                    f"{sorted(own)} / {own['params']}"
                )
        self._pending_groups = [{k: (tuple(v) if isinstance(own[k], tuple) else v)
                                 for k, v in g.items()}
                                for g, own in zip(groups, mine, strict=True)]  # fmt: skip

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        m = self.model
        m.policy.load_state_dict(
            {k[len("policy.") :]: torch.tensor(v) for k, v in arrays.items() if k[:7] == "policy."}
        )
        state = {
            i: {
                "step": torch.tensor(float(arrays[f"optimizer.{i}.step"]), dtype=torch.float32),
                "exp_avg": torch.tensor(arrays[f"optimizer.{i}.exp_avg"]),
                "exp_avg_sq": torch.tensor(arrays[f"optimizer.{i}.exp_avg_sq"]),
            }
            for i in range(len(self._adam_params()))
        }
        groups = self._pending_groups or m.policy.optimizer.state_dict()["param_groups"]
        m.policy.optimizer.load_state_dict({"state": state, "param_groups": groups})
        self._pending_groups = None
        m.num_timesteps = int(arrays["num_timesteps"])
        m._n_calls = int(arrays["n_calls"])
