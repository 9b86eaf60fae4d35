"""Fit the body model to BlazePose 3D world landmarks: per-frame pose, clip shape, camera-frame root.

BlazePose gives 33 metric landmarks per frame, hip-centred, in camera-aligned axes
(x right, y down, z away from the camera = the OpenCV camera frame).  The solver
wants body-model parameters, so we fit them:

1. shape: the median bone lengths over the clip (upper arm, forearm, thigh, shin,
   torso; left and right averaged) are matched by the rest-pose joints of the
   body model, with a ridge prior on the betas;
2. pose: every valid frame at once, with L-BFGS, minimising
   * joint-to-landmark distances (joints that have a landmark counterpart,
     weighted by the landmark's visibility and by how well the two definitions
     agree),
   * head / foot / hand direction terms (the landmarks there are surface points,
     not joints: we match directions, not positions),
   * a temporal term on joint accelerations and rotation velocities (BlazePose
     jitters frame to frame; the body moves smoothly),
   * a small pose prior pulling body_pose towards the rest pose (the joint
     positions leave limb twist unobserved).
   The root orientation starts from the hip/shoulder frame of the landmarks.

Frames without landmarks are not fitted; the caller marks them invalid (the
solver's prior preparation fills them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uuomocap.solver_core import rotations
from uuomocap.solver_core.lbs import SurfacePoints, forward

# BlazePose landmark indices used below.
NOSE, L_EAR, R_EAR = 0, 7, 8
L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 11, 12, 13, 14, 15, 16
L_PINKY, R_PINKY, L_INDEX, R_INDEX = 17, 18, 19, 20
L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE = 23, 24, 25, 26, 27, 28
L_HEEL, R_HEEL, L_FOOT_INDEX, R_FOOT_INDEX = 29, 30, 31, 32

# (SMPL joint, landmark indices averaged, weight).  Weights < 1 where the landmark is a
# surface point near, not at, the joint (hip landmarks sit higher/wider than the hip
# joints, the head joint is below the ears, the foot joint is behind the toe tip).
JOINT_LANDMARKS: tuple[tuple[int, tuple[int, ...], float], ...] = (
    (16, (L_SHOULDER,), 1.0), (17, (R_SHOULDER,), 1.0),
    (18, (L_ELBOW,), 1.0), (19, (R_ELBOW,), 1.0),
    (20, (L_WRIST,), 1.0), (21, (R_WRIST,), 1.0),
    (1, (L_HIP,), 0.7), (2, (R_HIP,), 0.7),
    (4, (L_KNEE,), 1.0), (5, (R_KNEE,), 1.0),
    (7, (L_ANKLE,), 1.0), (8, (R_ANKLE,), 1.0),
    (10, (L_FOOT_INDEX,), 0.3), (11, (R_FOOT_INDEX,), 0.3),
    (22, (L_PINKY, L_INDEX), 0.3), (23, (R_PINKY, R_INDEX), 0.3),
    (15, (L_EAR, R_EAR), 0.5),
)
# Spine1/2/3, neck and the collars: between landmarks, so only the prior decides how a bend
# is spread over them.
UNOBSERVED_JOINTS = (3, 6, 9, 12, 13, 14)
# Bones for the shape fit: (name, (joint a, joint b) pairs, (landmark a, landmark b) pairs),
# left and right pooled.
SHAPE_BONES = (
    ("upper_arm", ((16, 18), (17, 19)), ((L_SHOULDER, L_ELBOW), (R_SHOULDER, R_ELBOW))),
    ("forearm", ((18, 20), (19, 21)), ((L_ELBOW, L_WRIST), (R_ELBOW, R_WRIST))),
    ("thigh", ((1, 4), (2, 5)), ((L_HIP, L_KNEE), (R_HIP, R_KNEE))),
    ("shin", ((4, 7), (5, 8)), ((L_KNEE, L_ANKLE), (R_KNEE, R_ANKLE))),
)
# Left/right bone pairs reported as a symmetry check (landmark indices).
SYMMETRY_BONES = {
    "upper_arm": ((L_SHOULDER, L_ELBOW), (R_SHOULDER, R_ELBOW)),
    "forearm": ((L_ELBOW, L_WRIST), (R_ELBOW, R_WRIST)),
    "thigh": ((L_HIP, L_KNEE), (R_HIP, R_KNEE)),
    "shin": ((L_KNEE, L_ANKLE), (R_KNEE, R_ANKLE)),
}


@dataclass(frozen=True)
class LandmarkFitConfig:
    """Weights of the landmark fit (ours: the paper takes its prior from HMR2.0 instead)."""

    num_betas: int = 10  # shape components fitted (bone lengths constrain only a few)
    shape_prior: float = 1e-2  # ridge on betas against 4 pooled relative bone-length errors
    min_visibility: float = 0.5  # landmarks below this do not vote for bone lengths
    # Weights relative to the data term, a mean squared joint distance in m^2 (1 cm -> 1e-4);
    # tuned on the running clip so the fit stays within ~1 mm of its data-only residual
    # while the joint jitter (mean |acceleration|) drops ~3x.
    pose_prior: float = 2e-5  # L2 on body_pose axis-angle (rad^2 per joint), keeps limb twist sane
    smooth_accel: float = 0.5  # mean squared joint acceleration (m per frame^2)
    smooth_rot: float = 1e-3  # mean squared joint rotation velocity (Frobenius, per frame)
    direction: float = 1e-3  # head / hand / foot direction terms (1 - cos)
    # Joints no landmark pins down (spine, neck, collars): their rotation is shared with
    # their neighbours at will, so the prior on them is stiffer.
    unobserved_prior_scale: float = 100.0  # PA-MPJPE on rendered run 71 -> 62 mm, walk 90 -> 87 mm
    iterations: int = 150  # L-BFGS function evaluations (~2 s for 180 frames on one core)
    lr: float = 1.0


@dataclass(frozen=True)
class LandmarkFit:
    """Result for F frames.  Arrays are numpy float64 unless noted.

    global_orient (F, 3) axis-angle mapping the canonical body into the camera frame;
    body_pose (F, 23, 3); betas (nb,); joints (F, 24, 3) pelvis-centred, camera axes;
    residual (F,) metres (weighted RMS joint-landmark distance); valid (F,) bool.
    """

    global_orient: np.ndarray
    body_pose: np.ndarray
    betas: np.ndarray
    joints: np.ndarray
    residual: np.ndarray
    valid: np.ndarray


def bone_lengths(world: np.ndarray, visibility: np.ndarray, valid: np.ndarray, bones, min_visibility: float = 0.5
                 ) -> np.ndarray:
    """Median length over valid frames of each (a, b) landmark pair in ``bones``.

    world: (F, 33, 3); visibility: (F, 33); valid: (F,) bool -> (len(bones),) metres, NaN if never seen.
    """
    out = []
    for a, b in bones:
        seen = valid & (visibility[:, a] >= min_visibility) & (visibility[:, b] >= min_visibility)
        lengths = np.linalg.norm(world[seen, a] - world[seen, b], axis=-1)
        out.append(float(np.median(lengths)) if len(lengths) else np.nan)
    return np.asarray(out)


def symmetry_report(world: np.ndarray, visibility: np.ndarray, valid: np.ndarray, min_visibility: float = 0.5
                    ) -> dict[str, dict[str, float]]:
    """Left vs right median bone lengths of the landmarks: {bone: {left, right, rel_diff}}."""
    report = {}
    for name, (left, right) in SYMMETRY_BONES.items():
        lengths = bone_lengths(world, visibility, valid, (left, right), min_visibility)
        report[name] = {"left": lengths[0], "right": lengths[1],
                        "rel_diff": float(abs(lengths[0] - lengths[1]) / max(lengths.mean(), 1e-9))}
    return report


def _joints(model, betas: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Joints (B, 24, 3) and global joint rotations (B, 24, 3, 3) without evaluating the mesh."""
    out = forward(model, betas, pose, points=SurfacePoints.from_vertex_ids([0]), pose_blend=False)
    return out.joints, out.joint_rotations


def fit_shape(model, world: np.ndarray, visibility: np.ndarray, valid: np.ndarray,
              config: LandmarkFitConfig = LandmarkFitConfig()) -> np.ndarray:
    """Betas (nb,) whose rest-pose bone lengths match the clip's median landmark bone lengths."""
    nb = min(config.num_betas, model.num_betas)
    targets, pairs = [], []
    for _name, joint_pairs, landmark_pairs in SHAPE_BONES:
        lengths = bone_lengths(world, visibility, valid, landmark_pairs, config.min_visibility)
        if np.isfinite(lengths).any():
            targets.append(float(np.nanmean(lengths)))
            pairs.append(joint_pairs)
    if not targets:
        return np.zeros(nb)
    target = torch.tensor(targets, dtype=torch.float32)
    betas = torch.zeros(1, nb, requires_grad=True)
    rest_pose = torch.zeros(1, 24, 3)
    opt = torch.optim.LBFGS([betas], lr=1.0, max_iter=100, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        joints = _joints(model, betas, rest_pose)[0][0]
        lengths = torch.stack([
            torch.stack([(joints[a] - joints[b]).norm() for a, b in jp]).mean() for jp in pairs])
        loss = (((lengths - target) / target) ** 2).sum() + config.shape_prior * (betas ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return betas.detach()[0].double().numpy()


def root_from_landmarks(world: np.ndarray) -> np.ndarray:
    """Rotation matrices (F, 3, 3) mapping the canonical body (X left, Y up, Z forward)
    onto the landmark frame, from the hip line and the hip-to-shoulder direction."""
    left = world[:, L_HIP] - world[:, R_HIP] + world[:, L_SHOULDER] - world[:, R_SHOULDER]
    up = (world[:, L_SHOULDER] + world[:, R_SHOULDER] - world[:, L_HIP] - world[:, R_HIP]) / 2
    up = up / np.maximum(np.linalg.norm(up, axis=-1, keepdims=True), 1e-9)
    left = left - (left * up).sum(-1, keepdims=True) * up
    left = left / np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-9)
    fwd = np.cross(left, up)
    return np.stack([left, up, fwd], axis=-1)


def _landmark_targets(world: np.ndarray, visibility: np.ndarray):
    """Per correspondence targets (F, K, 3), weights (F, K) and the SMPL joint ids (K,)."""
    joint_ids, targets, weights = [], [], []
    for joint, lms, w in JOINT_LANDMARKS:
        joint_ids.append(joint)
        targets.append(world[:, list(lms)].mean(1))
        weights.append(w * visibility[:, list(lms)].min(1))
    return np.array(joint_ids), np.stack(targets, 1), np.stack(weights, 1)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def fit_landmarks(model, world: np.ndarray, visibility: np.ndarray, valid: np.ndarray,
                  config: LandmarkFitConfig = LandmarkFitConfig(), betas: np.ndarray | None = None,
                  progress=None) -> LandmarkFit:
    """Fit pose per frame (jointly, with temporal smoothness) and one shape to the landmarks.

    world: (F, 33, 3) metres, camera axes, hip-centred; visibility: (F, 33) in [0, 1];
    valid: (F,) bool (frames with a detection).  betas: fixed shape, else fitted.
    progress: optional callable(iteration, loss).
    """
    world = np.asarray(world, np.float64)
    visibility = np.asarray(visibility, np.float64)
    valid = np.asarray(valid, bool)
    n_frames = world.shape[0]
    if world.shape[1:] != (33, 3) or visibility.shape != (n_frames, 33) or valid.shape != (n_frames,):
        raise ValueError(f"expected world (F,33,3), visibility (F,33), valid (F,); got {world.shape}, "
                         f"{visibility.shape}, {valid.shape}")
    if betas is None:
        betas = fit_shape(model, world, visibility, valid, config)
    betas = np.asarray(betas, np.float64)
    idx = np.flatnonzero(valid)
    out_orient = np.zeros((n_frames, 3))
    out_pose = np.zeros((n_frames, 23, 3))
    out_joints = np.full((n_frames, 24, 3), np.nan)
    out_res = np.full(n_frames, np.nan)
    if len(idx) == 0:
        return LandmarkFit(out_orient, out_pose, betas, out_joints, out_res, valid.copy())

    w_sub, v_sub = world[idx], visibility[idx]
    root0 = rotations.matrix_to_axis_angle(torch.tensor(root_from_landmarks(w_sub), dtype=torch.float32))
    body0 = torch.zeros(len(idx), 23, 3)
    sol = _fit_frames(model, betas, w_sub, v_sub, np.diff(idx) == 1, root0, body0, config, config.iterations,
                      progress=progress)
    out_orient[idx] = sol.root
    out_pose[idx] = sol.body
    out_joints[idx] = sol.joints_rel
    out_res[idx] = sol.residual
    return LandmarkFit(out_orient, out_pose, betas, out_joints, out_res, valid.copy())


@dataclass(frozen=True)
class _FrameSolution:
    root: np.ndarray  # (n, 3)
    body: np.ndarray  # (n, 23, 3)
    joints_rel: np.ndarray  # (n, 24, 3) pelvis-centred
    rotations: np.ndarray  # (n, 24, 3, 3) global joint rotations
    residual: np.ndarray  # (n,) metres


def _fit_frames(model, betas: np.ndarray, world: np.ndarray, visibility: np.ndarray, consecutive: np.ndarray,
                root0: torch.Tensor, body0: torch.Tensor, config: LandmarkFitConfig, iterations: int,
                context: tuple[np.ndarray, np.ndarray] | None = None, progress=None) -> _FrameSolution:
    """Jointly fit n frames (all with landmarks).

    world (n, 33, 3), visibility (n, 33); consecutive (n-1,) bool: frame i+1 directly follows i
    (temporal terms only there).  root0 (n, 3), body0 (n, 23, 3) starting values.
    context: (joints_rel (2, 24, 3), rotations (1, 24, 3, 3)) of the two frames just before
    (streaming): they enter the temporal terms as constants.
    """
    n = world.shape[0]
    dt = torch.float32  # the body model's dtype
    joint_ids, targets_np, weights_np = _landmark_targets(world, visibility)
    targets = torch.tensor(targets_np, dtype=dt)
    weights = torch.tensor(weights_np, dtype=dt)
    joint_ids_t = torch.tensor(joint_ids)
    lm = torch.tensor(world, dtype=dt)
    vis = torch.tensor(visibility, dtype=dt)
    head_dir = _unit(lm[:, NOSE] - (lm[:, L_EAR] + lm[:, R_EAR]) / 2)
    head_w = torch.minimum(vis[:, NOSE], torch.minimum(vis[:, L_EAR], vis[:, R_EAR]))
    limb_dirs = [
        (7, 10, _unit(lm[:, L_FOOT_INDEX] - lm[:, L_HEEL]), torch.minimum(vis[:, L_FOOT_INDEX], vis[:, L_HEEL])),
        (8, 11, _unit(lm[:, R_FOOT_INDEX] - lm[:, R_HEEL]), torch.minimum(vis[:, R_FOOT_INDEX], vis[:, R_HEEL])),
        (20, 22, _unit((lm[:, L_INDEX] + lm[:, L_PINKY]) / 2 - lm[:, L_WRIST]),
         torch.minimum(vis[:, L_INDEX], vis[:, L_WRIST])),
        (21, 23, _unit((lm[:, R_INDEX] + lm[:, R_PINKY]) / 2 - lm[:, R_WRIST]),
         torch.minimum(vis[:, R_INDEX], vis[:, R_WRIST])),
    ]
    link = np.asarray(consecutive, bool)
    ctx_joints = ctx_rots = None
    if context is not None:
        ctx_joints = torch.tensor(context[0], dtype=dt)
        ctx_rots = torch.tensor(context[1], dtype=dt)
        link = np.concatenate([[True, True], link])  # context frames directly precede frame 0
    vel_ok = torch.tensor(link[-(n - 1 + (1 if context is not None else 0)):] if len(link) else link)
    accel_ok = torch.tensor(link[:-1] & link[1:]) if len(link) > 1 else torch.zeros(0, dtype=torch.bool)

    root = root0.detach().clone().to(dt).requires_grad_(True)
    body = body0.detach().clone().to(dt).requires_grad_(True)
    trans = torch.zeros(n, 3, dtype=dt, requires_grad=True)
    betas_t = torch.tensor(betas, dtype=dt)[None]
    forward_axis = torch.tensor([0.0, 0.0, 1.0], dtype=dt)
    prior_w = torch.ones(23, dtype=dt)
    prior_w[[j - 1 for j in UNOBSERVED_JOINTS]] = config.unobserved_prior_scale

    def energy() -> torch.Tensor:
        pose = torch.cat([root[:, None], body], dim=1)
        joints, rots = _joints(model, betas_t, pose)
        diff = joints[:, joint_ids_t] + trans[:, None] - targets
        data = (weights * (diff ** 2).sum(-1)).sum() / weights.sum().clamp_min(1e-9)
        direction = (head_w * (1 - ((rots[:, 15] @ forward_axis) * head_dir).sum(-1))).mean()
        for a, b, target_dir, w in limb_dirs:
            direction = direction + (w * (1 - (_unit(joints[:, b] - joints[:, a]) * target_dir).sum(-1))).mean()
        loss = data + config.direction * direction + config.pose_prior * ((body ** 2).sum(-1) * prior_w).sum(-1).mean()
        rel = joints - joints[:, :1]
        if ctx_joints is not None:
            rel = torch.cat([ctx_joints, rel])
            rots = torch.cat([ctx_rots, rots])
        if rel.shape[0] > 2 and bool(accel_ok.any()):
            accel = rel[2:] - 2 * rel[1:-1] + rel[:-2]
            loss = loss + config.smooth_accel * ((accel ** 2).sum(-1).mean(-1) * accel_ok).sum() / n
        if rots.shape[0] > 1 and bool(vel_ok.any()):
            vel = rots[1:] - rots[:-1]
            loss = loss + config.smooth_rot * ((vel ** 2).sum((-1, -2)).mean(-1) * vel_ok).sum() / n
        return loss

    opt = torch.optim.LBFGS([root, body, trans], lr=config.lr, max_iter=iterations, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12)
    step = [0]

    def closure():
        opt.zero_grad()
        loss = energy()
        loss.backward()
        step[0] += 1
        if progress is not None:
            progress(step[0], float(loss.detach()))
        return loss

    opt.step(closure)
    with torch.no_grad():
        pose = torch.cat([root[:, None], body], dim=1)
        joints, rots = _joints(model, betas_t, pose)
        diff = joints[:, joint_ids_t] + trans[:, None] - targets
        res = ((weights * (diff ** 2).sum(-1)).sum(-1) / weights.sum(-1).clamp_min(1e-9)).sqrt()
    return _FrameSolution(root.detach().double().numpy(), body.detach().double().numpy(),
                          (joints - joints[:, :1]).double().numpy(), rots.double().numpy(), res.double().numpy())


class StreamingLandmarkFitter:
    """Landmark fit for live use (the ``video_prior`` node), in small batches of frames.

    One L-BFGS per frame costs ~60 ms here (torch overhead of tiny problems), a batch
    of 15 frames ~150 ms in total, so frames are fitted ``batch_frames`` at a time
    (latency: batch_frames / rate, 0.5 s at 30 Hz), warm-started from the previous
    batch, whose last two frames enter the temporal terms as constants (no seam).
    Shape: refitted from all bone lengths seen so far at every batch until
    ``shape_frames`` frames were seen, then locked.  A frame without a person
    flushes the batch and breaks the temporal link.
    """

    def __init__(self, model, config: LandmarkFitConfig = LandmarkFitConfig(), batch_frames: int = 15,
                 iterations: int = 30, shape_frames: int = 60):
        if batch_frames < 1 or iterations < 1:
            raise ValueError("batch_frames and iterations must be >= 1")
        self.model, self.config = model, config
        self.batch_frames, self.iterations, self.shape_frames = batch_frames, iterations, shape_frames
        self.betas = np.zeros(min(config.num_betas, model.num_betas))
        self.shape_locked = False
        self._shape_world: list[np.ndarray] = []
        self._shape_vis: list[np.ndarray] = []
        self._pending: list[tuple[object, np.ndarray, np.ndarray]] = []
        self._last_body: np.ndarray | None = None
        self._context: tuple[np.ndarray, np.ndarray] | None = None

    def push(self, key, world: np.ndarray | None, visibility: np.ndarray | None) -> list[tuple[object, tuple | None]]:
        """Add one frame (``world`` (33, 3), ``visibility`` (33,), or None when no person).

        Returns the frames finished by this call, in order: (key, (global_orient (3,),
        body_pose (23, 3), betas (nb,), residual metres) or None).
        """
        if world is None:
            done = self.flush()
            self._context = None
            return done + [(key, None)]
        self._pending.append((key, np.asarray(world, np.float64), np.asarray(visibility, np.float64)[:33]))
        return self.flush() if len(self._pending) >= self.batch_frames else []

    def flush(self) -> list[tuple[object, tuple | None]]:
        """Fit and return every pending frame now."""
        if not self._pending:
            return []
        keys = [p[0] for p in self._pending]
        world = np.stack([p[1] for p in self._pending])
        vis = np.stack([p[2] for p in self._pending])
        self._pending = []
        if not self.shape_locked:
            self._shape_world.extend(world)
            self._shape_vis.extend(vis)
            seen = len(self._shape_world)
            self.betas = fit_shape(self.model, np.stack(self._shape_world), np.stack(self._shape_vis),
                                   np.ones(seen, bool), self.config)
            self._context = None  # joints of the previous shape would fight the new one
            if seen >= self.shape_frames:
                self.shape_locked = True
                self._shape_world, self._shape_vis = [], []
        n = len(keys)
        root0 = rotations.matrix_to_axis_angle(torch.tensor(root_from_landmarks(world), dtype=torch.float32))
        body0 = (torch.zeros(n, 23, 3) if self._last_body is None
                 else torch.tensor(np.repeat(self._last_body[None], n, 0), dtype=torch.float32))
        sol = _fit_frames(self.model, self.betas, world, vis, np.ones(n - 1, bool), root0, body0, self.config,
                          self.iterations, context=self._context)
        self._last_body = sol.body[-1]
        joints = sol.joints_rel if self._context is None or n >= 2 else np.concatenate([self._context[0], sol.joints_rel])
        self._context = (joints[-2:], sol.rotations[-1:]) if len(joints) >= 2 else None
        return [(k, (sol.root[i], sol.body[i], self.betas.copy(), float(sol.residual[i]))) for i, k in enumerate(keys)]
