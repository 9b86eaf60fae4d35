"""A restricted unpickler for data files that are pickles of numpy arrays.

Official SMPL model files are Python-2 pickles holding numpy arrays, chumpy
``Ch`` objects and a ``scipy.sparse.csc_matrix``; video-pose tools (PHALP,
4DHumans) write joblib pickles of numpy arrays.  A plain ``pickle.load`` runs
any code the file names, so this module resolves ONLY:

  * numpy array / dtype / scalar reconstruction,
  * chumpy objects -> small stand-ins that keep their state (``x`` / ``a``),
  * scipy sparse csc/csr/coo matrices -> stand-ins rebuilt densely with numpy,
  * joblib's ``NumpyArrayWrapper`` (the array bytes follow it in the stream),
  * inert builtins (plain value types, set, frozenset, complex, slice, OrderedDict, defaultdict),

and refuses every other global with ``UnsafePickleError`` naming it, before
anything is called.  Neither chumpy, scipy nor joblib is imported.
"""

from __future__ import annotations

import collections
import gzip
import io
import lzma
import os
import pickle
import zlib
from typing import Any, BinaryIO, Iterable

import numpy as np

__all__ = [
    "UnsafePickleError",
    "ChumpyStandIn",
    "SparseStandIn",
    "load_restricted_pickle",
    "to_numpy",
    "DEFAULT_ALLOWED",
]


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle names a class or function outside the allowed set."""


# --------------------------------------------------------------------------- stand-ins
class ChumpyStandIn:
    """State of a pickled chumpy object; ``to_numpy()`` gives its value."""

    chumpy_class = "chumpy.ch.Ch"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict = {}

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict state, slots state)
            state = {**(state[0] or {}), **(state[1] or {})}
        if not isinstance(state, dict):
            raise pickle.UnpicklingError(f"unexpected state for {self.chumpy_class}: {type(state).__name__}")
        self.state = state

    def to_numpy(self) -> np.ndarray:
        s = self.state
        name = self.chumpy_class.rsplit(".", 1)[-1]
        if "x" in s:
            return np.asarray(to_numpy(s["x"]))
        if "a" in s:
            a = np.asarray(to_numpy(s["a"]))
            # The reorderings SMPL files are known to contain; others keep `a` as is.
            if name == "transpose":
                return a.transpose(s.get("axes"))
            if name == "Reshape" and "newshape" in s:
                return a.reshape(s["newshape"])
            if name == "Select" and "idxs" in s:
                out = a.ravel()[np.asarray(s["idxs"])]
                shape = s.get("preferred_shape")
                return out.reshape(shape) if shape is not None else out
            return a
        raise pickle.UnpicklingError(f"pickled {self.chumpy_class} has neither 'x' nor 'a' in its state")


class SparseStandIn:
    """State of a pickled scipy sparse matrix; ``to_numpy()`` rebuilds it densely."""

    sparse_format = "csc"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict = {}

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:
            state = {**(state[0] or {}), **(state[1] or {})}
        if not isinstance(state, dict):
            raise pickle.UnpicklingError(f"unexpected state for a sparse matrix: {type(state).__name__}")
        self.state = state

    def to_numpy(self) -> np.ndarray:
        s = self.state
        shape = s.get("_shape", s.get("shape"))
        fmt = s.get("format", self.sparse_format)
        if shape is None:
            raise pickle.UnpicklingError("pickled sparse matrix has no shape")
        shape = tuple(int(n) for n in shape)
        data = np.asarray(s["data"])
        out = np.zeros(shape, dtype=data.dtype if data.size else np.float64)
        if fmt == "coo":
            rows, cols = np.asarray(s["row"]), np.asarray(s["col"])
            np.add.at(out, (rows, cols), data)
            return out
        indices, indptr = np.asarray(s["indices"]), np.asarray(s["indptr"])
        major = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
        if fmt == "csc":
            np.add.at(out, (indices, major), data)
        elif fmt == "csr":
            np.add.at(out, (major, indices), data)
        else:
            raise pickle.UnpicklingError(f"unsupported sparse format {fmt!r}")
        return out


def _make_standin(base: type, module: str, name: str) -> type:
    attr = "chumpy_class" if base is ChumpyStandIn else "sparse_format"
    value = f"{module}.{name}" if base is ChumpyStandIn else name[:3]
    return type(name, (base,), {attr: value, "__module__": __name__})


class JoblibArrayWrapper:
    """Stand-in for joblib's NumpyArrayWrapper: the array bytes follow it in the file."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict = {}

    def __setstate__(self, state: Any) -> None:
        self.state = state if isinstance(state, dict) else {}


# --------------------------------------------------------------------------- safe callables
def _codecs_encode(text: str, encoding: str = "utf-8", errors: str = "strict") -> bytes:
    # Protocol-2 pickles written by Python 3 store bytes as _codecs.encode(str, 'latin1').
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1", "utf-8", "utf8", "ascii"):
        raise UnsafePickleError("_codecs.encode is only allowed to rebuild bytes from str")
    return text.encode(encoding, errors)


def _reconstructor(cls: Any, base: Any, state: Any) -> Any:
    # copyreg._reconstructor for protocol 0/1 objects, limited to the stand-ins and ndarray.
    if isinstance(cls, type) and issubclass(cls, (ChumpyStandIn, SparseStandIn, JoblibArrayWrapper)):
        return cls()
    if cls is np.ndarray and base is np.ndarray:
        return np.ndarray.__new__(np.ndarray, state)
    raise UnsafePickleError(f"copyreg._reconstructor refused for {cls!r}")


def _numpy_globals() -> dict[tuple[str, str], Any]:
    try:
        from numpy._core import multiarray as ma  # numpy >= 2
        from numpy._core import numeric as nu
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray as ma  # type: ignore
        from numpy.core import numeric as nu  # type: ignore
    out: dict[tuple[str, str], Any] = {}
    for mod in ("numpy.core", "numpy._core"):
        out[(f"{mod}.multiarray", "_reconstruct")] = ma._reconstruct
        out[(f"{mod}.multiarray", "scalar")] = ma.scalar
        out[(f"{mod}.numeric", "_frombuffer")] = nu._frombuffer
    out[("numpy", "ndarray")] = np.ndarray
    out[("numpy", "dtype")] = np.dtype
    # numpy >= 1.25 pickles dtypes as numpy.dtypes.Float32DType etc.
    for dname in ("Float16DType", "Float32DType", "Float64DType", "Int8DType", "Int16DType", "Int32DType",
                  "Int64DType", "UInt8DType", "UInt16DType", "UInt32DType", "UInt64DType", "BoolDType",
                  "StrDType", "BytesDType", "Complex64DType", "Complex128DType", "VoidDType"):
        if hasattr(np, "dtypes") and hasattr(np.dtypes, dname):
            out[("numpy.dtypes", dname)] = getattr(np.dtypes, dname)
    return out


_CHUMPY_MODULES = ("chumpy.ch", "chumpy.ch_ops", "chumpy.reordering", "chumpy.linalg", "chumpy.utils")
_SPARSE_MODULES = (
    "scipy.sparse.csc", "scipy.sparse._csc", "scipy.sparse.csr", "scipy.sparse._csr",
    "scipy.sparse.coo", "scipy.sparse._coo", "scipy.sparse._arrays", "scipy.sparse",
)
_SPARSE_NAMES = ("csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array")
_INERT = {
    ("builtins", "set"): set, ("__builtin__", "set"): set,
    ("builtins", "frozenset"): frozenset, ("__builtin__", "frozenset"): frozenset,
    ("builtins", "complex"): complex, ("__builtin__", "complex"): complex,
    ("builtins", "slice"): slice, ("__builtin__", "slice"): slice,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("_codecs", "encode"): _codecs_encode,
    ("copy_reg", "_reconstructor"): _reconstructor, ("copyreg", "_reconstructor"): _reconstructor,
    ("__builtin__", "object"): object, ("builtins", "object"): object,
}
# Plain value types (e.g. a defaultdict's factory); calling them cannot reach foreign code
# because their arguments can only be values this unpickler built.
for _t in (list, dict, tuple, int, float, bool, str):
    _INERT[("builtins", _t.__name__)] = _t
    _INERT[("__builtin__", _t.__name__)] = _t
_JOBLIB = ("joblib.numpy_pickle", "sklearn.externals.joblib.numpy_pickle")

DEFAULT_ALLOWED = ("numpy", "chumpy", "scipy.sparse", "joblib")


class _RestrictedUnpickler(pickle._Unpickler):  # pure-Python unpickler: BUILD can be intercepted
    def __init__(self, file: BinaryIO, allowed: Iterable[str], extra: dict[tuple[str, str], Any] | None):
        super().__init__(file, encoding="latin1")
        self._fh = file
        self._allowed = set(allowed)
        self._table: dict[tuple[str, str], Any] = dict(_INERT)
        if "numpy" in self._allowed:
            self._table.update(_numpy_globals())
        if extra:
            self._table.update(extra)
        self._standins: dict[tuple[str, str], type] = {}

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        if key in self._table:
            return self._table[key]
        if "chumpy" in self._allowed and module in _CHUMPY_MODULES:
            return self._standins.setdefault(key, _make_standin(ChumpyStandIn, module, name))
        if "scipy.sparse" in self._allowed and module in _SPARSE_MODULES and name in _SPARSE_NAMES:
            return self._standins.setdefault(key, _make_standin(SparseStandIn, module, name))
        if "joblib" in self._allowed and module in _JOBLIB and name == "NumpyArrayWrapper":
            return JoblibArrayWrapper
        raise UnsafePickleError(
            f"refusing to load '{module}.{name}': only numpy arrays, chumpy arrays and sparse matrices "
            "are allowed in this file"
        )

    def load_build(self) -> None:
        super().load_build()
        obj = self.stack[-1]
        if isinstance(obj, JoblibArrayWrapper):
            self.stack[-1] = _read_joblib_array(obj.state, self)

    dispatch = dict(pickle._Unpickler.dispatch)
    dispatch[pickle.BUILD[0]] = load_build


def _read_joblib_array(state: dict, unpickler: _RestrictedUnpickler) -> np.ndarray:
    """Read the array that joblib wrote raw right after its wrapper (joblib >= 0.10 layout)."""
    f = unpickler._fh  # joblib writes the bytes between pickle frames, straight to the file
    dtype = np.dtype(state["dtype"])
    shape = tuple(int(n) for n in state["shape"])
    if dtype.hasobject:
        return load_restricted_pickle(f, allowed=unpickler._allowed, _stream=True)
    if state.get("numpy_array_alignment_bytes") is not None:
        pad = f.read(1)
        if pad and pad[0]:
            f.read(pad[0])
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    nbytes = count * dtype.itemsize
    raw = f.read(nbytes)
    if len(raw) != nbytes:
        raise pickle.UnpicklingError("joblib array data is truncated")
    arr = np.frombuffer(raw, dtype=dtype, count=count).copy()
    if state.get("order") == "F":
        return arr.reshape(shape[::-1]).transpose()
    return arr.reshape(shape)


def _open_maybe_compressed(raw: bytes) -> bytes:
    if raw[:2] == b"\x1f\x8b":
        return gzip.decompress(raw)
    if raw[:6] == b"\xfd7zXZ\x00":
        return lzma.decompress(raw)
    if raw[:2] == b"ZF":  # joblib < 0.10 zlib container: 'ZF' + 16-hex-digit length
        return zlib.decompress(raw[18:])
    if raw[:1] == b"\x78":  # zlib stream (joblib compress=True/int)
        try:
            return zlib.decompress(raw)
        except zlib.error:
            return raw
    return raw


def load_restricted_pickle(
    path_or_file: str | os.PathLike | BinaryIO,
    allowed: Iterable[str] = DEFAULT_ALLOWED,
    extra_globals: dict[tuple[str, str], Any] | None = None,
    _stream: bool = False,
) -> Any:
    """Unpickle ``path_or_file`` resolving only the globals of ``allowed`` groups.

    allowed: subset of {"numpy", "chumpy", "scipy.sparse", "joblib"}.  extra_globals maps
    (module, name) to a trusted replacement callable.  gzip/zlib/xz compressed files
    (joblib's compress=...) are decompressed first.  Raises UnsafePickleError naming the
    first refused global; nothing the file names is called unless allowed.
    """
    allowed = tuple(allowed)
    if _stream:
        return _RestrictedUnpickler(path_or_file, allowed, extra_globals).load()  # type: ignore[arg-type]
    if isinstance(path_or_file, (str, os.PathLike)):
        with open(path_or_file, "rb") as fh:
            raw = fh.read()
    else:
        raw = path_or_file.read()
    buf = io.BytesIO(_open_maybe_compressed(raw))
    return _RestrictedUnpickler(buf, allowed, extra_globals).load()


def to_numpy(value: Any) -> Any:
    """Stand-ins -> numpy arrays; arrays pass through; other values unchanged."""
    if isinstance(value, (ChumpyStandIn, SparseStandIn)):
        return value.to_numpy()
    return value


def resolve_tree(value: Any) -> Any:
    """Recursively replace stand-ins inside dicts / lists / tuples by numpy arrays."""
    if isinstance(value, dict):
        return {k: resolve_tree(v) for k, v in value.items()}
    if isinstance(value, list):
        return [resolve_tree(v) for v in value]
    if isinstance(value, tuple):
        return tuple(resolve_tree(v) for v in value)
    return to_numpy(value)

