"""A session from a real LABELED capture (``uuomocap sample from-capture FILE DIR``): real markers,
labels taken away, against the labelled fit as the reference.

Generated sessions place markers on the body model itself, so they cannot show what real capture
does to the solver: skin and clothing moving over the bones (a thigh marker wanders 15-20 mm
about any fixed body point), markers set by a lab's protocol (Plug-in Gait, OpenSim's) rather
than at random, real gaps, real noise. Here the markers are the file's own:

  labeled marker file -> labeled IK (``solver_core.labeled_fit``: each label one fixed surface
  point, the body fitted to every frame; the MoSh++ role in the paper's real-data tables)
  = the reference motion (gt.npz) -> the same camera, simulated video prior and rendered video
  as ``sample make`` (``synth.camera_prior_video``) -> the real markers, Z-up, in a seeded random
  column order, labels replaced by placeholders -> session files.

Scores against this reference measure agreement with a labelled solve of the same markers (the
paper's protocol on real data), not error against the true skeleton, which nobody has.  The
reference's own per-frame marker RMS is kept in gt.npz (``reference_rms_mm``) and in
provenance: a solver cannot be expected to agree with it to better than that.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from uuomocap.synth import SampleConfig, _rng, camera_prior_video

GENERATOR = "uuomocap sample from-capture"
GENERATOR_VERSION = 2  # 2: frames without markers at the take's ends left out
# a frame belongs to the take once this many of its labels are seen
MIN_TAKE_MARKERS = 3


def make_capture_session(marker_file: str | Path, out_dir: str | Path, cfg: SampleConfig,
                         frames: tuple[int | None, int | None] = (None, None), progress=None) -> dict:
    """Write a session built from a labeled capture into ``out_dir``; returns a summary dict.

    cfg: the camera / prior / video fields and the seed (its motion, layout and marker fields are
    not used: the capture decides them); frames: (A, B) slice of frame indices; progress: optional
    callable(stage) as each stage starts.  Raises ValueError for a file that is not labeled or has
    too little to fit.
    """
    import torch

    from uuomocap.protocol.markerio import read_markers
    from uuomocap.protocol.session import save_session
    from uuomocap.solver_core.body_model import load_body_model
    from uuomocap.solver_core.labeled_fit import LabeledFitConfig, fit_labeled_markers, motion_arrays, summarise_rms
    from uuomocap.solver_core.lbs import forward
    from uuomocap.solver_core.marker_sim import MARKER_OFFSET_M
    from uuomocap.solver_core.motions import Motion, canonical_to_world

    def stage(name):
        if progress is not None:
            progress(name)

    marker_file, out_dir = Path(marker_file), Path(out_dir)
    stage("read")
    md = read_markers(marker_file)
    if not md.labelled:
        raise ValueError(f"{marker_file}: the markers are not labeled (placeholder names); a reference needs labels")
    first = range(md.n_frames)[slice(*frames)].start if md.n_frames else 0
    positions, visible = md.positions[slice(*frames)], md.visible[slice(*frames)]
    # the take is where markers are: a file's leading / trailing frames with (almost) none (a gait
    # trial's walk into and out of the volume) have no reference to score against - the labelled
    # fit there is the smoothness term's extrapolation, 100-170 mm from any video prior's guess
    seen = np.flatnonzero(visible.sum(axis=1) >= MIN_TAKE_MARKERS)
    if seen.size:
        positions, visible = positions[seen[0]:seen[-1] + 1], visible[seen[0]:seen[-1] + 1]
        first += int(seen[0])
    if positions.shape[0] < 2:
        raise ValueError(f"frames {frames[0]}:{frames[1]} of {md.n_frames} hold {positions.shape[0]} frame(s) with "
                         f">= {MIN_TAKE_MARKERS} markers seen; need at least 2")
    rate = float(md.rate_hz)

    stage("reference")
    model = load_body_model(cfg.body_model)
    fit = fit_labeled_markers(positions, visible, rate, md.up_axis, model, md.labels, config=LabeledFitConfig())
    ref = motion_arrays(model, fit, md.up_axis, rate, cfg.body_model, md.labels)  # Z-up, as AMASS
    betas = ref["betas"]
    motion = Motion(marker_file.stem, ref["poses"], ref["trans"], rate, "+z", betas, {"source": marker_file.name})
    with torch.no_grad():
        out = forward(model, torch.as_tensor(betas, dtype=torch.float32).reshape(1, -1),
                      torch.as_tensor(motion.poses, dtype=torch.float32), torch.as_tensor(motion.trans, dtype=torch.float32))
    joints = out.joints.double().numpy()

    stage("markers")
    # the markers in the reference's Z-up world (motion_arrays turned the body by this rotation)
    turn = canonical_to_world("+z") @ canonical_to_world(md.up_axis).T
    z_up = np.where(visible[..., None], positions, np.nan) @ turn.T
    # labels the fit ignored (never seen) are no markers of this take; the rest in a random order:
    # a labelled file's columns often follow the body (head to feet), which an unlabelled stream's do not
    kept = np.setdiff1d(np.arange(md.n_markers), np.asarray(fit.ignored, dtype=np.int64))
    order = kept[_rng(cfg.seed, 2).permutation(len(kept))]
    markers = z_up[:, order]

    stage("camera")
    view = camera_prior_video(replace(cfg, up_axis="+z", rate_hz=rate), model, betas, motion, joints, out_dir, stage)

    stage("write")
    T = markers.shape[0]
    stamps = np.round(np.arange(T) / rate * 1e9).astype(np.int64)
    rms = summarise_rms(fit.frame_rms_m)
    gt = {
        "betas": betas.astype(np.float64), "poses": motion.poses.astype(np.float64), "trans": motion.trans.astype(np.float64),
        "mocap_framerate": np.float64(rate), "joints": joints, "body_model": np.str_(cfg.body_model),
        "gender": np.str_("neutral"), "stamps_ns": stamps,
        "marker_faces": fit.attachment.face_ids.numpy()[order].astype(np.int64),
        "marker_bary": fit.attachment.bary.double().numpy()[order],
        "marker_offset_m": np.float64(MARKER_OFFSET_M),
        # Extras beyond the contract (for evaluation and debugging; never for solving):
        "part": np.str_(""),
        "marker_names": np.array([md.labels[k] for k in order], dtype=np.str_),
        "reference": np.str_("labeled IK of the capture's own labels (solver_core.labeled_fit)"),
        "reference_rms_mm": 1000 * np.asarray(fit.frame_rms_m, dtype=np.float64),
        "camera_R_wc": view.camera.R_wc, "camera_position": view.camera.position, "camera_K": view.camera.K,
        "yaw_offset_deg": np.float64(view.yaw_deg),
    }
    if view.content_s is not None:
        gt["video_content_s"] = view.content_s
    prov = {
        "generator": GENERATOR, "generator_version": GENERATOR_VERSION,
        "capture": marker_file.name, "capture_frames": [first, first + T],
        "capture_up_axis": md.up_axis, "rate_hz": rate, "seed": int(cfg.seed),
        "n_markers": int(len(order)), "ignored_labels": [md.labels[k] for k in fit.ignored],
        "reference": "labeled IK", "reference_rms": rms,
        "reference_suspicious_labels": fit.diagnostics.get("suspicious_labels", []),
        "body_model": cfg.body_model, "prior": asdict(view.error) if cfg.prior else None,
        "yaw_offset_deg": round(view.yaw_deg, 6), "video_size": list(cfg.video_size) if cfg.video else None,
    }
    save_session(out_dir, markers, rate, up_axis="+z", body_model=cfg.body_model, prior=view.prior, gt=gt,
                 video_file=view.video_name, video_rate_hz=cfg.video_rate_hz, clock_offset_s=cfg.clock_offset_s,
                 provenance=prov)
    return {
        "session": str(out_dir), "capture": marker_file.name, "frames": T, "capture_frames": [first, first + T],
        "rate_hz": rate, "markers": int(len(order)),
        "ignored_labels": prov["ignored_labels"], "missing_fraction": float(np.isnan(markers[..., 0]).mean()),
        "reference_rms": rms, "reference_suspicious_labels": prov["reference_suspicious_labels"],
        "prior_frames": int(view.prior["stamps_ns"].shape[0]) if view.prior is not None else 0,
        "video": view.video_name, "yaw_offset_deg": round(view.yaw_deg, 3),
    }
