"""Unlabeled marker tracking: per-frame point clouds -> stable track ids.

A live optical system (or a raw, unlabeled file) gives, each frame, an
unordered set of 3D points: the visible markers plus ghosts (false
reconstructions, split or duplicated points).  The solver needs *tracks*: the
same index for the same physical marker across frames.  This module gives them:

1. **Predict** every live track with constant velocity from its last
   measurement: ``p = p_last + v * dt`` (``dt`` since that measurement, so a
   track that missed frames predicts across the gap).
2. **Gate**: a point can only go to a track within ``gate(dt)`` of the
   prediction: ``gate_floor_m + max_accel_mps2 * dt**2`` for a track with a
   velocity (the constant-velocity error of an accelerating marker grows with
   dt^2), ``gate_floor_m + max_speed_mps * dt`` for a one-point track without
   one; both capped at ``max_gate_m``.  At 120 Hz the defaults give 29 mm.
3. **Assign** with the Hungarian algorithm (``scipy.optimize.linear_sum_assignment``;
   scipy is installed as a scikit-learn dependency) on the Gaussian negative
   log-likelihood ``d^2 / (2 s^2) + 3 ln s`` with ``s = gate / 3``, so of two
   candidate tracks the one predicting more tightly wins.  Confirmed tracks are
   assigned first; tentative tracks only get the points left over, so a ghost
   can never steal a real marker.
4. **Birth**: a leftover point starts a *tentative* track; it is confirmed (gets
   an id and an output slot) after ``birth_s`` of consecutive hits, and is
   dropped at its first miss.  Short-lived ghosts therefore never get an id.
   Leftover points within ``duplicate_radius_m`` of a point already given to a
   confirmed track are duplicate reconstructions and start nothing.
5. **Coast and death**: a confirmed track that misses keeps its id and slot
   for ``max_coast_s`` (predicting through the gap), so a marker re-appearing
   near its predicted position continues under the same id.  After that it
   dies; its id stays in a bounded *recently dead* list for ``reacquire_s`` and
   a new track confirmed within ``reacquire_radius_m`` of where it vanished
   inherits the id (and its old slot if still free).

Memory is bounded: at most ``max_tracks`` confirmed tracks (fixed output
arrays), ``max_tentative`` tentative ones, ``max_points`` input points per
frame and ``max_tracks`` recently dead ids.  Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

FREE, TENTATIVE, CONFIRMED = 0, 1, 2


@dataclass(frozen=True)
class TrackerConfig:
    """Defaults are for human full-body capture; frame counts quoted at 120 Hz."""

    # Nominal frame rate, used when frames carry no stamps and to turn times into frame counts.
    rate_hz: float = 120.0
    # Gate radius floor: measurement noise plus marker wobble on soft tissue (optical systems: ~1 mm
    # noise, soft-tissue artefact several mm).  15 mm.
    gate_floor_m: float = 0.015
    # Acceleration a marker may have that constant velocity cannot predict; wrist/foot strikes reach
    # ~100-200 m/s^2.  Gate grows by max_accel * dt^2: +14 mm at 120 Hz (total 29 mm), +1.3 mm at 400 Hz.
    max_accel_mps2: float = 200.0
    # Speed bound for a track seen once (no velocity yet): hands and feet peak near 6 m/s.
    # Gate = floor + 6 m/s * dt: 65 mm at 120 Hz.
    max_speed_mps: float = 6.0
    # Cap on any gate (long coasts): beyond this the prediction is not worth trusting.  60 mm.
    max_gate_m: float = 0.06
    # Weight of the newest finite-difference velocity (1 = no smoothing); optical data is precise
    # enough that little smoothing is needed, and smoothing lags real accelerations.
    velocity_gain: float = 0.8
    # Consecutive hits before a track is confirmed: 25 ms = 3 frames at 120 Hz (10 at 400 Hz).
    birth_s: float = 0.025
    # Minimum number of hits to confirm whatever the rate (two points give a velocity).
    min_birth_hits: int = 2
    # A tentative track survives missed frames for this long (flickering new markers still get born;
    # 0 = the first miss drops it).  10 ms = 1 missed frame at 120 Hz, 3 at 400 Hz.
    tentative_coast_s: float = 0.010
    # A confirmed track coasts (keeps id and slot, invisible) this long without a measurement:
    # 100 ms = 12 frames at 120 Hz, enough for a marker passing behind a limb.
    max_coast_s: float = 0.1
    # After death, a new track confirmed within this radius of the dead track's extrapolated
    # position within reacquire_s inherits its id.
    reacquire_s: float = 0.5
    reacquire_radius_m: float = 0.05
    # Extrapolate dead tracks with their velocity for at most this long (then assume they stopped).
    max_extrapolation_s: float = 0.1
    # Leftover points this close to a point of a confirmed track are duplicate reconstructions.
    duplicate_radius_m: float = 0.008
    # Fixed capacities (bounded memory and fixed-size output arrays).
    max_tracks: int = 128
    max_tentative: int = 256
    max_points: int = 1024

    def __post_init__(self):
        positive = ("rate_hz", "gate_floor_m", "max_gate_m", "birth_s", "max_coast_s")
        for name in positive:
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"TrackerConfig.{name} must be a positive number, got {getattr(self, name)!r}")
        if not 0 < self.velocity_gain <= 1:
            raise ValueError(f"TrackerConfig.velocity_gain must be in (0, 1], got {self.velocity_gain}")
        for name in ("max_tracks", "max_tentative", "max_points", "min_birth_hits"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TrackerConfig.{name} must be >= 1, got {getattr(self, name)}")

    @property
    def birth_hits(self) -> int:
        return max(self.min_birth_hits, int(math.ceil(self.birth_s * self.rate_hz - 1e-9)))


# Per input point: what became of it.
POINT_TRACKED = 0  # given to a confirmed track (``point_track_ids`` >= 0)
POINT_CANDIDATE = 1  # given to (or started) a tentative track: a young marker or a ghost
POINT_DUPLICATE = 2  # within duplicate_radius_m of a tracked point: a split/duplicate reconstruction
POINT_DROPPED = 3  # non-finite, beyond max_points, or no capacity left


@dataclass
class TrackedFrame:
    """Tracker output for one frame; track arrays are fixed-size over ``max_tracks`` output slots.

    track_ids (S,) int64: id of the confirmed track in each slot, -1 for an empty slot.
    positions (S,3) float32 metres: the measured point, NaN unless ``visible``.
    visible (S,) bool: the slot's track was measured this frame (a coasting track is invisible).
    point_track_ids (N,) int64: per input point, the confirmed track id it went to, else -1.
    point_status (N,) int8: POINT_TRACKED / POINT_CANDIDATE / POINT_DUPLICATE / POINT_DROPPED.
    point_serials (N,) int64: per input point, the serial of the (tentative or confirmed) track
        it went to, -1 if none.  Serials are internal; offline analysis uses them to tell, after
        the fact, which candidate points belonged to ghosts (never confirmed).
    """

    track_ids: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    point_track_ids: np.ndarray
    point_status: np.ndarray
    point_serials: np.ndarray


@dataclass
class TrackerStats:
    frames: int = 0
    points: int = 0
    assigned_points: int = 0  # points given to confirmed tracks
    rejected_points: int = 0  # points not given to confirmed tracks (ghosts, duplicates, young tracks)
    frames_with_rejections: int = 0
    duplicates: int = 0
    births: int = 0  # tracks confirmed with a new id
    reacquired: int = 0  # tracks confirmed with a recently dead track's id
    deaths: int = 0  # confirmed tracks that coasted out
    ghost_tracks: int = 0  # tentative tracks dropped before confirmation
    non_finite_points: int = 0
    capped_points: int = 0  # points beyond max_points
    overflow: int = 0  # tracks that could not be created or confirmed because capacity was full

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class _Tracks:
    """Struct-of-arrays track pool (tentative and confirmed)."""

    capacity: int
    state: np.ndarray = field(init=False)
    track_id: np.ndarray = field(init=False)
    slot: np.ndarray = field(init=False)
    last_pos: np.ndarray = field(init=False)
    velocity: np.ndarray = field(init=False)
    has_velocity: np.ndarray = field(init=False)
    serial: np.ndarray = field(init=False)
    last_time: np.ndarray = field(init=False)
    hits: np.ndarray = field(init=False)
    first_pos: np.ndarray = field(init=False)  # where and when a track was first seen (re-acquisition)
    first_time: np.ndarray = field(init=False)

    def __post_init__(self):
        n = self.capacity
        self.state = np.zeros(n, np.int8)
        self.track_id = np.full(n, -1, np.int64)
        self.slot = np.full(n, -1, np.int64)
        self.last_pos = np.zeros((n, 3))
        self.velocity = np.zeros((n, 3))
        self.has_velocity = np.zeros(n, bool)
        self.serial = np.full(n, -1, np.int64)
        self.last_time = np.zeros(n)
        self.hits = np.zeros(n, np.int64)
        self.first_pos = np.zeros((n, 3))
        self.first_time = np.zeros(n)


def gate_radius(dt: np.ndarray, has_velocity: np.ndarray, config: TrackerConfig) -> np.ndarray:
    """Gate radius (metres) for tracks last measured ``dt`` (K,) seconds ago."""
    with_v = config.gate_floor_m + config.max_accel_mps2 * dt**2
    without_v = config.gate_floor_m + config.max_speed_mps * dt
    return np.minimum(np.where(has_velocity, with_v, without_v), config.max_gate_m)


def gated_assignment(predicted: np.ndarray, gates: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost one-to-one matching of tracks to points inside their gates.

    predicted (K,3), gates (K,) metres, points (N,3).  Returns ``(track_idx, point_idx)`` of
    matched pairs.  Cost is the Gaussian negative log-likelihood with sigma = gate / 3.
    """
    if len(predicted) == 0 or len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d2 = ((predicted[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    inside = d2 <= (gates**2)[:, None]
    rows = np.flatnonzero(inside.any(1))
    cols = np.flatnonzero(inside.any(0))
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    sigma2 = (gates[rows] / 3.0) ** 2
    cost = d2[np.ix_(rows, cols)] / (2 * sigma2[:, None]) + 1.5 * np.log(sigma2)[:, None]
    sub_inside = inside[np.ix_(rows, cols)]
    # Out-of-gate pairs cost more than any two in-gate matchings can differ (2 * pairs * max|cost|),
    # so the solver first maximises the number of in-gate pairs, then minimises their cost; the
    # out-of-gate pairs it had to fill in are discarded below.
    big = 2.0 * (np.abs(cost[sub_inside]).max() + 1.0) * (min(len(rows), len(cols)) + 1)
    cost = np.where(sub_inside, cost, big)
    r, c = linear_sum_assignment(cost)
    keep = sub_inside[r, c]
    return rows[r[keep]], cols[c[keep]]


class MarkerTracker:
    """Streaming tracker.  ``step(points, stamp_ns)`` once per frame, in time order."""

    def __init__(self, config: TrackerConfig | None = None):
        self.config = config or TrackerConfig()
        self.reset()

    def reset(self) -> None:
        cfg = self.config
        self.pool = _Tracks(cfg.max_tracks + cfg.max_tentative)
        self.slot_released = np.full(cfg.max_tracks, -np.inf)  # time each output slot was freed
        self.slot_owner = np.full(cfg.max_tracks, -1, np.int64)  # pool index holding the slot
        self.dead_id = np.full(cfg.max_tracks, -1, np.int64)  # ring buffer of recently dead tracks
        self.dead_pos = np.zeros((cfg.max_tracks, 3))
        self.dead_vel = np.zeros((cfg.max_tracks, 3))
        self.dead_time = np.full(cfg.max_tracks, -np.inf)
        self.dead_slot = np.full(cfg.max_tracks, -1, np.int64)
        self._dead_next = 0
        self.next_id = 1
        self.next_serial = 0
        self.frame_index = 0
        self.time_s: float | None = None
        self.stats = TrackerStats()

    # -------------------------------------------------------------- helpers
    def _frame_time(self, stamp_ns) -> float:
        if stamp_ns is None:
            return self.frame_index / self.config.rate_hz
        t = int(stamp_ns) * 1e-9
        if self.time_s is not None and t <= self.time_s:
            raise ValueError(f"frame stamps must increase: {t:.9f} s after {self.time_s:.9f} s")
        return t

    def _predict(self, idx: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        p = self.pool
        dt = t - p.last_time[idx]
        horizon = np.minimum(dt, self.config.max_extrapolation_s)[:, None]
        pred = p.last_pos[idx] + np.where(p.has_velocity[idx, None], p.velocity[idx] * horizon, 0.0)
        return pred, gate_radius(dt, p.has_velocity[idx], self.config)

    def _update(self, idx: np.ndarray, meas: np.ndarray, t: float) -> None:
        p = self.pool
        dt = (t - p.last_time[idx])[:, None]
        v_new = (meas - p.last_pos[idx]) / dt
        g = self.config.velocity_gain
        p.velocity[idx] = np.where(p.has_velocity[idx, None], g * v_new + (1 - g) * p.velocity[idx], v_new)
        p.has_velocity[idx] = True
        p.last_pos[idx] = meas
        p.last_time[idx] = t
        p.hits[idx] += 1

    def _free(self, i: int) -> None:
        p = self.pool
        if p.slot[i] >= 0:
            self.slot_owner[p.slot[i]] = -1
        p.state[i] = FREE
        p.track_id[i] = -1
        p.slot[i] = -1
        p.hits[i] = 0
        p.has_velocity[i] = False

    def _bury(self, i: int, t: float) -> None:
        p = self.pool
        k = self._dead_next
        self._dead_next = (k + 1) % len(self.dead_id)
        self.dead_id[k], self.dead_pos[k], self.dead_vel[k] = p.track_id[i], p.last_pos[i], p.velocity[i]
        self.dead_time[k], self.dead_slot[k] = p.last_time[i], p.slot[i]
        self.slot_released[p.slot[i]] = t
        self._free(i)
        self.stats.deaths += 1

    def _confirm(self, i: int, t: float) -> bool:
        """Give tentative track ``i`` an id (a recently dead one if it re-appeared) and a slot."""
        cfg, p = self.config, self.pool
        free_slots = np.flatnonzero(self.slot_owner < 0)
        if len(free_slots) == 0:
            return False
        track_id, slot = -1, -1
        # Compare where the dead track was heading with where the new one was FIRST seen: the
        # shortest extrapolation, made before the new track's birth delay.
        t0 = p.first_time[i]
        gap = t0 - self.dead_time
        recent = np.flatnonzero((self.dead_id >= 0) & (gap > 0) & (gap <= cfg.reacquire_s))
        if len(recent):
            horizon = np.minimum(gap[recent], cfg.max_extrapolation_s)[:, None]
            guess = self.dead_pos[recent] + self.dead_vel[recent] * horizon
            dist = np.linalg.norm(guess - p.first_pos[i], axis=1)
            best = int(np.argmin(dist))
            if dist[best] <= cfg.reacquire_radius_m:
                k = recent[best]
                track_id = int(self.dead_id[k])
                if self.slot_owner[self.dead_slot[k]] < 0:
                    slot = int(self.dead_slot[k])
                self.dead_id[k] = -1
                self.stats.reacquired += 1
        if track_id < 0:
            track_id = self.next_id
            self.next_id += 1
            self.stats.births += 1
        if slot < 0:  # least recently released slot: delays re-use so downstream sees fewer id swaps
            slot = int(free_slots[np.argmin(self.slot_released[free_slots])])
        p.state[i], p.track_id[i], p.slot[i] = CONFIRMED, track_id, slot
        self.slot_owner[slot] = i
        return True

    # -------------------------------------------------------------- main step
    def step(self, points: np.ndarray, stamp_ns: int | None = None) -> TrackedFrame:
        """Track one frame.  points: (N,3) metres, any order; NaN rows are ignored.

        stamp_ns: capture stamp (must increase); None = frame count / ``rate_hz``.
        """
        cfg, p, st = self.config, self.pool, self.stats
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        t = self._frame_time(stamp_ns)
        n_in = len(points)
        status = np.full(n_in, POINT_DROPPED, np.int8)
        pool_of = np.full(n_in, -1, np.int64)  # pool index each input point went to
        finite = np.flatnonzero(np.isfinite(points).all(1))
        st.non_finite_points += n_in - len(finite)
        if len(finite) > cfg.max_points:
            st.capped_points += len(finite) - cfg.max_points
            finite = finite[: cfg.max_points]
        pts = points[finite]
        taken = np.zeros(len(pts), bool)

        # 1. Confirmed tracks first: a ghost or young track must never steal a real marker's point.
        conf = np.flatnonzero(p.state == CONFIRMED)
        ti, pi = gated_assignment(*self._predict(conf, t), pts)
        matched_conf = conf[ti]
        self._update(matched_conf, pts[pi], t)
        taken[pi] = True
        pool_of[finite[pi]] = matched_conf
        tracked_pts = pts[pi]

        # 2. Tentative tracks get what is left.
        tent = np.flatnonzero(p.state == TENTATIVE)
        left = np.flatnonzero(~taken)
        ti, pj = gated_assignment(*self._predict(tent, t), pts[left])
        matched_tent = tent[ti]
        self._update(matched_tent, pts[left[pj]], t)
        taken[left[pj]] = True
        pool_of[finite[left[pj]]] = matched_tent

        # 3. Misses: tentative tracks die after tentative_coast_s (ghosts), confirmed ones after
        #    max_coast_s (their id is remembered for re-acquisition).
        missed = np.setdiff1d(tent, matched_tent, assume_unique=True)
        missed = missed[t - p.last_time[missed] > cfg.tentative_coast_s]
        for i in missed:
            self._free(int(i))
        st.ghost_tracks += len(missed)
        missed = np.setdiff1d(conf, matched_conf, assume_unique=True)
        for i in missed[t - p.last_time[missed] > cfg.max_coast_s]:
            self._bury(int(i), t)

        # 4. Leftover points start tentative tracks, unless they duplicate a tracked point.
        rest = np.flatnonzero(~taken)
        if len(rest) and len(tracked_pts):
            d2 = ((pts[rest, None, :] - tracked_pts[None, :, :]) ** 2).sum(-1)
            dup = d2.min(1) <= cfg.duplicate_radius_m**2
            st.duplicates += int(dup.sum())
            status[finite[rest[dup]]] = POINT_DUPLICATE
            rest = rest[~dup]
        free = np.flatnonzero(p.state == FREE)
        n_new = max(0, min(len(rest), len(free), cfg.max_tentative - int((p.state == TENTATIVE).sum())))
        st.overflow += len(rest) - n_new
        new, rest = free[:n_new], rest[:n_new]
        p.state[new] = TENTATIVE
        p.last_pos[new] = p.first_pos[new] = pts[rest]
        p.last_time[new] = p.first_time[new] = t
        p.hits[new] = 1
        p.has_velocity[new] = False
        p.velocity[new] = 0.0
        p.serial[new] = np.arange(self.next_serial, self.next_serial + n_new)
        self.next_serial += n_new
        pool_of[finite[rest]] = new

        # 5. Births: tentative tracks with enough hits get an id and an output slot.
        candidates = np.concatenate([matched_tent, new])
        for i in candidates[p.hits[candidates] >= cfg.birth_hits]:
            if not self._confirm(int(i), t):
                st.overflow += 1

        went = pool_of >= 0
        status[went] = np.where(p.state[pool_of[went]] == CONFIRMED, POINT_TRACKED, POINT_CANDIDATE)
        track_ids = np.full(n_in, -1, np.int64)
        serials = np.full(n_in, -1, np.int64)
        serials[went] = p.serial[pool_of[went]]
        tracked = status == POINT_TRACKED
        track_ids[tracked] = p.track_id[pool_of[tracked]]

        st.frames += 1
        st.points += n_in
        n_tracked = int(tracked.sum())
        st.assigned_points += n_tracked
        st.rejected_points += n_in - n_tracked
        st.frames_with_rejections += int(n_in > n_tracked)
        self.time_s = t
        self.frame_index += 1
        return self._output(t, track_ids, status, serials)

    def _output(self, t: float, track_ids, status, serials) -> TrackedFrame:
        p = self.pool
        s = self.config.max_tracks
        ids = np.full(s, -1, np.int64)
        pos = np.full((s, 3), np.nan, np.float32)
        vis = np.zeros(s, bool)
        owners = np.flatnonzero(self.slot_owner >= 0)
        idx = self.slot_owner[owners]
        ids[owners] = p.track_id[idx]
        seen = p.last_time[idx] == t
        vis[owners[seen]] = True
        pos[owners[seen]] = p.last_pos[idx[seen]]
        return TrackedFrame(ids, pos, vis, track_ids, status, serials)


@dataclass
class TrackingResult:
    """Offline tracking of a whole recording (see :func:`track_sequence`).

    track_ids (T,S) int64, positions (T,S,3) float32 (NaN where invisible), visible (T,S) bool over
    the tracker's output slots; ``summary`` has counts and the ghost statistics.
    """

    track_ids: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    summary: dict


def track_sequence(frames, stamps_ns=None, config: TrackerConfig | None = None) -> TrackingResult:
    """Track a whole recording offline.

    frames: sequence of (N_t,3) point arrays, or a (T,M,3) array with NaN for absent points.
    stamps_ns: (T,) int64 capture stamps or None (frame index / config.rate_hz).

    summary: ``tracks`` (distinct confirmed ids), ``mean_track_frames`` (visible frames per id),
    ``ghost_points`` (points of tentative tracks that were never confirmed, plus duplicates),
    ``frames_with_ghosts_rejected`` (fraction of frames holding at least one such point),
    ``tracked_point_fraction`` and the tracker's counters.
    """
    tracker = MarkerTracker(config)
    ids, pos, vis = [], [], []
    frame_serials: list[np.ndarray] = []  # per frame, serials of candidate points
    frame_dups = []
    confirmed_serials: set[int] = set()
    for t, pts in enumerate(frames):
        out = tracker.step(pts, None if stamps_ns is None else int(stamps_ns[t]))
        ids.append(out.track_ids)
        pos.append(out.positions)
        vis.append(out.visible)
        confirmed_serials.update(out.point_serials[out.point_status == POINT_TRACKED].tolist())
        frame_serials.append(out.point_serials[out.point_status == POINT_CANDIDATE])
        frame_dups.append(int((out.point_status == POINT_DUPLICATE).sum()))
    s = tracker.config.max_tracks
    if not ids:
        empty = {"frames": 0, "tracks": 0}
        return TrackingResult(np.zeros((0, s), np.int64), np.zeros((0, s, 3), np.float32),
                              np.zeros((0, s), bool), empty)
    track_ids, positions, visible = np.stack(ids), np.stack(pos), np.stack(vis)
    # Candidate points whose track was confirmed later were a young marker, not a ghost.
    confirmed = np.fromiter(confirmed_serials, np.int64, len(confirmed_serials))
    ghost_counts = np.array([int((~np.isin(fs, confirmed)).sum()) + d for fs, d in zip(frame_serials, frame_dups)])
    per_id = np.bincount(track_ids[visible]) if visible.any() else np.zeros(0, np.int64)
    lengths = per_id[per_id > 0]
    st = tracker.stats
    summary = {
        "frames": len(ids),
        "tracks": int(len(lengths)),
        "mean_track_frames": float(lengths.mean()) if len(lengths) else 0.0,
        "median_track_frames": float(np.median(lengths)) if len(lengths) else 0.0,
        "max_track_frames": int(lengths.max()) if len(lengths) else 0,
        "mean_visible_tracks": float(visible.sum(1).mean()),
        "ghost_points": int(ghost_counts.sum()),
        "frames_with_ghosts_rejected": float((ghost_counts > 0).mean()),
        "tracked_point_fraction": st.assigned_points / max(st.points, 1),
        "birth_frames": tracker.config.birth_hits,
        **{f"stats_{k}": v for k, v in st.as_dict().items()},
    }
    return TrackingResult(track_ids, positions, visible, summary)
