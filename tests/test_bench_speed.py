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


def test_the_long_takes_refined_frames_are_scored_by_minute_against_their_looped_source_frames():
    """bench speed's long take loops a session: refined frame k is scored against source frame
    k % P and binned by the minute it falls in; estimates are not scored."""
    from types import SimpleNamespace

    from uuomocap.commands.bench_speed import add_refined_errors

    rate = 1.0  # a frame per second: frames 0-59 are minute 0, 60-119 minute 1
    gt = np.zeros((3, 24, 3))
    gt[1, :, 0] = 0.01  # source frame 1 sits 10 mm along x
    results = [SimpleNamespace(kind="refined", frame_index=0, joints=np.zeros((24, 3))),   # exact
               SimpleNamespace(kind="refined", frame_index=61, joints=np.zeros((24, 3))),  # 61 % 3 = 1: 10 mm off
               SimpleNamespace(kind="estimate", frame_index=62, joints=np.ones((24, 3))),  # not the live output scored
               SimpleNamespace(kind="refined", frame_index=63, joints=np.full((24, 3), 0.002))]  # source 0: 2*sqrt(3) mm
    by = {}
    add_refined_errors(by, results, gt, rate)
    assert sorted(by) == [0, 1]
    np.testing.assert_allclose(by[0], [0.0])
    np.testing.assert_allclose(by[1], [0.01, 0.002 * np.sqrt(3)])
