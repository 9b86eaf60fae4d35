"""video_prior: run the video body estimator on a video file or live camera, publish BodyPrior.

Estimators: 'blazepose' (default: BlazePose GHUM 3D + a body-model fit to its 3D
landmarks, in batches of ``batch_frames`` -> latency batch_frames / rate) or
'onnx-hmr:MODEL.onnx' (a user's HMR-class network, one message per frame).
Stamps: capture stamp = video stamp + clock offset (``clock_offset_s``, else the
session.yaml next to the video, else 0).  Files play at ``speed`` x real time (0: as
fast as possible) or in ``lockstep`` on the credits of ``ack_from``; cameras and stream
URLs (a phone's rtsp:// or http:// stream) run live.  Live beside a mocap system, ``sync_to``
names its marker topic: each frame is then stamped on the capture system's clock
(``protocol.clock.ClockBridge``: this host's arrival time of the frame, mapped by the least-delayed
marker frames of the last seconds; ``clock_offset_s`` adds a fixed correction, e.g. minus the
camera's own latency), and ``video_stamp_ns`` is the frame's arrival on this host's monotonic clock;
a file there plays as a camera started with the marker stream (``ClockBridge.frame_times``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uuomocap.protocol.clock import ClockBridge
from uuomocap.protocol.messages import BodyPrior
from uuomocap.protocol.video import is_live_source

from .base import Node, Pacer, Port


@dataclass(frozen=True)
class VideoPriorConfig:
    video: str | int  # video file, a camera index such as 0, or a stream URL (rtsp://, http://)
    estimator: str = "blazepose"  # or "onnx-hmr:MODEL.onnx"
    body_model: str = "open-low"
    clock_offset_s: float | None = None
    rate_hz: float | None = None  # override the container's frame rate
    speed: float = 1.0
    lockstep: bool = False
    window: int = 16
    ack_from: list[str] = field(default_factory=list)
    ack_timeout_s: float = 30.0
    batch_frames: int = 15
    max_frames: int = 0  # 0 = all
    sync_to: str = ""  # marker topic whose capture clock stamps the priors ('' = the video's clock + clock_offset_s)
    sync_window_s: float = 10.0  # marker frames this recent set the clock mapping (drift, restarts)
    max_late_s: float = 1.5  # a file beside a live stream drops a frame this late (the first second waits for the clock)

    def __post_init__(self):
        object.__setattr__(self, "video", str(self.video))  # video:=0 from a launch file arrives as a number
        if not is_live_source(self.video) and not Path(self.video).is_file():
            raise ValueError(f"parameter 'video': no such video file {self.video!r}")
        if not (self.estimator == "blazepose" or self.estimator.startswith("onnx-hmr:")):
            raise ValueError(f"parameter 'estimator': {self.estimator!r} is not 'blazepose' or 'onnx-hmr:MODEL'")
        if self.speed < 0 or self.window < 1 or self.batch_frames < 1 or self.max_frames < 0 or not self.max_late_s > 0:
            raise ValueError("speed >= 0, window >= 1, batch_frames >= 1, max_frames >= 0 and max_late_s > 0 are required")
        if self.lockstep and not self.ack_from:
            raise ValueError("lockstep needs ack_from: the nodes whose acknowledgements pace the video")


class VideoPrior(Node):
    Config = VideoPriorConfig
    PUBLISHES = {"prior": "body/prior"}

    @classmethod
    def ports(cls, config: VideoPriorConfig):
        return ({"sync": Port(config.sync_to, types=("MarkerFrame",), optional=True)} if config.sync_to else {}), dict(cls.PUBLISHES)

    def setup(self) -> None:
        import torch

        from uuomocap.model_fetch import ensure_pose_models
        from uuomocap.protocol.video import session_video_settings, video_source
        from uuomocap.solver_core.video_prior import StreamingVideoPrior

        c = self.config
        self.video = video_source(c.video, rate_hz=c.rate_hz)
        offset = c.clock_offset_s
        session_yaml = Path(c.video).parent / "session.yaml"
        if offset is None:
            # a session's file only: a camera index or URL has no session.yaml beside it
            offset = session_video_settings(session_yaml)["clock_offset_s"] if not self.video.live and session_yaml.is_file() else 0.0
        self.offset_ns = int(round(offset * 1e9))
        torch.set_num_threads(1)  # the landmark fit's small batches; the cores belong to the graph
        models = ensure_pose_models(log=self.log.info)
        self.estimator = StreamingVideoPrior(c.estimator, models.detector, models.landmark, c.body_model, c.batch_frames)
        self.pacer = Pacer(c.speed) if c.speed > 0 and not (self.video.live or c.lockstep or c.sync_to) else None
        self.bridge = ClockBridge(c.sync_window_s) if c.sync_to else None
        self.frames: dict[int, tuple[int, int]] = {}  # index -> (video stamp, capture-clock stamp) until its prior is out
        self.count_frames, self.last_seq = 0, -1
        if c.ack_from:
            self.track_acks(self.ack_sources(c))
        self.log.info("video prior: %s at %.3f Hz, estimator %s, clock offset %.3f s%s", self.video.name,
                      self.video.rate_hz, c.estimator, offset, f", stamped on the clock of {c.sync_to}" if c.sync_to else "")

    def on_sync(self, msg, env) -> None:
        self.bridge.observe(msg.stamp_ns, time.monotonic_ns())

    def step(self) -> bool:
        c = self.config
        if self.bridge is not None and not self.video.live and not self.bridge.ready:
            return self.sleep_until(time.monotonic_ns() + 20_000_000)  # a file waits for the marker clock; a camera cannot
        frame = None if (c.max_frames and self.count_frames >= c.max_frames) else self.video.read()
        if frame is None:
            self._emit(self.estimator.flush())
            self.end_stream("prior")
            self.log.info("video prior finished: %d frames", self.count_frames)
            return False
        self.count_frames += 1
        if self.pacer is not None:
            self.wait_ready()  # the clock starts once the subscribers are ready (no start-up burst)
            if not self.sleep_until(self.pacer.due_ns(frame.stamp_ns)):
                return False
        stamp = capture = frame.stamp_ns
        if self.bridge is not None:  # the frame's time is its arrival here, mapped onto the markers' clock
            if not self.bridge.ready:
                self.count("before_marker_clock")  # no marker frame yet: no clock to put it on
                return not self.stopping
            now = time.monotonic_ns()
            stamp, capture = self.bridge.frame_times(frame.stamp_ns, self.video.live, frame.arrival_ns or now)
            if not self.video.live:  # a file frame waits for its moment; too late, it is dropped as a camera's would be
                if stamp < now - int(c.max_late_s * 1e9):
                    self.count("dropped_behind")
                    return not self.stopping
                if not self.sleep_until(stamp):
                    return False
        self.frames[frame.index] = (stamp, capture)
        finished = self.estimator.push(frame.index, frame.rgb())
        self.counters["camera_dropped"] = self.video.dropped  # frames a live source sent while the estimator was busy
        self.count("frames")
        self.count("person" if self.estimator.person_found else "no_person")
        self._emit(finished)
        return not self.stopping

    def _emit(self, finished) -> None:
        c = self.config
        for f in finished:
            stamp, capture = self.frames.pop(f.key)
            msg = BodyPrior(
                stamp_ns=capture + self.offset_ns, video_stamp_ns=stamp, frame_index=f.key,
                global_orient=f.global_orient.astype(np.float32), body_pose=f.body_pose.astype(np.float32),
                betas=f.betas.astype(np.float32), keypoints3d=f.keypoints3d, camera_frame=True,
                confidence=f.confidence, valid=f.valid, body_model=self.estimator.body_model)
            if c.lockstep:
                self.wait_for_credit("prior", self.last_seq + 1, msg.stamp_ns, c.ack_from, c.window, c.ack_timeout_s)
            if self.stopping:
                return
            self.last_seq = self.publish("prior", msg)

    def teardown(self) -> None:
        video = getattr(self, "video", None)
        if video is not None:
            video.close()
