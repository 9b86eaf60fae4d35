"""``uuomocap render``: a contact sheet PNG of a solved OUT.npz - look at a solve before trusting it."""

from __future__ import annotations

from dataclasses import dataclass
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
    p.add_argument("--markers", metavar="FILE", help="marker file (.c3d, .trc, or a recording's .mcap) when there is no session")
    p.add_argument("--gt", metavar="gt.npz", help="reference body (default: the session's gt.npz when it has one)")
    p.add_argument("--out", metavar="PNG", help="image to write (default: OUT.png beside OUT.npz)")
    p.add_argument("--frames", default="6", help="a count of frames (default 6, at most 24: the poses that differ most, in time order), or indices '0,120,240' (one: '120,')")
    p.add_argument("--tile", default="240x320", help="width x height of one view in pixels (default 240x320)")
    p.add_argument("--up-axis", choices=("+z", "+y"), help="world up axis (default: the session's / marker file's, else +z)")
    p.add_argument("--video", metavar="MP4", help="also write a video of the take from one fixed camera, with the same overlays")
    p.add_argument("--stride", type=int, default=1, help="video: every Nth frame (default 1; the video plays in real time)")
    add_json_flag(p)
    p.set_defaults(func=_handler)


MAX_FRAMES = 24  # columns of one sheet


def spread_frames(joints: np.ndarray, k: int, time_span_m: float = 0.3) -> list[int]:
    """k frames that differ most in pose, in time order: farthest-point sampling over each frame's
    root-relative joints (metres) with its time along one more axis (the take spans ``time_span_m``,
    so repeats of a pose - a walk's strides - are told apart by when they happen, but a different
    pose counts for more).  Evenly spaced frames of a cyclic motion can all land on one phase.
    joints: (F, 24, 3); frames holding NaN are never picked; starts at the first finite frame."""
    F = joints.shape[0]
    ok = np.isfinite(joints).all(axis=(1, 2))
    if not ok.any():
        return sorted(set(np.linspace(0, F - 1, min(k, F)).round().astype(int).tolist()))
    feats = np.concatenate([(joints - joints[:, :1]).reshape(F, -1), (np.arange(F) * time_span_m / max(F - 1, 1))[:, None]], axis=1)
    feats[~ok] = 0.0
    picked = [int(np.flatnonzero(ok)[0])]
    dist = np.where(ok, np.linalg.norm(feats - feats[picked[0]], axis=1), -np.inf)
    while len(picked) < min(k, int(ok.sum())):
        nxt = int(np.argmax(dist))
        picked.append(nxt)
        dist = np.minimum(dist, np.where(ok, np.linalg.norm(feats - feats[nxt], axis=1), -np.inf))
    return sorted(picked)


def _frames(spec: str, n: int, joints: np.ndarray) -> list[int]:
    try:
        if "," in spec:
            idx = [int(s) for s in spec.split(",") if s.strip()]
        else:
            k = int(spec)
            if not 1 <= k <= MAX_FRAMES:
                raise UserError(f"--frames {spec}: a count of 1-{MAX_FRAMES} frames (one frame by index: '{spec},')")
            idx = spread_frames(joints, k)
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
    solve = load_solve(pred_path, Path(args.session) if args.session else None, args.markers,
                       Path(args.gt) if args.gt else None, args.up_axis)
    info = render_sheet(solve, out, args.frames, (tw, th))
    text = f"wrote {out} ({info['width']}x{info['height']}, frames {', '.join(map(str, info['frames']))})"
    if args.video:
        if args.stride < 1:
            raise UserError(f"--stride {args.stride}: give 1 or more")
        import sys

        from tqdm import tqdm

        video = Path(args.video)
        if video.suffix.lower() != ".mp4":
            raise UserError(f"--video {video}: the video is an .mp4")
        n = len(range(0, solve.n, args.stride))
        with tqdm(total=n, desc="render video", unit="frame", file=sys.stderr, disable=args.json, leave=False) as bar:
            info["video"] = render_solve_video(solve, video, args.stride, progress=bar.update)
        text += f"\nwrote {video} ({n} frames at {info['video']['fps']:g} fps)"
    emit(args, info, text)
    return 0


@dataclass
class Solve:
    """A solved OUT.npz with what it is drawn against."""

    path: Path
    pred: dict
    model: object
    poses: np.ndarray  # (F, 72)
    trans: np.ndarray  # (F, 3)
    joints: np.ndarray  # (F, 24, 3)
    betas: np.ndarray  # (B,) or (F, B)
    up_axis: str
    rate_hz: float
    markers: np.ndarray | None = None  # (F, M, 3), NaN where unseen, aligned to the solve's frames
    gt_joints: np.ndarray | None = None  # (F, 24, 3)
    gt_name: str = ""

    @property
    def n(self) -> int:
        return self.poses.shape[0]

    @property
    def labels(self):
        """(faces (M,), bary (M, 3), parts [M]) when the solve's labels match the markers, else Nones."""
        p = self.pred
        if self.markers is None or "marker_faces" not in p or len(p["marker_faces"]) != self.markers.shape[1]:
            return None, None, None
        faces = np.asarray(p["marker_faces"], np.int64)
        return faces, np.asarray(p["marker_bary"], np.float64), [str(x) for x in p.get("marker_parts", [""] * len(faces))]

    def frame_errors(self, idx) -> np.ndarray | None:
        """(K,) MPJPE mm of frames ``idx`` against the reference, or None without one."""
        from uuomocap.solver_core.metrics import joint_errors

        if self.gt_joints is None:
            return None
        return joint_errors(self.joints[idx], self.gt_joints[idx]).mean(axis=1)

    def captions(self, idx) -> list[str]:
        err = self.frame_errors(idx)
        return [f"frame {f}" + (f"  {f / self.rate_hz:.2f} s" if np.isfinite(self.rate_hz) else "")
                + (f"  {err[i]:.0f} mm" if err is not None else "") for i, f in enumerate(idx)]


def load_solve(pred_path: Path, session: Path | None = None, markers_file: str | None = None, gt_path: Path | None = None,
               up_axis: str | None = None) -> Solve:
    """Read and check OUT.npz, its markers (a session's or a file's) and its reference."""
    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import SessionError, load_session, read_npz
    from uuomocap.solver_core.body_model import load_body_model

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
    name = str(pred["body_model"]) if "body_model" in pred else "open-low"
    try:
        model = load_body_model(name)
    except (ValueError, OSError) as exc:
        raise UserError(f"{pred_path}: cannot load body model {name!r} ({exc})") from None
    betas = np.asarray(pred["frame_betas"] if "frame_betas" in pred else pred["betas"], np.float64)
    if betas.ndim == 2 and betas.shape[0] != n:
        raise UserError(f"{pred_path}: frame_betas {betas.shape} must have a row per frame ({n})")
    markers = None
    if md is not None:
        rows = _align(pred.get("stamps_ns"), md, n)
        markers = np.where(md.visible[rows][..., None], md.positions[rows], np.nan)
    gt_joints = None
    if gt_path is not None:
        if not gt_path.is_file():
            raise UserError(f"{gt_path}: file not found")
        gt_joints = np.asarray(read_npz(gt_path)["joints"], np.float64)
        if gt_joints.shape != joints.shape:
            raise UserError(f"{gt_path}: joints {gt_joints.shape} do not match the solve's {joints.shape}")
    rate = float(pred["mocap_framerate"]) if "mocap_framerate" in pred else float("nan")
    return Solve(pred_path, pred, model, poses, trans, joints, betas, up_axis, rate, markers, gt_joints,
                 gt_path.name if gt_path is not None else "")


def _check_finite(solve: Solve, idx) -> None:
    b = solve.betas[idx] if solve.betas.ndim == 2 else solve.betas
    if not (np.isfinite(solve.poses[idx]).all() and np.isfinite(solve.trans[idx]).all() and np.isfinite(b).all()):
        raise UserError(f"{solve.path}: the chosen frames hold NaN or inf (unsolved frames); pick others with --frames")


def render_sheet(solve: Solve, out: Path, frames_spec: str = "6", tile: tuple[int, int] = (240, 320)) -> dict:
    """Write the contact sheet of ``solve`` to ``out`` (PNG); returns what was drawn."""
    import cv2

    from uuomocap.render import contact_sheet, marker_surface_points
    from uuomocap.solver_core.metrics import posed_vertices

    frames = _frames(frames_spec, solve.n, solve.joints)
    if out.suffix.lower() != ".png":
        raise UserError(f"--out {out}: the contact sheet is a .png")
    sel = np.asarray(frames)
    _check_finite(solve, sel)
    vertices = posed_vertices(solve.model, solve.betas[sel] if solve.betas.ndim == 2 else solve.betas,
                              solve.poses[sel], solve.trans[sel])  # (K, N, 3): the drawn frames only
    faces, bary, parts = solve.labels
    markers = solve.markers[sel] if solve.markers is not None else None
    points, labelled = None, 0
    if faces is not None:
        labelled = int((faces >= 0).sum())
        points = marker_surface_points(solve.model, vertices, faces, bary)  # (K, M, 3)
    err = solve.frame_errors(sel)
    method = str(solve.pred["method"]) if "method" in solve.pred else "?"
    title = f"{solve.path.name}: {method}, {solve.n} frames" + (f", {markers.shape[1]} markers ({labelled} labelled)" if markers is not None else "")
    if err is not None:
        title += f"; these frames' MPJPE {err.mean():.1f} mm against {solve.gt_name}"
    sheet = contact_sheet(solve.model, vertices, solve.joints[sel], solve.poses[sel, :3], solve.up_axis, markers, points, parts,
                          solve.gt_joints[sel] if solve.gt_joints is not None else None, solve.captions(sel), tile, title)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise UserError(f"{out}: could not write the image")
    return {"png": str(out), "frames": frames, "width": int(sheet.shape[1]), "height": int(sheet.shape[0]),
            "markers": int(markers.shape[1]) if markers is not None else 0, "labelled": labelled,
            "frame_mpjpe_mm": [round(float(e), 2) for e in err] if err is not None else None}


def render_solve_video(solve: Solve, out: Path, stride: int = 1, size: tuple[int, int] = (640, 480), progress=None) -> dict:
    """Every ``stride``-th frame of ``solve`` as an mp4 from one fixed camera (``render.solve_video``)."""
    from uuomocap.render import solve_video

    idx = np.arange(0, solve.n, stride)
    _check_finite(solve, idx)
    faces, bary, parts = solve.labels
    fps = solve.rate_hz / stride if np.isfinite(solve.rate_hz) else 30.0
    out.parent.mkdir(parents=True, exist_ok=True)
    info = solve_video(solve.model, solve.betas, solve.poses, solve.trans, solve.joints, out, fps, solve.up_axis, solve.markers,
                       faces, bary, parts, solve.gt_joints, dict(zip(idx.tolist(), solve.captions(idx))), size, idx, progress)
    return {"mp4": str(out), **info}


def session_sheet(pred_path: Path, session: Path, out: Path | None = None) -> dict:
    """The default contact sheet of a solve of ``session`` (beside OUT.npz unless ``out``): ``make demo``'s."""
    return render_sheet(load_solve(pred_path, session), out or pred_path.with_suffix(".png"))
