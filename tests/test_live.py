"""The live view (``cobel run --live``): foxglove-sdk's WebSocket server fed by the same log
calls as ``run.mcap``, watched by a real client (tests/live_client.py, its own process)."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from cobelrun.io.live import LAYOUTS, LiveSink, layout_texts
from cobelrun.io.mcap import McapRecorder
from cobelrun.io.validate import check_mcap
from tests.inprocess import cli  # noqa: F401  (fixture)

CLIENT = Path(__file__).with_name("live_client.py")
#: a short gridworld run: 2 runs of 5 trials of at most 30 steps
SHORT = ["task=gridworld", "task.runs=2", "task.protocol.phases.0.trials=5",
         "task.protocol.max_steps=30", "env=open_field"]  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _run_dir(stdout: str) -> Path:
    return Path(stdout.strip().splitlines()[-1])


def _topics(path: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        for _, channel, _ in make_reader(f, validate_crcs=True).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


@pytest.mark.slow  # timing: on a loaded machine (xdist) the run can outpace the client's
# subscriptions; test_series_reach_a_client_in_trial_order checks a real client deterministically
def test_live_run_streams_to_a_client(cli, tmp_path: Path) -> None:  # noqa: F811
    """A run with --live on a free port: a real client connecting while it goes gets the
    channel advertisements, the maze, poses and trial events; run.mcap is as without --live."""
    port = _free_port()
    client = subprocess.Popen([sys.executable, str(CLIENT), str(port), "60"],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        # 40 trials per run: the phase goes in pieces (the first of 8 trials), so the poses of
        # later pieces reach the client after it subscribed to the run's pose channel (the
        # first piece's may go out before its subscription arrives on a loaded machine)
        proc = cli("run", *SHORT, "task.protocol.phases.0.trials=40", "--port", str(port),
                   "task.record.live_wait=60",
                   "task.record.flush_seconds=0.05")  # fmt: skip
        out, _ = client.communicate(timeout=60)
    finally:
        client.kill()
    assert proc.returncode == 0, proc.stderr
    assert f"live view on ws://127.0.0.1:{port}" in proc.stderr
    got = json.loads(out)
    ch = got["channels"]
    assert ch["/maze"] == "foxglove.SceneUpdate"
    assert ch["/trial"] == "cobel.TrialEvent"
    assert ch["/trial_series"] == "cobel.TrialSeries"
    assert ch["/run_0000/pose"] == "foxglove.PoseInFrame"
    assert got["counts"].get("/maze", 0) >= 1  # latched: sent on subscribe
    # poses: a run's pose channel is advertised when the run starts, and its first piece's
    # poses may be sent before the client's subscription arrives; on a loaded machine the
    # run can even end first. test_series_reach_a_client_in_trial_order checks that they
    # reach a subscribed client.
    event = got["first"]["/trial"]
    assert event["run"] == 0 and event["trial"] >= 1 and event["event"] in ("start", "end")
    # the client left after its messages (said in one line if the server saw it before the
    # run ended; foxglove-sdk's own log lines are not shown); the run finished its files
    lines = proc.stderr.splitlines()
    assert sum("stopped watching" in ln for ln in lines) <= 1
    assert not [ln for ln in lines if "client" in ln.lower() and not ln.startswith("cobel: ")]
    run_dir = _run_dir(proc.stdout)
    check_mcap(run_dir / "run.mcap")
    topics = _topics(run_dir / "run.mcap")
    assert "/trial_series" not in topics  # live only
    assert topics["/trial"] == 2 * 2 * 40  # start and end of every trial of both runs
    assert (run_dir / "trials.parquet").is_file()


def test_series_reach_a_client_in_trial_order(tmp_path: Path, capfd) -> None:
    """/trial_series: one message per trial, at the trial's end on the pose clock; the client
    leaving is one line and the stream goes on."""
    port = _free_port()
    sink = LiveSink(port=port)
    rec = McapRecorder(tmp_path / "run.mcap", start_ns=10**18, live=[sink])
    client = subprocess.Popen([sys.executable, str(CLIENT), str(port), "5"],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert sink.wait_for_client(30)
        steps = np.array([3, 1, 4])
        for _ in range(40):  # until the client subscribed to /trial_series too
            rec.write_trial_table(0, "training", 1, 10**18, steps, np.array([0.0, 1.0, 0.5]),
                                  np.zeros(3, int), np.ones(3, int), np.array([1, 1, 0], bool))  # fmt: skip
            rec.write_trial_events(0, np.array([1]), "training", np.array([10**18]),
                                   np.array([10**18 + 1]), np.array([0]), np.array([1]),
                                   np.array([3]), np.array([0.0]))  # fmt: skip
            rec.write_poses(0, np.array([10**18]), np.zeros((1, 3)))
            if client.poll() is not None:
                break
            time.sleep(0.05)
        out, _ = client.communicate(timeout=30)
        said = ""
        for _ in range(100):  # the server sees the connection close
            said += capfd.readouterr().err
            if "stopped watching" in said:
                break
            time.sleep(0.05)
        rec.write_poses(0, np.array([10**18 + 50]), np.zeros((1, 3)))  # nobody watches: fine
    finally:
        client.kill()
        rec.close()
    said += capfd.readouterr().err
    assert said.count("stopped watching") == 1
    assert re.search(rf"cobel: live view: client \d+ is watching ws://127.0.0.1:{port}\n", said)
    got = json.loads(out)
    assert got["counts"].get("/run_0000/pose", 0) >= 1  # poses reach a subscribed client
    first = got["first"]["/trial_series"]
    assert first == {"run": 0, "trial": 1, "phase": "training", "steps": 3, "reward": 0.0,
                     "terminated": True}  # fmt: skip
    times = got["log_times"]["/trial_series"][:3]
    step = 100_000_000
    assert times == [10**18 + 3 * step, 10**18 + 5 * step, 10**18 + 10 * step]
    assert "/trial_series" not in _topics(tmp_path / "run.mcap")


def test_port_in_use_is_one_line_and_the_run_completes(cli) -> None:  # noqa: F811
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        proc = cli("run", *SHORT, "--port", str(port))
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "live view" in ln]
    assert lines == [
        f"cobel: live view off: port {port} on 127.0.0.1 is in use (pick another with --port, "
        "or --port 0 for any free one); the run goes on"
    ]
    run_dir = _run_dir(proc.stdout)
    assert (run_dir / "trials.parquet").is_file() and (run_dir / "steps.parquet").is_file()
    check_mcap(run_dir / "run.mcap")


def test_bad_port_is_one_line(cli) -> None:  # noqa: F811
    proc = cli("run", *SHORT, "task.record.live=true", "task.record.live_port=70000")
    assert proc.returncode != 0
    assert "live_port" in proc.stderr and "65535" in proc.stderr


def test_layouts_ship_with_the_package() -> None:
    """The shipped layouts are what the builders make (python -c 'from cobelrun.io.live
    import write_layouts; write_layouts()' rewrites them) and show the live topics."""
    for name, text in layout_texts().items():
        assert (LAYOUTS / name).read_text(encoding="utf-8") == text, f"{name} is stale"
    fox = json.loads((LAYOUTS / "cobel-live.foxglove.json").read_text())
    assert fox["version"] == 1
    panels = fox["content"]["items"]
    maze = panels[0]["content"]
    assert maze["panelType"] == "ThreeDee" and maze["config"]["followTf"] == "maze"
    assert {"/maze", "/run_0000/pose", "/run_0009/pose"} <= set(maze["config"]["topics"])
    plots = [i["content"] for i in panels[1]["content"]["items"]]
    assert plots[0]["config"]["paths"][0]["value"] == "/trial_series.steps"
    lb = json.loads((LAYOUTS / "cobel-live.lichtblick.json").read_text())
    assert set(lb["configById"]) == {"3D!maze", "Plot!steps", "Plot!reward", "Image!camera",
                                     "RawMessages!trial"}  # fmt: skip
    leaves = []

    def walk(node: object) -> None:
        if isinstance(node, str):
            leaves.append(node)
        else:
            assert isinstance(node, dict)
            walk(node["first"])
            walk(node["second"])

    walk(lb["layout"])
    assert sorted(leaves) == sorted(lb["configById"])


@pytest.mark.parametrize("timeline", ["sequential", "per_run"])
def test_mcap_timeline(cli, timeline: str) -> None:  # noqa: F811
    """per_run: every run's poses start at the file's start, so runs play side by side."""
    proc = cli("run", *SHORT, f"task.record.mcap_timeline={timeline}")
    assert proc.returncode == 0, proc.stderr
    path = _run_dir(proc.stdout) / "run.mcap"
    check_mcap(path)
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["cobel"]
        for _, channel, message in reader.iter_messages(log_time_order=True):
            first.setdefault(channel.topic, message.log_time)
            last[channel.topic] = message.log_time
    start = int(meta["start_ns"])
    assert first["/run_0000/pose"] == start
    if timeline == "per_run":
        assert meta["timeline"] == "per_run"
        assert first["/run_0001/pose"] == start
    else:
        assert "timeline" not in meta
        assert first["/run_0001/pose"] > last["/run_0000/pose"]


def test_grids_round_trip(tmp_path: Path) -> None:
    """A monitor's maps (SceneGrid) as foxglove.Grid: float32 fields, row 0 at the lowest y."""
    from mcap_protobuf.decoder import DecoderFactory

    from cobelrun.monitors import SceneGrid

    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    b = np.full((2, 3), np.nan, np.float32)
    grid = SceneGrid(name="activity_analysis", trial=3, origin=(-1.0, 2.0), cell_size=(0.5, 0.25),
                     fields={"unit_00": a, "unit_01": b})  # fmt: skip
    with McapRecorder(tmp_path / "run.mcap", start_ns=10**18) as rec:
        rec.write_grids(2, [10**18 + 7], [grid])
        with pytest.raises(ValueError, match="times for"):
            rec.write_grids(2, [], [grid])
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        ((schema, channel, message, msg),) = list(reader.iter_decoded_messages())
    assert channel.topic == "/run_0002/activity_analysis" and schema.name == "foxglove.Grid"
    assert message.log_time == 10**18 + 7
    assert msg.column_count == 3 and msg.cell_stride == 8 and msg.row_stride == 24
    assert (msg.pose.position.x, msg.pose.position.y) == (-1.0, 2.0)
    assert (msg.cell_size.x, msg.cell_size.y) == (0.5, 0.25)
    assert [f.name for f in msg.fields] == ["unit_00", "unit_01"]
    data = np.frombuffer(msg.data, "<f4").reshape(2, 3, 2)
    assert np.array_equal(data[..., 0], a) and np.isnan(data[..., 1]).all()


@pytest.mark.slow  # ~20 s: a DQN on rendered panoramas
def test_place_cell_maps_reach_the_mcap(cli) -> None:  # noqa: F811
    """The activity-map monitor's snapshots go to run.mcap (and so to the live view) as grids,
    one per snapshot at its trial's end."""
    pytest.importorskip("stable_baselines3")
    tiny = ["task=place_cells", "task.runs=1", "task.protocol.phases.0.trials=3",
            "task.protocol.max_steps=8", "agent.learning_starts=4", "task.monitors.maps.every=2",
            "task.monitors.maps.grid=[6,5]", "task.record.mcap=true"]  # fmt: skip
    proc = cli("run", *tiny)
    assert proc.returncode == 0, proc.stderr
    path = _run_dir(proc.stdout) / "run.mcap"
    check_mcap(path)
    from mcap_protobuf.decoder import DecoderFactory

    times, poses = [], []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = ["/run_0000/activity_analysis", "/run_0000/pose"]
        for _, channel, message, msg in reader.iter_decoded_messages(topics, log_time_order=True):
            if channel.topic == "/run_0000/activity_analysis":
                times.append(message.log_time)
                assert msg.column_count == 6 and len(msg.fields) == 16
            elif channel.topic == "/run_0000/pose":
                poses.append(message.log_time)
    assert len(times) == 3  # trials 0 (before training), 2 and 3 (the last)
    assert times[0] == poses[0] and times[-1] == poses[-1]
