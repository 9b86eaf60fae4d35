"""Rotation representations: axis-angle, matrices, 6D, unit quaternions.

All functions are batched over leading dimensions, differentiable, and safe
near the zero angle (no division by a vanishing norm in the forward or the
backward pass).  Quaternions are stored scalar-first: ``(w, x, y, z)``.
The 6D representation (Zhou et al. 2019) is the first two COLUMNS of the
matrix, ordered ``(R00, R10, R20, R01, R11, R21)``.
"""

from __future__ import annotations

import torch

# Below this squared angle the trigonometric ratios switch to their Taylor
# series: in float32 sin(t)/t loses all precision well before t**2 < 1e-6.
_SMALL_ANGLE_SQ = 1e-6


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices.  v: (..., 3) -> (..., 3, 3) with skew(v) @ u == v x u."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape + (3,))


# (3, 9) constant E with (v @ E).reshape(3, 3) == skew(v): row k holds the coefficients of v_k.
_SKEW_BASIS = torch.tensor(
    [[0, 0, 0, 0, 0, -1, 0, 1, 0],
     [0, 0, 1, 0, 0, 0, -1, 0, 0],
     [0, -1, 0, 1, 0, 0, 0, 0, 0]],
    dtype=torch.float32,
)


def _skew_basis(dtype: torch.dtype, device) -> torch.Tensor:
    if dtype == torch.float32 and device == _SKEW_BASIS.device:
        return _SKEW_BASIS
    return _SKEW_BASIS.to(dtype=dtype, device=device)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula.  axis_angle: (..., 3) radians * unit axis -> (..., 3, 3).

    R = cos(t) I + sin(t)/t [v]x + (1 - cos(t))/t^2 v v^T, written with few tensor ops
    (this runs inside every solver iteration) and a Taylor branch near t = 0.
    """
    theta_sq = (axis_angle * axis_angle).sum(-1, keepdim=True)
    small = theta_sq < _SMALL_ANGLE_SQ
    # Evaluate the exact branch on a safe value so its gradient stays finite.
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = torch.sqrt(safe_sq)
    a = torch.where(small, 1.0 - theta_sq / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta_sq / 24.0, (1.0 - torch.cos(theta)) / safe_sq)
    c = 1.0 - b * theta_sq  # == cos(theta) on both branches
    shape = axis_angle.shape[:-1] + (3, 3)
    outer = (axis_angle[..., :, None] * axis_angle[..., None, :]) * b[..., None]
    cross = ((a * axis_angle) @ _skew_basis(axis_angle.dtype, axis_angle.device)).reshape(shape)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return outer + cross + c[..., None] * eye


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (w, x, y, z), w >= 0.

    Shepperd's method without data-dependent control flow: the four candidate
    quaternions are computed and, per matrix, the numerically best conditioned
    one (largest denominator) is kept.
    """
    m = matrix
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * q_i**2 for each component; clamp keeps sqrt differentiable.
    four_sq = torch.stack(
        [
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    two_q = torch.sqrt(four_sq.clamp_min(1e-12))  # 2|q_i|
    candidates = torch.stack(
        [
            torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]], -1),
        ],
        dim=-2,
    ) / (2.0 * two_q[..., :, None])
    best = four_sq.argmax(-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_matrix(quaternion: torch.Tensor) -> torch.Tensor:
    """Quaternions (..., 4) (w, x, y, z), normalised here -> (..., 3, 3)."""
    q = quaternion / quaternion.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def axis_angle_to_quaternion(axis_angle: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 4) (w, x, y, z)."""
    theta_sq = (axis_angle * axis_angle).sum(-1, keepdim=True)
    small = theta_sq < _SMALL_ANGLE_SQ
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta_sq), theta_sq))
    # sin(theta/2)/theta -> 1/2 - theta^2/48 near zero.
    s = torch.where(small, 0.5 - theta_sq / 48.0, torch.sin(0.5 * theta) / theta)
    c = torch.where(small, 1.0 - theta_sq / 8.0, torch.cos(0.5 * theta))
    return torch.cat([c, s * axis_angle], dim=-1)


def quaternion_to_axis_angle(quaternion: torch.Tensor) -> torch.Tensor:
    """(..., 4) (w, x, y, z) -> (..., 3) axis-angle with angle in [0, pi]."""
    q = quaternion / quaternion.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    sin_sq = (v * v).sum(-1, keepdim=True)
    small = sin_sq < _SMALL_ANGLE_SQ
    sin_half = torch.sqrt(torch.where(small, torch.ones_like(sin_sq), sin_sq))
    angle = 2.0 * torch.atan2(sin_half, w)
    # angle / sin(angle/2) -> 2/w * (1 + sin^2/(3 w^2)) near zero.
    ratio = torch.where(small, 2.0 / w * (1.0 + sin_sq / (3.0 * w * w)), angle / sin_half)
    return ratio * v


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3); via quaternions, which is stable for angles near 0 and pi."""
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


def rot6d_to_matrix(rot6d: torch.Tensor) -> torch.Tensor:
    """6D (..., 6) = two column vectors -> (..., 3, 3) by Gram-Schmidt (Zhou et al. 2019)."""
    a1, a2 = rot6d[..., 0:3], rot6d[..., 3:6]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rot6d(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns."""
    return torch.cat([matrix[..., :, 0], matrix[..., :, 1]], dim=-1)


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z): rotation b then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quaternion_slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Shortest-arc spherical interpolation.  q0, q1: (..., 4); t broadcastable to (...,) in [0, 1]."""
    q0 = q0 / q0.norm(dim=-1, keepdim=True)
    q1 = q1 / q1.norm(dim=-1, keepdim=True)
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)  # q and -q are the same rotation: take the short way
    dot = dot.abs().clamp(max=1.0)
    t = t[..., None] if t.dim() > 0 else t
    omega = torch.acos(dot)
    sin_omega = torch.sin(omega)
    near = sin_omega < 1e-4  # nearly parallel: linear interpolation is exact to float32
    safe_sin = torch.where(near, torch.ones_like(sin_omega), sin_omega)
    w0 = torch.where(near, 1.0 - t, torch.sin((1.0 - t) * omega) / safe_sin)
    w1 = torch.where(near, t, torch.sin(t * omega) / safe_sin)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def slerp_axis_angle(a0: torch.Tensor, a1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Interpolate axis-angle rotations (..., 3) along the shortest arc."""
    q = quaternion_slerp(axis_angle_to_quaternion(a0), axis_angle_to_quaternion(a1), t)
    return quaternion_to_axis_angle(q)


def slerp_matrix(r0: torch.Tensor, r1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Interpolate rotation matrices (..., 3, 3) along the shortest arc."""
    q = quaternion_slerp(matrix_to_quaternion(r0), matrix_to_quaternion(r1), t)
    return quaternion_to_matrix(q)


def pose_to_matrices(pose: torch.Tensor, num_joints: int) -> torch.Tensor:
    """Any accepted pose layout -> rotation matrices (B, J, 3, 3).

    pose: (B, J*3) or (B, J, 3) axis-angle, (B, J, 3, 3) matrices, or (B, J, 6) 6D.
    """
    if pose.dim() == 2 and pose.shape[1] == num_joints * 3:
        pose = pose.reshape(pose.shape[0], num_joints, 3)
    if pose.dim() == 3 and pose.shape[1:] == (num_joints, 3):
        return axis_angle_to_matrix(pose)
    if pose.dim() == 3 and pose.shape[1:] == (num_joints, 6):
        return rot6d_to_matrix(pose)
    if pose.dim() == 4 and pose.shape[1:] == (num_joints, 3, 3):
        return pose
    raise ValueError(
        f"pose has shape {tuple(pose.shape)}; expected (B,{num_joints * 3}) or (B,{num_joints},3) axis-angle, "
        f"(B,{num_joints},3,3) matrices or (B,{num_joints},6) 6D"
    )
