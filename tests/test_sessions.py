"""Sessions, synthetic data and motion sources: determinism, file round trips, statistics."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CMU_BVH = DATA / "motion" / "cmu_131_01.bvh"


@pytest.fixture(scope="module")
def model():
    from uuomocap.solver_core.body_model import load_body_model

    return load_body_model("open-low")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """The same small configuration generated twice through the CLI (with video)."""
    from uuomocap.cli import main

    root = tmp_path_factory.mktemp("sessions")
    args = ["--motion", "jump", "--duration", "2", "--rate", "60", "--seed", "7", "--markers", "20",
            "--occlusion", "0.01", "--ghosts", "1", "--swaps", "1", "--quiet"]
    for name in ("a", "b"):
        assert main(["sample", "make", str(root / name), *args]) == 0
    return root / "a", root / "b"


def test_same_seed_gives_identical_files(sessions):
    a, b = sessions
    for name in ("markers.c3d", "gt.npz", "prior.npz", "session.yaml", "video.mp4"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_c3d_reads_back_identically_with_ezc3d_and_our_reader(sessions):
    import ezc3d

    from uuomocap.protocol.markerio import read_markers
    from uuomocap.protocol.session import load_session

    s = load_session(sessions[0])
    ours = read_markers(s.marker_file)
    c = ezc3d.c3d(str(s.marker_file))
    pts = c["data"]["points"][:3].transpose(2, 1, 0) / 1000.0  # (T, M, 3) metres
    res = c["data"]["meta_points"]["residuals"][0].T
    pts[res < 0] = np.nan
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(60.0)
    assert np.array_equal(np.isnan(pts), np.isnan(ours.positions))
    assert np.allclose(pts, ours.positions, equal_nan=True, atol=1e-6)
    assert not ours.labelled  # placeholder labels: an unlabeled capture
    # ... and both equal what the generator wrote: the true attachment order matches the file.
    assert s.gt["marker_faces"].shape[0] == ours.n_markers
    ghosts = s.gt["marker_faces"] < 0
    assert ghosts.sum() == s.provenance["ghost_tracks"]
    assert np.isnan(ours.positions[:, ghosts]).mean() > 0.5  # ghosts are short tracks


def test_session_contents_follow_the_contract(sessions):
    from uuomocap.protocol.session import load_session

    s = load_session(sessions[0])
    assert s.rate_hz == 60.0 and s.markers.n_frames == 120 and s.up_axis == "+z"
    assert s.video_file is not None and s.video_rate_hz == 30.0
    p = s.prior
    assert p["global_orient"].shape == (60, 3) and p["body_pose"].shape == (60, 23, 3)
    assert p["stamps_ns"][1] - p["stamps_ns"][0] == round(1e9 / 30)
    assert bool(p["camera_frame"]) and "trans" not in p  # no metric translation
    g = s.gt
    assert g["poses"].shape == (120, 72) and g["joints"].shape == (120, 24, 3)
    # Feet on the floor: the lowest joint (an ankle/toe) stays near z = 0 outside jumps.
    assert -0.02 < g["joints"][0, :, 2].min() < 0.15


def test_rendered_video_shows_the_figure(sessions):
    import cv2

    cap = cv2.VideoCapture(str(sessions[0] / "video.mp4"))
    ok, frame = cap.read()
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    assert ok and frame.shape == (240, 320, 3) and n == 60
    # The shirt is saturated blue, the background grey: the figure covers a visible area.
    b, g, r = (frame[..., i].astype(int) for i in range(3))
    assert ((b - r) > 60).mean() > 0.01


def test_load_session_errors_are_one_line(tmp_path, sessions):
    from uuomocap.protocol.session import SessionError, load_session, read_npz, write_npz

    with pytest.raises(SessionError, match="no session.yaml"):
        load_session(tmp_path)
    d = tmp_path / "s"
    shutil.copytree(sessions[0], d)
    (d / "prior.npz").unlink()
    with pytest.raises(SessionError, match="prior file .* is missing"):
        load_session(d)
    shutil.copy(sessions[0] / "prior.npz", d / "prior.npz")

    gt = read_npz(sessions[0] / "gt.npz")
    bad = dict(gt)
    bad["poses"] = bad["poses"].copy()
    bad["poses"][3, 5] = np.nan
    write_npz(d / "gt.npz", bad)
    with pytest.raises(SessionError, match="NaN"):
        load_session(d)
    bad = dict(gt, joints=gt["joints"] * 1000.0, trans=gt["trans"] * 1000.0)
    write_npz(d / "gt.npz", bad)
    with pytest.raises(SessionError, match="mm"):
        load_session(d)
    bad = dict(gt)
    del bad["betas"]
    write_npz(d / "gt.npz", bad)
    with pytest.raises(SessionError, match="missing key"):
        load_session(d)
    write_npz(d / "gt.npz", dict(gt, poses=np.degrees(gt["poses"]) + 200.0))
    with pytest.raises(SessionError, match="degrees"):
        load_session(d)
    write_npz(d / "gt.npz", gt)
    prior = read_npz(sessions[0] / "prior.npz")
    write_npz(d / "prior.npz", dict(prior, body_pose=prior["body_pose"][:, :20]))
    with pytest.raises(SessionError, match="body_pose has shape"):
        load_session(d)
    write_npz(d / "prior.npz", prior)
    assert load_session(d).gt is not None


def test_occlusion_statistics_match_the_probability():
    from uuomocap.solver_core.marker_sim import occlusion_mask

    F, M, p, L = 4000, 50, 0.01, 10
    vis = occlusion_mask(F, M, p, L, np.random.default_rng(0))
    starts = vis[:-1] & ~vis[1:]                    # visible at t, hidden at t+1
    rate = starts.sum() / vis[:-1].sum()
    assert rate == pytest.approx(p, rel=0.1)
    # Every completed hide lasts exactly L frames.
    col = np.concatenate([np.ones((1, M), bool), vis, np.ones((1, M), bool)])
    runs = []
    for m in range(M):
        edges = np.flatnonzero(np.diff(col[:, m].astype(int)))
        runs += list(np.diff(edges)[::2])
    interior = np.array(runs[: max(1, len(runs) - M)])
    assert (interior == L).mean() > 0.95
    assert (1 - vis.mean()) == pytest.approx(p * L / (1 + p * L), rel=0.15)
    assert occlusion_mask(10, 3, 0.0, L, np.random.default_rng(0)).all()


def test_nested_partial_and_structured_layouts(model):
    from uuomocap.solver_core.marker_sim import random_layout, structured_layout
    from uuomocap.solver_core.parts import PART_JOINTS, vertex_dominant_joint

    b = np.zeros(16)
    l50 = random_layout(model, b, 50, 3)
    for n in (20, 30, 40):
        ln = random_layout(model, b, n, 3)
        assert np.array_equal(ln.face_ids, l50.face_ids[:n]) and np.allclose(ln.bary, l50.bary[:n])
    assert not np.array_equal(random_layout(model, b, 20, 4).face_ids, l50.face_ids[:20])
    dom = np.asarray(vertex_dominant_joint(model))
    for part in ("left_leg", "right_arm", "left_shoulder"):
        lp = random_layout(model, b, 15, 0, PART_JOINTS[part])
        corners = model.faces.numpy()[lp.face_ids]
        assert np.isin(dom[corners], PART_JOINTS[part]).all()
    s = structured_layout(model, b)
    assert len(s) == 39 and len(set(s.names)) == 39
    assert (s.bary >= -1e-9).all() and np.allclose(s.bary.sum(1), 1)


def test_prior_is_in_the_camera_frame_with_the_yaw_offset(model):
    from uuomocap.solver_core.camera import place_camera
    from uuomocap.solver_core.motions import axis_angle_to_matrices, make_procedural_motion
    from uuomocap.solver_core.prior_sim import PriorErrorModel, simulate_prior

    m = make_procedural_motion("turn", model, np.zeros(16), 2.0, 30.0, seed=1)
    cam = place_camera(m.trans, "+z", np.radians(120.0))
    exact = PriorErrorModel(pose_noise_rad=0, pose_jitter_rad=0, root_noise_rad=0, shape_noise=0, shape_jitter=0,
                            dropout_prob=0)
    arrays, content = simulate_prior(m, model, np.zeros(16), cam.R_wc, exact, 0, "open-low")
    assert np.allclose(content, np.arange(60) / 30.0)
    root_world = axis_angle_to_matrices(m.poses[:, :3])
    root_cam = axis_angle_to_matrices(arrays["global_orient"].astype(np.float64))
    assert np.allclose(root_cam, cam.R_wc.T @ root_world, atol=1e-5)
    assert np.allclose(arrays["body_pose"], m.poses[:, 3:].reshape(-1, 23, 3), atol=1e-5)
    noisy, _ = simulate_prior(m, model, np.zeros(16), cam.R_wc, PriorErrorModel(dropout_prob=0.05), 0, "open-low")
    assert 0.5 < noisy["valid"].mean() < 1.0
    assert not noisy["confidence"][~noisy["valid"]].any()
    err = np.linalg.norm(noisy["body_pose"][noisy["valid"]] - m.poses[noisy["valid"], 3:].reshape(-1, 23, 3), axis=-1)
    assert 0.05 < err.mean() < 0.3  # default 0.15 rad RMS per joint


def test_rate_mismatch_and_clock_offset():
    from uuomocap.solver_core.prior_sim import PriorErrorModel, video_content_times

    stamps, content = video_content_times(10.0, PriorErrorModel(true_rate_hz=29.97, clock_offset_s=0.5))
    assert stamps[1] == round(1e9 / 30)
    assert content[0] == pytest.approx(0.5) and content[-1] <= 10.0
    assert content[100] == pytest.approx(0.5 + 100 / 29.97)


def test_procedural_motions_are_smooth_and_within_joint_limits():
    from uuomocap.solver_core.motions import (JOINT_LIMITS_DEG, PROCEDURAL_MOTIONS, matrices_to_axis_angle,
                                              procedural_curves)

    rate = 60.0
    for name in PROCEDURAL_MOTIONS:
        c = procedural_curves(name, 6.0, rate, seed=2)
        aa = matrices_to_axis_angle(c.local_rot)
        ang = np.degrees(np.linalg.norm(aa[:, 1:], axis=-1))
        assert (ang <= np.array(JOINT_LIMITS_DEG[1:]) + 1e-6).all(), name
        # Knees and elbows never hyperextend (flexion sign of the hinge).
        assert (aa[:, 4, 0] > -1e-6).all() and (aa[:, 5, 0] > -1e-6).all(), name
        # Smooth: angular speed between frames stays human (< 1000 deg/s) and accelerations bounded.
        rel = np.einsum("fjba,fjbc->fjac", c.local_rot[:-1], c.local_rot[1:])
        speed = np.degrees(np.linalg.norm(matrices_to_axis_angle(rel), axis=-1)) * rate
        assert speed.max() < 1000.0, name
        acc = np.abs(np.diff(speed, axis=0)) * rate
        assert np.percentile(acc, 99) < 20000.0, name


def test_motions_stand_on_the_floor(model):
    from uuomocap.solver_core.motions import make_procedural_motion, posed_extremes

    for name in ("walk", "squat", "jump"):
        m = make_procedural_motion(name, model, np.zeros(16), 4.0, 30.0, seed=0)
        low, _ = posed_extremes(model, np.zeros(16), m.poses, "+z")
        low = low + m.trans[:, 2]
        assert np.percentile(np.abs(low), 50) < 0.01, name
        assert low.min() > -0.02, name
    jump = make_procedural_motion("jump", model, np.zeros(16), 3.0, 30.0, seed=0)
    low, _ = posed_extremes(model, np.zeros(16), jump.poses, "+z")
    assert (low + jump.trans[:, 2]).max() > 0.12  # it does leave the ground


BVH_WITH_TPOSE = """HIERARCHY
ROOT Hips
{
 OFFSET 0 0 0
 CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
 JOINT LeftUpLeg { OFFSET 10 0 0 CHANNELS 3 Zrotation Yrotation Xrotation
  JOINT LeftLeg { OFFSET 0 -43 0 CHANNELS 3 Zrotation Yrotation Xrotation
   JOINT LeftFoot { OFFSET 0 -41 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET 0 -5 12 } } } }
 JOINT RightUpLeg { OFFSET -10 0 0 CHANNELS 3 Zrotation Yrotation Xrotation
  JOINT RightLeg { OFFSET 0 -43 0 CHANNELS 3 Zrotation Yrotation Xrotation
   JOINT RightFoot { OFFSET 0 -41 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET 0 -5 12 } } } }
 JOINT Spine { OFFSET 0 10 0 CHANNELS 3 Zrotation Yrotation Xrotation
  JOINT Neck { OFFSET 0 45 0 CHANNELS 3 Zrotation Yrotation Xrotation
   JOINT Head { OFFSET 0 10 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET 0 15 0 } } }
  JOINT LeftArm { OFFSET 18 40 0 CHANNELS 3 Zrotation Yrotation Xrotation
   JOINT LeftForeArm { OFFSET 28 0 0 CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT LeftHand { OFFSET 26 0 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET 8 0 0 } } } }
  JOINT RightArm { OFFSET -18 40 0 CHANNELS 3 Zrotation Yrotation Xrotation
   JOINT RightForeArm { OFFSET -28 0 0 CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT RightHand { OFFSET -26 0 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET -8 0 0 } } } } }
}
MOTION
Frames: 3
Frame Time: 0.0333333
"""


def _tpose_bvh_text() -> str:
    nch = 6 + 3 * 15
    rows = [np.zeros(nch), np.zeros(nch), np.zeros(nch)]
    rows[0][1] = 90.0                       # frame 0: the added rest pose
    for r in rows[1:]:
        r[1] = 88.0
        r[6 + 3 * 1] = 40.0                 # LeftLeg Zrotation ... any non-rest angles
        r[6 + 3 * 10 + 2] = -30.0
    return BVH_WITH_TPOSE + "\n".join(" ".join(f"{v:g}" for v in r) for r in rows) + "\n"


def test_bvh_rest_frame_detection_and_units(model):
    from uuomocap.solver_core.bvh import detect_unit, find_scheme, has_rest_pose_first_frame, parse_bvh, retarget

    b = parse_bvh(_tpose_bvh_text())
    assert b.num_frames == 3 and b.rate_hz == pytest.approx(30.0, rel=1e-4)
    assert has_rest_pose_first_frame(b)
    scheme, mapping = find_scheme(b)
    assert scheme in ("mixamo", "cmu-cgspeed")  # both name schemes fit this rig
    unit, m_per_unit, _ = detect_unit(b, mapping)
    assert unit == "cm" and m_per_unit == 0.01
    m = retarget(b, model, np.zeros(16))
    assert m.num_frames == 2 and m.info["dropped_rest_frame"]


@pytest.mark.skipif(not CMU_BVH.is_file(), reason="shared test data not available")
def test_cmu_bvh_retargets_bone_directions(model):
    import torch

    from uuomocap.solver_core.body_model import JOINT_NAMES
    from uuomocap.solver_core.bvh import (find_scheme, forward_kinematics, has_rest_pose_first_frame, parse_bvh,
                                          rest_body_frame, rest_positions, retarget)
    from uuomocap.solver_core.lbs import forward
    from uuomocap.solver_core.motions import canonical_to_world

    b = parse_bvh(CMU_BVH)
    assert b.num_frames == 994 and b.rate_hz == pytest.approx(120.0, rel=1e-4)
    assert not has_rest_pose_first_frame(b)  # frame 0 of this file is real motion
    m = retarget(b, model, np.zeros(16))
    assert m.num_frames == 994 and m.info["unit"].startswith("cmu_asf")
    assert 0.7 < m.info["actor_leg_m"] < 0.95
    sl = slice(0, 994, 20)
    out = forward(model, torch.zeros(1, 16), torch.as_tensor(m.poses[sl], dtype=torch.float32),
                  torch.as_tensor(m.trans[sl], dtype=torch.float32))
    js = out.joints.double().numpy()
    _, mapping = find_scheme(b)
    _, p = forward_kinematics(b, b.motion[sl])
    pw = p @ rest_body_frame(rest_positions(b), mapping) @ canonical_to_world("+z").T
    for a, c in (("left_hip", "left_knee"), ("right_knee", "right_ankle"), ("left_shoulder", "left_elbow"),
                 ("right_elbow", "right_wrist")):
        ds = js[:, JOINT_NAMES.index(c)] - js[:, JOINT_NAMES.index(a)]
        db = pw[:, mapping[c]] - pw[:, mapping[a]]
        cos = (ds * db).sum(1) / np.linalg.norm(ds, axis=1) / np.linalg.norm(db, axis=1)
        assert cos.min() > 0.999, (a, c)


def test_sample_make_from_bvh_and_structured_layout(tmp_path, capsys):
    import json

    from uuomocap.cli import main

    if CMU_BVH.is_file():
        rc = main(["sample", "make", str(tmp_path / "bvh"), "--motion", str(CMU_BVH), "--duration", "1", "--rate", "30",
                   "--layout", "structured", "--no-video", "--quiet", "--json"])
        assert rc == 0
        info = json.loads(capsys.readouterr().out)
        assert info["frames"] == 30 and info["real_markers"] == 39 and info["motion"] == "cmu_131_01.bvh"
    assert main(["sample", "make", str(tmp_path / "x"), "--motion", "nope", "--quiet"]) == 2
    assert "neither a procedural motion" in capsys.readouterr().err


def test_amass_npz_motion_source(tmp_path, model):
    from uuomocap.solver_core.motions import load_amass_npz, make_procedural_motion
    from uuomocap.synth import SampleConfig, build_motion

    src = make_procedural_motion("arms", model, np.zeros(16), 2.0, 120.0, seed=0)
    poses = np.zeros((src.num_frames, 156))            # SMPL-H layout: 52 joints
    poses[:, :66] = src.poses[:, :66]
    path = tmp_path / "clip_poses.npz"
    np.savez(path, poses=poses, trans=src.trans + [0.5, 0.0, 0.3], betas=np.zeros(16), mocap_framerate=120.0,
             gender="neutral")
    m = load_amass_npz(path)
    assert m.rate_hz == 120.0 and m.poses.shape == (240, 72) and np.allclose(m.poses[:, 66:], 0)
    placed = build_motion(SampleConfig(motion=str(path), duration_s=1.0, rate_hz=30.0), model, np.zeros(16))
    assert placed.num_frames == 30 and placed.rate_hz == 30.0
    # Back on the floor and centred, whatever the file's offset was.
    assert abs(placed.trans[:, 2].mean() - src.trans[:, 2].mean()) < 0.02
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((3, 72)))
    with pytest.raises(ValueError, match="missing trans"):
        load_amass_npz(bad)


def test_motions_are_re_expressed_against_an_a_pose_rest(model):
    """The open model rests in an A-pose (upper arms ~50 deg down, elbows bent): T-pose rotations
    (the procedural curves, AMASS) used as they are swung its arms through the chest."""
    import torch

    from uuomocap.solver_core.lbs import forward
    from uuomocap.solver_core.motions import (L_ELBOW, L_SHOULDER, L_WRIST, R_ELBOW, R_SHOULDER, R_WRIST,
                                              axis_angle_to_matrices, make_procedural_motion, poses_from_tpose)

    def unit(d):
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    betas = np.zeros(16)
    tpose = poses_from_tpose(np.zeros((1, 72)), model, betas)  # zero T-pose rotations on this model
    j = forward(model, torch.zeros(1, 16), torch.as_tensor(tpose, dtype=torch.float32)).joints[0].numpy()
    for a, b, side in ((L_SHOULDER, L_ELBOW, 1), (L_ELBOW, L_WRIST, 1), (R_SHOULDER, R_ELBOW, -1), (R_ELBOW, R_WRIST, -1)):
        assert unit(j[b] - j[a]) @ np.array([side, 0.0, 0.0]) > np.cos(np.radians(1.0))  # straight out sideways
    walk = make_procedural_motion("walk", model, betas, 2.0, 30.0, seed=2)
    joints = forward(model, torch.zeros(1, 16), torch.as_tensor(walk.poses, dtype=torch.float32),
                     torch.as_tensor(walk.trans, dtype=torch.float32)).joints.numpy()
    root = axis_angle_to_matrices(walk.poses[:, :3])  # canonical body axes (x left, y up) -> world
    for shoulder, elbow, side in ((L_SHOULDER, L_ELBOW, 1), (R_SHOULDER, R_ELBOW, -1)):
        upper = unit(np.einsum("fba,fb->fa", root, joints[:, elbow] - joints[:, shoulder]))
        down = np.degrees(np.arccos(np.clip(-upper[:, 1], -1, 1)))
        assert down.max() < 30.0, down.max()            # hanging, swinging +-18 deg
        assert (side * upper[:, 0] > 0.05).all()          # the elbow outside the shoulder, not across the chest


def test_demo_knows_a_session_from_an_older_generator(sessions, tmp_path):
    """make demo reuses demo_out/session; one made before the arms were re-expressed is made again."""
    from uuomocap.commands.demo import _generator_version
    from uuomocap.synth import GENERATOR_VERSION

    assert _generator_version(sessions[0] / "session.yaml") == GENERATOR_VERSION == 2
    old = tmp_path / "session.yaml"
    old.write_text((sessions[0] / "session.yaml").read_text().replace("generator_version: 2", "generator_version: 1"))
    assert _generator_version(old) == 1
    old.write_text("format: uuomocap-session/1\n")
    assert _generator_version(old) is None and _generator_version(tmp_path / "missing.yaml") is None


def test_export_npz_gives_the_poses_of_a_t_pose_body(sessions, tmp_path, model):
    """`uuomocap export OUT.npz --out x.npz`: the open model's poses (A-pose rest) as rotations of a
    T-pose body - for the generated jump, exactly the procedural curves the generator started from."""
    from uuomocap.cli import main
    from uuomocap.protocol.session import read_npz
    from uuomocap.solver_core.motions import (assemble_world_poses, axis_angle_to_matrices, poses_from_tpose,
                                              procedural_curves)

    gt = read_npz(sessions[0] / "gt.npz")
    out = tmp_path / "tpose.npz"
    assert main(["export", str(sessions[0] / "gt.npz"), "--out", str(out), "--session", str(sessions[0])]) == 0
    exported = read_npz(out)
    assert str(exported["rest_pose"]) == "tpose" and exported["poses"].shape == gt["poses"].shape
    curves = assemble_world_poses(procedural_curves("jump", 2.0, 60.0, 7), "+z")
    got = axis_angle_to_matrices(exported["poses"].reshape(-1, 3))
    want = axis_angle_to_matrices(curves.reshape(-1, 3))
    assert np.abs(got - want).max() < 1e-4
    assert np.abs(exported["trans"] - gt["trans"]).max() < 1e-9 and float(exported["mocap_framerate"]) == 60.0
    # and back: the model's own poses
    back = axis_angle_to_matrices(poses_from_tpose(exported["poses"], model, gt["betas"]).reshape(-1, 3))
    assert np.abs(back - axis_angle_to_matrices(gt["poses"].reshape(-1, 3))).max() < 1e-4
