"""`uuomocap track FILE --out TRACKED.c3d`: turn a raw unlabeled point stream into tracks, offline."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "track",
        help="track a raw unlabeled marker file (points per frame -> stable tracks)",
        description=(
            "Run the streaming marker tracker (the 'tracker' node) over a whole .c3d/.trc/.mcap file whose "
            "columns are per-frame point lists, not markers (raw unlabeled exports, live recordings). "
            "Prints how many tracks it found, their mean length and how many ghost points it rejected; "
            "with --out writes a C3D with one column per track (T<id>), NaN where a track is not visible."
        ),
    )
    p.add_argument("file", help="marker file: .c3d, .trc or .mcap (topic markers/raw)")
    p.add_argument("--out", help="write the tracks to this .c3d file")
    p.add_argument("--min-frames", type=int, default=0, help="drop tracks visible in fewer frames (default keep all)")
    p.add_argument("--birth-s", type=float, help="seconds of hits before a track is confirmed (default 0.025)")
    p.add_argument("--max-coast-s", type=float, help="seconds a lost track keeps its id (default 0.1)")
    p.add_argument("--gate-floor-m", type=float, help="gate radius floor in metres (default 0.015)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from uuomocap.protocol import recording  # noqa: F401  (lets read_markers open .mcap)
    from uuomocap.protocol.markerio import MarkerFileError, read_markers, write_c3d
    from uuomocap.solver_core.tracker import TrackerConfig, track_sequence

    if args.out and not args.out.lower().endswith(".c3d"):
        raise UserError(f"--out must be a .c3d path, got {args.out!r}")
    try:
        md = read_markers(args.file, progress=True)
    except MarkerFileError as exc:
        raise UserError(str(exc)) from None
    overrides = {k: v for k, v in (("birth_s", args.birth_s), ("max_coast_s", args.max_coast_s),
                                    ("gate_floor_m", args.gate_floor_m)) if v is not None}
    try:
        config = dataclasses.replace(TrackerConfig(rate_hz=md.rate_hz), **overrides)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    frames = (md.positions[t][md.visible[t]] for t in range(len(md.positions)))
    frames = tqdm(frames, total=len(md.positions), unit="frame", file=sys.stderr, leave=False,
                  disable=len(md.positions) < 2000)
    result = track_sequence(frames, md.stamps_ns, config)
    s = result.summary
    data = {"file": str(args.file), "rate_hz": md.rate_hz, "points_per_frame": float(md.visible.sum(1).mean()),
            **{k: v for k, v in s.items() if not k.startswith("stats_")},
            "tracker": {k[6:]: v for k, v in s.items() if k.startswith("stats_")}}
    if args.out:
        ids = np.unique(result.track_ids[result.visible])
        cols = []
        for tid in ids:
            pos = np.full((len(md.positions), 3), np.nan)
            t, slot = np.nonzero((result.track_ids == tid) & result.visible)
            pos[t] = result.positions[t, slot]
            if len(t) >= args.min_frames:
                cols.append((tid, pos))
        if not cols:
            raise UserError("no track to write (try a smaller --min-frames)")
        write_c3d(args.out, np.stack([c[1] for c in cols], 1), md.rate_hz,
                  labels=[f"T{tid}" for tid, _ in cols], up_axis=md.up_axis)
        data["out"] = {"file": args.out, "tracks_written": len(cols)}
    text = "\n".join([
        f"file:      {args.file} ({data['frames']} frames at {md.rate_hz:g} Hz, "
        f"{data['points_per_frame']:.1f} points per frame)",
        f"tracks:    {s['tracks']} (mean {s['mean_track_frames']:.1f} frames, median {s['median_track_frames']:.0f}, "
        f"longest {s['max_track_frames']}); {s['mean_visible_tracks']:.1f} visible per frame",
        f"tracked:   {100 * s['tracked_point_fraction']:.1f} % of points "
        f"(a new track waits {s['birth_frames']} frames before it is confirmed)",
        f"ghosts:    {s['ghost_points']} points rejected, in {100 * s['frames_with_ghosts_rejected']:.1f} % of frames",
    ] + ([f"written:   {args.out} ({len(cols)} tracks)"] if args.out else []))
    emit(args, data, text)
    return 0
