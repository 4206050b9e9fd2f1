"""The task-level schema (cobelrun/schema.py): every key's null, wrong type, out-of-range and
unknown-key error is one line that names the key, the value and what is allowed."""

from __future__ import annotations

import copy
from typing import Any

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from cobelrun.config import builtin_conf_dir, register_resolvers
from cobelrun.errors import ConfigError
from cobelrun.protocol import Phase, Protocol
from cobelrun.recorder import RecordConfig
from cobelrun.runner import build_task
from cobelrun.schema import (
    INT32_MAX,
    INT64_MAX,
    PhaseSpec,
    ProtocolSpec,
    RecordSpec,
    RunSpec,
    TaskSpec,
    validate,
    validate_run,
)

HUGE = 2**70
MISSING = object()


@pytest.fixture(scope="module")
def base() -> dict[str, Any]:
    """The composed ``task=tmaze_extinction`` config as plain data."""
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(builtin_conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["task=tmaze_extinction"])
    GlobalHydra.instance().clear()
    plain = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(plain, dict)
    return plain


def _set(cfg: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    cfg = copy.deepcopy(cfg)
    *parents, leaf = path.replace("[", ".").replace("]", "").split(".")
    node: Any = cfg
    for key in parents:
        node = node[int(key)] if key.isdigit() else node[key]
    if value is MISSING:
        del node[leaf]
    else:
        node[int(leaf) if leaf.isdigit() else leaf] = value
    return cfg


INT = "must be an integer"
P0 = "task.protocol.phases[0]"
CASES = [
    # seed
    ("seed", None, "seed must not be null"),
    ("seed", "3", "seed must be an integer >= 0, got '3'"),
    ("seed", 1.5, "seed must be an integer >= 0, got 1.5"),
    ("seed", True, "seed must be an integer >= 0, got True"),
    ("seed", -1, "seed must be an integer >= 0, got -1"),
    ("seed", HUGE, f"seed must be an integer <= {INT64_MAX}, got {HUGE}"),
    ("seed", MISSING, "the config has no 'seed'"),
    # task.name / description
    ("task.name", None, "task.name must not be null"),
    ("task.name", 3, "task.name must be a non-empty string, got 3"),
    ("task.name", "", "task.name must be a non-empty string, got ''"),
    ("task.name", MISSING, "task.name is missing"),
    ("task.description", 5, "task.description must be a string, got 5"),
    # task.runs
    ("task.runs", None, "task.runs must not be null"),
    ("task.runs", "many", "task.runs must be an integer >= 1, got 'many'"),
    ("task.runs", 2.0, "task.runs must be an integer >= 1, got 2.0"),
    ("task.runs", False, "task.runs must be an integer >= 1, got False"),
    ("task.runs", 0, "task.runs must be an integer >= 1, got 0"),
    ("task.runs", -3, "task.runs must be an integer >= 1, got -3"),
    ("task.runs", HUGE, f"task.runs must be an integer <= {INT32_MAX}, got {HUGE}"),
    # task.save_agents
    ("task.save_agents", 1, "task.save_agents must be all, last, none or a list of run indices, got 1"),
    ("task.save_agents", "yes", "task.save_agents must be all, last, none or a list of run indices"),
    ("task.save_agents", [0, -1], "task.save_agents must be all, last, none or a list of run indices"),
    ("task.save_agents", [0, 100], "task.save_agents must be all, last, none or a list of run indices in 0..99, got [0, 100]"),
    ("task.save_agents", [HUGE], "task.save_agents must be all, last, none or a list of run indices in 0..99"),
    # task.monitors (the nodes themselves are checked by config.instantiate)
    ("task.monitors", 3, "task.monitors must be a mapping name -> monitor, got 3"),
    ("task.monitors", [], "task.monitors must be a mapping name -> monitor, got []"),
    (
        "task.monitors.reward",
        "on",
        "task.monitors.reward must be a monitor config (a mapping with a _target_) or null, got 'on'",
    ),
    ("task.record", {"steps": "x" * 200}, "got 'xxxxxxx"),  # long values are shortened
    # task.job
    ("task.job", "run_me", "task.job must be a config node with a _target_, got 'run_me'"),
    # task.record.*
    ("task.record", None, "task.record must not be null"),
    ("task.record", [1], "task.record must be a mapping with keys 'steps', 'mcap'"),
    ("task.record.flush_secs", 1.0,
     "unknown key 'task.record.flush_secs' (did you mean 'flush_seconds'?); allowed: 'steps', "
     "'mcap', 'runs', 'trial_every', 'mcap_runs', 'flush_seconds', 'images'"),
    ("task.record.steps", None, "task.record.steps must not be null"),
    ("task.record.steps", "no", "task.record.steps must be true or false, got 'no'"),
    ("task.record.mcap", 0, "task.record.mcap must be true or false, got 0"),
    ("task.record.runs", None, "task.record.runs must not be null"),
    ("task.record.runs", "some", "task.record.runs must be 'all' or a list of run indices"),
    ("task.record.runs", 3, "task.record.runs must be 'all' or a list of run indices"),
    ("task.record.runs", [0, -1], "task.record.runs must be 'all' or a list of run indices"),
    ("task.record.runs", [0, HUGE], "task.record.runs must be 'all' or a list of run indices"),
    ("task.record.runs", [0, None], "got [0, None]"),
    ("task.record.trial_every", None, "task.record.trial_every must not be null"),
    ("task.record.trial_every", 0, "task.record.trial_every must be an integer >= 1, got 0"),
    ("task.record.trial_every", -2, "task.record.trial_every must be an integer >= 1, got -2"),
    ("task.record.trial_every", 1.5, "task.record.trial_every must be an integer >= 1, got 1.5"),
    ("task.record.trial_every", HUGE, f"task.record.trial_every {INT} <= {INT32_MAX}"),
    ("task.record.mcap_runs", None, "task.record.mcap_runs must not be null"),
    ("task.record.mcap_runs", -1, "task.record.mcap_runs must be 'all' or an integer from 0"),
    ("task.record.mcap_runs", "first", "task.record.mcap_runs must be 'all' or an integer"),
    ("task.record.mcap_runs", HUGE, f"from 0 to {INT32_MAX}, got {HUGE}"),
    ("task.record.flush_seconds", None, "task.record.flush_seconds must not be null"),
    ("task.record.flush_seconds", 0, "task.record.flush_seconds must be a number > 0, got 0"),
    ("task.record.flush_seconds", -1.5, "task.record.flush_seconds must be a number > 0, got -1.5"),
    ("task.record.flush_seconds", "2s", "task.record.flush_seconds must be a number > 0, got '2s'"),
    ("task.record.flush_seconds", float("inf"), "task.record.flush_seconds must be a number > 0"),
    ("task.record.flush_seconds", float("nan"), "task.record.flush_seconds must be a number > 0"),
    ("task.record.flush_seconds", True, "task.record.flush_seconds must be a number > 0, got True"),
    ("task.record.images", None, "task.record.images must not be null"),
    ("task.record.images", "on", "task.record.images must be true or false, got 'on'"),
    # task.protocol.*
    ("task.protocol", None, "task 'tmaze_extinction' has no protocol; pick one with protocol="),
    ("task.protocol", MISSING, "task 'tmaze_extinction' has no protocol"),
    ("task.protocol", "extinction", "task.protocol must be a mapping with keys 'max_steps'"),
    ("task.protocol.max_step", 3, "unknown key 'task.protocol.max_step' (did you mean 'max_steps'"),
    ("task.protocol.max_steps", None, "task.protocol.max_steps must not be null"),
    ("task.protocol.max_steps", MISSING, "task.protocol.max_steps is missing"),
    ("task.protocol.max_steps", 0, "task.protocol.max_steps must be an integer >= 1, got 0"),
    ("task.protocol.max_steps", -5, "task.protocol.max_steps must be an integer >= 1, got -5"),
    ("task.protocol.max_steps", "35", "task.protocol.max_steps must be an integer >= 1, got '35'"),
    ("task.protocol.max_steps", HUGE, f"task.protocol.max_steps {INT} <= {INT32_MAX}"),
    ("task.protocol.phases", None, "task.protocol.phases must not be null"),
    ("task.protocol.phases", [], "task.protocol.phases must be a non-empty list of phases, got []"),
    ("task.protocol.phases", {"a": 1}, "task.protocol.phases must be a non-empty list of phases"),
    ("task.protocol.phases[0]", None, f"{P0} must not be null"),
    ("task.protocol.phases[0]", 5, f"{P0} must be a mapping with keys 'name', 'trials'"),
    (f"{P0}.trails", 5, f"unknown key '{P0}.trails' (did you mean 'trials'?)"),
    (f"{P0}.name", None, f"{P0}.name must not be null"),
    (f"{P0}.name", MISSING, f"{P0}.name is missing"),
    (f"{P0}.name", 7, f"{P0}.name must be a non-empty string, got 7"),
    (f"{P0}.name", "extinction", "task.protocol.phases have duplicate names"),
    (f"{P0}.trials", None, f"{P0}.trials must not be null"),
    (f"{P0}.trials", MISSING, f"{P0}.trials is missing"),
    (f"{P0}.trials", -1, f"{P0}.trials must be an integer >= 0, got -1"),
    (f"{P0}.trials", 1.5, f"{P0}.trials must be an integer >= 0, got 1.5"),
    (f"{P0}.trials", HUGE, f"{P0}.trials {INT} <= {INT32_MAX}"),
    (f"{P0}.trials", INT32_MAX, f"task.protocol.phases have {INT32_MAX + 100} trials in all"),
    (f"{P0}.learning", None, f"{P0}.learning must not be null"),
    (f"{P0}.learning", "off", f"{P0}.learning must be true or false, got 'off'"),
    (f"{P0}.max_steps", 0, f"{P0}.max_steps must be an integer >= 1, got 0"),
    (f"{P0}.max_steps", -1, f"{P0}.max_steps must be an integer >= 1, got -1"),
    (f"{P0}.max_steps", HUGE, f"{P0}.max_steps {INT} <= {INT32_MAX}"),
    (f"{P0}.rewards", [1], f"{P0}.rewards must be a mapping state -> number, got [1]"),
    (f"{P0}.rewards.right_arm", "high", f"{P0}.rewards must be a mapping state -> number"),
    (f"{P0}.rewards.right_arm", None, f"{P0}.rewards must be a mapping state -> number"),
    (f"{P0}.terminals", 1, f"{P0}.terminals must be a mapping state -> true/false, got 1"),
    (f"{P0}.terminals", {"left_arm": 1}, f"{P0}.terminals must be a mapping state -> true/false"),
    (f"{P0}.starts", "start", f"{P0}.starts must be a list of states, got 'start'"),
    (f"{P0}.starts", 3, f"{P0}.starts must be a list of states, got 3"),
    # unknown task keys and missing components
    ("task.runz", 3, "unknown key 'task.runz' (did you mean 'runs'?); allowed: 'name', 'description'"),
    ("env", None, "env must not be null"),
    ("agent", 3, "agent must be a config node; pick one with agent=NAME, got 3"),
    ("env", MISSING, "the config has no 'env'; pick one with env=NAME"),
    ("task", None, "task must not be null"),
]  # fmt: skip


@pytest.mark.parametrize(
    "path, value, message",
    CASES,
    ids=[f"{c[0]}={'MISSING' if c[1] is MISSING else repr(c[1])}"[:60] for c in CASES],
)
def test_bad_task_level_value_is_one_clear_line(base, path, value, message):
    with pytest.raises(ConfigError) as info:
        validate_run(_set(base, path, value))
    text = str(info.value)
    assert message in text
    assert "\n" not in text and "pydantic" not in text and "For further information" not in text
    assert len(text) < 300  # long values are shortened


@pytest.mark.parametrize(
    "path, value",
    [
        ("task.runs", INT32_MAX),
        ("task.record.runs", [0, 3]),
        ("task.record.mcap_runs", "all"),
        ("task.record.flush_seconds", 1),  # an integer where a number is expected
        ("task.monitors", None),  # no monitors
        ("task.monitors.reward", None),  # one switched off
        ("task.description", None),
        (f"{P0}.rewards", None),  # no change
        (f"{P0}.max_steps", None),
        (f"{P0}.trials", 0),  # an empty phase
        (f"{P0}.starts", [[1, 3], "right_arm", 5]),  # cells, places, indices
        (f"{P0}.rewards", {7: 1, "left_arm": 0.5}),  # integer states, integer rewards
        ("seed", INT64_MAX),
        ("task.save_agents", None),  # null: none
        ("task.save_agents", False),
        ("task.save_agents", "last"),
        ("task.save_agents", [0, 99]),
        ("hydra", {"run": {"dir": "x"}}),  # Hydra's own node is not the schema's business
    ],
)
def test_good_values_pass(base, path, value):
    validate_run(_set(base, path, value))


def test_composed_task_builds_from_the_schema(base):
    cfg = OmegaConf.create(_set(base, "task.record.runs", [0, 2]))
    task = build_task(cfg)
    assert task.record.runs == (0, 2) and task.runs == 100 and task.seed == 0
    assert [p.name for p in task.protocol.phases] == ["acquisition", "extinction"]
    assert task.protocol.phases[0].rewards == {"right_arm": 1.0, "left_arm": 0.0}


def test_runtime_defaults_match_the_schema():
    """RecordConfig and Phase keep their own defaults (they are built directly in code too)."""
    assert RecordConfig() == RecordConfig.from_config({}) == RecordConfig.from_config(None)
    assert RecordConfig.from_spec(RecordSpec()) == RecordConfig()
    spec = PhaseSpec(name="a", trials=1)
    built = Protocol.from_spec(ProtocolSpec(max_steps=5, phases=[spec])).phases[0]
    assert built == Phase(name="a", trials=1)


def test_where_names_the_key_path():
    with pytest.raises(ConfigError, match=r"^custom\.runs must be 'all'"):
        RecordConfig.from_config({"runs": "x"}, where="custom")
    with pytest.raises(ConfigError, match=r"^p\.phases have duplicate names"):
        Protocol.from_config(
            {"max_steps": 3, "phases": [{"name": "a", "trials": 1}, {"name": "a", "trials": 1}]},
            where="p",
        )


def test_every_model_is_closed_and_strict():
    for model in (PhaseSpec, ProtocolSpec, RecordSpec, TaskSpec):
        assert model.model_config["extra"] == "forbid" and model.model_config["strict"]
    assert RunSpec.model_config["strict"]
    with pytest.raises(ConfigError, match=r"task\.record\.steps must be true or false"):
        validate(RecordSpec, {"steps": "true"})
