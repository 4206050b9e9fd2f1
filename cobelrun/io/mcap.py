"""``run.mcap``: a replay file that Foxglove opens, written with foxglove-sdk's typed channels.

Channels (all in the frame ``maze``, world units; see ``docs/mcap.md``)
-------------------------------------------------------------------------
``/maze``
    ``foxglove.SceneUpdate`` (protobuf), written once at the start: walls, free cells or arena
    outline, graph nodes and edges, and named regions (goals, starts, places) with labels.
``/run_NNNN/pose``
    ``foxglove.PoseInFrame`` (protobuf): the agent's position and heading (a rotation about +z)
    of run ``NNNN`` at every recorded step.
``/run_NNNN/camera``
    ``foxglove.RawImage`` (protobuf, ``rgb8``): camera frames, when the run records images.
``/run_NNNN/<name>``
    ``foxglove.SceneUpdate`` (protobuf): paths that monitors draw over the maze at a trial's
    start or end, e.g. ``/run_NNNN/replay``: each replay bout as highlighted line strips.
    ``foxglove.Grid`` (protobuf): maps that monitors show over the maze, e.g.
    ``/run_NNNN/activity_analysis``: a layer's units (a float32 field each) at each snapshot.
``/trial``
    ``cobel.TrialEvent`` (JSON, schema :data:`TRIAL_EVENT_SCHEMA`): one ``start`` and one ``end``
    event per trial of the runs kept in full, trials 1-based.
``/trials``
    ``cobel.TrialTable`` (protobuf, :data:`TRIAL_TABLE_PROTO`): the trials of every run, one
    message per run and phase (per piece of a long phase) with a packed column per field
    (steps, reward, start and end state, terminated, response), logged at its first trial's
    start.

Log times are nanoseconds since the Unix epoch, starting at the run's real wall-clock start
(``start_ns``), so Foxglove shows the date the run was made. The file is chunked (zstd, chunk
CRCs on); :meth:`McapRecorder.flush` closes the chunk in progress so that everything written so
far is on disk. A file left without its summary (the process was killed) is made readable again
by :func:`cobelrun.io.mcap_repair.repair_mcap`.

Sinks: one set of log calls, several destinations. A :class:`FoxgloveStream` builds each
message once and logs it on the channel of every :class:`FoxgloveSink` it feeds: the file
(:class:`McapSink`, ``run.mcap``) and the live view (:class:`cobelrun.io.live.LiveSink`,
foxglove-sdk's WebSocket server, ``task.record.live``). Each sink has a ``foxglove.Context``
of its own, so the file holds exactly what it held before a live view existed, while the live
view gets what it needs besides (the maze again for a client that connects late, and the
per-trial series on ``/trial_series``); a live channel no client subscribed to costs one check
per batch. :class:`McapRecorder` is the stream with the file sink (and optionally live ones).

Only public APIs are used: ``foxglove.open_mcap`` with a private ``foxglove.Context`` per file
(two recorders in one process never share channels), typed channels from ``foxglove.channels``,
messages from ``foxglove.messages``. The maze's scene is built by
:mod:`cobelrun.render.foxglove_scene`.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import foxglove
import numpy as np
from foxglove.channels import (
    GridChannel,
    PoseInFrameChannel,
    RawImageChannel,
    SceneUpdateChannel,
)
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import (
    Duration,
    Grid,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector2,
    Vector3,
)

from cobelrun.render.foxglove_scene import (
    FRAME_ID,
    PATH_COLORS,
    PATH_HEIGHT,
    scene_entities,
    scene_pose,
)


class _RepeatFilter(logging.Filter):
    """Lets each distinct message through once: on a full disk foxglove-sdk logs one warning
    per dropped message, hundreds of thousands of lines (those are dropped: the run's error
    line says the disk is full)."""

    def __init__(self, limit: int = 1000) -> None:
        super().__init__()
        self._seen: set[str] = set()
        self._limit = limit

    def filter(self, record: logging.LogRecord) -> bool:
        key = record.getMessage()
        if any(m in key for m in ("No space left on device", "Read-only file system",
                                  "AttemptedWriteAfterFail")):  # fmt: skip
            return False  # the run fails with one line that says so
        if key in self._seen:
            return False
        if len(self._seen) < self._limit:
            self._seen.add(key)
        return True


logging.getLogger("foxglove.log_sink_set").addFilter(_RepeatFilter())

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cobelrun.envs.base import Geometry
    from cobelrun.monitors import SceneGrid, ScenePath

__all__ = [
    "TIMELINES",
    "TRIAL_EVENT_SCHEMA",
    "TRIAL_SERIES_SCHEMA",
    "TRIAL_TABLE_PROTO",
    "FoxgloveSink",
    "FoxgloveStream",
    "McapRecorder",
    "McapSink",
    "heading_to_quaternion",
    "live_pose_indices",
    "per_run_cut",
]

#: ``task.record.mcap_timeline``: runs one after another on the log clock (``sequential``), or
#: every run's clock starting at the file's start (``per_run``: runs side by side)
TIMELINES = ("sequential", "per_run")

_NS_PER_S = 1_000_000_000

#: JSON schema of ``cobel.TrialEvent`` on ``/trial``.
TRIAL_EVENT_SCHEMA: dict[str, Any] = {
    "title": "cobel.TrialEvent",
    "description": "Start or end of one trial of a cobel run",
    "type": "object",
    "properties": {
        "event": {"type": "string", "enum": ["start", "end"]},
        "run": {"type": "integer", "description": "Run index (0-based, as in trials.parquet)"},
        "trial": {"type": "integer", "description": "Trial number, 1-based across phases"},
        "phase": {"type": "string", "description": "Protocol phase name"},
        "start_state": {"type": "integer", "description": "State the trial started in (start)"},
        "steps": {"type": "integer", "description": "Steps taken = escape latency (end)"},
        "reward": {"type": "number", "description": "Reward summed over the trial (end)"},
        "end_state": {"type": "integer", "description": "State the trial ended in (end)"},
        "response": {
            "type": "integer",
            "description": "Coded response of the trial (end; only when the task codes one)",
        },
    },
    "required": ["event", "run", "trial", "phase"],
}


#: JSON schema of ``cobel.TrialSeries`` on ``/trial_series`` (live view only): one message per
#: trial of every run, at the trial's end, for the Plot panel (``/trial_series.steps``).
TRIAL_SERIES_SCHEMA: dict[str, Any] = {
    "title": "cobel.TrialSeries",
    "description": "One trial of a cobel run: what trials.parquet gets, while the run goes",
    "type": "object",
    "properties": {
        "run": {"type": "integer", "description": "Run index (0-based, as in trials.parquet)"},
        "trial": {"type": "integer", "description": "Trial number, 1-based across phases"},
        "phase": {"type": "string", "description": "Protocol phase name"},
        "steps": {"type": "integer", "description": "Steps taken = escape latency"},
        "reward": {"type": "number", "description": "Reward summed over the trial"},
        "terminated": {"type": "boolean", "description": "false: the trial hit max_steps"},
        "response": {
            "type": "integer",
            "description": "Coded response of the trial (only when the task codes one)",
        },
    },
    "required": ["run", "trial", "phase", "steps", "reward", "terminated"],
}

#: ``cobel.TrialTable`` on ``/trials`` (protobuf; the file holds it as a FileDescriptorSet).
TRIAL_TABLE_PROTO = """\
syntax = "proto3";
package cobel;
import "google/protobuf/timestamp.proto";

// The trials of one phase of one run: one value per trial in each repeated field.
// Trial i (0-based) is trial number first_trial + i; it starts at timestamp +
// (sum(steps[:i]) + i) * 100 ms and ends steps[i] * 100 ms later (the pose clock).
message TrialTable {
  google.protobuf.Timestamp timestamp = 1;  // start of the phase's first trial
  uint32 run = 2;                           // run index, 0-based (as in trials.parquet)
  string phase = 3;                         // protocol phase name
  uint32 first_trial = 4;                   // 1-based, counted across phases
  repeated int64 steps = 5;                 // steps taken = escape latency
  repeated double reward = 6;               // reward summed over the trial
  repeated int64 start_state = 7;
  repeated int64 end_state = 8;
  repeated bool terminated = 9;             // false: the trial hit max_steps
  repeated int32 response = 10;             // coded response; empty if the task codes none
}
"""

_TRIAL_TABLE: tuple[Any, bytes] | None = None


def _trial_table_type() -> tuple[Any, bytes]:
    """The ``cobel.TrialTable`` message class and its FileDescriptorSet (built once, from
    descriptors equal to :data:`TRIAL_TABLE_PROTO`, through protobuf's public API)."""
    global _TRIAL_TABLE
    if _TRIAL_TABLE is None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2

        F = descriptor_pb2.FieldDescriptorProto
        proto = descriptor_pb2.FileDescriptorProto(
            name="cobel/trial_table.proto", package="cobel", syntax="proto3",
            dependency=["google/protobuf/timestamp.proto"],
        )  # fmt: skip
        msg = proto.message_type.add(name="TrialTable")
        fields = [("timestamp", F.TYPE_MESSAGE), ("run", F.TYPE_UINT32),
                  ("phase", F.TYPE_STRING), ("first_trial", F.TYPE_UINT32),
                  ("steps", F.TYPE_INT64), ("reward", F.TYPE_DOUBLE),
                  ("start_state", F.TYPE_INT64), ("end_state", F.TYPE_INT64),
                  ("terminated", F.TYPE_BOOL), ("response", F.TYPE_INT32)]  # fmt: skip
        for number, (name, typ) in enumerate(fields, start=1):
            repeated = number >= 5
            f = msg.field.add(name=name, number=number, type=typ,
                              label=F.LABEL_REPEATED if repeated else F.LABEL_OPTIONAL)  # fmt: skip
            if typ == F.TYPE_MESSAGE:
                f.type_name = ".google.protobuf.Timestamp"
        timestamp = descriptor_pb2.FileDescriptorProto()
        timestamp_pb2.DESCRIPTOR.CopyToProto(timestamp)
        pool = descriptor_pool.DescriptorPool()
        pool.Add(timestamp)
        pool.Add(proto)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("cobel.TrialTable"))
        fds = descriptor_pb2.FileDescriptorSet(file=[timestamp, proto]).SerializeToString()
        _TRIAL_TABLE = (cls, fds)
    return _TRIAL_TABLE


def heading_to_quaternion(heading_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation by ``heading_rad`` about +z as quaternion components ``(z, w)`` (x = y = 0).

    Parameters
    ----------
    heading_rad : array-like
        Heading angle(s) in radians, counter-clockwise from +x.

    Returns
    -------
    qz, qw : numpy.ndarray
        ``sin(h / 2)`` and ``cos(h / 2)``.
    """
    half = 0.5 * np.asarray(heading_rad, dtype=np.float64)
    return np.sin(half), np.cos(half)


def _timestamp(t_ns: int) -> Timestamp:
    sec, nsec = divmod(int(t_ns), _NS_PER_S)
    return Timestamp(sec, nsec)


def _json_string(text: str) -> str:
    """``text`` as a JSON string, safe inside a %-format (see :func:`_json_lines`)."""
    return json.dumps(str(text)).replace("%", "%%")


def _json_lines(fmt: str, columns: Sequence[Sequence[Any]]) -> list[bytes]:
    """One JSON object per row, the message payloads of ``/trial`` and ``/trial_series``.

    ``fmt`` is a %-format of one object whose fields take, in order, one value from each of
    ``columns`` (equal-length sequences; strings inside ``fmt`` through :func:`_json_string`).
    One format of the whole batch: ``json.dumps`` per message is ~5x slower."""
    n = len(columns[0]) if columns else 0
    if n == 0:
        return []
    rows = zip(*columns, strict=True)
    return ("\n".join([fmt] * n) % tuple(v for row in rows for v in row)).encode().split(b"\n")


def _check_times(t_ns: np.ndarray, n: int, what: str) -> np.ndarray:
    t = np.asarray(t_ns)
    if t.shape != (n,):
        raise ValueError(f"{what}: t_ns must have shape ({n},), got {t.shape}")
    if n and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"{what}: t_ns must be integer nanoseconds, got dtype {t.dtype}")
    t = t.astype(np.int64, copy=False)
    if n and t.min() < 0:
        raise ValueError(f"{what}: t_ns must be >= 0 (nanoseconds since the Unix epoch)")
    return t


#: this many poses of one batch (a piece of a phase) go to a live view, evenly spread, with the
#: last one and the arrivals of the last LIVE_TRIALS trials: they arrive at once, and the file
#: keeps every pose
LIVE_POSES = 256
#: and the events of at most this many trials of a batch, the last ones (``/trial_series``
#: still gets every trial)
LIVE_TRIALS = 64

#: height of monitors' maps above the floor (below the paths and the walls' tops)
GRID_HEIGHT = 0.01

#: simulated time per step on the log clock (100 ms; the pose clock of ``cobel.TrialTable``)
STEP_NS = 100_000_000


def live_pose_indices(k: int, arrivals: np.ndarray | None = None) -> np.ndarray | None:
    """Which of a batch's ``k`` poses a live view gets: all of them (None) up to
    :data:`LIVE_POSES`; else that many evenly spread, the last one, and the arrival poses
    (``arrivals``: indices of each trial's last pose) of the last :data:`LIVE_TRIALS` trials,
    so that a viewer sees every recent trial reach its end (the goal)."""
    if k <= LIVE_POSES:
        return None
    keep = np.linspace(0, k - 1, LIVE_POSES).round().astype(np.int64)
    if arrivals is not None and len(arrivals):
        last = np.asarray(arrivals, np.int64)[-LIVE_TRIALS:]
        if last.min() < 0 or last.max() >= k:
            raise ValueError(f"write_poses: arrivals must index the {k} poses")
        keep = np.concatenate([keep, last])
    return np.unique(keep)


def per_run_cut(start_ns: int, run_clocks_ns: Mapping[int, int]) -> Any:
    """Where to cut each message of a ``per_run`` timeline's MCAP when a resumed run joins
    the stopped process's file with its own (:func:`cobelrun.io.mcap_repair.join_mcap`).

    With ``task.record.mcap_timeline=per_run`` every run's clock starts at ``start_ns``, so
    no single time separates what was written before a checkpoint from what came after; each
    run's clock at the checkpoint (``run_clocks_ns``, the recorder's watermark) does. A
    message of run ``r`` (its ``/run_NNNN/...`` topic, or the ``run`` field of a
    ``/trial`` event or a ``/trials`` table) is cut at ``start_ns + run_clocks_ns[r]`` (0
    for a run not started by then); the scene on ``/maze``, logged once at ``start_ns``, is
    taken from the first file; other topics are kept from both.

    Returns
    -------
    callable
        ``cut(topic, data) -> int | None``: the log time from which a message is the
        resumed process's.
    """
    start = int(start_ns)
    clocks = {int(r): int(ns) for r, ns in run_clocks_ns.items()}

    def at(run: int) -> int:
        return start + clocks.get(int(run), 0)

    def cut(topic: str, data: bytes) -> int | None:
        if topic.startswith("/run_"):
            head = topic[5:].split("/", 1)[0]
            return at(int(head)) if head.isdigit() else None
        if topic == FoxgloveStream.TRIAL_TOPIC:
            return at(json.loads(data)["run"])
        if topic == FoxgloveStream.TRIALS_TOPIC:
            return at(_trial_table_type()[0].FromString(data).run)
        if topic == FoxgloveStream.SCENE_TOPIC:
            return start + 1
        return None

    return cut


class FoxgloveSink:
    """A destination of a :class:`FoxgloveStream`'s messages: a ``foxglove.Context`` of its
    own with one foxglove-sdk sink attached (an MCAP file, a WebSocket server).

    Subclasses attach the SDK sink to :attr:`context`; the stream creates its channels there.
    """

    #: a live sink logs a channel only while a client subscribes to it, gets the live-only
    #: topics (``/trial_series``), and sees the maze again when a client subscribes late
    live: bool = False

    def __init__(self) -> None:
        self.context = foxglove.Context()
        self._closed = False

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def write_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """A metadata record (files keep it; a live view has nowhere to keep it)."""

    def attach(self, *, log_time: int, name: str, media_type: str, data: bytes) -> None:
        """An attachment (files keep it; a live view has nowhere to keep it)."""

    def latch(self, channel: Any, message: Any, log_time: int) -> None:
        """``message`` is the state of ``channel`` (the maze): a live sink logs it again for
        every client that subscribes later."""

    def flush(self) -> None:
        """Make what was logged so far durable (files) or sent (live); a no-op by default."""

    def close(self) -> None:
        """Finish the sink; idempotent."""
        self._closed = True


class McapSink(FoxgloveSink):
    """``run.mcap`` as a sink: ``foxglove.open_mcap`` on the sink's context (zstd chunks, chunk
    CRCs, compressed on the calling thread).

    Parameters
    ----------
    path : path-like
        File to write (replaced if it exists).
    chunk_size : int, default 1 MiB
        Target uncompressed chunk size.
    """

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = 1 << 20) -> None:
        super().__init__()
        self._closed = True
        self.path = Path(path)
        options = MCAPWriteOptions(
            compression=MCAPCompression.Zstd,
            chunk_size=int(chunk_size),
            compression_threads=0,  # compress on the calling thread (cores are shared)
        )
        self._writer = foxglove.open_mcap(
            self.path, allow_overwrite=True, context=self.context, writer_options=options
        )
        self._closed = False

    def write_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        self._writer.write_metadata(name, dict(metadata))

    def attach(self, *, log_time: int, name: str, media_type: str, data: bytes) -> None:
        self._writer.attach(log_time=log_time, create_time=log_time, name=name,
                            media_type=media_type, data=data)  # fmt: skip

    def flush(self) -> None:
        """Close the chunk in progress and flush it to the file: everything written so far is
        readable after a crash (with :func:`repair_mcap`). Frequent flushes compress worse."""
        if not self._closed:
            self._writer.flush()

    def close(self) -> None:
        """Write the last chunk, the summary and the footer; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.close()
        finally:
            # a writer whose close failed (a full disk) is dropped now, while Python runs:
            # foxglove-sdk's writer logs from its destructor, which panics at interpreter exit
            self._writer = None


_Log = Any  # a channel's bound ``log`` method


class FoxgloveStream:
    """A run's Foxglove stream: maze scene, poses, trial events and tables, camera frames and
    monitors' paths, each message built once and logged to every sink.

    Parameters
    ----------
    sinks : sequence of FoxgloveSink
        Where the messages go (at least one): :class:`McapSink` and/or
        :class:`cobelrun.io.live.LiveSink`. The stream closes them.
    geometry : Geometry, optional
        The maze, graph or arena; written once as a ``foxglove.SceneUpdate`` on ``/maze`` (and
        as the attachment ``geometry.json`` of a file) so that Foxglove's 3D panel shows the
        maze under the poses.
    start_ns : int, optional
        Log time origin in nanoseconds since the Unix epoch: the run's real wall-clock start
        (``time.time_ns()``, the default). The scene and the metadata are logged at this time;
        callers pass absolute times ``start_ns + offset`` to the ``write_*`` methods.
    metadata : mapping of str to str, optional
        Written as the MCAP metadata record ``cobel`` (e.g. seed, task, config hash, which runs
        are kept in full); ``start_ns`` is added.
    """

    TRIAL_TOPIC = "/trial"
    TRIALS_TOPIC = "/trials"
    SCENE_TOPIC = "/maze"
    SERIES_TOPIC = "/trial_series"

    def __init__(
        self,
        sinks: Sequence[FoxgloveSink],
        *,
        geometry: Geometry | None = None,
        start_ns: int | None = None,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        self.sinks = list(sinks)
        self._closed = True
        try:
            if not self.sinks:
                raise ValueError("a FoxgloveStream needs at least one sink")
            self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
            if self.start_ns < 0:
                raise ValueError(f"start_ns must be >= 0, got {self.start_ns}")
        except BaseException:
            self._close_sinks()
            raise
        self._closed = False
        #: topic -> the channel on each sink (None: not created there yet, or not logged there)
        self._topics: dict[str, list[Any]] = {}
        self._live = any(s.live for s in self.sinks)
        try:
            self._logs(self.TRIAL_TOPIC, self._trial_channel)
            if self._live:
                self._logs(self.SERIES_TOPIC, self._series_channel, live_only=True)
            meta = {str(k): str(v) for k, v in (metadata or {}).items()}
            meta.setdefault("start_ns", str(self.start_ns))
            for sink in self.sinks:
                sink.write_metadata("cobel", meta)
            if geometry is not None:
                self._write_scene(geometry)
        except BaseException:
            self.close()  # complete (if empty) files, never a half-open writer
            raise

    # ------------------------------------------------------------------ channels
    @staticmethod
    def _trial_channel(context: foxglove.Context) -> foxglove.Channel:
        return foxglove.Channel(FoxgloveStream.TRIAL_TOPIC, schema=TRIAL_EVENT_SCHEMA,
                                context=context)  # fmt: skip

    @staticmethod
    def _series_channel(context: foxglove.Context) -> foxglove.Channel:
        return foxglove.Channel(FoxgloveStream.SERIES_TOPIC, schema=TRIAL_SERIES_SCHEMA,
                                context=context)  # fmt: skip

    def _logs(self, topic: str, make: Any, *, live_only: bool = False) -> list[_Log]:
        """The ``log`` methods of ``topic``'s channels that want this message: every file sink,
        and the live sinks where a client subscribes to it. Channels are created on first use
        by ``make(context)``; ``live_only`` topics exist on live sinks only."""
        files, live = self._split_logs(topic, make, live_only=live_only)
        return files + live

    def _split_logs(
        self, topic: str, make: Any, *, live_only: bool = False
    ) -> tuple[list[_Log], list[_Log]]:
        """:meth:`_logs`, as (the files' logs, the watched live sinks' logs)."""
        channels = self._topics.get(topic)
        if channels is None:
            channels = self._topics[topic] = [None] * len(self.sinks)
        files, live = [], []
        for i, sink in enumerate(self.sinks):
            if live_only and not sink.live:
                continue
            ch = channels[i]
            if ch is None:
                ch = channels[i] = make(sink.context)
            if not sink.live:
                files.append(ch.log)
            elif ch.has_sinks():
                live.append(ch.log)
        return files, live

    def prepare_run(self, run: int, images: bool = False) -> None:
        """Advertise run ``run``'s pose (and camera) channels to live clients before its first
        batch, so that a client subscribes in time to see it (files create them on first use)."""
        self._check_open()
        if not self._live:
            return
        for topic, make in self._run_channels(int(run), images):
            channels = self._topics.setdefault(topic, [None] * len(self.sinks))
            for i, sink in enumerate(self.sinks):
                if sink.live and channels[i] is None:
                    channels[i] = make(sink.context)

    @staticmethod
    def _run_channels(run: int, images: bool) -> list[tuple[str, Any]]:
        meta = {"run": str(run)}
        pose = f"/run_{run:04d}/pose"
        out: list[tuple[str, Any]] = [
            (pose, lambda c: PoseInFrameChannel(pose, metadata=meta, context=c))
        ]
        if images:
            camera = f"/run_{run:04d}/camera"
            out.append((camera, lambda c: RawImageChannel(camera, metadata=meta, context=c)))
        return out

    @property
    def live(self) -> bool:
        """True if a live sink is fed."""
        return self._live

    # ------------------------------------------------------------------ poses
    def write_poses(
        self, run: int, t_ns: np.ndarray, poses: np.ndarray, arrivals: np.ndarray | None = None
    ) -> None:
        """Write ``foxglove.PoseInFrame`` messages on ``/run_{run:04d}/pose``.

        Parameters
        ----------
        run : int
            Run index (0-based, as in ``trials.parquet``).
        t_ns : (k,) int64
            Absolute log times (nanoseconds since the Unix epoch), also the poses' timestamps.
        poses : (k, 3) float
            ``x, y, heading``: position in world units and heading in radians
            (counter-clockwise from +x), written as a quaternion about +z. A trial's poses
            are its start pose and the pose after each step, so its last one is where it
            arrived (the steps table's ``next_x, next_y, next_heading`` of its last step).
        arrivals : (n,) int, optional
            Indices into ``poses`` of each trial's arrival: the file gets every pose anyway;
            a live view, which gets :data:`LIVE_POSES` of a batch's poses, always gets those
            of the batch's last :data:`LIVE_TRIALS` trials (:func:`live_pose_indices`).
        """
        self._check_open()
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"write_poses: poses must have shape (k, 3), got {p.shape}")
        t = _check_times(t_ns, p.shape[0], "write_poses")
        if p.shape[0] == 0:
            return
        if not np.isfinite(p).all():
            raise ValueError("write_poses: x, y and heading must be finite (no NaN/inf)")
        topic, make = self._run_channels(int(run), False)[0]
        files, live = self._split_logs(topic, make)
        if files:
            self._log_poses(files, t, p)
        if live:  # a viewer sees a batch arrive at once: a few hundred poses draw its track
            keep = live_pose_indices(p.shape[0], arrivals)
            if keep is not None:
                t, p = t[keep], p[keep]
            self._log_poses(live, t, p)

    def _log_poses(self, logs: list[_Log], t: np.ndarray, p: np.ndarray) -> None:
        # a grid or graph run revisits a few hundred poses: build each Pose once
        uniq, inverse = np.unique(p, axis=0, return_inverse=True)
        qz, qw = heading_to_quaternion(uniq[:, 2])
        table = [
            Pose(position=Vector3(x=x, y=y, z=0.0), orientation=Quaternion(z=z, w=w))
            for x, y, z, w in zip(
                uniq[:, 0].tolist(), uniq[:, 1].tolist(), qz.tolist(), qw.tolist(), strict=True
            )
        ]
        sec, nsec = np.divmod(t, _NS_PER_S)
        rows = zip(t.tolist(), sec.tolist(), nsec.tolist(), inverse.reshape(-1).tolist(),
                   strict=True)  # fmt: skip
        if len(logs) == 1:
            log = logs[0]
            for ti, s, ns, k in rows:
                msg = PoseInFrame(timestamp=Timestamp(s, ns), frame_id=FRAME_ID, pose=table[k])
                log(msg, log_time=ti)
            return
        for ti, s, ns, k in rows:
            msg = PoseInFrame(timestamp=Timestamp(s, ns), frame_id=FRAME_ID, pose=table[k])
            for log in logs:
                log(msg, log_time=ti)

    # ------------------------------------------------------------------ trial events
    def write_trial_events(
        self,
        run: int,
        trial: np.ndarray,
        phase: str,
        t_start: np.ndarray,
        t_end: np.ndarray,
        start_state: np.ndarray,
        end_state: np.ndarray,
        steps: np.ndarray,
        reward: np.ndarray,
        response: np.ndarray | None = None,
    ) -> None:
        """Write one ``start`` and one ``end`` ``cobel.TrialEvent`` per trial on ``/trial``.

        Parameters
        ----------
        run : int
            Run index.
        trial : (n,) int
            Trial numbers, 1-based across phases (as in ``trials.parquet``).
        phase : str
            Protocol phase of these trials.
        t_start, t_end : (n,) int64
            Absolute log times of the trials' start and end events.
        start_state, end_state, steps : (n,) int
            Start and end state and the number of steps (escape latency) of each trial.
        reward : (n,) float
            Summed reward of each trial (finite).
        response : (n,) int, optional
            Coded response of each trial; the ``response`` field is left out when omitted.
        """
        self._check_open()
        tr = np.asarray(trial)
        n = tr.shape[0] if tr.ndim == 1 else -1
        if n < 0:
            raise ValueError(f"write_trial_events: trial must be 1-D, got shape {tr.shape}")
        ts = _check_times(t_start, n, "write_trial_events")
        te = _check_times(t_end, n, "write_trial_events")
        cols = {"trial": tr, "start_state": start_state, "end_state": end_state, "steps": steps}
        ints = {}
        for name, values in cols.items():
            a = np.asarray(values)
            if a.shape != (n,) or (n and not np.issubdtype(a.dtype, np.integer)):
                raise ValueError(
                    f"write_trial_events: {name} must be ({n},) integers, got {a.shape} {a.dtype}"
                )
            ints[name] = a.astype(np.int64).tolist()
        if n and min(ints["trial"]) < 1:
            raise ValueError("write_trial_events: trials are 1-based (got a trial < 1)")
        rew = np.asarray(reward, dtype=np.float64)
        if rew.shape != (n,) or not np.isfinite(rew).all():
            raise ValueError(f"write_trial_events: reward must be ({n},) finite floats")
        resp: list[int] | None = None
        if response is not None:
            r = np.asarray(response)
            if r.shape != (n,) or not (
                np.issubdtype(r.dtype, np.integer) or np.issubdtype(r.dtype, np.bool_)
            ):
                raise ValueError(f"write_trial_events: response must be ({n},) integers")
            resp = r.astype(np.int64).tolist()
        if n == 0:
            return
        tail = ',"run":%d,"trial":%d,"phase":' + _json_string(phase) + "}"
        runs = [int(run)] * n
        starts = _json_lines('{"event":"start","start_state":%d' + tail,
                             [ints["start_state"], runs, ints["trial"]])  # fmt: skip
        end_fmt = '{"event":"end","steps":%d,"reward":%r,"end_state":%d'
        end_cols: list[list[Any]] = [ints["steps"], rew.tolist(), ints["end_state"]]
        if resp is not None:
            end_fmt += ',"response":%d'
            end_cols.append(resp)
        ends = _json_lines(end_fmt + tail, [*end_cols, runs, ints["trial"]])
        files, live = self._split_logs(self.TRIAL_TOPIC, self._trial_channel)
        rows = list(zip(starts, ends, ts.tolist(), te.tolist(), strict=True))
        for logs, keep in ((files, rows), (live, rows[-LIVE_TRIALS:])):
            for log in logs:
                for a, b, t0, t1 in keep:
                    log(a, log_time=t0)
                    log(b, log_time=t1)

    # ------------------------------------------------------------------ trial tables
    def write_trial_table(
        self,
        run: int,
        phase: str,
        first_trial: int,
        t_ns: int,
        steps: np.ndarray,
        reward: np.ndarray,
        start_state: np.ndarray,
        end_state: np.ndarray,
        terminated: np.ndarray,
        response: np.ndarray | None = None,
    ) -> None:
        """Write trials of one phase of one run (the phase or a piece of it) as one
        ``cobel.TrialTable`` on ``/trials``.

        Parameters
        ----------
        run : int
            Run index (0-based).
        phase : str
            Protocol phase of these trials.
        first_trial : int
            Trial number (1-based, across phases) of the first trial.
        t_ns : int
            Absolute log time: the start of the first trial.
        steps, start_state, end_state : (n,) int
            Steps taken (escape latency), start and end state of each trial.
        reward : (n,) float
            Summed reward of each trial (finite).
        terminated : (n,) bool
            Whether each trial ended in a terminal state.
        response : (n,) int, optional
            Coded response of each trial (left empty when omitted).
        """
        self._check_open()
        st = np.asarray(steps)
        n = st.shape[0] if st.ndim == 1 else -1
        if n < 0:
            raise ValueError(f"write_trial_table: steps must be 1-D, got shape {st.shape}")
        t = int(t_ns)
        if t < 0:
            raise ValueError("write_trial_table: t_ns must be >= 0")
        if int(first_trial) < 1:
            raise ValueError("write_trial_table: trials are 1-based (first_trial < 1)")
        cols: dict[str, list[Any]] = {}
        for name, values in (("steps", st), ("start_state", start_state),
                             ("end_state", end_state), ("terminated", terminated),
                             ("response", response)):  # fmt: skip
            if values is None:
                continue
            a = np.asarray(values)
            if a.shape != (n,) or (n and a.dtype.kind not in "iub"):
                raise ValueError(f"write_trial_table: {name} must be ({n},) integers, "
                                 f"got {a.shape} {a.dtype}")  # fmt: skip
            cols[name] = a.astype(bool if name == "terminated" else np.int64).tolist()
        rew = np.asarray(reward, dtype=np.float64)
        if rew.shape != (n,) or not np.isfinite(rew).all():
            raise ValueError(f"write_trial_table: reward must be ({n},) finite floats")
        cls, fds = _trial_table_type()

        def make(context: foxglove.Context) -> foxglove.Channel:
            schema = foxglove.Schema(name="cobel.TrialTable", encoding="protobuf", data=fds)
            return foxglove.Channel(self.TRIALS_TOPIC, schema=schema,
                                    message_encoding="protobuf", context=context)  # fmt: skip

        logs = self._logs(self.TRIALS_TOPIC, make)
        if logs:
            msg = cls(run=int(run), phase=str(phase), first_trial=int(first_trial),
                      reward=rew.tolist(), **cols)  # fmt: skip
            msg.timestamp.seconds, msg.timestamp.nanos = divmod(t, _NS_PER_S)
            data = msg.SerializeToString()
            for log in logs:
                log(data, log_time=t)
        if self._live and n:
            self._write_series(int(run), str(phase), int(first_trial), t, cols, rew)

    def _write_series(
        self, run: int, phase: str, first_trial: int, t: int, cols: dict[str, list[Any]],
        reward: np.ndarray,
    ) -> None:  # fmt: skip
        """One ``cobel.TrialSeries`` per trial on ``/trial_series`` of the live sinks that a
        client subscribes to, logged at each trial's end on the pose clock."""
        logs = self._logs(self.SERIES_TOPIC, self._series_channel, live_only=True)
        if not logs:
            return
        steps = cols["steps"]
        n = len(steps)
        ends = t + (np.cumsum(steps, dtype=np.int64) + np.arange(n, dtype=np.int64)) * STEP_NS
        resp = cols.get("response")
        fmt = '{"run":%d,"trial":%d,"phase":' + _json_string(phase)
        fmt += ',"steps":%d,"reward":%r,"terminated":%s'
        values: list[list[Any]] = [[run] * n, list(range(first_trial, first_trial + n)), steps,
                                   reward.tolist(),
                                   ["true" if x else "false" for x in cols["terminated"]]]  # fmt: skip
        if resp is not None:
            fmt += ',"response":%d'
            values.append(resp)
        lines = _json_lines(fmt + "}", values)
        for log in logs:
            for line, te in zip(lines, ends.tolist(), strict=True):
                log(line, log_time=te)

    # ------------------------------------------------------------------ paths
    def write_paths(
        self, run: int, t_ns: Sequence[int], paths: Sequence[ScenePath], lifetime_ns: int = 0
    ) -> None:
        """Draw monitors' paths (:class:`~cobelrun.monitors.ScenePath`) over the maze: one
        ``foxglove.SceneUpdate`` per path on ``/run_{run:04d}/{path.name}``, with one entity
        (id = the name, so each path replaces the last) holding a line strip per segment,
        coloured by kind, and a sphere where each segment starts.

        Parameters
        ----------
        run : int
            Run index.
        t_ns : sequence of int
            Absolute log time of each path.
        paths : sequence of ScenePath
            What to draw.
        lifetime_ns : int
            How long a path stays drawn (0: until the next one replaces it).
        """
        self._check_open()
        if len(t_ns) != len(paths):
            raise ValueError(f"write_paths: {len(t_ns)} times for {len(paths)} paths")
        life = Duration(sec=int(lifetime_ns) // _NS_PER_S, nsec=int(lifetime_ns) % _NS_PER_S)
        for t, path in zip(t_ns, paths, strict=True):
            t = int(t)
            if t < 0:
                raise ValueError("write_paths: times must be >= 0")
            topic = f"/run_{int(run):04d}/{path.name}"
            logs = self._logs(topic, lambda c, topic=topic: SceneUpdateChannel(topic, context=c))
            if not logs:
                continue
            lines, spheres = [], []
            for seg, kind in zip(path.segments, path.kinds, strict=True):
                xy = np.asarray(seg, np.float64).reshape(-1, 2)
                if not np.isfinite(xy).all():
                    raise ValueError("write_paths: points must be finite")
                color = PATH_COLORS[kind]
                pts = [Point3(x=x, y=y, z=PATH_HEIGHT) for x, y in xy.tolist()]
                lines.append(LinePrimitive(type=LinePrimitiveLineType.LineStrip,
                                           pose=scene_pose(0.0, 0.0), thickness=0.12,
                                           points=pts, color=color))  # fmt: skip
                spheres.append(SpherePrimitive(pose=scene_pose(xy[0, 0], xy[0, 1], PATH_HEIGHT),
                                               size=Vector3(x=0.25, y=0.25, z=0.25),
                                               color=color))  # fmt: skip
            meta = [KeyValuePair(key=str(k), value=str(v)) for k, v in path.metadata.items()]
            entity = SceneEntity(timestamp=_timestamp(t), frame_id=FRAME_ID, id=path.name,
                                 lifetime=life, metadata=meta, lines=lines,
                                 spheres=spheres)  # fmt: skip
            update = SceneUpdate(entities=[entity])
            for log in logs:
                log(update, log_time=t)

    # ------------------------------------------------------------------ grids
    def write_grids(self, run: int, t_ns: Sequence[int], grids: Sequence[SceneGrid]) -> None:
        """Show monitors' maps (:class:`~cobelrun.monitors.SceneGrid`): one ``foxglove.Grid``
        per grid on ``/run_{run:04d}/{grid.name}``, a float32 field per map, its origin at the
        grid's lower-left corner just above the floor of the frame ``maze``.

        Parameters
        ----------
        run : int
            Run index.
        t_ns : sequence of int
            Absolute log time of each grid.
        grids : sequence of SceneGrid
            What to show.
        """
        self._check_open()
        if len(t_ns) != len(grids):
            raise ValueError(f"write_grids: {len(t_ns)} times for {len(grids)} grids")
        for t, grid in zip(t_ns, grids, strict=True):
            t = int(t)
            if t < 0:
                raise ValueError("write_grids: times must be >= 0")
            data = grid.stacked()
            _, nx, nf = data.shape
            dx, dy = (float(v) for v in grid.cell_size)
            if not (dx > 0 and dy > 0) or not all(np.isfinite(grid.origin)):
                raise ValueError(f"write_grids: {grid.name}: bad origin or cell size")
            topic = f"/run_{int(run):04d}/{grid.name}"
            logs = self._logs(topic, lambda c, topic=topic: GridChannel(topic, context=c))
            if not logs:
                continue
            fields = [PackedElementField(name=str(name), offset=4 * i,
                                         type=PackedElementFieldNumericType.Float32)
                      for i, name in enumerate(grid.fields)]  # fmt: skip
            msg = Grid(timestamp=_timestamp(t), frame_id=FRAME_ID,
                       pose=scene_pose(grid.origin[0], grid.origin[1], GRID_HEIGHT),
                       column_count=nx, cell_size=Vector2(x=dx, y=dy), row_stride=4 * nf * nx,
                       cell_stride=4 * nf, fields=fields,
                       data=np.ascontiguousarray(data, dtype="<f4").tobytes())  # fmt: skip
            for log in logs:
                log(msg, log_time=t)

    # ------------------------------------------------------------------ images
    def write_image(self, run: int, t_ns: int, image: np.ndarray) -> None:
        """Write one camera frame as ``foxglove.RawImage`` (``rgb8``) on ``/run_{run:04d}/camera``.

        Parameters
        ----------
        run : int
            Run index.
        t_ns : int
            Absolute log time of the frame.
        image : (H, W, 3) uint8
            RGB image, rows top to bottom.
        """
        self._check_open()
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(
                f"write_image: image must be (H, W, 3) uint8, got {img.shape} {img.dtype}"
            )
        t = int(t_ns)
        if t < 0:
            raise ValueError("write_image: t_ns must be >= 0")
        topic, make = self._run_channels(int(run), True)[1]
        logs = self._logs(topic, make)
        if not logs:
            return
        h, w, _ = img.shape
        msg = RawImage(
            timestamp=_timestamp(t),
            frame_id="camera",
            width=w,
            height=h,
            encoding="rgb8",
            step=3 * w,
            data=np.ascontiguousarray(img).tobytes(),
        )
        for log in logs:
            log(msg, log_time=t)

    # ------------------------------------------------------------------ scene
    def _write_scene(self, geometry: Geometry) -> None:
        entities = scene_entities(geometry, _timestamp(self.start_ns))
        update = SceneUpdate(entities=entities)
        topic = self.SCENE_TOPIC
        self._logs(topic, lambda c: SceneUpdateChannel(topic, context=c))
        data = geometry.to_json().encode()
        for sink, channel in zip(self.sinks, self._topics[topic], strict=True):
            channel.log(update, log_time=self.start_ns)
            sink.latch(channel, update, self.start_ns)
            sink.attach(log_time=self.start_ns, name="geometry.json",
                        media_type="application/json", data=data)  # fmt: skip

    # ------------------------------------------------------------------ lifecycle
    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self!r} is closed")

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def flush(self) -> None:
        """Flush every sink: the file closes the chunk in progress, so everything written so
        far is readable after a crash (with :func:`repair_mcap`)."""
        if not self._closed:
            for sink in self.sinks:
                sink.flush()

    def close(self) -> None:
        """Finish every sink (the file's last chunk, summary and footer; the live server
        stops); idempotent. Every sink is closed even when one fails (the first error is
        raised)."""
        if self._closed:
            return
        self._closed = True
        self._close_sinks()

    def _close_sinks(self) -> None:
        first: BaseException | None = None
        for sink in self.sinks:
            try:
                sink.close()
            except BaseException as exc:
                first = first or exc
        if first is not None:
            raise first

    def __enter__(self) -> FoxgloveStream:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        sinks = ", ".join(type(s).__name__ for s in self.sinks)
        return f"{type(self).__name__}([{sinks}], start_ns={self.start_ns}, {state})"


class McapRecorder(FoxgloveStream):
    """Write one run folder's ``run.mcap``: maze scene, poses, trial events, camera frames
    (a :class:`FoxgloveStream` whose first sink is the file).

    Parameters
    ----------
    path : path-like
        File to write (replaced if it exists).
    geometry, start_ns, metadata
        As :class:`FoxgloveStream`.
    chunk_size : int, default 1 MiB
        Target uncompressed chunk size.
    live : sequence of FoxgloveSink, optional
        More sinks fed the same messages (a live view: :class:`cobelrun.io.live.LiveSink`).

    Examples
    --------
    >>> with McapRecorder(run_dir / "run.mcap", geometry=env.unwrapped.geometry()) as rec:
    ...     rec.write_poses(0, t_ns, poses)        # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: Geometry | None = None,
        start_ns: int | None = None,
        metadata: Mapping[str, str] | None = None,
        chunk_size: int = 1 << 20,
        live: Sequence[FoxgloveSink] = (),
    ) -> None:
        self.path = Path(path)
        if start_ns is not None and int(start_ns) < 0:
            raise ValueError(f"start_ns must be >= 0, got {int(start_ns)}")
        try:
            file = McapSink(self.path, chunk_size=chunk_size)
        except BaseException:
            for sink in live:
                sink.close()
            raise
        super().__init__([file, *live], geometry=geometry, start_ns=start_ns,
                         metadata=metadata)  # fmt: skip

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"McapRecorder({str(self.path)!r}, start_ns={self.start_ns}, {state})"
