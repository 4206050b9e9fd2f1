"""What one click in ``cobel edit`` costs on the server: the check (``cobel run``'s builder and
protocol code) plus the redraw, by grid size, for the graph and arena pages too (also with a
phase picked), and the graph page's view preview (pybullet, or the render cache).

Run on demand (not a test)::

    python benchmarks/bench_edit.py [--repeat 5]

Prints the median seconds per click (check + SVG) after one warm-up call (imports, numba
compilation), and writes ``benchmarks/results/bench_edit.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path


def _median(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm-up: imports, numba, caches
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def _previews(repeat: int) -> dict[str, float]:
    """The graph page's view preview (grid template, 84 x 84 camera): rendered with pybullet
    (no cache), and read from a render cache built here (in a temporary folder)."""
    import tempfile

    from cobelrun.render import cache
    from cobelrun.web.graph_editor import load_graph_template
    from cobelrun.web.grid_design import build_with

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        d = load_graph_template("grid").design
        d.extra["observation"]["cache_dir"] = tmp
        out["graph view preview, pybullet (no cache)"] = _median(
            lambda: d.preview(12, 90.0), repeat
        )
        obs = d.camera()
        obs.bind(build_with("env.topology", d.topology_node()))
        cache.build(obs.cache_request(), jobs=1)
        assert d.preview(12, 90.0)[1].startswith("read from the render cache")
        out["graph view preview, render cache"] = _median(lambda: d.preview(12, 90.0), repeat)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    from cobelrun.web import edit_config as ec
    from cobelrun.web.arena_editor import load_arena
    from cobelrun.web.graph_editor import load_graph_template
    from cobelrun.web.grid_design import GridDesign

    out: dict[str, float] = {}
    for side in (5, 10, 20, 32):
        d = GridDesign.blank(side, side)
        d.paint("goal", (side - 1, side - 1))

        def click(d: GridDesign = d) -> None:
            d.paint("wall", (1, 1))
            d.svg(problems=d.problems())

        out[f"gridworld {side} x {side}"] = _median(click, args.repeat)
    tmaze = ec.load_template("tmaze_paper").design

    def phase_click() -> None:
        tmaze.paint("goal", (0, 0), value=1.0, phase=1)
        tmaze.svg(phase=1, problems=tmaze.problems())

    out["T-maze, extinction phase"] = _median(phase_click, args.repeat)
    hexg = load_graph_template("hex_3d").design

    def graph_click() -> None:
        hexg.toggle_edge(0, 1)
        hexg.svg()
        hexg.problems()

    out["hex_3d graph (77 nodes)"] = _median(graph_click, args.repeat)
    pool = load_arena(None, "water_maze").design

    def arena_click() -> None:
        pool.add_start(0.1, 0.1)
        pool.problems()
        pool.svg(pose=(0.2, 0.1))

    out["water maze arena (493 place cells, rays)"] = _median(arena_click, args.repeat)
    rev = pool.phase_names().index("reversal")

    def arena_phase_click() -> None:
        pool.paint_phase("goal", -0.42, -0.42, rev)  # the reversal platform off, then on
        pool.problems()
        pool.svg(phase=rev)

    out["water maze, reversal phase click"] = _median(arena_phase_click, args.repeat)
    hexg.phases.append({"name": "moved", "trials": 10})

    def graph_phase_click() -> None:
        hexg.paint("clear", 38, phase=len(hexg.phases) - 1)
        hexg.svg(phase=len(hexg.phases) - 1)
        hexg.problems()

    out["hex_3d graph, click in a phase"] = _median(graph_phase_click, args.repeat)
    out.update(_previews(args.repeat))
    for k, v in out.items():
        print(f"{k:45s} {v * 1000:8.1f} ms per click")
    res = Path(__file__).parent / "results"
    res.mkdir(exist_ok=True)
    (res / "bench_edit.json").write_text(json.dumps(
        {"seconds_per_click": out, "host": platform.node(), "python": platform.python_version()},
        indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
