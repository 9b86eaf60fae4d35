"""``uuomocap export``: a solve as BVH (skeleton + motion) and its joint centres as TRC / C3D."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A small Z-up session and an OUT.npz holding its ground-truth body, one frame left unsolved."""
    from uuomocap.cli import main
    from uuomocap.protocol.session import read_npz, write_npz

    root = tmp_path_factory.mktemp("export")
    sd = root / "s"
    assert main(["sample", "make", str(sd), "--motion", "jump", "--duration", "1.5", "--rate", "30", "--markers", "12",
                 "--no-video", "--seed", "2", "--quiet"]) == 0
    gt = read_npz(sd / "gt.npz")
    out = {k: np.asarray(gt[k]).copy() for k in ("betas", "poses", "trans", "joints", "mocap_framerate", "body_model")}
    out["poses"][7] = np.nan
    out["trans"][7] = np.nan
    out["joints"][7] = np.nan
    write_npz(root / "out.npz", out)
    return sd, root / "out.npz", gt


def test_bvh_export_reproduces_the_solved_joints_through_its_own_forward_kinematics(take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.solver_core.bvh import BVH_WRITE_NAMES, find_scheme, forward_kinematics, parse_bvh
    from uuomocap.solver_core.motions import canonical_to_world

    sd, out, gt = take
    bvh_path = tmp_path / "body.bvh"
    assert main(["export", str(out), "--session", str(sd), "--out", str(bvh_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["unsolved_frames"] == 1 and info["units"] == "cm" and info["up_axis"] == "+z"
    bvh = parse_bvh(bvh_path)
    assert bvh.num_frames == gt["poses"].shape[0] and abs(bvh.rate_hz - 30.0) < 1e-4
    assert find_scheme(bvh)[0] == "mixamo"  # the names retargeting tools recognise
    _, pos = forward_kinematics(bvh)
    order = [next(i for i, j in enumerate(bvh.joints) if j.name == n) for n in BVH_WRITE_NAMES]
    world = 0.01 * pos[:, order] @ canonical_to_world("+z").T  # cm, Y up -> metres in the capture's Z-up world
    truth = np.asarray(gt["joints"], np.float64)
    solved = np.arange(truth.shape[0]) != 7
    assert np.abs(world[solved] - truth[solved]).max() < 1e-5
    # the unsolved frame holds its nearest solved neighbour (6 or 8), not NaN
    assert np.isfinite(bvh.motion).all()
    assert min(np.abs(world[7] - truth[k]).max() for k in (6, 8)) < 1e-5
    # the rest skeleton is the T-pose, Y up: the left hip at +X, the knee below it, the spine above the hips
    rest = {j.name: j for j in bvh.joints}
    assert rest["LeftUpLeg"].offset[0] > 0 and rest["LeftLeg"].offset[1] < -30 and rest["Spine"].offset[1] > 0


def test_joint_centres_export_as_trc_and_c3d_with_gaps_for_unsolved_frames(take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers, to_y_up
    from uuomocap.solver_core.body_model import JOINT_NAMES

    sd, out, gt = take
    for ext in ("trc", "c3d"):
        path = tmp_path / f"joints.{ext}"
        assert main(["export", str(out), "--session", str(sd), "--out", str(path)]) == 0
        assert "24 joint centres" in capsys.readouterr().out
        md = read_markers(path)
        # C3D records the capture's +z; TRC is +y up for OpenSim, so the joints come back turned
        turn = np.eye(3) if ext == "c3d" else to_y_up("+z")
        assert md.labels == list(JOINT_NAMES) and md.up_axis == ("+z" if ext == "c3d" else "+y")
        assert abs(md.rate_hz - 30.0) < 1e-6
        assert not md.visible[7].any() and md.visible[np.arange(md.n_frames) != 7].all()
        np.testing.assert_allclose(md.positions[0], np.asarray(gt["joints"])[0] @ turn.T, atol=2e-5)


def test_export_names_the_problem_with_bad_input(take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.session import write_npz

    sd, out, gt = take
    empty = tmp_path / "empty.npz"
    write_npz(empty, {"betas": gt["betas"], "poses": np.full((3, 72), np.nan), "trans": np.full((3, 3), np.nan),
                      "joints": np.full((3, 24, 3), np.nan), "mocap_framerate": np.float64(30)})
    cases = [([str(out), "--out", str(tmp_path / "a.fbx")], "write a .bvh, .trc, .c3d or .npz"),
             ([str(tmp_path / "missing.npz"), "--out", str(tmp_path / "a.bvh")], "file not found"),
             ([str(empty), "--out", str(tmp_path / "a.bvh")], "no solved frame")]
    for argv, message in cases:
        assert main(["export", *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
