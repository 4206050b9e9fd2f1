"""Scaffolding shared by ``cobel edit``'s three pages (gridworlds ``/``, topology graphs
``/graph``, 2D arenas ``/arena``): the header, the load rows (template, env of the folder),
the tool buttons, the phase rows (pick, trials, add a phase), the save panel (name, "also
write task/NAME.yaml", save, run it with its :class:`~cobelrun.web.edit_runs.RunPanel`,
export PNG/SVG, the YAML as it will be saved), and the behaviour behind them (undo history,
loading, saving, "run it", exporting).

A page subclasses :class:`EditPage`, builds its own canvas between these parts and fills in
the hooks: :meth:`~EditPage.load_template`, :meth:`~EditPage.load_existing`,
:meth:`~EditPage.existing_names`, :meth:`~EditPage.write`, :meth:`~EditPage.figure`,
:meth:`~EditPage.run_target` and :meth:`~EditPage.refresh`. Its design holds ``phases`` (the
protocol's phases as plain data) and ``copy()``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError

#: the phase menu's "env (as built)"
ENV_NONE = -1
#: the pages: path -> link text
PAGES = {"/": "gridworlds", "/graph": "topology graphs", "/arena": "2D arenas"}
#: link classes the tests and docs refer to
_LINK_CLASSES = {"/": "cobel-grid-link", "/graph": "cobel-graph-link", "/arena": "cobel-arena-link"}


def phase_text(phase: dict[str, Any] | None, n_phases: int, what: str) -> str:
    """The phase hint: what the picked phase sets (or how many phases there are)."""
    if phase is None:
        return (f"{n_phases} protocol phase(s); pick one to see and edit the goals and starts "
                "it sets")  # fmt: skip
    sets = []
    for key in ("rewards", "terminals"):
        if phase.get(key):
            sets.append(f"{key} " + ", ".join(f"{k}: {v}" for k, v in phase[key].items()))
    if phase.get("starts") is not None:
        sets.append("starts " + ", ".join(str(s) for s in phase["starts"]))
    if phase.get("cycle"):
        sets.append(f"a per-trial cycle of {len(phase['cycle'])} changes")
    told = "; ".join(sets) or "nothing (the world as the phase before left it)"
    return f"{phase.get('name')} ({phase.get('trials')} trials) sets {told}. {what}."


class EditPage:
    """One browser tab's editor: the shared widgets and behaviour (see the module docstring).

    Attributes a subclass sets before :meth:`build_parts` runs: ``editor`` (the
    :class:`~cobelrun.web.edit_runs.Editor`), ``loaded``, ``design``, ``error`` (shown in the
    status line) and ``start_name`` (the name box's first value).
    """

    here = "/"  # the page's own path (left out of the header's links)
    title = "cobel edit"
    #: what the tools do while a phase is picked (the phase hint's last sentence)
    phase_tools = "Painting starts and goals now changes what this phase sets"
    task_label = "also write task/NAME.yaml (protocol, agent, monitors)"
    existing_label = "env in the folder"

    editor: Any
    loaded: Any
    design: Any
    error: str = ""
    start_name: str = "my_maze"

    def init_state(self) -> None:
        self.history: list[Any] = []
        self.phase: int | None = None
        self.tool_buttons: dict[str, Any] = {}

    @property
    def folder(self) -> Path:
        return Path(self.editor.folder)

    # ------------------------------------------------------------------ parts
    def header(self) -> None:
        from nicegui import ui

        with ui.row().classes("items-center w-full"):
            ui.label(self.title).classes("text-xl font-bold")
            ui.label(f"config folder {self.folder}").classes("text-sm cobel-folder")
            for path, text in PAGES.items():
                if path != self.here:
                    ui.link(text, path).classes(f"text-sm {_LINK_CLASSES[path]}")
            self.origin = ui.label().classes("text-sm text-gray-600 cobel-origin")

    def load_rows(self, templates: dict[str, str]) -> None:
        """ "start from": a template and an env of the folder."""
        from nicegui import ui

        ui.label("start from").classes("font-bold")
        with ui.row().classes("items-center no-wrap"):
            self.template = ui.select(templates, value=None, label="template")
            self.template.classes("w-48 cobel-template")
            ui.button("load", on_click=self.on_load_template).props("dense").classes(
                "cobel-load-template"
            )
        with ui.row().classes("items-center no-wrap"):
            self.existing = ui.select(self.existing_names(), value=None,
                                      label=self.existing_label).classes("w-48 cobel-existing")  # fmt: skip
            ui.button("open", on_click=self.on_open).props("dense").classes("cobel-open")

    def tool_grid(self, tools: dict[str, str]) -> None:
        from nicegui import ui

        with ui.grid(columns=2).classes("gap-1"):
            for name, what in tools.items():
                b = ui.button(name, on_click=lambda _, n=name: self.set_tool(n))
                b.props("dense no-caps").classes(f"cobel-tool cobel-tool-{name}").tooltip(what)
                self.tool_buttons[name] = b

    def phase_rows(self) -> None:
        """The phase menu, what the picked phase sets, its trials, and "add phase"."""
        from nicegui import ui

        ui.label("phase").classes("font-bold mt-2")
        with ui.row().classes("items-center no-wrap"):
            self.phase_select = ui.select({ENV_NONE: "env (as built)"}, value=ENV_NONE,
                                          on_change=self.on_phase).classes("w-44 cobel-phase")  # fmt: skip
            ui.button("add phase", on_click=self.add_phase).props("dense no-caps").classes(
                "whitespace-nowrap cobel-add-phase"
            )
        self.phase_hint = ui.label().classes("text-xs text-gray-600 cobel-phase-hint")
        self.trials = ui.number("trials in this phase", min=1, precision=0).classes(
            "w-40 cobel-trials"
        )
        self.trials.on("change", self.on_trials)
        self.trials.set_visibility(False)

    def save_panel(self, *, yaml_class: str = "w-96 text-xs cobel-yaml") -> None:
        """Name, "also write task/NAME.yaml", save, run it (and its panel), export, the YAML."""
        from nicegui import ui

        from cobelrun.web.edit_runs import RunPanel

        ui.label("save").classes("font-bold")
        self.name = ui.input("env name", value=self.start_name).classes("w-64 cobel-name")
        self.with_task = ui.checkbox(self.task_label).classes("cobel-with-task")
        with ui.row():
            ui.button("save", on_click=self.on_save).classes("cobel-save")
            ui.button("run it", on_click=self.run_it).classes("cobel-run")
        self.run_options()
        self.status = ui.label(self.error).classes("text-sm cobel-status")
        self.runner = RunPanel(self.editor)
        with ui.row():
            ui.button("export PNG", on_click=lambda: self.export("png")).props(
                "dense outline"
            ).classes("cobel-export-png")
            ui.button("export SVG", on_click=lambda: self.export("svg")).props(
                "dense outline"
            ).classes("cobel-export-svg")
        ui.label("env/NAME.yaml as it will be saved").classes("font-bold mt-2")
        self.yaml = ui.code("", language="yaml").classes(yaml_class)

    # ------------------------------------------------------------------ shared refresh
    def refresh_common(self) -> None:
        """The origin line, the tool buttons' colours and the phase menu and hint."""
        self.origin.text = f"from {self.loaded.origin}"
        self.paint_tools()
        if hasattr(self, "phase_select"):
            opts = {ENV_NONE: "env (as built)"}
            opts.update({i: f"phase {i + 1}: {n}" for i, n in enumerate(self.phase_names())})
            if self.phase is not None and self.phase >= len(self.design.phases):
                self.phase = None
            if self.phase_select.options != opts:
                self.phase_select.set_options(
                    opts, value=ENV_NONE if self.phase is None else self.phase
                )
            p = None if self.phase is None else self.design.phases[self.phase]
            self.phase_hint.text = phase_text(p, len(self.design.phases), self.phase_tools)

    def phase_names(self) -> list[str]:
        return [str(p.get("name", f"phase {i}")) for i, p in enumerate(self.design.phases)]

    def paint_tools(self) -> None:
        for n, b in self.tool_buttons.items():
            b.props(f"color={'primary' if n == self.tool else 'grey-6'}")

    # ------------------------------------------------------------------ events
    def change(self, fn: Any) -> bool:
        """Apply ``fn`` (an edit of the design) with undo; a CobelError restores the design
        and goes to the status line."""
        before = self.design.copy()
        try:
            fn()
        except CobelError as exc:
            self.design = before
            self.status.text = str(exc)
            return False
        self.history.append(before)
        del self.history[:-100]
        self.refresh()
        return True

    def undo(self) -> None:
        if self.history:
            self.design = self.history.pop()
            self.after_undo()
            self.refresh()

    def after_undo(self) -> None:
        """Hook: forget what pointed into the design before the undo."""

    def set_tool(self, name: str) -> None:
        self.tool = name
        self.paint_tools()

    def on_phase(self, e: Any) -> None:
        v = e.value
        self.phase = None if v in (None, ENV_NONE) else int(v)
        if self.phase is not None:
            self.trials.value = self.design.phases[self.phase].get("trials")
        self.trials.set_visibility(self.phase is not None)
        self.refresh()

    def on_trials(self) -> None:
        if self.phase is None or self.trials.value is None:
            return
        i, n = self.phase, int(self.trials.value)
        if self.design.phases[i].get("trials") != n:
            self.change(lambda: self.design.phases[i].__setitem__("trials", n))

    def add_phase(self) -> None:
        """A new last phase (10 trials) that changes nothing yet; picked, to be painted."""
        names = set(self.phase_names())
        k = len(self.design.phases) + 1
        while f"phase_{k}" in names:
            k += 1
        if self.change(lambda: self.design.phases.append({"name": f"phase_{k}", "trials": 10})):
            self.phase = len(self.design.phases) - 1
            self.phase_select.set_options(
                {**self.phase_select.options, self.phase: f"phase {self.phase + 1}: phase_{k}"},
                value=self.phase,
            )

    def use(self, loaded: Any, name: str) -> None:
        """Start over from ``loaded`` (a template or an env of the folder) named ``name``."""
        self.loaded, self.design = loaded, loaded.design.copy()
        self.history.clear()
        self.phase = None
        if hasattr(self, "trials"):
            self.trials.set_visibility(False)
        self.after_use()
        self.name.value = name
        self.status.text = f"loaded {loaded.origin}"
        self.refresh()

    def after_use(self) -> None:
        """Hook: set the page's own widgets from the newly loaded design."""

    def on_load_template(self) -> None:
        if not self.template.value:
            self.status.text = "pick a template first"
            return
        try:
            self.use(self.load_template(self.template.value), self.template.value)
        except CobelError as exc:
            self.status.text = str(exc)

    def on_open(self) -> None:
        if not self.existing.value:
            self.status.text = "pick an env of the folder first"
            return
        try:
            self.use(self.load_existing(self.existing.value), self.existing.value)
        except CobelError as exc:
            self.status.text = str(exc)
            self.open_failed(exc)

    def open_failed(self, exc: CobelError) -> None:
        """Hook: an env of the folder could not be opened."""

    def on_save(self) -> None:
        self.save()

    def save(self) -> list[Path] | None:
        """Write the design (and, ticked, its task); the files written, or None (the reason in
        the status line)."""
        name = str(self.name.value or "").strip()
        try:
            written = self.write(name, bool(self.with_task.value))
        except CobelError as exc:
            self.status.text = str(exc)
            return None
        self.existing.set_options(self.existing_names())
        self.status.text = "saved " + ", ".join(str(p) for p in written)
        self.refresh()
        return written

    def run_it(self) -> None:
        """Save, then ``cobel run -cd DIR task=... env=NAME`` with few runs (the panel follows
        it and links its page in the dashboard)."""
        name = str(self.name.value or "").strip()
        try:
            target = self.run_target(name)
        except CobelError as exc:
            self.status.text = str(exc)
            return
        if self.save() is None:
            return
        task, runs, extra = target
        self.runner.start(name, task, runs=runs, extra=extra)

    def export(self, fmt: str) -> None:
        from nicegui import ui

        try:
            data = self.figure(fmt)
        except CobelError as exc:
            self.status.text = str(exc)
            return
        name = str(self.name.value or "").strip() or "maze"
        ui.download.content(data, f"{name}.{fmt}")

    # ------------------------------------------------------------------ hooks
    def run_options(self) -> None:
        """Hook: widgets under "run it" that set how it runs."""

    def refresh(self) -> None:  # pragma: no cover - every page has its own
        raise NotImplementedError

    def load_template(self, name: str) -> Any:  # pragma: no cover
        raise NotImplementedError

    def load_existing(self, name: str) -> Any:  # pragma: no cover
        raise NotImplementedError

    def existing_names(self) -> list[str]:  # pragma: no cover
        raise NotImplementedError

    def write(self, name: str, with_task: bool) -> list[Path]:  # pragma: no cover
        """Save under ``name``; the files written (a CobelError says why not)."""
        raise NotImplementedError

    def figure(self, fmt: str) -> bytes:  # pragma: no cover
        raise NotImplementedError

    def run_target(self, name: str) -> tuple[str, int, list[str]]:  # pragma: no cover
        """``(task, runs, extra overrides)`` of "run it" for env ``name``, checked before the
        save (a CobelError says what is missing)."""
        raise NotImplementedError
