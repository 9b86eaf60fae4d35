"""Filling marker gaps from the solved body (solver_core.gap_fill, `label --fill-gaps`, `bench gap-fill`)."""

import json

import numpy as np


def test_bounded_gaps_are_the_gaps_seen_on_both_sides():
    from uuomocap.solver_core.gap_fill import GapSpan, bounded_gaps

    vis = np.ones((12, 3), bool)
    vis[3:6, 0] = False     # bounded: 3 frames
    vis[:2, 1] = False      # before the first sighting: nothing bounds it
    vis[8, 1] = False       # bounded: 1 frame
    vis[10:, 1] = False     # after the last sighting
    vis[:, 2] = False
    vis[5, 2] = True        # seen once: no gap is bounded
    assert bounded_gaps(vis) == [GapSpan(0, 3, 6), GapSpan(1, 8, 9)]
    assert bounded_gaps(vis)[0].frames == 3


def test_body_fill_removes_a_drifting_residual_and_leaves_what_it_cannot_fill_open():
    from uuomocap.solver_core.gap_fill import body_fill, linear_fill, spline_fill

    T = 40
    t = np.arange(T, dtype=float)
    truth = np.stack([np.stack([np.sin(t / 4 + k), np.cos(t / 5), 0.01 * t], -1) for k in range(3)], 1)  # (T, 3, 3)
    # the body's prediction is off by a residual that drifts linearly (a point slightly off, skin sliding)
    drift = np.array([0.01, -0.02, 0.005])[None, None, :] * (1 + t[:, None, None] / T)
    predicted = truth + drift
    vis = np.ones((T, 3), bool)
    vis[10:25, 0] = False   # filled, exactly: the drift is linear across the gap
    vis[30:, 1] = False     # at the take's end: left open
    vis[5:9, 2] = False
    predicted[6, 2] = np.nan  # the body was not solved there: left open
    filled_pos, filled = body_fill(truth, vis, predicted)
    np.testing.assert_allclose(filled_pos[10:25, 0], truth[10:25, 0], atol=1e-12)
    assert filled[10:25, 0].all() and not filled[30:, 1].any() and not filled[:, 2].any()
    assert np.isnan(filled_pos[30:, 1]).all() and np.isnan(filled_pos[5:9, 2]).all()
    np.testing.assert_array_equal(filled_pos[vis], truth[vis])  # measured samples untouched
    assert not body_fill(truth, vis, predicted, max_gap_frames=14)[1].any()  # the 15-frame gap is too long
    # the trajectory fills are exact where their model is: a line, a cubic
    line = np.repeat((0.3 * t)[:, None, None], 3, -1)
    np.testing.assert_allclose(linear_fill(line[:, :1], vis[:, :1])[0][10:25], line[10:25, :1], atol=1e-12)
    cubic = np.repeat((1e-4 * (t - 20) ** 3)[:, None, None], 3, -1)
    np.testing.assert_allclose(spline_fill(cubic[:, :1], vis[:, :1])[0][10:25], cubic[10:25, :1], atol=1e-9)
    # a residual fixed on a turning segment: blended in the segment's frame it is exact, fixed in the world it is not
    angle = np.linspace(0, np.pi, T)
    frames = np.zeros((T, 1, 3, 3))
    frames[:, 0] = [[[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]] for a in angle]  # rows: axes
    local = np.array([0.02, 0.0, 0.01])
    marker = truth[:, :1] + np.einsum("tij,i->tj", frames[:, 0], local)[:, None]
    turned = body_fill(marker, vis[:, :1], truth[:, :1], frames=frames)[0]
    np.testing.assert_allclose(turned[10:25], marker[10:25], atol=1e-12)
    assert np.abs(body_fill(marker, vis[:, :1], truth[:, :1])[0][10:25] - marker[10:25]).max() > 0.003  # the chord cuts the arc
    # and the body beats them on the sine
    err = {name: np.abs(f(truth, vis)[0][10:25, 0] - truth[10:25, 0]).max() for name, f in (("line", linear_fill), ("spline", spline_fill))}
    assert min(err.values()) > 0.1, err


def test_body_fill_at_the_frame_rate_smooths_a_jittering_body_and_carries_the_residuals_slope():
    from uuomocap.solver_core.gap_fill import body_fill, smooth_along_time

    rate, T = 100.0, 200
    t = np.arange(T) / rate
    marker = np.stack([0.3 * np.sin(2 * t), 0.2 * np.cos(3 * t), 1 + 0.1 * t], -1)[:, None]  # (T, 1, 3)
    # the body follows the marker up to a residual that drifts on a curve (skin sliding) and jitters per frame
    residual = np.stack([0.01 * np.sin(4 * t), 0.005 * t, np.zeros(T)], -1)[:, None]
    jitter = 0.002 * np.where(np.arange(T) % 2, 1.0, -1.0)[:, None, None]
    predicted = marker - residual + jitter
    vis = np.ones((T, 1), bool)
    vis[80:95] = False  # 0.15 s
    err = {}
    for name, kwargs in (("as solved, linear", {}), ("at the rate", {"rate_hz": rate})):
        filled, mask = body_fill(marker, vis, predicted, **kwargs)
        assert mask[80:95, 0].all()
        err[name] = np.linalg.norm(filled[80:95, 0] - marker[80:95, 0], axis=-1).max()
    assert err["at the rate"] < 0.5e-3 < 2e-3 < err["as solved, linear"], err
    # NaN samples are skipped by the smoothing and stay NaN
    track = np.arange(10.0)[:, None].repeat(3, 1)
    track[4] = np.nan
    out = smooth_along_time(track, 1.0)
    assert np.isnan(out[4]).all() and np.isfinite(np.delete(out, 4, 0)).all()
    np.testing.assert_allclose(out[:, 0][[0, 9]], [0.6, 8.4], atol=0.4)  # a line stays near itself


def test_solved_marker_positions_are_where_the_generator_put_the_markers(tmp_path):
    from uuomocap.cli import main
    from uuomocap.protocol.session import load_session
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.gap_fill import solved_marker_positions

    sd = tmp_path / "s"
    assert main(["sample", "make", str(sd), "--motion", "jump", "--duration", "1", "--rate", "30", "--noise-mm", "0",
                 "--no-video", "--quiet"]) == 0
    s = load_session(sd)
    gt = s.gt
    faces = np.asarray(gt["marker_faces"]).copy()
    faces[3] = -1
    poses = np.asarray(gt["poses"]).copy()
    poses[7] = np.nan
    frame_betas = np.repeat(np.asarray(gt["betas"])[None], poses.shape[0], 0)  # a streamed solve's per-frame shape
    pred = solved_marker_positions(load_body_model(str(gt["body_model"])), frame_betas, poses, gt["trans"], faces, gt["marker_bary"])
    assert np.isnan(pred[:, 3]).all() and np.isnan(pred[7]).all()
    ok = s.markers.visible.copy()
    ok[:, 3], ok[7] = False, False
    err = np.linalg.norm(pred - s.markers.positions, axis=-1)[ok]
    # the generator offsets along the posed vertex normals, the solver along the rest pose's smooth
    # normal carried by the face: the same within a fraction of a millimetre on most of the body
    # (at a bent joint the two part by up to ~8 mm: the posed normals turn with the neighbouring faces)
    assert np.median(err) < 0.5e-3 and np.percentile(err, 95) < 4e-3 and err.max() < 0.012, (np.median(err), np.percentile(err, 95), err.max())


def test_cut_gaps_lie_inside_seen_stretches_and_apart():
    from uuomocap.commands.bench_gap_fill import cut_gaps

    vis = np.ones((90, 5), bool)
    vis[20:30, 2] = False
    cuts = cut_gaps(vis, [3, 15], 4, seed=0)
    assert len(cuts) == 8 and sorted(b - a for _, a, b in cuts) == [3] * 4 + [15] * 4
    taken = np.zeros_like(vis)
    for m, a, b in cuts:
        assert vis[a - 1:b + 1, m].all()
        assert not taken[a - 1:b + 1, m].any()
        taken[a - 1:b + 1, m] = True


def test_bench_gap_fill_scores_the_body_against_the_trajectory_fills(capsys):
    from uuomocap.cli import main

    assert main(["bench", "gap-fill", "--motions", "walk", "--duration", "3", "--gap-lengths", "0.1,0.5",
                 "--gaps-per-length", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    pooled = out["pooled"]
    assert set(pooled) == {"body", "body as solved, linear blend", "body (no edge correction)", "spline", "linear"}
    assert set(pooled["body"]) == {"0.1", "0.5"}
    assert pooled["body"]["0.5"]["gaps"] == 4 and pooled["body"]["0.5"]["samples"] == 4 * 15
    # half a second of a walking marker: a straight line misses by centimetres, the body does not
    assert pooled["body"]["0.5"]["rms_mm"] < 0.5 * pooled["linear"]["0.5"]["rms_mm"], pooled
    assert pooled["body"]["0.5"]["rms_mm"] < 20.0
