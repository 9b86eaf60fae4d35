"""Turn signatures of marker clusters and bones, and the floor term of partial-body matching."""

import math

import numpy as np
import torch

from uuomocap.solver_core.rotations import axis_angle_to_matrix
from uuomocap.solver_core.segment_rotation import (
    bone_relative_rotations,
    cluster_relative_rotations,
    frame_pairs,
    kabsch_rotation,
    turn_mismatch,
)


def _rot(vec) -> np.ndarray:
    return axis_angle_to_matrix(torch.tensor(vec, dtype=torch.float64)).numpy()


def test_kabsch_recovers_a_rotation():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(6, 3))
    pts -= pts.mean(0)
    r = _rot([0.3, -0.5, 0.8])
    assert np.allclose(kabsch_rotation(pts, pts @ r.T), r, atol=1e-9)


def test_cluster_turns_follow_the_rigid_motion_and_reject_degenerate_clusters():
    rng = np.random.default_rng(1)
    frames = 6
    angles = np.linspace(0.0, 1.0, frames)
    body = np.array([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [-0.1, -0.1, 0.0]])                  # a rigid cluster of 4 markers
    line = np.stack([np.zeros(3), [0.05, 0, 0], [0.1, 0, 0]])      # 3 collinear markers
    markers = np.zeros((frames, 9, 3))
    for t, a in enumerate(angles):
        r = _rot([0.0, 0.0, a])
        markers[t, :4] = body @ r.T + [1.0, 0.0, 1.0]
        markers[t, 4:7] = line @ r.T
        markers[t, 7:] = rng.normal(size=(2, 3))                   # a 2-marker cluster
    labels = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2])
    visible = np.ones((frames, 9), dtype=bool)
    pairs = frame_pairs(frames, lags=(1, 3))
    rot, valid = cluster_relative_rotations(markers, visible, labels, pairs)
    assert valid[0].all() and not valid[1].any() and not valid[2].any()
    for p, (a, b) in enumerate(pairs):
        assert np.allclose(rot[0, p], _rot([0.0, 0.0, angles[b] - angles[a]]), atol=1e-9)
    # a marker hidden in one frame: pairs touching that frame keep the other three markers
    visible[2, 0] = False
    _, valid_hidden = cluster_relative_rotations(markers, visible, labels, pairs)
    assert valid_hidden[0].all()


def test_turn_mismatch_is_zero_for_the_carrying_bone_under_the_right_yaw():
    frames = 5
    pairs = frame_pairs(frames, lags=(1, 2))
    # bone 0 turns about x, bone 1 stays still, in the prior's world
    bones = torch.zeros(frames, 2, 3, 3, dtype=torch.float64)
    for t in range(frames):
        bones[t, 0] = torch.as_tensor(_rot([0.2 * t, 0.0, 0.0]))
        bones[t, 1] = torch.eye(3, dtype=torch.float64)
    bone_turns = bone_relative_rotations(bones, pairs)
    yaw = _rot([0.0, 0.0, math.radians(70)])
    # the markers see bone 0 through the unknown yaw: turns Y D Y^T
    cluster = np.stack([yaw @ bone_turns[0, p].numpy() @ yaw.T for p in range(len(pairs))])[None]
    valid = np.ones((1, len(pairs)), dtype=bool)
    frame_rot = torch.as_tensor(np.stack([yaw, np.eye(3)]))
    mism = turn_mismatch(cluster, valid, bone_turns, frame_rot)  # (H=2, K=1, J=2)
    assert mism[0, 0, 0] < 1e-12
    assert mism[0, 0, 1] > 0.01        # a bone that does not turn
    assert mism[1, 0, 0] > 0.01        # the right bone under the wrong yaw
    # no valid pair: no evidence, no cost
    assert torch.all(turn_mismatch(cluster, np.zeros_like(valid), bone_turns, frame_rot) == 0)


def test_floor_energy_penalises_a_floating_body_only_beyond_the_dead_zone():
    from uuomocap.solver_core.part_matching import PartMatchingConfig, floor_energy

    up = torch.tensor([0.0, 0.0, 1.0])
    pts = torch.tensor([[[0.0, 0.0, -0.9], [0.0, 0.0, 0.8]]]).expand(4, -1, -1)  # feet 0.9 m below the centre
    yaw = torch.zeros(3)
    tilt = torch.eye(3).expand(3, 3, 3)
    heights = torch.tensor([0.9, 0.93, 1.3])                     # on the floor, 3 cm up, 40 cm up
    offset = torch.zeros(3, 4, 3)
    offset[..., 2] = heights[:, None]
    e = floor_energy(pts, yaw, tilt, offset, up, PartMatchingConfig())
    assert e[0] == 0 and e[1] == 0
    assert torch.isclose(e[2], torch.tensor(10.0 * ((0.4 - 0.05) / 0.1) ** 2))
