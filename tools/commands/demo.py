"""``uuomocap demo``: the main job on the bundled default, as ``make demo`` runs it.

Generates a sample session with ground truth (no external data needed), replays it through
the streaming graph (``launch/replay_session.yaml``: marker replay -> prior -> segmenter ->
windowed solver -> recorder) and scores the recorded solve against the ground truth.
``--offline`` solves the whole session at once with the paper's staged solver instead.
"""

from __future__ import annotations

import time
from pathlib import Path

from uuomocap.commands import UserError, add_json_flag, emit


def _graph_plugins_present() -> bool:
    from uuomocap.nodes.base import discover_plugins

    plugins = discover_plugins()
    return all(name in plugins for name in ("marker_replay", "prior_replay", "segmenter", "solver", "recorder"))


def _handler(args) -> int:
    from uuomocap.commands.eval import evaluate_paths, format_metrics
    from uuomocap.synth import SampleConfig, make_session

    out = Path(args.out).resolve()
    session = out / "session"
    t0 = time.perf_counter()
    cfg = SampleConfig(motion=args.motion, duration_s=args.duration, seed=args.seed, video=not args.no_video)
    if args.fresh or not (session / "session.yaml").exists():
        print(f"[1/3] generating sample session: {args.motion}, {args.duration:g} s, 40 unlabeled markers, "
              f"simulated video prior -> {session}", flush=True)
        make_session(session, cfg)
    else:
        print(f"[1/3] reusing sample session {session} (--fresh to regenerate)", flush=True)
    t_gen = time.perf_counter() - t0

    t1 = time.perf_counter()
    use_graph = not args.offline and _graph_plugins_present()
    if use_graph:
        from uuomocap.launcher import LaunchError, launch, parse_cli_args

        recording = out / "stream.mcap"
        pred = recording.with_suffix(".npz")
        for stale in (recording, pred):
            stale.unlink(missing_ok=True)
        print("[2/3] replaying through the graph: launch/replay_session.yaml (lockstep)", flush=True)
        try:
            # Same typing as `uuomocap launch ... key:=value` on the command line.
            cli_args = parse_cli_args([f"session:={session}", f"out:={recording}", "lockstep:=true"])
            rc = launch("replay_session", cli_args, quiet=not args.verbose)
        except LaunchError as exc:
            raise UserError(str(exc)) from None
        if rc != 0 or not pred.exists():
            raise UserError(f"the replay graph exited with code {rc}; logs are under {out} (rerun with --verbose)")
        where = {"recording": str(recording), "solved_npz": str(pred)}
    else:
        from uuomocap.methods import get_method

        if not args.offline:
            print("(segmenter/solver graph plugins not installed: solving offline)", flush=True)
        pred = out / "OUT.npz"
        print(f"[2/3] offline solve (method uuo) -> {pred}", flush=True)
        get_method("uuo")(session, pred, "open-low")
        where = {"solved_npz": str(pred)}
    t_solve = time.perf_counter() - t1

    print("[3/3] accuracy against the session's ground truth", flush=True)
    res = evaluate_paths(pred, session / "gt.npz", session / "markers.c3d")
    from uuomocap.commands.render import session_sheet

    try:  # look at a solve before trusting it
        where["contact_sheet"] = session_sheet(pred, session)["png"]
    except UserError as exc:  # a picture is not worth failing the run that solved
        print(f"(no contact sheet: {exc})", flush=True)
    where.update(_hand_over(pred, session, out))
    data = {"session": str(session), "mode": "graph" if use_graph else "offline", **where,
            "seconds": {"generate": round(t_gen, 2), "solve": round(t_solve, 2)}, "metrics": res}
    text = "\n".join([
        f"session:       {session}",
        *(f"{k + ':':<14} {v}" for k, v in where.items()),
        f"time:          generate {t_gen:.1f} s, {'replay+solve' if use_graph else 'solve'} {t_solve:.1f} s",
        format_metrics(res),
    ])
    emit(args, data, text)
    return 0


def _hand_over(pred, session, out) -> dict:
    """What a user takes to other tools: the skeleton as BVH and the markers with names (the demo's
    markers are random, so segment names)."""
    from argparse import Namespace

    from uuomocap.commands.export import run_export
    from uuomocap.commands.label import run_label

    done = {}
    try:
        done["bvh"] = run_export(Namespace(pred=str(pred), out=str(out / "stream.bvh"), session=str(session), markers=None,
                                           up_axis=None, units="cm"))[0]["out"]
        done["named_markers"] = run_label(Namespace(pred=str(pred), out=str(out / "markers_named.c3d"), session=str(session),
                                                    markers=None, layout="segments", max_distance_mm=None))[0]["out"]
    except UserError as exc:  # nor are the hand-over files
        print(f"(no export: {exc})", flush=True)
    return done


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="generate a sample session, solve it through the replay graph, print accuracy",
        description=__doc__,
    )
    p.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    p.add_argument("--motion", default="walk", help="procedural motion for the sample session (default: walk)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds of motion (default: 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample session (default: 0)")
    p.add_argument("--no-video", action="store_true", help="skip rendering video.mp4 (the prior comes from prior.npz)")
    p.add_argument("--fresh", action="store_true", help="regenerate the session even if it exists")
    p.add_argument("--offline", action="store_true", help="solve the whole session at once instead of streaming")
    p.add_argument("--verbose", action="store_true", help="show the graph's node output")
    add_json_flag(p)
    p.set_defaults(func=_handler)
