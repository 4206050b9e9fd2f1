"""The ``--quick`` path of the figures not covered elsewhere (fig8, fig8_stable, fig9_fast,
pma, revaluation, conditioning), built in-process as ``cobel figure NAME --quick`` builds them: the spec's quick
overrides plus a few that make the runs tiny, run planning, the runs, the drawing and the
PNG/PDF/CSV files. (fig4, fig6a, fig6b, fig7, fig9 and morris: test_frame_times.py,
test_fig6a.py, test_figures.py, test_water_maze.py; fig6a_paper is fig6a's DQN at the paper's
84 x 84 images and 50 seeds: its plan is tested in test_fig6a.py, its runs are fig6a's.)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cobelrun.figures import registry

#: extra overrides (after the spec's own quick ones) that make each figure's runs tiny
TINY: dict[str, list[str]] = {
    "fig8": [
        "seed=range(0,1)",
        "task.protocol.phases.0.trials=4",
        "task.protocol.max_steps=6",
        "agent.learning_starts=4",
        "task.monitors.maps.every=2",
        "task.monitors.maps.grid=[6,5]",
    ],
    "fig8_stable": [
        "task.runs=1",
        "task.protocol.phases.0.trials=4",
        "task.protocol.max_steps=6",
        "agent.learning_starts=4",
        "task.monitors.maps.every=2",
        "task.monitors.maps.grid=[6,5]",
    ],
    "fig9_fast": ["task.runs=2"],
    "pma": [],  # its quick runs: 3 runs x 8 trials per agent
    "revaluation": ["task.job.runs=2", "task.job.training_trials=20"],
    "conditioning": ["task.runs=1"],
}
NEEDS = {
    "fig8": ("stable_baselines3", "pybullet"),
    "fig8_stable": ("stable_baselines3", "pybullet"),
    "fig9_fast": ("stable_baselines3",),
}


def build_quick(name: str, root: Path) -> tuple[registry.Figure, dict[str, Path]]:
    for module in NEEDS.get(name, ()):
        pytest.importorskip(module)
    figure = registry.figures()[name]
    quick = {label: list(extra) for label, extra in figure.quick.items()}
    quick["*"] = [*quick.get("*", []), *TINY[name]]
    figure = dataclasses.replace(figure, quick=quick)
    files = registry.build(figure, quick=True, root=root, out_dir=root / "figures", jobs=1)
    for suffix in ("png", "pdf", "csv"):
        assert files[suffix] == root / "figures" / f"{name}_quick.{suffix}"
        assert files[suffix].stat().st_size > 0
    assert files["pdf"].read_bytes().startswith(b"%PDF")
    assert files["png"].read_bytes().startswith(b"\x89PNG")
    return figure, files


def run_dirs(figure: registry.Figure, root: Path) -> dict[str, list[Path]]:
    """The run folders of each label, as the build planned them."""
    out: dict[str, list[Path]] = {}
    for planned in registry.plan_runs(figure, quick=True, root=root):
        out.setdefault(planned.label, []).append(planned.run_dir)
    return out


def test_fig8_quick(tmp_path):
    _, files = build_quick("fig8", tmp_path)
    table = pd.read_csv(files["csv"])
    # one job, snapshots before training and every 2 of its 4 trials, 50 analysis units
    assert table["job"].tolist() == [0, 0, 0] and table["trial"].tolist() == [0, 2, 4]
    assert (table["units"] == 50).all()
    assert table["place_cell_fraction"].between(0, 1).all()
    assert (table["place_cells"] == table["place_cell_fraction"] * table["units"]).all()


def test_pma_quick_medians_are_the_runs(tmp_path):
    figure, files = build_quick("pma", tmp_path)
    table = pd.read_csv(files["csv"])
    assert table["trial"].tolist() == list(range(1, 9))
    for label, dirs in run_dirs(figure, tmp_path).items():
        trials = pd.concat(pd.read_parquet(d / "trials.parquet") for d in dirs)
        assert trials["run"].nunique() == 3
        median = trials.groupby("trial")["steps"].median()
        np.testing.assert_allclose(table[f"{label}_median_steps"], median.to_numpy())
    for column in ("forward_per_trial_start", "reverse_per_trial_end"):
        assert (table[column] >= 0).all()


def test_revaluation_quick_scores_every_design_maze_and_budget(tmp_path):
    figure, files = build_quick("revaluation", tmp_path)
    table = pd.read_csv(files["csv"])
    assert set(table["design"]) == {"reward", "transition", "policy"}
    assert set(table["maze"]) == {"graph", "grid"}
    assert (table["runs"] == 2).all()
    np.testing.assert_allclose(table["score"], table["after"] - table["before"])
    dirs = run_dirs(figure, tmp_path)
    assert set(dirs) == {*table["design"], *(f"{d}_grid" for d in table["design"])}


def test_conditioning_quick_predictions_per_paradigm_and_model(tmp_path):
    _, files = build_quick("conditioning", tmp_path)
    table = pd.read_csv(files["csv"])
    assert set(table["task"]) == {"acquisition_extinction", "blocking", "overshadowing",
                                  "conditioned_inhibition", "second_order", "renewal",
                                  "latent_inhibition"}  # fmt: skip
    assert {"rescorla_wagner", "pearce_hall", "td_conditioning"} <= set(table["model"])
    assert np.isfinite(table["V"]).all()
    acq = table[(table["task"] == "acquisition_extinction") & (table["model"] == "rescorla_wagner")]
    # Rescorla-Wagner: V near the asymptote after acquisition, near 0 after extinction
    v = acq.set_index("probe")["V"]
    assert v["acquisition"] > 0.9 and v["extinction"] < 0.1
    # latent inhibition: Pearce-Hall's preexposed A lags the novel B while conditioning
    li = table[(table["task"] == "latent_inhibition") & (table["model"] == "pearce_hall")]
    v = li.set_index("probe")["V"]
    assert v["A"] < v["B"]


def test_fig8_stable_quick(tmp_path):
    """cobel's stabilised Fig. 8 training, tiny: snapshots before training and every 2 trials,
    boxes compared by extent."""
    _, files = build_quick("fig8_stable", tmp_path)
    table = pd.read_csv(files["csv"])
    assert table["trial"].tolist() == [0, 2, 4] and (table["units"] == 50).all()
    assert table["place_cell_fraction"].between(0, 1).all()


def test_fig9_fast_quick_is_the_two_afc_fast_task(tmp_path):
    """fig9_fast: two_afc_fast's runs (Q from 0.5) drawn as Fig. 9: 50 trials of 2 runs, mean
    reward and greedy probe in [0, 1]."""
    figure, files = build_quick("fig9_fast", tmp_path)
    table = pd.read_csv(files["csv"])
    assert len(table) == 50 and table["runs"].eq(2).all()
    assert table["greedy_correct_mean"].between(0, 1).all()
    assert table["reward_mean"].between(0, 1).all()
    (run_dir,) = run_dirs(figure, tmp_path)["dqn"]
    config = (run_dir / ".hydra" / "config.yaml").read_text()
    assert "two_afc_fast" in config
