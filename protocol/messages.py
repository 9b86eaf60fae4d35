"""Typed messages of the streaming graph, each with a schema name and version.

A message is a frozen dataclass. Its fields are either *scalars* (int, float,
bool, str, list[str], dict) that travel in the msgpack header, or *arrays*
(numpy, declared with :func:`array_field`) that travel as raw buffers next to
the header. Arrays have a fixed list of allowed dtypes (never object dtype) and
a shape pattern whose named dimensions (``"M"``) must agree across the fields of
one message, so a receiver can check a message without trusting the sender.

Units: metres, seconds; stamps are int64 nanoseconds of the capture clock.
A marker index in :class:`MarkerFrame` is a *track*, not a label.

Adding a field to a message type means bumping its ``VERSION``; receivers
reject versions they do not know (see ``envelope.decode``).
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

F32 = ("<f4",)
F32_F64 = ("<f4", "<f8")
I32 = ("<i4",)
BOOL = ("|b1",)

#: every dtype that may ever travel; anything else is rejected on decode
ALLOWED_DTYPES = frozenset(
    {"|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f4", "<f8"}
)


class MessageError(ValueError):
    """A message whose fields do not match its schema (wrong dtype, shape, type)."""


@dataclass(frozen=True)
class ArraySpec:
    """Allowed dtypes and shape pattern of one array field.

    shape entries: an int (fixed), a str (named dimension shared across fields
    of the message, e.g. "M" markers), or None (any length).
    """

    dtypes: tuple[str, ...]
    shape: tuple[int | str | None, ...]
    optional: bool = False


def array_field(dtypes: tuple[str, ...], shape: tuple, optional: bool = False):
    spec = ArraySpec(tuple(dtypes), tuple(shape), optional)
    if optional:
        return field(default=None, metadata={"array": spec})
    return field(metadata={"array": spec})


class Message:
    """Base of every message type. Subclasses are frozen dataclasses."""

    TYPE: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1

    # -- schema introspection (cached per class) ---------------------------------
    @classmethod
    def array_specs(cls) -> dict[str, ArraySpec]:
        cache = cls.__dict__.get("_array_specs_cache")
        if cache is None:
            cache = {f.name: f.metadata["array"] for f in dataclasses.fields(cls) if "array" in f.metadata}
            cls._array_specs_cache = cache
        return cache

    @classmethod
    def scalar_types(cls) -> dict[str, Any]:
        cache = cls.__dict__.get("_scalar_types_cache")
        if cache is None:
            hints = typing.get_type_hints(cls)
            cache = {f.name: hints[f.name] for f in dataclasses.fields(cls) if "array" not in f.metadata}
            cls._scalar_types_cache = cache
        return cache

    @classmethod
    def schema(cls) -> dict:
        """A JSON-able description used as the MCAP schema of a channel."""
        return {
            "type": cls.TYPE,
            "version": cls.VERSION,
            "scalars": {k: _type_name(t) for k, t in cls.scalar_types().items()},
            "arrays": {
                k: {"dtypes": list(s.dtypes), "shape": list(s.shape), "optional": s.optional}
                for k, s in cls.array_specs().items()
            },
        }

    @classmethod
    def schema_bytes(cls) -> bytes:
        return json.dumps(cls.schema(), sort_keys=True).encode()

    # -- validation ---------------------------------------------------------------
    def validate(self) -> None:
        """Raise MessageError naming the first field that breaks the schema."""
        for name, tp in self.scalar_types().items():
            _check_scalar(self.TYPE, name, getattr(self, name), tp)
        dims: dict[str, int] = {}
        for name, spec in self.array_specs().items():
            arr = getattr(self, name)
            if arr is None:
                if not spec.optional:
                    raise MessageError(f"{self.TYPE}.{name}: required array is missing")
                continue
            if not isinstance(arr, np.ndarray):
                raise MessageError(f"{self.TYPE}.{name}: expected numpy array, got {type(arr).__name__}")
            if arr.dtype.str not in spec.dtypes:
                raise MessageError(f"{self.TYPE}.{name}: dtype {arr.dtype.str} not in allowed {spec.dtypes}")
            if arr.ndim != len(spec.shape):
                raise MessageError(f"{self.TYPE}.{name}: shape {arr.shape} does not match {spec.shape}")
            for size, want in zip(arr.shape, spec.shape):
                if isinstance(want, int) and size != want:
                    raise MessageError(f"{self.TYPE}.{name}: shape {arr.shape} does not match {spec.shape}")
                if isinstance(want, str):
                    if dims.setdefault(want, size) != size:
                        raise MessageError(
                            f"{self.TYPE}.{name}: dimension {want}={size} disagrees with {dims[want]} of another field"
                        )
        self._validate_extra(dims)

    def _validate_extra(self, dims: dict[str, int]) -> None:
        """Per-type checks that the generic schema cannot express."""

    def scalars(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.scalar_types()}

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.array_specs() if getattr(self, k) is not None}


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp)


def _is_plain(value: Any, tp: type) -> bool:
    """isinstance that keeps bools out of int/float (msgpack keeps them apart too)."""
    if tp is bool:
        return isinstance(value, bool)
    return isinstance(value, tp) and not isinstance(value, bool)


def _check_scalar(tname: str, name: str, value: Any, tp: Any) -> None:
    origin = typing.get_origin(tp)
    if tp is float:
        ok = isinstance(value, (float, int)) and not isinstance(value, bool)
    elif tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif tp is bool:
        ok = isinstance(value, bool)
    elif tp is str:
        ok = isinstance(value, str)
    elif origin is list:
        (item,) = typing.get_args(tp)
        ok = isinstance(value, list) and all(_is_plain(v, item) for v in value)
    elif origin is dict or tp is dict:
        ok = isinstance(value, dict) and all(isinstance(k, str) for k in value)
    else:  # pragma: no cover - schema authoring error
        raise TypeError(f"{tname}.{name}: unsupported scalar type {tp}")
    if not ok:
        raise MessageError(f"{tname}.{name}: expected {_type_name(tp)}, got {type(value).__name__} {value!r:.60}")


# ------------------------------------------------------------------------------------------
# Data messages
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MarkerFrame(Message):
    """One capture frame of unlabeled markers (tracks), in the capture's world frame."""

    TYPE: ClassVar[str] = "MarkerFrame"
    VERSION: ClassVar[int] = 1

    stamp_ns: int  # capture clock
    frame_index: int
    positions: np.ndarray = array_field(F32, ("M", 3))  # metres, NaN where not visible
    visible: np.ndarray = array_field(BOOL, ("M",))
    track_ids: np.ndarray | None = array_field(I32, ("M",), optional=True)
    residuals: np.ndarray | None = array_field(F32, ("M",), optional=True)
    rate_hz: float = 0.0  # nominal capture rate, 0 when unknown
    up_axis: str = "+z"
    source: str = ""  # file name or live system
    labels: list[str] = field(default_factory=list)  # per track, only when the source has labels

    def _validate_extra(self, dims):
        if self.labels and len(self.labels) != dims.get("M", 0):
            raise MessageError(f"MarkerFrame.labels: {len(self.labels)} labels for {dims.get('M', 0)} markers")


@dataclass(frozen=True)
class BodyPrior(Message):
    """Video-based body estimate for one video frame (the paper's prior)."""

    TYPE: ClassVar[str] = "BodyPrior"
    VERSION: ClassVar[int] = 1

    stamp_ns: int  # capture (marker) clock = video clock + clock offset
    video_stamp_ns: int
    frame_index: int
    global_orient: np.ndarray = array_field(F32, (3,))  # axis-angle, camera frame if camera_frame
    body_pose: np.ndarray = array_field(F32, (23, 3))  # axis-angle
    betas: np.ndarray = array_field(F32, (None,))
    keypoints3d: np.ndarray | None = array_field(F32, (None, 3), optional=True)
    camera_frame: bool = True
    confidence: float = 1.0
    valid: bool = True
    body_model: str = ""


@dataclass(frozen=True)
class MarkerLabels(Message):
    """Marker (track) -> body part and surface point, from segmentation / matching."""

    TYPE: ClassVar[str] = "MarkerLabels"
    VERSION: ClassVar[int] = 1

    stamp_ns: int
    labels_version: int  # increments whenever the assignment changes
    marker_parts: list[str]  # joint name of the dominant bone, '' when unassigned
    marker_faces: np.ndarray = array_field(I32, ("M",))  # -1 when unassigned
    marker_bary: np.ndarray = array_field(F32, ("M", 3))
    track_ids: np.ndarray | None = array_field(I32, ("M",), optional=True)
    confidence: np.ndarray | None = array_field(F32, ("M",), optional=True)
    marker_offset_m: float = 0.0

    def _validate_extra(self, dims):
        if len(self.marker_parts) != dims.get("M", 0):
            raise MessageError(f"MarkerLabels.marker_parts: {len(self.marker_parts)} for {dims.get('M', 0)} markers")


SOLVED_KINDS = ("estimate", "refined", "revised")


@dataclass(frozen=True)
class SolvedFrame(Message):
    """Body parameters for one capture frame (AMASS layout, world frame).

    kind 'estimate' is the low-latency answer; 'refined' replaces it later
    (sliding window) and is what recordings export; 'revised' replaces a refined frame once a
    lock upgrade solved it again (recordings keep it over the refined one).
    """

    TYPE: ClassVar[str] = "SolvedFrame"
    VERSION: ClassVar[int] = 1

    stamp_ns: int
    frame_index: int
    kind: str
    betas: np.ndarray = array_field(F32_F64, (None,))
    poses: np.ndarray = array_field(F32_F64, (72,))  # axis-angle, poses[:3] root orientation
    trans: np.ndarray = array_field(F32_F64, (3,))
    joints: np.ndarray = array_field(F32_F64, (24, 3))
    marker_faces: np.ndarray | None = array_field(I32, ("M",), optional=True)
    marker_bary: np.ndarray | None = array_field(F32_F64, ("M", 3), optional=True)
    marker_parts: list[str] = field(default_factory=list)
    residual_m: float = float("nan")  # mean marker residual of the fit
    rate_hz: float = 0.0
    body_model: str = ""

    def _validate_extra(self, dims):
        if self.kind not in SOLVED_KINDS:
            raise MessageError(f"SolvedFrame.kind: {self.kind!r} is not one of {SOLVED_KINDS}")
        if self.marker_parts and len(self.marker_parts) != dims.get("M", 0):
            raise MessageError("SolvedFrame.marker_parts: length differs from marker_faces")


# ------------------------------------------------------------------------------------------
# Health, logs
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Heartbeat(Message):
    TYPE: ClassVar[str] = "Heartbeat"
    VERSION: ClassVar[int] = 1

    node: str
    plugin: str
    pid: int
    state: str  # starting | running | stopping
    uptime_s: float
    publishes: list[str] = field(default_factory=list)
    subscribes: list[str] = field(default_factory=list)
    incarnation: int = 0  # 0 for the first start, +1 per respawn


@dataclass(frozen=True)
class Diagnostics(Message):
    """Counters of one node. topics: {topic: {"received", "gaps", "missed_at_join", ...}}."""

    TYPE: ClassVar[str] = "Diagnostics"
    VERSION: ClassVar[int] = 1

    node: str
    counters: dict = field(default_factory=dict)  # str -> int
    topics: dict = field(default_factory=dict)  # str -> {str: int}
    rejected: dict = field(default_factory=dict)  # reason -> count

    def _validate_extra(self, dims):
        for name in ("counters", "rejected"):
            for k, v in getattr(self, name).items():
                if not isinstance(v, (int, float)) or isinstance(v, bool):
                    raise MessageError(f"Diagnostics.{name}[{k!r}] must be a number")
        for k, v in self.topics.items():
            if not isinstance(v, dict):
                raise MessageError(f"Diagnostics.topics[{k!r}] must be a map")


@dataclass(frozen=True)
class Log(Message):
    TYPE: ClassVar[str] = "Log"
    VERSION: ClassVar[int] = 1

    node: str
    level: int  # python logging level
    message: str
    logger: str = ""


# ------------------------------------------------------------------------------------------
# Graph control (readiness handshake, lockstep credits, end of stream)
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Probe(Message):
    """Sent by a publisher ON a data topic until every declared subscriber answers Ready.

    Receiving a probe proves the whole path publisher -> broker -> subscriber is
    live for that topic, so data sent afterwards is not lost to a slow joiner.
    """

    TYPE: ClassVar[str] = "Probe"
    VERSION: ClassVar[int] = 1

    topic: str
    publisher: str
    nonce: int


@dataclass(frozen=True)
class Ready(Message):
    """A subscriber's answer to a Probe, published on ``ready/<publisher>``."""

    TYPE: ClassVar[str] = "Ready"
    VERSION: ClassVar[int] = 1

    node: str
    topic: str
    publisher: str
    nonce: int


@dataclass(frozen=True)
class Ack(Message):
    """A consumer processed message ``seq`` of ``topic`` from ``publisher`` (lockstep credit)."""

    TYPE: ClassVar[str] = "Ack"
    VERSION: ClassVar[int] = 1

    node: str
    topic: str
    publisher: str
    instance: int
    seq: int
    stamp_ns: int
    eos: bool = False


@dataclass(frozen=True)
class EndOfStream(Message):
    """The publisher has no more data on ``topic`` (file replay finished)."""

    TYPE: ClassVar[str] = "EndOfStream"
    VERSION: ClassVar[int] = 1

    topic: str
    last_seq: int
    last_stamp_ns: int


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        MarkerFrame,
        BodyPrior,
        MarkerLabels,
        SolvedFrame,
        Heartbeat,
        Diagnostics,
        Log,
        Probe,
        Ready,
        Ack,
        EndOfStream,
    )
}

#: message types that steer the graph and never reach a node's data handlers
CONTROL_TYPES = frozenset({"Probe", "Ready", "Ack", "EndOfStream"})
