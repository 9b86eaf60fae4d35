"""Metrics: known answers, exact surface distance, ground truth against itself, eval CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from uuomocap.solver_core import metrics


@pytest.fixture(scope="module")
def model():
    from uuomocap.solver_core.body_model import load_body_model

    return load_body_model("open-low")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A short generated session with occlusion and ghosts (no video)."""
    from uuomocap.synth import SampleConfig, make_session

    d = tmp_path_factory.mktemp("metrics") / "s"
    make_session(d, SampleConfig(motion="walk", duration_s=2.0, rate_hz=30.0, seed=4, n_markers=30,
                                 occlusion=0.01, ghost_rate_hz=1.0, video=False))
    return d


def _joints(F=20, seed=0):
    return np.random.default_rng(seed).normal(0, 0.3, (F, 24, 3))


def test_rigid_offset_gives_its_length_as_mpjpe():
    gt = _joints()
    pred = gt + np.array([0.03, 0.04, 0.0])
    assert metrics.mpjpe(pred, gt) == pytest.approx(50.0)
    assert metrics.pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-6)
    assert metrics.mpjve(pred, gt, 30.0) == pytest.approx(0.0, abs=1e-9)
    # Only joints 0-21 count: moving the hands alone changes nothing.
    pred2 = gt.copy()
    pred2[:, 22:] += 1.0
    assert metrics.mpjpe(pred2, gt) == 0.0


def test_similarity_transform_is_removed_by_procrustes_but_not_by_mpjpe():
    gt = _joints(F=5)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    pred = 1.3 * gt @ R.T + np.array([1.0, -2.0, 0.5])
    assert metrics.pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-6)
    assert metrics.mpjpe(pred, gt) > 100.0


def test_mpjve_of_a_drifting_offset():
    gt = _joints(F=31)
    t = np.arange(31)[:, None, None] / 30.0
    pred = gt + t * np.array([0.0, 0.0, 0.06])  # 60 mm/s drift on every joint
    assert metrics.mpjve(pred, gt, 30.0) == pytest.approx(60.0)
    assert metrics.mpjpe(pred, gt) == pytest.approx(30.0)  # mean of 0..60 mm


def test_surface_distance_is_exact_against_brute_force(model):
    from uuomocap.solver_core.mesh import closest_point_on_mesh

    v = torch.as_tensor(metrics.posed_vertices(model, np.zeros(16), np.zeros((2, 72)), np.zeros((2, 3))))
    rng = np.random.default_rng(1)
    idx = rng.integers(0, v.shape[1], 60)
    pts = v[:, idx] + torch.as_tensor(rng.normal(0, 0.05, (2, 60, 3)))
    fast = metrics.closest_surface_distance(pts, v, model.faces)
    brute, _, _ = closest_point_on_mesh(pts, v, model.faces)
    assert torch.allclose(fast, brute, atol=1e-9)


def test_part_check_tells_the_mirrored_limb_apart(model):
    from uuomocap.solver_core.parts import PART_JOINTS

    names, parents = model.joint_names, model.parents.tolist()
    right = ["left_hip", "left_knee", "left_ankle", "left_knee"]
    wrong = ["right_hip", "right_knee", "right_ankle", "right_knee"]
    assert metrics.check_part(right, "left_leg", PART_JOINTS, names, parents).found
    res = metrics.check_part(wrong, "left_leg", PART_JOINTS, names, parents)
    assert not res.found and res.mirror == 1.0


def test_ground_truth_against_itself(session, model, tmp_path):
    from uuomocap.methods import METHODS
    from uuomocap.protocol.session import load_session, read_npz

    out = tmp_path / "gt_out.npz"
    METHODS["gt"](session, out, "open-low")
    s = load_session(session)
    res = metrics.evaluate(read_npz(out), s.gt, model, markers=s.markers.positions)
    for k in ("mpjpe", "pa_mpjpe", "mpjve", "v2v", "attach_err"):
        assert res[k] == pytest.approx(0.0, abs=1e-3), k
    assert res["label_accuracy"] == 1.0
    # Markers sit 9.5 mm off the skin along the smoothed normal: ~9 mm on average (a little
    # less in creases and where posing compresses the skin), never much more than 9.5.
    assert 8.5 < res["m2s"] < 9.6
    assert res["m2s"] == pytest.approx(res["m2s_gt"])
    assert res["markers"] == 30  # ghost tracks are excluded


def test_per_frame_betas_pose_each_frame_with_its_own_shape(session, model, tmp_path):
    """A streamed solve's shape changes mid-take (lock upgrades): V2V must pose every frame with
    the betas it was solved under (frame_betas), not with the last one."""
    from uuomocap.methods import METHODS
    from uuomocap.protocol.session import load_session, read_npz

    out = tmp_path / "gt_out.npz"
    METHODS["gt"](session, out, "open-low")
    s = load_session(session)
    pred = read_npz(out)
    F = pred["poses"].shape[0]
    true_b, wrong_b = np.asarray(pred["betas"]), np.asarray(pred["betas"]) + np.eye(len(pred["betas"]))[0]
    all_wrong = metrics.evaluate({**pred, "betas": wrong_b}, s.gt, model)["v2v"]
    assert all_wrong > 5.0
    per_frame = np.tile(true_b, (F, 1))
    assert metrics.evaluate({**pred, "betas": wrong_b, "frame_betas": per_frame}, s.gt, model)["v2v"] == pytest.approx(0.0, abs=1e-3)
    per_frame[F // 2:] = wrong_b  # the second half solved under the other shape: half the error
    half = metrics.evaluate({**pred, "betas": wrong_b, "frame_betas": per_frame}, s.gt, model)["v2v"]
    assert half == pytest.approx(all_wrong * (F - F // 2) / F, rel=1e-4)
    with pytest.raises(ValueError, match="per-frame betas"):
        metrics.evaluate({**pred, "frame_betas": per_frame[:-1]}, s.gt, model)


def test_eval_cli_reports_a_known_offset(session, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.methods import METHODS
    from uuomocap.protocol.session import read_npz, write_npz

    out = tmp_path / "shifted.npz"
    METHODS["gt"](session, out, "open-low")
    arrays = read_npz(out)
    offset = np.array([0.0, 0.02, 0.0])
    arrays["trans"] = arrays["trans"] + offset
    arrays["joints"] = arrays["joints"] + offset
    write_npz(out, arrays)
    rc = main(["eval", "--pred", str(out), "--gt", str(session / "gt.npz"), "--markers", str(session / "markers.c3d"),
               "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["mpjpe"] == pytest.approx(20.0, abs=1e-3)
    assert res["v2v"] == pytest.approx(20.0, abs=1e-2)
    assert res["mpjve"] == pytest.approx(0.0, abs=1e-3)
    assert res["m2s"] > res["m2s_gt"]


def test_eval_cli_one_line_errors(session, tmp_path, capsys):
    from uuomocap.cli import main

    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((3, 72)))
    assert main(["eval", "--pred", str(bad), "--gt", str(session / "gt.npz")]) == 2
    err = capsys.readouterr().err
    assert "missing key" in err and "Traceback" not in err
    assert main(["eval", "--pred", str(tmp_path / "none.npz"), "--gt", str(session / "gt.npz")]) == 2
    capsys.readouterr()
    nanb = tmp_path / "nan_betas.npz"
    np.savez(nanb, betas=np.zeros(16), poses=np.zeros((60, 72)), trans=np.zeros((60, 3)), joints=np.zeros((60, 24, 3)),
             frame_betas=np.full((60, 16), np.nan))
    assert main(["eval", "--pred", str(nanb), "--gt", str(session / "gt.npz")]) == 2
    err = capsys.readouterr().err
    assert "frame_betas contains NaN" in err and "Traceback" not in err


@pytest.mark.slow
def test_bench_accuracy_smoke_runs_its_methods(tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.commands.bench_accuracy import SMOKE_METHODS

    js = tmp_path / "smoke.json"
    rc = main(["bench", "accuracy", "--suite", "smoke", "--cache", str(tmp_path / "cache"), "--json", str(js), "--quiet"])
    assert rc == 0
    res = json.loads(js.read_text())
    assert set(res["methods"]) == set(SMOKE_METHODS)
    for method in SMOKE_METHODS:  # every method solved every smoke session
        assert all(scen["failed"] == 0 for scen in res["summary"][method].values()), method
    gt = res["summary"]["gt"]
    for scen in gt.values():
        assert scen["mpjpe"] == pytest.approx(0.0, abs=1e-3) and scen["failed"] == 0
        assert 8.0 < scen["m2s"] < 9.6
    # uuo-window's live outputs come out as rows of their own, scored from the npz it wrote
    from uuomocap.commands.bench_accuracy import live_output_metrics
    from uuomocap.protocol.session import read_npz
    from uuomocap.solver_core.metrics import mpjpe

    for row in ("uuo-window fixed-lag", "uuo-window estimate"):
        assert all(scen["failed"] == 0 and scen["mpjpe"] > 0 for scen in res["summary"][row].values()), row
    run = next(r for r in res["runs"] if r["method"] == "uuo-window")
    sdir = Path(res["sessions"][run["session"]]["dir"])
    out = Path(res["cache"]) / "outputs" / run["session"] / "uuo-window.npz"
    rows = live_output_metrics(out, sdir / "gt.npz")
    pred, gt_arrays = read_npz(out), read_npz(sdir / "gt.npz")
    assert rows["uuo-window fixed-lag"]["mpjpe"] == pytest.approx(mpjpe(pred["refined_joints"], gt_arrays["joints"]))
    fixed_lag = next(r for r in res["runs"] if r["method"] == "uuo-window fixed-lag" and r["session"] == run["session"])
    assert fixed_lag["metrics"]["mpjpe"] == pytest.approx(rows["uuo-window fixed-lag"]["mpjpe"])
    text = capsys.readouterr().out
    assert "MPJPE" in text and "uuo-window fixed-lag" in text and "uuo-window estimate" in text
