"""Joining one marker's columns (solver_core.track_stitching, `label --merge-tracks`)."""

import json

import numpy as np


def _fragment(markers: np.ndarray, hides: list[list[tuple[int, int]]]):
    """Columns of every seen stretch of each marker (markers (T, M, 3)); hides[m]: (start, stop) per marker."""
    T = markers.shape[0]
    cols, source = [], []
    for m, spans in enumerate(hides):
        seen = np.ones(T, bool)
        for a, b in spans:
            seen[a:b] = False
        idx = np.flatnonzero(seen)
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            col = np.full((T, 3), np.nan)
            col[run] = markers[run, m]
            cols.append(col)
            source.append(m)
    x = np.stack(cols, 1)
    return x, np.isfinite(x).all(-1), np.array(source)


def test_stitching_joins_each_markers_columns_and_not_its_neighbours():
    from uuomocap.solver_core.track_stitching import merge_columns, stitch_columns

    rate, T = 60.0, 180
    t = np.arange(T) / rate
    # three markers on one forearm-like segment turning about z: two of them 3 cm apart
    angle = 1.5 * np.sin(2 * t)
    rot = np.stack([np.stack([np.cos(angle), -np.sin(angle), 0 * t], -1), np.stack([np.sin(angle), np.cos(angle), 0 * t], -1),
                    np.stack([0 * t, 0 * t, 1 + 0 * t], -1)], 1)  # (T, 3, 3) world from segment
    local = np.array([[0.25, 0.0, 0.0], [0.25, 0.03, 0.0], [0.1, -0.05, 0.02]])
    origin = np.stack([0.5 * t, 0 * t, 1 + 0 * t], -1)
    markers = origin[:, None] + np.einsum("tij,mj->tmi", rot, local)
    x, vis, source = _fragment(markers, [[(40, 55), (120, 130)], [(60, 80)], [(30, 45), (90, 140)]])
    # the solve: each column's predicted point 8 mm off its marker along the segment, with 1 mm noise; frames = segment axes
    rng = np.random.default_rng(0)
    pred_markers = markers + np.einsum("tij,j->ti", rot, [0.008, 0.0, 0.0])[:, None] + rng.normal(0, 0.001, markers.shape)
    predicted = pred_markers[:, source]
    frames = np.repeat(np.transpose(rot, (0, 2, 1))[:, None], len(source), 1)  # rows = segment axes
    chains = stitch_columns(x, vis, predicted, frames, rate)
    assert sorted(sorted(int(source[c]) for c in chain) for chain in chains) == [[0, 0, 0], [1, 1], [2, 2, 2]]
    for chain in chains:  # in time order
        assert all(vis[:, a].nonzero()[0].max() < vis[:, b].nonzero()[0].min() for a, b in zip(chain, chain[1:]))
    merged, seen = merge_columns(x, vis, chains)
    k = next(i for i, c in enumerate(chains) if source[c[0]] == 0)
    np.testing.assert_array_equal(merged[seen[:, k], k], markers[seen[:, k], 0])
    assert (~seen[:, k]).sum() == 25
    # a gap longer than max_gap_s is not bridged
    from uuomocap.solver_core.track_stitching import StitchConfig

    short = stitch_columns(x, vis, predicted, frames, rate, StitchConfig(max_gap_s=0.5))
    assert len(short) == len(chains) + 1  # marker 2's 50-frame hide (0.83 s)


def test_label_merge_tracks_writes_one_named_column_per_marker(tmp_path, capsys):
    from uuomocap.cli import main
    from uuomocap.protocol.markerio import read_markers
    from uuomocap.protocol.session import read_npz, write_npz

    sd = tmp_path / "s"
    assert main(["sample", "make", str(sd), "--layout", "structured", "--motion", "walk", "--duration", "2", "--rate", "30",
                 "--occlusion", "0.03", "--track-breaks", "--no-video", "--seed", "5", "--quiet"]) == 0
    gt = read_npz(sd / "gt.npz")
    columns = len(gt["marker_faces"])
    assert columns > 39
    out = {k: gt[k] for k in ("betas", "poses", "trans", "joints", "mocap_framerate", "body_model", "stamps_ns", "marker_faces", "marker_bary")}
    write_npz(tmp_path / "out.npz", out)
    c3d = tmp_path / "merged.c3d"
    capsys.readouterr()
    assert main(["label", str(tmp_path / "out.npz"), "--session", str(sd), "--out", str(c3d), "--layout", "plug-in-gait",
                 "--merge-tracks", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["merge_tracks"]["columns"] == columns and info["markers"] == 39
    assert info["against_reference"]["right"] == 39
    got = read_markers(c3d)
    assert got.n_markers == 39 and sorted(got.labels) == sorted(set(str(n) for n in gt["marker_names"]))
    # each output column holds exactly the samples of its marker's columns
    source = read_markers(sd / "markers.c3d")
    for k, chain in enumerate(info["merge_tracks"]["chains"]):
        assert len({str(gt["marker_names"][c]) for c in chain}) == 1
        np.testing.assert_array_equal(got.visible[:, k], source.visible[:, chain].any(1))


def test_bench_merge_tracks_counts_joined_pure_and_whole_markers(capsys):
    from uuomocap.cli import main
    from uuomocap.commands.bench_merge_tracks import score_chains

    source = np.array([0, 1, 0, 2, 2, 1])
    assert score_chains([[0, 2], [1], [5], [3, 4]], source) == {"chains": 4, "pure": 4, "whole_markers": 2}
    assert score_chains([[0, 1], [2, 5], [3, 4]], source) == {"chains": 3, "pure": 1, "whole_markers": 1}

    assert main(["bench", "merge-tracks", "--motions", "walk", "--seeds", "1", "--duration", "2", "--occlusion", "0.03", "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["sessions"][0]
    assert row["markers"] == 39 and row["columns"] > 39
    assert row["truth"]["whole_markers"] == 39 and row["truth"]["chains"] == 39  # true points and poses: every marker whole
    assert row["solved"]["pure"] >= 0.9 * row["solved"]["chains"]


def test_a_handover_links_each_new_column_to_the_nearest_carried_marker_once():
    from uuomocap.solver_core.track_stitching import carried_positions, handover_links

    # two ended markers on faces turned 90 degrees about z; residuals 1 cm along each face's first edge
    surface = np.array([[0.0, 0.0, 1.0], [0.05, 0.0, 1.0]])
    turn = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # rows: edge along y, perpendicular along -x
    frames = np.stack([np.eye(3), turn])
    local = np.array([[0.01, 0.0, 0.0], [0.01, 0.0, 0.0]])
    carried = carried_positions(surface, frames, local)
    np.testing.assert_allclose(carried, [[0.01, 0.0, 1.0], [0.05, 0.01, 1.0]], atol=1e-12)
    # the first new column is 2 mm from marker 1, the second 3 mm from marker 0, the third near neither
    new = np.array([[0.05, 0.012, 1.0], [0.013, 0.0, 1.0], [0.5, 0.5, 1.0]])
    assert sorted(handover_links(new, carried, 0.04)) == [(0, 1), (1, 0)]
    # one marker, two candidates: only the nearer takes it
    assert handover_links(np.array([[0.012, 0.0, 1.0], [0.015, 0.0, 1.0]]), carried[:1], 0.04) == [(0, 0)]
    assert handover_links(new, carried, 0.001) == []
    assert handover_links(np.zeros((0, 3)), carried, 0.04) == []
