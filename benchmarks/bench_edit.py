"""What one click in ``cobel edit`` costs on the server: the check (``cobel run``'s builder and
protocol code) plus the redraw, by grid size, for the graph and arena pages too.

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
    for k, v in out.items():
        print(f"{k:45s} {v * 1000:8.1f} ms per click")
    res = Path(__file__).parent / "results"
    res.mkdir(exist_ok=True)
    (res / "bench_edit.json").write_text(json.dumps(
        {"seconds_per_click": out, "host": platform.node(), "python": platform.python_version()},
        indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
