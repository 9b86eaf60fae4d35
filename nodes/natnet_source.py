"""natnet_source: a live OptiTrack Motive (NatNet) stream as MarkerFrames on ``markers/raw``.

Each NatNet frame becomes one MarkerFrame holding the frame's measured point
cloud (unlabeled points, plus Motive-labeled ones unless ``include_labeled`` is
off; occluded/model-filled markers are left out), all visible, no track ids:
identities come from the ``tracker`` node.  The capture stamp is Motive's frame
timestamp (seconds since Motive started) in ns; ``frame_index`` is Motive's
frame number.  Positions are metres in Motive's streaming frame, Y-up unless
Motive is set to stream Z-up (then set ``up_axis: "+z"``).

The node never blocks on the network: it (re)sends NAT_CONNECT until the server
answers, reconnects after ``idle_timeout_s`` without frames, and publishes the
client's counters (malformed, stale, gaps, restarts) in its diagnostics.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from uuomocap.protocol.messages import MarkerFrame
from uuomocap.protocol.natnet import (
    DEFAULT_COMMAND_PORT,
    DEFAULT_DATA_PORT,
    DEFAULT_MULTICAST_GROUP,
    MOTIVE_UP_AXIS,
    NAT_CONNECT,
    OLDEST_SUPPORTED,
    NatNetClient,
)
from uuomocap.protocol.session import UP_AXES

from .base import Node


@dataclass(frozen=True)
class NatNetSourceConfig:
    server: str = "127.0.0.1"  # Motive's address (its "Local Interface" in the streaming pane)
    local_interface: str = "127.0.0.1"  # this machine's address on the streaming network
    multicast: bool = False  # Motive "Transmission Type": Multicast (True) or Unicast (False)
    multicast_group: str = DEFAULT_MULTICAST_GROUP
    command_port: int = DEFAULT_COMMAND_PORT
    data_port: int = DEFAULT_DATA_PORT
    up_axis: str = MOTIVE_UP_AXIS
    rate_hz: float = 0.0  # nominal capture rate; 0 = estimated from the frame timestamps
    include_labeled: bool = True  # also publish markers Motive has labeled
    bitstream: str = ""  # force a bitstream version like "4.1"; "" = what the server reports
    connect_retry_s: float = 0.5  # re-send NAT_CONNECT this often until the server answers
    idle_timeout_s: float = 2.0  # no frame this long: warn and re-send NAT_CONNECT
    max_frames: int = 0  # stop after this many frames (0 = run until stopped)

    def __post_init__(self):
        if self.up_axis not in UP_AXES:
            raise ValueError(f"parameter 'up_axis' must be one of {', '.join(UP_AXES)}, got {self.up_axis!r}")
        for name in ("command_port", "data_port"):
            if not 0 < getattr(self, name) < 65536:
                raise ValueError(f"parameter {name!r} must be a UDP port 1..65535")
        if self.rate_hz < 0 or self.max_frames < 0 or not (self.connect_retry_s > 0 and self.idle_timeout_s > 0):
            raise ValueError("rate_hz >= 0, max_frames >= 0 and positive timeouts are required")
        if self.bitstream:
            parts = self.bitstream.split(".")
            if len(parts) != 2 or not all(p.isdigit() for p in parts):
                raise ValueError(f"parameter 'bitstream' must look like '4.1', got {self.bitstream!r}")


class NatNetSource(Node):
    Config = NatNetSourceConfig
    PUBLISHES = {"markers": "markers/raw"}

    def setup(self) -> None:
        c = self.config
        bitstream = tuple(int(p) for p in c.bitstream.split(".")) if c.bitstream else None
        self.client = NatNetClient(c.server, local_address=c.local_interface, multicast=c.multicast,
                                   multicast_group=c.multicast_group, command_port=c.command_port,
                                   data_port=c.data_port, bitstream=bitstream)
        self.client.open()
        self.connected = False
        self.next_connect = 0.0
        self.published = 0
        self.last_frame_time = time.monotonic()
        self.recent_dt: deque[float] = deque(maxlen=64)
        self.last_timestamp: float | None = None
        self.source = f"natnet://{c.server}:{c.command_port}"

    def teardown(self) -> None:
        if hasattr(self, "client"):
            self.client.close()

    def _try_connect(self) -> None:
        """Non-blocking handshake: (re)send NAT_CONNECT, and go live once NAT_SERVERINFO arrived."""
        c, now = self.config, time.monotonic()
        if self.client.server_info is None:
            if now >= self.next_connect:
                self.next_connect = now + c.connect_retry_s
                try:
                    self.client.send_command(NAT_CONNECT, "Ping")
                except OSError as exc:
                    self.count("connect_errors")
                    self.log.warning("cannot reach %s:%d: %s", c.server, c.command_port, exc)
            self.client.poll(timeout_s=0.05)
            return
        info = self.client.server_info
        v = info.natnet_version
        if self.client.version < OLDEST_SUPPORTED:
            self.log.error("server streams NatNet %d.%d; this client needs 3.0 or newer", v[0], v[1])
            self.request_stop(1)
            return
        self.source = f"natnet://{c.server}:{c.command_port} {info.app_name} NatNet {v[0]}.{v[1]}"
        self.log.info("connected to %s (%s, data port %d)", self.source,
                      "multicast " + info.multicast_group if info.multicast else "unicast", info.data_port)
        if info.multicast != c.multicast:
            self.log.warning("server streams %s but this node is set to %s: set multicast: %s",
                             "multicast" if info.multicast else "unicast",
                             "multicast" if c.multicast else "unicast", info.multicast)
        self.connected = True
        self.last_frame_time = now

    def step(self) -> bool:
        c = self.config
        if not self.connected:
            self._try_connect()
            return not self.stopping
        frame = self.client.receive(timeout_s=0.05)
        self.counters.update({f"natnet_{k}": v for k, v in self.client.stats.as_dict().items() if k != "last_error"})
        if frame is None:
            if time.monotonic() - self.last_frame_time > c.idle_timeout_s:
                self.log.warning("no NatNet frame for %.1f s (%s); reconnecting", c.idle_timeout_s,
                                 self.client.stats.last_error or "no error")
                self.count("idle_reconnects")
                self.client.server_info = None
                self.connected = False
            return True
        self.last_frame_time = time.monotonic()
        self.publish("markers", self.to_marker_frame(frame))
        self.published += 1
        if c.max_frames and self.published >= c.max_frames:
            self.end_stream("markers")  # a bounded capture ends like a replay: downstream sees EOS
            return False
        return True

    def to_marker_frame(self, frame) -> MarkerFrame:
        positions, _ids, labelled = frame.point_cloud()
        if not self.config.include_labeled:
            positions = positions[~labelled]
        if self.last_timestamp is not None and frame.timestamp > self.last_timestamp:
            self.recent_dt.append(frame.timestamp - self.last_timestamp)
        self.last_timestamp = frame.timestamp
        rate = self.config.rate_hz or (1.0 / float(np.median(self.recent_dt)) if self.recent_dt else 0.0)
        return MarkerFrame(
            stamp_ns=self.client.capture_stamp_ns(frame),
            frame_index=int(frame.frame_number),
            positions=np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3),
            visible=np.ones(len(positions), dtype=bool),
            rate_hz=round(rate, 3),
            up_axis=self.config.up_axis,
            source=self.source,
        )
