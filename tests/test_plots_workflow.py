"""Sweep-aware plots (--hue, n per curve, band), compare, --kind plots on world.json, show."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
import pytest

import cobelrun
from cobelrun.figures.runs import ascii_geometry, curve_stats, load_geometry, occupancy, plot_curves
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process

matplotlib.use("Agg")

TINY = ["task.runs=3", "task.protocol.phases.0.trials=8", "task.protocol.phases.1.trials=8",
        "task.record.mcap=false", "task.save_agents=false"]  # fmt: skip


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A 2 x 2 sweep (agent.epsilon x seed) through the real CLI, sequential launcher."""
    import os
    import subprocess

    from tests.conftest import cobel_exe

    root = tmp_path_factory.mktemp("sweep")
    proc = subprocess.run(
        [*cobel_exe(), "run", "-m", "hydra/launcher=basic", "task=tmaze_extinction",
         "agent.epsilon=0.05,0.5", "seed=1,2", *TINY, f"hydra.sweep.dir={root / 'sw'}"],
        cwd=root, env={**os.environ, "COBEL_RESULTS": str(root)}, capture_output=True,
        text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root / "sw", proc


def test_sweep_ends_with_job_table(sweep):
    _, proc = sweep
    for text in ("agent.epsilon", "status", "time [s]", "done", "--hue agent.epsilon"):
        assert text in proc.stderr, proc.stderr


def test_curves_by_swept_key_have_the_right_n(sweep, tmp_path, cli):
    sweep_dir, _ = sweep
    trials = cobelrun.load_sweep(sweep_dir)
    assert {"agent.epsilon", "seed", "job"} <= set(trials.columns)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    drawn = plot_curves(trials, "steps", ax, hue="agent.epsilon", units=("job", "run"))
    plt.close(fig)
    # 2 seeds x 3 runs per epsilon value, not every job pooled
    assert drawn == [("agent.epsilon=0.05", 6), ("agent.epsilon=0.5", 6)]
    proc = cli("plot", str(sweep_dir), "--hue", "agent.epsilon", "-o", str(tmp_path / "h.png"))
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "h.png").stat().st_size > 5000
    bad = cli("plot", str(sweep_dir), "--hue", "agent.epsilom")
    assert bad.returncode == 2 and "did you mean 'agent.epsilon'" in bad.stderr


def test_curve_stats_band():
    trials = pd.DataFrame(
        {"run": [0, 1, 2, 0, 1, 2], "trial": [1, 1, 1, 2, 2, 2], "reward": [0, 1, 2, 1, 1, 1.0]}
    )
    s = curve_stats(trials, "reward")
    assert list(s["n"]) == [3, 3]
    assert s.loc[1, "mean"] == 1.0
    # t(0.975, 2) * sd / sqrt(3) with sd = 1
    assert s.loc[1, "hi"] - 1.0 == pytest.approx(4.302653 / np.sqrt(3), rel=1e-5)
    assert s.loc[2, "lo"] == s.loc[2, "hi"] == 1.0


def test_compare_and_kinds_on_saved_geometry(sweep, tmp_path, cli):
    sweep_dir, _ = sweep
    a, b = sweep_dir / "0", sweep_dir / "3"
    proc = cli("compare", str(a), str(b), "--labels", "low,high", "-o", str(tmp_path / "c.png"))
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "c.png").is_file()
    geometry = load_geometry(a)
    steps = cobelrun.load(a).steps
    counts, _, _ = occupancy(steps, geometry)
    assert counts.sum() == len(steps)  # every step falls in a cell of the saved grid
    for kind in ("occupancy", "trajectories", "latency", "response"):
        out = tmp_path / f"{kind}.png"
        proc = cli("plot", str(a), "--kind", kind, "-o", str(out))
        assert proc.returncode == 0, proc.stderr
        assert out.stat().st_size > 5000
    bad = cli("plot", str(a), "--kind", "ocupancy")
    assert bad.returncode == 2 and "did you mean 'occupancy'" in bad.stderr


def test_show_env_and_task(cli, tmp_path):
    proc = cli("show", "env=tmaze_paper", "-o", str(tmp_path / "t.png"))
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "t.png").stat().st_size > 3000
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("tmaze_paper: grid")
    assert any("#" in line and "." in line for line in lines)
    proc = cli("show", "task=latent_learning", "--no-png")
    assert proc.returncode == 0, proc.stderr
    assert not list(Path(tmp_path).glob("show_*.png"))
    bad = cli("show", "env=tmaze_papr")
    assert bad.returncode == 2 and "did you mean" in bad.stderr


def test_ascii_grid_marks_free_cells_and_regions():
    from cobelrun.envs.base import Geometry

    g = Geometry(kind="grid", bounds=(0, 0, 3, 2), cells=[[0.5, 0.5], [1.5, 0.5], [2.5, 0.5],
                 [1.5, 1.5]], regions={"goal": {"shape": "point", "x": 2.5, "y": 0.5}})  # fmt: skip
    assert ascii_geometry(g) == "#.#\n..G\nG: goal"
