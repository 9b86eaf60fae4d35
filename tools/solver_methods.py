"""Session -> OUT.npz adapters for the offline solver, its baselines and its ablations.

Registered in ``uuomocap.methods`` (imported by one line at the bottom of methods.py):
  uuo             the paper's staged solver with this project's improvements (default)
  uuo-paper       the paper as published: vertex chamfer, nearest-VERTEX correspondence,
                  E_M = (|s - m| - delta)^2, one Stage-5 round, no smoothing
  video-rr        the video prior rigidly registered to the markers (paper: HMR2.0+RR)
  no-mht          a single yaw hypothesis (paper's MHT ablation)
  markers-only    no video prior: a neutral upright body as the prior
  oracle-labeled  IK with the TRUE marker-surface correspondence from gt.npz (labelled
                  reference, the floor for our error; reads ground truth)
  uuo-matching / uuo-stage2 / uuo-stage4   the stage ablation (paper Table 4): the result after
                  part matching, Stage 2, Stage 4 (``uuo`` is after Stage 5)
Every method writes OUT.npz at the marker frames in the capture world (AMASS layout) with
marker labels, and returns an info dict (decisions, per-stage seconds).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from uuomocap.methods import register_method
from uuomocap.solver_core.body_model import load_solver_models as load_models  # the tests import it from here too
from uuomocap.solver_core.body_params import MarkerAttachment, up_tensor
from uuomocap.solver_core.prior_preparation import BodyPrior, neutral_prior, prepare_prior, prior_from_npz_arrays


@dataclass
class SolverInputs:
    """What every method needs from a session (or from loose files)."""

    markers: np.ndarray          # (T,M,3) metres, NaN missing
    visible: np.ndarray          # (T,M) bool
    rate_hz: float
    stamps_ns: np.ndarray        # (T,) int64 marker clock
    up_axis: str
    prior: BodyPrior | None      # world frame, at the marker frames (None: no prior available)
    shape_prior: np.ndarray | None
    body_model: str
    gt: dict | None = None
    source: str = ""
    clock_sync: dict | None = None  # what ``--clock-offset auto`` found (solve prints it)


def prior_for_markers(prior_arrays: dict, up_axis: str, marker_stamps_ns: np.ndarray, clock_offset_s: float) -> tuple[BodyPrior, np.ndarray]:
    """prior.npz arrays -> (world prior at the marker frames, shape prior)."""
    return prepare_prior(prior_from_npz_arrays(prior_arrays), up_axis, marker_stamps_ns, clock_offset_s)


def inputs_from_session(session_dir: Path, body_model: str | None = None, load_gt: bool = False) -> SolverInputs:
    from uuomocap.protocol.session import load_session

    s = load_session(session_dir, load_prior=True, load_gt=load_gt)
    md = s.markers
    prior, shape = (None, None)
    if s.prior is not None:
        prior, shape = prior_for_markers(s.prior, s.up_axis, md.stamps_ns, s.clock_offset_s)
    return SolverInputs(
        markers=np.asarray(md.positions, dtype=np.float64),
        visible=np.asarray(md.visible, dtype=bool),
        rate_hz=float(md.rate_hz),
        stamps_ns=np.asarray(md.stamps_ns, dtype=np.int64),
        up_axis=s.up_axis,
        prior=prior,
        shape_prior=shape,
        body_model=body_model or s.body_model,
        gt=s.gt,
        source=str(session_dir),
    )


def _require_prior(inputs: SolverInputs, method: str) -> None:
    if inputs.prior is None:
        raise ValueError(
            f"method {method!r} needs a video prior: the session has no prior.npz "
            "(make one with `uuomocap prior VIDEO`, pass --prior/--video, or use --method markers-only)"
        )


def _out_arrays(model, inputs: SolverInputs, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, joints: np.ndarray,
                attachment: MarkerAttachment | None, marker_parts: list[str] | None, method: str, stage_seconds: dict | None) -> dict:
    m = inputs.markers.shape[1]
    faces = np.full(m, -1, dtype=np.int64)
    bary = np.zeros((m, 3))
    parts = np.array([""] * m, dtype="<U32")
    if attachment is not None:
        faces = attachment.face_ids.numpy().astype(np.int64)
        bary = attachment.bary.double().numpy()
    if marker_parts is not None:
        parts = np.array(marker_parts, dtype="<U32")
    out = {
        "betas": np.asarray(betas, dtype=np.float64),
        "poses": np.asarray(poses, dtype=np.float64),
        "trans": np.asarray(trans, dtype=np.float64),
        "mocap_framerate": np.float64(inputs.rate_hz),
        "body_model": np.str_(inputs.body_model),
        "joints": np.asarray(joints, dtype=np.float64),
        "stamps_ns": np.asarray(inputs.stamps_ns, dtype=np.int64),
        "marker_parts": parts,
        "marker_faces": faces,
        "marker_bary": bary,
        "method": np.str_(method),
    }
    if stage_seconds:
        out["stage_seconds"] = np.str_(json.dumps(stage_seconds))
    return out


def _params_arrays(model, params, up_axis: str):
    from uuomocap.solver_core.body_params import pose_params
    from uuomocap.solver_core.lbs import SurfacePoints

    up = up_tensor(up_axis)
    with torch.no_grad():
        joints = pose_params(model, params, up, points=SurfacePoints.from_vertex_ids(torch.zeros(1, dtype=torch.long))).joints
    return params.poses72(up), params.trans.double().numpy(), params.betas.double().numpy(), joints.double().numpy()


# ----------------------------------------------------------------------------- the staged solver


def solver_config_for(method: str, **overrides):
    """SolverConfig of a staged-solver method name."""
    from uuomocap.solver_core.inverse_kinematics import InverseKinematicsConfig
    from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig
    from uuomocap.solver_core.pose_fitting import PoseFittingConfig
    from uuomocap.solver_core.staged_solver import SolverConfig

    cfg = SolverConfig()
    if method == "no-mht":
        cfg = replace(cfg, yaw_hypotheses_deg=(0.0,))
    elif method == "uuo-paper":
        cfg = replace(
            cfg,
            pose_fitting=replace(PoseFittingConfig(), data_term="vertex", smoothness_weight=0.0),
            correspondence=replace(CorrespondenceConfig(), method="vertex"),
            ik=replace(InverseKinematicsConfig(), offset_model="distance", smoothness_weight=0.0),
            refinement_rounds=1,
            placement_selection=replace(cfg.placement_selection, enabled=False),
            fit_offset_model="face_normal",
            decisive_full_body_ratio=None,  # the paper takes every yaw hypothesis through Stages 2-4
        )
    elif method == "markers-only":
        # the neutral prior has no rotation to offer a second opinion on the marker points
        cfg = replace(cfg, placement_selection=replace(cfg.placement_selection, enabled=False))
    elif method == "uuo-matching":
        cfg = replace(cfg, stop_after="matching")
    elif method == "uuo-stage2":
        cfg = replace(cfg, stop_after="stage2")
    elif method == "uuo-stage4":
        cfg = replace(cfg, stop_after="stage4")
    return replace(cfg, **overrides) if overrides else cfg


def run_staged_solver(inputs: SolverInputs, method: str = "uuo", progress=None, config=None):
    """Run ``staged_solver.solve`` for a method name -> (SolveResult, output model)."""
    from uuomocap.solver_core.staged_solver import solve

    model, chamfer_model = load_models(inputs.body_model)
    if method == "markers-only":
        prior = neutral_prior(inputs.markers.shape[0], inputs.up_axis, model.num_betas, inputs.stamps_ns)
        shape = np.zeros(model.num_betas)
    else:
        _require_prior(inputs, method)
        prior, shape = inputs.prior, inputs.shape_prior
    cfg = config if config is not None else solver_config_for(method)
    result = solve(inputs.markers, inputs.visible, inputs.rate_hz, inputs.up_axis, prior, shape, model, chamfer_model, cfg, progress)
    return result, model


def _staged_method(method: str) -> Callable[..., dict]:
    def run(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, inputs: SolverInputs | None = None, **opts) -> dict:
        from uuomocap.protocol.session import write_npz

        inputs = inputs or inputs_from_session(Path(session_dir), body_model)
        result, model = run_staged_solver(inputs, method, progress)
        poses, trans, betas, joints = _params_arrays(model, result.params, inputs.up_axis)
        d = result.diagnostics
        write_npz(out_npz, _out_arrays(model, inputs, poses, trans, betas, joints, result.attachment, result.marker_parts, method, d.get("stage_seconds")))
        return {"method": method, **{k: v for k, v in d.items() if k != "cluster_labels"}}

    run.__doc__ = f"staged UUO solver ({method})"
    return run


# ----------------------------------------------------------------------------- baselines


def video_rr(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, inputs: SolverInputs | None = None, **opts) -> dict:
    """HMR2.0+RR: the video prior rigidly registered to the unlabeled markers."""
    from uuomocap.protocol.session import write_npz
    from uuomocap.solver_core.baselines import video_rigid_registration

    t0 = time.perf_counter()
    inputs = inputs or inputs_from_session(Path(session_dir), body_model)
    _require_prior(inputs, "video-rr")
    model, chamfer_model = load_models(inputs.body_model)
    res = video_rigid_registration(inputs.markers, inputs.visible, inputs.up_axis, inputs.prior, inputs.shape_prior, chamfer_model)
    poses, trans, betas, joints = _params_arrays(model, res.params, inputs.up_axis)
    secs = {"registration": round(time.perf_counter() - t0, 3)}
    write_npz(out_npz, _out_arrays(model, inputs, poses, trans, betas, joints, None, None, "video-rr", secs))
    return {"method": "video-rr", "stage_seconds": secs, **res.diagnostics}


def oracle_labeled(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, inputs: SolverInputs | None = None, **opts) -> dict:
    """Labelled reference: IK with the true marker-surface correspondence (reads gt.npz)."""
    from uuomocap.protocol.session import write_npz
    from uuomocap.solver_core.baselines import labeled_inverse_kinematics
    from uuomocap.solver_core.staged_solver import marker_part_names

    t0 = time.perf_counter()
    inputs = inputs or inputs_from_session(Path(session_dir), body_model, load_gt=True)
    if inputs.gt is None or "marker_faces" not in inputs.gt:
        raise ValueError(f"{session_dir}: 'oracle-labeled' needs gt.npz with marker_faces/marker_bary")
    gt_model = str(inputs.gt["body_model"])
    if gt_model != inputs.body_model:
        raise ValueError(f"oracle-labeled: gt attachments are on {gt_model}, not {inputs.body_model}")
    model, _ = load_models(inputs.body_model)
    att = MarkerAttachment(
        torch.as_tensor(np.asarray(inputs.gt["marker_faces"]), dtype=torch.long),
        torch.as_tensor(np.asarray(inputs.gt["marker_bary"]), dtype=torch.float32),
        torch.zeros(inputs.markers.shape[1]),
    )
    if inputs.prior is not None:
        prior, shape = inputs.prior, inputs.shape_prior
    else:
        prior = neutral_prior(inputs.markers.shape[0], inputs.up_axis, model.num_betas, inputs.stamps_ns)
        shape = np.zeros(model.num_betas)
    res = labeled_inverse_kinematics(inputs.markers, inputs.visible, inputs.up_axis, prior, shape, att, model, rate_hz=inputs.rate_hz)
    poses, trans, betas, joints = _params_arrays(model, res.params, inputs.up_axis)
    secs = {"ik": round(time.perf_counter() - t0, 3)}
    write_npz(out_npz, _out_arrays(model, inputs, poses, trans, betas, joints, att, marker_part_names(model, att), "oracle-labeled", secs))
    return {"method": "oracle-labeled", "stage_seconds": secs, **res.diagnostics}


STAGED_METHODS = {
    "uuo": "the paper's staged solver (+ surface data term, robust surface correspondence)",
    "uuo-paper": "the staged solver as published (vertex chamfer and correspondence, distance E_M)",
    "no-mht": "staged solver with a single yaw hypothesis (MHT ablation)",
    "markers-only": "staged solver without a video prior (neutral upright prior)",
    "uuo-matching": "stage ablation: after marker-part matching",
    "uuo-stage2": "stage ablation: after Stage 2 (pose fitting)",
    "uuo-stage4": "stage ablation: after Stage 4 (IK, before Stage 5)",
}
for _name, _desc in STAGED_METHODS.items():
    register_method(_name, _staged_method(_name), _desc)
register_method("video-rr", video_rr, "video prior rigidly registered to the markers (paper: HMR2.0+RR)")
register_method("oracle-labeled", oracle_labeled, "IK with the true marker-surface correspondence (labelled reference)", reference=True)
