"""Video body prior: BlazePose pre/post-processing, the default estimator on a real clip,
a user's HMR-class ONNX model, 4D-Humans/PHALP import, video stamps and prior.npz."""

from __future__ import annotations

import json
import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch

from uuomocap.solver_core import blazepose as bp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
VIDEO = DATA / "video" / "person_running_320x240.mp4"


@pytest.fixture(scope="module")
def pose_models():
    from uuomocap.model_fetch import ModelFetchError, ensure_pose_models

    try:
        return ensure_pose_models(log=lambda msg: None)
    except (ModelFetchError, OSError) as exc:
        pytest.skip(f"pose models cannot be fetched here: {exc}")


def _need_video():
    if not VIDEO.is_file():
        pytest.skip(f"test video absent: {VIDEO}")


# ----------------------------------------------------------------------------- pure processing
def test_ssd_anchor_layout():
    anchors = bp.ssd_anchors()
    assert anchors.shape == (2254, 2)
    # stride 8: 28x28 cells x 2 anchors, first cell centre (0.5/28, 0.5/28), both anchors share it
    np.testing.assert_allclose(anchors[0], [0.5 / 28, 0.5 / 28], atol=1e-7)
    np.testing.assert_allclose(anchors[1], anchors[0])
    np.testing.assert_allclose(anchors[2], [1.5 / 28, 0.5 / 28], atol=1e-7)
    # stride 32 grid (7x7) carries 6 anchors per cell, last one at the bottom-right cell
    np.testing.assert_allclose(anchors[-6:], np.tile([6.5 / 7, 6.5 / 7], (6, 1)), atol=1e-6)
    assert (anchors >= 0).all() and (anchors <= 1).all()


def test_decode_detections_letterbox_and_weighted_nms():
    anchors = bp.ssd_anchors()
    raw = np.zeros((2254, 12), np.float32)
    scores = np.full(2254, -10.0, np.float32)
    # Two overlapping hits on neighbouring anchors (merged by NMS) and one far away, weaker.
    for i, (dx, logit) in {500: (2.0, 3.0), 501: (-2.0, 1.0), 100: (0.0, 0.5)}.items():
        raw[i, 0] = dx
        raw[i, 2:4] = 40.0  # 40 input pixels wide/tall
        raw[i, 4:6] = [0.0, 0.0]  # keypoint 0 at the anchor centre
        raw[i, 6:8] = [0.0, -30.0]  # keypoint 1 above it
        scores[i] = logit
    # 640x320 image -> scale 0.35, 56 pixel bars top and bottom
    letterbox = bp.letterbox_transform(640, 320)
    assert letterbox == pytest.approx((0.35, 0.0, 56.0))
    dets = bp.decode_detections(raw, scores, anchors, letterbox)
    assert len(dets) == 2
    best = dets[0]
    w = 1 / (1 + np.exp(-3.0)), 1 / (1 + np.exp(-1.0))
    mean_dx = (2.0 * w[0] - 2.0 * w[1]) / (w[0] + w[1])
    expect_cx = ((anchors[500, 0] * 224 + mean_dx) - 0.0) / 0.35
    assert best.score == pytest.approx(w[0], rel=1e-6)
    assert (best.box[0] + best.box[2]) / 2 == pytest.approx(expect_cx, rel=1e-5)
    assert best.box[2] - best.box[0] == pytest.approx(40 / 0.35, rel=1e-5)
    roi = bp.roi_from_detection(best)
    assert roi.rotation == pytest.approx(0.0, abs=1e-9)  # kp1 straight above kp0
    assert roi.size == pytest.approx(2 * (30 / 0.35) * 1.25, rel=1e-5)


def test_roi_crop_geometry_and_rotation():
    roi = bp.roi_from_points(np.array([100.0, 80.0]), np.array([130.0, 80.0]))  # scale point to the right
    assert roi.rotation == pytest.approx(np.pi / 2)
    m = bp.roi_crop_matrix(roi, 256)
    # crop centre (pixel-centre coordinate 127.5) -> ROI centre (pixel-centre coordinate cx - 0.5)
    centre = m @ np.array([127.5, 127.5, 1.0])
    np.testing.assert_allclose(centre, [99.5, 79.5], atol=1e-9)
    # "up" in the crop points towards the scale point in the image
    up = m[:, :2] @ np.array([0.0, -1.0])
    assert up[0] > 0 and abs(up[1]) < 1e-9
    # a landmark decoded at the top-centre of the crop lands on that side of the image
    raw = np.zeros((39, 5))
    raw[:, 0], raw[:, 1] = 128.0, 0.0
    res = bp.decode_landmarks(raw.ravel(), 1.0, None, np.tile([0.0, -1.0, 0.0], 39), roi)
    np.testing.assert_allclose(res.image[0, :2], [100 + roi.size / 2, 80], atol=1e-6)
    np.testing.assert_allclose(res.world[0], [1.0, 0.0, 0.0], atol=1e-9)  # world "up" rotated likewise


def test_heatmap_refinement_moves_to_peak():
    hm = np.full((64, 64, 39), -20.0, np.float32)
    hm[30, 40, 0] = 10.0  # landmark 0: peak at column 40, row 30
    xy = np.tile([[0.6, 0.45]], (39, 1))  # near the peak, within the 7x7 window
    out = bp.refine_with_heatmap(xy, hm)
    np.testing.assert_allclose(out[0], [(40 + 0.5) / 64, (30 + 0.5) / 64], atol=1e-6)
    np.testing.assert_allclose(out[1:], xy[1:])  # no confident peak -> unchanged


# ----------------------------------------------------------------------------- converted models
def test_converted_onnx_models_match_tflite_reference(pose_models):
    """Our TFLite->ONNX conversion reproduces the TFLite interpreter (reference values measured
    once with ai-edge-litert 2.3 on the clip's first frame, plain INTER_AREA resize)."""
    _need_video()
    import cv2

    from uuomocap.solver_core.pose_estimators import make_session

    ok, bgr = cv2.VideoCapture(str(VIDEO)).read()
    assert ok
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    det = make_session(pose_models.detector)
    x = (cv2.resize(rgb, (224, 224), interpolation=cv2.INTER_AREA).astype(np.float32) / 127.5 - 1)[None]
    boxes, scores = det.run(["Identity", "Identity_1"], {det.get_inputs()[0].name: x})
    best = int(np.argmax(scores.ravel()))
    assert best == 417 and scores.ravel()[best] == pytest.approx(3.7159374, abs=2e-3)
    np.testing.assert_allclose(boxes[0, best], [-1.618824, -1.770567, 44.725056, 44.72499, -6.686168, 44.826817,
                                                0.726942, -15.262758, -4.797709, 6.115647, 1.089903, -40.680923],
                               atol=2e-3)
    lm = make_session(pose_models.landmark)
    x = (cv2.resize(rgb, (256, 256), interpolation=cv2.INTER_AREA).astype(np.float32) / 255)[None]
    land, flag, heat, world = lm.run(["Identity", "Identity_1", "Identity_3", "Identity_4"],
                                     {lm.get_inputs()[0].name: x})
    np.testing.assert_allclose(land[0, :10], [121.47266, 60.864532, -12.787178, 5.229393, 6.519107, 119.77415,
                                              57.898407, -7.777757, 4.577803, 6.722958], atol=2e-3)
    assert flag.ravel()[0] == pytest.approx(0.99993, abs=1e-4)
    np.testing.assert_allclose(world[0, :6], [0.179382, -0.650522, -0.040599, 0.162918, -0.690975, -0.028388],
                               atol=1e-4)
    np.testing.assert_allclose(heat[0, 32, 32, :4], [-26.826332, -33.17326, -32.22712, -29.550203], atol=2e-3)
    assert [o.name for o in lm.get_outputs()] == ["Identity", "Identity_1", "Identity_3", "Identity_4"]  # no mask


# ----------------------------------------------------------------------------- default estimator
def test_blazepose_prior_on_real_video(pose_models, tmp_path, capsys):
    _need_video()
    from uuomocap.cli import main
    from uuomocap.protocol.prior_file import read_prior_npz

    torch.set_num_threads(1)
    out = tmp_path / "prior.npz"
    rc = main(["prior", str(VIDEO), "--out", str(out), "--json"])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert info["detection_rate"] >= 0.95, info
    for bone, sym in info["bone_symmetry"].items():
        assert sym["rel_diff"] < 0.10, (bone, sym)
    assert info["fit_residual_mm_median"] < 60
    prior = read_prior_npz(out)
    n = len(prior["stamps_ns"])
    assert n == 90 and prior["valid"].mean() >= 0.95
    assert prior["camera_frame"] and str(prior["body_model"]) == "open-low"
    assert prior["betas"].shape[0] == n and prior["keypoints3d"].shape == (n, 33, 3)
    assert prior["stamps_ns"][1] - prior["stamps_ns"][0] == 33_333_333
    # The runner is upright in the OpenCV camera frame: body up (+Y) maps to image up (-y).
    from uuomocap.solver_core.rotations import axis_angle_to_matrix

    rot = axis_angle_to_matrix(torch.from_numpy(prior["global_orient"][prior["valid"]].astype(np.float64)))
    body_up = rot[:, :, 1].numpy()
    assert np.median(body_up[:, 1]) < -0.8
    # fitted pose is a real pose (legs bent while running), not the rest pose
    assert np.abs(prior["body_pose"]).max() > 0.3


# ----------------------------------------------------------------------------- user HMR model
class _TinyHmr(torch.nn.Module):
    """Outputs fixed rotations in the chosen layout, plus betas that depend on the crop."""

    def __init__(self, layout: str, root: np.ndarray, joint: np.ndarray):
        super().__init__()
        self.layout = layout
        self.register_buffer("root", torch.tensor(root, dtype=torch.float32))
        self.register_buffer("joint", torch.tensor(joint, dtype=torch.float32))
        self.conv = torch.nn.Conv2d(3, 10, 16, stride=16)

    def _as(self, mat: torch.Tensor, n: int, count: int) -> torch.Tensor:
        from uuomocap.solver_core.rotations import matrix_to_axis_angle

        if self.layout == "matrix":
            out = mat.expand(n, count, 3, 3)
        elif self.layout == "6d":
            out = mat[..., :2].transpose(-1, -2).reshape(1, 1, 6).expand(n, count, 6)
        else:
            out = matrix_to_axis_angle(mat[None])[0].reshape(1, 1, 3).expand(n, count, 3)
        return out

    def forward(self, image):
        n = image.shape[0]
        betas = self.conv(image).mean((2, 3))
        return self._as(self.root, n, 1), self._as(self.joint, n, 23), betas, betas[:, :3]


def _rot(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch's legacy (TorchScript) ONNX exporter
@pytest.mark.parametrize("layout", ["matrix", "6d", "axis_angle"])
def test_onnx_hmr_estimator_with_tiny_exported_model(pose_models, tmp_path, layout):
    _need_video()
    from uuomocap.video_prior_run import estimate_prior, parse_estimator

    torch.set_num_threads(1)
    root, joint = _rot([1, 0, 0], np.pi * 0.9), _rot([0, 1, 1], 0.4)
    model = _TinyHmr(layout, root, joint).eval()
    path = tmp_path / f"hmr_{layout}.onnx"
    torch.onnx.export(model, torch.zeros(1, 3, 256, 256), str(path), input_names=["image"],
                      output_names=["pred_smpl_params/global_orient", "body_pose", "betas", "pred_cam"],
                      dynamo=False, dynamic_axes={"image": {0: "N"}})
    prior, info = estimate_prior(VIDEO, parse_estimator(f"onnx-hmr:{path}"), max_frames=8, log=lambda m: None)
    assert info["detection_rate"] == 1.0 and len(prior.valid) == 8
    from uuomocap.solver_core.rotations import axis_angle_to_matrix

    got_root = axis_angle_to_matrix(torch.from_numpy(prior.global_orient.astype(np.float64))).numpy()
    got_joint = axis_angle_to_matrix(torch.from_numpy(prior.body_pose.astype(np.float64))).numpy()
    np.testing.assert_allclose(got_root, np.broadcast_to(root, got_root.shape), atol=1e-4)
    np.testing.assert_allclose(got_joint, np.broadcast_to(joint, got_joint.shape), atol=1e-4)
    assert prior.betas.shape == (8, 10) and np.ptp(prior.betas[:, 0]) > 0  # betas follow the crops
    assert prior.body_model == "smpl"
    # the live path (the video_prior node's) gives the same frames, one message per frame
    from uuomocap.protocol.video import video_source
    from uuomocap.solver_core.video_prior import StreamingVideoPrior

    live = StreamingVideoPrior(f"onnx-hmr:{path}", pose_models.detector, pose_models.landmark)
    with video_source(VIDEO) as src:
        frames = [f for i in range(8) for f in live.push(i, src.read().rgb())]
    assert [f.key for f in frames] == list(range(8)) and live.flush() == [] and live.body_model == "smpl"
    np.testing.assert_allclose(np.stack([f.body_pose for f in frames]), prior.body_pose, atol=1e-5)
    np.testing.assert_allclose(np.stack([f.global_orient for f in frames]), prior.global_orient, atol=1e-5)
    np.testing.assert_allclose(np.stack([f.betas for f in frames]), prior.betas, atol=1e-5)


def test_the_live_prior_holds_the_last_fit_through_frames_without_a_person(pose_models):
    """StreamingVideoPrior (BlazePose + batched fit): frames come out in order, a frame without a
    person carries valid=False, confidence 0 and the last fitted body (zeros before any fit)."""
    _need_video()
    from uuomocap.protocol.video import video_source
    from uuomocap.solver_core.video_prior import StreamingVideoPrior

    torch.set_num_threads(1)
    live = StreamingVideoPrior("blazepose", pose_models.detector, pose_models.landmark, "open-low", batch_frames=4)
    black = np.zeros((240, 320, 3), np.uint8)
    with video_source(VIDEO) as src:
        images = [black] + [src.read().rgb() for _ in range(6)] + [black]
    out = []
    for i, image in enumerate(images):
        out += live.push(i, image)
        assert live.person_found == (0 < i < 7)
    assert [f.key for f in out] == [0, 1, 2, 3, 4, 5, 6, 7]  # the black frame ends the batch early
    out += live.flush()
    assert len(out) == 8 and live.body_model == "open-low"
    first, last = out[0], out[7]
    assert not first.valid and first.confidence == 0.0 and first.keypoints3d is None
    assert not np.any(first.body_pose) and not np.any(first.global_orient)
    assert all(f.valid and f.confidence > 0.5 and f.keypoints3d.shape == (33, 3) for f in out[1:7])
    assert not last.valid and last.confidence == 0.0
    np.testing.assert_array_equal(last.body_pose, out[6].body_pose)  # held, not reset
    assert np.abs(out[6].body_pose).max() > 0.05  # a fitted runner, not the rest pose
    with pytest.raises(ValueError, match="not 'blazepose' or 'onnx-hmr"):
        StreamingVideoPrior("openpose", pose_models.detector, pose_models.landmark)


def test_hmr_crop_box_aspect():
    from uuomocap.solver_core.pose_estimators import hmr_crop_box, hmr_input

    centre, side = hmr_crop_box(np.array([10.0, 20.0, 40.0, 220.0]))  # tall: 30 x 200
    np.testing.assert_allclose(centre, [25, 120])
    assert side == pytest.approx(200)
    _, side = hmr_crop_box(np.array([0.0, 0.0, 300.0, 100.0]))  # wide: 300 -> height 400
    assert side == pytest.approx(400)
    img = np.full((240, 320, 3), 255, np.uint8)
    x = hmr_input(img, np.array([160.0, 120.0]), 100.0)
    assert x.shape == (1, 3, 256, 256) and x.dtype == np.float32
    np.testing.assert_allclose(x[0, :, 128, 128], (1 - np.array([0.485, 0.456, 0.406])) / [0.229, 0.224, 0.225],
                               rtol=1e-5)


# ----------------------------------------------------------------------------- PHALP import
def _smpl(seed: int):
    rng = np.random.default_rng(seed)
    return {"global_orient": _rot(rng.normal(size=3), 1.0)[None].astype(np.float32),
            "body_pose": np.stack([_rot(rng.normal(size=3), 0.3) for _ in range(23)]).astype(np.float32),
            "betas": rng.normal(size=10).astype(np.float32)}


def _phalp_frames():
    """Track 7 seen in frames 0-4 (slot order changes), track 3 in 0,1,2,4, carried (tracked_time 2) in 3."""
    frames = {}
    for f in range(5):
        tids = [7, 3] if f % 2 == 0 else [3, 7]
        frames[f"{f:06d}.jpg"] = {
            "tid": tids,
            "tracked_time": [0 if (t == 7 or f != 3) else 2 for t in tids],
            "tracked_ids": [3, 7],  # NOT aligned with smpl
            "bbox": [np.array([t, f, 10, 20], np.float32) for t in tids],
            "smpl": [_smpl(100 * t + f) for t in tids],
            "camera": [np.array([0, 0, 10.0 + t]) for t in tids],
            "3d_joints": [np.full((45, 3), t, np.float32) for t in tids],
            "conf": [0.9, 0.8],
        }
    return frames


def test_phalp_import_pairs_by_tid(tmp_path):
    joblib = pytest.importorskip("joblib")
    from uuomocap.solver_core.phalp_import import load_phalp_pickle, phalp_track
    from uuomocap.solver_core.video_prior import prior_from_smpl_rotations

    frames = _phalp_frames()
    for compress in (0, 3):
        path = tmp_path / f"phalp_{compress}.pkl"
        joblib.dump(frames, path, compress=compress)
        data = load_phalp_pickle(path)
        track = phalp_track(data)  # default: the longest track
        assert track.track_id == 7 and track.track_lengths == {7: 5, 3: 4}
        for f in range(5):
            np.testing.assert_allclose(track.betas[f], _smpl(700 + f)["betas"], rtol=1e-6)
            np.testing.assert_allclose(track.global_orient[f], _smpl(700 + f)["global_orient"][0], rtol=1e-6)
        assert (track.bbox[:, 0] == 7).all() and (track.camera[:, 2] == 17).all()
        other = phalp_track(data, track_id=3)
        assert other.valid.tolist() == [True, True, True, False, True]  # carried, not seen, in frame 3
        np.testing.assert_allclose(other.betas[4], _smpl(304)["betas"], rtol=1e-6)
    prior = prior_from_smpl_rotations(other.global_orient, other.body_pose, other.betas, other.valid,
                                      other.confidence, np.arange(5) * 33_333_333, 30.0, "phalp")
    assert prior.valid.tolist() == [True, True, True, False, True] and prior.confidence[3] == 0
    np.testing.assert_allclose(prior.betas[3], prior.betas[2])  # filled from the nearest valid frame
    from uuomocap.solver_core.rotations import axis_angle_to_matrix

    back = axis_angle_to_matrix(torch.from_numpy(prior.body_pose[4])).numpy()
    np.testing.assert_allclose(back, _smpl(304)["body_pose"], atol=1e-5)


def test_phalp_pickle_with_reduce_payload_is_refused(tmp_path):
    import pickle

    from uuomocap.solver_core.phalp_import import PhalpFormatError, load_phalp_pickle

    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    frames = _phalp_frames()
    frames["000000.jpg"]["extra"] = Payload()
    path = tmp_path / "evil.pkl"
    with open(path, "wb") as fh:
        pickle.dump(frames, fh, protocol=4)
    with pytest.raises(PhalpFormatError, match="system"):
        load_phalp_pickle(path)
    assert not marker.exists()


def test_phalp_cli_import(tmp_path, capsys):
    _need_video()
    joblib = pytest.importorskip("joblib")
    from uuomocap.cli import main

    path = tmp_path / "phalp.pkl"
    joblib.dump(_phalp_frames(), path, compress=3)
    out = tmp_path / "prior.npz"
    assert main(["prior", str(VIDEO), "--out", str(out), "--estimator", f"phalp:{path}#3", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["track_id"] == 3 and info["frames_with_person"] == 4 and "warning" in info  # 5 vs 90 frames
    with np.load(out) as z:
        assert z["valid"].tolist() == [True, True, True, False, True]
    assert main(["prior", str(VIDEO), "--out", str(out), "--estimator", f"phalp:{path}#99"]) == 2


# ----------------------------------------------------------------------------- video + files
def test_video_stamps_ntsc_and_clock_offset(tmp_path):
    from uuomocap.protocol.video import exact_rate, index_stamp_ns, session_video_settings, to_marker_clock

    assert exact_rate(29.97002997) == Fraction(30000, 1001)
    assert exact_rate(30.0) == 30 and exact_rate(25.0) == 25
    assert int(index_stamp_ns(9000, Fraction(30000, 1001))) == 300_300_000_000  # not 300 s
    assert index_stamp_ns(np.arange(3), Fraction(30)).tolist() == [0, 33_333_333, 66_666_667]
    (tmp_path / "session.yaml").write_text("format: uuomocap-session/1\nvideo: {file: video.mp4, rate_hz: 29.97, "
                                           "clock_offset_s: -0.25}\n")
    settings = session_video_settings(tmp_path)
    assert settings["clock_offset_s"] == -0.25 and settings["path"].endswith("video.mp4")
    assert to_marker_clock(np.array([1_000_000_000]), -0.25).tolist() == [750_000_000]


def test_video_source_reads_frames():
    _need_video()
    from uuomocap.protocol.video import VideoError, video_source

    with video_source(VIDEO) as src:
        assert (src.width, src.height, src.frame_count, src.rate_hz) == (320, 240, 90, 30.0)
        frames = [src.read() for _ in range(3)]
    assert [f.stamp_ns for f in frames] == [0, 33_333_333, 66_666_667]
    assert frames[0].image_bgr.shape == (240, 320, 3) and frames[0].rgb()[0, 0, 0] == frames[0].image_bgr[0, 0, 2]
    with pytest.raises(VideoError, match="not found"):
        video_source(VIDEO.with_name("missing.mp4"))


def test_a_live_source_hands_a_slow_reader_the_newest_frame():
    """latest_only (live sources' default): a thread grabs frames as they come; a reader slower
    than the source gets the newest frame, not the driver's backlog, and the ones it never saw are
    counted (the file stands in for a camera: its thread reads it as fast as it decodes)."""
    _need_video()
    import time

    from uuomocap.protocol.video import video_source

    with video_source(VIDEO, latest_only=True) as video:
        first = video.read()
        time.sleep(1.0)  # the estimator busy: meanwhile the source went on
        later = video.read()
        rest = list(iter(video.read, None))
    read = [first, later, *rest]
    assert first.arrival_ns > 0 and later.index > first.index + 1 and later.arrival_ns > first.arrival_ns
    assert all(b.index > a.index for a, b in zip(read, read[1:]))  # newer each time, then the end
    assert video.dropped + len(read) == 90  # every frame of the file either read or counted as dropped
    with video_source(VIDEO) as video:  # a file otherwise: every frame, in order, no grab thread
        assert [f.index for f in video][:5] == [0, 1, 2, 3, 4] and video.dropped == 0


def test_live_sources_that_cannot_be_opened_say_which_and_why():
    """A camera index or a stream URL is a live source; when it cannot be opened the error names it
    (the live graphs' video:= argument; the node fails its setup with this message)."""
    from uuomocap.protocol.video import VideoError, is_live_source, is_stream_url, video_source

    assert is_live_source(0) and is_live_source("7") and is_live_source("rtsp://10.0.0.7:8554/live")
    assert is_stream_url("http://10.0.0.7:8080/video") and not is_stream_url("file:///tmp/a.mp4") and not is_live_source("a.mp4")
    with pytest.raises(VideoError, match="camera 63 .no such camera"):
        video_source(63)
    with pytest.raises(VideoError, match=r"rtsp://127.0.0.1:9/none \(unreachable"):
        video_source("rtsp://127.0.0.1:9/none")  # nothing listens on the discard port


def test_prior_file_validation(tmp_path):
    from uuomocap.protocol.prior_file import PriorFileError, read_prior_npz, write_prior_npz

    n = 4
    arrays = {"rate_hz": np.asarray(30.0), "stamps_ns": np.arange(n, dtype=np.int64) * 33_333_333,
              "global_orient": np.zeros((n, 3)), "body_pose": np.zeros((n, 23, 3)), "betas": np.zeros((n, 10)),
              "valid": np.ones(n, bool), "confidence": np.ones(n), "camera_frame": np.asarray(True),
              "body_model": np.asarray("open-low")}
    path = write_prior_npz(tmp_path / "prior.npz", arrays)
    assert set(read_prior_npz(path)) == set(arrays)
    with pytest.raises(PriorFileError, match="body_pose"):
        write_prior_npz(tmp_path / "bad.npz", {**arrays, "body_pose": np.zeros((n, 24, 3))})
    with pytest.raises(PriorFileError, match="global_orient holds NaN"):
        write_prior_npz(tmp_path / "bad.npz", {**arrays, "global_orient": np.full((n, 3), np.nan)})


# ----------------------------------------------------------------------------- streaming node
def test_video_prior_node_publishes_body_priors(pose_models, tmp_path):
    """video_prior (BlazePose + batched streaming fit) -> recorder, started by the launcher."""
    _need_video()
    import subprocess
    import sys

    from uuomocap.nodes.base import discover_plugins
    from uuomocap.protocol.recording import iter_recording

    if {"video_prior", "recorder"} - set(discover_plugins()):
        pytest.skip("node plugins not installed (pip install -e .)")
    launch = tmp_path / "video_prior_test.yaml"
    launch.write_text(
        "description: video prior -> recorder\nargs:\n  video: {}\n  out: {}\nnodes:\n"
        "  - name: video_prior\n    plugin: video_prior\n"
        "    params: {video: $(arg video), speed: 0, max_frames: 20, batch_frames: 8, clock_offset_s: 0.5}\n"
        "    on_exit: shutdown\n"
        "  - name: recorder\n    plugin: recorder\n    params: {out: $(arg out), topics: [body/prior]}\n")
    out = tmp_path / "prior.mcap"
    cmd = [sys.executable, "-m", "uuomocap.cli", "launch", "--log-dir", str(tmp_path), "--timeout", "90",
           str(launch), f"video:={VIDEO}", f"out:={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    logs = "".join(f"--- {p.name}\n{p.read_text()}" for p in sorted(tmp_path.glob("*.log")))
    assert proc.returncode == 0, proc.stderr + logs
    msgs = [r.decode().message for r in iter_recording(out)]
    priors = [m for m in msgs if type(m).__name__ == "BodyPrior"]
    assert [p.frame_index for p in priors] == list(range(20))
    assert all(p.valid and p.camera_frame and p.body_model == "open-low" for p in priors)
    assert priors[3].video_stamp_ns == 100_000_000 and priors[3].stamp_ns == 600_000_000
    assert priors[0].keypoints3d.shape == (33, 3) and priors[0].body_pose.shape == (23, 3)
    up = np.stack([bp_up(p.global_orient) for p in priors])
    assert np.median(up[:, 1]) < -0.8  # upright runner: body up is image up (-y)


def bp_up(axis_angle: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(axis_angle, np.float64))[0][:, 1]
