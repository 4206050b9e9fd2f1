"""The ``cobel`` command line: the typer app and its commands.

``cobel run`` hands its arguments to Hydra unchanged (single runs and ``-m`` multiruns); the
other commands read configs or run folders. User errors print one line and exit 2; add
``--debug`` (or set HYDRA_FULL_ERROR=1) for the traceback. The console script's entry point is
:func:`cobelrun.cli.main`, which runs a plain ``cobel run`` without this app
(:mod:`cobelrun.commands.run`); ``from cobelrun.cli import app`` still gives this app.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from cobelrun.commands.common import (
    EXIT_INTERRUPTED,
    STATUS_STYLE,
    AllowTarget,
    allow_targets,
    fail,
    launcher_choice,
)
from cobelrun.errors import CobelError

app = typer.Typer(
    name="cobel",
    help=(
        "Config-driven experiments for neuroscience-oriented reinforcement learning "
        "(CoBeL-RL rebuilt). Start with `cobel list` and `cobel run task=tmaze_extinction`."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        from cobelrun import __version__

        typer.echo(f"cobel {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version."),
    ] = False,
    allow_target: AllowTarget = None,
) -> None:
    """Config-driven experiments for neuroscience-oriented reinforcement learning."""
    allow_targets(allow_target)


RUN_HELP = """Run a task: `cobel run task=NAME [KEY=VALUE ...]` (Hydra overrides, passed unchanged).

\b
Examples:
  cobel run task=tmaze_extinction
  cobel run task=tmaze_extinction seed=3 task.runs=20 agent.epsilon=0.2
  cobel run -m task=tmaze_extinction seed=1,2,3          # a sweep (multirun)
  cobel run task=tmaze_extinction hydra.run.dir=out/x    # choose the output folder
  cobel run task=gridworld --live                        # watch it (docs/seeing.md)
\b
Hydra flags work as usual: -m/--multirun, --cfg job (print the config), --info, -c.
Results go to results/<task>/<date>/<time>_<id>/ (COBEL_RESULTS changes the root).
Sweeps (-m) run on all cores (joblib; hydra/launcher=slurm for SLURM) into
results/<task>/sweeps/<id>/, <id> a hash of the jobs: the same command resumes the
sweep, skipping finished jobs. Then: cobel status DIR, cobel collect DIR.
Add --debug for a full traceback on errors. `cobel list` shows tasks, envs and agents.
Configs build only cobel's own classes and installed plugins'; --allow-target mypkg.envs.*
(repeatable) or COBEL_ALLOW_TARGETS allows your own.
"""


@app.command(
    "run",
    help=RUN_HELP,
    context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
)
def run_cmd(
    ctx: typer.Context,
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks.")] = False,
    quiet: Annotated[
        bool, typer.Option("--quiet", help="No end-of-run summary (the folder is still printed).")
    ] = False,
    allow_target: AllowTarget = None,
    live: Annotated[
        bool,
        typer.Option(
            "--live",
            help="Stream the run to a live view (Foxglove/Lichtblick on ws://127.0.0.1:PORT; "
            "task.record.live=true).",
        ),
    ] = False,
    port: Annotated[
        int | None,
        typer.Option(
            "--port",
            min=0,
            max=65535,
            help="The live view's port (default 8765; 0: any free port). Implies --live.",
        ),
    ] = None,
) -> None:
    from cobelrun.commands.run import launch_run

    allow_targets(allow_target)
    try:
        code = launch_run(list(ctx.args), debug=debug, quiet=quiet, live=live, port=port)
    except CobelError as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail("interrupted", EXIT_INTERRUPTED)
    raise typer.Exit(code)


@app.command("list")
def list_cmd(
    group: Annotated[
        str | None, typer.Argument(help="task, env, agent or protocol (default: all of them).")
    ] = None,
    config_dir: Annotated[
        str | None,
        typer.Option(
            "--config-dir", "-cd", help="A config folder searched first (as cobel run -cd)."
        ),
    ] = None,
    config_path: Annotated[
        str | None, typer.Option("--config-path", "-cp", help="The same as --config-dir.")
    ] = None,
) -> None:
    """List the available tasks, environments, agents and protocols with one-line descriptions."""
    from rich.console import Console
    from rich.table import Table

    from cobelrun.compose import announce_shadows, check_yaml_folder, user_config_dir
    from cobelrun.config import GROUPS, describe, group_options, user_conf_dir
    from cobelrun.errors import suggest

    try:
        first = user_config_dir(config_dir or config_path)
        user = first or user_conf_dir()
        if user is not None:
            check_yaml_folder(user)
            announce_shadows(user)
    except CobelError as exc:
        fail(str(exc))
    groups = list(GROUPS)
    if group is not None and group not in groups:
        fail(f"unknown group {group!r}{suggest(group, groups)}; allowed: {', '.join(groups)}")
    console = Console()
    for g in [group] if group else groups:
        table = Table(title=f"{g}  (choose with {g}=NAME)", title_justify="left", box=None)
        table.add_column("name", style="bold cyan", no_wrap=True)
        table.add_column("description")
        for name, path in group_options(g, first).items():
            table.add_row(name, describe(path))
        console.print(table)
        console.print()


@app.command("plot")
def plot_cmd(
    run_dirs: Annotated[
        list[Path],
        typer.Argument(
            help="Run folder(s) written by `cobel run` (Fig. 7 takes a latent and a direct "
            "one), or a sweep folder (`cobel run -m`).",
            show_default=False,
            metavar="RUN_DIR",
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Output PNG (default: FIRST_RUN_DIR/plot.png; plot_KIND.png "
            "with --kind, a sweep's plot_Y.png with --y Y).",
        ),
    ] = None,
    kind: Annotated[
        str | None,
        typer.Option(
            "--kind",
            "-k",
            help="occupancy, trajectories (on the saved world.json), latency, response or "
            "reward (curves with a 95% band), value, policy, q, sr (saved agents) or rate "
            "(recorded units) instead of the task's figure; a run offers only what it has.",
        ),
    ] = None,
    hue: Annotated[
        str | None,
        typer.Option("--hue", help="Sweeps: one curve per value of this swept key."),
    ] = None,
    y: Annotated[
        str | None,
        typer.Option("--y", help="Sweeps: latency, response, reward or a trials column."),
    ] = None,
    run: Annotated[
        int | None, typer.Option("--run", help="--kind trajectories/value/policy/q/sr/rate: run.")
    ] = None,
    trials: Annotated[
        str | None, typer.Option("--trials", help="--kind trajectories/rate: trials A:B.")
    ] = None,
    state: Annotated[int | None, typer.Option("--state", help="--kind sr: the state.")] = None,
) -> None:
    """Plot a run: the task's own figure (Fig. 7, Fig. 9) or Fig. 6B-style response/latency.

    Several folders are drawn together where the task's figure compares groups, e.g.
    `cobel plot LATENT_DIR DIRECT_DIR` for Fig. 7B. A sweep folder gives one curve per value
    of `--hue KEY` (n = jobs x runs per curve, 95% confidence band); `--kind` draws
    occupancy, trajectories or one curve of any run.
    """
    from cobelrun.figures import plot_run

    first = run_dirs[0]
    try:
        if (first / "sweep.json").is_file():
            if kind is not None or len(run_dirs) > 1:
                fail("a sweep folder takes --hue/--y, not --kind or more folders")
            from cobelrun.figures.runs import plot_sweep_file

            path = plot_sweep_file(first, hue, y, out)
        elif hue is not None:
            fail(f"--hue needs a sweep folder (cobel run -m); {first} is not one")
        elif kind is not None:
            from cobelrun.figures.kinds import plot_kind

            if len(run_dirs) > 1:
                fail("--kind draws one run; use `cobel compare` for several")
            if run is not None or trials is not None or state is not None:
                from cobelrun.figures.kinds import plot_selection

                path = plot_selection(first, kind, out, run=run, trials=trials, state=state)
            else:
                path = plot_kind(first, kind, out)
        else:
            path = plot_run(first, out, *run_dirs[1:])
    except CobelError as exc:
        fail(str(exc))
    typer.echo(str(path))


@app.command("compare")
def compare_cmd(
    run_dirs: Annotated[
        list[Path], typer.Argument(help="Two or more run folders.", show_default=False)
    ],
    y: Annotated[
        str | None,
        typer.Option("--y", help="latency, response, reward or a trials column."),
    ] = None,
    labels: Annotated[
        str | None, typer.Option("--labels", help="Comma-separated curve labels.")
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Output PNG (default: FIRST_RUN_DIR/compare.png; compare_Y.png with --y Y).",
        ),
    ] = None,
) -> None:
    """Overlay runs: one curve per run folder (mean and 95% band over its runs, n in the legend)."""
    from cobelrun.figures.runs import compare_file

    try:
        path = compare_file(run_dirs, y, out, labels.split(",") if labels else None)
    except CobelError as exc:
        fail(str(exc))
    typer.echo(str(path))


from cobelrun.commands.render_cache import register as _register_render_cache  # noqa: E402

_register_render_cache(app)

from cobelrun.commands.export import register as _register_export  # noqa: E402

_register_export(app)

from cobelrun.commands.rerun import register as _register_rerun  # noqa: E402

_register_rerun(app)

from cobelrun.commands.resume import register as _register_resume  # noqa: E402

_register_resume(app)

from cobelrun.commands.show import register as _register_show  # noqa: E402

_register_show(app)

from cobelrun.commands.fit import register as _register_fit  # noqa: E402

_register_fit(app)

from cobelrun.commands.recover import register as _register_recover  # noqa: E402

_register_recover(app)

from cobelrun.commands.serve import register as _register_serve  # noqa: E402

_register_serve(app)

from cobelrun.commands.replay import register as _register_replay  # noqa: E402

_register_replay(app)

from cobelrun.commands.edit import register as _register_edit  # noqa: E402

_register_edit(app)


@app.command("status")
def status_cmd(
    sweep_dir: Annotated[
        Path,
        typer.Argument(
            help="A sweep folder (`cobel run -m`) or a run folder.", metavar="RUN_OR_SWEEP_DIR"
        ),
    ],
    problems: Annotated[
        bool, typer.Option("--problems", "-p", help="List only jobs that are not done.")
    ] = False,
) -> None:
    """A run's status and tables, or a sweep's jobs: done, failed (with the error), running
    and missing.

    For a sweep, rebuilds its job index (SWEEP_DIR/jobs.csv) and exits 1 when a job is not done.
    """
    from rich.console import Console

    from cobelrun.commands.summary import job_progress, sweep_table
    from cobelrun.io.run_folder import RunFolder
    from cobelrun.io.sweep_folder import SWEEP_FILE, job_rows, read_sweep, summary

    folder = RunFolder(sweep_dir)
    if folder.manifest.is_file():  # a single run folder
        run_status(folder)
        return
    if sweep_dir.is_dir() and not (sweep_dir / SWEEP_FILE).is_file():
        fail(
            f"{sweep_dir} is neither a run folder (no {folder.manifest.name}; made by `cobel "
            f"run`) nor a sweep folder (no {SWEEP_FILE}; made by `cobel run -m`)"
        )
    try:
        sweep = read_sweep(sweep_dir)
        rows = job_rows(sweep_dir)
    except CobelError as exc:
        fail(str(exc))
    console = Console()
    table = sweep_table(sweep_dir, sweep["swept"])
    table.add_column("error / progress", overflow="fold")
    for r in rows:
        if problems and r["status"] == "done":
            continue
        dur = r["duration_s"]
        note = "" if not isinstance(r["error"], str) else r["error"]
        if not note and r["status"] in ("running", "interrupted"):
            note = job_progress(Path(r["run_dir"]))
        table.add_row(
            str(r["job"]),
            *[str(r[k]) for k in sweep["swept"]],
            f"[{STATUS_STYLE[r['status']]}]{r['status']}[/]",
            "" if dur is None or dur != dur else f"{float(dur):.1f}",
            note,
        )
    console.print(table)
    counts = summary(rows)
    parts = [f"{n} {s}" for s, n in counts.items() if n]
    console.print(f"{len(rows)} jobs: " + ", ".join(parts))
    if counts["done"] < len(rows):
        console.print(f"resume (runs only what is not done): {sweep.get('command', '')}")
        raise typer.Exit(1)


def run_status(folder: Any) -> None:
    """``cobel status RUN_DIR`` (:func:`cobelrun.commands.summary.run_status`: validated)."""
    from cobelrun.commands.summary import run_status as status

    status(folder)


@app.command("collect")
def collect_cmd(
    sweep_dir: Annotated[Path, typer.Argument(help="A sweep folder written by `cobel run -m`.")],
    tables: Annotated[
        str, typer.Option("--tables", help="Comma-separated tables to collect.")
    ] = "trials,steps",
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Output folder (default SWEEP_DIR/collected)."),
    ] = None,
) -> None:
    """Combine a sweep's done jobs into one Parquet file per table, swept params as columns.

    Writes SWEEP_DIR/collected/trials.parquet and steps.parquet (streamed: memory stays flat),
    with `job` and one column per swept key; load with pandas.read_parquet or
    cobelrun.results.load_collected.
    """
    from cobelrun.io.sweep_collect import collect
    from cobelrun.io.sweep_folder import job_rows, summary
    from cobelrun.progress import counter_progress

    try:
        with counter_progress("collect", total=0, unit="files") as update:
            written = collect(
                sweep_dir, [t for t in tables.split(",") if t], out_dir=out, progress=update
            )
        counts = summary(job_rows(sweep_dir, write=False))
    except CobelError as exc:
        fail(str(exc))
    total = sum(counts.values())
    if counts["done"] < total:
        typer.echo(
            f"cobel: collected {counts['done']} of {total} jobs; the others are not done "
            f"(see cobel status {sweep_dir})",
            err=True,
        )
    for path in written.values():
        typer.echo(str(path))


@app.command("figure")
def figure_cmd(
    name: Annotated[
        str | None, typer.Argument(help="Figure name (e.g. fig6b) or `all`; see --list.")
    ] = None,
    quick: Annotated[
        bool, typer.Option("--quick", help="Small budget (few runs) for a fast check or CI.")
    ] = False,
    list_: Annotated[bool, typer.Option("--list", help="List the figures and exit.")] = False,
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Output folder (default $COBEL_RESULTS/figures)."),
    ] = None,
    from_: Annotated[
        list[Path] | None,
        typer.Option(
            "--from",
            help="Take finished runs the figure needs (same config hash) from this sweep or "
            "run folder, e.g. a `cobel run -m` of its jobs; repeatable.",
        ),
    ] = None,
    jobs: Annotated[
        int | None,
        typer.Option(
            "--jobs",
            "-j",
            help="Run up to N of the figure's missing runs at once, one process each (Hydra's "
            "joblib launcher, as cobel run -m; a deep agent uses one core: N up to the number "
            "of cores); 1: one after another. Default: the figure's own (1; one per core for "
            "fig8 and fig8_stable).",
        ),
    ] = None,
    launcher: Annotated[
        str | None,
        typer.Option(
            "--launcher",
            help="Run the missing runs through this Hydra launcher instead (a name as in "
            "`cobel run -m hydra/launcher=NAME`: slurm, slurm_gpu, local, submitit_local, ...).",
        ),
    ] = None,
    launcher_arg: Annotated[
        list[str] | None,
        typer.Option(
            "--launcher-arg",
            help="KEY=VALUE for the launcher (hydra.launcher.KEY=VALUE), e.g. partition=gpu; "
            "repeatable.",
        ),
    ] = None,
    finished_only: Annotated[
        bool,
        typer.Option(
            "--finished-only",
            help="Run nothing: draw from the figure's runs that are already finished (e.g. "
            "while its other runs go on), to NAME_partial.*; the runs left out are listed.",
        ),
    ] = False,
) -> None:
    """Build a paper figure: run what it needs (finished runs are reused), then draw it.

    Writes NAME.png, NAME.pdf and NAME.csv (the plotted numbers) to results/figures/
    (NAME_quick.* with --quick). Specs live in experiments/ (./experiments is searched first).
    """
    from rich.console import Console
    from rich.table import Table

    from cobelrun.figures.registry import build, figures, get

    try:
        known = figures()
        if list_ or name is None:
            table = Table(title="figures  (build with cobel figure NAME)", title_justify="left",
                          box=None)  # fmt: skip
            table.add_column("name", style="bold cyan", no_wrap=True)
            table.add_column("description")
            table.add_column("runs")
            for fig in known.values():
                runs = "; ".join(f"{k}: {' '.join(v)}" for k, v in fig.runs.items())
                table.add_row(fig.name, fig.title, runs)
            Console().print(table)
            return
        chosen = list(known.values()) if name == "all" else [get(name)]
        hydra_launcher = launcher_choice(launcher, launcher_arg or [])
        for fig in chosen:
            files = build(fig, quick=quick, out_dir=out, reuse_from=from_ or (), jobs=jobs,
                          finished_only=finished_only, launcher=hydra_launcher,
                          log=lambda m: typer.echo(m, err=True))  # fmt: skip
            for path in files.values():
                typer.echo(str(path))
    except CobelError as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail("interrupted", EXIT_INTERRUPTED)
