"""``uuomocap render``: a contact sheet PNG of a solved OUT.npz - look at a solve before trusting it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="contact sheet PNG of a solved OUT.npz (body, markers, labels, residuals)",
        description=(
            "Draw frames of a solved OUT.npz as a contact sheet: one column per frame, the shaded body "
            "seen from its front and from its left side.  With the markers (--session or --markers) every "
            "seen marker is a dot coloured by the body part it was labelled with (red ring = unlabelled) "
            "and a yellow line joins it to its solved surface point - the residual the solve left.  With "
            "ground truth (--gt, or the session's gt.npz) the reference skeleton is drawn as thin white "
            "lines and each column gives that frame's MPJPE."),
    )
    p.add_argument("pred", metavar="OUT.npz", help="solved output (uuomocap solve, or a recording's npz export)")
    p.add_argument("--session", metavar="DIR", help="the session it was solved from (markers, up axis, gt.npz)")
    p.add_argument("--markers", metavar="FILE", help="marker file (.c3d / .trc) when there is no session")
    p.add_argument("--gt", metavar="gt.npz", help="reference body (default: the session's gt.npz when it has one)")
    p.add_argument("--out", metavar="PNG", help="image to write (default: OUT.png beside OUT.npz)")
    p.add_argument("--frames", default="6", help="a count of evenly spaced frames (default 6, at most 24), or indices '0,120,240' (one: '120,')")
    p.add_argument("--tile", default="240x320", help="width x height of one view in pixels (default 240x320)")
    p.add_argument("--up-axis", choices=("+z", "+y"), help="world up axis (default: the session's / marker file's, else +z)")
    add_json_flag(p)
    p.set_defaults(func=_handler)


MAX_FRAMES = 24  # columns of one sheet


def _frames(spec: str, n: int) -> list[int]:
    try:
        if "," in spec:
            idx = [int(s) for s in spec.split(",") if s.strip()]
        else:
            k = int(spec)
            if not 1 <= k <= MAX_FRAMES:
                raise UserError(f"--frames {spec}: a count of 1-{MAX_FRAMES} frames (one frame by index: '{spec},')")
            idx = sorted(set(np.linspace(0, n - 1, min(k, n)).round().astype(int).tolist()))
    except ValueError:
        raise UserError(f"--frames {spec!r}: give a count (6) or frame indices (0,120,240)") from None
    bad = [i for i in idx if not 0 <= i < n]
    if len(idx) > MAX_FRAMES:
        raise UserError(f"--frames: at most {MAX_FRAMES} frames on one sheet")
    if bad or not idx:
        raise UserError(f"--frames {spec!r}: the solve has frames 0-{n - 1}")
    return idx


def _align(pred_stamps, md, n: int) -> np.ndarray:
    """Marker frame per solved frame: the same index when the counts agree, else the nearest stamp."""
    if md.positions.shape[0] == n:
        return np.arange(n)
    if pred_stamps is None:
        raise UserError(f"the marker file has {md.positions.shape[0]} frames, the solve {n}, and the solve has no stamps_ns to match them")
    st = np.asarray(md.stamps_ns, dtype=np.int64)
    return np.clip(np.searchsorted(st, np.asarray(pred_stamps, dtype=np.int64)), 0, len(st) - 1)


def _handler(args) -> int:
    try:
        tw, th = (int(v) for v in args.tile.lower().split("x"))
        if tw < 64 or th < 64:
            raise ValueError
    except ValueError:
        raise UserError(f"--tile {args.tile!r}: give WIDTHxHEIGHT, each at least 64 pixels") from None
    pred_path = Path(args.pred)
    out = Path(args.out) if args.out else pred_path.with_suffix(".png")
    info = render_sheet(pred_path, out, Path(args.session) if args.session else None, args.markers,
                        Path(args.gt) if args.gt else None, args.frames, (tw, th), args.up_axis)
    emit(args, info, f"wrote {out} ({info['width']}x{info['height']}, frames {', '.join(map(str, info['frames']))})")
    return 0


def render_sheet(pred_path: Path, out: Path, session: Path | None = None, markers_file: str | None = None,
                 gt_path: Path | None = None, frames_spec: str = "6", tile: tuple[int, int] = (240, 320),
                 up_axis: str | None = None) -> dict:
    """Write the contact sheet of ``pred_path`` to ``out`` (PNG); returns what was drawn."""
    import cv2

    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import SessionError, load_session, read_npz
    from uuomocap.render import contact_sheet
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.metrics import joint_errors, posed_vertices

    if not pred_path.is_file():
        raise UserError(f"{pred_path}: file not found")
    try:
        pred = read_npz(pred_path)
    except SessionError as exc:
        raise UserError(str(exc)) from None
    for k in ("poses", "trans", "joints", "betas"):
        if k not in pred:
            raise UserError(f"{pred_path}: missing key {k!r} (OUT.npz is AMASS layout: betas, poses, trans, joints, ...)")
    poses, trans, joints = (np.asarray(pred[k], np.float64) for k in ("poses", "trans", "joints"))
    n = poses.shape[0]
    if poses.shape != (n, 72) or trans.shape != (n, 3) or joints.shape != (n, 24, 3):
        raise UserError(f"{pred_path}: poses {poses.shape} / trans {trans.shape} / joints {joints.shape} must be (F, 72) / (F, 3) / (F, 24, 3)")
    frames = _frames(frames_spec, n)
    if out.suffix.lower() != ".png":
        raise UserError(f"--out {out}: the contact sheet is a .png")

    md = None
    if session is not None:
        try:
            s = load_session(session, load_prior=False, load_gt=False)
        except SessionError as exc:
            raise UserError(str(exc)) from None
        md, up_axis = s.markers, up_axis or s.up_axis
        if gt_path is None and (session / "gt.npz").is_file():
            gt_path = session / "gt.npz"
    elif markers_file:
        try:
            md = read_markers(markers_file)
        except MarkerFileError as exc:
            raise UserError(str(exc)) from None
        up_axis = up_axis or md.up_axis
    up_axis = up_axis or "+z"
    if up_axis not in ("+z", "+y"):
        raise UserError(f"up axis {up_axis!r}: render draws +z or +y worlds (give --up-axis)")

    sel = np.asarray(frames)
    name = str(pred["body_model"]) if "body_model" in pred else "open-low"
    try:
        model = load_body_model(name)
    except (ValueError, OSError) as exc:
        raise UserError(f"{pred_path}: cannot load body model {name!r} ({exc})") from None
    betas = np.asarray(pred["frame_betas"], np.float64)[sel] if "frame_betas" in pred else np.asarray(pred["betas"], np.float64)
    if not (np.isfinite(poses[sel]).all() and np.isfinite(trans[sel]).all() and np.isfinite(betas).all()):
        raise UserError(f"{pred_path}: the chosen frames hold NaN or inf (unsolved frames); pick others with --frames")
    vertices = posed_vertices(model, betas, poses[sel], trans[sel])  # (K, N, 3): the drawn frames only

    markers = points = parts = None
    labelled = 0
    if md is not None:
        rows = _align(pred.get("stamps_ns"), md, n)[sel]
        markers = np.where(md.visible[rows][..., None], md.positions[rows], np.nan)  # (K, M, 3)
        if "marker_faces" in pred and len(pred["marker_faces"]) == markers.shape[1]:
            faces = np.asarray(pred["marker_faces"], np.int64)
            bary = np.asarray(pred["marker_bary"], np.float64)
            parts = [str(p) for p in pred.get("marker_parts", [""] * len(faces))]
            ok = faces >= 0
            labelled = int(ok.sum())
            tri = model.faces.numpy()[np.where(ok, faces, 0)]  # (M, 3)
            points = np.where(ok[None, :, None], (vertices[:, tri] * bary[None, :, :, None]).sum(2), np.nan)

    gt_joints, err = None, None
    if gt_path is not None:
        if not gt_path.is_file():
            raise UserError(f"{gt_path}: file not found")
        gj = np.asarray(read_npz(gt_path)["joints"], np.float64)
        if gj.shape != joints.shape:
            raise UserError(f"{gt_path}: joints {gj.shape} do not match the solve's {joints.shape}")
        gt_joints, err = gj[sel], joint_errors(joints[sel], gj[sel]).mean(axis=1)  # (K,) mm per frame
    rate = float(pred["mocap_framerate"]) if "mocap_framerate" in pred else float("nan")
    captions = [f"frame {f}" + (f"  {f / rate:.2f} s" if np.isfinite(rate) else "") + (f"  {err[i]:.0f} mm" if err is not None else "")
                for i, f in enumerate(frames)]
    method = str(pred["method"]) if "method" in pred else "?"
    title = f"{pred_path.name}: {method}, {n} frames" + (f", {markers.shape[1]} markers ({labelled} labelled)" if markers is not None else "")
    if err is not None:
        title += f"; these frames' MPJPE {err.mean():.1f} mm against {gt_path.name}"
    sheet = contact_sheet(model, vertices, joints[sel], poses[sel, :3], up_axis, markers, points, parts, gt_joints,
                          captions, tile, title)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise UserError(f"{out}: could not write the image")
    return {"png": str(out), "frames": frames, "width": int(sheet.shape[1]), "height": int(sheet.shape[0]),
            "markers": int(markers.shape[1]) if markers is not None else 0, "labelled": labelled,
            "frame_mpjpe_mm": [round(float(e), 2) for e in err] if err is not None else None}
