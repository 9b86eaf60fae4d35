"""Near-online sliding-window variant of the staged solver (issue 6).

Three layers, each reusing the offline stages (no second copy of any stage):

* **Bootstrap**: once ``bootstrap_s`` of markers is in, the offline staged solver
  (``staged_solver.solve``: segmentation, part matching, yaw hypotheses, Stages 2-5) runs on that
  window, decimated to ``bootstrap_rate_hz`` (the paper's 30 Hz; neighbouring 120 Hz frames add
  cost, not information).  Shape, yaw and the marker-surface correspondence are then locked.
* **Estimate** (causal, every frame): Gauss-Newton / Levenberg-Marquardt on the Stage-4 energy of
  ``inverse_kinematics`` for the newest frame only: 3-vector marker residuals with the same offset
  model as the offline IK (surface point + 9.5 mm along the posed normal, or the paper's distance
  model), the pose prior (Stage 4 weight), warm-started from the previous frame.  The Jacobian is
  analytic from ONE forward pass of the body model (skinning transforms at the joints; linear
  blend skinning has no pose blend shapes in the open models, so it is exact there and a
  Gauss-Newton approximation for SMPL files with pose correctives).
* **Refined** (fixed lag): the same energy over a window of the not-yet-final frames plus a few
  already-final context frames, with a temporal-smoothness term (accelerations of the pelvis
  and of every bone vector; ``smoothness_target`` explains), solved by banded Gauss-Newton (the smoothness couples only neighbouring frames,
  so the normal equations are block-banded), warm-started from the previous pass.  Frames that
  leave the lag are published as ``refined``.
* **Revised** (beyond the paper): lock upgrades re-run the staged solver on a reservoir of refined
  frames spread over the take; an adopted one revises the frames refined under the old lock.  The
  take's end (``flush``) runs one more upgrade on the whole take (``upgrade_at_end_growth``) and
  revises the ring under the final lock with the mean-offset pose prior (``revise_at_end``).  A
  recording keeps each frame's ``revised`` result over its ``refined`` one.

Change handling: occluded markers keep their correspondence (they just drop out of the residual);
a marker index that was never assigned (or whose track id changes) is assigned to the surface
point that fits it best (Stage 3, ``find_marker_surface_points``) on the recent frames once it has
been seen for ``new_track_frames``; a marker whose residual stays above ``slip_threshold_m`` is
re-assigned the same way; when the whole fit degrades (mean residual above
``degrade_threshold_m`` for ``degrade_s``, or most visible markers unassigned: a new subject) the
solver re-bootstraps on the next window while it keeps estimating; every ``recheck_period_s`` the
correspondence of all markers is re-checked on the recent window (a group of markers per hop).

Memory is bounded: every buffer is a ring (``collections.deque(maxlen=...)``) sized from the
config and the rate, nothing grows with the take.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import weakref
from collections import deque
from concurrent.futures import BrokenExecutor, wait as wait_futures
from itertools import chain
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from uuomocap.solver_core import lbs
from uuomocap.solver_core.body_params import (
    BodyParams,
    FreeParameters,
    MarkerAttachment,
    interpolate_params,
    pose_params,
    up_tensor,
)
from uuomocap.solver_core.chamfer import vertex_face_table
from uuomocap.solver_core.inverse_kinematics import (InverseKinematicsConfig, predicted_markers, smooth_normals_in_face_frames,
                                                     solve_inverse_kinematics)
from uuomocap.solver_core.marker_surface_correspondence import find_marker_surface_points
from uuomocap.solver_core.optimization import LBFGSConfig
from uuomocap.solver_core.pose_fitting import PoseFittingConfig
from uuomocap.solver_core.prior_preparation import (
    BodyPrior,
    camera_to_world_rotation,
    neutral_prior,
    prepare_prior,
)
from uuomocap.solver_core.rotations import matrix_to_axis_angle
from uuomocap.solver_core.staged_solver import (
    SolverConfig,
    SolverProgress,
    marker_part_names,
    part_vertex_ids,
    preload_lazy_imports,
    solve,
    solved_part_joints,
)
from uuomocap.solver_core.solve_worker import SolveCancelled
from uuomocap.solver_core.track_stitching import StitchConfig, carried_positions, handover_links

N_POSE = 72  # root (before the yaw) + 23 body joints, axis-angle
N_PARAMS = N_POSE + 3  # + translation


class UpgradeCancelled(RuntimeError):
    """A background lock upgrade stopped because its result can no longer be used."""


class _StopWhenStale(SolverProgress):
    """Progress hook of a background lock upgrade: raises ``UpgradeCancelled`` at the solver's next
    stage or optimiser step once the job is cancelled (end of take) or its lock was superseded
    (re-bootstrap, reset).  Without it a dead upgrade keeps a core busy for its whole solve
    (~30-40 s), e.g. beside the next take's bootstrap."""

    def __init__(self, solver: "WindowedSolver", job: dict):
        self._solver, self._job = solver, job

    def _check(self) -> None:
        if self._job["cancel"].is_set() or self._solver._lock_generation != self._job["generation"]:
            raise UpgradeCancelled("lock upgrade cancelled: its take ended or its lock was replaced")

    def stage_start(self, name: str, detail: str = "") -> None:
        self._check()

    def stage_step(self, name: str, iterations: int, loss: float) -> None:
        self._check()


def windowed_staged_config(**overrides) -> SolverConfig:
    """The offline solver as the bootstrap runs it: Stage 2 keeps the paper's shape prior
    (lambda_beta 1), where the offline solver uses 0.1 (the lock upgrades use 0.1 since session 26:
    ``WindowedSolverConfig.upgrade_solver``).  Measured in session 13 (40 markers, refined
    MPJPE, 13 sessions = the bench's three + ten ``sample make`` takes): 0.1 in the bootstrap and the
    upgrades 15.46 mm (the bench's three 11.59), 1 in both 14.85 (11.02), 1 in the bootstrap only
    14.74 (11.63).  A 3 s window leans on the video's shape more than a whole take does.  Its Stage-2
    pose prior stays the paper's 1 too (the offline 2 of session 29 was measured on whole takes only).
    No track stitching (``SolverConfig.track_stitching``) here: the bootstrap turns it on
    (``fast_bootstrap_config``), the lock upgrades join columns by their identity instead."""
    c = SolverConfig(**{"track_stitching": None, **overrides})
    paper = PoseFittingConfig()
    return replace(c, pose_fitting=replace(c.pose_fitting, shape_weight=paper.shape_weight, pose_weight=paper.pose_weight))


def fast_bootstrap_config() -> SolverConfig:
    """The offline solver with budgets for a 2-3 s window (beyond the paper: speed).  Same stages,
    fewer L-BFGS iterations and frames (the window is short and re-solved continuously later)."""
    c = windowed_staged_config()
    return replace(
        c,
        # The offline solve's track stitching (SolverConfig.track_stitching): a window whose markers
        # come back from occlusions in new columns is solved again on the joined columns.  Whole
        # columns never link, so their bootstrap is unchanged.  Session 46, the first 3 s of two
        # 'breaks 1%' takes: arms 93.8 -> 16.8 mm MPJPE (16.5 -> 22.2 s), walk 18.9 -> 11.1 (9.1 -> 16.2 s).
        track_stitching=StitchConfig(),
        # ... and the joined pass starts from the first pass's body at Stage 3 when that fits its markers
        # to 10 mm (SolverConfig.track_stitching_warm_below_mm; offline it starts over).  Session 48,
        # 'breaks 1%' walk / jump seeds 0-2 (the arms' first passes fit 17-55 mm: unchanged), bootstrap
        # 23-25 s (walk, another bench beside) / 14-15 s (jump, alone) against 29-53 / 32-40 (session 47,
        # another bench beside); MPJPE fixed-lag
        # 13.5 -> 12.3 mm, recording 11.9 -> 11.1 (4 of 6 better, 1 level).  The first 3 s alone (own
        # script, one start): the joined pass 4.3 s instead of 10-14, the window's MPJPE 13.7 against 14.6.
        track_stitching_warm_below_mm=10.0,
        # The rigid-cluster check moves a marker only to a point within 10 cm of it
        # (ClusterConsistencyConfig.max_point_distance_m): in 3 s bones that did not move apart look
        # like one rigid group.  Session 48, the first 3 s of the 'breaks 1%' takes alone (own script):
        # the arms' first passes 17-55 -> 3.3-4.9 mm marker fit (MPJPE 26-96 -> 12-19 mm), the window's
        # MPJPE over the nine 15.4 -> 13.6; the moves it refused 0.43-1.07 m.
        cluster_consistency=replace(c.cluster_consistency, max_point_distance_m=0.1),
        screening_frames=20,
        chamfer_frames=60,
        # The two best-registered yaws, or the best only when the next one registers over 2x worse
        # (the lock upgrades screen the best one only).  Full bodies (40 markers, 9 sessions: 7 + bench
        # speed's two): the best-registered yaw always won, the next distinct one registered 2.0-3.7x
        # worse, and skipping it saved ~1.5 s of an 11-12 s bootstrap with the same refined MPJPE on
        # the 7.  Partial bodies (12 markers) register ambiguously (next one 1.5-1.9x): on the bench's
        # jump with right-arm markers the second-best won, and screening the best only cost
        # 23.7 -> 33.9 mm part MPJPE.  (Session 7: 4 hypotheses cost the jump 5.5 s of 11.7 s.)
        max_hypotheses=2,
        decisive_registration_ratio=2.0,
        # Screening of the yaw hypotheses: 40 iterations, plain squares at Stage 4 (with 40
        # iterations the robust kernel is not converged: 1.4 mm worse at the end).  The winner then
        # gets 100 iterations at Stages 2, 4, 5 and Stage 4's robust kernel as offline: the lock is
        # where the refined output's error comes from (the bootstrap's lock held fixed, 40 markers,
        # 8 s walk / jump / arms and 4 seed-1 sessions: mean refined MPJPE 19.5 -> 17.7 mm; 45
        # instead of 60 chamfer frames 19.6).
        # Stage 2 starts each line search at step 1.0 as offline (SolverConfig.pose_fitting says why).
        # Session 28 (40 markers, the bench's 8 s walk / jump / arms x seeds 0-2, each start alone,
        # against the paper's 0.1): final Stage-2 energy 10.1-20.5 -> 5.7-13.0, the winner's Stage 2
        # in 27-83 instead of 41-109 evaluations; the lock held fixed, mean refined MPJPE 13.64 ->
        # 13.24 mm (5 better, 4 worse), bootstrap wall mean 10.25 -> 9.52 s.
        screening_pose_fitting=replace(c.pose_fitting, lbfgs=replace(c.pose_fitting.lbfgs, max_iterations=40)),
        screening_ik=replace(c.ik, lbfgs=replace(c.ik.lbfgs, max_iterations=40), robust_scale_m=None),
        pose_fitting=replace(c.pose_fitting, lbfgs=replace(c.pose_fitting.lbfgs, max_iterations=100)),
        ik=replace(c.ik, lbfgs=replace(c.ik.lbfgs, max_iterations=100)),
        matching=replace(c.matching, lbfgs=replace(c.matching.lbfgs, max_iterations=40), frames=24),
        # Stage 5's per-marker point choice (placement_selection: a marker may take the point found
        # under the video prior's rotation of its bone) stays on, on all the window's frames: it is most
        # of what the offline budgets add to a 3 s lock.  Session 14, 40 markers, refined MPJPE: the lock
        # held fixed, one start, the 5 takes with the largest first-seconds error: 19.6 mm without it,
        # 17.4 with it (better on all 5), 17.5 on 45 frames, 17.8 with 40-iteration fits, 17.0 under
        # the whole offline config at 3-4x the time; end to end (two starts, upgrades) on 13 takes
        # 15.48 -> 14.37 mm, the bench's walk / jump / arms 10.68 -> 9.59.  It costs two more IK fits:
        # ~4 s of CPU per start on this session's 2 GHz machine (12.8 -> 16.9 s).
    )


def bootstrap_alternative_config() -> SolverConfig:
    """The second bootstrap start: ``fast_bootstrap_config`` with the offline part matching
    (48 frames, 60 iterations instead of 24 and 40)."""
    return replace(fast_bootstrap_config(), matching=SolverConfig().matching)


def upgrade_solver_config() -> SolverConfig:
    """The lock upgrades' staged solver: the offline one screening the best-registered yaw only, with
    the paper's Stage-2 pose prior (``WindowedSolverConfig.upgrade_solver`` says why)."""
    # no track stitching (SolverConfig.track_stitching): the reservoir's frames are not consecutive,
    # so a column's end and the next one's start are not a handover
    c = SolverConfig(max_hypotheses=1, track_stitching=None)
    return replace(c, pose_fitting=replace(c.pose_fitting, pose_weight=PoseFittingConfig().pose_weight))


@dataclass(frozen=True)
class WindowedSolverConfig:
    # Issue 6 "Bootstrap": seconds of markers (+ prior) the offline solver runs on.  3 s rather than
    # 2.5 (session 9, 40 markers, refined MPJPE, with upgrade_growth 1.5; 8 s walk / jump / arms |
    # seed-1 run / squat / turn / walk-2): 11.1 / 14.3 / 16.5 | 21.2 / 14.7 / 16.3 / 16.9 ->
    # 10.4 / 12.1 / 12.5 | 19.6 / 12.2 / 13.2 / 16.3 mm (mean 15.9 -> 13.8).  More poses fix more
    # of the correspondence; 4 s was better still under a fixed lock on the first three (10.2 /
    # 13.3 / 9.9) but a seed-1 turn locked into a wrong minimum (39.7 mm) that no upgrade repaired
    # before its take ended.
    bootstrap_s: float = 3.0
    # Wait up to this many more seconds of markers for video priors covering the bootstrap window
    # (priors within prior_tolerance_s of the newest frame count as covering it).
    prior_wait_s: float = 3.0
    prior_tolerance_s: float = 0.25
    # Beyond the paper (speed): the bootstrap window is decimated to this rate (paper: 30 Hz markers).
    bootstrap_rate_hz: float = 30.0
    # Beyond the paper: a take that ends before the bootstrap locked (shorter than bootstrap_s) is
    # bootstrapped at its end, where no frame waits on the result any more - at up to this rate, not
    # bootstrap_rate_hz.  The BTK clinical gait capture (1.9 s at 100 Hz, 20% of its samples
    # occluded): at 30 Hz both starts fit the markers 17.5 / 19.0 mm and the recording was 97.1 mm
    # MPJPE; at 100 Hz 7.8 / 8.1 mm and 19.6 mm, in 16.2 s.
    end_bootstrap_rate_hz: float = 120.0
    # The offline staged solver used for (re-)bootstraps.
    bootstrap_solver: SolverConfig = field(default_factory=fast_bootstrap_config)
    # Beyond the paper: the bootstrap also solves the window under each of these configs, in the
    # worker process beside the first (2 cores: about the wall time of one), and locks the result whose
    # markers fit best (most markers placed, then the lowest Stage-5 fit) - multiple hypotheses, as
    # Stage 1's yaws, over the part matching's start.  On 3 s the correspondence is weakly observed
    # and the solver lands in different minima from slightly different starts (part matching on 24
    # or 48 frames: first-4-s refined MPJPE 15.8 vs 8.4 mm on one take, 18.4 vs 22.6 on another).
    bootstrap_alternatives: tuple[SolverConfig, ...] = field(default_factory=lambda: (bootstrap_alternative_config(),))
    # Solve the bootstrap alternatives and the background lock upgrades in a warm worker process
    # (``solve_worker``), started with the solver.  False: on threads of this process, which share
    # its interpreter lock - on the 2-core CPU (demo walk, 40 markers) one start alone 18.5 s, two
    # starts on two threads 50.2 s wall, with the second in a warm worker process 22.2 s.
    worker_process: bool = True
    # Energy terms shared with the offline Stage 4 (paper: lambda_M 1, delta 9.5 mm).  Beyond the
    # paper, lambda_Theta = 2 instead of 0.1: the per-frame solves are exact where offline L-BFGS
    # stops early, and with the paper's weight they over-fit the markers along poorly observed
    # directions (40-marker walk / jump / arms refined 14.9 / 18.5 / 18.7 -> 13.7 / 16.1 / 15.8 mm
    # with 1).  Session 22, 1 -> 2 -> 3 (own script over ``stream_solve``, the bench's full-suite
    # sessions, walk / jump / arms each; recording MPJPE mm and MPJVE mm/s at 20 / 30 / 40 / 50
    # markers): 26.65 / 12.00 / 7.43 / 8.01 -> 26.26 / 11.33 / 7.14 / 7.95 -> 26.06 / 11.19 / 7.00 /
    # 8.09, MPJVE 82.4 / 55.8 / 33.6 / 20.2 -> 84.2 / 58.2 / 33.4 / 20.3 -> 85.7 / 60.0 / 33.6 / 20.6
    # (offline 86 / 63 / 34 / 25); fixed-lag refined 33.74 / 15.68 / 9.48 / 10.97 -> 32.70 / 16.04 /
    # 9.14 / 10.91 -> 32.16 / 16.00 / 8.98 / 10.10.  2: a better recording on all 12 sessions, the
    # video's jitter not yet above the offline MPJVE.  The facet normal, as the staged solver's IK
    # (its config explains).
    ik: InverseKinematicsConfig = InverseKinematicsConfig(pose_weight=2.0, offset_model="face_normal")
    # Issue 6 "Steady state": Gauss-Newton iterations of the per-frame estimate (and of the
    # bootstrap window's frames).  None: 1 at marker rates >= ``one_iteration_from_hz``, else 2.
    # Measured (session 19, 40 markers, own script over ``stream_solve``; refined MPJPE mm, estimate
    # MPJPE mm / MPJVE mm/s, 2 -> 1 iteration): 120 Hz bench walk / jump (upgrades off) refined
    # 8.58 / 16.39 -> 8.51 / 16.28, estimate MPJVE 145 / 148 -> 129 / 139, steady state 126 / 107 ->
    # 189 / 162 frames/s.  30 Hz (the bench's three + five ``sample make`` takes, upgrades on):
    # refined the same (9.47 -> 9.46, 14.87 -> 14.82 mean), but the estimate of fast motions worse
    # with one (jumps 9.55 / 14.41 -> 9.77 / 14.59 mm, MPJVE 56 / 42 -> 61 / 49; run 64 -> 70): 33 ms
    # between frames leave the warm start further from the answer.  A 30 Hz stream needs 30 frames/s.
    estimate_iterations: int | None = None
    one_iteration_from_hz: float = 60.0
    # Warm start the estimate by constant-velocity extrapolation of the previous two frames.
    extrapolate: bool = False
    # Beyond the paper: Cauchy IRLS scale (metres) of the per-frame solves.  A few markers on a
    # wrong surface point (the bootstrap saw the arms down; now they go up) would drag the whole
    # limb with least squares, every marker on it then looks slipped and the fit collapses; with
    # the robust kernel the pose follows the majority and only the wrong markers stand out (and
    # are re-assigned as slipped).  None = plain least squares.
    # (Tuned on the 40-marker walk/jump/arms sessions: 0.04 / 0.02 / 0.01 / 0.005 m gave refined
    # MPJPE 20.0 / 19.6 / 18.9 / 18.5 mm; 0.01 keeps typical 3-5 mm residuals near full weight.)
    robust_scale_m: float | None = 0.01
    # Levenberg-Marquardt damping (relative to the diagonal of the normal equations).
    damping: float = 1e-3
    # Issue 6: fixed lag (frames) after which a frame is final ("refined").
    lag_frames: int = 10
    # Frames finalised per smoothing pass (the pass runs every hop frames).  Beyond the paper (speed):
    # a pass costs ~(context + lag + hop) frames of work, so hop 10 does ~1/3 less per finalised
    # frame than hop 5 (2.4 vs 3.5 ms CPU at 40 markers) for +hop/rate of refined latency.
    hop_frames: int = 10
    # Already-final frames kept fixed at the start of each smoothing window (continuity).
    context_frames: int = 2
    # Gauss-Newton iterations per smoothing pass (warm-started from the previous pass).
    refine_iterations: int = 1
    # Acceleration weight of the smoothing pass (the offline IK's smoothness term, at
    # ik.smoothness_reference_hz; beyond the paper).  Session 17 (with smoothness_target "bones";
    # bench walk / jump / arms at 30 Hz, 40 markers, upgrades off, refined MPJPE mm / MPJVE mm/s,
    # means): 0.01 10.06 / 35.6, 0.02 10.09 / 33.9, 0.04 10.15 / 32.8 (the jump's wrists worse).
    smoothness_weight: float = 0.02
    # What the acceleration term smooths: "bones" = the pelvis position and each bone's vector
    # (joint minus parent joint), or "joints" = every joint's world position (the offline IK's
    # term).  Bones, because with world joints a well-observed body's real acceleration (a jump's
    # landing) is smoothed away on its poorly observed limbs: the solve swings an arm against the
    # trunk to keep the wrist's world path smooth (bench jump: right wrist 111 mm off at the
    # landing, the estimate 23 mm).  Session 17 (as above, weight 0.01): refined MPJVE walk / jump
    # / arms 37.5 / 51.6 / 31.8 -> 34.0 / 41.1 / 31.5 mm/s, MPJPE 10.22 -> 10.06 mm.  Bones in each
    # parent's frame (no rotation of the trunk reaching the limbs) smoothed less: 38.2 (0.01).
    smoothness_target: str = "bones"
    # Conjugate-gradient iterations per smoothing step (block-preconditioned).  Session 16: 25 do
    # not reach CG's tolerance (10 leave steps up to 0.15 rad from 25's), but an exact solve of the
    # same normal equations (dense) gave the same output (120 Hz walk: refined 8.77 vs 8.78 mm,
    # MPJVE 33.3 vs 33.8 mm/s), and a block-banded Cholesky in numpy costs more than the CG (~40 ms
    # vs ~15 ms for inverse + CG on a 20-frame window).
    cg_iterations: int = 25
    # Change handling (issue 6): an unassigned marker seen this many frames gets a surface point.
    new_track_frames: int = 10
    # Beyond that: a new column whose first sample is where a marker that ended within max_gap_s (a
    # column no longer seen, a tracker slot whose track changed) would be now - its last residual,
    # in the frame of its face, carried on this frame's pose - within max_handover_m takes that
    # marker's point at once (track_stitching's handover, causal; the offline solve joins columns
    # the same way).  Without it an unlabelled export's fragments wait new_track_frames and then get
    # a point from those frames alone.  None = off.
    handover: StitchConfig | None = StitchConfig()
    # A marker whose residual exceeds this for slip_frames visible frames is re-assigned.
    slip_threshold_m: float = 0.03
    slip_frames: int = 15
    # More than this fraction of the visible assigned markers over the slip threshold in one frame
    # is a pose failure, not slipping markers: no re-assignment.
    slip_storm_fraction: float = 0.25
    # An estimate with a mean residual above this is retried from the frame's pose prior with
    # recover_iterations Gauss-Newton iterations (the better of the two is kept).
    recover_threshold_m: float = 0.02
    recover_iterations: int = 8
    # Mean residual above this for degrade_s seconds -> re-bootstrap.
    degrade_threshold_m: float = 0.04
    degrade_s: float = 0.5
    # Periodic correspondence re-check on the recent window (0 = never).
    recheck_period_s: float = 2.0
    recheck_frames: int = 48
    # A re-checked point replaces the current one when its mean distance is this much smaller.
    recheck_improvement_m: float = 0.003
    # Beyond the paper (latency): a re-check is Stage 3 on recheck_samples frames spread over the
    # recent recheck_frames, recheck_group_markers markers at a time, one group per smoothing hop,
    # run by ``refine_ready`` half a hop after a pass (after that frame's estimate went out).
    # Session 20, 120 Hz bench walk, 40 markers: the whole re-check in one frame took 60-100 ms
    # (48 frames; every marker) and held the stream - the refined results behind it came 80-120 ms
    # past their lag, twice per 2 s (refined latency p95 = lag + 59 ms; the seconds without a
    # re-check lag + 7-12 ms).  One group (10 markers, 24 frames) takes ~23-35 ms, about a hop's
    # slack at 120 Hz (10 frames = 83 ms: ~31 ms of estimates + ~25-28 ms pass).
    recheck_samples: int = 24
    recheck_group_markers: int = 10
    # Beyond the paper: a joint whose rotation moves less than this many markers' worth of skin
    # weight (sum over markers of the skinning weight of the joint's subtree) gets its pose prior
    # weighted this much more (40-marker walk: the right ankle swung 0.7 rad off the prior; refined
    # MPJPE 16.1 -> 14.9 mm).
    unsupported_joint_support: float = 0.5
    unsupported_joint_prior_scale: float = 100.0
    # Beyond the paper: the 2-4 s bootstrap sees few poses, so its shape and correspondence are
    # worse than the offline solver's on the whole take.  Refined frames are kept in a reservoir
    # spread evenly over the take (at most upgrade_frames; memory stays bounded), and each time
    # the take has grown by upgrade_growth x since the last lock, the staged solver runs on the
    # reservoir and may replace the lock ("lock upgrade", see _finish_upgrade).  0 frames = never.
    # 192 rather than 96 (40 markers, refined MPJPE, 8 s walk / jump / arms and seed-1 run / squat /
    # turn / walk, 15 s walk): 12.9 / 18.0 / 15.6, 24.4 / 17.0 / 18.8 / 16.5, 22.8 ->
    # 12.0 / 14.2 / 16.5, 24.0 / 17.0 / 19.1 / 15.6, 22.1 mm.  The staged solver's lock improves with
    # its frames (15 s walk, that lock held fixed: 120 / 225 frames 24.4 / 21.5 mm, the whole
    # take 20.1); an upgrade costs ~30-60 s instead of ~25-30 (a worker thread in live use).
    upgrade_frames: int = 192
    # 1.5 rather than 2 (session 9, with the 3 s bootstrap): the first upgrade lands at 4.5 s of an
    # 8 s take instead of 6 s (the numbers under bootstrap_s); mean over the 7 sessions 14.5 -> 13.8 mm.
    upgrade_growth: float = 1.5
    # Run the upgrade on a worker thread while estimates go on (live streams: no ~5 s stall);
    # False keeps replays deterministic (the result lands at a fixed frame).
    upgrade_in_background: bool = False
    # The staged solver of the upgrades (None = bootstrap_solver): the offline solver itself - its full
    # budgets and its Stage-2 shape prior 0.1 (section "Mocap Solving" has 1; see pose_fitting) -
    # screening only the best-registered yaw hypothesis.  Full budgets: (40 markers, refined MPJPE)
    # 20 s walk / jump 18.2 / 25.5 mm with the bootstrap's short budgets, 16.6 / 20.1 with the full
    # ones (offline 16.0 / 12.9); ~15-20 s per upgrade instead of ~5 (the worker process in live use).
    # One yaw: the reservoir spans the take, its registration is reliable, and a wrong pick cannot
    # do harm - an upgrade is adopted only when the reservoir fits better under it (_finish_upgrade);
    # session 9: the same refined MPJPE to 0.1 mm on 7 sessions, upgrades 32-48 -> 22-31 s.
    # Full bodies: shape prior 0.1 rather than the bootstrap's 1 (partial bodies keep 1: _upgrade_config;
    # session 26, own script over stream_solve, the
    # bench's 8 s walk / jump / arms x seeds 0-2 at 20 / 30 / 40 / 50 markers, 36 sessions, the
    # recording's MPJPE): 27.25 / 14.03 / 9.72 / 9.12 -> 27.29 / 12.80 / 9.94 / 8.93 mm, mean 15.03
    # -> 14.74 (better on 17, worse on 11); fixed-lag refined 18.53 -> 18.34.  Session 13 had kept 1
    # here (40 markers, before the revisions and the take-end upgrade, whose reservoir spans the
    # whole take: 13 sessions 14.85 vs 14.74, the bench's three 11.02 vs 11.63).
    # Stage-2 pose prior: the paper's 1, as the bootstrap, not the offline 2 (session 29, the bench's replay, 36 sessions,
    # recording MPJPE at 20 / 30 / 40 / 50 markers: 24.4 / 13.1 / 9.2 / 8.6 mm with 1, 25.0 / 13.3 / 8.8 / 8.9 with 2).
    upgrade_solver: SolverConfig | None = field(default_factory=upgrade_solver_config)
    # Longest time gap (s) the upgrade's Stage 2 may interpolate its start across (see _solve_upgrade).
    upgrade_max_interpolation_s: float = 0.35
    # Adopt an upgrade when the reservoir re-solved under it fits better than this times the
    # reservoir re-solved under the current lock (upgrade_check_iterations per frame each).
    upgrade_accept_ratio: float = 1.0
    upgrade_check_iterations: int = 4
    # Beyond the paper: when a lock upgrade is adopted, the frames already refined under the old
    # lock (up to revise_s seconds back; memory stays bounded) are solved again under the new one
    # - the same estimate and smoothing pass, warm-started from their refined poses - and come out
    # as 'revised' results, which recordings keep over the 'refined' ones.  The refined output of
    # the first seconds runs on the bootstrap's lock from 3 s of markers; the upgrades' locks from
    # more of the take fit it much better.  Session 21 (own script, the bench's 30 Hz walk / jump /
    # arms, 40 markers, MPJPE mm): refined 10.22 / 10.34 / 7.82, those frames re-solved under the
    # final lock 8.35 / 6.31 / 7.78, offline 7.01 / 7.68 / 7.02.  0 = no revisions.
    revise_s: float = 30.0
    # Gauss-Newton iterations of a revised frame's estimate under the new lock (its refined pose
    # under the old lock is the start).
    revise_iterations: int = 4
    # Live (upgrade_in_background) without a worker process (worker_process False): one hop of
    # revision every this many hops of stream.  A step costs a bit more than a smoothing pass (~30
    # ms for 10 frames here) and stalls the frames arriving meanwhile.  Session 21, 120 Hz walk, 40
    # markers, on the capture clock, per second while revising: one step every hop put the solver
    # over its capacity (estimate p95 15 -> 540 ms), every third hop 26-44 ms, every sixth 17-29 ms
    # (without revisions 16-19 ms); a sixth revises 20 frames per second of stream, the rest when
    # the take ends (flush).  With the worker process (the default) the whole revision runs there,
    # in one job ahead of the next upgrade (~0.1 s of its core per second of ring).
    revise_every_hops: int = 6
    # Revised frames handed out per ``refine_ready`` call once the worker's revision is back (they
    # come back all at once; a caller publishes each).
    revise_emit_frames: int = 60
    # Beyond the paper: when the take ends (``flush``), the ring (the last ``revise_s``) is revised
    # once more under the final lock with the offline IK's mean-offset pose prior
    # (``regularizers.mean_pose_offset_energy``) in the form a per-frame solve can take: each frame's
    # pose-prior target is its video prior minus the ring's mean body-pose difference to the video
    # prior.  A limb with few markers slides its points and its pose together at little cost in the
    # markers; the per-frame prior cannot choose the place along that valley without the video's
    # jitter, the video's error averaged over the take can.  Session 23 (own script over
    # ``stream_solve``, the bench's full-suite walk / jump / arms; recording MPJPE mm without -> with):
    # 20 markers 31.99 / 28.91 / 17.88 -> 31.46 / 28.72 / 17.93, 30 markers 11.72 / 12.07 / 10.19 ->
    # 10.69 / 11.75 / 9.90, 40 markers 7.79 / 5.99 / 7.64 -> 7.24 / 5.78 / 7.45 (offline 22.05 / 18.18
    # / 16.66, 10.49 / 10.20 / 9.77, 6.72 / 7.77 / 7.62), MPJVE a little lower.  Part of it is the
    # revision itself (every frame under the final lock; frames refined after the last adoption are
    # revised too): without the shift 31.91 / 28.86 / 17.82, 11.08 / 12.07 / 10.20, 7.77 / 5.98 / 7.55.
    # Applying the shift 3 times: 30 / 40 markers better still (10.72 / 11.62 / 9.79, 7.03 / 5.54 /
    # 7.34), 20 markers worse (30.98 / 29.10 / 18.99).  The same term run causally in the live
    # estimate (an exponential mean of the refined frames' differences shifting the next frames'
    # targets) did not help (gain 3: 30-marker walk fixed-lag 14.42 -> 14.37 mm) or diverged (gain 36,
    # the offline weight's equivalent): under the bootstrap's lock that mean is the lock's error.
    # Costs one revision of the ring when the take ends (30 s of 120 Hz: ~8 s in the worker process).
    revise_at_end: bool = True
    # Beyond the paper: when the take ends (``flush``), one more lock upgrade on the reservoir (now
    # spread over the whole take) before the end-of-take revision, when the take grew by this
    # factor since the last lock upgrade started (0 = never).  Judged like every upgrade (adopted
    # only when the reservoir fits better under it), synchronous (the worker process solves it when
    # there is one; the revision waits for it).  A live stop skips it (``end_upgrades``); an end of
    # stream runs it.  Session 24 (own script over ``stream_solve``, the bench's full-suite walk /
    # jump / arms, recording MPJPE mm without -> with; this machine, where 7 of the 12 sessions kept
    # the bootstrap's lock through the take): 20 markers 31.51 / 27.34 / 17.75 -> 23.50 / 26.88 /
    # 17.75, 30 markers 12.15 / 10.92 / 11.65 -> 12.15 / 10.92 / 14.39, 40 markers 8.63 / 5.75 / 9.95
    # -> 8.63 / 5.75 / 6.28, 50 markers 7.49 / 8.69 / 6.48 -> 7.49 / 5.86 / 6.48: four better, one
    # worse (the 30-marker arms: fit 1.44 -> 1.30 mm under the new lock, MPJPE up), seven unchanged
    # (refused, or no better).  Costs one upgrade solve at the end (8 s takes at 30 Hz: 10-17 s).
    upgrade_at_end_growth: float = 1.1
    # Beyond the paper: before the end-of-take revision, Stage 3 once more on the whole ring (every
    # marker's surface point searched anew over the whole allowed surface, its mean distance over up
    # to ``CorrespondenceConfig.frames`` of the ring's frames) under the ring's poses revised under the
    # final lock - the paper's Stage 5 (repeat Stages 3-4) on the take's frames rather than on the
    # reservoir's or the re-checks' recent ones.  Session 31 (own scripts over ``stream_solve``, the
    # bench's walk / jump / arms x seeds 0-2): the lock's points against the truth (rest-pose distance
    # to the true attachment, 30 markers) were 14.0 mm off on average, the offline solver's 12.3; with
    # this 11.0 (median unchanged, 8.6: it moves the few markers that sat far off).  Recording MPJPE
    # at 20 / 30 / 40 / 50 markers 24.40 / 13.06 / 9.24 / 8.61 -> 24.45 / 12.85 / 9.11 / 8.40 mm (offline
    # 24.76 / 11.70 / 9.80 / 8.33): 23 of the 27 sessions at 30-50 markers better, none worse by over
    # 0.05 mm; at 20 markers 4 better, 3 worse (the points are 9-24 mm off there); 12-marker parts
    # (seed 0, left leg / right arm) 4 of 6 better.  A local search (Stage 5's ``refine_radius_m``
    # around each point) instead: 30 markers 13.38 (4 worse); a second round changes nothing.  Costs
    # one more revision of the ring and one Stage 3 when the take ends.
    reassign_at_end: bool = True
    # Ring sizes: recent frames kept for re-assignment (frames), priors kept (messages).
    history_frames: int = 64
    prior_buffer: int = 512

    def __post_init__(self):
        if self.upgrade_at_end_growth < 0:
            raise ValueError("upgrade_at_end_growth >= 0 is required (0 = no upgrade at the take's end)")
        if self.revise_s < 0 or self.revise_iterations < 1 or self.revise_every_hops < 1:
            raise ValueError("revise_s >= 0, revise_iterations >= 1 and revise_every_hops >= 1 are required")
        if self.bootstrap_s <= 0 or self.lag_frames < 0 or self.hop_frames < 1 or self.context_frames < 0:
            raise ValueError("bootstrap_s > 0, lag_frames >= 0, hop_frames >= 1, context_frames >= 0 are required")
        if self.recheck_samples < 2 or self.recheck_group_markers < 1:
            raise ValueError("recheck_samples >= 2 and recheck_group_markers >= 1 are required")
        if (self.estimate_iterations is not None and self.estimate_iterations < 1) or self.refine_iterations < 0:
            raise ValueError("estimate_iterations >= 1 (or None) and refine_iterations >= 0 are required")
        if self.smoothness_target not in ("bones", "joints"):
            raise ValueError(f"smoothness_target must be bones or joints, got {self.smoothness_target!r}")
        if self.ik.offset_model not in ("smooth_normal", "face_normal", "distance"):
            raise ValueError(f"ik.offset_model must be smooth_normal, face_normal or distance, got {self.ik.offset_model!r}")


@dataclass
class WindowResult:
    """One solved frame.  poses (72,) world-frame AMASS axis-angle (yaw folded into the root);
    trans (3,), joints (24,3) metres; betas (B,); residual_m: mean distance of the visible assigned
    markers to their predicted positions; kind 'estimate', 'refined' or 'revised' (a refined
    frame solved again after a lock upgrade, ``WindowedSolverConfig.revise_s``, or at the take's end,
    ``revise_at_end``)."""

    stamp_ns: int
    frame_index: int
    kind: str
    poses: np.ndarray
    trans: np.ndarray
    joints: np.ndarray
    betas: np.ndarray
    residual_m: float
    labels_version: int


@dataclass
class MarkerLabelState:
    """Current marker -> surface assignment.  face_ids (M,) (-1 unassigned), bary (M,3),
    parts: per marker the dominant joint name ('' unassigned); version increments on change."""

    version: int
    face_ids: np.ndarray
    bary: np.ndarray
    parts: list[str]
    marker_offset_m: float


class _Frame:
    """Per-frame state shared by the pending window, the context and the history rings."""

    __slots__ = ("stamp", "index", "markers", "visible", "theta", "trans", "prior", "prior_weight", "residual", "joints",
                 "video_prior", "identity")

    def __init__(self, stamp, index, markers, visible):
        self.stamp = int(stamp)
        self.index = int(index)
        self.markers = markers
        self.visible = visible
        self.theta = np.zeros(N_POSE)
        self.trans = np.zeros(3)
        self.prior = np.zeros(N_POSE)
        self.prior_weight = 1.0
        self.residual = math.nan
        self.joints = None
        self.video_prior = False  # ``prior`` is the video's (else the previous frame's pose)
        self.identity = None  # (M,) which marker each column held then (WindowedSolver._identity)

    # what a revision reads of a refined frame
    REVISED_FROM = ("stamp", "index", "markers", "visible", "theta", "trans", "prior")

    @classmethod
    def from_arrays(cls, arrays: dict) -> list["_Frame"]:
        """Frames from ``REVISED_FROM`` arrays stacked over frames."""
        frames = []
        for i in range(len(arrays["stamp"])):
            f = cls(arrays["stamp"][i], arrays["index"][i], arrays["markers"][i], arrays["visible"][i])
            f.theta, f.trans, f.prior = arrays["theta"][i].copy(), arrays["trans"][i].copy(), arrays["prior"][i]
            frames.append(f)
        return frames


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcasting); np.cross's generality costs ~0.3 ms per call here."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _triangle_frames(corners: np.ndarray) -> np.ndarray:
    """numpy twin of ``inverse_kinematics.triangle_frames``: (..., 3 corners, 3) -> (..., 3, 3)
    rows = first edge direction, in-plane perpendicular, unit normal."""
    e1 = corners[..., 1, :] - corners[..., 0, :]
    n = _cross(e1, corners[..., 2, :] - corners[..., 0, :])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    e1 = e1 / np.maximum(np.linalg.norm(e1, axis=-1, keepdims=True), 1e-12)
    return np.stack([e1, n[..., [1, 2, 0]] * e1[..., [2, 0, 1]] - n[..., [2, 0, 1]] * e1[..., [1, 2, 0]], n], axis=-2)


_UNIT_AXES = np.eye(3)


def lever_jacobian(levers: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Jacobian of points rotating about the joints: levers (B,K,24,3) the vector from joint j to
    point k (zero where j does not move k), axes (B,24,3,3) each joint's world rotation axes per
    local axis-angle component -> (B,K,3,72), block j = -[lever_kj]x axes_j.

    -[c]x R is linear in c: one (9,3) map per joint, applied to every point's lever by a single
    batched matmul instead of elementwise cross products over the (B,K,24,3,3) broadcast: B = 40
    frames, 40 markers 15.4 -> 7.9 ms (microbenchmark); a captured 22-frame window's whole
    linearisation 9.5-11.0 -> 8.0-10.8 ms; one frame the same (~0.15 ms)."""
    B, K = levers.shape[:2]
    cols = np.swapaxes(axes, -1, -2)  # (B,24,k,3): the columns of each joint's axes
    maps = np.empty(axes.shape[:2] + (3, 3, 3))  # (B,24,r,k,q) = (-[e_q]x axes_j)[r,k]
    for q in range(3):
        maps[..., q] = -np.swapaxes(_cross(_UNIT_AXES[q], cols), -1, -2)
    out = maps.reshape(B, 24, 9, 3) @ np.swapaxes(levers, 1, 2).swapaxes(-1, -2)  # (B,24,9,K)
    return out.reshape(B, 24, 3, 3, K).transpose(0, 4, 2, 1, 3).reshape(B, K, 3, 72)


def rotation_matrices(aa: np.ndarray) -> np.ndarray:
    """Rodrigues' formula in float64 numpy: axis-angle (...,3) -> (...,3,3) (the solver's inner loop
    converts 24 small rotations per frame; torch's per-call overhead dominated it)."""
    phi = np.linalg.norm(aa, axis=-1)[..., None, None]
    K = np.zeros(aa.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -aa[..., 2], aa[..., 1], -aa[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = aa[..., 2], -aa[..., 1], aa[..., 0]
    small = phi < 1e-8
    safe = np.where(small, 1.0, phi)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_vector(rot: np.ndarray) -> np.ndarray:
    """(3,3) rotation -> axis-angle (3,) (norm <= pi), via the unit quaternion (Shepperd's branch
    choice: stable near 0 and pi).  Scalar float64 math: the per-frame outputs convert one matrix
    at a time, where torch's per-call overhead was ~0.6 ms."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(rot, dtype=np.float64).tolist()
    tr = r00 + r11 + r22
    k = max(range(4), key=(tr, r00, r11, r22).__getitem__)
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + r11 - r00 - r22, 0.0))
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + r22 - r00 - r11, 0.0))
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(x * x + y * y + z * z)
    f = 2.0 * math.atan2(n, w) / n if n > 1e-12 else 2.0 / max(w, 1e-12)
    return np.array([x * f, y * f, z * f])


def rotation_vectors(rot: np.ndarray) -> np.ndarray:
    """Batched ``rotation_vector``: (B,3,3) -> (B,3) float64 (one torch call for the batch: the
    frames held at a lock change, up to revise_s seconds of them, are re-expressed at once)."""
    return matrix_to_axis_angle(torch.from_numpy(np.ascontiguousarray(rot, dtype=np.float64))).numpy()


def wrap_rotation_vector(aa: np.ndarray) -> np.ndarray:
    """Same rotations with every axis-angle (...,3) of norm <= pi (additive updates can leave it)."""
    n = np.linalg.norm(aa, axis=-1, keepdims=True)
    return np.where(n > math.pi, aa * (n - 2 * math.pi) / np.maximum(n, 1e-12), aa)


def nearest_equivalent(aa: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The representation of rotation ``aa`` (...,3) (itself or the one 2 pi along its axis
    backwards) nearest to ``ref``: the pose prior compares axis-angle vectors, which must not jump
    by 2 pi when the root turns past pi."""
    n = np.linalg.norm(aa, axis=-1, keepdims=True)
    alt = aa * (n - 2 * math.pi) / np.maximum(n, 1e-12)
    use = np.linalg.norm(alt - ref, axis=-1, keepdims=True) < np.linalg.norm(aa - ref, axis=-1, keepdims=True)
    return np.where(use & (n > 1e-6), alt, aa)


def bone_vector_operator(parents: np.ndarray) -> np.ndarray:
    """(3J, 3J) matrix taking stacked joint positions (J*3,) to the root's position and each
    bone's vector (joint minus parent joint), in the same stacking."""
    A = np.eye(len(parents))
    for j, p in enumerate(parents):
        if p >= 0:
            A[j, p] = -1.0
    return np.kron(A, np.eye(3))


def right_jacobian_so3(theta: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at axis-angle theta (...,3) -> (...,3,3):
    R(theta + d) ~= R(theta) exp(J_r(theta) d)."""
    phi = np.linalg.norm(theta, axis=-1)[..., None, None]
    K = np.zeros(theta.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -theta[..., 2], theta[..., 1], -theta[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = theta[..., 2], -theta[..., 1], theta[..., 0]
    small = phi < 1e-6
    safe = np.where(small, 1.0, phi)
    a = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) - a * K + b * (K @ K)

PriorRow = tuple  # (stamp_ns, global_orient (3,), body_pose (23,3), betas (B,), valid, camera_frame, confidence)


def world_prior_at(rows: list, stamps: np.ndarray, up_axis: str, num_betas: int) -> tuple[BodyPrior, np.ndarray, bool]:
    """World prior (up to yaw) at marker ``stamps`` (T,) from received prior rows (``PriorRow``).

    Only rows stamped at or before the last stamp are used (deterministic in lockstep: later priors
    may or may not have arrived); with none, the earliest valid later row; with no valid row at all,
    a neutral upright prior.  Returns (prior (T frames), shape prior (B,), has_prior)."""
    stamps = np.asarray(stamps, dtype=np.int64)
    last = int(stamps[-1])
    use = [p for p in rows if p[0] <= last and p[4]]
    if not use:
        use = [p for p in rows if p[4]][:1]
    if not use:
        return neutral_prior(len(stamps), up_axis, num_betas, stamps), np.zeros(num_betas), False
    nb = min(len(r[3]) for r in use)
    cam = BodyPrior(
        root_orient=np.stack([r[1] for r in use]),
        body_pose=np.stack([r[2] for r in use]),
        betas_per_frame=np.stack([r[3][:nb] for r in use]),
        valid=np.ones(len(use), dtype=bool),
        confidence=np.array([r[6] for r in use]),
        stamps_ns=np.array([r[0] for r in use], dtype=np.int64),
        frame="camera" if use[-1][5] else "world",
    )
    world, shape = prepare_prior(cam, up_axis, stamps, 0.0)
    return world, shape, True


def label_markers(model, chamfer_model, markers: np.ndarray, visible: np.ndarray, prior: BodyPrior, shape_prior: np.ndarray,
                  up_axis: str, config: SolverConfig = SolverConfig()) -> tuple[MarkerAttachment, list[str], dict]:
    """Marker labels from segmentation + part matching alone (the ``segmenter`` node): the offline
    Steps 1-2, then Stage 3 on the matched body (prior pose at the matched yaw, translation, shape).

    markers (T,M,3) metres NaN missing; visible (T,M); prior: world prior at these frames.
    Returns (attachment, per-marker joint names, diagnostics)."""
    from uuomocap.solver_core.part_matching import match_markers_to_part
    from uuomocap.solver_core.segmentation import segment_markers

    up = up_tensor(up_axis)
    vis = np.asarray(visible, dtype=bool) & np.isfinite(markers).all(axis=2)
    clusters = segment_markers(markers, vis, config.segmentation)
    mk = torch.as_tensor(markers, dtype=torch.float32)
    vis_t = torch.as_tensor(vis)
    root = torch.as_tensor(prior.root_orient, dtype=torch.float32)
    body = torch.as_tensor(prior.body_pose, dtype=torch.float32)
    nb = min(len(shape_prior), model.num_betas, chamfer_model.num_betas)
    beta_prior = torch.as_tensor(np.asarray(shape_prior)[:nb], dtype=torch.float32)
    match_cfg = replace(config.matching, yaw_starts_deg=tuple(config.yaw_hypotheses_deg))
    match = match_markers_to_part(chamfer_model, mk, vis_t, root, body, beta_prior, clusters, up, match_cfg, config.force_full_body)
    params = BodyParams(root, body, torch.as_tensor(match.trans, dtype=torch.float32),
                        torch.as_tensor(match.betas, dtype=torch.float32), torch.tensor(float(match.yaw)))
    allowed = None if match.full_body else part_vertex_ids(model, match.joints)
    att = find_marker_surface_points(model, mk, vis_t, params, up, allowed, config.correspondence)
    diag = {"clusters": int(clusters.max()) + 1, "full_body": bool(match.full_body),
            "part_joints": [model.joint_names[j] for j in match.joints], "yaw_deg": math.degrees(match.yaw) % 360.0}
    return att, marker_part_names(model, att), diag


def needs_worker(config: WindowedSolverConfig) -> bool:
    """Whether a solver under this config solves in a worker process (second bootstrap start,
    background lock upgrades)."""
    return bool(config.worker_process and (config.bootstrap_alternatives or config.upgrade_in_background))


def start_worker(model, chamfer_model, config: WindowedSolverConfig):
    """The worker process a ``WindowedSolver`` under this config needs (None when it needs none),
    started now: a driver starts it before the take (its imports take ~3-6 s on 2 cores) and hands
    it to the solver as ``worker=``."""
    if not needs_worker(config):
        return None
    from uuomocap.solver_core.solve_worker import StagedSolveWorker

    return StagedSolveWorker(model, chamfer_model or model)


def bootstrap_starts_summary(stats: dict) -> str:
    """'1.23 / failed mm, #1 locked': each bootstrap start's Stage-5 marker fit and the one locked
    ('' before a bootstrap with starts)."""
    fits = stats.get("bootstrap_start_fits_mm") or []
    if not fits:
        return ""
    return (" / ".join("failed" if f is None else f"{f:.2f}" for f in fits)
            + f" mm, #{(stats.get('bootstrap_start_chosen') or 0) + 1} locked")


def take_end_summary(stats: dict, revised_frames: int) -> str:
    """What the take's end did (lock upgrade, re-assigned markers, revised frames), or '' when it
    did neither: the reason a take's last frames came late."""
    if "upgrade_at_end_s" not in stats and "revise_at_end_s" not in stats:
        return ""
    upgrade = "%.1f s" % stats["upgrade_at_end_s"] if "upgrade_at_end_s" in stats else "skipped"
    return (f"lock upgrade {upgrade}, {stats.get('reassigned_at_end', 0)} markers re-assigned, {revised_frames} frames revised "
            f"in {stats.get('upgrade_at_end_s', 0.0) + stats.get('revise_at_end_s', 0.0):.1f} s")


class WindowedSolver:
    """Streaming solver: ``add_prior`` / ``add_markers`` in capture order, ``flush`` at the end.

    model: output body model (IK, correspondence); chamfer_model: low-resolution model for the
    bootstrap's chamfer stages (None = model); up_axis: capture world up ('+z'...); rate_hz:
    nominal marker rate (None: estimated from the stamps of the bootstrap window); worker: a
    ``solve_worker.StagedSolveWorker`` on the same models started earlier (a node starts it before
    the take: ~6 s of imports on the 2-core CPU), owned by the solver from here on (None: the solver
    starts its own when ``worker_process`` needs one).
    """

    def __init__(self, model, config: WindowedSolverConfig = WindowedSolverConfig(), up_axis: str = "+z",
                 rate_hz: float | None = None, chamfer_model=None, worker=None):
        self.model = model
        self.chamfer_model = chamfer_model or model
        self.config = config
        self.up_axis = up_axis
        self.up = up_tensor(up_axis)
        self.rate_hz = rate_hz
        # The solver multiplies thousands of tiny matrices per second; OpenBLAS's worker threads
        # make each of them ~100x slower on a busy CPU (measured: 15 ms vs 0.05 ms for a 75x120
        # product), so BLAS runs single-threaded in this process from here on.
        threadpool_limits(1, user_api="blas")
        preload_lazy_imports()  # before the stream, not inside the first bootstrap (~3.5 s)
        self.r_wc = camera_to_world_rotation(up_axis)
        # Stage 3's face table, built once (1.3 ms per re-check group otherwise)
        self._vertex_faces = vertex_face_table(model.faces, model.v_template.shape[0])
        self._priors: deque = deque(maxlen=config.prior_buffer)
        self._prior72: deque = deque(maxlen=config.prior_buffer)
        self._first_valid_prior: int | None = None  # stamp of the first valid prior received
        self.stats: dict = {"frames": 0, "bootstraps": 0, "rebootstraps": 0, "new_tracks": 0, "slips": 0,
                            "rechecks": 0, "reassigned": 0, "bootstrap_seconds": []}
        self.timing = {"estimate_s": 0.0, "refine_s": 0.0, "estimates": 0, "refines": 0}
        # descendants: D[j, k] = 1 when joint k is j or below it
        parents = model.parents.tolist()
        J = len(parents)
        D = np.eye(J)
        for k in range(J):
            p = parents[k]
            while p >= 0:
                D[p, k] = 1.0
                p = parents[p]
        self._desc = D
        self._parents = np.asarray(parents)
        self._bone_operator = bone_vector_operator(self._parents)
        self._levels = [(ids.numpy(), par.numpy()) for ids, par in lbs.kinematic_levels(model.parents)]
        self._worker = None
        if needs_worker(config):
            self._worker = worker or start_worker(model, self.chamfer_model, config)  # its imports run beside the first frames
            weakref.finalize(self, self._worker.close)
        elif worker is not None:
            worker.close()

        self._one_point = lbs.SurfacePoints.from_vertex_ids(torch.zeros(1, dtype=torch.long))
        self.reset()

    def wait_worker(self, timeout: float | None = None) -> bool:
        """Wait up to timeout seconds for the worker process's start-up (True when ready or when
        the solver uses none): a driver that starts solving at once calls this first, as a live
        solver is up before the take begins."""
        return self._worker is None or self._worker.ready(timeout)

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker process once it is ready (None without one)."""
        return None if self._worker is None else self._worker.pid

    # ------------------------------------------------------------------ public API
    def reset(self) -> None:
        """Forget everything but the priors (a new take / a different marker set)."""
        c = self.config
        self.num_markers: int | None = None
        self.locked = False
        self.betas = None
        self.yaw = 0.0
        self.camera_tilt = np.eye(3)
        self.face_ids = None
        self.bary = None
        self.allowed_ids = None
        self.part_joints: tuple[int, ...] | None = None  # the locked part's joints (None: full body)
        self.labels_version = 0
        self._label_arrays = None  # label_arrays()'s cache
        self._boot: deque | None = None  # frames collected for a (re-)bootstrap
        self._pending: deque = deque()  # estimated, not yet final (bounded by lag + hop)
        self._context: deque = deque(maxlen=max(c.context_frames, 2))
        self._history: deque = deque(maxlen=c.history_frames)
        self._index = 0
        self._track_ids = None
        self._seen_run = None
        self._slip_run = None
        # per column, which marker it holds: a new track (a changed track id) is a new marker, a
        # handover continues the ended one's; the lock upgrades solve each marker as one column
        self._identity = np.zeros(0, dtype=np.int64)
        self._next_identity = 0
        self._forget_sightings()
        self._degrade_run = 0
        self._since_recheck = 0
        self._recheck_groups: deque = deque()  # marker groups of the re-check in progress
        self._since_pass = 0  # refine_ready calls since the last smoothing pass
        self._lock_age = 0  # frames estimated since the lock was last adopted
        self._reservoir: list[_Frame] = []  # refined frames spread over the take (lock upgrade)
        self._reservoir_stride = 1
        self._reservoir_seen = 0
        self._locked_span = 0  # frames the current lock was estimated from
        # refined frames a lock upgrade may revise (the last revise_s seconds; made at the bootstrap,
        # when the rate is known) and the revision in progress ({"frames", "pos", "ready"})
        self._refined_ring: deque | None = None
        self._cancel_revision()
        self._hops_since_revision = 0
        # bumped by every (re-)bootstrap and reset: a background upgrade of an older lock is dropped
        self._lock_generation = getattr(self, "_lock_generation", 0) + 1
        self.cancel_upgrade()  # a running upgrade belongs to the old lock
        self._upgrade_job = None  # (future, inputs) of a background upgrade
        self._upgrades_ended = False  # end_upgrades(): the take is ending
        self._executor = getattr(self, "_executor", None)

    def add_prior(self, stamp_ns: int, global_orient, body_pose, betas, valid: bool = True, camera_frame: bool = True,
                  confidence: float = 1.0) -> None:
        """One video-prior frame on the marker clock.  global_orient (3,) axis-angle (camera frame
        when camera_frame), body_pose (23,3), betas (B,)."""
        go = np.asarray(global_orient, dtype=np.float64).reshape(3)
        bp = np.asarray(body_pose, dtype=np.float64).reshape(23, 3)
        if self._priors and int(stamp_ns) <= self._priors[-1][0]:
            return  # stamps must increase; a repeated / late prior is ignored
        self._priors.append((int(stamp_ns), go, bp, np.asarray(betas, dtype=np.float64).reshape(-1), bool(valid),
                             bool(camera_frame), float(confidence)))
        # the per-frame pose prior: (72,) world root (before the yaw) + body, computed once per prior
        root = rotation_vector(self.r_wc @ rotation_matrices(go)) if camera_frame else go
        self._prior72.append((int(stamp_ns), bool(valid), np.concatenate([root, bp.reshape(-1)])))
        if valid and self._first_valid_prior is None:
            self._first_valid_prior = int(stamp_ns)

    def add_markers(self, stamp_ns: int, positions, visible=None, track_ids=None, frame_index: int | None = None) -> list[WindowResult]:
        """One capture frame: positions (M,3) metres (NaN where missing), visible (M,) bool or None,
        track_ids (M,) ints or None (a slot whose id changes is a new marker); frame_index: the
        capture's frame number for the results (default: a running count).  Returns the results
        that became available (estimates and refined frames, in stamp order per kind)."""
        results = self.push_markers(stamp_ns, positions, visible, track_ids, frame_index)
        results += self.refine_ready()
        return results

    def push_markers(self, stamp_ns: int, positions, visible=None, track_ids=None, frame_index: int | None = None,
                     iterations: int | None = None) -> list[WindowResult]:
        """The causal half of ``add_markers``: the estimate(s) only (a node publishes them before
        running the smoothing pass with ``refine_ready``).  iterations: Gauss-Newton iterations of
        this frame's estimate (default ``estimate_iterations``; a node that is behind uses fewer)."""
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"positions must be (M, 3), got {pos.shape}")
        vis = np.isfinite(pos).all(axis=1)
        if visible is not None:
            vis &= np.asarray(visible, dtype=bool).reshape(-1)
        if self.num_markers is not None and pos.shape[0] != self.num_markers:
            # a different marker set: start over (correspondences are per marker index)
            self.reset()
        if self.num_markers is None:
            self.num_markers = pos.shape[0]
            self._seen_run = np.zeros(pos.shape[0], dtype=np.int64)
            self._slip_run = np.zeros(pos.shape[0], dtype=np.int64)
            self._forget_sightings(pos.shape[0])
            self._identity, self._next_identity = np.arange(pos.shape[0]), pos.shape[0]
        frame = _Frame(stamp_ns, self._index if frame_index is None else frame_index, np.where(vis[:, None], pos, np.nan), vis)
        self._index += 1
        self.stats["frames"] += 1
        self._handle_track_ids(track_ids)
        frame.identity = self._identity.copy()
        if not self.locked:
            return self._collect_bootstrap(frame)
        t0 = time.perf_counter()
        out = [self._estimate(frame, iterations or self.estimate_iterations)]
        self.timing["estimate_s"] += time.perf_counter() - t0
        self.timing["estimates"] += 1
        if self._boot is not None:  # a re-bootstrap is collecting while estimates go on
            self._boot.append(frame)
            if self._boot_ready():
                self._bootstrap(list(self._boot), rebootstrap=True)
        return out

    @property
    def estimate_iterations(self) -> int:
        """Gauss-Newton iterations per estimate: the configured count, else by the marker rate
        (``WindowedSolverConfig.estimate_iterations`` explains)."""
        c = self.config
        if c.estimate_iterations is not None:
            return c.estimate_iterations
        return 1 if (self.rate_hz or 0.0) >= c.one_iteration_from_hz else 2

    def refine_ready(self, max_passes: int | None = None) -> list[WindowResult]:
        """Run the smoothing pass when a hop of frames has left the lag (every due pass, or at most
        ``max_passes``: a caller that is behind spreads them out); returns refined frames, and
        revised ones while a revision after a lock upgrade is in progress (``revise_s``; a caller
        that is behind gets none)."""
        c = self.config
        out: list[WindowResult] = []
        passes = 0
        while len(self._pending) >= c.lag_frames + c.hop_frames and (max_passes is None or passes < max_passes):
            out += self._refine(c.hop_frames)
            passes += 1
        if passes:
            self._since_pass = 0
            self._hops_since_revision += passes
            if self._recheck_groups and c.hop_frames < 2:  # a pass every frame: no call falls between two
                self._recheck(self._recheck_groups.popleft())
        else:
            self._since_pass += 1
            if self._recheck_groups and self._since_pass == max(1, c.hop_frames // 2):
                # half a hop after the pass: this frame's estimate is out, the pass's backlog is
                # worked off and the next pass is half a hop away (right after the pass, the two
                # stalls added up for the frames arriving meanwhile)
                self._recheck(self._recheck_groups.popleft())
        if self._revision is not None and "future" in self._revision:
            if max_passes is None:
                out += self._worker_revision(wait=False, limit=c.revise_emit_frames)
        elif self._revision is not None and max_passes is None:
            if not c.upgrade_in_background:
                out += self._revise_all()  # a replay: at once, where the upgrade landed (deterministic)
            elif self._hops_since_revision >= c.revise_every_hops and (
                    (self._since_pass == max(1, (3 * c.hop_frames) // 4)) if c.hop_frames >= 4 else passes):
                # live: one hop of revision per revise_every_hops hops of stream (a step costs about
                # a smoothing pass), three quarters of a hop after the pass, away from the pass and
                # the re-check
                self._hops_since_revision = 0
                out += self._revise_step()
        return out

    def flush(self) -> list[WindowResult]:
        """End of stream: bootstrap on what is there if never locked, then finalise every frame."""
        out: list[WindowResult] = []
        for key in ("upgrade_at_end_s", "revise_at_end_s", "reassigned_at_end"):  # this flush's, not an earlier take's
            self.stats.pop(key, None)
        if self._revision is not None and "future" in self._revision:
            # the worker runs it ahead of any upgrade queued after it: wait for it, then cancel that
            out += self._worker_revision(wait=True)
        self.cancel_upgrade()  # its lock could only serve frames that are final now
        if not self.locked and self._boot:
            out += self._bootstrap(list(self._boot), rebootstrap=False, rate_hz=self.config.end_bootstrap_rate_hz)
        out += self._revise_all()
        while self._pending:
            out += self._refine(min(len(self._pending), self.config.lag_frames + self.config.hop_frames), final=True)
        if self.config.upgrade_at_end_growth > 0:
            self._upgrade_at_end()  # before the end-of-take revision: that one then runs under it
        if self.config.revise_at_end:
            out += self._revise_at_end()
        return out

    def _upgrade_at_end(self) -> None:
        """One more lock upgrade on the whole take's reservoir, waited for (``upgrade_at_end_growth``)."""
        c = self.config
        if not (self.locked and self._boot is None and c.upgrade_frames > 0 and not self._upgrades_ended
                and self._reservoir_seen >= self._MIN_UPGRADE_FRAMES
                and self._reservoir_seen >= c.upgrade_at_end_growth * self._locked_span):
            return
        t0 = time.perf_counter()
        self._upgrade_job = None  # flush cancelled the one in flight: its reservoir is older
        started = self.stats.get("upgrades_started", 0)
        self._upgrade_lock()
        while self._upgrade_job is not None:  # in the worker: wait, then judge / adopt (_poll_upgrade)
            wait_futures([self._upgrade_job[0]])
            self._poll_upgrade()
        if self.stats.get("upgrades_started", 0) > started:
            self.stats["upgrades_at_end"] = self.stats.get("upgrades_at_end", 0) + 1
        if c.revise_at_end:
            self._cancel_revision()  # an adoption queued a revision: the end-of-take one covers the ring
        self.stats["upgrade_at_end_s"] = round(time.perf_counter() - t0, 3)

    def _revise_at_end(self) -> list[WindowResult]:
        """The ring revised under the final lock, each frame's pose-prior target shifted by the
        ring's mean body-pose difference to the video prior (``revise_at_end``)."""
        frames = [f for f in self._refined_ring or () if f.video_prior]
        if not self.has_prior or len(frames) < 2:
            return []
        t0 = time.perf_counter()
        if self.config.reassign_at_end and len(frames) >= self._MIN_UPGRADE_FRAMES:
            self._reassign_on_ring(frames)
        diff = np.stack([f.theta - f.prior for f in frames])
        diff[:, :3] = 0.0  # the root keeps its own prior (the mean term is over the body's joints)
        shift = diff.mean(axis=0)
        for f in frames:
            f.prior = f.prior - shift
        out = self._revise_ring("revisions_at_end")
        # the take is over and its frames are final: a second flush (end of stream, then stop) or a
        # later upgrade has nothing left to revise, and the shift is not applied twice
        self._refined_ring.clear()
        self.stats["revise_at_end_s"] = round(time.perf_counter() - t0, 3)
        return out

    def _revise_ring(self, counter: str) -> list[WindowResult]:
        """The whole ring revised under the current lock, waited for (in the worker when live)."""
        self._start_revision(counter)
        out = self._worker_revision(wait=True) if self._revision is not None and "future" in self._revision else []
        return out + self._revise_all()

    def _reassign_on_ring(self, frames: list[_Frame]) -> None:
        """Stage 3 for every assigned marker over the ring's frames (``reassign_at_end``), their
        poses first revised under the final lock (the ring's results are revised again after)."""
        self._revise_ring("revisions_before_reassign")
        which = np.flatnonzero(self.face_ids >= 0)
        if len(which) == 0:
            return
        before = self.face_ids[which].copy()
        ok = self._place(which, *self._stacked(frames))
        if ok is None:
            return
        self.stats["reassigned_at_end"] = int((ok & (self.face_ids[which] != before)).sum())  # moved to another face
        self.labels_version += 1
        self._prepare_lock()

    def __getstate__(self) -> dict:
        """Copies (``copy.deepcopy``, pickles) leave the worker process and thread pool behind: a
        copy runs its extra bootstrap starts and upgrades on threads."""
        state = dict(self.__dict__)
        state["_worker"], state["_executor"], state["_upgrade_job"] = None, None, None
        if state.get("_revision") is not None and "future" in state["_revision"]:
            state["_revision"] = self._revision_here(state["_revision"])
        return state

    def _drop_broken_worker(self) -> None:
        """The worker process died or never started: threads from now on."""
        self.stats["worker_failed"] = "the worker process died or could not start"
        self._worker.close()
        self._worker = None

    def cancel_upgrade(self) -> None:
        """Stop a background lock upgrade at its next optimiser step (its result is dropped)."""
        job = getattr(self, "_upgrade_job", None)
        if job is not None:
            job[1]["cancel"].set()
            if "worker_job" in job[1]:
                self._worker.cancel(job[1]["worker_job"])

    def _cancel_revision(self) -> None:
        """Drop the revision in progress (and stop it in the worker process)."""
        rev = getattr(self, "_revision", None)
        if rev is not None and "worker_job" in rev and self._worker is not None:
            self._worker.cancel(rev["worker_job"])
        self._revision = None

    def end_upgrades(self) -> None:
        """The take is ending (a live stop): cancel a running lock upgrade and start no more - a
        new lock could only serve frames that are about to be flushed, and an upgrade solved in
        this process takes 30-60 s."""
        self.cancel_upgrade()
        self._upgrades_ended = True

    def close(self) -> None:
        """Cancel a running upgrade and release the worker thread (the solver stays usable)."""
        self.cancel_upgrade()
        if self._revision is not None and "future" in self._revision:
            self._revision = self._revision_here(self._revision)  # flush finishes it here
        if self._executor is not None:
            self._executor.shutdown(wait=False)
            self._executor = None
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    @property
    def labels(self) -> MarkerLabelState | None:
        if not self.locked:
            return None
        att = self._attachment()
        return MarkerLabelState(self.labels_version, self.face_ids.copy(), self.bary.copy(),
                                marker_part_names(self.model, att), self.config.ik.marker_offset_m)

    def label_arrays(self) -> tuple[np.ndarray | None, np.ndarray | None, list[str]]:
        """(faces (M,) int32, bary (M, 3) float32, part names) of the current correspondence for a
        publisher, (None, None, []) before the lock; the part names (~0.4 ms) are only recomputed
        when the correspondence changed."""
        if not self.locked:
            return None, None, []
        cached = self._label_arrays
        if cached is None or not (np.array_equal(cached[0], self.face_ids) and np.array_equal(cached[1], self.bary.astype(np.float32))):
            labels = self.labels
            cached = self._label_arrays = (labels.face_ids.astype(np.int32), labels.bary.astype(np.float32), list(labels.parts))
        return cached

    def buffer_sizes(self) -> dict[str, int]:
        """Lengths of every internal buffer (the memory-bound test watches these)."""
        return {"priors": len(self._priors), "pending": len(self._pending), "context": len(self._context),
                "history": len(self._history), "bootstrap": len(self._boot) if self._boot is not None else 0,
                "reservoir": len(self._reservoir), "refined_ring": len(self._refined_ring or ())}

    # ------------------------------------------------------------------ bootstrap
    def _boot_frames_needed(self) -> int:
        return max(3, int(math.ceil(self.config.bootstrap_s * (self.rate_hz or 120.0))))

    def _new_boot_buffer(self) -> deque:
        """Ring for a (re-)bootstrap window: bootstrap_s + prior_wait_s of frames (at the known
        rate, or up to 1 kHz before the rate is known) - bounded whatever the stream does."""
        c = self.config
        return deque(maxlen=max(3, int(math.ceil((c.bootstrap_s + c.prior_wait_s) * (self.rate_hz or 1000.0))) + 1))

    def _boot_ready(self) -> bool:
        b = self._boot
        if self.rate_hz is None and len(b) >= 3:
            dt = np.diff([f.stamp for f in b])
            if (dt > 0).all():
                self.rate_hz = float(1e9 / np.median(dt))
        needed = self._boot_frames_needed()
        if len(b) < needed:
            return False
        # The video prior lags the markers in a live graph (estimator latency, or a replay that
        # bursts frames at start-up): wait up to prior_wait_s more of markers for priors that
        # cover the window, else the bootstrap would start from a neutral body.  In lockstep the
        # priors up to every frame are there, so this never waits (deterministic).
        last = b[-1].stamp
        if self._priors and self._priors[-1][0] >= last - int(self.config.prior_tolerance_s * 1e9):
            return True
        return (last - b[needed - 1].stamp) / 1e9 >= self.config.prior_wait_s

    def _collect_bootstrap(self, frame: _Frame) -> list[WindowResult]:
        if self._boot is None:
            self._boot = self._new_boot_buffer()
        self._boot.append(frame)
        if self._boot_ready():
            return self._bootstrap(list(self._boot), rebootstrap=False)
        return []

    def _prior_window(self, stamps: np.ndarray) -> tuple[BodyPrior, np.ndarray, bool]:
        return world_prior_at(list(self._priors), stamps, self.up_axis, self.model.num_betas)

    def _bootstrap(self, frames: list[_Frame], rebootstrap: bool, rate_hz: float | None = None) -> list[WindowResult]:
        """Offline staged solver on the window, decimated to ``rate_hz`` (default
        ``bootstrap_rate_hz``); lock shape / yaw / correspondence; estimate every frame of the
        window (batched) and queue them for refinement."""
        t0 = time.perf_counter()
        c = self.config
        self._boot = None
        rate = self.rate_hz or 120.0
        stamps = np.array([f.stamp for f in frames], dtype=np.int64)
        markers = np.stack([f.markers for f in frames])
        vis = np.stack([f.visible for f in frames])
        step = max(1, int(round(rate / (rate_hz or c.bootstrap_rate_hz))))
        sel = np.arange(0, len(frames), step)
        if not vis[sel].any(axis=0).any():
            raise ValueError("no marker was visible during the bootstrap window")
        prior, shape, has_prior = self._prior_window(stamps)
        sub = BodyPrior(prior.root_orient[sel], prior.body_pose[sel], prior.betas_per_frame[sel], prior.valid[sel],
                        prior.confidence[sel], prior.stamps_ns[sel], prior.frame)
        res = self._solve_bootstrap_window(markers[sel], vis[sel], rate / step, sub, shape)
        self._join_identities(res.diagnostics.get("track_stitching"), frames)
        old_yaw = self.yaw
        self.shape_prior = torch.as_tensor(np.asarray(shape), dtype=torch.float32)
        self._reservoir, self._reservoir_stride, self._reservoir_seen = [], 1, 0
        # a (re-)bootstrap starts over: frames before it may be another subject's, or a failed fit's
        ring = int(round(c.revise_s * rate))
        self._refined_ring = deque(maxlen=ring) if ring > 0 else None
        self._cancel_revision()
        self._locked_span = len(frames)
        self._lock_generation += 1
        self.has_prior = has_prior
        self._adopt_lock(res)
        diag = res.diagnostics
        self.stats["bootstraps"] += 1
        self.stats["rebootstraps"] += int(rebootstrap)
        self.last_bootstrap = {k: v for k, v in diag.items() if k not in ("cluster_labels",)}
        self._seen_run[:] = 0
        self._slip_run[:] = 0
        self._degrade_run = 0
        if rebootstrap:
            # Frames still in flight: re-express them in the new yaw (their world pose is unchanged;
            # a frame sits in several rings, so once each), take the bootstrap's solution where the
            # window covers them, then settle them under the new lock (batched Gauss-Newton).
            self._reyaw_in_flight(old_yaw)
            full = interpolate_params(res.params, sel, np.arange(len(frames)))
            where = {id(f): i for i, f in enumerate(frames)}
            for f in self._pending:
                i = where.get(id(f))
                if i is not None:
                    f.theta = np.concatenate([full.root_orient[i].double().numpy(), full.body_pose[i].double().numpy().reshape(-1)])
                    f.trans = full.trans[i].double().numpy()
            pend = list(self._pending)
            if pend:
                theta, trans = self._gauss_newton(np.stack([f.theta for f in pend]), np.stack([f.trans for f in pend]),
                                                  np.stack([f.markers for f in pend]), np.stack([f.visible for f in pend]),
                                                  np.stack([f.prior for f in pend]), self.estimate_iterations)
                for i, f in enumerate(pend):
                    f.theta, f.trans = theta[i], trans[i]
            self.stats["bootstrap_seconds"].append(round(time.perf_counter() - t0, 3))
            return []
        full = interpolate_params(res.params, sel, np.arange(len(frames)))
        theta = np.concatenate([full.root_orient.double().numpy(), full.body_pose.double().numpy().reshape(len(frames), -1)], 1)
        trans = full.trans.double().numpy()
        prior72 = self._tilt_priors(np.concatenate([prior.root_orient, prior.body_pose.reshape(len(frames), -1)], 1))
        for i, f in enumerate(frames):
            f.prior = prior72[i] if has_prior else theta[i].copy()
            f.video_prior = has_prior
        theta, trans = self._gauss_newton(theta, trans, markers, vis, prior72 if has_prior else theta.copy(), self.estimate_iterations)
        out = []
        lin = self._linearize(theta, trans, markers, vis, jacobian=False)
        for i, f in enumerate(frames):
            f.theta, f.trans = theta[i], trans[i]
            f.residual, f.joints = lin["residual"][i], lin["joints"][i]
            self._pending.append(f)
            self._history.append(f)
            out.append(self._result(f, "estimate", lin["root_world"][i]))
        if c.handover is not None:  # a marker that ends in the window and comes back after it
            self._remember_sightings(frames, lin)
        self.stats["bootstrap_seconds"].append(round(time.perf_counter() - t0, 3))
        return out

    def _solve_bootstrap_window(self, markers: np.ndarray, vis: np.ndarray, rate_hz: float, prior: BodyPrior, shape: np.ndarray):
        """The staged solver on the bootstrap window (markers (S,M,3), vis (S,M)) under
        ``bootstrap_solver`` and each of ``bootstrap_alternatives`` (in the worker process, or
        on threads); the result
        with the most markers placed, then the lowest Stage-5 marker fit.  A start that fails
        is skipped; when all fail, the first one's error is raised."""
        configs = (self.config.bootstrap_solver, *self.config.bootstrap_alternatives)

        def run(cfg):
            return solve(markers, vis, rate_hz, self.up_axis, prior, shape, self.model, self.chamfer_model, cfg)

        if len(configs) == 1:
            return run(configs[0])
        from concurrent.futures import ThreadPoolExecutor

        def outcome(fn):
            try:
                return fn()
            except (ValueError, RuntimeError) as err:  # bad window, a numerical failure, a dead worker
                return err

        def collect(others):  # the first start here while the others run elsewhere
            return [outcome(lambda: run(configs[0])), *(outcome(job.result) for job in others)]

        if self._worker is not None:
            self.cancel_upgrade()  # the upgrade of an older lock would queue ahead of these
            self._cancel_revision()
            outcomes = collect([self._worker.submit(markers, vis, rate_hz, self.up_axis, prior, shape, cfg)[1] for cfg in configs[1:]])
            if self._worker.broken or any(isinstance(o, BrokenExecutor) for o in outcomes):
                # it could not start (e.g. a script that starts solving at import time, which a
                # spawned interpreter re-runs) or died: solve those starts here
                self._drop_broken_worker()
                outcomes = [outcome(lambda c=cfg: run(c)) if isinstance(o, BrokenExecutor) else o for cfg, o in zip(configs, outcomes)]
        else:
            with ThreadPoolExecutor(len(configs) - 1, thread_name_prefix="bootstrap") as pool:
                outcomes = collect([pool.submit(run, cfg) for cfg in configs[1:]])
        solved = [(i, r) for i, r in enumerate(outcomes) if not isinstance(r, Exception)]
        if not solved:
            raise outcomes[0]

        def rank(item):
            res = item[1]
            fit = res.diagnostics.get("stage5_marker_fit_mm", res.diagnostics.get("stage4_marker_fit_mm", math.inf))
            return (-int(res.attachment.assigned.sum()), fit if fit is not None else math.inf, item[0])

        best, res = min(solved, key=rank)
        fits = [None if isinstance(r, Exception) else r.diagnostics.get("stage5_marker_fit_mm") for r in outcomes]
        self.stats["bootstrap_start_fits_mm"] = [round(f, 3) if f is not None else None for f in fits]
        self.stats["bootstrap_start_chosen"] = best
        return res

    _LOCK_FIELDS = ("face_ids", "bary", "betas", "yaw", "camera_tilt", "allowed_ids")
    # refined frames seen before any upgrade: the staged solver needs a few frames to screen and
    # segment (the growth rule alone would fire on a handful of frames after a short bootstrap)
    _MIN_UPGRADE_FRAMES = 8

    def _part_joints_of(self, res) -> tuple[int, ...] | None:
        """Joint indices of the part a staged-solver result placed the markers on (None: a full body)."""
        return solved_part_joints(self.model, res.diagnostics) or None

    def _lock_from(self, res, column_owner: np.ndarray | None = None) -> tuple:
        """The lock (``_LOCK_FIELDS``) a staged-solver result implies.  column_owner (M,): the
        result's marker each column holds (-1: none), when the solve ran on markers joined from
        columns (``_upgrade_inputs``); None: the result's markers are the columns."""
        diag = res.diagnostics
        joints = solved_part_joints(self.model, diag)
        faces, bary = res.attachment.face_ids.numpy().astype(np.int64), res.attachment.bary.double().numpy()
        if column_owner is not None:
            owner = np.asarray(column_owner)
            faces = np.where(owner >= 0, faces[np.maximum(owner, 0)], -1)
            bary = np.where(owner[:, None] >= 0, bary[np.maximum(owner, 0)], 0.0)
        return (faces.copy(), bary.copy(),
                res.params.betas.detach().clone(), float(res.params.yaw),
                np.asarray(diag.get("camera_tilt", np.eye(3)), dtype=np.float64),
                part_vertex_ids(self.model, joints) if joints else None)

    def _set_lock(self, lock: tuple) -> None:
        for name, value in zip(self._LOCK_FIELDS, lock):
            setattr(self, name, value)
        self._prepare_lock()

    def _adopt_lock(self, res, column_owner: np.ndarray | None = None) -> None:
        """Lock shape, yaw, camera tilt and correspondence from a staged-solver result
        (column_owner: ``_lock_from``'s)."""
        lock = self._lock_from(res, column_owner)
        self.part_joints = self._part_joints_of(res)  # the part the lock upgrades re-solve
        # the solver estimated the video camera's tilt; every later prior root gets the same tilt,
        # and priors already attached to frames in flight carry the old one: swap it
        swap = lock[4] @ self.camera_tilt.T
        if self.has_prior and not np.allclose(swap, np.eye(3)):
            frames = list(self._frames_in_flight())
            if frames:
                priors = self._swap_prior_tilt(np.stack([f.prior for f in frames]), swap)
                for f, prior in zip(frames, priors):
                    f.prior = prior
        self._set_lock(lock)
        self._repoint_sightings()
        self.labels_version += 1
        self.locked = True
        self._lock_age = 0
        self._recheck_groups.clear()  # its frames were estimated under the old lock

    def _join_identities(self, stitching: dict | None, frames: list[_Frame]) -> None:
        """Columns the bootstrap's solve found to be one marker (``staged_solver.solve``'s track
        stitching) hold one identity from now on, in the window's frames too: the lock upgrades
        then solve them as one column (``_joined_markers``).  Also when the solve of the joined
        columns was dropped: the chains come from the first solve's body, and a 3 s window's
        second solve can go wrong on its own (a walk's: marker fit 3.8 -> 15.5 mm on pure chains)."""
        joined = [cols for cols in (stitching or {}).get("chains", []) if len(cols) > 1]
        if not joined:
            return
        held = {id(f): f for f in chain(frames, self._frames_in_flight()) if f.identity is not None}.values()
        for columns in joined:
            for f in held:
                f.identity[columns] = f.identity[columns[0]]
            self._identity[columns] = self._identity[columns[0]]

    def _frames_in_flight(self):
        """Every frame still held (pending, context, history, reservoir), once each: a frame sits
        in several rings."""
        seen: set[int] = set()
        for f in chain(self._pending, self._context, self._history, self._reservoir, self._refined_ring or ()):
            if id(f) not in seen:
                seen.add(id(f))
                yield f

    def _reyaw_in_flight(self, old_yaw: float) -> None:
        """Re-express held frames' roots under the new yaw (their world pose is unchanged)."""
        frames = list(self._frames_in_flight())
        if not frames or old_yaw == self.yaw:
            return
        roots = self._reyaw(np.stack([f.theta[:3] for f in frames]), old_yaw, self.yaw)
        for f, root in zip(frames, roots):
            f.theta[:3] = root

    def _reyaw(self, roots: np.ndarray, old: float, new: float) -> np.ndarray:
        """Roots (B,3) under yaw ``old`` -> the same world rotations under yaw ``new`` (one batched call)."""
        up = self.up.double().numpy()
        return rotation_vectors(rotation_matrices(-up * new) @ rotation_matrices(up * old) @ rotation_matrices(roots))

    def _attachment(self) -> MarkerAttachment:
        return MarkerAttachment(torch.as_tensor(self.face_ids), torch.as_tensor(self.bary, dtype=torch.float32),
                                torch.zeros(len(self.face_ids)))

    def _prepare_lock(self) -> None:
        """Precompute the rest-pose geometry of the assigned markers for the analytic Jacobian."""
        m = self.model
        self._betas_row = self.betas.reshape(1, -1)
        self._yaw_matrix = rotation_matrices(self.up.double().numpy() * self.yaw)
        assigned = np.flatnonzero(self.face_ids >= 0)
        self._assigned = assigned
        corners = m.faces[torch.as_tensor(self.face_ids[assigned])].reshape(-1)  # (3Ma,)
        with torch.no_grad():
            rest = lbs.forward(m, self.betas.reshape(1, -1), torch.zeros(1, 24, 3),
                               points=lbs.SurfacePoints.from_vertex_ids(corners)).vertices[0].double().numpy()
            joints = lbs.forward(m, self.betas.reshape(1, -1), torch.zeros(1, 24, 3), points=self._one_point).joints[0]
        self._rest_joints = joints.double().numpy()  # (24,3) at the locked shape
        self._rel_joints = self._rest_joints - np.where(self._parents[:, None] >= 0, self._rest_joints[self._parents], 0.0)
        Ma = len(assigned)
        self._vc = rest.reshape(Ma, 3, 3)  # rest corner positions
        self._wc = m.weights[corners].double().numpy().reshape(Ma, 3, -1)  # corner skinning weights
        bary = self.bary[assigned]
        self._bary_a = bary
        s = (self._vc * bary[:, :, None]).sum(1)
        if self.config.ik.offset_model == "smooth_normal":
            # the skin's smooth normal in each face's frame (inverse_kinematics explains why)
            self._smooth_local = smooth_normals_in_face_frames(m, self.betas, self._attachment()).double().numpy()
            n = np.einsum("mi,mij->mj", self._smooth_local, _triangle_frames(self._vc))
        else:
            self._smooth_local = None
            n = _cross(self._vc[:, 1] - self._vc[:, 0], self._vc[:, 2] - self._vc[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        self._rest_point = s + self.config.ik.marker_offset_m * n  # the marker's rest position
        self._w_point = np.einsum("mc,mcj->mj", bary, self._wc)
        self._w_desc = self._w_point @ self._desc.T  # W[m, j] = sum of weights of j's subtree
        # A bone no marker sits on (a foot, a hand) still moves the skin a few percent around the
        # markers next to its joint; the exact per-frame solve then swings it 30-40 deg against
        # the prior to buy a few mm of residual (L-BFGS offline stops before it gets there).
        support = self._w_desc.sum(0)  # (24,) markers' worth of skin each joint's rotation moves
        scale = np.where(support < self.config.unsupported_joint_support, self.config.unsupported_joint_prior_scale, 1.0)
        self._prior_scale = np.repeat(scale, 3)  # (72,)

    # ------------------------------------------------------------------ the model and its Jacobian
    def _linearize(self, theta: np.ndarray, trans: np.ndarray, markers: np.ndarray, vis: np.ndarray,
                   jacobian: bool = True, joint_jacobian: bool = False) -> dict:
        """Residuals and Jacobians for B frames.  theta (B,72), trans (B,3), markers (B,M,3), vis (B,M).
        Returns dict: pred (B,Ma,3), resid (B,Ma,3) pred - marker (0 where not visible), w (B,Ma),
        surface (B,Ma,3) the points without the marker offset, corners (B,Ma,3,3) their posed faces,
        residual (B,) mean distance, joints (B,24,3), root_world (B,3,3), J (B,Ma,3,75),
        GJ (B,72,75) joint Jacobian."""
        B = theta.shape[0]
        c = self.config.ik
        rot = rotation_matrices(theta.reshape(B, 24, 3))
        rot[:, 0] = self._yaw_matrix @ rot[:, 0]  # the world root is R_up(yaw) R(root_orient)
        A, grot, pj = self._forward_kinematics(rot)
        a = self._assigned
        Ma = len(a)
        Tc = (self._wc.reshape(Ma * 3, -1) @ A.reshape(B, 24, 12)).reshape(B, Ma, 3, 3, 4)
        pc = np.einsum("bmcrk,mck->bmcr", Tc[..., :3], self._vc) + Tc[..., 3] + trans[:, None, None, :]
        s = (pc * self._bary_a[None, :, :, None]).sum(2)
        mk = markers[:, a]
        w = vis[:, a].astype(np.float64)
        if c.offset_model == "smooth_normal":
            pred = s + c.marker_offset_m * np.einsum("mi,bmij->bmj", self._smooth_local, _triangle_frames(pc))
        elif c.offset_model == "face_normal":
            n = _cross(pc[:, :, 1] - pc[:, :, 0], pc[:, :, 2] - pc[:, :, 0])
            n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
            pred = s + c.marker_offset_m * n
        else:  # the paper's distance model as a 3-vector: the point delta from the surface towards the marker
            d = np.nan_to_num(mk) - s
            pred = s + c.marker_offset_m * d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
        resid = np.where(w[..., None] > 0, pred - np.nan_to_num(mk), 0.0)
        dist = np.linalg.norm(resid, axis=-1)
        res = {"pred": pred, "resid": resid, "w": w, "dist": dist, "surface": s, "corners": pc,
               "residual": (dist * w).sum(1) / np.maximum(w.sum(1), 1.0),
               "joints": pj + trans[:, None, :], "root_world": grot[:, 0]}
        if jacobian:
            jr = right_jacobian_so3(theta.reshape(B, 24, 3))
            gj = grot @ jr  # (B,24,3,3) world rotation axes per local axis-angle component
            # the marker's rest point under each joint's transform, blended over each subtree
            Y = np.einsum("bjrk,mk->bmjr", A[..., :3], self._rest_point) + A[:, None, :, :, 3]
            S = self._desc @ (Y * self._w_point[None, :, :, None])
            cvec = S - self._w_desc[None, :, :, None] * pj[:, None, :, :]
            J = np.zeros((B, len(a), 3, N_PARAMS))
            J[..., :N_POSE] = lever_jacobian(cvec, gj)
            J[..., N_POSE:] = np.eye(3)
            res["J"] = J
            if joint_jacobian:
                diff = pj[:, :, None, :] - pj[:, None, :, :]  # (B,k,j,3) p_k - p_j
                Gk = lever_jacobian(diff, gj).reshape(B, 24, 3, 24, 3) * self._desc.T[None, :, None, :, None]
                G = np.zeros((B, 24, 3, N_PARAMS))
                G[..., :N_POSE] = Gk.reshape(B, 24, 3, N_POSE)
                G[..., N_POSE:] = np.eye(3)
                res["GJ"] = G.reshape(B, 72, N_PARAMS)
        return res

    def _forward_kinematics(self, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Linear blend skinning transforms of the locked body, float64 numpy (what ``lbs.forward``
        computes for the joints, without torch's per-call overhead; the body is evaluated only at
        the marker points, so no mesh is needed).  rot (B,24,3,3) local rotations (root in the
        world) -> (A (B,24,3,4) skinning transforms, G (B,24,3,3) world rotations, joints (B,24,3)
        without translation)."""
        B = rot.shape[0]
        G = np.empty_like(rot)
        t = np.empty((B, rot.shape[1], 3))
        G[:, 0] = rot[:, 0]
        t[:, 0] = self._rel_joints[0]
        for ids, par in self._levels:
            Gp = G[:, par]
            G[:, ids] = Gp @ rot[:, ids]
            t[:, ids] = np.einsum("bjrk,jk->bjr", Gp, self._rel_joints[ids]) + t[:, par]
        A = np.empty((B, rot.shape[1], 3, 4))
        A[..., :3] = G
        A[..., 3] = t - np.einsum("bjrk,jk->bjr", G, self._rest_joints)
        return A, G, t

    def _prior_terms(self, theta: np.ndarray, prior: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose-prior residual (B,72) and its per-component weight^2 (72,) (root weight 0 unless
        prior_includes_root; joints no marker supports weigh unsupported_joint_prior_scale more)."""
        c = self.config.ik
        diff = theta - prior
        diff[:, :3] = theta[:, :3] - nearest_equivalent(prior[:, :3], theta[:, :3])
        count = N_POSE if c.prior_includes_root else N_POSE - 3
        weight = c.pose_weight / (count * frames) * self._prior_scale
        if not c.prior_includes_root:
            weight[:3] = 0.0
        return diff, weight

    def _gauss_newton(self, theta, trans, markers, vis, prior, iterations: int):
        """Independent per-frame Levenberg-Marquardt (batched over B frames) on the Stage-4 energy."""
        c = self.config
        unit = c.ik.distance_unit_m
        theta, trans = theta.copy(), trans.copy()
        for _ in range(iterations):
            lin = self._linearize(theta, trans, markers, vis)
            w = lin["w"]
            wm = c.ik.marker_weight / np.maximum(w.sum(1), 1.0) / unit**2  # (B,)
            root_w = self._robust_root_weights(lin)
            J = lin["J"] * (w * root_w)[..., None, None]
            Jf = J.reshape(J.shape[0], -1, N_PARAMS)
            rf = (lin["resid"] * root_w[..., None]).reshape(J.shape[0], -1)
            Jt = np.ascontiguousarray(Jf.transpose(0, 2, 1))  # numpy's stacked matmul is BLAS only on contiguous operands
            H = (Jt @ Jf) * wm[:, None, None]
            g = (Jt @ rf[..., None])[..., 0] * wm[:, None]
            pd, pw = self._prior_terms(theta, prior, 1)
            H[:, np.arange(N_POSE), np.arange(N_POSE)] += pw
            g[:, :N_POSE] += pw * pd
            diag = np.einsum("bii->bi", H)
            H[:, np.arange(N_PARAMS), np.arange(N_PARAMS)] += c.damping * diag + 1e-9
            step = np.linalg.solve(H, -g[..., None])[..., 0]
            theta += step[:, :N_POSE]
            trans += step[:, N_POSE:]
            theta[:, :3] = wrap_rotation_vector(theta[:, :3])
        return theta, trans

    def _robust_root_weights(self, lin: dict) -> np.ndarray:
        """(B,Ma) square roots of the Cauchy IRLS weights 1 / (1 + (d / scale)^2) of the markers'
        current distances d (1 everywhere when ``robust_scale_m`` is None)."""
        scale = self.config.robust_scale_m
        d = np.linalg.norm(lin["resid"], axis=-1)
        if scale is None:
            return np.ones_like(d)
        return 1.0 / np.sqrt(1.0 + (d / scale) ** 2)

    # ------------------------------------------------------------------ per frame
    def _prior_at(self, stamp: int) -> np.ndarray | None:
        """(72,) world prior (before the yaw) of the latest valid prior at or before ``stamp``."""
        for st, valid, prior in reversed(self._prior72):
            if st <= stamp and valid:
                return self._tilt_priors(prior[None])[0]
        return None

    def _tilt_priors(self, prior72: np.ndarray) -> np.ndarray:
        """(B,72) priors with the camera tilt found at bootstrap applied to their roots."""
        return self._swap_prior_tilt(prior72, self.camera_tilt)

    def _estimate(self, frame: _Frame, iterations: int) -> WindowResult:
        c = self.config
        prev = self._history[-1] if self._history else None
        theta0 = prev.theta.copy() if prev is not None else np.zeros(N_POSE)
        trans0 = prev.trans.copy() if prev is not None else np.zeros(3)
        if c.extrapolate and len(self._history) >= 2:  # constant-velocity warm start
            pp = self._history[-2]
            theta0[3:] += prev.theta[3:] - pp.theta[3:]
            trans0 = trans0 + (prev.trans - pp.trans)
            # the root rotation continues by its last frame-to-frame rotation (no axis-angle wrap issue)
            r_prev, r_pp = rotation_matrices(prev.theta[:3]), rotation_matrices(pp.theta[:3])
            theta0[:3] = rotation_vector(r_prev @ r_pp.T @ r_prev)
        prior = self._prior_at(frame.stamp) if self.has_prior else None
        frame.prior = prior if prior is not None else (prev.theta.copy() if prev is not None else theta0.copy())
        frame.video_prior = prior is not None
        mk, vis = frame.markers[None], frame.visible[None]
        theta, trans = self._gauss_newton(theta0[None], trans0[None], mk, vis, frame.prior[None], iterations)
        lin = self._linearize(theta, trans, mk, vis, jacobian=False)
        if float(lin["residual"][0]) > c.recover_threshold_m and prev is not None:
            # Lost track of a fast or unusual motion (the warm start is in the wrong basin): try
            # again from this frame's pose prior with more iterations and keep the better fit.
            # Without this the bad pose makes many markers look 'slipped' at once and their
            # re-assignment under the wrong pose corrupts the lock.
            start = frame.prior.copy()
            start[:3] = prev.theta[:3]
            th2, tr2 = self._gauss_newton(start[None], prev.trans[None].copy(), mk, vis, frame.prior[None], c.recover_iterations)
            lin2 = self._linearize(th2, tr2, mk, vis, jacobian=False)
            self.stats["recoveries"] = self.stats.get("recoveries", 0) + 1
            if float(lin2["residual"][0]) < float(lin["residual"][0]):
                theta, trans, lin = th2, tr2, lin2
        frame.theta, frame.trans = theta[0], trans[0]
        frame.residual, frame.joints = float(lin["residual"][0]), lin["joints"][0]
        self._pending.append(frame)
        self._history.append(frame)
        self._change_handling(frame, lin)
        return self._result(frame, "estimate", lin["root_world"][0])

    def _result(self, f: _Frame, kind: str, root_world: np.ndarray) -> WindowResult:
        """The result of frame f; root_world: its world root rotation, a matrix (3,3) or a rotation vector (3,)."""
        root = rotation_vector(root_world) if np.shape(root_world) == (3, 3) else np.asarray(root_world, dtype=np.float64)
        return WindowResult(f.stamp, f.index, kind, np.concatenate([root, f.theta[3:]]), f.trans.copy(),
                            f.joints.copy(), self.betas.double().numpy().copy(), float(f.residual), self.labels_version)

    # ------------------------------------------------------------------ fixed-lag smoothing
    def _refine(self, count: int, final: bool = False) -> list[WindowResult]:
        """Banded Gauss-Newton over [context | pending] with the offline IK energy + smoothness;
        finalise the first ``count`` pending frames."""
        t0 = time.perf_counter()
        c = self.config
        ctx = list(self._context)[-c.context_frames:] if c.context_frames else []
        free = list(self._pending)[: c.lag_frames + c.hop_frames] if not final else list(self._pending)[:count]
        self._smooth(ctx, free)
        done = [self._pending.popleft() for _ in range(min(count, len(self._pending)))]
        out = self._finalise(done, "refined")
        for f in done:
            self._context.append(f)
            self._keep_in_reservoir(f)
            if self._refined_ring is not None:
                self._refined_ring.append(f)
        self.timing["refine_s"] += time.perf_counter() - t0
        self.timing["refines"] += 1
        return out

    def _smooth(self, ctx: list, free: list) -> None:
        """``refine_iterations`` smoothing steps over [ctx | free]; the free frames' poses are updated."""
        c = self.config
        window = ctx + free
        C = len(ctx)
        if not c.refine_iterations or not free:
            return
        theta = np.stack([f.theta for f in window])
        trans = np.stack([f.trans for f in window])
        markers = np.stack([f.markers for f in window])
        vis = np.stack([f.visible for f in window])
        prior = np.stack([f.prior for f in window])
        for _ in range(c.refine_iterations):
            step = self._window_step(theta, trans, markers, vis, prior, C)
            theta[C:] += step[:, :N_POSE]
            trans[C:] += step[:, N_POSE:]
            theta[:, :3] = wrap_rotation_vector(theta[:, :3])
        for i, f in enumerate(free):
            f.theta, f.trans = theta[C + i], trans[C + i]

    def _finalise(self, done: list, kind: str) -> list[WindowResult]:
        """Residuals, joints and results of final frames."""
        if not done:
            return []
        th = np.stack([f.theta for f in done])
        tr = np.stack([f.trans for f in done])
        lin = self._linearize(th, tr, np.stack([f.markers for f in done]), np.stack([f.visible for f in done]), jacobian=False)
        out = []
        for i, f in enumerate(done):
            f.residual, f.joints = float(lin["residual"][i]), lin["joints"][i]
            out.append(self._result(f, kind, lin["root_world"][i]))
        return out

    # ------------------------------------------------------------------ revisions after a lock upgrade
    def _start_revision(self, counter: str = "revisions") -> None:
        """Queue every frame refined under the previous lock (the ring) for a revision under this
        one: live with the worker process, the whole revision as one job there; else hop by hop here.
        counter: the stats entry that counts it."""
        self._cancel_revision()
        if not self._refined_ring:
            return
        frames = list(self._refined_ring)
        self._revision = {"frames": frames, "pos": 0, "ready": 0}
        self.stats[counter] = self.stats.get(counter, 0) + 1
        if self.config.upgrade_in_background and self._worker is not None and not self._worker.broken:
            lock = self._lock_copy()
            # stacked arrays: the pool pickles the job on a thread holding the interpreter lock, and
            # 3600 frame objects (30 s at 120 Hz) stalled the stream ~170 ms there
            arrays = {name: np.stack([getattr(f, name) for f in frames]) for name in _Frame.REVISED_FROM}
            job, future = self._worker.call(revise_in_worker, self.config, self.up_axis, self.rate_hz, lock, arrays)
            self._revision.update(future=future, worker_job=job)

    @staticmethod
    def _revision_here(rev: dict) -> dict:
        """A worker's revision, continued in this process from the frames it has handed out."""
        return {"frames": rev["frames"], "pos": rev["pos"], "ready": rev["pos"]}

    def _worker_revision(self, wait: bool, limit: int | None = None) -> list[WindowResult]:
        """The worker's revision: once back, its poses go into the ring's frames and up to ``limit``
        'revised' results per call come out.  Failed or cancelled there: revised here instead, hop by
        hop (``_revise_step``).  (A lock adopted meanwhile replaces the revision: ``_start_revision``.)"""
        rev = self._revision
        if "poses" not in rev:
            if not (wait or rev["future"].done()):
                return []
            try:
                rev["poses"] = rev["future"].result()
            except (SolveCancelled, ValueError, RuntimeError) as exc:
                if isinstance(exc, BrokenExecutor) and self._worker is not None:
                    self._drop_broken_worker()
                self.stats["revision_errors"] = self.stats.get("revision_errors", 0) + 1
                self._revision = self._revision_here(rev)
                return []
            rev["pos"] = 0
        poses, frames, a = rev["poses"], rev["frames"], rev["pos"]
        end = len(frames) if limit is None else min(len(frames), a + limit)
        out = []
        for i in range(a, end):
            f = frames[i]
            f.theta, f.trans, f.joints, f.residual = poses["theta"][i], poses["trans"][i], poses["joints"][i], float(poses["residual"][i])
            out.append(self._result(f, "revised", poses["root"][i]))
        rev["pos"] = end
        if end >= len(frames):
            self._revision = None
        self.stats["revised_frames"] = self.stats.get("revised_frames", 0) + len(out)
        return out

    def _revise_step(self) -> list[WindowResult]:
        """One hop of the revision in progress, as the stream does it: the frames entering the
        window are estimated under the new lock (``revise_iterations`` from their refined poses),
        the smoothing pass runs over [revised context | lag + hop frames] and the first hop of them
        comes out 'revised'."""
        c = self.config
        rev = self._revision
        R, a = rev["frames"], rev["pos"]
        end = min(len(R), a + c.lag_frames + c.hop_frames)
        if rev["ready"] < end:
            new = R[rev["ready"]:end]
            theta, trans = self._gauss_newton(np.stack([f.theta for f in new]), np.stack([f.trans for f in new]),
                                              np.stack([f.markers for f in new]), np.stack([f.visible for f in new]),
                                              np.stack([f.prior for f in new]), c.revise_iterations)
            for i, f in enumerate(new):
                f.theta, f.trans = theta[i], trans[i]
            rev["ready"] = end
        self._smooth(R[max(0, a - c.context_frames):a] if c.context_frames else [], R[a:end])
        done = R[a:a + c.hop_frames] if end < len(R) else R[a:end]
        rev["pos"] = a + len(done)
        if rev["pos"] >= len(R):
            self._revision = None
        self.stats["revised_frames"] = self.stats.get("revised_frames", 0) + len(done)
        return self._finalise(done, "revised")

    def _revise_all(self) -> list[WindowResult]:
        out: list[WindowResult] = []
        while self._revision is not None:
            out += self._revise_step()
        return out

    def _window_step(self, theta, trans, markers, vis, prior, n_fixed: int) -> np.ndarray:
        """One damped Gauss-Newton step for the free frames -> (T - n_fixed, 75).

        The normal equations are block-banded (the acceleration term couples frames up to two
        apart); they are solved by conjugate gradients preconditioned with the per-frame blocks,
        which only ever touches (75,75) blocks and (72,75) joint Jacobians."""
        c = self.config
        unit = c.ik.distance_unit_m
        T = theta.shape[0]
        smooth = T >= 3 and c.smoothness_weight > 0
        lin = self._linearize(theta, trans, markers, vis, joint_jacobian=smooth)
        w = lin["w"]
        wm = c.ik.marker_weight / max(w.sum(), 1.0) / unit**2
        root_w = self._robust_root_weights(lin)
        J = (lin["J"] * (w * root_w)[..., None, None]).reshape(T, -1, N_PARAMS)[n_fixed:]
        rf = (lin["resid"] * root_w[..., None]).reshape(T, -1)[n_fixed:]
        Jt = np.ascontiguousarray(J.transpose(0, 2, 1))
        Hd = (Jt @ J) * wm
        g = (Jt @ rf[..., None])[..., 0] * wm
        pd, pw = self._prior_terms(theta[n_fixed:], prior[n_fixed:], T)
        idx = np.arange(N_POSE)
        Hd[:, idx, idx] += pw
        g[:, :N_POSE] += pw * pd
        F = T - n_fixed
        blocks = Hd.copy()
        if smooth:
            rate = self.rate_hz or c.ik.smoothness_reference_hz
            ws = c.smoothness_weight * (rate / c.ik.smoothness_reference_hz) ** 4 / ((T - 2) * 24) / unit**2
            L = np.zeros((T - 2, T))
            for i in range(T - 2):
                L[i, i:i + 3] = (1.0, -2.0, 1.0)
            Cm = (L.T @ L)[n_fixed:, n_fixed:]  # banded: frames up to 2 apart interact
            P = lin["joints"].reshape(T, 72)
            G = lin["GJ"][n_fixed:]
            if c.smoothness_target == "bones":
                P = P @ self._bone_operator.T
                G = self._bone_operator @ G
            Gt = np.ascontiguousarray(G.transpose(0, 2, 1))
            back = (L.T @ (L @ P))[n_fixed:]  # gradient of 0.5 |L P|^2 w.r.t. P
            g += ws * (Gt @ back[..., None])[..., 0]
            blocks += (ws * np.diagonal(Cm))[:, None, None] * (Gt @ G)
        damp = c.damping * np.einsum("tii->ti", blocks) + 1e-9
        blocks[:, np.arange(N_PARAMS), np.arange(N_PARAMS)] += damp
        Hd[:, np.arange(N_PARAMS), np.arange(N_PARAMS)] += damp
        # torch's batched inverse: 2.9 ms for the (20,75,75) blocks, numpy's 7.2 ms (the same
        # LAPACK math to 1e-13; ~0.4 ms per frame of the ~8 ms steady-state budget)
        precond = torch.linalg.inv(torch.from_numpy(blocks)).numpy()

        def matvec(x):
            y = (Hd @ x[..., None])[..., 0]
            if smooth:
                q = Cm @ (G @ x[..., None])[..., 0]
                y += ws * (Gt @ q[..., None])[..., 0]
            return y

        # preconditioned conjugate gradients on H x = -g
        x = -(precond @ g[..., None])[..., 0]
        r = -g - matvec(x)
        z = (precond @ r[..., None])[..., 0]
        p = z.copy()
        rz = float((r * z).sum())
        tol = 1e-10 * max(float((g * g).sum()), 1e-30)
        for _ in range(self.config.cg_iterations if smooth else 0):
            if float((r * r).sum()) <= tol:
                break
            Ap = matvec(p)
            alpha = rz / float((p * Ap).sum())
            x += alpha * p
            r -= alpha * Ap
            z = (precond @ r[..., None])[..., 0]
            rz_new = float((r * z).sum())
            p = z + (rz_new / rz) * p
            rz = rz_new
        return x

    # ------------------------------------------------------------------ change handling
    def _handle_track_ids(self, track_ids) -> None:
        if track_ids is None:
            return
        ids = np.asarray(track_ids).reshape(-1)
        if self._track_ids is not None and len(ids) == len(self._track_ids):
            changed = np.flatnonzero(ids != self._track_ids)
            if len(changed):
                if self.locked:
                    self._unassign(changed)
                self._identity[changed] = self._next_identity + np.arange(len(changed))
                self._next_identity += len(changed)
        self._track_ids = ids.copy()

    def _unassign(self, markers: np.ndarray) -> None:
        markers = np.asarray(markers)
        if self.face_ids is None or not len(markers):
            return
        was = self.face_ids[markers] >= 0
        self._end_sightings(markers)
        self.face_ids[markers] = -1
        self.bary[markers] = 0.0
        self._seen_run[markers] = 0
        self._slip_run[markers] = 0
        if was.any():
            self.labels_version += 1
            self._prepare_lock()

    def _change_handling(self, frame: _Frame, lin: dict) -> None:
        c = self.config
        rate = self.rate_hz or 120.0
        vis = frame.visible
        assigned = self.face_ids >= 0
        # slipping markers: residual jump that persists
        dist = np.zeros(len(vis))
        dist[self._assigned] = lin["dist"][0]
        over = vis & assigned & (dist > c.slip_threshold_m)
        storm = bool(over.sum() > c.slip_storm_fraction * max(1, int((vis & assigned).sum())))
        if storm:
            # many markers off at once: the pose is wrong, not the markers - re-assigning them
            # under this pose would corrupt the lock; the degrade check below handles it
            over[:] = False
            self.stats["slip_storms"] = self.stats.get("slip_storms", 0) + 1
        self._slip_run = np.where(over, self._slip_run + 1, np.where(vis, 0, self._slip_run))
        slipped = np.flatnonzero(self._slip_run >= c.slip_frames)
        if c.handover is not None:  # the sightings only serve the handover
            self._remember_sightings([frame], lin)
            first_seen = np.flatnonzero(vis & ~assigned & (self._seen_run == 0))
            if len(first_seen) and self._hand_over(frame, first_seen):
                assigned = self.face_ids >= 0
        # unassigned markers seen long enough
        self._seen_run = np.where(vis & ~assigned, self._seen_run + 1, np.where(assigned, 0, 0))
        fresh = np.flatnonzero(self._seen_run >= c.new_track_frames)
        if len(slipped):
            self.stats["slips"] += len(slipped)
        if len(slipped) or len(fresh):
            self._assign(np.union1d(slipped, fresh), frames=max(c.new_track_frames, c.slip_frames), count_new=len(fresh))
        # whole-fit degradation or a new subject -> re-bootstrap (estimates continue meanwhile)
        n_vis = int(vis.sum())
        bad = storm or (frame.residual > c.degrade_threshold_m) or (n_vis >= 4 and (vis & ~(self.face_ids >= 0)).sum() > 0.5 * n_vis)
        self._degrade_run = self._degrade_run + 1 if bad else 0
        if self._degrade_run >= c.degrade_s * rate and self._boot is None:
            self._boot = self._new_boot_buffer()
            # the markers since the fit went bad are already here (the bootstrap needs markers and
            # priors, not our estimates): start the window with them instead of waiting for all of
            # it.  Not earlier frames: after a marker-set change they belong to the old set.
            bad_frames = min(self._degrade_run, len(self._history), self._boot.maxlen - 1)
            self._boot.extend(list(self._history)[len(self._history) - bad_frames:])
            self._degrade_run = 0
        # A lock made before any video prior had come (a camera started late, a subject facing away
        # from BlazePose's face-based detector) re-bootstraps once priors have come for a bootstrap
        # window: the upgrades and the per-frame prior need a lock on the video's axes, so without
        # it the take ran markers-only to its end (session 38: 115 mm on a 20 s walk whose first
        # 3.2 s had no valid prior).  Recent frames start the window, as above.
        if (not self.has_prior and self._boot is None and self._first_valid_prior is not None
                and self._first_valid_prior <= frame.stamp - int(c.bootstrap_s * 1e9)):
            self._boot = self._new_boot_buffer()
            self._boot.extend(list(self._history)[-min(len(self._history), self._boot.maxlen - 1):])
            self.stats["prior_rebootstraps"] = self.stats.get("prior_rebootstraps", 0) + 1
        # lock upgrade once the take has grown enough since the lock was estimated
        self._poll_upgrade()
        if (c.upgrade_frames > 0 and self._boot is None and self._reservoir_seen >= self._MIN_UPGRADE_FRAMES
                and self._reservoir_seen >= c.upgrade_growth * self._locked_span and not self._upgrades_ended):
            self._upgrade_lock()
        # periodic re-check of every correspondence on the recent window
        self._since_recheck += 1
        self._lock_age += 1
        # A re-check runs Stage 3 under the recent frames' estimates: frames estimated under an
        # earlier lock would pull the points back to that lock's (after a lock upgrade, a re-check
        # on the old lock's estimates re-assigned 16-32 of 40 markers).  Wait for a window of frames
        # estimated under this one.
        if (c.recheck_period_s > 0 and self._since_recheck >= c.recheck_period_s * rate
                and self._lock_age >= c.recheck_frames and not self._recheck_groups):
            self._since_recheck = 0
            self._queue_recheck()

    _NEVER = -(1 << 62)

    def _forget_sightings(self, markers: int = 0) -> None:
        """Per marker column: the frame it was last seen assigned, its point then and its residual in
        the frame of that point's face (``_remember_sightings``), and the ended tracks' ones."""
        self._last_seen = np.full(markers, self._NEVER, dtype=np.int64)
        self._last_face = np.full(markers, -1, dtype=np.int64)
        self._last_bary = np.zeros((markers, 3))
        self._last_local = np.zeros((markers, 3))
        self._ended: list[tuple[int, int, np.ndarray, np.ndarray, int]] = []  # (last seen, face, bary, residual, marker)

    def _remember_sightings(self, frames: list[_Frame], lin: dict) -> None:
        """Each assigned column's last sighting in ``frames`` (the newest frames of the stream, in
        order; lin: ``_linearize`` of them)."""
        a = self._assigned
        seen = np.stack([f.visible[a] for f in frames])  # (B, Ma)
        k = np.flatnonzero(seen.any(axis=0))
        if not len(k):
            return
        last = len(frames) - 1 - np.argmax(seen[::-1, k], axis=0)  # each column's last frame seen
        cols = a[k]
        markers = np.stack([frames[i].markers[c] for i, c in zip(last, cols)])
        local = np.einsum("kij,kj->ki", _triangle_frames(lin["corners"][last, k]), markers - lin["surface"][last, k])
        self._last_seen[cols] = self._index - len(frames) + last
        self._last_face[cols] = self.face_ids[cols]
        self._last_bary[cols] = self.bary[cols]
        self._last_local[cols] = local

    def _repoint_sightings(self) -> None:
        """After a lock adoption the recent sightings and ended tracks keep their frame and marker
        but take the new lock's point of that marker, the marker at rest on its normal: their
        residuals were measured on the old lock's body.  (Forgetting them instead left a marker
        that ended just before an adoption nothing to hand over to.)"""
        rest = np.array([0.0, 0.0, self.config.ik.marker_offset_m])
        held = self.face_ids >= 0
        point = {int(self._identity[m]): m for m in np.flatnonzero(held)[::-1]}  # marker -> a column of it
        keep = (self._last_face >= 0) & held
        self._last_seen[~keep] = self._NEVER
        self._last_face = np.where(keep, self.face_ids, -1)
        self._last_bary[keep] = self.bary[keep]
        self._last_local[keep] = rest
        self._ended = [(seen, int(self.face_ids[point[marker]]), self.bary[point[marker]].copy(), rest.copy(), marker)
                       for seen, _, _, _, marker in self._ended if marker in point]

    def _end_sightings(self, markers: np.ndarray) -> None:
        """Markers whose column now holds another track: their last sightings become ended tracks."""
        for m in np.asarray(markers).reshape(-1):
            if self._last_face[m] >= 0 and self._last_seen[m] != self._NEVER:
                self._ended.append((int(self._last_seen[m]), int(self._last_face[m]), self._last_bary[m].copy(),
                                    self._last_local[m].copy(), int(self._identity[m])))
        self._last_seen[markers] = self._NEVER
        self._last_face[markers] = -1

    def _hand_over(self, frame: _Frame, first_seen: np.ndarray) -> int:
        """Give each column seen for the first time the point of the marker that ended and would be
        where it is (``WindowedSolverConfig.handover``).  Returns how many took one."""
        c = self.config.handover
        now = self._index - 1
        max_gap = c.max_gap_s * (self.rate_hz or 120.0)
        # bounded: ended tracks older than the gap are dropped
        self._ended = [e for e in self._ended if now - e[0] <= max_gap][-4 * len(self.face_ids):]
        cols = np.flatnonzero(~frame.visible & (self._last_face >= 0) & (now - self._last_seen <= max_gap))
        if not len(cols) and not self._ended:
            return 0
        faces = np.concatenate([self._last_face[cols], np.array([e[1] for e in self._ended], dtype=np.int64)])
        bary = np.concatenate([self._last_bary[cols], np.array([e[2] for e in self._ended]).reshape(-1, 3)])
        local = np.concatenate([self._last_local[cols], np.array([e[3] for e in self._ended]).reshape(-1, 3)])
        theta = torch.as_tensor(frame.theta, dtype=torch.float32)[None]
        params = BodyParams(theta[:, :3], theta[:, 3:].reshape(1, 23, 3), torch.as_tensor(frame.trans, dtype=torch.float32)[None],
                            self.betas, torch.tensor(self.yaw, dtype=torch.float32))
        corners = self.model.faces[torch.as_tensor(faces)].reshape(-1)
        with torch.no_grad():
            pc = pose_params(self.model, params, self.up, points=lbs.SurfacePoints.from_vertex_ids(corners)).vertices[0]
        pc = pc.double().numpy().reshape(-1, 3, 3)
        surface = (pc * bary[:, :, None]).sum(1)
        links = handover_links(frame.markers[first_seen], carried_positions(surface, _triangle_frames(pc), local), c.max_handover_m)
        used_ended = set()
        for i, k in links:
            m = first_seen[i]
            self.face_ids[m], self.bary[m] = faces[k], bary[k]
            if k < len(cols):  # the marker goes on in column m: it hands over once
                self._identity[m] = self._identity[cols[k]]
                self._last_seen[cols[k]], self._last_face[cols[k]] = self._NEVER, -1
            else:
                self._identity[m] = self._ended[k - len(cols)][4]
                used_ended.add(k - len(cols))
            frame.identity[m] = self._identity[m]
        if not links:
            return 0
        self._ended = [e for j, e in enumerate(self._ended) if j not in used_ended]
        self.stats["handovers"] = self.stats.get("handovers", 0) + len(links)
        self.labels_version += 1
        self._prepare_lock()
        return len(links)

    def _keep_in_reservoir(self, f: _Frame) -> None:
        """Keep every stride-th refined frame; when full, drop every other one and double the
        stride: the reservoir covers the whole take evenly in bounded memory."""
        c = self.config
        if c.upgrade_frames <= 0:
            return
        if self._reservoir_seen % self._reservoir_stride == 0 and f.visible.sum() >= 4:
            self._reservoir.append(f)
            if len(self._reservoir) > c.upgrade_frames:
                self._reservoir = self._reservoir[::2]
                self._reservoir_stride *= 2
        self._reservoir_seen += 1

    def _upgrade_lock(self) -> None:
        """Start a lock upgrade: the offline staged solver on the reservoir (frames spread over the
        take so far, with their video priors).  Synchronous, or in the worker process (a thread
        when ``worker_process`` is off) when ``upgrade_in_background`` (the estimates go on
        meanwhile; the result is adopted at the first frame after it is ready)."""
        c = self.config
        self._locked_span = self._reservoir_seen
        if not self.has_prior or self._upgrade_job is not None:
            return  # nothing to start Stage 2 from but our own estimates / one already running
        job = self._upgrade_inputs()
        self.stats["upgrades_started"] = self.stats.get("upgrades_started", 0) + 1
        if self._worker is not None and self._worker.broken:
            self._drop_broken_worker()
        if c.upgrade_in_background and self._worker is not None:
            # the worker also judges the result against the current lock (two re-solves of the
            # reservoir, ~0.5 s that stalled the stream when run here at adoption)
            check = (compare_upgrade_locks, (self.config, self.up_axis, self.rate_hz, self._lock_copy(), job["reservoir"]))
            job["worker_job"], future = self._worker.submit(job["markers"], job["visible"], self.rate_hz or 120.0, self.up_axis,
                                                            job["prior"], job["shape"], self._upgrade_config(job), after=check)
            self._upgrade_job = (future, job)
            return
        if c.upgrade_in_background:
            from concurrent.futures import ThreadPoolExecutor

            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="lock-upgrade")
            self._upgrade_job = (self._executor.submit(self._solve_upgrade, job), job)
        else:
            self._finish_upgrade(self._solve_upgrade(job), job)

    def _poll_upgrade(self) -> None:
        if self._upgrade_job is not None and self._upgrade_job[0].done():
            future, job = self._upgrade_job
            self._upgrade_job = None
            try:
                res = future.result()
            except (UpgradeCancelled, SolveCancelled):
                self.stats["upgrades_cancelled"] = self.stats.get("upgrades_cancelled", 0) + 1
                return
            except (ValueError, RuntimeError) as exc:  # e.g. no usable frame: keep the current lock
                if isinstance(exc, BrokenExecutor) and self._worker is not None:
                    self._drop_broken_worker()
                self.stats["upgrade_errors"] = self.stats.get("upgrade_errors", 0) + 1
                self.stats["last_upgrade_error"] = str(exc)
                return
            fits = None
            if "result" in job:  # a judgement again, in the worker (_judge_in_worker)
                res, fits = job["result"], res
            elif "worker_job" in job:
                res, fits = res
            self._finish_upgrade(res, job, fits)

    def _upgrade_inputs(self) -> dict:
        """Copies of everything the upgrade solve reads (the stream goes on while it runs)."""
        frames = list(self._reservoir)
        # the frames' priors carry the current camera tilt: take it out, the solver finds its own
        prior72 = self._swap_prior_tilt(np.stack([f.prior for f in frames]), self.camera_tilt.T)
        shape = self.shape_prior.double().numpy()
        prior = BodyPrior(prior72[:, :3].copy(), prior72[:, 3:].reshape(-1, 23, 3).copy(), np.tile(shape, (len(frames), 1)),
                          np.ones(len(frames), dtype=bool), np.ones(len(frames)), np.array([f.stamp for f in frames], dtype=np.int64),
                          "world")
        markers, visible = np.stack([f.markers for f in frames]), np.stack([f.visible for f in frames])
        # what the lock check reads (_compare_locks): the frames' refined poses and priors under the current lock
        reservoir = {"markers": markers, "visible": visible, "theta": np.stack([f.theta for f in frames]),
                     "trans": np.stack([f.trans for f in frames]), "prior": np.stack([f.prior for f in frames])}
        joined = self._joined_markers(frames, markers, visible)
        if joined is not None:  # the solve sees each marker as one column; its result goes back to the columns
            markers, visible, reservoir["column_owner"] = joined
        return {"markers": markers, "visible": visible, "prior": prior, "shape": shape,
                "generation": self._lock_generation, "labels_version": self.labels_version,
                "cancel": threading.Event(), "t0": time.perf_counter(),
                "stride": self._reservoir_stride, "reservoir": reservoir}

    def _joined_markers(self, frames: list[_Frame], markers: np.ndarray, visible: np.ndarray):
        """The frames' markers with each marker's columns joined into one (``_identity``):
        (F,K,3), (F,K) and the column owner (M,) (-1: a column whose marker is not in the frames),
        or None when every column held one marker throughout (nothing to join)."""
        M = markers.shape[1]
        ids = np.stack([f.identity if f.identity is not None and len(f.identity) == M else np.arange(M) for f in frames])
        if (ids == np.arange(M)).all() and (self._identity == np.arange(M)).all():
            return None
        seen_ids = np.unique(ids[visible])
        slot = np.searchsorted(seen_ids, ids)
        slot_ok = visible & (seen_ids[np.minimum(slot, len(seen_ids) - 1)] == ids) if len(seen_ids) else visible & False
        joined = np.full((len(frames), len(seen_ids), 3), np.nan)
        seen = np.zeros((len(frames), len(seen_ids)), dtype=bool)
        f_idx, c_idx = np.nonzero(slot_ok)
        joined[f_idx, slot[f_idx, c_idx]] = markers[f_idx, c_idx]
        seen[f_idx, slot[f_idx, c_idx]] = True
        pos = np.searchsorted(seen_ids, self._identity)
        owner = np.where((pos < len(seen_ids)) & (seen_ids[np.minimum(pos, len(seen_ids) - 1)] == self._identity), pos, -1)
        return joined, seen, owner

    def _solve_upgrade(self, job: dict):
        return solve(job["markers"], job["visible"], self.rate_hz or 120.0, self.up_axis, job["prior"], job["shape"],
                     self.model, self.chamfer_model, self._upgrade_config(job), progress=_StopWhenStale(self, job))

    def _upgrade_config(self, job: dict) -> SolverConfig:
        c = self.config
        # The reservoir's frames are not consecutive: no smoothness terms.  The staged solver starts
        # Stage 2 from its screening frames interpolated in time, fine while they are a few tenths
        # of a second apart; further apart (a reservoir spread over 40 s) the fits degraded to
        # 11-90 mm, so then every frame is screened (slower, and on short spans it fitted worse:
        # 5.8 vs 3.5 mm on a 5 s walk, hence not always).
        n = len(job["markers"])
        base = c.upgrade_solver or c.bootstrap_solver
        # the bootstrap decided full or partial body and the part; an upgrade refines that lock and
        # never moves the markers to another part (_finish_upgrade), so it does not search for one
        if self.part_joints is None:
            base = replace(base, force_full_body=True)
        else:
            base = replace(base, force_full_body=None, matching=replace(base.matching, part_joints=self.part_joints))
        if self.allowed_ids is not None and c.upgrade_solver is not None:
            # A partial body keeps the bootstrap's Stage-2 shape prior: its few markers see the shape
            # less (session 26, 12 markers, seed 0, walk / jump / arms: right arm part MPJPE 9.70 /
            # 28.12 / 18.10 mm with the bootstrap's 1, 10.08 / 29.40 / 19.86 with 0.1; the walk / jump
            # left leg and shoulder unchanged; the arms take's left leg fails either way, 302.7 / 313.2 mm).
            base = replace(base, pose_fitting=replace(base.pose_fitting,
                                                      shape_weight=c.bootstrap_solver.pose_fitting.shape_weight))
        screening = min(base.screening_frames, n)
        if (n / max(screening, 1)) * job["stride"] / (self.rate_hz or 120.0) > c.upgrade_max_interpolation_s:
            screening = n
        return replace(base, ik=replace(base.ik, smoothness_weight=0.0),
                       pose_fitting=replace(base.pose_fitting, smoothness_weight=0.0),
                       screening_frames=screening, chamfer_frames=n)

    def _finish_upgrade(self, res, job: dict, fits: tuple[float, float] | None = None) -> None:
        """Adopt the upgrade's shape, yaw, tilt and correspondence when it explains the reservoir's
        markers better than the current lock, both judged the same way: the reservoir frames
        re-solved per frame under each lock (``_compare_locks``).  Comparing the staged solver's
        own fit with the refined frames' residuals instead adopted worse locks (those frames were
        fitted to the current lock; the solver's budgets are short) and refused better ones.
        fits: (current, candidate) as the worker process judged them under the lock the upgrade
        started from; used while that is still the lock (else judged there again:
        ``_judge_in_worker``; without a worker, here).
        Dropped when the lock changed meanwhile (a re-bootstrap)."""
        c = self.config
        if (fits is not None and job["labels_version"] != self.labels_version and job["generation"] == self._lock_generation
                and job.get("judgements", 0) < self._MAX_JUDGEMENTS and self._worker is not None and not self._worker.broken):
            self._judge_in_worker(res, job)
            return
        self.stats["upgrades"] = self.stats.get("upgrades", 0) + 1
        self.stats.setdefault("upgrade_seconds", []).append(round(time.perf_counter() - job["t0"], 3))
        if job["generation"] != self._lock_generation:
            self.stats["upgrades_rejected"] = self.stats.get("upgrades_rejected", 0) + 1
            return
        new = self._lock_from(res, job["reservoir"].get("column_owner"))
        if not self._same_part(new[5], self.allowed_ids):
            # An upgrade refines the lock; it does not move the markers to another body part (or
            # between full and partial body): a still leg's mirror image fits its markers as well
            # as the leg itself (session 9: an 8 s arms take with left-leg markers, the second upgrade
            # moved them to the right leg on a better fit, 2.10 -> 1.64 mm).  The bootstrap decided
            # the part with its hypotheses; a wrong part degrades the fit and re-bootstraps.
            self.stats["upgrades_rejected"] = self.stats.get("upgrades_rejected", 0) + 1
            self.stats["upgrades_other_part"] = self.stats.get("upgrades_other_part", 0) + 1
            return
        if fits is not None and job["labels_version"] == self.labels_version:
            current, candidate = fits
            self.stats["upgrade_checks_in_worker"] = self.stats.get("upgrade_checks_in_worker", 0) + 1
        else:  # judged here: no worker, or markers kept being re-assigned while it judged
            current, candidate = self._compare_locks(new, job["reservoir"])
        self.stats.setdefault("upgrade_fit_mm", []).append((round(1000 * current, 2), round(1000 * candidate, 2)))
        if not candidate < c.upgrade_accept_ratio * current:
            self.stats["upgrades_rejected"] = self.stats.get("upgrades_rejected", 0) + 1
            return
        old_yaw = self.yaw
        self._adopt_lock(res, job["reservoir"].get("column_owner"))
        self._reyaw_in_flight(old_yaw)
        self._start_revision()

    # markers re-assigned while the worker judged an upgrade (the re-check re-assigns a marker or two
    # every few seconds; an upgrade runs 15-30 s): judged there again against the lock as it is now,
    # this many times at most, then here (a ~0.5 s stall of the stream)
    _MAX_JUDGEMENTS = 3

    def _judge_in_worker(self, res, job: dict) -> None:
        """Judge the upgrade's result in the worker process again, against the current lock; it is
        adopted or refused when that judgement is back (``_poll_upgrade``)."""
        job["judgements"] = job.get("judgements", 0) + 1
        job["labels_version"] = self.labels_version
        job["result"] = res
        job["worker_job"], future = self._worker.call(judge_locks_in_worker, self.config, self.up_axis, self.rate_hz,
                                                      self._lock_copy(), self._lock_from(res, job["reservoir"].get("column_owner")),
                                                      job["reservoir"])
        self._upgrade_job = (future, job)
        self.stats["upgrade_judged_again"] = self.stats.get("upgrade_judged_again", 0) + 1

    def _lock_copy(self) -> tuple:
        """The current lock (``_LOCK_FIELDS``), copied: a job to the worker is pickled later, on the
        pool's feeder thread, and re-assignments edit the arrays in place."""
        return tuple(copy.deepcopy(getattr(self, name)) for name in self._LOCK_FIELDS)

    @staticmethod
    def _same_part(a, b) -> bool:
        """Whether two locks' allowed vertex ids (None = full body) name the same body part."""
        if a is None or b is None:
            return a is None and b is None
        return np.array_equal(np.sort(np.asarray(a)), np.sort(np.asarray(b)))

    def _compare_locks(self, new: tuple, reservoir: dict) -> tuple[float, float]:
        """(current, candidate): mean marker residual (metres) of the reservoir frames
        (markers (R,M,3), visible (R,M), refined theta (R,72), trans (R,3), priors (R,72) under the
        current lock: ``_upgrade_inputs``) re-solved per frame under the current lock and under the lock
        ``new``, from the same world poses and priors expressed under each lock's yaw and camera
        tilt.  The current lock stays in place."""
        theta, trans, prior = reservoir["theta"], reservoir["trans"], reservoir["prior"]
        current = self._reservoir_fit(reservoir, theta, trans, prior)
        old = tuple(getattr(self, name) for name in self._LOCK_FIELDS)
        self._set_lock(new)
        try:
            theta_new = theta.copy()
            theta_new[:, :3] = self._reyaw(theta[:, :3], old[3], self.yaw)
            prior_new = self._swap_prior_tilt(prior, new[4] @ old[4].T)
            candidate = self._reservoir_fit(reservoir, theta_new, trans, prior_new)
        finally:
            self._set_lock(old)
        return current, candidate

    def _reservoir_fit(self, reservoir: dict, theta: np.ndarray, trans: np.ndarray, prior: np.ndarray) -> float:
        """Mean marker residual (metres) of the reservoir frames re-solved per frame under the
        current lock, from the given start (the same estimator the stream uses)."""
        theta, trans = self._gauss_newton(theta, trans, reservoir["markers"], reservoir["visible"], prior,
                                          self.config.upgrade_check_iterations)
        lin = self._linearize(theta, trans, reservoir["markers"], reservoir["visible"], jacobian=False)
        return float(np.mean(lin["residual"]))

    @staticmethod
    def _swap_prior_tilt(prior72: np.ndarray, swap: np.ndarray) -> np.ndarray:
        out = np.array(prior72, dtype=np.float64)
        if not np.allclose(swap, np.eye(3)) and len(out):
            out[:, :3] = rotation_vectors(swap @ rotation_matrices(out[:, :3]))
        return out

    def _recent(self, frames: int):
        return self._stacked(list(self._history)[-frames:])

    def _stacked(self, frames: list[_Frame]) -> tuple[torch.Tensor, torch.Tensor, BodyParams]:
        """The frames' markers (F,M,3), visibility (F,M) and poses under the current lock, for the
        staged solver's stages."""
        markers = torch.as_tensor(np.stack([f.markers for f in frames]), dtype=torch.float32)
        vis = torch.as_tensor(np.stack([f.visible for f in frames]))
        theta = torch.as_tensor(np.stack([f.theta for f in frames]), dtype=torch.float32)
        params = BodyParams(theta[:, :3].contiguous(), theta[:, 3:].reshape(-1, 23, 3).contiguous(),
                            torch.as_tensor(np.stack([f.trans for f in frames]), dtype=torch.float32), self.betas,
                            torch.tensor(self.yaw, dtype=torch.float32))
        return markers, vis, params

    def _place(self, which: np.ndarray, markers: torch.Tensor, vis: torch.Tensor, params: BodyParams) -> np.ndarray | None:
        """Stage 3 for the markers ``which`` over the given frames (markers (F,M,3), vis (F,M), their
        poses): each one that found a point takes it.  Returns that mask over ``which`` (None: none did)."""
        att = find_marker_surface_points(self.model, markers[:, which], vis[:, which], params, self.up, self.allowed_ids,
                                         self.config.bootstrap_solver.correspondence, self._vertex_faces)
        faces = att.face_ids.numpy()
        ok = faces >= 0
        if not ok.any():
            return None
        self.face_ids[which[ok]] = faces[ok]
        self.bary[which[ok]] = att.bary.double().numpy()[ok]
        return ok

    def _assign(self, which: np.ndarray, frames: int, count_new: int = 0) -> None:
        """Stage 3 for the given markers on the recent frames under the current estimates."""
        which = np.asarray(which)
        ok = self._place(which, *self._recent(frames))
        if ok is None:
            return
        self._seen_run[which] = 0
        self._slip_run[which] = 0
        self.stats["new_tracks"] += count_new
        self.stats["reassigned"] += int(ok.sum())
        self.labels_version += 1
        self._prepare_lock()

    def _queue_recheck(self) -> None:
        """Start a re-check: every marker, in interleaved groups of ``recheck_group_markers`` that
        ``refine_ready`` runs one per hop (``_recheck``)."""
        if len(self._history) < 4:
            return
        self.stats["rechecks"] += 1
        markers = np.arange(len(self.face_ids))
        groups = max(1, math.ceil(len(markers) / self.config.recheck_group_markers))
        self._recheck_groups = deque(markers[g::groups] for g in range(groups))

    def _recheck(self, which: np.ndarray) -> None:
        """Re-run Stage 3 for the assigned markers among ``which`` on ``recheck_samples`` frames
        spread over the recent window; keep a new point only when it fits clearly better than the
        current one."""
        c = self.config
        # markers unassigned since the group was queued (a new track) wait for new_track_frames:
        # the recent frames of their slot may still hold the old track
        which = np.asarray(which, dtype=np.int64)
        which = which[self.face_ids[which] >= 0]
        if len(which) == 0:
            return
        markers, vis, params = self._recent(c.recheck_frames)
        n = markers.shape[0]
        sel = torch.as_tensor(np.unique(np.linspace(0, n - 1, min(n, c.recheck_samples)).round().astype(np.int64)))
        # both points are scored on the same frames
        markers, vis, params = markers[sel][:, which], vis[sel][:, which], params.frames(sel)
        att = find_marker_surface_points(self.model, markers, vis, params, self.up, self.allowed_ids,
                                         c.bootstrap_solver.correspondence, self._vertex_faces)
        whole = self._attachment()
        cur = MarkerAttachment(whole.face_ids[which], whole.bary[which], whole.score_m[which])
        # scored like Stage 3 scores its candidates: distance to the point + the skin offset
        with torch.no_grad():
            posed = predicted_markers(self.model, params, cur, self.up, c.bootstrap_solver.correspondence.marker_offset_m,
                                      c.ik.offset_model)  # (S,len(which),3)
        d = (posed - torch.nan_to_num(markers)).norm(dim=-1)
        w = vis.float()
        current_score = torch.where(w.sum(0) > 0, (d * w).sum(0) / w.sum(0).clamp(min=1), torch.full_like(d[0], float("inf")))
        better = ((att.face_ids >= 0) & (att.score_m < current_score - c.recheck_improvement_m)).numpy()
        if better.any():
            self.face_ids[which[better]] = att.face_ids.numpy()[better]
            self.bary[which[better]] = att.bary.double().numpy()[better]
            self.stats["reassigned"] += int(better.sum())
            self.labels_version += 1
            self._prepare_lock()


def compare_upgrade_locks(res, worker_state: dict, config: WindowedSolverConfig, up_axis: str, rate_hz: float | None,
                          lock: tuple, reservoir: dict) -> tuple[float, float]:
    """Run in the solve worker after a lock upgrade's staged solve (``StagedSolveWorker.submit``'s
    ``after``): ``WindowedSolver._compare_locks`` of the result's lock against ``lock``, the lock
    the upgrade started from, on the reservoir frames.  The stream's process then only adopts.
    A lock-free solver on the same models and config is kept in the worker's cache."""
    new = _lock_free_solver(worker_state, config, up_axis, rate_hz)._lock_from(res, reservoir.get("column_owner"))
    return judge_locks_in_worker(worker_state, None, config, up_axis, rate_hz, lock, new, reservoir)


def judge_locks_in_worker(worker_state: dict, check, config: WindowedSolverConfig, up_axis: str, rate_hz: float | None,
                          lock: tuple, new: tuple, reservoir: dict) -> tuple[float, float]:
    """Run in the solve worker (``StagedSolveWorker.call``; check unused: ~0.5 s):
    ``WindowedSolver._compare_locks`` of the lock ``new`` against ``lock`` on the reservoir frames."""
    solver = _lock_free_solver(worker_state, config, up_axis, rate_hz)
    solver._set_lock(lock)
    return solver._compare_locks(new, reservoir)


def revise_in_worker(worker_state: dict, check, config: WindowedSolverConfig, up_axis: str, rate_hz: float | None,
                     lock: tuple, arrays: dict) -> dict:
    """Run in the solve worker (``StagedSolveWorker.call``) after a lock upgrade was adopted: the
    revision of the frames in ``arrays`` (``_Frame.REVISED_FROM`` stacked; refined under the old
    lock, in capture order) under ``lock``, hop by hop as ``WindowedSolver._revise_step`` does it.
    Returns per frame theta (N,72) and trans (N,3) under the lock, joints (N,24,3), residual (N,)
    and the world root rotation vector root (N,3)."""
    solver = _lock_free_solver(worker_state, config, up_axis, rate_hz)
    solver._set_lock(lock)
    frames = _Frame.from_arrays(arrays)
    solver._revision = {"frames": frames, "pos": 0, "ready": 0}
    results: list[WindowResult] = []
    while solver._revision is not None:
        check()  # cancelled: a re-bootstrap or a newer lock
        results += solver._revise_step()
    return {"theta": np.stack([f.theta for f in frames]), "trans": np.stack([f.trans for f in frames]),
            "joints": np.stack([f.joints for f in frames]), "residual": np.array([f.residual for f in frames]),
            "root": np.stack([r.poses[:3] for r in results])}


def _lock_free_solver(worker_state: dict, config: WindowedSolverConfig, up_axis: str, rate_hz: float | None) -> "WindowedSolver":
    """A solver on the worker's models and this config without a stream (the worker jobs set its
    lock), kept in the worker's cache while the config stays the same."""
    key = (config, up_axis, rate_hz)
    cached = worker_state["cache"].get("lock_free_solver")
    if cached is None or cached[0] != key:
        solver = WindowedSolver(worker_state["model"], replace(config, worker_process=False), up_axis, rate_hz,
                                worker_state["chamfer_model"])
        cached = worker_state["cache"]["lock_free_solver"] = (key, solver)
    return cached[1]
