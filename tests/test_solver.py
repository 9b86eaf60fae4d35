"""Offline staged solver: segmentation, matching candidates, prior preparation, chamfer, and small
end-to-end solves on generated sessions (yaw hypothesis, accuracy vs. baselines, partial body)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from uuomocap.solver_core.chamfer import NearestTargetCache, nearest_indices, unidirectional_chamfer
from uuomocap.solver_core.prior_preparation import (
    BodyPrior,
    camera_to_world_rotation,
    fill_missing_prior_frames,
    prior_to_world,
    resample_prior,
)
from uuomocap.solver_core.segmentation import pairwise_distance_std, segment_markers


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rigid_clusters(frames: int = 120, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Three rigid bodies of 4 markers each, moving independently -> (T, 12, 3), labels (12,)."""
    rng = np.random.default_rng(seed)
    local = rng.normal(0.0, 0.08, (12, 3))
    out = np.zeros((frames, 12, 3))
    for t in range(frames):
        for k in range(3):
            rot = _rot_z(0.05 * t * (k + 1)) @ _rot_z(0.3 * k).T
            out[t, 4 * k : 4 * k + 4] = local[4 * k : 4 * k + 4] @ rot.T + np.array([0.5 * k, 0.01 * t, 0.02 * k * math.sin(0.1 * t)])
    out += rng.normal(0.0, 0.0003, out.shape)
    return out, np.repeat(np.arange(3), 4)


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    return all((a[i] == a[j]) == (b[i] == b[j]) for i in range(len(a)) for j in range(len(a)))


def test_segmentation_groups_rigid_clusters_despite_occlusion_gaps():
    markers, truth = _rigid_clusters()
    assert _same_partition(segment_markers(markers), truth)
    gappy = markers.copy()
    gappy[10:70, 1] = np.nan  # long gap
    gappy[::3, 6] = np.nan  # flicker
    gappy[40:119, 11] = np.nan
    labels = segment_markers(gappy)
    assert _same_partition(labels, truth)
    std, covisible = pairwise_distance_std(gappy)
    assert covisible[1, 0] == 120 - 60
    assert std[0, 1] < 0.005 < std[0, 4]


def test_segmentation_rejects_bad_shape():
    with pytest.raises(ValueError, match="markers must be"):
        segment_markers(np.zeros((10, 3)))


def test_chunked_chamfer_matches_brute_force():
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(5, 7, 3, generator=gen)
    targets = torch.randn(5, 300, 3, generator=gen, requires_grad=True)
    visible = torch.rand(5, 7, generator=gen) > 0.2
    idx = nearest_indices(points, targets, max_elements=500)  # forces many chunks
    brute = ((points[:, :, None] - targets[:, None].detach()) ** 2).sum(-1)
    assert torch.equal(idx, brute.argmin(-1))
    value = unidirectional_chamfer(points, targets, visible, max_elements=500)
    expected = (brute.min(-1).values * visible).sum() / visible.sum()
    assert torch.allclose(value, expected, atol=1e-6)
    value.backward()
    assert targets.grad is not None and targets.grad.abs().sum() > 0


def test_nearest_target_cache_matches_a_full_search_while_targets_move():
    """The shortlist answers exactly what a full search answers, small steps and large jumps alike,
    and searches in full only the frames whose targets moved too far."""
    gen = torch.Generator().manual_seed(1)
    points = torch.randn(6, 9, 3, generator=gen)
    points[2, 3] = float("nan")  # a missing marker: index as the full search gives it
    targets = torch.randn(6, 400, 3, generator=gen)
    cache = NearestTargetCache(shortlist=8, max_elements=900)
    full_searches = []
    for step in range(40):
        # mostly small drifts (an optimiser's evaluations), every 10th a large jump of one frame
        targets = targets + 0.002 * torch.randn(targets.shape, generator=gen)
        if step % 10 == 9:
            targets[step % 6] += 0.5 * torch.randn(400, 3, generator=gen)
        assert torch.equal(cache.nearest(points, targets), nearest_indices(points, targets))
        full_searches.append(cache.full_searches)
    assert full_searches[0] == 6  # the first call builds every frame
    assert cache.full_searches < 6 * 40 // 4  # most calls answered from the shortlists
    assert full_searches[9] > full_searches[8]  # the jump was noticed
    moved = points.clone()
    moved[0, 0] += 1.0  # new points: every shortlist is rebuilt
    before = cache.full_searches
    assert torch.equal(cache.nearest(moved, targets), nearest_indices(moved, targets))
    assert cache.full_searches == before + 6


def test_prior_fill_world_axes_and_resampling():
    frames = 10
    root = np.zeros((frames, 3))
    root[:, 0] = np.linspace(0.0, 0.9, frames)  # rotation about camera x
    body = np.zeros((frames, 23, 3))
    body[:, 0, 2] = np.linspace(0.0, 0.9, frames)
    valid = np.ones(frames, bool)
    valid[[0, 4, 5, 9]] = False
    prior = BodyPrior(root, body, np.tile(np.arange(3.0), (frames, 1)), valid, np.ones(frames),
                      (np.arange(frames) * 1e8).astype(np.int64), "camera")
    filled = fill_missing_prior_frames(prior)
    assert np.allclose(filled.root_orient[0], root[1])  # nearest at the start
    assert np.allclose(filled.root_orient[9], root[8])  # nearest at the end
    assert np.allclose(filled.root_orient[4:6], root[4:6], atol=1e-6)  # slerp inside (same axis -> linear)
    assert np.allclose(filled.body_pose[4:6], body[4:6], atol=1e-6)
    # camera y (down) -> world -z for a Z-up world; camera axes stay right-handed
    r = camera_to_world_rotation("+z")
    assert np.allclose(r @ np.array([0.0, 1.0, 0.0]), [0.0, 0.0, -1.0])
    assert np.isclose(np.linalg.det(r), 1.0)
    world = prior_to_world(filled, "+z")
    assert world.frame == "world"
    # resample at twice the rate with a clock offset of +0.1 s (one source frame)
    target = (np.arange(2 * frames) * 5e7).astype(np.int64)
    res = resample_prior(filled, target, clock_offset_s=0.1)
    assert res.num_frames == 2 * frames
    assert np.allclose(res.body_pose[4], filled.body_pose[1], atol=1e-6)  # 0.2 s <- video 0.1 s
    assert np.allclose(res.body_pose[5], 0.5 * (filled.body_pose[1] + filled.body_pose[2]), atol=1e-6)


def test_part_candidates_are_connected_k_subtrees_and_pruned():
    from uuomocap.solver_core.body_model import SMPL_PARENTS
    from uuomocap.solver_core.part_matching import candidate_part_joints
    from uuomocap.solver_core.parts import PART_JOINTS, connected_subtrees

    parents = list(SMPL_PARENTS)
    four = candidate_part_joints(torch.tensor(parents), 4, overlap=0.9, max_candidates=1000)
    assert tuple(PART_JOINTS["left_leg"]) in four
    assert len(four) == len(connected_subtrees(parents, 4))  # nothing shares >= 90 % of 4 joints
    for cand in four:  # connected: every joint but one has its parent inside
        assert sum(parents[j] not in cand for j in cand) == 1
    pruned = candidate_part_joints(torch.tensor(parents), 12, overlap=0.9, max_candidates=1000)
    kept = [set(c) for c in pruned]
    assert len(pruned) < len(connected_subtrees(parents, 12))
    assert all(len(a & b) < 0.9 * 12 for i, a in enumerate(kept) for b in kept[i + 1 :])


# ----------------------------------------------------------------------------- end to end


def _make_session(tmp_path: Path, name: str, **cfg) -> Path:
    synth = pytest.importorskip("uuomocap.synth")
    out = tmp_path / name
    synth.make_session(out, synth.SampleConfig(video=False, **cfg))
    return out


def _fast_config(**over):
    """The default solver on fewer frames (the sessions here are 3 s long)."""
    from uuomocap.solver_core.staged_solver import SolverConfig

    return SolverConfig(screening_frames=30, chamfer_frames=60, **over)


def _mpjpe(joints: np.ndarray, gt: dict) -> float:
    from uuomocap.solver_core.metrics import mpjpe

    return mpjpe(joints, np.asarray(gt["joints"]))


@pytest.fixture(scope="module")
def full_session(tmp_path_factory) -> Path:
    return _make_session(tmp_path_factory.mktemp("solver"), "walk", motion="walk", duration_s=3.0, rate_hz=30.0,
                         n_markers=30, seed=3, yaw_offset_deg=180.0)


def test_labeled_reference_takes_its_shape_from_the_markers(full_session):
    """The labelled reference (oracle-labeled) is the floor for the unlabelled solver: with the true
    points it must read the shape off the markers, not keep the video's (shrunk, noisy) shape."""
    torch.set_num_threads(1)
    from uuomocap.solver_core.baselines import labeled_inverse_kinematics
    from uuomocap.solver_core.body_params import MarkerAttachment
    from uuomocap.solver_methods import inputs_from_session, load_models

    inp = inputs_from_session(full_session, load_gt=True)
    model, _ = load_models(inp.body_model)
    nb = model.num_betas
    true_betas = np.asarray(inp.gt["betas"])[:nb]
    prior_err = np.linalg.norm(np.asarray(inp.shape_prior)[:nb] - true_betas)
    assert prior_err > 0.5, prior_err  # the simulated video prior's shape is off
    att = MarkerAttachment(torch.as_tensor(inp.gt["marker_faces"]), torch.as_tensor(inp.gt["marker_bary"]).float(),
                           torch.zeros(inp.markers.shape[1]))
    res = labeled_inverse_kinematics(inp.markers, inp.visible, inp.up_axis, inp.prior, inp.shape_prior, att, model,
                                     rate_hz=inp.rate_hz)
    err = np.linalg.norm(res.params.betas.numpy() - true_betas)
    assert err < 0.6 * prior_err, (err, prior_err)


def test_full_body_solve_picks_yaw_and_beats_the_prior(full_session):
    torch.set_num_threads(1)
    from uuomocap.solver_core.baselines import labeled_inverse_kinematics, video_rigid_registration
    from uuomocap.solver_core.body_params import MarkerAttachment, pose_params, up_tensor
    from uuomocap.solver_core.staged_solver import solve
    from uuomocap.solver_methods import inputs_from_session, load_models

    inp = inputs_from_session(full_session, load_gt=True)
    model, chamfer_model = load_models(inp.body_model)
    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                _fast_config())
    d = res.diagnostics
    assert d["full_body"] is True
    # the prior's heading is 180 deg off the world; the solver's yaw undoes it
    assert abs(((d["chosen_yaw_deg"] - 180.0) + 180.0) % 360.0 - 180.0) < 20.0
    assert set(d["stage_seconds"]) >= {"segmentation", "matching", "stage1", "stage2", "stage3", "stage4", "stage5"}
    ours = _mpjpe(res.joints, inp.gt)

    up = up_tensor(inp.up_axis)
    rr = video_rigid_registration(inp.markers, inp.visible, inp.up_axis, inp.prior, inp.shape_prior, chamfer_model)
    with torch.no_grad():
        rr_joints = pose_params(model, rr.params, up).joints.double().numpy()
    att = MarkerAttachment(torch.as_tensor(inp.gt["marker_faces"]), torch.as_tensor(inp.gt["marker_bary"]).float(),
                           torch.zeros(inp.markers.shape[1]))
    oracle = labeled_inverse_kinematics(inp.markers, inp.visible, inp.up_axis, inp.prior, inp.shape_prior, att, model,
                                        config=_fast_config().ik, rate_hz=inp.rate_hz)
    with torch.no_grad():
        oracle_joints = pose_params(model, oracle.params, up).joints.double().numpy()
    prior_err, oracle_err = _mpjpe(rr_joints, inp.gt), _mpjpe(oracle_joints, inp.gt)
    assert ours < 0.5 * prior_err, (ours, prior_err)
    # a 3 s take averages the attachment over little motion: ~2x the labelled reference
    assert ours < 2.5 * oracle_err, (ours, oracle_err)
    # every marker is labelled with a body part, face and barycentric coordinates
    assert all(res.marker_parts)
    assert (res.attachment.face_ids >= 0).all()
    assert torch.allclose(res.attachment.bary.sum(1), torch.ones(inp.markers.shape[1]), atol=1e-4)


@pytest.mark.parametrize("part", ["left_leg", "right_arm"])
def test_partial_body_part_is_found(tmp_path, part):
    # right_arm on a walk is the hard case: the swinging arm is one rigid cluster that a torso or
    # thigh surface fits as well; the turn signature, the floor and candidate-level MHT decide it
    torch.set_num_threads(1)
    from uuomocap.solver_core.parts import PART_JOINTS
    from uuomocap.solver_core.staged_solver import solve
    from uuomocap.solver_methods import inputs_from_session, load_models

    session = _make_session(tmp_path, part, motion="walk", duration_s=3.0, rate_hz=30.0, n_markers=12, part=part,
                            seed=1)
    inp = inputs_from_session(session, load_gt=True)
    model, chamfer_model = load_models(inp.body_model)
    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                _fast_config(stop_after="stage4"))
    d = res.diagnostics
    assert d["full_body"] is False
    names = {model.joint_names[j] for j in PART_JOINTS[part]}
    parents = {model.joint_names[int(model.parents[j])] for j in PART_JOINTS[part]}
    assert names & set(d["part_joints"]), d["part_joints"]
    labelled = [p for p in res.marker_parts if p]
    assert sum(p in names | parents for p in labelled) >= 0.75 * len(labelled), res.marker_parts


def test_the_marker_centroid_follows_a_walk_through_fragmented_columns():
    # an unlabelled export starts a new column each time a marker comes back: each column is one
    # seen stretch, and the centroid must still carry the walk (it was 1.9 m off: session 45)
    from uuomocap.solver_core.part_matching import marker_centroid

    rng = np.random.default_rng(0)
    T, M = 240, 12
    walk = np.stack([np.linspace(0, 9.6, T), 0.05 * np.sin(np.arange(T) / 5), np.full(T, 0.9)], 1)  # 1.2 m/s for 8 s
    offsets = rng.normal(0, 0.25, (M, 3))
    markers = walk[:, None] + offsets[None] + rng.normal(0, 0.0005, (T, M, 3))
    columns, vis_cols = [], []
    for m in range(M):  # each marker in three stretches, hidden 10 frames between them
        cuts = np.sort(rng.choice(np.arange(30, T - 30), 2, replace=False))
        for a, b in ((0, cuts[0]), (cuts[0] + 10, cuts[1]), (cuts[1] + 10, T)):
            col, v = np.full((T, 3), np.nan), np.zeros(T, bool)
            col[a:b], v[a:b] = markers[a:b, m], True
            columns.append(col)
            vis_cols.append(v)
    frag = np.stack(columns, 1)
    vis = np.stack(vis_cols, 1)
    expected = walk + offsets.mean(0)
    centroid = marker_centroid(frag, vis)
    assert np.abs(centroid - expected).max() < 0.03, np.abs(centroid - expected).max()
    # markers seen throughout (gaps, no breaks): the own-mean centroid, as before
    whole_vis = np.ones((T, M), bool)
    whole_vis[100:110, 3] = False
    whole = np.where(whole_vis[..., None], markers, np.nan)
    assert np.abs(marker_centroid(whole, whole_vis) - expected).max() < 0.03


def test_a_take_in_fragmented_columns_solves(tmp_path):
    torch.set_num_threads(1)
    from uuomocap.solver_core.metrics import attachment_joint_names
    from uuomocap.solver_core.staged_solver import solve
    from uuomocap.solver_methods import inputs_from_session, load_models

    session = _make_session(tmp_path, "tb", motion="walk", duration_s=3.0, rate_hz=30.0, layout="structured", occlusion=0.02,
                            track_breaks=True, seed=2)
    inp = inputs_from_session(session, load_gt=True)
    gt = inp.gt
    source = np.asarray(gt["marker_source"])
    assert inp.markers.shape[1] > 39 and sorted(set(source.tolist())) == list(range(39))
    for c in range(inp.markers.shape[1]):  # every column is one seen stretch of one marker
        seen = np.flatnonzero(inp.visible[:, c])
        assert seen.size and seen[-1] - seen[0] + 1 == seen.size
    model, chamfer_model = load_models(inp.body_model)
    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                _fast_config(stop_after="stage4"))
    from uuomocap.solver_methods import _params_arrays

    joints = _params_arrays(model, res.params, inp.up_axis)[3]
    # measured (session 45, Stage 4): 21.4 mm, parts right for 71 % of the 87 columns; the same take in
    # 39 whole columns 20.7 mm and 92 % (a column seen for a second says less about its point than a whole
    # take); before the centroid handled fragments: 506 mm
    assert _mpjpe(joints, gt) < 40.0, _mpjpe(joints, gt)
    truth = attachment_joint_names(model, np.asarray(gt["marker_faces"]), np.asarray(gt["marker_bary"]))
    assert np.mean([a == b for a, b in zip(res.marker_parts, truth)]) > 0.6


def test_the_columns_of_one_marker_are_joined_and_solved_again(tmp_path):
    torch.set_num_threads(1)
    from uuomocap.solver_core.metrics import attachment_joint_names
    from uuomocap.solver_core.staged_solver import solve
    from uuomocap.solver_methods import _params_arrays, inputs_from_session, load_models

    session = _make_session(tmp_path, "tb", motion="walk", duration_s=3.0, rate_hz=30.0, layout="structured", occlusion=0.02,
                            track_breaks=True, seed=0)
    inp = inputs_from_session(session, load_gt=True)
    gt = inp.gt
    source = np.asarray(gt["marker_source"])
    model, chamfer_model = load_models(inp.body_model)
    truth = attachment_joint_names(model, np.asarray(gt["marker_faces"]), np.asarray(gt["marker_bary"]))
    M = inp.markers.shape[1]

    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model, _fast_config())
    err = _mpjpe(_params_arrays(model, res.params, inp.up_axis)[3], gt)
    parts = np.mean([a == b for a, b in zip(res.marker_parts, truth)])
    ts = res.diagnostics["track_stitching"]
    assert ts["kept"] and ts["columns"] == M and ts["links"] == M - ts["markers"] and ts["markers"] < M
    chains = ts["chains"]
    assert sorted(c for chain in chains for c in chain) == list(range(M))
    # measured: 39 chains, one of them two markers' columns (5 and 6)
    assert sum(len(set(source[chain].tolist())) == 1 for chain in chains) >= len(chains) - 2
    faces, bary = res.attachment.face_ids.numpy(), res.attachment.bary.numpy()
    for chain in chains:  # a joined chain's columns carry its marker's one point
        assert (faces[chain] == faces[chain[0]]).all() and np.allclose(bary[chain], bary[chain[0]])
    assert len(res.marker_parts) == M and len(res.diagnostics["cluster_labels"]) == M
    assert res.diagnostics["stage5_marker_fit_mm"] <= 1.1 * ts["first_pass_marker_fit_mm"]
    # measured (session 46): 98 columns -> 39 chains (the take has 39 markers), MPJPE 10.0 mm, parts right
    # for 93 % of the columns; the first pass 3.4 mm marker fit against 3.0 joined
    assert err < 15.0, err
    assert parts > 0.85, parts


def test_a_warm_joined_pass_starts_from_the_first_body(tmp_path):
    """The near-online bootstrap's track stitching (``track_stitching_warm_below_mm``): the joined
    columns go through Stages 3-5 only, from the first pass's body."""
    torch.set_num_threads(1)
    from uuomocap.solver_core.staged_solver import SolverProgress, solve
    from uuomocap.solver_methods import _params_arrays, inputs_from_session, load_models

    session = _make_session(tmp_path, "tb", motion="walk", duration_s=3.0, rate_hz=30.0, layout="structured", occlusion=0.02,
                            track_breaks=True, seed=0)
    inp = inputs_from_session(session, load_gt=True)
    model, chamfer_model = load_models(inp.body_model)

    class StageLog(SolverProgress):
        def __init__(self):
            self.stages: list[str] = []

        def stage_start(self, name, detail=""):
            self.stages.append(name)

    progress = StageLog()
    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                _fast_config(track_stitching_warm_below_mm=10.0), progress)
    ts, diag = res.diagnostics["track_stitching"], res.diagnostics
    assert ts["kept"] and diag["warm_start"] is True and ts["first_pass_marker_fit_mm"] <= 10.0
    # the second pass ran no part matching, no hypotheses and no chamfer fit
    second = progress.stages[progress.stages.index("track_stitching") + 1:]
    assert second == ["segmentation", "stage3", "stage4", "stage5"], second
    assert diag["stage5_marker_fit_mm"] <= 1.1 * ts["first_pass_marker_fit_mm"]
    # measured (session 48): 98 columns -> 39 markers, MPJPE 8.9 mm (from scratch, the test above: 10.0),
    # marker fit 3.4 -> 2.8 mm
    assert _mpjpe(_params_arrays(model, res.params, inp.up_axis)[3], inp.gt) < 15.0


def test_a_joined_pass_that_fits_worse_than_the_first_is_dropped(monkeypatch):
    """``solve``'s orchestration around its two passes (the passes themselves: the test above)."""
    from uuomocap.solver_core import staged_solver
    from uuomocap.solver_core.body_params import MarkerAttachment
    from uuomocap.solver_core.staged_solver import SolveResult, SolverConfig

    def result(columns: int, fit_mm: float) -> SolveResult:
        att = MarkerAttachment(torch.arange(columns), torch.full((columns, 3), 1 / 3), torch.zeros(columns))
        return SolveResult(params=None, poses=np.zeros((4, 72)), joints=np.zeros((4, 24, 3)), attachment=att,
                           marker_parts=[f"part{c}" for c in range(columns)],
                           diagnostics={"stage5_marker_fit_mm": fit_mm, "cluster_labels": list(range(columns)),
                                        "stage_seconds": {"stage5": 1.0}, "total_seconds": 1.0})

    markers = np.zeros((4, 5, 3))
    passes, starts = [], []
    first_fit = 5.0

    def one_pass(mk, vis, *args, start=None, **kwargs):
        passes.append(mk.shape[1])
        starts.append(start)
        return result(mk.shape[1], first_fit if len(passes) == 1 else joined_fit)

    monkeypatch.setattr(staged_solver, "solve_columns", one_pass)
    monkeypatch.setattr(staged_solver, "marker_chains", lambda *a, **k: [[0, 3], [1], [2, 4]])
    warm = SolverConfig(track_stitching_warm_below_mm=10.0)  # the near-online bootstrap's
    for joined_fit, kept in ((5.4, True), (5.6, False)):  # the ratio is 1.1
        passes.clear(), starts.clear()
        res = staged_solver.solve(markers, None, 30.0, "+z", None, None, None, None, warm)
        assert passes == [5, 3]
        assert starts[0] is None and starts[1] is not None and starts[1].attachment.face_ids.numel() == 5  # warm: from the first
        ts = res.diagnostics["track_stitching"]
        assert ts["kept"] is kept and ts["columns"] == 5 and ts["markers"] == 3
        if kept:  # each column has its chain's marker result
            assert res.attachment.face_ids.tolist() == [0, 1, 2, 0, 2] and res.marker_parts[3] == "part0"
            assert res.diagnostics["cluster_labels"] == [0, 1, 2, 0, 2] and ts["chains"] == [[0, 3], [1], [2, 4]]
            assert res.diagnostics["stage_seconds"]["stage5"] == 2.0  # both passes
        else:  # the first pass, its columns apart
            assert res.attachment.face_ids.tolist() == [0, 1, 2, 3, 4] and ts["joined_marker_fit_mm"] == 5.6
    # the offline default, or a first body that fits its markers worse than track_stitching_warm_below_mm:
    # the joined pass starts over
    for first_fit, config in ((5.0, SolverConfig()), (12.0, warm)):
        joined_fit = 5.0
        passes.clear(), starts.clear()
        res = staged_solver.solve(markers, None, 30.0, "+z", None, None, None, None, config)
        assert passes == [5, 3] and starts == [None, None] and res.diagnostics["track_stitching"]["kept"]
    first_fit = 5.0
    # no link: one pass
    monkeypatch.setattr(staged_solver, "marker_chains", lambda *a, **k: [[c] for c in range(5)])
    passes.clear()
    res = staged_solver.solve(markers, None, 30.0, "+z", None, None, None, None, SolverConfig())
    assert passes == [5] and "track_stitching" not in res.diagnostics


def test_whole_columns_are_solved_once(full_session):
    from uuomocap.solver_core.staged_solver import marker_chains, solve_columns
    from uuomocap.solver_methods import inputs_from_session, load_models

    torch.set_num_threads(1)
    inp = inputs_from_session(full_session)
    model, chamfer_model = load_models(inp.body_model)
    res = solve_columns(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                        _fast_config(stop_after="stage4"))
    chains = marker_chains(model, res, inp.markers, inp.visible, inp.rate_hz)
    assert chains == [[c] for c in range(inp.markers.shape[1])]


def test_solve_cli_writes_out_npz(full_session, tmp_path):
    from uuomocap.cli import main
    from uuomocap.protocol.session import read_npz

    out = tmp_path / "rr.npz"
    assert main(["solve", str(full_session), "--method", "video-rr", "--out", str(out), "--quiet"]) == 0
    arrays = read_npz(out)
    frames = np.asarray(arrays["poses"]).shape[0]
    assert np.asarray(arrays["joints"]).shape == (frames, 24, 3)
    for key in ("betas", "trans", "mocap_framerate", "stamps_ns", "marker_parts", "marker_faces", "marker_bary", "method"):
        assert key in arrays
    assert main(["solve", "--markers", str(full_session / "markers.c3d"), "--out", str(out), "--quiet"]) == 2  # no prior
    # the windowed solver replays a session as recorded: loose files and overrides are refused up front
    for extra in (["--markers", str(full_session / "markers.c3d")], [str(full_session), "--clock-offset", "0.1"]):
        assert main(["solve", *extra, "--method", "uuo-window", "--out", str(out), "--quiet"]) == 2


def test_solve_cli_runs_on_the_threads_it_is_given_and_restores_them(full_session, tmp_path, monkeypatch, capsys):
    """An offline solve has the machine to itself (every core unless the user set
    OMP_NUM_THREADS or --threads); in-process callers get their own thread count back."""
    import json
    import os

    import torch
    import uuomocap
    import uuomocap.methods
    from uuomocap.cli import main
    from uuomocap.commands import UserError, solo_thread_count

    seen = []
    real = uuomocap.methods.get_method

    def probing(name):
        method = real(name)

        def run(*args, **kwargs):
            seen.append(torch.get_num_threads())
            return method(*args, **kwargs)

        return run

    monkeypatch.setattr(uuomocap.methods, "get_method", probing)
    before = torch.get_num_threads()
    out = tmp_path / "rr.npz"
    assert main(["solve", str(full_session), "--method", "video-rr", "--out", str(out), "--threads", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["threads"] == 2
    assert seen == [2] and torch.get_num_threads() == before
    # the suite sets OMP_NUM_THREADS=1 (conftest): the user's choice wins over "every core"
    monkeypatch.setattr(uuomocap, "THREADS_FROM_ENVIRONMENT", True)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert solo_thread_count(None) == 1
    monkeypatch.setattr(uuomocap, "THREADS_FROM_ENVIRONMENT", False)
    assert solo_thread_count(None) == len(os.sched_getaffinity(0))
    with pytest.raises(UserError, match="--threads"):
        solo_thread_count(0)


def test_cluster_consistency_moves_a_marker_that_left_its_rigid_group():
    """Markers of one rigid cluster on the left arm, one of them labelled on the torso: only that
    one is flagged, and it may move to the arm's joints (and their tree neighbours) only."""
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.cluster_consistency import cluster_joint_owners, inconsistent_markers, tree_distances

    model = load_body_model("open-low")
    names = model.joint_names
    parents = model.parents.numpy()
    j = {n: names.index(n) for n in names}
    dist = tree_distances(parents)
    assert dist[j["left_wrist"], j["left_elbow"]] == 1 and dist[j["left_shoulder"], j["spine2"]] == 3
    assert (dist == dist.T).all() and (np.diag(dist) == 0).all()
    arm = [j["left_shoulder"], j["left_elbow"], j["left_elbow"], j["left_wrist"], j["spine2"]]
    torso = [j["spine2"], j["spine2"], j["spine3"], j["spine1"], j["left_collar"]]
    clusters = np.array([0] * 5 + [1] * 5)
    joints = np.array(arm + torso)
    owners = cluster_joint_owners(clusters, joints, len(names))
    assert owners[j["spine2"]] == 1 and owners[j["left_elbow"]] == 0
    bad = inconsistent_markers(clusters, joints, parents)
    assert list(bad) == [4]  # the arm cluster's torso marker; the torso's collar marker is one step away
    allowed = {names[k] for k in bad[4]}
    assert {"left_shoulder", "left_elbow", "left_wrist", "left_collar", "left_hand"} == allowed
    # a singleton says nothing about its marker
    assert inconsistent_markers(np.array([0, 0, 1]), np.array([j["left_elbow"], j["left_wrist"], j["head"]]), parents) == {}


def _solve_with_patched_stage5_ik(full_session, monkeypatch, patched_ik):
    """A real solve of the module's session with Stage 5's IK replaced by ``patched_ik(real, *args, **kwargs)``."""
    torch.set_num_threads(1)
    import uuomocap.solver_core.staged_solver as staged
    from uuomocap.solver_methods import inputs_from_session, load_models

    real = staged.solve_inverse_kinematics_with_slack
    monkeypatch.setattr(staged, "solve_inverse_kinematics_with_slack", lambda *a, **k: patched_ik(real, *a, **k))
    inp = inputs_from_session(full_session, load_gt=True)
    model, chamfer_model = load_models(inp.body_model)
    return staged.solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model,
                        chamfer_model, _fast_config())


def test_a_refinement_round_that_fits_worse_is_not_kept(full_session, monkeypatch):
    """Stage 5 keeps its start when its round explains the markers worse (a failed round must not
    replace a good Stage-4 result)."""
    from dataclasses import replace

    def drifting(real, *args, **kwargs):  # the real IK, then the body moved 10 cm: a failed round
        out, rep, disp = real(*args, **kwargs)
        return replace(out, trans=out.trans + torch.tensor([0.1, 0.0, 0.0])), rep, disp

    res = _solve_with_patched_stage5_ik(full_session, monkeypatch, drifting)
    d = res.diagnostics
    assert d["stage5_rounds_reverted"] == 1
    assert res.stage_results["stage5"] is res.stage_results["stage4"]
    assert d["stage5_marker_fit_mm"] == pytest.approx(d["stage4_marker_fit_mm"])
    assert "stage5" not in d["stage_losses"]  # no round kept: no Stage-5 loss reported
    assert d["stage4_marker_fit_mm"] < 50.0  # the kept result still fits (the 10 cm shift would not)


def test_a_failed_round_still_refines_on_its_start_points(full_session, monkeypatch):
    """When a round's new points fit worse, Stage 5's IK on the start's points is kept if it fits
    (it removes Stage 4's robust-kernel jitter)."""
    from dataclasses import replace

    calls = []

    def round_fails_once(real, *args, **kwargs):
        # calls 1-2: the placement choice's two fits; 3: the round's IK (moved 10 cm: a failed
        # round); 4: the IK on the start's points (real)
        calls.append(1)
        out, rep, disp = real(*args, **kwargs)
        if len(calls) == 3:
            out = replace(out, trans=out.trans + torch.tensor([0.1, 0.0, 0.0]))
        return out, rep, disp

    res = _solve_with_patched_stage5_ik(full_session, monkeypatch, round_fails_once)
    d = res.diagnostics
    assert len(calls) == 4
    assert d["stage5_rounds_reverted"] == 1 and d["stage5_rounds_kept_points"] == 1
    assert res.stage_results["stage5"] is not res.stage_results["stage4"]
    assert d["stage5_marker_fit_mm"] <= d["stage4_marker_fit_mm"]


def test_screening_budget_caps_only_the_hypotheses(full_session):
    """The screening configs cap the L-BFGS runs of the Stage-1 hypotheses; the winner's Stage 2
    keeps its own budget (the windowed bootstrap screens cheaply and spends on the winner)."""
    torch.set_num_threads(1)
    from dataclasses import replace

    from uuomocap.solver_core.staged_solver import SolverProgress, solve
    from uuomocap.solver_methods import inputs_from_session, load_models

    class MostIterations(SolverProgress):
        def __init__(self):
            self.most: dict[str, int] = {}

        def stage_step(self, name, iterations, loss):
            self.most[name] = max(self.most.get(name, 0), iterations)

    inp = inputs_from_session(full_session, load_gt=True)
    model, chamfer_model = load_models(inp.body_model)
    seen = MostIterations()
    base = _fast_config()
    cfg = replace(base, stop_after="stage2",
                  screening_pose_fitting=replace(base.pose_fitting, lbfgs=replace(base.pose_fitting.lbfgs, max_iterations=10)),
                  screening_ik=replace(base.ik, lbfgs=replace(base.ik.lbfgs, max_iterations=10)))
    res = solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model, cfg,
                progress=seen)
    assert seen.most["stage1"] == 10  # L-BFGS runs in steps of 10 iterations: one step per fit
    assert seen.most["stage2"] > 10
    assert res.diagnostics["full_body"] is True


def test_cluster_consistency_leaves_columns_seen_over_a_short_part_of_the_take_out():
    from uuomocap.solver_core.cluster_consistency import inconsistent_markers, seen_span_fraction

    vis = np.ones((100, 7), bool)
    vis[:, 2] = False
    vis[10:30, 2] = True       # a column of one stretch (an export's fragment)
    vis[1::3, 3] = False       # gaps, but seen from start to end
    np.testing.assert_allclose(seen_span_fraction(vis), [1.0, 1.0, 0.2, 1.0, 1.0, 1.0, 1.0])
    parents = np.array([-1, 0, 1, 2, 3])  # a chain of five joints
    # cluster 0 on joint 0, two of its markers far along the chain on joint 4, which cluster 1 owns
    labels = np.array([0, 0, 0, 0, 1, 1, 1])
    joints = np.array([0, 0, 4, 4, 4, 4, 4])
    assert set(inconsistent_markers(labels, joints, parents)) == {2, 3}
    assert set(inconsistent_markers(labels, joints, parents, judged=seen_span_fraction(vis) >= 0.5)) == {3}


def test_cluster_consistency_moves_a_marker_only_to_a_point_near_it():
    """A rigid cluster on the left upper arm holds a marker on the right thigh (bones that did not
    move apart in the take) and an arm marker Stage 3 put on the chest: the arm marker goes back to
    the arm, the thigh marker keeps its point (the arm is 0.55 m from it)."""
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.body_params import BodyParams, MarkerAttachment, up_tensor
    from uuomocap.solver_core.chamfer import vertex_face_table
    from uuomocap.solver_core.inverse_kinematics import predicted_markers
    from uuomocap.solver_core.parts import vertex_dominant_joint
    from uuomocap.solver_core.staged_solver import SolverConfig, enforce_cluster_consistency, marker_part_names
    from uuomocap.solver_core.windowed_solver import fast_bootstrap_config

    model = load_body_model("open-low")
    up = up_tensor("+z")
    T = 3
    params = BodyParams(torch.zeros(T, 3), torch.zeros(T, 23, 3), torch.zeros(T, 3), torch.zeros(model.num_betas), torch.tensor(0.0))
    owner = vertex_dominant_joint(model)[model.faces].numpy()  # (F, 3) the corners' joints
    names = model.joint_names

    def faces_on(joint: str, count: int) -> list[int]:
        whole = np.flatnonzero((owner == names.index(joint)).all(axis=1))
        return whole[np.linspace(0, len(whole) - 1, count).round().astype(int)].tolist()

    # cluster 0: four upper-arm markers and the thigh's; cluster 1: two chest and two thigh markers
    arm, chest, thigh = faces_on("left_shoulder", 4), faces_on("spine3", 3), faces_on("right_hip", 3)
    true_faces = arm + [thigh[0]] + chest[:2] + thigh[1:]
    labels = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1])
    m = len(true_faces)
    truth = MarkerAttachment(torch.tensor(true_faces), torch.full((m, 3), 1 / 3), torch.zeros(m))
    markers = predicted_markers(model, params, truth, up, 0.0095, "face_normal")
    visible = torch.ones(T, m, dtype=torch.bool)
    stage3 = MarkerAttachment(truth.face_ids.clone(), truth.bary.clone(), torch.zeros(m))
    stage3.face_ids[3] = chest[2]  # the fourth arm marker on the chest
    vertex_faces = vertex_face_table(model.faces, model.v_template.shape[0])
    config = fast_bootstrap_config()  # the near-online bootstrap's: a 3 s window
    assert config.cluster_consistency.max_point_distance_m == 0.1
    att, moved = enforce_cluster_consistency(model, markers, visible, params, up, stage3, labels, None, config, vertex_faces)
    parts = marker_part_names(model, att)
    assert moved == 1 and parts[3] == "left_shoulder" and parts[4] == "right_hip" and int(att.face_ids[4]) == thigh[0]
    assert float(att.score_m[3]) < 0.01  # back on the arm, where the marker is
    # without the limit (offline) the thigh marker goes to the arm as well, far from where it is
    loose = SolverConfig()
    assert loose.cluster_consistency.max_point_distance_m is None
    att, moved = enforce_cluster_consistency(model, markers, visible, params, up, stage3, labels, None, loose, vertex_faces)
    assert moved == 2 and marker_part_names(model, att)[4] != "right_hip" and float(att.score_m[4]) > 0.1


def test_a_decisive_registration_screens_one_hypothesis():
    from uuomocap.solver_core.staged_solver import _screened_hypotheses

    tilt = np.eye(3)
    yaws = lambda distinct, limit, ratio: [y for y, _ in _screened_hypotheses(distinct, limit, ratio)]  # noqa: E731
    ambiguous = [(0.1, tilt, 100.0), (2.0, tilt, 150.0), (3.0, tilt, 160.0)]   # best registration first
    decisive = [(0.1, tilt, 100.0), (2.0, tilt, 250.0), (3.0, tilt, 400.0)]
    assert yaws(ambiguous, 2, 2.0) == [0.1, 2.0]        # the next registers 1.5x worse: a second opinion
    assert yaws(decisive, 2, 2.0) == [0.1]              # 2.5x worse: only the best
    assert yaws(decisive, 2, None) == [0.1, 2.0]
    assert yaws(decisive, None, None) == [0.1, 2.0, 3.0]
    assert yaws(ambiguous, 1, 2.0) == [0.1]
    assert _screened_hypotheses([], 2, 2.0) == []


def test_the_offline_solver_trusts_a_decisive_registration_on_full_bodies_only():
    """A partial body's few markers register its part's yaw less surely (README: with one
    hypothesis the left leg was found in 2 of 3 sessions): its hypotheses are all screened, unless
    a config asks for the test everywhere (the windowed bootstrap); the published method screens all."""
    from types import SimpleNamespace

    from uuomocap.solver_core.staged_solver import SolverConfig, _decisive_ratio
    from uuomocap.solver_methods import solver_config_for

    full, part = SimpleNamespace(full_body=True), SimpleNamespace(full_body=False)
    cfg = SolverConfig()
    assert _decisive_ratio(cfg, full) == 2.0 and _decisive_ratio(cfg, part) is None
    everywhere = SolverConfig(decisive_registration_ratio=3.0)
    assert _decisive_ratio(everywhere, full) == 3.0 and _decisive_ratio(everywhere, part) == 3.0
    assert _decisive_ratio(solver_config_for("uuo-paper"), full) is None


def test_a_known_part_is_solved_without_searching_for_one(tmp_path):
    """``PartMatchingConfig.part_joints`` (the near-online lock upgrades: their bootstrap chose the
    part): matching tests that one candidate, even the mirror leg of the one the markers are on,
    and says so; joints the model does not have are refused."""
    torch.set_num_threads(1)
    from uuomocap.solver_core.parts import PART_JOINTS
    from uuomocap.solver_core.staged_solver import SolverConfig, solve
    from uuomocap.solver_methods import inputs_from_session, load_models

    session = _make_session(tmp_path, "leg", motion="walk", duration_s=2.0, rate_hz=30.0, n_markers=12, part="left_leg", seed=0)
    inp = inputs_from_session(session)
    model, chamfer_model = load_models(inp.body_model)

    def matched(part_joints, **over):
        cfg = _fast_config(stop_after="matching", **over)
        cfg = replace(cfg, matching=replace(cfg.matching, part_joints=part_joints))
        return solve(inp.markers, inp.visible, inp.rate_hz, inp.up_axis, inp.prior, inp.shape_prior, model, chamfer_model,
                     cfg).diagnostics

    searched = matched(None)
    assert searched["full_body"] is False and searched["part_candidates_tested"] > 1
    right = tuple(PART_JOINTS["right_leg"])
    # the volume test's decision (partial) and an explicit full-body request both give way to it
    for over in ({}, {"force_full_body": True}):
        d = matched(right, **over)
        assert d["full_body"] is False and d["part_candidates_tested"] == 1
        assert sorted(d["part_joints"]) == sorted(model.joint_names[j] for j in right)
    with pytest.raises(ValueError, match="part_joints"):
        matched((0, 99))
    assert SolverConfig().matching.part_joints is None  # the offline solver searches
