"""``uuomocap export OUT.npz --out body.bvh|joints.trc|joints.c3d|poses_tpose.npz``: a solve for the tools
animators and labs already use - the skeleton as BVH, the joint centres as a marker file, or the poses as
rotations of a T-pose body (SMPL's rest, what AMASS tools expect)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit

UNITS_M = {"cm": 0.01, "m": 1.0, "mm": 0.001}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="write a solve as BVH (skeleton + motion) or its joint centres as TRC/C3D",
        description=(
            "Write a solved OUT.npz for other tools.  .bvh: the body model's 24-joint skeleton with the "
            "solved shape's bone lengths, in its T-pose rest, Y up (the BVH convention: a Z-up capture is "
            "turned), Mixamo/MotionBuilder joint names (Hips, LeftUpLeg, ...), Z-X-Y Euler channels, one "
            "frame per solved frame (the common form: one 6-channel ROOT, 3 rotation channels per joint, End "
            "Sites; Blender 4.2's own BVH importer, scale 0.01 and default axes, puts its bone heads on the "
            "solve's joints to 0.001 mm).  .trc / .c3d: the 24 joint centres per frame as "
            "virtual markers in the capture's world (a TRC is turned +y up, as OpenSim reads every TRC).  A streamed "
            "solve (frame_betas) is written with its last shape's bones: frames solved under an earlier "
            "lock's shape and never revised move by that shape change.  Frames the solve left empty (NaN) are "
            "gaps in a TRC/C3D and hold the nearest solved frame in a BVH (counted in the output).  .npz: AMASS "
            "layout (poses (F,72), trans, mocap_framerate) with the poses re-expressed as rotations of a T-pose "
            "body - SMPL's rest.  OUT.npz's own poses rotate the solving model's rest, and the open body model "
            "rests in an A-pose (upper arms 50 degrees down, elbows bent): read as SMPL poses they raise its "
            "arms; these do not (the shape and the joints stay the open model's; unsolved frames stay NaN)."),
    )
    p.add_argument("pred", metavar="OUT.npz", help="solved output (uuomocap solve, or a recording's npz export)")
    p.add_argument("--out", required=True, metavar="FILE", help=".bvh, .trc, .c3d or .npz (T-pose-rest poses)")
    p.add_argument("--session", metavar="DIR", help="the session it was solved from (its up axis)")
    p.add_argument("--markers", metavar="FILE", help="the marker file it was solved from (its up axis)")
    p.add_argument("--up-axis", choices=("+z", "+y"), help="the capture world's up axis (default: the session's / "
                   "marker file's, else +z)")
    p.add_argument("--units", choices=tuple(UNITS_M), default="cm", help="BVH length unit (default cm)")
    add_json_flag(p)
    p.set_defaults(func=_handler)


def _up_axis(args) -> str:
    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import SessionError, load_session

    if args.up_axis:
        return args.up_axis
    try:
        if args.session:
            up = load_session(Path(args.session), load_prior=False, load_gt=False).up_axis
        elif args.markers:
            up = read_markers(args.markers).up_axis
        else:
            return "+z"
    except (SessionError, MarkerFileError) as exc:
        raise UserError(str(exc)) from None
    if up not in ("+z", "+y"):
        raise UserError(f"the capture's up axis is {up}: export writes +z or +y worlds (give --up-axis)")
    return up


def _fill_nearest(valid: np.ndarray) -> np.ndarray:
    """(F,) bool with at least one True -> (F,) index of the nearest valid frame (itself when valid)."""
    frames, idx = np.arange(valid.shape[0]), np.flatnonzero(valid)
    right = idx[np.minimum(np.searchsorted(idx, frames), len(idx) - 1)]
    left = idx[np.maximum(np.searchsorted(idx, frames, side="right") - 1, 0)]
    return np.where(np.abs(frames - left) <= np.abs(right - frames), left, right)


def _handler(args) -> int:
    info, text = run_export(args)
    emit(args, info, text)
    return 0


def run_export(args) -> tuple[dict, str]:
    """The verb without printing: (JSON info, text) - `uuomocap demo` calls it too."""
    from uuomocap.commands.render import load_solve
    from uuomocap.protocol.markerio import write_c3d, write_trc
    from uuomocap.solver_core.bvh import BVH_WRITE_NAMES, body_bvh_text
    from uuomocap.solver_core.marker_sim import rest_vertices
    from uuomocap.solver_core.motions import canonical_to_world

    out = Path(args.out)
    kind = out.suffix.lower()
    if kind not in (".bvh", ".trc", ".c3d", ".npz"):
        raise UserError(f"--out {out}: write a .bvh, .trc, .c3d or .npz")
    if kind == ".npz" and out.resolve() == Path(args.pred).resolve():
        raise UserError(f"--out {out} is the solve itself: choose another name")
    up = _up_axis(args)
    solve = load_solve(Path(args.pred), up_axis=up)
    rate = solve.rate_hz
    if not (np.isfinite(rate) and rate > 0):
        raise UserError(f"{args.pred}: no mocap_framerate - cannot time the frames")
    betas = solve.betas[-1] if solve.betas.ndim == 2 else solve.betas
    solved = np.isfinite(solve.poses).all(1) & np.isfinite(solve.trans).all(1)
    if not solved.any():
        raise UserError(f"{args.pred}: no solved frame (every pose is NaN)")
    names = [solve.model.joint_names[j] for j in range(24)]
    info = {"out": str(out), "frames": solve.n, "rate_hz": rate, "unsolved_frames": int((~solved).sum()), "up_axis": up}
    try:
        if kind == ".npz":
            from uuomocap.protocol.session import write_npz
            from uuomocap.solver_core.motions import poses_to_tpose

            if not np.isfinite(betas).all():
                raise UserError(f"{args.pred}: betas hold NaN/inf")
            write_npz(out, {"poses": poses_to_tpose(np.where(solved[:, None], solve.poses, np.nan), solve.model, betas),
                            "trans": np.where(solved[:, None], solve.trans, np.nan), "mocap_framerate": np.float64(rate),
                            "rest_pose": np.str_("tpose"), "body_model": np.str_(solve.model.name)})
            info.update(rest_pose="tpose")
            text_out = (f"wrote {out}: {solve.n} frames @ {rate:g} Hz, poses as rotations of a T-pose body (SMPL's rest)"
                        + (f" ({info['unsolved_frames']} unsolved frames are NaN)" if info["unsolved_frames"] else ""))
        elif kind == ".bvh":
            if not np.isfinite(betas).all():
                raise UserError(f"{args.pred}: betas hold NaN/inf")
            model = solve.model
            rest = (model.J_regressor.double().numpy() @ rest_vertices(model, betas).double().numpy())[:24]
            near = _fill_nearest(solved)
            hand = {j: 0.08 * (rest[j] - rest[j - 2]) / np.linalg.norm(rest[j] - rest[j - 2]) for j in (22, 23)}
            ends = {15: (0.0, 0.10, 0.0), 10: (0.0, 0.0, 0.06), 11: (0.0, 0.0, 0.06), **hand}
            text = body_bvh_text(model.parents[:24], rest, solve.poses[near], solve.trans[near],
                                 canonical_to_world(up).T, rate, UNITS_M[args.units], BVH_WRITE_NAMES, ends)
            tmp = out.with_name(f".{out.name}.tmp")
            tmp.write_text(text, encoding="ascii")
            tmp.replace(out)
            info.update(joints=24, units=args.units, joint_names=list(BVH_WRITE_NAMES))
            text_out = (f"wrote {out}: 24-joint skeleton, {solve.n} frames @ {rate:g} Hz, {args.units}, Y up"
                        + (f" ({info['unsolved_frames']} unsolved frames hold the nearest solved one)" if info["unsolved_frames"] else ""))
        else:
            joints = np.where(solved[:, None, None], solve.joints, np.nan)
            write = write_c3d if kind == ".c3d" else write_trc
            write(out, joints, rate, labels=names, up_axis=up)
            info.update(joints=24, joint_names=names)
            written_up = up if kind == ".c3d" else "+y"  # TRC: OpenSim's +y (markerio.write_trc turns it)
            info["written_up_axis"] = written_up
            text_out = (f"wrote {out}: 24 joint centres, {solve.n} frames @ {rate:g} Hz, {written_up} up"
                        + (f" (turned from the capture's {up})" if written_up != up else "")
                        + (f" ({info['unsolved_frames']} unsolved frames are gaps)" if info["unsolved_frames"] else ""))
    except OSError as exc:
        raise UserError(f"--out {out}: cannot write ({exc.strerror or exc})") from None
    return info, text_out
