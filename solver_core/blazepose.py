"""BlazePose GHUM 3D pre- and post-processing (numpy + OpenCV, no network code).

The two networks (person detector, landmark model) are run elsewhere
(``uuomocap.solver_core.pose_estimators``); this module turns images into their
input tensors and their raw outputs into detections, regions of interest (ROIs),
image landmarks and metric world landmarks.  Written from the published facts of
the BlazePose pipeline (Bazarevsky et al. 2020 and the model card):

* detector: 224x224 letterboxed RGB in [-1, 1]; 2254 SSD anchors from strides
  8/16/32/32/32 (two anchors per cell per layer, fixed size); 12 regressed values
  per anchor (box cx, cy, w, h + 4 keypoints x, y) in input pixels relative to the
  anchor; sigmoid scores; weighted non-maximum suppression.
* ROI: centred on keypoint 0 (mid-hip), square of side 2*|kp1 - kp0| * 1.25,
  rotated so that kp0 -> kp1 points up.
* landmark model: 256x256 RGB crop in [0, 1]; 39 landmarks x, y, z (crop pixels),
  visibility and presence logits; a 64x64x39 heatmap refines x, y; 39 world
  landmarks in metres (hip-centred, in the ROI's rotated frame); landmarks 33/34
  are auxiliary points that give the next frame's ROI.

Coordinates: image pixels are continuous, the image spans [0, W] x [0, H] and pixel
(i, j) covers [j, j+1] x [i, i+1].  Rotation angles are radians, positive rotating
the ROI's axes clockwise on screen (image y points down).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
HEATMAP_SIZE = 64
NUM_LANDMARKS = 39  # 33 body landmarks + auxiliary ROI landmarks
NUM_BODY_LANDMARKS = 33

LANDMARK_NAMES = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
    "left_foot_index", "right_foot_index",
)


@dataclass(frozen=True)
class BlazePoseConfig:
    """Pipeline constants (values of the published BlazePose pose pipeline)."""

    min_detection_score: float = 0.5
    nms_iou_threshold: float = 0.3
    score_clip: float = 100.0
    roi_scale: float = 1.25
    min_presence: float = 0.5  # below this the landmark model has lost the person -> re-detect
    heatmap_kernel: int = 7
    heatmap_min_confidence: float = 0.5


@dataclass(frozen=True)
class Roi:
    """A rotated square region of the image: centre (pixels), side (pixels), rotation (rad)."""

    cx: float
    cy: float
    size: float
    rotation: float

    def rotation_matrix(self) -> np.ndarray:
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        return np.array([[c, -s], [s, c]])


@dataclass(frozen=True)
class Detection:
    """A detected person in image pixels: box (x0, y0, x1, y1), 4 keypoints (4, 2), score."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float


@dataclass(frozen=True)
class LandmarkResult:
    """One frame's landmarks.

    image: (39, 3) x, y in image pixels and z in the same pixel scale (relative depth);
    visibility, presence: (39,) probabilities; world: (33, 3) metres, hip-centred,
    camera-aligned axes (x right, y down, z away from the camera); pose_score: the
    model's person-present probability; roi: the ROI the landmarks came from.
    """

    image: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    world: np.ndarray
    pose_score: float
    roi: Roi


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def ssd_anchors(input_size: int = DETECTOR_SIZE, strides=(8, 16, 32, 32, 32)) -> np.ndarray:
    """Anchor centres of the detector, (2254, 2) normalised to the input square.

    Consecutive layers with the same stride share one grid; each layer puts two
    fixed-size anchors (aspect 1 and the interpolated scale) on every cell, so the
    grid of stride 32 carries 3 x 2 = 6 anchors per cell.
    """
    centres = []
    layer = 0
    while layer < len(strides):
        stride = strides[layer]
        per_cell = 0
        while layer < len(strides) and strides[layer] == stride:
            per_cell += 2
            layer += 1
        cells = int(np.ceil(input_size / stride))
        ys, xs = np.meshgrid((np.arange(cells) + 0.5) / cells, (np.arange(cells) + 0.5) / cells, indexing="ij")
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        centres.append(np.repeat(grid, per_cell, axis=0))
    return np.concatenate(centres).astype(np.float32)


def letterbox_transform(width: int, height: int, size: int = DETECTOR_SIZE) -> tuple[float, float, float]:
    """Scale and offsets mapping image pixels into a centred, aspect-preserving square."""
    scale = size / max(width, height)
    return scale, (size - width * scale) / 2.0, (size - height * scale) / 2.0


def detector_input(image_rgb: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """(H, W, 3) uint8 RGB -> (1, 224, 224, 3) float32 in [-1, 1] and the letterbox transform."""
    h, w = image_rgb.shape[:2]
    scale, ox, oy = letterbox_transform(w, h)
    # Affine on integer pixel centres: dst = scale * (src + 0.5) - 0.5 + offset.
    m = np.array([[scale, 0.0, ox + 0.5 * scale - 0.5], [0.0, scale, oy + 0.5 * scale - 0.5]])
    square = cv2.warpAffine(image_rgb, m, (DETECTOR_SIZE, DETECTOR_SIZE), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    tensor = square.astype(np.float32) * (2.0 / 255.0) - 1.0
    return tensor[None], (scale, ox, oy)


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-12)


def decode_detections(raw_boxes: np.ndarray, raw_scores: np.ndarray, anchors: np.ndarray,
                      letterbox: tuple[float, float, float], config: BlazePoseConfig = BlazePoseConfig()
                      ) -> list[Detection]:
    """Raw detector outputs -> detections in image pixels, best first, after weighted NMS.

    raw_boxes: (2254, 12) or (1, 2254, 12); raw_scores: (2254,) or (1, 2254, 1) logits;
    anchors: (2254, 2) normalised centres; letterbox: from ``detector_input``.
    """
    raw_boxes = np.asarray(raw_boxes, np.float64).reshape(-1, 12)
    logits = np.clip(np.asarray(raw_scores, np.float64).reshape(-1), -config.score_clip, config.score_clip)
    if len(raw_boxes) != len(anchors) or len(logits) != len(anchors):
        raise ValueError(f"detector output has {len(raw_boxes)} boxes, expected {len(anchors)} anchors")
    scores = _sigmoid(logits)
    keep = scores >= config.min_detection_score
    if not keep.any():
        return []
    raw, anc, scores = raw_boxes[keep], anchors[keep].astype(np.float64), scores[keep]
    # Offsets are in input pixels relative to the anchor centre; anchors have unit size.
    centre = raw[:, 0:2] / DETECTOR_SIZE + anc
    half = raw[:, 2:4] / DETECTOR_SIZE / 2.0
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    keypoints = raw[:, 4:12].reshape(-1, 4, 2) / DETECTOR_SIZE + anc[:, None, :]
    # Letterbox square (normalised) -> image pixels.
    scale, ox, oy = letterbox
    offset = np.array([ox, oy])
    boxes = ((boxes.reshape(-1, 2, 2) * DETECTOR_SIZE - offset) / scale).reshape(-1, 4)
    keypoints = (keypoints * DETECTOR_SIZE - offset) / scale

    detections = []
    order = np.argsort(-scores)
    remaining = order
    while len(remaining):
        best = remaining[0]
        overlap = _iou(boxes[best], boxes[remaining])
        cluster = remaining[overlap > config.nms_iou_threshold]
        cluster = cluster if len(cluster) else remaining[:1]
        w = scores[cluster][:, None]
        box = (boxes[cluster] * w).sum(0) / w.sum()
        kps = (keypoints[cluster] * w[:, :, None]).sum(0) / w.sum()
        detections.append(Detection(box=box, keypoints=kps, score=float(scores[best])))
        remaining = remaining[overlap <= config.nms_iou_threshold]
        remaining = remaining[remaining != best]
    return detections


def roi_from_points(centre: np.ndarray, scale_point: np.ndarray, scale: float = 1.25) -> Roi:
    """Square ROI centred on ``centre`` with side 2*|scale_point-centre|*scale, rotated so
    that centre -> scale_point points up in the crop (the BlazePose alignment rule)."""
    d = np.asarray(scale_point, np.float64) - np.asarray(centre, np.float64)
    rotation = np.pi / 2 - np.arctan2(-d[1], d[0])
    rotation = (rotation + np.pi) % (2 * np.pi) - np.pi
    size = 2.0 * float(np.hypot(d[0], d[1])) * scale
    return Roi(float(centre[0]), float(centre[1]), size, float(rotation))


def roi_from_detection(det: Detection, config: BlazePoseConfig = BlazePoseConfig()) -> Roi:
    return roi_from_points(det.keypoints[0], det.keypoints[1], config.roi_scale)


def roi_crop_matrix(roi: Roi, out_size: int = LANDMARK_SIZE) -> np.ndarray:
    """2x3 affine mapping crop pixel centres (integer coords) to image pixel-centre coords,
    for ``cv2.warpAffine(..., flags=WARP_INVERSE_MAP)``."""
    r = roi.rotation_matrix() * (roi.size / out_size)
    # image_cont = c + R * (crop_cont - out/2) * size/out, with cont = int + 0.5.
    t = np.array([roi.cx, roi.cy]) - 0.5 + r @ (np.array([0.5, 0.5]) - out_size / 2.0)
    return np.concatenate([r, t[:, None]], axis=1)


def landmark_input(image_rgb: np.ndarray, roi: Roi) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 256, 256, 3) float32 in [0, 1], the rotated ROI crop."""
    m = roi_crop_matrix(roi)
    crop = cv2.warpAffine(image_rgb, m, (LANDMARK_SIZE, LANDMARK_SIZE),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    return (crop.astype(np.float32) * (1.0 / 255.0))[None]


def refine_with_heatmap(xy_norm: np.ndarray, heatmap: np.ndarray, kernel: int = 7,
                        min_confidence: float = 0.5) -> np.ndarray:
    """Replace each landmark by the confidence-weighted mean of its heatmap window.

    xy_norm: (L, 2) landmark positions normalised to the crop; heatmap: (64, 64, L)
    logits.  Landmarks whose window peak is below ``min_confidence`` are left as is.
    """
    hm_h, hm_w, n = heatmap.shape
    half = kernel // 2
    cols = np.floor(xy_norm[:, 0] * hm_w).astype(int)
    rows = np.floor(xy_norm[:, 1] * hm_h).astype(int)
    offsets = np.arange(-half, half + 1)
    rr = rows[:, None, None] + offsets[None, :, None]  # (L, k, 1)
    cc = cols[:, None, None] + offsets[None, None, :]  # (L, 1, k)
    inside = (rr >= 0) & (rr < hm_h) & (cc >= 0) & (cc < hm_w)
    rr_c, cc_c = np.clip(rr, 0, hm_h - 1), np.clip(cc, 0, hm_w - 1)
    conf = _sigmoid(heatmap[rr_c, cc_c, np.arange(n)[:, None, None]].astype(np.float64)) * inside
    total = conf.sum(axis=(1, 2))
    refine = (conf.max(axis=(1, 2)) >= min_confidence) & (total > 0)
    out = xy_norm.astype(np.float64).copy()
    safe = np.where(total > 0, total, 1.0)
    mean_c = ((cc + 0.5) * conf).sum(axis=(1, 2)) / safe / hm_w
    mean_r = ((rr + 0.5) * conf).sum(axis=(1, 2)) / safe / hm_h
    out[refine, 0] = mean_c[refine]
    out[refine, 1] = mean_r[refine]
    return out


def decode_landmarks(raw_landmarks: np.ndarray, pose_score: float, heatmap: np.ndarray | None,
                     raw_world: np.ndarray, roi: Roi, config: BlazePoseConfig = BlazePoseConfig()
                     ) -> LandmarkResult:
    """Landmark-model outputs -> image landmarks and camera-aligned world landmarks.

    raw_landmarks: (195,) = 39 x (x, y, z, visibility logit, presence logit) in crop
    pixels; heatmap: (64, 64, 39) logits or None; raw_world: (117,) = 39 x 3 metres.
    """
    lm = np.asarray(raw_landmarks, np.float64).reshape(NUM_LANDMARKS, 5)
    xy = lm[:, :2] / LANDMARK_SIZE
    if heatmap is not None:
        xy = refine_with_heatmap(xy, np.asarray(heatmap).reshape(HEATMAP_SIZE, HEATMAP_SIZE, NUM_LANDMARKS),
                                 config.heatmap_kernel, config.heatmap_min_confidence)
    rot = roi.rotation_matrix()
    image_xy = (xy - 0.5) * roi.size @ rot.T + np.array([roi.cx, roi.cy])
    z = lm[:, 2] / LANDMARK_SIZE * roi.size
    world = np.asarray(raw_world, np.float64).reshape(NUM_LANDMARKS, 3)[:NUM_BODY_LANDMARKS].copy()
    world[:, :2] = world[:, :2] @ rot.T  # undo the crop's in-plane rotation
    return LandmarkResult(
        image=np.concatenate([image_xy, z[:, None]], axis=1),
        visibility=_sigmoid(lm[:, 3]),
        presence=_sigmoid(lm[:, 4]),
        world=world,
        pose_score=float(pose_score),
        roi=roi,
    )


def tracking_roi(result: LandmarkResult, config: BlazePoseConfig = BlazePoseConfig()) -> Roi:
    """Next frame's ROI from the auxiliary landmarks 33 (centre) and 34 (scale/rotation)."""
    return roi_from_points(result.image[33, :2], result.image[34, :2], config.roi_scale)


def person_box(result: LandmarkResult, image_shape: tuple[int, int], margin: float = 1.2) -> np.ndarray:
    """Axis-aligned box (x0, y0, x1, y1) around the visible body landmarks, grown by ``margin``."""
    pts = result.image[:NUM_BODY_LANDMARKS, :2]
    lo, hi = pts.min(0), pts.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * margin
    return np.concatenate([centre - half, centre + half])
