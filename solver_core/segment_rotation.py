"""Rotation signatures of rigid marker clusters and of the prior's bones (beyond the paper).

The paper matches marker clusters to body parts by the chamfer distance alone, with the pose
fixed to the video prior.  A small part (an arm, a shoulder) is a cylinder of markers that the
large torso surface fits just as well, so the chamfer often picks the wrong part.  What the
chamfer ignores is how each cluster TURNS: a rigid cluster of >= 3 markers on bone j turns, from
frame a to frame b, by G_j(b) G_j(a)^T (G = the bone's world rotation), and the video prior
predicts that turn up to the global yaw.  The mismatch between a cluster's measured turns and a
bone's predicted turns tells an arm swinging through a walk from a torso that barely turns.

Shapes: S sampled frames, M markers, K clusters, P frame pairs, J joints, H hypotheses.
"""

from __future__ import annotations

import numpy as np
import torch


def frame_pairs(frame_count: int, lags: tuple[int, ...] = (1, 2, 4)) -> np.ndarray:
    """(P, 2) index pairs (a, a + lag) into S sampled frames for every lag."""
    pairs = [(a, a + lag) for lag in lags for a in range(frame_count - lag)]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def kabsch_rotation(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotation R (3,3) minimising sum |R src_i - dst_i|^2 over centred point sets (N,3)."""
    cov = src.T @ dst
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def cluster_relative_rotations(
    markers: np.ndarray,
    visible: np.ndarray,
    labels: np.ndarray,
    pairs: np.ndarray,
    min_markers: int = 3,
    min_spread_m: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Measured turn of every cluster between the frames of every pair.

    markers (S,M,3) metres; visible (S,M) bool; labels (M,) cluster ids in [0,K); pairs (P,2).
    Returns (rot (K,P,3,3), valid (K,P) bool): rot[k,p] takes the cluster's shape at frame a to
    frame b.  A pair is valid when >= ``min_markers`` of the cluster are seen in both frames and
    they are not (nearly) collinear: the second principal spread is >= ``min_spread_m``.
    """
    k_count = int(labels.max()) + 1 if len(labels) else 0
    rot = np.tile(np.eye(3), (k_count, len(pairs), 1, 1))
    valid = np.zeros((k_count, len(pairs)), dtype=bool)
    for k in range(k_count):
        members = np.flatnonzero(labels == k)
        if len(members) < min_markers:
            continue
        for p, (a, b) in enumerate(pairs):
            both = members[visible[a, members] & visible[b, members]]
            if len(both) < min_markers:
                continue
            src = markers[a, both] - markers[a, both].mean(axis=0)
            dst = markers[b, both] - markers[b, both].mean(axis=0)
            spread = np.linalg.svd(src, compute_uv=False)
            if spread[1] / np.sqrt(len(both)) < min_spread_m:
                continue
            rot[k, p] = kabsch_rotation(src, dst)
            valid[k, p] = True
    return rot, valid


def bone_relative_rotations(joint_rotations: torch.Tensor, pairs: np.ndarray) -> torch.Tensor:
    """Predicted turn of every bone: joint_rotations (S,J,3,3) world -> (J,P,3,3) G(b) G(a)^T."""
    a = joint_rotations[torch.as_tensor(pairs[:, 0])]
    b = joint_rotations[torch.as_tensor(pairs[:, 1])]
    return (b @ a.transpose(-1, -2)).transpose(0, 1)


def turn_mismatch(
    cluster_rot: np.ndarray, cluster_valid: np.ndarray, bone_rot: torch.Tensor, frame_rot: torch.Tensor
) -> torch.Tensor:
    """Mean squared angle (rad^2) between each cluster's turns and each bone's, per hypothesis.

    cluster_rot (K,P,3,3), cluster_valid (K,P); bone_rot (J,P,3,3) in the prior's world;
    frame_rot (H,3,3): the hypothesis' rotation of the prior (yaw x tilt), so a bone turn D is
    seen as F D F^T.  Returns (H,K,J); clusters with no valid pair get 0 (no evidence).
    """
    c = torch.as_tensor(cluster_rot, dtype=bone_rot.dtype)
    w = torch.as_tensor(cluster_valid, dtype=bone_rot.dtype)
    seen = torch.einsum("hab,jpbc,hdc->hjpad", frame_rot, bone_rot, frame_rot)  # F D F^T
    # trace(C^T B) = 1 + 2 cos(angle between C and B)
    tr = torch.einsum("kpab,hjpab->hkjp", c, seen)
    angle = torch.arccos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0))
    return (angle**2 * w[None, :, None]).sum(-1) / w.sum(-1).clamp(min=1.0)[None, :, None]
