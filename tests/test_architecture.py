"""Imports go down the layers of docs/architecture.md, never up (function-level imports count).

The layers, top to bottom (``LAYERS``): orchestration (CLI, commands, Hydra app, sweeps,
figures' run planning, benchmark jobs, the Python API), compose (config -> validated task, the
Hydra composer), runner (building a task and the phase loop with its strategies), library (envs,
agents, monitors, recorder, io, render, analysis, figure drawing, and the data definitions
everything validates with: the config schema, the instantiation gate's allowlist, the
validated instantiation helpers). A module imports its own layer or a
lower one. The edges that still point up are listed in ``KNOWN_UP`` with their reason; the test
fails on a new one and on a listed one that is gone (so the list only shrinks).
"""

from __future__ import annotations

from tests.test_imports import import_graph

#: layer number -> the modules (and packages: their submodules too) in it; anything not named
#: is library (0). The package root ``cobelrun`` is a lazy facade over ``cobelrun.api`` and is
#: checked separately (nothing below orchestration may import it).
LAYERS: dict[int, tuple[str, ...]] = {
    3: (
        "cobelrun.cli",
        "cobelrun.commands",
        "cobelrun.hydra_app",
        "cobelrun.sweep",
        "cobelrun.figures.registry",
        "cobelrun.figures.data",  # builds figures and writes their data tables (docs/figures/data)
        "cobelrun.figures.run_import",  # reads a figure's sweeps into those tables (asks the registry)
        "cobelrun.render.benchmark",
        "cobelrun.api",
        "cobelrun.recover",
        "cobelrun.web",
    ),
    2: ("cobelrun.compose",),
    1: ("cobelrun.runner", "cobelrun.batched", "cobelrun.revaluation"),
}
NAMES = {3: "orchestration", 2: "compose", 1: "runner", 0: "library"}

#: upward edges still in the code: (importer, imported) -> why it is there for now
KNOWN_UP: dict[tuple[str, str], str] = {}
#: modules below orchestration that still import the package root (none: the version is in
#: ``cobelrun._version``)
KNOWN_ROOT: dict[str, str] = {}


def layer(module: str) -> int:
    for level, members in LAYERS.items():
        if any(module == m or module.startswith(m + ".") for m in members):
            return level
    return 0


def upward_edges(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    return {
        (a, b)
        for a, deps in graph.items()
        for b in deps
        if "cobelrun" not in (a, b) and not b.startswith(a + ".") and layer(b) > layer(a)
    }


def root_importers(graph: dict[str, set[str]]) -> set[str]:
    return {
        a for a, deps in graph.items() if "cobelrun" in deps and a != "cobelrun" and layer(a) < 3
    }


def test_layer_check_finds_an_upward_edge():
    graph = {"cobelrun.envs.x": {"cobelrun.cli"}, "cobelrun.cli": {"cobelrun.envs.x"}}
    assert upward_edges(graph) == {("cobelrun.envs.x", "cobelrun.cli")}


def test_imports_point_down_the_layers():
    graph = import_graph()
    found = upward_edges(graph)
    new = sorted(found - set(KNOWN_UP))
    gone = sorted(set(KNOWN_UP) - found)
    shown = [f"{a} ({NAMES[layer(a)]}) -> {b} ({NAMES[layer(b)]})" for a, b in new]
    assert not new, "imports that point up a layer (docs/architecture.md): " + "; ".join(shown)
    assert not gone, f"KNOWN_UP lists edges that are gone (remove them): {gone}"


def test_library_does_not_import_the_package_root():
    found = root_importers(import_graph())
    assert found <= set(KNOWN_ROOT), (
        f"import the version from cobelrun._version: {found - set(KNOWN_ROOT)}"
    )
    assert set(KNOWN_ROOT) <= found, (
        f"KNOWN_ROOT lists importers that are gone: {set(KNOWN_ROOT) - found}"
    )
