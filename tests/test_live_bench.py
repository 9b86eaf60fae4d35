"""`uuomocap bench live`: its scoring matches the stream's frames to gt.npz by stamp; a session it
cannot run is refused with the reason (the real-time run itself is a benchmark, not a test)."""

from __future__ import annotations

import numpy as np
import pytest

from uuomocap.commands import UserError
from uuomocap.commands.live_bench import score


def test_score_matches_stream_frames_to_the_truth_by_stamp(tmp_path):
    rate = 60.0
    gt = np.random.default_rng(0).normal(size=(20, 24, 3))
    frames = np.arange(5, 15)  # the stream solved frames 5..14 of the take (a late start, an early stop)
    pred = gt[frames] + np.array([0.010, 0.0, 0.0])  # 10 mm off in x
    np.savez(tmp_path / "gt.npz", joints=gt)
    np.savez(tmp_path / "live.npz", joints=pred, stamps_ns=(frames * 1e9 / rate).round().astype(np.int64))
    res = score(tmp_path / "live.npz", tmp_path / "gt.npz", rate)
    assert res["frames_solved"] == 10 and res["frames_in_take"] == 20
    assert res["mpjpe_mm"] == pytest.approx(10.0) and res["mpjve_mm_s"] == pytest.approx(0.0, abs=1e-6)


def test_a_session_without_video_is_refused(tmp_path):
    from uuomocap.cli import build_parser
    from uuomocap.synth import SampleConfig, make_session

    make_session(tmp_path / "s", SampleConfig(motion="walk", rate_hz=30.0, duration_s=1.0, n_markers=10, seed=0, video=False))
    args = build_parser().parse_args(["bench", "live", "--session", str(tmp_path / "s")])
    with pytest.raises(UserError, match="video.mp4 is missing"):
        args.func(args)
