"""``uuomocap sample make DIR`` (generate a session with ground truth) and ``sample check DIR``."""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from uuomocap.commands import UserError, add_json_flag, emit


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"video size must look like 320x240, got {text!r}") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise argparse.ArgumentTypeError("video width and height must be even and >= 16")
    return w, h


def _prob(text: str) -> float:
    v = float(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a probability in [0, 1], got {text}")
    return v


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return v


def _nonneg(text: str) -> float:
    v = float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def config_from_args(args):
    from uuomocap.synth import SampleConfig

    return SampleConfig(
        motion=args.motion, duration_s=args.duration, start_s=args.start, rate_hz=args.rate, seed=args.seed,
        n_markers=args.markers, layout=args.layout, part=args.part, noise_mm=args.noise_mm, occlusion=args.occlusion,
        ghost_rate_hz=args.ghosts, swaps=args.swaps, track_breaks=args.track_breaks, body_model=args.body_model, shape_sigma=args.shape_sigma,
        up_axis=args.up_axis, prior=args.prior, video=args.video, video_size=args.video_size,
        video_rate_hz=args.video_rate, prior_noise_rad=args.prior_noise, prior_shape_noise=args.prior_shape_noise,
        prior_dropout=args.prior_dropout, yaw_offset_deg=args.yaw_offset, clock_offset_s=args.clock_offset,
        sync_error_s=args.sync_error, video_true_rate_hz=args.video_true_rate,
    )


def prepare_session_dir(directory: str, force: bool) -> Path:
    """The directory a new session goes to: it must not exist or be empty, or (with --force) be
    an old session, which is deleted."""
    out = Path(directory)
    if out.exists() and any(out.iterdir()):
        if not force:
            raise UserError(f"{out} exists and is not empty (use --force to replace it)")
        if not (out / "session.yaml").is_file():
            raise UserError(f"{out} is not a session directory; refusing to delete it even with --force")
        shutil.rmtree(out)
    return out


def add_camera_arguments(m) -> None:
    """The video prior / camera / video options a session's simulated video takes."""
    m.add_argument("--prior-noise", type=_nonneg, default=0.15,
                   help="video prior per-joint rotation error, RMS radians (AR(1), tau 0.3 s)")
    m.add_argument("--prior-shape-noise", type=_nonneg, default=0.5, help="video prior shape error (betas std)")
    m.add_argument("--prior-dropout", type=_prob, default=0.01, help="per-frame probability of a tracking loss")
    m.add_argument("--yaw-offset", type=float, default=None,
                   help="camera azimuth = prior yaw offset in degrees (default: uniform over 360)")
    m.add_argument("--clock-offset", type=float, default=0.0, help="marker_time = video_time + offset (s), recorded")
    m.add_argument("--sync-error", type=float, default=0.0, help="extra video time offset NOT recorded (s)")
    m.add_argument("--video-rate", type=_positive, default=30.0, help="nominal video / prior rate (Hz)")
    m.add_argument("--video-true-rate", type=_positive, default=None,
                   help="actual video rate when it differs from the nominal one (e.g. 29.97)")
    m.add_argument("--video-size", type=_size, default=(320, 240), help="WxH of the rendered video")
    m.add_argument("--video", action=argparse.BooleanOptionalAction, default=True, help="render video.mp4")
    m.add_argument("--prior", action=argparse.BooleanOptionalAction, default=True, help="write prior.npz")


def _make(args) -> int:
    from tqdm import tqdm

    from uuomocap.synth import make_session

    out = prepare_session_dir(args.dir, args.force)
    cfg = config_from_args(args)
    stages = ["motion", "markers", "camera", "prior", "video", "write"]
    bar = tqdm(total=len(stages), desc="sample", unit="stage", file=sys.stderr, disable=args.quiet, leave=False)
    seen: list[str] = []

    def progress(name: str) -> None:
        if seen:
            bar.update(1)
        seen.append(name)
        bar.set_postfix_str(name)

    t0 = time.perf_counter()
    try:
        info = make_session(out, cfg, progress=progress)
    except (ValueError, OSError) as exc:
        raise UserError(str(exc)) from None
    finally:
        bar.close()
    info["seconds"] = round(time.perf_counter() - t0, 2)
    text = (f"wrote {info['session']}: {info['frames']} frames @ {info['rate_hz']} Hz, {info['real_markers']} markers"
            f"{' + ' + str(info['ghost_tracks']) + ' ghost tracks' if info['ghost_tracks'] else ''}"
            f" ({100 * info['missing_fraction']:.1f}% missing), motion {info['motion']}"
            f"{', part ' + info['part'] if info['part'] else ''}, prior {info['prior_frames']} frames, "
            f"video {info['video'] or 'none'}, yaw offset {info['yaw_offset_deg']:.1f} deg, {info['seconds']} s")
    emit(args, info, text)
    return 0


def _check(args) -> int:
    from uuomocap.protocol.session import SessionError, load_session

    try:
        s = load_session(args.dir)
    except SessionError as exc:
        raise UserError(str(exc)) from None
    info = s.summary()
    lines = [f"{k}: {v}" for k, v in info.items() if k not in ("provenance", "warnings")]
    lines += [f"warning: {w}" for w in info["warnings"]]
    emit(args, info, "\n".join(lines))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("sample", help="generate synthetic sessions with ground truth",
                              description="Synthetic sessions with ground truth: `sample make DIR`, `sample check DIR`, "
                                          "`sample motion-from-markers FILE --out motion.npz` (a real labeled capture as a motion), "
                                          "`sample from-capture FILE DIR` (a real labeled capture's markers, unlabeled, "
                                          "against its labelled fit).")
    sub = p.add_subparsers(dest="sample_cmd", metavar="CMD")
    p.set_defaults(func=lambda a: (p.print_help(sys.stderr), 2)[1])

    m = sub.add_parser(
        "make",
        help="write a session directory (markers.c3d, prior.npz, video.mp4, gt.npz, session.yaml)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description=(
            "Generate a session with known ground truth.  Markers are unlabeled and shuffled, placed on the "
            "body surface 9.5 mm off the skin (random area-uniform layouts with nested counts per seed, a "
            "partial-body part, or a 39-marker anatomical layout), with optional noise, occlusion, ghosts "
            "and swaps.  The video prior simulates a monocular estimator (camera frame, unknown yaw, "
            "correlated pose noise, shape error, dropouts); the video renders the ground truth from the same "
            "unknown camera.  Defaults: 60 Hz markers (studio-like, cheap to solve), 30 Hz video/prior, 8 s.  "
            "The same arguments and seed always give byte-identical files."),
    )
    m.add_argument("dir", help="session directory to create")
    m.add_argument("--motion", default="walk",
                   help="walk, run, squat, arms, turn, jump, or a .bvh / AMASS .npz file")
    m.add_argument("--duration", type=_positive, default=8.0, help="seconds")
    m.add_argument("--start", type=_nonneg, default=0.0, help="start time in a motion file (s)")
    m.add_argument("--rate", type=_positive, default=60.0, help="marker / ground-truth rate (Hz)")
    m.add_argument("--seed", type=int, default=0, help="seed for shape, motion variation, layout, noise, camera")
    m.add_argument("--markers", type=int, default=None,
                   help="marker count (default 40 random; structured: all 39 landmarks)")
    m.add_argument("--layout", choices=("random", "structured"), default="random")
    m.add_argument("--part", choices=("left_arm", "left_leg", "left_shoulder", "right_arm", "right_leg", "right_shoulder"),
                   default=None, help="put the markers only on this part (partial-body capture)")
    m.add_argument("--noise-mm", type=_nonneg, default=0.5, help="marker position noise sigma (mm)")
    m.add_argument("--occlusion", type=_prob, default=0.0,
                   help="per-frame probability that a marker starts a 10-frame hide (paper: 0, 0.002, 0.01)")
    m.add_argument("--ghosts", type=_nonneg, default=0.0, help="ghost tracks starting per second")
    m.add_argument("--swaps", type=int, default=0, help="identity swaps between nearby tracks")
    m.add_argument("--track-breaks", action="store_true",
                   help="a marker back from an occlusion comes back as a new column, as unlabelled exports write it "
                        "(gt.npz marker_source: the physical marker of each column)")
    m.add_argument("--body-model", default="open-low", help="open-low, open-full, or a SMPL .pkl/.npz path")
    m.add_argument("--shape-sigma", type=_nonneg, default=1.0, help="body shape spread (betas std)")
    m.add_argument("--up-axis", choices=("+z", "+y"), default="+z", help="world up axis")
    add_camera_arguments(m)
    m.add_argument("--force", action="store_true", help="replace an existing session directory")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    add_json_flag(m)
    m.set_defaults(func=_make)

    c = sub.add_parser("check", help="load and validate a session directory, print what it holds",
                       description="Load a session directory with full validation and print a summary.")
    c.add_argument("dir")
    add_json_flag(c)
    c.set_defaults(func=_check)

    from uuomocap.commands.sample_motion import register_from_capture, register_motion_from_markers

    register_motion_from_markers(sub)
    register_from_capture(sub)
