"""Triangle-mesh helpers: normals, exact closest points, area-uniform surface sampling.

Shapes: vertices (B, N, 3) or (N, 3) metres; faces (F, 3) long; batched functions
accept an unbatched (N, 3) mesh and return without the batch axis in that case.
"""

from __future__ import annotations

import torch

__all__ = ["face_normals", "vertex_normals", "face_areas", "closest_point_on_mesh",
           "closest_point_on_triangles", "sample_surface"]


def _batched(vertices: torch.Tensor) -> tuple[torch.Tensor, bool]:
    if vertices.dim() == 2:
        return vertices[None], True
    if vertices.dim() != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must be (B, N, 3) or (N, 3), got {tuple(vertices.shape)}")
    return vertices, False


def _face_cross(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    tri = vertices[:, faces]  # (B, F, 3, 3)
    return torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals (B, F, 3) (counter-clockwise winding points outwards)."""
    v, single = _batched(vertices)
    n = _face_cross(v, faces)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return n[0] if single else n


def face_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Triangle areas (B, F) in square metres."""
    v, single = _batched(vertices)
    a = 0.5 * _face_cross(v, faces).norm(dim=-1)
    return a[0] if single else a


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (B, N, 3)."""
    v, single = _batched(vertices)
    B, N = v.shape[:2]
    cross = _face_cross(v, faces)  # |cross| = 2 * area: area weighting for free
    acc = v.new_zeros(B, N, 3)
    for k in range(3):
        acc = acc.index_add(1, faces[:, k], cross)
    out = acc / acc.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return out[0] if single else out


def closest_point_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates (..., 3) of the point of triangle (a, b, c) closest to p (all (..., 3)).

    Exact Voronoi-region classification (Ericson, Real-Time Collision Detection, 5.1.5),
    vectorised: every region's answer is computed and the first matching region wins.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    eps = 1e-20

    def safe_div(n, d):
        return n / torch.where(d.abs() < eps, torch.full_like(d, eps), d)

    one, zero = torch.ones_like(d1), torch.zeros_like(d1)
    # Interior.
    denom = va + vb + vc
    v = safe_div(vb, denom)
    w = safe_div(vc, denom)
    bary = torch.stack([1 - v - w, v, w], -1)

    def put(mask, u0, u1, u2):
        nonlocal bary
        bary = torch.where(mask[..., None], torch.stack([u0, u1, u2], -1), bary)

    # Regions in reverse order of Ericson's tests so the earliest test has the last word.
    e43, e56 = d4 - d3, d5 - d6
    wbc = safe_div(e43, e43 + e56)
    put((va <= 0) & (e43 >= 0) & (e56 >= 0), zero, 1 - wbc, wbc)              # edge BC
    wac = safe_div(d2, d2 - d6)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - wac, zero, wac)                # edge AC
    put((d6 >= 0) & (d5 <= d6), zero, zero, one)                              # vertex C
    vab = safe_div(d1, d1 - d3)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - vab, vab, zero)                # edge AB
    put((d3 >= 0) & (d4 <= d3), zero, one, zero)                              # vertex B
    put((d1 <= 0) & (d2 <= 0), one, zero, zero)                               # vertex A
    return bary


def closest_point_on_mesh(
    points: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    max_elements: int = 1_000_000,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact closest surface point for each query point.

    points (B, P, 3), vertices (B, N, 3) (or unbatched (P,3)/(N,3)), faces (F, 3).
    Returns dist (B, P) metres, face_ids (B, P) long, bary (B, P, 3).  The search runs in
    chunks of at most ``max_elements`` point-triangle pairs (never a full (B, P, F, 3) tensor);
    dist is then recomputed from the chosen triangle so it is differentiable with respect to
    points and vertices (the face choice and barycentrics are treated as constants).
    """
    single = points.dim() == 2
    pts = points[None] if single else points
    v, _ = _batched(vertices)
    if v.shape[0] != pts.shape[0]:
        if v.shape[0] == 1:
            v = v.expand(pts.shape[0], -1, -1)
        else:
            raise ValueError(f"points batch {pts.shape[0]} != vertices batch {v.shape[0]}")
    B, P = pts.shape[:2]
    F = faces.shape[0]
    best_d = pts.new_full((B, P), float("inf"))
    best_f = torch.zeros(B, P, dtype=torch.long, device=pts.device)
    best_b = pts.new_zeros(B, P, 3)
    with torch.no_grad():
        tri_all = v.detach()[:, faces]  # (B, F, 3, 3)
        pd = pts.detach()
        f_chunk = max(1, min(F, max_elements // max(1, B * min(P, 256))))
        p_chunk = max(1, min(P, max_elements // max(1, B * f_chunk)))
        for p0 in range(0, P, p_chunk):
            q = pd[:, p0:p0 + p_chunk, None, :]  # (B, p, 1, 3)
            for f0 in range(0, F, f_chunk):
                tri = tri_all[:, None, f0:f0 + f_chunk]  # (B, 1, f, 3, 3)
                a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
                bary = closest_point_on_triangles(q, a, b, c)  # (B, p, f, 3)
                closest = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
                d = (closest - q).square().sum(-1)  # (B, p, f)
                dmin, arg = d.min(-1)
                better = dmin < best_d[:, p0:p0 + p_chunk]
                best_d[:, p0:p0 + p_chunk] = torch.where(better, dmin, best_d[:, p0:p0 + p_chunk])
                best_f[:, p0:p0 + p_chunk] = torch.where(better, arg + f0, best_f[:, p0:p0 + p_chunk])
                bsel = torch.gather(bary, 2, arg[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
                best_b[:, p0:p0 + p_chunk] = torch.where(better[..., None], bsel, best_b[:, p0:p0 + p_chunk])
    corners = torch.gather(v, 1, faces[best_f].reshape(B, -1, 1).expand(-1, -1, 3)).reshape(B, P, 3, 3)
    surface = (best_b[..., None] * corners).sum(-2)
    dist = (pts - surface).norm(dim=-1)
    if single:
        return dist[0], best_f[0], best_b[0]
    return dist, best_f, best_b


def sample_surface(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    n: int,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """n points uniformly distributed over the surface area.

    vertices (N, 3), faces (F, 3).  Returns face_ids (n,) long and bary (n, 3); reproducible
    for a seeded ``generator``.
    """
    if vertices.dim() != 2:
        raise ValueError(f"sample_surface takes one mesh (N, 3), got {tuple(vertices.shape)}")
    areas = face_areas(vertices.detach(), faces)
    if not torch.isfinite(areas).all() or float(areas.sum()) <= 0:
        raise ValueError("mesh has no surface area to sample")
    face_ids = torch.multinomial(areas, n, replacement=True, generator=generator)
    r = torch.rand(n, 2, generator=generator, dtype=vertices.dtype)
    s = r[:, 0].sqrt()  # sqrt makes the density uniform over the triangle
    bary = torch.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], dim=-1)
    return face_ids, bary
