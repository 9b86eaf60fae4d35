"""tracker: unlabeled point clouds (``markers/raw``) -> stable tracks (``markers/tracked``).

Each incoming MarkerFrame's visible points go through
:class:`uuomocap.solver_core.tracker.MarkerTracker`; the output MarkerFrame has
fixed size ``max_tracks``: slot ``i`` holds track ``track_ids[i]`` (-1 = empty
slot), ``visible[i]`` says it was measured this frame, ``positions[i]`` is NaN
otherwise.  A track keeps its slot while it lives, so the slot index is a
stable marker index for the segmenter and solver; a slot whose id changes is a
new marker.  Parameters are the tracker's (see ``TrackerConfig``); the rate
comes from the stream unless ``use_stream_rate`` is off.

Stamps that do not increase (Motive restarted, a replay looped back) reset the
tracker: all ids are new afterwards (counted as ``resets``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from uuomocap.protocol.messages import MarkerFrame
from uuomocap.solver_core.tracker import MarkerTracker, TrackerConfig

from .base import Node, Port


@dataclass(frozen=True)
class TrackerNodeConfig(TrackerConfig):
    # Take rate_hz from the incoming MarkerFrames (when they carry one) instead of the parameter.
    use_stream_rate: bool = True
    log_every_s: float = 10.0  # period of the one-line tracking summary in the log (0 = never)

    def tracker_config(self, rate_hz: float | None = None) -> TrackerConfig:
        names = {f.name for f in dataclasses.fields(TrackerConfig)}
        values = {k: getattr(self, k) for k in names}
        if rate_hz:
            values["rate_hz"] = float(rate_hz)
        return TrackerConfig(**values)


class Tracker(Node):
    Config = TrackerNodeConfig
    SUBSCRIBES = {"markers": Port("markers/raw", types=("MarkerFrame",))}
    PUBLISHES = {"tracked": "markers/tracked"}
    # On a stop request, track what is already queued (the source stops first, so the input goes
    # quiet): a tracker that lagged ~1 s behind a 120 Hz stream on a loaded machine otherwise
    # dropped its backlog, and the recording held 124 tracked messages beside 241 raw ones (240 + end).
    DRAIN_ON_STOP_S = 0.5
    DRAIN_MAX_S = 8.0  # below STOP_TIMEOUT_S (10 s), after which SIGALRM ends the process

    def setup(self) -> None:
        self.tracker = MarkerTracker(self.config.tracker_config())
        self.timer_s = self.config.log_every_s or None
        self.last_stamp: int | None = None

    def on_markers(self, msg: MarkerFrame, env) -> None:
        c = self.config
        rate = msg.rate_hz if c.use_stream_rate and msg.rate_hz > 0 else 0.0
        # Only a real rate change rebuilds the tracker (and drops its tracks): the rate sets frame
        # counts such as the birth delay; the gates follow the actual stamps anyway.
        if rate and abs(rate - self.tracker.config.rate_hz) > 0.02 * rate:
            if self.tracker.stats.frames:
                self.log.info("stream rate changed to %.3f Hz: restarting the tracker", rate)
            self.tracker = MarkerTracker(c.tracker_config(rate))
            self.last_stamp = None
        if self.last_stamp is not None and msg.stamp_ns <= self.last_stamp:
            self.count("resets")
            self.log.warning("stamp went back (%d -> %d ns): restarting tracks", self.last_stamp, msg.stamp_ns)
            self.tracker.reset()
        self.last_stamp = msg.stamp_ns
        positions = np.asarray(msg.positions)[np.asarray(msg.visible, dtype=bool)]
        out = self.tracker.step(positions, msg.stamp_ns)
        self.publish("tracked", MarkerFrame(
            stamp_ns=msg.stamp_ns,
            frame_index=msg.frame_index,
            positions=out.positions,
            visible=out.visible,
            track_ids=out.track_ids.astype(np.int32),
            rate_hz=msg.rate_hz or self.tracker.config.rate_hz,
            up_axis=msg.up_axis,
            source=msg.source,
        ), msg.stamp_ns)
        st = self.tracker.stats
        self.counters.update({f"tracker_{k}": v for k, v in st.as_dict().items()})

    def on_eos(self, port: str, env) -> None:
        self.end_stream("tracked")  # a finished replay finishes the tracked stream too

    def on_timer(self) -> None:
        st = self.tracker.stats
        if st.frames:
            self.log.info("tracks: %d born, %d re-acquired, %d died; %.1f%% of points tracked, %d ghost tracks",
                          st.births, st.reacquired, st.deaths, 100.0 * st.assigned_points / max(st.points, 1),
                          st.ghost_tracks)
