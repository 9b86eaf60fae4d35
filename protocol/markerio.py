"""Marker files: read C3D / TRC into one in-memory form, write C3D / TRC.

Everything downstream (replay node, sessions, solvers, metrics) sees markers only
through :class:`MarkerData`: positions in METRES in the file's own world axes
(never rotated), NaN where a marker is missing, plus what the reader understood
about the file (units, rate, up axis and how it was found, labels or not, and
warnings for every quirk it had to work around).

Real files encode "missing" in several ways and this module normalises all of
them to NaN: NaN coordinates, (0,0,0) with residual -1 (the C3D convention),
exact (0,0,0) with a non-negative residual (some exporters), and blank TRC
fields.  A point at exactly (0,0,0) in all three coordinates is treated as
missing because a real marker sitting on the origin to the last bit is far less
likely than an exporter writing zeros for "not seen".

Format readers live in ``marker_c3d`` / ``marker_trc``; they return a
:class:`RawMarkers` (numbers in file units, metadata as found) and this module
interprets it (``_interpret``).  ``read_markers`` dispatches by file extension
through ``MARKER_READERS`` so other formats (our MCAP recordings) can be added by
registering a reader with :func:`register_reader`.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = [
    "MarkerData",
    "MarkerFileError",
    "RawMarkers",
    "read_markers",
    "write_c3d",
    "write_trc",
    "to_y_up",
    "register_reader",
    "MARKER_READERS",
    "parse_units",
    "is_placeholder_label",
    "infer_up_axis",
    "placeholder_labels",
]


class MarkerFileError(ValueError):
    """A marker file that cannot be read; the message is one line naming the file and the problem."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


# ---------------------------------------------------------------------------------------------
# Data classes
# ---------------------------------------------------------------------------------------------


@dataclass
class RawMarkers:
    """What a format reader found, before interpretation (units, missing encodings, labels).

    coords: (T, M, 3) float64 in FILE units, NaN where the file itself said "missing".
    residuals: (T, M) float64 or None; negative = missing (C3D convention).
    """

    coords: np.ndarray
    residuals: np.ndarray | None
    labels: list[str]
    units: str | None  # as written in the file (None: the file does not say)
    units_origin: str  # where the units came from, e.g. "POINT:UNITS"
    rate_hz: float
    first_frame: int
    format: str  # "c3d" | "trc" | ...
    reader: str  # library / parser that read it: "ezc3d", "c3d", "trc"
    up_axis: str | None = None  # from file metadata, if any
    up_axis_origin: str = ""  # e.g. "C3D POINT:Y_SCREEN '+Z'"
    default_up_axis: str = "+z"  # the format's convention when nothing else is known
    default_up_reason: str = "default (+z, the usual C3D lab convention)"
    label_prefixes: list[str] | None = None  # prefixes the file declares (C3D SUBJECTS:LABEL_PREFIXES)
    point_slots: bool = False  # True: columns are per-frame point lists of a raw stream, not tracks
    warnings: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)


@dataclass
class MarkerData:
    """Markers of one capture, in metres, in the file's world axes.

    positions:  (T, M, 3) float64 metres, NaN where missing
    visible:    (T, M) bool, True where the marker was seen
    rate_hz:    frame rate (may be non-integer, e.g. 65.036)
    labels:     (M,) names with subject prefixes stripped; placeholders ('M001', '*12') when unnamed
    labelled:   False when the names are placeholders (unlabeled capture) or columns are raw point slots
    units_found: the units string found in the file ('mm', 'm', 'mete', ...) or '' when it gave none
    up_axis:    '+z', '+y', ... ; up_axis_source says how it was determined
    residuals:  (T, M) float64 as in the file (C3D), or None (TRC)
    first_frame: frame number of the first frame as written in the file (C3D header / TRC Frame#)
    stamps_ns:  (T,) int64, frame index / rate, starting at 0
    source:     the path that was read
    warnings:   every quirk the reader worked around, one line each
    raw_labels: (M,) names exactly as in the file (subject prefixes kept)
    placeholder: (M,) bool, True where that marker's name is a placeholder
    """

    positions: np.ndarray
    visible: np.ndarray
    rate_hz: float
    labels: list[str]
    labelled: bool
    units_found: str
    up_axis: str
    residuals: np.ndarray | None
    first_frame: int
    stamps_ns: np.ndarray
    source: str
    warnings: list[str]
    up_axis_source: str = ""
    units_used: str = ""  # the units actually applied (differs from units_found when the file lied)
    format: str = ""
    reader: str = ""
    raw_labels: list[str] = field(default_factory=list)
    placeholder: np.ndarray | None = None
    dropped_points: list[str] = field(default_factory=list)  # non-marker points left out (angles, forces, model points)
    meta: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.rate_hz

    @property
    def missing_fraction(self) -> float:
        return float(1.0 - self.visible.mean()) if self.visible.size else 1.0

    @property
    def subjects(self) -> list[str]:
        """Distinct subject prefixes found on labels ('Subject' for 'Subject:LASI')."""
        out = []
        for raw, lab in zip(self.raw_labels, self.labels):
            if raw != lab and raw.endswith(lab) and raw[: -len(lab)].endswith(":"):
                p = raw[: -len(lab) - 1]
                if p not in out:
                    out.append(p)
        return out

    def summary(self, n_labels: int = 8) -> dict:
        """What the reader understood, as plain JSON-able values (used by `uuomocap markers info`)."""
        never_seen = [lab for lab, v in zip(self.labels, self.visible.any(axis=0)) if not v]
        return {
            "file": self.source,
            "format": self.format,
            "reader": self.reader,
            "frames": self.n_frames,
            "first_frame": self.first_frame,
            "rate_hz": self.rate_hz,
            "duration_s": round(self.duration_s, 6),
            "markers": self.n_markers,
            "units_found": self.units_found,
            "units_used": self.units_used,
            "up_axis": self.up_axis,
            "up_axis_source": self.up_axis_source,
            "missing_fraction": round(self.missing_fraction, 6),
            "markers_never_seen": never_seen,
            "labelled": self.labelled,
            "labels_first": self.labels[:n_labels],
            "subjects": self.subjects,
            "residuals": self.residuals is not None,
            "dropped_points": len(self.dropped_points),
            "warnings": list(self.warnings),
        }


# ---------------------------------------------------------------------------------------------
# Dispatch
# ---------------------------------------------------------------------------------------------

ReaderFn = Callable[..., "RawMarkers | MarkerData"]


def _c3d_reader(path: Path, progress: bool = False) -> RawMarkers:
    from uuomocap.protocol.marker_c3d import read_c3d_raw

    return read_c3d_raw(path)


def _trc_reader(path: Path, progress: bool = False) -> RawMarkers:
    from uuomocap.protocol.marker_trc import read_trc_raw

    return read_trc_raw(path, progress=progress)


# Suffix (lower case, with dot) -> reader(path, progress=bool).  A reader returns RawMarkers (this
# module interprets units, missing encodings, labels and the up axis) or a finished MarkerData
# (formats that are already in our conventions, e.g. our own MCAP recordings).
def _mcap_reader(path: Path, progress: bool = False) -> MarkerData:
    # our own graph recordings (owner: streaming graph, protocol/recording.py)
    from uuomocap.protocol.recording import read_markers_mcap

    return read_markers_mcap(path)


MARKER_READERS: dict[str, ReaderFn] = {".c3d": _c3d_reader, ".trc": _trc_reader, ".mcap": _mcap_reader}


def register_reader(suffix: str, reader: ReaderFn) -> None:
    """Add a reader for files ending in ``suffix`` (e.g. ``".mcap"``).

    ``reader(path: Path, progress: bool = False)`` returns RawMarkers (interpreted here) or a finished
    MarkerData, and raises MarkerFileError for files it cannot read.
    """
    suffix = suffix.lower()
    if not suffix.startswith("."):
        suffix = "." + suffix
    MARKER_READERS[suffix] = reader


def _sniff_suffix(path: Path) -> str | None:
    """Guess the format from the content when the extension is unknown or missing."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return None
    if len(head) >= 2 and head[1] == 0x50 and 1 <= head[0] <= 127:
        return ".c3d"
    text = head.decode("latin-1", "replace").lstrip().lower()
    if text.startswith("pathfiletype") or text.startswith("datarate"):
        return ".trc"
    return None


def read_markers(path, *, keep_model_points: bool = False, progress: bool = False) -> MarkerData:
    """Read a marker file (.c3d, .trc) into metres; raise MarkerFileError with a one-line reason.

    keep_model_points: keep points a biomechanical model computed (Plug-in Gait segment axes
        'LFEO/LFEA/LFEL/LFEP', 'CentreOfMass'), which are not physical markers; they are
        dropped by default.  Angles/forces/moments/powers stored as C3D points are never
        positions and are always dropped.
    progress: show a progress bar on stderr for long text files.
    """
    path = Path(path)
    name = str(path)
    if not path.exists():
        raise MarkerFileError(f"{name}: no such file")
    if path.is_dir():
        raise MarkerFileError(f"{name}: is a directory, not a marker file")
    if path.stat().st_size == 0:
        raise MarkerFileError(f"{name}: empty file (0 bytes)")
    suffix = path.suffix.lower()
    reader = MARKER_READERS.get(suffix)
    if reader is None:
        sniffed = _sniff_suffix(path)
        reader = MARKER_READERS.get(sniffed) if sniffed else None
        if reader is None:
            known = ", ".join(sorted(MARKER_READERS))
            raise MarkerFileError(f"{name}: unsupported marker file type '{suffix or '(none)'}' (supported: {known})")
    try:
        raw = reader(path, progress=progress)
        if isinstance(raw, MarkerData):
            return raw
        return _interpret(raw, name, keep_model_points=keep_model_points)
    except MarkerFileError:
        raise
    except MemoryError:
        raise MarkerFileError(f"{name}: file too large to load into memory") from None
    except Exception as exc:  # a library failed in a way we did not foresee: still one line, naming the file
        raise MarkerFileError(f"{name}: could not read ({type(exc).__name__}: {exc})") from exc


# ---------------------------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------------------------

_UNIT_METRES = {
    "mm": 1e-3,
    "cm": 1e-2,
    "dm": 1e-1,
    "m": 1.0,
    "km": 1e3,
    "in": 0.0254,
    "ft": 0.3048,
}
_UNIT_LONG = {  # long names; C3D stores UNITS in a fixed 4-char field so 'meters' arrives as 'mete'
    "millimeters": "mm",
    "millimetres": "mm",
    "millimeter": "mm",
    "millimetre": "mm",
    "centimeters": "cm",
    "centimetres": "cm",
    "centimeter": "cm",
    "centimetre": "cm",
    "decimeters": "dm",
    "decimetres": "dm",
    "meters": "m",
    "metres": "m",
    "meter": "m",
    "metre": "m",
    "inches": "in",
    "inch": "in",
    "feet": "ft",
    "foot": "ft",
}


def unit_metres(text: str | None) -> float | None:
    """Metres per unit for a units string as found in a file ('mm' -> 0.001), None if unknown."""
    unit = parse_units(text)
    return None if unit is None else _UNIT_METRES.get(unit)


def parse_units(text: str | None) -> str | None:
    """Canonical unit ('mm', 'cm', 'm', ...) for a units string as found in a file, None if unknown.

    Accepts truncated long names ('mete', 'mill', 'cent') because C3D writers cut UNITS to 4 chars.
    """
    if text is None:
        return None
    t = text.replace("\x00", "").strip().strip(".").lower()
    if not t:
        return None
    if t in _UNIT_METRES:
        return t
    if t in _UNIT_LONG:
        return _UNIT_LONG[t]
    if len(t) >= 3:
        hits = {unit for long, unit in _UNIT_LONG.items() if long.startswith(t)}
        if len(hits) == 1:
            return hits.pop()
    return None


# ---------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------

_PLACEHOLDER_RES = [
    re.compile(r"^\*\s*\d+$"),  # Vicon Nexus unlabeled trajectories: '*12'
    re.compile(r"^M\d{3,}$"),  # ours (write_c3d default): 'M001'
    re.compile(r"^\d+$"),  # bare numbers
    re.compile(
        r"^(unnamed|unlabel+ed|unidentified|unknown|untitled|no[ _-]?name|marker|point|pt|traj|trajectory|"
        r"track|new|uname\*?|c3d|mkr)[\s_\-.#*]*\d*$",
        re.IGNORECASE,
    ),
]


def is_placeholder_label(label: str) -> bool:
    """True for names that carry no identity: '*12', 'M001', 'Unnamed', 'Marker3', 'Unlabeled 1004', ''."""
    lab = label.strip()
    return lab == "" or any(r.match(lab) for r in _PLACEHOLDER_RES)


def placeholder_labels(n: int) -> list[str]:
    """'M001', 'M002', ... (the unlabeled names our writers use)."""
    width = max(3, len(str(n)))
    return [f"M{i + 1:0{width}d}" for i in range(n)]


def _strip_prefixes(raw: list[str], declared: list[str] | None, warnings: list[str]) -> list[str]:
    """'Subject:LASI' -> 'LASI'.  Declared prefixes (C3D SUBJECTS:LABEL_PREFIXES) first, else 'xxx:'."""
    declared = [p for p in (declared or []) if p]
    out = []
    for lab in raw:
        stripped = lab
        for p in declared:
            if lab.startswith(p) and len(lab) > len(p):
                stripped = lab[len(p) :]
                break
        else:
            m = re.match(r"^([^:]+):(.+)$", lab)
            if m and m.group(2).strip():
                stripped = m.group(2)
        out.append(stripped.strip())
    if len(set(out)) < len(set(raw)):
        # Two subjects with the same marker names: stripping would merge identities.
        warnings.append("labels of several subjects share names; subject prefixes kept")
        return [lab.strip() for lab in raw]
    return out


def _make_unique(labels: list[str], warnings: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    dups = []
    for lab in labels:
        if lab in seen:
            seen[lab] += 1
            dups.append(lab)
            out.append(f"{lab}_{seen[lab]}")
        else:
            seen[lab] = 1
            out.append(lab)
    if dups:
        warnings.append(f"duplicate labels renamed with a suffix: {', '.join(sorted(set(dups))[:5])}")
    return out


# Biomechanical model outputs stored as points.  Plug-in Gait / BodyBuilder segment axes come as
# quartets STEM+O/A/L/P (origin, anterior, lateral, proximal); they sit up to 0.4 m off the body.
_MODEL_POINT_NAMES = {"centreofmass", "centerofmass", "centreofmassfloor", "centerofmassfloor", "com", "comfloor"}


def _model_points(labels: list[str]) -> list[int]:
    names = set(labels)
    idx = []
    for i, lab in enumerate(labels):
        if lab.lower() in _MODEL_POINT_NAMES:
            idx.append(i)
            continue
        if len(lab) >= 3 and lab[-1] in "OALP":
            stem = lab[:-1]
            if all(stem + s in names for s in "OALP"):
                idx.append(i)
    return idx


# ---------------------------------------------------------------------------------------------
# Up axis
# ---------------------------------------------------------------------------------------------

_AXES = "xyz"


def parse_axis(text: str | None) -> str | None:
    """'+Z' / 'z' / '-Y' -> '+z' / '+z' / '-y'; None when not an axis."""
    if text is None:
        return None
    t = text.replace("\x00", "").strip().lower()
    m = re.match(r"^([+-]?)\s*([xyz])$", t)
    if not m:
        return None
    return (m.group(1) or "+") + m.group(2)


def infer_up_axis(positions: np.ndarray, max_frames: int = 600) -> tuple[str | None, str]:
    """Guess the up axis of a human capture from the markers alone.

    positions: (T, M, 3) metres, NaN missing.  Returns (up_axis or None, reason).
    Cues: a standing/moving person is about twice as tall as wide, so the axis with the
    largest per-frame extent is vertical; the lab floor is usually at 0, so the feet sit
    near 0 and the head 0.8-2.6 m above it, which also gives the sign.  Ghost points are
    rejected per frame (farther than 1.5 m from the frame's median point).
    None when the evidence is weak (partial bodies, lying poses, odd origins).
    """
    T = positions.shape[0]
    frames = np.unique(np.linspace(0, T - 1, num=min(T, max_frames)).round().astype(int))
    ext, low, high = [], [], []
    for t in frames:
        p = positions[t]
        p = p[~np.isnan(p).any(axis=1)]
        if len(p) < 3:
            continue
        med = np.median(p, axis=0)
        p = p[np.linalg.norm(p - med, axis=1) < 1.5]
        if len(p) < 3:
            continue
        lo, hi = p.min(axis=0), p.max(axis=0)
        ext.append(hi - lo)
        low.append(lo)
        high.append(hi)
    if len(ext) < 5:
        return None, "too few frames with 3+ visible markers to infer"
    extent = np.median(np.array(ext), axis=0)
    low_m = np.median(np.array(low), axis=0)
    high_m = np.median(np.array(high), axis=0)
    order = np.argsort(extent)[::-1]
    a1, a2 = int(order[0]), int(order[1])
    ratio = float(extent[a1] / max(extent[a2], 1e-9))

    def floor_ok(axis: int, sign: int) -> bool:
        lo = low_m[axis] if sign > 0 else -high_m[axis]
        hi = high_m[axis] if sign > 0 else -low_m[axis]
        return -0.15 <= lo <= 0.35 and 0.8 <= hi <= 2.6

    floor_hits = [(a, s) for a in range(3) for s in (1, -1) if floor_ok(a, s)]
    axis_name = _AXES[a1]
    if ratio >= 1.5:
        signs = [s for a, s in floor_hits if a == a1]
        if len(signs) == 1:
            up = ("+" if signs[0] > 0 else "-") + axis_name
            return up, (
                f"inferred from the markers: body extent along {axis_name} is {ratio:.1f}x the next axis, "
                f"floor near {axis_name}=0"
            )
        up = "+" + axis_name
        return up, (
            f"inferred from the markers: body extent along {axis_name} is {ratio:.1f}x the next axis; "
            "no floor near 0, sign assumed +"
        )
    if len(floor_hits) == 1 and floor_hits[0][0] == a1:
        a, s = floor_hits[0]
        up = ("+" if s > 0 else "-") + _AXES[a]
        return up, (
            f"inferred from the markers: only {_AXES[a]} has a floor near 0 with the body 0.8-2.6 m above it, "
            f"and it is the longest body extent ({ratio:.2f}x)"
        )
    return None, f"markers do not show a clear vertical axis (extent ratio {ratio:.2f})"


# ---------------------------------------------------------------------------------------------
# Interpretation shared by all formats
# ---------------------------------------------------------------------------------------------


def clean_rate(rate: float) -> float:
    """Undo float32 storage noise: 65.03600311 (C3D float32) -> 65.036 when that is the same float32."""
    r = float(rate)
    f32 = np.float32(r)
    if float(f32) != r:
        return r
    for digits in range(0, 7):
        cand = round(r, digits)
        if np.float32(cand) == f32:
            return float(cand)
    return r


def _robust_spread(coords: np.ndarray, max_frames: int = 400) -> float:
    """Typical size of the captured point cloud, in file units, robust to ghosts.

    Per sampled frame: largest 10-90 percentile range over the three axes; median over frames.
    Falls back to the range over time when frames hold fewer than 3 points (single markers).
    """
    T = coords.shape[0]
    frames = np.unique(np.linspace(0, T - 1, num=min(T, max_frames)).round().astype(int))
    vals = []
    for t in frames:
        p = coords[t]
        p = p[~np.isnan(p).any(axis=1)]
        if len(p) >= 3:
            q = np.percentile(p, [10, 90], axis=0)
            vals.append(float((q[1] - q[0]).max()))
    if vals and np.median(vals) > 0:
        return float(np.median(vals))
    p = coords.reshape(-1, 3)
    p = p[~np.isnan(p).any(axis=1)]
    if len(p) < 2:
        return 0.0
    q = np.percentile(p, [10, 90], axis=0)
    return float((q[1] - q[0]).max())


def _interpret(raw: RawMarkers, name: str, keep_model_points: bool = False) -> MarkerData:
    warnings = list(raw.warnings)
    coords = np.asarray(raw.coords, dtype=np.float64)
    if coords.ndim != 3 or coords.shape[-1] != 3:
        raise MarkerFileError(f"{name}: internal reader error, coordinates have shape {coords.shape}")
    T, M, _ = coords.shape
    if T == 0:
        raise MarkerFileError(f"{name}: zero frames")
    if M == 0:
        raise MarkerFileError(f"{name}: no marker points (0 columns)")
    rate = float(raw.rate_hz) if raw.rate_hz is not None else float("nan")
    if not math.isfinite(rate) or rate <= 0:
        raise MarkerFileError(f"{name}: invalid frame rate {raw.rate_hz!r}")
    rate = clean_rate(rate)

    # --- labels (pad / cut to M) ---
    raw_labels = [str(s).replace("\x00", "").strip() for s in raw.labels][:M]
    if len(raw_labels) < M:
        if raw_labels:
            warnings.append(f"file names {len(raw_labels)} markers but holds {M} columns; extra columns unnamed")
        raw_labels += [""] * (M - len(raw_labels))

    # --- drop points that are model outputs, not markers ---
    dropped: list[str] = []
    keep = np.ones(M, dtype=bool)
    if not keep_model_points:
        idx = _model_points(raw_labels)
        if idx and len(idx) < M:
            keep[idx] = False
            dropped = [raw_labels[i] for i in idx]
            warnings.append(
                f"left out {len(idx)} model-computed points that are not physical markers "
                f"(e.g. {', '.join(dropped[:4])}); read with keep_model_points=True to keep them"
            )
    if not keep.all():
        coords = coords[:, keep]
        raw_labels = [lab for lab, k in zip(raw_labels, keep) if k]
    residuals = None if raw.residuals is None else np.asarray(raw.residuals, dtype=np.float64)[:, keep]
    M = coords.shape[1]

    # --- missing encodings -> NaN ---
    missing = np.isnan(coords).any(axis=-1)
    if residuals is not None:
        missing |= residuals < 0
    zeros = np.all(coords == 0.0, axis=-1) & ~missing
    n_zero = int(zeros.sum())
    if n_zero:
        missing |= zeros
        if residuals is not None and np.any(residuals[zeros] >= 0):
            warnings.append(f"{n_zero} samples at exactly (0,0,0) with a non-negative residual treated as missing")
        elif raw.format != "c3d":
            warnings.append(f"{n_zero} samples at exactly (0,0,0) treated as missing")
    coords = coords.copy()
    coords[missing] = np.nan
    if missing.all():
        raise MarkerFileError(f"{name}: every marker sample is missing (all NaN / zero)")

    # --- units ---
    units_found = (raw.units or "").replace("\x00", "").strip()
    unit = parse_units(units_found) if units_found else None
    if units_found and unit is None:
        raise MarkerFileError(f"{name}: unknown units '{units_found}' in {raw.units_origin}")
    if unit is None:
        unit = "mm"
        warnings.append(f"no units in the file ({raw.units_origin} absent); assuming mm")
    elif unit != units_found.lower():
        warnings.append(f"units '{units_found}' read as '{unit}'")
    spread_file = _robust_spread(coords)
    spread_m = spread_file * _UNIT_METRES[unit]
    if spread_m > 0 and not (0.005 <= spread_m <= 50.0):
        # The header lies (e.g. 'm' on millimetre numbers): choose the unit that gives a body-sized cloud.
        fits = [u for u in ("mm", "cm", "m") if 0.05 <= spread_file * _UNIT_METRES[u] <= 5.0]
        if not fits:
            raise MarkerFileError(
                f"{name}: absurd marker spread of {spread_file:.3g} {unit} ({spread_m:.3g} m) that no unit explains"
            )
        best = min(fits, key=lambda u: abs(math.log10(spread_file * _UNIT_METRES[u])))
        warnings.append(
            f"units say '{units_found or unit}' but the markers spread {spread_file:.4g} units "
            f"({spread_m:.4g} m); the data look like {best}, using {best}"
        )
        unit = best
    # Divide by 1000 rather than multiply by 0.001: the result is then the correctly rounded metre
    # value, identical to what any other tool computes from the same millimetres.
    divisor = {"mm": 1000.0, "cm": 100.0, "dm": 10.0}.get(unit)
    positions = coords / divisor if divisor else coords * _UNIT_METRES[unit]

    # --- labels: prefixes, placeholders, uniqueness ---
    labels = _strip_prefixes(raw_labels, raw.label_prefixes, warnings)
    placeholder = np.array([is_placeholder_label(lab) for lab in labels], dtype=bool)
    fill = placeholder_labels(M)
    labels = [fill[i] if not lab else lab for i, lab in enumerate(labels)]
    labels = _make_unique(labels, warnings)
    n_ph = int(placeholder.sum())
    labelled = (not raw.point_slots) and n_ph * 2 < M
    if 0 < n_ph < M:
        warnings.append(f"{n_ph} of {M} labels are placeholders (unlabeled trajectories)")

    # --- up axis ---
    up = raw.up_axis
    if up is not None:
        source = raw.up_axis_origin
        guess, why = infer_up_axis(positions)
        if guess is not None and guess != up and "sign assumed" not in why:
            warnings.append(f"{raw.up_axis_origin} gives up axis {up} but the markers look {guess}-up; keeping {up}")
    else:
        guess, why = infer_up_axis(positions)
        if guess is not None:
            up, source = guess, why
        else:
            up, source = raw.default_up_axis, f"{raw.default_up_reason}; {why}"

    # --- report ---
    visible = ~np.isnan(positions).any(axis=-1)
    never = [lab for lab, v in zip(labels, visible.any(axis=0)) if not v]
    if never:
        warnings.append(f"{len(never)} marker(s) never visible: {', '.join(never[:5])}")
    stamps = np.round(np.arange(T, dtype=np.float64) * (1e9 / rate)).astype(np.int64)
    return MarkerData(
        positions=positions,
        visible=visible,
        rate_hz=rate,
        labels=labels,
        labelled=labelled,
        units_found=units_found,
        up_axis=up,
        residuals=residuals,
        first_frame=int(raw.first_frame),
        stamps_ns=stamps,
        source=name,
        warnings=warnings,
        up_axis_source=source,
        units_used=unit,
        format=raw.format,
        reader=raw.reader,
        raw_labels=raw_labels,
        placeholder=placeholder,
        dropped_points=dropped + list(raw.meta.get("non_position_points", [])),
        meta=dict(raw.meta),
    )


# ---------------------------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------------------------


def _check_write_args(positions, rate_hz, labels, up_axis) -> tuple[np.ndarray, float, list[str], str]:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise ValueError(f"positions must be (T, M, 3) metres, got shape {pos.shape}")
    T, M, _ = pos.shape
    if T == 0 or M == 0:
        raise ValueError(f"positions must have at least one frame and one marker, got shape {pos.shape}")
    if np.isinf(pos).any():
        raise ValueError("positions contain inf; use NaN for missing markers")
    rate = float(rate_hz)
    if not math.isfinite(rate) or rate <= 0:
        raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
    if labels is None:
        labels = placeholder_labels(M)
    labels = [str(s) for s in labels]
    if len(labels) != M:
        raise ValueError(f"{len(labels)} labels for {M} markers")
    if len(set(labels)) != M:
        raise ValueError("labels must be unique")
    for lab in labels:
        if not lab or not lab.isascii() or any(c in lab for c in "\t\r\n"):
            raise ValueError(f"label {lab!r} must be non-empty printable ASCII without tabs/newlines")
    up = parse_axis(up_axis)
    if up is None:
        raise ValueError(f"up_axis must be like '+z', '+y', '-z', got {up_axis!r}")
    return pos, rate, labels, up


def _atomic_target(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=str(path.parent))
    os.close(fd)
    return Path(tmp)


def write_c3d(path, positions, rate_hz, labels=None, up_axis: str = "+z", residuals=None) -> Path:
    """Write markers to a C3D file with ezc3d.

    positions: (T, M, 3) metres, NaN = missing.  Stored as float mm, POINT:UNITS 'mm'; missing
    markers are written as (0,0,0) with residual -1 (the C3D convention every reader knows).
    labels: (M,) names, default placeholders 'M001'... (an unlabeled capture).
    up_axis: recorded as POINT:Y_SCREEN (with a matching horizontal X_SCREEN); data are not rotated.
    residuals: optional (T, M) non-negative residuals (mm) of visible markers; default 0.
    """
    import ezc3d

    path = Path(path)
    pos, rate, labels, up = _check_write_args(positions, rate_hz, labels, up_axis)
    T, M, _ = pos.shape
    missing = np.isnan(pos).any(axis=-1)
    pts = np.zeros((4, M, T), dtype=np.float64)
    pts[:3] = np.where(missing[..., None], 0.0, pos * 1000.0).transpose(2, 1, 0)
    pts[3] = 1.0
    res = np.zeros((T, M), dtype=np.float64)
    if residuals is not None:
        res = np.asarray(residuals, dtype=np.float64).reshape(T, M).copy()
        if (res[~missing] < 0).any():
            raise ValueError("residuals of visible markers must be >= 0")
    res[missing] = -1.0

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([rate])
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [""] * M
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    axis = up[1].upper()
    x_screen = "+Y" if axis == "X" else "+X"
    c.add_parameter("POINT", "X_SCREEN", x_screen)
    c.add_parameter("POINT", "Y_SCREEN", up[0] + axis)
    c.add_parameter("MANUFACTURER", "SOFTWARE", "uuomocap")
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {
        "residuals": res.T[None, :, :].copy(),
        "camera_masks": np.zeros((7, M, T), dtype=bool),
    }
    tmp = _atomic_target(path)
    try:
        c.write(str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# An axis-aligned rotation taking each up axis onto +y (TRC's / OpenSim's up): rows map (x, y, z).
_TO_Y_UP = {
    "+y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "+z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),   # -90 deg about x: z -> y, y -> -z
    "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),   # +90 deg about x
    "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # 180 deg about x
    "+x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),   # +90 deg about z: x -> y
    "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),   # -90 deg about z
}


def to_y_up(up_axis: str) -> np.ndarray:
    """(3, 3) rotation taking a world with ``up_axis`` up into a +y-up one (``p_y = R @ p``)."""
    return np.asarray(_TO_Y_UP[up_axis], dtype=np.float64)


def write_trc(path, positions, rate_hz, labels=None, up_axis: str = "+y", units: str = "mm") -> Path:
    """Write markers to a TRC text file (OpenSim / Motion Analysis layout).

    positions: (T, M, 3) metres, NaN = missing (written as blank fields).
    units: 'mm' (default) or 'm'.  TRC has no up-axis field and OpenSim reads every TRC +y up, so
    a capture with another up axis is turned into +y up (``to_y_up``: a 90 or 180 degree turn, the
    same turn for every point).  The header holds exactly OpenSim's eight keys: opensim 4.6's
    TRCFileAdapter rejects a ninth ('Incorrect number of keys'), which is why the 'UpAxis' key this
    writer added before is gone (our reader still honours it in old files).
    """
    path = Path(path)
    pos, rate, labels, up = _check_write_args(positions, rate_hz, labels, up_axis)
    if units not in ("mm", "m"):
        raise ValueError(f"units must be 'mm' or 'm', got {units!r}")
    pos = pos @ to_y_up(up).T
    T, M, _ = pos.shape
    scale = 1000.0 if units == "mm" else 1.0
    decimals = 5 if units == "mm" else 8
    rate_s = f"{rate:.10g}"
    keys = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]
    vals = [rate_s, rate_s, str(T), str(M), units, rate_s, "1", str(T)]
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(keys),
        "\t".join(vals),
        "Frame#\tTime\t" + "\t".join(f"{lab}\t\t" for lab in labels).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(M)),
        "",
    ]
    data = pos * scale
    data[np.isnan(data).any(axis=-1)] = np.nan  # a point is missing as a whole
    fmt = f"{{:.{decimals}f}}".format
    for t in range(T):
        # NaN formats as 'nan'; blank it so missing markers are empty fields, as OpenSim writes them.
        coords = "\t".join(map(fmt, data[t].ravel().tolist())).replace("nan", "")
        lines.append(f"{t + 1}\t{t / rate:.6f}\t{coords}")
    tmp = _atomic_target(path)
    try:
        tmp.write_text("\n".join(lines) + "\n", encoding="ascii")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
