"""TRC (Motion Analysis / OpenSim marker text) reading for ``markerio``.

Layout (tab separated)::

    PathFileType  4  (X/Y/Z)  file.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    60        60          600        41          mm     60            1                   600
    Frame#  Time  R.ASIS        L.ASIS ...
                  X1  Y1  Z1    X2  Y2  Z2 ...
    <blank>
    1       0.000 809.0 1034.5 -64.6 ...

Real files break this in many ways and we trust the data over the header: NumMarkers / NumFrames
/ Units that disagree with the rows, rows of variable width, blank fields for missing markers,
and raw unlabeled streams (NumMarkers 0, no names, each row a list of the points seen in that
frame).  Every disagreement becomes a warning.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from uuomocap.protocol.markerio import MarkerFileError, RawMarkers, parse_axis

_NAN_TOKEN = re.compile(r"^[-+]?(nan|1\.#q?nan|1\.#ind|-?nan\(ind\)|inf|1\.#inf)", re.IGNORECASE)


def _split(line: str) -> list[str]:
    return line.split("\t") if "\t" in line else line.split()


def _number(tok: str) -> float | None:
    try:
        return float(tok)
    except ValueError:
        return None


def read_trc_raw(path: Path, progress: bool = False) -> RawMarkers:
    name = str(path)
    blob = path.read_bytes()
    if b"\x00" in blob[:4096]:
        raise MarkerFileError(f"{name}: not a TRC file (binary content)")
    text = blob.decode("utf-8", errors="replace")
    ends_with_newline = text.endswith(("\n", "\r"))
    lines = text.splitlines()
    warnings: list[str] = []

    # --- header: find the key/value lines and the names line ---
    first = lines[0].strip().lower() if lines else ""
    key_idx = next((i for i, ln in enumerate(lines[:4]) if ln.strip().lower().startswith("datarate")), None)
    if not first.startswith("pathfiletype") and key_idx is None:
        raise MarkerFileError(f"{name}: not a TRC file (first line should start with 'PathFileType')")
    if key_idx is None or key_idx + 1 >= len(lines):
        raise MarkerFileError(f"{name}: TRC header has no 'DataRate ...' key line")
    keys = [k.strip() for k in _split(lines[key_idx])]
    vals = [v.strip() for v in _split(lines[key_idx + 1])]
    header = {k.lower(): v for k, v in zip(keys, vals) if k}
    names_idx = next(
        (i for i in range(key_idx + 2, min(len(lines), key_idx + 6)) if lines[i].strip().lower().startswith("frame")),
        None,
    )
    if names_idx is None:
        raise MarkerFileError(f"{name}: TRC header has no 'Frame# Time <marker names>' line")
    names = _marker_names(lines[names_idx])

    # --- data rows: first field a frame number, then time, then X Y Z per point ---
    rows: list[tuple[int, list[str]]] = []
    line_iter = range(names_idx + 1, len(lines))
    if progress:
        from tqdm import tqdm

        line_iter = tqdm(line_iter, desc="reading TRC", unit="line", delay=1.0, leave=False)
    for i in line_iter:
        ln = lines[i]
        if not ln.strip():
            continue
        fields = _split(ln)
        if _number(fields[0].strip()) is None:
            if not rows:
                continue  # the X1 Y1 Z1 line and other header leftovers
            raise MarkerFileError(f"{name}: line {i + 1}: expected a frame number, found {fields[0][:20]!r}")
        rows.append((i, fields))
    if not rows:
        raise MarkerFileError(f"{name}: zero frames (no data rows after the header)")

    # A file cut mid-row (no final newline, row shorter than the others) would give wrong numbers.
    widths = [len(_trim(f)) for _i, f in rows]
    if not ends_with_newline and len(rows) > 1 and widths[-1] < max(widths[:-1]):
        warnings.append(f"last line {rows[-1][0] + 1} is incomplete (file truncated?); dropped")
        rows.pop()
        widths.pop()

    n_coords = max(0, max(widths) - 2)
    M_data = (n_coords + 2) // 3
    M = max(M_data, len(names))
    T = len(rows)
    width = 3 * M
    values: list[list[float]] = []
    frame_no = np.zeros(T, dtype=np.float64)
    times = np.full(T, np.nan)
    n_nan_tokens = 0
    nan = math.nan
    for r, (i, fields) in enumerate(rows):
        frame_no[r] = float(fields[0])
        t = _number(fields[1]) if len(fields) > 1 else None
        times[r] = t if t is not None else nan
        vals = fields[2 : 2 + width]
        try:  # fast path: plain numbers and empty fields (float() accepts surrounding spaces)
            row = [float(v) if v else nan for v in vals]
        except ValueError:
            row, n_bad = _parse_row_slow(vals, name, i)
            n_nan_tokens += n_bad
        if len(row) < width:
            row += [nan] * (width - len(row))
        values.append(row)
    coords = np.array(values, dtype=np.float64).reshape(T, M, 3)
    coords[~np.isfinite(coords).all(axis=-1)] = np.nan  # any blank / inf coordinate: whole point missing

    # --- header vs data ---
    raw_unlabeled = len(names) == 0
    declared_markers = _int(header.get("nummarkers"))
    if declared_markers is not None and declared_markers != M and not (raw_unlabeled and declared_markers == 0):
        warnings.append(f"header NumMarkers={declared_markers} but the rows hold {M} markers; using {M}")
    if names and M_data > len(names):
        warnings.append(f"{len(names)} marker names but rows hold {M_data} points; extra columns unnamed")
    declared_frames = _int(header.get("numframes"))
    if declared_frames is not None and declared_frames != T:
        hint = " (file truncated?)" if declared_frames > T else ""
        warnings.append(f"header NumFrames={declared_frames} but the file has {T} rows{hint}; using {T}")
    if n_nan_tokens:
        warnings.append(f"{n_nan_tokens} fields written as NaN/Inf text treated as missing")

    # --- frame numbers: fill gaps (dropped frames) with missing rows so stamps stay true ---
    first_frame = int(frame_no[0]) if float(frame_no[0]).is_integer() else 1
    steps = np.diff(frame_no)
    ints = np.all(frame_no == np.round(frame_no))
    if T > 1 and ints and np.all(steps >= 1) and np.any(steps > 1):
        span = int(frame_no[-1] - frame_no[0]) + 1
        if span <= 10 * T:
            full = np.full((span, M, 3), np.nan)
            idx = (frame_no - frame_no[0]).astype(int)
            full[idx] = coords
            full_times = np.full(span, np.nan)
            full_times[idx] = times
            warnings.append(f"{span - T} frame numbers missing between rows; inserted as missing frames")
            coords, times = full, full_times
            frame_no = np.arange(frame_no[0], frame_no[0] + span)
    elif T > 1 and not (ints and np.all(steps >= 1)):
        warnings.append("Frame# column is not increasing; rows taken in file order")
        frame_no = np.arange(T, dtype=np.float64) + first_frame

    time_decimals = max((len(f[1].strip().partition(".")[2]) for _i, f in rows[:20] if len(f) > 1), default=6)
    rate = _rate(header, frame_no, times, 10.0 ** -time_decimals, warnings, name)

    units = header.get("units")
    up = parse_axis(header.get("upaxis")) if "upaxis" in header else None
    if raw_unlabeled:
        warnings.append(
            "raw unlabeled stream: columns are per-frame point lists (slots), not marker tracks; "
            "a column may switch between points and includes ghosts"
        )
    meta = {
        k: header[k]
        for k in ("camerarate", "origdatarate", "origdatastartframe", "orignumframes")
        if k in header
    }
    return RawMarkers(
        coords=coords,
        residuals=None,
        labels=names,
        units=units,
        units_origin="TRC header Units",
        rate_hz=rate,
        first_frame=first_frame,
        format="trc",
        reader="trc",
        up_axis=up,
        up_axis_origin=f"TRC header UpAxis '{header.get('upaxis', '')}'" if up else "",
        default_up_axis="+y",
        default_up_reason="default +y (TRC files follow OpenSim's Y-up convention)",
        point_slots=raw_unlabeled,
        warnings=warnings,
        meta=meta,
    )


def _parse_row_slow(vals: list[str], name: str, line_index: int) -> tuple[list[float], int]:
    """Row with blanks padded by spaces or NaN spelled the C runtime way ('-nan(ind)', '1.#QNAN')."""
    row: list[float] = []
    n_nan_tokens = 0
    for v in vals:
        v = v.strip()
        if not v:
            row.append(math.nan)
            continue
        x = _number(v)
        if x is None:
            if not _NAN_TOKEN.match(v):
                raise MarkerFileError(f"{name}: line {line_index + 1}: cannot read {v[:20]!r} as a number")
            x = math.nan
            n_nan_tokens += 1
        row.append(x)
    return row, n_nan_tokens


def _trim(fields: list[str]) -> list[str]:
    """Fields without trailing empties (most writers end rows with a tab)."""
    n = len(fields)
    while n and not fields[n - 1].strip():
        n -= 1
    return fields[:n]


def _marker_names(line: str) -> list[str]:
    """Names from 'Frame#  Time  A<tab><tab><tab>B ...': every third field, or consecutive if packed."""
    fields = _split(line)[2:] if "\t" in line else line.split()[2:]
    fields = [f.strip() for f in fields]
    filled = [i for i, f in enumerate(fields) if f]
    if not filled:
        return []
    if all(i % 3 == 0 for i in filled):
        last = filled[-1] // 3
        return [fields[3 * k] for k in range(last + 1)]
    return [fields[i] for i in filled]


def _int(text: str | None) -> int | None:
    if text is None:
        return None
    x = _number(text.strip())
    return int(x) if x is not None and float(x).is_integer() else None


def _rate(
    header: dict, frame_no: np.ndarray, times: np.ndarray, time_resolution: float, warnings: list[str], name: str
) -> float:
    """DataRate from the header, checked against the Time column (which wins when they disagree).

    Times are often printed with 3 decimals, so the tolerance includes that rounding.
    """
    hdr = _number((header.get("datarate") or "").strip())
    if hdr is None or not math.isfinite(hdr) or hdr <= 0:
        cam = _number((header.get("camerarate") or "").strip())
        hdr = cam if cam is not None and math.isfinite(cam) and cam > 0 else None
    ok = ~np.isnan(times)
    data_rate = None
    if ok.sum() >= 2:
        t, f = times[ok], frame_no[ok]
        dt = t[-1] - t[0]
        df = f[-1] - f[0]
        if dt > 0 and df > 0 and np.all(np.diff(t) > 0):
            data_rate = float(df / dt)
    if hdr is not None and data_rate is not None:
        tolerance = 0.005 + 2.0 * time_resolution / (times[ok][-1] - times[ok][0])
        if abs(data_rate - hdr) / hdr > tolerance:
            warnings.append(f"header DataRate={hdr:g} Hz but the Time column runs at {data_rate:.6g} Hz; using the Time column")
            return data_rate
        return float(hdr)
    if hdr is not None:
        return float(hdr)
    if data_rate is not None:
        warnings.append(f"no usable DataRate in the header; {data_rate:.6g} Hz from the Time column")
        return data_rate
    raise MarkerFileError(f"{name}: no frame rate (header DataRate missing and no usable Time column)")
