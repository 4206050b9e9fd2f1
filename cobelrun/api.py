"""The Python API: run a task, rerun a run folder, load results, from a script or notebook.

``run`` composes configs exactly as ``cobel run`` does (``./conf`` first, then the built-in
configs; the same override syntax and one-line errors), validates everything before any file
is written, and runs one job into a run folder. ``load`` and ``load_sweep`` read folders
written by either the CLI or this API. Importing this module does not import torch.

Examples
--------
>>> import cobelrun
>>> r = cobelrun.run("tmaze_extinction", overrides=["task.runs=2"])  # doctest: +SKIP
>>> r.trials.groupby("phase")["reward"].mean()  # doctest: +SKIP
>>> r.plot()  # doctest: +SKIP
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from cobelrun.errors import CobelError, ConfigError
from cobelrun.io.run_folder import RunFolder
from cobelrun.run_summary import LAST_TRIALS, summary  # noqa: F401 (re-exported)

__all__ = [
    "Run", "compose", "default_run_dir", "load", "load_sweep", "make_env", "rerun", "resume",
    "run",
    "summary",
]  # fmt: skip


@dataclass
class Run:
    """A run folder and its results (tables are read when first asked for).

    Parameters
    ----------
    path
        The run folder (``cobel run`` or :func:`run` wrote it).
    """

    path: Path
    _cache: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.path = Path(self.path)

    @property
    def folder(self) -> RunFolder:
        """The folder's layout (:class:`cobelrun.io.run_folder.RunFolder`)."""
        return RunFolder(self.path)

    def table(self, name: str) -> pd.DataFrame:
        """Table ``name`` of the run (``trials``, ``steps``, ``activity``, ...)."""
        if name not in self._cache:
            from cobelrun.results import load_table

            self._cache[name] = load_table(self.path, name)
        return self._cache[name]

    @property
    def trials(self) -> pd.DataFrame:
        """One row per (run, trial): phase, reward, steps (latency), response, ..."""
        return self.table("trials")

    @property
    def steps(self) -> pd.DataFrame:
        """One row per recorded step: state, x, y, heading, action, reward."""
        return self.table("steps")

    @property
    def tables(self) -> list[str]:
        """Names of the tables the run wrote."""
        return self.folder.tables()

    @property
    def manifest(self) -> dict[str, Any]:
        """The run's manifest: status, seed, config hash, versions, wall time."""
        if not self.folder.manifest.is_file():
            raise CobelError(f"{self.path} has no {RunFolder.MANIFEST}")
        from cobelrun.io.validate import read_manifest  # a run folder is data: checked

        return read_manifest(self.folder.manifest)

    @property
    def config(self) -> Any:
        """The run's resolved config (an OmegaConf ``DictConfig``)."""
        from omegaconf import OmegaConf

        if not self.folder.config.is_file():
            raise CobelError(f"{self.path} has no {RunFolder.CONFIG}")
        return OmegaConf.load(self.folder.config)

    @property
    def objective(self) -> float | None:
        """The value of ``task.objective`` the run computed (``None`` when it declares none)."""
        value = self.manifest.get("objective")
        return None if value is None else float(value)

    def agent(self, run: int = 0) -> dict[str, Any]:
        """Run ``run``'s saved agent as arrays in their real shapes, read from ``agents.npz``
        with every header checked first (e.g. Dyna-Q: ``Q`` (states, actions); SR agents:
        ``M`` (states, actions, states) and ``w`` (states,); deep agents: their parameters
        by name). A run without a saved agent is a one-line CobelError naming the saved runs.

        Examples
        --------
        >>> q = cobelrun.load(RUN_DIR).agent(0)["Q"]  # doctest: +SKIP
        >>> q.max(axis=1)  # state values  # doctest: +SKIP
        """
        from cobelrun.figures.learned import load_agent

        return load_agent(self.path, run)

    def summary(self) -> pd.DataFrame:
        """Per phase: runs, trials, and the means of the phase's last trials (see :func:`summary`)."""
        return summary(self.trials)

    def plot(self, out: str | os.PathLike[str] | None = None, *, kind: str | None = None) -> Path:
        """Draw the run's figure (as ``cobel plot``) and return the PNG written.

        Parameters
        ----------
        out
            The PNG to write (default ``RUN_DIR/plot.png``).
        kind
            ``None`` for the task's own figure, or one of ``occupancy``, ``trajectories``,
            ``latency``, ``response``, ``reward``, ``value``, ``policy``, ``q``, ``sr``,
            ``rate`` (see ``cobel plot --kind``; a run offers only what it recorded).
        """
        if kind is None:
            from cobelrun.figures import plot_run

            return plot_run(self.path, out)
        from cobelrun.figures.kinds import plot_kind

        return plot_kind(self.path, kind, out)

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r})"


def default_run_dir(task: str) -> Path:
    """A new run folder as ``cobel run`` names it: ``$COBEL_RESULTS/<task>/<date>/<time>_<id>``."""
    from cobelrun.config import new_run_id

    root = Path(os.environ.get("COBEL_RESULTS") or "results")
    now = time.localtime()
    return (
        root
        / task
        / time.strftime("%Y-%m-%d", now)
        / f"{time.strftime('%H-%M-%S', now)}_{new_run_id()}"
    )


def _task_overrides(task: str | None, overrides: Sequence[str]) -> list[str]:
    if isinstance(overrides, str):
        raise ConfigError(f"overrides must be a list of strings, got the string {overrides!r}")
    out = [str(o) for o in overrides]
    if task is not None:
        if any(o.split("=", 1)[0].lstrip("+~") == "task" for o in out):
            raise ConfigError("give the task either as the first argument or as task=NAME")
        out.insert(0, f"task={task}")
    return out


def compose(task: str | None = None, overrides: Sequence[str] = ()) -> Any:
    """The composed job config of ``task`` + ``overrides``, as ``cobel run`` composes it.

    Parameters
    ----------
    task
        A task name (``cobel list task``), or ``None`` to take it from ``overrides``.
    overrides
        Hydra overrides (``["seed=3", "agent.epsilon=0.2"]``).

    Returns
    -------
    omegaconf.DictConfig
        The config without the ``hydra`` node (what a run's ``config.yaml`` holds).
    """
    from cobelrun.compose import composer
    from cobelrun.config import register_resolvers

    register_resolvers()
    with composer() as compose_:
        return compose_(_task_overrides(task, overrides))


def make_env(task: str | None = None, overrides: Sequence[str] = (), *, time_limit: bool = True):
    """The gymnasium env of a task, composed as ``cobel run`` composes it.

    With ``time_limit`` the env is wrapped in ``gymnasium.wrappers.TimeLimit`` with
    ``max_episode_steps`` = the protocol's ``max_steps`` (the trial length the task's agents
    get), so a plain gymnasium loop or another library's agent sees the same episodes.

    Parameters
    ----------
    task
        A task name (``cobel list task``), or ``None`` to take it from ``overrides``.
    overrides
        Hydra overrides (``["env=blodgett"]``, ``["task.protocol.max_steps=50"]``).
    time_limit
        Wrap the env in a ``TimeLimit`` from the config.
    """
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    cfg = compose(task, overrides)
    env = instantiate("env", cfg.env)
    steps = OmegaConf.select(cfg, "task.protocol.max_steps")
    if time_limit and steps is not None:
        from gymnasium.wrappers import TimeLimit

        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ConfigError(f"task.protocol.max_steps must be an integer >= 1, got {steps!r}")
        env = TimeLimit(env, max_episode_steps=steps)
    return env


def _execute(cfg: Any, out: str | os.PathLike[str] | None, progress: bool) -> Run:
    """Validate ``cfg`` (build every part once), then run it into ``out``."""
    from cobelrun.io.lock import refuse_existing
    from cobelrun.runner import build_task
    from cobelrun.runner import run as run_task

    task = build_task(cfg, probe_agent=True)  # bad input fails here, before any folder exists
    run_dir = Path(out) if out is not None else default_run_dir(str(cfg.task.name))
    refuse_existing(run_dir, "the out folder")
    if progress:
        from cobelrun.progress import run_progress

        with run_progress(str(cfg.task.name)) as bar:
            run_task(cfg, run_dir, progress=bar, task=task)
    else:
        run_task(cfg, run_dir, task=task)  # the task built once (locks the folder, checks again)
    return Run(run_dir)


def run(
    task: str | None = None,
    overrides: Sequence[str] = (),
    out: str | os.PathLike[str] | None = None,
    *,
    progress: bool = False,
) -> Run:
    """Run a task (as ``cobel run task=TASK OVERRIDES``) and return its results.

    Parameters
    ----------
    task
        A task name (``cobel list task``); ``None`` takes it from ``overrides`` (or the
        default task).
    overrides
        Hydra overrides, e.g. ``["seed=3", "task.runs=5", "agent=mfec"]``.
    out
        The run folder to write (default: a new ``$COBEL_RESULTS/<task>/<date>/<time>_<id>``);
        it must not hold a run already.
    progress
        Show a progress bar.

    Returns
    -------
    Run
        The finished run.

    Raises
    ------
    cobelrun.errors.ConfigError
        The config is invalid (nothing is written).
    """
    cfg = compose(task, overrides)
    return _execute(cfg, out, progress)


def rerun_config(run_dir: str | os.PathLike[str], overrides: Sequence[str] = ()) -> Any:
    """A run folder's saved ``config.yaml`` with ``key=value`` overrides applied.

    Overrides use Hydra's syntax (``key=value``, ``+key=value``, ``~key``); config groups
    (``agent=NAME``) cannot be changed, since the saved config is fully composed.
    """
    from omegaconf import OmegaConf

    from cobelrun.compose import _parse, load_config
    from cobelrun.config import GROUPS, apply_overrides
    from cobelrun.targets import check_config

    folder = RunFolder(run_dir)
    if not folder.config.is_file():
        from cobelrun.io.sweep_folder import SWEEP_FILE

        hint = ""
        if (folder.path / SWEEP_FILE).is_file():
            hint = (f"; it is a sweep folder ({SWEEP_FILE}): give one of its job folders (e.g. "
                    f"{folder.path / '0'}); the sweep's own `cobel run -m ...` command again "
                    "resumes its stopped jobs")  # fmt: skip
        raise CobelError(f"{folder.path} is not a run folder (no {RunFolder.CONFIG}){hint}")
    cfg = load_config(folder.config)
    parsed = _parse(_task_overrides(None, overrides))
    for o in parsed:
        if o.key_or_group in GROUPS or o.key_or_group.startswith("hydra"):
            raise ConfigError(
                f"cobel rerun takes key=value overrides, not {o.input_line!r}: the saved config "
                f"is already composed; use `cobel run` to choose another {o.key_or_group}"
            )
        if o.is_sweep_override():
            raise ConfigError(f"cobel rerun runs one job; {o.input_line!r} is a sweep")
    OmegaConf.set_struct(cfg, True)
    try:
        apply_overrides(cfg, parsed)
    except ConfigError as exc:
        raise ConfigError(f"{exc} (use +key=value to add a key)") from None
    OmegaConf.set_struct(cfg, False)
    try:  # a run folder is data: its targets pass the same gate as any config
        check_config(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{folder.config}: {exc}") from None
    return cfg


def resume(run_dir: str | os.PathLike[str], *, progress: bool = False) -> Run:
    """Continue a stopped run from its checkpoint (:mod:`cobelrun.checkpoint`) in its own
    folder, with its saved config: the finished tables equal those of the run without the stop.

    Raises a one-line :class:`~cobelrun.checkpoint.CheckpointError` when the folder has no
    checkpoint, completed already, or its checkpoint was written by another cobel version or
    for another config.
    """
    from cobelrun.runner import build_task
    from cobelrun.runner import run as run_task

    cfg = rerun_config(run_dir)  # the saved config through the target gate
    task = build_task(cfg)
    if progress:
        from cobelrun.progress import run_progress

        with run_progress(str(cfg.task.name)) as bar:
            run_task(cfg, Path(run_dir), progress=bar, task=task, resume=True)
    else:
        run_task(cfg, Path(run_dir), task=task, resume=True)
    return Run(Path(run_dir))


def rerun(
    run_dir: str | os.PathLike[str],
    overrides: Sequence[str] = (),
    out: str | os.PathLike[str] | None = None,
    *,
    progress: bool = False,
) -> Run:
    """Run a run folder's saved config again (with ``key=value`` overrides) into a new folder.

    The same config and seed give identical tables.

    Parameters
    ----------
    run_dir
        A run folder (its ``config.yaml`` is read).
    overrides
        ``key=value`` overrides, e.g. ``["seed=4"]``.
    out
        The new run folder (default: a new folder named as ``cobel run`` names it).
    progress
        Show a progress bar.
    """
    cfg = rerun_config(run_dir, overrides)
    return _execute(cfg, out, progress)


def load(run_dir: str | os.PathLike[str]) -> Run:
    """Open a run folder written by ``cobel run`` or :func:`run`.

    Raises
    ------
    cobelrun.errors.CobelError
        ``run_dir`` is not a run folder.
    """
    folder = RunFolder(run_dir)
    if not folder.path.is_dir():
        raise CobelError(f"run folder {folder.path} does not exist")
    if not folder.manifest.is_file() and not folder.table("trials").is_file():
        raise CobelError(f"{folder.path} is not a cobel run folder (no manifest, no trials table)")
    return Run(folder.path)


def load_sweep(sweep_dir: str | os.PathLike[str], table: str = "trials") -> pd.DataFrame:
    """One table of every done job of a sweep (``cobel run -m``), tidy: ``job`` and one column
    per swept parameter (``agent.epsilon``, ``seed``, ...) beside the table's own columns.

    Parameters
    ----------
    sweep_dir
        The sweep folder.
    table
        Which table (``trials``, ``steps``, ...).
    """
    from cobelrun.results import load_sweep as _load_sweep

    return _load_sweep(sweep_dir, table)
