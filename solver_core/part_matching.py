"""Marker-part matching (paper Sec. "Marker-Part Matching", Step 2: hypothesis testing for part localisation).

Given the K marker groups from segmentation, the candidates are the connected K-joint subtrees of
the kinematic tree (the published code enumerates all connected subtrees, not only chains).  Each
candidate is fitted to the markers with the body's pose fixed to the video prior, optimising the
yaw, a per-frame translation and the shape, by the unidirectional chamfer from the markers to the
candidate's vertices (lambda=10) plus the shape prior (lambda=0.1); the lowest error wins.

Implementation (cheap and batched, beyond the paper's plain L-BFGS):
1. every (candidate, yaw start) pair is first registered by ICP in closed form - nearest
   vertices, per-frame translation = centroid difference, yaw = 1-D Procrustes about the up
   axis - on a subsample of frames;
2. the best few candidates are then refined by L-BFGS over yaw, translation and shape with the
   paper's energy, and the lowest energy is kept.
The translation starts from aligning per-frame marker and body centres (paper: medians).  Whether the markers cover the
full body is decided from bounding-box volumes (published code: marker box / body box > 0.4 ->
full body); a full body has the single candidate "all joints".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from uuomocap.solver_core.body_params import apply_root_offset, fill_nan_rows, pose_body, yaw_matrix
from uuomocap.solver_core.chamfer import NearestTargetCache, gather_points, nearest_indices
from uuomocap.solver_core.pose_fitting import chamfer_to_body
from uuomocap.solver_core.optimization import LBFGSConfig, run_lbfgs
from uuomocap.solver_core.regularizers import DISTANCE_UNIT_M
from uuomocap.solver_core.parts import connected_subtrees, vertex_dominant_joint
from uuomocap.solver_core.segment_rotation import (
    bone_relative_rotations,
    cluster_relative_rotations,
    frame_pairs,
    turn_mismatch,
)


@dataclass(frozen=True)
class PartMatchingConfig:
    # Paper Sec. "Step 2": weight of the unidirectional chamfer.
    chamfer_weight: float = 10.0
    # Paper Sec. "Step 2": weight of the shape prior.
    shape_weight: float = 0.1
    # Paper Sec. "Implementation": L-BFGS learning rate 1.0 for part localisation.
    lbfgs: LBFGSConfig = LBFGSConfig(lr=1.0, max_iterations=60, iterations_per_step=10, rel_tol=1e-4)
    # Paper Sec. "Step 2": prune candidates sharing >= 90 % of their joints with a kept one.
    prune_overlap: float = 0.9
    # Published code: marker bounding-box volume / body bounding-box volume > 0.4 -> full body.
    # Our boxes are per frame, yaw-invariant (up x two horizontal principal axes) and compared by
    # median: random full-body layouts of 20-50 markers score 0.13-0.41, the paper's parts
    # (leg, arm, shoulder with 12 markers) 0.01-0.05, so the threshold sits at 0.1.
    full_body_volume_ratio: float = 0.1
    # Paper Sec. "Stage 1": yaw starts (degrees) - every candidate is registered from each.
    yaw_starts_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    # Beyond the paper (speed): frames used to rank candidates (evenly spaced).
    frames: int = 48
    # Beyond the paper (speed): closed-form ICP iterations per (candidate, yaw start).
    icp_iterations: int = 15
    # Beyond the paper: the registration may also tilt the prior by up to this much (the video
    # camera's unknown pitch/roll; the paper assumes a level camera).  0 = yaw only.
    max_tilt_deg: float = 20.0
    # Beyond the paper (speed): candidates refined by L-BFGS after the ICP ranking.
    refine_top: int = 3
    # Bound on the enumeration: K is capped here for partial bodies (a part of the paper's
    # appendix has at most 5 joints; 8 leaves room for over-segmentation).
    max_part_joints: int = 8
    # Beyond the paper: K from the clusters is only a lower bound on the part's joints (bones
    # that do not bend against each other during the take fall into one cluster: a swinging arm
    # is often one cluster), and a too-small candidate cannot hold all markers, so partial-body
    # candidates have at least this many joints (the paper's parts have 3-4).
    min_part_joints: int = 4
    # Beyond the paper: weight of the turn signature (segment_rotation) in the candidate ranking,
    # per squared radian of mismatch between the clusters' measured turns and the prior's bones'.
    # A torso surface fits an arm's markers as well as the arm does; it does not turn like it.
    turn_weight: float = 60.0
    # Beyond the paper: calibrated capture volumes put the floor at height 0 along the up axis
    # (the ground plane of Vicon, OptiTrack and Qualisys calibrations), so a partial-body
    # candidate must place the whole body's lowest point near the floor for much of the take:
    # arm markers read as a thigh would float the feet 40 cm up.  None disables the term.
    floor_height_m: float | None = 0.0
    # Weight of that term per (0.1 m)^2 beyond a dead zone (prior pose errors move the feet).
    floor_weight: float = 10.0
    floor_dead_zone_m: float = 0.05
    # Beyond the paper (candidate-level MHT): partial-body candidates handed on, with their yaw
    # hypotheses, to Stage 1, which decides between them by the fit after IK.
    partial_alternatives: int = 3
    # Bound on the enumeration: never test more candidates than this (after pruning).
    max_candidates: int = 400
    # Beyond the paper: the part when it is already known (joint indices; None = search).  The
    # near-online lock upgrades re-solve the part their bootstrap chose: another part's result
    # would be refused anyway (WindowedSolver._finish_upgrade), and searching cost them the time.
    part_joints: tuple[int, ...] | None = None
    # Energies measure distances in this unit (regularizers.DISTANCE_UNIT_M explains why it matters).
    distance_unit_m: float = DISTANCE_UNIT_M


@dataclass
class YawStart:
    """One yaw hypothesis of the chosen candidate: ICP-refined yaw and its chamfer error."""

    start_deg: float
    yaw: float
    error: float
    tilt: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3,3) camera tilt correction


@dataclass
class PartMatch:
    joints: tuple[int, ...]            # joints of the chosen candidate (all 24 for a full body)
    vertex_ids: np.ndarray             # (Nc,) vertices whose dominant joint is in ``joints``
    yaw: float                         # radians, best yaw of the chosen candidate
    trans: np.ndarray                  # (T,3) translation for every frame at ``yaw``
    betas: np.ndarray                  # (B,) shape after the refinement
    error: float                       # paper E_S of the chosen candidate
    full_body: bool
    volume_ratio: float
    cluster_count: int
    candidates_tested: int
    yaw_starts: list[YawStart] = field(default_factory=list)
    ranking: list[tuple[tuple[int, ...], float]] = field(default_factory=list)  # (joints, E_S) best first
    tilt: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3,3) root offset (camera tilt) at ``yaw``
    turn_mismatch: float = 0.0         # rad^2, the turn-signature term of the chosen candidate
    alternatives: list["PartMatch"] = field(default_factory=list)  # next-best partial candidates


# ----------------------------------------------------------------------------- geometry helpers


def oriented_box_volume(points: np.ndarray, up: np.ndarray) -> float:
    """Volume of a yaw-invariant bounding box: extent along ``up`` x extents along the two
    horizontal principal axes.  points: (P,3); returns m^3 (0 for fewer than 2 points)."""
    pts = points[np.isfinite(points).all(axis=1)]
    if len(pts) < 2:
        return 0.0
    height = float(np.ptp(pts @ up))
    horiz = pts - np.outer(pts @ up, up)
    horiz = horiz - horiz.mean(axis=0)
    # principal horizontal axes
    cov = horiz.T @ horiz
    _, vecs = np.linalg.eigh(cov)
    a, b = vecs[:, 2], vecs[:, 1]
    return height * float(np.ptp(horiz @ a)) * float(np.ptp(horiz @ b))


def marker_to_body_volume_ratio(markers: np.ndarray, visible: np.ndarray, body_vertices: np.ndarray, up: np.ndarray) -> float:
    """Median over frames of marker box volume / body box volume (published full-body test).

    markers (T,M,3); visible (T,M); body_vertices (T',N,3) prior-posed body at some frames.
    """
    vols = [oriented_box_volume(markers[t][visible[t]], up) for t in range(markers.shape[0]) if visible[t].sum() >= 4]
    body = [oriented_box_volume(v, up) for v in body_vertices]
    if not vols or not body:
        return 0.0
    return float(np.median(vols) / max(np.median(body), 1e-9))


def candidate_part_joints(parents: torch.Tensor, k: int, overlap: float, max_candidates: int) -> list[tuple[int, ...]]:
    """Connected k-joint subtrees, pruned: drop one sharing >= ``overlap`` of its joints with a kept one."""
    subtrees = [tuple(sorted(s)) for s in connected_subtrees([int(p) for p in parents], k)]
    kept: list[tuple[int, ...]] = []
    kept_sets: list[set[int]] = []
    for cand in subtrees:
        cs = set(cand)
        if any(len(cs & ks) >= overlap * len(cs) for ks in kept_sets):
            continue
        kept.append(cand)
        kept_sets.append(cs)
        if len(kept) >= max_candidates:
            break
    return kept


def rigid_yaw_icp(
    points: torch.Tensor,
    markers: torch.Tensor,
    visible: torch.Tensor,
    up: torch.Tensor,
    yaw_start: torch.Tensor,
    iterations: int,
    max_tilt_rad: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closed-form ICP for a yaw about ``up`` (and, if ``max_tilt_rad`` > 0, a tilt of at most that
    angle about a horizontal axis) and a translation, batched over hypotheses.

    The translation of frame t aligns the model's centroid with the markers' reference point
    (``marker_centroid``; the paper aligns medians) plus ONE offset shared by all frames: per-frame free translations let a body slide along
    itself (a standing body's markers fit it 20 cm too low as well), a shared offset cannot.
    points: (H, S, N, 3) model points relative to the rotation centre; markers: (S, M, 3);
    visible: (S, M) bool; yaw_start: (H,) radians.
    Returns (yaw (H,), offset (H, S, 3), mean squared distance (H,), tilt (H,3,3), nearest
    point index (H, S, M) of the last iteration) with world = R(yaw) tilt p + offset.
    """
    hyp, frames, _, _ = points.shape
    w = visible.to(points.dtype)  # (S, M)
    wall = w.sum().clamp(min=1.0)
    m_ref = torch.as_tensor(marker_centroid(markers.double().numpy(), visible.numpy().astype(bool)), dtype=points.dtype)
    mt = torch.nan_to_num(markers) - m_ref[:, None]  # (S,M,3) marker coordinates about the frame's reference
    p_ref = points.mean(dim=2)  # (H,S,3)
    pt = points - p_ref[:, :, None]
    yaw = yaw_start.clone()
    tilt = torch.eye(3, dtype=points.dtype).expand(hyp, 3, 3).clone()
    shift = torch.zeros(hyp, 3, dtype=points.dtype)
    err = torch.zeros(hyp)
    for _ in range(iterations + 1):
        rot = _batch_yaw(yaw, up) @ tilt
        posed = torch.einsum("hij,hsnj->hsni", rot, pt) + shift[:, None, None]
        idx = nearest_indices(mt[None].expand(hyp, -1, -1, -1).reshape(hyp * frames, -1, 3), posed.reshape(hyp * frames, -1, 3))
        q = gather_points(pt.reshape(hyp * frames, -1, 3), idx).reshape(hyp, frames, -1, 3)
        resid = torch.einsum("hij,hsmj->hsmi", rot, q) + shift[:, None, None] - mt[None]
        err = ((resid**2).sum(-1) * w[None]).sum((1, 2)) / wall
        # closed-form update over all frames: centre, 1-D Procrustes about up, shared offset
        q_c = (q * w[None, ..., None]).sum((1, 2)) / wall  # (H,3)
        m_c = (mt * w[..., None]).sum((0, 1)) / wall  # (3,)
        qt = q - q_c[:, None, None]
        mc = mt - m_c
        if max_tilt_rad > 0:
            yaw, tilt = _kabsch_yaw_tilt(qt, mc, w, up, max_tilt_rad)
        else:
            q_perp = qt - (qt @ up)[..., None] * up
            cross = torch.linalg.cross(up.expand_as(qt), qt, dim=-1)
            a = ((mc[None] * q_perp).sum(-1) * w[None]).sum((1, 2))
            b = ((mc[None] * cross).sum(-1) * w[None]).sum((1, 2))
            yaw = torch.atan2(b, a)
        rot = _batch_yaw(yaw, up) @ tilt
        shift = m_c[None] - torch.einsum("hij,hj->hi", rot, q_c)
    # world = R (p - p_ref) + m_ref + shift = R p + (m_ref + shift - R p_ref)
    offset = m_ref[None] + shift[:, None] - torch.einsum("hij,hsj->hsi", rot, p_ref)
    return yaw, offset, err, tilt, idx.reshape(hyp, frames, -1)


def floor_energy(points: torch.Tensor, yaw: torch.Tensor, tilt: torch.Tensor, offset: torch.Tensor, up: torch.Tensor,
                 config: PartMatchingConfig) -> torch.Tensor:
    """Floor term of each hypothesis: how far the whole body's lowest point sits from the floor.

    points (S,N,3) whole-body vertices about the rotation centre; yaw (H,); tilt (H,3,3);
    offset (H,S,3) with world = R(yaw) tilt p + offset.  The lowest point of each frame is taken
    at its 20th percentile over frames (a jump lifts both feet for a while).  Returns (H,).
    """
    rot = _batch_yaw(yaw, up.to(yaw.dtype)) @ tilt
    up_body = torch.einsum("i,hij->hj", up.to(rot.dtype), rot)  # up expressed in the body frame
    low = torch.einsum("snj,hj->hsn", points.to(rot.dtype), up_body).amin(-1) + offset.to(rot.dtype) @ up.to(rot.dtype)
    ground = torch.quantile(low, 0.2, dim=1)
    miss = ((ground - config.floor_height_m).abs() - config.floor_dead_zone_m).clamp(min=0.0)
    return config.floor_weight * (miss / 0.1) ** 2


def _kabsch_yaw_tilt(q: torch.Tensor, m: torch.Tensor, w: torch.Tensor, up: torch.Tensor, max_tilt: float):
    """Best rotation (Kabsch) taking centred model points q (H,S,M,3) to centred markers m (S,M,3),
    split as R = R_up(yaw) T with T about a horizontal axis, T's angle clamped to ``max_tilt``.
    Returns (yaw (H,), T (H,3,3))."""
    from uuomocap.solver_core.rotations import axis_angle_to_matrix, matrix_to_axis_angle

    cov = torch.einsum("hsmi,smj,sm->hij", q, m, w)  # sum q m^T
    u, _, vh = torch.linalg.svd(cov)
    d = torch.sign(torch.det(vh.transpose(1, 2) @ u.transpose(1, 2)))
    fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    rot = vh.transpose(1, 2) @ fix @ u.transpose(1, 2)  # (H,3,3): m ~ R q
    # T0: the smallest rotation taking up to R up (horizontal axis); Z = T0^T R turns about up;
    # R = T0 Z = Z (Z^T T0 Z) and Z^T T0 Z = Z^T R is again about a horizontal axis.
    a = rot @ up
    axis = torch.linalg.cross(up.expand_as(a), a, dim=-1)
    sin = axis.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sin[:, 0], (a * up).sum(-1))
    t0 = axis_angle_to_matrix(axis / sin.clamp(min=1e-12) * angle[:, None])
    z = t0.transpose(1, 2) @ rot
    yaw = (matrix_to_axis_angle(z) @ up)
    tilt = _batch_yaw(yaw, up).transpose(1, 2) @ rot
    vec = matrix_to_axis_angle(tilt)
    norm = vec.norm(dim=-1, keepdim=True)
    vec = vec * (norm.clamp(max=max_tilt) / norm.clamp(min=1e-12))
    return yaw, axis_angle_to_matrix(vec)


def _batch_yaw(yaw: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    from uuomocap.solver_core.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(yaw[:, None] * up[None].to(yaw.dtype))


def marker_centroid(markers: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(T,3) per-frame reference point of the markers for the translation initialisation.

    The paper uses the per-frame marker median; a median (or mean) jumps whenever a marker
    disappears or the middle marker changes.  Here: the markers' overall centroid plus the mean
    displacement of the VISIBLE markers from their own time averages, which moves only with the
    markers.  Frames without a visible marker are interpolated.
    """
    vis = visible & np.isfinite(markers).all(axis=2)
    filled = np.where(vis[..., None], markers, 0.0)
    count = vis.sum(axis=0)
    seen = count > 0
    own_mean = filled.sum(axis=0) / np.maximum(count, 1)[:, None]  # (M,3)
    centre = own_mean[seen].mean(axis=0)
    disp = np.where(vis[..., None], markers - own_mean[None], 0.0).sum(axis=1)
    n = vis.sum(axis=1)
    out = fill_nan_rows(np.where(n[:, None] > 0, centre + disp / np.maximum(n, 1)[:, None], np.nan))
    # An unlabelled export that starts a new column each time a marker comes back (every column one
    # seen stretch) breaks this: each column's own mean sits where IT was seen, and the
    # displacements from those means lose the walk (session 45: 1.9 m off on an 8 s walk, and the
    # solve failed).  The least-squares centroid with an offset per column is right either way;
    # it replaces this one only when the two part by more than FRAGMENTED_CENTROID_GAP_M, so takes
    # whose markers are seen throughout (gaps or not) keep the estimate they were tuned on.
    ls = _fragmented_centroid(markers, vis)
    if np.abs(ls - out).max() > FRAGMENTED_CENTROID_GAP_M:
        return ls
    return out


# ``marker_centroid``: fragmented columns part the two estimates by metres on a walk (1.9 m, 0.56 m
# on a 3 s one), gaps in whole columns by centimetres (5 cm at most on the 8 s walk with 1 % occlusion).
FRAGMENTED_CENTROID_GAP_M = 0.15


def _chained_centroid(markers: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(T,3) the per-frame displacement of the markers seen in both of two consecutive non-empty
    frames, summed along the take, placed so that its mean over the frames is the mean of the
    per-frame marker means.  Two frames with no marker in common step by their means' difference."""
    T = markers.shape[0]
    rows = np.flatnonzero(vis.any(1))
    filled = np.where(vis[..., None], markers, 0.0)
    frame_mean = filled[rows].sum(1) / vis[rows].sum(1)[:, None]  # (K,3)
    a, b = rows[:-1], rows[1:]
    common = vis[a] & vis[b]
    n_common = common.sum(1)
    step = np.where(common[..., None], filled[b] - filled[a], 0.0).sum(1) / np.maximum(n_common, 1)[:, None]
    step = np.where(n_common[:, None] > 0, step, frame_mean[1:] - frame_mean[:-1])
    path = np.concatenate([np.zeros((1, 3)), np.cumsum(step, axis=0)])
    out = np.full((T, 3), np.nan)
    out[rows] = path + (frame_mean - path).mean(0)
    return fill_nan_rows(out)


def _fragmented_centroid(markers: np.ndarray, vis: np.ndarray, iterations: int = 30) -> np.ndarray:
    """(T,3) a centroid c(t) and per-column offsets o_m with x_m(t) ~ c(t) + o_m on every seen
    sample, by alternating least squares started from ``_chained_centroid`` (the chain alone drifts
    as the set of seen markers changes: 5 cm on an 8 s walk with 1 % occlusion)."""
    rows = np.flatnonzero(vis.any(1))
    x = np.where(vis[..., None], markers, 0.0)[rows]
    v = vis[rows][..., None].astype(np.float64)
    c = _chained_centroid(markers, vis)[rows]
    n_t, n_m = v.sum(1), v.sum(0)
    for _ in range(iterations):
        o = ((x - c[:, None]) * v).sum(0) / np.maximum(n_m, 1)  # (M,3)
        o -= (o * n_m).sum(0) / max(n_m.sum(), 1)  # the offsets average to zero: c stays the markers' centre
        c = ((x - o[None]) * v).sum(1) / np.maximum(n_t, 1)
    out = np.full((vis.shape[0], 3), np.nan)
    out[rows] = c
    return fill_nan_rows(out)


# ----------------------------------------------------------------------------- the matching


def match_markers_to_part(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    prior_root: torch.Tensor,
    prior_body_pose: torch.Tensor,
    shape_prior: torch.Tensor,
    cluster_labels: np.ndarray,
    up: torch.Tensor,
    config: PartMatchingConfig = PartMatchingConfig(),
    force_full_body: bool | None = None,
) -> PartMatch:
    """Find the body part the markers sit on, its yaw hypotheses and a per-frame translation.

    markers (T,M,3) metres (NaN where missing); visible (T,M) bool; prior_root (T,3) world
    root orientation before yaw; prior_body_pose (T,23,3); shape_prior (B,); cluster_labels (M,)
    from segmentation; up (3,).  force_full_body overrides the volume test when not None.
    """
    frames_total = markers.shape[0]
    vis_np = visible.numpy().astype(bool)
    has_data = np.flatnonzero(vis_np.sum(1) >= 1)
    if len(has_data) == 0:
        raise ValueError("no frame has a visible marker")
    sel = has_data[np.unique(np.linspace(0, len(has_data) - 1, min(config.frames, len(has_data))).round().astype(int))]
    sel_t = torch.as_tensor(sel)
    mk = markers[sel_t]
    vis = visible[sel_t]
    zero = torch.zeros(())
    with torch.no_grad():
        rest = pose_body(model, prior_root[sel_t], prior_body_pose[sel_t], torch.zeros(len(sel), 3), shape_prior, zero, up)
    # rotation centre of the yaw: the pelvis joint (SMPL rotates the root about it)
    centre = rest.joints[:, :1]  # (S,1,3)
    pts_all = rest.vertices - centre  # (S,N,3)

    up_np = up.double().numpy()
    ratio = marker_to_body_volume_ratio(mk.double().numpy(), vis.numpy(), rest.vertices.double().numpy(), up_np)
    full_body = ratio > config.full_body_volume_ratio if force_full_body is None else bool(force_full_body)
    if config.part_joints is not None:
        full_body = False
    k = int(len(np.unique(cluster_labels)))
    dominant = vertex_dominant_joint(model)
    dominant = torch.as_tensor(dominant, dtype=torch.long)
    n_joints = int(model.parents.shape[0])
    if full_body:
        candidates = [tuple(range(n_joints))]
    elif config.part_joints is not None:
        if not config.part_joints or not all(0 <= j < n_joints for j in config.part_joints):
            raise ValueError(f"part_joints must be joint indices of the model (0..{n_joints - 1}), got {config.part_joints}")
        candidates = [tuple(int(j) for j in config.part_joints)]
    else:
        size = max(1, min(max(k, config.min_part_joints), config.max_part_joints, n_joints))
        candidates = candidate_part_joints(model.parents, size, config.prune_overlap, config.max_candidates)

    unit2 = config.distance_unit_m**2
    yaw_starts = torch.tensor([math.radians(d) for d in config.yaw_starts_deg], dtype=torch.float32)
    use_turns = not full_body and config.turn_weight > 0
    if use_turns:
        pairs = frame_pairs(len(sel))
        cluster_turns, turn_valid = cluster_relative_rotations(mk.double().numpy(), vis.numpy().astype(bool), cluster_labels, pairs)
        bone_turns = bone_relative_rotations(rest.joint_rotations.double(), pairs)
        use_turns = bool(turn_valid.any())
    labels_t = torch.as_tensor(cluster_labels, dtype=torch.long)
    vis_f = vis.double()
    # (best energy, joints, yaw (H,), offset (H,S,3), energy (H,), tilt (H,3,3), turn mismatch (H,),
    #  unrefined terms (H,))
    scored: list[tuple] = []
    for cand in candidates:
        vid = torch.nonzero(torch.isin(dominant, torch.tensor(cand))).reshape(-1)
        if vid.numel() == 0:
            continue
        pts = pts_all[:, vid]
        yaw, offset, err, tilt, nearest = rigid_yaw_icp(
            pts[None].expand(len(yaw_starts), -1, -1, -1), mk, vis, up, yaw_starts, config.icp_iterations,
            math.radians(config.max_tilt_deg),
        )
        energy = config.chamfer_weight * err / unit2
        turns = torch.zeros(len(yaw_starts), dtype=torch.float64)
        extra = torch.zeros(len(yaw_starts))  # terms the L-BFGS refinement does not optimise
        if use_turns:
            # each marker is judged on the bone under its nearest vertex, by its cluster's turns
            frame_rot = (_batch_yaw(yaw, up) @ tilt).double()
            mism = turn_mismatch(cluster_turns, turn_valid, bone_turns, frame_rot)  # (H,K,J)
            bone = dominant[vid][nearest]  # (H,S,M)
            per_marker = torch.stack([mism[h][labels_t[None].expand_as(bone[h]), bone[h]] for h in range(len(yaw))])
            turns = (per_marker * vis_f[None]).sum((1, 2)) / vis_f.sum().clamp(min=1.0)
            extra = extra + config.turn_weight * turns.float()
        if not full_body and config.floor_height_m is not None:
            extra = extra + floor_energy(pts_all, yaw, tilt, offset, up, config).float()
        energy = energy + extra
        scored.append((float(energy.min()), cand, yaw, offset, energy, tilt, turns, extra))
    if not scored:
        raise ValueError("no part candidate has vertices")
    scored.sort(key=lambda s: s[0])

    # refine the best few with the paper's energy over (yaw, translation, shape)
    refined: list[tuple[float, tuple[int, ...], float, torch.Tensor, torch.Tensor]] = []
    top = max(1, config.refine_top, 0 if full_body else config.partial_alternatives)
    for energy0, cand, yaw, offset, energies, tilt, turns, extra in scored[:top]:
        best_h = int(torch.argmin(energies))
        vid = torch.nonzero(torch.isin(dominant, torch.tensor(cand))).reshape(-1)
        e, y, tr, b = _refine_candidate(
            model, mk, vis, prior_root[sel_t], prior_body_pose[sel_t], shape_prior, up, vid,
            float(yaw[best_h]), offset[best_h] - centre[:, 0], config, tilt[best_h],
        )
        # the turn and floor terms are not refined (they barely move with it): carried over
        e += float(extra[best_h])
        refined.append((e, cand, y, tr, b))
    refined.sort(key=lambda r: r[0])
    ranking = [(r[1], r[0]) for r in refined] + [(s[1], s[0]) for s in scored[len(refined):]]

    def as_match(entry) -> PartMatch:
        energy, cand, cand_yaw, _, cand_betas = entry
        sc = next(s for s in scored if s[1] == cand)
        vid = torch.nonzero(torch.isin(dominant, torch.tensor(cand))).reshape(-1)
        # yaw hypotheses of the candidate: each start's ICP optimum (the refined one replaces its own)
        starts = [YawStart(start, float(sc[2][h]), float(sc[4][h]), sc[5][h].double().numpy())
                  for h, start in enumerate(config.yaw_starts_deg)]
        best_h = int(torch.argmin(sc[4]))
        best_tilt = sc[5][best_h]
        starts[best_h] = YawStart(starts[best_h].start_deg, cand_yaw, energy, best_tilt.double().numpy())
        trans = full_translation(model, markers, visible, apply_root_offset(prior_root, best_tilt), prior_body_pose,
                                 cand_betas, up, vid, torch.tensor(cand_yaw))
        return PartMatch(
            joints=tuple(cand), vertex_ids=vid.numpy(), yaw=cand_yaw, trans=trans.numpy(), betas=cand_betas.numpy(),
            error=energy, full_body=bool(full_body), volume_ratio=ratio, cluster_count=k,
            candidates_tested=len(scored), yaw_starts=starts, ranking=ranking, tilt=best_tilt.double().numpy(),
            turn_mismatch=float(sc[6][best_h]),
        )

    chosen = as_match(refined[0])
    if not full_body:
        chosen.alternatives = [as_match(r) for r in refined[1:config.partial_alternatives]]
    return chosen


def _refine_candidate(model, mk, vis, root, body_pose, shape_prior, up, vid, yaw0, trans0, config, tilt):
    """L-BFGS over (yaw, per-frame translation, shape) with the paper's E_S; pose fixed to the prior.

    trans0 (S,3): the ICP result as SMPL translation.  ICP places the body as R (x0 - c) + offset
    with c the pelvis; SMPL rotates the root about the pelvis, R (x0 - c) + c + trans, so
    trans = offset - c.  Returns (energy, yaw, trans (S,3), betas (B,)).
    """
    unit = config.distance_unit_m
    yaw = torch.tensor(float(yaw0), requires_grad=True)
    trans = trans0.detach().clone().requires_grad_(True)
    betas = shape_prior.detach().clone().float().requires_grad_(True)
    mk_u = mk / unit
    cache = NearestTargetCache()

    def loss() -> torch.Tensor:
        cham, _ = chamfer_to_body(model, mk_u, vis, root, body_pose, trans, betas, yaw, up, vid, unit, None, tilt, cache)
        shape = ((betas - shape_prior) ** 2).mean()
        return config.chamfer_weight * cham + config.shape_weight * shape

    run_lbfgs([yaw, trans, betas], loss, config.lbfgs)
    with torch.no_grad():
        energy = float(loss())
    return energy, wrap(float(yaw.detach())), trans.detach(), betas.detach()


def wrap(angle: float) -> float:
    return float(angle % (2 * math.pi))


@torch.no_grad()
@torch.no_grad()
def full_translation(
    model, markers, visible, prior_root, prior_body_pose, betas, up, vertex_ids, yaw, iterations: int = 8
) -> torch.Tensor:
    """(T,3) translation for every frame at a fixed yaw: the markers' reference point minus the
    candidate vertices' centroid (the paper aligns medians) plus one offset shared by all frames, found by
    closed-form ICP (see ``rigid_yaw_icp`` for why it is shared)."""
    frames = markers.shape[0]
    out = pose_body(model, prior_root, prior_body_pose, torch.zeros(frames, 3), betas, yaw, up)
    pts = out.vertices[:, torch.as_tensor(vertex_ids)]
    vis_np = visible.numpy().astype(bool)
    ref = torch.as_tensor(marker_centroid(markers.double().numpy(), vis_np), dtype=torch.float32)
    base = ref - pts.mean(dim=1)
    mk = torch.nan_to_num(markers)
    w = visible.float()
    wall = w.sum().clamp(min=1.0)
    shift = torch.zeros(3)
    for _ in range(iterations):
        trans = base + shift
        idx = nearest_indices(mk, pts + trans[:, None])
        q = gather_points(pts, idx)
        shift = shift + ((mk - q - trans[:, None]) * w[..., None]).sum((0, 1)) / wall
    return base + shift
