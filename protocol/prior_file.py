"""prior.npz: a per-video-frame body prior (the session contract's layout).

Keys (F video frames): rate_hz (), stamps_ns (F,) int64 video clock, global_orient (F,3)
axis-angle in the camera frame, body_pose (F,23,3) axis-angle, betas (F,B), valid (F,)
bool, confidence (F,), camera_frame () bool, body_model () str; optional keypoints3d
(F,K,3) and estimator () str.  Written without pickles, read with allow_pickle=False.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

REQUIRED = ("rate_hz", "stamps_ns", "global_orient", "body_pose", "betas", "valid", "confidence",
            "camera_frame", "body_model")


class PriorFileError(ValueError):
    """prior.npz is missing, unreadable or does not follow the layout (message names the key)."""


def validate_prior_arrays(arrays: dict) -> int:
    """Check keys, shapes and dtypes; returns F.  Raises PriorFileError naming the first problem."""
    for key in REQUIRED:
        if key not in arrays:
            raise PriorFileError(f"prior is missing the array '{key}'")
    stamps = np.asarray(arrays["stamps_ns"])
    if stamps.ndim != 1 or stamps.dtype.kind not in "iu":
        raise PriorFileError(f"stamps_ns must be (F,) integers, got {stamps.shape} {stamps.dtype}")
    n = stamps.shape[0]
    expect = {"global_orient": (n, 3), "body_pose": (n, 23, 3), "valid": (n,), "confidence": (n,)}
    for key, shape in expect.items():
        if np.asarray(arrays[key]).shape != shape:
            raise PriorFileError(f"{key} must have shape {shape}, got {np.asarray(arrays[key]).shape}")
    betas = np.asarray(arrays["betas"])
    if betas.ndim != 2 or betas.shape[0] != n:
        raise PriorFileError(f"betas must be (F, B) with F={n}, got {betas.shape}")
    if "keypoints3d" in arrays:
        kp = np.asarray(arrays["keypoints3d"])
        if kp.ndim != 3 or kp.shape[0] != n or kp.shape[2] != 3:
            raise PriorFileError(f"keypoints3d must be (F, K, 3), got {kp.shape}")
    if n > 1 and np.any(np.diff(stamps.astype(np.int64)) <= 0):
        raise PriorFileError("stamps_ns must increase strictly")
    for key in ("global_orient", "body_pose", "betas", "confidence"):
        if not np.all(np.isfinite(np.asarray(arrays[key], np.float64))):
            raise PriorFileError(f"{key} holds NaN or inf")
    return n


def write_prior_npz(path: str | Path, arrays: dict) -> Path:
    """Validate and write atomically (temporary file, then rename)."""
    validate_prior_arrays(arrays)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **{k: np.asarray(v) for k, v in arrays.items()})
    os.replace(tmp, path)
    return path


def read_prior_npz(path: str | Path) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise PriorFileError(f"prior file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as exc:
        raise PriorFileError(f"{path}: not a readable .npz ({exc})") from None
    try:
        validate_prior_arrays(arrays)
    except PriorFileError as exc:
        raise PriorFileError(f"{path}: {exc}") from None
    return arrays
