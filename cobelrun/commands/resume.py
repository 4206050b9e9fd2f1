"""``cobel resume RUN_DIR``: continue a stopped run from its checkpoint."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from cobelrun.commands.common import AllowTarget, allow_targets

HELP = """Continue a stopped run from its checkpoint, in its own folder (docs/clusters.md).

\b
Examples:
  cobel resume results/place_cells/2026-01-01/12-00-00_ab12cd34
\b
A run writes checkpoints as task.checkpoint says (deep agents: every 10 minutes by default)
and when it is stopped by SIGTERM, SIGUSR1 or Ctrl-C (it then exits 75). The resumed run's
tables equal those of the same run without the stop. A checkpoint written by another cobel
version or for another config is refused. Exit codes: 0 completed, 75 stopped again with a
new checkpoint (resume again), 2 refused, 130 interrupted.
"""


def log_launch(run_dir: Path, started: float) -> None:
    """Append this resumed launch to ``RUN_DIR/cobel.log`` as a ``cobel run`` job logs its own:
    the start line at the launch's time (so a run's launches can be counted from its log, as
    :func:`cobelrun.figures.run_import.launches` does), then how it ended. Called once the
    resume ran (a refused resume writes nothing)."""
    import logging

    from omegaconf import OmegaConf

    from cobelrun.hydra_app import LOG, log_end

    cfg = OmegaConf.load(run_dir / "config.yaml")
    handler = logging.FileHandler(run_dir / "cobel.log", encoding="utf-8")
    handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
    for msg, args in (("task %s, seed %s, folder %s", (cfg.task.name, cfg.seed, run_dir)),
                      ("resumed from its checkpoint (cobel resume)", ())):  # fmt: skip
        record = LOG.makeRecord(LOG.name, logging.INFO, __file__, 0, msg, args, None)
        record.created, record.msecs = started, (started % 1) * 1000
        handler.handle(record)
    level, propagate = LOG.level, LOG.propagate
    LOG.addHandler(handler)
    LOG.setLevel(logging.INFO)
    LOG.propagate = False  # the end lines go to the file only, as in a cobel run job
    try:
        log_end(run_dir)
    finally:
        LOG.removeHandler(handler)
        LOG.setLevel(level)
        LOG.propagate = propagate
        handler.close()


def register(app: typer.Typer) -> None:
    """Add ``cobel resume`` to ``app``."""

    @app.command("resume", help=HELP)
    def resume_cmd(
        run_dir: Annotated[Path, typer.Argument(help="A stopped run folder.", show_default=False)],
        quiet: Annotated[bool, typer.Option("--quiet", help="No end-of-run summary.")] = False,
        allow_target: AllowTarget = None,
    ) -> None:
        allow_targets(allow_target)
        from cobelrun.api import resume
        from cobelrun.checkpoint import REQUEUE_EXIT
        from cobelrun.commands.common import EXIT_INTERRUPTED, fail
        from cobelrun.errors import CobelError
        from cobelrun.progress import progress_enabled
        from cobelrun.signals import Stopped

        started = time.time()
        try:
            result = resume(run_dir, progress=progress_enabled())
        except CobelError as exc:
            fail(str(exc))
        except Stopped as exc:
            log_launch(run_dir, started)
            typer.echo(f"cobel: stopped by {exc.signame}; checkpoint written; continue "
                       f"with `cobel resume {run_dir}`", err=True)  # fmt: skip
            raise typer.Exit(REQUEUE_EXIT) from None
        except KeyboardInterrupt:
            fail("interrupted", EXIT_INTERRUPTED)
        log_launch(run_dir, started)
        if not quiet:
            from cobelrun.commands.summary import print_run_summary

            print_run_summary(result.path)
        typer.echo(str(result.path))
