"""Surface points of markers on weakly constrained bones, chosen under the video prior.

Beyond the paper.  With one or two markers on a bone and none below it (a random layout puts a
single marker on a shank and none on the foot), Stage 3 and Stage 4 feed each other: any
surface point of the shank can be reached by rotating the shank, and the nearest point under
the solved pose is the point that pose was solved for.  The pose prior is far too weak to break
the tie (lambda_Theta = 0.1 against centimetre marker residuals), so the first guess sticks: on
the benchmark's 40-marker walk a shank marker stayed 47 mm off its true point and the ankle
76 mm off (true point for that one marker: MPJPE 14.5 -> 8.6 mm).

The video prior's joint rotations are noisy but unbiased over a take, so for such bones the
point is chosen under a hybrid body: the solved pose for well constrained bones (the knee
position comes from the thigh markers) and the prior's local rotation for the weak bones.  The
robust time average of Stage 3 then averages the prior's noise away instead of inheriting the
solver's bias.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core.body_params import BodyParams, MarkerAttachment
from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, place_on_joints


@dataclass(frozen=True)
class WeakSegmentConfig:
    # Beyond the paper: a bone is weak when it and every bone below it carry at most this many
    # markers (1 on the 40-marker benchmark: 15.0 / 15.4 / 12.4 -> 10.7 / 9.8 / 9.8 mm MPJPE on
    # walk / jump / arms; 2 re-placed markers of well fitted forearms too: 11.9 / 10.0 / 9.8).
    max_markers: int = 1
    enabled: bool = True


def subtree_marker_counts(parents: np.ndarray, marker_joints: np.ndarray) -> np.ndarray:
    """(J,) markers on each bone plus every bone below it.  parents (J,) with parents[j] < j
    (-1 for the root); marker_joints (M,) dominant joint per marker (-1 unassigned)."""
    count = np.bincount(marker_joints[marker_joints >= 0], minlength=len(parents)).astype(np.int64)
    for j in range(len(parents) - 1, 0, -1):
        if parents[j] >= 0:
            count[parents[j]] += count[j]
    return count


def weak_joints(parents: np.ndarray, marker_joints: np.ndarray, max_markers: int) -> np.ndarray:
    """(J,) bool: non-root bones whose subtree carries between 1 and ``max_markers`` markers."""
    count = subtree_marker_counts(parents, marker_joints)
    weak = (count >= 1) & (count <= max_markers)
    weak[parents < 0] = False
    return weak


def hybrid_params(params: BodyParams, prior_body_pose: torch.Tensor, weak: np.ndarray) -> BodyParams:
    """``params`` with the prior's local rotation on the weak bones.  prior_body_pose (T,23,3)
    for the same frames; weak (J,) bool over all joints (joint j is body_pose[:, j-1])."""
    body = params.body_pose.clone()
    idx = torch.as_tensor(np.flatnonzero(weak[1:]), dtype=torch.long)
    body[:, idx] = prior_body_pose[:, idx].to(body.dtype)
    return BodyParams(params.root_orient, body, params.trans, params.betas, params.yaw)


def weak_segment_correspondence(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    params: BodyParams,
    prior_body_pose: torch.Tensor,
    up: torch.Tensor,
    attachment: MarkerAttachment,
    marker_joints: np.ndarray,
    allowed_vertex_ids: torch.Tensor | None,
    correspondence: CorrespondenceConfig,
    vertex_faces: torch.Tensor,
    config: WeakSegmentConfig = WeakSegmentConfig(),
) -> tuple[MarkerAttachment, list[int]]:
    """Re-place the markers of weak bones under the hybrid body.

    markers (T,M,3) metres; visible (T,M); params: solved body for those T frames; prior_body_pose
    (T,23,3) the video prior there; marker_joints (M,) dominant joint of each marker's current point.
    Each marker searches its own bone, its parent's and its children's vertices.  Returns the new
    attachment and the markers that were re-placed.
    """
    if not config.enabled:
        return attachment, []
    parents = model.parents.numpy()
    weak = weak_joints(parents, marker_joints, config.max_markers)
    if not weak.any():
        return attachment, []
    hybrid = hybrid_params(params, prior_body_pose, weak)
    face_ids, bary, score = attachment.face_ids.clone(), attachment.bary.clone(), attachment.score_m.clone()
    moved: list[int] = []
    for j in np.flatnonzero(weak):
        members = np.flatnonzero(marker_joints == j)
        if len(members) == 0:
            continue
        near = [int(j), int(parents[j])] + [int(c) for c in np.flatnonzero(parents == j)]
        moved += place_on_joints(model, markers, visible, hybrid, up, members, near, allowed_vertex_ids, correspondence,
                                 vertex_faces, face_ids, bary, score)
    return MarkerAttachment(face_ids, bary, score), moved
