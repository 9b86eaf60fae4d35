"""protocol.clock.ClockBridge: this host's clock mapped onto a capture system's from its frames."""

from __future__ import annotations

import numpy as np
import pytest

from uuomocap.protocol.clock import NS, ClockBridge


def feed(bridge: ClockBridge, rate_hz: float, seconds: float, capture_t0_s: float, local_t0_ns: int, latency_ms, rng) -> int:
    """Frames captured at rate_hz from capture_t0_s (capture clock), arriving after latency_ms
    (callable -> ms); returns the local time of the last arrival."""
    local = local_t0_ns
    for i in range(int(seconds * rate_hz)):
        capture = int(capture_t0_s * NS + i * NS / rate_hz)
        local = local_t0_ns + int(i * NS / rate_hz + latency_ms(rng) * 1e6)
        bridge.observe(capture, local)
    return local


def test_the_offset_is_the_clocks_difference_less_the_smallest_latency():
    rng = np.random.default_rng(0)
    bridge = ClockBridge(window_s=5.0, settle_s=1.0)
    assert not bridge.ready
    # Motive's clock at 1000 s when this host's monotonic clock reads 7 s; 2-40 ms transport + queueing
    feed(bridge, 120.0, 0.5, 1000.0, 7 * NS, lambda r: 2.0 + r.exponential(8.0), rng)
    assert not bridge.ready  # half a second seen: not settled
    feed(bridge, 120.0, 3.0, 1000.5, int(7.5 * NS), lambda r: 2.0 + r.exponential(8.0), rng)
    assert bridge.ready
    true_offset = 1000 * NS - 7 * NS
    assert abs(bridge.offset_ns - (true_offset - 2_000_000)) < 200_000  # within 0.2 ms of offset - min latency
    # a camera frame that arrived here at local 9 s was captured at Motive ~1002 s (less the 2 ms)
    assert abs(bridge.to_capture(9 * NS) - (1002 * NS - 2_000_000)) < 200_000


def test_the_window_follows_drift_and_a_restart_clears_it():
    rng = np.random.default_rng(1)
    bridge = ClockBridge(window_s=2.0, settle_s=0.5)
    feed(bridge, 100.0, 3.0, 50.0, 0, lambda r: 1.0, rng)
    first = bridge.offset_ns
    # the capture clock runs 20 ms ahead of where it was (drift): after the window the old offset is gone
    feed(bridge, 100.0, 3.0, 53.02, 3 * NS, lambda r: 1.0, rng)
    assert bridge.offset_ns - first == pytest.approx(20_000_000, abs=10)
    # Motive restarted: its stamps begin again at 0
    feed(bridge, 100.0, 0.2, 0.0, 6 * NS, lambda r: 1.0, rng)
    assert bridge.resets == 1 and not bridge.ready
    feed(bridge, 100.0, 1.0, 0.2, int(6.2 * NS), lambda r: 1.0, rng)
    assert bridge.ready and bridge.offset_ns == pytest.approx(-6 * NS - 1_000_000, abs=10)


def test_no_mapping_before_a_frame_and_bad_settings():
    bridge = ClockBridge()
    with pytest.raises(RuntimeError, match="no capture frame"):
        bridge.to_capture(0)
    for kwargs in ({"window_s": 0}, {"window_s": 2.0, "settle_s": 2.0}, {"settle_s": -1.0}):
        with pytest.raises(ValueError):
            ClockBridge(**kwargs)


def test_a_start_up_burst_does_not_settle_the_mapping():
    """A second of frames that waited in a queue and arrive within 50 ms spans a second of capture
    time but not of arrival time: no mapping from it (it would sit ~1 s off)."""
    bridge = ClockBridge(window_s=5.0, settle_s=1.0)
    for i in range(120):  # captured over 1 s, all arriving between 1.00 and 1.05 s local
        bridge.observe(int(500 * NS + i * NS / 120), int(1.0 * NS + i * 0.05 * NS / 120))
    assert not bridge.ready
    rng = np.random.default_rng(2)
    feed(bridge, 120.0, 1.2, 501.0, int(1.05 * NS), lambda r: 1.0 + r.exponential(3.0), rng)  # then the live stream
    assert bridge.ready and abs(bridge.offset_ns - (500 * NS - int(0.05 * NS) - 1_000_000)) < 300_000


def test_frame_times_of_a_camera_and_of_a_file_played_beside_the_stream():
    bridge = ClockBridge(window_s=5.0, settle_s=0.5)
    rng = np.random.default_rng(3)
    feed(bridge, 100.0, 1.0, 20.0, 3 * NS, lambda r: 1.0, rng)  # capture 20 s <-> local 3 s + 1 ms
    offset = bridge.offset_ns
    assert offset == 17 * NS - 1_000_000
    # a camera frame is where it arrived
    assert bridge.frame_times(123, True, 5 * NS) == (5 * NS, 5 * NS + offset)
    # a file's frame at 0.5 s of video belongs to the first marker frame + 0.5 s, due here that much later
    local, capture = bridge.frame_times(int(0.5 * NS), False, 5 * NS)
    assert capture == int(20.5 * NS) and local == capture - offset
