"""``uuomocap bench sync``: how well ``solve --clock-offset auto`` finds a video's clock offset.

Sessions are generated whose video really starts ``--sync-errors`` seconds off what their
session.yaml says (``sample make --sync-error``; with ``--captures``, real labelled marker files
through ``sample from-capture``), and the offset is found from the motion alone
(``solver_core.clock_sync``: the correlation of the body's articulation speed in the markers and in
the simulated video prior, refined by the registered prior body's marker fit).  Printed per motion:
how many offsets were found and used (right: within ``--tolerance``), used but wrong, and not used
(ambiguous: the motion repeats; weak: too little motion; flat: the body fits about as well at other
offsets), with the errors of the correlation's peak
and of the refined offset.  The generator's procedural motions repeat exactly, so they are expected
to be flagged, not found: give a recorded motion (``--motions take.bvh``) to measure the finding.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, bench_progress, emit_bench


def register_bench(subparsers) -> None:
    import argparse

    p = subparsers.add_parser("sync", help="finding a video's clock offset from the motion (solve --clock-offset auto)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--motions", default="walk,jump,arms,run,squat,turn",
                   help="procedural motions and/or .bvh / AMASS .npz files, comma-separated (default: the six procedural)")
    p.add_argument("--captures", default="", help="real labelled marker files (.c3d/.trc), comma-separated, as `sample from-capture`")
    p.add_argument("--sync-errors", default="-2.0,-0.4,0.7,1.3,3.0", help="seconds the video really starts off the recorded offset")
    p.add_argument("--seeds", type=int, default=3, help="seeds per motion and sync error (default 3)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds per generated session (default 8)")
    p.add_argument("--video", action="store_true",
                   help="render each session's video and sync BlazePose's prior from it instead of the simulated prior "
                        "(the estimator a user runs on a phone video; ~20 s more per session)")
    p.add_argument("--tolerance", type=float, default=0.05, help="a used offset within this many seconds is right (default 0.05)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE", help="write results as JSON to FILE (or stdout)")
    p.set_defaults(func=run)


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"--sync-errors: expected seconds separated by commas, got {text!r}") from None


def _one(model, directory: Path, truth: float, video: bool = False) -> dict:
    from uuomocap.protocol.session import load_session
    from uuomocap.solver_core.clock_sync import estimate_session_clock_offset
    from uuomocap.solver_core.prior_preparation import prior_from_npz_arrays

    s = load_session(directory, load_prior=not video, load_gt=False)
    if video:
        from uuomocap.video_methods import session_blazepose_prior

        prior_arrays = session_blazepose_prior(directory)[0]
    else:
        prior_arrays = s.prior
    t0 = time.perf_counter()
    try:
        est = estimate_session_clock_offset(model, s.markers.positions, s.markers.visible, s.markers.stamps_ns,
                                            prior_from_npz_arrays(prior_arrays), centre_s=s.clock_offset_s, up_axis=s.up_axis)
    except ValueError as exc:
        return {"truth_s": truth, "status": "error", "error": str(exc), "seconds": time.perf_counter() - t0}
    peak = est.correlation_offset_s if est.correlation_offset_s is not None else est.offset_s
    status = "used" if est.reliable else ("weak" if est.weak else "flat" if est.flat_fit else "ambiguous")
    return {"truth_s": truth, "status": status,
            "offset_s": est.offset_s, "error_s": est.offset_s - truth, "peak_error_s": peak - truth,
            "correlation": est.correlation, "fit_rms_mm": est.fit_rms_mm, "fit_contrast": est.fit_contrast, "runner_up_fit_rms_mm": est.runner_up_fit_rms_mm,
            "ambiguous": est.ambiguous, "weak": est.weak, "flat_fit": est.flat_fit,
            "seconds": time.perf_counter() - t0}


def _summary(rows: list[dict], tolerance: float) -> dict:
    used = [r for r in rows if r["status"] == "used"]
    right = [r for r in used if abs(r["error_s"]) <= tolerance]
    out = {"sessions": len(rows), "used_right": len(right), "used_wrong": len(used) - len(right),
           "ambiguous": sum(r["status"] == "ambiguous" for r in rows), "weak": sum(r["status"] == "weak" for r in rows),
           "flat": sum(r["status"] == "flat" for r in rows),
           "error": sum(r["status"] == "error" for r in rows)}
    if right:
        err, peak = np.abs([r["error_s"] for r in right]) * 1000, np.abs([r["peak_error_s"] for r in right]) * 1000
        out.update(median_error_ms=float(np.median(err)), max_error_ms=float(err.max()),
                   median_peak_error_ms=float(np.median(peak)), max_peak_error_ms=float(peak.max()))
    return out


def run(args) -> int:
    import torch

    from uuomocap.capture_session import make_capture_session
    from uuomocap.solver_core.body_model import load_solver_models
    from uuomocap.synth import SampleConfig, make_session

    errors = _floats(args.sync_errors)
    sources = [("motion", m.strip()) for m in args.motions.split(",") if m.strip()]
    sources += [("capture", c.strip()) for c in args.captures.split(",") if c.strip()]
    for kind, name in sources:
        if (kind == "capture" or "." in name) and not Path(name).is_file():
            raise UserError(f"no such file: {name}")
    if not sources or not errors or args.seeds < 1:
        raise UserError("nothing to run: give motions or captures, sync errors and at least one seed")
    torch.set_num_threads(1)
    _, model = load_solver_models("open-low")
    jobs = [(kind, name, seed, e) for kind, name in sources for seed in range(args.seeds) for e in errors]
    bar = bench_progress(args, len(jobs), "bench sync")
    results: dict[str, list[dict]] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="uuomocap-bench-sync-") as tmp:
        for i, (kind, name, seed, e) in enumerate(jobs):
            d = Path(tmp) / f"s{i}"
            cfg = SampleConfig(motion=name if kind == "motion" else "walk", duration_s=args.duration, seed=seed, sync_error_s=e,
                               video=args.video)
            (make_session if kind == "motion" else make_capture_session)(*((d, cfg) if kind == "motion" else (name, d, cfg)))
            row = {"seed": seed, **_one(model, d, e, args.video)}
            results.setdefault(Path(name).name, []).append(row)
            bar.update(1)
    bar.close()
    summaries = {k: _summary(v, args.tolerance) for k, v in results.items()}
    total = _summary([r for v in results.values() for r in v], args.tolerance)
    head = (f"{'motion':28} {'sessions':>8} {'right':>6} {'wrong':>6} {'ambig.':>6} {'weak':>5} {'flat':>5} {'no overlap':>10}"
            f"  {'refined ms (median/max)':>24}  {'peak ms':>11}")
    lines = [f"clock offset from the motion: used right (within {1000 * args.tolerance:.0f} ms) / used wrong / not used", head, "-" * len(head)]
    for k, s in [*summaries.items(), ("all", total)]:
        errs = (f"{s['median_error_ms']:.0f} / {s['max_error_ms']:.0f}", f"{s['median_peak_error_ms']:.0f} / {s['max_peak_error_ms']:.0f}") \
            if "median_error_ms" in s else ("-", "-")
        lines.append(f"{k[:28]:28} {s['sessions']:>8} {s['used_right']:>6} {s['used_wrong']:>6} {s['ambiguous']:>6} {s['weak']:>5} {s['flat']:>5} {s['error']:>10}"
                     f"  {errs[0]:>24}  {errs[1]:>11}")
    seconds = time.perf_counter() - t0
    lines.append(f"sync errors {', '.join(f'{e:+.1f}' for e in errors)} s x {args.seeds} seeds, {args.duration:.0f} s sessions, "
                 + ("BlazePose's prior from the rendered video; " if args.video else "simulated prior; ") + f"{seconds:.0f} s on 1 thread")
    emit_bench(args, {"summary": summaries, "all": total, "sessions": results, "tolerance_s": args.tolerance,
                      "sync_errors_s": errors, "seconds": seconds}, "\n".join(lines))
    return 0 if total["used_wrong"] == 0 else 1
