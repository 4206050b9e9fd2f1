"""Small tables the figures' data modules share: Fig. 8's summary and per-run trend test, and
the writer of a committed table with its provenance sidecar. Imported by
:mod:`cobelrun.figures.data` and :mod:`cobelrun.figures.run_import` (neither imports the other
for these)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd


def fig8_summary(per_run: pd.DataFrame) -> pd.DataFrame:
    """Fig. 8 per snapshot from the per-run counts: the runs measured there, the mean number
    of place cells over them (no run counted where it was not run; a run whose layer died
    counts with its zeros), its range, and the Spearman rho of that mean over the snapshots
    the surviving runs share (every snapshot with more than one run); beside it the per-run
    trend test (:func:`fig8_trend`), the same on every row. Rows of unfinished runs
    (``complete`` false, from :mod:`cobelrun.figures.run_import`) are left out."""
    from scipy import stats

    if "complete" in per_run:
        per_run = per_run[per_run["complete"].astype(bool)]
    g = per_run.groupby("trial")["place_cells"]
    out = pd.DataFrame({"runs": g.count(), "mean": g.mean(), "min": g.min(), "max": g.max()})
    out = out.reset_index()
    shared = out[out["runs"] > 1]
    rho = (stats.spearmanr(shared["trial"], shared["mean"]).statistic
           if shared["mean"].nunique() > 1 else np.nan)  # fmt: skip
    return out.assign(spearman_rho_mean_vs_trial=round(float(rho), 4), **fig8_trend(per_run))


def fig8_trend(per_run: pd.DataFrame) -> dict[str, float]:
    """Does the count rise within runs? Per run (``seed``, and ``run`` where given) with at
    least 3 snapshots, Spearman's rho of place cells against trial; a run whose count never
    changes (a dead layer: all zeros) has no rise, rho 0. Across runs: how many, how many
    rose (rho > 0), the median rho, the one-sided sign test (binomial, runs that did not rise
    count against the rise) and the one-sided Wilcoxon signed-rank test of the rhos against 0
    (zeros split between the signs)."""
    from scipy import stats

    keys = [k for k in ("seed", "run") if k in per_run]
    rhos = []
    for _, g in per_run.groupby(keys, sort=True):
        if g["trial"].nunique() < 3:
            continue
        if g["place_cells"].nunique() < 2:
            rhos.append(0.0)
        else:
            rhos.append(float(stats.spearmanr(g["trial"], g["place_cells"]).statistic))
    r = np.asarray(rhos)
    n, rising = len(r), int((r > 0).sum())
    sign_p = stats.binomtest(rising, n, 0.5, alternative="greater").pvalue if n else np.nan
    wilcoxon_p = (stats.wilcoxon(r, zero_method="zsplit", alternative="greater").pvalue
                  if n > 1 and np.any(r != 0) else np.nan)  # fmt: skip
    return {"runs_trend_test": n, "runs_rising": rising,
            "median_run_rho": round(float(np.median(r)), 4) if n else np.nan,
            "sign_test_p": round(float(sign_p), 4), "wilcoxon_p": round(float(wilcoxon_p), 4)}  # fmt: skip


def write_table(frame: pd.DataFrame, prov: Mapping[str, Any], out_dir: Path, name: str) -> Path:
    """``out_dir/name.csv`` (6 significant digits) and ``out_dir/name.provenance.json``."""
    from cobelrun.io.atomic import atomic_path

    out_dir.mkdir(parents=True, exist_ok=True)
    csv = out_dir / f"{name}.csv"
    with atomic_path(csv) as tmp:
        frame.to_csv(tmp, index=False, float_format="%.6g")
    side = out_dir / f"{name}.provenance.json"
    with atomic_path(side) as tmp:
        Path(tmp).write_text(json.dumps(dict(prov), indent=1) + "\n")
    return csv
