"""A small client of the live view's WebSocket protocol (foxglove.sdk.v1, and the
older foxglove.websocket.v1): what the tests and ``bench liveview`` use to see what a
Foxglove viewer gets. It subscribes to one topic once the server advertises it and
collects the messages (log time and CDR payload), with their arrival times."""

from __future__ import annotations

import json
import struct
import time

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 1  # binary opcode: subscription id (u32 LE), log time (u64 LE), payload


def connect(port: int, host: str = "127.0.0.1", timeout_s: float = 60.0):
    """Connect, retrying while the server (started with its node) is not up yet."""
    from websockets.exceptions import InvalidHandshake
    from websockets.sync.client import connect as ws_connect
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            from websockets.typing import Subprotocol
            return ws_connect(f"ws://{host}:{port}",
                              subprotocols=[Subprotocol(s) for s in SUBPROTOCOLS],
                              open_timeout=2, max_size=None)
        except (OSError, InvalidHandshake):
            if time.monotonic() > t_end:
                raise
            time.sleep(0.3)


def receive(ws, topic: str, want: int = 0, timeout_s: float = 60.0, stop=None):
    """Subscribe to ``topic`` when advertised and collect its messages until ``want``
    arrived (0: no limit), ``timeout_s`` passed, ``stop()`` is true or the server
    closed the connection. -> (the advertised channel or None, [(log_time_ns, payload
    bytes, arrival monotonic s)])."""
    from websockets.exceptions import ConnectionClosed
    chans: dict = {}
    channel = None
    got: list = []
    t_end = time.monotonic() + timeout_s
    while (not want or len(got) < want) and time.monotonic() < t_end \
            and not (stop and stop()):
        try:
            m = ws.recv(timeout=0.5)
        except TimeoutError:
            continue
        except ConnectionClosed:
            break
        if isinstance(m, str):
            j = json.loads(m)
            if j.get("op") == "advertise":
                chans.update({c["id"]: c for c in j["channels"]})
                hit = [c for c in chans.values() if c["topic"] == topic]
                if hit and channel is None:
                    channel = hit[0]
                    _subscribe(ws, channel)
            elif j.get("op") == "status" and channel is not None and \
                    "Unknown channel" in j.get("message", ""):
                time.sleep(0.1)  # advertised a moment before the server accepts it
                _subscribe(ws, channel)
            continue
        op, _, log_ns = struct.unpack_from("<BIQ", m)
        if op == MESSAGE_DATA:
            got.append((log_ns, bytes(m[13:]), time.monotonic()))
    return channel, got


def _subscribe(ws, channel):
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
        {"id": 1, "channelId": channel["id"]}]}))


def decoder(channel: dict):
    """A function payload -> message built from nothing but the advertised schema
    (what a Foxglove viewer has)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(channel["schema"], channel["schemaName"]))
    return lambda payload: store.deserialize_cdr(payload, channel["schemaName"])
