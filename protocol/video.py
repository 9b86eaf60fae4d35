"""Video input: frames and their stamps from a file (mp4/avi/...) or a live camera.

Stamps are int64 nanoseconds on the VIDEO clock, starting at 0 for the first frame.
The markers' clock relates to it by the session's ``video.clock_offset_s``:
``marker_time = video_time + clock_offset_s`` (see ``to_marker_clock``).

Rates: containers often store NTSC rates as 29.97002997 (= 30000/1001); we keep the
exact fraction so that frame 9000 lands at 300.3 s, not 300.0 s.  Per-frame stamps
come from ``index / rate`` by default (exact and monotonic); ``timestamps="container"``
uses the container's presentation times instead (variable-frame-rate files).

This module only needs OpenCV; it never imports solver_core or nodes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import numpy as np

NTSC_RATES = (Fraction(24000, 1001), Fraction(30000, 1001), Fraction(60000, 1001), Fraction(120000, 1001))


class VideoError(ValueError):
    """The video cannot be opened or read (message names the file and the problem)."""


@dataclass(frozen=True)
class VideoFrame:
    index: int
    stamp_ns: int  # video clock
    image_bgr: np.ndarray  # (H, W, 3) uint8, OpenCV's channel order

    def rgb(self) -> np.ndarray:
        return self.image_bgr[:, :, ::-1].copy()


def exact_rate(fps: float) -> Fraction:
    """Container fps -> exact rate: NTSC rates (29.97...) become n*1000/1001, others a close fraction."""
    if not np.isfinite(fps) or fps <= 0:
        raise VideoError(f"video reports an invalid frame rate {fps!r}")
    for ntsc in NTSC_RATES:
        if abs(fps - float(ntsc)) < 2e-3:
            return ntsc
    if abs(fps - round(fps)) < 1e-3:
        return Fraction(round(fps))
    return Fraction(fps).limit_denominator(1001)


def index_stamp_ns(index: int | np.ndarray, rate: Fraction) -> np.ndarray:
    """Stamp (ns) of frame ``index`` at an exact ``rate`` (rounded to the nearest ns)."""
    idx = np.asarray(index, dtype=np.int64)
    # index * 1e9 * den / num with integer arithmetic, then round half up.
    num, den = rate.numerator, rate.denominator
    return (idx * (1_000_000_000 * den) * 2 + num) // (2 * num)


def to_marker_clock(stamps_ns: np.ndarray, clock_offset_s: float) -> np.ndarray:
    """Video-clock stamps -> marker-clock stamps (marker_time = video_time + offset)."""
    return np.asarray(stamps_ns, np.int64) + np.int64(round(clock_offset_s * 1e9))


def session_video_settings(session_yaml: str | Path) -> dict:
    """The ``video`` block of a session.yaml: {file, rate_hz, clock_offset_s} (offset 0 if absent)."""
    import yaml

    path = Path(session_yaml)
    if path.is_dir():
        path = path / "session.yaml"
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise VideoError(f"cannot read {path}: {exc}") from None
    video = doc.get("video") or {}
    if not isinstance(video, dict):
        raise VideoError(f"{path}: 'video' must be a mapping, got {type(video).__name__}")
    out = dict(video)
    out["clock_offset_s"] = float(video.get("clock_offset_s", 0.0) or 0.0)
    if "file" in out and out["file"]:
        out["path"] = str((path.parent / str(out["file"])).resolve())
    return out


def is_stream_url(source) -> bool:
    """A network stream OpenCV opens by URL (``rtsp://phone:8554/live``, ``http://10.0.0.7:8080/video``)."""
    return isinstance(source, str) and "://" in source and not source.lower().startswith("file://")


def is_live_source(source) -> bool:
    """A camera index (``0``, ``"1"``) or a stream URL: frames come when they come, stamped on arrival."""
    return isinstance(source, int) or (isinstance(source, str) and (source.isdigit() or is_stream_url(source)))


class VideoSource:
    """Frames of a video file or a live camera.

    source: a file path, an int (or digit string) camera index, or a stream URL (rtsp://, http://).  rate_hz overrides
    the container's rate (e.g. the session's ``video.rate_hz``).  timestamps: "index"
    (default for files), "container" (presentation times) or "wallclock" (default for
    cameras: monotonic time since the first frame).
    """

    def __init__(self, source: str | Path | int, rate_hz: float | None = None, timestamps: str | None = None):
        import cv2

        self._cv2 = cv2
        self.live = is_live_source(source)
        if self.live and is_stream_url(source):  # a phone / IP camera: rtsp://, http(s)://, udp:// ... (OpenCV's FFmpeg)
            self.name = str(source)
            self.capture = cv2.VideoCapture(str(source))
        elif self.live:
            self.name = f"camera {int(source)}"
            self.capture = cv2.VideoCapture(int(source))
        else:
            path = Path(source)
            self.name = str(path)
            if not path.is_file():
                raise VideoError(f"video file not found: {path}")
            self.capture = cv2.VideoCapture(str(path))
        if not self.capture.isOpened():
            raise VideoError(f"cannot open {self.name} (unsupported codec or device busy)")
        fps = float(self.capture.get(cv2.CAP_PROP_FPS) or 0.0)
        if rate_hz is not None:
            self.rate = exact_rate(float(rate_hz))
        elif fps > 0:
            self.rate = exact_rate(fps)
        elif self.live:
            self.rate = Fraction(30)
        else:
            raise VideoError(f"{self.name} reports no frame rate; pass rate_hz")
        self.timestamps = timestamps or ("wallclock" if self.live else "index")
        if self.timestamps not in ("index", "container", "wallclock"):
            raise VideoError(f"timestamps must be 'index', 'container' or 'wallclock', not {self.timestamps!r}")
        self.width = int(self.capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self.capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        count = int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.frame_count = count if count > 0 and not self.live else None
        self._index = 0
        self._t0: int | None = None

    @property
    def rate_hz(self) -> float:
        return float(self.rate)

    def read(self) -> VideoFrame | None:
        ok, image = self.capture.read()
        if not ok or image is None:
            return None
        index = self._index
        self._index += 1
        if self.timestamps == "index":
            stamp = int(index_stamp_ns(index, self.rate))
        elif self.timestamps == "container":
            stamp = int(round(float(self.capture.get(self._cv2.CAP_PROP_POS_MSEC)) * 1e6))
        else:
            now = time.monotonic_ns()
            self._t0 = now if self._t0 is None else self._t0
            stamp = now - self._t0
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        return VideoFrame(index, stamp, image)

    def __iter__(self) -> Iterator[VideoFrame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    def close(self) -> None:
        self.capture.release()

    def __enter__(self) -> "VideoSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def video_source(source: str | Path | int, rate_hz: float | None = None, timestamps: str | None = None
                 ) -> VideoSource:
    """Open a video file or camera index (see ``VideoSource``)."""
    return VideoSource(source, rate_hz, timestamps)
