"""Names for solved markers (``solver_core.marker_naming``) and ``uuomocap label``, which writes them."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest


def test_assignment_gives_each_name_once_and_leaves_a_far_marker_unnamed():
    from uuomocap.solver_core.marker_naming import assign_layout_names

    layout = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.5, 0, 0]])
    names = ["A", "B", "C"]
    markers = np.array([
        [0.06, 0, 0],     # nearest A (60 mm) but B is free only if this one takes it: the sum decides
        [0.01, 0, 0],     # 10 mm from A
        [0.3, 0.3, 0.0],  # 360 mm from C: outside the cap, must not take C
        [np.nan] * 3,     # no surface point
    ])
    got, dist = assign_layout_names(markers, layout, names, max_distance_m=0.1)
    assert got == ["B", "A", "", ""]
    np.testing.assert_allclose(dist[:2], [0.04, 0.01], atol=1e-12)
    assert np.isnan(dist[2:]).all()


def test_segment_names_number_markers_from_the_segments_joint_and_skip_taken_names():
    from uuomocap.solver_core.marker_naming import segment_names

    parts = ["left_hip", "left_hip", "left_hip", "head", ""]
    points = np.array([[0, 0, -0.30], [0, 0, -0.05], [0, 0, -0.15], [0, 0, 1.7], [1, 1, 1]], float)
    origins = {"left_hip": np.zeros(3), "head": np.array([0, 0, 1.6])}
    got = segment_names(parts, points, origins, taken=["LThigh2"])
    assert got == ["LThigh4", "LThigh1", "LThigh3", "Head1", "Unlabeled1"]


@pytest.fixture(scope="module")
def pig_take(tmp_path_factory):
    """A Plug-in Gait session with gaps, and an OUT.npz holding its true marker points under a shape
    off the true one (the layout is cast on the solve's shape, as on a real solve); marker 0 unsolved."""
    from uuomocap.cli import main
    from uuomocap.protocol.session import read_npz, write_npz
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.metrics import attachment_joint_names

    root = tmp_path_factory.mktemp("label")
    sd = root / "s"
    assert main(["sample", "make", str(sd), "--layout", "structured", "--motion", "walk", "--duration", "2", "--rate", "30",
                 "--occlusion", "0.05", "--no-video", "--seed", "5", "--quiet"]) == 0
    gt = read_npz(sd / "gt.npz")
    faces = np.asarray(gt["marker_faces"], np.int64).copy()
    bary = np.asarray(gt["marker_bary"], np.float64)
    parts = attachment_joint_names(load_body_model(str(gt["body_model"])), faces, bary)
    faces[0], parts[0] = -1, ""
    betas = np.asarray(gt["betas"], np.float64) + np.random.default_rng(0).normal(0.0, 0.5, gt["betas"].shape)
    out = {k: gt[k] for k in ("poses", "trans", "joints", "mocap_framerate", "body_model", "stamps_ns")}
    out.update(betas=betas, marker_faces=faces, marker_bary=bary, marker_parts=np.array(parts))
    write_npz(root / "out.npz", out)
    return sd, root / "out.npz", [str(n) for n in gt["marker_names"]], parts


def test_label_writes_every_frame_of_the_take_with_plug_in_gait_names(pig_take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers

    sd, out, truth, parts = pig_take
    c3d = tmp_path / "labelled.c3d"
    assert main(["label", str(out), "--session", str(sd), "--out", str(c3d), "--layout", "plug-in-gait", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["markers"] == 39 and info["layout_names"] == 39 and info["named_from_layout"] == 38
    # the session's gt.npz knows the true names: the verb scores itself against them
    assert info["against_reference"] == {"compared": 39, "right": 38, "wrong": [], "unnamed": [truth[0]]}
    got = read_markers(c3d)
    source = read_markers(sd / "markers.c3d")
    assert got.labels[0] == "Unlabeled1"  # no surface point: no layout name, no part
    assert got.labels[1:] == truth[1:]
    assert got.labelled and len(set(got.labels)) == 39
    assert got.n_frames == source.n_frames and got.rate_hz == source.rate_hz and got.up_axis == source.up_axis
    assert (got.visible == source.visible).all() and (~source.visible).any()  # gaps stay gaps
    np.testing.assert_allclose(got.positions[got.visible], source.positions[source.visible], atol=1e-5)


def test_label_with_segment_names_and_with_a_template_to_trc(pig_take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers
    from uuomocap.solver_core.marker_naming import SEGMENT_NAMES

    sd, out, truth, parts = pig_take
    assert main(["label", str(out), "--markers", str(sd / "markers.c3d"), "--out", str(tmp_path / "seg.c3d"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layout"] == "segments" and info["named_from_layout"] == 0
    names = read_markers(tmp_path / "seg.c3d").labels
    assert len(set(names)) == 39
    for name, part in zip(names, parts):
        base = SEGMENT_NAMES.get(part, "Unlabeled")
        assert re.fullmatch(rf"{base}\d+", name), (name, part)

    # the session's labelled fit as the template: the names come back through the body surface
    trc = tmp_path / "templated.trc"
    assert main(["label", str(out), "--session", str(sd), "--out", str(trc), "--layout", str(sd / "gt.npz")]) == 0
    assert "38 named from" in capsys.readouterr().out
    assert read_markers(trc).labels[1:] == truth[1:]


def test_label_names_the_problem_with_bad_input(pig_take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import write_c3d
    from uuomocap.protocol.session import read_npz, write_npz

    sd, out, truth, parts = pig_take
    other = tmp_path / "other.c3d"
    write_c3d(other, np.random.default_rng(1).normal(0.0, 0.3, (5, 7, 3)) + [0, 0, 1], 30.0)
    cases = [
        (["--markers", str(other), "--out", str(tmp_path / "a.c3d")], "labels for 39 markers, the marker file has 7 columns"),
        (["--session", str(sd), "--out", str(tmp_path / "a.csv")], "write a .c3d or a .trc"),
        (["--out", str(tmp_path / "a.c3d")], "--session DIR or --markers FILE"),
        (["--session", str(sd), "--out", str(tmp_path / "a.c3d"), "--layout", "vicon"], "a template .npz"),
    ]
    template = dict(read_npz(sd / "gt.npz"))
    template["body_model"] = np.str_("open-full")
    write_npz(tmp_path / "full.npz", template)
    cases.append((["--session", str(sd), "--out", str(tmp_path / "a.c3d"), "--layout", str(tmp_path / "full.npz")],
                  "fitted on body model 'open-full', the solve on 'open-low'"))
    for argv, message in cases:
        assert main(["label", str(out), *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)


def test_label_fill_gaps_fills_from_the_body_and_marks_the_filled_samples(pig_take, tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers
    from uuomocap.protocol.session import read_npz
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.gap_fill import bounded_gaps, linear_fill, solved_marker_positions

    sd, out, truth, parts = pig_take
    c3d = tmp_path / "filled.c3d"
    assert main(["label", str(out), "--session", str(sd), "--out", str(c3d), "--fill-gaps", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)["gap_fill"]
    source, got = read_markers(sd / "markers.c3d"), read_markers(c3d)
    filled = got.visible & ~source.visible
    assert info["filled_samples"] == int(filled.sum()) > 100
    # marker 0 has no surface point in the solve: its gaps stay open, and are counted as such
    assert not filled[:, 0].any() and info["left_open_unsolved"] >= 1
    assert info["filled_gaps"] + info["left_open_unsolved"] == info["gaps"] and info["left_open_long"] == 0
    np.testing.assert_allclose(got.positions[source.visible], source.positions[source.visible], atol=1e-5)
    assert (got.residuals[filled] == 0).all()  # C3D: a residual of 0 = computed, not measured
    # the solve's shape is off the true one (fixture): the edge correction takes most of that out
    gt = read_npz(sd / "gt.npz")
    true_markers = solved_marker_positions(load_body_model("open-low"), gt["betas"], gt["poses"], gt["trans"],
                                           gt["marker_faces"], gt["marker_bary"])
    err = np.linalg.norm(got.positions - true_markers, axis=-1)[filled] * 1000
    line = np.linalg.norm(linear_fill(source.positions, source.visible)[0] - true_markers, axis=-1)[filled] * 1000
    assert np.sqrt(np.mean(err ** 2)) < 0.5 * np.sqrt(np.mean(line ** 2)) and np.percentile(err, 95) < 15, \
        (np.sqrt(np.mean(err ** 2)), np.sqrt(np.mean(line ** 2)))

    # --max-gap leaves the longer gaps open; it means nothing without --fill-gaps
    assert main(["label", str(out), "--session", str(sd), "--out", str(tmp_path / "short.trc"), "--fill-gaps", "--max-gap", "0.35",
                 "--json"]) == 0
    short = json.loads(capsys.readouterr().out)["gap_fill"]
    filled_lengths = [g["frames"] for g in info["filled"]]
    all_lengths = [g.frames for g in bounded_gaps(source.visible)]
    assert 0 < short["filled_gaps"] == sum(n <= 10 for n in filled_lengths) < info["filled_gaps"]
    assert short["left_open_long"] == sum(n > 10 for n in all_lengths)
    assert main(["label", str(out), "--session", str(sd), "--out", str(tmp_path / "x.c3d"), "--max-gap", "0.1"]) == 2
    assert "--max-gap needs --fill-gaps" in capsys.readouterr().err


def test_the_demos_hand_over_runs_label_and_export_as_their_command_lines_do(pig_take, tmp_path):
    # make demo calls the verbs in-process; it once built their arguments by hand and broke when label gained options
    from uuomocap.commands.demo import _hand_over

    sd, out, truth, parts = pig_take
    done = _hand_over(out, sd, tmp_path)
    assert set(done) == {"bvh", "named_markers"}
    assert (tmp_path / "stream.bvh").stat().st_size > 1000 and (tmp_path / "markers_named.c3d").is_file()
