"""BVH motion files: parsing, forward kinematics, and retargeting onto the body model's 24 joints.

Retargeting transfers GLOBAL segment orientations, which is robust to skeletons whose
joint chains differ from SMPL's (extra zero-length joints, two neck segments, a separate
hand segment):

    G_smpl(j) = W . B^T . G_bvh(m(j)) . B . C_j

where m(j) is the BVH joint mapped to SMPL joint j, B is the BVH rest body frame
(columns: body left, up, forward in BVH world axes, from the hips and the head), W turns the
canonical Y-up frame into the requested world (Z-up by default), and C_j is the smallest
rotation taking the SMPL rest bone direction of j onto the BVH rest bone direction, so
rest poses that differ (arms down in CMU files vs SMPL's T-pose) line up.  Unmapped SMPL
joints keep their parent's orientation.  Local rotations follow from the global ones.
Root translation follows the BVH hips, scaled to metres and then to the target body's
leg length, so feet do not slide when the body is smaller or taller than the actor.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .motions import Motion, canonical_to_world, matrices_to_axis_angle

# Candidate unit lengths (metres per file unit).  CMU's ASF files use "length 0.45":
# one unit = 1/0.45 inch; converters often keep those units in BVH.
UNIT_CANDIDATES = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": 0.0254,
    "cmu_asf (1/0.45 inch)": 0.0254 / 0.45,
    "dm": 0.1,
}
TYPICAL_LEG_M = 0.84  # hip joint to ankle joint of an adult (thigh ~0.43 + shank ~0.41 m)

# BVH joint names per SMPL joint for the skeletons we know (first scheme with the most
# matches wins; names compare case-insensitively after stripping a "prefix:" namespace).
SCHEMES: dict[str, dict[str, str]] = {
    # CMU via the bvh11 / ASF-style conversion (e.g. cmu_131_01.bvh): arms hang down at rest.
    "cmu-asf": {
        "pelvis": "Hips", "left_hip": "LeftHip", "right_hip": "RightHip", "spine1": "lowerback",
        "left_knee": "LeftKnee", "right_knee": "RightKnee", "spine2": "Chest", "left_ankle": "LeftAnkle",
        "right_ankle": "RightAnkle", "spine3": "Chest2", "left_foot": "LeftToe", "right_foot": "RightToe",
        "neck": "Neck", "left_collar": "LeftCollar", "right_collar": "RightCollar", "head": "Head",
        "left_shoulder": "LeftShoulder", "right_shoulder": "RightShoulder", "left_elbow": "LeftElbow",
        "right_elbow": "RightElbow", "left_wrist": "lhand", "right_wrist": "rhand", "left_hand": "LFingers",
        "right_hand": "RFingers",
    },
    # CMU via cgspeed's MotionBuilder-friendly conversion.
    "cmu-cgspeed": {
        "pelvis": "Hips", "left_hip": "LeftUpLeg", "right_hip": "RightUpLeg", "spine1": "LowerBack",
        "left_knee": "LeftLeg", "right_knee": "RightLeg", "spine2": "Spine", "left_ankle": "LeftFoot",
        "right_ankle": "RightFoot", "spine3": "Spine1", "left_foot": "LeftToeBase", "right_foot": "RightToeBase",
        "neck": "Neck", "left_collar": "LeftShoulder", "right_collar": "RightShoulder", "head": "Head",
        "left_shoulder": "LeftArm", "right_shoulder": "RightArm", "left_elbow": "LeftForeArm",
        "right_elbow": "RightForeArm", "left_wrist": "LeftHand", "right_wrist": "RightHand",
        "left_hand": "LeftFingerBase", "right_hand": "RightFingerBase",
    },
    # Mixamo-style rigs.
    "mixamo": {
        "pelvis": "Hips", "left_hip": "LeftUpLeg", "right_hip": "RightUpLeg", "spine1": "Spine",
        "left_knee": "LeftLeg", "right_knee": "RightLeg", "spine2": "Spine1", "left_ankle": "LeftFoot",
        "right_ankle": "RightFoot", "spine3": "Spine2", "left_foot": "LeftToeBase", "right_foot": "RightToeBase",
        "neck": "Neck", "left_collar": "LeftShoulder", "right_collar": "RightShoulder", "head": "Head",
        "left_shoulder": "LeftArm", "right_shoulder": "RightArm", "left_elbow": "LeftForeArm",
        "right_elbow": "RightForeArm", "left_wrist": "LeftHand", "right_wrist": "RightHand",
        "left_hand": "LeftHandMiddle1", "right_hand": "RightHandMiddle1",
    },
}
# Joints a retarget cannot do without.
CORE_JOINTS = ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
               "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow")
# The SMPL joint whose rest position gives joint j's bone direction (leaves: see _LEAF_DIRS).
_BONE_CHILD = {1: 4, 2: 5, 3: 6, 4: 7, 5: 8, 6: 9, 7: 10, 8: 11, 9: 12, 12: 15, 13: 16, 14: 17,
               16: 18, 17: 19, 18: 20, 19: 21, 20: 22, 21: 23}
_LEAF_DIRS = {10: (0.0, 0.0, 1.0), 11: (0.0, 0.0, 1.0), 15: (0.0, 1.0, 0.0)}  # toes forward, head up


class BvhError(ValueError):
    """A BVH file that cannot be parsed or retargeted (one-line message)."""


@dataclass
class BvhJoint:
    name: str
    parent: int
    offset: np.ndarray          # (3,) file units, in the parent's frame
    channels: list[str]
    end_site: np.ndarray | None  # (3,) offset of an End Site child, if any


@dataclass
class Bvh:
    """A parsed BVH: joints in file order, motion (F, C) values, frame time (s)."""

    joints: list[BvhJoint]
    motion: np.ndarray
    frame_time: float
    source: str = ""

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.frame_time

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    def index(self, name: str) -> int:
        key = _norm(name)
        for i, j in enumerate(self.joints):
            if _norm(j.name) == key:
                return i
        raise KeyError(name)

    def children(self, i: int) -> list[int]:
        return [k for k, j in enumerate(self.joints) if j.parent == i]


def _norm(name: str) -> str:
    return name.split(":")[-1].strip().lower()


def parse_bvh(source: str | Path) -> Bvh:
    """Parse BVH text or a path to a .bvh file."""
    label = ""
    if isinstance(source, Path) or (isinstance(source, str) and "\n" not in source and source.lower().endswith(".bvh")):
        path = Path(source)
        label = str(path)
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError as exc:
            raise BvhError(f"{path}: cannot read ({exc.strerror or exc})") from None
    else:
        text = str(source)
    where = label or "<bvh>"
    m = re.search(r"^\s*MOTION\s*$", text, flags=re.MULTILINE)
    if not text.lstrip().upper().startswith("HIERARCHY") or m is None:
        raise BvhError(f"{where}: not a BVH file (needs HIERARCHY ... MOTION sections)")
    tokens = text[: m.start()].split()
    joints: list[BvhJoint] = []
    stack: list[int] = []
    i = 1
    pending_end = False
    try:
        while i < len(tokens):
            t = tokens[i]
            if t in ("ROOT", "JOINT"):
                name = tokens[i + 1]
                parent = stack[-1] if stack else -1
                if t == "ROOT" and joints:
                    raise BvhError(f"{where}: more than one ROOT (only one skeleton is supported)")
                joints.append(BvhJoint(name, parent, np.zeros(3), [], None))
                i += 2
            elif t == "End":
                pending_end = True
                i += 2  # "End Site"
            elif t == "{":
                stack.append(-2 if pending_end else len(joints) - 1)
                i += 1
            elif t == "}":
                stack.pop()
                pending_end = False
                i += 1
            elif t == "OFFSET":
                off = np.array([float(x) for x in tokens[i + 1:i + 4]])
                if stack and stack[-1] == -2:
                    # End Site belongs to the joint below it on the stack.
                    joints[stack[-2]].end_site = off
                else:
                    joints[-1].offset = off
                i += 4
            elif t == "CHANNELS":
                n = int(tokens[i + 1])
                joints[-1].channels = tokens[i + 2:i + 2 + n]
                i += 2 + n
            else:
                raise BvhError(f"{where}: unexpected token {t!r} in HIERARCHY")
    except (IndexError, ValueError) as exc:
        if isinstance(exc, BvhError):
            raise
        raise BvhError(f"{where}: malformed HIERARCHY near token {i} ({exc})") from None
    if not joints:
        raise BvhError(f"{where}: no joints in HIERARCHY")
    for j in joints:
        for c in j.channels:
            if c.lower() not in ("xposition", "yposition", "zposition", "xrotation", "yrotation", "zrotation"):
                raise BvhError(f"{where}: joint {j.name} has unknown channel {c!r}")
    rest = text[m.end():]
    fm = re.search(r"Frames:\s*(\d+)", rest)
    tm = re.search(r"Frame\s+Time:\s*([0-9.eE+-]+)", rest)
    if not fm or not tm:
        raise BvhError(f"{where}: MOTION section needs 'Frames:' and 'Frame Time:' lines")
    nframes, frame_time = int(fm.group(1)), float(tm.group(1))
    if not frame_time > 0:
        raise BvhError(f"{where}: Frame Time {frame_time} is not positive")
    data = rest[tm.end():].split()
    nch = sum(len(j.channels) for j in joints)
    try:
        values = np.array(data, dtype=np.float64)
    except ValueError:
        raise BvhError(f"{where}: non-numeric values in MOTION data") from None
    if values.size < nframes * nch:
        raise BvhError(f"{where}: MOTION has {values.size} values; {nframes} frames x {nch} channels need {nframes * nch}")
    if values.size > nframes * nch:
        raise BvhError(f"{where}: MOTION has {values.size - nframes * nch} values more than {nframes} frames x {nch} channels")
    return Bvh(joints, values.reshape(nframes, nch), frame_time, label)


def _axis_rot(axis: str, deg: np.ndarray) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    if axis == "x":
        m = [i, o, o, o, c, -s, o, s, c]
    elif axis == "y":
        m = [c, o, s, o, i, o, -s, o, c]
    else:
        m = [c, -s, o, s, c, o, o, o, i]
    return np.stack(m, -1).reshape(a.shape + (3, 3))


def forward_kinematics(bvh: Bvh, frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Global joint rotations (F, J, 3, 3) and positions (F, J, 3) in file units.

    Rotation channels compose in the order listed (``Zrotation Yrotation Xrotation`` ->
    Rz . Ry . Rx).  Position channels replace the matching OFFSET component.
    frames: motion rows (F, C); default all.
    """
    motion = bvh.motion if frames is None else np.atleast_2d(frames)
    F, J = motion.shape[0], len(bvh.joints)
    rot = np.zeros((F, J, 3, 3))
    pos = np.zeros((F, J, 3))
    col = 0
    for k, j in enumerate(bvh.joints):
        local_r = np.tile(np.eye(3), (F, 1, 1))
        local_t = np.tile(j.offset, (F, 1))
        for c in j.channels:
            v = motion[:, col]
            col += 1
            axis, kind = c[0].lower(), c[1:].lower()
            if kind == "rotation":
                local_r = local_r @ _axis_rot(axis, v)
            else:
                local_t[:, "xyz".index(axis)] = v
        if j.parent < 0:
            rot[:, k], pos[:, k] = local_r, local_t
        else:
            rot[:, k] = rot[:, j.parent] @ local_r
            pos[:, k] = pos[:, j.parent] + (rot[:, j.parent] @ local_t[..., None])[..., 0]
    return rot, pos


def rest_positions(bvh: Bvh) -> np.ndarray:
    """(J, 3) joint positions of the rest pose (all rotations zero, offsets only)."""
    pos = np.zeros((len(bvh.joints), 3))
    for k, j in enumerate(bvh.joints):
        pos[k] = j.offset if j.parent < 0 else pos[j.parent] + j.offset
    return pos


def has_rest_pose_first_frame(bvh: Bvh, tol_deg: float = 0.5) -> bool:
    """True when frame 0 is an added rest/T-pose: every rotation channel ~0 while frame 1 moves."""
    if bvh.num_frames < 2:
        return False
    cols = [i for i, c in enumerate(c for j in bvh.joints for c in j.channels) if c.lower().endswith("rotation")]
    f0 = np.abs(bvh.motion[0, cols])
    f1 = np.abs(bvh.motion[1, cols])
    return bool(f0.max() < tol_deg and f1.max() > 5 * tol_deg)


def find_scheme(bvh: Bvh) -> tuple[str, dict[str, int]]:
    """Best-matching name scheme -> (scheme name, {smpl joint name: bvh joint index})."""
    names = {_norm(j.name): i for i, j in enumerate(bvh.joints)}
    best, best_map = "", {}
    for scheme, table in SCHEMES.items():
        m = {s: names[_norm(b)] for s, b in table.items() if _norm(b) in names}
        if len(m) > len(best_map):
            best, best_map = scheme, m
    missing = [c for c in CORE_JOINTS if c not in best_map]
    if missing:
        raise BvhError(f"{bvh.source or '<bvh>'}: skeleton not recognised (best match {best or 'none'} lacks "
                       f"{', '.join(missing)}); known schemes: {', '.join(SCHEMES)}")
    return best, best_map


def detect_unit(bvh: Bvh, mapping: dict[str, int]) -> tuple[str, float, float]:
    """Length unit from the leg length -> (unit name, metres per unit, leg length in units)."""
    rest = rest_positions(bvh)
    legs = []
    for hip, ankle in (("left_hip", "left_ankle"), ("right_hip", "right_ankle")):
        # Sum the segment lengths along the chain hip -> ankle.
        k, length = mapping[ankle], 0.0
        while k != mapping[hip] and k >= 0:
            p = bvh.joints[k].parent
            if p < 0:
                break
            length += float(np.linalg.norm(rest[k] - rest[p]))
            k = p
        legs.append(length)
    leg = float(np.mean(legs))
    if not leg > 0:
        raise BvhError(f"{bvh.source or '<bvh>'}: zero leg length; cannot infer units")
    name = min(UNIT_CANDIDATES, key=lambda n: abs(math.log(leg * UNIT_CANDIDATES[n] / TYPICAL_LEG_M)))
    return name, UNIT_CANDIDATES[name], leg


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking direction a onto direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1 + 1e-9:
        # Opposite: turn 180 degrees about any axis perpendicular to a.
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def rest_body_frame(rest: np.ndarray, mapping: dict[str, int]) -> np.ndarray:
    """BVH rest body frame B (3, 3): columns = body left, up, forward in BVH world axes."""
    up = rest[mapping["head"]] - rest[mapping["pelvis"]]
    up /= np.linalg.norm(up)
    left = rest[mapping["left_hip"]] - rest[mapping["right_hip"]]
    left -= (left @ up) * up
    n = np.linalg.norm(left)
    if n < 1e-9:
        raise BvhError("BVH rest pose has coincident hips; cannot find the body's left")
    left /= n
    return np.stack([left, up, np.cross(left, up)], axis=1)


def retarget(bvh: Bvh, model, betas: np.ndarray, up_axis: str = "+z", drop_rest_frame: bool | None = None) -> Motion:
    """BVH -> Motion on ``model`` with shape ``betas`` at the BVH frame rate.

    drop_rest_frame: drop frame 0 when it is an added rest/T-pose (None = detect).
    The result is not yet on the floor: ``motions.place_on_floor`` does that.
    """
    import torch

    from .body_model import JOINT_NAMES
    from .lbs import forward

    scheme, mapping = find_scheme(bvh)
    dropped = has_rest_pose_first_frame(bvh) if drop_rest_frame is None else bool(drop_rest_frame)
    motion_rows = bvh.motion[1:] if dropped else bvh.motion
    if motion_rows.shape[0] < 1:
        raise BvhError(f"{bvh.source or '<bvh>'}: no motion frames")
    unit, m_per_unit, leg_units = detect_unit(bvh, mapping)
    g_bvh, p_bvh = forward_kinematics(bvh, motion_rows)
    rest = rest_positions(bvh)
    B = rest_body_frame(rest, mapping)
    W = canonical_to_world(up_axis)

    with torch.no_grad():
        out = forward(model, torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1), torch.zeros(1, 24, 3))
    smpl_rest = out.joints[0].double().numpy()
    parents = [int(p) for p in model.parents]
    idx = {n: i for i, n in enumerate(JOINT_NAMES)}

    F = motion_rows.shape[0]
    glob = np.zeros((F, 24, 3, 3))
    for j in range(24):
        name = JOINT_NAMES[j]
        if name not in mapping:
            glob[:, j] = glob[:, parents[j]] if parents[j] >= 0 else np.eye(3)
            continue
        b = mapping[name]
        # Rest bone directions: SMPL (canonical) and BVH (canonical via B^T).
        if j in _BONE_CHILD and JOINT_NAMES[_BONE_CHILD[j]] in mapping:
            d_s = smpl_rest[_BONE_CHILD[j]] - smpl_rest[j]
            d_b = B.T @ (rest[mapping[JOINT_NAMES[_BONE_CHILD[j]]]] - rest[b])
        elif j in _LEAF_DIRS or j in (22, 23):
            d_s = np.array(_LEAF_DIRS[j]) if j in _LEAF_DIRS else smpl_rest[j] - smpl_rest[parents[j]]
            kids = bvh.children(b)
            tip = bvh.joints[b].end_site if bvh.joints[b].end_site is not None else (
                bvh.joints[kids[0]].offset if kids else None)
            d_b = B.T @ tip if tip is not None and np.linalg.norm(tip) > 1e-9 else d_s
        else:
            d_s = d_b = np.array([0.0, 1.0, 0.0])  # pelvis: the body frame B aligns it
        C = _min_rotation(d_s, d_b) if np.linalg.norm(d_b) > 1e-9 else np.eye(3)
        glob[:, j] = W @ B.T @ g_bvh[:, b] @ B @ C
    local = np.empty_like(glob)
    local[:, 0] = glob[:, 0]
    for j in range(1, 24):
        local[:, j] = np.swapaxes(glob[:, parents[j]], -1, -2) @ glob[:, j]
    poses = matrices_to_axis_angle(local).reshape(F, 72)

    # Root: BVH hips path in metres, scaled to this body's leg length.
    smpl_leg = float(np.mean([
        np.linalg.norm(smpl_rest[idx["left_knee"]] - smpl_rest[idx["left_hip"]])
        + np.linalg.norm(smpl_rest[idx["left_ankle"]] - smpl_rest[idx["left_knee"]]),
        np.linalg.norm(smpl_rest[idx["right_knee"]] - smpl_rest[idx["right_hip"]])
        + np.linalg.norm(smpl_rest[idx["right_ankle"]] - smpl_rest[idx["right_knee"]]),
    ]))
    scale = smpl_leg / leg_units
    hips = (p_bvh[:, mapping["pelvis"]] @ B) * scale          # canonical axes, metres
    pelvis_world = hips @ W.T
    trans = pelvis_world - smpl_rest[0]
    info = {"source": "bvh", "path": bvh.source, "scheme": scheme, "unit": unit, "metres_per_unit": m_per_unit,
            "actor_leg_m": leg_units * m_per_unit, "body_leg_m": smpl_leg, "dropped_rest_frame": dropped,
            "bvh_frames": bvh.num_frames, "bvh_rate_hz": bvh.rate_hz}
    return Motion(Path(bvh.source).stem if bvh.source else "bvh", poses, trans, bvh.rate_hz, up_axis,
                  np.asarray(betas, dtype=np.float64).copy(), info)


# ----------------------------------------------------------------------------- writing

# SMPL joint -> BVH joint name in the Mixamo / MotionBuilder convention, which retargeting tools
# (Blender add-ons, HumanIK's auto-characterise) recognise: hips, spine, neck, head, shoulders
# = clavicles, arms, forearms, hands = wrists, index-base as the hand's end.
BVH_WRITE_NAMES: tuple[str, ...] = (
    "Hips", "LeftUpLeg", "RightUpLeg", "Spine", "LeftLeg", "RightLeg", "Spine1", "LeftFoot", "RightFoot", "Spine2",
    "LeftToeBase", "RightToeBase", "Neck", "LeftShoulder", "RightShoulder", "Head", "LeftArm", "RightArm",
    "LeftForeArm", "RightForeArm", "LeftHand", "RightHand", "LeftHandIndex1", "RightHandIndex1",
)


def _euler_zxy_deg(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations R = Rz(z) . Rx(x) . Ry(y) -> (..., 3) degrees (z, x, y), the channel
    order ``Zrotation Xrotation Yrotation``.  At x = +-90 deg (gimbal lock) y is set to 0."""
    r = np.asarray(rot, np.float64)
    x = np.arcsin(np.clip(r[..., 2, 1], -1.0, 1.0))
    locked = np.abs(np.cos(x)) < 1e-7
    y = np.where(locked, 0.0, np.arctan2(-r[..., 2, 0], r[..., 2, 2]))
    z = np.where(locked, np.arctan2(r[..., 1, 0], r[..., 0, 0]), np.arctan2(-r[..., 0, 1], r[..., 1, 1]))
    return np.degrees(np.stack([z, x, y], axis=-1))


def body_bvh_text(parents, rest_joints: np.ndarray, poses: np.ndarray, trans: np.ndarray, world_to_bvh: np.ndarray,
                  rate_hz: float, unit_m: float = 0.01, names=BVH_WRITE_NAMES, end_sites: dict | None = None) -> str:
    """A solved body as BVH text: the body model's skeleton in its own rest pose (SMPL's T-pose,
    Y up, facing +Z), one frame per pose.

    parents: (J,) parent index (-1 root); rest_joints: (J, 3) metres, rest pose of the solved shape;
    poses: (F, 3J) axis-angle (root first, in the capture's world); trans: (F, 3) metres;
    world_to_bvh: (3, 3) rotation from the capture's world into the BVH's Y-up world; unit_m:
    metres per BVH unit (0.01: centimetres); end_sites: joint -> (3,) metres offset of its End Site.
    The skeleton's posed joints are exactly the solve's (same forward kinematics)."""
    from .motions import axis_angle_to_matrices

    parents = [int(p) for p in parents]
    J = len(parents)
    F = poses.shape[0]
    rot = axis_angle_to_matrices(np.asarray(poses, np.float64).reshape(F, J, 3))
    rot[:, 0] = world_to_bvh @ rot[:, 0]
    root = (world_to_bvh @ (rest_joints[0] + np.asarray(trans, np.float64)).T).T / unit_m
    euler = np.unwrap(np.radians(_euler_zxy_deg(rot)), axis=0)  # no 360-degree jumps between frames
    euler = np.degrees(euler)
    end_sites = end_sites or {}
    children = {j: [k for k in range(J) if parents[k] == j] for j in range(J)}
    lines = ["HIERARCHY"]

    def hierarchy(j: int, depth: int) -> None:
        pad = "  " * depth
        off = (rest_joints[j] - rest_joints[parents[j]]) / unit_m if parents[j] >= 0 else np.zeros(3)
        lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        lines.append(f"{pad}  CHANNELS " + ("6 Xposition Yposition Zposition " if parents[j] < 0 else "3 ")
                     + "Zrotation Xrotation Yrotation")
        for k in children[j]:
            hierarchy(k, depth + 1)
        if not children[j]:
            e = np.asarray(end_sites.get(j, (0.0, 0.05, 0.0)), np.float64) / unit_m
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {e[0]:.6f} {e[1]:.6f} {e[2]:.6f}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    order: list[int] = []

    def walk(j: int) -> None:
        order.append(j)
        for k in children[j]:
            walk(k)

    roots = [j for j in range(J) if parents[j] < 0]
    if len(roots) != 1:
        raise ValueError(f"a BVH skeleton has one root, this one has {len(roots)}")
    hierarchy(roots[0], 0)
    walk(roots[0])
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / rate_hz:.8f}"]
    for f in range(F):
        vals = [*root[f]] + [v for j in order for v in euler[f, j]]
        lines.append(" ".join(f"{v:.6f}" for v in vals))
    return "\n".join(lines) + "\n"
