"""Unlabeled marker tracker: id stability through crossings, occlusions and ghosts; bounds."""

from __future__ import annotations

import itertools
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from uuomocap.solver_core.tracker import (
    POINT_CANDIDATE,
    POINT_DUPLICATE,
    POINT_TRACKED,
    MarkerTracker,
    TrackerConfig,
    gated_assignment,
    track_sequence,
)

RATE = 120.0
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _stamp(f: int, rate: float = RATE) -> int:
    return int(round(f / rate * 1e9))


def synthetic_markers(seed: int, frames: int = 600, markers: int = 20):
    """(T,M,3) smooth marker paths (speeds up to ~3 m/s) with one crossing pair, and visibility
    with three 5-frame occlusion gaps per marker."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / RATE
    centers = rng.uniform(-1, 1, (markers, 3))
    amp = rng.uniform(0.1, 0.4, (markers, 3))
    freq = rng.uniform(0.3, 1.2, (markers, 3))
    phase = rng.uniform(0, 2 * np.pi, (markers, 3))
    pos = centers + amp * np.sin(2 * np.pi * freq * t[:, None, None] + phase)
    # Markers 0 and 1 cross head-on, passing 12 mm apart at 2 x 0.4 m/s.
    s = t / t[-1]
    pos[:, 0] = np.stack([-1 + 2 * s, 0 * s, 0.5 + 0 * s], 1)
    pos[:, 1] = np.stack([1 - 2 * s, 0.012 + 0 * s, 0.5 + 0 * s], 1)
    pos += rng.normal(0, 0.0005, pos.shape)  # 0.5 mm reconstruction noise
    visible = np.ones((frames, markers), bool)
    for m in range(markers):
        starts = 20 + np.sort(rng.choice((frames - 40) // 15, 3, replace=False)) * 15
        for a in starts:
            visible[a:a + 5, m] = False
    return pos, visible


def run_with_ghosts(pos, visible, seed: int, ghosts_per_frame: float = 3.0, config=None):
    """Feed shuffled point clouds with ghosts; returns (tracker, [(labels, point_track_ids)])."""
    rng = np.random.default_rng(seed)
    tracker = MarkerTracker(config or TrackerConfig(rate_hz=RATE))
    frames, markers, _ = pos.shape
    records = []
    persistent_ghost = None
    for f in range(frames):
        pts = [pos[f, m] for m in range(markers) if visible[f, m]]
        labels = [m for m in range(markers) if visible[f, m]]
        for _ in range(rng.poisson(ghosts_per_frame)):  # one-frame ghosts anywhere in the volume
            pts.append(rng.uniform(-1.5, 1.5, 3))
            labels.append(-1)
        if f % 40 == 0:  # a ghost lasting 2 frames (shorter than the 3-frame birth)
            persistent_ghost = (rng.uniform(-1.5, 1.5, 3), 2)
        if persistent_ghost is not None and persistent_ghost[1] > 0:
            pts.append(persistent_ghost[0])
            labels.append(-1)
            persistent_ghost = (persistent_ghost[0], persistent_ghost[1] - 1)
        m = int(rng.integers(markers))
        if rng.random() < 0.1 and visible[f, m]:  # split reconstruction next to a real marker
            pts.append(pos[f, m] + rng.normal(0, 0.002, 3))
            labels.append(-2)
        order = rng.permutation(len(pts))
        out = tracker.step(np.asarray(pts)[order], _stamp(f))
        records.append((np.asarray(labels)[order], out.point_track_ids.copy()))
    return tracker, records


def assignment_accuracy(records) -> tuple[float, int, Counter]:
    """Fraction of real marker points given to that marker's majority track id, ghost points
    given to a track, and per-id counts of ghost points."""
    pairs = Counter((int(l), int(i)) for labels, ids in records for l, i in zip(labels, ids) if l >= 0 and i >= 0)
    best: dict[int, tuple[int, int]] = {}
    for (label, tid), n in pairs.items():
        if n > best.get(label, (-1, 0))[1]:
            best[label] = (tid, n)
    total = correct = ghosts_tracked = 0
    ghost_ids: Counter = Counter()
    for labels, ids in records:
        for label, tid in zip(labels, ids):
            if label >= 0:
                total += 1
                correct += label in best and best[label][0] == tid
            elif tid >= 0:
                ghosts_tracked += 1
                ghost_ids[int(tid)] += 1
    return correct / total, ghosts_tracked, ghost_ids


@pytest.mark.parametrize("seed", [0, 1])
def test_ids_stable_through_crossing_occlusion_and_ghosts(seed):
    pos, visible = synthetic_markers(seed)
    tracker, records = run_with_ghosts(pos, visible, seed + 10)
    accuracy, ghosts_tracked, ghost_ids = assignment_accuracy(records)
    assert accuracy >= 0.99, accuracy
    # Every marker got exactly one id: no id switches at the crossing or the 5-frame gaps.
    ids_of = {}
    for labels, ids in records:
        for label, tid in zip(labels, ids):
            if label >= 0 and tid >= 0:
                ids_of.setdefault(int(label), set()).add(int(tid))
    assert all(len(v) == 1 for v in ids_of.values()) and len(ids_of) == pos.shape[1]
    # Ghosts: thousands were fed; a handful of points at most landed on real tracks' gates.
    n_ghosts = sum(int((labels < 0).sum()) for labels, _ in records)
    assert n_ghosts > 1500
    assert ghosts_tracked <= 0.01 * n_ghosts
    assert tracker.stats.ghost_tracks > 1000
    # A chance chain of ghosts may get confirmed, but it never becomes a long track.
    per_id = Counter(int(i) for _, ids in records for i in ids if i >= 0)
    real_ids = set().union(*ids_of.values())
    assert tracker.stats.births <= pos.shape[1] + 3
    for tid, n in per_id.items():
        if tid not in real_ids:
            assert n <= 10, (tid, n)
        else:
            assert ghost_ids[tid] <= 0.02 * n


def test_crossing_markers_keep_ids_frame_by_frame():
    pos, _ = synthetic_markers(3, frames=300, markers=2)
    tracker = MarkerTracker(TrackerConfig(rate_hz=RATE))
    first = None
    for f in range(300):
        order = [1, 0] if f % 2 else [0, 1]
        out = tracker.step(pos[f, order], _stamp(f))
        ids = out.point_track_ids[np.argsort(order)]
        if f >= 2:
            first = ids if first is None else first
            assert (ids == first).all(), f


def test_occlusion_gap_keeps_id_and_slot():
    tracker = MarkerTracker(TrackerConfig(rate_hz=RATE))
    path = lambda f: np.array([[0.5 * f / RATE, 0.0, 1.0], [0.0, 0.3, 1.0]])  # noqa: E731
    for f in range(10):
        out = tracker.step(path(f), _stamp(f))
    slots_before = out.track_ids.copy()
    ids_before = out.point_track_ids.copy()
    for f in range(10, 15):  # marker 0 hidden for 5 frames: coasts, invisible, same slot
        out = tracker.step(path(f)[1:], _stamp(f))
        coasting = np.flatnonzero(slots_before == ids_before[0])[0]
        assert out.track_ids[coasting] == ids_before[0] and not out.visible[coasting]
        assert np.isnan(out.positions[coasting]).all()
    out = tracker.step(path(15), _stamp(15))
    assert (out.point_track_ids == ids_before).all()
    assert (out.track_ids == slots_before).all()


def test_reacquires_id_after_death_near_where_it_vanished():
    cfg = TrackerConfig(rate_hz=RATE)
    tracker = MarkerTracker(cfg)
    still = np.array([[0.2, 0.1, 1.0]])
    for f in range(10):
        out = tracker.step(still, _stamp(f))
    tid = int(out.point_track_ids[0])
    slot = int(np.flatnonzero(out.track_ids == tid)[0])
    gap = int(0.3 * RATE)  # 300 ms: longer than max_coast_s, so the track dies
    for f in range(10, 10 + gap):
        out = tracker.step(np.zeros((0, 3)), _stamp(f))
    assert tracker.stats.deaths == 1 and (out.track_ids == -1).all()
    for f in range(10 + gap, 10 + gap + cfg.birth_hits):
        out = tracker.step(still + 0.003, _stamp(f))
    assert out.point_track_ids[0] == tid and out.track_ids[slot] == tid
    assert tracker.stats.reacquired == 1 and tracker.stats.births == 1


def test_short_ghosts_never_get_ids_and_duplicates_are_flagged():
    cfg = TrackerConfig(rate_hz=RATE)
    tracker = MarkerTracker(cfg)
    rng = np.random.default_rng(0)
    real = np.array([[0.0, 0.0, 1.0]])
    for f in range(60):
        ghosts = rng.uniform(-2, 2, (5, 3))  # new random ghosts each frame
        # A split reconstruction 4 mm from the marker, once the marker is tracked.
        dup = real + [[0.004, 0.0, 0.0]] if f >= cfg.birth_hits else np.zeros((0, 3))
        out = tracker.step(np.concatenate([real, ghosts, dup]), _stamp(f))
        if f >= cfg.birth_hits:
            assert out.point_status[0] == POINT_TRACKED
            assert (out.point_status[1:6] == POINT_CANDIDATE).all()
            assert out.point_status[6] == POINT_DUPLICATE
            assert (out.point_track_ids[1:] == -1).all()
    assert tracker.stats.births == 1
    assert tracker.stats.duplicates == 60 - cfg.birth_hits


def test_capacity_is_fixed_and_overflow_counted():
    cfg = TrackerConfig(rate_hz=RATE, max_tracks=4, max_tentative=3, max_points=8)
    tracker = MarkerTracker(cfg)
    grid = np.array(list(itertools.product([0, 0.3, 0.6], [0, 0.3, 0.6], [1.0])))  # 9 points
    for f in range(20):
        out = tracker.step(grid, _stamp(f))
        assert out.track_ids.shape == (4,) and out.positions.shape == (4, 3) and out.visible.shape == (4,)
    assert (out.track_ids >= 0).sum() == 4
    assert tracker.stats.capped_points == 20  # 9 points, 8 allowed
    assert tracker.stats.overflow > 0
    assert (tracker.pool.state > 0).sum() <= 7


def test_bad_input_is_rejected_or_ignored():
    tracker = MarkerTracker(TrackerConfig(rate_hz=RATE))
    out = tracker.step(np.array([[np.nan, 0, 0], [0.0, 0.0, 1.0]]), _stamp(0))
    assert tracker.stats.non_finite_points == 1 and out.point_status[1] == POINT_CANDIDATE
    with pytest.raises(ValueError, match="increase"):
        tracker.step(np.zeros((1, 3)), _stamp(0))
    with pytest.raises(ValueError, match="gate_floor_m"):
        TrackerConfig(gate_floor_m=-1)
    with pytest.raises(ValueError, match="max_tracks"):
        TrackerConfig(max_tracks=0)
    assert TrackerConfig(rate_hz=120).birth_hits == 3 and TrackerConfig(rate_hz=400).birth_hits == 10


def test_gated_assignment_matches_brute_force():
    rng = np.random.default_rng(5)
    for _ in range(200):
        k, n = int(rng.integers(0, 5)), int(rng.integers(0, 5))
        pred = rng.uniform(0, 0.1, (k, 3))
        pts = rng.uniform(0, 0.1, (n, 3))
        gates = rng.uniform(0.01, 0.08, k)
        ti, pi = gated_assignment(pred, gates, pts)
        d = np.linalg.norm(pred[:, None] - pts[None], axis=2) if k and n else np.zeros((k, n))
        inside = d <= gates[:, None]
        assert inside[ti, pi].all()
        assert len(set(ti.tolist())) == len(ti) and len(set(pi.tolist())) == len(pi)
        # Maximum cardinality among gated matchings (brute force over injective maps).
        if k <= n:
            best = max((sum(inside[i, j] for i, j in enumerate(perm))
                        for perm in itertools.permutations(range(n), k)), default=0)
        else:
            best = max((sum(inside[i, j] for j, i in enumerate(perm))
                        for perm in itertools.permutations(range(k), n)), default=0)
        assert len(ti) == best


def test_offline_raw_unlabeled_trc():
    path = DATA / "markers" / "btk_unlabeled_400hz.trc"
    if not path.exists():
        pytest.skip("shared test data not present")
    from uuomocap.protocol.markerio import read_markers

    md = read_markers(path)
    frames = [md.positions[t][md.visible[t]] for t in range(len(md.positions))]
    result = track_sequence(frames, md.stamps_ns, TrackerConfig(rate_hz=md.rate_hz))
    s = result.summary
    print("btk_unlabeled_400hz.trc:", {k: s[k] for k in (
        "frames", "tracks", "mean_track_frames", "max_track_frames", "mean_visible_tracks",
        "ghost_points", "frames_with_ghosts_rejected", "tracked_point_fraction")})
    assert s["frames"] == len(md.positions)
    assert result.track_ids.shape == (len(md.positions), 128)
    # Only confirmed tracks are output, so every id lasted at least the birth time.
    assert s["tracks"] > 10 and s["mean_track_frames"] >= s["birth_frames"]
    assert s["max_track_frames"] > 400  # some markers are followed for over a second
    assert 0.0 < s["frames_with_ghosts_rejected"] < 1.0
    assert 0.4 < s["tracked_point_fraction"] < 1.0


def test_track_cli_writes_one_column_per_track(tmp_path, capsys):
    import json

    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers, write_trc

    pos, visible = synthetic_markers(4, frames=240, markers=6)
    pos = np.where(visible[..., None], pos, np.nan)
    # Shuffle columns every frame: a raw stream's columns are point lists, not markers.
    rng = np.random.default_rng(0)
    raw = np.stack([p[rng.permutation(6)] for p in pos])
    write_trc(tmp_path / "raw.trc", raw, RATE)
    assert main(["track", str(tmp_path / "raw.trc"), "--out", str(tmp_path / "tracked.c3d"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["tracks"] == 6 and report["out"]["tracks_written"] == 6
    tracked = read_markers(tmp_path / "tracked.c3d")
    assert tracked.positions.shape == (240, 6, 3)
    # Each written column follows one synthetic marker: match columns to markers on a visible frame.
    f = 100
    d = np.linalg.norm(tracked.positions[f][:, None] - pos[f][None], axis=2)
    match = np.nanargmin(np.where(np.isnan(d), np.inf, d), axis=1)
    both = tracked.visible & visible[:, match]
    err = np.linalg.norm(tracked.positions - pos[:, match], axis=2)[both]
    assert both.sum() > 0.95 * visible.sum() and err.max() < 1e-4
