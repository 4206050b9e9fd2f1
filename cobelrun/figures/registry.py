"""Paper figures as specs: which runs a figure needs (cobel overrides) and how it is drawn.

A figure is one Python file in ``experiments/`` (shipped in the wheel as
``cobelrun/experiments``; an ``experiments/`` folder in the working directory is searched first)
that defines ``FIGURE = Figure(...)``::

    FIGURE = Figure(
        name="fig6b",
        title="Extinction learning with tabular Dyna-Q",
        runs={"dyna_q": ["task=tmaze_extinction"]},          # label -> overrides (sweeps ok)
        quick={"*": ["task.runs=5"]},                        # extra overrides for --quick
        draw=draw,                                           # FigureData -> (fig, table)
    )

``cobel figure NAME`` composes every run's config, finds finished runs again by config hash,
runs what is missing as ``cobel run -m`` does (one sweep per label, through Hydra's launcher:
``$COBEL_RESULTS/figures/sweeps/NAME/<label>/<job>``, resumed like any sweep), then calls ``draw``
and writes ``$COBEL_RESULTS/figures/NAME.png``, ``.pdf`` and ``.csv`` (the plotted numbers). ``--quick`` adds the spec's ``quick`` overrides (a small budget, for CI)
and writes ``NAME_quick.*``; quick runs have their own hashes, so they never mix with full ones.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest
from cobelrun.io.atomic import atomic_path, disk_error

FIGURE_DIR = "figures"
#: the run store of figures before their runs became sweeps: searched for finished runs
RUN_STORE = "runs"
#: where a figure's runs are: ``sweeps/<figure>[_quick]/<label>`` (one sweep per label)
SWEEPS = "sweeps"


@dataclass(frozen=True)
class RunRef:
    """One finished run a figure uses."""

    label: str
    job: int
    overrides: tuple[str, ...]
    params: Mapping[str, Any]
    run_dir: Path
    config_hash: str
    reused: bool = False


@dataclass
class FigureData:
    """What ``draw`` gets: the figure's runs by label, loaders for their tables."""

    runs: dict[str, list[RunRef]]
    quick: bool = False

    def trials(self, label: str) -> pd.DataFrame:
        """Trials of every run of ``label``, with ``job`` and the swept params as columns."""
        return self._table(label, "trials")

    def steps(self, label: str) -> pd.DataFrame:
        """Steps of every run of ``label``, with ``job`` and the swept params as columns."""
        return self._table(label, "steps")

    def activity(self, label: str) -> pd.DataFrame:
        """Activity snapshots (``activity.parquet``) of every run of ``label``, with ``job``."""
        return self._table(label, "activity")

    def run_dirs(self, label: str) -> list[Path]:
        """The run folders of ``label`` (e.g. to load saved agents or the config)."""
        if label not in self.runs:
            raise CobelError(f"figure has no runs labelled {label!r}; has {sorted(self.runs)}")
        return [ref.run_dir for ref in self.runs[label]]

    def _table(self, label: str, table: str) -> pd.DataFrame:
        from cobelrun.results import load_run

        if label not in self.runs:
            raise CobelError(f"figure has no runs labelled {label!r}; has {sorted(self.runs)}")
        frames = []
        for ref in self.runs[label]:
            df = load_run(ref.run_dir, table)
            front = {"job": ref.job, **ref.params}
            for i, (k, v) in enumerate(front.items()):
                df.insert(i, k if k not in df else f"param:{k}", v)
            frames.append(df)
        return pd.concat(frames, ignore_index=True)


@dataclass(frozen=True)
class Figure:
    """A paper figure: the runs it needs and how it is drawn.

    Attributes
    ----------
    name
        Command-line name (``cobel figure NAME``), e.g. ``fig6b``.
    title
        One line shown by ``cobel figure --list``.
    runs
        Label -> cobel overrides (as for ``cobel run``; ``a=1,2`` sweeps give one run per value).
    draw
        ``draw(data: FigureData) -> (matplotlib Figure, DataFrame of the plotted numbers)``.
    quick
        Label (or ``"*"`` for all) -> extra overrides for ``--quick`` (a small budget).
    jobs
        Runs at once when ``cobel figure`` is not given ``--jobs``: 1 (one after another, in
        the ``cobel`` process), or 0 for one worker process per core (figures of long runs of
        deep agents, each using one core).
    """

    name: str
    title: str
    runs: Mapping[str, Sequence[str]]
    draw: Callable[[FigureData], tuple[Any, pd.DataFrame]]
    quick: Mapping[str, Sequence[str]] = field(default_factory=dict)
    source: Path | None = None
    jobs: int = 1

    def overrides(self, label: str, quick: bool) -> list[str]:
        extra = [*self.quick.get("*", ()), *self.quick.get(label, ())] if quick else []
        return [*self.runs[label], *extra]


# -- discovery --------------------------------------------------------------------------------


def builtin_experiments_dir() -> Path | None:
    """``experiments/`` inside the installed wheel, or at the source checkout's root."""
    pkg = Path(__file__).resolve().parents[1]
    for candidate in (pkg / "experiments", pkg.parent / "experiments"):
        if candidate.is_dir():
            return candidate
    return None


def experiments_dirs() -> list[Path]:
    """Figure spec folders in search order: ``./experiments`` first, then the built-in one."""
    dirs = []
    user = Path.cwd() / "experiments"
    builtin = builtin_experiments_dir()
    if user.is_dir():
        dirs.append(user)
    if builtin is not None and (not dirs or builtin.resolve() != dirs[0].resolve()):
        dirs.append(builtin)
    return dirs


def _load(path: Path) -> list[Figure]:
    name = f"cobel_experiments.{path.parent.name}.{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise CobelError(f"cannot load figure spec {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except CobelError:
        raise
    except Exception as exc:
        raise CobelError(f"figure spec {path} failed to load: {type(exc).__name__}: {exc}") from exc
    found = list(getattr(module, "FIGURES", [])) + (
        [module.FIGURE] if hasattr(module, "FIGURE") else []
    )
    if not found or not all(isinstance(f, Figure) for f in found):
        raise CobelError(f"figure spec {path} must define FIGURE = Figure(...)")
    return [Figure(**{**f.__dict__, "source": path}) if f.source is None else f for f in found]


def figures() -> dict[str, Figure]:
    """Every figure spec, by name (``./experiments`` shadows built-in names)."""
    found: dict[str, Figure] = {}
    for folder in experiments_dirs():
        for path in sorted(folder.glob("*.py")):
            if path.name.startswith("_"):
                continue
            for fig in _load(path):
                found.setdefault(fig.name, fig)
    return dict(sorted(found.items()))


def get(name: str) -> Figure:
    """The figure called ``name``, or a one-line error listing the known ones."""
    known = figures()
    if name not in known:
        raise CobelError(
            f"unknown figure {name!r}{suggest(name, known)}; allowed: {allowed_list(known)} "
            "(see `cobel figure --list`)"
        )
    return known[name]


# -- building ---------------------------------------------------------------------------------


def results_root() -> Path:
    from cobelrun.safety import results_root as root

    return root()  # COBEL_RESULTS="" is refused (it used to mean /)


@contextlib.contextmanager
def _composer() -> Iterator[Callable[[list[str]], Any]]:
    """Compose (and resolve) run configs as ``cobel run`` does; errors name the run's overrides."""
    from omegaconf import OmegaConf

    from cobelrun.hydra_app import composer

    with composer() as compose:

        def _compose(overrides: list[str]) -> Any:
            try:
                cfg = compose(overrides)
            except ConfigError as exc:
                raise ConfigError(f"{' '.join(overrides)}: {exc}") from None
            OmegaConf.resolve(cfg)
            return cfg

        yield _compose


@dataclass
class _Planned:
    label: str
    job: int
    overrides: list[str]
    params: dict[str, Any]
    cfg: Any
    config_hash: str
    run_dir: Path


def sweep_dir(figure: Figure, label: str, *, quick: bool = False, root: Path | None = None) -> Path:
    """The sweep folder that runs ``label``'s jobs of ``figure``."""
    stem = f"{figure.name}_quick" if quick else figure.name
    return (root or results_root()) / FIGURE_DIR / SWEEPS / stem / label


def plan_runs(figure: Figure, *, quick: bool = False, root: Path | None = None) -> list[_Planned]:
    """Compose every run of ``figure``; each is a job of its label's sweep folder
    (:func:`sweep_dir`), numbered as ``cobel run -m`` numbers the label's overrides."""
    from cobelrun.io.sweep_folder import job_config_hash, job_dir
    from cobelrun.sweep_plan import plan

    root = root or results_root()
    planned = []
    with _composer() as compose:
        for label in figure.runs:
            _, jobs = plan(figure.overrides(label, quick))
            where = sweep_dir(figure, label, quick=quick, root=root)
            for j in jobs:
                cfg = compose(j["overrides"])
                chash = job_config_hash(cfg)
                run_dir = job_dir(where, j["job"])
                planned.append(
                    _Planned(label, j["job"], j["overrides"], j["params"], cfg, chash, run_dir)
                )
    return planned


def finished_runs(folders: Sequence[Path]) -> dict[str, Path]:
    """Completed run folders under ``folders`` (each a run folder or holding run folders, two
    levels deep at most), by config hash; a one-line CobelError for a folder that is missing."""
    from cobelrun.io.sweep_folder import is_complete
    from cobelrun.io.validate import read_json_or_none as read_json

    found: dict[str, Path] = {}
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            raise CobelError(f"--from {folder}: no such folder (give a sweep or run folder)")
        for manifest in sorted({*folder.glob("manifest.json"), *folder.glob("*/manifest.json"),
                                *folder.glob("*/*/manifest.json")}):  # fmt: skip
            data = read_json(manifest)
            chash = data.get("config_hash") if data else None
            if chash and chash not in found and is_complete(manifest.parent, chash, data):
                found[chash] = manifest.parent
    return found


def import_runs(planned: Sequence[_Planned], folders: Sequence[Path]) -> int:
    """Copy the finished runs under ``folders`` that ``planned`` needs (same config hash) into
    their job folders of the figure's sweeps; returns how many were copied. A folder that holds
    a symbolic link (or anything but folders and regular files) is not copied: its link could
    bring in any file of this machine (the run is made again instead)."""
    import shutil

    found = finished_runs(folders)
    taken = 0
    for p in planned:
        src = found.get(p.config_hash)
        if src is None or src.resolve() == p.run_dir.resolve() or not _plain_tree(src):
            continue
        tmp = p.run_dir.with_name(p.run_dir.name + ".importing")
        tmp.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(src, tmp)
        shutil.rmtree(p.run_dir, ignore_errors=True)
        tmp.rename(p.run_dir)  # the run folder appears whole or not at all
        taken += 1
    return taken


def _plain_tree(folder: Path) -> bool:
    """Whether ``folder`` holds only folders and regular files (no link, fifo, device)."""
    import os
    import stat

    if folder.is_symlink():
        return False
    for top, dirs, files in os.walk(folder):
        for name in (*dirs, *files):
            mode = os.lstat(os.path.join(top, name)).st_mode
            if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                return False
    return True


def launcher_overrides(jobs: int) -> list[str]:
    """Hydra's launcher for ``jobs`` runs at once: the basic launcher (one after another, in
    this process) for 1, else joblib with ``jobs`` workers (the basic one without joblib)."""
    from cobelrun.hydra_app import default_launcher

    if jobs <= 1 or not default_launcher([]):
        return ["hydra/launcher=basic"]
    return ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"]


def run_label(
    figure: Figure,
    label: str,
    todo: Sequence[_Planned],
    *,
    quick: bool,
    root: Path,
    launcher: Sequence[str],
    log: Callable[[str], None] | None = None,
) -> None:
    """Run ``label``'s missing jobs as ``cobel run -m`` does: a sweep of the label's overrides
    into its sweep folder (:func:`sweep_dir`), through Hydra's launcher (``launcher``:
    ``hydra/launcher=...`` overrides; joblib, basic, submitit), with cobel's sweeper, which
    skips the jobs already done there. A job that fails is a one-line CobelError naming it;
    Ctrl-C or SIGTERM stops the sweep cleanly (its running jobs close their files) and raises
    KeyboardInterrupt."""
    import contextlib as _contextlib

    from cobelrun.hydra_app import launch
    from cobelrun.io.sweep_folder import job_rows

    where = sweep_dir(figure, label, quick=quick, root=root)
    if log:
        log(f"{figure.name}: {label}: {len(todo)} runs to run, as the sweep {where} "
            f"({' '.join(launcher)})")  # fmt: skip
    args = ["-m", *figure.overrides(label, quick), *launcher, f"hydra.sweep.dir={where}"]
    root_log = logging.getLogger()
    level, handlers = root_log.level, list(root_log.handlers)
    try:
        with _contextlib.redirect_stdout(sys.stderr):  # stdout: the figure's files only
            code = launch(args, quiet=True)
    finally:  # Hydra configured logging for the sweep; drawing logs as before it
        root_log.handlers[:] = handlers
        root_log.setLevel(level)
    if code == 130:
        raise KeyboardInterrupt
    wanted = {p.job for p in todo}
    failed = [r for r in job_rows(where, write=False)
              if r["job"] in wanted and r["status"] != "done"]  # fmt: skip
    if code != 0 or failed:
        first = failed[0] if failed else {"job": "?", "status": "failed", "error": ""}
        raise CobelError(
            f"{figure.name}: {label} job {first['job']} {first['status']}"
            + (f": {first['error']}" if first.get("error") else "")
            + f" (see cobel status {where}; finished runs are kept and reused next time)"
        )


def _finished_part(
    figure: Figure,
    planned: list[_Planned],
    todo: list[_Planned],
    log: Callable[[str], None] | None,
) -> list[_Planned]:
    """``cobel figure --finished-only``: the planned runs that are finished; a one-line
    CobelError when a label of the figure has none."""
    missing = {p.run_dir for p in todo}
    done = [p for p in planned if p.run_dir not in missing]
    empty = [label for label in figure.runs if not any(p.label == label for p in done)]
    if empty:
        raise CobelError(
            f"{figure.name}: no finished run for {', '.join(map(repr, empty))} to draw; run "
            f"`cobel figure {figure.name}` (or take a sweep's runs with --from) first"
        )
    if log:
        params = [", ".join(f"{k}={v}" for k, v in p.params.items()) for p in todo]
        left = "; ".join(f"{p.label} job {p.job}" + (f" ({text})" if text else "")
                         for p, text in zip(todo, params, strict=True))  # fmt: skip
        log(f"{figure.name}: drawing the {len(done)} finished of {len(planned)} runs, running "
            f"nothing" + (f"; not finished: {left}" if left else ""))  # fmt: skip
    return done


def build(
    figure: Figure,
    *,
    quick: bool = False,
    out_dir: Path | None = None,
    root: Path | None = None,
    log: Callable[[str], None] | None = None,
    reuse_from: Sequence[Path] = (),
    jobs: int | None = None,
    finished_only: bool = False,
    launcher: Sequence[str] = (),
) -> dict[str, Path]:
    """Run what ``figure`` still needs, draw it, and write PNG, PDF and CSV.

    ``reuse_from``: folders (a sweep folder, a run folder, or folders of either) whose finished
    runs are copied into the figure's run store when their config hash is one the figure needs,
    e.g. a ``cobel run -m`` sweep of the figure's jobs run in parallel or on a cluster.
    ``jobs``: run up to this many of the missing runs at once, each in a process of its own
    (Hydra's joblib launcher); 1 runs them one after another in this process (the basic
    launcher); None takes the figure's own default (:attr:`Figure.jobs`). Either way the runs
    go through :func:`run_label`, the path of ``cobel run -m``.
    ``launcher``: Hydra overrides choosing another launcher for the runs
    (``["hydra/launcher=slurm", "hydra.launcher.partition=gpu"]``); ``jobs`` is then ignored.
    ``finished_only``: run nothing and draw from the runs already finished (each of the
    figure's labels needs one at least), to ``NAME_partial.*``; the runs left out are logged.

    Returns the written files by suffix (``png``, ``pdf``, ``csv``).
    """
    from cobelrun.figures.style import paper_style
    from cobelrun.io.sweep_folder import is_complete

    if jobs is not None and jobs < 1:
        raise CobelError(f"--jobs {jobs}: give 1 or more (runs at once, one process each)")
    if jobs is None:
        import os

        jobs = figure.jobs if figure.jobs >= 1 else os.cpu_count() or 1
    root = root or results_root()
    out_dir = out_dir or root / FIGURE_DIR
    planned = plan_runs(figure, quick=quick, root=root)
    todo = [p for p in planned if not is_complete(p.run_dir, p.config_hash)]
    if reuse_from:  # the folders are checked even when no run is missing
        taken = import_runs(todo, reuse_from)
        if log:
            log(f"{figure.name}: {taken} runs taken from {', '.join(map(str, reuse_from))}")
        todo = [p for p in todo if not is_complete(p.run_dir, p.config_hash)]
    if todo:  # the same runs finished for another figure, or in the store of older versions
        figures_dir = root / FIGURE_DIR
        stores = [d for d in (figures_dir / RUN_STORE, *figures_dir.glob(f"{SWEEPS}/*/*"))
                  if d.is_dir() and d not in {p.run_dir.parent for p in todo}]  # fmt: skip
        if stores:
            import_runs(todo, stores)
            todo = [p for p in todo if not is_complete(p.run_dir, p.config_hash)]
    if finished_only:
        planned, todo = _finished_part(figure, planned, todo, log), []
    elif log:
        log(f"{figure.name}: {len(planned)} runs, {len(planned) - len(todo)} reused, "
            f"{len(todo)} to run")  # fmt: skip
    launcher = list(launcher) or launcher_overrides(min(jobs, len(todo)))
    for label in figure.runs:
        missing = [p for p in todo if p.label == label]
        if missing:
            run_label(figure, label, missing, quick=quick, root=root, launcher=launcher, log=log)
    todo_dirs = {p.run_dir for p in todo}
    data = FigureData(quick=quick, runs={})
    for p in planned:
        ref = RunRef(p.label, p.job, tuple(p.overrides), p.params, p.run_dir, p.config_hash,
                     reused=p.run_dir not in todo_dirs)  # fmt: skip
        data.runs.setdefault(p.label, []).append(ref)
    stem = f"{figure.name}_quick" if quick else figure.name
    stem += "_partial" if finished_only else ""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with paper_style():
        fig, table = figure.draw(data)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            files = {"png": out_dir / f"{stem}.png", "pdf": out_dir / f"{stem}.pdf"}
            files["csv"] = out_dir / f"{stem}.csv"
            with atomic_path(files["png"]) as tmp:  # readers never see half a file
                fig.savefig(tmp, dpi=300)
            with atomic_path(files["pdf"]) as tmp:
                fig.savefig(tmp)
            with atomic_path(files["csv"]) as tmp:
                table.to_csv(tmp, index=False)
        except OSError as exc:
            raise CobelError(disk_error(exc, out_dir)) from None
        finally:
            plt.close(fig)
    return files
