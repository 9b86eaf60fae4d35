"""The marker offset model: a marker sits 9.5 mm off the skin along the skin's SMOOTH normal (the
blend of its face's vertex normals), which the solver carries in the posed face's frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.fixture(scope="module")
def exact_walk():
    """Noise-free markers of a short walk on the true body, with the true parameters and points."""
    from uuomocap.solver_core.body_params import BodyParams, MarkerAttachment
    from uuomocap.solver_core.marker_sim import marker_trajectories, random_layout
    from uuomocap.solver_core.motions import make_procedural_motion
    from uuomocap.solver_methods import load_models

    model, _ = load_models("open-low")
    betas = np.zeros(model.num_betas)
    betas[:2] = (0.8, -0.5)
    motion = make_procedural_motion("walk", model, betas, duration_s=1.0, rate_hz=30.0, seed=3)
    poses, trans = np.asarray(motion.poses, float), np.asarray(motion.trans, float)
    layout = random_layout(model, betas, 30, seed=5)
    markers = marker_trajectories(model, betas, poses, trans, layout)
    frames = poses.shape[0]
    truth = BodyParams(torch.as_tensor(poses[:, :3], dtype=torch.float32),
                       torch.as_tensor(poses[:, 3:], dtype=torch.float32).reshape(frames, 23, 3),
                       torch.as_tensor(trans, dtype=torch.float32), torch.as_tensor(betas, dtype=torch.float32), torch.zeros(()))
    att = MarkerAttachment(torch.as_tensor(layout.face_ids), torch.as_tensor(layout.bary, dtype=torch.float32),
                           torch.zeros(len(layout)))
    return model, truth, att, torch.as_tensor(markers, dtype=torch.float32), str(motion.up_axis)


def test_smooth_normal_in_the_face_frame_is_the_rest_pose_blend(exact_walk):
    from uuomocap.solver_core import lbs
    from uuomocap.solver_core.inverse_kinematics import offset_directions, posed_marker_frames, smooth_normals_in_face_frames
    from uuomocap.solver_core.mesh import vertex_normals

    model, truth, att, _, _ = exact_walk
    local = smooth_normals_in_face_frames(model, truth.betas, att)
    assert local.shape == (len(att.face_ids), 3)
    assert torch.allclose(local.norm(dim=1), torch.ones(len(local)), atol=1e-5)
    rest = lbs.forward(model, truth.betas.reshape(1, -1), torch.zeros(1, 24, 3)).vertices[0]
    tri = model.faces[att.face_ids]
    expected = (vertex_normals(rest, model.faces)[tri] * att.bary[:, :, None]).sum(1)
    expected = expected / expected.norm(dim=1, keepdim=True)
    corners = rest[tri][None]
    _, facet = posed_marker_frames(corners, att.bary)
    carried = offset_directions(corners, facet, local)[0]
    assert torch.allclose(carried, expected, atol=1e-5)
    # the facet normal is a different direction on a coarse mesh: the two models really differ
    assert float(torch.rad2deg(torch.arccos((facet[0] * expected).sum(1).clamp(-1, 1))).mean()) > 3.0


def test_smooth_offset_predicts_simulated_markers_better_than_the_facet_normal(exact_walk):
    from uuomocap.solver_core.body_params import up_tensor
    from uuomocap.solver_core.inverse_kinematics import predicted_markers

    model, truth, att, markers, up_axis = exact_walk
    up = up_tensor(up_axis)
    smooth = (predicted_markers(model, truth, att, up, 0.0095) - markers).norm(dim=-1)
    facet = (predicted_markers(model, truth, att, up, 0.0095, "face_normal") - markers).norm(dim=-1)
    # at the true pose the smooth model is off only where skinning bends the face's neighbourhood
    assert float(smooth.median()) < 0.5e-3
    assert float(smooth.mean()) < 0.5 * float(facet.mean())
    with pytest.raises(ValueError, match="offset_model"):
        predicted_markers(model, truth, att, up, 0.0095, "normal")


def test_stage3_recovers_the_true_points_from_exact_markers_at_the_true_pose(exact_walk):
    from uuomocap.solver_core.body_params import up_tensor
    from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, find_marker_surface_points
    from uuomocap.solver_core.metrics import surface_points_rest

    model, truth, att, markers, up_axis = exact_walk
    visible = torch.ones(markers.shape[:2], dtype=torch.bool)
    betas = truth.betas.numpy()
    true_pts = surface_points_rest(model, betas, att.face_ids.numpy(), att.bary.numpy())
    errors = {}
    for smooth in (True, False):
        found = find_marker_surface_points(model, markers, visible, truth, up_tensor(up_axis),
                                           config=CorrespondenceConfig(smooth_normals=smooth))
        pts = surface_points_rest(model, betas, found.face_ids.numpy(), found.bary.numpy())
        errors[smooth] = np.linalg.norm(pts - true_pts, axis=1)
    assert np.median(errors[True]) < 0.5e-3
    assert errors[True].mean() < 0.5 * errors[False].mean()
