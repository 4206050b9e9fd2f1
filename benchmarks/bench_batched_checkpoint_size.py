"""Checkpoint sizes of a batched chunk (issue 35, ``task.batch_runs``), measured on real runs.

A checkpoint written inside a batched chunk holds the batched learner (every run's weights,
target network, Adam moments, counters, generators and the filled part of its replay memory)
and the rows the chunk's runs hold back until the chunk ends (trial and step rows, the trial
batches they were built from, monitors' events such as Fig. 8's activity maps). This script
runs a task batched (R runs in one chunk) to ``T`` trials with ``task.checkpoint.keep=true``,
reads the last checkpoint written inside the chunk and splits its size into the learner's
fixed part, its replay memories (bytes per stored transition) and the held-back rows (bytes
per recorded step and per trial). The size at a full run is *derived*: fixed + runs x
``min(buffer_size, steps)`` x bytes per transition + held-back bytes per step x steps.

Usage::

    python benchmarks/bench_batched_checkpoint_size.py fig8 --trials 30
    python benchmarks/bench_batched_checkpoint_size.py dqn --trials 200
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import zipfile
from pathlib import Path

CASES = {
    # name: (task, overrides)
    "fig8": ("place_cells_original", ["task.runs=2", "task.batch_runs=2"]),
    "dqn": ("two_afc", ["agent=dqn", "task.runs=2", "task.batch_runs=2"]),
}


def measure(name: str, trials: int, every: int, extra: list[str]) -> dict[str, object]:
    import numpy as np

    from cobelrun import api, runner
    from cobelrun.checkpoint import read_header

    task, overrides = CASES[name]
    cfg = api.compose(task, [*overrides, *extra, f"task.protocol.phases=[{{name: training, trials: {trials}}}]",
                             f"task.checkpoint.every_trials={every}",
                             "task.checkpoint.every_minutes=null", "task.checkpoint.keep=true",
                             "task.record.flush_seconds=0.05"])  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.process_time()
        folder = runner.run(cfg, Path(tmp) / "run")
        cpu = time.process_time() - t0
        path = folder / "checkpoint.npz"
        header = read_header(path)
        pos = header["position"]
        done = pos["first"] - 1 + pos["k"]  # trials of each run before the checkpoint
        names = ("learner_replay", "learner_fixed", "held_back_rows", "held_back_index", "header")
        groups = dict.fromkeys(names, 0)  # uncompressed bytes
        packed = dict.fromkeys(names, 0)  # bytes in the file (members are deflated)
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                key = info.filename
                if key.startswith("agent/replay."):
                    group = "learner_replay"
                elif key.startswith("agent/"):
                    group = "learner_fixed"
                elif key == "pending/index.npy":
                    group = "held_back_index"
                elif key.startswith("pending/"):
                    group = "held_back_rows"
                else:
                    group = "header"
                groups[group] += info.file_size
                packed[group] += info.compress_size
        runs = len(header["batch"]["runs"])

        with np.load(path) as z:
            stored = int(z["agent/replay.obs"].shape[1])
            # one learning phase, memories not full: the steps every run took so far
            assert not z["agent/replay.full"].any(), "use fewer trials: a memory is full"
            steps_before = int(z["agent/replay.pos"].sum())
        file_bytes = path.stat().st_size
    return {
        "case": name, "task": task, "overrides": [*overrides, *extra], "runs_in_chunk": runs, "trials_run": trials,
        "checkpoint_at_trial": done, "steps_before_checkpoint_all_runs": steps_before,
        "replay_slots_kept_per_run": stored, "file_bytes": file_bytes,
        "groups_bytes_uncompressed": groups, "groups_bytes_in_file": packed,
        "bytes_per_transition_per_run": groups["learner_replay"] / max(runs * stored, 1),
        "file_bytes_per_transition_per_run": packed["learner_replay"] / max(runs * stored, 1),
        "held_back_bytes_per_step": groups["held_back_rows"] / max(steps_before, 1),
        "file_held_back_bytes_per_step": packed["held_back_rows"] / max(steps_before, 1),
        "index_bytes_per_trial": groups["held_back_index"] / max(runs * done, 1),
        "header_bytes": groups["header"],
        "run_cpu_s": round(cpu, 2),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=sorted(CASES))
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("overrides", nargs="*", help="more config overrides")
    args = ap.parse_intermixed_args()
    result = measure(args.case, args.trials, args.every, args.overrides)
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
