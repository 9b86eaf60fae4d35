"""`uuomocap prior VIDEO --out prior.npz`: the per-frame body prior from a video.

`uuomocap prior fetch-models`: download and convert the default estimator's models once.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from uuomocap.commands import UserError, add_json_flag, emit

FETCH = "fetch-models"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "prior",
        help="estimate the per-frame body prior from a video (or fetch the estimator's models)",
        description=(
            "Estimate a body prior for every video frame: pose (24 joints, axis-angle), shape, root "
            "orientation in the OpenCV camera frame (x right, y down, z forward), validity and confidence, "
            "written as prior.npz (the session layout). Estimators: 'blazepose' (default; MediaPipe "
            "BlazePose GHUM 3D, Apache-2.0, run with onnxruntime, then the body model is fitted to its 3D "
            "landmarks), 'onnx-hmr:MODEL.onnx' (your HMR-class network: input (N,3,256,256) ImageNet-"
            "normalised RGB crop; outputs global_orient, body_pose, betas[, pred_cam] as rotation "
            "matrices, 6D or axis-angle; person boxes from BlazePose) or 'phalp:RESULTS.pkl[#TRACK]' "
            "(import a 4D-Humans/PHALP result; default track: the longest). "
            f"`uuomocap prior {FETCH}` downloads the mediapipe 0.10.21 wheel once (models only, the "
            "package is not installed), checks the models' sha256 and converts them to ONNX in "
            "$UUOMOCAP_CACHE/models (default ~/.cache/uuomocap/models); it runs automatically when needed."
        ),
    )
    parser.add_argument("video", help=f"video file (.mp4, .avi, ...), or the word '{FETCH}'")
    parser.add_argument("--out", type=Path, help="output prior.npz (required unless fetching models)")
    parser.add_argument("--estimator", default="blazepose",
                        help="blazepose | onnx-hmr:MODEL.onnx | phalp:RESULTS.pkl[#TRACK] (default: blazepose)")
    parser.add_argument("--body-model", default="open-low",
                        help="body model fitted to the BlazePose landmarks: open-low, open-full or an SMPL file "
                             "(default: open-low)")
    parser.add_argument("--rate", type=float, default=None,
                        help="video frame rate in Hz when the container's is wrong (29.97 is kept exact)")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--wheel", type=Path, default=None,
                        help=f"with {FETCH}: take the models from this local mediapipe 0.10.21 wheel (offline)")
    parser.add_argument("--force", action="store_true", help=f"with {FETCH}: fetch and convert again")
    add_json_flag(parser)
    parser.set_defaults(func=_run)


def _run(args) -> int:
    if args.video == FETCH:
        return _fetch(args)
    return _estimate(args)


def _fetch(args) -> int:
    from uuomocap.model_fetch import ModelFetchError, cache_dir, fetch_pose_models

    try:
        manifest = fetch_pose_models(wheel=args.wheel, force=args.force)
    except ModelFetchError as exc:
        raise UserError(str(exc)) from None
    except Exception as exc:
        raise UserError(f"could not convert the pose models ({type(exc).__name__}: {exc})") from None
    data = {"directory": str(cache_dir()), **manifest}
    text = f"pose models ready in {cache_dir()} (from {manifest['source_wheel']})"
    emit(args, data, text)
    return 0


def _progress(total):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="prior", file=sys.stderr, leave=False)


def _estimate(args) -> int:
    from uuomocap.model_fetch import ModelFetchError
    from uuomocap.protocol.prior_file import write_prior_npz
    from uuomocap.protocol.video import VideoError
    from uuomocap.solver_core.body_model import BodyModelError
    from uuomocap.solver_core.phalp_import import PhalpFormatError
    from uuomocap.video_prior_run import estimate_prior, parse_estimator

    if args.out is None:
        raise UserError("--out PRIOR.npz is required")
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError("--max-frames must be at least 1")
    try:
        spec = parse_estimator(args.estimator)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if spec.path is not None and not spec.path.is_file():
        raise UserError(f"{spec.kind} file not found: {spec.path}")
    try:
        prior, info = estimate_prior(args.video, spec, body_model=args.body_model, max_frames=args.max_frames,
                                     rate_hz=args.rate, progress=_progress,
                                     log=lambda msg: print(msg, file=sys.stderr))
    except (VideoError, ModelFetchError, BodyModelError, PhalpFormatError, ValueError) as exc:
        raise UserError(" ".join(str(exc).split())) from None
    if not prior.valid.any():
        raise UserError(f"no person found in any of the {len(prior.valid)} frames of {args.video}")
    write_prior_npz(args.out, prior.to_arrays())
    info["out"] = str(args.out)
    lines = [f"wrote {args.out}: {len(prior.valid)} frames at {prior.rate_hz:.3f} Hz, person in "
             f"{int(prior.valid.sum())} ({100 * prior.valid.mean():.1f} %), estimator {prior.estimator}"]
    if "ms_per_frame" in info:
        lines.append(f"estimator: {info['ms_per_frame']:.1f} ms/frame (median {info['ms_per_frame_median']:.1f}), "
                     f"decoding {info['decode_ms_per_frame']:.1f} ms/frame, detector runs {info['detector_runs']}")
    if "fit_seconds" in info:
        lines.append(f"body-model fit: {info['fit_seconds']:.1f} s, median joint-landmark residual "
                     f"{info['fit_residual_mm_median']:.0f} mm")
    sym = info.get("bone_symmetry") or {}
    if sym:
        worst = max(sym.values(), key=lambda v: v["rel_diff"] if not math.isnan(v["rel_diff"]) else -1)
        lines.append("left/right bone lengths: " + ", ".join(
            f"{k} {v['left'] * 100:.1f}/{v['right'] * 100:.1f} cm" for k, v in sym.items())
            + f" (worst difference {100 * worst['rel_diff']:.1f} %)")
    if "warning" in info:
        lines.append(f"warning: {info['warning']}")
    emit(args, info, "\n".join(lines))
    return 0
