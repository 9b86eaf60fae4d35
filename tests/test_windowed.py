"""The near-online sliding-window solver: bootstrap, estimate + refined for every frame, accuracy
next to the offline solver, change handling (occlusion, new tracks), bounded memory.

One small generated session (30 Hz, 4 s, 40 markers) is bootstrapped once; the change-handling
tests continue from copies of that locked solver.  The offline reference runs with the
bootstrap's budgets (same stages, fewer iterations) to keep the test fast.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch

from uuomocap.solver_core.windowed_solver import UpgradeCancelled, WindowedSolver, WindowedSolverConfig, right_jacobian_so3


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from uuomocap.synth import SampleConfig, make_session

    d = tmp_path_factory.mktemp("win") / "s"
    make_session(d, SampleConfig(motion="walk", rate_hz=30.0, duration_s=4.0, n_markers=40, seed=0, video=False))
    return d


@pytest.fixture(scope="module")
def streamed(session):
    """Feed the session through WindowedSolver like the solver node does."""
    from uuomocap.solver_core.body_model import load_solver_models as load_models
    from uuomocap.window_methods import session_stream

    torch.set_num_threads(1)
    md, rows, up_axis, body_model, gt = session_stream(session)
    model, chamfer = load_models(body_model)
    # no lock upgrade inside the stream (the 4 s take would reach the first one): tests start them
    # and no end-of-take upgrade or revision at the flush (their own tests): the rings keep the refined frames
    cfg = replace(WindowedSolverConfig(), bootstrap_s=2.0, recheck_period_s=1.0, recheck_frames=24, upgrade_growth=2.0,
                  revise_at_end=False, upgrade_at_end_growth=0.0)
    solver = WindowedSolver(model, cfg, up_axis, md.rate_hz, chamfer)
    results, pi = [], 0
    for i in range(md.positions.shape[0]):
        st = int(md.stamps_ns[i])
        while pi < len(rows) and rows[pi][0] <= st:
            solver.add_prior(*rows[pi])
            pi += 1
        results += solver.add_markers(st, md.positions[i], md.visible[i])
        if solver.locked and i + 1 == int(2.0 * md.rate_hz) + 1:
            assert any(r.kind == "estimate" for r in results)  # the bootstrap window is estimated at once
    before_flush = len([r for r in results if r.kind == "refined"])
    results += solver.flush()
    return {"solver": solver, "results": results, "md": md, "rows": rows, "gt": gt, "model": model,
            "chamfer": chamfer, "before_flush": before_flush}


def _frames(md, rows, start_frame, count, start_stamp, order):
    """Frames of the session in ``order`` (ping-pong indices), re-stamped after ``start_stamp``,
    with the prior rows of the source frames re-stamped the same way."""
    period = int(round(1e9 / md.rate_hz))
    prior_t = np.array([r[0] for r in rows])
    for k in range(count):
        j = order[(start_frame + k) % len(order)]
        st = start_stamp + (k + 1) * period
        i = min(int(np.searchsorted(prior_t, md.stamps_ns[j])), len(rows) - 1)
        yield st, j, (st, *rows[i][1:])


def _clone(streamed) -> WindowedSolver:
    memo = {id(streamed["model"]): streamed["model"], id(streamed["chamfer"]): streamed["chamfer"]}
    return copy.deepcopy(streamed["solver"], memo)


def test_right_jacobian_matches_finite_differences():
    from uuomocap.solver_core.windowed_solver import rotation_matrices

    rng = np.random.default_rng(0)
    for theta in (rng.normal(size=3), np.array([0.0, 0.0, 3.0]), np.zeros(3)):
        jr = right_jacobian_so3(theta)
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            # R(theta)^T R(theta + d) ~= exp(J_r d)
            delta = rotation_matrices(theta).T @ rotation_matrices(theta + d)
            w = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]]) / 2
            np.testing.assert_allclose(w / 1e-6, jr[:, k], atol=1e-4)


def test_every_frame_gets_an_estimate_and_a_refined_result(streamed):
    T = streamed["md"].positions.shape[0]
    res = streamed["results"]
    est = sorted(r.frame_index for r in res if r.kind == "estimate")
    ref = sorted(r.frame_index for r in res if r.kind == "refined")
    assert est == list(range(T)) and ref == list(range(T))
    assert 0 < streamed["before_flush"] < T  # refined frames flow during the stream, the rest at flush
    s = streamed["solver"]
    assert s.stats["bootstraps"] == 1 and s.stats["rechecks"] >= 1
    labels = s.labels
    assert labels is not None and (labels.face_ids >= 0).sum() >= 0.9 * len(labels.face_ids)


def test_bootstrap_locks_the_best_fitting_start(streamed):
    s = streamed["solver"]
    fits = s.stats["bootstrap_start_fits_mm"]  # Stage-5 marker fit (mm) of each bootstrap start
    assert len(fits) == 1 + len(s.config.bootstrap_alternatives) == 2 and all(f is not None for f in fits)
    assert s.stats["bootstrap_start_chosen"] == int(np.argmin(fits))
    assert s.last_bootstrap["stage5_marker_fit_mm"] == pytest.approx(min(fits), abs=1e-3)
    # the locked start made the per-marker point choice (the markers that took the prior's point)
    assert isinstance(s.last_bootstrap["prior_placement_markers"], list)
    # the second start ran in the solver's worker process (not a thread sharing the interpreter lock)
    assert s._worker is not None and "worker_failed" not in s.stats


def test_bootstrap_skips_a_failing_start_and_reports_when_all_fail(streamed):
    from uuomocap.solver_core.staged_solver import SolverConfig

    s = _clone(streamed)
    md = streamed["md"]
    sel = np.arange(0, 45, 2)  # 1.5 s at 15 Hz: a cheap window
    prior, shape, _ = s._prior_window(np.asarray(md.stamps_ns)[sel])
    broken = SolverConfig(stop_after="nowhere")  # solve() rejects it before any work: a start that fails
    s.config = replace(s.config, bootstrap_alternatives=(broken,))
    res = s._solve_bootstrap_window(md.positions[sel], md.visible[sel], md.rate_hz / 2, prior, shape)
    assert s.stats["bootstrap_start_fits_mm"][1] is None and s.stats["bootstrap_start_chosen"] == 0
    assert int(res.attachment.assigned.sum()) >= 36
    s.config = replace(s.config, bootstrap_solver=broken)
    with pytest.raises(ValueError, match="stop_after"):
        s._solve_bootstrap_window(md.positions[sel], md.visible[sel], md.rate_hz / 2, prior, shape)


def test_bootstrap_falls_back_to_this_process_when_the_worker_died(streamed):
    import multiprocessing
    import os
    import signal

    from uuomocap.solver_core.solve_worker import StagedSolveWorker

    md = streamed["md"]
    sel = np.arange(0, 45, 2)  # 1.5 s at 15 Hz: a cheap window
    ref = _clone(streamed)  # a copy has no worker: its second start runs on a thread
    assert ref._worker is None
    prior, shape, _ = ref._prior_window(np.asarray(md.stamps_ns)[sel])
    expected = ref._solve_bootstrap_window(md.positions[sel], md.visible[sel], md.rate_hz / 2, prior, shape)
    s = _clone(streamed)
    before = set(multiprocessing.active_children())
    s._worker = StagedSolveWorker(streamed["model"], streamed["chamfer"])
    assert s.wait_worker(120)
    assert s.worker_pid in {c.pid for c in set(multiprocessing.active_children()) - before}
    for child in set(multiprocessing.active_children()) - before:
        os.kill(child.pid, signal.SIGKILL)  # the worker dies (out of memory, killed by hand...)
    res = s._solve_bootstrap_window(md.positions[sel], md.visible[sel], md.rate_hz / 2, prior, shape)
    assert "worker_failed" in s.stats and s._worker is None
    assert s.stats["bootstrap_start_fits_mm"] == ref.stats["bootstrap_start_fits_mm"]
    np.testing.assert_array_equal(res.attachment.face_ids.numpy(), expected.attachment.face_ids.numpy())


def test_the_bootstrap_stage_2_tries_the_whole_quasi_newton_step_first(streamed):
    # lr is only the first step each strong-Wolfe line search tries (optimization.run_lbfgs): at the
    # paper's 0.1 the line search accepts a tenth of the quasi-Newton step and the fit stops on the
    # relative-improvement test far above the minimum the bootstrap's 1.0 reaches
    from uuomocap.solver_core.pose_fitting import PoseFittingConfig
    from uuomocap.solver_core.staged_solver import SolverConfig

    # the offline solver (and so the lock upgrades) start there too; the stage's own default stays
    # the paper's 0.1, which the published-method ablation (uuo-paper) runs
    assert SolverConfig().pose_fitting.lbfgs.lr == 1.0 and PoseFittingConfig().lbfgs.lr == 0.1
    md = streamed["md"]
    sel = np.arange(0, 60, 2)  # 2 s at 15 Hz
    losses = {}
    for lr in (0.1, 1.0):
        s = _clone(streamed)
        boot = s.config.bootstrap_solver
        if lr != 1.0:
            assert boot.pose_fitting.lbfgs.lr == boot.screening_pose_fitting.lbfgs.lr == 1.0
            boot = replace(boot, pose_fitting=replace(boot.pose_fitting, lbfgs=replace(boot.pose_fitting.lbfgs, lr=lr)),
                           screening_pose_fitting=replace(boot.screening_pose_fitting,
                                                          lbfgs=replace(boot.screening_pose_fitting.lbfgs, lr=lr)))
        s.config = replace(s.config, bootstrap_solver=boot, bootstrap_alternatives=())
        prior, shape, _ = s._prior_window(np.asarray(md.stamps_ns)[sel])
        res = s._solve_bootstrap_window(md.positions[sel], md.visible[sel], md.rate_hz / 2, prior, shape)
        losses[lr] = res.diagnostics["stage_losses"]["stage2"]
    print(f"\nStage-2 energy at initial step 0.1: {losses[0.1]:.2f}, 1.0: {losses[1.0]:.2f}")
    assert losses[1.0] < 0.9 * losses[0.1], losses


def test_refined_accuracy_close_to_offline(streamed, session):
    from uuomocap.solver_core.metrics import mpjpe, mpjve
    from uuomocap.solver_core.windowed_solver import fast_bootstrap_config
    from uuomocap.solver_methods import inputs_from_session, run_staged_solver

    gt = streamed["gt"]
    T = streamed["md"].positions.shape[0]
    rate = streamed["md"].rate_hz
    joints = {k: np.zeros((T, 24, 3)) for k in ("estimate", "refined", "revised")}
    for r in streamed["results"]:
        joints[r.kind][r.frame_index] = r.joints
    offline, _ = run_staged_solver(inputs_from_session(session), "uuo", config=fast_bootstrap_config())
    gj = np.asarray(gt["joints"])[:T]
    off, ref, est = mpjpe(offline.joints, gj), mpjpe(joints["refined"], gj), mpjpe(joints["estimate"], gj)
    # at test sizes (4 s, 40 markers, 2 s bootstrap) within a generous factor of the offline solve
    print(f"\nMPJPE refined {ref:.1f} estimate {est:.1f} offline {off:.1f} mm")
    assert ref < 1.5 * off + 10.0, (ref, est, off)
    assert est < 1.5 * off + 15.0, (ref, est, off)
    # the smoothing pass is smoother than the causal estimate
    assert mpjve(joints["refined"], gj, rate) <= mpjve(joints["estimate"], gj, rate) + 1.0


def test_the_take_end_revises_the_ring_with_the_mean_offset_prior(streamed):
    from uuomocap.solver_core.metrics import mpjpe

    s = _clone(streamed)
    s.config = replace(s.config, revise_at_end=True)
    ring = list(s._refined_ring)
    assert len(ring) == streamed["md"].positions.shape[0] and all(f.video_prior for f in ring)
    video = np.stack([f.prior for f in ring])
    theta0 = np.stack([f.theta for f in ring])
    joints0 = np.stack([f.joints for f in ring])
    residual0 = np.array([f.residual for f in ring])
    out = s.flush()
    # every frame of the ring once more, in order, as a revised result
    assert [r.frame_index for r in out] == [f.index for f in ring] and {r.kind for r in out} == {"revised"}
    assert s.stats["revisions_at_end"] == 1 and "revisions" not in s.stats
    # the mean-offset term: each joint's mean rotation difference to the video prior shrinks ...
    theta1 = np.stack([f.theta for f in ring])
    before = np.abs((theta0 - video)[:, 3:].mean(axis=0))
    after = np.abs((theta1 - video)[:, 3:].mean(axis=0))
    # 40 markers pin most joints: the shrink is small and depends on the lock (this fixture's, with Stage 5's
    # whole-body search since session 32: 1.72 -> 1.57 deg, 0.91; before it 1.76 -> 1.55, 0.88)
    assert after.mean() < 0.95 * before.mean(), (before.mean(), after.mean())
    # ... while the markers still fit (mean residual within 0.5 mm of the refined frames')
    residual1 = np.array([r.residual_m for r in out])
    assert residual1.mean() < residual0.mean() + 5e-4, (residual0.mean(), residual1.mean())
    gt = np.asarray(streamed["gt"]["joints"])[[f.index for f in ring]]
    m0, m1 = mpjpe(joints0, gt), mpjpe(np.stack([r.joints for r in out]), gt)
    print(f"\nmean offset {np.degrees(before.mean()):.2f} -> {np.degrees(after.mean()):.2f} deg, residual "
          f"{residual0.mean() * 1e3:.2f} -> {residual1.mean() * 1e3:.2f} mm, MPJPE {m0:.2f} -> {m1:.2f} mm")
    assert m1 < m0 + 0.5
    # a second flush (end of stream, then the node's stop) revises nothing more
    assert s.flush() == []
    # without video priors there is no mean offset to take: nothing is revised
    s2 = _clone(streamed)
    s2.config = replace(s2.config, revise_at_end=True)
    s2.has_prior = False
    assert s2.flush() == []


def test_the_take_end_upgrades_the_lock_on_the_whole_take_before_the_revision(streamed):
    s = _clone(streamed)
    s.config = replace(s.config, revise_at_end=True, upgrade_at_end_growth=1.1)
    ring = [f.index for f in s._refined_ring]
    fits_before = len(s.stats.get("upgrade_fit_mm", []))
    # an adoption keeps the lock generation (that counts bootstraps) and replaces the shape
    rejected, betas = s.stats.get("upgrades_rejected", 0), s.betas.clone()
    out = s.flush()
    # one upgrade on the reservoir (which now spans the take), judged like every upgrade ...
    assert s.stats["upgrades_at_end"] == 1 and s.stats["upgrade_at_end_s"] > 0
    assert len(s.stats["upgrade_fit_mm"]) == fits_before + 1
    current, candidate = s.stats["upgrade_fit_mm"][-1]
    adopted = s.stats.get("upgrades_rejected", 0) == rejected
    assert adopted == (candidate < current), (current, candidate, adopted)
    assert adopted != torch.equal(s.betas, betas)
    # ... then the ring revised once, under the lock the take ends with (no second revision queued
    # by the adoption)
    assert [r.frame_index for r in out] == ring and {r.kind for r in out} == {"revised"}
    assert s.stats["revisions_at_end"] == 1 and "revisions" not in s.stats and s._revision is None
    assert all(r.labels_version == s.labels_version for r in out)
    # a second flush starts nothing: the take has not grown since
    assert s.flush() == [] and s.stats["upgrades_at_end"] == 1
    # a live stop (end_upgrades) skips it
    s2 = _clone(streamed)
    s2.config = replace(s2.config, upgrade_at_end_growth=1.1)
    s2.end_upgrades()
    s2.flush()
    assert "upgrades_at_end" not in s2.stats and "upgrade_at_end_s" not in s2.stats
    with pytest.raises(ValueError, match="upgrade_at_end_growth"):
        WindowedSolverConfig(upgrade_at_end_growth=-1.0)


def test_the_take_end_reassigns_the_markers_on_the_whole_ring(streamed):
    """Stage 3 once more over the ring before the end-of-take revision: six markers whose locked
    points were swapped among them after the stream get their own points back; without it they
    keep the wrong ones."""
    gt = streamed["gt"]
    s = _mislocked_clone(streamed)
    s.config = replace(s.config, revise_at_end=True)
    ring = [f.index for f in s._refined_ring]
    wrong_mm, version = _attach_error_mm(s, gt, streamed["model"]), s.labels_version
    published = s.label_arrays()  # what the solver node sends with each frame: cached while the points stay
    assert s.label_arrays() is published and published[0].dtype == np.int32 and np.array_equal(published[0], s.face_ids)
    out = s.flush()
    fixed_mm = _attach_error_mm(s, gt, streamed["model"])
    assert s.stats["reassigned_at_end"] >= 6 and s.labels_version > version
    republished = s.label_arrays()  # the re-assigned points go out from the next frame on
    assert np.array_equal(republished[0], s.face_ids) and not np.array_equal(republished[0], published[0])
    assert len(republished[2]) == len(s.face_ids)
    # the ring comes out once, revised under the repaired points
    assert [r.frame_index for r in out] == ring and all(r.labels_version == s.labels_version for r in out)
    kept = _mislocked_clone(streamed)
    kept.config = replace(kept.config, revise_at_end=True, reassign_at_end=False)
    kept.flush()
    kept_mm = _attach_error_mm(kept, gt, streamed["model"])
    good_mm = _attach_error_mm(_clone(streamed), gt, streamed["model"])
    print(f"\nattachment error: stream {good_mm:.1f} mm, swapped {wrong_mm:.1f}, take end {fixed_mm:.1f} (kept {kept_mm:.1f})")
    assert kept_mm == pytest.approx(wrong_mm) and "reassigned_at_end" not in kept.stats
    assert fixed_mm < 0.5 * wrong_mm and fixed_mm < good_mm + 3.0


def test_occlusion_gap_keeps_correspondence(streamed):
    s = _clone(streamed)
    # no periodic re-check here: it may legitimately move any marker to a better-fitting point,
    # and this test is about what the occlusion gap itself does to the correspondence
    s.config = replace(s.config, recheck_period_s=0.0, upgrade_frames=0)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])  # continue backwards: continuous motion
    k = int(np.flatnonzero(s.face_ids >= 0)[0])
    face, bary = s.face_ids[k], s.bary[k].copy()
    last = int(md.stamps_ns[-1])
    residuals = {"before": [], "after": []}
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, 40, last, order)):
        s.add_prior(*prior)
        pos = md.positions[j].copy()
        vis = md.visible[j].copy()
        if 5 <= step < 25:  # a 20-frame occlusion gap
            pos[k] = np.nan
            vis[k] = False
        out = s.add_markers(st, pos, vis)
        assert out and out[0].kind == "estimate"
        if step < 5 or step >= 30:
            residuals["before" if step < 5 else "after"].append(out[0].residual_m)
    assert s.face_ids[k] == face and np.allclose(s.bary[k], bary)
    # the marker came back onto its old surface point: the fit is as good as before the gap
    assert np.mean(residuals["after"]) < 1.5 * np.mean(residuals["before"]) + 0.002, residuals


def test_a_recheck_runs_in_marker_groups_one_per_hop_between_passes(streamed):
    """A re-check is Stage 3 for every marker, a group at a time: one group per smoothing hop, in
    the ``refine_ready`` call half a hop after a pass (the estimate is out; no refined result waits
    behind it).  A point moved off its marker is put back by its group."""
    s = _clone(streamed)
    s.config = replace(s.config, upgrade_frames=0, slip_frames=10_000, recheck_group_markers=10)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    # one marker's point swapped with another marker's (a wrong point a re-check should fix)
    a, b = np.flatnonzero(s.face_ids >= 0)[[5, 30]]
    good = s.face_ids[a]
    s.face_ids[a], s.bary[a] = s.face_ids[b], s.bary[b].copy()
    s._prepare_lock()
    before = _attach_error_mm(s, streamed["gt"], streamed["model"])
    M = len(s.face_ids)
    s._since_recheck = 10**6  # due at the next frame
    s._lock_age = 10**6
    calls = []  # (frame step, markers of the group) of every group run
    real = s._recheck
    step_now = [0]

    def spy(which):
        calls.append((step_now[0], list(which)))
        real(which)

    s._recheck = spy
    pass_steps = []
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, 6 * s.config.hop_frames, int(md.stamps_ns[-1]), order)):
        step_now[0] = step
        s.add_prior(*prior)
        s.push_markers(st, md.positions[j], md.visible[j])
        groups_before = len(calls)
        if s.refine_ready():
            pass_steps.append(step)
            assert len(calls) == groups_before  # never in a call that ran a pass
    assert s.stats["rechecks"] >= 1
    first = calls[: int(np.ceil(M / 10))]
    # every marker once, interleaved groups of at most 10
    assert sorted(m for _, g in first for m in g) == list(range(M)) and all(len(g) <= 10 for _, g in first)
    # one group per hop, half a hop after its pass
    half = s.config.hop_frames // 2
    for (s0, _), (s1, _) in zip(first, first[1:]):
        assert any(s0 < p <= s1 for p in pass_steps), (s0, s1, pass_steps)
    # (before the clone's first pass, half a hop after its start)
    assert all(step - half in pass_steps or step == half - 1 < pass_steps[0] for step, _ in first), \
        ([st for st, _ in first], pass_steps)
    assert s.face_ids[a] != s.face_ids[b] and s.face_ids[a] >= 0
    after = _attach_error_mm(s, streamed["gt"], streamed["model"])
    print(f"\nswapped point: attachment error {before:.1f} -> {after:.1f} mm (marker {a}: face {s.face_ids[a]}, was {good})")
    assert after < before
    # with a pass at every frame (hop 1) the groups run after the passes
    h = _clone(streamed)
    h.config = replace(h.config, upgrade_frames=0, hop_frames=1)
    h._since_recheck, h._lock_age, h._recheck_groups = 10**6, 10**6, type(h._recheck_groups)()
    for st, j, prior in _frames(md, rows, 0, h.config.lag_frames + 6, int(md.stamps_ns[-1]), order):
        h.add_prior(*prior)
        h.add_markers(st, md.positions[j], md.visible[j])
    assert h.stats["rechecks"] == streamed["solver"].stats["rechecks"] + 1 and not h._recheck_groups


def test_new_marker_track_gets_assigned(streamed):
    s = _clone(streamed)
    # a new track that no ended marker hands over to (the handover has its own tests, below)
    s.config = replace(s.config, handover=None)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    k = int(np.flatnonzero(s.face_ids >= 0)[3])
    ids = np.arange(md.positions.shape[1])
    last = int(md.stamps_ns[-1])
    version = s.labels_version
    assigned_at = None
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, 30, last, order)):
        s.add_prior(*prior)
        if step == 2:
            ids = ids.copy()
            ids[k] = 1000  # the tracker gave slot k to a new track: a new marker
        s.add_markers(st, md.positions[j], md.visible[j], track_ids=ids)
        if step == 2:
            assert s.face_ids[k] == -1  # forgotten at once
        if step > 2 and assigned_at is None and s.face_ids[k] >= 0:
            assigned_at = step
    cfg = s.config
    assert assigned_at is not None and assigned_at - 2 >= cfg.new_track_frames - 1
    assert s.stats["new_tracks"] >= 1 and s.labels_version > version
    # the new assignment fits: the marker's residual under the estimate is small
    out = s.add_markers(last + 10**9, md.positions[order[31]], md.visible[order[31]], track_ids=ids)
    a = list(s._assigned)
    lin = s._linearize(s._history[-1].theta[None], s._history[-1].trans[None], s._history[-1].markers[None],
                       s._history[-1].visible[None], jacobian=False)
    assert lin["dist"][0][a.index(k)] < 0.03
    assert out[0].kind == "estimate"


def test_a_tracker_slot_whose_track_changes_takes_the_ended_markers_point_at_once(streamed):
    s = _clone(streamed)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    k = int(np.flatnonzero(s.face_ids >= 0)[3])
    face, bary = int(s.face_ids[k]), s.bary[k].copy()
    ids = np.arange(md.positions.shape[1])
    last = int(md.stamps_ns[-1])
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, 6, last, order)):
        s.add_prior(*prior)
        if step == 2:
            ids = ids.copy()
            ids[k] = 1000  # a new track id in slot k, on the same marker (a tracker lost and found it)
        s.add_markers(st, md.positions[j], md.visible[j], track_ids=ids)
        if step == 2:  # forgotten, then handed back within the same frame: no new_track_frames wait
            assert s.face_ids[k] == face and np.allclose(s.bary[k], bary)
            assert s.stats["handovers"] == 1
    assert s.stats["new_tracks"] == 0


def test_a_window_of_frames_leaves_each_columns_last_sighting(streamed):
    """The bootstrap's window feeds the handover: each column's last sighting in the window is
    the one a frame-by-frame stream would have left (a marker that ends inside the window and comes
    back after it takes its point back)."""
    s = _clone(streamed)
    frames = [copy.deepcopy(f) for f in list(s._history)[-3:]]
    k = int(s._assigned[3])
    frames[2].visible[k] = False  # k last seen in the window's middle frame
    s._forget_sightings(s.num_markers)
    lin = s._linearize(np.stack([f.theta for f in frames]), np.stack([f.trans for f in frames]),
                       np.stack([f.markers for f in frames]), np.stack([f.visible for f in frames]), jacobian=False)
    s._remember_sightings(frames, lin)
    window = (s._last_seen.copy(), s._last_face.copy(), s._last_local.copy())
    s._forget_sightings(s.num_markers)
    index = s._index
    for i, f in enumerate(frames):  # frame by frame, as the steady state sees them
        s._index = index - 2 + i
        one = s._linearize(f.theta[None], f.trans[None], f.markers[None], f.visible[None], jacobian=False)
        s._remember_sightings([f], one)
    assert window[0][k] == index - 2 and window[1][k] == s.face_ids[k]
    np.testing.assert_array_equal(window[0], s._last_seen)
    np.testing.assert_array_equal(window[1], s._last_face)
    np.testing.assert_allclose(window[2], s._last_local, atol=1e-9)


def _comeback(streamed, offset, steps: int = 12, adopt_at: int | None = None):
    """Marker k's column ends at step 2; from step 6 the marker (moved by ``offset``) is seen in a
    column free until then; at step ``adopt_at`` a lock upgrade with the same points is adopted.
    Returns the solver, k's point then, k and that column."""
    s = _clone(streamed)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    assigned = np.flatnonzero(s.face_ids >= 0)
    k, spare = int(assigned[3]), int(assigned[20])
    point = (int(s.face_ids[k]), s.bary[k].copy())
    s._unassign(np.array([spare]))  # a free column for the comeback, seen before by nobody we track
    s._ended = []
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, steps, int(md.stamps_ns[-1]), order)):
        s.add_prior(*prior)
        pos, vis = md.positions[j].copy(), md.visible[j].copy()
        vis[spare] = False
        if step >= 2:
            vis[k] = False  # k's column ends
        if step >= 6:  # 4 frames later the marker is back, in the spare column
            pos[spare], vis[spare] = md.positions[j, k] + offset, True
        s.add_markers(st, np.where(vis[:, None], pos, np.nan), vis)
        if step == adopt_at:
            s._adopt_lock(_result_of_lock(s))
        if step == 6:
            s.stats["spare_face_at_comeback"] = int(s.face_ids[spare])
            s.stats["spare_bary_at_comeback"] = s.bary[spare].copy()
    return s, point, k, spare


def test_a_column_that_starts_where_an_ended_marker_would_be_takes_its_point(streamed):
    """An unlabelled export: marker k's column ends, the marker comes back in another column."""
    s, (face, bary), k, spare = _comeback(streamed, np.zeros(3))
    # taken in the comeback's first frame
    assert s.stats["spare_face_at_comeback"] == face and np.allclose(s.stats["spare_bary_at_comeback"], bary)
    assert s.stats["handovers"] == 1 and s.stats["new_tracks"] == 0
    # once handed over, the ended column's marker is not handed to a second column
    assert s._last_face[k] == -1 and s._identity[spare] == s._identity[k]


def _result_of_lock(s):
    """A staged-solver result whose lock is the solver's current one."""
    from types import SimpleNamespace

    return SimpleNamespace(attachment=SimpleNamespace(face_ids=torch.as_tensor(s.face_ids.copy()), bary=torch.as_tensor(s.bary.copy())),
                           params=SimpleNamespace(betas=s.betas.clone(), yaw=torch.tensor(s.yaw)),
                           diagnostics={"camera_tilt": s.camera_tilt.copy(), "full_body": True})


def test_a_marker_that_ended_just_before_a_lock_adoption_still_hands_over(streamed):
    """The sightings outlive the adoption, re-pointed to the new lock's points."""
    s, (face, bary), k, spare = _comeback(streamed, np.zeros(3), adopt_at=4)
    assert s.stats["spare_face_at_comeback"] == face and np.allclose(s.stats["spare_bary_at_comeback"], bary)
    assert s.stats["handovers"] == 1 and s._identity[spare] == s._identity[k]


def test_no_handover_to_a_column_far_from_every_ended_marker(streamed):
    s, _, k, spare = _comeback(streamed, np.array([0.0, 0.1, 0.0]), steps=9)  # 10 cm from where k's would be
    assert s.face_ids[spare] == -1 and s.stats.get("handovers", 0) == 0


def test_a_lock_upgrade_solves_each_markers_columns_as_one(streamed):
    from uuomocap.solver_core.windowed_solver import _Frame

    s = _clone(streamed)
    M = s.num_markers
    x = np.arange(3 * M * 3, dtype=float).reshape(3, M, 3)
    vis = np.ones((3, M), bool)
    vis[1:, 2] = False  # marker 2's column ends after frame 0 ...
    vis[0, 5] = False   # ... and it comes back in column 5, empty until then
    frames = [_Frame(i, i, x[i], vis[i]) for i in range(3)]
    for f in frames:
        f.identity = np.arange(M)
    assert s._joined_markers(frames, x, vis) is None  # every column one marker: nothing to join
    for f in frames[1:]:
        f.identity[5] = 2  # the handover gave column 5 marker 2's identity
    s._identity = frames[-1].identity.copy()
    joined, seen, owner = s._joined_markers(frames, x, vis)
    assert joined.shape == (3, M - 1, 3) and seen.shape == (3, M - 1)  # column 5 never held marker 5 while seen
    assert owner[2] == owner[5] == 2 and owner[6] == 5 and (owner >= 0).all()
    np.testing.assert_array_equal(joined[:, 2], np.stack([x[0, 2], x[1, 5], x[2, 5]]))
    assert seen[:, 2].all() and np.isnan(joined[~seen]).all()


def test_columns_the_bootstrap_joined_keep_one_identity(streamed):
    from uuomocap.solver_core.windowed_solver import _Frame

    s = _clone(streamed)
    M = s.num_markers
    window = [_Frame(i, i, np.zeros((M, 3)), np.ones(M, bool)) for i in range(3)]
    for f in window:
        f.identity = np.arange(M)
    s._join_identities({"kept": True, "chains": [[2], [3, 4]]}, window)
    assert s._identity[4] == 3 and (np.delete(s._identity, 4) == np.delete(np.arange(M), 4)).all()
    # a joined pass that was dropped (it fitted worse): its chains are still one marker each
    s._join_identities({"kept": False, "chains": [[1, 7, 9], [2]]}, window)
    for ids in [s._identity, *(f.identity for f in window), *(f.identity for f in s._history)]:
        assert ids[7] == ids[9] == ids[1] == 1 and ids[4] == ids[3] == 3 and ids[2] == 2


def test_buffers_do_not_grow_with_the_take(streamed):
    s = _clone(streamed)
    # the reservoir keeps sampling; the upgrade solves themselves are tested on their own
    s.config = replace(s.config, upgrade_growth=1e9)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    last = int(md.stamps_ns[-1])
    sizes = {}
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, 700, last, order)):
        s.add_prior(*prior)  # a prior every frame: more than the prior ring holds
        s.add_markers(st, md.positions[j], md.visible[j])
        if step + 1 in (500, 700):
            sizes[step + 1] = s.buffer_sizes()
    reservoir = {k: v.pop("reservoir") for k, v in sizes.items()}
    # the frames a lock upgrade may revise: the last revise_s seconds (not yet full after 23 s)
    ring = {k: v.pop("refined_ring") for k, v in sizes.items()}
    assert s._refined_ring.maxlen == round(s.config.revise_s * md.rate_hz) and ring[500] < ring[700] <= s._refined_ring.maxlen
    assert sizes[500] == sizes[700], sizes
    c = s.config
    assert all(8 <= r <= c.upgrade_frames for r in reservoir.values()), reservoir
    assert sizes[700]["pending"] <= c.lag_frames + c.hop_frames and sizes[700]["priors"] == c.prior_buffer
    assert sizes[700]["history"] == c.history_frames


def test_degraded_fit_rebootstraps_while_estimating(streamed):
    """Markers that no longer match their correspondences (here: every marker index permuted, as
    after a subject change) degrade the fit; the solver keeps estimating, re-bootstraps on a new
    window and fits again."""
    s = _clone(streamed)
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    perm = np.random.default_rng(1).permutation(md.positions.shape[1])
    last = int(md.stamps_ns[-1])
    residuals = []
    for st, j, prior in _frames(md, rows, 0, 130, last, order):
        s.add_prior(*prior)
        out = s.add_markers(st, md.positions[j][perm], md.visible[j][perm])
        assert out and out[0].kind == "estimate"  # estimates never stop
        residuals.append(out[0].residual_m)
    assert s.stats["rebootstraps"] == 1, s.stats
    assert np.mean(residuals[:10]) > s.config.degrade_threshold_m
    # fits again: as well as the first lock did on the same frames (before the permutation)
    baseline = np.mean([r.residual_m for r in streamed["results"] if r.kind == "estimate"])
    print(f"\nresidual after re-bootstrap {np.mean(residuals[-10:]) * 1e3:.1f} mm, first lock {baseline * 1e3:.1f} mm")
    assert np.mean(residuals[-10:]) < 0.015, residuals[-10:]


def _attach_error_mm(solver, gt, model) -> float:
    from uuomocap.solver_core.metrics import surface_points_rest

    real = np.asarray(gt["marker_faces"]) >= 0
    ok = real & (solver.face_ids >= 0)
    t = surface_points_rest(model, gt["betas"], np.asarray(gt["marker_faces"])[ok], np.asarray(gt["marker_bary"])[ok])
    p = surface_points_rest(model, gt["betas"], solver.face_ids[ok], solver.bary[ok])
    return float(1000 * np.linalg.norm(p - t, axis=1).mean())


def _mislocked_clone(streamed) -> WindowedSolver:
    """The streamed solver with six markers' locked points rotated among them (a wrong lock the
    upgrade has to repair; the bootstrap on this fixture is already good, 11 mm)."""
    s = _clone(streamed)
    wrong = np.flatnonzero(s.face_ids >= 0)[::6][:6]
    s.face_ids[wrong] = s.face_ids[np.roll(wrong, 1)]
    s.bary[wrong] = s.bary[np.roll(wrong, 1)]
    s._prepare_lock()
    return s


def test_lock_upgrade_on_the_reservoir_repairs_a_wrong_lock(streamed):
    s = _mislocked_clone(streamed)
    assert 8 <= len(s._reservoir) <= s.config.upgrade_frames
    frames = sorted(f.index for f in s._reservoir)
    assert frames[0] < 10 and frames[-1] > 90  # spread over the whole take, not the recent frames
    before = _attach_error_mm(s, streamed["gt"], streamed["model"])
    version = s.labels_version
    s._upgrade_lock()
    assert s.stats["upgrades"] == 1 and "upgrades_rejected" not in s.stats, s.stats
    after = _attach_error_mm(s, streamed["gt"], streamed["model"])
    print(f"\nattachment error {before:.1f} -> {after:.1f} mm")
    assert s.labels_version == version + 1
    assert after < before, (before, after)
    upgraded_faces = s.face_ids.copy()
    # the frames in the recent window were estimated under the old lock: a re-check on them would
    # pull the points back towards the old ones, so none runs until a window of frames was
    # estimated under the new lock; then it runs and keeps the repair
    md, rows = streamed["md"], streamed["rows"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    checks = s.stats["rechecks"]
    s._since_recheck = 10**6  # a re-check is due by the period
    for step, (st, j, prior) in enumerate(_frames(md, rows, 0, s.config.recheck_frames + 2, int(md.stamps_ns[-1]), order)):
        s.add_prior(*prior)
        s.add_markers(st, md.positions[j], md.visible[j])
        if step + 1 < s.config.recheck_frames:
            assert s.stats["rechecks"] == checks, step
    assert s.stats["rechecks"] == checks + 1
    assert _attach_error_mm(s, streamed["gt"], streamed["model"]) < before
    # on a worker thread (live streams): same result, adopted at the first frame after it is ready
    b = _mislocked_clone(streamed)
    b.config = replace(b.config, upgrade_in_background=True)
    b._upgrade_lock()
    assert b._upgrade_job is not None and b.labels_version == version
    b._upgrade_job[0].result(timeout=120)
    b._poll_upgrade()
    assert b._upgrade_job is None and b.labels_version == version + 1
    np.testing.assert_array_equal(b.face_ids, upgraded_faces)
    # a re-bootstrap meanwhile makes a running upgrade stale: it stops at its next optimiser step
    # (instead of keeping a core busy for its whole solve) and is not adopted
    c = _mislocked_clone(streamed)
    c.config = replace(c.config, upgrade_in_background=True)
    c._upgrade_lock()
    c._lock_generation += 1
    assert isinstance(c._upgrade_job[0].exception(timeout=120), UpgradeCancelled)
    c._poll_upgrade()
    assert c.stats["upgrades_cancelled"] == 1 and c._upgrade_job is None and c.labels_version == version
    # the end of the take (flush) cancels it too: every frame is final, its lock has nothing left to serve
    d = _mislocked_clone(streamed)
    d.config = replace(d.config, upgrade_in_background=True)
    d._upgrade_lock()
    future = d._upgrade_job[0]
    d.flush()
    assert isinstance(future.exception(timeout=120), UpgradeCancelled)
    assert d.labels_version == version
    d.close()
    # in the worker process (the default for live streams): the same lock, and a cancel stops it
    from uuomocap.solver_core.solve_worker import SolveCancelled, StagedSolveWorker

    worker = StagedSolveWorker(streamed["model"], streamed["chamfer"])
    e = _mislocked_clone(streamed)
    e.config = replace(e.config, upgrade_in_background=True)
    e._worker = worker
    e._upgrade_lock()
    assert e._upgrade_job is not None and "worker_job" in e._upgrade_job[1]
    e._upgrade_job[0].result(timeout=300)

    def judged_here(*args):
        raise AssertionError("the worker judged this upgrade: no reservoir re-solve in the stream's process")

    e._reservoir_fit = judged_here
    e._poll_upgrade()
    assert e.labels_version == version + 1 and "worker_failed" not in e.stats
    np.testing.assert_array_equal(e.face_ids, upgraded_faces)
    # the worker's judgement of the two locks is the one this process makes (thread path, b)
    assert e.stats["upgrade_checks_in_worker"] == 1
    np.testing.assert_allclose(e.stats["upgrade_fit_mm"], b.stats["upgrade_fit_mm"], atol=0.02)
    # a marker re-assigned (here: dropped) while the upgrade ran: the current lock is no longer
    # the one the worker judged against, so the worker judges it again against the lock as it is
    # now (still not in this process), and it is adopted when that is back
    g = _mislocked_clone(streamed)
    g.config = replace(g.config, upgrade_in_background=True)
    g._worker = worker
    g._upgrade_lock()
    g._unassign(np.array([int(np.flatnonzero(g.face_ids >= 0)[0])]))
    g._upgrade_job[0].result(timeout=300)
    g._reservoir_fit = judged_here
    g._poll_upgrade()
    assert g.stats["upgrade_judged_again"] == 1 and g._upgrade_job is not None and g.labels_version == version + 1
    g._upgrade_job[0].result(timeout=120)
    g._poll_upgrade()
    assert g.stats["upgrade_checks_in_worker"] == 1 and g.stats["upgrades"] == 1 and g._upgrade_job is None
    current, candidate = g.stats["upgrade_fit_mm"][0]
    assert candidate < current and g.labels_version == version + 2
    np.testing.assert_array_equal(g.face_ids, upgraded_faces)
    g._worker = None  # f closes the shared worker
    f = _mislocked_clone(streamed)
    f.config = replace(f.config, upgrade_in_background=True)
    f._worker = worker
    f._upgrade_lock()
    future = f._upgrade_job[0]
    f.flush()  # cancels the running upgrade
    assert isinstance(future.exception(timeout=120), SolveCancelled)
    f._poll_upgrade()
    assert f.labels_version == version
    f.close()  # closes the worker
    assert f._worker is None
    with pytest.raises(RuntimeError, match="shutdown"):
        worker.submit(None, None, 30.0, "+z", None, None, None)


def test_a_lock_upgrade_revises_the_frames_refined_under_the_old_lock(streamed):
    """Frames refined under a wrong lock come out again, 'revised', once an upgrade repaired the
    lock: each frame of the ring once, in order, under the new shape, fitting its markers better.
    A replay revises at once; a live solver one hop per hop, only while it keeps up; flush
    finishes a revision in progress."""
    md, rows, gt = streamed["md"], streamed["rows"], streamed["gt"]
    n = md.positions.shape[0]
    order = np.concatenate([np.arange(n - 1, 0, -1), np.arange(n)])
    last = int(md.stamps_ns[-1])

    def stream(solver, count, start=0, **kw):
        source, out = {}, []
        for st, j, prior in _frames(md, rows, start, count, last + start * 10**8, order):
            solver.add_prior(*prior)
            source[solver._index] = j
            res = solver.push_markers(st, md.positions[j], md.visible[j])
            res += solver.refine_ready(**kw)
            out.append(res)
        return source, out

    # the upgrades and revisions below only (since the arms hang at the sides, session 39, the six rotated
    # points misfit enough for the degradation test to re-bootstrap on its own, which repairs the lock first)
    quiet = dict(upgrade_growth=1e9, recheck_period_s=0.0, slip_frames=10_000, degrade_threshold_m=1e9)
    s = _mislocked_clone(streamed)
    s.config = replace(s.config, **quiet)
    source, _ = stream(s, 60)  # refined under the wrong lock
    wrong = {f.index: f for f in s._refined_ring if f.index in source}
    refined = {i: (f.residual, f.joints.copy()) for i, f in wrong.items()}
    ring = [f.index for f in s._refined_ring]
    attach_wrong = _attach_error_mm(s, gt, streamed["model"])
    s._upgrade_lock()
    assert s.stats["upgrades"] == 1 and s.stats.get("revisions") == 1, s.stats
    assert _attach_error_mm(s, gt, streamed["model"]) < 0.2 * attach_wrong  # the lock is repaired
    _, calls = stream(s, 1, start=60)
    revised = [r for r in calls[0] if r.kind == "revised"]
    assert [r.frame_index for r in revised] == ring  # each once, in order
    assert all(np.array_equal(r.betas, s.betas.double().numpy()) for r in revised)
    got = {r.frame_index: r for r in revised}
    before = np.mean([refined[i][0] for i in wrong])
    after = np.mean([got[i].residual_m for i in wrong])
    err = lambda joints, i: 1000 * np.linalg.norm(joints[:22] - gt["joints"][source[i]][:22], axis=-1).mean()
    mp_before = np.mean([err(refined[i][1], i) for i in wrong])
    mp_after = np.mean([err(got[i].joints, i) for i in wrong])
    # frames that come after the revision, refined under the repaired lock from the start
    later, calls = stream(s, 40, start=61)
    fresh = [r for res in calls for r in res if r.kind == "refined" and r.frame_index in later]
    mp_fresh = np.mean([1000 * np.linalg.norm(r.joints[:22] - gt["joints"][later[r.frame_index]][:22], axis=-1).mean() for r in fresh])
    print(f"\nrevised {len(revised)} frames; under the wrong lock: residual {before * 1e3:.2f} -> {after * 1e3:.2f} mm, "
          f"MPJPE {mp_before:.1f} -> {mp_after:.1f} mm ({len(fresh)} later frames under the repaired lock: {mp_fresh:.1f} mm)")
    assert after < before
    # The joints: the six swapped markers mostly hide behind the Cauchy kernel (since session 39's
    # generator, the arms at the sides: the streamed lock's frames 13.9 mm, the wrong lock's 14.8, the
    # repaired lock's 21.6 - its attachment is 9.9 mm off the truth against the wrong lock's 91.6, but
    # the body it locks from this 4 s reservoir is worse; fresh frames under it 22.0).  A revised
    # frame must come out as the repaired lock solves any frame, not worse.
    assert len(fresh) >= 20 and mp_after < mp_fresh + 1.0, (mp_before, mp_after, mp_fresh)
    assert s._revision is None and not any(r.kind == "revised" for r in s.flush())

    # live: the upgrade lands in the background; one hop of revised frames per revise_every_hops
    # hops of stream
    b = _mislocked_clone(streamed)
    b.config = replace(b.config, upgrade_in_background=True, **quiet)
    stream(b, 60)
    b._start_revision()
    total = len(b._revision["frames"])
    hop, every = b.config.hop_frames, b.config.revise_every_hops
    _, calls = stream(b, 3 * hop, start=60, max_passes=1)
    assert not any(r.kind == "revised" for res in calls for r in res)  # behind: none
    _, calls = stream(b, 3 * every * hop, start=90)
    per_call = [sum(r.kind == "revised" for r in res) for res in calls]
    steps = [i for i, k in enumerate(per_call) if k]
    assert len(steps) == 3 and max(per_call) == hop and np.all(np.diff(steps) == every * hop), per_call
    rest = [r for r in b.flush() if r.kind == "revised"]
    assert len(rest) == total - 3 * hop and b._revision is None

    # live with the worker process (the default): the whole revision runs there as one job; once
    # back it comes out revise_emit_frames per call (none while behind), the poses the same as
    # revised here; flush hands out the rest
    from uuomocap.solver_core.solve_worker import StagedSolveWorker

    w = _mislocked_clone(streamed)
    w.config = replace(w.config, upgrade_in_background=True, revise_emit_frames=7, **quiet)
    stream(w, 60)
    here = copy.deepcopy(w)
    here.config = replace(here.config, upgrade_in_background=False)
    here._start_revision()
    expected = {r.frame_index: r for r in here._revise_all()}
    w._worker = StagedSolveWorker(streamed["model"], streamed["chamfer"])
    try:
        w._start_revision()
        assert "future" in w._revision
        w._revision["future"].result(timeout=120)
        _, calls = stream(w, 2, start=60, max_passes=1)
        assert not any(r.kind == "revised" for res in calls for r in res)  # behind: none
        _, calls = stream(w, 3, start=62)
        per_call = [[r for r in res if r.kind == "revised"] for res in calls]
        assert [len(x) for x in per_call] == [7, 7, 7]
        got = [r for x in per_call for r in x] + [r for r in w.flush() if r.kind == "revised"]
        assert [r.frame_index for r in got] == list(expected) and w._revision is None
        for r in got:
            np.testing.assert_allclose(r.poses, expected[r.frame_index].poses, atol=1e-6)
            np.testing.assert_allclose(r.joints, expected[r.frame_index].joints, atol=1e-6)
            assert r.residual_m == pytest.approx(expected[r.frame_index].residual_m, abs=1e-7)
    finally:
        w.close()


def test_reservoir_stays_bounded_and_spread_over_a_long_take(streamed):
    from uuomocap.solver_core.windowed_solver import _Frame

    s = _clone(streamed)
    s._reservoir, s._reservoir_stride, s._reservoir_seen = [], 1, 0
    m = s.num_markers
    for i in range(10_000):
        s._keep_in_reservoir(_Frame(i, i, np.zeros((m, 3)), np.ones(m, dtype=bool)))
    idx = [f.index for f in s._reservoir]
    assert len(idx) <= s.config.upgrade_frames
    assert idx[0] == 0 and idx[-1] > 9_000 and np.ptp(np.diff(idx)) == 0  # evenly spaced over the take


def test_robust_kernel_keeps_the_pose_when_a_few_markers_are_locked_wrong(streamed):
    """Three markers moved to the far side of the body: least squares drags the pose towards them,
    the Cauchy kernel follows the other markers (and leaves the three standing out as slipped)."""
    md, gt = streamed["md"], streamed["gt"]
    errors = {}
    for scale in (None, 0.01):
        s = _clone(streamed)
        s.config = replace(s.config, robust_scale_m=scale, recheck_period_s=0.0, upgrade_frames=0, slip_frames=10_000)
        wrong = np.flatnonzero(s.face_ids >= 0)[:3]
        far = int(np.argmax(np.linalg.norm(s.model.v_template.numpy()[s.model.faces.numpy()].mean(1)
                                           - s.model.v_template.numpy()[s.model.faces.numpy()[s.face_ids[wrong[0]]]].mean(0), axis=1)))
        s.face_ids[wrong] = far
        s._prepare_lock()
        frames = [len(s._history) - 1 - k for k in range(10)]
        hist = list(s._history)
        theta = np.stack([hist[i].theta for i in frames])
        trans = np.stack([hist[i].trans for i in frames])
        theta, trans = s._gauss_newton(theta, trans, np.stack([hist[i].markers for i in frames]),
                                       np.stack([hist[i].visible for i in frames]), np.stack([hist[i].prior for i in frames]), 5)
        lin = s._linearize(theta, trans, np.stack([hist[i].markers for i in frames]), np.stack([hist[i].visible for i in frames]),
                           jacobian=False)
        gj = np.asarray(gt["joints"])[[hist[i].index for i in frames]]
        errors[scale] = float(np.linalg.norm(lin["joints"][:, :22] - gj[:, :22], axis=-1).mean() * 1000)
    print(f"\nMPJPE with 3 wrong markers: least squares {errors[None]:.1f} mm, Cauchy {errors[0.01]:.1f} mm")
    assert errors[0.01] < 0.7 * errors[None], errors


def test_recheck_keeps_a_good_lock(streamed):
    # the re-check scores the current points exactly as Stage 3 scores candidates (with the 9.5 mm
    # skin offset); scored without it every marker looked ~9 mm worse than any fresh candidate
    s = _clone(streamed)
    faces, bary, reassigned, version = s.face_ids.copy(), s.bary.copy(), s.stats["reassigned"], s.labels_version
    s._recheck(np.arange(len(s.face_ids)))  # every marker in one group
    # a re-assignment may keep the face and move the point on it (new barycentrics)
    moved = int(((s.face_ids != faces) | (np.abs(s.bary - bary).max(axis=1) > 0)).sum())
    assert s.stats["reassigned"] - reassigned == moved
    assert moved <= 2, moved
    # and a marker put on the wrong limb is moved back
    last = s._history[-1]
    ok = np.flatnonzero((faces >= 0) & last.visible)
    wrong = int(ok[0])
    far = int(ok[np.argmax(np.linalg.norm(last.markers[ok] - last.markers[wrong], axis=1))])  # farthest marker's point
    s.face_ids[wrong], s.bary[wrong] = s.face_ids[far], s.bary[far]
    s._prepare_lock()
    s._recheck(np.arange(len(s.face_ids)))  # every marker in one group
    assert s.face_ids[wrong] != faces[far] and s.labels_version > version


def test_lock_upgrade_keeps_the_body_part(streamed):
    """An upgrade refines the lock, it does not move the markers to another part: its solve is
    told the locked part (``_upgrade_config``), and a result on another part is refused whatever
    its fit - here the streamed full-body lock relabelled as a left leg whose part the upgrade
    does not know (so it solves a full body), which keeps its points."""
    from uuomocap.solver_core.staged_solver import part_vertex_ids

    s = _mislocked_clone(streamed)
    model = streamed["model"]
    leg = tuple(model.joint_names.index(n) for n in ("left_hip", "left_knee", "left_ankle"))
    s.allowed_ids = part_vertex_ids(model, leg)
    assert s.part_joints is None
    faces, version = s.face_ids.copy(), s.labels_version
    s._upgrade_lock()
    assert s.stats["upgrades"] == 1 and s.stats["upgrades_other_part"] == 1 and s.stats["upgrades_rejected"] == 1
    np.testing.assert_array_equal(s.face_ids, faces)
    assert s.labels_version == version


def test_lock_upgrades_use_the_offline_shape_prior_on_full_bodies_only(streamed):
    """A full body's upgrade holds the shape to the video as the offline solver does (Stage 2,
    0.1); a partial body's keeps the bootstrap's paper weight (1), which its few markers need.
    Both solve the body the bootstrap decided on: a full body, or the locked part."""
    from uuomocap.solver_core.pose_fitting import PoseFittingConfig
    from uuomocap.solver_core.staged_solver import SolverConfig, part_vertex_ids

    s = _clone(streamed)
    job = {"markers": np.zeros((40, 3, 3)), "stride": 1}
    assert s.allowed_ids is None
    full = s._upgrade_config(job)
    assert full.pose_fitting.shape_weight == SolverConfig().pose_fitting.shape_weight == 0.1
    # ...but the bootstrap's Stage-2 pose prior (the paper's), not the offline solver's stronger one
    assert full.pose_fitting.pose_weight == s.config.bootstrap_solver.pose_fitting.pose_weight == PoseFittingConfig().pose_weight
    assert SolverConfig().pose_fitting.pose_weight > PoseFittingConfig().pose_weight
    assert full.max_hypotheses == 1 and full.ik.smoothness_weight == 0.0
    # the bootstrap's decision stands: a full body stays one, a part is solved as that part
    assert full.force_full_body is True and full.matching.part_joints is None
    model = streamed["model"]
    leg = tuple(model.joint_names.index(n) for n in ("left_hip", "left_knee", "left_ankle"))
    s.allowed_ids, s.part_joints = part_vertex_ids(model, leg), leg
    part = s._upgrade_config(job)
    assert part.pose_fitting.shape_weight == s.config.bootstrap_solver.pose_fitting.shape_weight == PoseFittingConfig().shape_weight == 1.0
    assert part.max_hypotheses == 1 and part.ik == full.ik
    assert part.matching.part_joints == leg and part.force_full_body is None


def test_per_frame_model_matches_the_staged_solver_marker_models(streamed):
    """The per-frame solves' numpy body (``_linearize``) predicts the markers as the torch IK's
    ``predicted_markers`` does, for the facet and the smooth-normal offset models."""
    from uuomocap.solver_core.body_params import BodyParams
    from uuomocap.solver_core.inverse_kinematics import predicted_markers

    for offset_model in ("face_normal", "smooth_normal"):
        s = _clone(streamed)
        s.config = replace(s.config, ik=replace(s.config.ik, offset_model=offset_model))
        s._prepare_lock()
        hist = list(s._history)[-5:]
        theta = np.stack([h.theta for h in hist])
        trans = np.stack([h.trans for h in hist])
        lin = s._linearize(theta, trans, np.stack([h.markers for h in hist]), np.stack([h.visible for h in hist]), jacobian=False)
        params = BodyParams(torch.as_tensor(theta[:, :3], dtype=torch.float32),
                            torch.as_tensor(theta[:, 3:], dtype=torch.float32).reshape(len(hist), 23, 3),
                            torch.as_tensor(trans, dtype=torch.float32), torch.as_tensor(s.betas, dtype=torch.float32).reshape(-1),
                            torch.as_tensor(float(s.yaw), dtype=torch.float32))
        with torch.no_grad():
            expected = predicted_markers(s.model, params, s._attachment(), s.up, s.config.ik.marker_offset_m, offset_model)
        assert np.abs(lin["pred"] - expected.double().numpy()).max() < 1e-4, offset_model


def test_worker_process_ends_when_its_parent_is_killed(tmp_path):
    """A solver killed hard (SIGKILL: no pool shutdown) must not leave its worker process behind."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "parent.py"
    script.write_text(
        "import time\n"
        "from uuomocap.solver_core.body_model import load_body_model\n"
        "from uuomocap.solver_core.solve_worker import StagedSolveWorker\n"
        "if __name__ == '__main__':\n"
        "    w = StagedSolveWorker(load_body_model('open-low'))\n"
        "    assert w.ready(120)\n"
        "    print(w.pid, flush=True)\n"
        "    time.sleep(300)\n"
    )
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(parent.stdout.readline())
        assert worker_pid != parent.pid

        def alive(pid):
            try:
                with open(f"/proc/{pid}/stat") as f:
                    return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
            except FileNotFoundError:
                return False

        assert alive(worker_pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 15
        while alive(worker_pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not alive(worker_pid), "the worker outlived its killed parent"
    finally:
        parent.kill()
        parent.wait(10)


def test_smoothing_leaves_the_limbs_alone_when_the_whole_body_accelerates(streamed):
    """A landing: every marker of a 22-frame window gets the same sharp vertical dip (the trunk
    and limbs move together, no limb moves relative to the body).  The smoothing pass on bone
    vectors leaves the limbs' rotations where the markers put them; smoothing world joint
    positions (the offline IK's term) turns the limbs against the dip to keep their joints' paths
    smooth."""
    from uuomocap.solver_core.windowed_solver import N_POSE

    frames = list(streamed["solver"]._history)[-22:]
    t = np.arange(len(frames))
    dip = -0.08 * np.exp(-0.5 * ((t - 11) / 1.5) ** 2)  # metres: an 8 cm dip over ~0.1 s
    lift = np.stack([np.zeros_like(dip), np.zeros_like(dip), dip], 1)  # the session's up axis is +z
    markers = np.stack([f.markers for f in frames]) + lift[:, None]
    vis = np.stack([f.visible for f in frames])
    prior = np.stack([f.prior for f in frames])
    theta0 = np.stack([f.theta for f in frames])
    trans0 = np.stack([f.trans for f in frames]) + lift
    moved = {}
    for target in ("bones", "joints"):
        s = _clone(streamed)
        s.config = replace(s.config, smoothness_target=target)
        theta, trans = theta0.copy(), trans0.copy()
        for _ in range(4):  # to convergence (the streamed pass takes one step per hop)
            step = s._window_step(theta, trans, markers, vis, prior, 2)
            theta[2:] += step[:, :N_POSE]
            trans[2:] += step[:, N_POSE:]
        # how far the rotations of every joint but the root and the hips (spine1 on) moved, radians
        moved[target] = float(np.abs(theta[:, 9:] - theta0[:, 9:]).max())
    print(f"\nlimb rotation change under a whole-body dip: bones {moved['bones']:.4f} rad, joints {moved['joints']:.4f} rad")
    assert moved["bones"] < 0.5 * moved["joints"], moved


def test_solver_node_uses_the_windowed_solvers_defaults_unless_configured():
    """The node's launch-file parameters override the solver's config only when given (its own
    copy of the smoothing weight once kept an old default after the solver's was re-tuned)."""
    from uuomocap.nodes.base import Runtime
    from uuomocap.nodes.solver import Solver
    from uuomocap.solver_core.windowed_solver import WindowedSolverConfig

    default = WindowedSolverConfig()
    for params, expected in (({}, (default.smoothness_weight, default.estimate_iterations)),
                             ({"smoothness_weight": 0.005, "estimate_iterations": 3}, (0.005, 3))):
        node = Solver("solver", Solver.parse_config({**params, "bootstrap_starts": 1}, "solver"), Runtime(endpoints=None))
        node.setup()  # one bootstrap start: no worker process
        try:
            assert node.worker is None and node.solver_config.bootstrap_alternatives == ()
            assert (node.solver_config.smoothness_weight, node.solver_config.estimate_iterations) == expected
            assert node.solver_config.smoothness_target == WindowedSolverConfig().smoothness_target
        finally:
            node.teardown()
    with pytest.raises(ValueError, match="estimate_iterations"):
        Solver.parse_config({"estimate_iterations": 0}, "solver")
    # two starts: the worker process is up when setup returns - a lockstep replay delivers the
    # bootstrap window at once, and its imports then sat inside the bootstrap (make demo 12.0 -> 8.0 s)
    node = Solver("solver", Solver.parse_config({}, "solver"), Runtime(endpoints=None))
    node.setup()
    try:
        assert node.worker is not None and node.worker.pid is not None
    finally:
        node.teardown()


def test_estimate_iterations_follow_the_marker_rate_unless_configured(streamed):
    """One Gauss-Newton iteration per estimate from 60 Hz (a 120 Hz stream needs the throughput, and
    the warm start is close), two below; a configured count wins at any rate."""
    model = streamed["model"]
    for rate, config, expected in ((120.0, WindowedSolverConfig(), 1), (60.0, WindowedSolverConfig(), 1), (30.0, WindowedSolverConfig(), 2),
                                   (120.0, WindowedSolverConfig(estimate_iterations=2), 2), (30.0, WindowedSolverConfig(estimate_iterations=1), 1)):
        solver = WindowedSolver(model, replace(config, worker_process=False), "+z", rate)
        assert solver.estimate_iterations == expected, (rate, config.estimate_iterations)
    with pytest.raises(ValueError, match="estimate_iterations"):
        WindowedSolverConfig(estimate_iterations=0)


def test_lever_jacobian_is_minus_the_lever_cross_each_axis():
    """Block j of point k: d(p_k)/d(theta_j) = -[lever_kj]x axes_j, i.e. column q is axis_q x lever
    (a rotation about axis_q moves the point by axis_q x lever); checked against np.cross."""
    from uuomocap.solver_core.windowed_solver import lever_jacobian, rotation_matrices

    rng = np.random.default_rng(3)
    for B, K in ((1, 40), (5, 7)):
        levers = rng.normal(size=(B, K, 24, 3))
        axes = rotation_matrices(rng.normal(size=(B, 24, 3)))
        got = lever_jacobian(levers, axes).reshape(B, K, 3, 24, 3)
        want = np.cross(np.swapaxes(axes, -1, -2)[:, None], levers[:, :, :, None, :])  # (B,K,24,q,3): axis_q x lever
        np.testing.assert_allclose(got, want.transpose(0, 1, 4, 2, 3), atol=1e-12)


def test_a_lock_made_before_any_video_prior_rebootstraps_once_priors_come(tmp_path):
    """The video prior only from 2 s on (a camera started late; BlazePose's face-based detector
    finding no one while the subject faces away): the bootstrap at 1.5 s locks without a prior, and
    once priors have come for a bootstrap window the solver bootstraps again on them.  Before session
    38 the take ran markers-only to its end (no per-frame prior, no lock upgrade: ~110 mm here)."""
    from uuomocap.protocol.session import read_npz
    from uuomocap.synth import SampleConfig, make_session
    from uuomocap.window_methods import stream_solve

    session = tmp_path / "late_prior"
    make_session(session, SampleConfig(motion="walk", rate_hz=30.0, duration_s=5.0, n_markers=30, seed=0, video=False))
    truth = np.asarray(read_npz(session / "gt.npz")["joints"])[:, :22]
    config = replace(WindowedSolverConfig(), bootstrap_s=1.5, upgrade_frames=0, bootstrap_alternatives=())
    on_time = stream_solve(session, config=config)  # the prior from the first frame
    normal = (np.linalg.norm(on_time.refined["joints"][:, :22] - truth, axis=-1).mean(axis=1) * 1000)[-30:].mean()
    prior = dict(np.load(session / "prior.npz"))
    prior["valid"] = prior["valid"] & (prior["stamps_ns"] >= 2_000_000_000)
    np.savez(session / "prior.npz", **prior)
    run = stream_solve(session, config=config)
    assert run.stats["prior_rebootstraps"] == 1 and run.stats["bootstraps"] == 2
    err = np.linalg.norm(run.refined["joints"][:, :22] - truth, axis=-1).mean(axis=1) * 1000
    before, after = err[45:90].mean(), err[-30:].mean()  # markers-only lock | the prior's lock
    print(f"refined MPJPE under the markers-only lock {before:.1f} mm, after the re-bootstrap on the priors {after:.1f} mm "
          f"(with the prior from the start {normal:.1f} mm)")
    # session 39's generator (arms at the sides, as the neutral start has them): 41.3 -> 18.9 mm, on time 21.6
    assert after < 0.6 * before and after < normal + 3.0


def test_the_logged_summaries_say_what_the_stats_hold():
    """The solver node's 'bootstrap done' and 'take end' log lines (what `bench live` parses and a
    technician reads) and whether a config needs the worker process."""
    from uuomocap.solver_core.windowed_solver import bootstrap_starts_summary, needs_worker, start_worker, take_end_summary

    assert bootstrap_starts_summary({}) == ""
    assert bootstrap_starts_summary({"bootstrap_start_fits_mm": [1.234, None], "bootstrap_start_chosen": 0}) == "1.23 / failed mm, #1 locked"
    assert bootstrap_starts_summary({"bootstrap_start_fits_mm": [2.0, 1.5], "bootstrap_start_chosen": 1}) == "2.00 / 1.50 mm, #2 locked"
    assert take_end_summary({"reassigned": 4}, 0) == ""
    assert take_end_summary({"upgrade_at_end_s": 13.3, "revise_at_end_s": 2.2, "reassigned_at_end": 3}, 480) == \
        "lock upgrade 13.3 s, 3 markers re-assigned, 480 frames revised in 15.5 s"
    assert take_end_summary({"revise_at_end_s": 1.04}, 5) == "lock upgrade skipped, 0 markers re-assigned, 5 frames revised in 1.0 s"
    default = WindowedSolverConfig()
    assert needs_worker(default) and needs_worker(replace(default, bootstrap_alternatives=(), upgrade_in_background=True))
    assert not needs_worker(replace(default, worker_process=False))
    alone = replace(default, bootstrap_alternatives=(), upgrade_in_background=False)
    assert not needs_worker(alone) and start_worker(None, None, alone) is None
    # `solve --method uuo-window` prints the same starts summary, and none when no start reported
    from uuomocap.commands.solve import _summary

    info = {"out": "x.npz", "seconds": 1.0, "frames": 240, "markers": 30, "threads": 1, "stage_seconds": {"bootstrap": 7.5}}
    assert "bootstrap 7.5 s (starts' marker fit 3.26 / 3.02 mm, #2 locked);" in _summary(
        {**info, "bootstrap_start_fits_mm": [3.26, 3.02], "bootstrap_start_chosen": 1}, "uuo-window")
    assert "bootstrap 7.5 s; 0 re-bootstraps" in _summary(info, "uuo-window")
