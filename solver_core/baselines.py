"""Baselines and references of the paper's evaluation (Sec. "Compared methods"), built from the
solver's own stage functions so they differ from the full method only where they should.

- ``video_rigid_registration``: HMR2.0+RR - the video prior's pose and shape, rigidly registered
  to the unlabeled markers (yaw from four starts + per-frame translation, closed-form ICP to the
  whole body's vertices).
- ``labeled_inverse_kinematics``: the labelled-marker reference (MoSh++'s role in the paper):
  IK (Stage 4, then Stage 5's re-regularised repeat) with KNOWN marker-surface correspondences.
  With labels the heading is solved in closed form, so it needs neither part matching nor yaw
  hypotheses.  Also what turns real labelled captures into motions.
``no-mht`` and ``markers-only`` are configurations of ``staged_solver.solve`` (one yaw
hypothesis; a neutral upright prior) - see ``uuomocap.solver_methods``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core.body_params import BodyParams, FreeParameters, MarkerAttachment, pose_params, up_tensor
from uuomocap.solver_core.inverse_kinematics import InverseKinematicsConfig, predicted_markers, solve_inverse_kinematics
from uuomocap.solver_core.part_matching import full_translation, rigid_yaw_icp
from uuomocap.solver_core.prior_preparation import BodyPrior


# The labelled reference's Stage 4: the paper's weights except the shape prior.  Its shape prior is
# the video's shape, which is shrunk and noisy; with the points known, 40 markers see the shape far
# better (MPJPE over all 24 joints, lambda_beta 1 / 0.1 / 0.01: 13 generated 40-marker takes
# 4.7 / 3.1 / 2.7 mm, the bench's walk / jump / arms 4.5 / 3.7 / 3.6; 0.001 as 0.01).  A reference that is
# held to the video's shape would flatter every unlabelled method measured against it.
LABELED_IK = InverseKinematicsConfig(shape_weight=0.01)


@dataclass
class BaselineResult:
    params: BodyParams
    diagnostics: dict


def _evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
    if len(indices) <= count:
        return indices
    return indices[np.unique(np.linspace(0, len(indices) - 1, count).round().astype(int))]


@torch.no_grad()
def prior_yaw_registration(
    markers: np.ndarray,
    visible: np.ndarray,
    up_axis: str,
    prior: BodyPrior,
    shape_prior: np.ndarray,
    model,
    yaw_starts_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0),
    frames: int = 60,
    icp_iterations: int = 20,
) -> tuple[float, float]:
    """The prior body's yaw registered to the markers by ICP on ``frames`` evenly spaced frames.

    markers (T,M,3) metres NaN missing; visible (T,M); prior: world prior at marker frames;
    shape_prior (B,); model: body model (its every vertex is a registration target).
    Returns (yaw radians, RMS marker-to-vertex distance metres) of the best start.
    """
    up = up_tensor(up_axis)
    vis_np = np.asarray(visible, bool) & np.isfinite(markers).all(-1)
    nb = min(len(shape_prior), model.num_betas)
    betas = torch.as_tensor(np.asarray(shape_prior)[:nb], dtype=torch.float32)
    sel = torch.as_tensor(_evenly_spaced(np.flatnonzero(vis_np.any(1)), frames))
    root = torch.as_tensor(prior.root_orient, dtype=torch.float32)[sel]
    body = torch.as_tensor(prior.body_pose, dtype=torch.float32)[sel]
    out = pose_params(model, BodyParams(root, body, torch.zeros(len(sel), 3), betas, torch.zeros(())), up)
    pts = (out.vertices - out.joints[:, :1])[None].expand(len(yaw_starts_deg), -1, -1, -1)
    starts = torch.tensor([math.radians(d) for d in yaw_starts_deg], dtype=torch.float32)
    mk = torch.as_tensor(np.asarray(markers)[sel.numpy()], dtype=torch.float32)
    yaw, _, err, _, _ = rigid_yaw_icp(pts, mk, torch.as_tensor(vis_np[sel.numpy()]), up, starts, icp_iterations)
    best = int(torch.argmin(err))
    return float(yaw[best]), math.sqrt(float(err[best]))


def video_rigid_registration(
    markers: np.ndarray,
    visible: np.ndarray,
    up_axis: str,
    prior: BodyPrior,
    shape_prior: np.ndarray,
    model,
    yaw_starts_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0),
    frames: int = 60,
    icp_iterations: int = 20,
) -> BaselineResult:
    """HMR2.0+RR: prior pose/shape; yaw and per-frame translation registered to the markers.

    markers (T,M,3) metres NaN missing; visible (T,M); prior: world prior at marker frames;
    shape_prior (B,); model: body model (its every vertex is a registration target).
    """
    yaw, rms = prior_yaw_registration(markers, visible, up_axis, prior, shape_prior, model, yaw_starts_deg, frames, icp_iterations)
    vis = torch.as_tensor(np.asarray(visible, bool) & np.isfinite(markers).all(-1))
    root = torch.as_tensor(prior.root_orient, dtype=torch.float32)
    body = torch.as_tensor(prior.body_pose, dtype=torch.float32)
    nb = min(len(shape_prior), model.num_betas)
    betas = torch.as_tensor(np.asarray(shape_prior)[:nb], dtype=torch.float32)
    yaw_t = torch.tensor(yaw, dtype=torch.float32)
    all_ids = np.arange(model.v_template.shape[0])
    trans = full_translation(model, torch.as_tensor(markers, dtype=torch.float32), vis, root, body, betas, up_tensor(up_axis), all_ids, yaw_t)
    params = BodyParams(root.clone(), body.clone(), trans, betas.clone(), yaw_t.clone())
    return BaselineResult(params, {"yaw_deg": math.degrees(yaw) % 360.0, "icp_rms_mm": 1000 * rms})


@torch.no_grad()
def labeled_heading_and_translation(
    model, markers: torch.Tensor, visible: torch.Tensor, attachment: MarkerAttachment, root: torch.Tensor,
    body: torch.Tensor, betas: torch.Tensor, up: torch.Tensor, offset_m: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form yaw (about ``up``) and per-frame translation that best place the prior body's
    predicted markers on the labelled markers (1-D Procrustes with known correspondences)."""
    frames = markers.shape[0]
    zero = BodyParams(root, body, torch.zeros(frames, 3), betas, torch.zeros(()))
    pred = predicted_markers(model, zero, attachment, up, offset_m)  # (T,Ma,3)
    centre = pose_params(model, zero, up, points=_one_point()).joints[:, :1]
    mk = torch.nan_to_num(markers[:, attachment.assigned])
    w = visible[:, attachment.assigned].float()
    wsum = w.sum(1).clamp(min=1.0)
    p = pred - centre
    p_c = (p * w[..., None]).sum(1) / wsum[:, None]
    m_c = (mk * w[..., None]).sum(1) / wsum[:, None]
    pt = p - p_c[:, None]
    mt = mk - m_c[:, None]
    p_perp = pt - (pt @ up)[..., None] * up
    cross = torch.linalg.cross(up.expand_as(pt), pt, dim=-1)
    a = ((mt * p_perp).sum(-1) * w).sum()
    b = ((mt * cross).sum(-1) * w).sum()
    yaw = torch.atan2(b, a)
    from uuomocap.solver_core.body_params import yaw_matrix

    rot = yaw_matrix(yaw, up)
    offset = m_c - p_c @ rot.T  # world = R p + offset, p relative to the pelvis
    trans = offset - centre[:, 0]
    has = visible[:, attachment.assigned].any(1)
    if bool((~has).any()) and bool(has.any()):
        idx = torch.arange(frames)
        good = idx[has]
        nearest = good[torch.searchsorted(good, idx).clamp(max=len(good) - 1)]
        trans[~has] = trans[nearest[~has]]
    return yaw, trans


def labeled_inverse_kinematics(
    markers: np.ndarray,
    visible: np.ndarray,
    up_axis: str,
    prior: BodyPrior,
    shape_prior: np.ndarray,
    attachment: MarkerAttachment,
    model,
    config: InverseKinematicsConfig = LABELED_IK,
    refinement_rounds: int = 1,
    rate_hz: float = 30.0,
) -> BaselineResult:
    """The labelled reference: IK with known face/barycentric attachments (+ Stage-5-style
    re-regularised repeats).  markers (T,M,3); attachment: per marker (face -1 = ghost/unknown)."""
    up = up_tensor(up_axis)
    vis_np = np.asarray(visible, bool) & np.isfinite(markers).all(-1)
    mk = torch.as_tensor(markers, dtype=torch.float32)
    vis = torch.as_tensor(vis_np)
    root = torch.as_tensor(prior.root_orient, dtype=torch.float32)
    body = torch.as_tensor(prior.body_pose, dtype=torch.float32)
    nb = min(len(shape_prior), model.num_betas)
    betas = torch.as_tensor(np.asarray(shape_prior)[:nb], dtype=torch.float32)
    yaw, trans = labeled_heading_and_translation(model, mk, vis, attachment, root, body, betas, up, config.marker_offset_m)
    init = BodyParams(root.clone(), body.clone(), trans, betas.clone(), yaw.detach().clone())
    params, rep = solve_inverse_kinematics(model, mk, vis, attachment, root, body, betas, init, up, config, FreeParameters(yaw=False), rate_hz)
    for _ in range(refinement_rounds):
        params, rep = solve_inverse_kinematics(
            model, mk, vis, attachment, params.root_orient, params.body_pose, betas, params, up, config, FreeParameters(yaw=False), rate_hz
        )
    return BaselineResult(params, {"yaw_deg": math.degrees(float(yaw)) % 360.0, "ik_loss": rep.final_loss})


def _one_point():
    from uuomocap.solver_core import lbs

    return lbs.SurfacePoints.from_vertex_ids(torch.zeros(1, dtype=torch.long))
