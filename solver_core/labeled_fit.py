"""Labeled IK: fit the body to a LABELED marker capture (each label = one fixed body surface point).

With labels the correspondence problem of the unlabeled solver shrinks to "where on the body does
label k sit", which is constant over the whole take.  The fit:
  1. start: the staged solver's markers-only path (neutral upright prior; segmentation, part
     matching, yaw hypotheses, Stages 2-5) on an evenly spaced subsample of the frames, its body
     interpolated to every frame;
  2. alternate ``rounds`` times, over ALL frames:
       a. per label, the surface point (face + barycentric) with the smallest mean distance to the
          label's marker over the take (Stage 3, ``find_marker_surface_points``);
       b. IK of every frame to those points (Stage 4, 9.5 mm offset along the normal), the previous
          round's poses as the pose prior (as in the paper's Stage 5);
  3. residuals: per-frame RMS over the visible labels and per-label statistics, so a label that was
     swapped or mis-tracked for part of the take shows up as a large per-label max / bad-frame count.
Gaps (NaN) never contribute; labels never seen are left unassigned (the caller warns).
Label names are not used: any labeled file works.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from uuomocap.solver_core.body_params import (
    BodyParams,
    FreeParameters,
    MarkerAttachment,
    interpolate_params,
    pose_params,
    up_tensor,
)
from uuomocap.solver_core.inverse_kinematics import InverseKinematicsConfig, predicted_markers, solve_inverse_kinematics
from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, find_marker_surface_points


@dataclass(frozen=True)
class LabeledFitConfig:
    # Beyond the paper: alternations of (per-label surface point, IK over all frames).
    rounds: int = 4
    # Beyond the paper (speed): most upright frames the markers-only staged solver sees
    # for the starting body.
    init_frames: int = 30
    # Per-label surface point: whole-body search every round (labels are reliable over the take).
    correspondence: CorrespondenceConfig = CorrespondenceConfig(refine_radius_m=None)
    # Stage-4 IK; paper defaults (9.5 mm offset, lambda_M=1, lambda_Theta=0.1, lambda_beta=1) plus a
    # small joint-acceleration term (beyond the paper) against jitter on gappy labels.
    ik: InverseKinematicsConfig = InverseKinematicsConfig(smoothness_weight=0.1)
    # A frame/label residual above this is counted as a bad frame of that label (swap indicator).
    bad_residual_m: float = 0.03
    # Use label names (when >= 8 are recognised) for the start; else the markers-only solver starts.
    use_names: bool = True
    # Labels seen in fewer frames than this are ignored (reported).
    min_visible_frames: int = 1


@dataclass
class LabeledFit:
    params: BodyParams               # every frame, capture world, yaw separate
    attachment: MarkerAttachment     # per label (face -1: ignored label)
    frame_rms_m: np.ndarray          # (T,) RMS marker residual over visible labels (NaN: none visible)
    label_residuals: dict            # label statistics, see ``label_statistics``
    ignored: list[int]               # label indices never (or too rarely) seen
    diagnostics: dict = field(default_factory=dict)


def usable_labels(visible: np.ndarray, min_frames: int = 1) -> np.ndarray:
    """(M,) bool: labels visible in at least ``min_frames`` frames.  visible (T,M) bool."""
    return np.asarray(visible, bool).sum(axis=0) >= max(1, int(min_frames))


def evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` evenly spaced entries of ``indices`` (all when there are fewer)."""
    if len(indices) <= count:
        return np.asarray(indices)
    return indices[np.unique(np.linspace(0, len(indices) - 1, count).round().astype(int))]


def marker_residuals(model, markers: torch.Tensor, visible: torch.Tensor, params: BodyParams,
                     attachment: MarkerAttachment, up: torch.Tensor, offset_m: float) -> np.ndarray:
    """(T,M) metres: distance between each observed label and where the body puts it (surface point
    + offset along the normal); NaN where the label is missing or unassigned."""
    t_count, m_count = visible.shape
    out = np.full((t_count, m_count), np.nan)
    assigned = attachment.assigned
    if not bool(assigned.any()):
        return out
    with torch.no_grad():
        pred = predicted_markers(model, params, attachment, up, offset_m)
    dist = (pred - torch.nan_to_num(markers[:, assigned])).norm(dim=-1).double().numpy()
    vis = visible[:, assigned].numpy()
    sub = np.where(vis, dist, np.nan)
    out[:, assigned.numpy()] = sub
    return out


def frame_rms(residuals: np.ndarray) -> np.ndarray:
    """(T,M) residuals with NaN -> (T,) RMS over the finite entries (NaN for empty frames)."""
    sq = np.where(np.isfinite(residuals), residuals ** 2, 0.0)
    n = np.isfinite(residuals).sum(axis=1)
    return np.where(n > 0, np.sqrt(sq.sum(axis=1) / np.maximum(n, 1)), np.nan)


def label_statistics(residuals: np.ndarray, labels: list[str], bad_m: float) -> dict:
    """Per label: frames seen, mean / RMS / max residual (mm), frames above ``bad_m``, worst frame.

    residuals (T,M) metres with NaN.  A label whose max is far above the others, or with many bad
    frames, is likely swapped with another label or mis-tracked for part of the take."""
    out = {}
    for k, name in enumerate(labels):
        r = residuals[:, k]
        ok = np.isfinite(r)
        if not ok.any():
            out[name] = {"frames": 0}
            continue
        rv = r[ok]
        out[name] = {
            "frames": int(ok.sum()),
            "mean_mm": round(1000 * float(rv.mean()), 2),
            "rms_mm": round(1000 * float(np.sqrt((rv ** 2).mean())), 2),
            "max_mm": round(1000 * float(rv.max()), 2),
            "bad_frames": int((rv > bad_m).sum()),
            "worst_frame": int(np.flatnonzero(ok)[int(np.argmax(rv))]),
        }
    return out


def suspicious_labels(stats: dict, factor: float = 3.0, floor_mm: float = 20.0) -> list[str]:
    """Labels whose max residual exceeds max(floor_mm, factor x the median label RMS): candidate
    swaps / mis-tracks worth a look."""
    rms = [s["rms_mm"] for s in stats.values() if s.get("frames")]
    if not rms:
        return []
    limit = max(floor_mm, factor * float(np.median(rms)))
    return [name for name, s in stats.items() if s.get("frames") and s["max_mm"] > limit]


# label keywords -> a landmark of the structured anatomical layout (marker_sim); the first match wins
_NAME_KEYWORDS = (
    ("asi", "ASI"), ("psi", "PSI"), ("sacr", "PSI"), ("strn", "STRN"), ("stern", "STRN"), ("xiph", "STRN"),
    ("clav", "CLAV"), ("jug", "CLAV"), ("c7", "C7"), ("t10", "T10"), ("t8", "T10"), ("acrom", "SHO"),
    ("sho", "SHO"), ("bicep", "UPA"), ("upa", "UPA"), ("humer", "UPA"), ("elb", "ELB"), ("frm", "FRM"),
    ("forearm", "FRM"), ("wr", "WRA"), ("styl", "WRA"), ("fin", "FIN"), ("hand", "FIN"), ("thi", "THI"),
    ("kne", "KNE"), ("shank", "TIB"), ("tib", "TIB"), ("shin", "TIB"), ("ank", "ANK"), ("mall", "ANK"),
    ("hee", "HEE"), ("calc", "HEE"), ("toe", "TOE"), ("midfoot", "TOE"), ("met", "TOE"), ("foot", "TOE"),
    ("head", "FHD"), ("hd", "FHD"), ("temple", "FHD"),
)


def label_landmark(label: str) -> str | None:
    """A label name -> the structured-layout landmark it is near ('LASI', 'STRN', ...) or None.

    Side from a leading 'L'/'R' (+ separator or capital, e.g. 'L.ASIS', 'LASI', 'Left_Knee');
    centre labels take the left landmark of a pair (a rough start; the fit moves it)."""
    import re

    m = (re.match(r"^(left|right|l|r)(?=[._\-\s])", label, re.IGNORECASE) or re.match(r"^(Left|Right|L|R)(?=[A-Z0-9])", label)
         or re.match(r"^(left|right)", label, re.IGNORECASE))
    side = m.group(1)[0].upper() if m else ""
    rest = label[m.end():] if m else label
    low = rest.lower()
    for key, mark in _NAME_KEYWORDS:
        if key in low:
            if mark in ("STRN", "CLAV", "C7", "T10"):
                return mark
            return (side or "L") + mark
    return None


def name_attachment(model, labels: list[str], usable: np.ndarray) -> MarkerAttachment | None:
    """Rough per-label surface points from label names (``label_landmark``) on the mean shape, or
    None when fewer than 8 usable labels (or no left AND right label) are recognised."""
    from uuomocap.solver_core.marker_sim import structured_layout

    layout = structured_layout(model, np.zeros(model.num_betas))
    index = {n: k for k, n in enumerate(layout.names)}
    m_count = len(labels)
    faces = torch.full((m_count,), -1, dtype=torch.long)
    bary = torch.zeros(m_count, 3)
    sides = set()
    for k, lab in enumerate(labels):
        mark = label_landmark(lab)
        if mark is None or mark not in index or not usable[k]:
            continue
        faces[k] = int(layout.face_ids[index[mark]])
        bary[k] = torch.as_tensor(layout.bary[index[mark]], dtype=torch.float32)
        sides.add(mark[0])
    if int((faces >= 0).sum()) < 8 or not {"L", "R"} <= sides:
        return None
    return MarkerAttachment(faces, bary, torch.zeros(m_count))


def start_from_names(model, mk: torch.Tensor, vis: torch.Tensor, att: MarkerAttachment, up_axis: str,
                     config: "LabeledFitConfig", rate_hz: float) -> BodyParams:
    """Every frame from the neutral upright body: closed-form heading + translation to the named
    labels, then IK to them (plain least squares, so far-off limbs still pull)."""
    from uuomocap.solver_core.baselines import labeled_heading_and_translation
    from uuomocap.solver_core.prior_preparation import neutral_prior

    t_count = mk.shape[0]
    prior = neutral_prior(t_count, up_axis, model.num_betas, np.zeros(t_count, dtype=np.int64))
    root = torch.as_tensor(prior.root_orient, dtype=torch.float32)
    body = torch.as_tensor(prior.body_pose, dtype=torch.float32)
    betas = torch.zeros(model.num_betas)
    up = up_tensor(up_axis)
    yaw, trans = labeled_heading_and_translation(model, mk, vis, att, root, body, betas, up, config.ik.marker_offset_m)
    init = BodyParams(root.clone(), body.clone(), trans, betas.clone(), yaw.detach().clone())
    ik = config.ik  # plain least squares: a robust kernel would ignore the far-off (T-pose) arms
    params, _ = solve_inverse_kinematics(model, mk, vis, att, root, body, betas, init, up, ik, FreeParameters(yaw=True),
                                         rate_hz=rate_hz)
    return params


def upright_frames(markers: np.ndarray, visible: np.ndarray, up_axis: str, count: int) -> np.ndarray:
    """The ``count`` frames closest to a neutral stance, increasing: most labels visible, then the
    smallest horizontal spread of the labels about their centroid (legs together, arms down, as
    the neutral start of the unlabeled solver expects).  markers (T,M,3); visible (T,M)."""
    from uuomocap.solver_core.prior_preparation import up_axis_vector

    up = up_axis_vector(up_axis)
    n_vis = visible.sum(axis=1)
    cand = np.flatnonzero(n_vis >= max(3, int(n_vis.max() * 0.9)))
    x = np.where(visible[cand, :, None], markers[cand], np.nan)
    horiz = x - (x @ up)[..., None] * up
    spread = np.sqrt(np.nanmean(((horiz - np.nanmean(horiz, axis=1, keepdims=True)) ** 2).sum(-1), axis=1))
    return np.sort(cand[np.argsort(spread)[:count]])


def initial_fit(markers: np.ndarray, visible: np.ndarray, rate_hz: float, up_axis: str, model, chamfer_model,
                frames: int, progress=None) -> tuple[BodyParams, MarkerAttachment, dict]:
    """Starting body: the staged markers-only solve on the ``frames`` most upright frames
    (``upright_frames``), their per-label attachment, and every frame started from the mean of
    those bodies moved to the frame's label centroid.  markers (T,M,3) metres NaN missing;
    visible (T,M).  Returns (params (T frames), attachment, staged-solver diagnostics)."""
    from uuomocap.solver_core.prior_preparation import neutral_prior
    from uuomocap.solver_core.rotations import axis_angle_to_matrix, matrix_to_axis_angle
    from uuomocap.solver_core.staged_solver import SolverConfig, solve

    t_count = markers.shape[0]
    sel = upright_frames(markers, visible, up_axis, frames)
    stamps = np.round(np.arange(len(sel)) * 1e9).astype(np.int64)
    prior = neutral_prior(len(sel), up_axis, model.num_betas, stamps)
    cfg = SolverConfig(screening_frames=len(sel), chamfer_frames=len(sel), force_full_body=True,
                       track_stitching=None)  # the frames are not consecutive: no handovers
    # the neutral prior has no rotation to offer a second opinion on the marker points
    cfg = replace(cfg, placement_selection=replace(cfg.placement_selection, enabled=False))
    # frames are not consecutive: a 1 Hz "rate" makes the temporal terms negligible
    res = solve(markers[sel], visible[sel], 1.0, up_axis, prior, np.zeros(model.num_betas), model,
                chamfer_model, cfg, progress)
    p = res.params
    mean_rot = axis_angle_to_matrix(torch.cat([p.root_orient[:, None], p.body_pose], 1)).mean(0)
    u, _, vt = torch.linalg.svd(mean_rot)
    rots = matrix_to_axis_angle(u @ vt)  # (24,3) chordal mean of every joint
    # translation: the mean body's offset from the label centroid, moved to each frame's centroid
    centroid = np.array([np.nanmean(np.where(visible[t, :, None], markers[t], np.nan), axis=0) if visible[t].any()
                         else np.full(3, np.nan) for t in range(t_count)])
    from uuomocap.solver_core.body_params import fill_nan_rows

    centroid = fill_nan_rows(centroid)
    offset = (p.trans.double().numpy() - centroid[sel]).mean(0)
    trans = torch.as_tensor(centroid + offset, dtype=torch.float32)
    params = BodyParams(rots[0].expand(t_count, 3).clone(), rots[1:].expand(t_count, 23, 3).clone(), trans,
                        p.betas.clone(), p.yaw.clone())
    return params, res.attachment, res.diagnostics


def fit_labeled_markers(markers: np.ndarray, visible: np.ndarray | None, rate_hz: float, up_axis: str, model,
                        labels: list[str] | None = None, chamfer_model=None,
                        config: LabeledFitConfig = LabeledFitConfig(), progress=None,
                        on_round=None) -> LabeledFit:
    """Fit the body to a labeled capture.

    markers (T,M,3) metres in the capture world, NaN where missing (column k = label k for the whole
    take); visible (T,M) bool or None (= finite); up_axis '+z' / '+y' ...; model: output body model;
    chamfer_model: low-resolution model with the same skeleton for the start (None = model);
    on_round(round, frame_rms_m (T,)): optional callback after each round.
    """
    markers = np.asarray(markers, dtype=np.float64)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise ValueError(f"markers must be (T, M, 3), got {markers.shape}")
    finite = np.isfinite(markers).all(axis=2)
    vis_np = finite if visible is None else (np.asarray(visible, bool) & finite)
    t_count, m_count, _ = markers.shape
    labels = list(labels) if labels is not None else [f"M{k:03d}" for k in range(m_count)]
    use = usable_labels(vis_np, config.min_visible_frames)
    if int(use.sum()) < 3:
        raise ValueError(f"only {int(use.sum())} label(s) are ever visible; need at least 3")
    vis_np = vis_np & use[None, :]
    ignored = [int(k) for k in np.flatnonzero(~use)]
    chamfer_model = chamfer_model or model
    up = up_tensor(up_axis)
    mk = torch.as_tensor(markers, dtype=torch.float32)
    vis = torch.as_tensor(vis_np)
    beta_prior = torch.zeros(model.num_betas)

    named = name_attachment(model, labels, use) if config.use_names else None
    if named is not None:
        # start from label names (rough anatomical points), every frame
        params = start_from_names(model, mk, vis, named, up_axis, config, rate_hz)
        diag = {"start": "label names", "named_labels": int(named.assigned.sum()), "rounds": []}
    else:
        # start: markers-only staged solve on the most upright frames (only the usable labels)
        cols = np.flatnonzero(use)
        sub_mk = np.where(vis_np[..., None], markers, np.nan)[:, cols]
        params, att0, init_diag = initial_fit(sub_mk, vis_np[:, cols], rate_hz, up_axis, model, chamfer_model,
                                              config.init_frames, progress)
        diag = {"start": "markers-only solver", "init_yaw_deg": init_diag.get("chosen_yaw_deg"),
                "init_marker_fit_mm": init_diag.get("stage5_marker_fit_mm"), "rounds": []}
        att = MarkerAttachment(torch.full((m_count,), -1, dtype=torch.long), torch.zeros(m_count, 3),
                               torch.full((m_count,), float("inf")))
        cols_t = torch.as_tensor(cols)
        att.face_ids[cols_t], att.bary[cols_t], att.score_m[cols_t] = att0.face_ids, att0.bary, att0.score_m
        params, _ = solve_inverse_kinematics(model, mk, vis, att, params.root_orient, params.body_pose, beta_prior, params,
                                             up, config.ik, FreeParameters(yaw=False), rate_hz=rate_hz)

    from uuomocap.solver_core.chamfer import vertex_face_table

    vertex_faces = vertex_face_table(model.faces, model.v_template.shape[0])
    for r in range(max(1, config.rounds)):
        att = find_marker_surface_points(model, mk, vis, params, up, None, config.correspondence, vertex_faces)
        params, rep = solve_inverse_kinematics(
            model, mk, vis, att, params.root_orient, params.body_pose, beta_prior, params, up, config.ik,
            FreeParameters(yaw=False), rate_hz=rate_hz,
        )
        res = marker_residuals(model, mk, vis, params, att, up, config.ik.marker_offset_m)
        rms = frame_rms(res)
        diag["rounds"].append({"round": r + 1, "ik_loss": rep.final_loss,
                               "marker_rms_mm": round(1000 * float(np.sqrt(np.nanmean(res ** 2))), 3)})
        if on_round is not None:
            on_round(r + 1, rms)
    stats = label_statistics(res, labels, config.bad_residual_m)
    diag["suspicious_labels"] = suspicious_labels(stats)
    return LabeledFit(params, att, rms, stats, ignored, diag)


def params_joints(model, params: BodyParams, up_axis: str) -> np.ndarray:
    """(T,24,3) joint positions of ``params`` in the capture world."""
    from uuomocap.solver_core import lbs

    with torch.no_grad():
        out = pose_params(model, params, up_tensor(up_axis), lbs.SurfacePoints.from_vertex_ids(torch.zeros(1, dtype=torch.long)))
    return out.joints.double().numpy()


def rest_root_joint(model, betas: np.ndarray) -> np.ndarray:
    """(3,) the root joint's rest position for ``betas`` (LBS: posed root = this + trans)."""
    from uuomocap.solver_core import lbs

    with torch.no_grad():
        out = lbs.forward(model, torch.as_tensor(betas, dtype=torch.float32).reshape(1, -1), torch.zeros(1, 24, 3))
    return out.joints[0, 0].double().numpy()


def to_z_up(poses: np.ndarray, trans: np.ndarray, root_joint: np.ndarray, up_axis: str) -> tuple[np.ndarray, np.ndarray]:
    """Re-express a world motion with ``up_axis`` in the AMASS Z-up world, exactly.

    poses (T,72) world axis-angle; trans (T,3); root_joint (3,) rest root of the shape.  The whole
    world turns by R: root rotations R @ R_root, and the posed root R (J0 + t) = J0 + t'."""
    from uuomocap.solver_core.motions import axis_angle_to_matrices, canonical_to_world, matrices_to_axis_angle

    r = canonical_to_world("+z") @ canonical_to_world(up_axis).T
    aa = np.array(poses, dtype=np.float64).reshape(-1, 24, 3)
    aa[:, 0] = matrices_to_axis_angle(r @ axis_angle_to_matrices(aa[:, 0]))
    new_trans = (np.asarray(trans) + root_joint) @ r.T - root_joint
    return aa.reshape(-1, 72), new_trans


def motion_arrays(model, fit: LabeledFit, up_axis: str, rate_hz: float, body_model: str, labels: list[str]) -> dict:
    """The AMASS-style motion npz (Z-up world, like AMASS): poses (T,72), trans (T,3), betas,
    mocap_framerate, gender, body_model, plus the per-label attachment and fit residuals."""
    up = up_tensor(up_axis)
    betas = fit.params.betas.double().numpy()
    poses, trans = to_z_up(fit.params.poses72(up), fit.params.trans.double().numpy(), rest_root_joint(model, betas), up_axis)
    return {
        "poses": poses,
        "trans": trans,
        "betas": betas,
        "mocap_framerate": np.float64(rate_hz),
        "gender": np.str_("neutral"),
        "body_model": np.str_(body_model),
        "marker_labels": np.array(labels, dtype=np.str_),
        "marker_faces": fit.attachment.face_ids.numpy().astype(np.int64),
        "marker_bary": fit.attachment.bary.double().numpy(),
        "frame_rms_mm": 1000 * np.asarray(fit.frame_rms_m, dtype=np.float64),
        "source_up_axis": np.str_(up_axis),
    }


def summarise_rms(frame_rms_m: np.ndarray) -> dict:
    """Median / mean / p95 / max of the per-frame RMS (mm) over frames with data."""
    v = 1000 * np.asarray(frame_rms_m)[np.isfinite(frame_rms_m)]
    if v.size == 0:
        return {"frames": 0}
    return {"frames": int(v.size), "mean_mm": round(float(v.mean()), 2), "median_mm": round(float(np.median(v)), 2),
            "p95_mm": round(float(np.percentile(v, 95)), 2), "max_mm": round(float(v.max()), 2)}

