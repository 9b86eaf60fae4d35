"""qtm_source: a live Qualisys Track Manager stream (RT protocol, 3D no labels) on ``markers/raw``.

Each QTM data packet becomes one MarkerFrame with the frame's unlabeled 3D
points (metres), all visible, no track ids (the ``tracker`` node gives them).
The capture stamp is QTM's frame timestamp (microseconds) in ns; the rate is
QTM's capture frequency (``GetParameters General``) unless ``rate_hz`` is set.
QTM's lab frame is Z-up by default.  A lost connection is re-opened every
``reconnect_s``; counters (malformed, stale, gaps, QTM errors) go to diagnostics.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from uuomocap.protocol.messages import MarkerFrame
from uuomocap.protocol.qtm import DEFAULT_PORT, DEFAULT_PROTOCOL_VERSION, QTM_UP_AXIS, QTMClient, QTMError
from uuomocap.protocol.session import UP_AXES

from .base import Node


@dataclass(frozen=True)
class QTMSourceConfig:
    host: str = "127.0.0.1"  # the QTM computer
    port: int = DEFAULT_PORT  # 22223: little-endian RT port
    version: str = DEFAULT_PROTOCOL_VERSION
    residuals: bool = False  # ask for 3DNoLabelsRes (residuals are not forwarded yet)
    up_axis: str = QTM_UP_AXIS
    rate_hz: float = 0.0  # 0 = QTM's capture frequency
    reconnect_s: float = 1.0
    max_frames: int = 0  # stop after this many frames (0 = until stopped)

    def __post_init__(self):
        if self.up_axis not in UP_AXES:
            raise ValueError(f"parameter 'up_axis' must be one of {', '.join(UP_AXES)}, got {self.up_axis!r}")
        if not 0 < self.port < 65536:
            raise ValueError("parameter 'port' must be a TCP port 1..65535")
        if self.rate_hz < 0 or self.max_frames < 0 or not self.reconnect_s > 0:
            raise ValueError("rate_hz >= 0, max_frames >= 0 and reconnect_s > 0 are required")


class QTMSource(Node):
    Config = QTMSourceConfig
    PUBLISHES = {"markers": "markers/raw"}

    def setup(self) -> None:
        self.client: QTMClient | None = None
        self.next_attempt = 0.0
        self.published = 0
        self.source = f"qtm://{self.config.host}:{self.config.port}"

    def teardown(self) -> None:
        if self.client is not None:
            self.client.close()

    def _connect(self) -> None:
        c = self.config
        if time.monotonic() < self.next_attempt:
            self.serve(50)
            return
        self.next_attempt = time.monotonic() + c.reconnect_s
        client = QTMClient(c.host, c.port, version=c.version, residuals=c.residuals)
        try:
            client.connect(timeout_s=min(2.0, c.reconnect_s * 2))
        except (TimeoutError, QTMError, OSError) as exc:
            self.count("connect_failures")
            if self.counters["connect_failures"] in (1, 10) or self.counters["connect_failures"] % 100 == 0:
                self.log.warning("cannot stream from QTM at %s:%d: %s", c.host, c.port, exc)
            client.close()
            return
        self.client = client
        self.log.info("streaming 3D no labels from QTM at %s:%d (capture %.3g Hz)", c.host, c.port,
                      client.capture_rate_hz)

    def step(self) -> bool:
        c = self.config
        if self.client is None:
            self._connect()
            return not self.stopping
        try:
            frame = self.client.receive(timeout_s=0.05)
        except (ConnectionError, QTMError, OSError) as exc:
            self.count("disconnects")
            self.log.warning("QTM connection lost (%s); reconnecting", exc)
            self.client.close()
            self.client = None
            return True
        self.counters.update({f"qtm_{k}": v for k, v in self.client.stats.as_dict().items() if k != "last_error"})
        if frame is None:
            return True
        self.publish("markers", MarkerFrame(
            stamp_ns=int(frame.timestamp_us) * 1000,
            frame_index=int(frame.frame_number),
            positions=np.ascontiguousarray(frame.positions, dtype=np.float32).reshape(-1, 3),
            visible=np.ones(len(frame.positions), dtype=bool),
            rate_hz=float(c.rate_hz or self.client.capture_rate_hz),
            up_axis=c.up_axis,
            source=self.source,
        ))
        self.published += 1
        if c.max_frames and self.published >= c.max_frames:
            self.end_stream("markers")
            return False
        return True
