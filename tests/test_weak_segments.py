"""Markers of weakly constrained bones are placed under the video prior's rotation of that bone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uuomocap.solver_core.weak_segment_correspondence import subtree_marker_counts, weak_joints

# SMPL tree: pelvis 0; hips 1/2; knees 4/5; ankles 7/8; feet 10/11 ...
SMPL_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])


def test_subtree_counts_and_weak_bones():
    # five thigh markers (2), one shank marker (5), nothing below it; two markers on a forearm (19)
    joints = np.array([2, 2, 2, 2, 2, 5, 19, 19, -1])
    count = subtree_marker_counts(SMPL_PARENTS, joints)
    assert count[5] == 1 and count[2] == 6 and count[8] == 0 and count[0] == 8
    assert count[17] == 2 and count[14] == 2
    weak = weak_joints(SMPL_PARENTS, joints, max_markers=1)
    assert np.flatnonzero(weak).tolist() == [5]
    # with two allowed the forearm and everything above it down to the shoulder chain are weak,
    # the root never is
    weak2 = weak_joints(SMPL_PARENTS, joints, max_markers=2)
    assert {5, 19, 17, 14}.issubset(set(np.flatnonzero(weak2).tolist()))
    assert not weak2[0] and not weak2[2]


@pytest.fixture(scope="module")
def walk_gt(tmp_path_factory):
    synth = pytest.importorskip("uuomocap.synth")
    out = tmp_path_factory.mktemp("weak") / "walk"
    synth.make_session(out, synth.SampleConfig(video=False, motion="walk", duration_s=4.0, rate_hz=30.0, n_markers=20, seed=2))
    return dict(np.load(out / "gt.npz"))


def test_a_lone_shank_marker_is_placed_under_the_prior_not_the_biased_solve(walk_gt):
    """One marker on the right shank.  The 'solved' body has the shank 0.25 rad off for the whole
    take (what Stages 3-4 lock into when nothing but the marker constrains it); the prior is the
    truth plus zero-mean noise.  Stage 3 under the solved body puts the marker where that body
    needs it; the prior-guided placement lands near the true point."""
    from uuomocap.solver_core.body_params import BodyParams, MarkerAttachment, pose_params, up_tensor
    from scipy.spatial.transform import Rotation

    from uuomocap.solver_core.chamfer import vertex_face_table
    from uuomocap.solver_core.inverse_kinematics import predicted_markers
    from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, find_marker_surface_points
    from uuomocap.solver_core.metrics import surface_points_rest
    from uuomocap.solver_core.parts import vertex_dominant_joint
    from uuomocap.solver_core.weak_segment_correspondence import weak_segment_correspondence
    from uuomocap.solver_methods import load_models

    model, _ = load_models(str(walk_gt["body_model"]))
    up = up_tensor("+z")  # yaw stays 0: the up axis does not enter the pose
    poses = torch.as_tensor(walk_gt["poses"], dtype=torch.float32)
    frames = poses.shape[0]
    betas = torch.as_tensor(walk_gt["betas"][: model.num_betas], dtype=torch.float32)
    truth = BodyParams(poses[:, :3], poses[:, 3:].reshape(frames, 23, 3).clone(), torch.as_tensor(walk_gt["trans"], dtype=torch.float32),
                       betas, torch.zeros(()))
    # a face on the outer side of the right shank, halfway down
    dominant = vertex_dominant_joint(model)
    faces = model.faces
    shank = torch.nonzero((dominant[faces] == 5).all(dim=1)).reshape(-1)
    rest = pose_params(model, BodyParams(torch.zeros(1, 3), torch.zeros(1, 23, 3), torch.zeros(1, 3), betas, torch.zeros(())), up).vertices[0]
    centres = rest[faces[shank]].mean(dim=1)
    mid = (centres[:, 1] - centres[:, 1].median()).abs() < 0.03
    face = int(shank[mid][torch.argmin(centres[mid, 0])])  # most lateral (SMPL right = -x)
    true_att = MarkerAttachment(torch.tensor([face]), torch.tensor([[1 / 3, 1 / 3, 1 / 3]]), torch.zeros(1))
    with torch.no_grad():
        markers = predicted_markers(model, truth, true_att, up, 0.0095)  # (T,1,3)
    visible = torch.ones(frames, 1, dtype=torch.bool)

    biased_body = truth.body_pose.clone()
    knee = 5 - 1  # body_pose index of joint 5
    bias = Rotation.from_rotvec([0.0, 0.0, 0.25])

    biased_body[:, knee] = torch.as_tensor((Rotation.from_rotvec(biased_body[:, knee].numpy()) * bias).as_rotvec(), dtype=torch.float32)
    solved = BodyParams(truth.root_orient, biased_body, truth.trans, betas, truth.yaw)
    rng = np.random.default_rng(0)
    noisy = Rotation.from_rotvec(truth.body_pose.reshape(-1, 3).numpy()) * Rotation.from_rotvec(rng.normal(0, 0.08, (frames * 23, 3)))
    prior_body = torch.as_tensor(noisy.as_rotvec().reshape(frames, 23, 3), dtype=torch.float32)

    vf = vertex_face_table(model.faces, model.v_template.shape[0])
    plain = find_marker_surface_points(model, markers, visible, solved, up, None, vertex_faces=vf)
    guided, moved = weak_segment_correspondence(model, markers, visible, solved, prior_body, up, plain, np.array([5]), None,
                                                 CorrespondenceConfig(), vf)
    assert moved == [0]
    b = betas.numpy()
    true_pt = surface_points_rest(model, b, np.array([face]), np.array([[1 / 3, 1 / 3, 1 / 3]]))[0]
    err_plain = 1000 * np.linalg.norm(surface_points_rest(model, b, plain.face_ids.numpy(), plain.bary.numpy())[0] - true_pt)
    err_guided = 1000 * np.linalg.norm(surface_points_rest(model, b, guided.face_ids.numpy(), guided.bary.numpy())[0] - true_pt)
    assert err_plain > 25.0, err_plain  # the bias moved Stage 3's point
    assert err_guided < 0.5 * err_plain and err_guided < 15.0, (err_plain, err_guided)
