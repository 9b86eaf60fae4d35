"""Body parameters shared by the solver stages, and posing them in the capture world.

The solver keeps the unknown heading as its own parameter: the world root rotation of frame t is
``R_up(yaw) @ R(root_orient[t])`` (paper Stage 1/2: Phi_img = b x Phi_hat).  Keeping the yaw
separate lets the pose prior compare ``root_orient`` with the video prior's root orientation
(both before the yaw), and lets the stages warm-start from any other stage's result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from uuomocap.solver_core import lbs
from uuomocap.solver_core.prior_preparation import up_axis_vector
from uuomocap.solver_core.rotations import axis_angle_to_matrix, matrix_to_axis_angle


@dataclass(frozen=True)
class BodyParams:
    """Per-frame body parameters (float32 torch tensors, no grad).

    root_orient (T,3) axis-angle before the yaw; body_pose (T,23,3) axis-angle; trans (T,3) metres;
    betas (B,); yaw () radians about the up axis.
    """

    root_orient: torch.Tensor
    body_pose: torch.Tensor
    trans: torch.Tensor
    betas: torch.Tensor
    yaw: torch.Tensor

    @property
    def num_frames(self) -> int:
        return int(self.root_orient.shape[0])

    def detached(self) -> "BodyParams":
        return BodyParams(*(t.detach().clone() for t in (self.root_orient, self.body_pose, self.trans, self.betas, self.yaw)))

    def frames(self, index) -> "BodyParams":
        """The parameters of a subset of frames (index: slice / index tensor)."""
        return replace(self, root_orient=self.root_orient[index], body_pose=self.body_pose[index], trans=self.trans[index])

    def with_yaw_folded(self, up: torch.Tensor) -> "BodyParams":
        """Same body with yaw 0: the yaw moved into root_orient."""
        root = matrix_to_axis_angle(yaw_matrix(self.yaw, up) @ axis_angle_to_matrix(self.root_orient))
        return replace(self, root_orient=root, yaw=torch.zeros_like(self.yaw))

    def poses72(self, up: torch.Tensor) -> np.ndarray:
        """(T,72) float64 world-frame AMASS poses (yaw folded into the root)."""
        folded = self.with_yaw_folded(up)
        return torch.cat([folded.root_orient, folded.body_pose.reshape(self.num_frames, -1)], 1).double().numpy()


@dataclass(frozen=True)
class FreeParameters:
    """Which parameters a stage may change (the windowed solver locks shape / yaw)."""

    yaw: bool = True
    root_orient: bool = True
    body_pose: bool = True
    trans: bool = True
    betas: bool = True


@dataclass(frozen=True)
class MarkerAttachment:
    """Where each marker sits on the body: face (M,) long (-1 = unassigned), barycentric (M,3),
    plus the mean marker-to-point distance that chose it (M,) metres (diagnostic)."""

    face_ids: torch.Tensor
    bary: torch.Tensor
    score_m: torch.Tensor

    @property
    def assigned(self) -> torch.Tensor:
        return self.face_ids >= 0


def up_tensor(up_axis: str) -> torch.Tensor:
    """(3,) float32 unit up vector from '+z' / '-y' ..."""
    return torch.tensor(up_axis_vector(up_axis), dtype=torch.float32)


def yaw_matrix(yaw: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """Rotation (3,3) by ``yaw`` radians about the unit axis ``up`` (differentiable in yaw)."""
    return axis_angle_to_matrix(up.to(yaw.dtype) * yaw.reshape(()))


def pose_matrices(
    root_orient: torch.Tensor, body_pose: torch.Tensor, yaw: torch.Tensor, up: torch.Tensor, root_offset: torch.Tensor | None = None
) -> torch.Tensor:
    """(T,24,3,3) local rotations with the yaw applied to the root: R_up(yaw) [root_offset] R(root)."""
    root = axis_angle_to_matrix(root_orient)
    if root_offset is not None:
        root = root_offset @ root
    root = yaw_matrix(yaw, up) @ root
    body = axis_angle_to_matrix(body_pose)
    return torch.cat([root[:, None], body], dim=1)


def pose_body(
    model,
    root_orient: torch.Tensor,
    body_pose: torch.Tensor,
    trans: torch.Tensor,
    betas: torch.Tensor,
    yaw: torch.Tensor,
    up: torch.Tensor,
    points: lbs.SurfacePoints | None = None,
    root_offset: torch.Tensor | None = None,
) -> lbs.LBSOutput:
    """Pose the model in the world for every frame (differentiable in every argument).
    root_offset (3,3): an extra rotation between the yaw and the root (the camera tilt correction)."""
    rot = pose_matrices(root_orient, body_pose, yaw, up, root_offset)
    return lbs.forward(model, betas.reshape(1, -1), rot, trans, points=points)


def pose_params(model, params: BodyParams, up: torch.Tensor, points: lbs.SurfacePoints | None = None) -> lbs.LBSOutput:
    return pose_body(model, params.root_orient, params.body_pose, params.trans, params.betas, params.yaw, up, points)


def tilt_matrix(tilt: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """Rotation (3,3) by the small rotation vector ``tilt`` (2,) radians about two horizontal axes
    (the video camera's unknown pitch and roll; the yaw is separate)."""
    from uuomocap.solver_core.prior_preparation import horizontal_basis

    right, forward = horizontal_basis(up.double().numpy())
    basis = torch.tensor(np.stack([right, forward]), dtype=tilt.dtype)
    return axis_angle_to_matrix(tilt @ basis)


def apply_root_offset(root_orient: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """(T,3) axis-angle roots premultiplied by the rotation ``offset`` (3,3)."""
    return matrix_to_axis_angle(offset @ axis_angle_to_matrix(root_orient))


def wrap_angle(angle: float) -> float:
    """Angle in radians wrapped to [0, 2 pi)."""
    return float(angle % (2.0 * math.pi))


def angle_difference(a: float, b: float) -> float:
    """Smallest absolute difference between two angles (radians), in [0, pi]."""
    d = (a - b) % (2.0 * math.pi)
    return float(min(d, 2.0 * math.pi - d))


def fill_nan_rows(values: np.ndarray) -> np.ndarray:
    """(T, D) with NaN rows -> rows filled by linear interpolation (nearest at the ends)."""
    values = np.array(values, dtype=np.float64)
    ok = np.isfinite(values).all(axis=1)
    if ok.all():
        return values
    if not ok.any():
        raise ValueError("no frame has data to interpolate from")
    idx = np.arange(values.shape[0])
    for d in range(values.shape[1]):
        values[:, d] = np.interp(idx, idx[ok], values[ok, d])
    return values


def interpolate_params(params: BodyParams, src_frames: np.ndarray, dst_frames: np.ndarray) -> BodyParams:
    """Parameters known at frame indices ``src_frames`` (S,) (increasing) -> at ``dst_frames`` (D,).

    Rotations slerp, translations lerp, nearest beyond the ends; betas and yaw are shared.
    """
    from uuomocap.solver_core.rotations import slerp_axis_angle

    src = np.asarray(src_frames, dtype=np.float64)
    dst = np.asarray(dst_frames, dtype=np.float64)
    if len(src) == 1:
        j0 = j1 = np.zeros(len(dst), dtype=np.int64)
        w = np.zeros(len(dst))
    else:
        j1 = np.searchsorted(src, dst, side="left").clip(1, len(src) - 1)
        j0 = j1 - 1
        w = ((dst - src[j0]) / (src[j1] - src[j0])).clip(0.0, 1.0)
    i0, i1 = torch.as_tensor(j0), torch.as_tensor(j1)
    wt = torch.as_tensor(w, dtype=params.trans.dtype)
    rots = torch.cat([params.root_orient[:, None], params.body_pose], dim=1)
    out = slerp_axis_angle(rots[i0], rots[i1], wt[:, None].expand(-1, rots.shape[1]))
    trans = params.trans[i0] * (1 - wt[:, None]) + params.trans[i1] * wt[:, None]
    return BodyParams(out[:, 0].contiguous(), out[:, 1:].contiguous(), trans, params.betas.clone(), params.yaw.clone())
