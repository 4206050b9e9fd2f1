"""Checkpoints (cobelrun.checkpoint): an agent restored from a checkpoint file goes on exactly
as the agent that wrote it (the same trials, actions, rewards and learned state), for every
agent config; refusals of foreign, damaged or other-version checkpoints are one line."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cobelrun import checkpoint as ck
from cobelrun.checkpoint import CheckpointConfig, CheckpointError
from cobelrun.errors import ConfigError
from tests.test_agent_conformance import AGENT_CONFIGS, assert_same_batch, build

HASH = "0" * 64


def save(agent: Any, env: Any, path: Path, **header: Any) -> int:
    arrays, entry = ck.agent_entry(agent)
    head = {"config_hash": HASH, "agent": entry, "env": ck.env_state(env), **header}
    return ck.write_checkpoint(path, head, arrays)


def restore(agent: Any, env: Any, path: Path) -> ck.Checkpoint:
    found = ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    ck.restore_agent(agent, found, path)
    ck.restore_env(env, found.header["env"])
    return found


def assert_same_state(a: Any, b: Any) -> None:
    sa, sb = a.checkpoint_state(), b.checkpoint_state()
    assert sa[0].keys() == sb[0].keys()
    for key in sa[0]:
        np.testing.assert_array_equal(sa[0][key], sb[0][key], err_msg=key)
    assert json.dumps(sa[1], sort_keys=True) == json.dumps(sb[1], sort_keys=True)


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=[pytest.mark.slow] if n == "dqn_fig8" else []) for n in AGENT_CONFIGS],
)
def test_round_trip_goes_on_exactly(name: str, tmp_path: Path) -> None:
    """Train, checkpoint, go on; a differently seeded fresh agent and env restored from the
    file give the same trials (learning and test) and end in the same state."""
    env, agent = build(name, seed=3, env_seed=0)
    agent.train(3, 15)
    path = tmp_path / "checkpoint.npz"
    save(agent, env, path)
    want = [agent.train(4, 15), agent.test(2, 15), agent.train(2, 15)]
    env2, other = build(name, seed=11, env_seed=5)
    restore(other, env2, path)
    got = [other.train(4, 15), other.test(2, 15), other.train(2, 15)]
    for w, g in zip(want, got, strict=True):
        assert_same_batch(w, g)
    assert_same_state(agent, other)


@pytest.mark.parametrize("name", ["per_dqn", "dyna_dsr"])
def test_deep_state_is_in_the_file(name: str, tmp_path: Path) -> None:
    """The replay memory with its sum tree (PER) and the optimiser moments are saved."""
    env, agent = build(name)
    agent.train(4, 15)
    save(agent, env, tmp_path / "c.npz")
    with zipfile.ZipFile(tmp_path / "c.npz") as zf:
        names = {n[: -len(".npy")] for n in zf.namelist()}
    if name == "per_dqn":
        assert {"agent/per.sums", "agent/replay.observations", "agent/rng.torch"} <= names
        sums = ck.read_checkpoint(tmp_path / "c.npz", ck.agent_specs(agent), config_hash=HASH)
        assert sums.arrays["agent/per.sums"][1] > 0  # the tree holds the priorities
    else:
        assert {"agent/optim.sr.0.exp_avg", "agent/optim.reward.0.exp_avg_sq"} <= names


def test_other_version_or_config_is_refused(tmp_path: Path) -> None:
    env, agent = build("dyna_q")
    path = tmp_path / "c.npz"
    save(agent, env, path)
    with pytest.raises(CheckpointError, match="another config"):
        ck.read_checkpoint(path, ck.agent_specs(agent), config_hash="1" * 64)
    arrays, entry = ck.agent_entry(agent)
    head = {"config_hash": HASH, "agent": entry, "cobel_version": "0.0.1"}
    ck.write_checkpoint(path, head, arrays)
    with pytest.raises(CheckpointError, match=r"written by cobel '0.0.1'"):
        ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)


def test_damaged_or_foreign_files_are_refused(tmp_path: Path) -> None:
    _env, agent = build("dyna_q")
    before = agent.checkpoint_state()[0]["Q"].copy()
    path = tmp_path / "c.npz"
    arrays, entry = ck.agent_entry(agent)
    head = {"config_hash": HASH, "agent": entry}
    bad = dict(arrays)
    bad["agent/Q"] = np.zeros((3, 3))  # another shape
    ck.write_checkpoint(path, head, bad)
    with pytest.raises(CheckpointError, match=r"array 'agent/Q': expected shape"):
        ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    bad = dict(arrays)
    bad["agent/memory_next_state"] = np.full_like(arrays["agent/memory_next_state"], 999)
    ck.write_checkpoint(path, head, bad)
    with pytest.raises(CheckpointError, match=r"memory_next_state.*expected values in"):
        ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    ck.write_checkpoint(path, {**head, "agent": {**entry, "class": "x.Y"}}, arrays)
    found = ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    with pytest.raises(CheckpointError, match=r"holds agent 'x\.Y'"):
        ck.restore_agent(agent, found, path)
    ck.write_checkpoint(path, {**head, "agent": {**entry, "state": {"rng": {"x": 1}}}}, arrays)
    found = ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    with pytest.raises(CheckpointError, match="agent generator"):
        ck.restore_agent(agent, found, path)
    np.testing.assert_array_equal(agent.checkpoint_state()[0]["Q"], before)  # untouched
    np.save(tmp_path / "p.npy", np.array([object()], dtype=object), allow_pickle=True)
    with zipfile.ZipFile(path, "w") as zf:  # a pickled member is never read
        zf.writestr(
            ck.HEADER_KEY + ".npy",
            _npy(
                np.array(
                    json.dumps({"format": 1, "cobel_version": ck.__version__, "config_hash": HASH})
                )
            ),
        )
        zf.write(tmp_path / "p.npy", "agent/Q.npy")
    with pytest.raises(CheckpointError, match="pickle"):
        ck.read_checkpoint(path, ck.agent_specs(agent), config_hash=HASH)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        ck.read_checkpoint(tmp_path / "junk.npz", ck.agent_specs(agent), config_hash=HASH)


def _npy(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def test_write_is_atomic_and_replaces(tmp_path: Path) -> None:
    env, agent = build("dyna_q")
    path = tmp_path / "c.npz"
    n1 = save(agent, env, path)
    agent.train(5, 15)
    n2 = save(agent, env, path)
    assert n1 > 0 and n2 == path.stat().st_size
    assert [p.name for p in tmp_path.iterdir()] == ["c.npz"]  # no temporary file left


def test_settings() -> None:
    from cobelrun.agents import DynaQ
    from cobelrun.agents.dqn import DQNAgent

    assert not CheckpointConfig.resolve(None, DynaQ).enabled  # tabular: off by default
    deep = CheckpointConfig.resolve({"every_trials": "auto"}, DQNAgent)
    assert deep.enabled and deep.every_minutes == CheckpointConfig.AUTO_MINUTES
    assert CheckpointConfig.resolve({"every_trials": 50}, DynaQ).every_trials == 50
    off = CheckpointConfig.resolve({"every_minutes": None}, DQNAgent)
    assert not off.enabled
    for node, match in (({"every_trials": 0}, "every_trials must be"),
                        ({"every_minutes": -1}, "every_minutes must be"),
                        ({"keep": "yes"}, "keep must be"),
                        ({"evry_trials": 3}, "not a setting")):  # fmt: skip
        with pytest.raises(ConfigError, match=match):
            CheckpointConfig.resolve(node, DQNAgent)
