"""The per-marker second opinion: points placed under the prior's rotation of their bone, kept
where IK fits them better."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uuomocap.solver_core.body_params import MarkerAttachment
from uuomocap.solver_core.placement_selection import choose_placements


def _att(faces, score=None):
    faces = torch.as_tensor(faces, dtype=torch.long)
    bary = torch.stack([torch.full((len(faces),), float(i + 1)) for i in range(3)], dim=1) * (faces[:, None] + 1)
    return MarkerAttachment(faces, bary, torch.zeros(len(faces)) if score is None else torch.as_tensor(score))


def test_choice_takes_the_lower_residual_per_marker_and_never_an_unassigned_point():
    current = _att([10, 11, 12, 13])
    alternative = _att([20, 21, -1, 23])
    cur_res = torch.tensor([0.004, 0.002, 0.009, float("inf")])
    alt_res = torch.tensor([0.001, 0.003, 0.001, 0.005])
    merged, took = choose_placements(current, alternative, cur_res, alt_res)
    # marker 2's alternative is unassigned: kept despite the lower residual
    assert took == [0, 3]
    assert merged.face_ids.tolist() == [20, 11, 12, 23]
    assert torch.equal(merged.bary[0], alternative.bary[0]) and torch.equal(merged.bary[1], current.bary[1])


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    synth = pytest.importorskip("uuomocap.synth")
    from uuomocap.solver_core.body_params import BodyParams
    from uuomocap.solver_methods import load_models

    out = tmp_path_factory.mktemp("placement") / "walk"
    synth.make_session(out, synth.SampleConfig(video=False, motion="walk", duration_s=4.0, rate_hz=30.0, n_markers=20, seed=2))
    gt = dict(np.load(out / "gt.npz"))
    model, _ = load_models(str(gt["body_model"]))
    poses = torch.as_tensor(gt["poses"], dtype=torch.float32)
    frames = poses.shape[0]
    betas = torch.as_tensor(gt["betas"][: model.num_betas], dtype=torch.float32)
    truth = BodyParams(poses[:, :3], poses[:, 3:].reshape(frames, 23, 3).clone(),
                       torch.as_tensor(gt["trans"], dtype=torch.float32), betas, torch.zeros(()))
    return model, truth


def _faces_on(model, joint: int, count: int) -> torch.Tensor:
    """``count`` faces spread along bone ``joint`` (all three corners dominated by it)."""
    from uuomocap.solver_core.parts import vertex_dominant_joint

    dominant = vertex_dominant_joint(model)
    on_bone = torch.nonzero((dominant[model.faces] == joint).all(dim=1)).reshape(-1)
    return on_bone[torch.linspace(0, len(on_bone) - 1, count).round().long()]


def test_fit_residuals_measure_each_marker_over_its_visible_frames(walk):
    from uuomocap.solver_core.body_params import up_tensor
    from uuomocap.solver_core.inverse_kinematics import predicted_markers
    from uuomocap.solver_core.placement_selection import marker_fit_residuals

    model, truth = walk
    up = up_tensor("+z")
    faces = _faces_on(model, 2, 3)
    att = MarkerAttachment(torch.cat([faces, torch.tensor([-1])]), torch.full((4, 3), 1 / 3), torch.zeros(4))
    with torch.no_grad():
        pred = predicted_markers(model, truth, att, up, 0.0095)  # (T,3,3) for the assigned markers
    markers = torch.zeros(truth.num_frames, 4, 3)
    markers[:, :3] = pred
    markers[:, 1, 2] += 0.010  # marker 1 sits 10 mm above its point in every frame
    markers[::2, 2] += 0.5  # marker 2 is far off in frames it is not seen in
    visible = torch.ones(truth.num_frames, 4, dtype=torch.bool)
    visible[::2, 2] = False
    res = 1000 * marker_fit_residuals(model, markers, visible, truth, att, up, 0.0095)
    assert res[0] < 0.01 and abs(float(res[1]) - 10.0) < 0.01 and res[2] < 0.01
    assert torch.isinf(res[3])


def test_prior_rotation_placement_undoes_a_biased_thigh(walk):
    """Four markers on the right thigh; the 'solved' body has the thigh turned 0.15 rad about its
    own axis for the whole take (points and pose that confirm each other); the prior is the truth
    plus noise.  Stage 3 under the solved body puts the points where that body needs them; the
    prior-rotation placement lands them near their true points and touches only that bone."""
    from scipy.spatial.transform import Rotation

    from uuomocap.solver_core.body_params import BodyParams, up_tensor
    from uuomocap.solver_core.chamfer import vertex_face_table
    from uuomocap.solver_core.inverse_kinematics import predicted_markers
    from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, find_marker_surface_points
    from uuomocap.solver_core.metrics import surface_points_rest
    from uuomocap.solver_core.placement_selection import prior_rotation_placement
    from uuomocap.solver_core.staged_solver import marker_joint_ids

    model, truth = walk
    up = up_tensor("+z")
    frames = truth.num_frames
    thigh = _faces_on(model, 2, 4)
    pelvis = _faces_on(model, 0, 2)
    faces = torch.cat([thigh, pelvis])
    true_att = MarkerAttachment(faces, torch.full((6, 3), 1 / 3), torch.zeros(6))
    with torch.no_grad():
        markers = predicted_markers(model, truth, true_att, up, 0.0095)
    visible = torch.ones(frames, 6, dtype=torch.bool)

    body = truth.body_pose.clone()
    hip = 2 - 1  # body_pose index of joint 2
    body[:, hip] = torch.as_tensor((Rotation.from_rotvec(body[:, hip].numpy()) * Rotation.from_rotvec([0.0, 0.15, 0.0])).as_rotvec(),
                                   dtype=torch.float32)
    solved = BodyParams(truth.root_orient, body, truth.trans, truth.betas, truth.yaw)
    rng = np.random.default_rng(1)
    noisy = Rotation.from_rotvec(truth.body_pose.reshape(-1, 3).numpy()) * Rotation.from_rotvec(rng.normal(0, 0.08, (frames * 23, 3)))
    prior_body = torch.as_tensor(noisy.as_rotvec().reshape(frames, 23, 3), dtype=torch.float32)

    vf = vertex_face_table(model.faces, model.v_template.shape[0])
    plain = find_marker_surface_points(model, markers, visible, solved, up, None, vertex_faces=vf)
    joints = marker_joint_ids(model, plain)
    assert joints[:4].tolist() == [2, 2, 2, 2] and joints[4:].tolist() == [0, 0]
    placed = prior_rotation_placement(model, markers, visible, solved, prior_body, up, plain, joints, None,
                                      CorrespondenceConfig(), vf)
    b = truth.betas.numpy()
    true_pts = surface_points_rest(model, b, faces.numpy(), np.full((6, 3), 1 / 3))

    def errors(att):
        return 1000 * np.linalg.norm(surface_points_rest(model, b, att.face_ids.numpy(), att.bary.numpy()) - true_pts, axis=1)

    e_plain, e_placed = errors(plain), errors(placed)
    assert e_plain[:4].mean() > 8.0, e_plain  # the bias moved Stage 3's thigh points
    assert e_placed[:4].mean() < 0.5 * e_plain[:4].mean() and e_placed[:4].mean() < 5.0, (e_plain, e_placed)
    # the pelvis (root: no prior rotation) keeps its points
    assert torch.equal(placed.face_ids[4:], plain.face_ids[4:]) and torch.equal(placed.bary[4:], plain.bary[4:])
