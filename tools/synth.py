"""Generate a synthetic session with ground truth (``uuomocap sample make``, the benchmark).

Pipeline (every random choice comes from its own stream of the seed, so the same
configuration always writes byte-identical files, and changing e.g. the occlusion does not
change the motion, the shape, the layout or the camera):

  shape (betas) -> motion (procedural / BVH / AMASS, on the floor, at the marker rate)
  -> marker layout (random nested / partial / structured) -> marker trajectories + realism
  -> camera at a random azimuth (= the prior's yaw offset) -> simulated video prior
  -> rendered video of the ground truth at the video frames' true times -> session files.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from uuomocap.protocol.session import save_session

GENERATOR = "uuomocap sample make"
# bump when the same configuration would produce different data; 2: motions re-expressed against the
# model's rest pose (the open model's A-pose arms had swung through the chest under T-pose rotations)
GENERATOR_VERSION = 2

DEFAULT_RANDOM_MARKERS = 40


@dataclass(frozen=True)
class SampleConfig:
    """What to generate.  Defaults: an 8 s walk, 40 random markers at 60 Hz (a studio-like
    rate that stays cheap to solve), 0.5 mm noise, no occlusion, a 30 Hz video prior with the
    default error model (uniform yaw), a 320x240 video."""

    motion: str = "walk"              # procedural name, or a .bvh / AMASS .npz file
    duration_s: float = 8.0
    start_s: float = 0.0              # where to start in a motion file
    rate_hz: float = 60.0             # marker (and ground truth) rate
    seed: int = 0
    n_markers: int | None = None      # default: 40 random / all 39 structured landmarks
    layout: str = "random"            # random | structured
    part: str | None = None           # left_leg, right_arm, ... (paper appendix parts)
    noise_mm: float = 0.5
    occlusion: float = 0.0            # per-frame hide probability (paper: 0, 0.002, 0.01)
    occlusion_frames: int = 10
    ghost_rate_hz: float = 0.0
    swaps: int = 0
    track_breaks: bool = False        # a marker back from a hide is a new column (unlabelled exports)
    body_model: str = "open-low"
    shape_sigma: float = 1.0          # betas ~ N(0, sigma^2), clipped to +-2.5 sigma
    up_axis: str = "+z"
    prior: bool = True
    video: bool = True
    video_size: tuple[int, int] = (320, 240)
    video_rate_hz: float = 30.0
    prior_noise_rad: float = 0.15
    prior_noise_tau_s: float = 0.3
    prior_shape_noise: float = 0.5
    prior_dropout: float = 0.01
    yaw_offset_deg: float | None = None   # None: uniform over 360 degrees
    clock_offset_s: float = 0.0
    sync_error_s: float = 0.0
    video_true_rate_hz: float | None = None
    extra: dict = field(default_factory=dict)

    def markers_count(self) -> int | None:
        if self.n_markers is not None:
            return int(self.n_markers)
        return DEFAULT_RANDOM_MARKERS if self.layout == "random" else None


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), 9000 + stream])


def sample_betas(num_betas: int, seed: int, sigma: float) -> np.ndarray:
    """Body shape for a seed: N(0, sigma^2) per component (the open model's betas are
    unit-variance PCA coordinates of adult shapes), clipped to +-2.5 sigma."""
    b = _rng(seed, 1).normal(0.0, sigma, num_betas)
    return np.clip(b, -2.5 * sigma, 2.5 * sigma) if sigma > 0 else b


def build_motion(cfg: SampleConfig, model, betas: np.ndarray):
    """The ground-truth motion at the marker rate, standing on the floor."""
    from uuomocap.solver_core import motions as mo

    if cfg.motion in mo.PROCEDURAL_MOTIONS:
        return mo.make_procedural_motion(cfg.motion, model, betas, cfg.duration_s, cfg.rate_hz, cfg.seed, cfg.up_axis)
    path = Path(cfg.motion)
    if not path.is_file():
        raise ValueError(f"motion {cfg.motion!r} is neither a procedural motion "
                         f"({', '.join(mo.PROCEDURAL_MOTIONS)}) nor an existing .bvh/.npz file")
    if path.suffix.lower() == ".bvh":
        from uuomocap.solver_core.bvh import parse_bvh, retarget

        motion = retarget(parse_bvh(path), model, betas, cfg.up_axis)
    elif path.suffix.lower() == ".npz":
        motion = mo.change_up_axis(mo.load_amass_npz(path), cfg.up_axis)
        # AMASS poses rotate SMPL's T-pose; a model resting otherwise (the open model's A-pose) gets them re-expressed
        motion = replace(motion, poses=mo.poses_from_tpose(motion.poses, model, betas))
    else:
        raise ValueError(f"motion file {path} must be .bvh or an AMASS .npz")
    available = (motion.num_frames - 1) / motion.rate_hz - cfg.start_s
    if available <= 0:
        raise ValueError(f"motion {path.name} lasts {motion.duration_s:.2f} s; start {cfg.start_s} s is past its end")
    duration = min(cfg.duration_s, available + 0.5 / cfg.rate_hz)
    motion = mo.resample_motion(motion, cfg.rate_hz, duration, cfg.start_s)
    return mo.place_on_floor(motion, model, betas)


@dataclass
class SessionView:
    """What the camera sees of a motion: the camera, its azimuth (= the prior's yaw offset), the
    simulated video prior (session-contract arrays, None without one) with each video frame's
    marker-clock time, and the rendered video's name (None without one)."""

    camera: object
    yaw_deg: float
    error: object
    prior: dict | None
    content_s: np.ndarray | None
    video_name: str | None
    render_info: dict


def camera_prior_video(cfg: SampleConfig, model, betas: np.ndarray, motion, joints: np.ndarray, out_dir: Path,
                       stage=lambda name: None) -> SessionView:
    """Place the camera at a random azimuth (seeded), simulate the video prior of ``motion`` (poses
    at the marker rate, joints (F,24,3) of those poses) and render ``out_dir/video.mp4`` of it, per
    ``cfg``'s prior and video fields.  Shared by generated sessions and sessions built from a real
    capture (``capture_session``)."""
    from uuomocap.solver_core.camera import place_camera
    from uuomocap.solver_core.motions import sample_motion_at
    from uuomocap.solver_core.prior_sim import PriorErrorModel, simulate_prior

    cam_rng = _rng(cfg.seed, 3)
    yaw = cam_rng.uniform(0.0, 360.0)
    if cfg.yaw_offset_deg is not None:
        yaw = float(cfg.yaw_offset_deg) % 360.0
    cam_height = cam_rng.uniform(1.0, 1.6)
    roll = math.radians(float(np.clip(cam_rng.normal(0.0, 1.5), -4.0, 4.0)))
    w, h = cfg.video_size
    camera = place_camera(joints[:, 0], cfg.up_axis, math.radians(yaw), int(w), int(h), camera_height_m=cam_height,
                          roll_rad=roll)
    prior_arrays, content = None, None
    error = PriorErrorModel(video_rate_hz=cfg.video_rate_hz, pose_noise_rad=cfg.prior_noise_rad,
                            pose_noise_tau_s=cfg.prior_noise_tau_s, shape_noise=cfg.prior_shape_noise,
                            dropout_prob=cfg.prior_dropout, clock_offset_s=cfg.clock_offset_s,
                            sync_error_s=cfg.sync_error_s, true_rate_hz=cfg.video_true_rate_hz)
    if cfg.prior or cfg.video:
        stage("prior")
        prior_arrays, content = simulate_prior(motion, model, betas, camera.R_wc, error, cfg.seed, cfg.body_model)
    out_dir.mkdir(parents=True, exist_ok=True)
    video_name, render_info = None, {}
    if cfg.video:
        stage("video")
        from uuomocap.render import render_video

        duration = (motion.num_frames - 1) / motion.rate_hz
        vposes, vtrans = sample_motion_at(motion, np.clip(content, 0.0, duration))
        video_name = "video.mp4"
        render_info = render_video(model, betas, vposes, vtrans, camera, out_dir / video_name, cfg.video_rate_hz,
                                   cfg.up_axis)
    return SessionView(camera, yaw, error, prior_arrays if cfg.prior else None, content, video_name, render_info)


def make_session(out_dir: str | Path, cfg: SampleConfig, progress=None) -> dict:
    """Generate a session into ``out_dir``; returns a summary dict.

    progress: optional callable(stage: str) called as each stage starts.
    """
    import torch

    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.lbs import forward
    from uuomocap.solver_core.marker_sim import (MARKER_OFFSET_M, MarkerRealism, marker_trajectories, random_layout,
                                                 simulate_markers, structured_layout)
    from uuomocap.solver_core.parts import PART_JOINTS

    def stage(name):
        if progress is not None:
            progress(name)

    out_dir = Path(out_dir)
    if cfg.layout not in ("random", "structured"):
        raise ValueError(f"layout must be 'random' or 'structured', got {cfg.layout!r}")
    if cfg.part is not None and cfg.part not in PART_JOINTS:
        raise ValueError(f"unknown part {cfg.part!r}; parts are {', '.join(PART_JOINTS)}")
    if not (cfg.rate_hz > 0 and cfg.duration_s > 0):
        raise ValueError("rate and duration must be positive")

    stage("motion")
    model = load_body_model(cfg.body_model)
    betas = sample_betas(model.num_betas, cfg.seed, cfg.shape_sigma)
    motion = build_motion(cfg, model, betas)
    F = motion.num_frames
    with torch.no_grad():
        out = forward(model, torch.as_tensor(betas, dtype=torch.float32).reshape(1, -1),
                      torch.as_tensor(motion.poses, dtype=torch.float32), torch.as_tensor(motion.trans, dtype=torch.float32))
    joints = out.joints.double().numpy()
    stamps = np.round(np.arange(F) / cfg.rate_hz * 1e9).astype(np.int64)

    stage("markers")
    part_joints = PART_JOINTS[cfg.part] if cfg.part else None
    n = cfg.markers_count()
    if cfg.layout == "random":
        layout = random_layout(model, betas, n, cfg.seed, part_joints)
    else:
        layout = structured_layout(model, betas, part_joints)
        if n is not None:
            if n > len(layout):
                raise ValueError(f"the structured layout has {len(layout)} landmarks{' on ' + cfg.part if cfg.part else ''}; "
                                 f"cannot place {n}")
            layout = layout.subset(np.arange(n))
    clean = marker_trajectories(model, betas, motion.poses, motion.trans, layout)
    realism = MarkerRealism(noise_mm=cfg.noise_mm, occlusion_prob=cfg.occlusion, occlusion_frames=cfg.occlusion_frames,
                            ghost_rate_hz=cfg.ghost_rate_hz, swaps=cfg.swaps, track_breaks=cfg.track_breaks)
    sim = simulate_markers(clean, layout, cfg.rate_hz, realism, cfg.seed)

    stage("camera")
    view = camera_prior_video(cfg, model, betas, motion, joints, out_dir, stage)
    camera, yaw, prior_arrays, content, error = view.camera, view.yaw_deg, view.prior, view.content_s, view.error
    video_name, render_info = view.video_name, view.render_info
    w, h = cfg.video_size

    stage("write")
    gt = {
        "betas": betas.astype(np.float64),
        "poses": motion.poses.astype(np.float64),
        "trans": motion.trans.astype(np.float64),
        "mocap_framerate": np.float64(cfg.rate_hz),
        "joints": joints,
        "body_model": np.str_(cfg.body_model),
        "gender": np.str_("neutral"),
        "stamps_ns": stamps,
        "marker_faces": sim.face_ids.astype(np.int64),
        "marker_bary": sim.bary.astype(np.float64),
        "marker_offset_m": np.float64(MARKER_OFFSET_M),
        # Extras beyond the contract (for evaluation and debugging; never for solving):
        "part": np.str_(cfg.part or ""),
        "marker_names": np.array(sim.names, dtype=np.str_),
        "marker_source": np.asarray(sim.source, dtype=np.int64),  # the physical marker of each column (-1 ghost)
        "camera_R_wc": camera.R_wc,
        "camera_position": camera.position,
        "camera_K": camera.K,
        "yaw_offset_deg": np.float64(yaw),
    }
    if content is not None:
        gt["video_content_s"] = content
    prov = {
        "generator": GENERATOR,
        "generator_version": GENERATOR_VERSION,
        "motion": cfg.motion if cfg.motion in _procedural() else Path(cfg.motion).name,
        "motion_info": {k: v for k, v in motion.info.items() if k != "path"},
        "seed": int(cfg.seed),
        "duration_s": round((F - 1) / cfg.rate_hz + 1 / cfg.rate_hz, 6),
        "rate_hz": float(cfg.rate_hz),
        "layout": cfg.layout,
        "n_markers": len(layout),
        "part": cfg.part,
        "ghost_tracks": int(sim.num_ghosts),
        "swaps": [list(map(int, s)) for s in sim.swaps],
        "noise_mm": float(cfg.noise_mm),
        "occlusion": float(cfg.occlusion),
        "occlusion_frames": int(cfg.occlusion_frames),
        "ghost_rate_hz": float(cfg.ghost_rate_hz),
        "track_breaks": bool(cfg.track_breaks),
        "shape_sigma": float(cfg.shape_sigma),
        "body_model": cfg.body_model,
        "prior": {k: v for k, v in asdict(error).items()} if cfg.prior else None,
        "yaw_offset_deg": round(yaw, 6),
        "video_size": [int(w), int(h)] if cfg.video else None,
    }
    save_session(out_dir, sim.positions, cfg.rate_hz, up_axis=cfg.up_axis, body_model=cfg.body_model,
                 prior=prior_arrays if cfg.prior else None, gt=gt, video_file=video_name,
                 video_rate_hz=cfg.video_rate_hz, clock_offset_s=cfg.clock_offset_s, provenance=prov)
    return {
        "session": str(out_dir),
        "frames": F,
        "rate_hz": cfg.rate_hz,
        "markers": int(sim.positions.shape[1]),
        "real_markers": len(layout),
        "ghost_tracks": int(sim.num_ghosts),
        "missing_fraction": float(np.isnan(sim.positions[..., 0]).mean()),
        "prior_frames": int(prior_arrays["stamps_ns"].shape[0]) if (cfg.prior and prior_arrays is not None) else 0,
        "video": video_name,
        "video_ms_per_frame": round(1000 * render_info.get("seconds_per_frame", 0.0), 2) if render_info else None,
        "yaw_offset_deg": round(yaw, 3),
        "motion": prov["motion"],
        "part": cfg.part or "",
    }


def _procedural() -> tuple[str, ...]:
    from uuomocap.solver_core.motions import PROCEDURAL_MOTIONS

    return PROCEDURAL_MOTIONS
