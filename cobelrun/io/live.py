"""The live view: foxglove-sdk's WebSocket server as a sink of a run's Foxglove stream.

``cobel run ... --live [--port P]`` (``task.record.live=true``) starts
``foxglove.start_server`` on ``127.0.0.1`` and feeds it, while the run goes, the messages
``run.mcap`` gets (maze scene, poses of the first ``mcap_runs`` runs, trial events and tables,
camera frames, monitors' paths) plus the per-trial series on ``/trial_series``; see
:class:`cobelrun.io.mcap.FoxgloveStream`. Foxglove (Open connection > Foxglove WebSocket) and
Lichtblick connect to ``ws://127.0.0.1:PORT``; :data:`LAYOUTS` holds a layout for each
(:func:`foxglove_layout`, :func:`lichtblick_layout`).

A live view never stops a run: a port in use is one line on stderr and the run goes on
without it; a client that disconnects is one line. Nothing is sent on a channel no client
subscribes to, and a slow client loses its oldest messages (foxglove-sdk keeps at most
``message_backlog_size`` per client) instead of slowing the run. A piece of a phase reaches a
client at once, so it gets :data:`~cobelrun.io.mcap.LIVE_POSES` poses of it (and the arrival of
each of its last :data:`~cobelrun.io.mcap.LIVE_TRIALS` trials) and the events
of the last :data:`~cobelrun.io.mcap.LIVE_TRIALS` trials of each piece (the file gets all).
"""

from __future__ import annotations

import json
import logging
import sys
import threading
from pathlib import Path
from typing import Any

import foxglove
from foxglove.websocket import ServerListener

from cobelrun.io.mcap import FoxgloveSink

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "LAYOUTS",
    "LiveSink",
    "foxglove_layout",
    "lichtblick_layout",
    "write_layouts",
]

#: where the server binds unless ``task.record.live_host`` says otherwise
DEFAULT_HOST = "127.0.0.1"
#: foxglove-sdk's and Foxglove's default port
DEFAULT_PORT = 8765
#: the layouts shipped with cobel (3D maze and poses, per-trial plots, camera, trial events):
#: ``cobel-live.foxglove.json`` (Foxglove) and ``cobel-live.lichtblick.json`` (Lichtblick)
LAYOUTS = Path(__file__).parent / "layouts"
#: poses of this many runs are shown in the layouts' 3D panel (``record.mcap_runs``' default)
LAYOUT_RUNS = 10
#: the pose arrows' length and thickness in the layouts (world units; cells are 1): thicker
#: than Foxglove's default (1, 0.15, 0.15), which hides in the goal's disk a trial ends on
POSE_ARROW = (0.7, 0.4, 0.4)


def foxglove_layout(runs: int = LAYOUT_RUNS) -> Any:
    """The live view's layout for Foxglove, built with foxglove-sdk's typed
    ``foxglove.layouts``: the maze and the poses of the first ``runs`` runs in a 3D panel
    (frame ``maze``), steps and reward per trial (``/trial_series``) in two plots, run 0's
    camera, and the last trial event. It opens ``run.mcap`` files as well."""
    import foxglove.layouts as fl

    topics: dict[str, Any] = {"/maze": fl.BaseRendererSceneUpdateTopicSettings(visible=True)}
    for run in range(runs):
        topics[f"/run_{run:04d}/pose"] = fl.BaseRendererPoseTopicSettings(
            visible=True, type="arrow", arrow_scale=POSE_ARROW
        )
        topics[f"/run_{run:04d}/replay"] = fl.BaseRendererSceneUpdateTopicSettings(visible=True)
    maze = fl.ThreeDeePanel(
        title="maze",
        config=fl.ThreeDeeConfig(follow_tf="maze", follow_mode="follow-none", topics=topics),
    )

    def plot(field: str, label: str) -> Any:
        series = fl.PlotSeries(value=f"/trial_series.{field}", label=label)
        return fl.PlotPanel(title=label, config=fl.PlotConfig(paths=[series]))

    camera = fl.ImagePanel(
        title="run 0 camera",
        config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic="/run_0000/camera")),
    )
    events = fl.RawMessagesPanel(
        title="trial events", config=fl.RawMessagesConfig(topic_path="/trial")
    )
    side = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(content=plot("steps", "steps per trial (latency)")),
            fl.SplitItem(content=plot("reward", "reward per trial")),
            fl.SplitItem(content=camera),
            fl.SplitItem(content=events),
        ],
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=maze),
                fl.SplitItem(proportion=2, content=side),
            ],
        )
    )


def lichtblick_layout(runs: int = LAYOUT_RUNS) -> dict[str, Any]:
    """The same layout as :func:`foxglove_layout` in the layout format Lichtblick (and
    Foxglove Studio 1.x) imports: ``configById`` and a mosaic ``layout`` tree."""
    topics: dict[str, Any] = {"/maze": {"visible": True}}
    for run in range(runs):
        topics[f"/run_{run:04d}/pose"] = {"visible": True, "type": "arrow",
                                          "arrowScale": list(POSE_ARROW)}  # fmt: skip
        topics[f"/run_{run:04d}/replay"] = {"visible": True}

    def plot(field: str, label: str) -> dict[str, Any]:
        series = {"value": f"/trial_series.{field}", "label": label, "enabled": True,
                  "timestampMethod": "receiveTime"}  # fmt: skip
        return {"title": label, "paths": [series], "showLegend": True,
                "xAxisVal": "timestamp", "isSynced": False}  # fmt: skip

    side = {
        "direction": "column",
        "first": {"direction": "column", "first": "Plot!steps", "second": "Plot!reward"},
        "second": {"direction": "column", "first": "Image!camera", "second": "RawMessages!trial"},
    }
    return {
        "configById": {
            "3D!maze": {"followTf": "maze", "followMode": "follow-none", "topics": topics},
            "Plot!steps": plot("steps", "steps per trial (latency)"),
            "Plot!reward": plot("reward", "reward per trial"),
            "Image!camera": {"imageMode": {"imageTopic": "/run_0000/camera"}},
            "RawMessages!trial": {"topicPath": "/trial"},
        },
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {"direction": "row", "first": "3D!maze", "second": side, "splitPercentage": 60},
    }


def layout_texts() -> dict[str, str]:
    """File name -> text of each shipped layout (what :func:`write_layouts` writes)."""
    fox = json.dumps(json.loads(foxglove_layout().to_json()), indent=2) + "\n"
    return {
        "cobel-live.foxglove.json": fox,
        "cobel-live.lichtblick.json": json.dumps(lichtblick_layout(), indent=2) + "\n",
    }


def write_layouts(folder: Path = LAYOUTS) -> None:
    """(Re)write the shipped layouts (a test checks that they match the builders)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in layout_texts().items():
        (folder / name).write_text(text, encoding="utf-8")


def _say(line: str) -> None:
    print(f"cobel: {line}", file=sys.stderr, flush=True)


def _quiet_server_logs() -> None:
    """foxglove-sdk's server logs every client's connect, full outbox and reset connection
    through Python's ``logging`` (``foxglove.websocket.*``); cobel says what matters in one
    line of its own (:class:`_Listener`), so those records are dropped."""
    logger = logging.getLogger("foxglove.websocket")
    if not any(isinstance(h, logging.NullHandler) for h in logger.handlers):
        logger.addHandler(logging.NullHandler())
    logger.propagate = False


class _Listener(ServerListener):
    """foxglove-sdk's ``ServerListener``: sends the latched maze to a client that subscribes
    to it, and says in one line when a client starts or stops watching."""

    def __init__(self, sink: LiveSink) -> None:
        super().__init__()
        self._sink = sink
        self._lock = threading.Lock()
        self._subscribed: dict[int, set[int]] = {}  # client id -> channel ids

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            subs = self._subscribed.setdefault(client.id, set())
            first = not subs
            subs.add(channel.id)
        if first:
            _say(f"live view: client {client.id} is watching {self._sink.url}")
            self._sink._watching.set()
        self._sink._resend(channel.id)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            subs = self._subscribed.get(client.id)
            if subs is None:
                return
            subs.discard(channel.id)
            left = not subs
            if left:
                del self._subscribed[client.id]
        if left and not self._sink.closed:
            _say(f"live view: client {client.id} stopped watching (closed or unsubscribed); "
                 "the run goes on")  # fmt: skip


class LiveSink(FoxgloveSink):
    """A live view: foxglove-sdk's WebSocket server on a context of its own.

    Parameters
    ----------
    host : str
        Interface to bind (``127.0.0.1``: this machine only).
    port : int
        Port (0: any free port; :attr:`port` says which).
    name : str
        Server name the client shows.

    Raises
    ------
    RuntimeError
        foxglove-sdk's error when the server cannot start (a port in use);
        :meth:`start` turns it into one line.
    """

    live = True

    def __init__(
        self, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, name: str = "cobel"
    ) -> None:
        super().__init__()
        self._latched: dict[int, tuple[Any, Any, int]] = {}
        self._latch_lock = threading.Lock()
        self._watching = threading.Event()
        _quiet_server_logs()
        self.host = host
        self._server = foxglove.start_server(
            name=name, host=host, port=int(port), context=self.context,
            server_listener=_Listener(self),
        )  # fmt: skip
        self.port = int(self._server.port)

    @classmethod
    def start(
        cls, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, name: str = "cobel"
    ) -> LiveSink | None:
        """Start the server and say where it listens (one line on stderr); if it cannot start
        (a port in use), say so in one line and return None: the run goes on without it."""
        try:
            sink = cls(host=host, port=port, name=name)
        except (RuntimeError, OSError) as exc:
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            if "in use" in text:
                _say(f"live view off: port {port} on {host} is in use (pick another with "
                     "--port, or --port 0 for any free one); the run goes on")  # fmt: skip
            else:
                _say(f"live view off: no server on {host}:{port} ({text}); the run goes on")
            return None
        _say(f"live view on {sink.url}: open it in Foxglove or Lichtblick (Open connection > "
             f"Foxglove WebSocket); layouts: {LAYOUTS}")  # fmt: skip
        return sink

    @property
    def url(self) -> str:
        """``ws://HOST:PORT`` to connect to."""
        return f"ws://{self.host}:{self.port}"

    def wait_for_client(self, seconds: float) -> bool:
        """Wait up to ``seconds`` until a client subscribes to a channel (so that a viewer sees
        a run from its first trial); True if one did."""
        if self._watching.is_set():
            return True
        _say(f"live view: waiting up to {seconds:g} s for a client on {self.url}")
        return self._watching.wait(seconds)

    def latch(self, channel: Any, message: Any, log_time: int) -> None:
        with self._latch_lock:
            self._latched[channel.id()] = (channel, message, int(log_time))

    def _resend(self, channel_id: int) -> None:
        """Log a latched message again (a client just subscribed to its channel)."""
        with self._latch_lock:
            latched = self._latched.get(channel_id)
        if latched is not None and not self.closed:
            channel, message, log_time = latched
            channel.log(message, log_time=log_time)

    def close(self) -> None:
        """Stop the server (clients see the connection close); idempotent."""
        if self._closed:
            return
        self._closed = True
        self._server.stop()

    def __repr__(self) -> str:
        return f"LiveSink({self.url!r}, {'closed' if self._closed else 'open'})"
