"""segmenter: marker segmentation + part matching on a window of markers (+ prior) -> MarkerLabels.

Buffers the first ``window_s`` of ``markers/raw`` (and the ``body/prior`` frames up to it), then
runs the offline Steps 1-2 (``segmentation``, ``part_matching``) and Stage 3 on the matched body
(``windowed_solver.label_markers``) and publishes ``markers/labels``.  With ``update_s`` > 0 it
re-labels on the latest window that often and publishes only when the labels changed.  Buffers
are rings: memory does not grow with the take.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from uuomocap.protocol.messages import MarkerLabels

from .base import Node, Port


@dataclass(frozen=True)
class SegmenterConfig:
    body_model: str = "open-low"
    window_s: float = 3.0  # seconds of markers the labels are computed on
    rate_hz: float = 30.0  # the window is decimated to this rate (paper: 30 Hz markers)
    update_s: float = 0.0  # re-label this often on the latest window (0 = once)
    threads: int = 1

    def __post_init__(self):
        if self.window_s <= 0 or self.rate_hz <= 0 or self.update_s < 0 or self.threads < 1:
            raise ValueError("window_s > 0, rate_hz > 0, update_s >= 0 and threads >= 1 are required")


class Segmenter(Node):
    Config = SegmenterConfig
    SUBSCRIBES = {
        "markers": Port("markers/raw", types=("MarkerFrame",)),
        "prior": Port("body/prior", types=("BodyPrior",), optional=True),
    }
    PUBLISHES = {"labels": "markers/labels"}
    # a labelling in progress (offline stages, niced: ~5-30 s on a loaded 2-core machine) finishes
    # before the node stops; with the default 10 s the stop alarm can end it mid-way (exit by
    # SIGALRM), which the launcher reports as a failed graph
    STOP_TIMEOUT_S = 60

    def setup(self) -> None:
        import torch

        from uuomocap.solver_core.body_model import load_solver_models

        torch.set_num_threads(self.config.threads)
        self.model, self.chamfer_model = load_solver_models(self.config.body_model)
        self.frames: deque | None = None
        self.priors: deque = deque(maxlen=512)
        self.last_run_ns: int | None = None
        self.version = 0
        self.current: tuple | None = None
        self.num_markers: int | None = None

    def on_prior(self, msg, env) -> None:
        self.priors.append((msg.stamp_ns, np.asarray(msg.global_orient, np.float64), np.asarray(msg.body_pose, np.float64),
                            np.asarray(msg.betas, np.float64), msg.valid, msg.camera_frame, msg.confidence))

    def on_markers(self, msg, env) -> None:
        c = self.config
        rate = msg.rate_hz if msg.rate_hz > 0 else 120.0
        step = max(1, int(round(rate / c.rate_hz)))
        if self.frames is None or len(msg.positions) != self.num_markers:
            self.num_markers = len(msg.positions)
            self.frames = deque(maxlen=max(3, int(round(c.window_s * rate / step))))
            self.count_in, self.last_run_ns, self.up_axis = 0, None, msg.up_axis
        self.count_in += 1
        if (self.count_in - 1) % step == 0:
            self.frames.append((msg.stamp_ns, np.asarray(msg.positions, np.float64), np.asarray(msg.visible, bool)))
        full = len(self.frames) == self.frames.maxlen
        due = self.last_run_ns is None or (c.update_s > 0 and msg.stamp_ns - self.last_run_ns >= c.update_s * 1e9)
        if full and due:
            self.last_run_ns = msg.stamp_ns
            self._label(msg.stamp_ns)

    def _label(self, stamp_ns: int) -> None:
        from uuomocap.solver_core.windowed_solver import label_markers, world_prior_at

        stamps = np.array([f[0] for f in self.frames], np.int64)
        markers = np.stack([f[1] for f in self.frames])
        vis = np.stack([f[2] for f in self.frames]) & np.isfinite(markers).all(axis=2)
        prior, shape, _ = world_prior_at(list(self.priors), stamps, self.up_axis, self.model.num_betas)
        att, parts, diag = label_markers(self.model, self.chamfer_model, markers, vis, prior, shape, self.up_axis)
        faces = att.face_ids.numpy().astype(np.int32)
        bary = att.bary.numpy().astype(np.float32)
        if self.current is not None and np.array_equal(faces, self.current[0]) and np.allclose(bary, self.current[1], atol=1e-3):
            return
        self.current = (faces, bary)
        self.version += 1
        score = att.score_m.numpy()
        conf = np.where(np.isfinite(score), 1.0 / (1.0 + score / 0.01), 0.0).astype(np.float32)
        self.publish("labels", MarkerLabels(stamp_ns=int(stamp_ns), labels_version=self.version, marker_parts=list(parts),
                                            marker_faces=faces, marker_bary=bary, confidence=conf, marker_offset_m=0.0095))
        self.log.info("labels v%d: %d clusters, %s, part %s", self.version, diag["clusters"],
                      "full body" if diag["full_body"] else "partial body", ",".join(diag["part_joints"][:6]))
