"""``uuomocap bench gap-fill``: filling marker gaps from the solved body against trajectory fills.

Held-out protocol: in each session, gaps of each ``--gap-lengths`` are cut into stretches where a
marker was seen (``--gaps-per-length`` per length, at random, each bounded by seen frames), the
unlabelled markers with those gaps are solved (``uuo``, the offline staged solver), and the cut
samples are filled back by

* ``body``: the solved body's marker prediction (smoothed along time), corrected by the residual
  carried in from the gap's edges with its slope there (``solver_core.gap_fill.body_fill``, what
  ``uuomocap label --fill-gaps`` writes);
* ``body as solved, linear blend``: the prediction as solved, the edge residuals blended linearly;
* ``body (no edge correction)``: the prediction alone;
* ``spline``: a cubic spline through the seen samples 10 frames either side (labelling tools' fill);
* ``linear``: a straight line across the gap.

Each fill is scored against the samples that were cut (real measurements on ``--captures``, the
simulated markers on generated sessions): RMS, median and worst error in mm per gap length.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, bench_progress, emit_bench

FILLS = ("body", "body as solved, linear blend", "body (no edge correction)", "spline", "linear")


def register_bench(subparsers) -> None:
    import argparse

    p = subparsers.add_parser("gap-fill", help="filling marker gaps from the solved body vs spline and linear fills",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--motions", default="walk,jump,arms", help="generated sessions' motions, comma-separated (default walk,jump,arms)")
    p.add_argument("--captures", default="", help="real labelled marker files (.c3d/.trc), comma-separated, as `sample from-capture`")
    p.add_argument("--gap-lengths", default="0.1,0.25,0.5,1,2", help="gap lengths in seconds (default 0.1,0.25,0.5,1,2)")
    p.add_argument("--gaps-per-length", type=int, default=6, help="gaps of each length cut per session (default 6)")
    p.add_argument("--seeds", type=int, default=1, help="seeds per motion / capture (default 1)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds per generated session (default 8)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE", help="write results as JSON to FILE (or stdout)")
    p.set_defaults(func=run)


def cut_gaps(visible: np.ndarray, lengths_frames: list[int], per_length: int, seed: int) -> list[tuple[int, int, int]]:
    """(marker, start, stop) gaps to cut: each lies where the marker was seen, with a seen frame
    before and after it, and apart from every other cut gap of the same marker.  visible: (T, M)."""
    rng = np.random.default_rng(seed)
    free = np.asarray(visible, bool).copy()
    T, M = free.shape
    cuts = []
    for n in lengths_frames:
        for _ in range(per_length):
            for _attempt in range(200):
                m, a = int(rng.integers(M)), int(rng.integers(1, max(2, T - n)))
                if a + n < T and free[a - 1:a + n + 1, m].all():
                    cuts.append((m, a, a + n))
                    free[a - 1:a + n + 1, m] = False  # the edges stay seen: no other cut may take them
                    break
    return cuts


def _score(filled: np.ndarray, truth: np.ndarray, cuts: list, names: dict[int, str]) -> dict[str, dict]:
    """Errors of the cut samples per gap length.  names: gap frames -> the length asked for ('0.25')."""
    by_len: dict[str, list[float]] = {}
    worst: dict[str, list[float]] = {}
    for m, a, b in cuts:
        key = names[b - a]
        e = np.linalg.norm(filled[a:b, m] - truth[a:b, m], axis=-1) * 1000
        e = np.where(np.isfinite(e), e, np.nan)
        by_len.setdefault(key, []).extend(e.tolist())
        worst.setdefault(key, []).append(float(np.nanmax(e)) if np.isfinite(e).any() else float("nan"))
    return {k: {"rms_mm": float(np.sqrt(np.nanmean(np.square(v)))), "median_mm": float(np.nanmedian(v)),
                "max_mm": float(np.nanmax(v)), "unfilled": int(np.isnan(v).sum()), "samples": len(v),
                "gaps": len(worst[k])} for k, v in by_len.items()}


def _one(directory: Path, lengths_s: list[float], per_length: int, seed: int) -> dict:
    from uuomocap.solver_core.gap_fill import body_fill, linear_fill, solved_marker_positions, spline_fill
    from uuomocap.solver_methods import _params_arrays, inputs_from_session, run_staged_solver

    inputs = inputs_from_session(directory)
    rate = inputs.rate_hz
    frames = [max(1, round(s * rate)) for s in lengths_s]
    names = {n: f"{s:g}" for n, s in zip(frames, lengths_s)}
    cuts = cut_gaps(inputs.visible, frames, per_length, seed)
    visible = inputs.visible.copy()
    for m, a, b in cuts:
        visible[a:b, m] = False
    truth = inputs.markers
    t0 = time.perf_counter()
    result, model = run_staged_solver(replace(inputs, visible=visible, markers=np.where(visible[..., None], truth, np.nan)))
    solve_s = time.perf_counter() - t0
    poses, trans, betas, _ = _params_arrays(model, result.params, inputs.up_axis)
    att = result.attachment
    predicted, frames = solved_marker_positions(model, betas, poses, trans, att.face_ids.numpy(), att.bary.double().numpy(),
                                                return_frames=True)
    fills = {"body": body_fill(truth, visible, predicted, frames, rate)[0],
             "body as solved, linear blend": body_fill(truth, visible, predicted, frames)[0],
             "body (no edge correction)": np.where(visible[..., None], truth, predicted),
             "spline": spline_fill(truth, visible)[0], "linear": linear_fill(truth, visible)[0]}
    return {"rate_hz": rate, "frames": int(truth.shape[0]), "markers": int(truth.shape[1]), "gaps": len(cuts), "solve_s": solve_s,
            "scores": {name: _score(f, truth, cuts, names) for name, f in fills.items()}}


def _pool(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """Per fill and gap length over sessions: RMS over all cut samples, median of session medians, worst."""
    out: dict[str, dict[str, dict]] = {}
    for name in FILLS:
        for r in rows:
            for k, s in r["scores"][name].items():
                acc = out.setdefault(name, {}).setdefault(k, {"sq": 0.0, "n": 0, "max_mm": 0.0, "unfilled": 0, "gaps": 0})
                n = s["samples"] - s["unfilled"]
                acc["sq"] += s["rms_mm"] ** 2 * n
                acc["n"] += n
                acc["max_mm"] = max(acc["max_mm"], s["max_mm"])
                acc["unfilled"] += s["unfilled"]
                acc["gaps"] += s["gaps"]
    for name in out:
        for k, acc in out[name].items():
            acc["rms_mm"] = float(np.sqrt(acc.pop("sq") / max(1, acc["n"])))
            acc["samples"] = acc.pop("n")
    return out


def run(args) -> int:
    import torch

    from uuomocap.capture_session import make_capture_session
    from uuomocap.synth import SampleConfig, make_session

    try:
        lengths = [float(x) for x in args.gap_lengths.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"--gap-lengths: expected seconds separated by commas, got {args.gap_lengths!r}") from None
    sources = [("motion", m.strip()) for m in args.motions.split(",") if m.strip()]
    sources += [("capture", c.strip()) for c in args.captures.split(",") if c.strip()]
    for kind, name in sources:
        if (kind == "capture" or "." in name) and not Path(name).is_file():
            raise UserError(f"no such file: {name}")
    if not sources or not lengths or min(lengths) <= 0 or args.seeds < 1 or args.gaps_per_length < 1:
        raise UserError("nothing to run: give motions or captures, positive gap lengths, seeds >= 1 and gaps per length >= 1")
    torch.set_num_threads(1)
    jobs = [(kind, name, seed) for kind, name in sources for seed in range(args.seeds)]
    bar = bench_progress(args, len(jobs), "bench gap-fill")
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="uuomocap-bench-gapfill-") as tmp:
        for i, (kind, name, seed) in enumerate(jobs):
            d = Path(tmp) / f"s{i}"
            cfg = SampleConfig(motion=name if kind == "motion" else "walk", duration_s=args.duration, rate_hz=30.0, seed=seed, video=False)
            if kind == "motion":
                make_session(d, cfg)
            else:
                make_capture_session(name, d, cfg)
            rows.append({"source": Path(name).name, "seed": seed, **_one(d, lengths, args.gaps_per_length, seed)})
            bar.update(1)
    bar.close()
    pooled = _pool(rows)
    keys = sorted(pooled["body"], key=float)
    head = f"{'fill':27}" + "".join(f"{k + ' s':>16}" for k in keys)
    lines = ["error on the cut samples, mm: RMS / worst (all sessions pooled)", head, "-" * len(head)]
    for name in FILLS:
        cells = [pooled[name][k] for k in keys]
        lines.append(f"{name:27}" + "".join(f"{c['rms_mm']:>8.1f} /{c['max_mm']:>6.0f}" for c in cells))
    unfilled = sum(c["unfilled"] for c in pooled["body"].values())
    seconds = time.perf_counter() - t0
    lines.append(f"{len(rows)} sessions ({', '.join(sorted({r['source'] for r in rows}))}), {sum(r['gaps'] for r in rows)} gaps cut, "
                 f"{unfilled} cut samples the body left open; solves {sum(r['solve_s'] for r in rows):.0f} s, "
                 f"{seconds:.0f} s in all on 1 thread")
    emit_bench(args, {"pooled": pooled, "sessions": rows, "gap_lengths_s": lengths, "seconds": seconds}, "\n".join(lines))
    return 0
