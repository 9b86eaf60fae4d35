"""The video -> marker clock offset, found from the motion itself.

A phone started by hand is seconds off the mocap system's clock, and the session's
``clock_offset_s`` (marker time = video time + offset) is then a guess.  Beyond the paper (it
assumes synchronised streams): both streams see the same body move, so how fast the body
articulates - its points moving relative to the body, not the body travelling - is one signal
seen twice.  We compute it from each stream and take the offset that correlates them best:

* markers: per frame, each marker's speed relative to the markers' median velocity (the body's
  travel), averaged over the markers with the extremes trimmed (ghosts, track swaps and gaps
  give single wild values);
* video prior: per frame, each joint's speed relative to the pelvis under the prior's poses and
  mean shape (the prior has no translation; camera or world axes do not change a speed).

The correlation is Pearson's over the overlap at each candidate offset (so a partial overlap is
judged on what overlaps), on a grid of ``1 / rate_hz`` refined by a parabola through the peak.
Periodic motion (gait) correlates again one cycle away: the runner-up peak is reported beside
the best, and ``ambiguous`` says when it comes close; ``weak`` says when even the best peak is
low (a near-still take).  Two unrelated smooth signals can still correlate by chance (0.6 was
seen), so the summary always carries the numbers.

``estimate_session_clock_offset`` then lets the body decide: around the best peaks the prior body
is registered to the markers (``refine_clock_offset``), the best fit wins, and a fit that is not
clearly worse half a second either side (``fit_contrast``) cannot confirm the peak: ``flat_fit``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch

from .lbs import forward
from .prior_preparation import BodyPrior, fill_missing_prior_frames, prior_shape


@dataclass(frozen=True)
class ClockSyncConfig:
    # Grid of the offset search (the peak is refined between grid points).
    rate_hz: float = 60.0
    # Both signals are smoothed with a Gaussian of this sigma first: the prior's frame-to-frame
    # jitter and the markers' noise are fast, the body's articulation is not.
    smooth_s: float = 0.04
    # Candidate offsets must overlap the two streams by at least this many seconds, and by at
    # least this fraction of the shorter stream (short overlaps correlate by chance).
    min_overlap_s: float = 2.0
    min_overlap_fraction: float = 0.5
    # Search only |offset - centre| <= this (None: every offset with enough overlap).
    max_offset_s: float | None = None
    # A runner-up peak at least this far from the best counts as a separate candidate.
    runner_up_min_distance_s: float = 0.25
    # ``ambiguous`` when the runner-up peak ranks at least this fraction of the best (on the ranking score).
    ambiguous_ratio: float = 0.9
    # Below this correlation the two signals share too little to trust the peak (measured: right
    # offsets correlated 0.48-0.94; a near-still take's wrong peak 0.13, sensor noise alone 0.27).
    min_correlation: float = 0.4
    # Rank offsets by the significance of their correlation (Fisher z times the square root of the
    # overlap) instead of the correlation alone: a short overlap correlates high by chance.
    rank_by_significance: bool = True
    # Beyond the correlation: the offset is refined within +-refine_half_width_s (steps of
    # refine_step_s, then a parabola) by how well the prior body, registered to the markers by
    # the rigid yaw ICP of ``video-rr``, fits them on refine_frames frames.  The correlation peak
    # was 2-106 ms off on the CMU sessions; the fit's minimum sits at the true offset (session 43).
    refine_half_width_s: float = 0.25
    refine_step_s: float = 0.05
    refine_frames: int = 60
    # The fit also judges between correlation peaks: every peak ranking at least this fraction of
    # the best (up to refine_peaks of them) is refined, and the best fit wins.  Motions with few
    # cycles in a take (the generator's squat, arms, turn: 2-3) let a peak one cycle off rank first
    # by the correlation (6 of 105 bench sessions, session 43); the fit tells the cycles apart when
    # the motion does, and ``ambiguous`` says when it does not (the second fit within
    # fit_ambiguous_ratio of the best: on the bench's walk / run / turn the right offsets won by
    # 1.20-1.76x, the cycle-off ones by 1.10-1.21x).  The peaks are judged on the frames the video
    # covers at all of them; fits over different frames differ by more than the cycles do.  Further
    # such peaks are each checked by one fit at their centre (up to max_unjudged_checks; more is a
    # periodic motion, ``ambiguous``): the Hamner treadmill run peaks every step (0.35 s), and with
    # the true one fourth the fit picked a step off by 1.38x (session 44).
    candidate_ratio: float = 0.6
    refine_peaks: int = 3
    max_unjudged_checks: int = 4
    fit_ambiguous_ratio: float = 1.25
    # The refined offset is used only if the registered body fits the markers at least this many
    # times worse contrast_distance_s either side (``fit_contrast``): where it fits about as well at
    # any offset, the fit cannot confirm the correlation's peak, which may be chance.  Measured
    # (session 44): the one real capture's wrong offset (c3d.org, correlation 0.41, 1.7 s off) 1.05;
    # right offsets 1.13-1.68, BlazePose's prior on the CMU renders 1.25-1.41.  At +-0.25 s the V is
    # too shallow to tell (BlazePose 1.08-1.35).
    contrast_distance_s: float = 0.5
    min_fit_contrast: float = 1.10
    # Fraction trimmed at each end of the per-frame marker speeds before averaging.
    trim_fraction: float = 0.1


@dataclass(frozen=True)
class ClockOffsetEstimate:
    offset_s: float  # marker time = video time + offset_s
    correlation: float  # Pearson correlation of the two motion signals at offset_s
    overlap_s: float  # seconds the two streams overlap at offset_s
    runner_up_offset_s: float | None  # the best other peak (None when there is none)
    runner_up_correlation: float | None
    ambiguous: bool  # the runner-up correlates nearly as well (periodic motion): check the offset by eye
    weak: bool  # the best correlation is below ``min_correlation``: the streams share too little motion
    correlation_offset_s: float | None = None  # the correlation's peak, when offset_s was refined by the fit
    fit_rms_mm: float | None = None  # the registered prior body's marker fit at offset_s (refined only)
    candidates_s: tuple[float, ...] = ()  # the correlation peaks worth refining, best first
    # correlation peaks as strong as the candidates, beyond ``refine_peaks``: not refined, each checked
    # by one fit at its centre against the winner's on the frames the video covers at both
    unjudged_peaks_s: tuple[float, ...] = ()
    runner_up_fit_rms_mm: float | None = None  # the best fit among the other refined peaks
    # how much worse the fit is contrast_distance_s either side of offset_s (the better side):
    # near 1 the fit does not locate the offset at all (refined only)
    fit_contrast: float | None = None
    flat_fit: bool = False  # fit_contrast below ``min_fit_contrast``: the body fits as well elsewhere
    fit_points: tuple[tuple[float, float], ...] = ()  # every offset the fit scored: (offset s, RMS mm)

    @property
    def reliable(self) -> bool:
        return not (self.ambiguous or self.weak or self.flat_fit)

    def summary(self) -> str:
        text = f"{self.offset_s:+.3f} s ("
        if self.correlation_offset_s is not None:
            text += f"registered body fit {self.fit_rms_mm:.1f} mm"
            if self.fit_contrast is not None:
                text += f" ({self.fit_contrast:.2f}x worse either side)"
            if self.runner_up_fit_rms_mm is not None:
                text += f" against {self.runner_up_fit_rms_mm:.1f} at the next peak"
            text += f"; motion correlation peak {self.correlation_offset_s:+.3f} s, "
        text += f"correlation {self.correlation:.2f} over {self.overlap_s:.1f} s"
        if self.runner_up_offset_s is not None:
            text += f"; next best {self.runner_up_offset_s:+.3f} s at {self.runner_up_correlation:.2f}"
        text += ")"
        if self.weak:
            text += " - WEAK: the streams share too little motion to trust it"
        elif self.flat_fit:
            text += " - FLAT: the body fits the markers about as well at other offsets; check the offset by eye"
        elif self.ambiguous:
            text += " - AMBIGUOUS: the motion repeats (gait?); a hop or clap at the start of the take pins it"
        return text

    def to_dict(self) -> dict:
        return {"offset_s": self.offset_s, "correlation": self.correlation, "overlap_s": self.overlap_s,
                "runner_up_offset_s": self.runner_up_offset_s, "runner_up_correlation": self.runner_up_correlation,
                "ambiguous": self.ambiguous, "weak": self.weak, "reliable": self.reliable,
                "correlation_offset_s": self.correlation_offset_s, "fit_rms_mm": self.fit_rms_mm,
                "runner_up_fit_rms_mm": self.runner_up_fit_rms_mm, "fit_contrast": self.fit_contrast, "flat_fit": self.flat_fit,
                "fit_points": [list(p) for p in self.fit_points], "unjudged_peaks_s": list(self.unjudged_peaks_s)}


def _smooth(x: np.ndarray, dt: float, sigma_s: float) -> np.ndarray:
    """Gaussian smoothing of a 1-D signal with NaN gaps (NaN stays NaN; weights renormalised)."""
    if sigma_s <= 0:
        return x
    half = max(1, int(np.ceil(3 * sigma_s / dt)))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * dt / sigma_s) ** 2)
    ok = np.isfinite(x)
    # "full" then the centre: "same" returns the kernel's length for a signal shorter than the kernel
    num = np.convolve(np.where(ok, x, 0.0), k, mode="full")[half:half + len(x)]
    den = np.convolve(ok.astype(float), k, mode="full")[half:half + len(x)]
    out = np.full_like(x, np.nan, dtype=np.float64)
    out[ok] = num[ok] / den[ok]
    return out


def marker_motion_signal(positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray,
                         trim_fraction: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """How fast the markers move relative to the body's travel, per frame.

    positions: (T, M, 3) metres (NaN where missing); visible: (T, M) bool; stamps_ns: (T,) marker clock.
    Returns (times_s (T-1,) midpoints, speed (T-1,) m/s; NaN where fewer than 3 markers were seen
    in both frames).
    """
    p = np.asarray(positions, np.float64)
    vis = np.asarray(visible, bool) & np.isfinite(p).all(-1)
    t = np.asarray(stamps_ns, np.float64) * 1e-9
    if p.shape[0] < 2:
        raise ValueError("markers: need at least 2 frames to measure motion")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("markers: stamps must increase")
    both = vis[1:] & vis[:-1]
    vel = np.where(both[..., None], (p[1:] - p[:-1]) / dt[:, None, None], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a frame pair with no marker seen twice -> NaN
        travel = np.nanmedian(vel, axis=1)  # (T-1, 3): the body's travel
    rel = np.linalg.norm(vel - travel[:, None], axis=-1)  # (T-1, M), NaN where unseen
    rel = np.sort(np.where(np.isfinite(rel), rel, np.inf), axis=1)
    n = both.sum(1)
    speed = np.full(len(n), np.nan)
    for k in np.flatnonzero(n >= 3):  # a trimmed mean over the markers seen in both frames
        cut = int(np.floor(trim_fraction * n[k]))
        speed[k] = rel[k, cut:n[k] - cut].mean()
    return 0.5 * (t[1:] + t[:-1]), speed


def prior_motion_signal(model, prior: BodyPrior, batch: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """How fast the prior's joints move relative to its pelvis, per frame.

    prior: BodyPrior on its own (video) clock, camera or world frame; model: BodyModel of its betas.
    Returns (times_s (F-1,) midpoints on the video clock, speed (F-1,) m/s; NaN next to frames
    without an estimate).
    """
    if prior.num_frames < 2:
        raise ValueError("prior: need at least 2 frames to measure motion")
    filled = fill_missing_prior_frames(prior)
    betas = torch.as_tensor(prior_shape(prior) if prior.valid.any() else filled.betas_per_frame[0], dtype=torch.float32)[None]
    pose = torch.as_tensor(filled.poses72(), dtype=torch.float32)
    with torch.no_grad():
        joints = torch.cat([forward(model, betas, pose[i:i + batch]).joints for i in range(0, len(pose), batch)]).double().numpy()
    rel = joints - joints[:, :1]  # the prior has no translation: the pelvis is its origin
    t = prior.stamps_ns.astype(np.float64) * 1e-9
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("prior: stamps must increase")
    speed = np.linalg.norm(np.diff(rel, axis=0), axis=-1).mean(1) / dt
    ok = prior.valid[1:] & prior.valid[:-1]
    return 0.5 * (t[1:] + t[:-1]), np.where(ok, speed, np.nan)


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else float("nan")


@dataclass(frozen=True)
class CorrelationCurve:
    """The two motion signals on a common grid and their correlation at every offset searched.

    marker_t, marker_signal: (N,) seconds on the marker clock, smoothed m/s; prior_t, prior_signal:
    (K,) seconds on the video clock; offsets_s, correlation, overlap_s: (O,) the offsets searched
    (marker time = video time + offset), Pearson's r there (NaN: too little overlap or no motion)
    and the seconds of overlap.
    """

    marker_t: np.ndarray
    marker_signal: np.ndarray
    prior_t: np.ndarray
    prior_signal: np.ndarray
    offsets_s: np.ndarray
    correlation: np.ndarray
    overlap_s: np.ndarray


def correlation_curve(marker_t: np.ndarray, marker_speed: np.ndarray, prior_t: np.ndarray, prior_speed: np.ndarray,
                      config: ClockSyncConfig = ClockSyncConfig(), centre_s: float = 0.0) -> CorrelationCurve:
    """Both signals smoothed on a ``1 / config.rate_hz`` grid, correlated at every offset that
    overlaps them enough (see ``estimate_clock_offset`` for the arguments).  Raises ValueError when
    no offset can give the required overlap."""
    dt = 1.0 / config.rate_hz
    grid_m = np.arange(marker_t[0], marker_t[-1] + 1e-9, dt)
    m = _smooth(np.interp(grid_m, marker_t, np.where(np.isfinite(marker_speed), marker_speed, np.nan)), dt, config.smooth_s)
    # np.interp spreads NaN to both neighbours; that only loses a sample each side of a gap
    grid_p = np.arange(prior_t[0], prior_t[-1] + 1e-9, dt)
    p = _smooth(np.interp(grid_p, prior_t, np.where(np.isfinite(prior_speed), prior_speed, np.nan)), dt, config.smooth_s)
    span_m, span_p = grid_m[-1] - grid_m[0], grid_p[-1] - grid_p[0]
    need = max(config.min_overlap_s, config.min_overlap_fraction * min(span_m, span_p))
    lo, hi = grid_m[0] - grid_p[-1] + need, grid_m[-1] - grid_p[0] - need
    if config.max_offset_s is not None:
        lo, hi = max(lo, centre_s - config.max_offset_s), min(hi, centre_s + config.max_offset_s)
    if hi < lo:
        raise ValueError(f"the streams cannot overlap by {need:.1f} s (markers {span_m:.1f} s, video {span_p:.1f} s"
                         + (f", offsets within {config.max_offset_s} s of {centre_s:+.2f} s" if config.max_offset_s is not None else "") + ")")
    offsets = np.arange(lo, hi + 1e-9, dt)
    corr, overlap = np.full(len(offsets), np.nan), np.zeros(len(offsets))
    for i, o in enumerate(offsets):
        q = np.interp(grid_m - o, grid_p, p, left=np.nan, right=np.nan)  # the prior's signal on the marker grid
        ok = np.isfinite(q) & np.isfinite(m)
        overlap[i] = ok.sum() * dt
        if overlap[i] >= need and np.ptp(m[ok]) > 0 and np.ptp(q[ok]) > 0:
            corr[i] = _pearson(m[ok], q[ok])
    return CorrelationCurve(grid_m, m, grid_p, p, offsets, corr, overlap)


def estimate_clock_offset(marker_t: np.ndarray, marker_speed: np.ndarray, prior_t: np.ndarray, prior_speed: np.ndarray,
                          config: ClockSyncConfig = ClockSyncConfig(), centre_s: float = 0.0) -> ClockOffsetEstimate:
    """The offset (marker time = video time + offset) that best aligns the two motion signals.

    marker_t, marker_speed: (N,) seconds on the marker clock and m/s (``marker_motion_signal``);
    prior_t, prior_speed: (K,) seconds on the video clock and m/s (``prior_motion_signal``).
    centre_s: where ``config.max_offset_s`` is measured from (e.g. the session's recorded offset).
    Raises ValueError when no offset gives the required overlap or a signal does not move.
    """
    return _estimate_from_curve(correlation_curve(marker_t, marker_speed, prior_t, prior_speed, config, centre_s), config)


def _estimate_from_curve(curve: CorrelationCurve, config: ClockSyncConfig) -> ClockOffsetEstimate:
    """The best peak of ``curve``, its rivals and the candidates worth refining."""
    dt = 1.0 / config.rate_hz
    offsets, corr, overlap = curve.offsets_s, curve.correlation, curve.overlap_s
    if not np.isfinite(corr).any():
        raise ValueError("no offset gives an overlap where both streams move (a still subject, or no shared frames)")
    # the peak search runs on the ranking score; the correlations are what is reported
    score = np.arctanh(np.clip(corr, -0.999, 0.999)) * np.sqrt(overlap) if config.rank_by_significance else corr
    c = np.where(np.isfinite(corr), score, -np.inf)
    best = int(np.argmax(c))
    shift = 0.0
    if 0 < best < len(c) - 1 and np.isfinite(c[best - 1]) and np.isfinite(c[best + 1]):
        den = c[best - 1] - 2 * c[best] + c[best + 1]
        shift = float(np.clip(0.5 * (c[best - 1] - c[best + 1]) / den, -0.5, 0.5)) if den < 0 else 0.0
    # runner-up: the best local maximum far enough from the winner
    peaks = [i for i in range(len(c)) if np.isfinite(c[i]) and (i == 0 or c[i] >= c[i - 1]) and (i == len(c) - 1 or c[i] >= c[i + 1])
             and abs(offsets[i] - offsets[best]) >= config.runner_up_min_distance_s]
    runner = max(peaks, key=lambda i: c[i]) if peaks else None
    ambiguous = runner is not None and c[runner] >= config.ambiguous_ratio * c[best]
    # the peaks worth refining: local maxima ranking near the best, each far enough from those kept
    candidates = [best]
    for i in sorted(peaks, key=lambda i: -c[i]):
        if c[i] < config.candidate_ratio * c[best]:
            break
        if all(abs(offsets[i] - offsets[j]) >= config.runner_up_min_distance_s for j in candidates):
            candidates.append(i)
    unjudged = tuple(float(offsets[i]) for i in candidates[config.refine_peaks:])  # beyond what the refinement can afford
    candidates = candidates[:config.refine_peaks]
    return ClockOffsetEstimate(
        offset_s=float(offsets[best] + shift * dt), correlation=float(corr[best]), overlap_s=float(overlap[best]),
        runner_up_offset_s=None if runner is None else float(offsets[runner]),
        runner_up_correlation=None if runner is None else float(corr[runner]), ambiguous=bool(ambiguous),
        weak=bool(corr[best] < config.min_correlation),
        candidates_s=(float(offsets[best] + shift * dt), *(float(offsets[i]) for i in candidates[1:])), unjudged_peaks_s=unjudged)


def _covered(stamps_ns: np.ndarray, prior: BodyPrior, start_offset_s: float, end_offset_s: float) -> np.ndarray:
    """(T,) bool: marker frames inside the video's span moved by ``start_offset_s`` at its start and
    ``end_offset_s`` at its end (marker time = video time + offset)."""
    video = prior.stamps_ns[[0, -1]].astype(np.float64) * 1e-9
    t = np.asarray(stamps_ns, np.float64) * 1e-9
    return (t >= video[0] + start_offset_s) & (t <= video[1] + end_offset_s)


ALL_YAW_STARTS = (0.0, 90.0, 180.0, 270.0)


def _registered_fit(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, up_axis: str, prior: BodyPrior,
                    offset_s: float, frames: int, yaw_starts: tuple[float, ...] = ALL_YAW_STARTS) -> tuple[float, float]:
    """(yaw radians, RMS metres) of the video-clock prior, moved by ``offset_s`` onto the marker
    frames and registered to the markers by ``baselines.prior_yaw_registration`` on ``frames`` of them."""
    from .baselines import prior_yaw_registration
    from .prior_preparation import prepare_prior

    world, shape = prepare_prior(prior, up_axis, stamps_ns, offset_s)
    return prior_yaw_registration(positions, visible, up_axis, world, shape, model, yaw_starts, frames)


def refine_clock_offset(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, up_axis: str, prior: BodyPrior,
                        start_s: float, config: ClockSyncConfig = ClockSyncConfig()) -> tuple[float, float, tuple]:
    """Refine an offset by the marker fit of the prior body registered to the markers at each candidate.

    positions (T, M, 3) metres, visible (T, M), stamps_ns (T,) marker clock; prior on the video clock
    (camera frame); start_s: the offset to search around.  Returns (offset_s, RMS fit metres there,
    every offset scored as (offset_s, RMS metres) pairs in offset order).
    """
    k = int(round(config.refine_half_width_s / config.refine_step_s))
    # only marker frames the video covers at every candidate: beyond its ends the prior holds its
    # last pose, which fits worse or better by chance
    reach = k * config.refine_step_s
    inside = _covered(stamps_ns, prior, start_s + reach, start_s - reach)
    if inside.sum() < 2:
        raise ValueError("refining the clock offset: the video covers no marker frame at every candidate offset")
    positions, visible, stamps_ns = positions[inside], visible[inside], stamps_ns[inside]
    order = sorted(range(-k, k + 1), key=abs)  # the centre first: its four-start yaw serves the rest
    rms, yaw_starts = {}, ALL_YAW_STARTS
    for i in order:
        yaw, rms[i] = _registered_fit(model, positions, visible, stamps_ns, up_axis, prior, start_s + i * config.refine_step_s,
                                      config.refine_frames, yaw_starts)
        yaw_starts = (float(np.degrees(yaw)),)  # a fraction of a second does not turn the body
    best = min(rms, key=rms.get)
    shift = 0.0
    if -k < best < k:  # a parabola through the minimum and its neighbours
        a, b, c = rms[best - 1], rms[best], rms[best + 1]
        den = a - 2 * b + c
        shift = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den > 0 else 0.0
    scored = tuple((start_s + i * config.refine_step_s, float(rms[i])) for i in sorted(rms))
    return start_s + (best + shift) * config.refine_step_s, rms[best], scored


def fit_contrast(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, up_axis: str, prior: BodyPrior,
                 offset_s: float, config: ClockSyncConfig = ClockSyncConfig()) -> tuple[float, tuple] | None:
    """How much better the registered prior body fits the markers at ``offset_s`` than
    ``config.contrast_distance_s`` either side: the better side's RMS over the centre's, on the marker
    frames the video covers at all three (arguments as ``refine_clock_offset``).  Returns (contrast,
    ((offset_s, RMS metres), ...) of the two sides), or None when the video covers too few such frames.
    """
    far = config.contrast_distance_s
    inside = _covered(stamps_ns, prior, offset_s + far, offset_s - far)
    t = np.asarray(stamps_ns, np.float64)[inside] * 1e-9
    if inside.sum() < 2 or np.ptp(t) < config.min_overlap_s:
        return None
    positions, visible, stamps_ns = positions[inside], visible[inside], np.asarray(stamps_ns)[inside]
    rms = {}
    for o in (offset_s, offset_s - far, offset_s + far):  # every yaw start at each: the body may turn in a second
        rms[o] = _registered_fit(model, positions, visible, stamps_ns, up_axis, prior, o, config.refine_frames)[1]
    return min(rms[offset_s - far], rms[offset_s + far]) / rms[offset_s], ((offset_s - far, rms[offset_s - far]),
                                                                           (offset_s + far, rms[offset_s + far]))


def _an_unjudged_peak_fits(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, up_axis: str,
                           prior: BodyPrior, offset_s: float, peaks_s: tuple[float, ...], config: ClockSyncConfig) -> bool:
    """True when any of ``peaks_s`` fits (at its centre) within ``fit_ambiguous_ratio`` of ``offset_s``,
    both on the frames the video covers at the two, or when they share too little to tell."""
    if len(peaks_s) > config.max_unjudged_checks:  # a peak every step (a treadmill): periodic, no need to look
        return True
    t = np.asarray(stamps_ns, np.float64) * 1e-9
    for peak in peaks_s:
        both = _covered(stamps_ns, prior, max(peak, offset_s), min(peak, offset_s))
        if both.sum() < 2 or np.ptp(t[both]) < config.min_overlap_s:
            return True
        rms = [_registered_fit(model, positions[both], visible[both], np.asarray(stamps_ns)[both], up_axis, prior, o,
                               config.refine_frames)[1] for o in (offset_s, peak)]
        if rms[1] <= config.fit_ambiguous_ratio * rms[0]:
            return True
    return False


def session_correlation_curve(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, prior: BodyPrior,
                              config: ClockSyncConfig = ClockSyncConfig(), centre_s: float = 0.0) -> CorrelationCurve:
    """``correlation_curve`` from the markers (T, M, 3) and a video-clock prior, as
    ``estimate_session_clock_offset`` computes it (e.g. to draw it)."""
    mt, ms = marker_motion_signal(positions, visible, stamps_ns, config.trim_fraction)
    pt, ps = prior_motion_signal(model, prior)
    return correlation_curve(mt, ms, pt, ps, config, centre_s)


def estimate_session_clock_offset(model, positions: np.ndarray, visible: np.ndarray, stamps_ns: np.ndarray, prior: BodyPrior,
                                  config: ClockSyncConfig = ClockSyncConfig(), centre_s: float = 0.0,
                                  up_axis: str | None = None) -> ClockOffsetEstimate:
    """``estimate_clock_offset`` from the markers (T, M, 3) and a video-clock prior, in one call; with
    ``up_axis`` (the markers'), a clear peak is then refined by ``refine_clock_offset``."""
    est = _estimate_from_curve(session_correlation_curve(model, positions, visible, stamps_ns, prior, config, centre_s), config)
    if up_axis is None or est.weak or config.refine_half_width_s <= 0:
        return est
    candidates = est.candidates_s
    every_frame = (positions, visible, stamps_ns)  # the contrast looks at the winner alone, on all it covers
    if len(candidates) > 1:
        # judge the peaks on the same frames: those the video covers at every candidate's refinement
        # (fits over different frames differ by more than the cycles do)
        reach = config.refine_half_width_s
        common = _covered(stamps_ns, prior, max(candidates) + reach, min(candidates) - reach)
        t = np.asarray(stamps_ns, np.float64) * 1e-9
        if common.sum() < 2 or np.ptp(t[common]) < config.min_overlap_s:  # too little shared: the fit cannot judge
            candidates = candidates[:1]
            est = replace(est, ambiguous=True)
        else:
            positions, visible, stamps_ns = positions[common], visible[common], np.asarray(stamps_ns)[common]
    fits, peaks = [], []
    for c in candidates:
        try:
            fits.append(refine_clock_offset(model, positions, visible, stamps_ns, up_axis, prior, c, config))
            peaks.append(c)
        except ValueError:  # a peak so far out that the video covers no marker frame around it
            continue
    if not fits:
        raise ValueError("refining the clock offset: the video covers no marker frame around any correlation peak")
    order = sorted(range(len(fits)), key=lambda i: fits[i][1])
    offset, rms, _ = fits[order[0]]
    contrast = fit_contrast(model, *every_frame, up_axis, prior, offset, config)
    if contrast is None:  # a take too short to look that far: the refinement's own ends
        ends = dict(fits[order[0]][2])
        contrast = (min(ends[min(ends)], ends[max(ends)]) / rms, ())
    # a peak whose refinement slid to within runner_up_min_distance_s of the winner is the winner's
    # own minimum seen from its side (BlazePose's prior: a peak 0.34 s off refined to 0.08 s off)
    rivals = [fits[i][1] for i in order[1:] if abs(fits[i][0] - offset) >= config.runner_up_min_distance_s]
    other = rivals[0] if rivals else None
    if other is not None:  # with candidates to judge between, the fit decides the ambiguity
        ambiguous = other <= config.fit_ambiguous_ratio * rms
    else:
        ambiguous = est.ambiguous and len(fits) == 1
    if not ambiguous and est.unjudged_peaks_s:  # could a peak the refinement left out fit as well?
        ambiguous = _an_unjudged_peak_fits(model, *every_frame, up_axis, prior, offset, est.unjudged_peaks_s, config)
    return replace(est, offset_s=offset, correlation_offset_s=peaks[order[0]], fit_rms_mm=1000 * rms,
                   runner_up_fit_rms_mm=None if other is None else 1000 * other, ambiguous=bool(ambiguous),
                   fit_contrast=float(contrast[0]), flat_fit=bool(contrast[0] < config.min_fit_contrast),
                   fit_points=tuple(sorted((o, 1000 * r) for o, r in (*(p for f in fits for p in f[2]), *contrast[1]))))
