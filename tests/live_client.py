"""A Foxglove WebSocket client for the live-view tests (its own process, so its reads never
wait for the run's GIL): ``python tests/live_client.py PORT [SECONDS]``.

It connects to ``ws://127.0.0.1:PORT`` (retrying until the server is up) with the
``foxglove.sdk.v1`` subprotocol, subscribes to every channel the server advertises, and prints
one JSON object: the advertised channels (topic -> schema name) and, per topic, the number of
messages received and the first JSON payload. It stops once it has a message on a pose and on
a trial topic, or after SECONDS (default 30).
"""

from __future__ import annotations

import json
import struct
import sys
import time

import websocket  # websocket-client (selenium's dependency: in the dev extra)

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1  # binary opcode: u8 op, u32 subscription id, u64 log time, payload


def main(port: int, seconds: float) -> dict:
    deadline = time.monotonic() + seconds
    ws = None
    while ws is None:
        try:
            ws = websocket.create_connection(f"ws://127.0.0.1:{port}",
                                             subprotocols=[SUBPROTOCOL], timeout=2)  # fmt: skip
        except OSError:
            if time.monotonic() > deadline:
                return {"error": "no server"}
            time.sleep(0.02)
    ws.settimeout(0.5)
    channels: dict[int, dict] = {}
    sub_topic: dict[int, str] = {}
    counts: dict[str, int] = {}
    first: dict[str, object] = {}
    log_times: dict[str, list[int]] = {}
    next_sub = 1
    try:
        while time.monotonic() < deadline:
            try:
                msg = ws.recv()
            except websocket.WebSocketTimeoutException:
                continue
            except websocket.WebSocketConnectionClosedException:
                break
            if isinstance(msg, str):
                if not msg:  # websocket-client returns '' for the server's close frame
                    break
                op = json.loads(msg)
                if op.get("op") == "advertise":
                    subs = []
                    for ch in op["channels"]:
                        channels[ch["id"]] = ch
                        sub_topic[next_sub] = ch["topic"]
                        subs.append({"id": next_sub, "channelId": ch["id"]})
                        next_sub += 1
                    try:
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                    except (OSError, websocket.WebSocketException):
                        break  # the run ended (and its server closed) meanwhile
                continue
            if not msg or msg[0] != MESSAGE_DATA:
                continue
            sub, log_time = struct.unpack_from("<IQ", msg, 1)
            topic = sub_topic[sub]
            counts[topic] = counts.get(topic, 0) + 1
            log_times.setdefault(topic, []).append(log_time)
            if topic not in first:
                payload = msg[13:]
                try:
                    first[topic] = json.loads(payload)
                except ValueError:
                    first[topic] = len(payload)
            if any(t.endswith("/pose") for t in counts) and "/trial" in counts:
                break
    finally:
        ws.close(timeout=0.2)
    return {
        "channels": {c["topic"]: c["schemaName"] for c in channels.values()},
        "counts": counts,
        "first": first,
        "log_times": {t: v[:5] for t, v in log_times.items()},
    }


if __name__ == "__main__":
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 30.0
    print(json.dumps(main(int(sys.argv[1]), seconds)))
