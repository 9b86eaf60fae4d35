"""Wire format: ZeroMQ multipart ``[topic | msgpack header | raw array frames...]``.

The header (a msgpack map, short keys to keep it small):

    v     envelope version            t    message type name     tv   message type version
    seq   per-(publisher, topic) sequence number (-1 for probes, which are not counted)
    st    capture stamp, ns            pt   publish stamp, monotonic ns (CLOCK_MONOTONIC is
                                            system-wide, so latencies between processes on one
                                            machine are differences of these)
    src   publishing node              inst publisher instance (random per process; a respawned
                                            node starts a new sequence)
    sess  session / graph id           f    scalar fields of the message
    a     [[name, dtype, shape], ...]  one entry per array frame that follows, in order

Arrays travel as raw C-contiguous buffers and are received zero-copy
(``np.frombuffer`` over the ZeroMQ frame; the arrays are read-only). Nothing is
pickled. :func:`decode` bounds every size before touching the data and raises
:class:`DecodeError` (with a short ``reason`` for counting) on anything it does
not fully understand; receivers log and count those and keep running.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Sequence

import msgpack
import numpy as np

from .messages import ALLOWED_DTYPES, MESSAGE_TYPES, Message, MessageError

ENVELOPE_VERSION = 1


@dataclass(frozen=True)
class Limits:
    """Upper bounds applied to every received message before it is parsed."""

    max_frames: int = 34  # topic + header + 32 arrays
    max_topic_bytes: int = 200
    max_header_bytes: int = 64 * 1024
    max_array_bytes: int = 64 * 1024 * 1024
    max_total_bytes: int = 256 * 1024 * 1024
    max_ndim: int = 4


DEFAULT_LIMITS = Limits()

#: reasons a message is rejected; receivers count them per reason
REJECT_REASONS = (
    "frames",  # too few / too many frames
    "topic",  # topic frame too long, not UTF-8, or differs from the header
    "header",  # header too large or not a msgpack map with the expected keys
    "envelope_version",
    "unknown_type",
    "unknown_version",
    "array",  # bad dtype / shape / size declaration
    "size",  # declared shape * itemsize != buffer size
    "fields",  # scalar/array fields do not match the message schema
)


class DecodeError(Exception):
    """A received message was rejected. ``reason`` is one of REJECT_REASONS."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class Envelope:
    """A decoded message and its routing/timing metadata."""

    topic: str
    message: Message
    seq: int
    stamp_ns: int
    publish_ns: int
    source: str
    instance: int
    session: str
    nbytes: int

    @property
    def type(self) -> str:
        return self.message.TYPE


def encode(
    topic: str,
    message: Message,
    *,
    seq: int,
    stamp_ns: int,
    source: str,
    instance: int,
    session: str = "",
    publish_ns: int | None = None,
    validate: bool = True,
) -> list[Any]:
    """Frames to send with ``socket.send_multipart(frames, copy=False)``.

    Array frames are the arrays' own buffers (no copy on the Python side).
    """
    if validate:
        message.validate()
    arrays = message.arrays()
    descr = []
    buffers = []
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        descr.append([name, arr.dtype.str, list(arr.shape)])
        buffers.append(memoryview(arr).cast("B") if arr.size else b"")
    header = {
        "v": ENVELOPE_VERSION,
        "t": message.TYPE,
        "tv": message.VERSION,
        "seq": int(seq),
        "st": int(stamp_ns),
        "pt": int(time.monotonic_ns() if publish_ns is None else publish_ns),
        "src": source,
        "inst": int(instance),
        "sess": session,
        "f": message.scalars(),
        "a": descr,
    }
    return [topic.encode(), msgpack.packb(header, use_bin_type=True), *buffers]


def _buffer(frame: Any) -> memoryview:
    buf = getattr(frame, "buffer", None)  # zmq.Frame (copy=False receive)
    return memoryview(frame if buf is None else buf)


def _header_int(header: dict, key: str) -> int:
    value = header.get(key)
    if not isinstance(value, int) or isinstance(value, bool):
        raise DecodeError("header", f"header field {key!r} must be an integer, got {type(value).__name__}")
    return value


def _header_str(header: dict, key: str) -> str:
    value = header.get(key)
    if not isinstance(value, str):
        raise DecodeError("header", f"header field {key!r} must be a string, got {type(value).__name__}")
    return value


def decode(frames: Sequence[Any], limits: Limits = DEFAULT_LIMITS) -> Envelope:
    """Parse and check one multipart message; raise DecodeError if anything is off."""
    if not 2 <= len(frames) <= limits.max_frames:
        raise DecodeError("frames", f"{len(frames)} frames (allowed 2..{limits.max_frames})")
    bufs = [_buffer(f) for f in frames]
    total = sum(b.nbytes for b in bufs)
    if total > limits.max_total_bytes:
        raise DecodeError("frames", f"message of {total} bytes exceeds {limits.max_total_bytes}")
    topic_buf, header_buf, array_bufs = bufs[0], bufs[1], bufs[2:]
    if topic_buf.nbytes > limits.max_topic_bytes:
        raise DecodeError("topic", f"topic of {topic_buf.nbytes} bytes")
    try:
        topic = bytes(topic_buf).decode("utf-8")
    except UnicodeDecodeError:
        raise DecodeError("topic", "topic is not UTF-8") from None
    if header_buf.nbytes > limits.max_header_bytes:
        raise DecodeError("header", f"header of {header_buf.nbytes} bytes exceeds {limits.max_header_bytes}")
    try:
        header = msgpack.unpackb(
            header_buf,
            raw=False,
            strict_map_key=True,
            max_str_len=limits.max_header_bytes,
            max_bin_len=0,
            max_ext_len=0,
            max_array_len=4096,
            max_map_len=1024,
        )
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise DecodeError("header", f"not msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(header, dict):
        raise DecodeError("header", f"header is a {type(header).__name__}, not a map")
    if header.get("v") != ENVELOPE_VERSION:
        raise DecodeError("envelope_version", f"envelope version {header.get('v')!r} (expected {ENVELOPE_VERSION})")
    type_name = header.get("t")
    cls = MESSAGE_TYPES.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        raise DecodeError("unknown_type", f"unknown message type {type_name!r:.40}")
    if header.get("tv") != cls.VERSION:
        raise DecodeError("unknown_version", f"{type_name} version {header.get('tv')!r} (this build reads {cls.VERSION})")
    seq = _header_int(header, "seq")
    stamp_ns = _header_int(header, "st")
    publish_ns = _header_int(header, "pt")
    instance = _header_int(header, "inst")
    source = _header_str(header, "src")
    session = _header_str(header, "sess")
    fields = header.get("f")
    descr = header.get("a")
    if not isinstance(fields, dict) or not isinstance(descr, list):
        raise DecodeError("header", "header lacks the 'f' map or 'a' list")
    if len(descr) != len(array_bufs):
        raise DecodeError("frames", f"header declares {len(descr)} arrays, message has {len(array_bufs)} array frames")

    specs = cls.array_specs()
    scalar_types = cls.scalar_types()
    if set(fields) != set(scalar_types):
        missing = sorted(set(scalar_types) - set(fields))
        extra = sorted(map(str, set(fields) - set(scalar_types)))
        raise DecodeError("fields", f"{type_name} scalar fields: missing {missing}, unexpected {extra[:5]}")
    kwargs: dict[str, Any] = dict(fields)
    for entry, buf in zip(descr, array_bufs):
        arr_name, arr = _decode_array(entry, buf, limits)
        if arr_name not in specs:
            raise DecodeError("fields", f"{type_name} has no array field {arr_name!r:.40}")
        if arr_name in kwargs:
            raise DecodeError("fields", f"array {arr_name!r} appears twice")
        kwargs[arr_name] = arr
    for name, spec in specs.items():
        if name not in kwargs:
            if not spec.optional:
                raise DecodeError("fields", f"{type_name} lacks required array {name!r}")
            kwargs[name] = None
    try:
        message = cls(**kwargs)
        message.validate()
    except (MessageError, TypeError, ValueError) as exc:
        raise DecodeError("fields", str(exc)) from None
    return Envelope(
        topic=topic,
        message=message,
        seq=seq,
        stamp_ns=stamp_ns,
        publish_ns=publish_ns,
        source=source,
        instance=instance,
        session=session,
        nbytes=total,
    )


def _decode_array(entry: Any, buf: memoryview, limits: Limits) -> tuple[str, np.ndarray]:
    if not (isinstance(entry, list) and len(entry) == 3):
        raise DecodeError("array", "array descriptor must be [name, dtype, shape]")
    name, dtype_str, shape = entry
    if not isinstance(name, str) or not isinstance(dtype_str, str) or not isinstance(shape, list):
        raise DecodeError("array", "array descriptor has wrong field types")
    if dtype_str not in ALLOWED_DTYPES:
        raise DecodeError("array", f"array {name!r:.40}: dtype {dtype_str!r:.20} not allowed")
    if len(shape) > limits.max_ndim or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape):
        raise DecodeError("array", f"array {name!r:.40}: bad shape {shape!r:.60}")
    dtype = np.dtype(dtype_str)
    nbytes = dtype.itemsize
    for d in shape:
        nbytes *= d
        if nbytes > limits.max_array_bytes:
            raise DecodeError("array", f"array {name!r:.40}: declared size exceeds {limits.max_array_bytes} bytes")
    if nbytes != buf.nbytes:
        raise DecodeError("size", f"array {name!r:.40}: shape {shape} needs {nbytes} bytes, frame has {buf.nbytes}")
    if nbytes:
        arr = np.frombuffer(buf, dtype=dtype).reshape(shape)
    else:  # empty arrays: nothing to view; read-only like every received array
        arr = np.zeros(shape, dtype)
        arr.setflags(write=False)
    return name, arr


def envelope_to_frames(env: Envelope, *, seq: int | None = None, source: str | None = None, instance: int | None = None) -> list[Any]:
    """Re-encode a decoded envelope (used by replay of recordings and relays)."""
    return encode(
        env.topic,
        env.message,
        seq=env.seq if seq is None else seq,
        stamp_ns=env.stamp_ns,
        source=env.source if source is None else source,
        instance=env.instance if instance is None else instance,
        session=env.session,
        validate=False,
    )
