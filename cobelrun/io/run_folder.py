"""The run folder's layout: every file name a run writes, in one place.

::

    <run>/
      config.yaml          resolved config
      manifest.json        seed, config hash, versions, status (written atomically)
      world.json           the environment's geometry (plots, viewers, exports read it)
      <table>.parquet      one file per table a monitor declares (trials, steps, activity, ...)
      run.mcap             pose stream, trial events and maze scene (Foxglove)
      agents.npz           every saved run's trained agent, with a run axis
                           (:mod:`cobelrun.io.agents_archive`)
      job.json             sweep bookkeeping (sweeps only)
      .parts/<table>/      table parts while a run is going (merged into <table>.parquet at
                           the end; left behind only by a killed run, see :mod:`cobelrun.io.repair`)
      training/run_0007/   deep agents' training curves (record.training_log: SB3 CSV/TensorBoard)
      .parts-agents/       batches of agents while a run is going (merged into agents.npz)
      checkpoint.npz       the last checkpoint of a run that is going or stopped (removed when it
                           completes unless task.checkpoint.keep; cobelrun.checkpoint)
      .done                written last, only when the run completed

Readers and writers ask :class:`RunFolder` for paths; no other module spells a file name.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

__all__ = ["DONE_MARKER", "RunFolder"]

#: written last into a run folder, only when the run completed
DONE_MARKER = ".done"


class RunFolder:
    """Paths of one run folder (nothing is created until a writer asks for its parent).

    Parameters
    ----------
    path
        The run folder.
    """

    CONFIG = "config.yaml"
    MANIFEST = "manifest.json"
    WORLD = "world.json"
    MCAP = "run.mcap"
    AGENTS = "agents"
    TRAINING = "training"
    AGENTS_ARCHIVE = "agents.npz"
    PARTS = ".parts"
    AGENT_PARTS = ".parts-agents"
    JOB = "job.json"
    DONE = DONE_MARKER
    TABLE_SUFFIX = ".parquet"
    #: figures a run's plot command writes next to the tables
    PLOTS = ("plot.png", "plot.pdf")

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __fspath__(self) -> str:
        return os.fspath(self.path)

    # -- files -------------------------------------------------------------------------------
    @property
    def config(self) -> Path:
        return self.path / self.CONFIG

    @property
    def manifest(self) -> Path:
        return self.path / self.MANIFEST

    @property
    def world(self) -> Path:
        return self.path / self.WORLD

    @property
    def mcap(self) -> Path:
        return self.path / self.MCAP

    @property
    def checkpoint(self) -> Path:
        """The run's last checkpoint (:mod:`cobelrun.checkpoint`), while it runs or stopped."""
        return self.path / "checkpoint.npz"

    @property
    def mcap_before_resume(self) -> Path:
        """A resumed run's MCAP from before the resume, until it is joined with the new one."""
        return self.path / ".run-before-resume.mcap"

    @property
    def done(self) -> Path:
        return self.path / self.DONE

    @property
    def job(self) -> Path:
        return self.path / self.JOB

    @property
    def agents(self) -> Path:
        return self.path / self.AGENTS

    @property
    def agents_archive(self) -> Path:
        """All saved agents of the job in one file, with a run axis."""
        return self.path / self.AGENTS_ARCHIVE

    @property
    def agent_parts(self) -> Path:
        return self.path / self.AGENT_PARTS

    def table(self, name: str) -> Path:
        """The Parquet file of table ``name`` (``trials``, ``steps``, ``activity``, ...)."""
        return self.path / f"{name}{self.TABLE_SUFFIX}"

    def parts(self, name: str) -> Path:
        """Folder of table ``name``'s parts while the run is going."""
        return self.path / self.PARTS / name

    @property
    def training(self) -> Path:
        return self.path / self.TRAINING

    def training_log(self, run: int) -> Path:
        """Run ``run``'s training-curve folder: ``training/run_0007/`` (``progress.csv``)."""
        return self.training / f"run_{int(run):04d}"

    def agent(self, run: int) -> Path:
        """A single saved agent file of run ``run`` (``agents/run_0007.npz``; older layout)."""
        return self.agents / f"run_{int(run):04d}.npz"

    def legacy_agent(self, run: int) -> Path | None:
        """Run ``run``'s agent file in an older layout (``agents/run_0007.npz``,
        ``agent_run7.npz``), if there is one."""
        found = [self.agent(run)] if self.agent(run).is_file() else []
        found += sorted(self.path.glob(f"agent_run{int(run)}.*"))
        return found[0] if found else None

    # -- what is there -----------------------------------------------------------------------
    def tables(self) -> list[str]:
        """Names of the tables written (complete ``<name>.parquet`` files)."""
        return sorted(
            p.name[: -len(self.TABLE_SUFFIX)] for p in self.path.glob(f"*{self.TABLE_SUFFIX}")
        )

    def unfinished_tables(self) -> list[str]:
        """Tables whose parts were never merged (the run was killed)."""
        root = self.path / self.PARTS
        return sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []

    def outputs(self) -> Iterator[Path]:
        """Every file or folder a run writes that exists now (``job.json`` excluded: it belongs
        to the sweep). A rerun removes exactly these."""
        fixed = [self.config, self.manifest, self.world, self.mcap, self.agents, self.training, self.done,
                 self.agents_archive, self.agent_parts, self.path / self.PARTS,
                 self.checkpoint, self.mcap_before_resume,
                 *(self.path / p for p in self.PLOTS)]  # fmt: skip
        seen = set()
        for p in [*fixed, *(self.table(t) for t in self.tables()),
                  *self.path.glob("agent_run*.*"), *self.path.glob(f".{self.MCAP}.*"),
                  *self.path.glob(f".*{self.TABLE_SUFFIX}.tmp")]:  # fmt: skip
            if p not in seen and (p.exists() or p.is_symlink()):
                seen.add(p)
                yield p

    def clear(self) -> None:
        """Remove every output of a previous run (the done marker first, so that a reader
        never sees a completed run with missing files)."""
        if self.done.exists():
            self.done.unlink()
        for p in list(self.outputs()):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
