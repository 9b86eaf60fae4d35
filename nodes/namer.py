"""namer: the markers of the stream with names (``markers/named``), as the solver labelled them.

Inputs: ``markers/raw`` (MarkerFrame: the frames the solver solves - remap it to
``markers/tracked`` where the solver reads the tracker) and ``body/solved`` (SolvedFrame: each
marker's surface point under the current lock, the solved shape).  Output ``markers/named``: every
marker frame as it came, with ``labels`` - Vicon Plug-in Gait names, a lab's own template's, or
``LThigh1``-style segment names (``solver_core.marker_naming``, the same naming as ``uuomocap
label``) - under the lock its solved frame came with: a frame goes out when its first answer
(the estimate) does, so the names are the body's, with the body's latency ('' for a slot without a
surface point: an empty tracker slot, a new track not yet assigned).  Frames wait at most
``max_waiting_frames`` (then go out as they are); at the end of the solved stream, or a stop, every
waiting frame goes out (without a solver in the graph, only then).  ``uuomocap label`` names a whole recorded take under its final lock.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np

from uuomocap.protocol.messages import MarkerFrame, SolvedFrame

from .base import Node, Port


@dataclass(frozen=True)
class NamerConfig:
    layout: str = "segments"  # segments | plug-in-gait | template .npz (`uuomocap sample motion-from-markers`)
    max_distance_mm: float = 100.0  # furthest a marker may sit from a layout point and take its name
    body_model: str = "open-low"  # for solved frames that do not name theirs
    # frames waiting for their solved answer (a bootstrap of ~10-40 s on 2 cores: 120 Hz x 60 s here; memory bound)
    max_waiting_frames: int = 7200

    def __post_init__(self):
        if not self.max_distance_mm > 0 or self.max_waiting_frames < 1:
            raise ValueError("max_distance_mm > 0 and max_waiting_frames >= 1 are required")
        if self.layout not in ("segments", "plug-in-gait") and not self.layout.lower().endswith(".npz"):
            raise ValueError(f"layout {self.layout!r}: segments, plug-in-gait or a template .npz")


class Namer(Node):
    Config = NamerConfig
    SUBSCRIBES = {
        "markers": Port("markers/raw", types=("MarkerFrame",)),
        "solved": Port("body/solved", types=("SolvedFrame",), optional=True),
    }
    PUBLISHES = {"named": "markers/named"}
    DRAIN_ON_STOP_S = 0.5  # name what is queued when the graph stops: a recording keeps every frame

    def setup(self) -> None:
        from uuomocap.solver_core.marker_naming import MarkerNamingConfig

        self.naming = MarkerNamingConfig(max_distance_m=self.config.max_distance_mm / 1000.0)
        self.models: dict = {}
        self.templates: dict = {}  # body model -> a template layout's (faces, bary, names)
        self.names: list[str] = []
        self.lock_key: tuple | None = None
        self.waiting: deque[MarkerFrame] = deque()  # marker frames whose solved answer has not come yet
        model = self._model(self.config.body_model)
        self._layout(model, np.zeros(model.num_betas), self.config.body_model)  # a bad template fails at start-up
        self.log.info("naming %s with %s", self.inputs["markers"].topic, self.config.layout)

    def _model(self, name: str):
        if name not in self.models:
            from uuomocap.solver_core.body_model import load_body_model

            self.models[name] = load_body_model(name)
        return self.models[name]

    def _layout(self, model, betas: np.ndarray, body_model: str):
        from uuomocap.solver_core.marker_naming import load_layout

        if self.config.layout.lower().endswith(".npz"):  # a template's points do not depend on the shape: read it once
            if body_model not in self.templates:
                self.templates[body_model] = load_layout(self.config.layout, model, betas, body_model)
            return self.templates[body_model]
        return load_layout(self.config.layout, model, betas, body_model)

    def on_solved(self, msg: SolvedFrame, env) -> None:
        if msg.kind == "revised":  # an old frame solved again: its markers went out with its first answer
            return
        if msg.marker_faces is not None:
            self._rename(msg)
        while self.waiting and self.waiting[0].stamp_ns <= msg.stamp_ns:  # this frame, and any the solver skipped
            self._publish(self.waiting.popleft(), self.names)

    def _rename(self, msg: SolvedFrame) -> None:
        # the names change only with the lock (faces, points, parts); a frame's shape alone moves them by nothing
        key = (msg.body_model, msg.marker_faces.tobytes(), msg.marker_bary.tobytes(), tuple(msg.marker_parts))
        if key == self.lock_key:
            return
        from uuomocap.solver_core.marker_naming import name_markers_with_points

        body_model = msg.body_model or self.config.body_model
        model = self._model(body_model)
        betas = np.asarray(msg.betas, np.float64)
        faces, bary, names = self._layout(model, betas, body_model)
        new = name_markers_with_points(model, betas, msg.marker_faces, msg.marker_bary, msg.marker_parts, faces, bary,
                                       names, self.naming)
        if new != self.names:
            named, layout_names = sum(1 for n in new if n), set(names)
            how = f"{sum(1 for n in new if n in layout_names)} from {self.config.layout}" if layout_names else "segment names"
            self.log.info("frame %d: %d markers named (%s)", msg.frame_index, named, how)
            self.count("renamed")
        self.names, self.lock_key = new, key

    def on_markers(self, msg: MarkerFrame, env) -> None:
        if len(self.waiting) >= self.config.max_waiting_frames:  # the solver is far behind or gone: bounded memory
            self.count("unnamed_waited_too_long")
            self._publish(self.waiting.popleft(), [])
        self.waiting.append(msg)

    def _publish(self, msg: MarkerFrame, names: list[str]) -> None:
        if names and len(names) != msg.positions.shape[0]:  # another stream's slots: never guess
            self.count("unnamed_size_mismatch")
            names = []
        self.publish("named", dataclasses.replace(msg, labels=list(names)), msg.stamp_ns)
        self.count("named_frames" if names else "unnamed_frames")

    def _release_all(self) -> None:
        while self.waiting:
            self._publish(self.waiting.popleft(), self.names)

    def on_eos(self, port: str, env) -> None:
        # the solved stream ends after the markers (the take's end solves the last frames; a bootstrap still
        # running when a short live take ends answers them all later): only its end releases the rest
        if port == "solved":
            self._release_all()
            self.end_stream("named")

    def on_stop(self) -> None:
        self._release_all()  # stopped mid-take: the recording keeps every frame
