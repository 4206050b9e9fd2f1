"""Every YAML under conf/ parses, composes and instantiates (SB3/Hydra-app style)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from cobelrun.config import builtin_conf_dir, group_options, instantiate, register_resolvers
from cobelrun.errors import ConfigError
from cobelrun.protocol import Protocol
from cobelrun.runner import build_task

CONF = builtin_conf_dir()
ALL_YAML = sorted(CONF.rglob("*.yaml"))


def _compose(*overrides: str):
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_conf_is_not_empty():
    for group in ("task", "env", "agent", "protocol"):
        assert group_options(group), group


@pytest.mark.parametrize("path", ALL_YAML, ids=lambda p: str(p.relative_to(CONF)))
def test_every_yaml_parses_and_describes_itself(path: Path):
    OmegaConf.load(path)
    text = path.read_text()
    assert (
        any(
            line.startswith("#") and not line.startswith("# @package") for line in text.splitlines()
        )
        or "description" in text
    ), f"{path} needs a one-line description comment"


@pytest.mark.parametrize("task", sorted(group_options("task")))
def test_every_task_composes_and_builds(task: str):
    cfg = _compose(f"task={task}")
    built = build_task(cfg, probe_agent=True)
    assert built.runs >= 1 and built.protocol.n_trials >= 1


@pytest.mark.parametrize("env", sorted(group_options("env")))
def test_every_env_instantiates_and_passes_check_env(env: str):
    from gymnasium.utils.env_checker import check_env

    cfg = _compose(f"env={env}")
    instance = instantiate("env", cfg.env)
    assert isinstance(instance.unwrapped, gym.Env)
    check_env(instance.unwrapped, skip_render_check=True)


def _env_for(agent_cls, agent_cfg=None):
    """An environment from conf/env whose spaces the agent supports (and, given the agent's
    config, that the agent can be built on: some agents need a tabular world)."""
    for env in sorted(group_options("env")):
        instance = instantiate("env", _compose(f"env={env}").env)
        try:
            agent_cls.check_spaces(instance)
            if agent_cfg is not None:
                instantiate("agent", agent_cfg, env=instance, seed=0)
            return instance
        except Exception:
            continue
    return None


@pytest.mark.parametrize("agent", sorted(group_options("agent")))
def test_every_agent_instantiates(agent: str):
    import importlib

    # task=gridworld sets no agent parameters (the default task's belong to Dyna-Q)
    cfg = _compose("task=gridworld", f"agent={agent}")
    module, _, name = cfg.agent._target_.rpartition(".")
    agent_cls = getattr(importlib.import_module(module), name)
    env = _env_for(agent_cls, cfg.agent)
    if env is None:  # agents for special envs are covered by the task that uses them
        tasks = [
            t
            for t in group_options("task")
            if _compose(f"task={t}").agent._target_ == cfg.agent._target_
        ]
        assert tasks, f"agent {agent} fits no env in conf/env and no task uses it"
        return
    try:
        instance = instantiate("agent", cfg.agent, env=env, seed=0)
    except ConfigError:
        # an agent configured for one kind of input (agent=dqn_fig8: a CNN for images) is
        # built on the first env it accepts
        env = _env_accepting(cfg.agent)
        instance = instantiate("agent", cfg.agent, env=env, seed=0)
    assert instance.env is env


def _env_accepting(agent_cfg):
    for name in sorted(group_options("env")):
        env = instantiate("env", _compose(f"env={name}").env)
        try:
            instantiate("agent", agent_cfg, env=env, seed=0)
            return env
        except ConfigError:
            continue
    raise AssertionError(f"no env in conf/env accepts {agent_cfg._target_} as configured")


@pytest.mark.parametrize("protocol", sorted(group_options("protocol")))
def test_every_protocol_composes(protocol: str):
    cfg = _compose(f"protocol={protocol}")
    p = Protocol.from_config(OmegaConf.to_container(cfg.task.protocol, resolve=True))
    assert p.n_trials > 0 and p.max_steps > 0


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("epsilonn", 0.1, "unknown key 'agent.epsilonn'"),  # a typo of a base-class key
        ("epsilon", "abc", "agent.epsilon must be"),  # a base-class key of the wrong type
    ],
)
def test_keys_passed_on_to_a_base_class_are_checked(key, value, message):
    """Dyna-DSR takes Dyna-DQN's parameters as **kwargs; validation follows them to the base."""
    from cobelrun.config import validate_node
    from cobelrun.errors import ConfigError

    node = {"_target_": "cobelrun.agents.DynaDSR", "reward_learning_rate": 0.1, key: value}
    with pytest.raises(ConfigError, match=message):
        validate_node("agent", node, provided=("env",))
    validate_node("agent", {"_target_": "cobelrun.agents.DynaDSR", "epsilon": 0.2})


def test_factory_builds_a_fresh_object_per_call_and_reports_bad_values_as_instantiate_does():
    from cobelrun.config import factory

    flat = {"_target_": "cobelrun.envs.choice.TwoAFCEnv", "choices": [[0, 1], [2, 3]]}
    make = factory("env", flat)
    a, b = make(), make()
    assert a is not b and type(a).__name__ == "TwoAFCEnv"
    assert a.choices.tolist() == [[0, 1], [2, 3]] and a.choices is not b.choices
    # a node with nested objects goes through instantiate each call: nothing shared either
    nested = OmegaConf.to_container(_compose("task=latent_learning").env, resolve=True)
    make_nested = factory("env", nested)
    e1, e2 = make_nested(), make_nested()
    assert e1 is not e2 and e1.unwrapped.world is not e2.unwrapped.world
    # validated once, up front: an unknown key fails before any object is built
    with pytest.raises(ConfigError, match="unknown key"):
        factory("env", {**flat, "colour": 3})
    # a constructor's own error is one line naming the node, as with instantiate
    bad = factory("env", {"_target_": "cobelrun.envs.choice.TwoAFCEnv", "stimuli": "abc"})
    with pytest.raises(ConfigError, match=r"^cannot build env: could not convert"):
        bad()
    with pytest.raises(ConfigError, match=r"^cannot build env: could not convert"):
        instantiate("env", {"_target_": "cobelrun.envs.choice.TwoAFCEnv", "stimuli": "abc"})
    # the env's own checks keep their message
    with pytest.raises(ConfigError, match="choices name stimuli outside"):
        factory("env", {**flat, "choices": [[0, 9]]})()
