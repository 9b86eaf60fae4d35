"""``uuomocap sample motion-from-markers FILE --out motion.npz``: a labeled capture -> AMASS-style motion;
``uuomocap sample from-capture FILE DIR``: a labeled capture -> a session of its markers, unlabeled.

Labeled IK (``solver_core.labeled_fit``): every label is one fixed body surface point; the body is
fitted to all frames, and the motion is written Z-up like AMASS, so ``sample make --motion`` replays it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit


def _frames(text: str) -> tuple[int | None, int | None]:
    try:
        a, b = text.split(":")
        return (int(a) if a else None, int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames must look like A:B (Python slice of frame indices), got {text!r}") from None


def register_motion_from_markers(sub) -> None:
    p = sub.add_parser(
        "motion-from-markers",
        help="fit the body to a LABELED marker file (.trc/.c3d) and write an AMASS-style motion npz",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description=(
            "Labeled IK: each marker label is one fixed point on the body surface for the whole take.  "
            "Start from label names when they are recognised (ASIS, knee, heel, ...; else from the "
            "markers-only solver), then alternate the per-label surface point (smallest mean distance "
            "over the take) and IK over all frames (markers 9.5 mm off the skin).  Gaps are skipped; "
            "labels never seen are ignored with a warning.  Prints per-frame marker RMS and the "
            "labels with large residuals (likely swaps).  The npz (poses (F,72), trans, betas, "
            "mocap_framerate, Z-up) works as `uuomocap sample make DIR --motion motion.npz`."),
    )
    p.add_argument("file", help="labeled marker file (.trc or .c3d)")
    p.add_argument("--out", required=True, help="motion .npz to write")
    p.add_argument("--body-model", default="open-low", help="open-low, open-full, or a SMPL .pkl/.npz path")
    p.add_argument("--frames", type=_frames, default=(None, None), metavar="A:B", help="only frames A..B-1 (0-based)")
    p.add_argument("--rounds", type=int, default=4, help="surface-point / IK alternations")
    p.add_argument("--no-names", action="store_true", help="do not use label names for the start")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    import torch

    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.session import write_npz
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.labeled_fit import LabeledFitConfig, fit_labeled_markers, motion_arrays, summarise_rms

    torch.set_num_threads(1)  # shared machines: one thread is as fast as two here
    if not str(args.out).endswith(".npz"):
        raise UserError(f"--out must end in .npz, got {args.out}")
    if args.rounds < 1:
        raise UserError("--rounds must be >= 1")
    try:
        md = read_markers(args.file)
    except MarkerFileError as exc:
        raise UserError(str(exc)) from None
    if not md.labelled:
        raise UserError(f"{args.file}: markers are not labeled (placeholder names); use `uuomocap solve` for unlabeled data")
    a, b = args.frames
    sl = slice(a, b)
    pos, vis = md.positions[sl], md.visible[sl]
    if pos.shape[0] < 2:
        raise UserError(f"--frames {a}:{b} selects {pos.shape[0]} frame(s) of {md.n_frames}; need at least 2")
    try:
        model = load_body_model(args.body_model)
    except (OSError, ValueError) as exc:
        raise UserError(str(exc)) from None
    warnings = list(md.warnings)
    t0 = time.perf_counter()
    cfg = LabeledFitConfig(rounds=args.rounds, use_names=not args.no_names)
    try:
        fit = fit_labeled_markers(pos, vis, md.rate_hz, md.up_axis, model, md.labels, config=cfg)
    except ValueError as exc:
        raise UserError(f"{args.file}: {exc}") from None
    seconds = round(time.perf_counter() - t0, 2)
    for k in fit.ignored:
        warnings.append(f"label {md.labels[k]} never seen in the selected frames: ignored")
    arrays = motion_arrays(model, fit, md.up_axis, md.rate_hz, args.body_model, md.labels)
    write_npz(args.out, arrays)
    rms = summarise_rms(fit.frame_rms_m)
    info = {
        "file": str(args.file), "out": str(args.out), "frames": int(pos.shape[0]), "rate_hz": md.rate_hz,
        "labels": md.n_markers, "ignored_labels": [md.labels[k] for k in fit.ignored], "up_axis": md.up_axis,
        "body_model": args.body_model, "start": fit.diagnostics.get("start"), "marker_rms": rms,
        "frame_rms_mm": [None if not np.isfinite(v) else round(1000 * float(v), 2) for v in fit.frame_rms_m],
        "rounds": fit.diagnostics["rounds"], "suspicious_labels": fit.diagnostics["suspicious_labels"],
        "label_residuals": fit.label_residuals, "seconds": seconds, "warnings": warnings,
    }
    worst = sorted(((s.get("rms_mm", 0.0), n) for n, s in fit.label_residuals.items() if s.get("frames")), reverse=True)[:5]
    lines = [f"wrote {args.out}: {info['frames']} frames @ {md.rate_hz} Hz, {md.n_markers} labels "
             f"({len(fit.ignored)} ignored), start from {info['start']}, {seconds} s",
             f"marker fit RMS per frame (mm): mean {rms.get('mean_mm')}, median {rms.get('median_mm')}, "
             f"p95 {rms.get('p95_mm')}, max {rms.get('max_mm')}",
             "worst labels (RMS mm): " + ", ".join(f"{n} {v}" for v, n in worst)]
    if info["suspicious_labels"]:
        lines.append("check these labels (large max residual: swap or mis-track?): " + ", ".join(info["suspicious_labels"]))
    lines += [f"warning: {w}" for w in warnings]
    emit(args, info, "\n".join(lines))
    return 0


def register_from_capture(sub) -> None:
    from uuomocap.commands.sample import add_camera_arguments

    p = sub.add_parser(
        "from-capture",
        help="a session of a real LABELED capture's markers, labels taken away, scored against its labelled fit",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description=(
            "Real markers for the unlabelled solvers: fit the body to the labeled file (as "
            "motion-from-markers) and write a session whose markers are the file's own - Z-up, in a "
            "random column order, placeholder labels - with that fit as gt.npz (the labelled "
            "reference, the paper's MoSh++ role on real data), a simulated video prior of it and a "
            "rendered video (as `sample make`).  Scores against it (`uuomocap solve DIR`, `uuomocap "
            "eval`) are agreement with a labelled solve of the same markers; the reference's own "
            "marker RMS is printed and kept in gt.npz."),
    )
    p.add_argument("file", help="labeled marker file (.trc or .c3d)")
    p.add_argument("dir", help="session directory to create")
    p.add_argument("--frames", type=_frames, default=(None, None), metavar="A:B", help="only frames A..B-1 (0-based)")
    p.add_argument("--seed", type=int, default=0, help="seed for the marker order, camera and prior error")
    p.add_argument("--body-model", default="open-low", help="open-low, open-full, or a SMPL .pkl/.npz path")
    add_camera_arguments(p)
    p.add_argument("--force", action="store_true", help="replace an existing session directory")
    add_json_flag(p)
    p.set_defaults(func=_from_capture)


def _from_capture(args) -> int:
    import torch

    from uuomocap.capture_session import make_capture_session
    from uuomocap.commands.sample import prepare_session_dir
    from uuomocap.protocol.markerio import MarkerFileError
    from uuomocap.synth import SampleConfig

    torch.set_num_threads(1)
    out = prepare_session_dir(args.dir, args.force)
    cfg = SampleConfig(motion=str(args.file), seed=args.seed, body_model=args.body_model, prior=args.prior, video=args.video,
                       video_size=args.video_size, video_rate_hz=args.video_rate, prior_noise_rad=args.prior_noise,
                       prior_shape_noise=args.prior_shape_noise, prior_dropout=args.prior_dropout,
                       yaw_offset_deg=args.yaw_offset, clock_offset_s=args.clock_offset, sync_error_s=args.sync_error,
                       video_true_rate_hz=args.video_true_rate)
    t0 = time.perf_counter()
    try:
        info = make_capture_session(args.file, out, cfg, frames=args.frames)
    except (MarkerFileError, ValueError, OSError) as exc:
        raise UserError(str(exc)) from None
    info["seconds"] = round(time.perf_counter() - t0, 2)
    rms = info["reference_rms"]
    a, b = info["capture_frames"]
    lines = [f"wrote {info['session']}: {info['frames']} frames (the file's {a}:{b}) @ {info['rate_hz']} Hz, {info['markers']} real markers "
             f"({100 * info['missing_fraction']:.1f}% missing) from {info['capture']}, prior {info['prior_frames']} frames, "
             f"video {info['video'] or 'none'}, yaw offset {info['yaw_offset_deg']:.1f} deg, {info['seconds']} s",
             f"reference (labelled fit) marker RMS per frame (mm): mean {rms.get('mean_mm')}, median {rms.get('median_mm')}, "
             f"p95 {rms.get('p95_mm')}, max {rms.get('max_mm')}"]
    if info["ignored_labels"]:
        lines.append("labels never seen, left out: " + ", ".join(info["ignored_labels"]))
    if info["reference_suspicious_labels"]:
        lines.append("labels the reference fits badly (skin motion, swaps?): " + ", ".join(info["reference_suspicious_labels"]))
    emit(args, info, "\n".join(lines))
    return 0
