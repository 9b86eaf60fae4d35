"""Recordings: graph messages in MCAP files (Foxglove's chunked, indexed container).

One MCAP channel per (topic, message type); the channel's schema is the
message type's JSON schema (name ``uuomocap.<Type>``, metadata carries the
schema and envelope versions). Message encoding ``msgpack``: each MCAP message
is the envelope header map with one extra key ``"d"``, the list of raw array
buffers, so a recorded message decodes through exactly the same bounded
``envelope.decode`` as a live one.

Times: MCAP ``log_time`` is the recorder's receive time and ``publish_time`` the
publisher's send time, both CLOCK_MONOTONIC ns of the recording machine (so
latencies are differences); the capture stamp travels inside the message. The
file's ``clock`` metadata pairs a monotonic and a wall-clock reading.

Crash safety: the writer closes a chunk and flushes the file every
``flush_interval_s`` (and whenever a chunk is full), so a recorder killed with
SIGKILL leaves a file that :func:`iter_recording` reads up to the last flushed
chunk (it stops quietly at a truncated tail and reports ``truncated``).
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import msgpack
import numpy as np

from .envelope import DEFAULT_LIMITS, ENVELOPE_VERSION, DecodeError, Envelope, Limits, decode, envelope_to_frames
from .messages import MESSAGE_TYPES, MarkerFrame

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "uuomocap-schema+json"
PROFILE = "uuomocap"


class RecordingError(ValueError):
    """A recording that cannot be opened or is not one of ours (one-line message)."""


def envelope_record(env: Envelope) -> bytes:
    """The msgpack bytes stored in MCAP for one received message."""
    frames = envelope_to_frames(env)
    header = msgpack.unpackb(frames[1], raw=False)
    header["pt"] = env.publish_ns
    header["d"] = [bytes(b) for b in frames[2:]]
    return msgpack.packb(header, use_bin_type=True)


def record_frames(topic: str, data: bytes, limits: Limits = DEFAULT_LIMITS) -> list[bytes]:
    """Inverse of :func:`envelope_record`: multipart frames ready for ``envelope.decode``."""
    try:
        header = msgpack.unpackb(
            data,
            raw=False,
            max_bin_len=limits.max_array_bytes,
            max_str_len=limits.max_header_bytes,
            max_array_len=4096,
            max_map_len=1024,
            max_ext_len=0,
        )
    except Exception as exc:
        raise DecodeError("header", f"recorded message is not msgpack: {type(exc).__name__}") from None
    if not isinstance(header, dict) or not isinstance(header.get("d"), list):
        raise DecodeError("header", "recorded message lacks its array list 'd'")
    arrays = header.pop("d")
    if not all(isinstance(a, bytes) for a in arrays):
        raise DecodeError("array", "recorded array entries must be binary")
    return [topic.encode(), msgpack.packb(header, use_bin_type=True), *arrays]


class RecordingWriter:
    """Append graph messages to an MCAP file, flushing a chunk at least every ``flush_interval_s``."""

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_size: int = 512 * 1024,
        flush_interval_s: float = 0.5,
        compression: str = "none",
        metadata: dict[str, str] | None = None,
    ):
        from mcap.writer import CompressionType, Writer

        comp = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}.get(compression)
        if comp is None:
            raise RecordingError(f"compression must be none, lz4 or zstd, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "wb")
        self._writer = Writer(self._fh, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile=PROFILE, library="uuomocap")
        self._writer.add_metadata(
            "clock", {"monotonic_ns": str(time.monotonic_ns()), "wall_ns": str(time.time_ns()), "log_time": "receive, CLOCK_MONOTONIC ns"}
        )
        if metadata:
            self._writer.add_metadata("graph", {str(k): str(v) for k, v in metadata.items()})
        self._flush_interval_ns = int(flush_interval_s * 1e9)
        self._last_flush = time.monotonic_ns()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self.messages = 0
        self.closed = False

    def _channel(self, topic: str, type_name: str) -> int:
        key = (topic, type_name)
        cid = self._channels.get(key)
        if cid is None:
            cls = MESSAGE_TYPES[type_name]
            sid = self._schemas.get(type_name)
            if sid is None:
                sid = self._writer.register_schema(f"uuomocap.{type_name}", SCHEMA_ENCODING, cls.schema_bytes())
                self._schemas[type_name] = sid
            cid = self._writer.register_channel(
                topic,
                MESSAGE_ENCODING,
                sid,
                {"type": type_name, "schema_version": str(cls.VERSION), "envelope_version": str(ENVELOPE_VERSION)},
            )
            self._channels[key] = cid
        return cid

    def write(self, env: Envelope, log_time_ns: int | None = None) -> None:
        now = time.monotonic_ns()
        self._writer.add_message(
            self._channel(env.topic, env.type),
            log_time=now if log_time_ns is None else int(log_time_ns),
            data=envelope_record(env),
            publish_time=int(env.publish_ns),
            sequence=max(0, env.seq) & 0xFFFFFFFF,
        )
        self.messages += 1
        if now - self._last_flush >= self._flush_interval_ns:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and push it to the OS (survives a SIGKILL of this process)."""
        self._writer.flush()
        self._last_flush = time.monotonic_ns()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._writer.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()


@dataclass
class RecordedMessage:
    topic: str
    type: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes

    def frames(self, limits: Limits = DEFAULT_LIMITS) -> list[bytes]:
        return record_frames(self.topic, self.data, limits)

    def decode(self, limits: Limits = DEFAULT_LIMITS) -> Envelope:
        return decode(self.frames(limits), limits)


@dataclass
class RecordingInfo:
    path: str
    messages: int = 0
    topics: dict = field(default_factory=dict)  # topic -> {"type", "count", "first_stamp_ns", "last_stamp_ns"}
    truncated: bool = False
    finished: bool = False  # the file has its summary/footer (clean close)
    metadata: dict = field(default_factory=dict)


def iter_recording(path: str | Path, topics: list[str] | None = None, info: RecordingInfo | None = None) -> Iterator[RecordedMessage]:
    """Messages of a recording in file order; tolerant of a truncated tail (killed recorder).

    ``info`` (optional) is filled while iterating: counts, truncated, finished.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Footer, Message, Metadata
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such recording")
    info = info if info is not None else RecordingInfo(str(path))
    wanted = set(topics) if topics else None
    channels: dict[int, tuple[str, str]] = {}
    with open(path, "rb") as fh:
        reader = StreamReader(fh, record_size_limit=DEFAULT_LIMITS.max_total_bytes)
        records = reader.records
        try:
            for rec in records:
                if isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic, rec.metadata.get("type", ""))
                elif isinstance(rec, Metadata):
                    info.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    info.finished = True
                elif isinstance(rec, Message):
                    topic, type_name = channels.get(rec.channel_id, ("", ""))
                    if wanted is not None and topic not in wanted:
                        continue
                    info.messages += 1
                    t = info.topics.setdefault(topic, {"type": type_name, "count": 0})
                    t["count"] += 1
                    yield RecordedMessage(topic, type_name, rec.log_time, rec.publish_time, rec.data)
        except McapError as exc:
            if info.messages == 0 and not channels and "magic" in str(exc).lower():
                raise RecordingError(f"{path}: not an MCAP file ({exc})") from None
            info.truncated = True
        except (EOFError, ValueError, KeyError, IndexError, struct.error):
            # a half-written record at the tail of a killed recording
            info.truncated = True


def recording_info(path: str | Path) -> RecordingInfo:
    info = RecordingInfo(str(path))
    for msg in iter_recording(path, info=info):
        pass
    return info


def read_markers_mcap(path: str | Path, topic: str = "markers/raw", progress: bool = False):
    """Our MCAP recordings as :class:`uuomocap.protocol.markerio.MarkerData` (registered for ``.mcap``).

    Columns are tracks: ``track_ids`` when the frames carry them, else the index in
    the frame. A track absent from a frame is NaN / not visible there.
    """
    from .markerio import MarkerData, MarkerFileError, is_placeholder_label, placeholder_labels

    info = RecordingInfo(str(path))
    frames: list[MarkerFrame] = []
    bad = 0
    try:
        for rec in iter_recording(path, topics=[topic], info=info):
            try:
                env = rec.decode()
            except DecodeError:
                bad += 1
                continue
            if isinstance(env.message, MarkerFrame):
                frames.append(env.message)
    except RecordingError as exc:
        raise MarkerFileError(str(exc)) from None
    if not frames:
        raise MarkerFileError(f"{path}: recording has no MarkerFrame messages on topic '{topic}'")
    frames.sort(key=lambda f: f.stamp_ns)
    col_of: dict[int, int] = {}
    labels_of: dict[int, str] = {}
    per_frame_ids = []
    for f in frames:
        ids = f.track_ids if f.track_ids is not None else np.arange(len(f.positions), dtype=np.int32)
        per_frame_ids.append(ids)
        for j, tid in enumerate(ids.tolist()):
            if tid not in col_of:
                col_of[tid] = len(col_of)
            if f.labels and f.labels[j]:  # the last name a track had: a live namer's follow the solver's lock
                labels_of[tid] = f.labels[j]
    T, M = len(frames), len(col_of)
    positions = np.full((T, M, 3), np.nan)
    visible = np.zeros((T, M), bool)
    residuals = np.full((T, M), -1.0)
    any_residuals = False
    for t, (f, ids) in enumerate(zip(frames, per_frame_ids)):
        cols = np.array([col_of[i] for i in ids.tolist()], dtype=np.int64)
        vis = np.asarray(f.visible, bool)
        positions[t, cols[vis]] = f.positions[vis]
        visible[t, cols] = vis
        if f.residuals is not None:
            any_residuals = True
            residuals[t, cols[vis]] = f.residuals[vis]
    tracks = sorted(col_of, key=col_of.get)
    default = placeholder_labels(M)
    labels = [labels_of.get(tid, default[i]) for i, tid in enumerate(tracks)]
    placeholder = np.array([is_placeholder_label(lab) for lab in labels], bool)
    stamps = np.array([f.stamp_ns for f in frames], np.int64)
    rate = frames[0].rate_hz
    if not rate > 0 and T > 1:
        rate = 1e9 / float(np.median(np.diff(stamps)))
    warnings = []
    if info.truncated:
        warnings.append("recording ends in a truncated chunk (recorder was killed); read up to the last flushed chunk")
    if bad:
        warnings.append(f"{bad} recorded messages failed to decode and were skipped")
    return MarkerData(
        positions=positions,
        visible=visible,
        rate_hz=float(rate),
        labels=labels,
        labelled=not placeholder.any() and bool(labels_of),
        units_found="m",
        up_axis=frames[0].up_axis,
        residuals=residuals if any_residuals else None,
        first_frame=int(frames[0].frame_index),
        stamps_ns=stamps,
        source=str(path),
        warnings=warnings,
        up_axis_source="recording",
        units_used="m",
        format="mcap",
        reader="uuomocap.recording",
        raw_labels=list(labels),
        placeholder=placeholder,
        meta={"topic": topic, "tracks": tracks},
    )


_KIND_RANK = {"estimate": 0, "refined": 1, "revised": 2}


def best_solved_frames(frames) -> list:
    """One SolvedFrame per capture stamp: the last 'revised' one, else the last 'refined', else the
    last 'estimate'; sorted by stamp."""
    best: dict[int, object] = {}
    for f in frames:
        prev = best.get(f.stamp_ns)
        if prev is None or _KIND_RANK.get(f.kind, 0) >= _KIND_RANK.get(prev.kind, 0):
            best[f.stamp_ns] = f
    return [best[k] for k in sorted(best)]


def export_solved_npz(frames, path: str | Path, method: str = "stream", stage_seconds: str | None = None) -> dict:
    """Write SolvedFrames as OUT.npz (AMASS layout, see the brief); returns a small summary.

    betas and the marker labels come from the last frame (the solver's latest shape and
    assignment); ``frame_betas`` (F, B) is the shape each frame was solved under (a lock upgrade
    changes it mid-take; pose a frame with its own row); ``frame_kind`` says per frame which
    answer it holds (estimate, refined, or revised after a lock upgrade).
    """
    frames = best_solved_frames(frames)
    if not frames:
        raise ValueError("no solved frames to export")
    last = frames[-1]
    stamps = np.array([f.stamp_ns for f in frames], np.int64)
    rate = last.rate_hz
    if not rate > 0:
        rate = 1e9 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    M = 0 if last.marker_faces is None else len(last.marker_faces)
    out = {
        "betas": np.asarray(last.betas),
        "frame_betas": np.stack([np.asarray(f.betas) for f in frames]),
        "poses": np.stack([f.poses for f in frames]),
        "trans": np.stack([f.trans for f in frames]),
        "mocap_framerate": np.array(float(rate)),
        "body_model": np.array(last.body_model),
        "joints": np.stack([f.joints for f in frames]),
        "stamps_ns": stamps,
        "frame_index": np.array([f.frame_index for f in frames], np.int64),
        "frame_kind": np.array([f.kind for f in frames]),
        "residual_m": np.array([f.residual_m for f in frames], np.float64),
        "marker_parts": np.array(list(last.marker_parts) if last.marker_parts else [""] * M, dtype=str).reshape(M),
        "marker_faces": np.asarray(last.marker_faces if M else np.zeros(0, np.int32)).astype(np.int64),
        "marker_bary": np.asarray(last.marker_bary if last.marker_bary is not None else np.zeros((M, 3))).reshape(M, 3),
        "method": np.array(method),
    }
    if stage_seconds is not None:
        out["stage_seconds"] = np.array(stage_seconds)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **out)
    os.replace(tmp, path)
    kinds = out["frame_kind"]
    return {"frames": len(frames), "refined": int(np.isin(kinds, ("refined", "revised")).sum()),
            "revised": int((kinds == "revised").sum()), "path": str(path)}


__all__ = [
    "RecordingWriter",
    "RecordingError",
    "RecordedMessage",
    "RecordingInfo",
    "iter_recording",
    "recording_info",
    "read_markers_mcap",
    "export_solved_npz",
    "best_solved_frames",
    "envelope_record",
    "record_frames",
]

