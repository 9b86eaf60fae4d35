"""The paper's staged UUO solver for a whole session (paper Secs. "Marker-Part Matching" and
"Mocap Solving"): segmentation -> part matching -> Stage 1 yaw hypotheses, each through
Stage 2 (pose fitting), Stage 3 (marker-surface correspondence) and Stage 4 (IK) -> the best
hypothesis by marker-to-surface fit -> Stage 5 (repeat 3-4 with the Stage-4 result as pose prior).

This module only orchestrates; every stage is a pure function in its own module, reused by the
sliding-window solver.

Speed (beyond the paper, which optimises every stage over every frame for up to 10k L-BFGS
iterations): hypotheses are screened through Stages 2-4 on a subsample of frames (a single
hypothesis needs no ranking and stops after its Stage 2); the winner's
chamfer stage runs on a larger subsample and is interpolated to every frame as the IK warm start;
the IK stages (cheap: only the markers' surface points are skinned) run on every frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from uuomocap.solver_core.body_params import (
    BodyParams,
    FreeParameters,
    apply_root_offset,
    MarkerAttachment,
    angle_difference,
    interpolate_params,
    pose_params,
    up_tensor,
)
from uuomocap.solver_core.inverse_kinematics import (
    InverseKinematicsConfig,
    check_offset_model,
    predicted_markers,
    fold_marker_slack,
    solve_inverse_kinematics,
    solve_inverse_kinematics_with_slack,
)
from uuomocap.solver_core.marker_surface_correspondence import (
    CorrespondenceConfig,
    find_marker_surface_points,
    place_on_joints,
)
from uuomocap.solver_core.chamfer import vertex_face_table
from uuomocap.solver_core.cluster_consistency import ClusterConsistencyConfig, inconsistent_markers, seen_span_fraction
from uuomocap.solver_core.part_matching import PartMatch, PartMatchingConfig, full_translation, match_markers_to_part
from uuomocap.solver_core.parts import vertex_dominant_joint
from uuomocap.solver_core.placement_selection import PlacementSelectionConfig, select_marker_placements
from uuomocap.solver_core.pose_fitting import PoseFittingConfig, fit_pose
from uuomocap.solver_core.prior_preparation import BodyPrior
from uuomocap.solver_core.rotations import matrix_to_axis_angle
from uuomocap.solver_core.segmentation import SegmentationConfig, segment_markers
from uuomocap.solver_core.track_stitching import StitchConfig, merge_columns, stitch_columns
from uuomocap.solver_core.weak_segment_correspondence import WeakSegmentConfig, weak_segment_correspondence

STAGES = ("segmentation", "matching", "stage1", "stage2", "stage3", "stage4", "stage5")


@dataclass(frozen=True)
class SolverConfig:
    # Paper Sec. "Step 1: marker segmentation".
    segmentation: SegmentationConfig = SegmentationConfig()
    # Paper Sec. "Step 2: multiple hypothesis testing for part localization".
    matching: PartMatchingConfig = PartMatchingConfig()
    # Paper Sec. "Stage 2: pose fitting".  Shape prior lambda_beta = 0.1 instead of the paper's 1
    # (beyond the paper, as at Stage 4): the video's shape is shrunk and noisy, and the body Stage 2
    # leaves is where Stages 3-5 stay - the points slide with it (13 sessions, 40 markers, MPJPE
    # 10.94 -> 10.55 mm, better on 9; the bench's walk / jump / arms 7.56 / 8.06 / 7.26 -> 7.01 /
    # 7.68 / 7.02; 0.01: 10.59, the bench's three worse).
    # L-BFGS initial step 1.0 instead of the paper's lr 0.1 (beyond the paper): our L-BFGS runs a
    # strong-Wolfe line search (optimization.run_lbfgs), where lr is only the first step tried, and
    # its lenient curvature test accepts a tenth of the quasi-Newton step - the fit crawls and stops
    # on the relative-improvement test far above its minimum.  Session 29 (bench accuracy --suite
    # full --seeds 3, walk / jump / arms, 20 / 30 / 40 / 50 markers, 36 sessions, same machine and
    # day): MPJPE 25.1 / 12.7 / 10.6 / 10.0 -> 25.4 / 12.0 / 10.2 / 8.5 mm, better on 20 sessions,
    # worse on 13; MPJVE level; 17.5 -> 15.6 s per session.  The fit that gets there leans on the
    # markers more than the crawl did (the seed-0 walk: Stage-2 energy 11.5 -> 6.0, MPJPE after Stage
    # 4 12.5 -> 16.5 mm), so the pose prior is lambda_Theta = 2 instead of the paper's 1 (same 36
    # sessions: 25.4 / 12.0 / 10.2 / 8.5 -> 24.8 / 11.7 / 9.8 / 8.3 mm, against the step 0.1 and
    # prior 1 better on 26, worse on 9; PA-MPJPE lower at every count, MPJVE level; 3: 14.06 mm
    # mean against 13.65 with 2 and 14.01 with 1).
    pose_fitting: PoseFittingConfig = PoseFittingConfig(shape_weight=0.1, pose_weight=2.0,
                                                        lbfgs=replace(PoseFittingConfig().lbfgs, lr=1.0))
    # Paper Sec. "Stage 3: marker-vertex correspondence".
    correspondence: CorrespondenceConfig = CorrespondenceConfig(smooth_normals=False)  # as ik.offset_model
    # Paper Sec. "Stage 4: inverse kinematics".  Beyond the paper: a Geman-McClure kernel (1 cm)
    # at Stages 1 and 4, where some correspondences are still wrong and would drag limbs (40-marker
    # walk / jump / arms: 16.4 / 18.5 / 13.0 -> 14.9 / 16.3 / 12.4 mm MPJPE, MPJVE unchanged).
    # Shape prior lambda_beta = 0.1 instead of the paper's 1 (beyond the paper): the video's shape
    # is shrunk and noisy, 40 markers see the body better (10.2 / 9.7 / 9.9 -> 8.1 / 10.5 / 8.3 mm).
    # Facet normals here, though the markers sit along the skin's smooth normal (which the labelled
    # reference uses; inverse_kinematics explains): on 13 sessions the smooth model moved the unlabelled
    # solve's MPJPE 11.51 -> 11.60 mm (10.94 -> 11.07 with the mean-offset term) - its error is the
    # points, not the offset.  Beyond the paper, mean_offset_weight (regularizers.mean_pose_offset_energy):
    # a limb with few markers slides its points and pose together; the video's mean pose picks the
    # place (13 sessions 11.51 -> 10.94 mm; the bench's three 7.98 -> 7.63).
    ik: InverseKinematicsConfig = InverseKinematicsConfig(robust_scale_m=0.01, shape_weight=0.1, offset_model="face_normal",
                                                         mean_offset_weight=1.0)
    # Beyond the paper: the marker model of the fit that ranks the hypotheses, judges each Stage-5
    # round and makes the per-marker placement choice - the smooth normal, which predicts markers at
    # the true pose to 1.0 mm where the facet normal's 2.0 mm blurs the comparison (with the
    # mean-offset term, seed-1 walk / seed-2 walk / seed-2 run: 12.69 / 12.33 / 13.61 mm judged
    # with the facet normal, 12.66 / 12.13 / 12.92 with the smooth one).
    fit_offset_model: str = "smooth_normal"
    # Kernel scale at Stage 5 (None = plain squares: robust there too doubled MPJVE, 37 -> 77 mm/s).
    refinement_robust_scale_m: float | None = None
    # Paper Sec. "Stage 1": yaw offsets tried, degrees about the up axis (also the part-matching starts).
    yaw_hypotheses_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    # Beyond the paper: hypotheses whose registered yaws agree within this are solved once.
    merge_hypotheses_deg: float = 20.0
    # Beyond the paper (speed): screen only this many of them, best registration first (None = all).
    max_hypotheses: int | None = None
    # Beyond the paper (speed): when the next distinct yaw registers more than this many times worse
    # than the best, the registration is decisive and only the best is screened (None = never).
    decisive_registration_ratio: float | None = None
    # Beyond the paper (speed): the same test for a full body only, where part matching's four ICP
    # starts already register the yaw (README: the hypotheses add nothing there).  Nine 40-marker
    # sessions (the bench's three, five 8 s takes, one 15 s walk): every registration decisive, the
    # same winner and MPJPE to the digit, Stage 1 17.5-36.3 -> 3.4-8.7 s.  None = screen them all.
    decisive_full_body_ratio: float | None = 2.0
    # Beyond the paper (speed): frames on which each hypothesis goes through Stages 2-4.
    screening_frames: int = 60
    # Beyond the paper (speed): Stage 2 and Stage 4 settings while screening the hypotheses
    # (None = the stages' own): a ranking can be cheaper than the winner's fit.
    screening_pose_fitting: PoseFittingConfig | None = None
    screening_ik: InverseKinematicsConfig | None = None
    # Beyond the paper (speed): frames of the winner's Stage 2 (interpolated to all frames for IK).
    chamfer_frames: int = 150
    # Paper Sec. "Stage 5": repeat Stages 3-4 once (more rounds are beyond the paper).
    refinement_rounds: int = 1
    # Beyond the paper (MoSh-style latent markers): at Stage 5 each marker may slide off its
    # surface point with this prior scale (metres), jointly with the pose; None = the paper's Stage 5.
    refinement_marker_slack_m: float | None = 0.03
    # Beyond the paper: markers of bones with one marker at or below them are placed under the
    # video prior's rotation of those bones (weak_segment_correspondence explains why).
    weak_segments: WeakSegmentConfig = WeakSegmentConfig()
    # Beyond the paper: in each Stage-5 round, before its IK, each marker may take the point chosen
    # under the video prior's rotation of its bone, where that fits better (placement_selection).
    placement_selection: PlacementSelectionConfig = PlacementSelectionConfig()
    # Beyond the paper: markers of one rigid cluster stay on neighbouring bones (cluster_consistency).
    cluster_consistency: ClusterConsistencyConfig = ClusterConsistencyConfig()
    # Beyond the paper: a second pass through Stages 1-5 with this temporal smoothness weight at
    # Stages 1-2 (pose_fitting's smoothness_weight) when the first pass's Stage-5 marker fit is worse
    # than stage2_smooth_trigger_mm; the pass whose markers fit better wins (None = one pass).
    # 0.03: BTK gait 138 -> 21.5 mm MPJPE (docs/NOTEBOOK.md, sessions 33-34: 0.01 / 0.1 gave 33 / 19 mm).
    stage2_smooth_alternative: float | None = 0.03
    # A right solve fits the markers to 2.6-8.9 mm on the 36 generated sessions and 7.8-10.3 mm on
    # three real captures; the gait capture's slid-apart Stage 2 ends at 21.5 mm.  Below this the
    # second pass is not tried (it would double the solve's time).
    stage2_smooth_trigger_mm: float = 12.0
    # Beyond the paper: an unlabelled export starts a new column each time a marker comes back from
    # an occlusion, and a column seen for a second says little about its point.  After the solve,
    # the columns the solved body shows to be one marker (track_stitching) are joined and the take
    # is solved again on the joined columns; each column takes its marker's result.  Whole columns
    # never link (a link needs one column to end before the next starts), so such takes solve once.
    # Session 46, 'breaks 1%' (40 markers in 117-134 columns, nine 8 s takes): MPJPE 16.1 -> 10.1 mm
    # with the fit check below (whole columns: 10.2), the arms take that had failed 34.2 -> 10.5.  None = off.
    track_stitching: StitchConfig | None = StitchConfig()
    # The second pass is kept unless its markers fit worse than this times the first pass's (Stage-5
    # marker fit).  The same nine: joined columns fit 0.14-0.97x the first pass's on eight, and on the
    # ninth 1.31x with MPJPE 8.7 -> 11.4 mm; a 3 s walk in 87 columns 3.6 -> 12.9 mm fit, 18.9 -> 30.8 MPJPE.
    track_stitching_max_fit_ratio: float = 1.1
    # Beyond the paper (speed): the second pass starts from the first pass's body at Stage 3 (no part
    # matching, Stage 1 or Stage 2) when that body fits its markers to this Stage-5 marker fit (mm) or
    # better; None = the whole pipeline again.  None offline: on a whole take the joined columns' own
    # Stage 2 finds a better body than the first pass's (session 48, 'breaks 1%' walk / jump seeds
    # 0-2: MPJPE 10.0 mm from scratch, 11.9 warm; the walk seed 0 6.7 against 15.6).  The near-online
    # bootstrap turns it on (fast_bootstrap_config).
    track_stitching_warm_below_mm: float | None = None
    # Stop early for the stage ablation: None, "matching", "stage2" or "stage4".
    stop_after: str | None = None
    # None: decide full/partial body from the marker volume (published code); True/False forces it.
    force_full_body: bool | None = None

    def __post_init__(self):
        check_offset_model(self.fit_offset_model)
        # Stage 3 must place points on the offset surface Stage 4 fits them to
        if self.correspondence.method == "surface" and self.ik.offset_model != "distance" and (
                self.correspondence.smooth_normals != (self.ik.offset_model == "smooth_normal")):
            raise ValueError(f"correspondence.smooth_normals={self.correspondence.smooth_normals} does not match "
                             f"ik.offset_model={self.ik.offset_model!r}")


class SolverProgress:
    """Callbacks for progress display; the default does nothing."""

    def stage_start(self, name: str, detail: str = "") -> None:
        pass

    def stage_step(self, name: str, iterations: int, loss: float) -> None:
        pass

    def stage_end(self, name: str, seconds: float) -> None:
        pass


@dataclass
class SolveResult:
    params: BodyParams                       # every marker frame, world frame (yaw kept separate)
    poses: np.ndarray                        # (T,72) world-frame AMASS poses (yaw folded)
    joints: np.ndarray                       # (T,24,3) metres
    attachment: MarkerAttachment             # per-marker face/bary on the output model
    marker_parts: list[str]                  # per marker: dominant joint name ('' unassigned)
    diagnostics: dict = field(default_factory=dict)
    stage_results: dict[str, BodyParams] = field(default_factory=dict)


def preload_lazy_imports() -> None:
    """Import what a first solve would otherwise import on its way: scikit-learn's clustering
    (segmentation) and torch's compiler stack, which ``torch.optim`` pulls in when the first
    optimizer is built.  ~3.5 s on the 2-core CPU; a live solver calls this at start-up so its
    first bootstrap does not pay it mid-take."""
    import sklearn.cluster  # noqa: F401
    import torch._dynamo  # noqa: F401


def _evenly_spaced(indices: np.ndarray, count: int) -> np.ndarray:
    if len(indices) <= count:
        return indices
    return indices[np.unique(np.linspace(0, len(indices) - 1, count).round().astype(int))]


def marker_fit_error(model, markers: torch.Tensor, visible: torch.Tensor, params: BodyParams, attachment: MarkerAttachment, up: torch.Tensor, offset_m: float,
                     offset_model: str = "smooth_normal") -> float:
    """Mean distance (metres) between visible markers and the body's predicted marker positions
    (surface point + offset along the normal): the hypothesis score of Stage 1."""
    with torch.no_grad():
        pred = predicted_markers(model, params, attachment, up, offset_m, offset_model)
        obs = torch.nan_to_num(markers[:, attachment.assigned])
        w = visible[:, attachment.assigned].float()
        dist = (pred - obs).norm(dim=-1)
        return float((dist * w).sum() / w.sum().clamp(min=1.0))


def part_vertex_ids(model, joints: tuple[int, ...]) -> torch.Tensor | None:
    """Vertices of ``model`` whose dominant joint is in ``joints`` (None when that is every joint)."""
    if len(joints) >= int(model.parents.shape[0]):
        return None
    dominant = torch.as_tensor(vertex_dominant_joint(model), dtype=torch.long)
    return torch.nonzero(torch.isin(dominant, torch.tensor(joints))).reshape(-1)


def solved_part_joints(model, diagnostics: dict) -> tuple[int, ...]:
    """Joint indices of the part a solve placed the markers on (its diagnostics), () for a full body."""
    if diagnostics.get("full_body", True):
        return ()
    return tuple(model.joint_names.index(n) for n in diagnostics.get("part_joints", []))


def marker_joint_ids(model, attachment: MarkerAttachment) -> np.ndarray:
    """(M,) dominant joint at each marker's surface point (-1 unassigned)."""
    dominant = torch.as_tensor(vertex_dominant_joint(model), dtype=torch.long)
    out = np.full(len(attachment.face_ids), -1, dtype=np.int64)
    for m, (f, b) in enumerate(zip(attachment.face_ids.tolist(), attachment.bary)):
        if f >= 0:
            out[m] = int(dominant[int(model.faces[f][int(torch.argmax(b))])])
    return out


def enforce_cluster_consistency(model, markers, visible, params, up, attachment: MarkerAttachment, cluster_labels: np.ndarray,
                                allowed_vertex_ids, config: SolverConfig, vertex_faces) -> tuple[MarkerAttachment, int]:
    """Re-assign markers whose body part disagrees with their rigid cluster (cluster_consistency)
    on the vertices of the cluster's joints.  markers (T,M,3), visible (T,M), params for those T
    frames.  Returns (attachment, number of markers moved)."""
    if not config.cluster_consistency.enabled:
        return attachment, 0
    vis_np = visible.numpy() if isinstance(visible, torch.Tensor) else np.asarray(visible)
    judged = seen_span_fraction(vis_np) >= config.cluster_consistency.min_span_fraction
    bad = inconsistent_markers(cluster_labels, marker_joint_ids(model, attachment), model.parents.numpy(), config.cluster_consistency,
                               judged)
    if not bad:
        return attachment, 0
    face_ids, bary, score = attachment.face_ids.clone(), attachment.bary.clone(), attachment.score_m.clone()
    groups: dict[tuple[int, ...], list[int]] = {}
    for m, joints in bad.items():
        groups.setdefault(tuple(int(j) for j in joints), []).append(m)
    moved = 0
    for joints, members in groups.items():
        moved += len(place_on_joints(model, markers, visible, params, up, members, joints, allowed_vertex_ids,
                                     config.correspondence, vertex_faces, face_ids, bary, score,
                                     config.cluster_consistency.max_point_distance_m))
    return MarkerAttachment(face_ids, bary, score), moved


def marker_part_names(model, attachment: MarkerAttachment) -> list[str]:
    """Per marker the name of the dominant joint at its surface point ('' when unassigned)."""
    dominant = torch.as_tensor(vertex_dominant_joint(model), dtype=torch.long)
    names = []
    for f, b in zip(attachment.face_ids.tolist(), attachment.bary):
        if f < 0:
            names.append("")
            continue
        corner = int(model.faces[f][int(torch.argmax(b))])
        names.append(model.joint_names[int(dominant[corner])])
    return names


def solve(
    markers: np.ndarray,
    visible: np.ndarray | None,
    rate_hz: float,
    up_axis: str,
    prior: BodyPrior,
    shape_prior: np.ndarray,
    model,
    chamfer_model=None,
    config: SolverConfig = SolverConfig(),
    progress: SolverProgress | None = None,
) -> SolveResult:
    """Solve a whole session.

    markers (T,M,3) metres in the capture world, NaN where missing; visible (T,M) bool or None
    (= finite); rate_hz: marker rate; up_axis: '+z', '+y', ...; prior: world-frame body prior at
    the marker frames (``prior_preparation.prepare_prior`` or ``neutral_prior``); shape_prior (B,);
    model: output body model (IK, correspondence); chamfer_model: low-resolution model with the same
    skeleton for the chamfer stages (None = ``model``).  With ``config.track_stitching``, columns
    found to be one marker are joined and solved again (``solve_columns`` is one pass).
    """
    first = solve_columns(markers, visible, rate_hz, up_axis, prior, shape_prior, model, chamfer_model, config, progress)
    if config.track_stitching is None or config.stop_after is not None:
        return first
    progress = progress or SolverProgress()
    markers = np.asarray(markers, dtype=np.float64)
    vis = np.isfinite(markers).all(axis=2) if visible is None else (np.asarray(visible, bool) & np.isfinite(markers).all(axis=2))
    progress.stage_start("track_stitching", "joining the columns of one marker")
    t0 = time.perf_counter()
    chains = marker_chains(model, first, markers, vis, rate_hz, config.track_stitching)
    stitch_s = time.perf_counter() - t0
    progress.stage_end("track_stitching", stitch_s)
    if all(len(chain) == 1 for chain in chains):
        return first
    joined, joined_vis = merge_columns(markers, vis, chains)
    again = solve_columns(joined, joined_vis, rate_hz, up_axis, prior, shape_prior, model, chamfer_model, config, progress,
                          start=first if _warm_enough(config, first) else None)
    fits = first.diagnostics["stage5_marker_fit_mm"], again.diagnostics["stage5_marker_fit_mm"]
    if fits[1] > config.track_stitching_max_fit_ratio * fits[0]:
        # the joined pass explains the markers worse: its solve went wrong, not the columns' split
        first.diagnostics["track_stitching"] = {"columns": markers.shape[1], "markers": len(chains), "kept": False,
                                                "joined_marker_fit_mm": fits[1], "chains": [[int(c) for c in chain] for chain in chains]}
        return first
    return _per_column(model, again, chains, markers.shape[1], first, stitch_s)


def _warm_enough(config: SolverConfig, first: SolveResult) -> bool:
    fit = first.diagnostics.get("stage5_marker_fit_mm")
    return config.track_stitching_warm_below_mm is not None and fit is not None and fit <= config.track_stitching_warm_below_mm


def marker_chains(model, result: SolveResult, markers: np.ndarray, visible: np.ndarray, rate_hz: float,
                  config: StitchConfig = StitchConfig()) -> list[list[int]]:
    """Chains of columns that are one marker on ``result``'s solved body (``track_stitching``).

    markers (T,M,3) metres; visible (T,M) bool."""
    from uuomocap.solver_core.gap_fill import solved_marker_positions

    att = result.attachment
    predicted, frames = solved_marker_positions(
        model, result.params.betas.double().numpy(), np.asarray(result.poses, np.float64), result.params.trans.double().numpy(),
        att.face_ids.numpy(), att.bary.double().numpy(), return_frames=True)
    return stitch_columns(markers, visible, predicted, frames, rate_hz, config)


def _per_column(model, joined: SolveResult, chains: list[list[int]], columns: int, first: SolveResult, stitch_s: float) -> SolveResult:
    """The solve of the joined columns, with each column given its chain's marker result."""
    owner = np.empty(columns, dtype=np.int64)
    for k, chain in enumerate(chains):
        owner[chain] = k
    idx = torch.as_tensor(owner)
    att = joined.attachment
    attachment = MarkerAttachment(att.face_ids[idx].clone(), att.bary[idx].clone(), att.score_m[idx].clone())
    diag = dict(joined.diagnostics)
    if "cluster_labels" in diag:
        diag["cluster_labels"] = [diag["cluster_labels"][k] for k in owner]
    d1 = first.diagnostics
    diag["track_stitching"] = {
        "columns": columns, "markers": len(chains), "links": columns - len(chains), "kept": True,
        "first_pass_marker_fit_mm": d1.get("stage5_marker_fit_mm"), "first_pass_seconds": d1.get("total_seconds"),
        "chains": [[int(c) for c in chain] for chain in chains],
    }
    seconds = dict(d1.get("stage_seconds", {}))
    for name, sec in diag.get("stage_seconds", {}).items():
        seconds[name] = round(seconds.get(name, 0.0) + sec, 3)
    seconds["track_stitching"] = round(stitch_s, 3)
    diag["stage_seconds"] = seconds  # both passes
    diag["total_seconds"] = round(sum(seconds.values()), 3)
    return replace(joined, attachment=attachment, marker_parts=[joined.marker_parts[k] for k in owner], diagnostics=diag)


def solve_columns(
    markers: np.ndarray,
    visible: np.ndarray | None,
    rate_hz: float,
    up_axis: str,
    prior: BodyPrior,
    shape_prior: np.ndarray,
    model,
    chamfer_model=None,
    config: SolverConfig = SolverConfig(),
    progress: SolverProgress | None = None,
    start: SolveResult | None = None,
) -> SolveResult:
    """One pass of the staged solver over the columns as given (``solve``'s arguments; no stitching).

    start: a solve of the same frames (other columns allowed) whose body this pass starts from at
    Stage 3 (a warm pass: no part matching, Stage 1 or Stage 2); None = the whole pipeline."""
    progress = progress or SolverProgress()
    chamfer_model = chamfer_model or model
    if config.stop_after not in (None, "matching", "stage2", "stage4"):
        raise ValueError(f"stop_after must be None, 'matching', 'stage2' or 'stage4', got {config.stop_after!r}")
    markers = np.asarray(markers, dtype=np.float64)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise ValueError(f"markers must be (T, M, 3), got {markers.shape}")
    finite = np.isfinite(markers).all(axis=2)
    vis_np = finite if visible is None else (np.asarray(visible, dtype=bool) & finite)
    frames_total, marker_count, _ = markers.shape
    if prior.num_frames != frames_total:
        raise ValueError(f"prior has {prior.num_frames} frames but the markers have {frames_total}")
    if not vis_np.any():
        raise ValueError("no marker is visible in any frame")
    up = up_tensor(up_axis)
    mk = torch.as_tensor(markers, dtype=torch.float32)
    vis = torch.as_tensor(vis_np)
    prior_root = torch.as_tensor(prior.root_orient, dtype=torch.float32)
    prior_body = torch.as_tensor(prior.body_pose, dtype=torch.float32)
    nb = min(int(np.asarray(shape_prior).shape[-1]), model.num_betas, chamfer_model.num_betas)
    beta_prior = torch.as_tensor(np.asarray(shape_prior)[:nb], dtype=torch.float32)
    seconds: dict[str, float] = {}
    losses: dict[str, float] = {}
    diag: dict = {"frames": frames_total, "markers": marker_count, "rate_hz": rate_hz, "up_axis": up_axis}
    stage_results: dict[str, BodyParams] = {}
    all_frames = np.arange(frames_total)
    data_frames = np.flatnonzero(vis_np.any(axis=1))
    vertex_faces = vertex_face_table(model.faces, model.v_template.shape[0])

    def timed(name: str, detail: str = ""):
        class _T:
            def __enter__(self_inner):
                progress.stage_start(name, detail)
                self_inner.t0 = time.perf_counter()
                return self_inner

            def __exit__(self_inner, *exc):
                dt = time.perf_counter() - self_inner.t0
                seconds[name] = seconds.get(name, 0.0) + dt
                progress.stage_end(name, dt)
                return False

        return _T()

    def stepper(name):
        return lambda it, loss: progress.stage_step(name, it, loss)

    # ---- Step 1: segmentation
    with timed("segmentation"):
        labels = segment_markers(markers, vis_np, config.segmentation)
    diag["clusters"] = int(labels.max()) + 1
    diag["cluster_labels"] = labels.tolist()

    if start is None:
        # ---- Step 2: part matching (yaw starts = the Stage-1 hypotheses)
        match_cfg = replace(config.matching, yaw_starts_deg=tuple(config.yaw_hypotheses_deg))
        with timed("matching"):
            match = match_markers_to_part(
                chamfer_model, mk, vis, prior_root, prior_body, beta_prior, labels, up, match_cfg, config.force_full_body
            )
        losses["matching"] = match.error
        diag.update(_match_diagnostics(model, match))
        part_chamfer_ids = None if match.full_body else torch.as_tensor(match.vertex_ids, dtype=torch.long)
        part_output_ids = None if match.full_body else part_vertex_ids(model, match.joints)
        betas0 = torch.as_tensor(match.betas, dtype=torch.float32)
        matched = BodyParams(
            apply_root_offset(prior_root, torch.as_tensor(match.tilt, dtype=torch.float32)), prior_body.clone(),
            torch.as_tensor(match.trans, dtype=torch.float32), betas0, torch.tensor(match.yaw),
        )
        stage_results["matching"] = matched
        if config.stop_after == "matching":
            return _finish(model, matched, None, diag, seconds, losses, stage_results, up)

    def stages_1_to_5(pose_fitting_config: PoseFittingConfig, match: PartMatch, prior_root: torch.Tensor,
                      part_chamfer_ids, part_output_ids, diag: dict, losses: dict, stage_results: dict) -> SolveResult:
        """Stages 1-5 after part matching with this Stage-2 configuration (its own diagnostics)."""
        # ---- Stage 1: yaw hypotheses, each through Stages 2-4 on a subsample of frames.  For a
        # partial body the next-best part candidates come along with their own yaw hypotheses
        # (beyond the paper: with the pose fixed to a noisy prior, matching alone often prefers a
        # large torso surface over the arm the markers are on; after IK the true part fits best).
        candidates = [match] + list(match.alternatives)
        hypotheses = [(cand, yaw, tilt) for cand in candidates
                      for yaw, tilt in _screened_hypotheses(_distinct_hypotheses(cand, config.merge_hypotheses_deg),
                                                            config.max_hypotheses if cand is match else 2, _decisive_ratio(config, cand))]
        screen = _evenly_spaced(data_frames, config.screening_frames)
        screen_t = torch.as_tensor(screen)
        screen_pf = config.screening_pose_fitting or pose_fitting_config
        screen_ik = config.screening_ik or config.ik
        results = []
        with timed("stage1", f"{len(hypotheses)} hypotheses"):
            for cand, hyp_yaw, hyp_tilt in hypotheses:
                cand_chamfer_ids = None if cand.full_body else torch.as_tensor(cand.vertex_ids, dtype=torch.long)
                cand_output_ids = None if cand.full_body else part_vertex_ids(model, cand.joints)
                cand_betas = torch.as_tensor(cand.betas, dtype=torch.float32)
                yaw_t = torch.tensor(hyp_yaw)
                root_h = apply_root_offset(prior_root[screen_t], torch.as_tensor(hyp_tilt, dtype=torch.float32))
                trans = full_translation(
                    chamfer_model, mk[screen_t], vis[screen_t], root_h, prior_body[screen_t], cand_betas, up, cand.vertex_ids, yaw_t,
                )
                init = BodyParams(root_h.clone(), prior_body[screen_t].clone(), trans, cand_betas.clone(), yaw_t)
                p2, _, tilt = fit_pose(
                    chamfer_model, mk[screen_t], vis[screen_t], root_h, prior_body[screen_t], beta_prior, init, up,
                    cand_chamfer_ids, screen_pf, rate_hz=rate_hz, on_step=stepper("stage1"),
                )
                tilt = tilt @ torch.as_tensor(hyp_tilt, dtype=torch.float32)  # total tilt of this hypothesis
                err = math.nan
                if len(hypotheses) > 1:
                    # Stages 3-4 on the screening frames only rank the hypotheses (the winner goes on from
                    # its Stage 2): a single hypothesis skips them (same result; bootstrap Stage 1 1.1-1.5 -> 0.8-1.0 s)
                    tilted_root = apply_root_offset(prior_root[screen_t], tilt)
                    att = find_marker_surface_points(
                        model, mk[screen_t], vis[screen_t], p2, up, cand_output_ids, config.correspondence, vertex_faces
                    )
                    p4, _ = solve_inverse_kinematics(
                        model, mk[screen_t], vis[screen_t], att, tilted_root, prior_body[screen_t], beta_prior, p2, up,
                        screen_ik, FreeParameters(yaw=False), rate_hz=rate_hz, on_step=stepper("stage1"),
                    )
                    err = marker_fit_error(model, mk[screen_t], vis[screen_t], p4, att, up, config.ik.marker_offset_m, config.fit_offset_model)
                results.append({"yaw": hyp_yaw, "fit_m": err, "stage2": p2, "stage2_yaw": float(p2.yaw), "tilt": tilt,
                                "match": cand})
        best = min(results, key=lambda r: r["fit_m"])
        diag["hypotheses"] = [
            {"start_yaw_deg": math.degrees(r["yaw"]), "stage2_yaw_deg": math.degrees(r["stage2_yaw"]) % 360.0, "marker_fit_mm": None if math.isnan(r["fit_m"]) else 1000 * r["fit_m"],
             "part_joints": [model.joint_names[j] for j in r["match"].joints] if not r["match"].full_body else "full body"}
            for r in results
        ]
        diag["chosen_yaw_deg"] = math.degrees(best["stage2_yaw"]) % 360.0
        if best["match"] is not match:
            match = best["match"]
            diag["part_joints"] = [model.joint_names[j] for j in match.joints]
            diag["part_chosen_by"] = "stage1"
            part_chamfer_ids = torch.as_tensor(match.vertex_ids, dtype=torch.long)
            part_output_ids = part_vertex_ids(model, match.joints)

        # ---- Stage 2 for the winner on more frames, warm-started from its screening result
        # (the tilt found while screening is kept in the prior's roots; Stage 2 may refine it)
        prior_root = apply_root_offset(prior_root, best["tilt"])
        chamfer_frames = _evenly_spaced(data_frames, config.chamfer_frames)
        cf_t = torch.as_tensor(chamfer_frames)
        with timed("stage2"):
            init = interpolate_params(best["stage2"], screen, chamfer_frames)
            p2, rep, tilt = fit_pose(
                chamfer_model, mk[cf_t], vis[cf_t], prior_root[cf_t], prior_body[cf_t], beta_prior, init, up,
                part_chamfer_ids, pose_fitting_config, rate_hz=rate_hz, on_step=stepper("stage2"),
            )
        losses["stage2"] = rep.final_loss
        prior_root = apply_root_offset(prior_root, tilt)
        camera_tilt = tilt @ best["tilt"]
        diag["camera_tilt_deg"] = math.degrees(float(matrix_to_axis_angle(camera_tilt).norm()))
        # (3,3) rotation premultiplying every prior root (before the yaw): consumers that keep using
        # the video prior after this solve (the windowed solver) must tilt their priors the same way
        diag["camera_tilt"] = camera_tilt.tolist()
        stage2_all = interpolate_params(p2, chamfer_frames, all_frames)
        stage_results["stage2"] = stage2_all
        if config.stop_after == "stage2":
            return _finish(model, stage2_all, None, diag, seconds, losses, stage_results, up, markers=mk, visible=vis, vertex_faces=vertex_faces, allowed=part_output_ids, corr_cfg=config.correspondence)
        return stages_3_to_5(p2, cf_t, stage2_all, prior_root, part_output_ids, diag, losses, stage_results)

    def stages_3_to_5(p2: BodyParams, cf_t: torch.Tensor, stage2_all: BodyParams, prior_root: torch.Tensor, part_output_ids,
                      diag: dict, losses: dict, stage_results: dict) -> SolveResult:
        """Stages 3-5 from a Stage-2 body: p2 on the frames cf_t (Stage 3's), stage2_all on every
        frame (Stage 4's start); prior_root: the prior's roots with the camera tilt applied."""
        # ---- Stage 3 + Stage 4 on every frame
        with timed("stage3"):
            att = find_marker_surface_points(model, mk[cf_t], vis[cf_t], p2, up, part_output_ids, config.correspondence, vertex_faces)
            att, moved = enforce_cluster_consistency(model, mk[cf_t], vis[cf_t], p2, up, att, labels, part_output_ids, config, vertex_faces)
            diag["cluster_consistency_moved"] = moved
            att, weak_moved = weak_segment_correspondence(
                model, mk[cf_t], vis[cf_t], p2, prior_body[cf_t], up, att, marker_joint_ids(model, att), part_output_ids,
                config.correspondence, vertex_faces, config.weak_segments,
            )
            diag["weak_segment_markers"] = weak_moved
        with timed("stage4"):
            p4, rep = solve_inverse_kinematics(
                model, mk, vis, att, prior_root, prior_body, beta_prior, stage2_all, up, config.ik,
                FreeParameters(yaw=False), rate_hz=rate_hz, on_step=stepper("stage4"), bias_prior=prior_body,
            )
        losses["stage4"] = rep.final_loss
        stage_results["stage4"] = p4
        diag["stage4_marker_fit_mm"] = 1000 * marker_fit_error(model, mk, vis, p4, att, up, config.ik.marker_offset_m, config.fit_offset_model)
        if config.stop_after == "stage4":
            return _finish(model, p4, att, diag, seconds, losses, stage_results, up)

        # ---- Stage 5: repeat Stages 3-4 with the previous result as the pose prior
        refine_ik = replace(config.ik, robust_scale_m=config.refinement_robust_scale_m)

        def refine(params: BodyParams, attachment: MarkerAttachment, markers_t: torch.Tensor, visible_t: torch.Tensor,
                   frames: torch.Tensor | None = None, max_iterations: int | None = None):
            """Stage 5's IK (pose prior = ``params``), with latent markers folded back into points;
            ``frames``: which of the session's frames ``markers_t`` holds (None = all);
            ``max_iterations``: its L-BFGS budget (None = ``config.ik``'s)."""
            bias = prior_body if frames is None else prior_body[frames]
            ik_cfg = refine_ik if max_iterations is None else replace(
                refine_ik, lbfgs=replace(refine_ik.lbfgs, max_iterations=max_iterations))
            if config.refinement_marker_slack_m is None:
                out, rep = solve_inverse_kinematics(
                    model, markers_t, visible_t, attachment, params.root_orient, params.body_pose, beta_prior, params, up,
                    ik_cfg, FreeParameters(yaw=False), rate_hz=rate_hz, on_step=stepper("stage5"), bias_prior=bias,
                )
            else:
                ik_cfg = replace(ik_cfg, marker_slack_m=config.refinement_marker_slack_m)
                out, rep, disp = solve_inverse_kinematics_with_slack(
                    model, markers_t, visible_t, attachment, params.root_orient, params.body_pose, beta_prior, params, up,
                    ik_cfg, FreeParameters(yaw=False), rate_hz=rate_hz, on_step=stepper("stage5"), bias_prior=bias,
                )
                attachment = fold_marker_slack(model, out.betas, attachment, disp, vertex_faces)
            losses["stage5"] = rep.final_loss
            return out, attachment

        current, current_att = p4, att
        current_fit = diag["stage4_marker_fit_mm"] / 1000
        sel = torch.as_tensor(_evenly_spaced(data_frames, config.placement_selection.frames))
        with timed("stage5", f"{config.refinement_rounds} round(s)"):
            for _ in range(config.refinement_rounds):
                start, start_att, start_loss = current, current_att, losses.get("stage5")
                current_att = find_marker_surface_points(
                    model, mk, vis, current, up, part_output_ids, config.correspondence, vertex_faces, previous=current_att
                )
                current_att, moved = enforce_cluster_consistency(model, mk, vis, current, up, current_att, labels, part_output_ids,
                                                                 config, vertex_faces)
                diag["cluster_consistency_moved"] = diag.get("cluster_consistency_moved", 0) + moved
                current_att, weak_moved = weak_segment_correspondence(
                    model, mk, vis, current, prior_body, up, current_att, marker_joint_ids(model, current_att), part_output_ids,
                    config.correspondence, vertex_faces, config.weak_segments,
                )
                diag["weak_segment_markers"] = weak_moved
                if config.placement_selection.enabled:
                    current_att, took = select_marker_placements(
                        model, mk[sel], vis[sel], current.frames(sel), current_att, marker_joint_ids(model, current_att),
                        prior_body[sel], up, part_output_ids, config.correspondence, vertex_faces,
                        lambda p, a, m, v: refine(p, a, m, v, frames=sel, max_iterations=config.placement_selection.max_iterations),
                        refine_ik.marker_offset_m, config.fit_offset_model,
                    )
                    diag["prior_placement_markers"] = took
                current, current_att = refine(current, current_att, mk, vis)
                fit = marker_fit_error(model, mk, vis, current, current_att, up, config.ik.marker_offset_m, config.fit_offset_model)
                if fit > current_fit:
                    # Beyond the paper: a round that explains the markers worse than its start failed (a
                    # seed-1 turn: fit 9.7 -> 11.2 mm, MPJPE 14.9 -> 24.0 mm).  Its new points are what
                    # failed: the IK alone on the start's points, kept if it fits, still takes out Stage
                    # 4's robust-kernel jitter (the turn: 14.9 mm / 109 mm/s at Stage 4 -> 9.6 / 36).
                    diag["stage5_rounds_reverted"] = diag.get("stage5_rounds_reverted", 0) + 1
                    current, current_att = refine(start, start_att, mk, vis)
                    fit = marker_fit_error(model, mk, vis, current, current_att, up, config.ik.marker_offset_m, config.fit_offset_model)
                    if fit > current_fit:
                        current, current_att = start, start_att
                        if start_loss is None:  # the loss reported is the kept round's (none kept: no Stage-5 loss)
                            losses.pop("stage5", None)
                        else:
                            losses["stage5"] = start_loss
                    else:
                        current_fit = fit
                        diag["stage5_rounds_kept_points"] = diag.get("stage5_rounds_kept_points", 0) + 1
                    break
                current_fit = fit
        stage_results["stage5"] = current
        diag["stage5_marker_fit_mm"] = 1000 * current_fit
        return _finish(model, current, current_att, diag, seconds, losses, stage_results, up)

    def _warm_pass(start: SolveResult) -> SolveResult:
        """Stages 3-5 from ``start``'s body: its part, yaw and camera tilt, its final poses as
        Stage 2's (no part matching, no hypotheses, no chamfer fit)."""
        d0 = start.diagnostics
        diag.update({k: d0[k] for k in _WARM_CARRIED if k in d0})
        diag["warm_start"] = True
        joints = solved_part_joints(model, d0)
        part_output_ids = part_vertex_ids(model, joints) if joints else None
        tilted_root = apply_root_offset(prior_root, torch.as_tensor(d0.get("camera_tilt", np.eye(3)), dtype=torch.float32))
        params = start.params
        stage_results["stage2"] = params
        cf_t = torch.as_tensor(_evenly_spaced(data_frames, config.chamfer_frames))
        return stages_3_to_5(params.frames(cf_t), cf_t, params, tilted_root, part_output_ids, diag, losses, stage_results)

    def run(pose_fitting_config: PoseFittingConfig) -> SolveResult:
        return stages_1_to_5(pose_fitting_config, match, prior_root, part_chamfer_ids, part_output_ids,
                             dict(diag), dict(losses), dict(stage_results))

    if start is not None:
        return _warm_pass(start)
    result = run(config.pose_fitting)
    if (config.stage2_smooth_alternative is None or config.stop_after is not None
            or result.diagnostics["stage5_marker_fit_mm"] <= config.stage2_smooth_trigger_mm):
        return result
    # Beyond the paper: Stage 2 fits each frame on its own, and where the markers are few or sit on
    # the lower body the frames can slide apart into bodies that still fit their chamfer (the BTK
    # gait capture: Stage-5 marker fit 21.5 mm, MPJPE 138 mm); with a smoothness term across
    # frames (at the screening too) the same capture fits to 7.7 mm / 21.5 mm, but the term costs
    # where Stage 2 was right (Hamner run 14 -> 30 mm).  Both go through Stages 1-5 and the better
    # marker fit wins (README, "Real captures"; docs/NOTEBOOK.md, session 34).
    alternative = run(replace(config.pose_fitting, smoothness_weight=config.stage2_smooth_alternative))
    fits = (result.diagnostics["stage5_marker_fit_mm"], alternative.diagnostics["stage5_marker_fit_mm"])
    chosen = alternative if fits[1] < fits[0] else result
    chosen.diagnostics["stage2_alternative"] = {"smoothness_weight": config.stage2_smooth_alternative,
                                                "marker_fit_mm": fits[1], "without_mm": fits[0],
                                                "chosen": chosen is alternative}
    chosen.diagnostics["stage_seconds"] = {k: round(v, 3) for k, v in seconds.items()}  # both passes
    chosen.diagnostics["total_seconds"] = round(sum(seconds.values()), 3)
    return chosen


# what a warm pass (solve_columns' ``start``) takes over from the solve it starts from
_WARM_CARRIED = ("full_body", "volume_ratio", "part_joints", "part_candidates_tested", "matching_yaw_deg", "matching_energy",
                 "yaw_starts", "hypotheses", "chosen_yaw_deg", "camera_tilt_deg", "camera_tilt")


def _distinct_hypotheses(match: PartMatch, merge_deg: float) -> list[tuple[float, np.ndarray, float]]:
    """(yaw, tilt, registration energy) from each start, best first, dropping near-duplicate yaws."""
    ordered = sorted(match.yaw_starts, key=lambda s: s.error)
    kept: list[tuple[float, np.ndarray, float]] = []
    for s in ordered:
        if all(angle_difference(s.yaw, k[0]) > math.radians(merge_deg) for k in kept):
            kept.append((s.yaw, s.tilt, float(s.error)))
    return kept


def _decisive_ratio(config: SolverConfig, cand: PartMatch) -> float | None:
    if config.decisive_registration_ratio is not None:
        return config.decisive_registration_ratio
    return config.decisive_full_body_ratio if cand.full_body else None


def _screened_hypotheses(distinct: list, limit: int | None, decisive_ratio: float | None) -> list[tuple[float, np.ndarray]]:
    """(yaw, tilt) of the hypotheses Stage 1 screens: the best ``limit`` registrations, or only the
    best when the next one's registration energy is over ``decisive_ratio`` times the best's."""
    kept = distinct[:limit]
    if decisive_ratio is not None and len(kept) > 1 and kept[1][2] > decisive_ratio * kept[0][2]:
        kept = kept[:1]
    return [(yaw, tilt) for yaw, tilt, _ in kept]


def _match_diagnostics(model, match: PartMatch) -> dict:
    names = model.joint_names
    return {
        "full_body": match.full_body,
        "volume_ratio": match.volume_ratio,
        "part_joints": [names[j] for j in match.joints],
        "part_candidates_tested": match.candidates_tested,
        "matching_yaw_deg": math.degrees(match.yaw) % 360.0,
        "matching_energy": match.error,
        "yaw_starts": [
            {"start_deg": s.start_deg, "yaw_deg": math.degrees(s.yaw) % 360.0, "energy": s.error} for s in match.yaw_starts
        ],
    }


def _finish(model, params, attachment, diag, seconds, losses, stage_results, up, markers=None, visible=None, vertex_faces=None, allowed=None, corr_cfg=None) -> SolveResult:
    if attachment is None:
        if markers is not None:
            # Stage-2 snapshot: label markers with the Stage-3 rule on that body
            attachment = find_marker_surface_points(model, markers, visible, params, up, allowed, corr_cfg, vertex_faces)
        else:
            m = len(diag.get("cluster_labels", []))
            attachment = MarkerAttachment(torch.full((m,), -1, dtype=torch.long), torch.zeros(m, 3), torch.full((m,), float("inf")))
    with torch.no_grad():
        joints = pose_params(model, params, up, points=_no_points(model)).joints.double().numpy()
    diag["stage_seconds"] = {k: round(v, 3) for k, v in seconds.items()}
    diag["total_seconds"] = round(sum(seconds.values()), 3)
    diag["stage_losses"] = losses
    return SolveResult(
        params=params,
        poses=params.poses72(up),
        joints=joints,
        attachment=attachment,
        marker_parts=marker_part_names(model, attachment),
        diagnostics=diag,
        stage_results=stage_results,
    )


def _no_points(model):
    """A one-vertex subset: joints without skinning the whole mesh."""
    from uuomocap.solver_core import lbs

    return lbs.SurfacePoints.from_vertex_ids(torch.zeros(1, dtype=torch.long))
