"""Qualisys Track Manager (QTM) real-time protocol over TCP: the unlabeled 3D point stream.

Written from the public description of the QTM RT protocol (version 1.x).  On
port 22223 everything is little-endian (22222 is the legacy big-endian port).
Every packet is ``u32 size (header included) | u32 type | payload``:

* type 0 error (text), 1 command (text, NUL-terminated), 2 XML, 3 data,
  4 no more data (no capture running), 6 event (u8 id).
* On connect QTM sends the command ``"QTM RT Interface connected"``; the client
  sends ``"Version 1.25"`` (answered ``"Version set to 1.25"``), may ask
  ``"GetParameters General"`` (XML with the capture ``<Frequency>``), then
  ``"StreamFrames AllFrames 3DNoLabels"``; ``"StreamFrames Stop"`` ends it.
* Data payload: ``u64 timestamp (microseconds) | u32 frame number | u32 component
  count`` then components ``u32 size (header included) | u32 type | ...``.
  3D-no-labels (type 2): ``u32 marker count | u16 2D drop rate | u16 2D
  out-of-sync rate`` then per marker ``f32 x, y, z (mm) | u32 id``; type 10 adds
  ``f32 residual`` per marker.  Labeled 3D (type 1 / 9 with residual) has
  ``f32 x, y, z`` (NaN when not seen) per marker.  Other components are skipped
  by their size.

Positions are converted to metres; QTM's default lab frame is Z-up
(:data:`QTM_UP_AXIS`).  Every length is bounds-checked: malformed data raises
:class:`QTMError`; the client counts it.  A TCP stream whose framing breaks
(impossible packet size) cannot be resynchronised and is closed.
"""

from __future__ import annotations

import re
import select
import socket
import struct
import time
from dataclasses import dataclass, field

import numpy as np

PACKET_ERROR, PACKET_COMMAND, PACKET_XML, PACKET_DATA, PACKET_NO_MORE_DATA = 0, 1, 2, 3, 4
PACKET_C3D_FILE, PACKET_EVENT, PACKET_DISCOVER, PACKET_QTM_FILE = 5, 6, 7, 8
COMPONENT_3D, COMPONENT_3D_NO_LABELS, COMPONENT_3D_RES, COMPONENT_3D_NO_LABELS_RES = 1, 2, 9, 10
DEFAULT_PORT = 22223  # little-endian RT port
DEFAULT_PROTOCOL_VERSION = "1.25"
QTM_UP_AXIS = "+z"
WELCOME = "QTM RT Interface connected"
MAX_PACKET_BYTES = 16 << 20  # no sane 3D frame comes near this; larger means broken framing

_HEADER = struct.Struct("<II")
_DATA_HEADER = struct.Struct("<QII")
_NO_LABELS_HEADER = struct.Struct("<IHH")
NO_LABELS_DTYPE = np.dtype([("position", "<f4", (3,)), ("id", "<u4")])
NO_LABELS_RES_DTYPE = np.dtype([("position", "<f4", (3,)), ("id", "<u4"), ("residual", "<f4")])
LABELED_DTYPE = np.dtype([("position", "<f4", (3,))])
LABELED_RES_DTYPE = np.dtype([("position", "<f4", (3,)), ("residual", "<f4")])


class QTMError(ValueError):
    """A QTM RT packet that cannot be decoded, or a protocol exchange that failed."""


@dataclass
class QTMFrame:
    """One data packet.  Positions in metres (QTM sends mm)."""

    frame_number: int = 0
    timestamp_us: int = 0  # QTM's capture clock, microseconds
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # unlabeled points
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))  # QTM's per-point ids
    residuals_mm: np.ndarray | None = None  # with the 3DNoLabelsRes component
    labeled_positions: np.ndarray | None = None  # (M,3) metres, NaN when not seen (3D component)
    drop_rate_2d: int = 0  # per mille of 2D frames dropped, as reported
    out_of_sync_rate_2d: int = 0
    skipped_components: int = 0


def encode_packet(packet_type: int, payload: bytes) -> bytes:
    return _HEADER.pack(_HEADER.size + len(payload), packet_type) + payload


def encode_command(text: str) -> bytes:
    return encode_packet(PACKET_COMMAND, text.encode("utf-8") + b"\0")


def encode_data(frame: QTMFrame, residuals: bool = False) -> bytes:
    """A data packet holding the 3D-no-labels component (with residuals: type 10) of ``frame``."""
    pts = np.asarray(frame.positions, np.float64).reshape(-1, 3)
    rec = np.zeros(len(pts), NO_LABELS_RES_DTYPE if residuals else NO_LABELS_DTYPE)
    rec["position"] = pts * 1000.0
    rec["id"] = frame.ids if len(frame.ids) == len(pts) else np.arange(1, len(pts) + 1)
    if residuals:
        rec["residual"] = 0.0 if frame.residuals_mm is None else frame.residuals_mm
    body = _NO_LABELS_HEADER.pack(len(pts), frame.drop_rate_2d, frame.out_of_sync_rate_2d) + rec.tobytes()
    ctype = COMPONENT_3D_NO_LABELS_RES if residuals else COMPONENT_3D_NO_LABELS
    component = _HEADER.pack(_HEADER.size + len(body), ctype) + body
    return encode_packet(PACKET_DATA, _DATA_HEADER.pack(frame.timestamp_us, frame.frame_number, 1) + component)


def _text(payload) -> str:
    return bytes(payload).split(b"\0", 1)[0].decode("utf-8", errors="replace")


def decode_data(payload) -> QTMFrame:
    """Decode a data packet's payload (after the 8-byte packet header)."""
    buf = memoryview(payload).cast("B")
    if len(buf) < _DATA_HEADER.size:
        raise QTMError(f"data packet of {len(buf)} bytes is shorter than its 16-byte header")
    timestamp, frame_number, count = _DATA_HEADER.unpack(buf[:16])
    f = QTMFrame(frame_number=frame_number, timestamp_us=timestamp)
    pos = 16
    for i in range(count):
        if len(buf) - pos < 8:
            raise QTMError(f"component {i + 1} of {count}: header truncated at offset {pos}")
        size, ctype = _HEADER.unpack(buf[pos:pos + 8])
        if size < 8 or size > len(buf) - pos:
            raise QTMError(f"component {i + 1} (type {ctype}) claims {size} bytes, {len(buf) - pos} left")
        body = buf[pos + 8:pos + size]
        pos += size
        if ctype in (COMPONENT_3D_NO_LABELS, COMPONENT_3D_NO_LABELS_RES, COMPONENT_3D, COMPONENT_3D_RES):
            if len(body) < 8:
                raise QTMError(f"3D component of {len(body)} bytes is shorter than its 8-byte header")
            n, f.drop_rate_2d, f.out_of_sync_rate_2d = _NO_LABELS_HEADER.unpack(body[:8])
            dtype = {COMPONENT_3D_NO_LABELS: NO_LABELS_DTYPE, COMPONENT_3D_NO_LABELS_RES: NO_LABELS_RES_DTYPE,
                     COMPONENT_3D: LABELED_DTYPE, COMPONENT_3D_RES: LABELED_RES_DTYPE}[ctype]
            if n * dtype.itemsize != len(body) - 8:
                raise QTMError(f"3D component (type {ctype}) says {n} markers but holds {len(body) - 8} bytes")
            rec = np.frombuffer(body[8:], dtype, count=n)
            with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf checked below, never warned
                positions = rec["position"].astype(np.float32) / np.float32(1000.0)
            if ctype in (COMPONENT_3D, COMPONENT_3D_RES):
                f.labeled_positions = positions
            else:
                f.positions, f.ids = positions, rec["id"].copy()
                if ctype == COMPONENT_3D_NO_LABELS_RES:
                    f.residuals_mm = rec["residual"].copy()
        else:
            f.skipped_components += 1
    if pos != len(buf):
        raise QTMError(f"{len(buf) - pos} unexpected bytes after {count} components")
    if not np.isfinite(f.positions).all():
        raise QTMError("3D-no-labels component holds non-finite coordinates")
    return f


class PacketStream:
    """Cuts a TCP byte stream into packets; bounded buffer; broken framing raises QTMError."""

    def __init__(self, max_packet_bytes: int = MAX_PACKET_BYTES):
        self.max_packet_bytes = max_packet_bytes
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self._buf += data
        out = []
        while len(self._buf) >= 8:
            size, ptype = _HEADER.unpack_from(self._buf)
            if size < 8 or size > self.max_packet_bytes:
                raise QTMError(f"packet size {size} is impossible: the stream lost its framing")
            if len(self._buf) < size:
                break
            out.append((ptype, bytes(self._buf[8:size])))
            del self._buf[:size]
        return out


@dataclass
class QTMStats:
    packets: int = 0
    frames: int = 0
    malformed: int = 0
    errors: int = 0  # error packets from QTM
    events: int = 0
    no_more_data: int = 0  # QTM has no capture running
    stale: int = 0
    gaps: int = 0
    last_error: str = ""

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class QTMClient:
    """Streams 3D-no-labels frames from QTM over one TCP connection."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, version: str = DEFAULT_PROTOCOL_VERSION,
                 residuals: bool = False, frequency_hz: int = 0):
        self.host, self.port, self.version = host, int(port), version
        self.component = "3DNoLabelsRes" if residuals else "3DNoLabels"
        self.frequency_hz = int(frequency_hz)  # 0 = every frame
        self.capture_rate_hz = 0.0  # from GetParameters General
        self.stats = QTMStats()
        self._sock: socket.socket | None = None
        self._stream = PacketStream()
        self._pending: list[QTMFrame] = []
        self._replies: list[tuple[int, str]] = []
        self._last_frame: int | None = None

    def __enter__(self) -> "QTMClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.sendall(encode_command("StreamFrames Stop"))
            except OSError:
                pass
            self._sock.close()
            self._sock = None

    def connect(self, timeout_s: float = 5.0) -> None:
        """Open the connection, agree on the protocol version, read the rate, start streaming."""
        deadline = time.monotonic() + timeout_s
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        except OSError as exc:
            raise TimeoutError(f"no QTM RT server at {self.host}:{self.port}: {exc}") from None
        self._sock.setblocking(False)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        welcome = self._reply(deadline)
        if welcome[0] != PACKET_COMMAND or WELCOME not in welcome[1]:
            raise QTMError(f"unexpected greeting from {self.host}:{self.port}: {welcome[1]!r}")
        self._sock.sendall(encode_command(f"Version {self.version}"))
        reply = self._reply(deadline)
        if reply[0] != PACKET_COMMAND or not reply[1].startswith("Version set to"):
            raise QTMError(f"QTM refused protocol version {self.version}: {reply[1]!r}")
        self._sock.sendall(encode_command("GetParameters General"))
        reply = self._reply(deadline)
        match = re.search(r"<Frequency>\s*([0-9.]+)\s*</Frequency>", reply[1]) if reply[0] == PACKET_XML else None
        self.capture_rate_hz = float(match.group(1)) if match else 0.0
        rate = f"Frequency:{self.frequency_hz}" if self.frequency_hz else "AllFrames"
        self._sock.sendall(encode_command(f"StreamFrames {rate} {self.component}"))

    def _reply(self, deadline: float) -> tuple[int, str]:
        while not self._replies:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"QTM at {self.host}:{self.port} did not answer in time")
            self._drain(left)
        return self._replies.pop(0)

    def receive(self, timeout_s: float = 1.0) -> QTMFrame | None:
        deadline = time.monotonic() + timeout_s
        while not self._pending:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._drain(left)
        return self._pending.pop(0)

    def _drain(self, timeout_s: float) -> None:
        if self._sock is None:
            raise QTMError("not connected")
        readable, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        if not readable:
            return
        try:
            data = self._sock.recv(1 << 20)
        except (BlockingIOError, InterruptedError):
            return
        if not data:
            raise ConnectionError(f"QTM at {self.host}:{self.port} closed the connection")
        for ptype, payload in self._stream.feed(data):  # QTMError here: framing lost, caller reconnects
            self._handle(ptype, payload)

    def _handle(self, ptype: int, payload: bytes) -> None:
        self.stats.packets += 1
        if ptype == PACKET_DATA:
            try:
                frame = decode_data(payload)
            except QTMError as exc:
                self.stats.malformed += 1
                self.stats.last_error = str(exc)
                return
            if self._last_frame is not None and frame.frame_number <= self._last_frame:
                self.stats.stale += 1
                return
            if self._last_frame is not None and not self.frequency_hz:  # decimated streams skip by design
                self.stats.gaps += frame.frame_number - self._last_frame - 1
            self._last_frame = frame.frame_number
            self.stats.frames += 1
            self._pending.append(frame)
        elif ptype in (PACKET_COMMAND, PACKET_XML):
            self._replies.append((ptype, _text(payload)))
        elif ptype == PACKET_ERROR:
            self.stats.errors += 1
            self.stats.last_error = _text(payload)
            self._replies.append((ptype, _text(payload)))
        elif ptype == PACKET_NO_MORE_DATA:
            self.stats.no_more_data += 1
        elif ptype == PACKET_EVENT:
            self.stats.events += 1


class QTMServer:
    """Loopback stand-in for QTM's RT server (tests, demos): one listening socket, any number of clients."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, capture_rate_hz: float = 120.0,
                 residuals: bool = False):
        self.capture_rate_hz, self.residuals = capture_rate_hz, residuals
        self._listen = socket.create_server((host, port))
        self._listen.setblocking(False)
        self._clients: dict[socket.socket, PacketStream] = {}
        self.streaming: set[socket.socket] = set()

    @property
    def address(self) -> tuple[str, int]:
        return self._listen.getsockname()

    def close(self) -> None:
        for sock in list(self._clients):
            sock.close()
        self._listen.close()

    def __enter__(self) -> "QTMServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def serve(self, timeout_s: float = 0.0) -> None:
        """Accept clients and answer their commands."""
        readable, _, _ = select.select([self._listen, *self._clients], [], [], max(0.0, timeout_s))
        for sock in readable:
            if sock is self._listen:
                conn, _ = self._listen.accept()
                conn.setblocking(True)
                conn.sendall(encode_command(WELCOME))
                self._clients[conn] = PacketStream()
                continue
            try:
                data = sock.recv(65536)
                packets = self._clients[sock].feed(data) if data else None
            except (OSError, QTMError):
                packets = None
            if packets is None:
                self._drop(sock)
                continue
            for ptype, payload in packets:
                self._command(sock, _text(payload) if ptype == PACKET_COMMAND else "")

    def _command(self, sock: socket.socket, text: str) -> None:
        words = text.split()
        if words[:1] == ["Version"] and len(words) == 2:
            sock.sendall(encode_command(f"Version set to {words[1]}"))
        elif words[:2] == ["GetParameters", "General"]:
            xml = (f"<QTM_Parameters_Ver_{DEFAULT_PROTOCOL_VERSION}><General><Frequency>{self.capture_rate_hz:g}"
                   f"</Frequency></General></QTM_Parameters_Ver_{DEFAULT_PROTOCOL_VERSION}>")
            sock.sendall(encode_packet(PACKET_XML, xml.encode() + b"\0"))
        elif words[:2] == ["StreamFrames", "Stop"]:
            self.streaming.discard(sock)
        elif words[:1] == ["StreamFrames"]:
            self.streaming.add(sock)
        else:
            sock.sendall(encode_packet(PACKET_ERROR, b"Parse error\0"))

    def _drop(self, sock: socket.socket) -> None:
        self._clients.pop(sock, None)
        self.streaming.discard(sock)
        sock.close()

    def send_frame(self, frame: QTMFrame) -> int:
        packet = encode_data(frame, residuals=self.residuals)
        for sock in list(self.streaming):
            try:
                sock.sendall(packet)
            except OSError:
                self._drop(sock)
        return len(self.streaming)
