"""Fig. 7: latent learning in the Blodgett maze (Dyna-DSR).

- 7B: escape latency of the latent and the direct group, aligned on the first rewarded trial.
- 7C: the successor representation of the start state drawn on the maze, at the end of the
  exploration phase and at the end of training (from the ``sr/output`` layer recorded by the
  activity monitor: ``M(s_start, a)`` for every action, averaged over actions).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError

REWARDED = "rewarded"
GROUP_COLORS = {"latent": "tab:blue", "direct": "tab:orange"}


def aligned_latency(trials: pd.DataFrame, phase: str = REWARDED) -> pd.DataFrame:
    """Rows of the ``phase`` trials with ``rewarded_trial`` = 1 for the phase's first trial."""
    if "steps" not in trials:
        raise CobelError("the trials table has no steps column (no latency monitor)")
    rows = trials[trials["phase"] == phase]
    if rows.empty:
        raise CobelError(f"the trials table has no {phase!r} phase to align on")
    return rows.assign(rewarded_trial=rows["trial_in_phase"].astype(int))


def plot_latency_groups(groups: Mapping[str, pd.DataFrame], ax) -> None:
    """Fig. 7B: mean latency (band: 25th-75th percentile over runs) per rewarded trial."""
    for name, trials in groups.items():
        rows = aligned_latency(trials)
        g = rows.groupby("rewarded_trial")["steps"]
        x = g.mean().index.to_numpy()
        color = GROUP_COLORS.get(name)
        ax.plot(x, g.mean(), lw=1.5, color=color, label=f"{name} ({rows['run'].nunique()} runs)")
        ax.fill_between(x, g.quantile(0.25), g.quantile(0.75), alpha=0.2, lw=0, color=color)
    ax.set_xlabel("trial since reward introduced")
    ax.set_ylabel("escape latency [steps]")
    ax.legend(frameon=False, fontsize=8)


def start_state_sr(
    activity: pd.DataFrame, probe: int, trial: int, n_states: int, layer: str = "sr/output"
) -> np.ndarray:
    """SR of ``probe`` at ``trial`` (mean over runs and actions), shape (n_states,)."""
    rows = activity[
        (activity["layer"] == layer) & (activity["probe"] == probe) & (activity["trial"] == trial)
    ]
    if rows.empty:
        raise CobelError(f"no {layer} activity of probe {probe} at trial {trial}")
    per_unit = rows.groupby("unit")["value"].mean().sort_index().to_numpy()
    return per_unit.reshape(-1, n_states).mean(axis=0)


def plot_sr_on_maze(sr: np.ndarray, height: int, width: int, blocked: np.ndarray, ax, title=""):
    """Draw a per-state vector on the grid; wall cells grey. Returns the image."""
    grid = np.ma.masked_array(sr.reshape(height, width), mask=blocked.reshape(height, width))
    import matplotlib as mpl

    cmap = mpl.colormaps["viridis"].copy()
    cmap.set_bad("0.6")
    im = ax.imshow(grid, cmap=cmap, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)
    return im


def _load(run_dir: Path) -> tuple[pd.DataFrame, dict]:
    from cobelrun.results import load_manifest, load_trials

    trials = load_trials(run_dir)
    return trials, load_manifest(run_dir)


def _group_of(trials: pd.DataFrame) -> str:
    return "latent" if (trials["phase"] != REWARDED).any() else "direct"


def _world(run_dir: Path):
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    cfg = OmegaConf.load(run_dir / "config.yaml")
    return instantiate("env", cfg.env).unwrapped.world


def plot_run(run_dir: str | Path, out: str | Path | None = None, other: str | Path | None = None):
    """Fig. 7 for a run folder (and optionally the other group's folder) into ``out``.

    With an ``activity.parquet`` holding ``sr/output``, the SR of the start state is drawn at
    the end of exploration (trial 100 of the latent group) and at the end of training.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_dir = Path(run_dir)
    trials, _ = _load(run_dir)
    groups = {_group_of(trials): trials}
    if other is not None:
        t2, _ = _load(Path(other))
        groups[_group_of(t2)] = t2
    activity_path = run_dir / "activity.parquet"
    latent_dir = run_dir if _group_of(trials) == "latent" else Path(other) if other else None
    has_sr = latent_dir is not None and (latent_dir / "activity.parquet").is_file()
    fig, axes = plt.subplots(1, 3 if has_sr else 1, figsize=(11 if has_sr else 4.5, 3.4),
                             constrained_layout=True, squeeze=False)  # fmt: skip
    plot_latency_groups(groups, axes[0, 0])
    if has_sr:
        activity_path = latent_dir / "activity.parquet"
        activity = pd.read_parquet(activity_path)
        world = _world(latent_dir)
        lt = groups["latent"]
        end_explore = int(lt.loc[lt["phase"] != REWARDED, "trial"].max())
        last = int(lt["trial"].max())
        start = int(world.starts[0])
        snaps = np.sort(activity["trial"].unique())
        for ax, wanted, label in ((axes[0, 1], end_explore, "end of exploration"),
                                  (axes[0, 2], last, "end of training")):  # fmt: skip
            trial = int(snaps[snaps <= wanted].max())  # the latest snapshot up to then
            sr = start_state_sr(activity, start, trial, world.n_states)
            im = plot_sr_on_maze(sr, world.height, world.width, world.blocked, ax,
                                 f"SR of start state {start}: {label} (trial {trial})")  # fmt: skip
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle("Latent learning (Fig. 7)", fontsize=10)
    out = Path(out) if out is not None else run_dir / "plot.png"
    try:
        fig.savefig(out, dpi=150)
    except OSError as exc:
        raise CobelError(f"cannot write {out}: {exc.strerror}") from None
    finally:
        plt.close(fig)
    return out
