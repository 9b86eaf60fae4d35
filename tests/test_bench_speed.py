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
