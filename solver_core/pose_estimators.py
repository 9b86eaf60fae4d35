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
