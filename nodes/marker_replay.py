"""marker_replay: publish a marker file (.c3d, .trc, or our .mcap recording) as MarkerFrames.

Modes: real time at ``speed`` x, ``loop`` (capture stamps keep increasing across
loops), ``start_offset_s``, and ``lockstep``: as fast as the graph consumes --
frame k is sent only once every node in ``ack_from`` has acknowledged frame
k - window ('node'), or has consumed another topic up to frame k's stamp
('node:topic', e.g. the solver's priors). Ends with EndOfStream on its topic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uuomocap.protocol.messages import MarkerFrame

from .base import Node, Pacer


@dataclass(frozen=True)
class MarkerReplayConfig:
    file: str  # .c3d / .trc / .mcap, or a session directory (session.yaml names the file, may override the up axis)
    speed: float = 1.0  # x real time (ignored in lockstep)
    loop: bool = False
    start_offset_s: float = 0.0
    lockstep: bool = False
    window: int = 1  # lockstep: frames in flight before waiting for credit
    ack_from: list[str] = field(default_factory=list)  # 'node' or 'node:topic'
    ack_timeout_s: float = 30.0
    max_frames: int = 0  # 0 = all
    send_labels: bool = False  # carry the file's labels (the stream is unlabeled by design)

    def __post_init__(self):
        if not Path(self.file).exists():
            raise ValueError(f"parameter 'file': no such marker file or session directory {self.file!r}")
        if not self.speed > 0:
            raise ValueError(f"parameter 'speed' must be > 0, got {self.speed}")
        if self.start_offset_s < 0 or self.window < 1 or self.max_frames < 0:
            raise ValueError("start_offset_s >= 0, window >= 1 and max_frames >= 0 are required")
        if self.lockstep and not self.ack_from:
            raise ValueError("lockstep needs ack_from: the nodes whose acknowledgements pace the replay")


class MarkerReplay(Node):
    Config = MarkerReplayConfig
    PUBLISHES = {"markers": "markers/raw"}

    def setup(self) -> None:
        from uuomocap.protocol.markerio import read_markers
        from uuomocap.protocol.session import load_session

        c = self.config
        if Path(c.file).is_dir():
            session = load_session(c.file, load_prior=False, load_gt=False)
            md, up_axis = session.markers, session.up_axis
        else:
            md = read_markers(c.file)
            up_axis = md.up_axis
        self.rate = float(md.rate_hz)
        self.positions = np.ascontiguousarray(md.positions, dtype=np.float32)
        self.visible = np.ascontiguousarray(md.visible, dtype=bool)
        self.residuals = None if md.residuals is None else np.ascontiguousarray(md.residuals, dtype=np.float32)
        self.stamps = np.asarray(md.stamps_ns, dtype=np.int64)
        self.track_ids = np.arange(md.n_markers, dtype=np.int32)
        self.labels = list(md.labels) if c.send_labels else []
        self.up_axis, self.source, self.first_frame = up_axis, Path(md.source).name, md.first_frame
        self.start = min(int(round(c.start_offset_s * self.rate)), md.n_frames)
        self.end = md.n_frames if not c.max_frames else min(md.n_frames, self.start + c.max_frames)
        self.period_ns = int(round(1e9 / self.rate))
        self.i, self.loop_offset_ns, self.last_seq = self.start, 0, -1
        self.pacer = Pacer(c.speed)
        if c.ack_from:
            self.track_acks(self.ack_sources(c))
        self.log.info("replaying %s: %d frames x %d markers at %.3f Hz (%s)", self.source, self.end - self.start,
                      md.n_markers, self.rate, "lockstep" if c.lockstep else f"{c.speed}x real time")

    def frame(self, i: int) -> MarkerFrame:
        return MarkerFrame(
            stamp_ns=int(self.stamps[i]) + self.loop_offset_ns,
            frame_index=self.first_frame + i,
            positions=self.positions[i],
            visible=self.visible[i],
            track_ids=self.track_ids,
            residuals=None if self.residuals is None else self.residuals[i],
            rate_hz=self.rate,
            up_axis=self.up_axis,
            source=self.source,
            labels=self.labels,
        )

    def step(self) -> bool:
        c = self.config
        if self.i >= self.end:
            if c.loop and self.end > self.start:
                self.loop_offset_ns += int(self.stamps[self.end - 1] - self.stamps[self.start]) + self.period_ns
                self.i = self.start
                return True
            return self.finish()
        msg = self.frame(self.i)
        seq = self.last_seq + 1
        if c.lockstep:
            self.wait_for_credit("markers", seq, msg.stamp_ns, c.ack_from, c.window, c.ack_timeout_s)
        else:
            self.wait_ready("markers")  # the clock starts once the subscribers are ready: no start-up burst
            if not self.sleep_until(self.pacer.due_ns(msg.stamp_ns)):
                return False
        if self.stopping:
            return False
        self.last_seq = self.publish("markers", msg)
        self.i += 1
        return True

    def finish(self) -> bool:
        """Tell consumers the stream ended, and wait until the credit nodes have handled its end."""
        c = self.config
        self.end_stream("markers")
        if c.ack_from and self.last_seq >= 0:
            last_stamp = int(self.stamps[self.end - 1]) + self.loop_offset_ns
            self.wait_for_credit("markers", self.last_seq + 1, last_stamp, c.ack_from, 1, c.ack_timeout_s, require_eos=True)
        self.log.info("replay finished: %d frames published", self.last_seq + 1)
        return False
