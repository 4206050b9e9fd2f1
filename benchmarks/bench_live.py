"""Live-view overhead: the same run with the live view off, on with no client, and on with one
connected client that subscribes to every channel.

Run on demand (not a test)::

    python benchmarks/bench_live.py [--repeats 3] [--runs 20] [-- extra overrides]

Each repeat runs the three settings one after another (so that machine load hits them alike)
as whole ``cobel run`` processes of this tree (a gridworld task, Dyna-Q, steps and ``run.mcap``
recorded: poses of the first 10 runs). The client is a separate process started before the
run (``task.record.live_wait`` holds the first trial until it subscribed), reading every
message as Foxglove would. Reported: the median of the run's ``wall_time_s`` (manifest: setup,
trials, recording, closing the files) and of its phases' time, each as a ratio to "off", and
how many messages the client got; and CPU time, which machine load disturbs less: the run's
simulation and writer threads (manifest ``cpu_time_s``) and the whole process's (``wait4``:
foxglove-sdk's server threads included), the latter's excess over "off" per second of the "off"
run. First, the stream's own cost in this process (:func:`micro`: less disturbed by load).
Writes ``benchmarks/results/live.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
CLIENT = ROOT / "tests" / "live_client.py"

TASK = ["task=gridworld", "env=open_field", "task.record.mcap_runs=10"]
SETTINGS = ("off", "live_no_client", "live_one_client")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client_code() -> str:
    """A client that reads everything until the server closes (the test client stops early)."""
    return f"""
import json, sys, time
sys.path.insert(0, {str(CLIENT.parent)!r})
import live_client
import websocket
port = int(sys.argv[1])
deadline = time.monotonic() + 600
while True:
    try:
        ws = websocket.create_connection(f"ws://127.0.0.1:{{port}}",
                                         subprotocols=[live_client.SUBPROTOCOL], timeout=600)
        break
    except OSError:
        if time.monotonic() > deadline:
            raise
        time.sleep(0.005)
n = nbytes = sub = 0
while True:
    try:
        msg = ws.recv()
    except (websocket.WebSocketConnectionClosedException, OSError):
        break
    if not msg:
        break
    if isinstance(msg, str):
        op = json.loads(msg)
        if op.get("op") == "advertise":
            subs = []
            for ch in op["channels"]:
                sub += 1
                subs.append({{"id": sub, "channelId": ch["id"]}})
            ws.send(json.dumps({{"op": "subscribe", "subscriptions": subs}}))
    elif msg[0] == live_client.MESSAGE_DATA:
        n += 1
        nbytes += len(msg)
print(json.dumps({{"messages": n, "bytes": nbytes, "channels": sub}}))
"""


def run_once(setting: str, runs: int, extra: list[str], out: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    args = [*TASK, f"task.runs={runs}", *extra, f"hydra.run.dir={out}"]
    client = None
    if setting != "off":
        port = free_port()
        args += ["task.record.live=true", f"task.record.live_port={port}"]
        if setting == "live_one_client":
            args.append("task.record.live_wait=60")
            client = subprocess.Popen([sys.executable, "-c", client_code(), str(port)],
                                      stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip
    t0 = time.perf_counter()
    with open(out.parent / f"{out.name}.err", "w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "cobelrun.cli", "run", *args], env=env,
                                stdout=subprocess.DEVNULL, stderr=err)  # fmt: skip
        _, status, usage = os.wait4(proc.pid, 0)  # this process's CPU time, its threads' too
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        err.seek(0)
        stderr = err.read()
    got: dict[str, int] = {}
    if client is not None:
        text, _ = client.communicate(timeout=120)
        got = json.loads(text.strip().splitlines()[-1])
    if proc.returncode != 0:
        raise SystemExit(f"{setting}: cobel run failed:\n{stderr}")
    if setting == "live_no_client" and "is watching" in stderr:
        raise SystemExit("a client connected to the no-client run")
    manifest = json.loads((out / "manifest.json").read_text())
    cpu = manifest.get("cpu_time_s", {})
    return {
        "process_s": wall,
        "run_s": float(manifest["wall_time_s"]),
        "phases_s": float(sum(manifest.get("phase_wall_time_s", {}).values())),
        "run_cpu_s": float(cpu.get("simulation_thread", 0) + cpu.get("writer_thread", 0)),
        "process_cpu_s": usage.ru_utime + usage.ru_stime,
        "messages": float(got.get("messages", 0)),
        "mbytes": got.get("bytes", 0) / 1e6,
    }


def micro(repeats: int, poses: int = 40_000, trials: int = 2_000) -> dict[str, dict[str, float]]:
    """The stream's own cost, in this process: the same poses, trial events and trial table
    written to ``run.mcap`` alone, with a live view nobody watches, and with a client
    subscribed to every channel (settings alternate; median of ``repeats``). CPU is
    ``time.process_time`` over the writes and 0.3 s after them (the server's sending threads
    included); per message of the batch."""
    import math

    import numpy as np

    from cobelrun.io.live import LiveSink
    from cobelrun.io.mcap import STEP_NS, McapRecorder

    rng = np.random.default_rng(0)
    headings = rng.choice([0.0, math.pi / 2, math.pi, -math.pi / 2], poses)
    p = np.column_stack([rng.integers(0, 11, poses), rng.integers(0, 11, poses), headings])
    start = 1_763_900_000_000_000_000
    t = start + np.arange(poses, dtype=np.int64) * STEP_NS
    per = poses // trials
    steps = np.full(trials, per - 1)
    trial = np.arange(1, trials + 1)
    t0s = t[::per][:trials]
    t1s = t0s + (per - 1) * STEP_NS
    zeros = np.zeros(trials, dtype=np.int64)
    reward = rng.random(trials)
    n_messages = poses + 2 * trials + 1
    samples: dict[str, list[tuple[float, float]]] = {s: [] for s in SETTINGS}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeats):
            for setting in SETTINGS:
                live, client = [], None
                if setting != "off":
                    port = free_port()
                    live = [LiveSink(port=port)]
                rec = McapRecorder(Path(tmp) / f"{setting}_{i}.mcap", start_ns=start, live=live)
                if setting == "live_one_client":
                    rec.prepare_run(0)
                    client = subprocess.Popen([sys.executable, "-c", client_code(), str(port)],
                                              stdout=subprocess.PIPE, text=True)  # fmt: skip
                    live[0].wait_for_client(60)
                    time.sleep(0.5)  # its subscriptions to every channel are in
                c0, w0 = time.process_time(), time.perf_counter()
                rec.write_poses(0, t, p)
                rec.write_trial_events(0, trial, "training", t0s, t1s, zeros, zeros, steps, reward)
                rec.write_trial_table(0, "training", 1, start, steps, reward, zeros, zeros,
                                      np.ones(trials, bool))  # fmt: skip
                wall = time.perf_counter() - w0
                time.sleep(0.3)
                cpu = time.process_time() - c0
                rec.close()
                if client is not None:
                    client.communicate(timeout=60)
                samples[setting].append((cpu, wall))
    out = {}
    for setting, v in samples.items():
        cpu = statistics.median(c for c, _ in v)
        wall = statistics.median(w for _, w in v)
        out[setting] = {"cpu_us_per_message": 1e6 * cpu / n_messages,
                        "wall_us_per_message": 1e6 * wall / n_messages}  # fmt: skip
    base = out["off"]["cpu_us_per_message"]
    print(f"\nstream only ({poses} poses, {trials} trials: {n_messages} messages), median of "
          f"{repeats}")  # fmt: skip
    for setting, r in out.items():
        r["cpu_ratio"] = r["cpu_us_per_message"] / base
        print(f"{setting:16s} CPU {r['cpu_us_per_message']:6.2f} us/message (x{r['cpu_ratio']:.2f})"
              f", calling thread {r['wall_us_per_message']:6.2f} us/message")  # fmt: skip
    return out


def paired_ratios(samples: dict[str, list[dict[str, float]]]) -> dict[str, dict[str, Any]]:
    """Each setting against "off" of the same repeat (run back to back, so that machine load
    hits both alike): per key, the median, min and max of the per-repeat ratios, and the
    spread of "off" itself (max / min over the repeats), printed and returned."""
    keys = ("run_s", "phases_s", "run_cpu_s", "process_cpu_s")
    off = samples["off"]
    out: dict[str, dict[str, Any]] = {}
    print("\nper repeat, against off of the same repeat: median [min, max] of the ratios")
    spread = {k: max(x[k] for x in off) / min(x[k] for x in off) for k in keys
              if min(x[k] for x in off) > 0}  # fmt: skip
    print("off itself, max/min over repeats: " + ", ".join(
        f"{k} x{v:.2f}" for k, v in spread.items()))  # fmt: skip
    out["off_spread"] = spread
    for setting, rows in samples.items():
        if setting == "off":
            continue
        out[setting] = {}
        parts = []
        for k in keys:
            r = [a[k] / b[k] for a, b in zip(rows, off, strict=True) if b[k] > 0]
            if not r:
                continue
            med, lo, hi = statistics.median(r), min(r), max(r)
            out[setting][k] = {"median": med, "min": lo, "max": hi, "ratios": r}
            parts.append(f"{k} x{med:.3f} [{lo:.3f}, {hi:.3f}]")
        print(f"{setting:16s} " + "; ".join(parts))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--micro-only", action="store_true", help="only the stream's own cost")
    ap.add_argument("extra", nargs="*", help="more overrides for every run")
    opts = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    stream = micro(max(opts.repeats, 5))
    if opts.micro_only:
        return
    samples: dict[str, list[dict[str, float]]] = {s: [] for s in SETTINGS}
    with tempfile.TemporaryDirectory() as tmp:
        run_once("off", 1, opts.extra, Path(tmp) / "warmup")  # numba's cache, page cache
        for i in range(opts.repeats):
            for setting in SETTINGS:
                out = Path(tmp) / f"{setting}_{i}"
                samples[setting].append(run_once(setting, opts.runs, opts.extra, out))
                print(f"  {setting:16s} #{i}: " + ", ".join(
                    f"{k} {v:.3f}" for k, v in samples[setting][-1].items()), flush=True)  # fmt: skip
    rows = {s: {k: statistics.median(x[k] for x in v) for k in v[0]} for s, v in samples.items()}
    base = rows["off"]
    print(f"\ncobel run {' '.join(TASK)} task.runs={opts.runs} {' '.join(opts.extra)}; "
          f"median of {opts.repeats}")  # fmt: skip
    print(f"{'setting':16s} {'run [s]':>8s} {'ratio':>6s} {'phases [s]':>10s} {'ratio':>6s} "
          f"{'run CPU [s]':>11s} {'ratio':>6s} {'process CPU [s]':>15s} {'+CPU/run':>8s} "
          f"{'messages':>9s} {'MB':>6s}")  # fmt: skip
    for s, r in rows.items():
        r["run_ratio"] = r["run_s"] / base["run_s"]
        r["phases_ratio"] = r["phases_s"] / base["phases_s"] if base["phases_s"] else float("nan")
        r["run_cpu_ratio"] = r["run_cpu_s"] / base["run_cpu_s"]
        # extra CPU of the whole process (the server's threads included) per second of run
        r["extra_cpu_per_run_s"] = (r["process_cpu_s"] - base["process_cpu_s"]) / base["run_s"]
        print(f"{s:16s} {r['run_s']:8.3f} {r['run_ratio']:6.3f} {r['phases_s']:10.3f} "
              f"{r['phases_ratio']:6.3f} {r['run_cpu_s']:11.3f} {r['run_cpu_ratio']:6.3f} "
              f"{r['process_cpu_s']:15.3f} {r['extra_cpu_per_run_s']:8.3f} "
              f"{r['messages']:9.0f} {r['mbytes']:6.1f}")  # fmt: skip
    paired = paired_ratios(samples)
    out = HERE / "results" / "live.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"task": TASK, "runs": opts.runs, "extra": opts.extra,
                               "repeats": opts.repeats, "median": rows, "stream": stream,
                               "paired": paired, "samples": samples}, indent=2))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
