"""Wire protocol: messages, envelope bounds, broker pub/sub, recordings."""

from __future__ import annotations

import dataclasses
import socket
import time

import msgpack
import numpy as np
import pytest

from uuomocap.nodes.config import ConfigError, parse_config
from uuomocap.protocol.envelope import DecodeError, decode, encode
from uuomocap.protocol.messages import (
    MESSAGE_TYPES,
    Ack,
    BodyPrior,
    Diagnostics,
    EndOfStream,
    Heartbeat,
    Log,
    MarkerFrame,
    MarkerLabels,
    MessageError,
    Probe,
    Ready,
    SolvedFrame,
)
from uuomocap.protocol.recording import (
    RecordingWriter,
    export_solved_npz,
    iter_recording,
    read_markers_mcap,
    recording_info,
)
from uuomocap.protocol.transport import LATEST, BrokerThread, Endpoints, Publisher, Subscriber, endpoint_in_use

RNG = np.random.default_rng(7)


def f32(*shape):
    return RNG.normal(size=shape).astype(np.float32)


def solved(i: int, kind: str = "refined", m: int = 5) -> SolvedFrame:
    return SolvedFrame(
        stamp_ns=i * 8_333_333, frame_index=i, kind=kind, betas=f32(16), poses=f32(72), trans=f32(3), joints=f32(24, 3),
        marker_faces=np.arange(m, dtype=np.int32), marker_bary=np.full((m, 3), 1 / 3, np.float32),
        marker_parts=["left_arm"] * m, residual_m=0.004, rate_hz=120.0, body_model="open-low",
    )


EXAMPLES = [
    MarkerFrame(stamp_ns=10, frame_index=3, positions=f32(7, 3), visible=RNG.random(7) > 0.3,
                track_ids=np.arange(7, dtype=np.int32), residuals=f32(7), rate_hz=120.0, source="x.c3d", labels=list("abcdefg")),
    MarkerFrame(stamp_ns=0, frame_index=0, positions=np.zeros((0, 3), np.float32), visible=np.zeros(0, bool)),
    BodyPrior(stamp_ns=5, video_stamp_ns=3, frame_index=1, global_orient=f32(3), body_pose=f32(23, 3), betas=f32(10),
              keypoints3d=f32(17, 3), confidence=0.7, body_model="open-low"),
    MarkerLabels(stamp_ns=1, labels_version=2, marker_parts=["", "left_leg"], marker_faces=np.array([-1, 4], np.int32),
                 marker_bary=f32(2, 3), confidence=f32(2), marker_offset_m=0.0095),
    solved(4),
    SolvedFrame(stamp_ns=2, frame_index=2, kind="estimate", betas=np.zeros(10), poses=np.zeros(72), trans=np.zeros(3),
                joints=np.zeros((24, 3))),
    Heartbeat(node="n", plugin="p", pid=1, state="running", uptime_s=1.5, publishes=["a/b"], subscribes=[], incarnation=2),
    Diagnostics(node="n", counters={"handled": 3}, topics={"a": {"gaps": 1}}, rejected={"size": 2}),
    Log(node="n", level=30, message="hello ü", logger="x"),
    Probe(topic="a/b", publisher="n", nonce=3),
    Ready(node="m", topic="a/b", publisher="n", nonce=3),
    Ack(node="m", topic="a/b", publisher="n", instance=9, seq=4, stamp_ns=100, eos=True),
    EndOfStream(topic="a/b", last_seq=9, last_stamp_ns=77),
]


def frames_of(msg, topic="t/x", seq=0, **kw):
    return [bytes(f) for f in encode(topic, msg, seq=seq, stamp_ns=getattr(msg, "stamp_ns", 0), source="src", instance=1, **kw)]


def same(a, b) -> bool:
    if type(a) is not type(b):
        return False
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
                return False
        elif x != y and not (isinstance(x, float) and np.isnan(x) and np.isnan(y)):
            return False
    return True


def test_every_message_type_round_trips():
    assert {type(m).TYPE for m in EXAMPLES} == set(MESSAGE_TYPES)
    for msg in EXAMPLES:
        env = decode(frames_of(msg, seq=5))
        assert same(env.message, msg), type(msg).__name__
        assert (env.seq, env.source, env.instance, env.topic) == (5, "src", 1, "t/x")
        for arr in env.message.arrays().values():
            assert not arr.flags.writeable  # views over the received buffer, not copies


def test_schema_violations_are_refused_at_the_sender():
    with pytest.raises(MessageError, match="dtype"):
        MarkerFrame(stamp_ns=0, frame_index=0, positions=np.zeros((2, 3)), visible=np.ones(2, bool)).validate()
    with pytest.raises(MessageError, match="dimension M"):
        MarkerFrame(stamp_ns=0, frame_index=0, positions=np.zeros((2, 3), np.float32), visible=np.ones(3, bool)).validate()
    with pytest.raises(MessageError, match="dtype"):
        MarkerFrame(stamp_ns=0, frame_index=0, positions=np.zeros((2, 3), np.float32), visible=np.array([1, 2], object)).validate()
    with pytest.raises(MessageError, match="kind"):
        dataclasses.replace(solved(0), kind="final").validate()
    with pytest.raises(MessageError, match="expected int"):
        dataclasses.replace(solved(0), frame_index=1.5).validate()


def _header(frames) -> dict:
    return msgpack.unpackb(frames[1], raw=False)


def _with_header(frames, **changes):
    h = _header(frames)
    h.update(changes)
    return [frames[0], msgpack.packb(h, use_bin_type=True), *frames[2:]]


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda f: f[:1], "frames"),
        (lambda f: f + [b"x"] * 40, "frames"),
        (lambda f: [b"t" * 500, *f[1:]], "topic"),
        (lambda f: [b"\xff\xfe", *f[1:]], "topic"),
        (lambda f: [f[0], b"\xc1garbage", *f[2:]], "header"),
        (lambda f: [f[0], msgpack.packb([1, 2]), *f[2:]], "header"),
        (lambda f: [f[0], b"\x00" * 70000, *f[2:]], "header"),
        (lambda f: _with_header(f, v=99), "envelope_version"),
        (lambda f: _with_header(f, t="Pickle"), "unknown_type"),
        (lambda f: _with_header(f, tv=2), "unknown_version"),
        (lambda f: _with_header(f, seq="1"), "header"),
        (lambda f: [*f[:2], f[2][:-4], *f[3:]], "size"),
        (lambda f: _with_header(f, a=[["positions", "|O", [7, 3]], *_header(f)["a"][1:]]), "array"),
        (lambda f: _with_header(f, a=[["positions", "<f4", [-7, 3]], *_header(f)["a"][1:]]), "array"),
        (lambda f: _with_header(f, a=[["positions", "<f4", [2**40, 3]], *_header(f)["a"][1:]]), "array"),
        (lambda f: _with_header(f, a=[["positions", "<f8", [7, 3]], *_header(f)["a"][1:]]), "size"),
        (lambda f: _with_header(f, f={**_header(f)["f"], "extra": 1}), "fields"),
        (lambda f: _with_header(f, f={k: v for k, v in _header(f)["f"].items() if k != "frame_index"}), "fields"),
        (lambda f: _with_header(f, f={**_header(f)["f"], "frame_index": "3"}), "fields"),
        (lambda f: _with_header(f, a=[["nonsense", "<f4", [7, 3]], *_header(f)["a"][1:]]), "fields"),
        (lambda f: _with_header(f, a=_header(f)["a"][1:]), "frames"),
    ],
)
def test_malformed_messages_are_rejected_with_a_reason(mutate, reason):
    good = frames_of(EXAMPLES[0])
    with pytest.raises(DecodeError) as exc:
        decode(mutate(list(good)))
    assert exc.value.reason == reason


def test_fuzzed_headers_never_raise_anything_but_decode_error():
    rng = np.random.default_rng(1)
    good = frames_of(EXAMPLES[0])
    header = bytearray(good[1])
    outcomes = {"ok": 0, "rejected": 0}
    for _ in range(3000):
        h = bytearray(header)
        for _ in range(int(rng.integers(1, 6))):
            h[int(rng.integers(len(h)))] = int(rng.integers(256))
        if rng.random() < 0.2:
            h = h[: int(rng.integers(len(h)))]
        try:
            decode([good[0], bytes(h), *good[2:]])
            outcomes["ok"] += 1
        except DecodeError:
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > 1000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_path(pub: Publisher, sub: Subscriber, topic: str, deadline_s: float = 20.0) -> None:
    """Probe until the subscription is live end to end (what nodes do before publishing)."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        pub.send_probe(topic, 1)
        if any(e.type == "Probe" for e in sub.recv(30)):
            return
    raise AssertionError("subscription never became live")


def _collect(sub: Subscriber, n: int, deadline_s: float = 20.0) -> list:
    out, end = [], time.monotonic() + deadline_s
    while len(out) < n and time.monotonic() < end:
        out += [e for e in sub.recv(50) if e.type != "Probe"]
    return out


@pytest.mark.parametrize("kind", ["ipc", "tcp"])
def test_broker_pub_sub_keeps_every_message_and_survives_garbage(kind, tmp_path):
    ep = Endpoints.ipc(tmp_path) if kind == "ipc" else Endpoints.tcp("127.0.0.1", _free_port(), _free_port())
    broker = BrokerThread(ep)
    pub, sub = Publisher(ep.frontend, "p"), Subscriber(ep.backend)
    rejects = []
    sub.on_reject = lambda reason, detail, topic: rejects.append(reason)
    try:
        sub.subscribe("markers/raw")
        sub.subscribe("log/")
        # each subscription travels through the broker on its own: one live path says nothing of the
        # other (a CI run lost the first log message to a "log/" subscription still in flight)
        _wait_path(pub, sub, "markers/raw")
        _wait_path(pub, sub, "log/p")
        good = frames_of(EXAMPLES[0], topic="markers/raw")
        for i in range(300):
            pub.send("markers/raw", dataclasses.replace(EXAMPLES[0], frame_index=i))
            if i % 10 == 0:  # garbage interleaved: wrong size, unknown version, random bytes
                pub.send_raw([good[0], good[1], good[2][:-1], *good[3:]])
                pub.send_raw(_with_header(good, tv=7))
                pub.send_raw([b"markers/raw", bytes(RNG.integers(0, 256, 40, dtype=np.uint8))])
            if i % 50 == 0:
                pub.send("log/p", Log("p", 20, f"at {i}"))
                pub.send("markers/raw_other", EXAMPLES[0])  # prefix of a longer name: filtered out
        got = _collect(sub, 306)
        frames = [e for e in got if e.topic == "markers/raw"]
        assert [e.message.frame_index for e in frames] == list(range(300))
        assert sum(e.topic.startswith("log/") for e in got) == 6
        assert not any(e.topic == "markers/raw_other" for e in got)
        assert sorted(set(rejects)) == ["header", "size", "unknown_version"] and len(rejects) == 90
        st = sub.stats["markers/raw"]
        assert (st.received, st.gaps, st.missed_at_join, st.rejected) == (300, 0, 0, 90)
    finally:
        pub.close()
        sub.close()
        broker.stop()


def test_gaps_late_join_and_latest_policy_are_counted(tmp_path):
    ep = Endpoints.ipc(tmp_path)
    broker = BrokerThread(ep)
    pub, sub, latest = Publisher(ep.frontend, "p"), Subscriber(ep.backend), Subscriber(ep.backend)
    try:
        sub.subscribe("a/x")
        latest.subscribe("a/x", LATEST)
        _wait_path(pub, sub, "a/x")
        _wait_path(pub, latest, "a/x")
        msg = EXAMPLES[0]
        for seq in [3, 4, 5, 9, 10, 10, 11]:  # joined late (3 missed), 3 lost, one duplicate
            pub.send_raw(encode("a/x", msg, seq=seq, stamp_ns=seq, source="p", instance=5))
        got = _collect(sub, 7)
        st = sub.stats["a/x"]
        assert (len(got), st.missed_at_join, st.gaps, st.out_of_order) == (7, 3, 3, 1)
        # the keep-all subscriber has all 7, so they are queued for the latest-only one too
        seen: list[int] = []
        end = time.monotonic() + 20
        while 11 not in seen and time.monotonic() < end:
            seen += [e.seq for e in latest.recv(50) if e.type != "Probe"]
        superseded = latest.stats["a/x"].superseded
        assert seen[-1] == 11 and superseded >= 1 and superseded + len(seen) == 7
    finally:
        for s in (pub, sub, latest):
            s.close()
        broker.stop()


def test_endpoint_collisions_are_detected(tmp_path):
    ep = Endpoints.ipc(tmp_path)
    assert endpoint_in_use(ep.frontend) is None
    broker = BrokerThread(ep)
    try:
        assert "in use" in endpoint_in_use(ep.frontend)
    finally:
        broker.stop()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        assert "cannot be bound" in endpoint_in_use(f"tcp://127.0.0.1:{s.getsockname()[1]}")


def test_recording_round_trip_truncation_and_markers(tmp_path):
    path = tmp_path / "r.mcap"
    w = RecordingWriter(path, chunk_size=4096, flush_interval_s=0.001)
    sent = []
    for i in range(200):
        msg = MarkerFrame(stamp_ns=i * 10_000_000, frame_index=i, positions=f32(6, 3), visible=np.arange(6) != i % 6,
                          track_ids=np.arange(10, 16, dtype=np.int32), rate_hz=100.0)
        env = decode(frames_of(msg, topic="markers/raw", seq=i))
        w.write(env)
        sent.append(msg)
    w.write(decode(frames_of(EXAMPLES[6], topic="heartbeat/n")))
    w.close()
    info = recording_info(path)
    assert info.finished and not info.truncated
    assert info.topics["markers/raw"] == {"type": "MarkerFrame", "count": 200}
    back = [r.decode().message for r in iter_recording(path, topics=["markers/raw"])]
    assert all(same(a, b) for a, b in zip(back, sent)) and len(back) == 200

    md = read_markers_mcap(path)
    assert md.positions.shape == (200, 6, 3) and md.rate_hz == 100.0 and md.meta["tracks"] == list(range(10, 16))
    assert np.array_equal(md.visible[:, 0], np.arange(200) % 6 != 0)
    assert np.allclose(md.positions[1, 0], sent[1].positions[0]) and np.isnan(md.positions[0, 0]).all()

    # a killed recorder: cut the file anywhere after a few chunks -> readable prefix, flagged truncated
    data = path.read_bytes()
    for cut in (len(data) // 3, len(data) // 2 + 17, len(data) - 100):
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        pinfo = recording_info(part)
        assert pinfo.truncated and not pinfo.finished and 0 < pinfo.messages <= 201
        prefix = [r.decode().message.frame_index for r in iter_recording(part, topics=["markers/raw"])]
        assert prefix == list(range(len(prefix)))


def test_solved_export_layout_prefers_revised_then_refined_and_is_deterministic(tmp_path):
    frames = [solved(i, "estimate") for i in range(10)] + [solved(i, "refined") for i in range(8)]
    frames.append(solved(9, "estimate"))  # a later estimate never replaces a refined frame... nor needs one
    revised = [solved(i, "revised") for i in (5, 6)]  # after a lock upgrade
    frames += revised + [solved(6, "refined")]  # ... and a refined frame never replaces a revised one
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    info = export_solved_npz(frames, a, method="stream")
    export_solved_npz(list(frames), b, method="stream")
    assert a.read_bytes() == b.read_bytes()
    assert info == {"frames": 10, "refined": 8, "revised": 2, "path": str(a)}
    with np.load(a, allow_pickle=False) as z:
        assert z["poses"].shape == (10, 72) and z["joints"].shape == (10, 24, 3) and z["trans"].shape == (10, 3)
        assert z["betas"].shape == (16,) and z["marker_parts"].tolist() == ["left_arm"] * 5
        assert z["marker_faces"].dtype == np.int64 and z["marker_bary"].shape == (5, 3)
        assert float(z["mocap_framerate"]) == 120.0 and str(z["method"]) == "stream" and str(z["body_model"]) == "open-low"
        assert z["frame_kind"].tolist() == ["refined"] * 5 + ["revised"] * 2 + ["refined"] + ["estimate"] * 2
        assert np.array_equal(z["poses"][3], frames[13].poses) and np.array_equal(z["poses"][6], revised[1].poses)
        # each frame keeps the shape it was solved under (a lock upgrade changes it mid-take)
        assert z["frame_betas"].shape == (10, 16) and np.array_equal(z["frame_betas"][3], frames[13].betas)
        assert np.array_equal(z["frame_betas"][9], frames[18].betas) and np.array_equal(z["betas"], frames[18].betas)


def test_config_parsing_names_the_problem():
    @dataclasses.dataclass(frozen=True)
    class C:
        file: str
        speed: float = 1.0
        topics: list[str] = dataclasses.field(default_factory=list)
        mode: "str | None" = None

        def __post_init__(self):
            if self.speed <= 0:
                raise ValueError("speed must be > 0")

    assert parse_config(C, {"file": "x", "speed": 2}, "n").speed == 2.0
    for params, text in [
        ({"file": "x", "sped": 1}, "unknown parameter 'sped'"),
        ({}, "missing required parameter 'file'"),
        ({"file": 3}, "parameter 'file' must be str"),
        ({"file": "x", "speed": True}, "parameter 'speed' must be float"),
        ({"file": "x", "topics": ["a", 1]}, r"topics'\[1\] must be str"),
        ({"file": "x", "speed": -1}, "speed must be > 0"),
    ]:
        with pytest.raises(ConfigError, match=text):
            parse_config(C, params, "node 'n'")
