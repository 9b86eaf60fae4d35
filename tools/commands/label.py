"""``uuomocap label OUT.npz --out labeled.c3d``: the take's markers written back with names.

The solve gave every unlabelled marker a body part and a surface point; this verb turns those into
the labelled trajectories a lab passes on (Plug-in Gait names, a studio's own template's, else
``LThigh1``-style segment names) - every frame and column of the marker file as recorded, only
the labels new (``solver_core.marker_naming``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit

def register(subparsers) -> None:
    p = subparsers.add_parser(
        "label",
        help="write a solved take's markers with names (C3D/TRC): Plug-in Gait, your template's, or segment names",
        description=(
            "Name the markers of a solved take and write them to a C3D or TRC file: every frame and column "
            "of the marker file as recorded (gaps stay gaps unless --fill-gaps; an unlabelled export's "
            "fragmented columns stay apart unless --merge-tracks; a TRC is turned +y up, as OpenSim reads it), "
            "with labels.  Each marker's solved surface point is matched to the named points of a layout on "
            "the rest pose of the solved body (each name used once, the summed distance smallest, no pair "
            "further apart than --max-distance-mm); "
            "a marker left over is named by the body segment it rides and its order from the segment's "
            "joint (LThigh1 nearest the hip).  Layouts: segments (default: segment names only, for markers "
            "put anywhere), plug-in-gait (Vicon's full-body Plug-in Gait names, LFHD ... RTOE, for a PiG "
            "marker set), or a template .npz of "
            "your own marker set: `uuomocap sample motion-from-markers one_labelled_take.c3d --out "
            "template.npz` fits it once; the names transfer through the body surface to other takes and "
            "subjects of the same marker set and placement protocol."),
    )
    p.add_argument("pred", metavar="OUT.npz", help="solved output of `uuomocap solve` (marker_faces / marker_bary / marker_parts)")
    p.add_argument("--session", metavar="DIR", help="the session it was solved from (its marker file)")
    p.add_argument("--markers", metavar="FILE", help="the marker file it was solved from (.c3d / .trc) when there is no session")
    p.add_argument("--out", required=True, metavar="FILE", help="labelled marker file to write: .c3d or .trc")
    p.add_argument("--layout", default="segments", metavar="NAME|TEMPLATE.npz",
                   help="segments (default: segment names only) | plug-in-gait | a template npz with marker_labels (or marker_names), "
                        "marker_faces and marker_bary on the solve's body model")
    p.add_argument("--max-distance-mm", type=float, default=None,
                   help="furthest a marker may sit from a layout point and take its name (default 100)")
    p.add_argument("--fill-gaps", action="store_true",
                   help="fill each marker's gaps (seen before and after) from the solved body: the marker's point on the body, "
                        "corrected by its residual at the gap's edges; in a C3D the filled samples carry residual 0 "
                        "(C3D: computed, not measured)")
    p.add_argument("--merge-tracks", action="store_true",
                   help="join the columns that are one marker (an unlabelled export starts a new column each time a marker "
                        "comes back): a column continues another when it starts where the solved body carries the other's "
                        "marker; the file gets one column per marker")
    p.add_argument("--max-gap", type=float, default=None, metavar="S",
                   help="with --fill-gaps: leave gaps longer than S seconds open (default: fill every gap the body covers)")
    add_json_flag(p)
    p.set_defaults(func=_handler)


def load_layout(spec: str, model, betas: np.ndarray, body_model_name: str):
    """``marker_naming.load_layout`` with its errors as one-line user errors naming ``--layout``."""
    from uuomocap.solver_core.marker_naming import LayoutError
    from uuomocap.solver_core.marker_naming import load_layout as load

    try:
        return load(spec, model, betas, body_model_name)
    except LayoutError as exc:
        raise UserError(f"--layout {exc}") from None


def _handler(args) -> int:
    info, text = run_label(args)
    emit(args, info, text)
    return 0


def run_label(args) -> tuple[dict, str]:
    """The verb without printing: (JSON info, text) - `uuomocap demo` calls it too."""
    from uuomocap.protocol.markerio import MarkerFileError, read_markers, write_c3d, write_trc
    from uuomocap.protocol.session import SessionError, load_session
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.marker_naming import MarkerNamingConfig, compare_names, name_markers

    out = Path(args.out)
    if out.suffix.lower() not in (".c3d", ".trc"):
        raise UserError(f"--out {out}: write a .c3d or a .trc")
    pred_path = Path(args.pred)
    pred = _read_npz(pred_path)
    for k in ("betas", "marker_faces", "marker_bary"):
        if k not in pred:
            raise UserError(f"{pred_path}: missing {k!r} - label needs a solve's marker labels (`uuomocap solve` writes them)")
    if bool(args.session) == bool(args.markers):
        raise UserError("give the marker file the take was solved from: --session DIR or --markers FILE")
    try:
        md = load_session(Path(args.session), load_prior=False, load_gt=False).markers if args.session else read_markers(args.markers)
    except (SessionError, MarkerFileError) as exc:
        raise UserError(str(exc)) from None
    faces = np.asarray(pred["marker_faces"], np.int64)
    if faces.shape[0] != md.n_markers:
        raise UserError(f"{pred_path}: labels for {faces.shape[0]} markers, the marker file has {md.n_markers} columns - "
                        "not the file this was solved from")
    body_model = str(pred.get("body_model", "open-low"))
    try:
        model = load_body_model(body_model)
    except (ValueError, OSError) as exc:
        raise UserError(f"{pred_path}: cannot load body model {body_model!r} ({exc})") from None
    betas = np.asarray(pred["betas"], np.float64).reshape(-1)
    if not np.isfinite(betas).all():
        raise UserError(f"{pred_path}: betas hold NaN/inf (an unsolved take)")
    cap_mm = MarkerNamingConfig().max_distance_m * 1000 if args.max_distance_mm is None else args.max_distance_mm
    if not cap_mm > 0:
        raise UserError(f"--max-distance-mm {args.max_distance_mm}: give a positive distance")
    l_faces, l_bary, l_names = load_layout(args.layout, model, betas, body_model)
    parts = [str(x) for x in pred.get("marker_parts", [""] * faces.shape[0])]
    bary = np.asarray(pred["marker_bary"], np.float64)
    was = [md.raw_labels[k] if md.raw_labels else md.labels[k] for k in range(md.n_markers)]
    positions, visible, residuals = md.positions, md.visible, _file_residuals_mm(md)
    predicted = frames = None
    if args.fill_gaps or args.merge_tracks:
        predicted, frames = _body_predictions(pred, pred_path, model, md)
    merge_info = None
    if args.merge_tracks:
        from uuomocap.solver_core.track_stitching import merge_columns, stitch_columns

        chains = stitch_columns(md.positions, md.visible, predicted, frames, md.rate_hz)
        rep = [max(c, key=lambda k: int(md.visible[:, k].sum())) for c in chains]  # the longest column's point
        positions, visible = merge_columns(md.positions, md.visible, chains)
        residuals = np.stack([residuals[:, c].max(1) for c in chains], 1)  # columns of a chain never overlap
        faces, bary, parts = faces[rep], bary[rep], [parts[r] for r in rep]
        predicted, frames = predicted[:, rep], frames[:, rep]
        was = ["+".join(was[c] for c in chain[:3]) + (f"+{len(chain) - 3} more" if len(chain) > 3 else "") for chain in chains]
        merge_info = {"columns": md.n_markers, "markers": len(chains), "chains": [[int(c) for c in chain] for chain in chains]}
    named = name_markers(model, betas, faces, bary, parts, l_faces, l_bary, l_names,
                         MarkerNamingConfig(max_distance_m=cap_mm / 1000.0))
    fill_info = None
    if args.fill_gaps:
        positions, residuals, fill_info = _fill_gaps(args, positions, visible, residuals, predicted, frames, md.rate_hz)
    elif args.max_gap is not None:
        raise UserError("--max-gap needs --fill-gaps")
    if not args.fill_gaps:
        positions = np.where(visible[..., None], positions, np.nan)
    n_out = positions.shape[1]
    try:
        if out.suffix.lower() == ".c3d":
            write_c3d(out, positions, md.rate_hz, labels=list(named.names), up_axis=md.up_axis,
                      residuals=residuals if (args.fill_gaps or md.residuals is not None) else None)
        else:
            write_trc(out, positions, md.rate_hz, labels=list(named.names), up_axis=md.up_axis)
    except (OSError, ValueError) as exc:
        raise UserError(f"--out {out}: cannot write ({exc})") from None
    rows = [{"column": k, "was": was[k], "name": n, "part": parts[k],
             "layout_distance_mm": None if not np.isfinite(d) else round(1000 * float(d), 1)}
            for k, (n, d) in enumerate(zip(named.names, named.distance_m))]
    info = {"out": str(out), "frames": md.n_frames, "markers": n_out, "layout": args.layout,
            "layout_names": len(l_names), "named_from_layout": named.named_count,
            "max_distance_mm": cap_mm, "markers_named": rows}
    how = (f"{named.named_count} named from {args.layout} ({len(l_names)} names), {n_out - named.named_count} by segment"
           if l_names else "named by segment")
    lines = [f"wrote {out}: {md.n_frames} frames @ {md.rate_hz:g} Hz, {n_out} markers; {how}"]
    if merge_info is not None:
        info["merge_tracks"] = merge_info
        lines.append(f"joined {md.n_markers} columns into {n_out} markers (one marker's columns: each starts where the "
                     "solved body carries the previous one's marker)")
    if fill_info is not None:
        info["gap_fill"] = fill_info
        lines.append(f"filled {fill_info['filled_gaps']} of {fill_info['gaps']} gaps from the solved body "
                     f"({fill_info['filled_samples']} samples, {100 * fill_info['visible_before']:.1f} -> "
                     f"{100 * fill_info['visible_after']:.1f} % of the samples); left open: {fill_info['left_open_long']} longer than "
                     f"--max-gap, {fill_info['left_open_unsolved']} where the body was not solved or the marker has no point")
    if out.suffix.lower() == ".trc" and md.up_axis != "+y":  # markerio.write_trc: OpenSim reads every TRC +y up
        info["written_up_axis"] = "+y"
        lines.append(f"(the TRC is +y up, turned from the capture's {md.up_axis}, as OpenSim reads it)")
    reference = _reference_names(args.session, md.n_markers)
    if reference is not None and merge_info is not None:
        reference = [reference[max(c, key=lambda k: int(md.visible[:, k].sum()))] for c in merge_info["chains"]]
    if reference is not None and l_names and compare_names(named.names, reference, l_names)["compared"]:
        info["against_reference"] = c = compare_names(named.names, reference, l_names)
        if 2 * c["compared"] < n_out:  # another lab's names (BTK's 'R.Ankle'): a 'wrong' list would mislead
            lines.append(f"the session's gt.npz names are another convention ({c['compared']} of {n_out} are "
                         f"{args.layout} names): not scored")
        else:
            lines.append(f"against the session's gt.npz names: {c['right']} of {c['compared']} right"
                         + (f"; wrong: {' '.join(c['wrong'])}" if c["wrong"] else "")
                         + (f"; unnamed: {' '.join(c['unnamed'])}" if c["unnamed"] else ""))
    lines += [f"  {r['was']:>10} -> {r['name']:<12} {r['part'] or '-':<15}"
              + (f" {r['layout_distance_mm']:5.1f} mm from the layout point" if r["layout_distance_mm"] is not None else "")
              for r in rows]
    return info, "\n".join(lines)


def _file_residuals_mm(md) -> np.ndarray:
    """(T, M) the file's own residuals in mm where it has them (a measured sample's is positive), else 0."""
    from uuomocap.protocol.markerio import unit_metres

    if md.residuals is None:
        return np.zeros(md.positions.shape[:2])
    to_mm = 1000.0 * (unit_metres(md.units_found) or 1e-3)  # the reader assumes mm when the file names none
    return np.where(md.visible, np.clip(md.residuals, 0, None) * to_mm, 0.0)


def _body_predictions(pred: dict, pred_path: Path, model, md) -> tuple[np.ndarray, np.ndarray]:
    """Where the solved body puts each column's marker at every frame of the marker file, and its
    face frames: ``gap_fill.solved_marker_positions`` (NaN where the solve has no frame)."""
    from uuomocap.solver_core.gap_fill import solved_marker_positions

    for k in ("poses", "trans"):
        if k not in pred:
            raise UserError(f"{pred_path}: missing {k!r} - --fill-gaps / --merge-tracks need the solved poses")
    poses, trans = np.asarray(pred["poses"], np.float64), np.asarray(pred["trans"], np.float64)
    betas = np.asarray(pred["frame_betas"] if "frame_betas" in pred else pred["betas"], np.float64)
    n = poses.shape[0]
    if poses.shape != (n, 72) or trans.shape != (n, 3) or (betas.ndim == 2 and betas.shape[0] != n):
        raise UserError(f"{pred_path}: poses {poses.shape}, trans {trans.shape}, betas {betas.shape} do not describe one solve")
    rows = np.arange(n)
    if n != md.n_frames:  # a solve of part of the take: its frames by their stamps
        if "stamps_ns" not in pred:
            raise UserError(f"{pred_path}: {n} solved frames for {md.n_frames} marker frames and no stamps_ns to match them")
        rows = np.searchsorted(md.stamps_ns, np.asarray(pred["stamps_ns"], np.int64))
        ok = (rows < md.n_frames) & (np.abs(md.stamps_ns[np.minimum(rows, md.n_frames - 1)] - np.asarray(pred["stamps_ns"])) < 1e6)
        rows, poses, trans = rows[ok], poses[ok], trans[ok]
        betas = betas[ok] if betas.ndim == 2 else betas
    predicted, frames = np.full(md.positions.shape, np.nan), np.full((*md.positions.shape, 3), np.nan)
    predicted[rows], frames[rows] = solved_marker_positions(model, betas, poses, trans, pred["marker_faces"], pred["marker_bary"],
                                                            return_frames=True)
    return predicted, frames


def _fill_gaps(args, positions, visible, residuals, predicted, frames, rate_hz) -> tuple[np.ndarray, np.ndarray, dict]:
    """``--fill-gaps``: (positions with the bounded gaps filled from the body, residuals for write_c3d
    (the file's own where it has them; 0 on filled samples: C3D's 'computed'), what was filled)."""
    from uuomocap.solver_core.gap_fill import body_fill, bounded_gaps

    if args.max_gap is not None and not args.max_gap > 0:
        raise UserError(f"--max-gap {args.max_gap}: give a positive number of seconds")
    max_frames = None if args.max_gap is None else int(np.floor(args.max_gap * rate_hz + 1e-9))
    filled_pos, filled = body_fill(positions, visible, predicted, frames, rate_hz, max_frames)
    gaps = bounded_gaps(visible)
    long = sum(max_frames is not None and g.frames > max_frames for g in gaps)
    n_filled = sum(bool(filled[g.start, g.marker]) for g in gaps)
    total = visible.size
    return filled_pos, np.where(filled, 0.0, residuals), {
        "gaps": len(gaps), "filled_gaps": n_filled, "filled_samples": int(filled.sum()), "left_open_long": int(long),
        "left_open_unsolved": len(gaps) - n_filled - int(long), "max_gap_s": args.max_gap,
        "visible_before": float(visible.sum() / total), "visible_after": float((visible | filled).sum() / total),
        "filled": [{"column": g.marker, "first_frame": g.start, "frames": g.frames} for g in gaps if filled[g.start, g.marker]],
    }


def _read_npz(path: Path, context: str = "") -> dict:
    """An npz as a dict, or a one-line error naming the file."""
    from uuomocap.protocol.session import SessionError, read_npz

    if not path.is_file():
        raise UserError(f"{context or str(path) + ': '}file not found")
    try:
        return read_npz(path)
    except SessionError as exc:
        raise UserError(f"{context}{exc}") from None


def _reference_names(session: str | None, m_count: int) -> list[str] | None:
    """The true names of a generated or `sample from-capture` session's columns (gt.npz marker_names), if any."""
    from uuomocap.protocol.session import SessionError, read_npz

    gt = Path(session) / "gt.npz" if session else None
    if gt is None or not gt.is_file():
        return None
    try:
        names = read_npz(gt).get("marker_names")
    except SessionError:
        return None
    return None if names is None or len(names) != m_count else [str(n) for n in names]
