"""Synthetic optical markers on a posed body, with the realism of real captures.

Layouts (where markers sit on the body, as face + barycentric surface points):
- ``random_layout``: area-uniform samples on the shaped rest mesh, as in the paper's
  appendix "Synthetic Marker Placement".  Counts are NESTED: the first ``pool`` (50) points
  are drawn for a seed and a layout of n <= pool markers keeps the first n, so 20/30/40/50
  markers of one seed are subsets of each other (the paper drops 10 at a time).
- partial-body layouts: the same, restricted to faces whose three corners' dominant joint
  belongs to the part (paper appendix, Table "Part definitions").
- ``structured_layout``: 39 anatomical landmarks in the spirit of the common full-body
  sets (head, C7/T10/clavicle/sternum/back, shoulder/arm/wrist/hand, pelvis spines,
  thigh/knee/tibia/ankle/heel/toe), found by casting a ray from a joint along an anatomical
  direction to the skin.

Trajectories: each marker is its posed surface point pushed 9.5 mm along the interpolated
posed surface normal (paper Sec. "Mocap Solving": delta = 9.5 mm off the skin), so it moves
with the skin.  Realism (each optional): Gaussian position noise (default sigma 0.5 mm,
typical residual of a calibrated optical system), occlusion as in the paper's "Marker
Tracking Loss" (each frame a visible marker starts a 10-frame hide with probability p),
ghost points (short spurious tracks near the body) and swaps (two nearby tracks exchange
identities from some frame on, as a tracker sometimes does).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .motions import (HEAD, L_ANKLE, L_COLLAR, L_ELBOW, L_FOOT, L_HAND, L_HIP, L_KNEE, L_SHOULDER, L_WRIST, NECK,
                      PELVIS, R_ANKLE, R_COLLAR, R_ELBOW, R_FOOT, R_HAND, R_HIP, R_KNEE, R_SHOULDER, R_WRIST, SPINE1,
                      SPINE2, SPINE3)

MARKER_OFFSET_M = 0.0095   # paper Sec. "Mocap Solving": markers sit 9.5 mm off the skin
NESTED_POOL = 50           # paper appendix: draw 50, drop 10 at a time


@dataclass(frozen=True)
class MarkerLayout:
    """Marker attachment: face_ids (M,) int64, bary (M, 3) float64, names (M,) ('' for random)."""

    face_ids: np.ndarray
    bary: np.ndarray
    names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return int(self.face_ids.shape[0])

    def subset(self, idx) -> "MarkerLayout":
        idx = np.asarray(idx, dtype=np.int64)
        names = tuple(self.names[i] for i in idx) if self.names else ()
        return MarkerLayout(self.face_ids[idx], self.bary[idx], names)


def rest_vertices(model, betas: np.ndarray) -> torch.Tensor:
    """Shaped rest mesh (N, 3) float32 (zero pose, no translation)."""
    from .lbs import forward

    with torch.no_grad():
        out = forward(model, torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1), torch.zeros(1, 24, 3))
    return out.vertices[0]


def part_face_mask(model, part_joints) -> np.ndarray:
    """(F,) bool: faces whose three corners are dominated by joints of the part."""
    from .parts import vertex_dominant_joint

    dom = np.asarray(vertex_dominant_joint(model))
    inside = np.isin(dom, np.asarray(list(part_joints)))
    return inside[model.faces.numpy()].all(1)


def random_layout(model, betas: np.ndarray, n: int, seed: int, part_joints=None, pool: int = NESTED_POOL) -> MarkerLayout:
    """n area-uniform surface points; the first n of a seed's max(n, pool) draw (nested counts)."""
    from .mesh import sample_surface

    if n < 1:
        raise ValueError(f"need at least one marker, got {n}")
    faces = model.faces
    face_index = torch.arange(faces.shape[0])
    if part_joints is not None:
        mask = torch.as_tensor(part_face_mask(model, part_joints))
        if not bool(mask.any()):
            raise ValueError(f"no faces belong to joints {list(part_joints)}")
        faces, face_index = faces[mask], face_index[mask]
    g = torch.Generator().manual_seed(int(np.random.SeedSequence([int(seed), 7]).generate_state(1)[0]))
    fid, bary = sample_surface(rest_vertices(model, betas), faces, max(int(n), int(pool)), g)
    fid = face_index[torch.as_tensor(fid, dtype=torch.long)][:n]
    return MarkerLayout(fid.numpy().astype(np.int64), torch.as_tensor(bary)[:n].double().numpy())


# Structured landmarks: (name, origin, direction) in canonical axes (+X body's left, +Y up,
# +Z front).  origin is a joint or (joint_a, joint_b, fraction along a->b).  Right-side
# landmarks mirror the left ones (x -> -x, left joints -> right joints).
_LEFT_LANDMARKS = [
    ("LFHD", HEAD, (0.45, 0.35, 1.0)),
    ("LBHD", HEAD, (0.45, 0.35, -1.0)),
    ("LSHO", L_SHOULDER, (0.25, 1.0, 0.0)),
    ("LUPA", (L_SHOULDER, L_ELBOW, 0.55), (0.0, 0.3, -1.0)),
    ("LELB", L_ELBOW, (0.0, 0.2, -1.0)),
    ("LFRM", (L_ELBOW, L_WRIST, 0.55), (0.0, 0.3, -1.0)),
    ("LWRA", L_WRIST, (0.0, 0.2, 1.0)),
    ("LWRB", L_WRIST, (0.0, 0.2, -1.0)),
    ("LFIN", L_HAND, (0.0, 1.0, 0.0)),
    ("LASI", PELVIS, (0.6, 0.35, 1.0)),
    ("LPSI", (PELVIS, SPINE1, 0.6), (0.25, 0.0, -1.0)),
    ("LTHI", (L_HIP, L_KNEE, 0.55), (1.0, 0.0, 0.2)),
    ("LKNE", L_KNEE, (1.0, 0.0, 0.0)),
    ("LTIB", (L_KNEE, L_ANKLE, 0.55), (1.0, 0.0, 0.2)),
    ("LANK", L_ANKLE, (1.0, -0.1, 0.0)),
    ("LHEE", L_ANKLE, (0.0, -0.45, -1.0)),
    ("LTOE", L_FOOT, (0.0, 1.0, 0.2)),
]
_CENTRE_LANDMARKS = [
    ("C7", NECK, (0.0, 0.25, -1.0)),
    ("T10", SPINE2, (0.0, 0.0, -1.0)),
    ("CLAV", (SPINE3, NECK, 0.7), (0.0, 0.0, 1.0)),
    ("STRN", (SPINE2, SPINE3, 0.6), (0.0, 0.0, 1.0)),
    ("RBAK", (SPINE3, R_COLLAR, 0.5), (-0.35, 0.0, -1.0)),
]
_MIRROR_JOINT = {L_SHOULDER: R_SHOULDER, L_ELBOW: R_ELBOW, L_WRIST: R_WRIST, L_HAND: R_HAND, L_HIP: R_HIP,
                 L_KNEE: R_KNEE, L_ANKLE: R_ANKLE, L_FOOT: R_FOOT, L_COLLAR: R_COLLAR}


def _mirror(origin):
    if isinstance(origin, tuple):
        return (_MIRROR_JOINT.get(origin[0], origin[0]), _MIRROR_JOINT.get(origin[1], origin[1]), origin[2])
    return _MIRROR_JOINT.get(origin, origin)


def structured_landmarks() -> list[tuple[str, object, tuple[float, float, float]]]:
    """The 39 landmark definitions (name, origin, canonical direction)."""
    out = list(_CENTRE_LANDMARKS)
    for name, origin, d in _LEFT_LANDMARKS:
        out.append((name, origin, d))
        out.append(("R" + name[1:], _mirror(origin), (-d[0], d[1], d[2])))
    return out


def ray_mesh_first_hit(origin: np.ndarray, direction: np.ndarray, vertices: np.ndarray, faces: np.ndarray):
    """First intersection of a ray with a triangle mesh (Moller-Trumbore, all faces at once).

    -> (face id, bary (3,), distance) or None when the ray misses.
    """
    d = direction / np.linalg.norm(direction)
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = (e1 * p).sum(1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - v0
    u = (s * p).sum(1) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = (e2 * q).sum(1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    if not hit.any():
        return None
    k = int(np.argmin(np.where(hit, t, np.inf)))
    return k, np.array([1.0 - u[k] - v[k], u[k], v[k]]), float(t[k])


def structured_layout(model, betas: np.ndarray, part_joints=None) -> MarkerLayout:
    """The 39-landmark anatomical layout on the shaped rest mesh (optionally only a part's)."""
    from .parts import vertex_dominant_joint

    verts = rest_vertices(model, betas).double().numpy()
    faces = model.faces.numpy()
    joints = model.J_regressor.double().numpy() @ verts
    dom = np.asarray(vertex_dominant_joint(model))
    fids, barys, names = [], [], []
    for name, origin, d in structured_landmarks():
        if isinstance(origin, tuple):
            o = joints[origin[0]] + origin[2] * (joints[origin[1]] - joints[origin[0]])
        else:
            o = joints[origin]
        hit = ray_mesh_first_hit(o, np.asarray(d, dtype=np.float64), verts, faces)
        if hit is None:
            raise ValueError(f"landmark {name}: ray from the joint misses the mesh of {model.name}")
        f, b, _ = hit
        if part_joints is not None:
            corner = faces[f][int(np.argmax(b))]
            if int(dom[corner]) not in set(part_joints):
                continue
        fids.append(f)
        barys.append(b)
        names.append(name)
    if not fids:
        raise ValueError("no structured landmark lies on the requested part")
    return MarkerLayout(np.array(fids, dtype=np.int64), np.array(barys), tuple(names))


def marker_trajectories(model, betas: np.ndarray, poses: np.ndarray, trans: np.ndarray, layout: MarkerLayout,
                        offset_m: float = MARKER_OFFSET_M, chunk: int = 128) -> np.ndarray:
    """Exact marker positions (F, M, 3) metres: posed surface point + offset * posed normal.

    The normal is the barycentric blend of the posed (area-weighted) vertex normals of the
    face's corners, renormalised: smooth across faces, like a marker base on skin.
    """
    from .lbs import forward
    from .mesh import vertex_normals

    faces = model.faces
    corners = faces[torch.as_tensor(layout.face_ids, dtype=torch.long)]            # (M, 3)
    bary = torch.as_tensor(layout.bary, dtype=torch.float32)                         # (M, 3)
    b = torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1)
    out = np.empty((poses.shape[0], len(layout), 3))
    with torch.no_grad():
        for s in range(0, poses.shape[0], chunk):
            o = forward(model, b, torch.as_tensor(np.asarray(poses[s:s + chunk], dtype=np.float32)),
                        torch.as_tensor(np.asarray(trans[s:s + chunk], dtype=np.float32)))
            v = o.vertices
            n = vertex_normals(v, faces)                                              # (B, N, 3)
            p = (v[:, corners] * bary[None, :, :, None]).sum(2)
            nn = (n[:, corners] * bary[None, :, :, None]).sum(2)
            nn = nn / nn.norm(dim=-1, keepdim=True).clamp_min(1e-9)
            out[s:s + chunk] = (p.double() + offset_m * nn.double()).numpy()
    return out


@dataclass(frozen=True)
class MarkerRealism:
    """Realism of simulated optical markers; defaults are a clean but realistic studio.

    noise_mm: per-axis Gaussian sigma (mm); 0.5 mm is a typical residual of a calibrated
      optical system.
    occlusion_prob: per frame, the probability that a visible marker starts a hide
      (paper "Marker Tracking Loss": 0 / 0.2 % / 1 %).
    occlusion_frames: length of a hide in frames (paper: 10).
    ghost_rate_hz: expected number of ghost tracks starting per second (0 = none); a ghost
      is a short spurious track (reflection) near the body, lasting ghost_seconds.
    swaps: number of identity swaps between two nearby tracks (from a random frame on).
    track_breaks: a marker that reappears after a hide comes back as a new track (a new column),
      as an unlabelled export of an optical system writes it: every column is one seen stretch.
    """

    noise_mm: float = 0.5
    occlusion_prob: float = 0.0
    occlusion_frames: int = 10
    ghost_rate_hz: float = 0.0
    ghost_seconds: tuple[float, float] = (0.05, 0.5)
    swaps: int = 0
    track_breaks: bool = False

    def __post_init__(self):
        if self.noise_mm < 0:
            raise ValueError(f"noise_mm must be >= 0, got {self.noise_mm}")
        if not 0.0 <= self.occlusion_prob <= 1.0:
            raise ValueError(f"occlusion_prob must be in [0, 1], got {self.occlusion_prob}")
        if self.occlusion_frames < 1:
            raise ValueError(f"occlusion_frames must be >= 1, got {self.occlusion_frames}")
        if self.ghost_rate_hz < 0 or self.swaps < 0:
            raise ValueError("ghost_rate_hz and swaps must be >= 0")


def occlusion_mask(num_frames: int, num_markers: int, prob: float, length: int, rng: np.random.Generator) -> np.ndarray:
    """(F, M) visibility: each frame, each visible marker starts a ``length``-frame hide with
    probability ``prob`` (the hide includes the frame it starts on)."""
    visible = np.ones((num_frames, num_markers), dtype=bool)
    if prob <= 0:
        return visible
    hidden_until = np.zeros(num_markers, dtype=np.int64)  # first frame visible again
    draws = rng.random((num_frames, num_markers))
    for t in range(num_frames):
        free = hidden_until <= t
        start = free & (draws[t] < prob)
        hidden_until[start] = t + length
        visible[t] = hidden_until <= t
    return visible


@dataclass
class SimulatedMarkers:
    """positions (F, M, 3) metres with NaN where missing, in the SHUFFLED file order;
    face_ids (M,) (-1 for ghosts), bary (M, 3), names (M,) (landmark names or ''),
    order (M,) index into the unshuffled tracks (real markers first, then ghosts),
    swaps: list of (frame, track_a, track_b) in file order,
    source (M,) the physical marker of each track (index into the layout; -1 for ghosts): with
    track breaks several tracks are one marker's stretches."""

    positions: np.ndarray
    face_ids: np.ndarray
    bary: np.ndarray
    names: list[str]
    order: np.ndarray
    num_real: int
    num_ghosts: int
    swaps: list = field(default_factory=list)
    source: np.ndarray | None = None


def simulate_markers(clean: np.ndarray, layout: MarkerLayout, rate_hz: float, realism: MarkerRealism,
                     seed: int) -> SimulatedMarkers:
    """Apply noise, occlusion, ghosts, swaps and shuffle the track order.

    clean: (F, M, 3) exact trajectories from ``marker_trajectories``.  Each effect draws from
    its own stream of ``seed``, so e.g. turning ghosts on does not change the occlusions.
    """
    F, M, _ = clean.shape
    noise_rng, occ_rng, ghost_rng, swap_rng, order_rng = (np.random.default_rng([int(seed), 101, k]) for k in range(5))
    pos = clean + noise_rng.normal(0.0, realism.noise_mm / 1000.0, clean.shape)
    vis = occlusion_mask(F, M, realism.occlusion_prob, realism.occlusion_frames, occ_rng)
    pos = np.where(vis[..., None], pos, np.nan)
    source = np.arange(M)
    if realism.track_breaks:  # one column per seen stretch of each marker
        runs = []
        for m in range(M):
            seen = np.flatnonzero(vis[:, m])
            for run in np.split(seen, np.flatnonzero(np.diff(seen) > 1) + 1) if seen.size else []:
                col = np.full((F, 3), np.nan)
                col[run] = pos[run, m]
                runs.append((m, col))
        source = np.array([m for m, _ in runs], dtype=np.int64)
        pos = np.stack([c for _, c in runs], 1) if runs else np.full((F, 0, 3), np.nan)

    # Ghosts: a Poisson number of short tracks, each either hovering at a fixed offset from a
    # real marker (a reflection on nearby skin/clothing) or still (a reflective object nearby).
    ghosts = []
    duration = F / rate_hz
    n_ghosts = int(ghost_rng.poisson(realism.ghost_rate_hz * duration)) if realism.ghost_rate_hz > 0 else 0
    for _ in range(n_ghosts):
        start = int(ghost_rng.integers(0, F))
        length = max(1, int(round(ghost_rng.uniform(*realism.ghost_seconds) * rate_hz)))
        g = np.full((F, 3), np.nan)
        stop = min(F, start + length)
        anchor = int(ghost_rng.integers(0, M))
        offset = ghost_rng.normal(0.0, 1.0, 3)
        offset *= ghost_rng.uniform(0.03, 0.15) / np.linalg.norm(offset)
        if ghost_rng.random() < 0.5:
            g[start:stop] = clean[start:stop, anchor] + offset
        else:
            g[start:stop] = clean[start, anchor] + offset
        g[start:stop] += ghost_rng.normal(0.0, realism.noise_mm / 1000.0, (stop - start, 3))
        ghosts.append(g)
    if ghosts:
        pos = np.concatenate([pos, np.stack(ghosts, 1)], 1)
    total = pos.shape[1]

    order = order_rng.permutation(total)
    pos = pos[:, order]
    source = np.concatenate([source, np.full(n_ghosts, -1, dtype=np.int64)])[order]
    real = source >= 0
    face_ids = np.where(real, np.asarray(layout.face_ids)[np.maximum(source, 0)], -1).astype(np.int64)
    bary = np.where(real[:, None], np.asarray(layout.bary)[np.maximum(source, 0)], 0.0)
    layout_names = list(layout.names) if layout.names else [""] * M
    names = [layout_names[k] if k >= 0 else "" for k in source]

    # Swaps (in file order): two tracks close at frame t exchange identities from t on.
    swaps = []
    real_cols = np.nonzero(face_ids >= 0)[0]
    for _ in range(realism.swaps):
        t = int(swap_rng.integers(1, F))
        cand = [c for c in real_cols if np.isfinite(pos[t, c]).all()]
        if len(cand) < 2:
            continue
        a = int(swap_rng.choice(cand))
        others = [c for c in cand if c != a]
        d = [np.linalg.norm(pos[t, c] - pos[t, a]) for c in others]
        b = int(others[int(np.argmin(d))])
        pos[t:, [a, b]] = pos[t:, [b, a]]
        swaps.append((t, a, b))
    return SimulatedMarkers(pos, face_ids, bary, names, order, M, n_ghosts, swaps, source)
