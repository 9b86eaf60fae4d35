"""``uuomocap eval``: the paper's metrics for a solved OUT.npz against ground truth."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit

OUT_REQUIRED = ("betas", "poses", "trans", "joints")

# Order and units of the printed metrics.
METRIC_UNITS = {
    "m2s": "mm", "m2s_gt": "mm", "mpjpe": "mm", "pa_mpjpe": "mm", "mpjve": "mm/s", "v2v": "mm",
    "part_mpjpe": "mm", "part_mpjve": "mm/s", "attach_err": "mm", "label_accuracy": "", "unassigned_fraction": "",
    "part_hit": "", "part_mirror": "", "part_found": "",
}


@functools.lru_cache(maxsize=4)
def _model(name: str):
    from uuomocap.solver_core.body_model import load_body_model

    return load_body_model(name)


def _load_model(name: str, what: str):
    try:
        return _model(name)
    except (ValueError, OSError) as exc:
        raise UserError(f"{what}: cannot load body model {name!r} ({exc})") from None


def evaluate_paths(pred_path: Path, gt_path: Path, markers_path: Path | None = None, part: str | None = None,
                   with_gt_m2s: bool = True) -> dict:
    """Metrics for OUT.npz vs gt.npz (+ the session's marker file for m2s)."""
    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import SessionError, read_npz, validate_gt
    from uuomocap.solver_core.metrics import evaluate

    try:
        pred = read_npz(pred_path)
        gt = read_npz(gt_path)
        validate_gt(gt, str(gt_path))
    except SessionError as exc:
        raise UserError(str(exc)) from None
    missing = [k for k in OUT_REQUIRED if k not in pred]
    if missing:
        raise UserError(f"{pred_path}: missing key(s) {', '.join(missing)} (OUT.npz is AMASS layout: betas, poses, trans, joints, ...)")
    for k in OUT_REQUIRED:
        if not np.isfinite(np.asarray(pred[k], dtype=np.float64)).all():
            raise UserError(f"{pred_path}: {k} contains NaN or inf")
    if np.asarray(pred["poses"]).shape[1:] != (72,) or np.asarray(pred["joints"]).shape[1:] != (24, 3):
        raise UserError(f"{pred_path}: poses {np.asarray(pred['poses']).shape} / joints {np.asarray(pred['joints']).shape} "
                        f"must be (F, 72) / (F, 24, 3)")
    if "frame_betas" in pred:
        fb = np.asarray(pred["frame_betas"], dtype=np.float64)
        if fb.ndim != 2 or fb.shape[0] != np.asarray(pred["poses"]).shape[0]:
            raise UserError(f"{pred_path}: frame_betas {fb.shape} must be (F, B) with F = {np.asarray(pred['poses']).shape[0]} frames")
        if not np.isfinite(fb).all():
            raise UserError(f"{pred_path}: frame_betas contains NaN or inf")
    gt_model_name = str(gt["body_model"])
    model = _load_model(gt_model_name, str(gt_path))
    pred_model_name = str(pred["body_model"]) if "body_model" in pred else gt_model_name
    pred_model = model if pred_model_name == gt_model_name else _load_model(pred_model_name, str(pred_path))
    markers = None
    if markers_path is not None:
        try:
            markers = read_markers(markers_path).positions
        except MarkerFileError as exc:
            raise UserError(str(exc)) from None
    if part is None and "part" in gt:
        part = str(gt["part"]) or None
    try:
        res = evaluate(pred, gt, model, pred_model, markers=markers, part=part, with_gt_m2s=with_gt_m2s)
    except ValueError as exc:
        raise UserError(f"{pred_path}: {exc}") from None
    res["method"] = str(pred["method"]) if "method" in pred else ""
    res["body_model"] = pred_model_name
    return res


def format_metrics(res: dict) -> str:
    lines = []
    for k, unit in METRIC_UNITS.items():
        if k in res:
            v = res[k]
            if isinstance(v, (bool, np.bool_)):
                lines.append(f"{k:>20}: {'yes' if v else 'no'}")
            else:
                lines.append(f"{k:>20}: {v:10.2f} {unit}".rstrip())
    extra = [f"frames {res.get('frames')} @ {res.get('rate_hz')} Hz"]
    if "markers" in res:
        extra.append(f"{res['markers']} markers, {100 * res.get('visible_fraction', 1):.1f}% visible")
    if res.get("part"):
        extra.append(f"part {res['part']}")
    return "\n".join(lines + ["  (" + "; ".join(extra) + ")"])


def _handler(args) -> int:
    pred = Path(args.pred)
    if args.session:
        sdir = Path(args.session)
        gt = Path(args.gt) if args.gt else sdir / "gt.npz"
        markers = Path(args.markers) if args.markers else None
        if markers is None:
            from uuomocap.protocol.session import SessionError, load_session

            try:
                markers = load_session(sdir, load_prior=False, load_gt=False).marker_file
            except SessionError as exc:
                raise UserError(str(exc)) from None
    else:
        if not args.gt:
            raise UserError("give --gt gt.npz (or --session DIR)")
        gt = Path(args.gt)
        markers = Path(args.markers) if args.markers else None
    for p in (pred, gt) + ((markers,) if markers else ()):
        if not p.is_file():
            raise UserError(f"{p}: file not found")
    res = evaluate_paths(pred, gt, markers, args.part)
    emit(args, res, format_metrics(res))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="metrics of a solved OUT.npz against ground truth (MPJPE, PA-MPJPE, MPJVE, V2V, m2s)",
        description=(
            "Evaluate a solved OUT.npz against a ground-truth gt.npz, in millimetres (mm/s for MPJVE): "
            "MPJPE over joints 0-21 in the world frame without alignment, PA-MPJPE (per-frame similarity "
            "Procrustes), MPJVE (finite-difference velocities at the sequence rate), V2V (mean vertex "
            "distance) and, with --markers, m2s (marker to mesh SURFACE; the ground truth scores ~9.5 mm "
            "because markers sit 9.5 mm off the skin).  Partial-body sessions also get metrics on the part's "
            "joints and whether the markers were put on the right part."),
    )
    p.add_argument("--pred", required=True, metavar="OUT.npz", help="solved output (AMASS layout)")
    p.add_argument("--gt", metavar="gt.npz", help="ground truth (default with --session: SESSION/gt.npz)")
    p.add_argument("--markers", metavar="FILE", help="the session's marker file (.c3d/.trc) for m2s")
    p.add_argument("--session", metavar="DIR", help="take gt.npz and the marker file from a session directory")
    p.add_argument("--part", help="evaluate a partial-body part (default: the part recorded in gt.npz)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
