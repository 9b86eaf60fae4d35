"""Simulated video body prior: what a monocular estimator (HMR 2.0, BlazePose-based fits, ...)
would output for the session's video, written as ``prior.npz`` at the video rate.

The error model, each part a parameter of ``PriorErrorModel`` (defaults and why):

- Camera frame.  The root orientation is expressed in the OpenCV frame of the video camera
  (x right, y down, z forward), whose pose the solver does not know.  Because the camera is
  placed at a random azimuth around the subject, the prior's heading relative to the world
  is off by a yaw that is uniform over 360 degrees by default: the reason the paper tests
  four yaw hypotheses (Sec. "Mocap Solving", Stage 1).  The camera is upright and roughly
  level but not exactly: a few degrees of pitch/roll remain (set by the camera, see
  ``camera.place_camera``).
- Per-joint rotation error with temporal correlation.  Monocular estimators are biased in a
  way that drifts slowly (depth ambiguity, self-occlusion) plus a little frame-to-frame
  jitter.  Modelled as an AR(1) (first-order low-pass) process per joint and axis with
  stationary RMS angle ``pose_noise_rad`` (0.15 rad ~ 8.6 deg: the per-joint angular error
  of current estimators is roughly 5-15 deg) and correlation time ``pose_noise_tau_s``
  (0.3 s), plus white jitter ``pose_jitter_rad`` (0.02 rad).  The root gets its own, smaller
  error ``root_noise_rad`` (0.08 rad) on top of the unknown yaw.
- Shape error.  Regressed shapes shrink towards the mean body and carry an identity error:
  prior betas = ``shape_shrink`` * true + N(0, ``shape_noise``) per component (0.5 / 0.5 of a
  standard deviation), constant over the clip, plus a per-frame jitter ``shape_jitter`` (0.05).
- No metric translation or scale.  A single camera cannot see absolute depth, so the prior
  has no translation at all; ``keypoints3d`` are root-relative.
- Tracking dropouts.  Each frame a tracked person is lost with probability
  ``dropout_prob`` (1 % per frame, ~every 3 s at 30 Hz) for ``dropout_frames`` (3-15) frames;
  such frames are ``valid = False`` with confidence 0 and identity pose (no NaN, so naive
  readers do not crash, but they must honour ``valid``).
- Clocks.  ``clock_offset_s`` (marker time = video time + offset) is written to
  session.yaml; ``sync_error_s`` is an extra offset the session does NOT record (default
  0); ``true_rate_hz`` lets the video really run at e.g. 29.97 Hz while its stamps claim the
  nominal 30 Hz (the paper met this on CMU Kitchen; default: no mismatch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .motions import Motion, axis_angle_to_matrices, matrices_to_axis_angle, sample_motion_at


@dataclass(frozen=True)
class PriorErrorModel:
    """Monocular-estimator error model (see the module docstring for the rationale)."""

    video_rate_hz: float = 30.0
    pose_noise_rad: float = 0.15
    pose_noise_tau_s: float = 0.3
    pose_jitter_rad: float = 0.02
    root_noise_rad: float = 0.08
    shape_shrink: float = 0.5
    shape_noise: float = 0.5
    shape_jitter: float = 0.05
    dropout_prob: float = 0.01
    dropout_frames: tuple[int, int] = (3, 15)
    clock_offset_s: float = 0.0
    sync_error_s: float = 0.0
    true_rate_hz: float | None = None

    def __post_init__(self):
        for name in ("video_rate_hz",):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        for name in ("pose_noise_rad", "pose_jitter_rad", "root_noise_rad", "shape_noise", "shape_jitter"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.dropout_prob <= 1:
            raise ValueError(f"dropout_prob must be in [0, 1], got {self.dropout_prob}")
        if self.true_rate_hz is not None and not self.true_rate_hz > 0:
            raise ValueError("true_rate_hz must be positive")


def ar1_noise(num_frames: int, shape: tuple, rms: float, tau_s: float, rate_hz: float,
              rng: np.random.Generator) -> np.ndarray:
    """Stationary AR(1) noise (F, *shape): x_k = a x_{k-1} + sqrt(1-a^2) s e_k, a = exp(-dt/tau).

    ``rms`` is the stationary RMS of the vector norm when the last axis has 3 components
    (each component gets rms / sqrt(3)).
    """
    s = rms / np.sqrt(shape[-1]) if shape else rms
    a = float(np.exp(-1.0 / (rate_hz * tau_s))) if tau_s > 0 else 0.0
    e = rng.normal(0.0, s, (num_frames,) + tuple(shape))
    out = np.empty_like(e)
    out[0] = e[0]
    c = np.sqrt(1.0 - a * a)
    for k in range(1, num_frames):
        out[k] = a * out[k - 1] + c * e[k]
    return out


def dropout_mask(num_frames: int, prob: float, frames: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """(F,) bool valid: runs of invalid frames start with probability ``prob`` per valid frame."""
    valid = np.ones(num_frames, dtype=bool)
    draws = rng.random(num_frames)
    lengths = rng.integers(frames[0], frames[1] + 1, num_frames)
    k = 0
    while k < num_frames:
        if draws[k] < prob:
            valid[k:k + int(lengths[k])] = False
            k += int(lengths[k])
        else:
            k += 1
    return valid


def video_content_times(duration_s: float, model: PriorErrorModel) -> tuple[np.ndarray, np.ndarray]:
    """Video frames covering the marker clip.

    -> (stamps_ns (K,) video clock at the NOMINAL rate, content_s (K,) the marker-clock time
    each frame really shows = offset + sync error + k / true rate).  Frames showing times
    before the markers start are kept (the subject is still); the video ends with the clip.
    """
    true_rate = model.true_rate_hz or model.video_rate_hz
    t0 = model.clock_offset_s + model.sync_error_s
    k_max = int(np.floor((duration_s - t0) * true_rate + 1e-9))
    if k_max < 1:
        raise ValueError(f"clock offset {t0:.3f} s leaves no video frame inside the {duration_s:.3f} s clip")
    k = np.arange(k_max + 1)
    stamps = np.round(k / model.video_rate_hz * 1e9).astype(np.int64)
    return stamps, t0 + k / true_rate


def simulate_prior(gt: Motion, model, betas: np.ndarray, R_wc: np.ndarray, error: PriorErrorModel, seed: int,
                   body_model_name: str) -> tuple[dict, np.ndarray]:
    """Simulated ``prior.npz`` arrays for a ground-truth motion seen by a camera with
    world-from-camera rotation ``R_wc``.

    Returns (arrays per the session contract, content_s (K,) marker-clock time of each video
    frame; the renderer shows the ground truth at exactly those times).
    """
    from .lbs import forward

    rng_pose, rng_root, rng_shape, rng_drop = (np.random.default_rng([int(seed), 202, k]) for k in range(4))
    duration = (gt.num_frames - 1) / gt.rate_hz
    stamps, content = video_content_times(duration, error)
    K = stamps.shape[0]
    poses, _ = sample_motion_at(gt, np.clip(content, 0.0, duration))
    rot = axis_angle_to_matrices(poses.reshape(K, 24, 3))

    body_noise = ar1_noise(K, (23, 3), error.pose_noise_rad, error.pose_noise_tau_s, error.video_rate_hz, rng_pose)
    body_noise += rng_pose.normal(0.0, error.pose_jitter_rad / np.sqrt(3), body_noise.shape)
    root_noise = ar1_noise(K, (3,), error.root_noise_rad, error.pose_noise_tau_s, error.video_rate_hz, rng_root)
    body = rot[:, 1:] @ axis_angle_to_matrices(body_noise)
    root_cam = R_wc.T[None] @ rot[:, 0] @ axis_angle_to_matrices(root_noise)

    b = np.asarray(betas, dtype=np.float64)
    shape = error.shape_shrink * b + rng_shape.normal(0.0, error.shape_noise, b.shape)
    betas_f = shape[None] + rng_shape.normal(0.0, error.shape_jitter, (K, b.shape[0]))

    valid = dropout_mask(K, error.dropout_prob, error.dropout_frames, rng_drop)
    # Confidence: lower when the pose error is large and next to a dropout.
    err = np.linalg.norm(body_noise, axis=-1).mean(1)
    conf = np.clip(1.0 - err / (4 * max(error.pose_noise_rad, 1e-6)), 0.2, 1.0)
    near = np.convolve((~valid).astype(float), np.ones(5), mode="same") > 0
    conf = np.where(near, 0.5 * conf, conf)

    go = matrices_to_axis_angle(root_cam)
    bp = matrices_to_axis_angle(body)
    # Root-relative 3D joints in the camera frame from the noisy pose and shape.
    pose_cam = np.concatenate([go[:, None], bp], 1)
    with torch.no_grad():
        out = forward(model, torch.as_tensor(betas_f, dtype=torch.float32), torch.as_tensor(pose_cam, dtype=torch.float32))
    kp = out.joints.double().numpy()
    kp = kp - kp[:, :1]
    go[~valid] = 0.0
    bp[~valid] = 0.0
    kp[~valid] = 0.0
    conf[~valid] = 0.0
    arrays = {
        "rate_hz": np.float64(error.video_rate_hz),
        "stamps_ns": stamps,
        "global_orient": go.astype(np.float32),
        "body_pose": bp.astype(np.float32),
        "betas": betas_f.astype(np.float32),
        "valid": valid,
        "confidence": conf.astype(np.float32),
        "camera_frame": np.bool_(True),
        "body_model": np.str_(body_model_name),
        "keypoints3d": kp.astype(np.float32),
    }
    return arrays, content
