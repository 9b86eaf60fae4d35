"""Stage 2: pose fitting (paper Sec. "Mocap Solving", Stage 2).

Optimise the yaw offset b, the per-frame pose Theta (and root orientation), translation Gamma and
shape beta by
    E_pose = lambda_3D E_3D (unidirectional chamfer markers -> body vertices)
           + lambda_beta E_beta (shape prior) + lambda_Theta E_Theta (pose prior)
with L-BFGS, lr 0.1.  The chamfer targets are the vertices of the matched part (all vertices for a
full body) of the LOW-resolution model: nearest-vertex search is the cost and the coarse mesh
loses nothing at the data's noise level.

A pure function over any window of frames: inputs are explicit tensors (markers, visibility,
prior pose window, shape prior, warm start), outputs are new parameters and a report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from uuomocap.solver_core.body_params import BodyParams, FreeParameters, apply_root_offset, pose_body, tilt_matrix
from uuomocap.solver_core import lbs
from uuomocap.solver_core.chamfer import NearestTargetCache, nearest_indices, vertex_face_table
from uuomocap.solver_core.mesh import closest_point_on_vertex_fans
from uuomocap.solver_core.optimization import LBFGSConfig, OptimizationReport, run_lbfgs
from uuomocap.solver_core.regularizers import DISTANCE_UNIT_M, pose_prior_energy, shape_prior_energy, temporal_smoothness_energy


@dataclass(frozen=True)
class PoseFittingConfig:
    # Paper Sec. "Implementation": lambda_3D = 10 at Stage 2.
    chamfer_weight: float = 10.0
    # "surface" (beyond the paper: each marker to the closest point of the faces around its
    # nearest vertex, lifted by the marker offset along the face normal, so the true body is
    # the minimum) or "vertex" (the paper's chamfer to the nearest vertex, which pulls the skin
    # 9.5 mm + half a vertex spacing towards the markers).
    data_term: str = "surface"
    # Paper Sec. Stage 4: delta = 9.5 mm, used by the "surface" data term.
    marker_offset_m: float = 0.0095
    # Paper Sec. "Implementation": lambda_Theta = 1 at Stage 2.
    pose_weight: float = 1.0
    # Paper Sec. "Implementation": lambda_beta = 1 at Stage 2.
    shape_weight: float = 1.0
    # Beyond the paper: the pose prior also holds the root orientation (before the yaw offset),
    # which the published energy leaves free; partial bodies otherwise tilt the whole body.
    prior_includes_root: bool = True
    # Beyond the paper: weight of the joint-acceleration term (0 = the paper's per-frame energy).
    smoothness_weight: float = 0.0
    # Beyond the paper: also estimate the video camera's tilt (pitch/roll, one rotation for the
    # whole take).  The paper maps camera axes to the world assuming a level camera; a camera
    # looking down by 10 degrees tilts every prior root by 10 degrees, which the root prior
    # would otherwise keep.
    estimate_tilt: bool = True
    # Beyond the paper: weight of the tilt's prior (squared radians).
    tilt_weight: float = 0.1
    # Beyond the paper: Geman-McClure scale (metres) against ghost markers; None = plain squares.
    robust_scale_m: float | None = None
    # Paper Sec. "Implementation": L-BFGS lr 0.1 at Stage 2; early stopping instead of 10k iterations.
    lbfgs: LBFGSConfig = LBFGSConfig(lr=0.1, max_iterations=150, iterations_per_step=10, rel_tol=2e-4)
    # Energies measure distances in this unit (regularizers.DISTANCE_UNIT_M explains why it matters).
    distance_unit_m: float = DISTANCE_UNIT_M
    # Frame rate the smoothness weight is tuned for (the term scales with (rate/ref)^4).
    smoothness_reference_hz: float = 30.0


def fit_pose(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    prior_root: torch.Tensor,
    prior_body_pose: torch.Tensor,
    shape_prior: torch.Tensor,
    init: BodyParams,
    up: torch.Tensor,
    target_vertex_ids: torch.Tensor | None = None,
    config: PoseFittingConfig = PoseFittingConfig(),
    free: FreeParameters = FreeParameters(),
    rate_hz: float = 30.0,
    on_step: Callable[[int, float], None] | None = None,
) -> tuple[BodyParams, OptimizationReport, torch.Tensor]:
    """Stage 2 on a window of T frames.

    markers (T,M,3) metres, NaN where missing; visible (T,M) bool; prior_root (T,3) and
    prior_body_pose (T,23,3): the video prior (root before yaw); shape_prior (B,);
    init: warm start (yaw in ``init.yaw``); target_vertex_ids (Nc,) vertices of the matched part
    or None for every vertex.  Returns (fitted BodyParams, optimisation report, tilt (3,3)): the
    estimated camera tilt is folded into the returned root orientations, and later stages must
    compare them with ``apply_root_offset(prior_root, tilt)``.
    """
    unit = config.distance_unit_m
    root = init.root_orient.clone().requires_grad_(free.root_orient)
    body = init.body_pose.clone().requires_grad_(free.body_pose)
    trans = init.trans.clone().requires_grad_(free.trans)
    betas = init.betas.clone().requires_grad_(free.betas)
    yaw = init.yaw.clone().reshape(()).requires_grad_(free.yaw)
    tilt = torch.zeros(2, requires_grad=config.estimate_tilt and free.root_orient)
    markers_u = markers / unit
    smooth_scale = (rate_hz / config.smoothness_reference_hz) ** 4

    robust = None if config.robust_scale_m is None else config.robust_scale_m / unit
    targets = (
        torch.arange(model.v_template.shape[0]) if target_vertex_ids is None else torch.as_tensor(target_vertex_ids, dtype=torch.long)
    )

    if config.data_term not in ("surface", "vertex"):
        raise ValueError(f"data_term must be 'surface' or 'vertex', got {config.data_term!r}")
    table = vertex_face_table(model.faces, model.v_template.shape[0]) if config.data_term == "surface" else None
    # every evaluation's nearest-vertex search, exact, without a full search each time
    cache = NearestTargetCache()

    def energy() -> torch.Tensor:
        offset = tilt_matrix(tilt, up) if tilt.requires_grad else None
        if table is None:
            cham, joints = chamfer_to_body(model, markers_u, visible, root, body, trans, betas, yaw, up, targets, unit, robust, offset,
                                           cache)
        else:
            cham, joints = surface_chamfer_to_body(
                model, markers_u, visible, root, body, trans, betas, yaw, up, targets, table, unit,
                config.marker_offset_m / unit, robust, offset, cache,
            )
        if offset is not None:
            cham = cham + config.tilt_weight * (tilt**2).sum()
        total = config.chamfer_weight * cham
        total = total + config.pose_weight * pose_prior_energy(
            body, prior_body_pose, root if config.prior_includes_root else None, prior_root
        )
        total = total + config.shape_weight * shape_prior_energy(betas, shape_prior)
        if config.smoothness_weight > 0:
            total = total + config.smoothness_weight * smooth_scale * temporal_smoothness_energy(joints / unit)
        return total

    report = run_lbfgs([root, body, trans, betas, yaw, tilt], energy, config.lbfgs, on_step)
    offset = tilt_matrix(tilt.detach(), up)
    fitted = BodyParams(apply_root_offset(root.detach(), offset), body.detach(), trans.detach(), betas.detach(), yaw.detach())
    return fitted, report, offset


def chamfer_to_body(
    model,
    markers_u: torch.Tensor,
    visible: torch.Tensor,
    root: torch.Tensor,
    body: torch.Tensor,
    trans: torch.Tensor,
    betas: torch.Tensor,
    yaw: torch.Tensor,
    up: torch.Tensor,
    target_vertex_ids: torch.Tensor,
    unit: float,
    robust_scale: float | None = None,
    root_offset: torch.Tensor | None = None,
    nearest_cache: NearestTargetCache | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unidirectional chamfer (paper Eq. chamfer_unidirectional) from markers to posed target vertices.

    markers_u (T,M,3) in ``unit``; target_vertex_ids (Nc,).  Returns (chamfer scalar in unit^2,
    joints (T,24,3) metres).  The nearest vertex of every marker is found on a gradient-free
    skinning of the targets; then only the vertices that are somebody's nearest neighbour are
    skinned again with gradient (subset evaluation) - the same value and gradient as skinning the
    whole mesh, at a fraction of the cost.  nearest_cache: a ``NearestTargetCache`` shared by one
    optimisation's evaluations (same answers as the full search; None = full search every call).
    """
    with torch.no_grad():
        full = pose_body(model, root, body, trans, betas, yaw, up, lbs.SurfacePoints.from_vertex_ids(target_vertex_ids), root_offset)
        search = nearest_indices if nearest_cache is None else nearest_cache.nearest
        idx_local = search(markers_u, full.vertices / unit)  # (T,M) into target_vertex_ids
        used, inverse = torch.unique(idx_local, return_inverse=True)
    sub = pose_body(model, root, body, trans, betas, yaw, up, lbs.SurfacePoints.from_vertex_ids(target_vertex_ids[used]), root_offset)
    nearest = torch.gather(sub.vertices / unit, 1, inverse.unsqueeze(-1).expand(-1, -1, 3))
    sq = ((nearest - torch.nan_to_num(markers_u)) ** 2).sum(-1)
    if robust_scale is not None:
        c2 = robust_scale * robust_scale
        sq = c2 * sq / (sq + c2)
    w = visible.to(sq.dtype)
    return (sq * w).sum() / w.sum().clamp(min=1.0), sub.joints


def surface_chamfer_to_body(
    model,
    markers_u: torch.Tensor,
    visible: torch.Tensor,
    root: torch.Tensor,
    body: torch.Tensor,
    trans: torch.Tensor,
    betas: torch.Tensor,
    yaw: torch.Tensor,
    up: torch.Tensor,
    target_vertex_ids: torch.Tensor,
    vertex_faces: torch.Tensor,
    unit: float,
    offset_u: float,
    robust_scale: float | None = None,
    root_offset: torch.Tensor | None = None,
    nearest_cache: NearestTargetCache | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Marker-to-surface data term: mean over visible markers of || m - (q + offset n) ||^2 with q
    the closest point of the faces around the marker's nearest target vertex and n that face's
    normal.  markers_u (T,M,3) in ``unit``; vertex_faces from ``vertex_face_table``.
    Returns (energy in unit^2, joints (T,24,3) metres).  Face choice and barycentrics are found
    without gradient; the chosen faces' corners are skinned with gradient (subset evaluation).
    nearest_cache: as in ``chamfer_to_body``.
    """
    frames = markers_u.shape[0]
    mk = torch.nan_to_num(markers_u)
    with torch.no_grad():
        allv = pose_body(model, root, body, trans, betas, yaw, up, None, root_offset).vertices / unit  # (T,N,3)
        tgt = allv if target_vertex_ids.numel() == allv.shape[1] else allv[:, target_vertex_ids]
        search = nearest_indices if nearest_cache is None else nearest_cache.nearest
        nearest = target_vertex_ids[search(mk, tgt)]  # (T,M) vertex ids
        face, bary = closest_point_on_vertex_fans(mk, allv, nearest, model.faces, vertex_faces)  # (T,M), (T,M,3)
        used, inverse = torch.unique(model.faces[face], return_inverse=True)  # inverse (T,M,3)
    sub = pose_body(model, root, body, trans, betas, yaw, up, lbs.SurfacePoints.from_vertex_ids(used), root_offset)
    verts = sub.vertices / unit
    corners = torch.gather(verts, 1, inverse.reshape(frames, -1, 1).expand(-1, -1, 3)).reshape(frames, -1, 3, 3)
    q = (bary[..., None] * corners).sum(-2)
    n = torch.linalg.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    sq = ((mk - q - offset_u * n) ** 2).sum(-1)
    if robust_scale is not None:
        c2 = robust_scale * robust_scale
        sq = c2 * sq / (sq + c2)
    w = visible.to(sq.dtype)
    return (sq * w).sum() / w.sum().clamp(min=1.0), sub.joints
