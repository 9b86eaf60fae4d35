"""Mesh helpers: exact closest point, normals, surface sampling; body-model CLI verbs."""

from __future__ import annotations

import json

import pytest
import torch

from uuomocap.solver_core.body_model import load_body_model
from uuomocap.solver_core.lbs import SurfacePoints, forward
from uuomocap.solver_core.mesh import (
    closest_point_on_mesh,
    closest_point_on_triangles,
    closest_point_on_vertex_fans,
    face_areas,
    face_normals,
    sample_surface,
    vertex_normals,
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Small ops: intra-op threads only add contention on the shared 2-core machine.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def low():
    return load_body_model("open-low")


def test_closest_point_on_triangle_regions():
    a, b, c = torch.tensor([0.0, 0, 0]), torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0])
    cases = {
        (0.2, 0.2, 0.5): (0.6, 0.2, 0.2),    # above the interior
        (-1.0, -1.0, 0.0): (1.0, 0.0, 0.0),  # vertex A region
        (2.0, -0.5, 0.0): (0.0, 1.0, 0.0),   # vertex B region
        (-0.3, 3.0, 1.0): (0.0, 0.0, 1.0),   # vertex C region
        (0.5, -1.0, 0.0): (0.5, 0.5, 0.0),   # edge AB
        (-1.0, 0.25, 0.0): (0.75, 0.0, 0.25),  # edge AC
        (1.0, 1.0, 0.0): (0.0, 0.5, 0.5),    # edge BC
    }
    p = torch.tensor(list(cases))
    bary = closest_point_on_triangles(p, a.expand_as(p), b.expand_as(p), c.expand_as(p))
    torch.testing.assert_close(bary, torch.tensor(list(cases.values())), atol=1e-6, rtol=0)


def test_closest_point_matches_brute_force(low):
    g = torch.Generator().manual_seed(0)
    pose = torch.randn(2, 24, 3, generator=g) * 0.3
    verts = forward(low, torch.zeros(1, 16), pose).vertices
    pts = verts[:, torch.randint(0, low.num_vertices, (40,), generator=g)] + torch.randn(2, 40, 3, generator=g) * 0.03
    # Near and far queries: far ones fall through to the wider candidate stages.
    pts = torch.cat([pts, pts[:, :10] + torch.randn(2, 10, 3, generator=g) * 0.3], dim=1)
    dist, fid, bary = closest_point_on_mesh(pts, verts, low.faces, max_elements=60_000, candidates=(2, 8))
    assert (bary >= -1e-6).all() and torch.allclose(bary.sum(-1), torch.ones(2, 50), atol=1e-5)
    # Brute force over every face with the same exact triangle routine, no chunking.
    tri = verts[:, low.faces]  # (B, F, 3, 3)
    q = pts[:, :, None, :]
    bb = closest_point_on_triangles(q, tri[:, None, :, 0], tri[:, None, :, 1], tri[:, None, :, 2])
    cp = (bb[..., None] * tri[:, None]).sum(-2)
    brute = (cp - q).norm(dim=-1).min(-1).values
    torch.testing.assert_close(dist, brute, atol=1e-6, rtol=0)
    # ...and no surface sample is closer than the reported distance.
    sf, sb = sample_surface(verts[0], low.faces, 5000, g)
    samples = (verts[0][low.faces[sf]] * sb[..., None]).sum(1)
    assert (torch.cdist(pts[0], samples).min(1).values >= dist[0] - 1e-6).all()


def test_closest_point_on_vertex_fans_tests_each_vertex_fan_like_every_column(low):
    # The chamfer stages' face pick: only each vertex's own faces are tested; the answer must be the
    # one from testing every column of the padded vertex-face table (first smallest distance wins).
    from uuomocap.solver_core.chamfer import vertex_face_table

    g = torch.Generator().manual_seed(3)
    verts = forward(low, torch.randn(1, 16, generator=g), torch.randn(3, 24, 3, generator=g) * 0.3).vertices  # (3,N,3)
    table = vertex_face_table(low.faces, low.num_vertices)
    vid = torch.randint(0, low.num_vertices, (3, 25), generator=g)
    pts = verts[torch.arange(3)[:, None], vid] + torch.randn(3, 25, 3, generator=g) * 0.02
    face, bary = closest_point_on_vertex_fans(pts, verts, vid, low.faces, table)
    cand = table[vid]  # (3,25,K)
    tri = verts[torch.arange(3)[:, None, None, None], low.faces[cand]]  # (3,25,K,3,3)
    q = pts[:, :, None]
    bb = closest_point_on_triangles(q.expand_as(tri[..., 0, :]), tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    best = (((bb[..., None] * tri).sum(-2) - q) ** 2).sum(-1).argmin(2, keepdim=True)
    assert torch.equal(face, torch.gather(cand, 2, best)[..., 0])
    assert torch.equal(bary, torch.gather(bb, 2, best[..., None].expand(-1, -1, 1, 3))[:, :, 0])
    # every answer is a face of its vertex, with a valid barycentric point
    assert (low.faces[face] == vid[..., None]).any(-1).all()
    assert (bary >= 0).all() and torch.allclose(bary.sum(-1), torch.ones(3, 25))


def test_closest_point_distance_is_differentiable(low):
    verts = low.v_template[None].clone().requires_grad_()
    pts = (low.v_template[:5] + 0.02)[None].requires_grad_()
    dist, _, _ = closest_point_on_mesh(pts, verts, low.faces)
    dist.sum().backward()
    assert torch.isfinite(pts.grad).all() and pts.grad.abs().sum() > 0 and verts.grad.abs().sum() > 0


def test_normals_point_outwards(low):
    v, f = low.v_template, low.faces
    vn = vertex_normals(v, f)
    assert vn[v[:, 1].argmax(), 1] > 0.9  # top of the head points up
    assert vn[v[:, 2].argmax(), 2] > 0.5  # the frontmost point faces +Z
    torch.testing.assert_close(vn.norm(dim=-1), torch.ones(len(v)), atol=1e-5, rtol=0)
    fn = face_normals(v[None].expand(3, -1, -1), f)
    assert fn.shape == (3, f.shape[0], 3)
    # Closed surface: the area-weighted normals cancel.
    assert (face_areas(v, f)[:, None] * face_normals(v, f)).sum(0).norm() < 1e-4


def test_sample_surface_is_seeded_and_area_uniform(low):
    v, f = low.v_template, low.faces
    a1 = sample_surface(v, f, 4000, torch.Generator().manual_seed(5))
    a2 = sample_surface(v, f, 4000, torch.Generator().manual_seed(5))
    assert torch.equal(a1[0], a2[0]) and torch.equal(a1[1], a2[1])
    fid, bary = a1
    assert (bary >= 0).all() and torch.allclose(bary.sum(-1), torch.ones(4000))
    # Share of samples above the pelvis ~ share of area above the pelvis.
    area = face_areas(v, f)
    upper_faces = v[f].mean(1)[:, 1] > 0
    expected = float(area[upper_faces].sum() / area.sum())
    got = float(upper_faces[fid].float().mean())
    assert abs(got - expected) < 0.03
    pts = forward(low, torch.zeros(1, 16), torch.zeros(1, 72), points=SurfacePoints(fid[:10], bary[:10])).vertices
    d, _, _ = closest_point_on_mesh(pts, v[None], f)
    assert d.max() < 1e-5


def test_body_model_info_cli(capsys):
    from uuomocap.cli import main

    assert main(["body-model", "info", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["vertices"] == 1229 and data["betas"] == 16 and data["joints"] == 24
    h = data["height_m"]
    assert 1.4 < h["beta0_minus_2sd"] < h["betas_0"] < h["beta0_plus_2sd"] < 2.1
    assert main(["body-model", "info", "--model", "open-full"]) == 0
    assert "13718" in capsys.readouterr().out
    assert main(["body-model", "info", "--model", "/nonexistent/SMPL_NEUTRAL.pkl"]) == 2
    assert "smpl.is.tue.mpg.de" in capsys.readouterr().err


def test_bench_cli_writes_json(tmp_path, capsys):
    from uuomocap.cli import main

    out = tmp_path / "bench.json"
    assert main(["bench", "body-model", "--batches", "1", "--repeats", "1", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    cases = {(r["case"], r["shape"]) for r in data["rows"]}
    assert ("subset50", "shared") in cases and ("full", "per-frame") in cases
    assert all(r["forward_ms"] > 0 and r["forward_backward_ms"] > 0 for r in data["rows"])
    assert "fwd+bwd" in capsys.readouterr().out
