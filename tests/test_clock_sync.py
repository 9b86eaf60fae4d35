"""The video -> marker clock offset found from the motion (solver_core.clock_sync, solve --clock-offset auto)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from uuomocap.solver_core.clock_sync import (
    ClockSyncConfig,
    estimate_clock_offset,
    marker_motion_signal,
    prior_motion_signal,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CMU_BVH = DATA / "motion" / "cmu_131_01.bvh"


def _bumpy(t: np.ndarray, seed: int) -> np.ndarray:
    """An aperiodic positive 'articulation speed' on 0-12 s: a sum of random Gaussian bumps."""
    rng = np.random.default_rng(seed)
    centres, widths, heights = rng.uniform(0, 12, 40), rng.uniform(0.05, 0.3, 40), rng.uniform(0.2, 1.0, 40)
    return (heights * np.exp(-0.5 * ((t[:, None] - centres) / widths) ** 2)).sum(1)


def test_a_shifted_aperiodic_signal_is_found_to_a_fraction_of_a_frame():
    t_m = np.arange(0, 12, 1 / 100)  # markers at 100 Hz, marker clock
    truth = 1.37  # marker time = video time + 1.37
    t_v = np.arange(-0.5, 9.0, 1 / 30)  # video at 30 Hz, video clock
    rng = np.random.default_rng(1)
    m = _bumpy(t_m, 0) + 0.05 * rng.standard_normal(len(t_m))
    v = _bumpy(t_v + truth, 0) * 0.7 + 0.1 + 0.05 * rng.standard_normal(len(t_v))  # other scale and floor
    v[40:50] = np.nan  # a dropout of the video estimator
    est = estimate_clock_offset(t_m, m, t_v, v)
    assert abs(est.offset_s - truth) < 0.01, est
    assert est.reliable and est.correlation > 0.9 and est.overlap_s > 8
    # a search window that leaves the truth out finds something else, and says it is weak or ambiguous
    far = estimate_clock_offset(t_m, m, t_v, v, replace(ClockSyncConfig(), max_offset_s=0.5), centre_s=-2.0)
    assert abs(far.offset_s - truth) > 0.8 and not far.reliable


def test_repeating_motion_is_ambiguous_and_a_still_subject_is_weak():
    t = np.arange(0, 10, 1 / 60)
    gait = 1 + np.sin(2 * np.pi * t / 1.1)  # a stride every 1.1 s, for ever
    est = estimate_clock_offset(t, gait, t, gait)
    assert est.ambiguous and not est.reliable and abs(abs(est.runner_up_offset_s - est.offset_s) % 1.1) < 0.05
    assert "AMBIGUOUS" in est.summary()
    # a peak every stride, all alike: more than the fit refines, and it says how many it left unjudged
    assert len(est.candidates_s) == ClockSyncConfig().refine_peaks and len(est.unjudged_peaks_s) >= 2, est
    rng = np.random.default_rng(3)  # a subject standing still: both signals are sensor noise
    still = estimate_clock_offset(t, 0.01 * rng.random(len(t)), t, 0.01 * rng.random(len(t)))
    assert still.weak and not still.reliable and "WEAK" in still.summary()
    with pytest.raises(ValueError, match="cannot overlap"):
        estimate_clock_offset(t[:60], gait[:60], t[:60], gait[:60])  # 1 s of each: under the 2 s overlap
    with pytest.raises(ValueError, match="both streams move"):
        estimate_clock_offset(t, np.ones_like(t), t, gait)  # a still subject


def test_the_marker_signal_ignores_travel_gaps_and_wild_markers():
    rng = np.random.default_rng(0)
    T, M = 200, 30
    t = np.arange(T) / 100.0
    local = rng.normal(0, 0.2, (M, 3))
    swing = np.sin(2 * np.pi * t)[:, None, None] * rng.normal(0, 0.05, (1, M, 3))  # articulation
    still = local[None] + swing
    _, base = marker_motion_signal(still, np.ones((T, M), bool), (t * 1e9).astype(np.int64))
    walking = still + np.array([1.3, 0.0, 0.0]) * t[:, None, None]  # + 1.3 m/s of travel
    vis = np.ones((T, M), bool)
    vis[50:60, :5] = False  # gaps
    walking[50:60, :5] = np.nan
    walking[100, 7] += 0.5  # one wild sample (a ghost / a swap) in one frame
    _, moved = marker_motion_signal(walking, vis, (t * 1e9).astype(np.int64))
    ok = np.isfinite(moved)
    assert ok.all() and np.allclose(moved[:45], base[:45], atol=1e-9)  # travel removed exactly
    assert np.nanmax(np.abs(moved - base)) < 0.2 * np.nanmax(base)  # the wild sample is trimmed away
    vis[:, 2:] = False
    _, few = marker_motion_signal(walking, vis, (t * 1e9).astype(np.int64))
    assert np.isnan(few).all()  # fewer than 3 markers: no reading


def test_the_prior_signal_does_not_see_the_camera_frame():
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.prior_preparation import BodyPrior, prior_to_world

    model = load_body_model("open-low")
    F = 40
    rng = np.random.default_rng(2)
    t = np.arange(F) / 30.0
    pose = np.zeros((F, 23, 3))
    pose[:, 0, 0] = 0.6 * np.sin(2 * np.pi * t)  # the left hip swings
    pose[:, 17, 2] = 0.4 * np.sin(2 * np.pi * t + 1)  # the right elbow
    root = np.tile(rng.normal(0, 1, 3), (F, 1))
    valid = np.ones(F, bool)
    valid[20] = False
    prior = BodyPrior(root, pose, np.zeros((F, 10)), valid, valid.astype(float), (t * 1e9).astype(np.int64), "camera")
    tc, cam = prior_motion_signal(model, prior)
    _, world = prior_motion_signal(model, prior_to_world(prior, "+z"))
    assert len(tc) == F - 1 and np.isnan(cam[19]) and np.isnan(cam[20])  # next to the frame without an estimate
    np.testing.assert_allclose(cam, world, rtol=1e-4, atol=1e-6)
    assert np.nanmin(cam) >= 0 and np.nanmax(cam) > 0.05


def test_solve_finds_a_phone_started_late_on_a_real_motion(tmp_path, capsys):
    """A session whose video really starts 1.3 s late while session.yaml says 0 (generated from
    the CMU motion, which does not repeat): --clock-offset auto finds it, and solve uses it."""
    if not CMU_BVH.is_file():
        pytest.skip(f"test motion absent: {CMU_BVH}")
    from uuomocap.cli import main
    from uuomocap.synth import SampleConfig, make_session

    session = tmp_path / "late_phone"
    make_session(session, SampleConfig(motion=str(CMU_BVH), duration_s=8.0, n_markers=40, seed=4, sync_error_s=1.3, video=False))
    out = tmp_path / "rr.npz"
    plot = tmp_path / "sync.png"
    assert main(["solve", str(session), "--method", "video-rr", "--clock-offset", "auto", "--sync-plot", str(plot), "--out", str(out),
                 "--quiet", "--json"]) == 0
    captured = capsys.readouterr()
    import cv2

    image = cv2.imread(str(plot))
    assert image is not None and image.shape[1] == 1000 and image.shape[0] > 400, "no sync plot written"
    from uuomocap.sync_plot import BLUE, GREEN, ORANGE

    for colour in (BLUE, ORANGE, GREEN):  # both signals and the offset found are drawn
        assert (np.abs(image.astype(int) - colour).max(-1) < 10).sum() > 50, colour
    assert main(["solve", str(session), "--sync-plot", str(plot), "--out", str(out), "--quiet"]) == 2  # nothing found to draw
    sync = json.loads(captured.out)["clock_sync"]
    assert abs(sync["offset_s"] - 1.3) < 0.03 and sync["reliable"] and sync["used_s"] == sync["offset_s"], sync
    assert abs(sync["correlation_offset_s"] - 1.3) < 0.15 and sync["fit_rms_mm"] > 0  # the peak, refined by the fit
    assert sync["fit_contrast"] >= ClockSyncConfig().min_fit_contrast and not sync["flat_fit"]
    assert "clock offset: auto +1.2" in captured.err or "clock offset: auto +1.3" in captured.err
    # --write-offset records it in session.yaml (the rest kept), where replays and uuo-window read it
    from uuomocap.protocol.session import load_session

    before = (session / "session.yaml").read_text()
    assert main(["solve", str(session), "--method", "video-rr", "--clock-offset", "auto", "--write-offset", "--out", str(out), "--quiet"]) == 0
    assert "written to" in capsys.readouterr().err
    s = load_session(session, load_prior=False, load_gt=False)
    assert abs(s.clock_offset_s - sync["offset_s"]) < 1e-4
    import yaml

    cfg_before, cfg_after = yaml.safe_load(before), yaml.safe_load((session / "session.yaml").read_text())
    assert cfg_after["video"]["clock_offset_note"].startswith("uuomocap solve --clock-offset auto: motion correlation")
    assert {k: v for k, v in cfg_after.items() if k != "video"} == {k: v for k, v in cfg_before.items() if k != "video"}
    assert main(["solve", "--markers", str(session / "markers.c3d"), "--prior", str(session / "prior.npz"), "--write-offset",
                 "--out", str(out), "--quiet"]) == 2  # loose files have no session.yaml to write
    # without a prior there is nothing to sync against
    assert main(["solve", "--markers", str(session / "markers.c3d"), "--clock-offset", "auto", "--out", str(out), "--quiet"]) == 2
    assert "needs a video prior" in capsys.readouterr().err


def test_an_offset_the_body_fit_cannot_locate_is_flagged_flat(tmp_path):
    """Markers of the CMU motion against a video prior that articulates on its own (a random sway
    about a held pose): the motion correlation finds some peak (its floor lowered here so it does not
    stop there as WEAK), but the registered body fits about as well at every offset - FLAT, not used.
    The same session with its own prior has a V-shaped fit around the peak."""
    if not CMU_BVH.is_file():
        pytest.skip(f"test motion absent: {CMU_BVH}")
    from uuomocap.protocol.session import load_session
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.clock_sync import estimate_session_clock_offset
    from uuomocap.solver_core.prior_preparation import prior_from_npz_arrays
    from uuomocap.synth import SampleConfig, make_session

    make_session(tmp_path / "s", SampleConfig(motion=str(CMU_BVH), duration_s=6.0, n_markers=40, seed=4, video=False))
    s = load_session(tmp_path / "s", load_prior=True, load_gt=False)
    model = load_body_model("open-low")
    args = (model, s.markers.positions, s.markers.visible, s.markers.stamps_ns)
    own = estimate_session_clock_offset(*args, prior_from_npz_arrays(s.prior), up_axis=s.up_axis)
    assert own.reliable and abs(own.offset_s) < 0.05 and own.fit_contrast >= ClockSyncConfig().min_fit_contrast, own.summary()
    rng = np.random.default_rng(0)
    F = len(s.prior["stamps_ns"])
    sway = np.cumsum(rng.normal(0, 0.02, (F, 23, 3)), axis=0)  # articulation that has nothing to do with the markers
    unrelated = dict(s.prior, body_pose=np.asarray(s.prior["body_pose"])[:1].reshape(1, 23, 3) + sway)
    config = replace(ClockSyncConfig(), min_correlation=0.0)
    est = estimate_session_clock_offset(*args, prior_from_npz_arrays(unrelated), config, up_axis=s.up_axis)
    assert est.flat_fit and not est.reliable and est.fit_contrast < config.min_fit_contrast, est.summary()
    assert "FLAT" in est.summary() and est.to_dict()["flat_fit"]


def test_bench_sync_counts_found_flagged_and_wrong_offsets(tmp_path, capsys):
    """`uuomocap bench sync` on the procedural walk (which repeats exactly: flagged, never used) and,
    when the shared data is here, the CMU motion (found within the tolerance)."""
    from uuomocap.cli import main

    motions = "walk" + (f",{CMU_BVH}" if CMU_BVH.is_file() else "")
    out = tmp_path / "sync.json"
    assert main(["bench", "sync", "--motions", motions, "--seeds", "1", "--sync-errors", "1.3", "--quiet", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "used right" in text and "walk" in text
    data = json.loads(out.read_text())
    walk = data["summary"]["walk"]
    assert walk["sessions"] == 1 and walk["used_right"] == 0 and walk["used_wrong"] == 0 and walk["ambiguous"] + walk["weak"] + walk["flat"] == 1
    if CMU_BVH.is_file():
        cmu = data["summary"][CMU_BVH.name]
        assert cmu["used_right"] == 1 and cmu["max_error_ms"] < 50, cmu
    assert main(["bench", "sync", "--motions", "no_such.bvh", "--quiet"]) == 2


def test_a_video_shorter_than_the_smoothing_is_refused_not_crashed():
    """A video overlapping the take by a fraction of a second (9 samples, shorter than the smoothing
    kernel) gets the overlap error, not an index error."""
    t = np.arange(0, 3, 1 / 60)
    with pytest.raises(ValueError, match="cannot overlap"):
        estimate_clock_offset(t, _bumpy(t, 0), t[:9], _bumpy(t[:9], 0))
