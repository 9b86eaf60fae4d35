"""Import 4D-Humans / PHALP tracking results (the ``.pkl`` written with joblib).

Layout (facts of the PHALP output format): a dict ``{frame_name: frame_dict}``, frames in
name order; per frame, index-aligned lists ``tid`` (track id), ``tracked_time`` (0 when
the track was seen in this frame, >0 when it is being carried through an occlusion),
``bbox``, ``smpl`` (dicts with ``global_orient`` (1,3,3), ``body_pose`` (23,3,3),
``betas`` (10,)), ``camera``, ``3d_joints``, ...  ``tracked_ids`` is a different list
(not aligned with ``smpl``): detections are paired with tracks through ``tid`` only.

The file is read with the project's restricted unpickler (numpy arrays and joblib's
array wrapper only; anything else, e.g. a ``__reduce__`` payload, is refused) -- the
4D-Humans pickle is untrusted input.
"""

from __future__ import annotations

import bz2
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uuomocap.solver_core.safe_pickle import UnsafePickleError, load_restricted_pickle


class PhalpFormatError(ValueError):
    """The file is not a readable PHALP/4D-Humans result (message says why)."""


@dataclass(frozen=True)
class PhalpTrack:
    """One person's track over all F frames of the file (frames in name order).

    global_orient (F, 3, 3) camera frame; body_pose (F, 23, 3, 3); betas (F, B);
    valid (F,) True where the track was seen (tracked_time == 0); bbox (F, 4) or NaN;
    camera (F, 3) or NaN; joints3d (F, K, 3) or None; confidence (F,).
    """

    track_id: int
    frame_names: list[str]
    global_orient: np.ndarray
    body_pose: np.ndarray
    betas: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    bbox: np.ndarray
    camera: np.ndarray
    joints3d: np.ndarray | None
    track_lengths: dict[int, int]  # every track in the file -> frames seen


_LZ4_MAGIC = b"\x04\x22\x4d\x18"


def load_phalp_pickle(path: str | Path) -> dict:
    """The raw ``{frame_name: frame_dict}`` of a PHALP pickle, read without running code."""
    path = Path(path)
    if not path.is_file():
        raise PhalpFormatError(f"PHALP result file not found: {path}")
    raw = path.read_bytes()
    if raw[:4] == _LZ4_MAGIC:
        raise PhalpFormatError(f"{path}: lz4-compressed joblib files are not supported; re-save with "
                               "joblib.dump(..., compress=3) (zlib) or uncompressed")
    if raw[:3] == b"BZh":
        raw = bz2.decompress(raw)
    try:
        data = load_restricted_pickle(io.BytesIO(raw), allowed=("numpy", "joblib"))
    except UnsafePickleError as exc:
        raise PhalpFormatError(f"{path}: unsafe pickle, not loaded ({exc})") from None
    except Exception as exc:  # truncated or not a pickle at all
        raise PhalpFormatError(f"{path}: not a readable PHALP pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or not data:
        raise PhalpFormatError(f"{path}: expected a non-empty dict of frames, got {type(data).__name__}")
    return data


def _aligned(frame: dict, key: str, n: int, name: str) -> list:
    values = frame.get(key)
    if values is None:
        return [None] * n
    values = list(values)
    if len(values) != n:
        raise PhalpFormatError(f"frame {name!r}: '{key}' has {len(values)} entries but 'tid' has {n}")
    return values


def track_lengths(data: dict) -> dict[int, int]:
    """Track id -> number of frames where it was seen (tracked_time == 0)."""
    counts: dict[int, int] = {}
    for name in sorted(data):
        frame = data[name]
        tids = list(frame.get("tid", []) or [])
        times = _aligned(frame, "tracked_time", len(tids), str(name))
        for tid, tt in zip(tids, times):
            if tt is None or int(tt) == 0:
                counts[int(tid)] = counts.get(int(tid), 0) + 1
    return counts


def phalp_track(data: dict, track_id: int | None = None) -> PhalpTrack:
    """Extract one track (default: the one seen in the most frames) as per-frame arrays."""
    if not isinstance(data, dict):
        raise PhalpFormatError("PHALP data must be a dict of frames")
    lengths = track_lengths(data)
    if not lengths:
        raise PhalpFormatError("no track is seen in any frame (every 'tid' list is empty)")
    if track_id is None:
        track_id = max(lengths, key=lambda t: (lengths[t], -t))
    elif track_id not in lengths:
        raise PhalpFormatError(f"track {track_id} is not in the file; tracks: {sorted(lengths)}")
    names = sorted(data)
    n = len(names)
    go = np.tile(np.eye(3), (n, 1, 1))
    bp = np.tile(np.eye(3), (n, 23, 1, 1))
    betas = None
    valid = np.zeros(n, bool)
    conf = np.zeros(n)
    bbox = np.full((n, 4), np.nan)
    camera = np.full((n, 3), np.nan)
    joints = None
    for i, name in enumerate(names):
        frame = data[name]
        if not isinstance(frame, dict):
            raise PhalpFormatError(f"frame {name!r} is a {type(frame).__name__}, not a dict")
        tids = [int(t) for t in (frame.get("tid", []) or [])]
        k = len(tids)
        times = _aligned(frame, "tracked_time", k, str(name))
        smpl = _aligned(frame, "smpl", k, str(name))
        hits = [j for j in range(k) if tids[j] == track_id and (times[j] is None or int(times[j]) == 0)]
        if not hits:
            continue
        j = hits[0]
        params = smpl[j]
        if not isinstance(params, dict) or not {"global_orient", "body_pose", "betas"} <= set(params):
            raise PhalpFormatError(f"frame {name!r}: smpl entry {j} lacks global_orient/body_pose/betas")
        try:
            go[i] = np.asarray(params["global_orient"], np.float64).reshape(3, 3)
            bp[i] = np.asarray(params["body_pose"], np.float64).reshape(23, 3, 3)
        except ValueError as exc:
            raise PhalpFormatError(f"frame {name!r}: smpl rotations are not 3x3 matrices ({exc})") from None
        b = np.asarray(params["betas"], np.float64).reshape(-1)
        if betas is None:
            betas = np.zeros((n, len(b)))
        betas[i, : len(b)] = b[: betas.shape[1]]
        valid[i] = True
        confs = _aligned(frame, "conf", k, str(name))
        conf[i] = float(np.clip(np.asarray(confs[j], np.float64).mean(), 0, 1)) if confs[j] is not None else 1.0
        boxes = _aligned(frame, "bbox", k, str(name))
        if boxes[j] is not None:
            bbox[i] = np.asarray(boxes[j], np.float64).reshape(-1)[:4]
        cams = _aligned(frame, "camera", k, str(name))
        if cams[j] is not None:
            camera[i] = np.asarray(cams[j], np.float64).reshape(-1)[:3]
        j3d = _aligned(frame, "3d_joints", k, str(name))
        if j3d[j] is not None:
            arr = np.asarray(j3d[j], np.float64).reshape(-1, 3)
            if joints is None:
                joints = np.full((n, arr.shape[0], 3), np.nan)
            if arr.shape[0] == joints.shape[1]:
                joints[i] = arr
    return PhalpTrack(track_id=int(track_id), frame_names=[str(x) for x in names], global_orient=go,
                      body_pose=bp, betas=betas if betas is not None else np.zeros((n, 10)), valid=valid,
                      confidence=conf, bbox=bbox, camera=camera, joints3d=joints, track_lengths=lengths)
