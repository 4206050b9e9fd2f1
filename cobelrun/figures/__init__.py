"""Paper-style plots. Functions take data frames and a matplotlib ``ax``, never live objects."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError
from cobelrun.io.atomic import atomic_path, disk_error
from cobelrun.io.run_folder import RunFolder

#: plot modules by task name (``cobel plot`` picks one from the run's manifest); each has
#: ``plot_run(run_dir, out=None) -> Path`` (``plot_run(run_dir, out=None, *others)``
#: where the figure compares several run folders, e.g. Fig. 7's latent and direct groups).
#: Tasks not listed get a figure chosen from what the run recorded (:mod:`cobelrun.figures.tasks`).
PLOTS_BY_TASK: dict[str, str] = {
    "latent_learning": "cobelrun.figures.latent",
    "two_afc": "cobelrun.figures.choice",
    "place_cells": "cobelrun.figures.place_cells",
    "place_cells_original": "cobelrun.figures.place_cells",
}
DEFAULT_PLOT = "cobelrun.figures.tasks"


def plot_run(run_dir: str | Path, out: str | Path | None = None, *others: str | Path) -> Path:
    """Draw a run folder's figure, chosen by the task named in its manifest.

    ``others`` (more run folders, e.g. Fig. 7's direct group) go to figures that compare runs;
    other figures refuse them. Returns the file written (default ``RUN_DIR/plot.png``).
    """
    from cobelrun.io.validate import read_manifest

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CobelError(f"run folder {run_dir} does not exist")
    if not RunFolder(run_dir).manifest.is_file():
        task = ""  # a run folder without manifest: draw the default plot
    else:  # a damaged manifest is one line naming it (a job's folder may have no trials table)
        task = str(read_manifest(RunFolder(run_dir).manifest).get("task") or "")
    draw = importlib.import_module(PLOTS_BY_TASK.get(task, DEFAULT_PLOT)).plot_run
    takes_more = any(
        p.kind is inspect.Parameter.VAR_POSITIONAL
        for p in inspect.signature(draw).parameters.values()
    )
    if others and not takes_more:
        raise CobelError(
            f"the {task or 'Fig. 6B'} plot takes one run folder, got {1 + len(others)}"
        )
    return draw(run_dir, out, *others)


def save_figure(fig: Any, out: Path, *, dpi: int = 150) -> Path:
    """Write ``fig`` to ``out`` (folders created) and close it; OSError -> one-line CobelError."""
    import matplotlib.pyplot as plt

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:  # readers never see half a figure
            fig.savefig(tmp, dpi=dpi)
    except OSError as exc:
        raise CobelError(disk_error(exc, out)) from None
    finally:
        plt.close(fig)
    return out
