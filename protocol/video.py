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
    arrival_ns: int = 0  # this host's monotonic clock when the frame was grabbed (live sources; 0 for files)

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
    cameras: monotonic time since the first frame).  latest_only (default for live sources): a
    thread grabs frames as they come and ``read`` returns the newest one, so a reader slower than
    the camera gets current frames instead of an ever older backlog from the driver's or FFmpeg's
    buffer (``dropped`` counts the frames it never saw).
    """

    def __init__(self, source: str | Path | int, rate_hz: float | None = None, timestamps: str | None = None,
                 latest_only: bool | None = None):
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
            why = ("unreachable, or a stream OpenCV's FFmpeg cannot read" if is_stream_url(source) else
                   "no such camera, or another program holds it" if self.live else "unsupported codec")
            raise VideoError(f"cannot open {self.name} ({why})")
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
        self.dropped = 0
        self._grabber = None
        if self.live if latest_only is None else latest_only:
            import threading

            self._latest: tuple | None = None  # (grab index, arrival ns, image) not yet read
            self._grab_done = False
            self._cond = threading.Condition()
            self._grabber = threading.Thread(target=self._grab_loop, name=f"grab {self.name}", daemon=True)
            self._grabber.start()

    @property
    def rate_hz(self) -> float:
        return float(self.rate)

    def _grab_loop(self) -> None:
        index = 0
        while True:
            try:
                ok, image = self.capture.read()
            except Exception:  # cv2.error from a dying device or stream: the end of the source
                ok, image = False, None
            now = time.monotonic_ns()
            pos_ms = float(self.capture.get(self._cv2.CAP_PROP_POS_MSEC)) if ok and self.timestamps == "container" else 0.0
            with self._cond:
                if not ok or image is None or self._grab_done:
                    self._grab_done = True
                    self._cond.notify_all()
                    return
                if self._latest is not None:
                    self.dropped += 1
                self._latest = (index, now, image, pos_ms)
                self._cond.notify_all()
            index += 1

    def _next(self) -> tuple | None:
        """(index, arrival ns, image, container ms) of the next frame, or None at the end."""
        if self._grabber is None:
            ok, image = self.capture.read()
            if not ok or image is None:
                return None
            self._index += 1
            pos_ms = float(self.capture.get(self._cv2.CAP_PROP_POS_MSEC)) if self.timestamps == "container" else 0.0
            return self._index - 1, time.monotonic_ns() if self.live else 0, image, pos_ms
        with self._cond:
            while self._latest is None and not self._grab_done:
                self._cond.wait(0.5)
            latest, self._latest = self._latest, None
        return latest

    def read(self) -> VideoFrame | None:
        got = self._next()
        if got is None:
            return None
        index, arrival, image, pos_ms = got
        if self.timestamps == "index":
            stamp = int(index_stamp_ns(index, self.rate))
        elif self.timestamps == "container":
            stamp = int(round(pos_ms * 1e6))
        else:
            now = arrival or time.monotonic_ns()
            self._t0 = now if self._t0 is None else self._t0
            stamp = now - self._t0
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        return VideoFrame(index, stamp, image, arrival)

    def __iter__(self) -> Iterator[VideoFrame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    def close(self) -> None:
        if self._grabber is not None:  # let the grab thread leave its read before the capture goes away
            with self._cond:
                self._grab_done = True
            self._grabber.join(timeout=2.0)
        self.capture.release()

    def __enter__(self) -> "VideoSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def video_source(source: str | Path | int, rate_hz: float | None = None, timestamps: str | None = None,
                 latest_only: bool | None = None) -> VideoSource:
    """Open a video file, camera index or stream URL (see ``VideoSource``)."""
    return VideoSource(source, rate_hz, timestamps, latest_only)
