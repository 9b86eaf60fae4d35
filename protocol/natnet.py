"""OptiTrack NatNet (Motive) live stream: packet codec, client and a loopback server.

Written from the public description of the NatNet bitstream (no OptiTrack sample
code).  Every packet is ``uint16 message id | uint16 payload bytes | payload``,
little-endian.  The messages handled here:

* ``NAT_CONNECT`` (0)      client -> server command port, payload ``"Ping\\0"`` (any payload is accepted).
* ``NAT_SERVERINFO`` (1)   server reply: ``char name[256] | u8 app_version[4] | u8 natnet_version[4] |
                           u64 high_res_clock_hz | u16 data_port | u8 is_multicast | u8 multicast_group[4]``.
* ``NAT_FRAMEOFDATA`` (7)  one capture frame (layout below).
* ``NAT_KEEPALIVE`` (10)   unicast clients send it on the command channel; no payload, no reply.
* ``NAT_DISCONNECT`` (9), ``NAT_MESSAGESTRING`` (8), ``NAT_REQUEST`` (2) / ``NAT_RESPONSE`` (3).

Frame of data, bitstream 3.0 .. 4.0 (each ``count`` is int32)::

    i32 frame_number
    count marker sets:    { cstring name | count | count x f32[3] }
    count other markers:  count x f32[3]                 ("legacy" unlabeled points)
    count rigid bodies:   { i32 id | f32[3] pos | f32[4] quat xyzw | f32 mean_error | i16 params }
    count skeletons:      { i32 id | count rigid bodies (as above) }
    count labeled markers:{ i32 id (model<<16 | member) | f32[3] pos | f32 size | i16 params | f32 residual }
    count force plates:   { i32 id | count channels: { count frames x f32 } }
    count devices:        { i32 id | count channels: { count frames x f32 } }
    u32 timecode | u32 timecode_sub | f64 timestamp (s) |
    u64 stamp_camera_mid_exposure | u64 stamp_data_received | u64 stamp_transmit   (high-res clock ticks)
    i16 params (bit0 recording, bit1 tracked models changed) | i32 end-of-data (0)

Bitstream 4.1+ puts ``i32 section_bytes`` after every section count (so unknown
content can be skipped), adds an *assets* section between skeletons and labeled
markers (``{ i32 id | count rigid bodies | count asset markers (labeled-marker
layout) }``) and ``u32 precision_secs | u32 precision_fraction`` before the
params.  Newer servers (4.2+) may append further sized sections after devices;
they are skipped and counted.

Positions are metres in Motive's streaming frame, Y-up by default
(:data:`MOTIVE_UP_AXIS`).  Every length is bounds-checked: a malformed packet
raises :class:`NatNetError`; the client counts it and keeps going.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from dataclasses import dataclass, field

import numpy as np

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

DEFAULT_COMMAND_PORT = 1510
DEFAULT_DATA_PORT = 1511
DEFAULT_MULTICAST_GROUP = "239.255.42.99"
MOTIVE_UP_AXIS = "+y"  # Motive streams Y-up unless "Up Axis: Z" is chosen in its streaming pane
MAX_NAME_BYTES = 256
MAX_PAYLOAD_BYTES = 0xFFFF  # the header's payload length is a uint16
SERVER_INFO_BYTES = MAX_NAME_BYTES + 4 + 4 + 8 + 2 + 1 + 4
OLDEST_SUPPORTED = (3, 0)

# Labeled-marker params bits (bitstream 3.0+).
MARKER_OCCLUDED = 0x01  # position is not a measurement (e.g. filled by the model)
MARKER_POINT_CLOUD_SOLVED = 0x02
MARKER_MODEL_SOLVED = 0x04
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10
MARKER_ACTIVE = 0x20
RIGID_BODY_TRACKING_VALID = 0x01
FRAME_RECORDING = 0x01
FRAME_MODELS_CHANGED = 0x02

RIGID_BODY_DTYPE = np.dtype(
    [("id", "<i4"), ("position", "<f4", (3,)), ("orientation", "<f4", (4,)),
     ("mean_error", "<f4"), ("params", "<i2")]
)
LABELED_MARKER_DTYPE = np.dtype(
    [("id", "<i4"), ("position", "<f4", (3,)), ("size", "<f4"), ("params", "<i2"), ("residual", "<f4")]
)
POINT_DTYPE = np.dtype("<f4")
_HEADER = struct.Struct("<HH")
_SUFFIX_TIMES = struct.Struct("<IIdQQQ")
_PRECISION = struct.Struct("<II")
_PARAMS = struct.Struct("<h")
_EOD = struct.Struct("<i")
assert RIGID_BODY_DTYPE.itemsize == 38 and LABELED_MARKER_DTYPE.itemsize == 26


class NatNetError(ValueError):
    """A NatNet packet that cannot be decoded (truncated, inconsistent length, unsupported version)."""


def _version_tuple(version) -> tuple[int, int]:
    try:
        major, minor = int(version[0]), int(version[1])
    except (TypeError, ValueError, IndexError):
        raise NatNetError(f"NatNet version must be (major, minor), got {version!r}") from None
    if (major, minor) < OLDEST_SUPPORTED:
        raise NatNetError(
            f"NatNet bitstream {major}.{minor} is not supported (needs 3.0 or newer; "
            "choose a newer bitstream version in Motive's streaming settings)"
        )
    return major, minor


def _sized_sections(version: tuple[int, int]) -> bool:
    return version >= (4, 1)


# --------------------------------------------------------------------------- data


def _empty(dtype, shape=(0,)) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass
class Skeleton:
    id: int
    rigid_bodies: np.ndarray  # RIGID_BODY_DTYPE records


@dataclass
class Asset:
    id: int
    rigid_bodies: np.ndarray  # RIGID_BODY_DTYPE records
    markers: np.ndarray  # LABELED_MARKER_DTYPE records


@dataclass
class AnalogDevice:
    """A force plate or peripheral device: one float32 array of sub-frame samples per channel."""

    id: int
    channels: list[np.ndarray]


@dataclass
class ServerInfo:
    app_name: str = "Motive"
    app_version: tuple[int, int, int, int] = (3, 1, 0, 0)
    natnet_version: tuple[int, int, int, int] = (4, 1, 0, 0)
    high_res_clock_hz: int = 1_000_000_000
    data_port: int = DEFAULT_DATA_PORT
    multicast: bool = False
    multicast_group: str = DEFAULT_MULTICAST_GROUP


@dataclass
class FrameOfData:
    """One decoded ``NAT_FRAMEOFDATA``.  Positions are float32 metres in Motive's streaming frame."""

    frame_number: int = 0
    marker_sets: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (n,3)
    other_markers: np.ndarray = field(default_factory=lambda: _empty(POINT_DTYPE, (0, 3)))
    rigid_bodies: np.ndarray = field(default_factory=lambda: _empty(RIGID_BODY_DTYPE))
    skeletons: list[Skeleton] = field(default_factory=list)
    assets: list[Asset] = field(default_factory=list)  # 4.1+
    labeled_markers: np.ndarray = field(default_factory=lambda: _empty(LABELED_MARKER_DTYPE))
    force_plates: list[AnalogDevice] = field(default_factory=list)
    devices: list[AnalogDevice] = field(default_factory=list)
    timecode: int = 0
    timecode_sub: int = 0
    timestamp: float = 0.0  # seconds since the server started (double since bitstream 2.7)
    stamp_camera_mid_exposure: int = 0  # high-res clock ticks (ServerInfo.high_res_clock_hz)
    stamp_data_received: int = 0
    stamp_transmit: int = 0
    precision_timestamp_secs: int = 0  # 4.1+
    precision_timestamp_frac: int = 0  # 4.1+
    params: int = 0
    skipped_sections: int = 0  # sized sections of a newer bitstream this decoder does not know

    @property
    def is_recording(self) -> bool:
        return bool(self.params & FRAME_RECORDING)

    @property
    def tracked_models_changed(self) -> bool:
        return bool(self.params & FRAME_MODELS_CHANGED)

    def point_cloud(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All measured 3D points of this frame: ``positions (N,3) f32, ids (N,) i32, labelled (N,) bool``.

        Since bitstream 3.0 the labeled-marker list carries every reconstructed
        point (unlabeled ones flagged ``MARKER_UNLABELED``); the legacy
        "other markers" list repeats the unlabeled ones, so it is used only when
        the labeled list is empty.  Occluded markers are model fills, not
        measurements, and are left out.  ``ids`` is Motive's ``model<<16|member``
        (-1 for legacy points); it is not a stable track id.
        """
        lm = self.labeled_markers
        if len(lm):
            keep = (lm["params"] & MARKER_OCCLUDED) == 0
            pos = np.ascontiguousarray(lm["position"][keep], dtype=np.float32)
            ids = lm["id"][keep].astype(np.int32)
            labelled = ((lm["params"][keep] & MARKER_UNLABELED) == 0) & ((ids >> 16) != 0)
            return pos, ids, labelled
        pos = np.ascontiguousarray(self.other_markers, dtype=np.float32).reshape(-1, 3)
        return pos, np.full(len(pos), -1, np.int32), np.zeros(len(pos), bool)


# --------------------------------------------------------------------------- decoding


class _Reader:
    """Bounds-checked little-endian cursor over a payload."""

    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf: memoryview, pos: int, end: int):
        self.buf, self.pos, self.end = buf, pos, end

    def remaining(self) -> int:
        return self.end - self.pos

    def take(self, n: int, what: str) -> memoryview:
        if n < 0 or n > self.end - self.pos:
            raise NatNetError(f"truncated packet: {what} needs {n} bytes at offset {self.pos}, "
                              f"{self.end - self.pos} left")
        view = self.buf[self.pos:self.pos + n]
        self.pos += n
        return view

    def unpack(self, st: struct.Struct, what: str) -> tuple:
        return st.unpack(self.take(st.size, what))

    def i32(self, what: str) -> int:
        return self.unpack(_EOD, what)[0]

    def count(self, min_item_bytes: int, what: str) -> int:
        n = self.i32(f"{what} count")
        if n < 0 or n * min_item_bytes > self.remaining():
            raise NatNetError(f"bad {what} count {n} with {self.remaining()} bytes left")
        return n

    def records(self, dtype: np.dtype, n: int, what: str) -> np.ndarray:
        view = self.take(n * dtype.itemsize, what)
        return np.frombuffer(view, dtype=dtype, count=n).copy()

    def cstring(self, what: str) -> str:
        limit = min(self.end, self.pos + MAX_NAME_BYTES)
        raw = bytes(self.buf[self.pos:limit])
        nul = raw.find(b"\0")
        if nul < 0:
            raise NatNetError(f"{what}: string not NUL-terminated within {limit - self.pos} bytes")
        self.pos += nul + 1
        return raw[:nul].decode("utf-8", errors="replace")


def _counted(r: _Reader, count: int | None, min_item: int, what: str) -> int:
    """The section's item count: read inline (``count is None``) or given by a 4.1+ section header."""
    if count is None:
        return r.count(min_item, what)
    if count < 0 or count * min_item > r.remaining():
        raise NatNetError(f"bad {what} count {count} with {r.remaining()} bytes left")
    return count


def _read_rigid_bodies(r: _Reader, count: int | None = None, what: str = "rigid body") -> np.ndarray:
    n = _counted(r, count, RIGID_BODY_DTYPE.itemsize, what)
    return r.records(RIGID_BODY_DTYPE, n, what)


def _read_labeled(r: _Reader, count: int | None = None, what: str = "labeled marker") -> np.ndarray:
    n = _counted(r, count, LABELED_MARKER_DTYPE.itemsize, what)
    return r.records(LABELED_MARKER_DTYPE, n, what)


def _read_other(r: _Reader, count: int | None = None) -> np.ndarray:
    n = _counted(r, count, 12, "other marker")
    return r.records(POINT_DTYPE, 3 * n, "other markers").reshape(n, 3)


def _read_marker_sets(r: _Reader, count: int | None = None) -> dict[str, np.ndarray]:
    sets = {}
    for _ in range(_counted(r, count, 5, "marker set")):
        name = r.cstring("marker set name")
        n = r.count(12, f"marker set {name!r}")
        sets[name] = r.records(POINT_DTYPE, 3 * n, f"marker set {name!r}").reshape(n, 3)
    return sets


def _read_skeletons(r: _Reader, count: int | None = None) -> list[Skeleton]:
    return [Skeleton(r.i32("skeleton id"), _read_rigid_bodies(r, what="skeleton rigid body"))
            for _ in range(_counted(r, count, 8, "skeleton"))]


def _read_assets(r: _Reader, count: int | None = None) -> list[Asset]:
    return [Asset(r.i32("asset id"), _read_rigid_bodies(r, what="asset rigid body"),
                  _read_labeled(r, what="asset marker"))
            for _ in range(_counted(r, count, 12, "asset"))]


def _read_analog(r: _Reader, count: int | None = None, what: str = "device") -> list[AnalogDevice]:
    out = []
    for _ in range(_counted(r, count, 8, what)):
        dev_id = r.i32(f"{what} id")
        channels = []
        for _ in range(r.count(4, f"{what} channel")):
            n = r.count(4, f"{what} samples")
            channels.append(r.records(POINT_DTYPE, n, f"{what} samples"))
        out.append(AnalogDevice(dev_id, channels))
    return out


def _section(r: _Reader, sized: bool, what: str, body):
    """Decode one section with ``body(reader, count)``.

    Before 4.1 the body reads its own count.  From 4.1 the section starts with
    ``i32 count | i32 bytes``: the body is confined to those bytes (it can never
    read past them) and any bytes it does not understand are skipped.
    """
    if not sized:
        return body(r, None)
    count = r.i32(f"{what} count")
    nbytes = r.i32(f"{what} section size")
    if count < 0 or nbytes < 0 or nbytes > r.remaining():
        raise NatNetError(f"bad {what} section: count {count}, {nbytes} bytes, {r.remaining()} left")
    inner = _Reader(r.buf, r.pos, r.pos + nbytes)
    value = body(inner, count)
    r.pos += nbytes
    return value


def decode_frame_of_data(payload, version) -> FrameOfData:
    """Decode a ``NAT_FRAMEOFDATA`` payload (without the 4-byte packet header)."""
    version = _version_tuple(version)
    sized = _sized_sections(version)
    buf = memoryview(payload).cast("B")
    r = _Reader(buf, 0, len(buf))
    f = FrameOfData()
    f.frame_number = r.i32("frame number")
    f.marker_sets = _section(r, sized, "marker set", _read_marker_sets)
    f.other_markers = _section(r, sized, "other marker", _read_other)
    f.rigid_bodies = _section(r, sized, "rigid body", _read_rigid_bodies)
    f.skeletons = _section(r, sized, "skeleton", _read_skeletons)
    if version >= (4, 1):
        f.assets = _section(r, sized, "asset", _read_assets)
    f.labeled_markers = _section(r, sized, "labeled marker", _read_labeled)
    f.force_plates = _section(r, sized, "force plate", lambda r, c: _read_analog(r, c, "force plate"))
    f.devices = _section(r, sized, "device", lambda r, c: _read_analog(r, c, "device"))

    suffix = _SUFFIX_TIMES.size + (_PRECISION.size if version >= (4, 1) else 0) + _PARAMS.size
    if sized:
        # Sections a newer server appends after devices (4.2+): skip them by their byte counts.
        while r.remaining() not in (suffix, suffix + _EOD.size):
            if r.remaining() < suffix + 8:
                raise NatNetError(f"frame suffix: {r.remaining()} bytes left, expected {suffix}")
            _section(r, True, "extension", lambda inner, count: None)
            f.skipped_sections += 1
    (f.timecode, f.timecode_sub, f.timestamp, f.stamp_camera_mid_exposure,
     f.stamp_data_received, f.stamp_transmit) = r.unpack(_SUFFIX_TIMES, "frame suffix")
    if version >= (4, 1):
        f.precision_timestamp_secs, f.precision_timestamp_frac = r.unpack(_PRECISION, "precision timestamp")
    (f.params,) = r.unpack(_PARAMS, "frame params")
    if r.remaining() >= _EOD.size:
        (eod,) = r.unpack(_EOD, "end of data")
        if eod != 0:
            raise NatNetError(f"end-of-data tag is {eod}, expected 0")
    if r.remaining():
        raise NatNetError(f"{r.remaining()} unexpected bytes after the frame")
    if not np.isfinite(f.timestamp):
        raise NatNetError("frame timestamp is not finite")
    return f


def decode_server_info(payload) -> ServerInfo:
    """Decode a ``NAT_SERVERINFO`` payload (279 bytes)."""
    buf = bytes(payload)
    if len(buf) < SERVER_INFO_BYTES:
        raise NatNetError(f"server info is {len(buf)} bytes, expected {SERVER_INFO_BYTES}")
    name = buf[:MAX_NAME_BYTES].split(b"\0", 1)[0].decode("utf-8", errors="replace")
    clock, port, mcast = struct.unpack_from("<QHB", buf, 264)
    return ServerInfo(app_name=name, app_version=tuple(buf[256:260]), natnet_version=tuple(buf[260:264]),
                      high_res_clock_hz=clock, data_port=port, multicast=bool(mcast),
                      multicast_group=socket.inet_ntoa(buf[275:279]))


def split_packet(data) -> tuple[int, memoryview]:
    """``(message_id, payload)`` of one datagram, checking the header's length against the datagram."""
    buf = memoryview(data).cast("B")
    if len(buf) < _HEADER.size:
        raise NatNetError(f"datagram of {len(buf)} bytes is shorter than the 4-byte header")
    message_id, nbytes = _HEADER.unpack(buf[:4])
    if nbytes != len(buf) - 4:
        raise NatNetError(f"header says {nbytes} payload bytes, datagram carries {len(buf) - 4}")
    return message_id, buf[4:]


# --------------------------------------------------------------------------- encoding


def _packet(message_id: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise NatNetError(f"payload of {len(payload)} bytes exceeds NatNet's {MAX_PAYLOAD_BYTES}-byte limit")
    return _HEADER.pack(message_id, len(payload)) + payload


def _records(arr: np.ndarray, dtype: np.dtype) -> bytes:
    return np.ascontiguousarray(arr, dtype=dtype).tobytes()


def _put_section(out: list, sized: bool, count: int, body: bytes) -> None:
    out.append(struct.pack("<ii", count, len(body)) if sized else struct.pack("<i", count))
    out.append(body)


def _analog_bytes(devices: list[AnalogDevice]) -> bytes:
    parts = []
    for dev in devices:
        parts.append(struct.pack("<ii", dev.id, len(dev.channels)))
        for ch in dev.channels:
            ch = np.ascontiguousarray(ch, dtype=POINT_DTYPE).reshape(-1)
            parts.append(struct.pack("<i", len(ch)) + ch.tobytes())
    return b"".join(parts)


def _cstring(name: str) -> bytes:
    raw = name.encode("utf-8")
    if len(raw) >= MAX_NAME_BYTES or b"\0" in raw:
        raise NatNetError(f"name {name!r} must be < {MAX_NAME_BYTES} bytes without NUL")
    return raw + b"\0"


def encode_frame_of_data(frame: FrameOfData, version=(4, 1)) -> bytes:
    """A complete ``NAT_FRAMEOFDATA`` datagram (header included) in the given bitstream layout."""
    version = _version_tuple(version)
    sized = _sized_sections(version)
    out = [struct.pack("<i", frame.frame_number)]
    sets = b"".join(
        _cstring(name) + struct.pack("<i", len(pts)) + _records(np.reshape(pts, (-1, 3)), POINT_DTYPE)
        for name, pts in frame.marker_sets.items()
    )
    _put_section(out, sized, len(frame.marker_sets), sets)
    other = np.reshape(frame.other_markers, (-1, 3))
    _put_section(out, sized, len(other), _records(other, POINT_DTYPE))
    _put_section(out, sized, len(frame.rigid_bodies), _records(frame.rigid_bodies, RIGID_BODY_DTYPE))
    skel = b"".join(struct.pack("<ii", s.id, len(s.rigid_bodies)) + _records(s.rigid_bodies, RIGID_BODY_DTYPE)
                    for s in frame.skeletons)
    _put_section(out, sized, len(frame.skeletons), skel)
    if version >= (4, 1):
        assets = b"".join(
            struct.pack("<ii", a.id, len(a.rigid_bodies)) + _records(a.rigid_bodies, RIGID_BODY_DTYPE)
            + struct.pack("<i", len(a.markers)) + _records(a.markers, LABELED_MARKER_DTYPE)
            for a in frame.assets
        )
        _put_section(out, sized, len(frame.assets), assets)
    _put_section(out, sized, len(frame.labeled_markers), _records(frame.labeled_markers, LABELED_MARKER_DTYPE))
    _put_section(out, sized, len(frame.force_plates), _analog_bytes(frame.force_plates))
    _put_section(out, sized, len(frame.devices), _analog_bytes(frame.devices))
    out.append(_SUFFIX_TIMES.pack(frame.timecode, frame.timecode_sub, float(frame.timestamp),
                                  frame.stamp_camera_mid_exposure, frame.stamp_data_received,
                                  frame.stamp_transmit))
    if version >= (4, 1):
        out.append(_PRECISION.pack(frame.precision_timestamp_secs, frame.precision_timestamp_frac))
    out.append(_PARAMS.pack(frame.params))
    out.append(_EOD.pack(0))
    return _packet(NAT_FRAMEOFDATA, b"".join(out))


def encode_server_info(info: ServerInfo) -> bytes:
    name = info.app_name.encode("utf-8")[: MAX_NAME_BYTES - 1].ljust(MAX_NAME_BYTES, b"\0")
    payload = (name + bytes(info.app_version[:4]) + bytes(info.natnet_version[:4])
               + struct.pack("<QHB", info.high_res_clock_hz, info.data_port, int(info.multicast))
               + socket.inet_aton(info.multicast_group))
    return _packet(NAT_SERVERINFO, payload)


def encode_command(message_id: int, text: str = "") -> bytes:
    """A command-channel packet: NAT_CONNECT ("Ping"), NAT_REQUEST (command string), keep-alive, ..."""
    if message_id in (NAT_KEEPALIVE, NAT_REQUEST_MODELDEF, NAT_REQUEST_FRAMEOFDATA, NAT_DISCONNECT):
        return _packet(message_id, b"")
    return _packet(message_id, text.encode("utf-8") + b"\0")


def labeled_marker_records(positions, ids=None, sizes=None, params=None, residuals=None) -> np.ndarray:
    """Build LABELED_MARKER_DTYPE records from ``positions (n,3)`` metres (helper for servers and tests)."""
    positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    n = len(positions)
    rec = np.zeros(n, LABELED_MARKER_DTYPE)
    rec["position"] = positions
    rec["id"] = np.arange(1, n + 1) if ids is None else ids
    rec["size"] = 0.014 if sizes is None else sizes
    rec["params"] = (MARKER_UNLABELED | MARKER_POINT_CLOUD_SOLVED) if params is None else params
    rec["residual"] = 0.0 if residuals is None else residuals
    return rec


def decode_packet(data, version=None):
    """Decode one datagram: ``(message_id, value)``.

    ``value`` is a :class:`FrameOfData` (needs ``version``), a :class:`ServerInfo`,
    a ``str`` for message strings and responses, or the raw payload bytes for other
    messages.  Raises :class:`NatNetError` for anything malformed.
    """
    message_id, payload = split_packet(data)
    if message_id == NAT_FRAMEOFDATA:
        if version is None:
            raise NatNetError("frame of data before the server's version is known (no NAT_SERVERINFO yet)")
        return message_id, decode_frame_of_data(payload, version)
    if message_id == NAT_SERVERINFO:
        return message_id, decode_server_info(payload)
    if message_id in (NAT_MESSAGESTRING, NAT_RESPONSE, NAT_REQUEST, NAT_CONNECT):
        return message_id, bytes(payload).split(b"\0", 1)[0].decode("utf-8", errors="replace")
    return message_id, bytes(payload)


# --------------------------------------------------------------------------- sockets


@dataclass
class NatNetStats:
    """Counters of one client; nothing is dropped without being counted here."""

    packets: int = 0
    frames: int = 0  # frames delivered
    malformed: int = 0  # datagrams that failed to decode
    ignored: int = 0  # well-formed messages this client does not use (model defs, responses, ...)
    foreign: int = 0  # command-channel datagrams from an address that is not the server
    stale: int = 0  # frames not newer than the last delivered one (UDP duplicate/reorder), dropped
    gaps: int = 0  # frame numbers skipped between delivered frames (lost datagrams)
    restarts: int = 0  # frame numbers jumping far back: Motive playback looped or restarted
    last_error: str = ""

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _udp_socket(recv_buffer_bytes: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:  # bursts of large frames: ask for a big kernel buffer (the OS may grant less)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, recv_buffer_bytes)
    except OSError:
        pass
    sock.setblocking(False)
    return sock


class NatNetClient:
    """Receives frames from Motive (or any NatNet server) over UDP.

    Unicast: one command socket on ``local_address`` (ephemeral port) sends
    ``NAT_CONNECT`` to the server's command port and keep-alives every
    ``keepalive_interval_s``; the server streams frames back to that socket.
    Multicast: frames arrive on ``multicast_group:data_port`` joined on the
    ``local_address`` interface.  Frames are accepted on either socket.

    >>> with NatNetClient("192.168.1.10", local_address="192.168.1.20") as c:   # doctest: +SKIP
    ...     c.connect()
    ...     frame = c.receive(timeout_s=1.0)
    """

    def __init__(self, server_address: str = "127.0.0.1", local_address: str = "127.0.0.1",
                 multicast: bool = False, multicast_group: str = DEFAULT_MULTICAST_GROUP,
                 command_port: int = DEFAULT_COMMAND_PORT, data_port: int = DEFAULT_DATA_PORT,
                 keepalive_interval_s: float = 1.0, bitstream=None, restart_window: int = 1000,
                 recv_buffer_bytes: int = 1 << 22):
        self.server_address = socket.gethostbyname(server_address)
        self.local_address = local_address
        self.multicast = bool(multicast)
        self.multicast_group = multicast_group
        self.command_port = int(command_port)
        self.data_port = int(data_port)
        self.keepalive_interval_s = float(keepalive_interval_s)
        self.bitstream = None if bitstream is None else _version_tuple(bitstream)
        self.restart_window = int(restart_window)
        self.recv_buffer_bytes = int(recv_buffer_bytes)
        self.server_info: ServerInfo | None = None
        self.stats = NatNetStats()
        self.messages: list[str] = []  # last few NAT_MESSAGESTRING texts from the server
        self._last_frame: int | None = None
        self._last_keepalive = 0.0
        self._pending: list[FrameOfData] = []
        self._command: socket.socket | None = None
        self._data: socket.socket | None = None

    # -- lifecycle
    def open(self) -> None:
        if self._command is not None:
            return
        self._command = _udp_socket(self.recv_buffer_bytes)
        self._command.bind((self.local_address, 0))
        if self.multicast:
            self._data = _udp_socket(self.recv_buffer_bytes)
            try:  # binding the group address filters out other traffic to this port (Linux)
                self._data.bind((self.multicast_group, self.data_port))
            except OSError:
                self._data.bind(("", self.data_port))
            membership = socket.inet_aton(self.multicast_group) + socket.inet_aton(self.local_address)
            self._data.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)

    def close(self) -> None:
        for sock in (self._command, self._data):
            if sock is None:
                continue
            if sock is self._command and self.server_info is not None and not self.multicast:
                try:
                    sock.sendto(encode_command(NAT_DISCONNECT), (self.server_address, self.command_port))
                except OSError:
                    pass
            sock.close()
        self._command = self._data = None

    def __enter__(self) -> "NatNetClient":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def local_command_address(self) -> tuple[str, int]:
        self.open()
        return self._command.getsockname()

    @property
    def version(self) -> tuple[int, int] | None:
        if self.bitstream is not None:
            return self.bitstream
        if self.server_info is None:
            return None
        return tuple(self.server_info.natnet_version[:2])

    # -- commands
    def send_command(self, message_id: int, text: str = "") -> None:
        self.open()
        self._command.sendto(encode_command(message_id, text), (self.server_address, self.command_port))

    def connect(self, timeout_s: float = 5.0, retry_interval_s: float = 0.25) -> ServerInfo:
        """Ask for NAT_SERVERINFO (re-sent every ``retry_interval_s``: UDP may drop it)."""
        self.open()
        deadline = time.monotonic() + timeout_s
        next_send = 0.0
        while self.server_info is None:
            now = time.monotonic()
            if now >= deadline:
                raise TimeoutError(f"no NatNet server answered at {self.server_address}:{self.command_port} "
                                   f"within {timeout_s:.1f} s")
            if now >= next_send:
                self.send_command(NAT_CONNECT, "Ping")
                next_send = now + retry_interval_s
            self._wait_and_drain(min(deadline, next_send) - now)
        if self.version is not None and self.version < OLDEST_SUPPORTED:
            raise NatNetError(f"server streams NatNet {self.version[0]}.{self.version[1]}; needs 3.0+")
        self._last_keepalive = time.monotonic()
        return self.server_info

    # -- receiving
    def receive(self, timeout_s: float = 1.0) -> FrameOfData | None:
        """The next frame in arrival order, or None after ``timeout_s`` without one."""
        deadline = time.monotonic() + timeout_s
        while not self._pending:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._wait_and_drain(left)
        return self._pending.pop(0)

    def poll(self, timeout_s: float = 0.0) -> list[FrameOfData]:
        """Every frame received so far (waiting up to ``timeout_s`` for the first)."""
        if not self._pending and timeout_s > 0:
            self._wait_and_drain(timeout_s)
        else:
            self._wait_and_drain(0.0)
        frames, self._pending = self._pending, []
        return frames

    def _wait_and_drain(self, timeout_s: float) -> None:
        self.open()
        self._maybe_keepalive()
        socks = [s for s in (self._command, self._data) if s is not None]
        readable, _, _ = select.select(socks, [], [], max(0.0, timeout_s))
        for sock in readable:
            for _ in range(10_000):  # bounded drain; the rest waits for the next call
                try:
                    data, addr = sock.recvfrom(MAX_PAYLOAD_BYTES + 64)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as err:  # e.g. ICMP port unreachable while the server is down
                    self.stats.last_error = str(err)
                    break
                if sock is self._command and addr[0] != self.server_address:
                    self.stats.foreign += 1
                    continue
                self._handle(data)

    def _maybe_keepalive(self) -> None:
        if self.multicast or self.server_info is None:
            return
        now = time.monotonic()
        if now - self._last_keepalive >= self.keepalive_interval_s:
            self._last_keepalive = now
            try:
                self.send_command(NAT_KEEPALIVE)
            except OSError as err:
                self.stats.last_error = str(err)

    def _handle(self, data: bytes) -> None:
        self.stats.packets += 1
        if self.version is None and data[:2] == _HEADER.pack(NAT_FRAMEOFDATA, 0)[:2]:
            self.stats.ignored += 1  # multicast frames before NAT_SERVERINFO told us the layout
            return
        try:
            message_id, value = decode_packet(data, self.version)
        except NatNetError as err:
            self.stats.malformed += 1
            self.stats.last_error = str(err)
            return
        if message_id == NAT_SERVERINFO:
            self.server_info = value
        elif message_id == NAT_FRAMEOFDATA:
            self._accept(value)
        elif message_id == NAT_MESSAGESTRING:
            self.messages = (self.messages + [value])[-20:]
        else:
            self.stats.ignored += 1

    def _accept(self, frame: FrameOfData) -> None:
        last = self._last_frame
        if last is not None:
            step = frame.frame_number - last
            if step <= 0 and -step < self.restart_window:
                self.stats.stale += 1
                return
            if step <= 0:
                self.stats.restarts += 1
            elif step > 1:
                self.stats.gaps += step - 1
        self._last_frame = frame.frame_number
        self.stats.frames += 1
        self._pending.append(frame)

    def capture_stamp_ns(self, frame: FrameOfData) -> int:
        """Capture time of ``frame`` in ns: the server's frame timestamp (seconds since it started)."""
        return int(round(frame.timestamp * 1e9))

    def latency_s(self, frame: FrameOfData) -> float | None:
        """Mid-exposure to transmit latency on the server's high-resolution clock, if it reports one."""
        hz = self.server_info.high_res_clock_hz if self.server_info else 0
        if hz <= 0 or frame.stamp_transmit < frame.stamp_camera_mid_exposure or frame.stamp_camera_mid_exposure == 0:
            return None
        return (frame.stamp_transmit - frame.stamp_camera_mid_exposure) / hz


class NatNetServer:
    """A minimal NatNet server: answers NAT_CONNECT and streams frames (for tests, demos and replay).

    Unicast: frames go to every client that connected (and keeps sending
    keep-alives within ``client_timeout_s``), from the command socket.
    Multicast: frames go to ``info.multicast_group:info.data_port``.
    Binds ``host`` (127.0.0.1 by default); ``command_port=0`` picks a free port.
    """

    def __init__(self, info: ServerInfo | None = None, host: str = "127.0.0.1",
                 command_port: int = DEFAULT_COMMAND_PORT, client_timeout_s: float = 10.0,
                 multicast_ttl: int = 1):
        self.info = info or ServerInfo()
        self.version = _version_tuple(self.info.natnet_version[:2])
        self.client_timeout_s = float(client_timeout_s)
        self.clients: dict[tuple[str, int], float] = {}
        self.malformed = 0
        self._sock = _udp_socket(1 << 20)
        self._sock.bind((host, command_port))
        if self.info.multicast:
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, multicast_ttl)
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(host))

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> "NatNetServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def serve_commands(self, timeout_s: float = 0.0) -> int:
        """Answer pending command packets (waiting up to ``timeout_s``); returns how many were handled."""
        handled = 0
        readable, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        while readable:
            try:
                data, addr = self._sock.recvfrom(MAX_PAYLOAD_BYTES + 64)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # ICMP errors from a client that went away
            handled += 1
            try:
                message_id, _ = split_packet(data)
            except NatNetError:
                self.malformed += 1
                continue
            now = time.monotonic()
            if message_id == NAT_CONNECT:
                self.clients[addr] = now
                self._sock.sendto(encode_server_info(self.info), addr)
            elif message_id == NAT_KEEPALIVE:
                if addr in self.clients:
                    self.clients[addr] = now
            elif message_id == NAT_DISCONNECT:
                self.clients.pop(addr, None)
            elif message_id == NAT_REQUEST_MODELDEF:
                self._sock.sendto(_packet(NAT_MODELDEF, struct.pack("<i", 0)), addr)
            else:
                self._sock.sendto(_packet(NAT_UNRECOGNIZED_REQUEST, b""), addr)
        return handled

    def send_frame(self, frame: FrameOfData) -> int:
        """Send one frame to every live client (or the multicast group); returns datagrams sent."""
        packet = encode_frame_of_data(frame, self.version)
        if self.info.multicast:
            self._sock.sendto(packet, (self.info.multicast_group, self.info.data_port))
            return 1
        now = time.monotonic()
        sent = 0
        for addr, seen in list(self.clients.items()):
            if now - seen > self.client_timeout_s:
                del self.clients[addr]
                continue
            try:
                self._sock.sendto(packet, addr)
                sent += 1
            except OSError:
                del self.clients[addr]
        return sent
