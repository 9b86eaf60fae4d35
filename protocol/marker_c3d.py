"""C3D reading for ``markerio``: ezc3d first, the pure-python ``c3d`` package for files ezc3d refuses.

Both paths return a :class:`RawMarkers` with coordinates in the file's units; ``markerio``
interprets units, missing encodings, labels and the up axis.  Before either library runs,
``_preflight`` reads the 512-byte header itself so that "not a C3D file" and "truncated"
get a clear message instead of a library's stream error.
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np

from uuomocap.protocol.markerio import MarkerFileError, RawMarkers, parse_axis

# Groups listed in POINT:TYPE_GROUPS hold points that are not positions (degrees, newtons...).
_DEFAULT_NON_POSITION_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "REACTIONS", "SCALARS")
_PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}


def _preflight(path: Path) -> dict:
    """Check magic, processor type and that the file reaches its data; return header facts.

    Raises MarkerFileError for "not a C3D" and for files cut before their data starts.
    """
    name = str(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(512)
        if len(head) < 2:
            raise MarkerFileError(f"{name}: too short to be a C3D file ({size} bytes)")
        if head[1] != 0x50:
            raise MarkerFileError(f"{name}: not a C3D file (second byte is 0x{head[1]:02x}; C3D files have 0x50)")
        if len(head) < 512:
            raise MarkerFileError(f"{name}: truncated C3D: {size} bytes, shorter than the 512-byte header")
        pblock = head[0]
        if pblock < 2:
            raise MarkerFileError(f"{name}: not a C3D file (parameter section pointer is {pblock})")
        poff = (pblock - 1) * 512
        if size < poff + 4:
            raise MarkerFileError(f"{name}: truncated C3D: file ends before its parameter section ({size} bytes)")
        fh.seek(poff)
        phead = fh.read(4)
    n_param_blocks, proc = phead[2], phead[3]
    if proc not in _PROCESSORS:
        raise MarkerFileError(f"{name}: not a C3D file or corrupt (processor type byte {proc}, expected 84-86)")
    endian = ">" if proc == 86 else "<"
    n_points, analog_total, first, last = struct.unpack(endian + "4H", head[2:10])
    (data_start,) = struct.unpack(endian + "H", head[16:18])
    params_end = poff + n_param_blocks * 512
    if n_param_blocks and size < params_end:
        raise MarkerFileError(
            f"{name}: truncated C3D: file ends inside the parameter section ({size} of {params_end} bytes)"
        )
    declared = last - first + 1 if last >= first else 0
    # Sign of the header's scale float says float (negative) or integer data; its sign bit sits in a
    # different byte for each processor's float format.
    sign_byte = {84: head[15], 85: head[13], 86: head[12]}[proc]
    word = 4 if sign_byte & 0x80 else 2
    data_offset = (data_start - 1) * 512
    if data_start >= 2 and declared > 0 and (n_points or analog_total):
        if size <= data_offset:
            raise MarkerFileError(
                f"{name}: truncated C3D: file ends before the data starts "
                f"({size} bytes; header declares {declared} frames from block {data_start})"
            )
        frame_bytes = (4 * n_points + analog_total) * word
        need = data_offset + declared * frame_bytes
        # Only when even 2-byte words would not fit: writers sometimes disagree between the header's
        # scale sign and POINT:SCALE, and the libraries then read frame by frame (checked after).
        need_int = data_offset + declared * (4 * n_points + analog_total) * 2
        if size < need and size < need_int:
            held = (size - data_offset) // frame_bytes
            raise MarkerFileError(
                f"{name}: truncated C3D: header declares {declared} frames ({need} bytes) "
                f"but the file has {size} bytes, about {held} frames"
            )
    return {
        "size": size,
        "proc": proc,
        "analog_per_frame": analog_total,
        "processor": _PROCESSORS[proc],
        "n_points": n_points,
        "first_frame": first,
        "declared_frames": declared,
        "data_start": data_start,
    }


def read_c3d_raw(path: Path) -> RawMarkers:
    pre = _preflight(path)
    try:
        return _read_with_ezc3d(path, pre)
    except MarkerFileError:
        raise
    except Exception as ez_exc:  # ezc3d refuses the file: try the pure-python reader
        try:
            raw = _read_with_c3d_package(path, pre)
        except MarkerFileError:
            raise
        except Exception as py_exc:
            raise MarkerFileError(
                f"{path}: unreadable C3D (ezc3d: {_one_line(ez_exc)}; c3d: {_one_line(py_exc)})"
            ) from py_exc
        raw.warnings.insert(0, f"ezc3d refused the file ({_one_line(ez_exc)}); read with the c3d package")
        return raw


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]


def _truncation_error(path: Path, declared: int, got: int, size: int) -> MarkerFileError:
    return MarkerFileError(
        f"{path}: truncated C3D: header declares {declared} frames but the file ({size} bytes) holds only {got}"
    )


# ------------------------------------------------------------------ ezc3d


def _ez_value(params: dict, group: str, key: str):
    """Parameter value, matching group and key names case-insensitively (writers differ: 'Company')."""
    g = params.get(group) or next((v for k, v in params.items() if k.upper() == group), None)
    if not g:
        return None
    entry = g.get(key) or next((v for k, v in g.items() if k.upper() == key), None)
    return entry.get("value") if isinstance(entry, dict) else None


def _ez_strings(params: dict, group: str, key: str) -> list[str] | None:
    v = _ez_value(params, group, key)
    if v is None:
        return None
    if isinstance(v, str):
        return [v]
    if isinstance(v, (list, tuple)):
        return [str(s) for s in v]
    return None


def _ez_number(params: dict, group: str, key: str) -> float | None:
    v = _ez_value(params, group, key)
    if v is None or isinstance(v, (list, str)):
        return None
    arr = np.asarray(v).ravel()
    return float(arr[0]) if arr.size else None


def _read_with_ezc3d(path: Path, pre: dict) -> RawMarkers:
    import ezc3d

    c = ezc3d.c3d(str(path))
    params = c["parameters"]
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, M, T)
    T = pts.shape[2] if pts.ndim == 3 else 0
    head = c["header"]["points"]  # ezc3d rewrites last_frame to what it read: compare with the raw header
    if T < pre["declared_frames"] and pre["n_points"] > 0:
        raise _truncation_error(path, pre["declared_frames"], T, pre["size"])
    coords = pts[:3].transpose(2, 1, 0) if T else np.zeros((0, pts.shape[1] if pts.ndim == 3 else 0, 3))
    scale = _ez_number(params, "POINT", "SCALE") or 0.0
    residuals = _residuals_from_file(path, pre, T, coords.shape[1], scale) if T else None
    if residuals is not None and not np.array_equal(residuals < 0, np.isnan(coords).any(axis=-1)):
        residuals = None  # our decoding disagrees with ezc3d about which points are valid: trust ezc3d
    if residuals is None and T:
        meta_points = c["data"].get("meta_points") or {}
        if "residuals" in meta_points:
            residuals = np.asarray(meta_points["residuals"], dtype=np.float64)[0].T  # (T, M)

    def strings(key: str) -> list[str] | None:
        return _ez_strings(params, "POINT", key)

    labels = _concat_labels(lambda k: strings(k), coords.shape[1])
    descriptions = _concat_labels(lambda k: strings(k.replace("LABELS", "DESCRIPTIONS")), coords.shape[1])
    rate = _ez_number(params, "POINT", "RATE") or float(head.get("frame_rate") or 0.0)
    units = (strings("UNITS") or [None])[0]
    type_groups = strings("TYPE_GROUPS")
    group_labels = {g: strings(g) or [] for g in _non_position_groups(type_groups)}
    x_screen = (strings("X_SCREEN") or [None])[0]
    y_screen = (strings("Y_SCREEN") or [None])[0]
    uses_prefixes = _ez_number(params, "SUBJECTS", "USES_PREFIXES")
    prefixes = _ez_strings(params, "SUBJECTS", "LABEL_PREFIXES") if uses_prefixes else None
    meta = {
        "c3d_processor": pre["processor"],
        "point_scale": _ez_number(params, "POINT", "SCALE"),
        "manufacturer": (_ez_strings(params, "MANUFACTURER", "COMPANY") or [""])[0],
        "software": (_ez_strings(params, "MANUFACTURER", "SOFTWARE") or [""])[0],
        "subject_names": _ez_strings(params, "SUBJECTS", "NAMES") or [],
    }
    return _assemble(
        path,
        coords,
        residuals,
        labels,
        units,
        rate,
        int(head["first_frame"]) + 1,  # ezc3d counts from 0; the file's header counts from 1
        x_screen,
        y_screen,
        group_labels,
        prefixes,
        meta,
        descriptions=descriptions,
        reader="ezc3d",
    )


def _residuals_from_file(path: Path, pre: dict, T: int, M: int, scale: float) -> np.ndarray | None:
    """(T, M) residuals decoded from word 4 of each point, as the C3D spec defines it.

    The spec (c3d.org, "Notes for programmers - Integer 3D data") puts the camera mask in the HIGH
    byte of word 4 and the residual (in units of |POINT:SCALE|) in the LOW byte; a negative word
    means invalid.  ezc3d 1.x reads the two bytes the other way round, so we decode the words
    ourselves.  Returns None when the layout cannot be trusted (then ezc3d's values are used).
    """
    if M != pre["n_points"] or pre["data_start"] < 2 or scale == 0:
        return None
    is_float = scale < 0
    word = 4 if is_float else 2
    frame_words = 4 * M + pre["analog_per_frame"]
    offset = (pre["data_start"] - 1) * 512
    need = offset + T * frame_words * word
    if pre["size"] < need:
        return None
    big = pre["proc"] == 86
    raw = np.fromfile(path, dtype=np.uint8, count=need - offset, offset=offset)
    if is_float:
        if pre["proc"] == 85:  # DEC F-float: swap 16-bit halves, read as IEEE, divide by 4
            b = raw.reshape(-1, 4)[:, [2, 3, 0, 1]].copy()
            words = b.view("<f4").ravel() / 4.0
        else:
            words = raw.view(">f4" if big else "<f4")
        w4 = words.reshape(T, frame_words)[:, 3 : 4 * M : 4].astype(np.float64)
        if not np.all(np.isfinite(w4)):
            return None
        w4 = np.round(w4).astype(np.int64)
    else:
        w4 = raw.view(">i2" if big else "<i2").reshape(T, frame_words)[:, 3 : 4 * M : 4].astype(np.int64)
    return np.where(w4 < 0, -1.0, (w4 & 0xFF) * abs(scale))


# ------------------------------------------------------------------ c3d package


def _read_with_c3d_package(path: Path, pre: dict) -> RawMarkers:
    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = c3d.Reader(fh)
        frames = [p[:, :4].astype(np.float64) for _i, p, _a in reader.read_frames(copy=True)]
        first, last = int(reader.first_frame), int(reader.last_frame)
        hit_eof = any("end of file" in str(w.message).lower() for w in caught)

        def strings(key: str) -> list[str] | None:
            param = reader.get(f"POINT:{key}")
            return _c3d_param_strings(param)

        M = int(reader.point_used)
        labels = _concat_labels(strings, M)
        descriptions = _concat_labels(lambda k: strings(k.replace("LABELS", "DESCRIPTIONS")), M)
        units = (strings("UNITS") or [None])[0]
        type_groups = strings("TYPE_GROUPS")
        group_labels = {g: strings(g) or [] for g in _non_position_groups(type_groups)}
        x_screen = (strings("X_SCREEN") or [None])[0]
        y_screen = (strings("Y_SCREEN") or [None])[0]
        uses = reader.get("SUBJECTS:USES_PREFIXES")
        prefixes = _c3d_param_strings(reader.get("SUBJECTS:LABEL_PREFIXES")) if uses and uses.int16_value else None
        rate = float(reader.point_rate)
        meta = {
            "c3d_processor": pre["processor"],
            "point_scale": float(reader.point_scale),
            "manufacturer": (_c3d_param_strings(reader.get("MANUFACTURER:COMPANY")) or [""])[0],
            "software": (_c3d_param_strings(reader.get("MANUFACTURER:SOFTWARE")) or [""])[0],
            "subject_names": _c3d_param_strings(reader.get("SUBJECTS:NAMES")) or [],
        }
    declared = last - first + 1
    if hit_eof or len(frames) < declared:
        raise _truncation_error(path, declared, len(frames), pre["size"])
    data = np.stack(frames) if frames else np.zeros((0, M, 4))
    coords = data[..., :3].copy()
    residuals = data[..., 3].copy()
    return _assemble(
        path,
        coords,
        residuals,
        labels,
        units,
        rate,
        first,
        x_screen,
        y_screen,
        group_labels,
        prefixes,
        meta,
        descriptions=descriptions,
        reader="c3d",
    )


def _c3d_param_strings(param) -> list[str] | None:
    if param is None:
        return None
    try:
        dims = list(param.dimensions)
        if len(dims) <= 1:
            return [param.string_value.strip()]
        arr = np.asarray(param.string_array).ravel()
        return [str(s).strip() for s in arr]
    except Exception:
        return None


# ------------------------------------------------------------------ shared


def _concat_labels(strings, M: int) -> list[str]:
    """POINT:LABELS, then LABELS2, LABELS3... (C3D splits more than 255 names)."""
    labels = list(strings("LABELS") or [])
    k = 2
    while len(labels) < M:
        more = strings(f"LABELS{k}")
        if not more:
            break
        labels += more
        k += 1
    return [s.strip() for s in labels[:M]]


def _non_position_groups(type_groups: list[str] | None) -> list[str]:
    if type_groups:
        # TYPE_GROUPS pairs a list parameter with its type name: ['ANGLES', 'ANGLE', 'FORCES', 'FORCE', ...]
        return [g.strip().upper() for g in type_groups[::2] if g.strip()]
    return list(_DEFAULT_NON_POSITION_GROUPS)


def _assemble(
    path: Path,
    coords: np.ndarray,
    residuals: np.ndarray | None,
    labels: list[str],
    units: str | None,
    rate: float,
    first_frame: int,
    x_screen: str | None,
    y_screen: str | None,
    group_labels: dict[str, list[str]],
    prefixes: list[str] | None,
    meta: dict,
    descriptions: list[str],
    reader: str,
) -> RawMarkers:
    warnings_out: list[str] = []
    M = coords.shape[1]
    # Some writers (Motion Analysis EVa) cut labels to 4 characters, so 'R.Knee' and 'R.Knee.Medial'
    # both become 'RKNE'; the full names survive in POINT:DESCRIPTIONS.
    if len(set(labels)) < len(labels) and len(descriptions) == len(labels):
        if all(descriptions) and len(set(descriptions)) == len(descriptions):
            warnings_out.append("POINT:LABELS has duplicates (names cut short); using POINT:DESCRIPTIONS as names")
            labels = list(descriptions)
    # Points listed under ANGLES/FORCES/... are model outputs in degrees, newtons...: never markers.
    non_pos_names = {s.strip() for names in group_labels.values() for s in names if s.strip()}
    keep = np.array([lab not in non_pos_names for lab in labels] + [True] * (M - len(labels)), dtype=bool)
    dropped = [lab for lab, k in zip(labels, keep) if not k]
    if dropped:
        groups = ", ".join(g for g, names in group_labels.items() if names)
        warnings_out.append(f"left out {len(dropped)} points that are not positions ({groups})")
        coords = coords[:, keep]
        residuals = residuals[:, keep] if residuals is not None else None
        labels = [lab for lab, k in zip(labels, keep[: len(labels)]) if k]
        meta["non_position_points"] = dropped

    up = None
    up_origin = ""
    y_axis, x_axis = parse_axis(y_screen), parse_axis(x_screen)
    if y_axis is not None and (x_axis is None or x_axis[1] != y_axis[1]):
        up = y_axis
        up_origin = f"C3D POINT:Y_SCREEN '{y_screen.strip()}'" + (f" (X_SCREEN '{x_screen.strip()}')" if x_screen else "")
    elif y_screen or x_screen:
        warnings_out.append(f"unusable POINT:X_SCREEN/Y_SCREEN ({x_screen!r}, {y_screen!r}); up axis from the data")
    return RawMarkers(
        coords=coords,
        residuals=residuals,
        labels=labels,
        units=units,
        units_origin="POINT:UNITS",
        rate_hz=rate,
        first_frame=first_frame,
        format="c3d",
        reader=reader,
        up_axis=up,
        up_axis_origin=up_origin,
        default_up_axis="+z",
        default_up_reason="default +z (no POINT:Y_SCREEN; the usual C3D lab convention)",
        label_prefixes=prefixes,
        warnings=warnings_out,
        meta=meta,
    )
