"""Methods that run the video estimator on the session's own video instead of reading prior.npz.

Registered in ``uuomocap.methods`` (one import line at the bottom of methods.py):
  blazepose-prior  the BlazePose prior (``uuomocap prior VIDEO``: BlazePose GHUM 3D + body-model
                   fit) rigidly registered to the markers, exactly like ``video-rr`` does with
                   prior.npz: the estimator's own accuracy, in the capture world
  uuo+blazepose    the staged solver (``uuo``) with that BlazePose prior in the loop
Both need the session's video (``video.mp4``, e.g. ``uuomocap sample make DIR --video`` or
``bench accuracy --video``); on a session without one they raise ValueError, which the
benchmark records as a failure of that method on that session.

The estimated prior is cached next to the video as ``prior_blazepose.npz`` (or, when the
session directory is read-only, under $XDG_CACHE_HOME/uuomocap/priors) together with the
estimator's info (detection rate, timings) and the video's size and mtime, and re-estimated
when any of those or ``ESTIMATOR_VERSION`` change.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from uuomocap.methods import register_method

PRIOR_FILE = "prior_blazepose.npz"
ESTIMATOR_VERSION = 1  # bump when the estimator or the landmark fit would give a different prior


def _video_of(session) -> Path:
    if session.video_file is None or not Path(session.video_file).is_file():
        raise ValueError(f"{session.path}: no video in the session (session.yaml video.file); methods that run "
                         "the video estimator need one (uuomocap sample make DIR --video, bench accuracy --video)")
    return Path(session.video_file)


def _stamp(video: Path, body_model: str) -> dict:
    st = video.stat()
    return {"version": ESTIMATOR_VERSION, "video": video.name, "size": st.st_size, "mtime_ns": st.st_mtime_ns,
            "body_model": body_model}


def _cache_paths(session_dir: Path, video: Path) -> list[Path]:
    """Where the prior may live: the session directory first, the user cache as a fallback."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    h = hashlib.sha1(str(video.resolve()).encode()).hexdigest()[:16]
    return [session_dir / PRIOR_FILE, Path(base) / "uuomocap" / "priors" / f"{h}-{PRIOR_FILE}"]


def _read_cached(path: Path, stamp: dict) -> tuple[dict, dict] | None:
    from uuomocap.protocol.prior_file import PriorFileError, read_prior_npz

    meta = path.with_suffix(".json")
    if not (path.is_file() and meta.is_file()):
        return None
    try:
        doc = json.loads(meta.read_text(encoding="utf-8"))
        if doc.get("stamp") != stamp:
            return None
        return read_prior_npz(path), dict(doc.get("info") or {})
    except (OSError, ValueError, PriorFileError):
        return None


def session_blazepose_prior(session_dir: str | Path, body_model: str = "open-low", log=None) -> tuple[dict, dict]:
    """Run BlazePose (+ body-model fit) on a session's video, cached -> (prior.npz arrays, info).

    info: the estimator's report (frames, frames_with_person, detection_rate, ms_per_frame,
    fit_seconds, ...) plus ``cached`` (bool) and ``prior_file``.
    Raises ValueError when the session has no video or no frame shows a person.
    """
    from uuomocap.protocol.prior_file import write_prior_npz
    from uuomocap.protocol.session import load_session
    from uuomocap.video_prior_run import estimate_prior, parse_estimator

    session_dir = Path(session_dir)
    s = load_session(session_dir, load_prior=False, load_gt=False)
    video = _video_of(s)
    stamp = _stamp(video, body_model)
    paths = _cache_paths(session_dir, video)
    for p in paths:
        hit = _read_cached(p, stamp)
        if hit is not None:
            return hit[0], {**hit[1], "cached": True, "prior_file": str(p)}
    prior, info = estimate_prior(video, parse_estimator("blazepose"), body_model=body_model, rate_hz=s.video_rate_hz,
                                 log=log or (lambda msg: None))
    if not prior.valid.any():
        raise ValueError(f"{video}: BlazePose found no person in any of the {len(prior.valid)} frames")
    arrays = prior.to_arrays()
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool, dict, list)) or v is None}
    for p in paths:
        try:
            write_prior_npz(p, arrays)
            p.with_suffix(".json").write_text(json.dumps({"stamp": stamp, "info": info}, default=float) + "\n",
                                              encoding="utf-8")
            return arrays, {**info, "cached": False, "prior_file": str(p)}
        except OSError:
            continue
    return arrays, {**info, "cached": False, "prior_file": None}


def blazepose_inputs(session_dir: Path, body_model: str | None = None):
    """SolverInputs of a session with the BlazePose prior in place of prior.npz -> (inputs, estimator info)."""
    from uuomocap.protocol.session import load_session
    from uuomocap.solver_methods import SolverInputs, prior_for_markers

    s = load_session(session_dir, load_prior=False, load_gt=False)
    arrays, info = session_blazepose_prior(session_dir)
    md = s.markers
    prior, shape = prior_for_markers(arrays, s.up_axis, md.stamps_ns, s.clock_offset_s)
    inputs = SolverInputs(
        markers=np.asarray(md.positions, dtype=np.float64), visible=np.asarray(md.visible, dtype=bool),
        rate_hz=float(md.rate_hz), stamps_ns=np.asarray(md.stamps_ns, dtype=np.int64), up_axis=s.up_axis,
        prior=prior, shape_prior=shape, body_model=body_model or s.body_model, source=str(session_dir))
    return inputs, info


def _estimator_report(info: dict, seconds: float) -> dict:
    keep = ("frames", "frames_with_person", "detection_rate", "ms_per_frame", "fit_seconds",
            "fit_residual_mm_median", "cached", "prior_file")
    return {"estimator": {k: info[k] for k in keep if k in info}, "estimator_seconds": round(seconds, 3)}


def blazepose_prior(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, **opts) -> dict:
    """The BlazePose prior of the session's video rigidly registered to the markers (like video-rr)."""
    from uuomocap.protocol.session import read_npz, write_npz
    from uuomocap.solver_methods import video_rr

    t0 = time.perf_counter()
    inputs, info = blazepose_inputs(Path(session_dir), body_model)
    est = _estimator_report(info, time.perf_counter() - t0)
    res = video_rr(session_dir, out_npz, body_model, inputs=inputs)
    out = read_npz(out_npz)
    out["method"] = np.str_("blazepose-prior")
    write_npz(out_npz, out)
    return {**res, "method": "blazepose-prior", **est}


def uuo_blazepose(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, **opts) -> dict:
    """The staged solver (uuo) with the BlazePose prior of the session's video instead of prior.npz."""
    from uuomocap.protocol.session import write_npz
    from uuomocap.solver_methods import _out_arrays, _params_arrays, run_staged_solver

    t0 = time.perf_counter()
    inputs, info = blazepose_inputs(Path(session_dir), body_model)
    est = _estimator_report(info, time.perf_counter() - t0)
    result, model = run_staged_solver(inputs, "uuo", progress)
    poses, trans, betas, joints = _params_arrays(model, result.params, inputs.up_axis)
    d = result.diagnostics
    secs = dict(d.get("stage_seconds") or {})
    secs["estimator"] = est["estimator_seconds"]
    write_npz(out_npz, _out_arrays(model, inputs, poses, trans, betas, joints, result.attachment,
                                   result.marker_parts, "uuo+blazepose", secs))
    return {"method": "uuo+blazepose", **{k: v for k, v in d.items() if k != "cluster_labels"}, **est}


register_method("blazepose-prior", blazepose_prior,
                "BlazePose prior of the session video rigidly registered to the markers (needs video.mp4)")
register_method("uuo+blazepose", uuo_blazepose,
                "staged solver with the BlazePose prior of the session video in the loop (needs video.mp4)")
