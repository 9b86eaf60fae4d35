"""Session -> OUT.npz for the near-online sliding-window solver (method ``uuo-window``), and the
frame-by-frame session driver ``uuomocap bench speed`` uses.

The session is fed to ``WindowedSolver`` exactly as the ``solver`` node sees it: priors and
marker frames in capture-stamp order (a prior is handed over once the marker clock reached its
stamp).  OUT.npz holds what a recording of the stream exports: the REVISED frames where a lock
upgrade revised them, else the REFINED ones; the fixed-lag refined output and the causal
``estimate`` of every frame are kept as extra keys ``refined_*`` / ``estimate_*`` (poses, trans,
joints) and, when the session has ground truth, their accuracy is in the info dict.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uuomocap.methods import register_method


@dataclass
class StreamRun:
    """Everything a streamed solve produced.  Per frame (T,): stamps; estimate / refined / revised
    poses (T,72), trans (T,3), joints (T,24,3) (NaN where a frame has none: revised only where a lock
    upgrade revised it); latency_*_ms (T,) NaN where not measured."""

    stamps_ns: np.ndarray
    rate_hz: float
    estimate: dict
    refined: dict
    betas: np.ndarray
    labels: object
    bootstrap_s: float
    steady_frames: int
    steady_busy_s: float
    steady_cpu_s: float
    latency_estimate_ms: np.ndarray
    latency_refined_ms: np.ndarray
    stats: dict = field(default_factory=dict)
    # per steady-state frame: (frame index, seconds in push_markers, seconds in refine_ready,
    # frame indices refined by that refine_ready call) - the input of ``queue_latencies``
    calls: list = field(default_factory=list)
    revised: dict = field(default_factory=dict)

    @property
    def recording(self) -> dict:
        """What a recording of the stream holds per frame: the last revised result, else the refined one."""
        if not self.revised:
            return self.refined
        has = np.isfinite(self.revised["poses"]).all(axis=1)
        return {k: np.where(has.reshape((-1,) + (1,) * (v.ndim - 1)), self.revised[k], v) for k, v in self.refined.items()}

    @property
    def steady_fps(self) -> float:
        """Wall-clock throughput (depends on what else the machine runs)."""
        return self.steady_frames / self.steady_busy_s if self.steady_busy_s > 0 else float("nan")

    @property
    def steady_fps_cpu(self) -> float:
        """Throughput per CPU-second of this process (what one free core would give)."""
        return self.steady_frames / self.steady_cpu_s if self.steady_cpu_s > 0 else float("nan")


def session_stream(session_dir: Path):
    """(MarkerData, prior rows sorted by marker-clock stamp, up axis, body model, gt or None)."""
    from uuomocap.protocol.session import load_session

    s = load_session(Path(session_dir), load_prior=True, load_gt=True)
    rows = []
    if s.prior is not None:
        p = s.prior
        offset = int(round(float(s.clock_offset_s) * 1e9))
        cam = bool(np.asarray(p.get("camera_frame", True)))
        conf = np.asarray(p["confidence"]) if "confidence" in p else np.ones(len(p["stamps_ns"]))
        betas = np.asarray(p["betas"])
        for i, st in enumerate(np.asarray(p["stamps_ns"]).astype(np.int64)):
            rows.append((int(st) + offset, np.asarray(p["global_orient"][i], np.float64), np.asarray(p["body_pose"][i], np.float64),
                         np.asarray(betas[i] if betas.ndim == 2 else betas, np.float64), bool(p["valid"][i]), cam, float(conf[i])))
    return s.markers, rows, s.up_axis, s.body_model, s.gt


def stream_solve(session_dir: Path, body_model: str | None = None, config=None, realtime: bool = False,
                 progress=None, max_frames: int | None = None) -> StreamRun:
    """Feed a session frame by frame through ``WindowedSolver``.

    realtime: after the bootstrap, frames 'arrive' on the capture clock (the driver sleeps when it
    is ahead) so latencies are arrival -> result; otherwise frames are fed as fast as the solver
    takes them (latency = processing time of the call that produced the result).
    Steady-state throughput = frames after the bootstrap / time spent inside the solver for them.
    """
    import torch

    from uuomocap.solver_core.body_model import load_solver_models as load_models
    from uuomocap.solver_core.windowed_solver import WindowedSolver, WindowedSolverConfig

    torch.set_num_threads(1)
    md, rows, up_axis, session_model, _ = session_stream(session_dir)
    model, chamfer_model = load_models(body_model or session_model)
    solver = WindowedSolver(model, config or WindowedSolverConfig(), up_axis, float(md.rate_hz), chamfer_model)
    solver.wait_worker(120)  # a live solver is up before the take starts; the replay starts at once
    T = md.positions.shape[0] if max_frames is None else min(max_frames, md.positions.shape[0])
    est = {"poses": np.full((T, 72), np.nan), "trans": np.full((T, 3), np.nan), "joints": np.full((T, 24, 3), np.nan)}
    ref = {k: v.copy() for k, v in est.items()}
    # the shape each refined frame was solved under (a lock upgrade changes it mid-take)
    ref["betas"] = np.full((T, model.num_betas), np.nan)
    rev = {k: v.copy() for k, v in ref.items()}
    lat_e, lat_r = np.full(T, np.nan), np.full(T, np.nan)
    arrival = np.full(T, np.nan)
    stamps = np.asarray(md.stamps_ns[:T], dtype=np.int64)
    bootstrap_s, busy, cpu, steady, clock0, pi = float("nan"), 0.0, 0.0, 0, None, 0
    calls: list = []

    def take(results, now):
        for r in results:
            d = {"estimate": est, "refined": ref, "revised": rev}[r.kind]
            i = r.frame_index
            d["poses"][i], d["trans"][i], d["joints"][i] = r.poses, r.trans, r.joints
            if r.kind != "estimate":  # a prior with fewer betas (BlazePose's fit: 10) solves that many; the rest are 0
                nb = min(len(r.betas), model.num_betas)
                d["betas"][i] = 0.0
                d["betas"][i, :nb] = r.betas[:nb]
            if r.kind != "revised" and not np.isnan(arrival[i]):
                (lat_e if r.kind == "estimate" else lat_r)[i] = 1000.0 * (now - arrival[i])

    for i in range(T):
        st = int(stamps[i])
        while pi < len(rows) and rows[pi][0] <= st:
            solver.add_prior(*rows[pi])
            pi += 1
        locked = solver.locked
        if locked and realtime:
            if clock0 is None:
                clock0 = time.perf_counter() - st / 1e9
            due = clock0 + st / 1e9
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            # the frame arrived when it was due, also when the solver is behind (the wait in the
            # queue is part of its latency)
            arrival[i] = due
        elif locked:
            arrival[i] = time.perf_counter()
        c0, t0 = time.process_time(), time.perf_counter()
        res = solver.push_markers(st, md.positions[i], md.visible[i], frame_index=i)
        tp = time.perf_counter()
        take(res, tp)
        # as the node: behind the capture clock (the next frame is due already), at most one smoothing
        # pass per frame and no revision work (nodes/solver.py)
        behind = realtime and clock0 is not None and i + 1 < T and tp > clock0 + int(stamps[i + 1]) / 1e9
        res = solver.refine_ready(max_passes=1 if behind else None)
        t1 = time.perf_counter()
        take(res, t1)
        if locked:
            busy += t1 - t0
            cpu += time.process_time() - c0
            steady += 1
            calls.append((i, tp - t0, t1 - tp, [r.frame_index for r in res if r.kind == "refined"]))
        elif solver.locked:
            bootstrap_s = solver.stats["bootstrap_seconds"][-1]
        if progress is not None:
            progress(i)
    take(solver.flush(), time.perf_counter())
    # release the worker process now: a bench runs many sessions in one process, and a solver left
    # to the garbage collector kept its ~430 MB worker alive into the next session's solve
    solver.close()
    return StreamRun(stamps, float(md.rate_hz), est, ref, solver.betas.double().numpy(), solver.labels, bootstrap_s, steady, busy, cpu,
                     lat_e, lat_r, {**solver.stats, "timing": dict(solver.timing),
                      "lag_frames": solver.config.lag_frames + solver.config.hop_frames - 1}, calls,
                     rev if np.isfinite(rev["poses"]).any() else {})


def queue_latencies(run: StreamRun) -> tuple[np.ndarray, np.ndarray]:
    """Latencies (ms) of the estimates and the refined frames of the steady state as a solver
    alone on its core would give them: the frames arrive at the capture rate and are served one
    at a time, each call taking as long as it took in ``run`` (a single-server queue over the
    measured per-call times).  On a shared machine the capture-clock latencies also hold the
    time the process waited for a core; this model leaves that out and keeps what the solver's
    own work costs, including the queueing behind its own stalls.  Returns (estimate (F,),
    refined (R,)) for the F steady-state frames and the R frames they refined."""
    if not run.calls:
        return np.zeros(0), np.zeros(0)
    first = run.calls[0][0]
    free, est, ref = 0.0, [], []
    for i, push_s, refine_s, refined in run.calls:
        arrival = (i - first) / run.rate_hz
        done = max(arrival, free) + push_s
        est.append(done - arrival)
        done += refine_s
        ref += [done - (j - first) / run.rate_hz for j in refined if j >= first]
        free = done
    return 1000.0 * np.asarray(est), 1000.0 * np.asarray(ref)


def estimate_metrics(run: StreamRun, gt: dict, kind: str = "estimate") -> dict:
    """MPJPE (mm) and MPJVE (mm/s) of the estimate, refined or recording (revised, else refined)
    joints against gt.npz arrays."""
    from uuomocap.solver_core.metrics import mpjpe, mpjve

    joints = {"estimate": run.estimate, "refined": run.refined, "recording": run.recording}[kind]["joints"]
    gj = np.asarray(gt["joints"])[: len(joints)]
    ok = np.isfinite(joints).all(axis=(1, 2))
    if not ok.all():
        raise ValueError(f"{int((~ok).sum())} frames have no {kind} result")
    return {f"{kind}_mpjpe": mpjpe(joints, gj), f"{kind}_mpjve": mpjve(joints, gj, run.rate_hz)}  # mm, mm/s


def uuo_window(session_dir: Path, out_npz: Path, body_model: str | None = None, progress=None, **opts) -> dict:
    """Near-online sliding-window solver (the recording: revised, else refined frames; the
    fixed-lag refined and the causal estimate as extra keys)."""
    from uuomocap.protocol.session import write_npz

    t0 = time.perf_counter()
    run = stream_solve(Path(session_dir), body_model)
    md, _, _, session_model, gt = session_stream(Path(session_dir))
    labels = run.labels
    M = md.positions.shape[1]
    rec = run.recording
    out = {
        "betas": run.betas,
        "frame_betas": rec["betas"],
        "poses": rec["poses"],
        "trans": rec["trans"],
        "mocap_framerate": np.float64(run.rate_hz),
        "body_model": np.str_(body_model or session_model),
        "joints": rec["joints"],
        "stamps_ns": run.stamps_ns,
        "marker_parts": np.array(labels.parts if labels else [""] * M, dtype="<U32"),
        "marker_faces": (labels.face_ids if labels else np.full(M, -1)).astype(np.int64),
        "marker_bary": (labels.bary if labels else np.zeros((M, 3))).astype(np.float64),
        "method": np.str_("uuo-window"),
        "estimate_poses": run.estimate["poses"],
        "estimate_trans": run.estimate["trans"],
        "estimate_joints": run.estimate["joints"],
        "refined_poses": run.refined["poses"],
        "refined_trans": run.refined["trans"],
        "refined_joints": run.refined["joints"],
    }
    secs = {"bootstrap": round(run.bootstrap_s, 3), "total": round(time.perf_counter() - t0, 3)}
    for key in ("upgrade_at_end_s", "revise_at_end_s"):  # the take's end (WindowedSolver.flush)
        if key in run.stats:
            secs[key.removesuffix("_s")] = run.stats[key]
    out["stage_seconds"] = np.str_(json.dumps(secs))
    write_npz(out_npz, out)
    info = {"method": "uuo-window", "stage_seconds": secs, "steady_fps": round(run.steady_fps, 1),
            "steady_fps_cpu": round(run.steady_fps_cpu, 1),
            "rebootstraps": run.stats.get("rebootstraps", 0), "reassigned": run.stats.get("reassigned", 0),
            "new_tracks": run.stats.get("new_tracks", 0), "handovers": run.stats.get("handovers", 0),
            "revised_frames": int(np.isfinite(run.revised["poses"]).all(axis=1).sum()) if run.revised else 0,
            # Stage-5 marker fit (mm) of each bootstrap start, and the one locked
            "bootstrap_start_fits_mm": run.stats.get("bootstrap_start_fits_mm"), "bootstrap_start_chosen": run.stats.get("bootstrap_start_chosen"),
            # marker fit (mm) of the reservoir under the current lock and under each upgrade's (the last: the take's end)
            "upgrade_fit_mm": run.stats.get("upgrade_fit_mm", [])}
    if gt is not None and "joints" in gt:
        for kind in ("estimate", "refined"):
            info.update({k: round(v, 3) for k, v in estimate_metrics(run, gt, kind).items()})
    return info


register_method("uuo-window", uuo_window, "near-online sliding-window solver (refined; estimate accuracy in info)")
