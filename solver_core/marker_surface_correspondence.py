"""Stage 3: marker-surface correspondence (paper Sec. "Mocap Solving", Stage 3).

The paper picks, for every marker, the VERTEX with the smallest mean distance to the marker over
the sequence.  Beyond the paper (method "surface", the default) the answer is a continuous
surface point (face + barycentric) found robustly:
  1. the paper's score (mean distance over the frames where the marker is visible) shortlists
     the few best vertices; their incident faces form the marker's local surface patch;
  2. in every frame, the closest point of the posed patch to the marker is found and pulled back
     to the rest-pose surface (face + barycentric coordinates are pose-invariant);
  3. the geometric median of those rest-pose points (robust to frames with a bad pose or a
     mistracked marker) is projected onto the rest-pose patch -> face + barycentric.
Frames where the marker is occluded never vote.  An optional ``allowed_vertex_ids`` restricts
the search (e.g. to the matched part for a partial body).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core import lbs
from uuomocap.solver_core.body_params import BodyParams, pose_params
from uuomocap.solver_core.chamfer import mean_distance_to_targets, vertex_face_table
from uuomocap.solver_core.body_params import MarkerAttachment
from uuomocap.solver_core.inverse_kinematics import triangle_frames
from uuomocap.solver_core.mesh import closest_point_on_triangles, vertex_normals
from uuomocap.solver_core.parts import vertex_dominant_joint


@dataclass(frozen=True)
class CorrespondenceConfig:
    # "surface" (beyond the paper: robust continuous face+barycentric point) or "vertex" (paper Stage 3).
    method: str = "surface"
    # Beyond the paper: vertices shortlisted per marker by the paper's mean-distance score.
    shortlist_vertices: int = 6
    # Beyond the paper (speed): at most this many evenly spaced frames vote.
    frames: int = 200
    # Beyond the paper: when refining (Stage 5) a partial body, a marker may move at most this far
    # over the rest surface.  The paper's Stage 5 searches the whole body again, which lets a marker
    # jump to a limb that happens to follow it (e.g. the other forearm when the hands are held
    # together); on a 12-marker part that cost the near-online jump's left leg 16.19 -> 19.36 mm
    # part MPJPE (session 31).  None = the whole allowed surface.
    refine_radius_m: float | None = 0.05
    # The same for a full body: the paper's whole-body search (None).  Session 31 (the bench's 36
    # full-body sessions, walk / jump / arms x seeds 0-2, offline MPJPE at 20 / 30 / 40 / 50 markers):
    # 0.05 m 24.76 / 11.70 / 9.80 / 8.33 mm, None 24.81 / 11.50 / 9.65 / 8.24 (16 better, 6 worse).
    full_body_refine_radius_m: float | None = None
    # Beyond the paper: Weiszfeld iterations of the geometric median.
    median_iterations: int = 20
    # Paper Sec. Stage 4: delta = 9.5 mm.  Beyond the paper, Stage 3 scores points by the same
    # residual IK will minimise (|d - delta| for the shortlist, the patch offset along its face
    # normals for the point): with plain distances a marker between two limbs (hands together in
    # the benchmark's jump) takes the nearer skin of the wrong forearm, 7 mm away instead of 9.5.
    marker_offset_m: float = 0.0095
    # Beyond the paper: the offset surface follows the skin's smooth normals (each patch corner
    # moved along its vertex normal) as IK's "smooth_normal" model does; False = facet normals.
    smooth_normals: bool = True


def squared_distance_to_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest point of triangles (a,b,c) to points p, all (...,3) broadcastable.

    Returns (squared distance (...), barycentric (...,3)).
    """
    p, a, b, c = torch.broadcast_tensors(p, a, b, c)
    bary = closest_point_on_triangles(p, a, b, c)
    q = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
    return ((p - q) ** 2).sum(-1), bary


def _geometric_median(points: torch.Tensor, weights: torch.Tensor, iterations: int) -> torch.Tensor:
    """Weighted geometric median per row.  points (M,S,3), weights (M,S) -> (M,3) (Weiszfeld)."""
    w = weights.clamp(min=0)
    est = (points * w[..., None]).sum(1) / w.sum(1, keepdim=True).clamp(min=1e-9)
    for _ in range(iterations):
        dist = (points - est[:, None]).norm(dim=-1).clamp(min=1e-6)
        ww = w / dist
        est = (points * ww[..., None]).sum(1) / ww.sum(1, keepdim=True).clamp(min=1e-12)
    return est


def _restrict_near_previous(model, betas, allowed, previous: MarkerAttachment, mean_dist, radius_m: float):
    """Set the score of vertices farther than ``radius_m`` (rest pose) from each previously
    assigned marker's point to +inf (the nearest vertex always stays)."""
    rest = lbs.forward(model, betas.reshape(1, -1), torch.zeros(1, 24, 3)).vertices[0]
    ok = previous.assigned
    if not bool(ok.any()):
        return mean_dist
    corners = rest[model.faces[previous.face_ids[ok]]]
    prev_pts = (corners * previous.bary[ok][..., None]).sum(1)  # (Mo,3)
    dist = torch.cdist(prev_pts, rest[allowed])  # (Mo,Na)
    far = dist > radius_m
    far[torch.arange(far.shape[0]), dist.argmin(dim=1)] = False
    out = mean_dist.clone()
    sub = out[ok]
    sub[far] = float("inf")
    out[ok] = sub
    return out


def _evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
    if len(indices) <= count:
        return indices
    return indices[np.unique(np.linspace(0, len(indices) - 1, count).round().astype(int))]


@torch.no_grad()
def find_marker_surface_points(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    params: BodyParams,
    up: torch.Tensor,
    allowed_vertex_ids: torch.Tensor | None = None,
    config: CorrespondenceConfig = CorrespondenceConfig(),
    vertex_faces: torch.Tensor | None = None,
    previous: MarkerAttachment | None = None,
) -> MarkerAttachment:
    """Stage 3 for a window: every marker's surface point under the body ``params``.

    markers (T,M,3) metres NaN where missing; visible (T,M) bool; params: the fitted body for the
    same T frames; allowed_vertex_ids: restrict to these vertices (None = all); previous: an earlier
    attachment to refine locally (Stage 5) - each marker then only searches the rest-pose surface
    within ``config.refine_radius_m`` of its previous point (``full_body_refine_radius_m`` when
    ``allowed_vertex_ids`` is None: a full body).
    Markers never visible get face -1.  Returns MarkerAttachment.
    """
    if config.method not in ("surface", "vertex"):
        raise ValueError(f"correspondence method must be 'surface' or 'vertex', got {config.method!r}")
    vis_np = visible.numpy().astype(bool)
    frames = _evenly_spaced(np.flatnonzero(vis_np.any(axis=1)), config.frames)
    m_count = markers.shape[1]
    face_ids = torch.full((m_count,), -1, dtype=torch.long)
    bary = torch.zeros(m_count, 3)
    score = torch.full((m_count,), float("inf"))
    if len(frames) == 0:
        return MarkerAttachment(face_ids, bary, score)
    sel = torch.as_tensor(frames)
    n_vertices = model.v_template.shape[0]
    allowed = torch.arange(n_vertices) if allowed_vertex_ids is None else torch.as_tensor(allowed_vertex_ids, dtype=torch.long)
    sub = params.frames(sel)
    posed = pose_params(model, sub, up, lbs.SurfacePoints.from_vertex_ids(allowed)).vertices  # (S,Na,3)
    mk = markers[sel]
    vis = visible[sel]
    mean_dist = mean_distance_to_targets(mk, vis, posed, offset_m=config.marker_offset_m)  # (M,Na)
    radius = config.refine_radius_m if allowed_vertex_ids is not None else config.full_body_refine_radius_m
    if previous is not None and radius is not None:
        mean_dist = _restrict_near_previous(model, params.betas, allowed, previous, mean_dist, radius)
    seen = vis.any(dim=0)
    k = min(config.shortlist_vertices, allowed.numel())
    best_local = torch.topk(mean_dist, k, dim=1, largest=False).indices  # (M,k)
    best_vertices = allowed[best_local]
    if vertex_faces is None:
        vertex_faces = vertex_face_table(model.faces, n_vertices)
    faces = model.faces

    if config.method == "vertex":
        for m in range(m_count):
            if not bool(seen[m]):
                continue
            v = int(best_vertices[m, 0])
            f = int(vertex_faces[v, 0])
            face_ids[m] = f
            corner = faces[f].tolist().index(v)
            bary[m] = 0.0
            bary[m, corner] = 1.0
            score[m] = mean_dist[m, best_local[m, 0]]
        return MarkerAttachment(face_ids, bary, score)

    # local patch of faces per marker (padded by repetition to a common size)
    allowed_set = None if allowed_vertex_ids is None else set(allowed.tolist())
    patches = []
    for m in range(m_count):
        fs: list[int] = []
        finite = torch.isfinite(mean_dist[m, best_local[m]])
        finite[0] = True
        for v in best_vertices[m][finite].tolist():
            for f in vertex_faces[v].tolist():
                if allowed_set is not None and not all(int(x) in allowed_set for x in faces[f].tolist()):
                    continue
                if f not in fs:
                    fs.append(f)
        if not fs:
            fs = [int(vertex_faces[int(best_vertices[m, 0]), 0])]
        patches.append(fs)
    width = max(len(p) for p in patches)
    patch = torch.tensor([p + [p[0]] * (width - len(p)) for p in patches], dtype=torch.long)  # (M,Fp)
    corner_ids = faces[patch]  # (M,Fp,3)
    uniq, inverse = torch.unique(corner_ids.reshape(-1), return_inverse=True)
    corner_pos = pose_params(model, sub, up, lbs.SurfacePoints.from_vertex_ids(uniq)).vertices  # (S,U,3)
    tri = corner_pos[:, inverse.reshape(-1)].reshape(len(frames), m_count, width, 3, 3)
    rest_params = BodyParams(
        torch.zeros(1, 3), torch.zeros(1, 23, 3), torch.zeros(1, 3), params.betas, torch.zeros(())
    )
    rest_corner = pose_params(model, rest_params, up, lbs.SurfacePoints.from_vertex_ids(uniq)).vertices[0]  # (U,3)
    rest_tri = rest_corner[inverse.reshape(-1)].reshape(m_count, width, 3, 3)
    # the skin offset by delta: where IK will put the marker
    if config.smooth_normals:
        # each corner moves along its smooth (vertex) normal, carried from the rest pose in the
        # posed face's frame - the offset surface of IK's "smooth_normal" model
        rest_all = lbs.forward(model, params.betas.reshape(1, -1).float(), torch.zeros(1, 24, 3)).vertices[0]
        corner_normals = vertex_normals(rest_all, faces)[corner_ids]  # (M,Fp,3 corners,3)
        local = corner_normals @ triangle_frames(rest_all[corner_ids]).transpose(-1, -2)  # (M,Fp,3,3) in the face frame
        shift = config.marker_offset_m * (local @ triangle_frames(tri))  # (S,M,Fp,3,3)
        off = tri + shift
    else:
        normal = torch.linalg.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
        shift = config.marker_offset_m * normal / normal.norm(dim=-1, keepdim=True).clamp(min=1e-12)  # (S,M,Fp,3)
        off = tri + shift[..., None, :]
    p = torch.nan_to_num(mk)[:, :, None, :]
    d2, bc = squared_distance_to_triangles(p, off[..., 0, :], off[..., 1, :], off[..., 2, :])  # (S,M,Fp)
    best_face = d2.argmin(dim=2)  # (S,M)
    best_bary = torch.gather(bc, 2, best_face[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]  # (S,M,3)

    # pull every frame's closest point back to the rest-pose (shaped) surface
    chosen = torch.gather(rest_tri[None].expand(len(frames), -1, -1, -1, -1), 2, best_face[..., None, None, None].expand(-1, -1, 1, 3, 3))[:, :, 0]
    rest_points = (chosen * best_bary[..., None]).sum(dim=2)  # (S,M,3)
    centre = _geometric_median(rest_points.transpose(0, 1), vis.t().float(), config.median_iterations)  # (M,3)
    d2r, bcr = squared_distance_to_triangles(centre[:, None], rest_tri[..., 0, :], rest_tri[..., 1, :], rest_tri[..., 2, :])
    pick = d2r.argmin(dim=1)
    face_ids = torch.where(seen, patch[torch.arange(m_count), pick], torch.full_like(face_ids, -1))
    bary = bcr[torch.arange(m_count), pick]
    # diagnostic: the mean posed distance marker -> chosen point (+ offset) over the voting frames
    posed_pts = (off[:, torch.arange(m_count), pick] * bary[None, :, :, None]).sum(2)  # (S,M,3)
    dist = (posed_pts - torch.nan_to_num(mk)).norm(dim=-1)
    w = vis.float()
    score = torch.where(seen, (dist * w).sum(0) / w.sum(0).clamp(min=1), torch.full_like(score, float("inf")))
    return MarkerAttachment(face_ids, bary, score)


def place_on_joints(model, markers: torch.Tensor, visible: torch.Tensor, params: BodyParams, up: torch.Tensor,
                    members, joints, allowed_vertex_ids, config: CorrespondenceConfig, vertex_faces,
                    face_ids: torch.Tensor, bary: torch.Tensor, score: torch.Tensor, max_score_m: float | None = None) -> list[int]:
    """Stage 3 for the markers ``members`` on the vertices whose dominant joint is in ``joints``
    (and in ``allowed_vertex_ids`` when given).  markers (T,M,3), visible (T,M), params for those
    frames.  Writes the new points into face_ids / bary / score (M,...) in place and returns the
    markers placed; max_score_m: a marker whose new point is farther than this from it (mean over
    its frames, metres) keeps its old one (None: no limit)."""
    verts = torch.nonzero(torch.isin(vertex_dominant_joint(model), torch.tensor(list(joints)))).reshape(-1)
    if allowed_vertex_ids is not None:
        verts = verts[torch.isin(verts, torch.as_tensor(allowed_vertex_ids))]
    if verts.numel() == 0:
        return []
    idx = torch.as_tensor(list(members), dtype=torch.long)
    sub = find_marker_surface_points(model, markers[:, idx], visible[:, idx], params, up, verts, config, vertex_faces)
    ok = sub.face_ids >= 0
    if max_score_m is not None:
        ok &= sub.score_m <= max_score_m
    face_ids[idx[ok]] = sub.face_ids[ok]
    bary[idx[ok]] = sub.bary[ok]
    score[idx[ok]] = sub.score_m[ok]
    return [int(m) for m in idx[ok]]
