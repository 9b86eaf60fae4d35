"""QTM RT protocol: packet codec, bounds checks, a real TCP stream, and the live graph via the launcher."""

from __future__ import annotations

import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from uuomocap.protocol import qtm


def frame(i: int, n: int = 5, rate: float = 120.0) -> qtm.QTMFrame:
    k = np.arange(n)
    pts = np.stack([0.5 * np.cos(i / rate + k), 0.5 * np.sin(i / rate + k), 1.0 + 0.1 * k], 1)
    return qtm.QTMFrame(frame_number=100 + i, timestamp_us=int(round(i * 1e6 / rate)),
                       positions=pts.astype(np.float32), ids=np.arange(1, n + 1, dtype=np.uint32))


@pytest.mark.parametrize("residuals", [False, True])
def test_data_round_trip(residuals):
    f = frame(7)
    f.residuals_mm = np.linspace(0, 1, 5).astype(np.float32) if residuals else None
    packet = qtm.encode_data(f, residuals=residuals)
    size, ptype = struct.unpack_from("<II", packet)
    assert size == len(packet) and ptype == qtm.PACKET_DATA
    assert len(packet) == 8 + 16 + 8 + 8 + 5 * (20 if residuals else 16)
    g = qtm.decode_data(packet[8:])
    assert (g.frame_number, g.timestamp_us) == (f.frame_number, f.timestamp_us)
    np.testing.assert_allclose(g.positions, f.positions, atol=1e-6)  # mm on the wire, metres here
    np.testing.assert_array_equal(g.ids, f.ids)
    if residuals:
        np.testing.assert_array_equal(g.residuals_mm, f.residuals_mm)


def test_labeled_and_unknown_components():
    labeled = np.array([[1000.0, 0, 0], [np.nan, np.nan, np.nan]], np.float32)
    body3d = struct.pack("<IHH", 2, 3, 4) + labeled.tobytes()
    comp3d = struct.pack("<II", 8 + len(body3d), qtm.COMPONENT_3D) + body3d
    other = struct.pack("<II", 12, 17) + b"\x00" * 4  # a timecode component: skipped by its size
    payload = struct.pack("<QII", 5, 9, 2) + comp3d + other
    g = qtm.decode_data(payload)
    assert g.skipped_components == 1 and (g.drop_rate_2d, g.out_of_sync_rate_2d) == (3, 4)
    assert g.labeled_positions[0].tolist() == [1.0, 0.0, 0.0] and np.isnan(g.labeled_positions[1]).all()
    assert len(g.positions) == 0


def test_malformed_data_is_rejected():
    payload = qtm.encode_data(frame(1))[8:]
    for cut in range(len(payload)):
        with pytest.raises(qtm.QTMError):
            qtm.decode_data(payload[:cut])
    bad = bytearray(payload)
    struct.pack_into("<I", bad, 24, 9)  # marker count disagrees with the component size
    with pytest.raises(qtm.QTMError, match="says 9 markers"):
        qtm.decode_data(bytes(bad))
    bad = bytearray(payload)
    struct.pack_into("<I", bad, 16, 4)  # component size smaller than its header
    with pytest.raises(qtm.QTMError, match="claims 4 bytes"):
        qtm.decode_data(bytes(bad))
    bad = bytearray(payload)
    struct.pack_into("<f", bad, 32, float("nan"))
    with pytest.raises(qtm.QTMError, match="non-finite"):
        qtm.decode_data(bytes(bad))
    with pytest.raises(qtm.QTMError, match="trailing|unexpected"):
        qtm.decode_data(payload + b"\0")
    rng = np.random.default_rng(0)
    for _ in range(2000):  # fuzz: only QTMError, never anything else
        data = np.frombuffer(payload, np.uint8).copy()
        idx = rng.integers(0, len(data), 3)
        data[idx] = rng.integers(0, 256, 3)
        try:
            qtm.decode_data(data.tobytes())
        except qtm.QTMError:
            pass


def test_packet_stream_reassembles_and_detects_broken_framing():
    packets = qtm.encode_command("Version 1.25") + qtm.encode_data(frame(0)) + qtm.encode_command("x")
    stream = qtm.PacketStream()
    got = []
    for i in range(0, len(packets), 7):  # TCP may deliver any split
        got += stream.feed(packets[i:i + 7])
    assert [t for t, _ in got] == [qtm.PACKET_COMMAND, qtm.PACKET_DATA, qtm.PACKET_COMMAND]
    with pytest.raises(qtm.QTMError, match="framing"):
        qtm.PacketStream().feed(struct.pack("<II", 3, 1))
    with pytest.raises(qtm.QTMError, match="framing"):
        qtm.PacketStream(max_packet_bytes=100).feed(struct.pack("<II", 1000, 3))


def _stream(server: qtm.QTMServer, n: int, rate: float, done: threading.Event, errors: list) -> None:
    try:
        deadline = time.monotonic() + 30
        while not server.streaming and time.monotonic() < deadline and not done.is_set():
            server.serve(0.05)
        start, i = time.monotonic(), 0
        while (n == 0 or i < n) and not done.is_set() and time.monotonic() < deadline:
            server.serve(0.0)
            server.send_frame(frame(i, rate=rate))
            i += 1
            time.sleep(max(0.0, start + i / rate - time.monotonic()))
        server.serve(0.2)
    except Exception as exc:
        errors.append(exc)


def test_real_tcp_stream_200_frames_in_order():
    errors: list = []
    done = threading.Event()
    with qtm.QTMServer(capture_rate_hz=120.0) as server:
        thread = threading.Thread(target=_stream, args=(server, 200, 120.0, done, errors), daemon=True)
        thread.start()
        with qtm.QTMClient(*server.address) as client:
            client.connect(timeout_s=5.0)
            got = []
            deadline = time.monotonic() + 10
            while len(got) < 200 and time.monotonic() < deadline:
                f = client.receive(0.5)
                if f is not None:
                    got.append(f)
        done.set()
        thread.join(5)
    assert not errors
    assert client.capture_rate_hz == 120.0
    assert [f.frame_number for f in got] == [100 + i for i in range(200)]
    np.testing.assert_allclose(got[-1].positions, frame(199).positions, atol=1e-6)
    assert client.stats.frames == 200 and client.stats.malformed == 0 and client.stats.gaps == 0


def test_client_reports_refusals_and_missing_server():
    with qtm.QTMServer() as server:
        port = server.address[1]
        server_thread_stop = threading.Event()

        def answer():
            while not server_thread_stop.is_set():
                server.serve(0.05)

        t = threading.Thread(target=answer, daemon=True)
        t.start()
        client = qtm.QTMClient(*server.address, version="not-a-version extra")
        with pytest.raises(qtm.QTMError, match="refused protocol version"):
            client.connect(timeout_s=3.0)
        client.close()
        server_thread_stop.set()
        t.join(2)
    with pytest.raises(TimeoutError, match="no QTM RT server"):
        qtm.QTMClient("127.0.0.1", port).connect(timeout_s=1.0)


def test_live_graph_qtm_source_tracker_recorder(tmp_path):
    """The launcher runs launch/live_qtm.yaml against a loopback QTM server: every frame recorded,
    raw and tracked; five markers give five stable tracks."""
    from uuomocap.nodes.base import discover_plugins
    from uuomocap.protocol.recording import iter_recording, read_markers_mcap

    missing = {"qtm_source", "tracker", "recorder"} - set(discover_plugins())
    if missing:
        pytest.skip(f"node plugins not installed: {sorted(missing)} (pip install -e .)")
    n, rate = 240, 120.0
    out = tmp_path / "live.mcap"
    errors: list = []
    done = threading.Event()
    with qtm.QTMServer(capture_rate_hz=rate) as server:
        thread = threading.Thread(target=_stream, args=(server, 0, rate, done, errors), daemon=True)
        thread.start()
        try:
            cmd = [sys.executable, "-m", "uuomocap.cli", "launch", "--log-dir", str(tmp_path), "--timeout", "60",
                   "live_qtm", f"port:={server.address[1]}", f"max_frames:={n}", f"out:={out}"]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
            logs = "".join(f"--- {p.name}\n{p.read_text()}" for p in sorted(tmp_path.glob("*.log")))
            assert proc.returncode == 0, proc.stderr + logs
        finally:
            done.set()
            thread.join(5)
    assert not errors
    counts: dict[str, int] = {}
    for rec in iter_recording(out):
        counts[rec.topic] = counts.get(rec.topic, 0) + 1
    assert counts.get("markers/raw") == n + 1 and counts.get("markers/tracked") == n + 1  # + EndOfStream
    tracked = read_markers_mcap(out, topic="markers/tracked")
    seen = tracked.visible.any(0)
    assert seen.sum() == 5 and tracked.visible[2:, seen].all()
    assert tracked.up_axis == "+z" and tracked.rate_hz == rate
    assert np.diff(tracked.stamps_ns) == pytest.approx(1e9 / rate, abs=1e3)  # microsecond stamps
