"""Names for solved markers: the layout landmark each one sits at, else its segment and a number.

The point of unlabelled capture is to skip the labelling; what a lab hands on (Plug-in Gait,
OpenSim scaling, a studio's retargeting) still wants named trajectories.  A solve gives every
marker a surface point (face + barycentric) of the body model, and a layout - the built-in
Plug-in Gait landmarks (`marker_sim.structured_layout`) or the user's own labelled template take
fitted once (`labeled_fit`) - is a set of named surface points of the same model.  Naming is then
an assignment problem on the rest-pose body of the solved shape: each layout name goes to at most
one marker and each marker takes at most one name, minimising the summed rest-pose distance, and a
pair further apart than ``max_distance_m`` is not made (Hungarian with a "no name" column per
marker, so a far marker stays unnamed instead of stealing the name its neighbour needs).
Markers left without a layout name are named by the segment they ride and their order from the
segment's joint (``LThigh1`` nearest the hip), so every trajectory still gets a readable,
stable, unique label.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Body segment moved by each SMPL joint (the bone a marker rides, `metrics.attachment_joint_names`):
# readable, space-free names in the C3D style ('LThigh1'), left and right as L/R prefixes.
SEGMENT_NAMES: dict[str, str] = {
    "pelvis": "Pelvis", "left_hip": "LThigh", "right_hip": "RThigh", "spine1": "Abdomen",
    "left_knee": "LShank", "right_knee": "RShank", "spine2": "Trunk", "left_ankle": "LFoot",
    "right_ankle": "RFoot", "spine3": "Chest", "left_foot": "LToes", "right_foot": "RToes", "neck": "Neck",
    "left_collar": "LClavicle", "right_collar": "RClavicle", "head": "Head", "left_shoulder": "LUpperArm",
    "right_shoulder": "RUpperArm", "left_elbow": "LForearm", "right_elbow": "RForearm", "left_wrist": "LHand",
    "right_wrist": "RHand", "left_hand": "LFingers", "right_hand": "RFingers",
}
UNLABELLED_NAME = "Unlabeled"  # a marker the solve left without a body part (a ghost track)


@dataclass(frozen=True)
class MarkerNamingConfig:
    """How far a solved marker point may sit from a layout point and still take its name.

    Ours (the paper labels markers by body part only).  Measured on the two public Plug-in Gait
    captures of ../shared/data (session 37, docs/NOTEBOOK.md): the built-in landmarks sit 34 / 46 mm
    (median; up to 105 mm at ASIS, UPA, ELB, FHD) from where those labs put the markers, and a solve's
    points 11 / 19 mm (median) from the labelled fit's - so a cap under ~10 cm leaves right names
    unmade, and one much over it lets a marker outside the layout (a 5th metatarsal) take a name."""

    max_distance_m: float = 0.10


@dataclass(frozen=True)
class MarkerNames:
    """Per marker (M,): the name given, the layout name it took ('' = none), and the rest-pose
    distance (m) to that layout point (NaN when none)."""

    names: tuple[str, ...]
    layout_names: tuple[str, ...]
    distance_m: np.ndarray

    @property
    def named_count(self) -> int:
        return sum(1 for n in self.layout_names if n)


def assign_layout_names(marker_points: np.ndarray, layout_points: np.ndarray, layout_names, max_distance_m: float
                        ) -> tuple[list[str], np.ndarray]:
    """Each layout name to at most one marker, minimising the summed distance, no pair over the cap.

    marker_points: (M, 3) metres, NaN rows = markers without a surface point (never named);
    layout_points: (L, 3) metres; layout_names: (L,).  -> names (M,) ('' = none), distances (M,) m (NaN = none).
    """
    from scipy.optimize import linear_sum_assignment

    m_count, l_count = marker_points.shape[0], layout_points.shape[0]
    names, dist = [""] * m_count, np.full(m_count, np.nan)
    ok = np.isfinite(marker_points).all(axis=1)
    if not ok.any() or l_count == 0:
        return names, dist
    d = np.linalg.norm(marker_points[ok][:, None, :] - layout_points[None, :, :], axis=-1)   # (M', L)
    # one private "no name" column per marker at the cap: a pair over the cap always loses to it
    big = 1e6
    reject = np.full((d.shape[0], d.shape[0]), big)
    np.fill_diagonal(reject, max_distance_m)
    cost = np.concatenate([np.where(d <= max_distance_m, d, big), reject], axis=1)
    rows, cols = linear_sum_assignment(cost)
    where = np.flatnonzero(ok)
    for r, c in zip(rows, cols):
        if c < l_count and d[r, c] <= max_distance_m:
            names[where[r]] = str(layout_names[c])
            dist[where[r]] = float(d[r, c])
    return names, dist


def segment_names(marker_parts, marker_points: np.ndarray, segment_origins: dict[str, np.ndarray], taken=()) -> list[str]:
    """``LThigh1``, ``LThigh2``... per marker: its segment's name, numbered by distance from the
    segment's joint (1 = nearest), skipping names in ``taken``.  marker_parts: (M,) joint names
    ('' = no part -> ``Unlabeled1``...); marker_points: (M, 3) rest-pose metres (NaN allowed);
    segment_origins: joint name -> (3,) rest-pose joint position."""
    taken = set(taken)
    out = [""] * len(marker_parts)
    groups: dict[str, list[int]] = {}
    for k, part in enumerate(marker_parts):
        groups.setdefault(str(part), []).append(k)
    for part, idx in groups.items():
        base = SEGMENT_NAMES.get(part, UNLABELLED_NAME if not part else part)
        origin = segment_origins.get(part)
        if origin is not None:
            d = np.linalg.norm(marker_points[idx] - origin, axis=1)
            idx = [idx[i] for i in np.argsort(np.where(np.isfinite(d), d, np.inf), kind="stable")]
        n = 0
        for k in idx:
            n += 1
            while f"{base}{n}" in taken:
                n += 1
            out[k] = f"{base}{n}"
    return out


def name_markers(model, betas: np.ndarray, marker_faces: np.ndarray, marker_bary: np.ndarray, marker_parts,
                 layout_faces: np.ndarray | None = None, layout_bary: np.ndarray | None = None, layout_names=(),
                 config: MarkerNamingConfig = MarkerNamingConfig()) -> MarkerNames:
    """Names for a solve's M markers.

    betas: (B,) the solve's shape; marker_faces (M,) (-1 = no surface point), marker_bary (M, 3),
    marker_parts (M,) joint names ('' = none); the layout: faces (L,), bary (L, 3), names (L,) on
    the same body model (None = segment names only)."""
    from .metrics import surface_points_rest as rest_surface_points

    faces = np.asarray(marker_faces, dtype=np.int64)
    has_point = faces >= 0
    points = np.full((faces.shape[0], 3), np.nan)
    if has_point.any():
        points[has_point] = rest_surface_points(model, betas, faces[has_point], np.asarray(marker_bary)[has_point])
    if layout_faces is not None and len(layout_names):
        lp = rest_surface_points(model, betas, layout_faces, layout_bary)
        layout, dist = assign_layout_names(points, lp, list(layout_names), config.max_distance_m)
    else:
        layout, dist = [""] * faces.shape[0], np.full(faces.shape[0], np.nan)
    from .marker_sim import rest_vertices

    joints = model.J_regressor.double().numpy() @ rest_vertices(model, np.asarray(betas, np.float64)).double().numpy()
    origins = {name: joints[j] for j, name in enumerate(model.joint_names)}
    rest = [k for k, n in enumerate(layout) if not n]
    fallback = segment_names([str(marker_parts[k]) for k in rest], points[rest], origins, taken=[n for n in layout if n])
    names = list(layout)
    for k, n in zip(rest, fallback):
        names[k] = n
    return MarkerNames(tuple(names), tuple(layout), dist)


def compare_names(names, reference_names, layout_names) -> dict:
    """How a naming agrees with a reference's names (a labelled take of the same markers).

    Only markers whose reference name is one of the layout's can be named right; ``wrong`` lists
    every layout name given to a marker whose reference name differs ('LMT5->LTOE').
    names, reference_names: (M,); layout_names: (L,).  -> {compared, right, wrong, unnamed}."""
    layout = set(layout_names)
    compared = [(r, n) for r, n in zip(reference_names, names) if r in layout]
    return {"compared": len(compared), "right": sum(r == n for r, n in compared),
            "wrong": [f"{r}->{n}" for r, n in zip(reference_names, names) if n in layout and r != n],
            "unnamed": [r for r, n in compared if n not in layout]}


class LayoutError(ValueError):
    """A layout spec that cannot be used (unknown name, unreadable or mismatched template)."""


LAYOUTS = ("segments", "plug-in-gait")


def load_layout(spec: str, model, betas: np.ndarray, body_model_name: str):
    """A layout's named surface points -> (faces (L,), bary (L, 3), names (L,)), or (None, None, ())
    for segment names only.

    spec: 'segments' | 'plug-in-gait' (Vicon's full-body landmarks, ``marker_sim.structured_layout``
    on ``betas``) | a template .npz with marker_labels (or marker_names), marker_faces and
    marker_bary fitted on ``body_model_name`` (``uuomocap sample motion-from-markers``).  Never
    unpickles; raises :class:`LayoutError` naming what is wrong."""
    from pathlib import Path

    from .marker_sim import structured_layout

    if spec == "segments":
        return None, None, ()
    if spec == "plug-in-gait":
        layout = structured_layout(model, betas)
        return layout.face_ids, layout.bary, layout.names
    path = Path(spec)
    if path.suffix.lower() != ".npz":
        raise LayoutError(f"{spec}: give {' or '.join(LAYOUTS)}, or a template .npz "
                          "(`uuomocap sample motion-from-markers labelled.c3d --out template.npz`)")
    if not path.is_file():
        raise LayoutError(f"{spec}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            t = {k: z[k] for k in z.files}
    except ValueError as exc:
        raise LayoutError(f"{spec}: " + ("contains pickled objects, which are never loaded" if "pickle" in str(exc).lower()
                                         else f"not a valid npz ({exc})")) from None
    except Exception as exc:  # zipfile.BadZipFile, OSError: a truncated or foreign file
        raise LayoutError(f"{spec}: not a valid npz ({exc})") from None
    key = "marker_labels" if "marker_labels" in t else "marker_names" if "marker_names" in t else None
    if key is None or "marker_faces" not in t or "marker_bary" not in t:
        raise LayoutError(f"{spec}: a template holds marker_labels (or marker_names), marker_faces and marker_bary "
                          "(write one with `uuomocap sample motion-from-markers`)")
    template_model = str(t.get("body_model", "open-low"))
    if template_model != body_model_name:
        raise LayoutError(f"{spec}: fitted on body model {template_model!r}, the solve on {body_model_name!r}: re-fit it with "
                          f"`uuomocap sample motion-from-markers FILE --out T.npz --body-model {body_model_name}`")
    names, faces, bary = np.asarray(t[key]).astype(str), np.asarray(t["marker_faces"], np.int64), np.asarray(t["marker_bary"], np.float64)
    if not (names.shape[0] == faces.shape[0] == bary.shape[0]) or bary.shape[1:] != (3,):
        raise LayoutError(f"{spec}: marker_faces {faces.shape}, marker_bary {bary.shape} and names {names.shape} disagree")
    keep = (faces >= 0) & (faces < model.faces.shape[0])
    if not keep.any():
        raise LayoutError(f"{spec}: no name has a surface point")
    return faces[keep], bary[keep], tuple(names[keep].tolist())


def name_markers_with_points(model, betas: np.ndarray, marker_faces: np.ndarray, marker_bary: np.ndarray, marker_parts,
                             layout_faces: np.ndarray | None = None, layout_bary: np.ndarray | None = None, layout_names=(),
                             config: MarkerNamingConfig = MarkerNamingConfig()) -> list[str]:
    """:func:`name_markers` over the markers that have a surface point, '' for the others - a live
    stream's slots: empty tracker slots, tracks the solver has not assigned yet, everything before
    its bootstrap locks.  Shapes as :func:`name_markers`; -> names (M,)."""
    faces = np.asarray(marker_faces, dtype=np.int64).reshape(-1)
    has_point = np.flatnonzero(faces >= 0)
    out = [""] * faces.shape[0]
    if has_point.size:
        named = name_markers(model, betas, faces[has_point], np.asarray(marker_bary)[has_point],
                             [str(marker_parts[k]) if k < len(marker_parts) else "" for k in has_point],
                             layout_faces, layout_bary, layout_names, config)
        for k, n in zip(has_point, named.names):
            out[k] = n
    return out
