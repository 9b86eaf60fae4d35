"""bench speed's memory probe: the long take's flat-memory check reads the solver's and the
worker's resident size now (VmRSS), not only the process's lifetime peak."""

from __future__ import annotations

import os

import numpy as np


def test_process_memory_is_read_now_and_at_peak():
    from uuomocap.commands.bench_speed import _proc_memory_mib

    before = _proc_memory_mib()
    block = np.ones(64 * 1024 * 1024 // 8)  # 64 MiB, touched
    during = _proc_memory_mib(os.getpid())
    assert during["rss_mib"] >= before["rss_mib"] + 60
    del block
    after = _proc_memory_mib()
    assert after["rss_mib"] < during["rss_mib"] - 60  # resident now: back down
    assert after["peak_mib"] >= during["rss_mib"] - 2  # the peak remembers it (the kernel syncs it lazily)
    assert _proc_memory_mib(2**22 + 12345) == {}  # no such process


def test_queue_model_serves_the_measured_calls_one_at_a_time_at_the_capture_rate():
    """bench speed's queue model: frames arrive every 1/rate, each call takes what it took; a stall
    delays the frames behind it until the backlog is worked off."""
    from uuomocap.window_methods import StreamRun, queue_latencies

    rate = 100.0  # a frame every 10 ms
    calls = [(50, 0.002, 0.0, []), (51, 0.002, 0.030, [40, 41]),  # frame 51's call runs a 30 ms pass
             (52, 0.002, 0.0, []), (53, 0.002, 0.0, []), (54, 0.002, 0.0, [])]
    run = StreamRun(np.zeros(0), rate, {}, {}, np.zeros(0), None, 0.0, 5, 0.0, 0.0, np.zeros(0), np.zeros(0), {}, calls)
    est, ref = queue_latencies(run)
    # 50: 2 ms; 51: 2 ms, then its pass ends at 10+2+30 = 42 ms; 52 (arrives at 20) starts at 42: 24 ms;
    # 53 (30) starts at 44: 16 ms; 54 (40) starts at 46: 8 ms
    np.testing.assert_allclose(est, [2.0, 2.0, 24.0, 16.0, 8.0], atol=1e-9)
    # frames refined by 51's pass that arrived before the steady state began are left out
    assert ref.size == 0
    calls[1] = (51, 0.002, 0.030, [50, 51])
    est, ref = queue_latencies(StreamRun(np.zeros(0), rate, {}, {}, np.zeros(0), None, 0.0, 5, 0.0, 0.0, np.zeros(0),
                                         np.zeros(0), {}, calls))
    np.testing.assert_allclose(ref, [42.0, 32.0], atol=1e-9)  # done at 42 ms; arrived at 0 and 10
