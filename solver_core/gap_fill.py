"""Filling a marker's gaps from the solved body (beyond the paper: what a labelled pipeline does next).

A capture loses markers to occlusion; a technician fills the gaps before the data goes on.
Trajectory fills (linear, spline) know nothing of the body and drift on gaps longer than a few
frames.  The solve knows where each marker rides (its face + barycentric point and the 9.5 mm
offset) and where the body is in every frame, so it predicts the marker through the gap.  The
prediction is off by the marker's fit residual (skin motion, the point's error), which changes
slowly: the fill adds to the prediction the residual measured at the gap's two edges, blended
linearly across it, so the filled path joins the measured one without a step at either end
(the idea of a "pattern" or "rigid body" fill, with the body as the donor).

``solved_marker_positions`` predicts, ``body_fill`` fills; ``linear_fill`` and ``spline_fill``
are the trajectory fills a user would otherwise run (``uuomocap bench gap-fill`` compares them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class GapSpan:
    """One gap of one marker column: frames ``start`` .. ``stop - 1`` missing, seen at
    ``start - 1`` and at ``stop`` (gaps at the take's ends are not spans: nothing bounds them)."""

    marker: int
    start: int
    stop: int

    @property
    def frames(self) -> int:
        return self.stop - self.start


def column_spans(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, last) seen frame of every column (M,), -1 for a column never seen.  visible: (T, M)."""
    vis = np.asarray(visible, bool)
    seen = vis.any(0)
    first = np.where(seen, vis.argmax(0), -1)
    last = np.where(seen, vis.shape[0] - 1 - vis[::-1].argmax(0), -1)
    return first, last


def _line_across(before: np.ndarray, after: np.ndarray, frames: int) -> np.ndarray:
    """(frames, 3) a straight line from the sample before a gap to the one after it, exclusive."""
    w = (np.arange(1, frames + 1) / (frames + 1))[:, None]
    return (1 - w) * before + w * after


def bounded_gaps(visible: np.ndarray) -> list[GapSpan]:
    """Every gap bounded by seen frames on both sides.  visible: (T, M) bool."""
    vis = np.asarray(visible, bool)
    spans = []
    for m in range(vis.shape[1]):
        seen = np.flatnonzero(vis[:, m])
        if seen.size < 2:
            continue
        jumps = np.flatnonzero(np.diff(seen) > 1)
        spans += [GapSpan(m, int(seen[j]) + 1, int(seen[j + 1])) for j in jumps]
    return spans


def solved_marker_positions(model, betas: np.ndarray, poses: np.ndarray, trans: np.ndarray, marker_faces: np.ndarray,
                            marker_bary: np.ndarray, offset_m: float = 0.0095, chunk: int = 256,
                            return_frames: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Where the solved body puts each marker: its surface point plus ``offset_m`` along the smooth
    skin normal (the offline IK's marker model, ``inverse_kinematics.predicted_markers``).

    betas: (B,) or (T, B) a shape per frame (streamed solves); poses: (T, 72) world axis-angle;
    trans: (T, 3) metres; marker_faces: (M,) face ids, -1 = no point; marker_bary: (M, 3).
    Returns (T, M, 3) metres, NaN for unassigned markers and for frames the solve left empty; with
    ``return_frames`` also (T, M, 3, 3) the posed frame of each marker's face (rows: edge, in-plane
    perpendicular, normal; ``inverse_kinematics.triangle_frames``), for ``body_fill``.
    """
    from uuomocap.solver_core import lbs
    from uuomocap.solver_core.body_params import MarkerAttachment
    from uuomocap.solver_core.inverse_kinematics import (offset_directions, posed_marker_frames,
                                                          smooth_normals_in_face_frames, triangle_frames)

    poses, trans = np.asarray(poses, np.float64), np.asarray(trans, np.float64)
    faces = np.asarray(marker_faces, np.int64)
    betas = np.asarray(betas, np.float64)
    T, M = poses.shape[0], faces.shape[0]
    out = np.full((T, M, 3), np.nan)
    frames = np.full((T, M, 3, 3), np.nan) if return_frames else None
    assigned = faces >= 0
    if not assigned.any():
        return (out, frames) if return_frames else out
    frame_betas = betas if betas.ndim == 2 else np.broadcast_to(betas, (T, betas.shape[-1]))
    solved = np.isfinite(poses).all(1) & np.isfinite(trans).all(1) & np.isfinite(frame_betas).all(1)
    att = MarkerAttachment(torch.as_tensor(faces), torch.as_tensor(np.asarray(marker_bary, np.float64)), torch.zeros(M))
    corners = lbs.SurfacePoints.from_vertex_ids(model.faces[att.face_ids[att.assigned]].reshape(-1))
    bary = att.bary[att.assigned].float()
    rows = np.flatnonzero(solved)
    smooth_cache: dict[bytes, torch.Tensor] = {}  # a streamed solve changes shape a few times per take
    with torch.no_grad():
        for s in range(0, rows.size, chunk):
            r = rows[s:s + chunk]
            b = torch.as_tensor(frame_betas[r], dtype=torch.float32)
            o = lbs.forward(model, b, torch.as_tensor(poses[r], dtype=torch.float32), torch.as_tensor(trans[r], dtype=torch.float32),
                            points=corners)
            c = o.vertices.reshape(len(r), -1, 3, 3)
            pts, nrm = posed_marker_frames(c, bary)
            # one smooth normal per distinct shape (it is computed in the rest pose of that shape)
            offsets = torch.empty_like(pts)
            keys = [frame_betas[i].tobytes() for i in r]
            for key in dict.fromkeys(keys):
                if key not in smooth_cache:
                    smooth_cache[key] = smooth_normals_in_face_frames(model, torch.as_tensor(np.frombuffer(key).copy()), att)
                sel = torch.as_tensor([k == key for k in keys])
                offsets[sel] = offset_directions(c[sel], nrm[sel], smooth_cache[key])
            out[r[:, None], np.flatnonzero(assigned)[None, :]] = (pts + offset_m * offsets).double().numpy()
            if frames is not None:
                frames[r[:, None], np.flatnonzero(assigned)[None, :]] = triangle_frames(c).double().numpy()
    return (out, frames) if return_frames else out


@dataclass(frozen=True)
class GapFillConfig:
    """How ``body_fill`` turns the body's prediction into a fill (beyond the paper).  Measured with
    ``uuomocap bench gap-fill`` on the four labelled captures of ../shared/data/markers (60-128 Hz;
    session 45; RMS mm over the cut samples at gaps of 0.1 / 0.25 / 0.5 / 1 / 2 s): the prediction
    as solved with a linear residual blend 8.0 / 10.1 / 7.7 / 13.8 / 12.0; smoothed (0.02 s) 4.1 /
    7.3 / 6.5 / 11.5 / 11.5; and the residual carried in with its edge slopes 2.7 / 6.1 / 6.3 /
    10.9 / 11.4 (a cubic spline of the markers: 1.8 / 17.0 / 61.5 / 160.9 / 280.0)."""

    # Gaussian sigma (s) of the prediction along time: a solve jitters from frame to frame at
    # 100-128 Hz, a marker does not (0.01 / 0.02 / 0.03 s: 4.3 / 2.7 / 2.3 mm at 0.1 s gaps, 11.6 /
    # 10.9 / 11.2 at 1 s; 0 = as solved).
    smooth_s: float = 0.02
    # The residual's slope at each edge, fitted over this many seconds of seen frames beside it
    # (a cubic Hermite blend between the edges instead of a line: it joins the measured path
    # without a kink).
    slope_s: float = 0.05
    # A slope carries over at most this many seconds into the gap (its weight shrinks as
    # fade_s / gap for longer gaps): a slope extrapolated across a long gap overshoots.
    slope_fade_s: float = 0.1


def smooth_along_time(track: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 of (T, ...) that skips NaN samples (normalised
    convolution); NaN stays NaN."""
    from scipy.ndimage import gaussian_filter1d

    if sigma_frames <= 0:
        return track
    ok = np.isfinite(track)
    num = gaussian_filter1d(np.where(ok, track, 0.0), sigma_frames, axis=0, mode="nearest")
    den = gaussian_filter1d(ok.astype(np.float64), sigma_frames, axis=0, mode="nearest")
    return np.where(ok, num / np.maximum(den, 1e-12), np.nan)


def _edge_slope(local: np.ndarray) -> np.ndarray:
    """Least-squares slope (3,) per frame of residuals (n, 3) on consecutive frames; 0 for n < 2."""
    n = local.shape[0]
    if n < 2:
        return np.zeros(3)
    t = np.arange(n) - (n - 1) / 2
    return (t[:, None] * (local - local.mean(0))).sum(0) / (t ** 2).sum()


def _seen_run(ok: np.ndarray, edge: int, step: int, n: int) -> np.ndarray:
    """Frames edge, edge + step, ... (at most max(1, n)) while ``ok`` (T,) holds."""
    out = [edge]
    while len(out) < max(1, n) and 0 <= out[-1] + step < ok.shape[0] and ok[out[-1] + step]:
        out.append(out[-1] + step)
    return np.asarray(out)


def body_fill(positions: np.ndarray, visible: np.ndarray, predicted: np.ndarray, frames: np.ndarray | None = None,
              rate_hz: float | None = None, max_gap_frames: int | None = None,
              config: GapFillConfig = GapFillConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Fill every bounded gap (``bounded_gaps``) from the body's prediction, corrected by the marker's
    residual (measured minus predicted) carried from the gap's edges.

    positions: (T, M, 3) metres (anything where not visible); visible: (T, M) bool; predicted:
    (T, M, 3) from ``solved_marker_positions``; frames: its (T, M, 3, 3) face frames, or None;
    rate_hz: the frame rate (None: the prediction is used as it is and the residual is blended
    linearly, as ``GapFillConfig`` all 0).
    With frames the residual is blended in the frame of the marker's face, so it turns with the
    body segment through the gap: a marker whose solved point is 2 cm off rides the segment at
    that offset, where a residual fixed in the world would stay behind as the limb turns.
    A gap is left open when it is longer than ``max_gap_frames`` or the body is not predicted on
    every one of its frames and both edges.
    Returns (positions with the filled samples, NaN where still missing; filled (T, M) bool).
    """
    vis = np.asarray(visible, bool)
    pos = np.where(vis[..., None], np.asarray(positions, np.float64), np.nan)
    filled = np.zeros(pos.shape[:2], bool)
    T = pos.shape[0]
    c = config if rate_hz else GapFillConfig(smooth_s=0.0, slope_s=0.0, slope_fade_s=0.0)
    rate = rate_hz or 1.0
    predicted = smooth_along_time(np.asarray(predicted, np.float64), c.smooth_s * rate)
    context = max(2, int(round(c.slope_s * rate))) if c.slope_s > 0 else 0
    usable = np.isfinite(predicted).all(-1)

    def to_local(t: np.ndarray, m: int) -> np.ndarray:  # residuals (n, 3) of seen frames t, in the face frames
        r = pos[t, m] - predicted[t, m]
        return r if frames is None else np.einsum("tij,tj->ti", frames[t, m], r)

    for g in bounded_gaps(vis):
        m = g.marker
        if max_gap_frames is not None and g.frames > max_gap_frames:
            continue
        if not np.isfinite(predicted[g.start - 1:g.stop + 1, m]).all():
            continue
        lb = to_local(_seen_run(vis[:, m] & usable[:, m], g.start - 1, -1, context)[::-1], m)  # ends at the edge
        la = to_local(_seen_run(vis[:, m] & usable[:, m], g.stop, 1, context), m)  # starts at the edge
        if context:  # cubic Hermite between the edge residuals; tangents per frame, faded on long gaps
            span = g.frames + 1  # frames from the edge before to the edge after
            s = (np.arange(1, span) / span)[:, None]
            fade = min(1.0, c.slope_fade_s * rate / span)
            local = ((2 * s ** 3 - 3 * s ** 2 + 1) * lb[-1] + (-2 * s ** 3 + 3 * s ** 2) * la[0]
                     + fade * span * ((s ** 3 - 2 * s ** 2 + s) * _edge_slope(lb) + (s ** 3 - s ** 2) * _edge_slope(la)))
        else:  # no slopes: the linear blend (a Hermite with zero tangents would ease in and out)
            local = _line_across(lb[-1], la[0], g.frames)
        inner = predicted[g.start:g.stop, m]
        pos[g.start:g.stop, m] = inner + (local if frames is None else np.einsum("tij,ti->tj", frames[g.start:g.stop, m], local))
        filled[g.start:g.stop, m] = True
    return pos, filled


def linear_fill(positions: np.ndarray, visible: np.ndarray, max_gap_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Straight lines across bounded gaps (the simplest trajectory fill).  Same arrays as ``body_fill``."""
    pos = np.where(np.asarray(visible, bool)[..., None], np.asarray(positions, np.float64), np.nan)
    filled = np.zeros(pos.shape[:2], bool)
    for g in bounded_gaps(visible):
        if max_gap_frames is not None and g.frames > max_gap_frames:
            continue
        pos[g.start:g.stop, g.marker] = _line_across(pos[g.start - 1, g.marker], pos[g.stop, g.marker], g.frames)
        filled[g.start:g.stop, g.marker] = True
    return pos, filled


def spline_fill(positions: np.ndarray, visible: np.ndarray, max_gap_frames: int | None = None,
                context_frames: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A cubic spline through the seen samples within ``context_frames`` either side of each bounded
    gap (the spline fill of labelling tools; scipy's not-a-knot ``CubicSpline``).  Same arrays as
    ``body_fill``."""
    from scipy.interpolate import CubicSpline

    vis = np.asarray(visible, bool)
    pos = np.where(vis[..., None], np.asarray(positions, np.float64), np.nan)
    filled = np.zeros(pos.shape[:2], bool)
    T = pos.shape[0]
    for g in bounded_gaps(vis):
        if max_gap_frames is not None and g.frames > max_gap_frames:
            continue
        lo, hi = max(0, g.start - context_frames), min(T, g.stop + context_frames)
        t = np.flatnonzero(vis[lo:hi, g.marker]) + lo
        # samples already filled are not measurements: only seen ones carry the spline
        if t.size < 4:  # too few for a cubic: a line
            pos[g.start:g.stop, g.marker] = _line_across(pos[g.start - 1, g.marker], pos[g.stop, g.marker], g.frames)
        else:
            pos[g.start:g.stop, g.marker] = CubicSpline(t, pos[t, g.marker], axis=0)(np.arange(g.start, g.stop))
        filled[g.start:g.stop, g.marker] = True
    return pos, filled
