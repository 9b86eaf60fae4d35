"""Run a video body estimator over a whole video and build its prior (used by the CLI and benches).

Estimator specs:
  ``blazepose``        BlazePose GHUM 3D (fetched once, run with onnxruntime) + body-model fit
  ``onnx-hmr:MODEL``   a user's HMR-class ONNX model; person boxes from BlazePose
  ``phalp:PKL``        import a 4D-Humans / PHALP result file (``phalp:PKL#TRACK`` picks a track)
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uuomocap.protocol.video import VideoError, VideoSource


@dataclass(frozen=True)
class EstimatorSpec:
    kind: str  # "blazepose" | "onnx-hmr" | "phalp"
    path: Path | None = None
    track: int | None = None


def parse_estimator(text: str) -> EstimatorSpec:
    """'blazepose' | 'onnx-hmr:MODEL' | 'phalp:PKL[#TRACK]' -> EstimatorSpec (ValueError otherwise)."""
    if text == "blazepose":
        return EstimatorSpec("blazepose")
    kind, sep, rest = text.partition(":")
    if not sep or not rest:
        raise ValueError(f"unknown estimator {text!r}; use blazepose, onnx-hmr:MODEL.onnx or phalp:RESULTS.pkl")
    if kind == "onnx-hmr":
        return EstimatorSpec("onnx-hmr", Path(rest))
    if kind == "phalp":
        path, _, track = rest.partition("#")
        if track and not track.lstrip("-").isdigit():
            raise ValueError(f"phalp track must be an integer id, got {track!r}")
        return EstimatorSpec("phalp", Path(path), int(track) if track else None)
    raise ValueError(f"unknown estimator kind {kind!r}; use blazepose, onnx-hmr:MODEL.onnx or phalp:RESULTS.pkl")


def _frames(video: VideoSource, max_frames: int | None, progress):
    total = video.frame_count if max_frames is None else min(video.frame_count or max_frames, max_frames)
    bar = progress(total) if progress else None
    count = 0
    t_read = time.perf_counter()
    for frame in video:
        decode = time.perf_counter() - t_read
        yield frame, decode
        count += 1
        if bar is not None:
            bar.update(1)
        if max_frames is not None and count >= max_frames:
            break
        t_read = time.perf_counter()
    if bar is not None:
        bar.close()


def _timing(est_s: list[float], decode_s: list[float]) -> dict:
    est = np.asarray(est_s) * 1000
    return {
        "ms_per_frame": float(est.mean()) if len(est) else float("nan"),
        "ms_per_frame_median": float(np.median(est)) if len(est) else float("nan"),
        "decode_ms_per_frame": float(np.mean(decode_s) * 1000) if decode_s else float("nan"),
    }


def estimate_prior(video_path: str | Path, spec: EstimatorSpec, body_model: str = "open-low",
                   max_frames: int | None = None, rate_hz: float | None = None, progress=None, log=print):
    """Run ``spec`` over the video; returns (PriorSequence, info dict).

    progress: optional callable(total) -> object with update(n)/close() (e.g. tqdm).
    """
    import torch

    from uuomocap.model_fetch import ensure_pose_models
    from uuomocap.solver_core import video_prior as vp
    from uuomocap.solver_core.pose_estimators import BlazePoseEstimator, OnnxHmrEstimator

    video = VideoSource(video_path, rate_hz=rate_hz)
    info: dict = {"video": str(video_path), "width": video.width, "height": video.height,
                  "rate_hz": video.rate_hz, "estimator": spec.kind}
    try:
        if spec.kind == "phalp":
            from uuomocap.solver_core.phalp_import import load_phalp_pickle, phalp_track

            track = phalp_track(load_phalp_pickle(spec.path), spec.track)
            n = len(track.frame_names)
            if video.frame_count is not None and video.frame_count != n:
                info["warning"] = (f"the PHALP file has {n} frames but the video has {video.frame_count}; "
                                   "frames are matched in order")
            stamps = vp_stamps(n, video)
            prior = vp.prior_from_smpl_rotations(
                track.global_orient, track.body_pose, track.betas, track.valid, track.confidence, stamps,
                video.rate_hz, estimator=f"phalp:{spec.path.name}#{track.track_id}",
                keypoints3d=track.joints3d)
            info.update(frames=n, frames_with_person=int(track.valid.sum()), detection_rate=float(track.valid.mean()),
                        track_id=track.track_id, tracks={str(k): v for k, v in track.track_lengths.items()})
            return prior, info

        models = ensure_pose_models(log=log)
        tracker = BlazePoseEstimator(models.detector, models.landmark)
        if spec.kind == "onnx-hmr":
            if not spec.path.is_file():
                raise ValueError(f"ONNX model not found: {spec.path}")
            estimator = OnnxHmrEstimator(spec.path, tracker)
        else:
            estimator = tracker
        results, stamps, est_s, decode_s = [], [], [], []
        for frame, decode in _frames(video, max_frames, progress):
            rgb = frame.rgb()
            t0 = time.perf_counter()
            results.append(estimator.process(rgb))
            est_s.append(time.perf_counter() - t0)
            decode_s.append(decode)
            stamps.append(frame.stamp_ns)
        if not results:
            raise ValueError(f"{video_path}: no frame could be decoded")
        stamps = np.asarray(stamps, np.int64)
        info.update(_timing(est_s, decode_s), detector_runs=tracker.detector_runs)
        if spec.kind == "onnx-hmr":
            valid = np.array([r is not None for r in results])
            good = next(r for r in results if r is not None) if valid.any() else None
            if good is None:
                raise ValueError("no person was found in any frame")

            def pick(attr):
                ref = np.asarray(getattr(good, attr))
                return np.stack([np.asarray(getattr(r, attr)) if r is not None else ref for r in results])

            prior = vp.prior_from_smpl_rotations(
                pick("global_orient"), pick("body_pose"), pick("betas"), valid,
                np.array([r.score if r is not None else 0.0 for r in results]), stamps, video.rate_hz,
                estimator=f"onnx-hmr:{spec.path.name}")
            info.update(frames=len(results), frames_with_person=int(valid.sum()), detection_rate=float(valid.mean()))
            return prior, info

        from uuomocap.solver_core.body_model import load_body_model

        model = load_body_model(body_model)
        torch.set_num_threads(1)
        t0 = time.perf_counter()
        prior = vp.prior_from_landmarks(results, stamps, video.rate_hz, model, body_model)
        info["fit_seconds"] = time.perf_counter() - t0
        info.update(prior.info)
        return prior, info
    finally:
        video.close()


def vp_stamps(n: int, video: VideoSource) -> np.ndarray:
    from uuomocap.protocol.video import index_stamp_ns

    return index_stamp_ns(np.arange(n), video.rate)


__all__ = ["EstimatorSpec", "parse_estimator", "estimate_prior", "VideoError"]
