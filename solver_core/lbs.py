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
    SMPL) rather than one per joint, with one split/cat instead of per-level
    slices (each slice costs a zero-filled full-size gradient in backward).
  * With one body shape for the batch (the usual solver case) skinning is a
    single (B*3, 4J) @ (4J, n) matmul against X[(j,k), n] = w[n,j] (v_n,1)[k]:
    no per-point 3x4 transforms are ever built.  Per-frame shapes or pose blend
    shapes use per-point transforms in a component-major (3, n) layout.
  * Tiny batched matmuls (3x3 @ 3x1 per vertex) are avoided: on CPU they cost
    more in backward than the whole rest of the pass.
"""

from __future__ import annotations

import weakref
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
    skinning: torch.Tensor          # (B, 24, 3, 4) top rows of the skinning transforms

    @property
    def transforms(self) -> torch.Tensor:
        """(B, 24, 4, 4) skinning transforms (rest pose -> posed, without trans)."""
        A = self.skinning
        row = A.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(A.shape[:-2] + (1, 4))
        return torch.cat([A, row], dim=-2)


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
        # Per-SurfacePoints gathers of template / shape basis / weights rows, reused while the
        # SurfacePoints object lives (solvers evaluate the same points every iteration).
        self._points: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def __getstate__(self) -> dict:
        # a pickled model (e.g. sent to a solver worker process) rebuilds its derived tensors there
        return {"_m": self._m}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["_m"])

    def point_data(self, points: "SurfacePoints") -> tuple:
        """(template (3,n), shapedirs (nb,3,n), weights (J,n), posedirs (207,3,n)|None, corner weights (P,K))."""
        hit = self._points.get(points)
        if hit is not None:
            return hit
        vids, bw = points.corner_vertices(self._m.faces)
        flat = vids.reshape(-1)
        data = (
            self.template_cm[:, flat].contiguous(),
            self.shapedirs_cm[:, :, flat].contiguous(),
            self.weights_t[:, flat].contiguous(),
            None if self.posedirs_cm is None else self.posedirs_cm[:, :, flat].contiguous(),
            bw.to(self._m.v_template.dtype),
        )
        self._points[points] = data
        return data

    # Vertex data in component-major layout ((3, N): all x, then all y, then all z) so the
    # skinning below works on long contiguous rows.
    @cached_property
    def template_cm(self) -> torch.Tensor:  # (3, N)
        return self._m.v_template.t().contiguous()

    @cached_property
    def shapedirs_cm(self) -> torch.Tensor:  # (nb, 3, N)
        return self._m.shapedirs.permute(2, 1, 0).contiguous()

    @cached_property
    def posedirs_cm(self) -> torch.Tensor | None:  # (207, 3, N)
        m = self._m
        return None if m.posedirs is None else m.posedirs.permute(2, 1, 0).contiguous()

    @cached_property
    def weights_t(self) -> torch.Tensor:  # (J, N)
        return self._m.weights.t().contiguous()

    @cached_property
    def joint_template(self) -> torch.Tensor:  # (2J, 3): rest joints, then offsets to the parent
        m = self._m
        j = m.J_regressor @ m.v_template
        return torch.cat([j, self._relative(j)])

    @cached_property
    def joint_shapedirs_t(self) -> torch.Tensor:  # (nb, 2J*3): joints (and offsets) are linear in betas
        m = self._m
        jd = torch.einsum("jn,nkb->bjk", m.J_regressor, m.shapedirs)  # (nb, J, 3)
        return torch.cat([jd, self._relative(jd)], dim=1).reshape(jd.shape[0], -1).contiguous()

    def _relative(self, j: torch.Tensor) -> torch.Tensor:
        parents = self._m.parents
        rel = j.clone()
        rel[..., 1:, :] = j[..., 1:, :] - j[..., parents[1:], :]
        return rel

    @cached_property
    def levels(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return kinematic_levels(self._m.parents)

    @cached_property
    def fk_plan(self) -> tuple[list[int] | None, list, torch.Tensor | None]:
        """How forward kinematics walks the tree, level by level.

        Returns (split sizes, per-level parent selectors, inverse permutation).  When every
        level's joints are contiguous in joint order (true for SMPL), the local transforms are
        cut with one torch.split (one cheap backward) instead of per-level slicing (a zero-filled
        full-size gradient per slice); otherwise split sizes is None and levels are indexed.
        A parent selector is None (same block or single parent: broadcast), or an index tensor.
        The inverse permutation maps level order back to joint order (None when identity).
        """
        levels = self.levels
        order = torch.cat([torch.zeros(1, dtype=torch.long)] + [ids for ids, _ in levels])
        identity = torch.equal(order, torch.arange(order.numel()))
        sizes = [1] + [int(ids.numel()) for ids, _ in levels] if identity else None
        parents = []
        prev = [0]
        for ids, par in levels:
            pos = [prev.index(int(p)) for p in par]
            if len(set(pos)) == 1 and len(prev) == 1 or pos == list(range(len(prev))):
                parents.append(None)
            else:
                parents.append(torch.tensor(pos))
            prev = [int(i) for i in ids]
        inverse = None if identity else torch.argsort(order)
        return sizes, parents, inverse


def _shape_betas(betas: torch.Tensor, num_betas: int) -> torch.Tensor:
    if betas.dim() == 1:
        betas = betas[None]
    if betas.dim() != 2:
        raise ValueError(f"betas must be (B, nb), got shape {tuple(betas.shape)}")
    if betas.shape[1] > num_betas:
        raise ValueError(f"betas has {betas.shape[1]} components but the model has only {num_betas}")
    return betas


_HOMOGENEOUS_ROW = torch.tensor([0.0, 0.0, 0.0, 1.0])


def _forward_kinematics(cache: ModelCache, rot: torch.Tensor, rel: torch.Tensor) -> torch.Tensor:
    """World 3x4 transforms (B, J, 3, 4) from local rotations (B,J,3,3) and offsets to the parent (B,J,3)."""
    B, J = rot.shape[:2]
    local = torch.cat([rot, rel[..., None]], dim=-1)  # (B, J, 3, 4) = [R_j | J_j - J_parent]
    row = _HOMOGENEOUS_ROW.to(dtype=rot.dtype, device=rot.device).expand(B, J, 1, 4)
    local4 = torch.cat([local, row], dim=2)  # (B, J, 4, 4)
    sizes, parent_sel, inverse = cache.fk_plan
    if sizes is not None:
        children = torch.split(local4, sizes, dim=1)[1:]
    else:
        children = [local4[:, ids] for ids, _ in cache.levels]
    prev = local[:, :1]  # the root's world transform is its local one
    blocks = [prev]
    for child, sel in zip(children, parent_sel):
        # W_c = W_p [R_c | o_c; 0 0 0 1]
        cur = (prev if sel is None else prev[:, sel]) @ child
        blocks.append(cur)
        prev = cur
    world = torch.cat(blocks, dim=1)
    return world if inverse is None else world[:, inverse]


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
    dtype = model.v_template.dtype  # float32: inputs of other precisions are converted
    rot = pose_to_matrices(pose.to(dtype), J)
    betas = _shape_betas(torch.as_tensor(betas).to(dtype), model.num_betas)
    nb = betas.shape[1]
    B = max(rot.shape[0], betas.shape[0])
    if rot.shape[0] != B:
        if rot.shape[0] != 1:
            raise ValueError(f"pose batch {rot.shape[0]} does not match betas batch {betas.shape[0]}")
        rot = rot.expand(B, -1, -1, -1)
    if betas.shape[0] not in (1, B):
        raise ValueError(f"betas batch {betas.shape[0]} does not match pose batch {B}")

    # Rest joints and their offsets to the parent straight from betas (no mesh needed).
    jt = cache.joint_template
    jt = (jt.reshape(1, -1) + betas @ cache.joint_shapedirs_t[:nb]).reshape(-1, 2 * J, 3).expand(B, 2 * J, 3)
    rest_joints, rel = torch.split(jt, [J, J], dim=1)
    world = _forward_kinematics(cache, rot, rel)
    glob_rot, glob_pos = torch.split(world, [3, 1], dim=-1)
    glob_pos = glob_pos[..., 0]
    # Skinning transforms A_j = [G_j | t_j - G_j J_j]: x -> G_j (x - J_j) + t_j.
    offset = glob_pos - (glob_rot @ rest_joints[..., None])[..., 0]
    A = torch.cat([glob_rot, offset[..., None]], dim=-1)  # (B, J, 3, 4)

    # Rest-pose geometry in component-major layout: template (3, n), shape basis (nb, 3, n).
    if points is None:
        tmpl, sdirs, wt = cache.template_cm, cache.shapedirs_cm[:nb], cache.weights_t
        pdirs = cache.posedirs_cm
        corners = None
    else:
        tmpl, sdirs, wt, pdirs, corners = cache.point_data(points)  # corners: (P, K) weights
        sdirs = sdirs[:nb]
    n = tmpl.shape[1]
    use_pose_blend = pose_blend and pdirs is not None
    # A'[b, i, (j, k)] = A[b, j, i, k]: blending and applying the transforms is then one matmul
    # against X[(j, k), n] = weights[n, j] * (v_n, 1)[k].
    A_rows = A.permute(0, 2, 1, 3).reshape(B, 3, J * 4)

    if betas.shape[0] == 1 and not use_pose_blend:
        # One body shape for the whole batch (the usual case: one subject): X is shared, so the
        # skinning is a single (B*3, 4J) @ (4J, n) product -- no per-point 3x4 transforms.
        v = tmpl + (betas[0] @ sdirs.reshape(nb, -1)).reshape(3, n)
        vh = torch.cat([v, v.new_ones(1, n)], dim=0)  # (4, n)
        X = (wt[:, None, :] * vh[None]).reshape(J * 4, n)
        if corners is not None:
            X = (X.reshape(J * 4, len(points), -1) * corners).sum(-1)  # fold the barycentrics in
        verts = (A_rows.reshape(B * 3, J * 4) @ X).reshape(B, 3, -1).transpose(1, 2)
    else:
        # Per-frame shapes or pose blend shapes: per-point transforms T (B, 3, 4, n), applied
        # component-wise on long rows.
        v = tmpl + (betas @ sdirs.reshape(nb, -1)).reshape(-1, 3, n)  # (B|1, 3, n)
        if use_pose_blend:
            feat = (rot[:, 1:] - torch.eye(3, dtype=rot.dtype, device=rot.device)).reshape(B, -1)
            v = v + (feat @ pdirs.reshape(pdirs.shape[0], -1)).reshape(B, 3, n)
        T = (A.reshape(B, J, 12).transpose(1, 2).reshape(B * 12, J) @ wt).reshape(B, 3, 4, n)
        out = T[:, :, 0] * v[:, None, 0] + T[:, :, 1] * v[:, None, 1] + T[:, :, 2] * v[:, None, 2] + T[:, :, 3]
        if corners is not None:
            out = (out.reshape(B, 3, len(points), -1) * corners).sum(-1)
        verts = out.transpose(1, 2)
    verts = verts.contiguous()
    joints = glob_pos
    if trans is not None:
        trans = trans.to(dtype).reshape(-1, 1, 3)
        verts = verts + trans
        joints = joints + trans
    return LBSOutput(joints=joints, vertices=verts, joint_rotations=glob_rot, skinning=A)
