"""prior_replay: publish a session's prior.npz as BodyPrior messages on the capture clock.

Stamps: capture stamp = video stamp + clock offset (session.yaml
``video.clock_offset_s`` unless given). The replay follows the marker clock: a
prior for capture time t is published once a marker frame with stamp
>= t + ``latency_s`` has been seen (so speed factors, pauses and loops of the
marker replay carry over, and ``latency_s`` simulates the video estimator's
delay). In ``lockstep`` it publishes ahead as fast as its consumers take it;
the marker replay then waits on 'solver:body/prior' credits so the solver holds
every prior up to a frame's stamp before the frame arrives (deterministic).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from uuomocap.protocol.messages import BodyPrior
from uuomocap.protocol.prior_file import read_prior_npz

from .base import LATEST, Node, Port


@dataclass(frozen=True)
class PriorReplayConfig:
    file: str  # prior.npz
    clock_offset_s: float | None = None  # None: session.yaml next to the file, else 0
    latency_s: float = 0.0  # simulated estimator delay (following mode)
    lockstep: bool = False
    window: int = 16
    ack_from: list[str] = field(default_factory=list)
    ack_timeout_s: float = 30.0

    def __post_init__(self):
        if not Path(self.file).is_file():
            raise ValueError(f"parameter 'file': no such prior file {self.file!r}")
        if self.latency_s < 0 or self.window < 1:
            raise ValueError("latency_s >= 0 and window >= 1 are required")


def session_clock_offset(prior_path: Path) -> float:
    session_yaml = prior_path.parent / "session.yaml"
    if not session_yaml.is_file():
        return 0.0
    doc = yaml.safe_load(session_yaml.read_text()) or {}
    return float(((doc.get("video") or {}).get("clock_offset_s")) or 0.0)


class PriorReplay(Node):
    Config = PriorReplayConfig
    SUBSCRIBES = {"clock": Port("markers/raw", types=("MarkerFrame",), policy=LATEST)}
    PUBLISHES = {"prior": "body/prior"}

    @classmethod
    def ports(cls, config: PriorReplayConfig):
        subs, pubs = super().ports(config)
        return ({} if config.lockstep else subs), pubs  # lockstep runs ahead and needs no marker clock

    def setup(self) -> None:
        c = self.config
        self.d = read_prior_npz(c.file)
        offset = c.clock_offset_s if c.clock_offset_s is not None else session_clock_offset(Path(c.file))
        self.stamps = self.d["stamps_ns"].astype(np.int64) + int(round(offset * 1e9))
        self.camera_frame = bool(self.d["camera_frame"])
        self.body_model = str(self.d["body_model"])
        self.i, self.clock_ns, self.last_seq, self.markers_ended = 0, None, -1, False
        if c.ack_from:
            self.track_acks(self.ack_sources(c))
        self.log.info("prior: %d frames, clock offset %.3fs, %s", len(self.stamps), offset, "lockstep" if c.lockstep else "following markers")

    def on_clock(self, msg, env) -> None:
        self.clock_ns = msg.stamp_ns

    def on_eos(self, port, env) -> None:
        self.markers_ended = True

    def prior(self, i: int) -> BodyPrior:
        d = self.d
        kp = d.get("keypoints3d")
        return BodyPrior(
            stamp_ns=int(self.stamps[i]),
            video_stamp_ns=int(d["stamps_ns"][i]),
            frame_index=i,
            global_orient=d["global_orient"][i].astype(np.float32),
            body_pose=d["body_pose"][i].astype(np.float32),
            betas=d["betas"][i].astype(np.float32),
            keypoints3d=None if kp is None else kp[i].astype(np.float32),
            camera_frame=self.camera_frame,
            confidence=float(d["confidence"][i]),
            valid=bool(d["valid"][i]),
            body_model=self.body_model,
        )

    def step(self) -> bool:
        c = self.config
        if self.i >= len(self.stamps) or (self.markers_ended and not c.lockstep):
            self.end_stream("prior")
            return False
        msg = self.prior(self.i)
        if c.lockstep:
            if c.ack_from:
                self.wait_for_credit("prior", self.last_seq + 1, msg.stamp_ns, c.ack_from, c.window, c.ack_timeout_s)
        elif self.clock_ns is None or self.clock_ns < msg.stamp_ns + int(c.latency_s * 1e9):
            self.serve(20)  # wait for the marker clock to advance
            return True
        if self.stopping:
            return False
        self.last_seq = self.publish("prior", msg)
        self.i += 1
        return True
