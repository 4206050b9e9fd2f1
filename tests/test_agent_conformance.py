"""Conformance of every registered agent (each ``conf/agent/*.yaml``), the SB3 way.

Each agent config is instantiated (through cobel's own config validation) on a small
environment that fits it and must: save and load without changing its predictions, give
identical trials for the same seed, refuse a bad save file with a one-line ConfigError naming
the problem (and stay untouched), and refuse an environment that lacks a contract it requires.
A new agent YAML gets all of this without touching this file; ``FAST`` only shrinks budgets.
Plus unit tests of :mod:`cobelrun.agents.policy` and its numba twin.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from omegaconf import OmegaConf

from cobelrun.agents import policy
from cobelrun.agents.base import META_KEY, Agent, ArraySpec, Transition, TrialCallback
from cobelrun.config import instantiate
from cobelrun.envs import DiscreteGridWorldEnv, GridWorldEnv, open_field
from cobelrun.errors import ConfigError

#: configs whose agents need no torch (the rest are skipped without the deep extra)
NUMPY_ONLY = {"dyna_q", "mfec", "sarsa", "q_lambda", "sarsa_lambda", "mc_control",
              "tabular_actor_critic", "dyna_actor_critic"}  # fmt: skip
CONF = Path(__file__).resolve().parents[1] / "conf" / "agent"
AGENT_CONFIGS = sorted(p.stem for p in CONF.glob("*.yaml"))

#: smaller budgets for speed (keys a config does not have are ignored)
FAST: dict[str, Any] = {
    "replay_batch": 4, "hidden": [16], "net_arch": [16], "learning_starts": 5,
    "buffer_size": 200, "batch_size": 8, "projection_dim": 8,
}  # fmt: skip


def small_env(env_cls: type[GridWorldEnv], seed: int = 0) -> GridWorldEnv:
    env = env_cls(world=open_field(4, 4, starts=[0], goal=15))
    env.np_random = np.random.default_rng(seed)
    return env


def small_sequence(seed: int = 0) -> gym.Env:
    """Conditioning trials: A+ and AB- (cues at steps 1-3, US at 3), with the serial compound."""
    from cobelrun.envs import SequenceEnv

    env = SequenceEnv(["A", "B"], {"A": {"cues": {"A": [1, 4]}, "outcome": 1.0, "us": 3},
                                   "AB": {"cues": {"A": [1, 4], "B": [1, 4]}, "us": 3}},
                      length=5, csc=True)  # fmt: skip
    env.np_random = np.random.default_rng(seed)
    return env


def build(name: str, seed: int = 3, env_seed: int = 0) -> tuple[gym.Env, Agent]:
    """Agent ``name`` from its YAML on the first small env whose spaces it supports."""
    if name not in NUMPY_ONLY:
        pytest.importorskip("stable_baselines3")
    node = OmegaConf.to_container(OmegaConf.load(CONF / f"{name}.yaml"))
    assert isinstance(node, dict)
    node.update({k: v for k, v in FAST.items() if k in node})
    error: ConfigError | None = None
    for make in (
        lambda: small_env(GridWorldEnv, env_seed),
        lambda: small_env(DiscreteGridWorldEnv, env_seed),
        lambda: ImageObservations(small_env(GridWorldEnv, env_seed)),
        lambda: small_sequence(env_seed),  # conditioning agents (the trial_script contract)
    ):
        env = make()
        try:
            return env, instantiate(f"agent {name}", node, env=env, seed=seed)
        except ConfigError as exc:
            if not any(
                m in str(exc)
                for m in (
                    "does not support observation space",
                    "needs image observations",
                    "needs an environment with 'trial_script'",
                )
            ):
                raise
            error = exc
    raise AssertionError(f"no small env fits agent {name}: {error}")


class ImageObservations(gym.ObservationWrapper):
    """The small gridworld seen as a fixed random 12 x 48 RGB image per state (for CNN agents,
    e.g. agent=dqn_fig8, without a renderer)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        n = env.unwrapped.world.n_states
        self.observation_space = spaces.Box(0, 255, (3, 12, 48), np.uint8)
        self.images = np.random.default_rng(7).integers(0, 256, (n, 3, 12, 48), dtype=np.uint8)
        self.probe_observations = self.images

    def observation(self, observation: Any) -> np.ndarray:
        return self.images[int(observation)].copy()


def probes(env: gym.Env) -> np.ndarray:
    if hasattr(env, "probe_observations"):
        return env.probe_observations
    obs = getattr(env.unwrapped, "observations", None)
    return np.asarray(obs) if isinstance(env.observation_space, spaces.Box) else np.arange(16)


def assert_same_batch(a: Any, b: Any) -> None:
    for field in ("start_state", "end_state", "steps", "reward", "terminated", "offsets",
                  "step_state", "step_action", "step_next_state", "step_reward",
                  "start_pose", "step_pose"):  # fmt: skip
        x, y = getattr(a, field), getattr(b, field)
        assert (x is None) == (y is None), field
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=field)


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """One trained-and-saved agent file per config, shared by the bad-file cases."""
    cache: dict[str, Path] = {}

    def get(name: str) -> Path:
        if name not in cache:
            _env, agent = build(name)
            agent.train(3, 15)
            cache[name] = agent.save(tmp_path_factory.mktemp(name) / "agent")
        return cache[name]

    return get


# -- every agent -----------------------------------------------------------------------------


@pytest.mark.parametrize("name", AGENT_CONFIGS)
def test_save_load_round_trip(name: str, saved: Any, tmp_path: Path) -> None:
    env, agent = build(name)
    agent.train(3, 15)
    path = agent.save(tmp_path / "agent")
    assert path == tmp_path / "agent.npz" and path.is_file()
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data[META_KEY]))
        assert set(data.files) - {META_KEY} == set(agent.state_schema())
    assert meta["agent"] == agent.agent_name() and meta["schema_version"] == agent.state_version
    json.dumps(meta["hyperparameters"])
    _env2, fresh = build(name, seed=99)
    x = probes(env)
    fresh.load(path)
    np.testing.assert_array_equal(agent.predict(x), fresh.predict(x))
    assert agent.predict(x).shape == (len(x), env.action_space.n)
    # saving the loaded agent writes the same arrays
    again = fresh.save(tmp_path / "again.npz")
    with np.load(path) as a, np.load(again) as b:
        for key in agent.state_schema():
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.parametrize("name", AGENT_CONFIGS)
def test_same_seed_same_trials(name: str) -> None:
    runs = []
    for _ in range(2):
        _env, agent = build(name)
        runs.append((agent.train(3, 15), agent.test(2, 15)))
    for a, b in zip(*runs, strict=True):
        assert_same_batch(a, b)


@pytest.mark.parametrize("name", AGENT_CONFIGS)
def test_a_phase_in_pieces_gives_the_same_trials(name: str) -> None:
    """train(8) equals train(3) then train(5) (and so for test): the runner may hand an agent
    a long phase in pieces (cobelrun.runner.PhasePacer) without changing what it learns."""
    from cobelrun.records import TrialBatch

    _env, whole = build(name)
    _env, pieces = build(name)
    assert_same_batch(whole.train(8, 15), TrialBatch.concat([pieces.train(3, 15),
                                                             pieces.train(5, 15)]))  # fmt: skip
    assert_same_batch(whole.test(5, 15), TrialBatch.concat([pieces.test(2, 15),
                                                            pieces.test(3, 15)]))  # fmt: skip


def _bad_files(path: Path, agent: Agent, tmp: Path) -> dict[str, tuple[Path, str]]:
    """Crafted variants of a good file: case -> (file, expected message regex)."""
    with np.load(path, allow_pickle=False) as data:
        good = {k: data[k] for k in data.files}
    schema = agent.state_schema()

    def write(case: str, arrays: dict[str, np.ndarray]) -> Path:
        out = tmp / f"{case}.npz"
        np.savez(out, **arrays)
        return out

    cases: dict[str, tuple[Path, str]] = {}
    first = next(iter(schema))
    cases["missing_key"] = (write("missing", {k: v for k, v in good.items() if k != first}),
                            rf"key '{first}' is missing")  # fmt: skip
    cases["unknown_key"] = (write("unknown", {**good, "zzz": np.zeros(1)}), "unknown key 'zzz'")
    fkey = next(k for k, s in schema.items() if s.kind == "f" and good[k].size and s.finite)
    cases["wrong_shape"] = (write("shape", {**good, fkey: np.zeros((*good[fkey].shape, 2))}),
                            rf"key '{fkey}': expected shape")  # fmt: skip
    nan = good[fkey].copy()
    nan.reshape(-1)[0] = np.nan
    cases["nan"] = (write("nan", {**good, fkey: nan}), rf"key '{fkey}': expected finite values")
    cases["wrong_dtype"] = (write("dtype", {**good, fkey: good[fkey].astype(np.complex64)}),
                            rf"key '{fkey}': expected dtype kind 'f'")  # fmt: skip
    bounded = [k for k, s in schema.items() if s.high is not None or s.low is not None]
    if bounded:
        key, spec = bounded[0], schema[bounded[0]]
        bad = good[key].copy().reshape(-1) if good[key].ndim else good[key].copy()
        value = spec.high if spec.high is not None else spec.low - 1  # type: ignore[operator]
        if bad.ndim:
            bad[0] = value
        else:
            bad = np.array(value, dtype=good[key].dtype)
        cases["out_of_range"] = (write("range", {**good, key: bad.reshape(good[key].shape)}),
                                 rf"key '{key}': expected values in \[")  # fmt: skip
    meta = json.loads(str(good[META_KEY]))
    meta["agent"] = "cobelrun.agents.Other"
    cases["wrong_agent"] = (write("agent", {**good, META_KEY: np.array(json.dumps(meta))}),
                            "holds agent 'cobelrun.agents.Other', expected")  # fmt: skip
    cases["no_meta"] = (write("nometa", {k: v for k, v in good.items() if k != META_KEY}),
                        "not a cobel agent file")  # fmt: skip
    text = tmp / "text.npz"
    text.write_text("not an archive")
    cases["not_npz"] = (text, "not a readable .npz archive")
    npy = tmp / "array.npz"
    with open(npy, "wb") as fh:
        np.save(fh, np.zeros(3))
    cases["npy_not_npz"] = (npy, "not an .npz archive")
    pickled = tmp / "pickled.npz"
    np.savez(pickled, **good, obj=np.array([{"a": 1}], dtype=object))
    cases["pickle"] = (pickled, "without pickle")
    cases["no_file"] = (tmp / "nope.npz", "no such file")
    return cases


BAD_CASES = ["missing_key", "unknown_key", "wrong_shape", "nan", "wrong_dtype", "out_of_range",
             "wrong_agent", "no_meta", "not_npz", "npy_not_npz", "pickle", "no_file"]  # fmt: skip


@pytest.mark.parametrize("name", AGENT_CONFIGS)
def test_bad_files_are_refused_and_change_nothing(name: str, saved: Any, tmp_path: Path) -> None:
    env, agent = build(name, seed=5)
    agent.train(2, 10)
    x = probes(env)
    before = agent.predict(x)
    cases = _bad_files(saved(name), agent, tmp_path)
    for case in BAD_CASES:
        if case not in cases:
            continue
        path, match = cases[case]
        with pytest.raises(ConfigError, match=match) as info:
            agent.load(path)
        msg = str(info.value)
        assert "\n" not in msg and str(path) in msg, (case, msg)
        np.testing.assert_array_equal(agent.predict(x), before, err_msg=case)
    agent.train(1, 10)  # still usable


def test_dyna_q_refuses_index_that_would_crash_the_kernel(saved: Any, tmp_path: Path) -> None:
    with np.load(saved("dyna_q")) as data:
        good = {k: data[k] for k in data.files}
    nxt = good["memory_next_state"].copy()
    nxt[0, 0] = 10**9
    np.savez(tmp_path / "crafted.npz", **{**good, "memory_next_state": nxt})
    _env, agent = build("dyna_q")
    with pytest.raises(ConfigError, match=r"'memory_next_state': expected values in \[0, 16\)"):
        agent.load(tmp_path / "crafted.npz")
    agent.train(2, 15)


class NoModelEnv(gym.Env):
    """Discrete states but none of the contracts (no world, no pose)."""

    observation_space = spaces.Discrete(16)
    action_space = spaces.Discrete(4)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return 0, {}

    def step(self, action):
        return 1, 1.0, True, False, {}


class NoModelBoxEnv(NoModelEnv):
    observation_space = spaces.Box(0.0, 1.0, (16,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(16, np.float32), {}

    def step(self, action):
        return np.ones(16, np.float32), 1.0, True, False, {}


@pytest.mark.parametrize("name", AGENT_CONFIGS)
def test_requires_mismatch_is_a_config_error(name: str) -> None:
    _env, agent = build(name)
    cls = type(agent)
    for bare in (NoModelEnv(), NoModelBoxEnv()):
        if not (isinstance(bare.observation_space, cls.observation_spaces)):
            continue
        if cls.requires:
            with pytest.raises(
                ConfigError, match=rf"needs an environment with '{cls.requires[0]}'"
            ):
                type(agent)(bare)
        else:  # nothing required: the agent runs on the bare env through the base loop
            batch = cls(bare).train(2, 5)
            assert batch.steps.tolist() == [1, 1]
            assert batch.start_pose is None and batch.step_pose is None


def test_requires_is_checked_at_construction() -> None:
    class NeedsPose(Agent):
        observation_spaces = (spaces.Discrete,)
        requires = ("pose",)

        def predict(self, observations):
            return np.zeros((len(observations), 4))

    with pytest.raises(ConfigError, match=r"agent NeedsPose needs an environment with 'pose'.*"
                                          r"NoModelEnv does not offer"):  # fmt: skip
        NeedsPose(NoModelEnv())
    NeedsPose(small_env(GridWorldEnv))


def test_dyna_q_options_that_need_a_model() -> None:
    from cobelrun.agents import DynaQ

    with pytest.raises(ConfigError, match=r"agent.action_mask needs an environment with "
                                          r"'tabular_model'"):  # fmt: skip
        DynaQ(NoModelEnv(), action_mask=True)
    with pytest.raises(ConfigError, match=r"agent.engine 'compiled'.*'tabular_model'"):
        DynaQ(NoModelEnv(), engine="compiled")


# -- the base loop ----------------------------------------------------------------------------


class Scripted(Agent):
    """Acts from a list; counts the hooks (a minimal agent on the base loop)."""

    observation_spaces = (spaces.Discrete,)

    def __init__(self, env: gym.Env, actions: list[int]) -> None:
        super().__init__(env, seed=0)
        self.actions = actions
        self.calls: list[str] = []
        self.transitions: list[Transition] = []

    def begin_trial(self, obs, info, learn):
        self.calls.append("begin")
        self._i = 0

    def act(self, obs, info, learn):
        self._i += 1
        return self.actions[(self._i - 1) % len(self.actions)]

    def observe(self, transition, learn):
        self.transitions.append(transition)

    def end_trial(self, learn):
        self.calls.append(f"end:{learn}")

    def predict(self, observations):
        return np.zeros((len(observations), 4))


def test_base_loop_records_states_poses_and_calls_hooks_in_order() -> None:
    env = small_env(GridWorldEnv)  # 4 x 4 open field, start 0, goal 15
    agent = Scripted(env, [1, 2])
    events: list[str] = []

    class Log(TrialCallback):
        def _on_trial_start(self, agent, trial, state):
            events.append(f"start{trial}:{state}")

        def _on_step(self, agent, trial, step, transition):
            events.append(f"step{step}:{transition['state']}->{transition.next_state}")
            return step < 3  # end every trial after 3 steps

        def _on_trial_end(self, agent, trial, record):
            events.append(f"end{trial}:{len(record['actions'])}")

    batch = agent.train(2, 10, callbacks=[Log()])
    assert batch.steps.tolist() == [3, 3] and agent.calls == ["begin", "end:True"] * 2
    assert events[0] == "start0:0" and events[4] == "end0:3" and len(events) == 10
    t = agent.transitions[0]
    assert (t.state, t.action, t.next_state) == (0, 1, batch.step_next_state[0])
    assert t.info["state"] == 0 and t.next_info["state"] == t.next_state
    # poses from the Posed contract: start pose, then one per step, matching the states
    base = env.unwrapped
    np.testing.assert_allclose(batch.start_pose[:, :2], base.poses_of(batch.start_state)[:, :2])
    np.testing.assert_allclose(batch.step_pose[:, :2], base.poses_of(batch.step_next_state)[:, :2])
    assert agent.test(1, 2).steps.tolist() == [2] and agent.calls[-1] == "end:False"


def test_agent_without_act_says_so() -> None:
    class Lazy(Agent):
        observation_spaces = (spaces.Discrete,)

        def predict(self, observations):
            return np.zeros((1, 4))

    with pytest.raises(NotImplementedError, match="Lazy does not implement act"):
        Lazy(NoModelEnv()).train(1, 1)
    with pytest.raises(NotImplementedError, match="Lazy declares no state schema"):
        Lazy(NoModelEnv()).state_schema()


def test_array_spec() -> None:
    spec = ArraySpec((None, 3), "f")
    assert spec.problem(np.zeros((5, 3))) is None
    assert "expected shape (*, 3), got (5, 2)" in spec.problem(np.zeros((5, 2)))
    assert "dtype kind 'f'" in spec.problem(np.zeros((5, 3), np.int64))
    assert "finite" in spec.problem(np.full((1, 3), np.inf))
    assert ArraySpec((2,), "f", finite=False).problem(np.array([np.nan, 1.0])) is None
    assert "[0, 4), found 4" in ArraySpec((2,), "i", 0, 4).problem(np.array([0, 4]))
    assert "[0, inf), found -1" in ArraySpec((), "i", low=0).problem(np.array(-1))


# -- the policy module ------------------------------------------------------------------------


def test_epsilon_greedy_breaks_ties_at_random_and_respects_allowed() -> None:
    rng = np.random.default_rng(0)
    q = np.array([1.0, 3.0, 3.0, 0.0])
    picks = [policy.epsilon_greedy(rng, q, 0.0) for _ in range(2000)]
    counts = np.bincount(picks, minlength=4)
    assert counts[0] == counts[3] == 0 and 850 < counts[1] < 1150
    allowed = np.array([True, False, True, True])
    assert {policy.epsilon_greedy(rng, q, 0.0, allowed) for _ in range(200)} == {2}
    explore = [policy.epsilon_greedy(rng, q, 1.0, allowed) for _ in range(3000)]
    counts = np.bincount(explore, minlength=4)
    assert counts[1] == 0 and all(900 < c < 1100 for c in counts[[0, 2, 3]])
    none = np.zeros(4, bool)  # no allowed action (a wall cell): all actions
    assert {policy.epsilon_greedy(rng, q, 1.0, none) for _ in range(200)} == {0, 1, 2, 3}


def test_softmax_follows_boltzmann_probabilities() -> None:
    rng = np.random.default_rng(1)
    q, beta = np.array([0.0, 1.0, 2.0]), 1.5
    n = 20_000
    counts = np.bincount([policy.softmax(rng, q, beta) for _ in range(n)], minlength=3)
    p = np.exp(beta * q) / np.exp(beta * q).sum()
    chi2 = ((counts - n * p) ** 2 / (n * p)).sum()
    assert chi2 < 13.8  # 2 degrees of freedom, p = 0.001
    allowed = np.array([True, True, False])
    assert 2 not in {policy.softmax(rng, q, beta, allowed) for _ in range(300)}
    assert policy.softmax(rng, np.array([0.0, 1e6]), 10.0) == 1  # stable for huge values


def test_select_dispatches_and_names_unknown_policies() -> None:
    q = np.array([0.0, 1.0])
    a, b = np.random.default_rng(2), np.random.default_rng(2)
    assert policy.select(a, q, "epsilon_greedy", 0.3, 5.0) == policy.epsilon_greedy(b, q, 0.3)
    assert policy.select(a, q, "softmax", 0.3, 5.0) == policy.softmax(b, q, 5.0)
    with pytest.raises(ValueError, match="unknown policy 'greedy'"):
        policy.select(a, q, "greedy", 0.3, 5.0)
    with pytest.raises(ConfigError, match=r"agent.policy 'softmx' is not known \(did you mean"):
        policy.check_policy("softmx")


@pytest.mark.parametrize("name", ["epsilon_greedy", "softmax"])
def test_policies_match_their_numba_twin(name: str) -> None:
    """The compiled kernel's select_action draws the same actions from the same generator."""
    from cobelrun.agents.codes import POLICIES
    from cobelrun.agents.kernels import select_action

    a, b, gen = np.random.default_rng(7), np.random.default_rng(7), np.random.default_rng(0)
    for _ in range(500):
        q = gen.integers(0, 3, 4).astype(float)  # many ties
        mask = gen.random(4) < 0.7
        use_mask = bool(gen.random() < 0.5)
        mine = policy.select(a, q, name, 0.3, 2.0, mask if use_mask else None)
        twin = select_action(b, q, mask, use_mask, POLICIES[name], 0.3, 2.0)
        assert mine == twin
