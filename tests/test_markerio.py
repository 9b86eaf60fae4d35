"""Marker file layer: real files from other labs, synthetic quirky files, round trips, CLI."""

from __future__ import annotations

import json
from pathlib import Path
from unittest import mock

import ezc3d
import numpy as np
import pytest

from uuomocap.cli import main
from uuomocap.protocol import marker_c3d
from uuomocap.protocol.markerio import (
    MarkerFileError,
    infer_up_axis,
    is_placeholder_label,
    parse_units,
    read_markers,
    write_c3d,
    write_trc,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "markers"


def shared(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"shared test data absent: {path}")
    return path


def shared_files() -> list[Path]:
    return sorted(DATA.glob("*")) if DATA.is_dir() else []


def body_spread_m(positions: np.ndarray) -> float:
    """Median over frames of the largest per-axis extent of the visible markers (metres)."""
    ext = []
    for frame in positions[:: max(1, len(positions) // 100)]:
        p = frame[~np.isnan(frame).any(axis=1)]
        if len(p) >= 3:
            q = np.percentile(p, [5, 95], axis=0)
            ext.append((q[1] - q[0]).max())
    return float(np.median(ext))


def synthetic_body(T: int = 120, M: int = 30, up: int = 2, seed: int = 0) -> np.ndarray:
    """(T, M, 3) metres: markers on a 0.4 x 0.3 x 1.7 m person walking along x, feet on the floor."""
    rng = np.random.default_rng(seed)
    local = rng.uniform([-0.2, -0.15, 0.02], [0.2, 0.15, 1.75], size=(M, 3))
    walk = np.zeros((T, 1, 3))
    walk[:, 0, 0] = np.linspace(0.0, 1.5, T)
    pos = local[None] + walk + rng.normal(0, 0.002, size=(T, M, 3))
    if up != 2:  # move the vertical axis from z to `up`, keeping a right-handed frame
        pos = np.roll(pos, shift=up - 2, axis=-1)
    return pos


def make_c3d(path: Path, coords: np.ndarray, residuals: np.ndarray, labels, units="mm", rate=100.0, params=None):
    """A C3D written directly with ezc3d (not our writer), to plant quirks: coords (T,M,3) file units."""
    T, M, _ = coords.shape
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([rate])
    c["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    for (group, key), value in (params or {}).items():
        c.add_parameter(group, key, value)
    pts = np.ones((4, M, T))
    pts[:3] = coords.transpose(2, 1, 0)
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {
        "residuals": residuals.T[None].astype(float).copy(),
        "camera_masks": np.zeros((7, M, T), dtype=bool),
    }
    c.write(str(path))
    return path


def make_trc(path: Path, header: dict, names: list[str], rows: list[list[str]], rate="100") -> Path:
    keys = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]
    vals = {"DataRate": rate, "CameraRate": rate, "NumFrames": str(len(rows)), "NumMarkers": str(len(names)),
            "Units": "mm", "OrigDataRate": rate, "OrigDataStartFrame": "1", "OrigNumFrames": str(len(rows))}
    vals.update(header)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(keys),
        "\t".join(vals[k] for k in keys),
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names),
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(names))),
        "",
    ]
    lines += ["\t".join(r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def trc_rows(pos_file_units: np.ndarray, rate: float, fmt="{:.4f}") -> list[list[str]]:
    rows = []
    for t, frame in enumerate(pos_file_units):
        fields = [str(t + 1), f"{t / rate:.5f}"]
        for p in frame:
            fields += ["", "", ""] if np.isnan(p).any() else [fmt.format(v) for v in p]
        rows.append(fields)
    return rows


# ----------------------------------------------------------------------------------- real files


@pytest.mark.parametrize("path", shared_files(), ids=lambda p: p.name)
def test_every_shared_file_reads_with_sensible_numbers(path):
    md = read_markers(path)
    T, M, _ = md.positions.shape
    assert T > 100 and M >= 20
    assert md.visible.shape == (T, M) and md.visible.dtype == bool
    assert np.array_equal(md.visible, ~np.isnan(md.positions).any(-1))
    assert md.stamps_ns.dtype == np.int64 and md.stamps_ns[0] == 0 and np.all(np.diff(md.stamps_ns) > 0)
    assert abs(md.stamps_ns[-1] - (T - 1) / md.rate_hz * 1e9) < 10
    assert md.up_axis in {"+x", "-x", "+y", "-y", "+z", "-z"} and md.up_axis_source
    assert len(md.labels) == M == len(set(md.labels))
    # metres: a person is 0.5-2.5 m across (a mm file misread would be ~1000, a m file as mm ~0.001)
    assert 0.5 < body_spread_m(md.positions) < 2.5
    assert 0.0 <= md.missing_fraction < 1.0


def test_c3dorg_pig_metres():
    md = read_markers(shared("c3dorg_pig_fullbody_metres.c3d"))
    assert md.positions.shape == (721, 40, 3)
    assert md.rate_hz == 128.0 and md.units_found == "m" and md.units_used == "m"
    assert md.labelled and md.labels[:3] == ["C7", "CLAV", "LANK"]
    assert md.missing_fraction == 0.0 and md.warnings == []
    # no X_SCREEN/Y_SCREEN in this file: up comes from the markers (heights 0-1.63 m along y)
    assert md.up_axis == "+y" and md.up_axis_source.startswith("inferred")
    assert md.reader == "ezc3d" and md.first_frame == 1


def test_opensim_hamner_trc():
    md = read_markers(shared("opensim_hamner_running.trc"))
    assert md.positions.shape == (600, 41, 3)
    assert md.rate_hz == 60.0 and md.units_found == "mm" and md.duration_s == pytest.approx(10.0)
    assert md.labelled and md.labels[0] == "R.ASIS" and md.residuals is None
    bicep = md.labels.index("L.Bicep")  # written as 0,0,0 in every frame
    assert not md.visible[:, bicep].any()
    assert md.visible[:, [i for i in range(41) if i != bicep]].all()
    assert md.up_axis == "+y"
    assert any("never visible" in w for w in md.warnings)


def test_btk_unlabeled_stream():
    md = read_markers(shared("btk_unlabeled_400hz.trc"))
    assert md.rate_hz == 400.0 and md.n_frames == 1313
    assert not md.labelled and all(is_placeholder_label(lab) for lab in md.labels)
    per_frame = md.visible.sum(axis=1)
    assert per_frame.min() == 3 and per_frame.max() == 27  # as documented in SOURCES.md
    assert md.n_markers == 37  # widest row: slots up to 37, blanks inside rows are missing slots
    assert any("not marker tracks" in w for w in md.warnings)
    assert md.up_axis == "+y"


def test_btk_pig_flatfoot_drops_model_outputs():
    path = shared("btk_pig_flatfoot_hole.c3d")
    md = read_markers(path)
    # 193 C3D points: 35 physical markers, 78 Plug-in Gait model points, 80 angles/forces/moments/powers.
    # The ~10 % gaps of this file are all in the angle/force/moment/power channels.
    assert md.n_markers == 35 and md.labels[:4] == ["LFHD", "RFHD", "LBHD", "RBHD"]
    assert md.missing_fraction == 0.0
    assert "LHipAngles" in md.dropped_points and "CentreOfMass" in md.dropped_points
    assert md.first_frame == 143 and md.up_axis == "+z" and "Y_SCREEN" in md.up_axis_source
    full = read_markers(path, keep_model_points=True)
    assert full.n_markers == 113 and "LFEO" in full.labels
    # raw C3D gap fraction over all 193 points is ~10 %
    c = ezc3d.c3d(str(path))
    assert 0.08 < np.isnan(c["data"]["points"][:3]).any(0).mean() < 0.12


def test_btk_gait_occluded():
    md = read_markers(shared("btk_gait_occluded.c3d"))
    assert md.n_markers == 33 and md.rate_hz == 100.0
    assert 0.55 < md.missing_fraction < 0.65
    assert md.up_axis == "+z"
    # EVa cut labels to 4 chars ('RKNE' twice); the full names come from DESCRIPTIONS
    assert "R.Knee.Medial" in md.labels and len(set(md.labels)) == 33
    vis = md.residuals[md.visible]
    assert (vis >= 0).all() and 0.1 < np.median(vis) < 5.0  # mm-sized residuals
    assert (md.residuals[~md.visible] < 0).all()


def test_c3d_package_fallback_gives_the_same_data():
    for path in [p for p in shared_files() if p.suffix == ".c3d"] or [pytest.skip("no shared C3D files")]:
        a = read_markers(path)
        with mock.patch.object(marker_c3d, "_read_with_ezc3d", side_effect=RuntimeError("refused")):
            b = read_markers(path)
        assert b.reader == "c3d" and "ezc3d refused" in b.warnings[0]
        assert a.labels == b.labels and a.rate_hz == b.rate_hz and a.first_frame == b.first_frame
        assert np.array_equal(a.visible, b.visible)
        np.testing.assert_allclose(a.positions[a.visible], b.positions[b.visible], atol=1e-6)
        np.testing.assert_allclose(a.residuals, b.residuals, atol=1e-6)


# ----------------------------------------------------------------------------------- round trips


def test_write_c3d_round_trip_ours_and_ezc3d(tmp_path):
    pos = synthetic_body(T=50, M=12)
    rng = np.random.default_rng(1)
    pos[rng.random(pos.shape[:2]) < 0.1] = np.nan
    path = write_c3d(tmp_path / "m.c3d", pos, 65.036, up_axis="+z")
    md = read_markers(path)
    assert md.rate_hz == 65.036 and md.units_found == "mm"
    assert md.up_axis == "+z" and "Y_SCREEN" in md.up_axis_source
    assert not md.labelled and md.labels[0] == "M001"
    assert np.array_equal(np.isnan(md.positions), np.isnan(pos))
    vis = ~np.isnan(pos)
    tol = 1e-6 * np.abs(pos[vis]) + 1e-9  # float32 millimetres
    assert np.all(np.abs(md.positions[vis] - pos[vis]) <= tol)
    # ezc3d directly: mm, NaN where missing, residual -1
    c = ezc3d.c3d(str(path))
    ez = c["data"]["points"][:3].transpose(2, 1, 0) / 1000.0
    assert np.array_equal(np.isnan(ez), np.isnan(pos))
    np.testing.assert_array_equal(ez[vis], md.positions[vis])
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c["parameters"]["POINT"]["Y_SCREEN"]["value"] == ["+Z"]
    miss = np.isnan(pos).any(-1)
    assert np.all(c["data"]["meta_points"]["residuals"][0].T[miss] == -1)
    # the raw bytes hold (0, 0, 0) for missing markers (read without ezc3d's NaN conversion)
    with mock.patch.object(marker_c3d, "_read_with_ezc3d", side_effect=RuntimeError("refused")):
        b = read_markers(path)
    assert np.array_equal(b.visible, md.visible)


def test_write_c3d_labels_and_y_up(tmp_path):
    pos = synthetic_body(T=30, M=5, up=1)
    labels = ["LASI", "RASI", "C7", "LKNE", "RKNE"]
    md = read_markers(write_c3d(tmp_path / "y.c3d", pos, 120.0, labels=labels, up_axis="+y"))
    assert md.labelled and md.labels == labels and md.up_axis == "+y" and md.warnings == []
    with pytest.raises(ValueError):
        write_c3d(tmp_path / "bad.c3d", pos, 120.0, labels=["a", "a", "b", "c", "d"])
    with pytest.raises(ValueError):
        write_c3d(tmp_path / "bad.c3d", pos, 0.0)


def test_write_trc_round_trip(tmp_path):
    pos = synthetic_body(T=40, M=6)
    pos[3:9, 2] = np.nan
    path = write_trc(tmp_path / "m.trc", pos, 100.0, labels=[f"P{i}" for i in range(6)], up_axis="+z")
    md = read_markers(path)
    assert md.labels == [f"P{i}" for i in range(6)] and md.labelled
    # OpenSim reads every TRC +y up (and rejects extra header keys): a +z capture is turned, x kept
    header = path.read_text().splitlines()[1].split("\t")
    assert len(header) == 8 and "UpAxis" not in header
    assert md.up_axis == "+y"
    assert np.array_equal(np.isnan(md.positions), np.isnan(pos))
    turned = np.stack([pos[..., 0], pos[..., 2], -pos[..., 1]], axis=-1)
    np.testing.assert_allclose(md.positions, turned, atol=1e-8)
    assert md.warnings == []


@pytest.mark.parametrize("up", ["+x", "-x", "+y", "-y", "+z", "-z"])
def test_to_y_up_turns_each_up_axis_onto_plus_y(up):
    from uuomocap.protocol.markerio import to_y_up

    r = to_y_up(up)
    axis = np.zeros(3)
    axis["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0
    np.testing.assert_allclose(r @ axis, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(r @ r.T, np.eye(3))
    assert np.isclose(np.linalg.det(r), 1.0)


# ----------------------------------------------------------------------------------- bad files


def test_truncated_c3d_is_an_error(tmp_path):
    src = write_c3d(tmp_path / "full.c3d", synthetic_body(T=200, M=20), 100.0)
    blob = src.read_bytes()
    for cut in (len(blob) // 2, len(blob) - 600, 1000, 300):  # (the last block is padding)
        bad = tmp_path / f"cut{cut}.c3d"
        bad.write_bytes(blob[:cut])
        with pytest.raises(MarkerFileError, match="truncated") as err:
            read_markers(bad)
        assert str(bad) in str(err.value) and "\n" not in str(err.value)


def test_garbage_and_unsupported_files(tmp_path):
    rng = np.random.default_rng(0)
    junk = tmp_path / "junk.c3d"
    junk.write_bytes(bytes([7, 1]) + rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(MarkerFileError, match="not a C3D file"):
        read_markers(junk)
    text = tmp_path / "notes.trc"
    text.write_text("hello\nworld\n")
    with pytest.raises(MarkerFileError, match="not a TRC file"):
        read_markers(text)
    other = tmp_path / "data.xyz"
    other.write_text("1 2 3\n")
    with pytest.raises(MarkerFileError, match="unsupported marker file type"):
        read_markers(other)
    empty = tmp_path / "empty.c3d"
    empty.write_bytes(b"")
    with pytest.raises(MarkerFileError, match="empty file"):
        read_markers(empty)
    with pytest.raises(MarkerFileError, match="no such file"):
        read_markers(tmp_path / "missing.c3d")


def test_sanity_errors(tmp_path):
    pos = synthetic_body(T=10, M=4) * 1000
    res = np.zeros((10, 4))
    with pytest.raises(MarkerFileError, match="unknown units 'furl'"):
        read_markers(make_c3d(tmp_path / "u.c3d", pos, res, "ABCD", units="furl"))
    with pytest.raises(MarkerFileError, match="every marker sample is missing"):
        read_markers(make_c3d(tmp_path / "n.c3d", pos, -np.ones((10, 4)), "ABCD"))
    with pytest.raises(MarkerFileError, match="zero frames"):
        read_markers(make_trc(tmp_path / "z.trc", {}, ["A"], []))
    with pytest.raises(MarkerFileError, match="absurd marker spread"):
        read_markers(make_c3d(tmp_path / "s.c3d", pos * 1e9, res, "ABCD"))


# ----------------------------------------------------------------------------------- quirks


def test_c3d_missing_encodings_units_prefixes_placeholders(tmp_path):
    T, M = 60, 8
    pos_m = synthetic_body(T=T, M=M)
    coords = pos_m * 1000.0
    res = np.full((T, M), 0.8)
    coords[5, 0] = 0.0  # zeros with a positive residual
    coords[6, 1] = np.nan  # NaN
    coords[7, 2] = 0.0  # zeros with residual -1 (the C3D convention)
    res[7, 2] = -1.0
    labels = [f"Subject:{n}" for n in ("LASI", "RASI", "C7", "T10")] + ["*12", "*13", "*14", "*15"]
    path = make_c3d(tmp_path / "q.c3d", coords, res, labels, params={("POINT", "X_SCREEN"): "+X", ("POINT", "Y_SCREEN"): "+Z"})
    md = read_markers(path)
    assert not md.visible[5, 0] and not md.visible[6, 1] and not md.visible[7, 2]
    assert md.visible.sum() == T * M - 3
    assert md.labels[:4] == ["LASI", "RASI", "C7", "T10"] and md.raw_labels[0] == "Subject:LASI"
    assert md.subjects == ["Subject"]
    assert md.placeholder.tolist() == [False] * 4 + [True] * 4
    assert any("non-negative residual" in w for w in md.warnings)
    assert any("4 of 8 labels are placeholders" in w for w in md.warnings)
    vis = md.visible
    np.testing.assert_allclose(md.positions[vis], pos_m[vis], atol=1e-6)
    # all placeholders: unlabeled
    md2 = read_markers(make_c3d(tmp_path / "u.c3d", coords, np.zeros((T, M)), [f"*{i}" for i in range(M)]))
    assert not md2.labelled


@pytest.mark.parametrize("units, factor", [("mm", 1000.0), ("cm", 100.0), ("mete", 1.0), ("m", 1.0), ("millimeters", 1000.0)])
def test_c3d_units(tmp_path, units, factor):
    pos_m = synthetic_body(T=20, M=6)
    md = read_markers(make_c3d(tmp_path / "u.c3d", pos_m * factor, np.zeros((20, 6)), "ABCDEF", units=units))
    assert md.units_found == units
    np.testing.assert_allclose(md.positions, pos_m, rtol=1e-6, atol=1e-7)


def test_units_that_lie_are_detected(tmp_path):
    pos_m = synthetic_body(T=20, M=6)
    md = read_markers(make_c3d(tmp_path / "lie.c3d", pos_m * 1000, np.zeros((20, 6)), "ABCDEF", units="m"))
    assert md.units_found == "m" and md.units_used == "mm"
    assert any("look like mm" in w for w in md.warnings)
    np.testing.assert_allclose(md.positions, pos_m, rtol=1e-6)


def test_non_integer_rate_and_inferred_up_axis(tmp_path):
    pos_m = synthetic_body(T=100, M=10, up=1)  # y up, no screen parameters
    md = read_markers(make_c3d(tmp_path / "r.c3d", pos_m * 1000, np.zeros((100, 10)), "ABCDEFGHIJ", rate=65.036))
    assert md.rate_hz == 65.036
    assert md.stamps_ns[1] == round(1e9 / 65.036)
    assert md.up_axis == "+y" and md.up_axis_source.startswith("inferred")
    # upside-down capture: z axis pointing down
    flipped = synthetic_body(T=100, M=10) * np.array([1.0, -1.0, -1.0])
    assert infer_up_axis(flipped)[0] == "-z"
    # a single arm (no clear vertical): not confident, falls back to the format default
    arm = np.random.default_rng(0).normal(0, 0.05, size=(50, 5, 3)) + 1.0
    assert infer_up_axis(arm)[0] is None
    md = read_markers(make_c3d(tmp_path / "arm.c3d", arm * 1000, np.zeros((50, 5)), "ABCDE"))
    assert md.up_axis == "+z" and md.up_axis_source.startswith("default")


def test_trc_wrong_header_blank_fields_and_cm(tmp_path):
    T = 30
    pos_m = synthetic_body(T=T, M=5)
    pos_m[4, 1] = np.nan
    pos_m[10:14, 3] = np.nan
    rows = trc_rows(pos_m * 100.0, 100.0)
    rows[20][2:5] = ["0", "0", "0"]  # zeros = missing as well
    rows[21][2:5] = ["NaN", "nan", "NaN"]
    rows[22] = rows[22][:-3]  # variable width: last marker absent, row cut short
    rows[23] = rows[23] + [""]  # trailing tab
    path = make_trc(tmp_path / "w.trc", {"NumMarkers": "7", "Units": "cm", "NumFrames": "31"}, [f"N{i}" for i in range(5)], rows)
    md = read_markers(path)
    assert md.n_markers == 5 and md.n_frames == T and md.units_found == "cm"
    assert any("NumMarkers=7" in w for w in md.warnings)
    assert any("NumFrames=31" in w for w in md.warnings)
    expected = ~np.isnan(pos_m).any(-1)
    expected[20, 0] = expected[21, 0] = expected[22, 4] = False
    assert np.array_equal(md.visible, expected)
    np.testing.assert_allclose(md.positions[expected], pos_m[expected], atol=1e-6)
    assert md.up_axis == "+z"  # inferred (z up data), overriding the TRC default +y


def test_trc_mete_units_and_rate_from_time_column(tmp_path):
    pos_m = synthetic_body(T=25, M=4)
    rows = trc_rows(pos_m, 50.0, fmt="{:.6f}")
    path = make_trc(tmp_path / "m.trc", {"Units": "mete", "DataRate": "x"}, ["A", "B", "C", "D"], rows, rate="x")
    md = read_markers(path)
    assert md.units_used == "m" and md.rate_hz == pytest.approx(50.0)
    assert any("Time column" in w for w in md.warnings)
    np.testing.assert_allclose(md.positions, pos_m, atol=1e-6)


def test_trc_truncated_last_line_is_dropped(tmp_path):
    pos_m = synthetic_body(T=20, M=4)
    path = make_trc(tmp_path / "t.trc", {}, ["A", "B", "C", "D"], trc_rows(pos_m * 1000, 100.0))
    blob = path.read_text()
    path.write_text(blob[: len(blob) - 30])  # cut mid-row, no final newline
    md = read_markers(path)
    assert md.n_frames == 19 and any("incomplete" in w for w in md.warnings)


def test_parse_units_and_placeholders():
    assert parse_units("mete") == "m" and parse_units("mm") == "mm" and parse_units(" CM ") == "cm"
    assert parse_units("mill") == "mm" and parse_units("cent") == "cm" and parse_units("furlong") is None
    for lab in ("*12", "M001", "Unnamed", "unlabeled 1004", "Marker3", "", "17"):
        assert is_placeholder_label(lab), lab
    for lab in ("LASI", "C7", "R.Knee.Medial", "M1", "T10"):
        assert not is_placeholder_label(lab), lab


# ----------------------------------------------------------------------------------- CLI


def test_cli_markers_info(tmp_path, capsys):
    path = write_c3d(tmp_path / "m.c3d", synthetic_body(T=20, M=5), 120.0)
    assert main(["markers", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 20 and info["markers"] == 5 and info["rate_hz"] == 120.0
    assert info["units_found"] == "mm" and info["up_axis"] == "+z" and info["labelled"] is False
    assert main(["markers", "info", str(path)]) == 0
    assert "frames:" in capsys.readouterr().out


def test_cli_markers_info_bad_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"\x02\x50" + b"\x00" * 100)
    assert main(["markers", "info", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("uuomocap: error:") and "\n" not in err and "truncated" in err
    assert main(["markers", "info", str(tmp_path / "nope.trc")]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize("path", shared_files(), ids=lambda p: p.name)
def test_cli_markers_info_shared(path, capsys):
    assert main(["markers", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] > 0 and info["markers"] > 0 and info["up_axis_source"]
