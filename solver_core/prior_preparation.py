"""Prior preparation: turn a per-video-frame body estimate into a per-marker-frame body prior.

Paper section "Monocular Reconstruction from Video": the video estimator gives per-frame SMPL
pose and shape in the CAMERA frame; the solver needs one prior per MARKER frame in the capture
WORLD frame (up to an unknown yaw about the up axis, which the yaw hypotheses resolve).

Steps (each a pure function, usable on any window of frames):
1. ``fill_missing_prior_frames``: frames the estimator missed are filled - nearest valid frame at
   the ends, linear interpolation of translation/shape and slerp of every joint rotation inside.
2. ``prior_shape``: the shape prior is the mean shape over the valid frames.
3. ``camera_to_world_rotation``: OpenCV camera axes (x right, y down, z forward) -> world axes with
   the session's up axis.  The camera's heading in the world is unknown, so the world "forward" is
   an arbitrary horizontal axis; the solver's yaw offset absorbs the difference.
4. ``resample_prior``: video stamps + clock offset -> marker stamps (slerp between video frames,
   nearest beyond the ends).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core import rotations

# ----------------------------------------------------------------------------- axes


def up_axis_vector(up_axis: str) -> np.ndarray:
    """'+z' / '-y' / 'z' ... -> unit vector (3,) float64.  Raises ValueError on anything else."""
    text = str(up_axis).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in ("x", "y", "z"):
        raise ValueError(f"up axis {up_axis!r} is not one of +x, -x, +y, -y, +z, -z")
    vec = np.zeros(3)
    vec["xyz".index(name)] = sign
    return vec


def horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two horizontal unit axes (right, forward) with (right, -up, forward) right-handed.

    forward is the first world axis orthogonal to ``up`` in cyclic order after it (z-up -> +y,
    y-up -> +z, x-up -> +y), so that for a Z-up world the mapping equals the published code's
    camera (x, y, z) -> world (x, z, -y) convention.
    """
    up = np.asarray(up, dtype=np.float64)
    axis = int(np.argmax(np.abs(up)))
    forward = np.zeros(3)
    forward[{2: 1, 1: 2, 0: 1}[axis]] = 1.0
    down = -up
    right = np.cross(down, forward)
    return right, forward


def camera_to_world_rotation(up_axis: str) -> np.ndarray:
    """Rotation (3,3) mapping OpenCV camera vectors (x right, y down, z forward) to world vectors.

    Assumes a level camera (its y axis along gravity).  Columns are the world images of the
    camera axes: x -> right, y -> -up, z -> forward.
    """
    up = up_axis_vector(up_axis)
    right, forward = horizontal_basis(up)
    return np.stack([right, -up, forward], axis=1)


def canonical_to_world_rotation(up_axis: str) -> np.ndarray:
    """Rotation (3,3) taking the canonical body frame (Y up, faces +Z) into an upright world pose.

    Used for a prior-free start (markers-only): the body stands along the up axis and faces the
    world's 'forward' horizontal axis; the yaw hypotheses cover the heading.
    """
    up = up_axis_vector(up_axis)
    right, forward = horizontal_basis(up)
    # canonical +X is the body's left; with the body facing `forward` and up `up`, left = up x forward
    left = np.cross(up, forward)
    return np.stack([left, up, forward], axis=1)


# ----------------------------------------------------------------------------- rotations (numpy views)
# The rotation math lives in ``rotations`` (torch); these wrap it for float64 numpy arrays.


def slerp_axis_angle(aa0: np.ndarray, aa1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Shortest-arc interpolation.  aa0, aa1: (..., 3) axis-angle; w: broadcastable to (...,) in [0, 1]."""
    a0 = torch.as_tensor(np.asarray(aa0, dtype=np.float64))
    a1 = torch.as_tensor(np.asarray(aa1, dtype=np.float64))
    t = torch.as_tensor(np.broadcast_to(np.asarray(w, dtype=np.float64), a0.shape[:-1]).copy())
    return rotations.slerp_axis_angle(a0, a1, t).numpy()


def _aa_to_matrix(aa: np.ndarray) -> np.ndarray:
    return rotations.axis_angle_to_matrix(torch.as_tensor(np.asarray(aa, dtype=np.float64))).numpy()


def _matrix_to_aa(rot: np.ndarray) -> np.ndarray:
    return rotations.matrix_to_axis_angle(torch.as_tensor(np.asarray(rot, dtype=np.float64))).numpy()


# ----------------------------------------------------------------------------- the prior


@dataclass(frozen=True)
class BodyPrior:
    """A per-frame body prior (numpy float64).

    root_orient (T,3) axis-angle mapping the canonical body into the frame named by ``frame``
    ("camera" or "world"); body_pose (T,23,3) axis-angle; betas_per_frame (T,B);
    valid (T,) bool (estimator output present at that frame); confidence (T,);
    stamps_ns (T,) int64 on the clock named by ``frame`` semantics (video clock before
    resampling, marker clock after).
    """

    root_orient: np.ndarray
    body_pose: np.ndarray
    betas_per_frame: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    stamps_ns: np.ndarray
    frame: str

    @property
    def num_frames(self) -> int:
        return int(self.root_orient.shape[0])

    def poses72(self) -> np.ndarray:
        """(T,72) axis-angle: root then the 23 body joints (AMASS layout)."""
        return np.concatenate([self.root_orient, self.body_pose.reshape(self.num_frames, -1)], axis=1)


def prior_from_npz_arrays(arrays: dict) -> BodyPrior:
    """Build a camera-frame BodyPrior from prior.npz arrays (keys per the session contract).

    Raises ValueError naming the missing/ill-shaped key.
    """
    for key in ("stamps_ns", "global_orient", "body_pose", "betas", "valid"):
        if key not in arrays:
            raise ValueError(f"prior is missing the array {key!r}")
    go = np.asarray(arrays["global_orient"], dtype=np.float64)
    bp = np.asarray(arrays["body_pose"], dtype=np.float64)
    betas = np.asarray(arrays["betas"], dtype=np.float64)
    valid = np.asarray(arrays["valid"]).astype(bool)
    stamps = np.asarray(arrays["stamps_ns"]).astype(np.int64)
    n = go.shape[0]
    if go.shape != (n, 3):
        raise ValueError(f"prior global_orient must be (F,3), got {go.shape}")
    if bp.shape[0] != n or bp.reshape(n, -1).shape[1] != 69:
        raise ValueError(f"prior body_pose must be (F,23,3), got {bp.shape}")
    if betas.ndim == 1:
        betas = np.broadcast_to(betas, (n, betas.shape[0])).copy()
    if betas.shape[0] != n or valid.shape != (n,) or stamps.shape != (n,):
        raise ValueError("prior arrays disagree on the number of frames")
    if not valid.any():
        raise ValueError("prior has no valid frame")
    conf = np.asarray(arrays["confidence"], dtype=np.float64) if "confidence" in arrays else valid.astype(np.float64)
    camera_frame = bool(np.asarray(arrays.get("camera_frame", True)))
    return BodyPrior(go, bp.reshape(n, 23, 3), betas, valid, conf, stamps, "camera" if camera_frame else "world")


def fill_missing_prior_frames(prior: BodyPrior) -> BodyPrior:
    """Fill invalid frames: nearest valid frame before the first / after the last valid frame,
    linear interpolation of shape and slerp of every joint rotation in between.  ``valid`` keeps
    saying which frames were estimated (filled frames stay False)."""
    valid = prior.valid
    if not valid.any():
        raise ValueError("prior has no valid frame to fill from")
    idx = np.arange(prior.num_frames)
    good = idx[valid]
    # for each frame: the valid frame at/before and at/after (clamped at the ends -> nearest)
    after_pos = np.searchsorted(good, idx, side="left").clip(0, len(good) - 1)
    before_pos = (np.searchsorted(good, idx, side="right") - 1).clip(0, len(good) - 1)
    i0, i1 = good[before_pos], good[after_pos]
    span = (i1 - i0).astype(np.float64)
    w = np.where(span > 0, (idx - i0) / np.where(span > 0, span, 1.0), 0.0).clip(0.0, 1.0)
    rots = np.concatenate([prior.root_orient[:, None], prior.body_pose], axis=1)  # (T,24,3)
    filled = slerp_axis_angle(rots[i0], rots[i1], w[:, None])
    betas = prior.betas_per_frame[i0] * (1 - w[:, None]) + prior.betas_per_frame[i1] * w[:, None]
    conf = np.where(valid, prior.confidence, 0.0)
    return BodyPrior(filled[:, 0], filled[:, 1:], betas, valid.copy(), conf, prior.stamps_ns.copy(), prior.frame)


def prior_shape(prior: BodyPrior) -> np.ndarray:
    """(B,) the mean shape over the valid frames (paper: beta_img)."""
    return prior.betas_per_frame[prior.valid].mean(axis=0)


def prior_to_world(prior: BodyPrior, up_axis: str) -> BodyPrior:
    """Rotate a camera-frame prior's root orientation into the world (up to the unknown yaw)."""
    if prior.frame == "world":
        return prior
    r_wc = camera_to_world_rotation(up_axis)
    root = _matrix_to_aa(r_wc[None] @ _aa_to_matrix(prior.root_orient))
    return BodyPrior(root, prior.body_pose, prior.betas_per_frame, prior.valid, prior.confidence, prior.stamps_ns, "world")


def resample_prior(prior: BodyPrior, target_stamps_ns: np.ndarray, clock_offset_s: float = 0.0) -> BodyPrior:
    """Resample a (filled) prior to target stamps.

    target_stamps_ns: (T,) int64 marker-clock stamps.  clock_offset_s: marker_time = video_time + offset.
    Rotations slerp between the two neighbouring prior frames; beyond the ends the nearest frame is
    used.  valid/confidence come from the nearer source frame.
    """
    src = prior.stamps_ns.astype(np.float64) + float(clock_offset_s) * 1e9
    if np.any(np.diff(src) <= 0):
        raise ValueError("prior stamps must be strictly increasing")
    dst = np.asarray(target_stamps_ns, dtype=np.float64)
    j1 = np.searchsorted(src, dst, side="left").clip(1, max(len(src) - 1, 1)) if len(src) > 1 else np.zeros(len(dst), int)
    if len(src) == 1:
        j0 = j1 = np.zeros(len(dst), dtype=int)
        w = np.zeros(len(dst))
    else:
        j0 = j1 - 1
        w = ((dst - src[j0]) / (src[j1] - src[j0])).clip(0.0, 1.0)
    rots = np.concatenate([prior.root_orient[:, None], prior.body_pose], axis=1)
    out = slerp_axis_angle(rots[j0], rots[j1], w[:, None])
    betas = prior.betas_per_frame[j0] * (1 - w[:, None]) + prior.betas_per_frame[j1] * w[:, None]
    nearest = np.where(w < 0.5, j0, j1)
    return BodyPrior(
        out[:, 0],
        out[:, 1:],
        betas,
        prior.valid[nearest].copy(),
        prior.confidence[nearest].copy(),
        np.asarray(target_stamps_ns, dtype=np.int64).copy(),
        prior.frame,
    )


def prepare_prior(
    prior: BodyPrior, up_axis: str, marker_stamps_ns: np.ndarray, clock_offset_s: float = 0.0
) -> tuple[BodyPrior, np.ndarray]:
    """The whole preparation: fill, to world, resample to the marker stamps.

    Returns (prior at marker frames in the world frame up to yaw, shape prior (B,)).
    """
    filled = fill_missing_prior_frames(prior)
    shape = prior_shape(prior)
    world = prior_to_world(filled, up_axis)
    return resample_prior(world, marker_stamps_ns, clock_offset_s), shape


def neutral_prior(num_frames: int, up_axis: str, num_betas: int, stamps_ns: np.ndarray) -> BodyPrior:
    """A prior-free start: an upright neutral (zero-pose) body, for the markers-only baseline."""
    root = _matrix_to_aa(canonical_to_world_rotation(up_axis)[None])[0]
    return BodyPrior(
        np.repeat(root[None], num_frames, 0),
        np.zeros((num_frames, 23, 3)),
        np.zeros((num_frames, num_betas)),
        np.ones(num_frames, dtype=bool),
        np.ones(num_frames),
        np.asarray(stamps_ns, dtype=np.int64),
        "world",
    )
