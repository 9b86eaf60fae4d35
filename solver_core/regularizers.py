"""Prior and regularisation energies shared by the optimisation stages.

Paper Sec. "Mocap Solving": E_Theta = 1/(|T| |Theta|) sum_t (Theta_img_t - Theta_t)^2 and
E_beta = (beta - beta_img)^2 / |beta_img| (mean squared error).  The temporal term is beyond the
paper (its per-frame energies leave Stage-2 jitter visible in MPJVE).
"""

from __future__ import annotations

import torch

# Every energy measures distances in this unit before squaring.  The paper gives its weights
# (lambda_3D = 10, lambda_Theta = 1 / 0.1, lambda_beta = 1 / 0.1) without a length unit; the
# unit decides how data terms (squared distances) trade against the pose prior (squared radians).
# Centimetres balance them the way the paper's results need (see the ablation in the README).
DISTANCE_UNIT_M = 0.01


def pose_prior_energy(
    body_pose: torch.Tensor,
    prior_body_pose: torch.Tensor,
    root_orient: torch.Tensor | None = None,
    prior_root: torch.Tensor | None = None,
    frame_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean squared axis-angle difference to the prior.

    body_pose, prior_body_pose: (T,23,3); root_orient, prior_root: (T,3) or None (root excluded);
    frame_weights: (T,) or None.  Returns a scalar.
    """
    diff = (body_pose - prior_body_pose).reshape(body_pose.shape[0], -1)
    if root_orient is not None:
        diff = torch.cat([root_orient - prior_root, diff], dim=1)
    per_frame = (diff**2).mean(dim=1)
    if frame_weights is None:
        return per_frame.mean()
    return (per_frame * frame_weights).sum() / frame_weights.sum().clamp(min=1e-9)


def mean_pose_offset_energy(body_pose: torch.Tensor, prior_body_pose: torch.Tensor) -> torch.Tensor:
    """Sum over joints of the squared MEAN (over frames) axis-angle difference to the prior.

    body_pose, prior_body_pose: (T,23,3).  A video estimator's per-frame error is large but
    comes and goes within a fraction of a second; its mean over a take is small.  Where the
    markers do not decide a joint's rotation (a limb with two or three markers can slide its
    points and its pose together at almost no cost), this term picks the rotation the video
    sees on average, while the per-frame prior stays weak enough not to add the video's jitter.
    """
    return ((body_pose - prior_body_pose).mean(dim=0) ** 2).sum()


def shape_prior_energy(betas: torch.Tensor, shape_prior: torch.Tensor) -> torch.Tensor:
    """Paper Eq. shape-MSE: mean over components of (beta - beta_img)^2.  betas (B,), shape_prior (B,)."""
    n = min(betas.shape[-1], shape_prior.shape[-1])
    return ((betas[..., :n] - shape_prior[..., :n]) ** 2).mean()


def temporal_smoothness_energy(joints: torch.Tensor) -> torch.Tensor:
    """Mean squared second difference of joint positions over frames.  joints (T,J,3) -> scalar
    (0 for fewer than 3 frames)."""
    if joints.shape[0] < 3:
        return joints.new_zeros(())
    accel = joints[2:] - 2.0 * joints[1:-1] + joints[:-2]
    return (accel**2).sum(-1).mean()
