"""A second opinion on every marker's surface point, kept where it fits better (beyond the paper).

Stage 3 places the markers under the solved pose and Stage 4 solves the pose for those points,
so the two steps confirm each other: a group of points that started a centimetre off along a
limb stays there, and the joints follow it.  On the benchmark's 40-marker walk the four thigh
markers sat 13-15 mm from their true points and the knee 13 mm off, while Stage 3 under the TRUE
pose finds every point within 1.3 mm (median) - the points, not the IK, hold the error.

The second opinion places the markers of each bone under the solved pose with only that bone's
local rotation replaced by the video prior's.  The prior is noisy per frame but not biased
towards the solver's points, and Stage 3's robust time average removes most of its noise (the
same reasoning as ``weak_segment_correspondence``, applied to every bone, one bone at a time so
that the prior's errors do not accumulate down a chain).  Both sets of points then go through IK
on a subsample of frames, and each marker keeps the point with the lower fit residual: a point
that is right lets the pose fit the marker, a wrong one leaves a residual IK cannot remove.

Shapes: T frames, M markers, J joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core.body_params import BodyParams, MarkerAttachment
from uuomocap.solver_core.inverse_kinematics import predicted_markers
from uuomocap.solver_core.marker_surface_correspondence import CorrespondenceConfig, place_on_joints
from uuomocap.solver_core.weak_segment_correspondence import hybrid_params


@dataclass(frozen=True)
class PlacementSelectionConfig:
    # Beyond the paper (in each Stage-5 round): 40-marker walk / jump / arms 8.1 / 10.5 / 8.3 ->
    # 7.4 / 7.9 / 8.0 mm MPJPE (the prior's placement alone, without the choice: 7.3 / 9.7 / 8.5).
    enabled: bool = True
    # Frames on which both placements are fitted for the choice (evenly spread over the take).
    frames: int = 150
    # L-BFGS iterations of those two fits (None = Stage 5's own budget).
    max_iterations: int | None = None


def prior_rotation_placement(
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
) -> MarkerAttachment:
    """Stage 3 for each bone's markers under ``params`` with that bone's local rotation taken from
    the prior.  markers (T,M,3) metres; visible (T,M); params, prior_body_pose (T,23,3): the same T
    frames; marker_joints (M,) dominant joint of each marker's current point (-1 unassigned, 0 =
    pelvis: the root has no prior rotation, so its markers keep their points).  Each marker
    searches its own bone, its parent's and its children's vertices, as the weak-bone placement."""
    parents = model.parents.numpy()
    face_ids, bary, score = attachment.face_ids.clone(), attachment.bary.clone(), attachment.score_m.clone()
    for j in np.unique(marker_joints[marker_joints > 0]):
        only_j = np.zeros(len(parents), dtype=bool)
        only_j[j] = True
        hybrid = hybrid_params(params, prior_body_pose, only_j)
        near = [int(j), int(parents[j])] + [int(c) for c in np.flatnonzero(parents == j)]
        place_on_joints(model, markers, visible, hybrid, up, np.flatnonzero(marker_joints == j), near, allowed_vertex_ids,
                        correspondence, vertex_faces, face_ids, bary, score)
    return MarkerAttachment(face_ids, bary, score)


@torch.no_grad()
def marker_fit_residuals(model, markers: torch.Tensor, visible: torch.Tensor, params: BodyParams,
                         attachment: MarkerAttachment, up: torch.Tensor, offset_m: float,
                         offset_model: str = "smooth_normal") -> torch.Tensor:
    """(M,) RMS distance (metres) over visible frames between each marker and the point the body
    predicts for it (surface point + offset along the normal); inf for unassigned or never-seen
    markers.  markers (T,M,3); visible (T,M)."""
    out = torch.full((markers.shape[1],), float("inf"))
    assigned = attachment.assigned
    pred = predicted_markers(model, params, attachment, up, offset_m, offset_model)
    sq = ((pred - torch.nan_to_num(markers[:, assigned])) ** 2).sum(-1)
    w = visible[:, assigned].to(sq.dtype)
    seen = w.sum(0)
    rms = torch.where(seen > 0, ((sq * w).sum(0) / seen.clamp(min=1.0)).sqrt(), torch.full_like(seen, float("inf")))
    out[assigned] = rms
    return out


def choose_placements(current: MarkerAttachment, alternative: MarkerAttachment, current_residual: torch.Tensor,
                      alternative_residual: torch.Tensor) -> tuple[MarkerAttachment, list[int]]:
    """Per marker, the alternative's point where its residual (M,) is lower, else the current one.
    Returns the merged attachment and the markers that took the alternative."""
    take = (alternative_residual < current_residual) & (alternative.face_ids >= 0)
    face_ids = torch.where(take, alternative.face_ids, current.face_ids)
    bary = torch.where(take[:, None], alternative.bary, current.bary)
    score = torch.where(take, alternative.score_m, current.score_m)
    return MarkerAttachment(face_ids, bary, score), [int(m) for m in torch.nonzero(take).reshape(-1)]


def select_marker_placements(
    model,
    markers: torch.Tensor,
    visible: torch.Tensor,
    params: BodyParams,
    attachment: MarkerAttachment,
    marker_joints: np.ndarray,
    prior_body_pose: torch.Tensor,
    up: torch.Tensor,
    allowed_vertex_ids: torch.Tensor | None,
    correspondence: CorrespondenceConfig,
    vertex_faces: torch.Tensor,
    refine,
    offset_m: float,
    offset_model: str = "smooth_normal",
) -> tuple[MarkerAttachment, list[int]]:
    """The per-marker choice between the current points and the prior-rotation placement.

    markers (S,M,3), visible (S,M), params and prior_body_pose (S,23,3): the subsample of frames
    the choice is made on; attachment: the current points; marker_joints (M,) their dominant
    joints; refine(params, attachment, markers, visible) -> (params, attachment): the IK both
    placements go through (Stage 5's, so they are compared on the energy that will use them);
    offset_m, offset_model: the marker offset of that IK and its model.  Returns the chosen points (as refined by that IK) and
    the markers that took the prior's.
    """
    alternative = prior_rotation_placement(model, markers, visible, params, prior_body_pose, up, attachment, marker_joints,
                                           allowed_vertex_ids, correspondence, vertex_faces)
    fitted = [refine(params, att, markers, visible) for att in (attachment, alternative)]
    residuals = [marker_fit_residuals(model, markers, visible, p, att, up, offset_m, offset_model) for p, att in fitted]
    return choose_placements(fitted[0][1], fitted[1][1], residuals[0], residuals[1])
