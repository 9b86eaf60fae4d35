"""Per-video-frame body priors from any estimator, in the prior.npz layout.

Three ways in, one result (``PriorSequence``):
* BlazePose landmarks -> ``prior_from_landmarks`` (fits the body model, see landmark_fit);
* SMPL-parameter estimators (a user's HMR-class ONNX model, imported 4D-Humans/PHALP
  tracks) -> ``prior_from_smpl_rotations``, which accepts rotation matrices, 6D or
  axis-angle.

Root orientations are in the OpenCV camera frame (x right, y down, z forward), as the
estimators give them.  Frames without an estimate get valid=False, confidence 0, and
the parameters of the nearest valid frame (so every array is finite); the solver's
prior preparation re-fills them by slerp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from uuomocap.solver_core import rotations
from uuomocap.solver_core.blazepose import LandmarkResult
from uuomocap.solver_core.landmark_fit import LandmarkFitConfig, fit_landmarks, symmetry_report


@dataclass
class PriorSequence:
    """prior.npz content for F video frames (see the session contract in the project brief)."""

    stamps_ns: np.ndarray  # (F,) int64, video clock
    rate_hz: float
    global_orient: np.ndarray  # (F, 3) axis-angle, camera frame
    body_pose: np.ndarray  # (F, 23, 3) axis-angle
    betas: np.ndarray  # (F, B)
    valid: np.ndarray  # (F,) bool
    confidence: np.ndarray  # (F,) in [0, 1]
    body_model: str  # the model the betas belong to ("open-low", "smpl", ...)
    estimator: str
    keypoints3d: np.ndarray | None = None  # (F, K, 3) metres, camera axes, hip-centred
    info: dict = field(default_factory=dict)

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {
            "rate_hz": np.asarray(float(self.rate_hz)),
            "stamps_ns": np.asarray(self.stamps_ns, np.int64),
            "global_orient": np.asarray(self.global_orient, np.float32),
            "body_pose": np.asarray(self.body_pose, np.float32),
            "betas": np.asarray(self.betas, np.float32),
            "valid": np.asarray(self.valid, bool),
            "confidence": np.asarray(self.confidence, np.float32),
            "camera_frame": np.asarray(True),
            "body_model": np.asarray(self.body_model),
            "estimator": np.asarray(self.estimator),
        }
        if self.keypoints3d is not None:
            out["keypoints3d"] = np.asarray(self.keypoints3d, np.float32)
        return out


def nearest_valid_index(valid: np.ndarray) -> np.ndarray:
    """(F,) index of the nearest valid frame for every frame (itself when valid)."""
    valid = np.asarray(valid, bool)
    good = np.flatnonzero(valid)
    if len(good) == 0:
        return np.arange(len(valid))
    pos = np.searchsorted(good, np.arange(len(valid))).clip(1, len(good) - 1) if len(good) > 1 else None
    if pos is None:
        return np.full(len(valid), good[0])
    left, right = good[pos - 1], good[pos]
    idx = np.arange(len(valid))
    return np.where(np.abs(idx - left) <= np.abs(right - idx), left, right)


def rotations_to_matrices(x: np.ndarray, num_joints: int, what: str) -> np.ndarray:
    """Rotations in any common layout -> (F, num_joints, 3, 3).

    Accepts (F, J, 3, 3) / (F, J*9) matrices, (F, J, 6) / (F, J*6) 6D (two columns,
    Zhou et al.), (F, J, 3) / (F, J*3) axis-angle.  ``what`` names the array in errors.
    """
    arr = np.asarray(x, np.float64)
    n = arr.shape[0]
    per_joint = arr.reshape(n, -1).shape[1] / num_joints
    t = torch.from_numpy(arr.reshape(n, num_joints, -1) if per_joint in (3, 6, 9) else arr)
    if per_joint == 9:
        return t.reshape(n, num_joints, 3, 3).numpy()
    if per_joint == 6:
        return rotations.rot6d_to_matrix(t).numpy()
    if per_joint == 3:
        return rotations.axis_angle_to_matrix(t).numpy()
    raise ValueError(f"{what} has shape {arr.shape}: expected {num_joints} rotations per frame as 3x3 "
                     "matrices, 6D or axis-angle")


def matrices_to_axis_angle(mats: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3), projecting onto SO(3) first (network outputs are rarely exact)."""
    u, _, vt = np.linalg.svd(np.asarray(mats, np.float64))
    det = np.linalg.det(u @ vt)
    fix = np.ones_like(u[..., 0, :])
    fix[..., -1] = det
    r = (u * fix[..., None, :]) @ vt
    return rotations.matrix_to_axis_angle(torch.from_numpy(r)).numpy()


def prior_from_smpl_rotations(global_orient, body_pose, betas, valid, confidence, stamps_ns, rate_hz: float,
                              estimator: str, body_model: str = "smpl", keypoints3d=None,
                              info: dict | None = None) -> PriorSequence:
    """Build a prior from per-frame SMPL parameters (any rotation layout, see rotations_to_matrices).

    global_orient: (F, ...) one rotation per frame; body_pose: (F, ...) 23 rotations;
    betas (F, B); valid (F,) bool; confidence (F,); stamps_ns (F,) int64.
    """
    valid = np.asarray(valid, bool)
    n = len(valid)
    go = matrices_to_axis_angle(rotations_to_matrices(np.asarray(global_orient).reshape(n, -1), 1, "global_orient"))
    bp = matrices_to_axis_angle(rotations_to_matrices(np.asarray(body_pose).reshape(n, -1), 23, "body_pose"))
    betas = np.asarray(betas, np.float64).reshape(n, -1)
    near = nearest_valid_index(valid)
    conf = np.where(valid, np.asarray(confidence, np.float64), 0.0)
    return PriorSequence(
        stamps_ns=np.asarray(stamps_ns, np.int64), rate_hz=float(rate_hz), global_orient=go[near, 0],
        body_pose=bp[near], betas=betas[near], valid=valid, confidence=conf, body_model=body_model,
        estimator=estimator, keypoints3d=None if keypoints3d is None else np.asarray(keypoints3d)[near],
        info=dict(info or {}))


def prior_from_landmarks(results: list[LandmarkResult | None], stamps_ns, rate_hz: float, model,
                         body_model: str, config: LandmarkFitConfig = LandmarkFitConfig(),
                         progress=None) -> PriorSequence:
    """Fit the body model to BlazePose world landmarks of every frame (None = no person)."""
    n = len(results)
    valid = np.array([r is not None for r in results], bool)
    world = np.zeros((n, 33, 3))
    vis = np.zeros((n, 33))
    score = np.zeros(n)
    for i, r in enumerate(results):
        if r is not None:
            world[i], vis[i], score[i] = r.world, r.visibility[:33], r.pose_score
    fit = fit_landmarks(model, world, vis, valid, config, progress=progress)
    near = nearest_valid_index(valid)
    # Confidence: the model's person score times the mean visibility of the limb landmarks.
    confidence = np.where(valid, score * vis[:, 11:29].mean(1), 0.0)
    info = {
        "frames": n,
        "frames_with_person": int(valid.sum()),
        "detection_rate": float(valid.mean()) if n else 0.0,
        "fit_residual_mm_median": float(np.nanmedian(fit.residual) * 1000) if valid.any() else float("nan"),
        "bone_symmetry": symmetry_report(world, vis, valid) if valid.any() else {},
    }
    return PriorSequence(
        stamps_ns=np.asarray(stamps_ns, np.int64), rate_hz=float(rate_hz),
        global_orient=fit.global_orient[near], body_pose=fit.body_pose[near],
        betas=np.broadcast_to(fit.betas, (n, len(fit.betas))).copy(), valid=valid, confidence=confidence,
        body_model=body_model, estimator="blazepose", keypoints3d=world[near], info=info)


@dataclass(frozen=True)
class PriorFrame:
    """One video frame's body prior, as ``StreamingVideoPrior`` hands it out."""

    key: object  # the caller's frame key (the video node: the frame index)
    global_orient: np.ndarray  # (3,) axis-angle, OpenCV camera frame
    body_pose: np.ndarray  # (23, 3) axis-angle
    betas: np.ndarray  # (B,)
    valid: bool  # False: no person in this frame; the parameters are the last fitted frame's (zeros before any)
    confidence: float  # the person / pose score of the frame, 0 when not valid
    keypoints3d: np.ndarray | None  # (33, 3) BlazePose world landmarks (metres, camera axes), None without them


class StreamingVideoPrior:
    """The video body prior for a live stream: RGB frames in one at a time, finished frames out in order.

    ``estimator`` 'blazepose': BlazePose GHUM 3D, then the body model fitted to its 3D landmarks
    ``batch_frames`` at a time (``StreamingLandmarkFitter``; latency batch_frames / rate).
    'onnx-hmr:MODEL.onnx': a user's HMR-class network on BlazePose's person box, one frame per call,
    any rotation layout turned into axis-angle (the SMPL parameters ``prior_from_smpl_rotations`` takes).
    A frame without a person holds the last fitted parameters with valid=False, so every frame is finite.
    """

    def __init__(self, estimator: str, detector_path, landmark_path, body_model: str = "open-low",
                 batch_frames: int = 15):
        from .pose_estimators import BlazePoseEstimator, OnnxHmrEstimator

        tracker = BlazePoseEstimator(detector_path, landmark_path)
        self.fitter = None
        if estimator.startswith("onnx-hmr:"):
            self.estimator, self.body_model = OnnxHmrEstimator(estimator.split(":", 1)[1], tracker), "smpl"
        elif estimator == "blazepose":
            from .body_model import load_body_model
            from .landmark_fit import StreamingLandmarkFitter

            self.estimator, self.body_model = tracker, body_model
            self.fitter = StreamingLandmarkFitter(load_body_model(body_model), batch_frames=batch_frames)
        else:
            raise ValueError(f"estimator {estimator!r} is not 'blazepose' or 'onnx-hmr:MODEL.onnx'")
        self.person_found = False  # in the last frame pushed
        self._results: dict[object, object] = {}  # key -> the estimator's result, until the frame is finished
        self._last = (np.zeros(3), np.zeros((23, 3)), np.zeros(10))

    def push(self, key, image_rgb: np.ndarray) -> list[PriorFrame]:
        """Estimate one frame (``image_rgb`` (H, W, 3) uint8); returns the frames this call finished."""
        result = self.estimator.process(image_rgb)
        self.person_found = result is not None
        self._results[key] = result
        if self.fitter is None:  # HMR output: one rotation / 23 rotations in any layout -> axis-angle
            fit = None if result is None else (
                matrices_to_axis_angle(rotations_to_matrices(np.asarray(result.global_orient).reshape(1, -1), 1, "global_orient"))[0, 0],
                matrices_to_axis_angle(rotations_to_matrices(np.asarray(result.body_pose).reshape(1, -1), 23, "body_pose"))[0],
                result.betas)
            return self._finish([(key, fit)])
        return self._finish(self.fitter.push(key, None if result is None else result.world,
                                             None if result is None else result.visibility))

    def flush(self) -> list[PriorFrame]:
        """Finish every frame still waiting for its batch (end of the video)."""
        return self._finish(self.fitter.flush()) if self.fitter is not None else []

    def _finish(self, finished: list[tuple[object, tuple | None]]) -> list[PriorFrame]:
        out = []
        for key, fit in finished:
            result = self._results.pop(key)
            if fit is not None:
                self._last = (np.asarray(fit[0], np.float64).reshape(3), np.asarray(fit[1], np.float64).reshape(23, 3),
                              np.asarray(fit[2], np.float64).reshape(-1))
            score = 0.0 if result is None else float(getattr(result, "pose_score", getattr(result, "score", 1.0)))
            world = getattr(result, "world", None)
            out.append(PriorFrame(key, *self._last, valid=fit is not None, confidence=score if fit is not None else 0.0,
                                  keypoints3d=None if world is None else np.asarray(world, np.float32)))
        return out
