"""Session directories: one capture (markers, optional video / body prior / ground truth).

A session is a directory::

    session.yaml   format, rates, clock offset video -> markers, body model, provenance
    markers.c3d    unlabeled marker trajectories (or .trc), read through ``markerio``
    video.mp4      optional video of the same take
    prior.npz      optional per-video-frame body prior (camera frame)
    gt.npz         optional ground truth, AMASS layout (users' real captures have none)

session.yaml::

    format: uuomocap-session/1
    markers: {file: markers.c3d, rate_hz: 60.0, up_axis: "+z"}
    video:   {file: video.mp4, rate_hz: 30.0, clock_offset_s: 0.0}   # marker_time = video_time + offset
                                                                     # (no 'file' when only the prior exists)
    prior:   {file: prior.npz}
    gt:      {file: gt.npz}
    body_model: open-low
    provenance: {generator: ..., seed: ..., ...}

``load_session`` validates everything it loads and raises ``SessionError`` with one line
naming the file and the problem (missing files, wrong keys or shapes, NaN in ground truth,
numbers that look like millimetres or degrees).  ``write_npz`` writes byte-reproducible npz
files (fixed zip timestamps), so the same generator inputs give identical files.
"""

from __future__ import annotations

import io
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .markerio import MarkerData, MarkerFileError, read_markers, write_c3d

SESSION_FORMAT = "uuomocap-session/1"
SESSION_YAML = "session.yaml"

# prior.npz: key -> (trailing shape after the frame axis, or None for a scalar); '*' = any size.
PRIOR_FRAME_KEYS = {
    "stamps_ns": (),
    "global_orient": (3,),
    "body_pose": (23, 3),
    "betas": ("*",),
    "valid": (),
    "confidence": (),
}
PRIOR_SCALAR_KEYS = ("rate_hz", "camera_frame", "body_model")
GT_FRAME_KEYS = {"poses": (72,), "trans": (3,), "joints": (24, 3), "stamps_ns": ()}
GT_SCALAR_KEYS = ("mocap_framerate", "body_model", "gender")
GT_MARKER_KEYS = ("marker_faces", "marker_bary", "marker_offset_m")
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")  # the vertical axis a capture may name


class SessionError(ValueError):
    """A session that cannot be used; the message is one line naming the file and the problem."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


# ----------------------------------------------------------------------------- npz files


def write_npz(path: str | Path, arrays: dict, compress: bool = True) -> Path:
    """Write arrays to ``path`` as .npz with reproducible bytes (fixed member timestamps).

    numpy's savez stamps each member with the current time, so two identical sessions would
    differ; here every member gets 1980-01-01.  Object arrays are refused (no pickles).
    Written to a temporary file and renamed, so readers never see half a file.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    try:
        with zipfile.ZipFile(tmp, "w", compression=method) as zf:
            for key, value in arrays.items():
                arr = np.asanyarray(value)
                if arr.dtype == object:
                    raise ValueError(f"{path.name}: array {key!r} has dtype object; only plain arrays are stored")
                buf = io.BytesIO()
                np.lib.format.write_array(buf, arr, allow_pickle=False)
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = method
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of an .npz, never unpickling (object arrays raise SessionError)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise SessionError(f"{path}: file not found") from None
    except ValueError as exc:
        if "pickle" in str(exc).lower():
            raise SessionError(f"{path}: contains pickled objects, which are never loaded") from None
        raise SessionError(f"{path}: not a valid npz ({exc})") from None
    except (OSError, zipfile.BadZipFile) as exc:
        raise SessionError(f"{path}: not a valid npz ({exc})") from None


# ----------------------------------------------------------------------------- validation


def _shape_ok(arr: np.ndarray, frames: int, trailing: tuple) -> bool:
    if arr.ndim != 1 + len(trailing) or arr.shape[0] != frames:
        return False
    return all(t == "*" or t == s for t, s in zip(trailing, arr.shape[1:]))


def _fmt_shape(frames, trailing) -> str:
    return "(" + ", ".join([str(frames)] + [("B" if t == "*" else str(t)) for t in trailing]) + ")"


def _check_angles(arr: np.ndarray, where: str, key: str) -> None:
    a = np.asarray(arr, dtype=np.float64).reshape(-1, 3)
    a = a[np.isfinite(a).all(1)]
    if a.size and np.linalg.norm(a, axis=1).max() > 2.5 * np.pi:
        raise SessionError(f"{where}: {key} has rotation angles up to {np.linalg.norm(a, axis=1).max():.1f}; "
                           f"axis-angle must be in radians (looks like degrees)")


def validate_prior(arrays: dict, where: str) -> int:
    """Check prior.npz arrays against the contract; returns the number of frames."""
    missing = [k for k in (*PRIOR_FRAME_KEYS, *PRIOR_SCALAR_KEYS) if k not in arrays]
    if missing:
        raise SessionError(f"{where}: missing key(s) {', '.join(missing)} (prior.npz needs "
                           f"{', '.join((*PRIOR_SCALAR_KEYS, *PRIOR_FRAME_KEYS))})")
    n = int(np.asarray(arrays["stamps_ns"]).shape[0]) if np.asarray(arrays["stamps_ns"]).ndim == 1 else -1
    if n < 1:
        raise SessionError(f"{where}: stamps_ns must be a non-empty (F,) array")
    for key, trailing in PRIOR_FRAME_KEYS.items():
        arr = np.asarray(arrays[key])
        if not _shape_ok(arr, n, trailing):
            raise SessionError(f"{where}: {key} has shape {arr.shape}; expected {_fmt_shape(n, trailing)}")
    for key in PRIOR_SCALAR_KEYS:
        if np.asarray(arrays[key]).ndim != 0:
            raise SessionError(f"{where}: {key} must be a scalar, has shape {np.asarray(arrays[key]).shape}")
    rate = float(np.asarray(arrays["rate_hz"]))
    if not (np.isfinite(rate) and rate > 0):
        raise SessionError(f"{where}: rate_hz {rate} is not a positive frame rate")
    stamps = np.asarray(arrays["stamps_ns"])
    if stamps.dtype.kind not in "iu":
        raise SessionError(f"{where}: stamps_ns must be int64 nanoseconds, has dtype {stamps.dtype}")
    if n > 1 and not (np.diff(stamps) > 0).all():
        raise SessionError(f"{where}: stamps_ns must increase strictly")
    if n > 1:
        step = np.median(np.diff(stamps)) / 1e9
        if abs(step * rate - 1.0) > 0.05:
            raise SessionError(f"{where}: stamps_ns step {step:.6f} s does not match rate_hz {rate} (are stamps in ns?)")
    valid = np.asarray(arrays["valid"])
    if valid.dtype != bool:
        raise SessionError(f"{where}: valid must be bool, has dtype {valid.dtype}")
    for key in ("global_orient", "body_pose", "betas"):
        arr = np.asarray(arrays[key])
        if not np.isfinite(arr[valid]).all():
            raise SessionError(f"{where}: {key} has NaN/inf in frames marked valid")
    _check_angles(np.asarray(arrays["global_orient"])[valid], where, "global_orient")
    _check_angles(np.asarray(arrays["body_pose"])[valid], where, "body_pose")
    if "keypoints3d" in arrays:
        kp = np.asarray(arrays["keypoints3d"])
        if kp.ndim != 3 or kp.shape[0] != n or kp.shape[2] != 3:
            raise SessionError(f"{where}: keypoints3d has shape {kp.shape}; expected ({n}, K, 3)")
    return n


def validate_gt(arrays: dict, where: str, frames: int | None = None, markers: int | None = None) -> int:
    """Check gt.npz arrays (AMASS layout + marker attachment); returns the number of frames."""
    required = ("betas", *GT_FRAME_KEYS, *GT_SCALAR_KEYS)
    missing = [k for k in required if k not in arrays]
    if missing:
        raise SessionError(f"{where}: missing key(s) {', '.join(missing)} (gt.npz needs {', '.join(required)})")
    n = int(np.asarray(arrays["poses"]).shape[0]) if np.asarray(arrays["poses"]).ndim == 2 else -1
    if n < 1:
        raise SessionError(f"{where}: poses must be (F, 72), has shape {np.asarray(arrays['poses']).shape}")
    for key, trailing in GT_FRAME_KEYS.items():
        arr = np.asarray(arrays[key])
        if not _shape_ok(arr, n, trailing):
            raise SessionError(f"{where}: {key} has shape {arr.shape}; expected {_fmt_shape(n, trailing)}")
    if np.asarray(arrays["betas"]).ndim != 1:
        raise SessionError(f"{where}: betas must be (B,), has shape {np.asarray(arrays['betas']).shape}")
    for key in ("betas", "poses", "trans", "joints"):
        if not np.isfinite(np.asarray(arrays[key], dtype=np.float64)).all():
            raise SessionError(f"{where}: {key} contains NaN or inf (ground truth must be complete)")
    rate = float(np.asarray(arrays["mocap_framerate"]))
    if not rate > 0:
        raise SessionError(f"{where}: mocap_framerate {rate} is not positive")
    _check_angles(np.asarray(arrays["poses"]), where, "poses")
    joints = np.asarray(arrays["joints"], dtype=np.float64)
    height = float(np.median(joints.max(1) - joints.min(1), axis=0).max())
    if height > 10.0:
        raise SessionError(f"{where}: joints span {height:.0f} units per frame; positions must be metres (looks like mm)")
    if np.abs(np.asarray(arrays["trans"], dtype=np.float64)).max() > 1000.0:
        raise SessionError(f"{where}: trans reaches {np.abs(arrays['trans']).max():.0f}; positions must be metres (looks like mm)")
    if frames is not None and n != frames:
        raise SessionError(f"{where}: {n} frames but the marker file has {frames}; gt must be at the marker rate")
    present = [k for k in GT_MARKER_KEYS if k in arrays]
    if present and len(present) != len(GT_MARKER_KEYS):
        raise SessionError(f"{where}: marker attachment needs all of {', '.join(GT_MARKER_KEYS)}")
    if present:
        mf = np.asarray(arrays["marker_faces"])
        mb = np.asarray(arrays["marker_bary"])
        if mf.ndim != 1 or mb.shape != (mf.shape[0], 3):
            raise SessionError(f"{where}: marker_faces {mf.shape} / marker_bary {mb.shape} must be (M,) / (M, 3)")
        if mf.dtype.kind not in "iu":
            raise SessionError(f"{where}: marker_faces must be integers, has dtype {mf.dtype}")
        if markers is not None and mf.shape[0] != markers:
            raise SessionError(f"{where}: attaches {mf.shape[0]} markers but the marker file has {markers}")
        real = mf >= 0
        if not np.isfinite(mb).all() or (mb[real] < -1e-6).any() or (np.abs(mb[real].sum(1) - 1) > 1e-4).any():
            raise SessionError(f"{where}: marker_bary must be barycentric weights (>= 0, summing to 1)")
        off = float(np.asarray(arrays["marker_offset_m"]))
        if not 0 <= off < 0.1:
            raise SessionError(f"{where}: marker_offset_m {off} is not a marker offset in metres (expected ~0.0095)")
    return n


# ----------------------------------------------------------------------------- session


@dataclass
class Session:
    """A loaded session.  prior / gt are dicts of arrays (None when absent)."""

    path: Path
    config: dict
    markers: MarkerData
    marker_file: Path
    up_axis: str
    body_model: str
    video_file: Path | None = None
    video_rate_hz: float | None = None
    clock_offset_s: float = 0.0
    prior: dict | None = None
    gt: dict | None = None
    provenance: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def rate_hz(self) -> float:
        return float(self.markers.rate_hz)

    @property
    def part(self) -> str:
        """The partial-body part the markers were placed on ('' = full body / unknown)."""
        if self.gt is not None and "part" in self.gt:
            return str(self.gt["part"])
        return str(self.provenance.get("part") or "")

    def summary(self) -> dict:
        return {
            "session": str(self.path),
            "markers_file": self.marker_file.name,
            "frames": self.markers.n_frames,
            "markers": self.markers.n_markers,
            "rate_hz": self.rate_hz,
            "up_axis": self.up_axis,
            "missing_fraction": round(self.markers.missing_fraction, 6),
            "video": self.video_file.name if self.video_file else None,
            "video_rate_hz": self.video_rate_hz,
            "clock_offset_s": self.clock_offset_s,
            "prior_frames": int(self.prior["stamps_ns"].shape[0]) if self.prior is not None else None,
            "ground_truth": self.gt is not None,
            "body_model": self.body_model,
            "part": self.part,
            "provenance": self.provenance,
            "warnings": self.warnings,
        }


def _section(cfg: dict, key: str, where: Path) -> dict | None:
    sec = cfg.get(key)
    if sec is None:
        return None
    if not isinstance(sec, dict):
        raise SessionError(f"{where}: '{key}' must be a mapping (e.g. {key}: {{file: ...}}), got {type(sec).__name__}")
    return sec


def _file_in(directory: Path, sec: dict, key: str, where: Path) -> Path:
    name = sec.get("file")
    if not isinstance(name, str) or not name:
        raise SessionError(f"{where}: '{key}.file' must name a file")
    p = Path(name)
    p = p if p.is_absolute() else directory / p
    if not p.is_file():
        raise SessionError(f"{where}: {key} file {p} is missing")
    return p


def _float(sec: dict, key: str, section: str, where: Path, default=None):
    if key not in sec or sec[key] is None:
        return default
    try:
        return float(sec[key])
    except (TypeError, ValueError):
        raise SessionError(f"{where}: {section}.{key} must be a number, got {sec[key]!r}") from None


def load_session(path: str | Path, load_prior: bool = True, load_gt: bool = True) -> Session:
    """Load and validate a session directory (see the module docstring for the layout)."""
    directory = Path(path)
    if not directory.is_dir():
        raise SessionError(f"{directory}: not a session directory (no such directory)")
    ypath = directory / SESSION_YAML
    if not ypath.is_file():
        raise SessionError(f"{directory}: no {SESSION_YAML}; a session needs session.yaml and a marker file")
    try:
        cfg = yaml.safe_load(ypath.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise SessionError(f"{ypath}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(cfg, dict):
        raise SessionError(f"{ypath}: must be a YAML mapping")
    if cfg.get("format") != SESSION_FORMAT:
        raise SessionError(f"{ypath}: format is {cfg.get('format')!r}; expected {SESSION_FORMAT!r}")
    warnings: list[str] = []

    msec = _section(cfg, "markers", ypath)
    if msec is None:
        raise SessionError(f"{ypath}: no 'markers' section (markers: {{file: markers.c3d}})")
    mfile = _file_in(directory, msec, "markers", ypath)
    try:
        md = read_markers(mfile)
    except MarkerFileError as exc:
        raise SessionError(str(exc)) from None
    rate = _float(msec, "rate_hz", "markers", ypath)
    if rate is not None and abs(rate - md.rate_hz) > 0.01 * md.rate_hz:
        raise SessionError(f"{ypath}: markers.rate_hz {rate} but {mfile.name} says {md.rate_hz}")
    up = msec.get("up_axis", md.up_axis)
    if up not in UP_AXES:
        raise SessionError(f"{ypath}: markers.up_axis {up!r} is not one of {', '.join(sorted(UP_AXES))}")
    if up != md.up_axis:
        warnings.append(f"session.yaml overrides the marker file's up axis {md.up_axis} with {up}")

    body_model = cfg.get("body_model", "open-low")
    if not isinstance(body_model, str) or not body_model:
        raise SessionError(f"{ypath}: body_model must be a model name or path")

    video_file, video_rate, offset = None, None, 0.0
    vsec = _section(cfg, "video", ypath)
    if vsec is not None:
        # A video section without a file still gives the clock of a prior made elsewhere.
        video_file = _file_in(directory, vsec, "video", ypath) if vsec.get("file") is not None else None
        video_rate = _float(vsec, "rate_hz", "video", ypath)
        if video_rate is not None and not video_rate > 0:
            raise SessionError(f"{ypath}: video.rate_hz must be positive")
        offset = _float(vsec, "clock_offset_s", "video", ypath, 0.0)

    prior = None
    psec = _section(cfg, "prior", ypath)
    if psec is not None and load_prior:
        ppath = _file_in(directory, psec, "prior", ypath)
        prior = read_npz(ppath)
        validate_prior(prior, str(ppath))
        prate = float(np.asarray(prior["rate_hz"]))
        if video_rate is not None and abs(prate - video_rate) > 0.01 * video_rate:
            raise SessionError(f"{ppath}: rate_hz {prate} differs from video.rate_hz {video_rate} in session.yaml")

    gt = None
    gsec = _section(cfg, "gt", ypath)
    gpath = _file_in(directory, gsec, "gt", ypath) if gsec is not None else directory / "gt.npz"
    if load_gt and gpath.is_file():
        gt = read_npz(gpath)
        validate_gt(gt, str(gpath), frames=md.n_frames, markers=md.n_markers)
        grate = float(np.asarray(gt["mocap_framerate"]))
        if abs(grate - md.rate_hz) > 1e-3 * md.rate_hz:
            raise SessionError(f"{gpath}: mocap_framerate {grate} differs from the marker rate {md.rate_hz}")
        if str(gt["body_model"]) != body_model:
            warnings.append(f"gt.npz body model {gt['body_model']} differs from session body_model {body_model}")

    prov = cfg.get("provenance") or {}
    if not isinstance(prov, dict):
        raise SessionError(f"{ypath}: provenance must be a mapping")
    return Session(directory, cfg, md, mfile, up, body_model, video_file, video_rate, float(offset), prior, gt,
                   prov, warnings + list(md.warnings))


def save_session(
    directory: str | Path,
    positions: np.ndarray,
    rate_hz: float,
    up_axis: str = "+z",
    body_model: str = "open-low",
    labels: list[str] | None = None,
    prior: dict | None = None,
    gt: dict | None = None,
    video_file: str | None = None,
    video_rate_hz: float | None = None,
    clock_offset_s: float = 0.0,
    provenance: dict | None = None,
) -> Path:
    """Write a session directory (created if needed); returns the session.yaml path.

    positions: (T, M, 3) metres, NaN = missing -> markers.c3d.  prior / gt: arrays per the
    contract (validated before anything is written).  video_file: name of an mp4 already in
    the directory (the caller renders it).  Files are byte-reproducible.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise SessionError(f"{directory}: marker positions must be (T, M, 3), got {positions.shape}")
    if up_axis not in UP_AXES:
        raise SessionError(f"{directory}: up_axis {up_axis!r} is not one of {', '.join(sorted(UP_AXES))}")
    if prior is not None:
        validate_prior(prior, f"{directory}/prior.npz")
    if gt is not None:
        validate_gt(gt, f"{directory}/gt.npz", frames=positions.shape[0], markers=positions.shape[1])
    if video_file is not None and not (directory / video_file).is_file():
        raise SessionError(f"{directory}: video file {video_file} is not in the session directory")
    write_c3d(directory / "markers.c3d", positions, rate_hz, labels=labels, up_axis=up_axis)
    cfg: dict = {"format": SESSION_FORMAT,
                 "markers": {"file": "markers.c3d", "rate_hz": float(rate_hz), "up_axis": up_axis}}
    if video_file is not None:
        cfg["video"] = {"file": video_file, "rate_hz": float(video_rate_hz or 30.0), "clock_offset_s": float(clock_offset_s)}
    if prior is not None:
        write_npz(directory / "prior.npz", prior)
        cfg["prior"] = {"file": "prior.npz"}
        if video_file is None:
            # No video file, but the prior runs on the video's clock: record its rate and offset.
            cfg["video"] = {"rate_hz": float(np.asarray(prior["rate_hz"])), "clock_offset_s": float(clock_offset_s)}
    if gt is not None:
        write_npz(directory / "gt.npz", gt)
        cfg["gt"] = {"file": "gt.npz"}
    cfg["body_model"] = body_model
    cfg["provenance"] = _plain(provenance or {})
    text = yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None, width=100)
    ypath = directory / SESSION_YAML
    tmp = ypath.with_name(ypath.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, ypath)
    return ypath


def set_session_clock_offset(directory: str | Path, offset_s: float, note: str = "") -> Path:
    """Record ``offset_s`` (marker time = video time + offset) as the session's video clock offset,
    keeping everything else in session.yaml; ``note`` says where it came from (kept beside it).
    The file is replaced atomically.  Returns the session.yaml path."""
    ypath = Path(directory) / SESSION_YAML
    load_session(directory, load_prior=False, load_gt=False)  # a valid session, or the reason it is not
    cfg = yaml.safe_load(ypath.read_text(encoding="utf-8"))
    video = cfg.get("video") if isinstance(cfg.get("video"), dict) else {}
    video["clock_offset_s"] = round(float(offset_s), 4)  # 0.1 ms: far below a video frame
    if note:
        video["clock_offset_note"] = str(note)
    cfg["video"] = video
    tmp = ypath.with_name(ypath.name + ".part")
    tmp.write_text(yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None, width=100), encoding="utf-8")
    os.replace(tmp, ypath)
    return ypath


def _plain(obj):
    """YAML-safe plain values (numpy scalars -> Python, tuples -> lists)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj
