"""``uuomocap bench merge-tracks``: joining an unlabelled export's columns back into markers.

An unlabelled export starts a new column each time a marker comes back from an occlusion.  Sessions
are generated that way (``sample make --layout structured --track-breaks``: Plug-in Gait markers,
every column one seen stretch, the true marker of each column in gt.npz), solved with ``uuo``, and
the columns joined (``solver_core.track_stitching``, what ``uuomocap label --merge-tracks`` does).
Printed per motion: columns, markers, the joined markers, how many are pure (every column one
marker's), how many markers came out whole (all their columns in one), and how many of the
Plug-in Gait names ``label --layout plug-in-gait`` gives the joined markers are right; also with
the true surface points and poses in place of the solve (the joining alone).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, bench_progress, emit_bench


def register_bench(subparsers) -> None:
    import argparse

    p = subparsers.add_parser("merge-tracks", help="joining an unlabelled export's fragmented columns back into markers",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--motions", default="walk,jump,arms", help="procedural motions, comma-separated (default walk,jump,arms)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per motion (default 3)")
    p.add_argument("--occlusion", type=float, default=0.01, help="per-frame hide probability (default 0.01: 10-frame hides)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds per session (default 8)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE", help="write results as JSON to FILE (or stdout)")
    p.set_defaults(func=run)


def score_chains(chains: list[list[int]], source: np.ndarray) -> dict:
    """Pure chains (one marker's columns only) and whole markers (every column of it in one chain)."""
    pure = [c for c in chains if len(set(source[c].tolist())) == 1]
    whole = sum(1 for m in set(source.tolist()) if any(set(np.flatnonzero(source == m).tolist()) == set(c) for c in pure))
    return {"chains": len(chains), "pure": len(pure), "whole_markers": whole}


def _join_and_name(model, betas, poses, trans, faces, bary, md, names_true, source) -> dict:
    from uuomocap.solver_core.gap_fill import solved_marker_positions
    from uuomocap.solver_core.marker_naming import compare_names, load_layout, name_markers
    from uuomocap.solver_core.track_stitching import stitch_columns

    predicted, frames = solved_marker_positions(model, betas, poses, trans, faces, bary, return_frames=True)
    chains = stitch_columns(md.positions, md.visible, predicted, frames, md.rate_hz)
    rep = [max(c, key=lambda k: int(md.visible[:, k].sum())) for c in chains]
    l_faces, l_bary, l_names = load_layout("plug-in-gait", model, np.asarray(betas).reshape(-1), "open-low")
    named = name_markers(model, np.asarray(betas).reshape(-1), faces[rep], bary[rep], [""] * len(rep), l_faces, l_bary, l_names)
    names = compare_names(named.names, [names_true[r] for r in rep], l_names)
    return {**score_chains(chains, source), "names_right": names["right"]}


def _one(directory: Path) -> dict:
    from uuomocap.protocol.session import load_session
    from uuomocap.solver_methods import _params_arrays, inputs_from_session, run_staged_solver

    s = load_session(directory)
    gt, md = s.gt, s.markers
    source, names_true = np.asarray(gt["marker_source"]), [str(n) for n in gt["marker_names"]]
    t0 = time.perf_counter()
    result, model = run_staged_solver(inputs_from_session(directory))
    solve_s = time.perf_counter() - t0
    poses, trans, betas, _ = _params_arrays(model, result.params, s.up_axis)
    att = result.attachment
    solved = _join_and_name(model, betas, poses, trans, att.face_ids.numpy(), att.bary.double().numpy(), md, names_true, source)
    truth = _join_and_name(model, gt["betas"], gt["poses"], gt["trans"], np.asarray(gt["marker_faces"]), np.asarray(gt["marker_bary"]),
                           md, names_true, source)
    return {"columns": int(md.n_markers), "markers": int(len(set(source.tolist()))), "solve_s": solve_s, "solved": solved, "truth": truth}


def run(args) -> int:
    import torch

    from uuomocap.synth import SampleConfig, make_session

    motions = [m.strip() for m in args.motions.split(",") if m.strip()]
    if not motions or args.seeds < 1 or not 0 < args.occlusion < 1:
        raise UserError("nothing to run: give motions, seeds >= 1 and an occlusion between 0 and 1")
    torch.set_num_threads(1)
    jobs = [(m, s) for m in motions for s in range(args.seeds)]
    bar = bench_progress(args, len(jobs), "bench merge-tracks")
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="uuomocap-bench-merge-") as tmp:
        for i, (motion, seed) in enumerate(jobs):
            d = Path(tmp) / f"s{i}"
            make_session(d, SampleConfig(motion=motion, duration_s=args.duration, rate_hz=30.0, seed=seed, layout="structured",
                                         occlusion=args.occlusion, track_breaks=True, video=False))
            rows.append({"motion": motion, "seed": seed, **_one(d)})
            bar.update(1)
    bar.close()
    head = f"{'motion':8} {'sessions':>8} {'columns':>8} {'markers':>8} | {'joined':>7} {'pure':>5} {'whole':>6} {'names':>6} | truth: {'joined':>6} {'whole':>6}"
    lines = ["an unlabelled export's columns joined into markers (uuo's solve; and the true points and poses)", head, "-" * len(head)]
    for motion in [*motions, "all"]:
        sel = [r for r in rows if motion in ("all", r["motion"])]
        tot = {k: sum(r[k] for r in sel) for k in ("columns", "markers")}
        sv = {k: sum(r["solved"][k] for r in sel) for k in ("chains", "pure", "whole_markers", "names_right")}
        tr = {k: sum(r["truth"][k] for r in sel) for k in ("chains", "whole_markers")}
        lines.append(f"{motion:8} {len(sel):>8} {tot['columns']:>8} {tot['markers']:>8} | {sv['chains']:>7} {sv['pure']:>5} "
                     f"{sv['whole_markers']:>6} {sv['names_right']:>6} | {tr['chains']:>12} {tr['whole_markers']:>6}")
    seconds = time.perf_counter() - t0
    lines.append(f"{args.duration:g} s sessions, 30 Hz, 39 Plug-in Gait markers, occlusion {100 * args.occlusion:g} % (hides of 10 "
                 f"frames, each a new column); solves {sum(r['solve_s'] for r in rows):.0f} s, {seconds:.0f} s in all on 1 thread")
    emit_bench(args, {"sessions": rows, "seconds": seconds}, "\n".join(lines))
    return 0
