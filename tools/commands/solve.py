"""``uuomocap solve``: offline solve of a whole session (or loose marker + prior/video files) -> OUT.npz."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_json_flag, add_threads_flag, emit, solo_thread_count, torch_threads

SOLVER_METHODS = ("uuo", "uuo-window", "uuo-paper", "video-rr", "no-mht", "markers-only", "oracle-labeled", "uuo-matching", "uuo-stage2",
                  "uuo-stage4")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "solve",
        help="solve unlabeled markers (+ video prior) offline into body poses and marker labels (OUT.npz)",
        description=(
            "Solve a whole capture at once with the paper's staged method (Milef et al. 2024): marker "
            "segmentation, marker-part matching (full or partial body, decided automatically), yaw "
            "hypotheses through pose fitting / marker-surface correspondence / inverse kinematics, and a "
            "refinement round. Input: a session directory (markers.c3d + prior.npz or video.mp4), or "
            "--markers FILE (.c3d/.trc) with --prior prior.npz or --video FILE (runs the video estimator). "
            "Output OUT.npz (AMASS layout, capture world frame, one frame per marker frame): betas, poses "
            "(F,72), trans, joints, and per marker its body part (marker_parts), face and barycentric "
            "coordinates. Prints the decisions and per-stage seconds. Other --method values run the "
            "paper's baselines and ablations on the same input."
        ),
    )
    parser.add_argument("session", nargs="?", type=Path, help="session directory (omit with --markers)")
    parser.add_argument("--markers", type=Path, help="marker file (.c3d or .trc) instead of a session")
    parser.add_argument("--prior", type=Path, help="prior.npz (video prior) to use")
    parser.add_argument("--video", type=Path, help="run the video estimator on this video to get the prior")
    parser.add_argument("--clock-offset", type=_clock_offset, default=None, metavar="SECONDS|auto",
                        help="marker_time = video_time + offset, seconds (default: the session's, else 0). 'auto' finds "
                             "it from the motion: how fast the body articulates, in the markers and in the video prior, "
                             "correlated over every offset; used when the peak is clear, otherwise the default stays "
                             "and the reason is printed (motion that repeats, e.g. steady gait, is ambiguous)")
    parser.add_argument("--sync-plot", type=Path, metavar="PNG",
                        help="with --clock-offset auto: draw the two motion signals aligned at the offset used, the "
                             "correlation at every offset and the body fit around its peaks, to check the offset by eye")
    parser.add_argument("--write-offset", action="store_true",
                        help="record the clock offset this solve used (e.g. the one --clock-offset auto found) in "
                             "SESSION/session.yaml, so replays through the graph and --method uuo-window use it too; "
                             "an unclear auto result writes nothing")
    parser.add_argument("--up-axis", choices=("+x", "-x", "+y", "-y", "+z", "-z"), default=None,
                        help="override the marker file's up axis")
    parser.add_argument("--out", type=Path, required=True, help="output OUT.npz")
    parser.add_argument("--method", default="uuo", choices=SOLVER_METHODS,
                        help="uuo (default) | uuo-window (the near-online solver replayed frame by frame: what the live "
                             "graph records; session directories only) | uuo-paper (as published) | video-rr | no-mht | markers-only | "
                             "oracle-labeled (needs gt.npz) | uuo-matching / uuo-stage2 / uuo-stage4 (stage ablation)")
    parser.add_argument("--body-model", default=None,
                        help="open-low, open-full or an SMPL .pkl/.npz (default: the session's, else open-low)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    add_threads_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(func=_run)


class _TqdmProgress:
    """One tqdm bar per solver stage (iterations and loss), on stderr."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.bar = None

    def stage_start(self, name: str, detail: str = "") -> None:
        if self.quiet:
            return
        from tqdm import tqdm

        self.bar = tqdm(desc=f"{name}{' (' + detail + ')' if detail else ''}", unit="it", file=sys.stderr, leave=False)

    def stage_step(self, name: str, iterations: int, loss: float) -> None:
        if self.bar is not None:
            self.bar.update(max(0, iterations - self.bar.n))
            self.bar.set_postfix(loss=f"{loss:.4g}")

    def stage_end(self, name: str, seconds: float) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        if not self.quiet:
            print(f"  {name}: {seconds:.2f} s", file=sys.stderr)


def _estimate_video_prior(video: Path, body_model: str) -> dict:
    try:
        from uuomocap.video_prior_run import estimate_prior, parse_estimator
    except ImportError as exc:
        raise UserError(f"the video estimator is not available in this installation ({exc})") from None
    from tqdm import tqdm

    if not video.is_file():
        raise UserError(f"video not found: {video}")
    try:
        prior, _ = estimate_prior(str(video), parse_estimator("blazepose"), body_model=body_model,
                                  progress=lambda total: tqdm(total=total, unit="frame", desc="video prior", file=sys.stderr, leave=False),
                                  log=lambda msg: print(msg, file=sys.stderr))
    except Exception as exc:  # the estimator's own errors are user-facing (missing models, bad video)
        raise UserError(f"video estimator failed on {video}: {' '.join(str(exc).split())}") from None
    if not prior.valid.any():
        raise UserError(f"no person found in any frame of {video}")
    return prior.to_arrays()


def _clock_offset(text: str):
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or 'auto', got {text!r}") from None


def _auto_clock_offset(md, prior_arrays: dict, body_model: str, recorded_s: float, up_axis: str,
                       plot: Path | None = None) -> tuple[float, dict]:
    """The video->marker offset from the motion (``solver_core.clock_sync``); the recorded one when unclear."""
    from uuomocap.solver_core.body_model import load_solver_models
    from uuomocap.solver_core.clock_sync import estimate_session_clock_offset
    from uuomocap.solver_core.prior_preparation import prior_from_npz_arrays

    model_name = str(prior_arrays.get("body_model", body_model))
    prior = prior_from_npz_arrays(prior_arrays)
    try:
        # the low-resolution model: the refinement registers its every vertex, as video-rr does
        _, model = load_solver_models(model_name if model_name in ("open-low", "open-full") else body_model)
        est = estimate_session_clock_offset(model, md.positions, md.visible, md.stamps_ns, prior, centre_s=recorded_s, up_axis=up_axis)
    except ValueError as exc:
        print(f"clock offset: auto failed ({exc}); keeping {recorded_s:+.3f} s", file=sys.stderr)
        return recorded_s, {"error": str(exc), "used_s": recorded_s}
    used = est.offset_s if est.reliable else recorded_s
    print(f"clock offset: auto {est.summary()}; " + ("using it" if est.reliable else f"keeping {recorded_s:+.3f} s"), file=sys.stderr)
    if plot is not None:
        from uuomocap.solver_core.clock_sync import session_correlation_curve
        from uuomocap.sync_plot import write_sync_plot

        curve = session_correlation_curve(model, md.positions, md.visible, md.stamps_ns, prior, centre_s=recorded_s)
        print(f"clock offset: plot written to {write_sync_plot(plot, curve, est, used, recorded_s)}", file=sys.stderr)
    return used, {**est.to_dict(), "used_s": used}


def _write_offset(args, offset: float, clock_sync: dict | None) -> None:
    from uuomocap.protocol.session import SessionError, set_session_clock_offset

    if args.session is None:
        raise UserError("--write-offset records the offset in a session's session.yaml: give a SESSION directory")
    if clock_sync is not None and not clock_sync.get("reliable"):
        print("clock offset: not written (auto found no clear offset)", file=sys.stderr)
        return
    note = "" if clock_sync is None else (f"uuomocap solve --clock-offset auto: motion correlation {clock_sync['correlation']:.2f}"
                                          + (f", registered body fit {clock_sync['fit_rms_mm']:.1f} mm" if clock_sync.get("fit_rms_mm") else ""))
    try:
        path = set_session_clock_offset(args.session, offset, note)
    except SessionError as exc:
        raise UserError(str(exc)) from None
    print(f"clock offset {offset:+.3f} s written to {path}", file=sys.stderr)


def _read_prior(path: Path) -> dict:
    from uuomocap.protocol.prior_file import PriorFileError, read_prior_npz

    if not path.is_file():
        raise UserError(f"prior not found: {path}")
    try:
        return read_prior_npz(path)
    except (PriorFileError, ValueError, OSError) as exc:
        raise UserError(f"{path}: {exc}") from None


def build_inputs(args):
    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import SessionError, load_session
    from uuomocap.solver_methods import SolverInputs, prior_for_markers

    if (args.session is None) == (args.markers is None):
        raise UserError("give either a SESSION directory or --markers FILE (not both)")
    if args.prior is not None and args.video is not None:
        raise UserError("give --prior or --video, not both")
    gt = None
    if args.session is not None:
        try:
            s = load_session(args.session, load_prior=args.prior is None and args.video is None, load_gt=args.method == "oracle-labeled")
        except SessionError as exc:
            raise UserError(str(exc)) from None
        md, up, offset, body_model, gt = s.markers, s.up_axis, s.clock_offset_s, s.body_model, s.gt
        prior_arrays = s.prior
        if args.prior is not None:
            prior_arrays = _read_prior(args.prior)
        elif args.video is not None or (prior_arrays is None and s.video_file is not None and args.method != "markers-only"):
            prior_arrays = _estimate_video_prior(args.video or s.video_file, args.body_model or body_model)
        source = str(args.session)
    else:
        try:
            md = read_markers(args.markers)
        except MarkerFileError as exc:
            raise UserError(str(exc)) from None
        up, offset, body_model = md.up_axis, 0.0, "open-low"
        prior_arrays = None
        if args.prior is not None:
            prior_arrays = _read_prior(args.prior)
        elif args.video is not None:
            prior_arrays = _estimate_video_prior(args.video, args.body_model or body_model)
        source = str(args.markers)
    if args.up_axis:
        up = args.up_axis
    body_model = args.body_model or body_model
    clock_sync = None
    if args.clock_offset == "auto":
        if prior_arrays is None:
            raise UserError("--clock-offset auto needs a video prior (a session's prior.npz, --prior or --video)")
        offset, clock_sync = _auto_clock_offset(md, prior_arrays, body_model, offset, up, args.sync_plot)
    elif args.clock_offset is not None:
        offset = float(args.clock_offset)
    if args.sync_plot is not None and args.clock_offset != "auto":
        raise UserError("--sync-plot draws what --clock-offset auto found: add --clock-offset auto")
    if args.write_offset:
        _write_offset(args, offset, clock_sync)
    prior = shape = None
    if prior_arrays is not None and args.method != "markers-only":
        try:
            prior, shape = prior_for_markers(prior_arrays, up, md.stamps_ns, offset)
        except ValueError as exc:
            raise UserError(f"prior: {exc}") from None
    if prior is None and args.method not in ("markers-only", "oracle-labeled"):
        raise UserError(f"method {args.method!r} needs a video prior: give --prior prior.npz or --video FILE "
                        "(or use --method markers-only)")
    if args.method == "oracle-labeled" and (gt is None or "marker_faces" not in gt):
        raise UserError("--method oracle-labeled needs a session with gt.npz (true marker attachments)")
    markers = np.asarray(md.positions, dtype=np.float64)
    if md.n_frames < 3 or not np.isfinite(markers).any():
        raise UserError(f"{source}: too few frames or no visible marker to solve")
    return SolverInputs(markers, np.asarray(md.visible, bool), float(md.rate_hz), np.asarray(md.stamps_ns, np.int64), up, prior,
                        shape, body_model, gt, source, clock_sync)


def _run(args) -> int:
    from uuomocap.methods import get_method
    from uuomocap.solver_core.body_model import BodyModelError

    import uuomocap.solver_methods  # noqa: F401  (registers the methods)

    if args.method == "uuo-window":
        # the windowed solver replays the session's own streams (markers + prior at their clocks)
        if args.session is None or args.prior is not None or args.video is not None or args.up_axis or args.clock_offset is not None:
            raise UserError("--method uuo-window solves a session directory as recorded (markers.c3d + prior.npz); "
                            "--markers / --prior / --video / --up-axis / --clock-offset are offline-only")
        from uuomocap.protocol.session import SessionError, load_session

        try:
            has_prior = load_session(args.session, load_prior=True).prior is not None
        except SessionError as exc:
            raise UserError(str(exc)) from None
        if not has_prior:
            raise UserError(f"{args.session}: --method uuo-window needs the session's prior.npz (make one with `uuomocap prior`)")
        import uuomocap.window_methods  # noqa: F401  (registers uuo-window)
    inputs = build_inputs(args)
    if args.out.suffix != ".npz":
        raise UserError(f"--out must end in .npz, got {args.out}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # uuo-window replays the live solver node, which runs on one thread beside the graph's other nodes
    threads = 1 if args.method == "uuo-window" else solo_thread_count(args.threads)
    t0 = time.perf_counter()
    try:
        # an offline solve has the machine to itself: two threads on the 2-core CPU take the
        # 450-frame, 40-marker session from 91 to 59 s (the live graph's nodes keep one each)
        with torch_threads(threads):
            info = get_method(args.method)(args.session, args.out, inputs.body_model, progress=_TqdmProgress(args.quiet), inputs=inputs)
    except BodyModelError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:
        raise UserError(" ".join(str(exc).split())) from None
    info["seconds"] = round(time.perf_counter() - t0, 3)
    if inputs.clock_sync is not None:
        info["clock_sync"] = inputs.clock_sync
    info["threads"] = threads
    info["out"] = str(args.out)
    info["frames"], info["markers"] = int(inputs.markers.shape[0]), int(inputs.markers.shape[1])
    emit(args, info, _summary(info, args.method))
    return 0


def _summary(info: dict, method: str) -> str:
    lines = [f"wrote {info['out']}: {info['frames']} frames, {info['markers']} markers, method {method}, {info['seconds']:.1f} s "
             f"({info['threads']} thread{'s' if info['threads'] != 1 else ''})"]
    if "full_body" in info:
        kind = "full body" if info["full_body"] else "partial body: " + ", ".join(info.get("part_joints", []))
        lines.append(f"markers cover: {kind} (marker/body box volume {info.get('volume_ratio', float('nan')):.2f}; "
                     f"{info.get('clusters', '?')} rigid marker groups)")
    if "chosen_yaw_deg" in info:
        hyp = ", ".join(f"{h['stage2_yaw_deg']:.0f} deg: " + ("the only one" if h["marker_fit_mm"] is None else f"{h['marker_fit_mm']:.1f} mm")
                        for h in info.get("hypotheses", []))
        lines.append(f"yaw: {info['chosen_yaw_deg']:.1f} deg (hypotheses {hyp})")
    if "stage5_marker_fit_mm" in info:
        lines.append(f"mean marker fit: {info['stage5_marker_fit_mm']:.1f} mm")
    if "track_stitching" in info:
        ts = info["track_stitching"]
        if ts["kept"]:
            lines.append(f"track stitching: {ts['columns']} columns are {ts['markers']} markers on the first solve's body; "
                         f"solved again on the joined columns (marker fit {ts['first_pass_marker_fit_mm']:.1f} mm before)")
        else:
            lines.append(f"track stitching: {ts['columns']} columns are {ts['markers']} markers, but the joined columns' solve "
                         f"fitted worse ({ts['joined_marker_fit_mm']:.1f} mm); the first solve is kept")
    secs = info.get("stage_seconds") or {}
    if method == "uuo-window":
        from uuomocap.solver_core.windowed_solver import bootstrap_starts_summary

        starts = bootstrap_starts_summary(info)
        lines.append(f"bootstrap {secs.get('bootstrap', float('nan')):.1f} s" + (f" (starts' marker fit {starts})" if starts else "") + "; "
                     f"{info.get('rebootstraps', 0)} re-bootstraps, "
                     f"{info.get('reassigned', 0)} markers re-assigned; lock upgrades ran inline (a live take runs them in the background)")
    elif secs:
        lines.append("seconds per stage: " + ", ".join(f"{k} {v:.2f}" for k, v in secs.items()) + f" (total {sum(secs.values()):.2f})")
    return "\n".join(lines)
