"""Accuracy metrics of the paper (Sec. "Evaluation Protocols"), in millimetres and mm/s.

- MPJPE: mean per-joint position error over SMPL joints 0-21 (hands excluded, as is common),
  world frame, no alignment.
- PA-MPJPE: the same after a per-frame similarity Procrustes alignment (Umeyama 1991).
- MPJVE: mean over joints and frames of |v_pred - v_gt|, velocities by finite differences
  of adjacent frames at the sequence rate (mm/s).
- V2V: mean vertex-to-vertex distance between predicted and reference meshes.
- m2s: mean distance from each observed marker to the predicted mesh SURFACE (closest
  point on the triangles, not the closest vertex).  Real markers sit ~9.5 mm off the skin
  (Sec. "Mocap Solving", delta = 9.5 mm), so the ground truth itself scores ~9.5.
- Partial layouts: MPJPE / MPJVE on the part's joints, and whether the markers were put on
  the right part (vs. e.g. the mirrored limb).

All functions take numpy arrays; ``evaluate`` runs everything for one prediction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EVAL_JOINTS = tuple(range(22))  # SMPL joints 0-21: body without the two hand end joints
MARKER_OFFSET_M = 0.0095         # paper Sec. "Mocap Solving": delta = 9.5 mm


def _check_same(pred: np.ndarray, gt: np.ndarray, what: str) -> None:
    if pred.shape != gt.shape:
        raise ValueError(f"{what}: prediction has shape {pred.shape}, ground truth {gt.shape}")


def joint_errors(pred_joints: np.ndarray, gt_joints: np.ndarray, joints=EVAL_JOINTS) -> np.ndarray:
    """(F, J, 3) metres each -> (F, len(joints)) Euclidean errors in mm."""
    _check_same(pred_joints, gt_joints, "joints")
    j = list(joints)
    return 1000.0 * np.linalg.norm(pred_joints[:, j] - gt_joints[:, j], axis=-1)


def mpjpe(pred_joints: np.ndarray, gt_joints: np.ndarray, joints=EVAL_JOINTS) -> float:
    """Mean per-joint position error (mm), world frame, no alignment."""
    return float(joint_errors(pred_joints, gt_joints, joints).mean())


def similarity_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame similarity Procrustes: scale s, rotation R, translation t minimising
    |s R pred + t - gt|^2 (Umeyama 1991, reflection excluded).  (F, P, 3) -> aligned (F, P, 3)."""
    _check_same(pred, gt, "points")
    mp = pred.mean(1, keepdims=True)
    mg = gt.mean(1, keepdims=True)
    x, y = pred - mp, gt - mg
    cov = np.einsum("fpi,fpj->fij", y, x) / pred.shape[1]        # (F, 3, 3) = E[y x^T]
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((pred.shape[0], 3))
    D[:, 2] = d
    R = U @ (D[..., None] * Vt)
    var_x = (x ** 2).sum((1, 2)) / pred.shape[1]
    s = (S * D).sum(1) / np.maximum(var_x, 1e-12)
    return s[:, None, None] * np.einsum("fij,fpj->fpi", R, x) + mg


def pa_mpjpe(pred_joints: np.ndarray, gt_joints: np.ndarray, joints=EVAL_JOINTS) -> float:
    """MPJPE (mm) after per-frame similarity alignment of the evaluated joints."""
    j = list(joints)
    aligned = similarity_align(pred_joints[:, j], gt_joints[:, j])
    return float(1000.0 * np.linalg.norm(aligned - gt_joints[:, j], axis=-1).mean())


def mpjve(pred_joints: np.ndarray, gt_joints: np.ndarray, rate_hz: float, joints=EVAL_JOINTS) -> float:
    """Mean per-joint velocity error (mm/s): finite differences of adjacent frames at ``rate_hz``."""
    _check_same(pred_joints, gt_joints, "joints")
    if pred_joints.shape[0] < 2:
        return float("nan")
    j = list(joints)
    vp = np.diff(pred_joints[:, j], axis=0) * rate_hz
    vg = np.diff(gt_joints[:, j], axis=0) * rate_hz
    return float(1000.0 * np.linalg.norm(vp - vg, axis=-1).mean())


def v2v(pred_vertices: np.ndarray, gt_vertices: np.ndarray) -> float:
    """Mean vertex-to-vertex distance (mm) between meshes of the same topology."""
    _check_same(pred_vertices, gt_vertices, "vertices")
    return float(1000.0 * np.linalg.norm(pred_vertices - gt_vertices, axis=-1).mean())


def closest_surface_distance(points: "torch.Tensor", vertices: "torch.Tensor", faces: "torch.Tensor",
                             k: int = 24) -> "torch.Tensor":
    """Exact point-to-mesh-surface distance (B, P) for points (B, P, 3), vertices (B, N, 3).

    Pruned search: a point's distance to a triangle is at least its distance to the
    triangle's bounding ball (centroid c_f, radius r_f) and at least its distance to the
    triangle's plane; the larger of the two is a lower bound.  The k triangles with the
    smallest lower bounds are solved exactly (``mesh.closest_point_on_triangles``); where the
    k-th bound does not prove the answer (rare), that point falls back to all triangles.
    Far faster than testing every triangle for markers on a body mesh, and still exact.
    """
    import torch

    from .mesh import closest_point_on_mesh, closest_point_on_triangles

    tri = vertices[:, faces]                                   # (B, F, 3, 3)
    cen = tri.mean(2)                                          # (B, F, 3)
    rad = (tri - cen[:, :, None]).norm(dim=-1).amax(-1)        # (B, F)
    nrm = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    plane = (torch.einsum("bpk,bfk->bpf", points, nrm) - (nrm * tri[:, :, 0]).sum(-1)[:, None, :]).abs()
    lower = torch.maximum(torch.cdist(points, cen) - rad[:, None, :], plane)   # (B, P, F)
    kk = min(k, faces.shape[0])
    low_k, idx = torch.topk(lower, kk, dim=-1, largest=False)  # (B, P, kk) ascending
    B, P = points.shape[:2]
    bi = torch.arange(B)[:, None, None]
    cand = tri[bi, idx]                                        # (B, P, kk, 3, 3)
    a, b_, c = cand[..., 0, :], cand[..., 1, :], cand[..., 2, :]
    q = points[:, :, None, :]
    bary = closest_point_on_triangles(q, a, b_, c)
    closest = bary[..., 0:1] * a + bary[..., 1:2] * b_ + bary[..., 2:3] * c
    d = (closest - q).norm(dim=-1).amin(-1)                    # (B, P)
    if kk < faces.shape[0]:
        # Faces outside the candidate set have lower bound >= the largest candidate bound.
        unproven = d > low_k[..., -1]
        if bool(unproven.any()):
            bs, ps = torch.nonzero(unproven, as_tuple=True)
            for bb in torch.unique(bs).tolist():
                sel = ps[bs == bb]
                dd, _, _ = closest_point_on_mesh(points[bb, sel], vertices[bb], faces)
                d[bb, sel] = dd
    return d


def marker_surface_distances(markers: np.ndarray, vertices: np.ndarray, faces, chunk: int = 24) -> np.ndarray:
    """Distance (metres) of every marker to the mesh surface: (F, M, 3) NaN=missing,
    (F, N, 3), faces (K, 3) -> (F, M) with NaN where the marker is missing."""
    import torch

    if markers.shape[0] != vertices.shape[0]:
        raise ValueError(f"markers have {markers.shape[0]} frames, mesh {vertices.shape[0]}")
    vis = np.isfinite(markers).all(-1)
    pts = np.where(vis[..., None], markers, 0.0)
    out = np.full(vis.shape, np.nan)
    f = torch.as_tensor(np.asarray(faces), dtype=torch.long)
    with torch.no_grad():
        for s in range(0, markers.shape[0], chunk):
            d = closest_surface_distance(torch.as_tensor(pts[s:s + chunk], dtype=torch.float32),
                                         torch.as_tensor(vertices[s:s + chunk], dtype=torch.float32), f)
            out[s:s + chunk] = d.double().numpy()
    out[~vis] = np.nan
    return out


def m2s(markers: np.ndarray, vertices: np.ndarray, faces) -> float:
    """Mean marker-to-surface distance (mm) over visible marker observations."""
    d = marker_surface_distances(markers, vertices, faces)
    return float(1000.0 * np.nanmean(d)) if np.isfinite(d).any() else float("nan")


def mirror_part(part: str) -> str:
    """'left_leg' <-> 'right_leg' etc."""
    if part.startswith("left_"):
        return "right_" + part[5:]
    if part.startswith("right_"):
        return "left_" + part[6:]
    return part


@dataclass(frozen=True)
class PartCheck:
    """Did the method put the markers on the right part?  hit: share of markers labelled with
    a joint of the true part (or its parent joint, for markers on the boundary); mirror: the
    same share for the mirrored part; found: hit >= 0.5 and hit > mirror."""

    hit: float
    mirror: float
    found: bool


def check_part(pred_marker_parts, part: str, part_joints: dict, joint_names, parents) -> PartCheck:
    """pred_marker_parts: (M,) joint names (or '' when unassigned) of the real markers."""
    labels = [str(x) for x in pred_marker_parts]
    if not labels:
        return PartCheck(0.0, 0.0, False)

    def share(p: str) -> float:
        idx = set(part_joints[p])
        idx |= {int(parents[j]) for j in part_joints[p] if int(parents[j]) >= 0}
        names = {joint_names[j] for j in idx}
        return float(np.mean([lab in names for lab in labels]))

    hit = share(part)
    mir = share(mirror_part(part)) if mirror_part(part) in part_joints and mirror_part(part) != part else 0.0
    return PartCheck(hit, mir, bool(hit >= 0.5 and hit > mir))


def posed_vertices(model, betas: np.ndarray, poses: np.ndarray, trans: np.ndarray, chunk: int = 128) -> np.ndarray:
    """World vertices (F, N, 3) float64 for AMASS-layout parameters, evaluated in chunks.
    betas: (B,) one shape for every frame, or (F, B) a shape per frame."""
    import torch

    from .lbs import forward

    b_all = np.asarray(betas, dtype=np.float32)
    if b_all.ndim == 2 and b_all.shape[0] != poses.shape[0]:
        raise ValueError(f"per-frame betas have {b_all.shape[0]} rows for {poses.shape[0]} frames")
    outs = []
    with torch.no_grad():
        for s in range(0, poses.shape[0], chunk):
            b = torch.as_tensor(b_all[s:s + chunk] if b_all.ndim == 2 else b_all.reshape(1, -1))
            o = forward(model, b, torch.as_tensor(np.asarray(poses[s:s + chunk], dtype=np.float32)),
                        torch.as_tensor(np.asarray(trans[s:s + chunk], dtype=np.float32)))
            outs.append(o.vertices.double().numpy())
    return np.concatenate(outs)


def surface_points_rest(model, betas: np.ndarray, faces_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Rest-pose (zero pose) positions (P, 3) of face + barycentric surface points."""
    v = posed_vertices(model, betas, np.zeros((1, 72)), np.zeros((1, 3)))[0]
    f = model.faces.numpy()[np.asarray(faces_ids, dtype=np.int64)]
    return (v[f] * np.asarray(bary, dtype=np.float64)[..., None]).sum(1)


def attachment_joint_names(model, faces_ids: np.ndarray, bary: np.ndarray) -> list[str]:
    """Joint name of the dominant bone at each surface point (its largest-weight corner's bone)."""
    from .parts import vertex_dominant_joint

    dom = np.asarray(vertex_dominant_joint(model))
    f = model.faces.numpy()[np.asarray(faces_ids, dtype=np.int64)]
    corner = f[np.arange(len(f)), np.argmax(np.asarray(bary), axis=1)]
    return [model.joint_names[int(j)] for j in dom[corner]]


def evaluate(pred: dict, gt: dict, model, pred_model=None, markers: np.ndarray | None = None,
             part: str | None = None, with_gt_m2s: bool = True) -> dict:
    """All metrics for one prediction against ground truth.

    pred / gt: AMASS-layout dicts (betas, poses (F,72), trans (F,3), joints (F,24,3); pred optionally
    frame_betas (F,B), the shape each frame was solved under (streamed solves); gt also
    mocap_framerate and the true marker attachment marker_faces/marker_bary; pred optionally
    marker_parts / marker_faces / marker_bary).  model: the ground truth's body model;
    pred_model: the prediction's (default: the same).  markers: (F, M, 3) metres, NaN where
    missing, in the order of gt's marker attachment.  part: the partial-body part name, if any.
    with_gt_m2s: also report m2s of the ground-truth mesh (``m2s_gt``, the ~9.5 mm reference).
    Returns a flat dict of floats (mm, mm/s) and a few counts/flags.
    """
    from .parts import PART_JOINTS

    pred_model = pred_model if pred_model is not None else model
    F = int(np.asarray(gt["poses"]).shape[0])
    if int(np.asarray(pred["poses"]).shape[0]) != F:
        raise ValueError(f"prediction has {np.asarray(pred['poses']).shape[0]} frames, ground truth {F}")
    rate = float(np.asarray(gt["mocap_framerate"]))
    pj, gj = np.asarray(pred["joints"], dtype=np.float64), np.asarray(gt["joints"], dtype=np.float64)
    res: dict = {"frames": F, "rate_hz": rate}
    res["mpjpe"] = mpjpe(pj, gj)
    res["pa_mpjpe"] = pa_mpjpe(pj, gj)
    res["mpjve"] = mpjve(pj, gj, rate)
    # A streamed solve may change its shape mid-take (a lock upgrade): each frame was solved under
    # its own betas (frame_betas), the AMASS betas key holds only the last one.
    pred_betas = pred["frame_betas"] if "frame_betas" in pred else pred["betas"]
    pv = posed_vertices(pred_model, pred_betas, np.asarray(pred["poses"]), np.asarray(pred["trans"]))
    gv = posed_vertices(model, gt["betas"], np.asarray(gt["poses"]), np.asarray(gt["trans"]))
    res["v2v"] = v2v(pv, gv) if pv.shape == gv.shape else float("nan")

    real = None
    if "marker_faces" in gt:
        real = np.asarray(gt["marker_faces"]) >= 0          # ghost tracks have no attachment
    if markers is not None:
        mk = np.asarray(markers, dtype=np.float64)
        if mk.shape[0] != F:
            raise ValueError(f"markers have {mk.shape[0]} frames, ground truth {F}")
        if real is not None and real.shape[0] != mk.shape[1]:
            raise ValueError(f"markers file has {mk.shape[1]} tracks, ground truth attaches {real.shape[0]}")
        sel = mk[:, real] if real is not None else mk
        res["m2s"] = m2s(sel, pv, pred_model.faces.numpy())
        if with_gt_m2s:
            res["m2s_gt"] = m2s(sel, gv, model.faces.numpy())
        res["markers"] = int(sel.shape[1])
        res["visible_fraction"] = float(np.isfinite(sel).all(-1).mean())

    if part:
        if part not in PART_JOINTS:
            raise ValueError(f"unknown part {part!r}; parts are {', '.join(PART_JOINTS)}")
        pjs = PART_JOINTS[part]
        res["part"] = part
        res["part_mpjpe"] = mpjpe(pj, gj, pjs)
        res["part_mpjve"] = mpjve(pj, gj, rate, pjs)
    labels = pred.get("marker_parts")
    if labels is not None and real is not None and len(labels) == real.shape[0]:
        lab = [str(x) for x, r in zip(np.asarray(labels).tolist(), real) if r]
        res["unassigned_fraction"] = float(np.mean([x == "" for x in lab])) if lab else float("nan")
        if part:
            pc = check_part(lab, part, PART_JOINTS, model.joint_names, model.parents.tolist())
            res.update(part_hit=pc.hit, part_mirror=pc.mirror, part_found=pc.found)
        if "marker_faces" in gt and "marker_bary" in gt:
            truth = attachment_joint_names(model, np.asarray(gt["marker_faces"])[real], np.asarray(gt["marker_bary"])[real])
            res["label_accuracy"] = float(np.mean([a == b for a, b in zip(lab, truth)])) if lab else float("nan")
            pf = pred.get("marker_faces")
            pb = pred.get("marker_bary")
            if pf is not None and pb is not None and pred_model.v_template.shape == model.v_template.shape:
                pf = np.asarray(pf)[real]
                ok = pf >= 0
                if ok.any():
                    t = surface_points_rest(model, gt["betas"], np.asarray(gt["marker_faces"])[real][ok],
                                            np.asarray(gt["marker_bary"])[real][ok])
                    p = surface_points_rest(model, gt["betas"], pf[ok], np.asarray(pb)[real][ok])
                    res["attach_err"] = float(1000.0 * np.linalg.norm(p - t, axis=1).mean())
    return res
