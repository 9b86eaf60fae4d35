"""Body model layer: loaders (open model, official SMPL pickle layout, npz), the restricted
unpickler, LBS, rotations, parts."""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import torch

from uuomocap.solver_core.body_model import (
    JOINT_NAMES,
    SMPL_PARENTS,
    BodyModelError,
    load_body_model,
    standing_height,
)
from uuomocap.solver_core.lbs import SurfacePoints, forward
from uuomocap.solver_core.parts import PART_JOINTS, connected_subtrees, kinematic_chains, vertex_dominant_joint
from uuomocap.solver_core.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    quaternion_slerp,
    axis_angle_to_quaternion,
    quaternion_to_axis_angle,
    rot6d_to_matrix,
    slerp_axis_angle,
)
from uuomocap.solver_core.safe_pickle import UnsafePickleError, load_restricted_pickle


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


@pytest.fixture(scope="module")
def full():
    return load_body_model("open-full")


# --------------------------------------------------------------------------- official SMPL layout
def _fake_official_arrays(rng: np.random.Generator, n: int = 40, f: int = 30) -> dict:
    jr = rng.random((24, n)) * (rng.random((24, n)) < 0.2)
    jr[:, 0] += 0.1
    jr /= jr.sum(1, keepdims=True)
    w = rng.random((n, 24))
    w /= w.sum(1, keepdims=True)
    return {
        "v_template": rng.normal(size=(n, 3)),
        "f": rng.integers(0, n, size=(f, 3)).astype(np.uint32),
        "shapedirs": rng.normal(size=(n, 3, 10)) * 0.01,
        "posedirs": rng.normal(size=(n, 3, 207)) * 0.001,
        "J_regressor": jr,
        "weights": w,
        "kintree_table": np.array([[4294967295] + list(SMPL_PARENTS[1:]), list(range(24))], dtype=np.int64),
        "J": rng.normal(size=(24, 3)),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
        "vert_sym_idxs": np.arange(n),
    }


def _write_official_pickle(path, arrays: dict, monkeypatch) -> None:
    """Pickle ``arrays`` like the official SMPL files: chumpy Ch for shapedirs/posedirs/weights,
    a scipy.sparse.csc csc_matrix for J_regressor, protocol 2.  The chumpy and scipy classes are
    fakes registered under the original module names, so neither library is needed."""

    class Ch:  # state layout of chumpy.ch.Ch: a dict with the value in 'x'
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"

    class csc_matrix:  # state layout of old scipy.sparse.csc.csc_matrix
        pass

    csc_matrix.__module__, csc_matrix.__qualname__ = "scipy.sparse.csc", "csc_matrix"
    for name in ("chumpy", "chumpy.ch", "scipy", "scipy.sparse", "scipy.sparse.csc"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    sys.modules["chumpy.ch"].Ch = Ch
    sys.modules["scipy.sparse.csc"].csc_matrix = csc_matrix

    def ch(x):
        obj = Ch()
        obj.__dict__.update({"x": x, "dterms": ("x",), "_dirty_vars": set()})
        return obj

    jr = arrays["J_regressor"]
    cols, data, indices, indptr = jr.T, [], [], [0]
    for col in cols:
        nz = np.nonzero(col)[0]
        indices.extend(nz.tolist())
        data.extend(col[nz].tolist())
        indptr.append(len(indices))
    sparse = csc_matrix()
    sparse.__dict__.update({
        "_shape": jr.shape, "data": np.array(data), "indices": np.array(indices, dtype=np.int32),
        "indptr": np.array(indptr, dtype=np.int32), "format": "csc", "maxprint": 50,
    })
    payload = dict(arrays)
    payload.update(shapedirs=ch(arrays["shapedirs"]), posedirs=ch(arrays["posedirs"]),
                   weights=ch(arrays["weights"]), J_regressor=sparse)
    with open(path, "wb") as fh:
        pickle.dump(payload, fh, protocol=2)


def test_official_pickle_round_trip(tmp_path, monkeypatch):
    arrays = _fake_official_arrays(np.random.default_rng(0))
    path = tmp_path / "basicModel_neutral_lbs_10_207_0_v1.0.0.pkl"
    _write_official_pickle(path, arrays, monkeypatch)
    monkeypatch.undo()  # the loader must not need the fake chumpy/scipy modules
    raw = path.read_bytes()
    assert b"chumpy.ch\nCh" in raw and b"scipy.sparse.csc\ncsc_matrix" in raw and raw[:2] == b"\x80\x02"
    model = load_body_model(path)
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
        got = getattr(model, key).numpy()
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, arrays[key].astype(np.float32), rtol=0, atol=0, err_msg=key)
    assert model.faces.dtype == torch.long and np.array_equal(model.faces.numpy(), arrays["f"].astype(np.int64))
    assert model.parents.tolist() == list(SMPL_PARENTS)
    assert model.num_betas == 10 and model.joint_names == JOINT_NAMES
    out = forward(model, torch.zeros(1, 10), torch.zeros(1, 24, 3))  # posedirs used, zero at rest
    torch.testing.assert_close(out.vertices[0], model.v_template)


def test_npz_round_trip(tmp_path):
    arrays = _fake_official_arrays(np.random.default_rng(1))
    arrays = {k: v for k, v in arrays.items() if isinstance(v, np.ndarray)}
    path = tmp_path / "SMPL_NEUTRAL.npz"
    np.savez(path, **arrays)
    model = load_body_model(path)
    np.testing.assert_array_equal(model.J_regressor.numpy(), arrays["J_regressor"].astype(np.float32))
    assert model.parents.tolist() == list(SMPL_PARENTS)


def test_malicious_pickle_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            import os

            return (os.system, (f"touch {marker}",))

    path = tmp_path / "SMPL_NEUTRAL.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"v_template": np.zeros((3, 3)), "f": Payload()}, fh, protocol=2)
    with pytest.raises(BodyModelError, match=r"refusing to load '(posix|os|nt)\.system'"):
        load_body_model(path)
    with pytest.raises(UnsafePickleError):
        load_restricted_pickle(path)
    assert not marker.exists()


@pytest.mark.parametrize("payload", [
    b"cbuiltins\neval\n(S'1+1'\ntR.",  # protocol 0 global + reduce
    b"\x80\x02cbuiltins\ngetattr\nq\x00.",
])
def test_other_globals_refused(tmp_path, payload):
    path = tmp_path / "x.pkl"
    path.write_bytes(payload)
    with pytest.raises(UnsafePickleError, match="builtins"):
        load_restricted_pickle(path)


def test_missing_and_malformed_files_explain(tmp_path):
    with pytest.raises(BodyModelError, match="smpl.is.tue.mpg.de"):
        load_body_model(tmp_path / "SMPL_NEUTRAL.pkl")
    bad = tmp_path / "SMPL_MALE.pkl"
    bad.write_bytes(b"\x80\x02}q\x00(X\x01")  # truncated
    with pytest.raises(BodyModelError, match="smpl.is.tue.mpg.de"):
        load_body_model(bad)
    wrong = tmp_path / "model.pkl"
    with open(wrong, "wb") as fh:
        pickle.dump({"v_template": np.zeros((5, 3))}, fh, protocol=2)
    with pytest.raises(BodyModelError, match="missing key 'shapedirs'"):
        load_body_model(wrong)


def test_joblib_pickle_of_arrays(tmp_path):
    joblib = pytest.importorskip("joblib")
    import collections

    data = {"pose": np.random.rand(5, 72).astype(np.float32), "fortran": np.asfortranarray(np.random.rand(3, 4)),
            "tid": [np.array([1, 2]), 3], "name": "x", "conf": np.float64(0.5),
            "per_frame": collections.defaultdict(list, {"f1": [np.zeros(3)]})}
    for compress in (0, 3):
        path = tmp_path / f"phalp_{compress}.pkl"
        joblib.dump(data, path, compress=compress)
        out = load_restricted_pickle(path)
        np.testing.assert_array_equal(out["pose"], data["pose"])
        np.testing.assert_array_equal(out["fortran"], data["fortran"])
        np.testing.assert_array_equal(out["tid"][0], data["tid"][0])
        assert out["name"] == "x" and out["conf"] == 0.5
        np.testing.assert_array_equal(out["per_frame"]["f1"][0], np.zeros(3))


# --------------------------------------------------------------------------- open model
@pytest.mark.parametrize("name,n", [("open-low", 1229), ("open-full", 13718)])
def test_open_models_load(name, n):
    m = load_body_model(name)
    assert m.num_vertices == n and m.num_betas == 16 and m.posedirs is None
    assert m.v_template.dtype == torch.float32 and m.parents.tolist() == list(SMPL_PARENTS)
    torch.testing.assert_close(m.J_regressor.sum(1), torch.ones(24), atol=1e-4, rtol=0)
    torch.testing.assert_close(m.weights.sum(1), torch.ones(n), atol=1e-4, rtol=0)
    assert "Anny" in m.source


def test_heights_in_range(low, full):
    betas = torch.zeros(3, 16)
    betas[1, 0], betas[2, 0] = -2.0, 2.0
    for m in (low, full):
        h = standing_height(m, betas)
        assert ((h > 1.4) & (h < 2.1)).all(), h
        assert h[1] < h[0] < h[2]  # beta 0 is oriented to grow the body
    torch.testing.assert_close(standing_height(low, betas), standing_height(full, betas), atol=0.01, rtol=0)


def test_open_model_symmetric_and_facing(low):
    v = low.v_template
    mirrored = v * torch.tensor([-1.0, 1.0, 1.0])
    d = torch.cdist(mirrored, v).min(1).values
    assert d.mean() < 0.002 and d.max() < 0.005
    j = low.J_regressor @ v
    for i, name in enumerate(JOINT_NAMES):
        if name.startswith("left_"):
            r = JOINT_NAMES.index("right_" + name[5:])
            assert (j[i] - j[r] * torch.tensor([-1.0, 1.0, 1.0])).norm() < 0.003, name
            assert j[i, 0] > 0  # +X is the body's left
    # Y up (head above pelvis above ankles); facing +Z: toes in front of the ankles.
    assert j[15, 1] > j[0, 1] > j[7, 1]
    assert j[10, 2] > j[7, 2]


def test_low_and_full_share_betas(low, full):
    betas = torch.randn(4, 16)
    jl = forward(low, betas, torch.zeros(4, 72)).joints
    jf = forward(full, betas, torch.zeros(4, 72)).joints
    assert (jl - jf).norm(dim=-1).max() < 0.005


# --------------------------------------------------------------------------- LBS
def test_zero_pose_reproduces_template(low):
    betas = torch.randn(3, 16)
    out = forward(low, betas, torch.zeros(3, 24, 3))
    shaped = low.v_template + torch.einsum("nkb,Bb->Bnk", low.shapedirs, betas)
    torch.testing.assert_close(out.vertices, shaped, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.joints, torch.einsum("jn,bnk->bjk", low.J_regressor, shaped), atol=1e-5, rtol=0)
    trans = torch.randn(3, 3)
    moved = forward(low, betas, torch.zeros(3, 72), trans)
    torch.testing.assert_close(moved.vertices, shaped + trans[:, None], atol=1e-5, rtol=0)


def test_elbow_moves_only_forearm_and_hand(low):
    pose = torch.zeros(1, 24, 3)
    pose[0, 18] = torch.tensor([0.0, 1.2, 0.0])  # left elbow
    rest = forward(low, torch.zeros(1, 16), torch.zeros(1, 24, 3)).vertices[0]
    bent = forward(low, torch.zeros(1, 16), pose).vertices[0]
    moved = (bent - rest).norm(dim=-1)
    below = low.weights[:, [18, 20, 22]].sum(1)
    assert moved[below < 1e-6].max() < 1e-6  # nothing outside the elbow's subtree moves
    hand = low.weights[:, [20, 22]].sum(1) > 0.9
    assert hand.any() and moved[hand].min() > 0.05
    dom = vertex_dominant_joint(low)
    assert moved[dom == 19].max() < 1e-6  # the other elbow stays


def test_joints_follow_the_chain(low):
    torch.manual_seed(0)
    betas = torch.randn(5, 16)
    rest = forward(low, betas, torch.zeros(5, 72)).joints
    posed = forward(low, betas, torch.randn(5, 24, 3) * 0.5, torch.randn(5, 3)).joints
    par = torch.tensor(SMPL_PARENTS[1:])
    bone_rest = (rest[:, 1:] - rest[:, par]).norm(dim=-1)
    bone_posed = (posed[:, 1:] - posed[:, par]).norm(dim=-1)
    torch.testing.assert_close(bone_posed, bone_rest, atol=1e-5, rtol=0)


@pytest.mark.parametrize("shared_betas", [True, False])
def test_subset_equals_full_mesh(low, shared_betas):
    torch.manual_seed(1)
    B = 4
    betas = torch.randn(1 if shared_betas else B, 16)
    pose = torch.randn(B, 24, 3) * 0.4
    full_mesh = forward(low, betas, pose).vertices
    g = torch.Generator().manual_seed(0)
    from uuomocap.solver_core.mesh import sample_surface

    fid, bary = sample_surface(low.v_template, low.faces, 50, g)
    pts = forward(low, betas, pose, points=SurfacePoints(fid, bary)).vertices
    expected = (full_mesh[:, low.faces[fid]] * bary[None, :, :, None]).sum(2)
    torch.testing.assert_close(pts, expected, atol=2e-6, rtol=0)
    ids = torch.tensor([0, 17, 600, 1228])
    sub = forward(low, betas, pose, points=SurfacePoints.from_vertex_ids(ids)).vertices
    torch.testing.assert_close(sub, full_mesh[:, ids], atol=2e-6, rtol=0)


def test_pose_blend_matches_reference(tmp_path, monkeypatch):
    """With posedirs (SMPL files) the per-frame path adds posedirs . (R - I) before skinning."""
    arrays = _fake_official_arrays(np.random.default_rng(2))
    path = tmp_path / "m.npz"
    np.savez(path, **{k: v for k, v in arrays.items() if isinstance(v, np.ndarray)})
    m = load_body_model(path)
    pose = torch.randn(2, 24, 3) * 0.3
    rot = axis_angle_to_matrix(pose)
    feat = (rot[:, 1:] - torch.eye(3)).reshape(2, -1)
    with_blend = forward(m, torch.zeros(1, 10), pose).vertices
    without = forward(m, torch.zeros(1, 10), pose, pose_blend=False).vertices
    # Skinning is linear in the rest vertices: the difference is the skinned blend offsets.
    offs = torch.einsum("nkp,bp->bnk", m.posedirs, feat)
    T = torch.einsum("nj,bjkl->bnkl", m.weights, forward(m, torch.zeros(1, 10), pose).transforms[:, :, :3, :3])
    torch.testing.assert_close(with_blend - without, (T @ offs[..., None])[..., 0], atol=1e-5, rtol=0)
    pts = forward(m, torch.zeros(1, 10), pose, points=SurfacePoints.from_vertex_ids([1, 5])).vertices
    torch.testing.assert_close(pts, with_blend[:, [1, 5]], atol=1e-5, rtol=0)


def test_pose_representations_agree(low):
    torch.manual_seed(2)
    aa = torch.randn(3, 24, 3) * 0.6
    mats = axis_angle_to_matrix(aa)
    a = forward(low, torch.zeros(1, 16), aa).vertices
    b = forward(low, torch.zeros(1, 16), aa.reshape(3, 72)).vertices
    c = forward(low, torch.zeros(1, 16), mats).vertices
    d = forward(low, torch.zeros(1, 16), matrix_to_rot6d(mats)).vertices
    for other in (b, c, d):
        torch.testing.assert_close(other, a, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="pose has shape"):
        forward(low, torch.zeros(1, 16), torch.zeros(3, 23, 3))
    with pytest.raises(ValueError, match="only 16"):
        forward(low, torch.zeros(1, 17), aa)


def test_gradients_flow(low):
    betas = torch.zeros(1, 16, requires_grad=True)
    pose = torch.zeros(2, 24, 3, requires_grad=True)  # zero angle: the Taylor branch
    trans = torch.zeros(2, 3, requires_grad=True)
    out = forward(low, betas, pose, trans, points=SurfacePoints.from_vertex_ids(torch.arange(0, 1229, 7)))
    (out.vertices.square().sum() + out.joints.square().sum()).backward()
    for t in (betas, pose, trans):
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


# --------------------------------------------------------------------------- rotations
def test_rotation_round_trips():
    torch.manual_seed(3)
    aa = torch.randn(500, 3)
    aa = aa / aa.norm(dim=-1, keepdim=True) * torch.rand(500, 1) * 3.1
    R = axis_angle_to_matrix(aa)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand(500, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(matrix_to_axis_angle(R), aa, atol=1e-4, rtol=0)
    torch.testing.assert_close(rot6d_to_matrix(matrix_to_rot6d(R)), R, atol=1e-5, rtol=0)
    tiny = torch.tensor([[1e-9, -2e-9, 5e-10], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(matrix_to_axis_angle(axis_angle_to_matrix(tiny)), tiny, atol=1e-7, rtol=0)
    torch.testing.assert_close(quaternion_to_axis_angle(axis_angle_to_quaternion(aa)), aa, atol=1e-4, rtol=0)
    near_pi = torch.tensor([[0.0, 3.14159, 0.0]])
    assert (axis_angle_to_matrix(matrix_to_axis_angle(axis_angle_to_matrix(near_pi)))
            - axis_angle_to_matrix(near_pi)).abs().max() < 1e-4


def test_slerp():
    a = torch.tensor([[0.0, 0.0, 0.2]])
    b = torch.tensor([[0.0, 0.0, 1.0]])
    torch.testing.assert_close(slerp_axis_angle(a, b, 0.5), torch.tensor([[0.0, 0.0, 0.6]]), atol=1e-6, rtol=0)
    q = axis_angle_to_quaternion(a)
    torch.testing.assert_close(quaternion_slerp(q, q, 0.3), q, atol=1e-6, rtol=0)
    torch.testing.assert_close(quaternion_slerp(q, -q, 0.7), q, atol=1e-6, rtol=0)  # same rotation


# --------------------------------------------------------------------------- parts
def test_parts_and_subtrees(low):
    assert PART_JOINTS["left_leg"] == [1, 4, 7, 10] and PART_JOINTS["right_shoulder"] == [9, 14, 17, 19]
    subtrees3 = connected_subtrees(SMPL_PARENTS, 3)
    chains3 = kinematic_chains(SMPL_PARENTS, 3)
    assert (1, 4, 7) in subtrees3 and (0, 1, 2) in subtrees3  # a chain and a branching set
    assert all(tuple(sorted(c)) in subtrees3 for c in chains3)
    assert len(set(subtrees3)) == len(subtrees3)
    assert len(connected_subtrees(SMPL_PARENTS, 1)) == 24 and len(connected_subtrees(SMPL_PARENTS, 2)) == 23
    for part in PART_JOINTS.values():
        assert tuple(sorted(part)) in connected_subtrees(SMPL_PARENTS, len(part))
    # brute force check for k = 3: every connected 3-set
    import itertools

    edges = {(j, p) for j, p in enumerate(SMPL_PARENTS) if p >= 0}

    def connected(s):
        inner = sum(1 for j, p in edges if j in s and p in s)
        return inner == len(s) - 1

    brute = sorted(c for c in itertools.combinations(range(24), 3) if connected(c))
    assert brute == subtrees3
    dom = vertex_dominant_joint(low)
    assert dom.shape == (1229,) and set(dom.unique().tolist()) >= set(range(22))
