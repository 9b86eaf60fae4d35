"""`uuomocap markers info FILE`: what the marker reader understood about a C3D / TRC file."""

from __future__ import annotations

import sys

from uuomocap.commands import UserError, add_json_flag, emit


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "markers",
        help="inspect marker files (C3D, TRC)",
        description="Inspect optical marker files the way every uuomocap tool reads them.",
    )
    sub = parser.add_subparsers(dest="markers_cmd", metavar="CMD")
    parser.set_defaults(func=lambda args: _usage(parser))

    info = sub.add_parser(
        "info",
        help="frames, rate, markers, units, up axis, missing fraction, labels, warnings",
        description=(
            "Read a marker file (.c3d or .trc) and print what the reader understood: frames, frame rate, "
            "duration, marker count, units found in the file (and the units used if the header lied), "
            "up axis and how it was determined, fraction of missing samples, whether markers are "
            "labelled (and the first labels), and a warning for every quirk worked around. "
            "A file that cannot be read gives a one-line error and exit code 2."
        ),
    )
    info.add_argument("file", help="marker file: .c3d or .trc")
    info.add_argument(
        "--keep-model-points",
        action="store_true",
        help="keep points computed by a biomechanical model (Plug-in Gait segment axes, centre of mass)",
    )
    add_json_flag(info)
    info.set_defaults(func=_info)


def _usage(parser) -> int:
    parser.print_help(sys.stderr)
    return 2


def _info(args) -> int:
    from uuomocap.protocol.markerio import MarkerFileError, read_markers

    try:
        md = read_markers(args.file, keep_model_points=args.keep_model_points, progress=True)
    except MarkerFileError as exc:
        raise UserError(str(exc)) from None
    except Exception as exc:  # never a traceback for a bad file
        raise UserError(f"{args.file}: could not read ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    s = md.summary()
    units = s["units_found"] or "(none)"
    if s["units_used"] and s["units_used"] != (s["units_found"] or "").lower():
        units += f" -> using {s['units_used']}"
    labels = "labelled" if s["labelled"] else "unlabeled"
    first = ", ".join(s["labels_first"]) + (", ..." if s["markers"] > len(s["labels_first"]) else "")
    lines = [
        f"file:      {s['file']}",
        f"format:    {s['format']} (read with {s['reader']})",
        f"frames:    {s['frames']} (first frame number {s['first_frame']})",
        f"rate:      {s['rate_hz']:g} Hz",
        f"duration:  {s['duration_s']:.3f} s",
        f"markers:   {s['markers']} ({labels}: {first})",
        f"units:     {units}",
        f"up axis:   {s['up_axis']} ({s['up_axis_source']})",
        f"missing:   {100 * s['missing_fraction']:.1f} % of samples"
        + (f"; never seen: {', '.join(s['markers_never_seen'][:5])}" if s["markers_never_seen"] else ""),
    ]
    if s["subjects"]:
        lines.append(f"subjects:  {', '.join(s['subjects'])}")
    if s["warnings"]:
        lines.append("warnings:")
        lines += [f"  - {w}" for w in s["warnings"]]
    emit(args, s, "\n".join(lines))
    return 0
