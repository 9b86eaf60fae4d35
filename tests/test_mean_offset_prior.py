"""The mean-offset pose prior: the window's MEAN rotation difference to the video prior per joint
(regularizers.mean_pose_offset_energy), which decides joints the markers leave free."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def test_energy_sees_only_the_mean_offset():
    from uuomocap.solver_core.regularizers import mean_pose_offset_energy

    prior = torch.randn(50, 23, 3) * 0.3
    wiggle = torch.randn(50, 23, 3) * 0.2
    wiggle = wiggle - wiggle.mean(0, keepdim=True)  # zero-mean per joint: no systematic offset
    assert float(mean_pose_offset_energy(prior + wiggle, prior)) < 1e-10
    offset = torch.zeros(23, 3)
    offset[17] = torch.tensor([0.1, 0.0, -0.2])  # left elbow off by a constant
    energy = mean_pose_offset_energy(prior + wiggle + offset, prior)
    assert float(energy) == pytest.approx(0.05, rel=1e-4)


def test_ik_puts_an_unobserved_joint_at_the_prior_mean():
    """No marker on the left forearm: with no per-frame pose prior, only the mean-offset term
    moves the left elbow - to the prior's mean offset from the start, not to each frame's prior."""
    from uuomocap.solver_core.body_params import BodyParams, FreeParameters, MarkerAttachment, up_tensor
    from uuomocap.solver_core.inverse_kinematics import InverseKinematicsConfig, solve_inverse_kinematics
    from uuomocap.solver_core.marker_sim import marker_trajectories, random_layout
    from uuomocap.solver_core.motions import make_procedural_motion
    from uuomocap.solver_core.parts import vertex_dominant_joint
    from uuomocap.solver_methods import load_models

    model, _ = load_models("open-low")
    betas = np.zeros(model.num_betas)
    motion = make_procedural_motion("walk", model, betas, duration_s=0.5, rate_hz=30.0, seed=1)
    poses, trans = np.asarray(motion.poses, float), np.asarray(motion.trans, float)
    layout = random_layout(model, betas, 50, seed=4)
    # keep markers whose face is not on the left forearm / hand (joints 18 = left elbow, 20, 22)
    dominant = vertex_dominant_joint(model)
    keep = [i for i, f in enumerate(layout.face_ids) if not np.isin(dominant[model.faces[f]].numpy(), (18, 20, 22)).any()]
    layout = layout.subset(keep)
    markers = torch.as_tensor(marker_trajectories(model, betas, poses, trans, layout), dtype=torch.float32)
    frames = poses.shape[0]
    truth_body = torch.as_tensor(poses[:, 3:], dtype=torch.float32).reshape(frames, 23, 3)
    root = torch.as_tensor(poses[:, :3], dtype=torch.float32)
    att = MarkerAttachment(torch.as_tensor(layout.face_ids), torch.as_tensor(layout.bary, dtype=torch.float32), torch.zeros(len(keep)))
    noise = torch.randn(frames, 3, generator=torch.Generator().manual_seed(0)) * 0.2
    prior_body = truth_body.clone()
    prior_body[:, 17] += noise - noise.mean(0) + torch.tensor([0.0, 0.0, 0.3])  # elbow: jitter + a 0.3 rad mean offset
    init = BodyParams(root.clone(), truth_body.clone(), torch.as_tensor(trans, dtype=torch.float32),
                      torch.zeros(model.num_betas), torch.zeros(()))
    vis = torch.ones(markers.shape[:2], dtype=torch.bool)
    elbow = {}
    for weight in (0.0, 1.0):
        cfg = InverseKinematicsConfig(pose_weight=0.0, shape_weight=1.0, mean_offset_weight=weight)
        out, _ = solve_inverse_kinematics(model, markers, vis, att, root, prior_body, torch.zeros(model.num_betas), init,
                                          up_tensor(motion.up_axis), cfg, FreeParameters(yaw=False), 30.0, bias_prior=prior_body)
        elbow[weight] = out.body_pose[:, 17] - truth_body[:, 17]
    # without the term nothing moves the elbow from its start (the truth); with it the elbow takes
    # the prior's mean offset, and not the prior's per-frame jitter
    assert float(elbow[0.0].abs().max()) < 1e-3
    mean = elbow[1.0].mean(0)
    assert float(mean[2]) == pytest.approx(0.3, abs=0.02)
    assert float((elbow[1.0] - mean).abs().max()) < 0.02
