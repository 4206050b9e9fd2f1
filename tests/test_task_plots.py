"""``cobel plot RUN`` draws a figure for every built-in task (chosen from what the run recorded),
``--kind`` offers only what a run has, and what the agent learned (value, policy, Q, SR, rate
maps) is drawn from the saved agents. Tiny real runs, in-process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import cobelrun
from cobelrun.config import group_options
from cobelrun.errors import CobelError
from cobelrun.figures import plot_run
from cobelrun.figures.kinds import available_kinds, plot_kind, plot_selection
from cobelrun.figures.learned import action_vectors, q_table
from cobelrun.runner import run as run_cfg
from tests.test_env_conformance import HEAVY_TASKS, tiny

#: tasks whose tiny run takes long (deep agents on images, revaluation jobs)
SLOW = {"place_cells", "place_cells_original", "latent_learning", "reward_revaluation",
        "transition_revaluation", "policy_revaluation", "two_afc", "two_afc_fast",
        "two_afc_probabilistic", "two_afc_reversal"}  # fmt: skip
#: the revaluation jobs' own tiny budget
JOB_TINY = {"runs": 2, "training_trials": 30, "revaluation_trials": 5, "replay_budgets": [0]}


def _png_size(path: Path) -> tuple[int, int]:
    import struct

    head = Path(path).read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def _tiny_run(task: str, out: Path, trials: int = 8, steps: int = 60) -> Path:
    cfg = tiny(task, trials=trials, runs=2, steps=steps)
    if cfg.task.get("job") is not None:
        for k, v in JOB_TINY.items():
            if k in cfg.task.job:
                cfg.task.job[k] = v
    run_cfg(cfg, out)
    return out


def _param(task: str):
    marks = [pytest.mark.slow] if task in SLOW or task in HEAVY_TASKS else []
    return pytest.param(task, id=task, marks=marks)


@pytest.mark.parametrize("task", [_param(t) for t in sorted(group_options("task"))])
def test_every_task_has_a_figure_and_its_kinds(task: str, tmp_path: Path) -> None:
    run_dir = _tiny_run(task, tmp_path / task)
    png = plot_run(run_dir, tmp_path / "fig.png")
    w, h = _png_size(png)
    assert w > 300 and h > 200
    kinds = available_kinds(run_dir)
    for kind in kinds[:1]:  # every kind of the maze run: test_learned_kinds_and_selections
        w, _ = _png_size(plot_kind(run_dir, kind, tmp_path / f"{kind}.png"))
        assert w > 300
    missing = [
        k for k in ("occupancy", "trajectories", "latency", "reward", "sr") if k not in kinds
    ]
    for kind in missing[:2]:  # refused in one line that names what the run offers
        with pytest.raises(CobelError, match=f"nothing for --kind {kind}; this run offers"):
            plot_kind(run_dir, kind, tmp_path / "no.png")


@pytest.fixture(scope="module")
def maze(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("maze") / "run"
    return _tiny_run("dyna_maze", out, trials=6, steps=400)  # long enough to find the goal


def test_default_figures_follow_the_monitors(maze: Path, tmp_path: Path) -> None:
    # dyna_maze has no response monitor (once: "no cumulative_response column"): steps per
    # episode and replay directions, two panels side by side
    w, h = _png_size(plot_run(maze, tmp_path / "a.png"))
    assert w > 1.8 * h
    assert set(available_kinds(maze)) >= {"occupancy", "trajectories", "latency", "reward",
                                          "value", "policy", "q"}  # fmt: skip


@pytest.mark.slow  # a DQN run (~15 s)
def test_two_afc_offers_no_maze_kinds(tmp_path: Path) -> None:
    cfg = tiny("two_afc_fast", trials=5, runs=1)
    run_dir = run_cfg(cfg, tmp_path / "afc") and tmp_path / "afc"
    assert "occupancy" not in available_kinds(run_dir)
    with pytest.raises(
        CobelError, match=r"nothing for --kind occupancy; this run offers: .*reward"
    ):
        plot_kind(run_dir, "occupancy", tmp_path / "x.png")


def test_agent_loader_returns_real_shapes(maze: Path) -> None:
    r = cobelrun.load(maze)
    a0, a1 = r.agent(0), r.agent(1)
    assert a0["Q"].ndim == 2 and a0["Q"].shape == a1["Q"].shape
    n_states = a0["Q"].shape[0]
    assert r.steps["state"].max() < n_states
    assert not np.array_equal(a0["Q"], a1["Q"])  # two independently seeded agents
    with pytest.raises(CobelError, match=r"run 7 has no saved agent.*saved runs: 0, 1"):
        r.agent(7)


def test_q_from_sr_is_m_times_w() -> None:
    rng = np.random.default_rng(0)
    M, w = rng.random((5, 4, 5)), rng.random(5)
    q = q_table({"M": M, "w": w})
    assert q.shape == (5, 4)
    assert q[2, 3] == pytest.approx(float(M[2, 3] @ w))


def test_action_vectors_are_the_recorded_moves(maze: Path) -> None:
    steps = cobelrun.load(maze).steps
    vec = action_vectors(steps, 4)
    # four grid actions, four distinct unit moves along the axes
    assert np.allclose(np.abs(vec).sum(axis=1), 1.0)
    assert len({tuple(v) for v in np.round(vec).astype(int)}) == 4


def test_learned_kinds_and_selections(maze: Path, tmp_path: Path) -> None:
    for kind in ("value", "policy", "q"):
        assert _png_size(plot_selection(maze, kind, tmp_path / f"{kind}.png", run=1))[0] > 300
    with pytest.raises(CobelError, match="nothing for --kind sr"):
        plot_selection(maze, "sr", tmp_path / "sr.png", state=3)
    png = plot_selection(maze, "trajectories", tmp_path / "t.png", run=1, trials="2:4")
    assert _png_size(png)[0] > 300
    with pytest.raises(CobelError, match="recorded runs: 0, 1"):
        plot_selection(maze, "trajectories", tmp_path / "t.png", run=5)
    with pytest.raises(CobelError, match="give A:B"):
        plot_selection(maze, "trajectories", tmp_path / "t.png", trials="x")


def test_sr_row_of_a_state(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from cobelrun.api import compose

    cfg = OmegaConf.create(OmegaConf.to_container(compose("dyna_maze", ["agent=sr_td"])))
    cfg.task.runs = 1
    cfg.task.protocol.max_steps = 200
    for phase in cfg.task.protocol.phases:
        phase.trials = 4
    run_cfg(cfg, tmp_path / "sr")
    assert "sr" in available_kinds(tmp_path / "sr")
    assert _png_size(plot_selection(tmp_path / "sr", "sr", tmp_path / "sr.png", state=0))[0] > 300
    M = cobelrun.load(tmp_path / "sr").agent(0)["M"]
    assert M.ndim == 3 and M.shape[0] == M.shape[2]
    with pytest.raises(CobelError, match=r"--state 9999 is not a state"):
        plot_selection(tmp_path / "sr", "sr", tmp_path / "sr.png", state=9999)
