"""Tests of ``run.mcap``: McapRecorder (foxglove-sdk protobuf channels) and repair_mcap."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from cobelrun.envs.base import Geometry
from cobelrun.envs.gridworld import GridWorldEnv
from cobelrun.envs.world import from_layout
from cobelrun.io.mcap import McapRecorder
from cobelrun.io.mcap_repair import repair_mcap

START = 1_763_900_000_123_456_789  # 2025-11-23, a run's wall-clock start


def read(path: Path) -> list[tuple[str, str, int, Any]]:
    """(topic, schema name, log time, decoded message) of every message, through the indexed
    reader with CRCs checked; protobuf decoded with the schemas stored in the file."""
    factory = DecoderFactory()
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary() is not None
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                decoded: Any = json.loads(message.data)
            else:
                assert channel.message_encoding == "protobuf"
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                decoded = decoder(message.data)
            out.append((channel.topic, schema.name, message.log_time, decoded))
    return out


def grid_geometry() -> Geometry:
    env = GridWorldEnv(world=from_layout("S.#\n..G"))
    return env.geometry()


# --------------------------------------------------------------------------- round trip
def test_poses_trials_images_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    poses = np.array([[0.0, 0.0, math.pi / 2], [1.0, 0.0, 0.0], [1.0, -1.0, -math.pi / 2],
                      [2.5, 3.25, math.pi], [2.5, 3.25, 3.0]])  # fmt: skip
    t = START + np.arange(5, dtype=np.int64) * 100_000_000
    with McapRecorder(path, start_ns=START, metadata={"seed": "7", "mcap_runs": "0,1"}) as rec:
        rec.write_poses(0, t, poses)
        rec.write_poses(1, t[:2], poses[:2] + 10)
        rec.write_trial_events(
            0, np.array([1, 2]), "acquisition", t[[0, 2]], t[[1, 4]],
            start_state=np.array([0, 3]), end_state=np.array([3, 5]), steps=np.array([1, 2]),
            reward=np.array([1.0, 0.0]), response=np.array([1, 0], np.int8),
        )  # fmt: skip
        rec.write_trial_events(
            1, np.array([1]), 'ext"inction', t[[0]], t[[1]], start_state=np.array([0]),
            end_state=np.array([3]), steps=np.array([1]), reward=np.array([-0.5]),
        )  # fmt: skip
        img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
        rec.write_image(0, int(t[1]), img)
    msgs = read(path)

    pose_msgs = [m for m in msgs if m[0] == "/run_0000/pose"]
    assert [m[1] for m in pose_msgs] == ["foxglove.PoseInFrame"] * 5
    assert [m[2] for m in pose_msgs] == t.tolist()
    for (_, _, lt, p), (x, y, h) in zip(pose_msgs, poses, strict=True):
        assert p.frame_id == "maze"
        assert p.timestamp.seconds * 10**9 + p.timestamp.nanos == lt
        assert (p.pose.position.x, p.pose.position.y, p.pose.position.z) == (x, y, 0.0)
        q = p.pose.orientation
        assert q.x == 0 and q.y == 0
        assert q.z == pytest.approx(math.sin(h / 2)) and q.w == pytest.approx(math.cos(h / 2))
        back = 2 * math.atan2(q.z, q.w)
        assert math.isclose(math.remainder(back - h, 2 * math.pi), 0.0, abs_tol=1e-12)
    run1 = [m[3].pose.position.x for m in msgs if m[0] == "/run_0001/pose"]
    assert run1 == [10.0, 11.0]

    events = [m for m in msgs if m[0] == McapRecorder.TRIAL_TOPIC]
    assert {m[1] for m in events} == {"cobel.TrialEvent"}
    ev0 = [m[3] for m in events if m[3]["run"] == 0]
    assert [(e["event"], e["trial"]) for e in ev0] == [("start", 1), ("end", 1), ("start", 2),
                                                       ("end", 2)]  # fmt: skip
    assert [e["response"] for e in ev0 if e["event"] == "end"] == [1, 0]
    assert ev0[1] == {"event": "end", "steps": 1, "reward": 1.0, "end_state": 3, "response": 1,
                      "run": 0, "trial": 1, "phase": "acquisition"}  # fmt: skip
    assert ev0[0]["start_state"] == 0 and ev0[2]["start_state"] == 3
    assert [m[2] for m in events if m[3]["run"] == 0] == t[[0, 1, 2, 4]].tolist()
    ev1 = [m[3] for m in events if m[3]["run"] == 1]
    assert ev1[1]["phase"] == 'ext"inction' and "response" not in ev1[1]
    assert ev1[1]["reward"] == -0.5

    (cam,) = [m for m in msgs if m[0] == "/run_0000/camera"]
    assert cam[1] == "foxglove.RawImage" and cam[2] == t[1]
    im = cam[3]
    assert (im.width, im.height, im.encoding, im.step) == (6, 4, "rgb8", 18)
    assert np.array_equal(np.frombuffer(im.data, np.uint8).reshape(4, 6, 3), img)

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        chans = {c.topic: c for c in summary.channels.values()}
        assert chans["/run_0001/pose"].metadata == {"run": "1"}
        schema = summary.schemas[chans["/trial"].schema_id]
        assert "1-based" in json.loads(schema.data)["properties"]["trial"]["description"]
        (meta,) = list(reader.iter_metadata())
    assert meta.name == "cobel"
    assert meta.metadata == {"seed": "7", "mcap_runs": "0,1", "start_ns": str(START)}


def test_log_time_defaults_to_now(tmp_path: Path) -> None:
    before = time.time_ns()
    rec = McapRecorder(tmp_path / "run.mcap", geometry=grid_geometry())
    after = time.time_ns()
    rec.close()
    assert before <= rec.start_ns <= after
    (scene,) = read(tmp_path / "run.mcap")
    assert scene[0] == "/maze" and scene[2] == rec.start_ns
    assert scene[2] > 1_700_000_000 * 10**9  # not 1970


# --------------------------------------------------------------------------- scene
def _entities(path: Path) -> dict[str, Any]:
    (scene,) = [m for m in read(path) if m[0] == "/maze"]
    assert scene[1] == "foxglove.SceneUpdate"
    ents = {e.id: e for e in scene[3].entities}
    assert all(e.frame_id == "maze" for e in ents.values())
    return ents


def test_scene_of_a_grid(tmp_path: Path) -> None:
    geo = grid_geometry()
    path = tmp_path / "run.mcap"
    McapRecorder(path, geometry=geo, start_ns=START).close()
    ents = _entities(path)
    assert set(ents) == {"floor", "walls", "regions"}
    assert len(ents["floor"].cubes) == len(geo.cells) == 5
    floor = sorted((c.pose.position.x, c.pose.position.y) for c in ents["floor"].cubes)
    assert floor == sorted(map(tuple, geo.cells.tolist()))
    walls = ents["walls"].cubes
    assert len(walls) == len(geo.walls) > 0
    for cube, (x0, y0, x1, y1) in zip(walls, geo.walls, strict=True):
        assert cube.pose.position.x == pytest.approx((x0 + x1) / 2)
        assert cube.pose.position.y == pytest.approx((y0 + y1) / 2)
        assert cube.size.z > 0 and cube.size.x == pytest.approx(
            math.hypot(x1 - x0, y1 - y0), abs=0.1
        )
        angle = 2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w)
        assert math.isclose(abs(math.sin(angle)), abs(y1 - y0) / math.hypot(x1 - x0, y1 - y0))
    names = {t.text for t in ents["regions"].texts}
    assert names == set(geo.regions) and {"goal"} <= names
    goal = geo.regions["goal"]
    spots = [(c.pose.position.x, c.pose.position.y) for c in ents["regions"].cylinders]
    assert (goal["x"], goal["y"]) in spots and len(spots) == len(geo.regions)
    with open(path, "rb") as f:
        (att,) = make_reader(f).get_summary().attachment_indexes
    assert att.name == "geometry.json"


def test_scene_of_a_graph_and_an_arena(tmp_path: Path) -> None:
    graph = Geometry(
        kind="graph",
        bounds=(0, 0, 2, 1),
        nodes=[[0, 0], [1, 0], [2, 1]],
        edges=[[0, 1], [1, 2]],
        regions={"goal": {"shape": "point", "x": 2, "y": 1}},
    )
    McapRecorder(tmp_path / "g.mcap", geometry=graph, start_ns=START).close()
    ents = _entities(tmp_path / "g.mcap")
    assert len(ents["graph"].spheres) == 3
    (edges,) = ents["graph"].lines
    assert [(p.x, p.y) for p in edges.points] == [(0, 0), (1, 0), (1, 0), (2, 1)]
    arena = Geometry(kind="arena", bounds=(-1, -1, 1, 1), outline=[[-1, -1], [1, -1], [1, 1], [-1, 1]],
                     regions={"platform": {"shape": "circle", "x": 0.5, "y": 0.5, "radius": 0.1},
                              "zone": {"shape": "polygon", "points": [[0, 0], [1, 0], [0, 1]]}})  # fmt: skip
    McapRecorder(tmp_path / "a.mcap", geometry=arena, start_ns=START).close()
    ents = _entities(tmp_path / "a.mcap")
    (outline,) = ents["floor"].lines
    assert len(outline.points) == 4
    (cyl,) = ents["regions"].cylinders
    assert cyl.size.x == pytest.approx(0.2)
    assert len(ents["regions"].lines[0].points) == 3
    assert {t.text for t in ents["regions"].texts} == {"platform", "zone"}


# --------------------------------------------------------------------------- errors, lifecycle
def test_bad_input_fails_clearly(tmp_path: Path) -> None:
    with McapRecorder(tmp_path / "run.mcap", start_ns=START) as rec:
        t = np.array([START, START + 1])
        with pytest.raises(ValueError, match=r"poses must have shape \(k, 3\)"):
            rec.write_poses(0, t, np.zeros((2, 2)))
        with pytest.raises(ValueError, match="finite"):
            rec.write_poses(0, t, np.array([[0, 0, 0], [np.nan, 0, 0]]))
        with pytest.raises(ValueError, match="integer nanoseconds"):
            rec.write_poses(0, t.astype(float), np.zeros((2, 3)))
        with pytest.raises(ValueError, match=r"t_ns must have shape \(2,\)"):
            rec.write_poses(0, t[:1], np.zeros((2, 3)))
        one = np.array([1])
        with pytest.raises(ValueError, match="1-based"):
            rec.write_trial_events(0, np.array([0]), "a", t[:1], t[:1], one, one, one, [1.0])
        with pytest.raises(ValueError, match="finite"):
            rec.write_trial_events(0, one, "a", t[:1], t[:1], one, one, one, [np.inf])
        with pytest.raises(ValueError, match="response"):
            rec.write_trial_events(0, one, "a", t[:1], t[:1], one, one, one, [1.0], ["x"])
        two, yes = np.array([3, 4]), np.array([True, False])
        with pytest.raises(ValueError, match="1-based"):
            rec.write_trial_table(0, "a", 0, START, two, [0.0, 1.0], two, two, yes)
        with pytest.raises(ValueError, match="reward must be"):
            rec.write_trial_table(0, "a", 1, START, two, [0.0, np.nan], two, two, yes)
        with pytest.raises(ValueError, match="end_state must be"):
            rec.write_trial_table(0, "a", 1, START, two, [0.0, 1.0], two, one, yes)
        with pytest.raises(ValueError, match="steps must be 1-D"):
            rec.write_trial_table(0, "a", 1, START, np.zeros((2, 2), int), [0.0], two, two, yes)
        with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
            rec.write_image(0, START, np.zeros((4, 4), np.uint8))
        rec.write_poses(0, t[:0], np.zeros((0, 3)))  # empty: nothing written
    assert read(tmp_path / "run.mcap") == []
    bad = Geometry(kind="arena", bounds=(0, 0, 1, 1), regions={"goal": {"shape": "circle"}})
    with pytest.raises(KeyError):
        McapRecorder(tmp_path / "bad.mcap", geometry=bad)
    assert read(tmp_path / "bad.mcap") == []  # closed, complete, readable


def test_close_is_idempotent_and_final(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path / "run.mcap", start_ns=START)
    rec.write_poses(0, np.array([START]), np.zeros((1, 3)))
    rec.close()
    rec.close()
    assert rec.closed
    with rec:
        pass
    with pytest.raises(ValueError, match="closed"):
        rec.write_poses(0, np.array([START]), np.zeros((1, 3)))
    assert len(read(tmp_path / "run.mcap")) == 1
    assert repair_mcap(tmp_path / "run.mcap") is False


def test_readable_after_exception(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with pytest.raises(KeyboardInterrupt), McapRecorder(path, start_ns=START) as rec:
        rec.write_poses(0, START + np.arange(10), np.zeros((10, 3)))
        raise KeyboardInterrupt
    assert len(read(path)) == 10


def _write_many(path: Path, n: int, chunk_size: int) -> list[tuple[int, float]]:
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.integers(0, 9, n), rng.integers(0, 5, n), rng.uniform(-3, 3, n)])
    t = START + np.arange(n, dtype=np.int64) * 1000
    with McapRecorder(path, geometry=grid_geometry(), start_ns=START, chunk_size=chunk_size) as r:
        for i in range(0, n, 500):
            r.write_poses(0, t[i : i + 500], poses[i : i + 500])
            r.write_trial_events(0, np.array([i // 500 + 1]), "a", t[i : i + 1],
                                 t[i + 499 : i + 500], *([np.array([1])] * 3), np.array([0.0]))  # fmt: skip
    return list(zip(t.tolist(), poses[:, 0].tolist(), strict=True))


def _poses_of(msgs: list[tuple[str, str, int, Any]]) -> list[tuple[int, float]]:
    return [(m[2], m[3].pose.position.x) for m in msgs if m[0] == "/run_0000/pose"]


def test_repair_truncated_copies(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    expected = _write_many(full, 3000, chunk_size=16_384)
    data = full.read_bytes()
    with open(full, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    ends = sorted((c.chunk_start_offset + c.chunk_length, c.message_end_time) for c in chunks)
    assert len(ends) >= 4
    for cut in [ends[1][0] + 9, ends[2][0] + 3000, ends[-1][0] - 10, len(data) - 20]:
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        with open(part, "rb") as f, pytest.raises(Exception):  # noqa: B017 - any reader error
            list(make_reader(f).iter_messages())
        assert repair_mcap(part) is True
        assert repair_mcap(part) is False
        msgs = read(part)
        got = _poses_of(msgs)
        assert got == expected[: len(got)]  # complete messages only, in order, no gaps
        assert msgs[0][0] == "/maze"
        # every pose of a chunk that ended before the cut is there (poses are in time order)
        last = max(t for end, t in ends if end <= cut)
        assert len(got) >= sum(1 for t, _ in expected if t <= last)
    assert not list(tmp_path.glob("*.repair"))


def test_repair_rejects_non_mcap(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap at all")
    with pytest.raises(ValueError, match="not an MCAP"):
        repair_mcap(bad)


_WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from cobelrun.io.mcap import McapRecorder
    from cobelrun.envs.base import Geometry
    path, start, n_flushed, n_more = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    x = np.arange(n_flushed + n_more, dtype=float)
    poses = np.column_stack([x % 11, x % 7, x / 100])
    t = start + np.arange(len(x), dtype=np.int64) * 1000
    rec = McapRecorder(path, start_ns=start, geometry=Geometry(kind="graph", bounds=(0, 0, 1, 1),
                       nodes=[[0, 0], [1, 1]], edges=[[0, 1]]))
    rec.write_poses(0, t[:n_flushed], poses[:n_flushed])
    rec.flush()
    rec.write_poses(0, t[n_flushed:], poses[n_flushed:])  # not flushed: in a chunk being written
    print("written", flush=True)
    sys.stdin.read()  # wait to be killed
    """
)


def _messages_in_complete_chunks(path: Path) -> int:
    """Messages in the chunks of an unfinished MCAP that were written completely."""
    from mcap.stream_reader import StreamReader, breakup_chunk

    n = 0
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, emit_chunks=True).records:
                if type(rec).__name__ == "Chunk":
                    n += sum(type(r).__name__ == "Message" for r in breakup_chunk(rec))
        except Exception:  # the file breaks off
            pass
    return n


def test_repair_after_sigkill(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    n_flushed, n_more = 2000, 40_000  # 2 full 1 MiB chunks after the flush, then a partial one
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path), str(START), str(n_flushed), str(n_more)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "written"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    killed = tmp_path / "killed.mcap"
    shutil.copy(path, killed)
    with open(killed, "rb") as f, pytest.raises(Exception):  # noqa: B017
        list(make_reader(f).iter_messages())
    in_chunks = _messages_in_complete_chunks(killed)
    assert repair_mcap(path) is True
    with open(path, "rb") as f:
        raw = [(c.topic, m) for _, c, m in make_reader(f, validate_crcs=True).iter_messages()]
    assert raw[0][0] == "/maze"
    poses = [m for topic, m in raw if topic == "/run_0000/pose"]
    # everything flushed survives, in order, and then a prefix of the rest: whole chunks and
    # the complete messages of the chunk being written when the process was killed
    assert len(raw) > in_chunks > n_flushed
    assert len(poses) < n_flushed + n_more
    assert [m.log_time for m in poses] == (START + np.arange(len(poses)) * 1000).tolist()
    assert [m.sequence for m in poses] == list(range(1, len(poses) + 1))
    x = np.arange(n_flushed + n_more, dtype=float)
    factory = DecoderFactory()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        for schema, channel, m in reader.iter_messages(topics=["/run_0000/pose"]):
            i = (m.log_time - START) // 1000
            if i % 97 == 0 or i == len(poses) - 1:  # decode a sample
                p = factory.decoder_for(channel.message_encoding, schema)(m.data)
                assert (p.pose.position.x, p.pose.position.y) == (x[i] % 11, x[i] % 7)
