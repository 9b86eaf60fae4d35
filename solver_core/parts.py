"""Body parts on the SMPL kinematic tree.

PART_JOINTS are the paper's part definitions (Milef et al. 2024, Appendix A,
Table "Part definitions"); the marker-part matching step (Sec. 3.2, Step 2)
searches over connected groups of K bones, enumerated by connected_subtrees.
"""

from __future__ import annotations

from typing import Sequence

import torch

from .body_model import JOINT_NAMES

__all__ = [
    "PART_JOINTS",
    "PART_NAMES",
    "vertex_dominant_joint",
    "connected_subtrees",
    "kinematic_chains",
    "joint_parts",
    "part_vertex_mask",
    "subtree_vertex_mask",
    "joint_part",
]

# Appendix A.  The paper lists left/right_shoulder twice in the shoulder parts; the set is
# spine3, collar, shoulder, elbow.
PART_JOINTS: dict[str, list[int]] = {
    "left_arm": [16, 18, 20],
    "left_leg": [1, 4, 7, 10],
    "left_shoulder": [9, 13, 16, 18],
    "right_arm": [17, 19, 21],
    "right_leg": [2, 5, 8, 11],
    "right_shoulder": [9, 14, 17, 19],
}
PART_NAMES: tuple[str, ...] = tuple(PART_JOINTS)


def vertex_dominant_joint(model) -> torch.Tensor:
    """(N,) long: the joint ("bone" in the paper) with the largest skinning weight per vertex."""
    return model.weights.argmax(dim=1)


def joint_parts(joint: int) -> list[str]:
    """Names of the paper's parts that contain ``joint`` (possibly several, possibly none)."""
    return [name for name, joints in PART_JOINTS.items() if joint in joints]


def joint_part(joint: int) -> str:
    """The joint's name (JOINT_NAMES), the label OUT.npz stores in ``marker_parts``."""
    return JOINT_NAMES[joint]


def part_vertex_mask(model, part: str) -> torch.Tensor:
    """(N,) bool: vertices whose dominant joint belongs to ``part``."""
    if part not in PART_JOINTS:
        raise ValueError(f"unknown part {part!r}; known: {', '.join(PART_NAMES)}")
    return subtree_vertex_mask(model, PART_JOINTS[part])


def subtree_vertex_mask(model, joints: Sequence[int]) -> torch.Tensor:
    """(N,) bool: vertices whose dominant joint is one of ``joints``."""
    dom = vertex_dominant_joint(model)
    return torch.isin(dom, torch.as_tensor(list(joints), dtype=dom.dtype))


def _children(parents: Sequence[int]) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    return kids


def connected_subtrees(parents, k: int) -> list[tuple[int, ...]]:
    """All connected sets of exactly k joints of the tree (chains AND branching sets).

    parents: (J,) sequence/tensor with -1 at the root.  Returns sorted tuples of joint
    ids, each set once, in lexicographic order.  A connected set of a tree has a unique
    top joint, so sets are grown downward from every top joint: add any child of a joint
    already in the set.  Duplicates from different growth orders are merged.
    """
    par = [int(p) for p in (parents.tolist() if isinstance(parents, torch.Tensor) else parents)]
    if k < 1:
        raise ValueError("k must be >= 1")
    if k > len(par):
        return []
    kids = _children(par)
    found: set[tuple[int, ...]] = set()
    for top in range(len(par)):
        level = {frozenset([top])}
        for _ in range(k - 1):
            nxt = set()
            for s in level:
                for j in s:
                    for c in kids[j]:
                        if c not in s:
                            nxt.add(s | {c})
            level = nxt
        found.update(tuple(sorted(s)) for s in level)
    return sorted(found)


def kinematic_chains(parents, k: int) -> list[tuple[int, ...]]:
    """All downward chains of k joints (parent -> child -> grandchild ...), top joint first."""
    par = [int(p) for p in (parents.tolist() if isinstance(parents, torch.Tensor) else parents)]
    kids = _children(par)
    chains: list[tuple[int, ...]] = []

    def grow(chain: list[int]) -> None:
        if len(chain) == k:
            chains.append(tuple(chain))
            return
        for c in kids[chain[-1]]:
            grow(chain + [c])

    for top in range(len(par)):
        grow([top])
    return chains
