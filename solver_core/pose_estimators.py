"""Per-frame body estimators run with onnxruntime: BlazePose GHUM 3D and user HMR models.

Each estimator takes RGB frames one at a time (``process(image_rgb)``) and keeps
whatever tracking state it needs.  Models are given as ONNX file paths; fetching
them is the caller's business (``uuomocap.model_fetch``).

onnxruntime runs with one intra-op thread: on the 2-core machines this targets,
two threads measured 5x slower for these small networks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from uuomocap.solver_core import blazepose as bp


def make_session(path: str | Path, threads: int = 1):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


class BlazePoseEstimator:
    """Single-person BlazePose: detect, crop the rotated ROI, run landmarks, track.

    ``process`` returns a ``LandmarkResult`` or None when no person is found.  The
    ROI is tracked from the auxiliary landmarks; when the landmark model's person
    score drops below ``min_presence`` the detector runs again on the same frame.
    """

    def __init__(self, detector_path: str | Path, landmark_path: str | Path,
                 config: bp.BlazePoseConfig = bp.BlazePoseConfig(), threads: int = 1):
        self.config = config
        self.detector = make_session(detector_path, threads)
        self.landmarker = make_session(landmark_path, threads)
        self._det_input = self.detector.get_inputs()[0].name
        self._lm_input = self.landmarker.get_inputs()[0].name
        det_outputs = [o.name for o in self.detector.get_outputs()]
        # The detector's outputs: regressors (1, 2254, 12) and scores (1, 2254, 1).
        shapes = {o.name: o.shape for o in self.detector.get_outputs()}
        self._det_boxes = next(n for n in det_outputs if shapes[n][-1] == 12)
        self._det_scores = next(n for n in det_outputs if shapes[n][-1] == 1)
        lm_shapes = {o.name: tuple(o.shape) for o in self.landmarker.get_outputs()}
        by_shape = {s: n for n, s in lm_shapes.items()}
        try:
            self._lm_names = [by_shape[(1, 195)], by_shape[(1, 1)], by_shape[(1, 117)]]
        except KeyError as exc:
            raise ValueError(f"{landmark_path} is not the BlazePose GHUM landmark model (outputs {lm_shapes})") from exc
        self._hm_name = by_shape.get((1, bp.HEATMAP_SIZE, bp.HEATMAP_SIZE, bp.NUM_LANDMARKS))
        self.anchors = bp.ssd_anchors()
        self.roi: bp.Roi | None = None
        self.detector_runs = 0

    def reset(self) -> None:
        self.roi = None

    def detect(self, image_rgb: np.ndarray) -> list[bp.Detection]:
        tensor, letterbox = bp.detector_input(image_rgb)
        boxes, scores = self.detector.run([self._det_boxes, self._det_scores], {self._det_input: tensor})
        self.detector_runs += 1
        return bp.decode_detections(boxes, scores, self.anchors, letterbox, self.config)

    def landmarks(self, image_rgb: np.ndarray, roi: bp.Roi) -> bp.LandmarkResult:
        names = self._lm_names + ([self._hm_name] if self._hm_name else [])
        outs = self.landmarker.run(names, {self._lm_input: bp.landmark_input(image_rgb, roi)})
        heatmap = outs[3][0] if self._hm_name else None
        return bp.decode_landmarks(outs[0][0], float(outs[1].ravel()[0]), heatmap, outs[2][0], roi, self.config)

    def process(self, image_rgb: np.ndarray) -> bp.LandmarkResult | None:
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) RGB image, got shape {image_rgb.shape}")
        result = None
        if self.roi is not None and self.roi.size > 1.0:
            result = self.landmarks(image_rgb, self.roi)
            if result.pose_score < self.config.min_presence:
                result = None
        if result is None:
            detections = self.detect(image_rgb)
            if detections:
                result = self.landmarks(image_rgb, bp.roi_from_detection(detections[0], self.config))
                if result.pose_score < self.config.min_presence:
                    result = None
        self.roi = bp.tracking_roi(result, self.config) if result is not None else None
        return result


IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
HMR_INPUT_SIZE = 256
HMR_ASPECT = 192 / 256  # width / height of the person box HMR2.0 was trained on
HMR_OUTPUTS = ("global_orient", "body_pose", "betas", "pred_cam")


def hmr_crop_box(box: np.ndarray, aspect: float = HMR_ASPECT) -> tuple[np.ndarray, float]:
    """Person box (x0, y0, x1, y1) -> (centre (2,), side) of the square crop: the box is grown to
    the width:height ``aspect`` and the crop's side is the larger side of that box."""
    box = np.asarray(box, np.float64)
    centre = (box[:2] + box[2:]) / 2
    w, h = box[2] - box[0], box[3] - box[1]
    if w > h * aspect:
        h = w / aspect
    else:
        w = h * aspect
    return centre, float(max(w, h))


def hmr_input(image_rgb: np.ndarray, centre: np.ndarray, side: float, size: int = HMR_INPUT_SIZE) -> np.ndarray:
    """Square crop -> (1, 3, size, size) float32, ImageNet-normalised RGB."""
    scale = side / size
    # crop pixel centre u -> image pixel-centre coordinate: centre - side/2 + (u + 0.5) * scale - 0.5
    m = np.array([[scale, 0.0, centre[0] - side / 2 + 0.5 * scale - 0.5],
                  [0.0, scale, centre[1] - side / 2 + 0.5 * scale - 0.5]])
    crop = cv2.warpAffine(image_rgb, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    x = (crop.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return x.transpose(2, 0, 1)[None].astype(np.float32)


@dataclass(frozen=True)
class HmrResult:
    """One frame of an HMR-class model: raw output arrays (batch dim removed) and the crop."""

    global_orient: np.ndarray  # one rotation: (1,3,3) / (3,3) / (6,) / (3,) ...
    body_pose: np.ndarray  # 23 rotations in any layout
    betas: np.ndarray  # (B,)
    pred_cam: np.ndarray | None  # (3,) weak-perspective camera of the crop, if given
    box: np.ndarray  # person box (x0, y0, x1, y1), image pixels
    score: float  # person score of the box source


class OnnxHmrEstimator:
    """A user's HMR-class ONNX model: RGB crop (N, 3, 256, 256) -> SMPL parameters.

    Outputs are matched by name (``global_orient``, ``body_pose``, ``betas``, and
    optionally ``pred_cam``; a name containing the key also matches, e.g.
    ``pred_smpl_params/body_pose``).  Person boxes come from BlazePose (the box of
    its tracked landmarks).
    """

    def __init__(self, model_path: str | Path, person_tracker: BlazePoseEstimator, threads: int = 1):
        self.session = make_session(model_path, threads)
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(f"{model_path}: expected one image input, found {[i.name for i in inputs]}")
        self._input = inputs[0].name
        shape = inputs[0].shape
        if len(shape) != 4 or shape[1] not in (3, "3") or any(
                isinstance(s, int) and s != HMR_INPUT_SIZE for s in shape[2:]):
            raise ValueError(f"{model_path}: input {self._input} has shape {shape}, expected (N, 3, 256, 256)")
        names = [o.name for o in self.session.get_outputs()]
        self._outputs = {}
        for key in HMR_OUTPUTS:
            exact = [n for n in names if n == key]
            loose = [n for n in names if key in n.lower()]
            match = exact or loose
            if not match and key != "pred_cam":
                raise ValueError(f"{model_path}: no output named like {key!r} (outputs: {names})")
            if match:
                self._outputs[key] = match[0]
        self.tracker = person_tracker

    def reset(self) -> None:
        self.tracker.reset()

    def process(self, image_rgb: np.ndarray) -> HmrResult | None:
        person = self.tracker.process(image_rgb)
        if person is None:
            return None
        box = bp.person_box(person, image_rgb.shape[:2])
        centre, side = hmr_crop_box(box)
        keys = list(self._outputs)
        outs = self.session.run([self._outputs[k] for k in keys], {self._input: hmr_input(image_rgb, centre, side)})
        got = {k: np.asarray(v)[0] for k, v in zip(keys, outs)}
        return HmrResult(global_orient=got["global_orient"], body_pose=got["body_pose"], betas=got["betas"],
                         pred_cam=got.get("pred_cam"), box=box, score=person.pose_score)
