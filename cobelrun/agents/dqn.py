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
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

from cobelrun.agents.base import Agent, ArraySpec, SeedLike, TrialCallback, layer_sizes
from cobelrun.agents.conv import ACTIVATIONS, DEFAULT_CONVS, ConvFeatures
from cobelrun.agents.networks import set_torch_threads
from cobelrun.agents.per import PrioritizedDQN, PrioritizedReplayBuffer
from cobelrun.agents.sb3 import TrialDQN, TrialRecorder
from cobelrun.agents.schema import (
    AgentArgs,
    at_least,
    finite_or_none,
    interval,
    one_of,
    positive,
    positive_or_none,
    validate_args,
)
from cobelrun.agents.torch_init import INITS
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation

POLICIES = ("auto", "MlpPolicy", "CnnPolicy", "MultiInputPolicy")


#: TD losses by config name: SB3's Huber (smooth L1, delta 1) or keras-rl's squared error
LOSSES: dict[str, Callable[..., torch.Tensor]] = {"huber": F.smooth_l1_loss, "mse": F.mse_loss}
#: SB3's NatureCNN (used for image inputs of a Dict observation by MultiInputPolicy)
NATURE_CONVS = ((32, 8, 4), (64, 4, 2), (64, 3, 1))
#: Layer name aliases of the CNN network: ``analysis`` is the dense ReLU layer after the
#: convolutions (Fig. 8's "analysis" layer, recorded for place-cell maps).
CNN_LAYER_ALIASES = {"analysis": "features_extractor.linear.1"}
#: the line a run prints when task.record.training_log cannot write TensorBoard files
TENSORBOARD_SKIPPED = (
    "task.record.training_log: TensorBoard output skipped, tensorboard is not installed "
    "(pip install tensorboard, or pip install 'cobelrun[tensorboard]'); the CSV log "
    "(training/run_NNNN/progress.csv) is written"
)


def tensorboard_available() -> bool:
    """Whether SB3's TensorBoard writer can run (``torch.utils.tensorboard`` imports, which
    needs the ``tensorboard`` package)."""
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError:
        return False
    return True


def conv_output_hw(
    height: int, width: int, convs: Sequence[Sequence[int]]
) -> list[tuple[int, int]]:
    """Feature-map size ``(h, w)`` after each ``[channels, kernel, stride]`` layer (no padding)."""
    out = []
    h, w = int(height), int(width)
    for _, kernel, stride in convs:
        h = (h - int(kernel)) // int(stride) + 1
        w = (w - int(kernel)) // int(stride) + 1
        out.append((h, w))
    return out


def check_image_fits(
    shape: Sequence[int], convs: Sequence[Sequence[int]], what: str = "agent.convs"
) -> None:
    """One-line ConfigError if a channel-first image ``shape`` is too small for ``convs``."""
    c, h, w = (int(v) for v in shape)
    inputs = [(h, w), *conv_output_hw(h, w, convs)]
    for i, (ih, iw) in enumerate(inputs[:-1]):
        kernel = int(convs[i][1])
        if ih < kernel or iw < kernel:
            layers = " -> ".join(f"{int(n)}@{int(k)}x{int(k)}/{int(st)}" for n, k, st in convs)
            raise ConfigError(
                f"image observation {h}x{w}x{c} (HxWxC) is too small for the CNN {what} "
                f"[{layers}]: conv layer {i + 1} gets a {max(ih, 0)}x{max(iw, 0)} input for its "
                f"{kernel}x{kernel} kernel; use larger images (env.observation.height/width) or "
                "smaller kernels"
            )


def _channel_first(space: gym.spaces.Space) -> tuple[int, int, int]:
    """(C, H, W) of an image space as SB3 sees it (it transposes H x W x C images itself)."""
    c, h, w = (int(v) for v in space.shape)
    if is_image_space_channels_first(space):  # type: ignore[arg-type]
        return c, h, w
    return w, c, h


def replay_bytes(space: gym.Space, capacity: int) -> int:
    """Bytes of SB3's replay memory of ``capacity`` transitions: observations and next
    observations in the space's dtype (``optimize_memory_usage`` off), plus actions, rewards,
    dones and time-out flags."""
    spaces = space.spaces.values() if isinstance(space, gym.spaces.Dict) else [space]
    per_obs = sum(int(np.prod(s.shape or (1,))) * np.dtype(s.dtype or np.int64).itemsize
                  for s in spaces)  # fmt: skip
    return int(capacity) * (2 * per_obs + 8 + 4 + 4 + 4)


class DQNArgs(AgentArgs):
    """The ranges of :class:`DQNAgent`'s arguments (checked in this order)."""

    #: exploration rate while training (epsilon-greedy)
    epsilon: Annotated[Any, interval(0.0, 1.0)]
    #: exploration rate in test trials
    test_epsilon: Annotated[Any, interval(0.0, 1.0)]
    #: discount factor
    gamma: Annotated[Any, interval(0.0, 1.0)]
    #: soft update coefficient of the target network (1: hard copy)
    tau: Annotated[Any, interval(0.0, 1.0)]
    #: prioritized replay: priority exponent
    per_alpha: Annotated[Any, interval(0.0, 1.0)]
    #: prioritized replay: initial importance-sampling exponent
    per_beta: Annotated[Any, interval(0.0, 1.0)]
    #: dropout after the convolutional features
    dropout: Annotated[Any, interval(0.0, 0.99)]
    #: transitions per gradient step
    batch_size: Annotated[Any, at_least(1)]
    #: replay memory size (transitions)
    buffer_size: Annotated[Any, at_least(1)]
    #: steps before learning starts
    learning_starts: Annotated[Any, at_least(0)]
    #: steps between updates
    train_freq: Annotated[Any, at_least(1)]
    #: gradient steps per update
    gradient_steps: Annotated[Any, at_least(1)]
    #: extra gradient steps at each trial's end
    trial_end_updates: Annotated[Any, at_least(0)]
    #: gradient steps between target network updates
    target_update_interval: Annotated[Any, at_least(1)]
    #: gradient steps over which the importance-sampling exponent anneals to 1
    per_beta_steps: Annotated[Any, at_least(1)]
    #: initial bias of the output layer (null: the init's)
    q_init: Annotated[Any, finite_or_none()]
    #: Adam's learning rate
    learning_rate: Annotated[Any, positive()]
    #: padding of the convolutions
    conv_padding: Annotated[Any, one_of(("valid", "same"), hint=False)]
    #: gradient norm clip (null: none)
    max_grad_norm: Annotated[Any, positive_or_none()]
    #: weight initialisation
    init: Annotated[Any, one_of(INITS)]
    #: TD loss
    loss: Annotated[Any, one_of(LOSSES)]
    #: hidden layers' activation
    activation: Annotated[Any, one_of(ACTIVATIONS)]
    #: SB3 policy (auto: from the observation space)
    policy: Annotated[Any, one_of(POLICIES)]
    #: size of the convolutional features
    features_dim: Annotated[Any, at_least(1)]


class DQNAgent(Agent):
    """DQN (Mnih et al. 2015) through stable-baselines3, trained in trials.

    Defaults are CoBeL-RL's DQN defaults (docs/paper-settings.md): 4 x dense 64 tanh, epsilon 0.3,
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
    trial_end_updates
        Extra gradient steps when a trial ends (default 0, SB3's schedule; CoBeL-RL's keras-rl
        DQN makes 1: its fit loop calls ``backward`` once more on the terminal observation).
    tau, target_update_interval
        Target network update ``target <- tau * online + (1 - tau) * target`` every
        ``target_update_interval`` steps: soft (0.01 every step, default) or hard
        (``tau=1``, interval N).
    loss
        TD loss: ``"huber"`` (SB3's smooth L1, default) or ``"mse"`` (squared error, keras-rl's
        and so CoBeL-RL's: its ``delta_clip`` is infinite by default).
    max_grad_norm
        Gradient-norm clipping (SB3's default 10; ``None``: no clipping, as keras-rl).
    policy
        ``"auto"`` (``MultiInputPolicy`` for Dict, ``CnnPolicy`` for images, else
        ``MlpPolicy``) or one of those names.
    net_arch
        Hidden layer sizes of the Q head (default: [64, 64, 64, 64] on vectors, [] after a CNN).
    activation
        Hidden-layer activation: tanh (default), relu, elu, sigmoid, linear.
    convs, features_dim
        CNN layers ``[[channels, kernel, stride], ...]`` and the dense features after them
        (Fig. 6A's by default); used with ``CnnPolicy``. An image too small for the kernels is
        a ConfigError naming both shapes.
    conv_padding
        ``"valid"`` (default) or ``"same"`` (Keras' zero padding; any image size fits).
    dropout
        Dropout rate after the CNN's dense layer (default 0; Fig. 8: 0.35). Active while
        learning only; acting, testing and :meth:`activations` run the network in eval mode.
    init
        Initial weights of the Q network: ``"torch"`` (PyTorch's layer defaults, uniform
        +-1/sqrt(fan_in) for weights and biases; default) or ``"keras"`` (Glorot-uniform weights
        and zero biases, Keras' defaults and so CoBeL-RL's). The target network starts as a copy.
    q_init
        Initial Q value: the output layer's biases start at this value (default ``None``: as
        ``init``). With a constant step cost ``c`` per step, ``c / (1 - gamma)`` starts the
        network at the return of a trial that never ends, so learning does not have to move
        every Q value there through the hidden units (docs/place_cells.md).
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
    batchable = True
    checkpoint_by_default = True

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
        trial_end_updates: int = 0,
        tau: float = 0.01,
        target_update_interval: int = 1,
        loss: str = "huber",
        max_grad_norm: float | None = 10.0,
        policy: str = "auto",
        net_arch: Sequence[int] | None = None,
        activation: str = "tanh",
        convs: Sequence[Sequence[int]] | None = None,
        features_dim: int = 256,
        conv_padding: str = "valid",
        dropout: float = 0.0,
        init: str = "torch",
        q_init: float | None = None,
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
        validate_args(DQNArgs, locals())
        set_torch_threads(torch_threads)
        self.epsilon, self.test_epsilon = float(epsilon), float(test_epsilon)
        self.prioritized = bool(prioritized)
        self.device = str(device)
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
        check_allocation("agent.buffer_size", replay_bytes(obs_space, buffer_size),
                         f"a replay memory of {buffer_size:,} transitions of {obs_space}",
                         "lower agent.buffer_size")  # fmt: skip
        policy_kwargs: dict[str, Any] = {
            "net_arch": layer_sizes("agent.net_arch", net_arch),
            "activation_fn": ACTIVATIONS[activation],
        }
        if policy == "CnnPolicy":
            conv_layers = [list(map(int, c)) for c in (convs or DEFAULT_CONVS)]
            if not conv_layers or any(len(c) != 3 or min(c) < 1 for c in conv_layers):
                raise ConfigError(
                    f"agent.convs must be a non-empty list of [channels, kernel, stride] with "
                    f"positive integers, got {convs!r}"
                )
            if conv_padding == "valid":  # "same" padding fits any image size
                check_image_fits(_channel_first(obs_space), conv_layers)
            policy_kwargs["features_extractor_class"] = ConvFeatures
            policy_kwargs["features_extractor_kwargs"] = {
                "convs": conv_layers,
                "features_dim": int(features_dim),
                "padding": conv_padding,
                "dropout": float(dropout),
            }
        elif policy == "MultiInputPolicy" and isinstance(obs_space, gym.spaces.Dict):
            for key, sub in obs_space.spaces.items():
                if is_image_space(sub):
                    check_image_fits(
                        _channel_first(sub), NATURE_CONVS, f"(SB3 NatureCNN for input {key!r})"
                    )
        self.hyper = {
            "epsilon": self.epsilon, "test_epsilon": self.test_epsilon, "gamma": gamma,
            "learning_rate": learning_rate, "batch_size": batch_size, "buffer_size": buffer_size,
            "learning_starts": learning_starts, "tau": tau,
            "target_update_interval": target_update_interval, "policy": policy,
            "net_arch": policy_kwargs["net_arch"], "activation": activation,
            "prioritized": self.prioritized, "loss": loss, "max_grad_norm": max_grad_norm,
            "trial_end_updates": trial_end_updates, "dropout": dropout, "init": init,
            "q_init": q_init,
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
            q_net = self.model.q_net
            INITS[init](q_net)  # seeded: inside the agent's torch generator scope
            if q_init is not None:
                out = [m for m in q_net.q_net.modules() if isinstance(m, torch.nn.Linear)][-1]
                with torch.no_grad():
                    out.bias.fill_(float(q_init))
        self.model.q_net_target.load_state_dict(self.model.q_net.state_dict())
        self.model.td_loss = LOSSES[loss]
        self.model.trial_end_updates = int(trial_end_updates)
        # a private action space: its sampler is the agent's, not the environment's
        self.model.action_space = gym.spaces.Discrete(int(env.action_space.n))
        self.model.action_space.seed(int(space_seed))
        self.n_actions = int(env.action_space.n)

    # -- batched runs ----------------------------------------------------------------------
    def batch_unsupported(self) -> str | None:
        from cobelrun.agents.batched_pick import unsupported

        return unsupported(self)

    def batch_auto_declines(self) -> str | None:
        from cobelrun.agents.batched_pick import auto_declines

        return auto_declines(self)

    def batch_learner(
        self, seeds: Sequence[np.random.SeedSequence], steps: int, make: Any = None
    ) -> Any:
        """:class:`~cobelrun.agents.batched_dqn.BatchedDQN` (or its CNN subclass) for one run
        per seed."""
        from cobelrun.agents.batched_pick import make_batched

        return make_batched(self, seeds, capacity=steps, device=self.device)

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
        rec.begin(max_steps, callbacks, self, quota=n_trials)
        if n_trials == 0:
            return rec.batch()
        m = self.model
        m.stop_when = lambda: len(rec.finished) >= n_trials
        with self._rng_scope():
            # a fresh trial: phase changes (start states, rewards) apply from here
            m._last_obs = m.env.reset()
            m._last_episode_starts = np.ones((1,), dtype=bool)
            m.learn(total_timesteps=n_trials * max_steps, reset_num_timesteps=False,
                    log_interval=1 if m.log_q else None)  # fmt: skip
        m.stop_when = None
        rec.finished = rec.finished[:n_trials]
        return rec.batch()

    def log_training(self, folder: str | Path) -> list[str]:
        """Log training curves through SB3's logger into ``folder`` (``progress.csv``, and
        TensorBoard event files when ``tensorboard`` is installed), one row per trial:
        ``train/loss``, ``train/q_max`` (max Q at the current observation),
        ``rollout/exploration_rate`` (epsilon), ``rollout/ep_rew_mean`` (mean trial return,
        SB3's window of 100 trials).

        Returns
        -------
        list of str
            Notes for the user: one line saying that TensorBoard output was skipped (and how to
            install it) when ``tensorboard`` cannot be imported; empty otherwise.
        """
        from stable_baselines3.common.logger import configure

        tensorboard = tensorboard_available()
        Path(folder).mkdir(parents=True, exist_ok=True)
        self.model.set_logger(configure(str(folder), ["csv"] + (["tensorboard"] * tensorboard)))
        self.model.log_q = True
        return [] if tensorboard else [TENSORBOARD_SKIPPED]

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
        """Q values, shape (n, n_actions), of a batch of observations (eval mode: no dropout)."""
        net = self.model.q_net
        was_training = net.training
        net.train(False)
        try:
            with torch.no_grad():
                return net(self._obs_tensor(observations)).cpu().numpy()
        finally:
            net.train(was_training)

    def _aliases(self) -> dict[str, str]:
        modules = dict(self.model.q_net.named_modules())
        if not isinstance(modules.get("features_extractor"), ConvFeatures):
            return {}
        return {k: v for k, v in CNN_LAYER_ALIASES.items() if v in modules}

    def layer_names(self) -> list[str]:
        """Names of the Q network's layers usable with :meth:`activations` (plus ``"q"``).

        A CNN network also has ``analysis``: its dense ReLU layer (Fig. 8's analysis layer).
        """
        names = [n for n, mod in self.model.q_net.named_modules() if n and not list(mod.children())]
        return [*self._aliases(), *names, "q"]

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        """Outputs of the named layers of the online Q network for a batch of observations.

        The network runs in eval mode (no dropout); its training mode is restored afterwards.
        """
        net = self.model.q_net
        modules = dict(net.named_modules())
        for alias, target in self._aliases().items():
            modules[alias] = modules[target]
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
        was_training = net.training
        net.train(False)
        try:
            with torch.no_grad():
                q = net(self._obs_tensor(observations)).cpu().numpy()
        finally:
            net.train(was_training)
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

    # -- checkpoints (cobelrun.checkpoint) ------------------------------------------------------
    # Besides the learned state (weights, Adam): the replay memory (its filled rows, position
    # and PER sum tree), the numpy and torch generator states the agent swaps in around SB3,
    # the private action space's generator, and SB3's counters. Between train/test calls
    # nothing else carries over (each call starts a fresh trial with its own reset).
    def _replay_arrays(self) -> dict[str, np.ndarray]:
        """The replay memory's filled rows, by ``FIELD`` or ``FIELD.KEY`` (Dict observations)."""
        buf = self.model.replay_buffer
        n = buf.buffer_size if buf.full else buf.pos
        out: dict[str, np.ndarray] = {}
        for field in _REPLAY_FIELDS:
            value = getattr(buf, field, None)
            if isinstance(value, dict):
                out.update({f"{field}.{k}": v[:n] for k, v in value.items()})
            elif value is not None:
                out[field] = value[:n]
        return out

    def checkpoint_schema(self) -> dict[str, ArraySpec]:
        schema = super().checkpoint_schema()
        buf = self.model.replay_buffer
        for key, arr in self._replay_arrays().items():
            finite = arr.dtype.kind == "f"
            schema[f"replay.{key}"] = ArraySpec((None, *arr.shape[1:]), arr.dtype.kind,
                                                finite=finite)  # fmt: skip
        schema["rng.numpy_keys"] = ArraySpec((624,), "u")
        schema["rng.torch"] = ArraySpec((int(self._torch_state.numel()),), "u")
        if isinstance(buf, PrioritizedReplayBuffer):
            width = 2 * buf.tree.size
            schema["per.sums"] = ArraySpec((width,), "f", low=0)
            schema["per.mins"] = ArraySpec((width,), "f", low=0, finite=False)
        return schema

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        from cobelrun.checkpoint import generator_state

        arrays, meta = super().checkpoint_state()
        m, buf = self.model, self.model.replay_buffer
        arrays.update({f"replay.{k}": v for k, v in self._replay_arrays().items()})
        kind, keys, pos, has_gauss, gauss = self._np_state
        arrays["rng.numpy_keys"] = np.asarray(keys, np.uint32)
        arrays["rng.torch"] = self._torch_state.numpy().copy()
        meta["numpy"] = {"kind": str(kind), "pos": int(pos), "has_gauss": int(has_gauss),
                         "cached_gaussian": float(gauss)}  # fmt: skip
        meta["action_space"] = generator_state(m.action_space.np_random)
        meta["sb3"] = {"n_updates": int(m._n_updates), "episode_num": int(m._episode_num),
                       "exploration_rate": float(m.exploration_rate),
                       "progress_remaining": float(m._current_progress_remaining)}  # fmt: skip
        meta["replay"] = {"pos": int(buf.pos), "full": bool(buf.full)}
        if isinstance(buf, PrioritizedReplayBuffer):
            arrays["per.sums"] = buf.tree.sums
            arrays["per.mins"] = buf.tree.mins
            meta["per"] = {"max_priority": float(buf.max_priority),
                           "n_sampled": int(buf.n_sampled), "rng": generator_state(buf.rng)}  # fmt: skip
        return arrays, meta

    def restore_checkpoint(self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
        from cobelrun.checkpoint import set_generator_state

        m, buf = self.model, self.model.replay_buffer
        replay = meta.get("replay")
        if not isinstance(replay, dict):
            raise ValueError("replay: expected {pos, full}")
        pos, full = replay.get("pos"), replay.get("full")
        if not isinstance(full, bool) or not isinstance(pos, int) or not 0 <= pos < buf.buffer_size:
            raise ValueError(f"replay: pos must be in [0, {buf.buffer_size}) and full a bool")
        n = buf.buffer_size if full else pos
        for key in self._replay_arrays():
            if len(arrays[f"replay.{key}"]) != n:
                raise ValueError(f"replay.{key}: expected {n} rows, got "
                                 f"{len(arrays[f'replay.{key}'])}")  # fmt: skip
        numpy = meta.get("numpy")
        if not isinstance(numpy, dict) or numpy.get("kind") != "MT19937":
            raise ValueError("numpy: expected an MT19937 state")
        np_state = ("MT19937", np.asarray(arrays["rng.numpy_keys"], np.uint32),
                    int(numpy["pos"]), int(numpy["has_gauss"]), float(numpy["cached_gaussian"]))  # fmt: skip
        try:
            np.random.RandomState().set_state(np_state)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"numpy: not a valid MT19937 state ({exc})") from None
        sb3 = meta.get("sb3")
        if not isinstance(sb3, dict) or not all(
            isinstance(sb3.get(k), int) and sb3[k] >= 0 for k in ("n_updates", "episode_num")
        ):
            raise ValueError("sb3: expected counters n_updates and episode_num >= 0")
        for key in ("exploration_rate", "progress_remaining"):
            value = sb3.get(key)
            if not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
                raise ValueError(f"sb3.{key}: expected a number in [0, 1]")
        probe = np.random.Generator(np.random.PCG64())
        set_generator_state(probe, meta.get("action_space"), "action space generator")
        per = meta.get("per") if isinstance(buf, PrioritizedReplayBuffer) else None
        if isinstance(buf, PrioritizedReplayBuffer):
            if not isinstance(per, dict):
                raise ValueError("per: expected the prioritized replay state")
            set_generator_state(np.random.Generator(np.random.PCG64()), per.get("rng"),
                                "replay generator")  # fmt: skip
            if not isinstance(per.get("n_sampled"), int) or per["n_sampled"] < 0:
                raise ValueError("per.n_sampled: expected an integer >= 0")
            mp = per.get("max_priority")
            if not isinstance(mp, int | float) or not np.isfinite(mp) or mp <= 0:
                raise ValueError("per.max_priority: expected a number > 0")
        torch_state = torch.from_numpy(np.array(arrays["rng.torch"], np.uint8))
        try:
            torch.Generator().set_state(torch_state)
        except RuntimeError as exc:
            raise ValueError(f"torch generator: not a valid state ({exc})") from None
        super().restore_checkpoint(arrays, meta)  # weights, Adam, counters, agent generator
        for key in self._replay_arrays():
            field, _, sub = key.partition(".")
            target = getattr(buf, field)
            target = target[sub] if sub else target
            target[:n] = arrays[f"replay.{key}"]
        buf.pos, buf.full = pos, full
        self._np_state = np_state
        self._torch_state = torch_state
        set_generator_state(m.action_space.np_random, meta["action_space"], "action space")
        m._n_updates, m._episode_num = sb3["n_updates"], sb3["episode_num"]
        # the rate of a call's first step is the one the last step left (SB3 sets it after
        # each step): a fresh model's is 0 until its first step
        m.exploration_rate = float(sb3["exploration_rate"])
        m._current_progress_remaining = float(sb3["progress_remaining"])
        if isinstance(buf, PrioritizedReplayBuffer):
            assert per is not None
            buf.tree.sums[...] = arrays["per.sums"]
            buf.tree.mins[...] = arrays["per.mins"]
            buf.max_priority = float(per["max_priority"])
            buf.n_sampled = int(per["n_sampled"])
            set_generator_state(buf.rng, per["rng"], "replay generator")


#: the arrays of SB3's replay memory a checkpoint keeps (filled rows only)
_REPLAY_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
