"""Rigid-cluster consistency of the marker-surface correspondence (beyond the paper).

Marker segmentation (paper Sec. "Step 1") finds groups of markers that move rigidly together;
a group sits on one or a few neighbouring bones.  Stage 3 chooses every marker's surface point
independently under the Stage-2 body, so when that body is wrong somewhere (an arm held close to
the torso, say) a few markers land on another part of the body entirely - a torso point for an
upper-arm marker - and no later stage can move them back: the refinement only searches near
the previous point.  Those markers are visible as disagreements with their own rigid group.

Each joint is *owned* by the cluster with the most markers on it (ties: the larger cluster).
A marker whose joint is more than ``max_tree_steps`` kinematic-tree steps from every joint its
own cluster owns is inconsistent; it is re-assigned on the vertices of its cluster's joints
(and their tree neighbours).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClusterConsistencyConfig:
    # Beyond the paper: switch (False = the paper's independent per-marker Stage 3).
    enabled: bool = True
    # A marker may sit this many tree steps from its cluster's joints (1: a bone next to them,
    # e.g. a forearm marker near the elbow crease skinned to the upper arm).
    max_tree_steps: int = 1
    # Only clusters with at least this many markers vote (a singleton says nothing).
    min_cluster_size: int = 2
    # Only markers seen over at least this part of the take vote or move (first to last sighting).
    # An unlabelled export that starts a new column at every return from an occlusion has columns
    # of a second or two; pairs of them seen together that briefly look rigid across a joint that
    # did not move then, and their clusters moved right markers to wrong bones (session 45, an 8 s
    # generated arms take, 39 markers in 133 columns: 66.0 mm MPJPE, 42 markers moved; without the
    # check 13.0, as the same take in whole columns, 13.0).  Whole columns span the take: unchanged.
    min_span_fraction: float = 0.5
    # A marker is moved only to a point within this of it (mean distance over its frames, metres)
    # under the body of the moment; None = no limit.  In a short window a rigid cluster can span
    # bones that did not move apart (the first 3 s of a generated walk: a hip marker 0.54-0.61 m from
    # two upper-arm markers, their distances' deviation 0.7-1.2 mm), and its move put that hip marker
    # on the left elbow, 0.41 m off.  The near-online bootstrap sets 0.1 m (fast_bootstrap_config);
    # offline it is off: on whole takes it never acts, and on fragmented ones (session 48, 'breaks 1%'
    # arms, the moves it refused 0.5 m) the solves came out 1.4-2.0 mm worse on two of three.
    max_point_distance_m: float | None = None


def tree_distances(parents: np.ndarray) -> np.ndarray:
    """(J,J) number of edges between joints of the kinematic tree (parents[0] < 0 for the root)."""
    parents = np.asarray(parents)
    n = len(parents)
    adj = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].append(int(p))
            adj[int(p)].append(j)
    dist = np.full((n, n), n, dtype=np.int64)
    for s in range(n):
        dist[s, s] = 0
        frontier = [s]
        while frontier:
            nxt = []
            for a in frontier:
                for b in adj[a]:
                    if dist[s, b] > dist[s, a] + 1:
                        dist[s, b] = dist[s, a] + 1
                        nxt.append(b)
            frontier = nxt
    return dist


def cluster_joint_owners(cluster_labels: np.ndarray, marker_joints: np.ndarray, num_joints: int) -> np.ndarray:
    """(J,) cluster owning each joint (-1: no marker on it).

    cluster_labels (M,) int; marker_joints (M,) dominant joint per marker (-1 unassigned)."""
    cluster_labels = np.asarray(cluster_labels)
    marker_joints = np.asarray(marker_joints)
    sizes = np.bincount(cluster_labels, minlength=int(cluster_labels.max()) + 1 if len(cluster_labels) else 1)
    owners = np.full(num_joints, -1, dtype=np.int64)
    for j in range(num_joints):
        on = cluster_labels[marker_joints == j]
        if len(on) == 0:
            continue
        counts = np.bincount(on, minlength=len(sizes))
        best = np.flatnonzero(counts == counts.max())
        owners[j] = int(best[np.argmax(sizes[best])])
    return owners


def seen_span_fraction(visible: np.ndarray) -> np.ndarray:
    """(M,) part of the frames between each marker's first and last sighting, inclusive (0 if never
    seen).  visible: (T, M) bool."""
    from uuomocap.solver_core.gap_fill import column_spans

    first, last = column_spans(visible)
    return np.where(first >= 0, (last - first + 1) / max(1, np.asarray(visible).shape[0]), 0.0)


def inconsistent_markers(
    cluster_labels: np.ndarray, marker_joints: np.ndarray, parents: np.ndarray, config: ClusterConsistencyConfig = ClusterConsistencyConfig(),
    judged: np.ndarray | None = None,
) -> dict[int, np.ndarray]:
    """Markers whose joint disagrees with their rigid cluster -> the joints (K,) they may move to.

    cluster_labels (M,), marker_joints (M,) (-1 unassigned), parents (J,); judged (M,) bool: the
    markers that vote and may move (None: all; ``min_span_fraction``)."""
    cluster_labels = np.asarray(cluster_labels)
    marker_joints = np.asarray(marker_joints)
    if judged is not None:
        marker_joints = np.where(np.asarray(judged, bool), marker_joints, -1)
    num_joints = len(parents)
    owners = cluster_joint_owners(cluster_labels, marker_joints, num_joints)
    dist = tree_distances(parents)
    sizes = np.bincount(cluster_labels)
    out: dict[int, np.ndarray] = {}
    for m, (c, j) in enumerate(zip(cluster_labels, marker_joints)):
        if j < 0 or sizes[c] < config.min_cluster_size:
            continue
        owned = np.flatnonzero(owners == c)
        if len(owned) == 0:
            continue
        if dist[j, owned].min() > config.max_tree_steps:
            allowed = np.flatnonzero(dist[:, owned].min(axis=1) <= config.max_tree_steps)
            out[m] = allowed
    return out
