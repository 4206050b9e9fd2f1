"""Conformance suite for every environment (the Gymnasium/SB3 way).

Parametrized over every env config in ``conf/env`` (instantiated through the composer
``cobel run`` uses) and every ``cobel/...`` gymnasium id. Each env passes
``gymnasium.utils.env_checker.check_env``, gives identical rollouts for two instances with the
same seed, and every contract it declares (:func:`cobelrun.envs.base.capabilities`) behaves.
Every task in ``conf/task`` then records a tiny run through all of its monitors, and each
declared table exists with its declared schema and cobel's Parquet metadata.

A new env gets the whole suite by adding its YAML (or registering its id). Tasks that render
3D scenes or run the frame-time benchmark record with ``-m slow`` only.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pyarrow.parquet as pq
import pytest
from gymnasium.utils.env_checker import check_env
from omegaconf import DictConfig, OmegaConf

import cobelrun
from cobelrun.config import group_options, instantiate
from cobelrun.envs.base import (
    CONTRACTS,
    Changeable,
    DiscreteStates,
    Geometry,
    HasGeometry,
    Posed,
    RendersAtPose,
    TabularModel,
    capabilities,
)
from cobelrun.errors import CobelError
from cobelrun.hydra_app import composer
from cobelrun.io.manifest import config_hash
from cobelrun.io.run_folder import RunFolder
from cobelrun.monitors import TrialKeysMonitor
from cobelrun.recorder import SCHEMA_VERSION
from cobelrun.runner import build_task, run
from cobelrun.targets import allow

COBEL_IDS = sorted(env_id for env_id in gym.registry if env_id.startswith("cobel/"))
ENV_CONFIGS = sorted(group_options("env"))
#: tasks too heavy for the default suite (3D rendering, the frame-time benchmark job)
HEAVY_TASKS = {t for t in group_options("task") if "_3d" in t or t == "render_benchmark"}

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"

_composed: dict[tuple[str, ...], DictConfig] = {}


def compose(*overrides: str) -> DictConfig:
    """The config ``cobel run OVERRIDES`` composes (cached; callers must not modify it)."""
    if overrides not in _composed:
        with composer() as c:
            _composed[overrides] = c(list(overrides))
    return _composed[overrides]


# ------------------------------------------------------------------------------ env sources
ENV_SOURCES = [
    *(pytest.param(("conf", name, ()), id=f"conf:{name}") for name in ENV_CONFIGS),
    *(pytest.param(("id", env_id, ()), id=env_id) for env_id in COBEL_IDS),
    # docs/extending.md's worked example: a user's env module + YAML gets the same suite
    *(pytest.param(("yaml", str(p), ()), id=f"docs:{p.stem}") for p in sorted(EXAMPLES.glob("conf/env/*.yaml"))),
]  # fmt: skip


def make_env(source: tuple[str, str, tuple[str, ...]]) -> gym.Env:
    """A fresh env of a source: ``("conf", name, overrides)`` or ``("id", env_id, ())``."""
    kind, name, extra = source
    if kind == "id":
        return gym.make(name)
    if kind == "yaml":  # a user's env: its module sits next to its conf/ folder
        if str(EXAMPLES) not in sys.path:
            sys.path.insert(0, str(EXAMPLES))
        target = str(OmegaConf.load(name)._target_)
        allow([target.rpartition(".")[0] + ".*"])  # a user's class: allowed as a user does
        return instantiate("env", OmegaConf.load(name))
    return instantiate("env", compose(f"env={name}", *extra).env)


@pytest.fixture(params=ENV_SOURCES)
def factory(request: pytest.FixtureRequest) -> Callable[[], gym.Env]:
    made: list[gym.Env] = []

    def _make() -> gym.Env:
        made.append(make_env(request.param))
        return made[-1]

    yield _make
    for env in made:
        env.close()


# ------------------------------------------------------------------------------ helpers
def rollout(env: gym.Env, seed: int, n: int = 60) -> list[dict[str, Any]]:
    """``n`` seeded random steps (reset on termination): per reset/step the observation,
    reward, flags, info, the action taken (-1 at a reset) and the pose where declared."""
    # the actions' own stream: default_rng(seed) would replay the draws of env.reset(seed=seed),
    # tying the first action to the start drawn (on a two-start linear track, always a bump)
    rng = np.random.default_rng([seed, 1])
    base = env.unwrapped
    posed = isinstance(base, Posed)

    def record(obs: Any, info: dict, action: int, *rest: Any) -> dict[str, Any]:
        row = {"obs": _plain(obs), "info": _plain(info), "action": action, "rest": list(rest)}
        if posed:
            row["pose"] = np.asarray(base.agent_pose())
        return row

    out = [record(*env.reset(seed=seed), -1)]
    for _ in range(n):
        action = int(rng.integers(env.action_space.n))
        obs, reward, term, trunc, info = env.step(action)
        out.append(record(obs, info, action, float(reward), bool(term), bool(trunc)))
        if term or trunc:
            out.append(record(*env.reset(), -1))
    return out


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return np.asarray(x).tolist() if isinstance(x, np.ndarray | np.generic) else x


def _same(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if {k: v for k, v in x.items() if k != "pose"} != {
            k: v for k, v in y.items() if k != "pose"
        }:
            return False
        if "pose" in x and not np.array_equal(x["pose"], y["pose"]):
            return False
    return True


# ------------------------------------------------------------------------------ gymnasium
def test_every_env_config_and_id_is_covered():
    assert ENV_CONFIGS and COBEL_IDS
    assert {"cobel/GridWorld-v0", "cobel/TwoAFC-v0"} <= set(COBEL_IDS)


def test_check_env(factory):
    check_env(factory().unwrapped, skip_render_check=True)


def test_same_seed_same_rollout(factory):
    a, b = factory(), factory()
    assert _same(rollout(a, 11), rollout(b, 11))
    assert _same(rollout(a, 11), rollout(a, 11))  # reset(seed) restarts the env's stream


def test_capabilities_are_known_contracts(factory):
    env = factory()
    caps = capabilities(env)
    assert set(caps) <= set(CONTRACTS)
    assert caps == capabilities(env.unwrapped)


# ------------------------------------------------------------------------------ contracts
def test_pose_is_finite_float_triple(factory):
    env = factory()
    if not isinstance(env.unwrapped, Posed):
        pytest.skip("no 'pose' contract")
    for row in rollout(env, 3):
        pose = row["pose"]
        assert pose.shape == (3,) and pose.dtype == np.float64 and np.isfinite(pose).all()


def test_discrete_states_poses_match_agent_pose(factory):
    env = factory()
    base = env.unwrapped
    if not isinstance(base, DiscreteStates):
        pytest.skip("no 'discrete_states' contract")
    n = base.n_states
    assert isinstance(n, int) and n > 0
    rows = rollout(env, 5)
    states = np.array([r["info"]["state"] for r in rows])
    assert ((states >= 0) & (states < n)).all()
    assert all(base.state_index(int(s)) == s for s in np.unique(states))
    poses = base.poses_of(states, np.array([r["action"] for r in rows]))
    assert poses.shape == (len(rows), 3) and np.isfinite(poses).all()
    assert np.array_equal(base.poses_of(states)[:, :2], poses[:, :2])
    if isinstance(base, Posed):
        walked = np.stack([r["pose"] for r in rows])
        np.testing.assert_allclose(poses[:, :2], walked[:, :2])
        if isinstance(base, HasGeometry) and base.geometry().kind == "grid":
            # in a grid the heading is the last move's direction: poses_of knows it too
            np.testing.assert_allclose(poses[:, 2], walked[:, 2])


def test_geometry_round_trips_and_bounds_every_pose(factory):
    env = factory()
    base = env.unwrapped
    if not isinstance(base, HasGeometry):
        pytest.skip("no 'geometry' contract")
    geo = base.geometry()
    assert isinstance(geo, Geometry) and geo.kind in Geometry.KINDS
    data = json.loads(geo.to_json())
    assert data == geo.to_dict()
    back = Geometry.from_dict(data)
    assert back.to_dict() == geo.to_dict()
    for key in ("walls", "cells", "nodes", "edges", "outline"):
        np.testing.assert_array_equal(getattr(back, key), getattr(geo, key))
    xmin, ymin, xmax, ymax = geo.bounds
    assert xmin < xmax and ymin < ymax
    for arr in (geo.cells, geo.nodes, geo.outline):
        assert ((arr >= [xmin, ymin]) & (arr <= [xmax, ymax])).all()
    if len(geo.edges):
        assert geo.edges.min() >= 0 and geo.edges.max() < len(geo.nodes)
    if isinstance(base, Posed):
        xy = np.stack([r["pose"][:2] for r in rollout(env, 9)])
        assert ((xy >= [xmin, ymin]) & (xy <= [xmax, ymax])).all(), "a pose outside the bounds"


def _first_step(env: gym.Env, seed: int) -> tuple[int, float, bool, dict]:
    """The first seeded step's (action, reward, terminated, info) of :func:`rollout`."""
    rows = rollout(env, seed, n=1)
    reward, term, _ = rows[1]["rest"]
    return rows[1]["action"], reward, term, rows[1]["info"]


def test_changes_take_effect_and_reset_world_restores(factory):
    env = factory()
    base = env.unwrapped
    if not isinstance(base, Changeable):
        pytest.skip("no 'changeable' contract")
    before = rollout(env, 21)
    world = base.world if isinstance(base, TabularModel) else None
    arrays = {k: np.array(getattr(world, k)) for k in ("rewards", "terminal", "starts")} if world else {}  # fmt: skip
    if isinstance(base, DiscreteStates):
        for seed in range(20):  # a first step that moves to a non-terminal state
            rows = rollout(env, seed, n=1)
            s0, s = rows[0]["info"]["state"], rows[1]["info"]["state"]
            if s != s0 and not rows[1]["rest"][1]:
                break
        else:
            pytest.fail("no seeded first step moved to another non-terminal state")
        base.apply_changes(starts=[s0])
        assert {env.reset(seed=k)[1]["state"] for k in range(5)} == {s0}

        def arrivals() -> list[tuple[float, bool]]:
            """(reward, terminated) of every action that leads from s0 to s."""
            found = []
            for action in range(env.action_space.n):
                env.reset(seed=seed)
                _, reward, term, _, info = env.step(action)
                if info["state"] == s:
                    found.append((reward, term))
            return found

        base.apply_changes(rewards={s: 7.25})
        low = arrivals()
        base.apply_changes(rewards={s: 9.25})
        high = arrivals()
        # arrival rewards moved (approx: a noisy reward, env.world.reward_sd, adds the same draw)
        assert low and [r for r, _ in high] == pytest.approx([r + 2.0 for r, _ in low], abs=1e-12)
        try:
            base.apply_changes(terminals={s: True})
        except (CobelError, ValueError):
            pass  # an env may refuse a change it does not support, with an error
        else:
            assert all(term for _, term in arrivals())  # arriving at s now ends the trial
    else:  # no state to point at: a change that keeps the world as it is
        base.apply_changes(rewards=None, terminals=None, starts=None)
    base.reset_world()
    assert _same(rollout(env, 21), before)
    for key, value in arrays.items():
        np.testing.assert_array_equal(getattr(base.world, key), value)


def test_renders_at_pose(factory):
    env = factory()
    base = env.unwrapped
    if not isinstance(base, RendersAtPose):
        pytest.skip("no 'render_at_pose' contract")
    env.reset(seed=0)
    x, y, heading = base.agent_pose() if isinstance(base, Posed) else (0.0, 0.0, 0.0)
    a = base.render_at_pose(float(x), float(y), float(heading))
    b = base.render_at_pose(float(x), float(y), float(heading))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# ------------------------------------------------------------------------------ recording
def _task_param(name: str) -> Any:
    marks = [pytest.mark.slow] if name in HEAVY_TASKS else []
    return pytest.param(name, id=name, marks=marks)


def tiny(task: str, trials: int = 1, runs: int = 1, steps: int = 20) -> DictConfig:
    """``task`` with a tiny budget: ``runs`` runs, ``trials`` trials per phase, ``steps`` steps."""
    cfg = OmegaConf.create(OmegaConf.to_container(compose(f"task={task}")))
    cfg.task.runs = runs
    if cfg.task.get("protocol") is not None:
        cfg.task.protocol.max_steps = min(int(cfg.task.protocol.max_steps), steps)
        for phase in cfg.task.protocol.phases:
            phase.trials = min(int(phase.trials), trials)
    return cfg


def declared_tables(cfg: DictConfig) -> tuple[dict[str, list], int, bool]:
    """Tables the task's monitors declare (name -> fields) as the recorder writes them, the
    number of trials in all, and whether the env has a geometry."""
    task = build_task(cfg)
    tables: dict[str, list] = {}
    for monitor in [TrialKeysMonitor(), *task.monitors.values()]:
        for t in monitor.tables():
            if t.per == "step" and not task.record.steps:
                continue
            tables.setdefault(t.name, []).extend(t.fields)
    geometry = isinstance(task.env.unwrapped, HasGeometry)
    task.env.close()
    return tables, task.runs * task.protocol.n_trials, geometry


@pytest.mark.parametrize("task", [_task_param(t) for t in sorted(group_options("task"))])
def test_short_run_records_every_declared_table(task, tmp_path):
    cfg = tiny(task)
    if cfg.task.get("job") is not None:
        pytest.skip("a custom job, no monitors")
    tables, n_trials, geometry = declared_tables(cfg)
    assert "trials" in tables
    folder = RunFolder(run(cfg, tmp_path / task))
    assert folder.done.is_file()
    assert sorted(folder.tables()) == sorted(tables)
    assert not folder.unfinished_tables()
    assert folder.world.is_file() == geometry
    if geometry:
        Geometry.from_dict(json.loads(folder.world.read_text()))
    resolved = OmegaConf.to_container(cfg, resolve=True)
    for name, fields in tables.items():
        pf = pq.ParquetFile(folder.table(name))
        schema = pf.schema_arrow
        assert [(f.name, f.type) for f in schema] == [(f.name, f.type) for f in fields], name
        meta = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()}
        assert meta["cobel.version"] == cobelrun.__version__
        assert meta["cobel.config_hash"] == config_hash(resolved)
        assert meta["cobel.seed"] == str(cfg.seed)
        assert meta["cobel.schema_version"] == SCHEMA_VERSION
        pf.read()  # every row group decodes
    trials = pq.read_table(folder.table("trials")).to_pandas()
    assert len(trials) == n_trials
    assert trials["trial"].tolist() == list(range(1, n_trials + 1))
