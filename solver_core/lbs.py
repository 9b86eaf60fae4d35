"""Differentiable linear blend skinning for SMPL-layout body models.

Written for this project from the published SMPL equations (Loper et al. 2015):
    v_shaped = v_template + shapedirs . betas
    J        = J_regressor . v_shaped
    v_posed  = v_shaped + posedirs . (R[1:] - I)            (optional)
    G_j      = G_parent(j) . [R_j | J_j - J_parent(j)]       (forward kinematics)
    A_j      = G_j . [I | -J_j]                              (skinning transforms)
    v        = sum_j weights[:, j] A_j v_posed + trans

Speed notes (why it is written this way):
  * Joints never need the mesh: J_regressor . shapedirs is precomputed once per
    model, so evaluating a few surface points costs O(P) not O(N).
  * Forward kinematics runs one batched matmul per tree depth level (9 for
    SMPL) rather than one per joint.
  * Skinning blends the 3x4 transforms per point (weights @ A) and applies one
    small product, which is the cheapest order on CPU for N >> 24.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from .rotations import pose_to_matrices

__all__ = ["SurfacePoints", "LBSOutput", "forward", "ModelCache", "kinematic_levels"]


@dataclass(frozen=True, eq=False)
class SurfacePoints:
    """Points on the template surface: face ids (P,) long and barycentric weights (P, 3).

    A point is ``sum_k bary[:, k] * vertex[faces[face_ids, k]]``; skinning
    evaluates the three corners and combines them, so the point moves exactly
    like the surface it lies on.
    """

    face_ids: torch.Tensor
    bary: torch.Tensor
    vertex_ids: torch.Tensor | None = None  # set by from_vertex_ids: points ARE vertices

    @staticmethod
    def from_vertex_ids(ids) -> "SurfacePoints":
        ids = torch.as_tensor(ids, dtype=torch.long).reshape(-1)
        bary = torch.zeros(ids.shape[0], 3)
        bary[:, 0] = 1.0
        return SurfacePoints(face_ids=torch.full_like(ids, -1), bary=bary, vertex_ids=ids)

    def __len__(self) -> int:
        return int(self.bary.shape[0])

    def corner_vertices(self, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertex ids (P, K) and weights (P, K) that define the points (K = 1 or 3)."""
        if self.vertex_ids is not None:
            return self.vertex_ids[:, None], torch.ones(len(self), 1)
        fid = torch.as_tensor(self.face_ids, dtype=torch.long)
        if fid.numel() and (int(fid.min()) < 0 or int(fid.max()) >= faces.shape[0]):
            raise ValueError(f"face_ids must lie in [0, {faces.shape[0]}), got [{int(fid.min())}, {int(fid.max())}]")
        return faces[fid], torch.as_tensor(self.bary, dtype=torch.float32)


@dataclass
class LBSOutput:
    joints: torch.Tensor            # (B, 24, 3) posed joint positions (+ trans)
    vertices: torch.Tensor          # (B, N, 3) or (B, P, 3) for a SurfacePoints subset
    joint_rotations: torch.Tensor   # (B, 24, 3, 3) global rotations
    transforms: torch.Tensor        # (B, 24, 4, 4) skinning transforms (rest -> posed, without trans)


def kinematic_levels(parents: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Joints grouped by depth: [(joint ids (n,), parent ids (n,)), ...] excluding the root.

    parents: (J,) long with parents[0] == -1 and parents[j] < j.
    """
    par = [int(p) for p in parents]
    if par[0] != -1 or any(not (0 <= p < j) for j, p in enumerate(par) if j > 0):
        raise ValueError("parents must have parents[0] == -1 and 0 <= parents[j] < j for j > 0")
    depth = [0] * len(par)
    for j in range(1, len(par)):
        depth[j] = depth[par[j]] + 1
    levels = []
    for d in range(1, max(depth) + 1):
        ids = [j for j in range(len(par)) if depth[j] == d]
        levels.append((torch.tensor(ids), torch.tensor([par[j] for j in ids])))
    return levels


class ModelCache:
    """Derived per-model tensors, computed on first use (owned by the BodyModel)."""

    def __init__(self, model) -> None:
        self._m = model

    @cached_property
    def shapedirs_flat(self) -> torch.Tensor:  # (N*3, nb)
        m = self._m
        return m.shapedirs.reshape(-1, m.shapedirs.shape[-1]).contiguous()

    @cached_property
    def posedirs_flat(self) -> torch.Tensor | None:  # (N*3, 207)
        m = self._m
        return None if m.posedirs is None else m.posedirs.reshape(-1, m.posedirs.shape[-1]).contiguous()

    @cached_property
    def joint_template(self) -> torch.Tensor:  # (J, 3)
        return self._m.J_regressor @ self._m.v_template

    @cached_property
    def joint_shapedirs(self) -> torch.Tensor:  # (J*3, nb): joints are linear in betas
        m = self._m
        return torch.einsum("jn,nkb->jkb", m.J_regressor, m.shapedirs).reshape(-1, m.shapedirs.shape[-1]).contiguous()

    @cached_property
    def levels(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return kinematic_levels(self._m.parents)

    @cached_property
    def level_order(self) -> tuple[torch.Tensor | None, list[int]]:
        """Permutation from level-concatenated order back to joint order (None if identity)."""
        order = torch.cat([torch.zeros(1, dtype=torch.long)] + [ids for ids, _ in self.levels])
        inverse = torch.argsort(order)
        if torch.equal(order, torch.arange(order.numel())):
            return None, [0] + [int(ids.numel()) for ids, _ in self.levels]
        return inverse, [0] + [int(ids.numel()) for ids, _ in self.levels]

    @cached_property
    def parent_slices(self) -> list[torch.Tensor]:
        """Per level: positions of the parents inside the previous level's block."""
        out = []
        prev = torch.zeros(1, dtype=torch.long)
        for ids, par in self.levels:
            lookup = {int(j): i for i, j in enumerate(prev)}
            out.append(torch.tensor([lookup[int(p)] for p in par]))
            prev = ids
        return out

    @cached_property
    def weights_t(self) -> torch.Tensor:  # (J, N) for one matmul per batch
        return self._m.weights.t().contiguous()


def _shape_betas(betas: torch.Tensor, num_betas: int) -> torch.Tensor:
    if betas.dim() == 1:
        betas = betas[None]
    if betas.dim() != 2:
        raise ValueError(f"betas must be (B, nb), got shape {tuple(betas.shape)}")
    if betas.shape[1] > num_betas:
        raise ValueError(f"betas has {betas.shape[1]} components but the model has only {num_betas}")
    return betas


def _forward_kinematics(cache: ModelCache, rot: torch.Tensor, joints: torch.Tensor):
    """Global rotations (B,J,3,3) and joint positions (B,J,3) from local rotations and rest joints."""
    B = rot.shape[0]
    parents = cache._m.parents
    rel = joints.clone()
    rel[:, 1:] = joints[:, 1:] - joints[:, parents[1:]]
    # Local 3x4 transforms K_j = [R_j | J_j - J_parent]; chain G_j = G_p K_j level by level.
    local = torch.cat([rot, rel[..., None]], dim=-1)  # (B, J, 3, 4)
    bottom = rot.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(B, 1, 1, 4)
    inverse, _ = cache.level_order
    blocks = [local[:, :1]]
    prev = local[:, :1]
    for (ids, _), pos in zip(cache.levels, cache.parent_slices):
        parent_tf = prev[:, pos]  # (B, n, 3, 4)
        child = local[:, ids]
        # [Rp | tp] [Rc | tc; 0 1] = [Rp Rc | Rp tc + tp]
        child4 = torch.cat([child, bottom.expand(B, ids.numel(), 1, 4)], dim=2)
        cur = parent_tf @ child4
        blocks.append(cur)
        prev = cur
    world = torch.cat(blocks, dim=1)
    if inverse is not None:
        world = world[:, inverse]
    return world[..., :3], world[..., 3]


def forward(
    model,
    betas: torch.Tensor,
    pose: torch.Tensor,
    trans: torch.Tensor | None = None,
    points: SurfacePoints | None = None,
    pose_blend: bool = True,
) -> LBSOutput:
    """Pose a body model.

    model: BodyModel.  betas: (B, nb) with nb <= model.num_betas (missing components are 0);
    a batch of 1 broadcasts against the pose batch.  pose: (B, 24, 3) / (B, 72) axis-angle,
    (B, 24, 3, 3) matrices or (B, 24, 6) 6D; pose[:, 0] rotates the body about the pelvis joint.
    trans: (B, 3) metres or None.  points: evaluate only these surface points instead of
    every vertex.  pose_blend: apply posedirs when the model has them.
    Returns LBSOutput (joints (B,24,3), vertices (B,N|P,3), joint_rotations, transforms).
    """
    cache = model.cache
    J = model.parents.shape[0]
    rot = pose_to_matrices(pose, J)
    betas = _shape_betas(betas.to(rot.dtype), model.num_betas)
    nb = betas.shape[1]
    B = max(rot.shape[0], betas.shape[0])
    if rot.shape[0] != B:
        if rot.shape[0] != 1:
            raise ValueError(f"pose batch {rot.shape[0]} does not match betas batch {betas.shape[0]}")
        rot = rot.expand(B, -1, -1, -1)
    if betas.shape[0] not in (1, B):
        raise ValueError(f"betas batch {betas.shape[0]} does not match pose batch {B}")

    # Rest joints directly from betas (no mesh needed).
    rest_joints = cache.joint_template + (betas @ cache.joint_shapedirs[:, :nb].t()).reshape(-1, J, 3)
    rest_joints = rest_joints.expand(B, J, 3)
    glob_rot, glob_pos = _forward_kinematics(cache, rot, rest_joints)
    # Skinning transforms: A_j x = G_j (x - J_j) + t_j.
    offset = glob_pos - (glob_rot @ rest_joints[..., None])[..., 0]
    A = torch.cat([glob_rot, offset[..., None]], dim=-1)  # (B, J, 3, 4)

    if points is None:
        v = model.v_template.reshape(1, -1) + betas @ cache.shapedirs_flat[:, :nb].t()  # (B|1, N*3)
        weights = model.weights
        posedirs = cache.posedirs_flat if pose_blend else None
        n = model.v_template.shape[0]
    else:
        vids, bw = points.corner_vertices(model.faces)
        flat = vids.reshape(-1)
        n = flat.numel()
        sd = model.shapedirs[flat, :, :nb].reshape(n * 3, nb)
        v = model.v_template[flat].reshape(1, -1) + betas @ sd.t()
        weights = model.weights[flat]
        posedirs = None
        if pose_blend and model.posedirs is not None:
            posedirs = model.posedirs[flat].reshape(n * 3, -1)
    if pose_blend and posedirs is not None:
        eye = torch.eye(3, dtype=rot.dtype)
        feat = (rot[:, 1:] - eye).reshape(B, -1)
        v = v + feat @ posedirs.t()
    v = v.reshape(-1, n, 3).expand(B, n, 3)

    # Blend the 3x4 transforms per point, then apply: (B, n, 12).
    T = (weights @ A.reshape(B, J, 12)).reshape(B, n, 3, 4)
    verts = (T[..., :3] @ v[..., None])[..., 0] + T[..., 3]

    if points is not None:
        verts = (verts.reshape(B, len(points), -1, 3) * bw.to(verts.dtype)[None, :, :, None]).sum(2)
    joints = glob_pos
    if trans is not None:
        trans = trans.to(verts.dtype).reshape(-1, 1, 3)
        verts = verts + trans
        joints = joints + trans
    transforms = torch.cat([A, A.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(B, J, 1, 4)], dim=2)
    return LBSOutput(joints=joints, vertices=verts, joint_rotations=glob_rot, transforms=transforms)
