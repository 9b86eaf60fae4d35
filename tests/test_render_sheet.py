"""``uuomocap render``: the contact sheet of a solve draws the body, its markers by label, and the reference."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """A small session and an OUT.npz that is its ground truth, with one marker left unlabelled."""
    from uuomocap.cli import main
    from uuomocap.protocol.session import read_npz, write_npz
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.metrics import attachment_joint_names

    root = tmp_path_factory.mktemp("render")
    sd = root / "s"
    assert main(["sample", "make", str(sd), "--motion", "walk", "--duration", "2", "--rate", "30", "--markers", "20",
                 "--no-video", "--seed", "3", "--quiet"]) == 0
    gt = read_npz(sd / "gt.npz")
    faces = np.asarray(gt["marker_faces"], np.int64).copy()
    bary = np.asarray(gt["marker_bary"], np.float64)
    parts = attachment_joint_names(load_body_model(str(gt["body_model"])), faces, bary)
    faces[0] = -1
    parts[0] = ""
    out = {k: gt[k] for k in ("betas", "poses", "trans", "joints", "mocap_framerate", "body_model", "stamps_ns")}
    out.update(marker_faces=faces, marker_bary=bary, marker_parts=np.array(parts), method=np.str_("truth"))
    write_npz(root / "out.npz", out)
    return sd, root / "out.npz", parts


def test_contact_sheet_shows_the_frames_markers_by_part_and_the_reference(solved, tmp_path, capsys):
    import cv2

    from uuomocap.cli import main
    from uuomocap.render import _PART_BGR, UNLABELLED_BGR

    sd, out, parts = solved
    png = tmp_path / "sheet.png"
    assert main(["render", str(out), "--session", str(sd), "--out", str(png), "--frames", "4", "--tile", "160x200", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    frames = info["frames"]
    assert len(frames) == 4 and frames == sorted(frames) and frames[0] == 0 and frames[-1] <= 59
    assert info["markers"] == 20 and info["labelled"] == 19
    assert info["frame_mpjpe_mm"] == [0.0] * 4  # the solve is the reference
    img = cv2.imread(str(png))
    assert img.shape == (22 + 2 * 200, 4 * 160, 3)  # title strip, front + side rows, one column per frame
    colours = {tuple(int(c) for c in px) for px in img.reshape(-1, 3)}
    labelled_parts = sorted({p for p in parts if p})
    drawn = [c for c in _PART_BGR[: len(labelled_parts)] if c in colours]
    assert len(drawn) == min(len(labelled_parts), len(_PART_BGR)), (labelled_parts, drawn)
    assert UNLABELLED_BGR in colours  # the marker left unlabelled
    assert (255, 255, 255) in colours  # the reference skeleton over the body


def test_render_without_markers_and_its_errors(solved, tmp_path, capsys):
    from uuomocap.cli import main

    sd, out, _ = solved
    png = tmp_path / "bare.png"
    assert main(["render", str(out), "--out", str(png), "--frames", "0,59"]) == 0
    assert png.is_file()
    capsys.readouterr()
    assert main(["render", str(out), "--frames", "0,60"]) == 2
    assert "frames 0-59" in capsys.readouterr().err
    assert main(["render", str(out), "--frames", "60"]) == 2  # a count, too many columns
    assert "1-24" in capsys.readouterr().err
    assert main(["render", str(out), "--out", str(tmp_path / "x.jpg")]) == 2
    assert ".png" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((3, 72)))
    assert main(["render", str(bad)]) == 2
    assert "missing key" in capsys.readouterr().err


def test_render_writes_a_video_of_the_take(solved, tmp_path, capsys):
    import cv2

    from uuomocap.cli import main

    sd, out, _ = solved
    mp4 = tmp_path / "take.mp4"
    assert main(["render", str(out), "--session", str(sd), "--out", str(tmp_path / "s.png"), "--video", str(mp4),
                 "--stride", "3", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["video"]["frames"] == 20 and info["video"]["fps"] == 10.0  # 60 frames at 30 Hz, every third
    cap = cv2.VideoCapture(str(mp4))
    try:
        assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 20
        ok, frame = cap.read()
        assert ok and frame.shape == (480, 640, 3)
        assert frame.std() > 10  # a body on the floor, not a blank frame
    finally:
        cap.release()
    assert main(["render", str(out), "--video", str(tmp_path / "x.avi")]) == 2
    assert ".mp4" in capsys.readouterr().err


def test_the_demo_sheet_lands_beside_the_solve(solved):
    """``make demo`` calls this after its solve (``commands.demo``)."""
    from uuomocap.commands.render import session_sheet

    sd, out, _ = solved
    info = session_sheet(out, sd)
    assert info["png"] == str(out.with_suffix(".png")) and out.with_suffix(".png").is_file()
    assert len(info["frames"]) == 6 and info["labelled"] == 19


def test_a_count_of_frames_picks_distinct_poses_where_evenly_spaced_frames_repeat_one_phase():
    """A cyclic motion whose period is the even spacing: linspace picks one phase six times, the
    sheet's choice spreads over the cycle (its extremes included), in time order, never a NaN frame."""
    from uuomocap.commands.render import spread_frames

    t = np.arange(61)
    joints = np.zeros((61, 24, 3))
    joints[:, 5, 0] = 0.3 * np.sin(2 * np.pi * t / 12)  # a hand swinging 30 cm either way, period 12 frames
    assert {int(i) % 12 for i in np.linspace(0, 60, 6).round()} == {0}  # evenly spaced: one phase
    picked = spread_frames(joints, 6)
    assert picked == sorted(picked) and len(set(picked)) == 6
    phases = {i % 12 for i in picked}
    assert len(phases) >= 4 and {3, 9} <= phases, picked  # both extremes of the swing
    joints[3::12] = np.nan  # unsolved frames (every frame at the forward extreme)
    picked = spread_frames(joints, 6)
    assert not any(i % 12 == 3 for i in picked) and len(picked) == 6
