"""Joining the columns of one marker back together (beyond the paper).

An unlabelled export of an optical system starts a new column each time a marker comes back from an
occlusion, so a 40-marker take arrives as hundreds of short columns.  The solve gives each column a
surface point; two columns are one marker's when the second starts where the first one's marker
would be: the first column's residual (measured minus predicted, in the frame of its face) carried
across the gap on the solved body, as ``gap_fill.body_fill`` carries it, lands on the second column's
first sample, and the same backwards.  Links are chosen by the Hungarian method (a column has at
most one successor and one predecessor), so a nearer marker of the same body region cannot take a
link that fits another column better.  ``stitch_columns`` returns the chains; ``merge_columns``
writes each chain as one column.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uuomocap.solver_core.gap_fill import column_spans


@dataclass(frozen=True)
class StitchConfig:
    # Largest handover error (m) of a link.  Session 45, an 8 s generated walk, 39 markers in 133
    # columns (occlusion 1 %, 10-frame hides), solved with `uuo`: the 94 true links 4.3 mm median,
    # 40 mm worst; the wrong candidates 85 mm at their 1st percentile; with 40 mm 93 of 94 links
    # made, none wrong (20 mm: 90, none wrong).
    max_handover_m: float = 0.04
    # Longest gap (s) a link may bridge: beyond it the body alone carries the marker (as the gap
    # fill does), and its pose through a long gap is the video prior's more than the markers'.
    max_gap_s: float = 1.0


def handover_costs(positions: np.ndarray, visible: np.ndarray, predicted: np.ndarray, frames: np.ndarray,
                   rate_hz: float, config: StitchConfig = StitchConfig()) -> np.ndarray:
    """(M, M) the handover error (m) of column a followed by column b, inf where b does not start
    after a ends within ``max_gap_s`` or either has no prediction there.

    positions (T, M, 3) metres; visible (T, M); predicted (T, M, 3) and frames (T, M, 3, 3) from
    ``gap_fill.solved_marker_positions(..., return_frames=True)``.  The error is the larger of: b's
    first sample against a's marker carried there (a's last residual, in its face's frame, on a's
    predicted point), and a's last sample against b's carried back."""
    x = np.asarray(positions, np.float64)
    first, last = column_spans(visible)
    M = x.shape[1]
    cost = np.full((M, M), np.inf)
    max_gap = config.max_gap_s * rate_hz
    for a in np.flatnonzero(last >= 0):
        e = last[a]
        later = np.flatnonzero((first > e) & (first - e <= max_gap))
        if later.size == 0 or not np.isfinite(predicted[e, a]).all():
            continue
        s = first[later]
        ok = np.isfinite(predicted[s, a]).all(-1) & np.isfinite(predicted[e, later]).all(-1) & np.isfinite(predicted[s, later]).all(-1)
        later, s = later[ok], s[ok]
        if later.size == 0:
            continue
        r_a = frames[e, a] @ (x[e, a] - predicted[e, a])  # a's residual in its face frame at its end
        ahead = predicted[s, a] + np.einsum("nij,i->nj", frames[s, a], r_a)  # a's marker at each b's start
        r_b = np.einsum("nij,nj->ni", frames[s, later], x[s, later] - predicted[s, later])
        back = predicted[e, later] + np.einsum("nij,ni->nj", frames[e, later], r_b)  # each b's marker at a's end
        cost[a, later] = np.maximum(np.linalg.norm(x[s, later] - ahead, axis=-1), np.linalg.norm(x[e, a] - back, axis=-1))
    return cost


def stitch_columns(positions: np.ndarray, visible: np.ndarray, predicted: np.ndarray, frames: np.ndarray, rate_hz: float,
                   config: StitchConfig = StitchConfig()) -> list[list[int]]:
    """Chains of columns that are one marker, each in time order; every column is in exactly one
    chain (a column without a link is a chain of one).  Chains are ordered by their first column."""
    from scipy.optimize import linear_sum_assignment

    M = np.asarray(visible).shape[1]
    cost = handover_costs(positions, visible, predicted, frames, rate_hz, config)
    allowed = cost <= config.max_handover_m
    nxt = np.full(M, -1)
    has_prev = np.zeros(M, bool)
    if allowed.any():
        rows, cols = np.flatnonzero(allowed.any(1)), np.flatnonzero(allowed.any(0))
        sub = np.where(allowed[np.ix_(rows, cols)], cost[np.ix_(rows, cols)], 1e6)
        for i, j in zip(*linear_sum_assignment(sub)):
            if sub[i, j] < 1e6:
                nxt[rows[i]], has_prev[cols[j]] = cols[j], True
    chains = []
    for start in range(M):
        if has_prev[start]:
            continue
        chain = [start]
        while nxt[chain[-1]] >= 0:
            chain.append(int(nxt[chain[-1]]))
        chains.append(chain)
    return chains


def merge_columns(positions: np.ndarray, visible: np.ndarray, chains: list[list[int]]) -> tuple[np.ndarray, np.ndarray]:
    """(T, len(chains), 3) positions and (T, len(chains)) visibility with each chain's columns written
    into one (they never overlap in time: a link needs the next column to start after the last ends)."""
    x, vis = np.asarray(positions, np.float64), np.asarray(visible, bool)
    out = np.full((x.shape[0], len(chains), 3), np.nan)
    seen = np.zeros((x.shape[0], len(chains)), bool)
    for k, chain in enumerate(chains):
        for c in chain:
            out[vis[:, c], k] = x[vis[:, c], c]
            seen[:, k] |= vis[:, c]
    return out, seen


def carried_positions(surface: np.ndarray, frames: np.ndarray, residual_local: np.ndarray) -> np.ndarray:
    """(K, 3) where each marker is now: its point's posed surface position ``surface`` (K, 3) plus
    its last residual ``residual_local`` (K, 3), kept in the frame of its face ``frames`` (K, 3, 3)
    (rows: edge, in-plane perpendicular, normal), as ``handover_costs`` carries it."""
    return np.asarray(surface) + np.einsum("kij,ki->kj", np.asarray(frames), np.asarray(residual_local))


def handover_links(new_positions: np.ndarray, carried: np.ndarray, max_m: float) -> list[tuple[int, int]]:
    """The causal half of ``stitch_columns``: (new column, ended marker) pairs, each at most once,
    by the Hungarian method on the distances of new_positions (N, 3) to carried (K, 3), only those
    within ``max_m`` metres."""
    from scipy.optimize import linear_sum_assignment

    new_positions, carried = np.asarray(new_positions, np.float64), np.asarray(carried, np.float64)
    if not len(new_positions) or not len(carried):
        return []
    cost = np.linalg.norm(new_positions[:, None, :] - carried[None, :, :], axis=-1)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    allowed = cost <= max_m
    if not allowed.any():
        return []
    rows, cols = linear_sum_assignment(np.where(allowed, cost, 1e6))
    return [(int(i), int(j)) for i, j in zip(rows, cols) if allowed[i, j]]
