"""Stage 4: inverse kinematics to the markers' surface points (paper Sec. "Mocap Solving", Stage 4).

    E_IK = lambda_M E_M + lambda_beta E_beta + lambda_Theta E_Theta
E_M pulls every visible marker to its body surface point, which sits delta = 9.5 mm under the
marker (SOMA/MoSh marker offset).  Two formulations:
  * "distance" (the paper): (|| s_m(t) - m(t) || - delta)^2;
  * "smooth_normal" (default, beyond the paper): || s_m(t) + delta n_m(t) - m(t) ||^2 with n the
    skin's smooth normal at the point (the blend of its face's vertex normals), which also fixes
    the marker's direction from the surface (3 constraints per marker instead of 1).  A marker's
    base sits on smooth skin, not on a facet of the model's mesh: on the 1229-vertex body the
    facet normal is 10 deg (mean; 21 deg p90) off the smooth one, which puts the predicted marker
    ~2 mm off at the true pose - twice the 0.8 mm of a calibrated system's noise.  The rest-pose
    smooth normal is carried in the posed face's frame (only the 3 corners are skinned): 0.9-1.1
    mm at the true pose.  The labelled IK uses it; the unlabelled solver keeps the facet normal
    (staged_solver.SolverConfig.ik says why);
  * "face_normal": the same with the posed face normal (sessions before 12).
Only the markers' surface points are skinned (subset evaluation of the body model), so a
450-frame, 40-marker window is cheap.  Invisible markers contribute nothing (occlusion-aware).

A pure function over any window: explicit markers/visibility/prior window, locked attachment and
a warm start; ``FreeParameters`` locks shape or yaw for the windowed solver.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from uuomocap.solver_core import lbs
from uuomocap.solver_core.body_params import BodyParams, FreeParameters, MarkerAttachment, pose_body
from uuomocap.solver_core.optimization import LBFGSConfig, OptimizationReport, run_lbfgs
from uuomocap.solver_core.regularizers import (DISTANCE_UNIT_M, mean_pose_offset_energy, pose_prior_energy, shape_prior_energy,
                                               temporal_smoothness_energy)


@dataclass(frozen=True)
class InverseKinematicsConfig:
    # Paper Sec. "Implementation": lambda_M = 1 at Stage 4.
    marker_weight: float = 1.0
    # Paper Sec. "Implementation": lambda_Theta = 0.1 at Stage 4.
    pose_weight: float = 0.1
    # Paper Sec. "Implementation": lambda_beta = 1 at Stage 4.
    shape_weight: float = 1.0
    # Paper Sec. Stage 4: delta = 9.5 mm marker offset from the skin (SOMA).
    marker_offset_m: float = 0.0095
    # "smooth_normal" (beyond the paper: offset along the skin's smooth normal), "face_normal" (along
    # the posed facet normal) or "distance" (paper's E_M).  Module docstring: why smooth.
    offset_model: str = "smooth_normal"
    # Beyond the paper: pose prior also on the root orientation.
    prior_includes_root: bool = True
    # Beyond the paper: joint-acceleration weight (0 = the paper's per-frame energy).
    smoothness_weight: float = 0.0
    # Beyond the paper: Geman-McClure scale (metres) against mislabelled / ghost markers.
    robust_scale_m: float | None = None
    # Beyond the paper (MoSh-style latent markers): a marker may sit off its surface point by a
    # per-marker displacement in the posed triangle's frame (tangent, tangent, normal), estimated
    # jointly with the pose under a Gaussian prior of this scale (metres).  Stage 3 picks points
    # under an imperfect pose; letting the points slide with the pose removes the bias that the
    # two steps alternating alone leave.  None = the paper's fixed points.
    marker_slack_m: float | None = None
    # Paper Sec. "Implementation": L-BFGS lr 1.0 for IK; early stopping instead of 10k iterations.
    lbfgs: LBFGSConfig = LBFGSConfig(lr=1.0, max_iterations=200, iterations_per_step=10, rel_tol=1e-4)
    # Energies measure distances in this unit (regularizers.DISTANCE_UNIT_M explains why it matters).
    distance_unit_m: float = DISTANCE_UNIT_M
    # Frame rate the smoothness weight is tuned for (the term scales with (rate/ref)^4).
    smoothness_reference_hz: float = 30.0
    # Beyond the paper: weight of the window's MEAN body-pose difference to ``bias_prior`` (the
    # video prior) per joint, in squared radians against the data term's squared centimetres.
    # 0 = off.  See ``mean_pose_offset_energy``.
    mean_offset_weight: float = 0.0


def attachment_corners(model, attachment: MarkerAttachment) -> lbs.SurfacePoints:
    """The three corner vertices of every assigned marker's face, as vertex points (3*Ma)."""
    faces = model.faces[attachment.face_ids[attachment.assigned]]
    return lbs.SurfacePoints.from_vertex_ids(faces.reshape(-1))


def posed_marker_frames(corners: torch.Tensor, bary: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface points and unit face normals from posed face corners.

    corners: (T, P, 3, 3) (corner k of point p); bary: (P,3).  Returns (points (T,P,3), normals (T,P,3)).
    """
    points = (corners * bary[None, :, :, None]).sum(dim=2)
    normal = torch.linalg.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0], dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    return points, normal


OFFSET_MODELS = ("smooth_normal", "face_normal", "distance")


def check_offset_model(name: str) -> None:
    if name not in OFFSET_MODELS:
        raise ValueError(f"offset_model must be one of {', '.join(OFFSET_MODELS)}; got {name!r}")


def smooth_normals_in_face_frames(model, betas: torch.Tensor, attachment: MarkerAttachment) -> torch.Tensor:
    """(Ma, 3) each assigned marker's smooth skin normal in its face's frame (``triangle_frames``
    coordinates), from the rest pose of shape ``betas`` (B,): the barycentric blend of the face
    corners' area-weighted vertex normals, renormalised.  Carried by the posed face's frame, it
    follows the skin without skinning the neighbouring vertices."""
    from uuomocap.solver_core.mesh import vertex_normals

    with torch.no_grad():
        rest = lbs.forward(model, betas.detach().reshape(1, -1).float(), torch.zeros(1, 24, 3)).vertices[0]
        normals = vertex_normals(rest, model.faces)
        tri = model.faces[attachment.face_ids[attachment.assigned]]  # (Ma,3)
        bary = attachment.bary[attachment.assigned].to(rest.dtype)
        n = (normals[tri] * bary[:, :, None]).sum(1)
        n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        return (triangle_frames(rest[tri]) @ n[:, :, None])[..., 0]


def offset_directions(corners: torch.Tensor, face_normals: torch.Tensor, smooth: torch.Tensor | None) -> torch.Tensor:
    """Unit directions (T, P, 3) along which each marker sits off its surface point.
    corners: (T, P, 3, 3) posed face corners; face_normals: (T, P, 3); smooth: (P, 3) from
    ``smooth_normals_in_face_frames`` or None (the facet normal)."""
    if smooth is None:
        return face_normals
    return (smooth.to(corners.dtype)[None, :, :, None] * triangle_frames(corners)).sum(-2)


def predicted_markers(
    model, params: BodyParams, attachment: MarkerAttachment, up: torch.Tensor, offset_m: float,
    offset_model: str = "smooth_normal",
) -> torch.Tensor:
    """(T, Ma, 3) marker positions the body predicts for the assigned markers (surface + offset
    along the smooth skin normal, or the facet normal for ``offset_model`` "face_normal" /
    "distance")."""
    check_offset_model(offset_model)
    corners_pts = attachment_corners(model, attachment)
    out = pose_body(model, params.root_orient, params.body_pose, params.trans, params.betas, params.yaw, up, corners_pts)
    corners = out.vertices.reshape(out.vertices.shape[0], -1, 3, 3)
    pts, nrm = posed_marker_frames(corners, attachment.bary[attachment.assigned])
    smooth = smooth_normals_in_face_frames(model, params.betas, attachment) if offset_model == "smooth_normal" else None
    return pts + offset_m * offset_directions(corners, nrm, smooth)


def triangle_frames(corners: torch.Tensor) -> torch.Tensor:
    """Orthonormal frames (..., 3, 3) of triangles (..., 3 corners, 3): rows = first edge
    direction, in-plane perpendicular, unit normal."""
    e1 = corners[..., 1, :] - corners[..., 0, :]
    n = torch.linalg.cross(e1, corners[..., 2, :] - corners[..., 0, :], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    e2 = torch.linalg.cross(n, e1, dim=-1)
    return torch.stack([e1, e2, n], dim=-2)


def solve_inverse_kinematics(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    attachment: MarkerAttachment,
    prior_root: torch.Tensor,
    prior_body_pose: torch.Tensor,
    shape_prior: torch.Tensor,
    init: BodyParams,
    up: torch.Tensor,
    config: InverseKinematicsConfig = InverseKinematicsConfig(),
    free: FreeParameters = FreeParameters(yaw=False),
    rate_hz: float = 30.0,
    on_step: Callable[[int, float], None] | None = None,
    bias_prior: torch.Tensor | None = None,
) -> tuple[BodyParams, OptimizationReport]:
    """Stage 4 on a window of T frames.

    markers (T,M,3) metres; visible (T,M) bool; attachment: per-marker face/bary (locked);
    prior_root (T,3), prior_body_pose (T,23,3): the pose prior (video prior at Stage 4, the Stage-4
    result at Stage 5), in the same yaw convention as ``init``; shape_prior (B,); init: warm start.
    Returns (BodyParams, optimisation report).
    """
    params, report, _ = _solve(model, markers, visible, attachment, prior_root, prior_body_pose, shape_prior, init, up,
                               config, free, rate_hz, on_step, bias_prior)
    return params, report


def solve_inverse_kinematics_with_slack(
    model, markers, visible, attachment, prior_root, prior_body_pose, shape_prior, init, up,
    config: InverseKinematicsConfig, free: FreeParameters = FreeParameters(yaw=False), rate_hz: float = 30.0, on_step=None,
    bias_prior: torch.Tensor | None = None,
) -> tuple[BodyParams, OptimizationReport, torch.Tensor]:
    """Stage 4 with latent markers (``config.marker_slack_m`` must be set): as
    ``solve_inverse_kinematics`` and also each assigned marker's displacement (Ma,3) metres in its
    triangle frame (``triangle_frames``: along the first edge, in-plane perpendicular, normal -
    the normal part is on top of the 9.5 mm offset).  ``fold_marker_slack`` turns it into new
    surface points."""
    if config.marker_slack_m is None:
        raise ValueError("marker_slack_m is None: use solve_inverse_kinematics")
    return _solve(model, markers, visible, attachment, prior_root, prior_body_pose, shape_prior, init, up, config, free,
                  rate_hz, on_step, bias_prior)


def fold_marker_slack(model, betas: torch.Tensor, attachment: MarkerAttachment, displacement: torch.Tensor,
                      vertex_faces: torch.Tensor | None = None) -> MarkerAttachment:
    """New surface points: each assigned marker's point moved by the tangential part of its
    displacement (Ma,3) on the rest-pose surface of shape ``betas`` and snapped back onto the
    closest face among those around its old face's corners (a step of a few cm at most)."""
    from uuomocap.solver_core.chamfer import vertex_face_table
    from uuomocap.solver_core.mesh import closest_point_on_triangles

    assigned = attachment.assigned
    if not bool(assigned.any()):
        return attachment
    with torch.no_grad():
        rest = lbs.forward(model, betas.reshape(1, -1), torch.zeros(1, 24, 3)).vertices[0]  # (N,3)
        faces = model.faces
        fid = attachment.face_ids[assigned]
        corners = rest[faces[fid]]  # (Ma,3,3)
        frame = triangle_frames(corners)
        point = (corners * attachment.bary[assigned][:, :, None]).sum(1)
        target = point + displacement[:, 0:1] * frame[:, 0] + displacement[:, 1:2] * frame[:, 1]
        if vertex_faces is None:
            vertex_faces = vertex_face_table(faces, rest.shape[0])
        # candidate faces: every face touching a vertex of the faces around the old face's corners
        ring = vertex_faces[faces[fid]].reshape(len(fid), -1)  # (Ma, 3K) faces around the corners (-1 padded)
        ring_v = faces[ring.clamp(min=0)].reshape(len(fid), -1)  # their vertices
        cand = vertex_faces[ring_v].reshape(len(fid), -1)  # faces around those: a 2-ring patch
        cand = torch.where(cand < 0, fid[:, None], cand)
        tri = rest[faces[cand]]  # (Ma,C,3,3)
        p = target[:, None].expand(-1, cand.shape[1], -1)
        bary = closest_point_on_triangles(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
        q = (bary[..., None] * tri).sum(-2)
        best = ((q - p) ** 2).sum(-1).argmin(1)
        rows = torch.arange(len(fid))
        face_ids = attachment.face_ids.clone()
        new_bary = attachment.bary.clone()
        face_ids[assigned] = cand[rows, best]
        new_bary[assigned] = bary[rows, best].to(new_bary.dtype)
    return MarkerAttachment(face_ids, new_bary, attachment.score_m)


def _solve(model, markers, visible, attachment, prior_root, prior_body_pose, shape_prior, init, up, config, free, rate_hz,
           on_step, bias_prior=None):
    check_offset_model(config.offset_model)
    unit = config.distance_unit_m
    assigned = attachment.assigned
    mk = torch.nan_to_num(markers[:, assigned]) / unit
    weight = visible[:, assigned].to(mk.dtype)
    weight_sum = weight.sum().clamp(min=1.0)
    corners_pts = attachment_corners(model, attachment)
    bary = attachment.bary[assigned].to(mk.dtype)
    delta = config.marker_offset_m / unit
    robust = None if config.robust_scale_m is None else (config.robust_scale_m / unit) ** 2
    smooth_scale = (rate_hz / config.smoothness_reference_hz) ** 4

    root = init.root_orient.clone().requires_grad_(free.root_orient)
    body = init.body_pose.clone().requires_grad_(free.body_pose)
    trans = init.trans.clone().requires_grad_(free.trans)
    betas = init.betas.clone().requires_grad_(free.betas)
    yaw = init.yaw.clone().reshape(()).requires_grad_(free.yaw)
    slack = config.marker_slack_m is not None
    disp = torch.zeros(mk.shape[1], 3, dtype=mk.dtype, requires_grad=slack)
    slack_scale = (config.marker_slack_m / unit) ** 2 if slack else 1.0
    # the smooth normals at the warm start's shape: a shape step moves them by far less than a degree
    smooth = smooth_normals_in_face_frames(model, init.betas, attachment) if config.offset_model == "smooth_normal" else None

    def energy() -> torch.Tensor:
        out = pose_body(model, root, body, trans, betas, yaw, up, corners_pts)
        corners = out.vertices.reshape(out.vertices.shape[0], -1, 3, 3) / unit
        pts, nrm = posed_marker_frames(corners, bary)
        if config.offset_model != "distance":
            nrm = offset_directions(corners, nrm, smooth)
        if slack:
            frame = triangle_frames(corners)  # (T,Ma,3,3)
            offset = (disp[None, :, :, None] * frame).sum(-2) + delta * nrm
            sq = ((pts + offset - mk) ** 2).sum(-1)
        elif config.offset_model != "distance":
            sq = ((pts + delta * nrm - mk) ** 2).sum(-1)
        else:
            sq = ((pts - mk).norm(dim=-1) - delta) ** 2
        if robust is not None:
            sq = robust * sq / (sq + robust)
        total = config.marker_weight * (sq * weight).sum() / weight_sum
        if slack:  # per marker, on the scale of one marker's share of the data term
            total = total + (disp**2).sum() / slack_scale / max(1, disp.shape[0])
        total = total + config.pose_weight * pose_prior_energy(
            body, prior_body_pose, root if config.prior_includes_root else None, prior_root
        )
        total = total + config.shape_weight * shape_prior_energy(betas, shape_prior)
        if bias_prior is not None and config.mean_offset_weight > 0:
            total = total + config.mean_offset_weight * mean_pose_offset_energy(body, bias_prior)
        if config.smoothness_weight > 0:
            total = total + config.smoothness_weight * smooth_scale * temporal_smoothness_energy(out.joints / unit)
        return total

    report = run_lbfgs([root, body, trans, betas, yaw, disp], energy, config.lbfgs, on_step)
    params = BodyParams(root.detach(), body.detach(), trans.detach(), betas.detach(), yaw.detach())
    return params, report, disp.detach() * unit
