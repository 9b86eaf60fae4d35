"""Marker segmentation: group markers that move rigidly together (paper "Step 1: marker segmentation").

Affinity between two markers = standard deviation over time of their Euclidean distance
(de Aguiar et al. 2006).  Markers on one bone keep their distance, so a small deviation means
"same rigid group".  Agglomerative clustering with average linkage and a 5 mm distance threshold
(scikit-learn, precomputed metric) gives K groups.

Beyond the published code: the deviation is computed only over frames where BOTH markers are
visible, so a marker with occlusion gaps still joins its group instead of becoming a singleton
(NaNs poison the published code's statistics).  Pairs that are never seen together enough
cannot be judged and get a large deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SegmentationConfig:
    # Paper Sec. "Step 1: marker segmentation": 5 mm distance threshold on the std of pair distances.
    distance_threshold_m: float = 0.005
    # Paper Sec. "Step 1": average linkage.
    linkage: str = "average"
    # Beyond the paper (occlusion-aware affinity): pairs co-visible in fewer frames than this are
    # not trusted and get ``unknown_affinity_m``.
    min_covisible_frames: int = 5
    # Beyond the paper: the affinity assigned to pairs that cannot be judged (far above the threshold).
    unknown_affinity_m: float = 1.0
    # Memory bound: at most this many frames per chunk when accumulating pair statistics.
    frames_per_chunk: int = 256


def pairwise_distance_std(markers: np.ndarray, visible: np.ndarray | None = None, config: SegmentationConfig = SegmentationConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Occlusion-aware affinity.

    markers: (T, M, 3) metres (NaN where missing); visible: (T, M) bool or None (= not NaN).
    Returns (std (M, M) metres, covisible_frames (M, M) int); std is ``unknown_affinity_m`` where
    the pair was co-visible in fewer than ``min_covisible_frames`` frames; diagonal 0.
    """
    markers = np.asarray(markers, dtype=np.float64)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise ValueError(f"markers must be (T, M, 3), got {markers.shape}")
    finite = np.isfinite(markers).all(axis=2)
    vis = finite if visible is None else (np.asarray(visible, dtype=bool) & finite)
    t_count, m_count, _ = markers.shape
    total = np.zeros((m_count, m_count))
    total_sq = np.zeros((m_count, m_count))
    count = np.zeros((m_count, m_count))
    filled = np.where(vis[..., None], markers, 0.0)
    # keep the (chunk, M, M, 3) difference tensor near 4 M elements whatever M is
    chunk = max(1, min(config.frames_per_chunk, 4_000_000 // max(1, 3 * m_count * m_count)))
    for start in range(0, t_count, chunk):
        pts = filled[start : start + chunk]
        ok = vis[start : start + chunk].astype(np.float64)
        diff = pts[:, :, None, :] - pts[:, None, :, :]
        dist = np.sqrt(np.sum(diff * diff, axis=-1))
        both = ok[:, :, None] * ok[:, None, :]
        dist = dist * both
        total += dist.sum(axis=0)
        total_sq += (dist * dist).sum(axis=0)
        count += both.sum(axis=0)
    safe = np.maximum(count, 1.0)
    mean = total / safe
    # shift-free variance is fine in float64 at metre scale and sub-millimetre deviations
    var = np.maximum(total_sq / safe - mean * mean, 0.0)
    std = np.sqrt(var)
    std = np.where(count >= config.min_covisible_frames, std, config.unknown_affinity_m)
    np.fill_diagonal(std, 0.0)
    return std, count.astype(np.int64)


def segment_markers(markers: np.ndarray, visible: np.ndarray | None = None, config: SegmentationConfig = SegmentationConfig()) -> np.ndarray:
    """Cluster markers into rigidly co-moving groups.

    markers: (T, M, 3) metres; visible: (T, M) bool or None.
    Returns labels (M,) int in [0, K), clusters numbered by first appearance.
    """
    from sklearn.cluster import AgglomerativeClustering

    std, _ = pairwise_distance_std(markers, visible, config)
    m_count = std.shape[0]
    if m_count == 0:
        raise ValueError("no markers to segment")
    if m_count == 1:
        return np.zeros(1, dtype=np.int64)
    clustering = AgglomerativeClustering(
        n_clusters=None,
        metric="precomputed",
        linkage=config.linkage,
        distance_threshold=config.distance_threshold_m,
    )
    raw = clustering.fit_predict(std)
    # renumber by first appearance so results are deterministic and readable
    order: dict[int, int] = {}
    for lab in raw:
        order.setdefault(int(lab), len(order))
    return np.array([order[int(lab)] for lab in raw], dtype=np.int64)


def cluster_count(labels: np.ndarray) -> int:
    """K: the number of distinct groups in ``labels`` (M,)."""
    return int(len(np.unique(labels)))
