"""Registry of solving methods: anything that maps a session to a solved OUT.npz.

A method is ``fn(session_dir: Path, out_npz: Path, body_model: str, **opts) -> dict`` (an
info dict: timings, decisions...).  It reads the session (``uuomocap.protocol.session``),
writes OUT.npz in the AMASS layout at the marker rate (betas, poses, trans,
mocap_framerate, body_model, joints, stamps_ns, marker_parts, marker_faces, marker_bary,
method, optional stage_seconds) with ``session.write_npz``, and returns info.

Solver modules register themselves with ``register_method`` and are imported by ONE line
each at the bottom of this file.  ``uuomocap bench accuracy`` and ``uuomocap solve`` look
methods up here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

MethodFn = Callable[..., dict]

METHODS: dict[str, MethodFn] = {}
DESCRIPTIONS: dict[str, str] = {}
# Methods that read the ground truth: sanity references, never real solvers.
REFERENCE_METHODS: set[str] = set()


def register_method(name: str, fn: MethodFn, description: str = "", reference: bool = False) -> MethodFn:
    """Add a method under ``name`` (re-registering the same function is a no-op)."""
    if not name or not isinstance(name, str):
        raise ValueError("method name must be a non-empty string")
    if name in METHODS and METHODS[name] is not fn:
        raise ValueError(f"method {name!r} is already registered by {METHODS[name].__module__}")
    METHODS[name] = fn
    DESCRIPTIONS[name] = description or (fn.__doc__ or "").strip().split("\n")[0]
    if reference:
        REFERENCE_METHODS.add(name)
    return fn


def get_method(name: str) -> MethodFn:
    if name not in METHODS:
        known = ", ".join(sorted(METHODS)) or "none"
        raise KeyError(f"unknown method {name!r}; registered methods: {known}")
    return METHODS[name]


def ground_truth_copy(session_dir: Path, out_npz: Path, body_model: str, **opts) -> dict:
    """Reference, not a solver: copies gt.npz (true shape, poses and marker labels) into the
    OUT.npz layout.  Evaluating it gives MPJPE 0 and the ground truth's m2s (~9.5 mm): a
    sanity check of the benchmark pipeline.  Needs a session with gt.npz."""
    from uuomocap.protocol.session import load_session, write_npz
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.metrics import attachment_joint_names

    s = load_session(session_dir, load_prior=False)
    if s.gt is None:
        raise ValueError(f"{session_dir}: the 'gt' reference method needs gt.npz")
    gt = s.gt
    model = load_body_model(str(gt["body_model"]))
    faces = np.asarray(gt["marker_faces"]).astype(np.int64)
    bary = np.asarray(gt["marker_bary"], dtype=np.float64)
    real = faces >= 0
    parts = np.array([""] * faces.shape[0], dtype="<U32")
    if real.any():
        parts[real] = attachment_joint_names(model, faces[real], bary[real])
    out = {
        "betas": np.asarray(gt["betas"]),
        "poses": np.asarray(gt["poses"]),
        "trans": np.asarray(gt["trans"]),
        "mocap_framerate": np.asarray(gt["mocap_framerate"]),
        "body_model": np.str_(str(gt["body_model"])),
        "joints": np.asarray(gt["joints"]),
        "stamps_ns": np.asarray(gt["stamps_ns"]),
        "marker_parts": parts,
        "marker_faces": faces,
        "marker_bary": bary,
        "method": np.str_("gt"),
    }
    write_npz(out_npz, out)
    return {"method": "gt", "reference": True}


register_method("gt", ground_truth_copy, "ground truth copied into OUT.npz (sanity reference, not a solver)",
                reference=True)

# Solver modules register their methods below, one import line each.
import uuomocap.window_methods  # noqa: E402,F401  (uuo-window: near-online sliding-window solver)
import uuomocap.solver_methods  # noqa: E402,F401  (uuo, baselines and stage ablations of the offline solver)
import uuomocap.video_methods  # noqa: E402,F401  (blazepose-prior, uuo+blazepose: the BlazePose estimator on the session video)
