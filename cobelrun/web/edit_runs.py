"""``cobel edit``'s "run it": the editor's state (config folder, results, children) and the
panel that starts ``cobel run -cd DIR ...`` with a few runs, follows the child process and
links to its page in a ``cobel serve`` dashboard. Shared by the gridworld, graph and arena
pages (:mod:`cobelrun.web.editor`, :mod:`cobelrun.web.arena_editor`)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from cobelrun.errors import CobelError
from cobelrun.web import edit_config as ec

#: runs of a "run it"
RUN_IT_RUNS = 3
#: seconds "run it" waits, after the run, for the dashboard to listen before giving up its link
DASHBOARD_WAIT_S = 60.0


def _cobel() -> list[str]:
    return [sys.executable, "-c", "from cobelrun.cli import main; main()"]


@dataclass
class Child:
    """A child process the editor started (a run or the dashboard)."""

    proc: subprocess.Popen[bytes]
    what: str
    log: Path | None = None
    out: Path | None = None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()


@dataclass
class Editor:
    """What one editor process holds: the config folder, where runs go, what was asked for
    on the command line, and its children."""

    folder: Path
    results: Path
    name: str = "my_maze"
    initial: ec.Loaded | None = None
    graph_env: str | None = None  # env=NAME named a topology graph or an arena: that page
    graph_page: str = "graph"
    runs: list[Child] = field(default_factory=list)
    dashboard: Child | None = None
    dashboard_port: int = 0

    def first(self) -> ec.Loaded:
        """What a new tab starts with: its own copy of what the command line named."""
        import copy

        if self.initial is None:
            return ec.load_template("open_field")
        return copy.deepcopy(self.initial)

    # ------------------------------------------------------------------ run it
    def run_command(self, env: str, task: str, out: Path, runs: int,
                    extra: list[str] | None = None) -> list[str]:  # fmt: skip
        """``cobel run -cd DIR task=TASK env=ENV task.runs=N [EXTRA...] hydra.run.dir=OUT``."""
        quoted = "'" + str(out).replace("\\", "\\\\").replace("'", "\\'") + "'"  # Hydra's quoting
        return [*_cobel(), "run", "-cd", str(self.folder), f"task={task}", f"env={env}",
                f"task.runs={int(runs)}", *(extra or []), f"hydra.run.dir={quoted}"]  # fmt: skip

    def start_run(self, env: str, task: str, runs: int = RUN_IT_RUNS,
                  extra: list[str] | None = None) -> Child:  # fmt: skip
        stamp = time.strftime("%Y%m%d-%H%M%S")
        out = (self.results / "edit" / env / f"{stamp}-{len(self.runs)}").resolve()
        out.parent.mkdir(parents=True, exist_ok=True)
        log = out.parent / f"{out.name}.log"
        with open(log, "wb") as f:
            proc = subprocess.Popen(self.run_command(env, task, out, runs, extra), stdout=f,
                                    stderr=subprocess.STDOUT, env=_child_env())  # fmt: skip
        what = " ".join([f"cobel run task={task} env={env} task.runs={runs}", *(extra or [])])
        child = Child(proc, what, log, out)
        self.runs.append(child)
        return child

    def dashboard_url(self, run: Child) -> str | None:
        """The dashboard's page of ``run`` (starting the dashboard once the run folder exists)."""
        from cobelrun.web.app import port_free

        if run.out is None or not (run.out / "manifest.json").is_file():
            return None
        if self.dashboard is None or self.dashboard.proc.poll() is not None:
            port = _free_port()
            if not port_free("127.0.0.1", port):
                return None
            cmd = [*_cobel(), "serve", str(self.results.resolve()), "--port", str(port)]
            proc = subprocess.Popen(cmd, env=_child_env(), stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)  # fmt: skip
            self.dashboard, self.dashboard_port = Child(proc, "cobel serve"), port
        if port_free("127.0.0.1", self.dashboard_port):  # not listening yet: no dead link
            return None
        rel = run.out.relative_to(self.results.resolve()).as_posix()
        return f"http://127.0.0.1:{self.dashboard_port}/run?p={quote(rel)}"

    def stop(self) -> None:
        for child in [*self.runs, *([self.dashboard] if self.dashboard else [])]:
            child.stop()


def _child_env() -> dict[str, str]:
    # NiceGUI treats a process with PYTEST_CURRENT_TEST as its own test harness
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RunPanel:
    """ "Run it": the run's status line, the dashboard link, and the timer that follows the
    child process (shared by the three pages)."""

    def __init__(self, editor: Editor) -> None:
        from nicegui import ui

        self.editor = editor
        self.run: Child | None = None
        self.status = ui.label().classes("text-sm cobel-run-status")
        self.link = ui.link("", "#", new_tab=True).classes("cobel-dashboard")
        self.link.set_visibility(False)
        self.finished_at: float | None = None  # when the run's process ended
        self.timer = ui.timer(1.0, self.poll, active=False)

    def start(self, env: str, task: str, runs: int = RUN_IT_RUNS,
              extra: list[str] | None = None) -> None:  # fmt: skip
        try:
            self.run = self.editor.start_run(env, task, runs, extra)
        except (OSError, CobelError) as exc:
            self.status.text = f"cannot start the run: {exc}"
            return
        self.status.text = f"running: {self.run.what} -> {self.run.out}"
        self.finished_at = None
        self.link.set_visibility(False)
        self.timer.activate()

    def poll(self) -> None:
        run = self.run
        if run is None:
            self.timer.deactivate()
            return
        rc = run.proc.poll()
        url = self.editor.dashboard_url(run) if rc == 0 or rc is None else None
        if url and not self.link.visible:
            self.link.text = f"open the run in the dashboard ({url})"
            self.link.props(f'href="{url}"')
            self.link.set_visibility(True)
        if rc is None:
            return
        if self.finished_at is None:
            self.finished_at = time.monotonic()
            if rc == 0:
                self.status.text = f"finished: {run.what} -> {run.out}"
            else:
                tail = ""
                if run.log is not None and run.log.is_file():
                    lines = run.log.read_text(errors="replace").strip().splitlines()
                    tail = lines[-1] if lines else ""
                self.status.text = f"failed (exit {rc}): {tail}"
        dashboard = self.editor.dashboard
        starting = (rc == 0 and not self.link.visible and dashboard is not None
                    and dashboard.proc.poll() is None)  # fmt: skip
        if starting and time.monotonic() - self.finished_at < DASHBOARD_WAIT_S:
            return  # the dashboard is still starting: its link comes when it listens
        self.timer.deactivate()
