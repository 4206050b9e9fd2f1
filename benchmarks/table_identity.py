"""Tables of every built-in task at tiny settings, hashed: the before/after check of a refactor.

Runs each task in ``conf/task`` (2-3 runs, phases cut to a few trials and steps; deep tasks
with their batched and sequential paths) through :func:`cobelrun.api.run`, reads every Parquet
table back and hashes its rows (column names, types, values, order). Columns that hold wall
times are left out (they differ between two runs of one commit).

Usage::

    python benchmarks/table_identity.py OUT.json            # run and write the hashes
    python benchmarks/table_identity.py OUT.json --against BEFORE.json
    python benchmarks/table_identity.py OUT.json --tasks two_afc,gridworld

Run it at the commit before a change and after it; ``--against`` prints the tables that differ
and exits 1 if any does.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq
from omegaconf import open_dict

ROOT = (
    Path.cwd() if (Path.cwd() / "conf" / "task").is_dir() else Path(__file__).resolve().parents[1]
)
#: trials per phase and steps per trial at the tiny settings
TRIALS, STEPS = 4, 30
#: columns that hold wall-clock times (not part of the identity)
TIMED = ("wall", "time_s", "seconds", "duration", "elapsed", "frame_ms", "_ms")
#: extra variants: (label, task, overrides)
VARIANTS = [
    ("two_afc@batched", "two_afc", ["task.batch_runs=true"]),
    ("two_afc@sequential", "two_afc", ["task.batch_runs=false"]),
]


def _tiny(cfg) -> None:
    """Cut a composed config to a few runs, trials and steps, in place."""
    with open_dict(cfg):
        cfg.task.runs = min(int(cfg.task.get("runs", 1) or 1), 3)
        proto = cfg.task.get("protocol")
        if proto is None:
            return
        if proto.get("max_steps") is not None:
            proto.max_steps = min(int(proto.max_steps), STEPS)
        for phase in proto.get("phases") or []:
            if phase.get("trials") is not None:
                phase.trials = min(int(phase.trials), TRIALS)
            if phase.get("max_steps") is not None:
                phase.max_steps = min(int(phase.max_steps), STEPS)


def table_hash(path: Path) -> str:
    """sha256 of a Parquet table's schema and rows, wall-time columns left out."""
    table = pq.read_table(path)
    keep = [c for c in table.column_names if not any(t in c for t in TIMED)]
    table = table.select(keep)
    h = hashlib.sha256(str(table.schema.remove_metadata()).encode())  # not the config hash
    for name in keep:
        h.update(repr(table.column(name).to_pylist()).encode())
    return h.hexdigest()[:16]


def run_one(task: str, overrides: list[str], out: Path) -> dict[str, str]:
    from cobelrun import api

    cfg = api.compose(task, ["seed=7", *overrides])
    _tiny(cfg)
    if cfg.task.get("job"):
        return {"__skipped__": "a job task (no phase loop)"}
    run = api._execute(cfg, out, progress=False)
    return {p.name: table_hash(p) for p in sorted(run.folder.path.glob("*.parquet"))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--against")
    ap.add_argument("--tasks", help="comma-separated labels (default: every task + variants)")
    args = ap.parse_args()
    items = [(p.stem, p.stem, []) for p in sorted((ROOT / "conf" / "task").glob("*.yaml"))]
    items += VARIANTS
    if args.tasks:
        wanted = set(args.tasks.split(","))
        items = [i for i in items if i[0] in wanted]
    results: dict[str, dict[str, str]] = {}
    for label, task, overrides in items:
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            try:
                results[label] = run_one(task, overrides, Path(tmp) / "run")
            except Exception as exc:  # a task that fails is a result too
                results[label] = {"__error__": f"{type(exc).__name__}: {str(exc)[:200]}"}
        print(f"{label:32s} {time.perf_counter() - t0:6.1f} s  {results[label]}", flush=True)
    Path(args.out).write_text(json.dumps(results, indent=1, sort_keys=True))
    if args.against:
        before = json.loads(Path(args.against).read_text())
        bad = [(k, before.get(k), v) for k, v in results.items() if before.get(k) != v]
        for k, b, a in bad:
            print(f"DIFFERS {k}: before {b} after {a}")
        print(f"{len(results) - len(bad)} of {len(results)} tasks identical")
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
