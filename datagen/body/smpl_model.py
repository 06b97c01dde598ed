"""SMPL as an optional body model, for users who hold an SMPL licence (nothing is shipped).

`SMPLBody({"female": ..., "male": ..., "neutral": ...})` reads the official model files:

- `.pkl`, the format SMPL ships (Python-2 pickles of numpy arrays, chumpy arrays and a scipy CSC
  `J_regressor`). They are read by a restricted unpickler that only rebuilds numeric numpy arrays
  and turns chumpy and scipy objects into inert stubs holding their pickled state; chumpy is
  never imported and no other callable can be reached, so a foreign pickle fails before anything
  in it runs. Besides numpy's array/dtype/scalar rebuilders (wrapped to refuse object dtypes), the
  only globals resolved are the pickle plumbing such files use: `copy_reg._reconstructor` (for
  stubs only), `object`, `set` (chumpy's state holds one), and, for files re-saved by Python 3
  with protocol 2, `_codecs.encode` (latin1 only) and `bytes()` (empty only).
- `.npz` (`np.load(allow_pickle=False)`) with the keys `v_template (V, 3)`, `shapedirs (V, 3, S)`,
  `posedirs (V, 3, 207)`, `J_regressor (24, V)`, `weights (V, 24)`, `kintree_table (2, 24)` and
  `f (T, 3)`. `J_regressor` may instead be stored as a CSC triplet: `J_regressor_data`,
  `J_regressor_indices`, `J_regressor_indptr` and `J_regressor_shape` (what
  `scipy.sparse.csc_matrix` holds as `data`, `indices`, `indptr` and `shape`).

Frames: SMPL's own frame is y up, facing +z; ours is z up, facing -y (datagen.skeleton). A
canonical root rotation R acts on the upright z-up body, so SMPL is driven with the root rotation
R @ SMPL_TO_WORLD and the other 23 rotations unchanged; the posed body is then shifted so that its
pelvis joint lands at the canonical `trans`. Posing is standard SMPL: shape and pose blend shapes,
joints regressed from the shaped template, linear blend skinning. Because of the pose blend shapes
the result is not pure LBS, so `PosedBody.skinning` is None and the shard stores vertices.
"""

from __future__ import annotations

import functools
import pickle
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from datagen.body.base import PosedBody, check_gender
from datagen.body.parts import JOINT_TO_PART, PART_NAMES
from datagen.errors import InputError
from datagen.rotations import axis_angle_to_matrix
from datagen.skeleton import NUM_JOINTS, PARENTS, SMPL_TO_WORLD
from datagen.types import RestBody

BETA_RANGE = (-3.0, 3.0)  # CLOTH3D samples each beta in this range
NUM_POSE_DIRS = (NUM_JOINTS - 1) * 9  # 207: (R_j - I) of joints 1..23, flattened
MODEL_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
CSC_SUFFIXES = ("data", "indices", "indptr", "shape")
PICKLE_EXPECTED = "an SMPL model (numpy/scipy/chumpy arrays only)"
_PATH_KEYS = ("female", "male", "neutral")
_CHUNK_BYTES = 64 * 2**20  # bounds the per-vertex (F, V, 3, 4) skinning transforms


# -- restricted unpickling -----------------------------------------------------------------------


class _Stub:
    """Inert stand-in for a pickled object: keeps its state, runs nothing."""

    origin = "?"
    state: Any = None

    def __new__(cls, *args: Any, **kwargs: Any) -> _Stub:
        return object.__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        self.state = state


class _ChumpyStub(_Stub):
    """A chumpy object (`chumpy.ch.Ch` and friends); its value is the `x` entry of its state."""


class _SparseStub(_Stub):
    """A scipy CSC matrix; densified from its `data`, `indices`, `indptr` and `_shape`."""

    origin = "scipy.sparse.csc_matrix"


class _NDArrayMarker:
    """Stands for `numpy.ndarray` inside a pickle, so the real constructor is never callable."""


@functools.cache
def _chumpy_class(module: str, name: str) -> type[_ChumpyStub]:
    return type(name, (_ChumpyStub,), {"origin": f"{module}.{name}"})


_NP_RECONSTRUCT = np.zeros(0).__reduce__()[0]  # numpy's own, whichever module it lives in


def _as_dtype(spec: Any, align: Any = False, copy: Any = False) -> np.dtype:
    if isinstance(spec, bytes):
        spec = spec.decode("latin1")
    dtype = np.dtype(spec, bool(align), bool(copy))
    if dtype.hasobject:  # object arrays would carry arbitrary pickled objects
        raise pickle.UnpicklingError(f"object dtype {dtype} in an SMPL model")
    return dtype


def _reconstruct_array(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
    if subtype is not _NDArrayMarker:
        raise pickle.UnpicklingError("only plain numpy arrays are allowed")
    # The real shape and data come with the BUILD that follows (ndarray.__setstate__).
    return _NP_RECONSTRUCT(np.ndarray, (0,), _as_dtype(dtype))


def _make_scalar(dtype: Any, data: Any = b"") -> Any:
    if not isinstance(dtype, np.dtype) or dtype.hasobject:
        raise pickle.UnpicklingError("only numeric numpy scalars are allowed")
    raw = data.encode("latin1") if isinstance(data, str) else bytes(data)
    return np.frombuffer(raw, dtype=dtype, count=1)[0]


def _latin1_encode(text: Any, encoding: str = "latin1") -> bytes:
    # Python 3 protocol-2 pickles store bytes as _codecs.encode(str, "latin1").
    if not isinstance(text, str) or encoding.lower() not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("_codecs.encode is only allowed for latin1 bytes")
    return text.encode("latin1")


def _empty_bytes(*args: Any) -> bytes:
    # ... and an empty bytes object as __builtin__.bytes().
    if args:
        raise pickle.UnpicklingError("bytes() with arguments")
    return b""


def _reconstructor(cls: Any, base: Any, state: Any = None) -> _Stub:
    # copy_reg._reconstructor, as protocol-0/1 pickles create class instances.
    if not (isinstance(cls, type) and issubclass(cls, _Stub)) or base is not object:
        raise pickle.UnpicklingError("copy_reg._reconstructor for a non-stub class")
    return cls.__new__(cls)


_NUMPY_CORES = ("numpy.core.multiarray", "numpy._core.multiarray")
_ALLOWED: dict[tuple[str, str], Any] = {
    **{(core, "_reconstruct"): _reconstruct_array for core in _NUMPY_CORES},
    **{(core, "scalar"): _make_scalar for core in _NUMPY_CORES},
    ("numpy", "ndarray"): _NDArrayMarker,
    ("numpy", "dtype"): _as_dtype,
    ("scipy.sparse.csc", "csc_matrix"): _SparseStub,
    ("scipy.sparse._csc", "csc_matrix"): _SparseStub,
    ("scipy.sparse._csc", "csc_array"): _SparseStub,
    ("copy_reg", "_reconstructor"): _reconstructor,
    ("copyreg", "_reconstructor"): _reconstructor,
    ("__builtin__", "object"): object,
    ("builtins", "object"): object,
    ("__builtin__", "set"): set,  # chumpy's state holds a set (_dirty_vars)
    ("builtins", "set"): set,
    ("__builtin__", "bytes"): _empty_bytes,
    ("builtins", "bytes"): _empty_bytes,
    ("_codecs", "encode"): _latin1_encode,
}


class _SMPLUnpickler(pickle.Unpickler):
    """Resolves only the globals an SMPL model file needs; anything else is refused at lookup,
    i.e. before the pickle can call it."""

    def __init__(self, file: Any, source: Path) -> None:
        super().__init__(file, encoding="latin1")  # SMPL files are Python-2 pickles
        self._source = source

    def find_class(self, module: str, name: str) -> Any:
        target = _ALLOWED.get((module, name))
        if target is not None:
            return target
        if module == "chumpy" or module.startswith("chumpy."):
            return _chumpy_class(module, name)
        raise InputError(self._source, "pickle", PICKLE_EXPECTED, f"{module}.{name}")


def _load_pickle(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            data = _SMPLUnpickler(fh, path).load()
    except InputError:
        raise
    except OSError as exc:
        raise InputError(path, None, "a readable SMPL model file", str(exc)) from exc
    except Exception as exc:  # anything malformed in untrusted data is an input error
        raise InputError(path, "pickle", PICKLE_EXPECTED, f"{type(exc).__name__}: {exc}") from exc
    if not isinstance(data, dict):
        raise InputError(path, "pickle", "a dict of model arrays", type(data).__name__)
    return data


def _load_npz(path: Path) -> dict[str, Any]:
    wanted = set(MODEL_KEYS) | {f"J_regressor_{s}" for s in CSC_SUFFIXES}
    try:
        with np.load(path, allow_pickle=False) as archive:
            raw = {}
            for key in archive.files:
                if key not in wanted:
                    continue
                try:
                    raw[key] = archive[key]
                except ValueError as exc:  # object arrays need pickle, which is off
                    raise InputError(path, key, "a numeric array", str(exc)) from exc
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, None, "an .npz archive of SMPL model arrays", str(exc)) from exc
    return raw


# -- model arrays and their validation -----------------------------------------------------------


def _csc_to_dense(
    path: Path, key: str, data: Any, indices: Any, indptr: Any, shape: Any
) -> np.ndarray:
    """Dense matrix from CSC triplets, without scipy (duplicates add up, as in scipy)."""
    try:
        n_rows, n_cols = (int(n) for n in np.asarray(shape).ravel())
        data = np.asarray(data, dtype=np.float64).ravel()
        indices = np.asarray(indices).ravel()
        indptr = np.asarray(indptr).ravel()
    except (TypeError, ValueError) as exc:
        raise InputError(path, key, "a CSC sparse matrix", str(exc)) from exc
    valid = (
        indices.dtype.kind in "iu"
        and indptr.dtype.kind in "iu"
        and n_rows >= 0
        and n_cols >= 0
        and indptr.shape == (n_cols + 1,)
        and indices.shape == data.shape
        and indptr[0] == 0
        and indptr[-1] == data.size
        and bool(np.all(np.diff(indptr) >= 0))
        and (indices.size == 0 or (indices.min() >= 0 and indices.max() < n_rows))
    )
    if not valid:
        raise InputError(path, key, "a valid CSC sparse matrix", (n_rows, n_cols))
    dense = np.zeros((n_rows, n_cols))
    cols = np.repeat(np.arange(n_cols), np.diff(indptr))
    np.add.at(dense, (indices.astype(np.int64), cols), data)
    return dense


def _to_array(path: Path, key: str, value: Any) -> np.ndarray:
    if isinstance(value, _ChumpyStub):
        state = value.state if isinstance(value.state, dict) else {}
        if "x" not in state:
            raise InputError(path, key, "a chumpy array holding its value in 'x'", value.origin)
        return _to_array(path, key, state["x"])
    if isinstance(value, _SparseStub):
        state = value.state if isinstance(value.state, dict) else {}
        parts = [state.get(k) for k in ("data", "indices", "indptr")]
        shape = state.get("_shape", state.get("shape"))
        if any(p is None for p in parts) or shape is None:
            raise InputError(path, key, "a CSC sparse matrix", sorted(state))
        return _csc_to_dense(path, key, *parts, shape)
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
        got = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
        raise InputError(path, key, "a numeric array", str(got))
    return value


def _get(path: Path, raw: dict[str, Any], key: str) -> np.ndarray:
    if key == "J_regressor" and key not in raw:
        triplet = [f"{key}_{s}" for s in CSC_SUFFIXES]
        if all(k in raw for k in triplet):
            return _csc_to_dense(path, key, *(_to_array(path, k, raw[k]) for k in triplet))
    if key not in raw:
        raise InputError(path, key, f"the key '{key}' in the SMPL model file", "missing")
    return _to_array(path, key, raw[key])


def _check_shape(path: Path, key: str, array: np.ndarray, expected: tuple, text: str) -> None:
    """`expected` holds ints, or None for a free dimension."""
    ok = array.ndim == len(expected) and all(
        e is None or e == n for e, n in zip(expected, array.shape, strict=True)
    )
    if not ok:
        raise InputError(path, key, text, tuple(array.shape))


@dataclass
class SMPLModelData:
    """One validated SMPL model file, float64, in SMPL's own frame."""

    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, num_betas)
    posedirs: np.ndarray  # (V * 3, 207)
    j_regressor: np.ndarray  # (24, V)
    weights: np.ndarray  # (V, 24)
    parents: np.ndarray  # (24,), parents[0] = -1
    faces: np.ndarray  # (T, 3) int32
    part_labels: np.ndarray  # (V,) int16

    def shaped(self, betas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shaped template (V, 3) and its regressed joints (24, 3)."""
        v_shaped = self.v_template + self.shapedirs @ betas
        return v_shaped, self.j_regressor @ v_shaped


def _validate(path: Path, raw: dict[str, Any], num_betas: int) -> SMPLModelData:
    arrays = {key: _get(path, raw, key) for key in MODEL_KEYS}
    for key, array in arrays.items():
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            raise InputError(path, key, "finite values", "NaN or inf")

    v_template = arrays["v_template"].astype(np.float64)
    _check_shape(path, "v_template", v_template, (None, 3), "(V, 3)")
    n_verts = v_template.shape[0]
    if n_verts == 0:
        raise InputError(path, "v_template", "(V, 3) with V > 0", v_template.shape)

    shapedirs = arrays["shapedirs"].astype(np.float64)
    _check_shape(
        path, "shapedirs", shapedirs, (n_verts, 3, None), f"({n_verts}, 3, S) with S >= {num_betas}"
    )
    if shapedirs.shape[2] < num_betas:
        raise InputError(
            path, "shapedirs", f"({n_verts}, 3, S) with S >= {num_betas}", shapedirs.shape
        )

    posedirs = arrays["posedirs"].astype(np.float64)
    _check_shape(
        path, "posedirs", posedirs, (n_verts, 3, NUM_POSE_DIRS), f"({n_verts}, 3, {NUM_POSE_DIRS})"
    )

    j_regressor = arrays["J_regressor"].astype(np.float64)
    _check_shape(
        path, "J_regressor", j_regressor, (NUM_JOINTS, n_verts), f"({NUM_JOINTS}, {n_verts})"
    )

    weights = arrays["weights"].astype(np.float64)
    _check_shape(path, "weights", weights, (n_verts, NUM_JOINTS), f"({n_verts}, {NUM_JOINTS})")
    sums = weights.sum(axis=1)
    if np.any(weights < -1e-6) or not np.allclose(sums, 1.0, atol=1e-3):
        worst = float(sums[np.argmax(np.abs(sums - 1.0))])
        raise InputError(path, "weights", "non-negative rows summing to 1", worst)

    kintree = arrays["kintree_table"]
    _check_shape(path, "kintree_table", kintree, (2, NUM_JOINTS), f"(2, {NUM_JOINTS})")
    if kintree.dtype.kind == "f" and np.any(kintree != np.round(kintree)):
        raise InputError(path, "kintree_table", "integer joint indices", str(kintree.dtype))
    tree = kintree.astype(np.int64)
    # The canonical poses are defined on the SMPL tree; the root's parent entry is arbitrary
    # (SMPL stores 2**32 - 1).
    if not (
        np.array_equal(tree[1], np.arange(NUM_JOINTS)) and np.array_equal(tree[0, 1:], PARENTS[1:])
    ):
        raise InputError(
            path, "kintree_table", f"the SMPL joint tree, parents {PARENTS[1:]}", tree.tolist()
        )
    parents = tree[0].copy()
    parents[0] = -1

    faces = arrays["f"]
    _check_shape(path, "f", faces, (None, 3), "(T, 3)")
    if faces.dtype.kind == "f" and np.any(faces != np.round(faces)):
        raise InputError(path, "f", "integer vertex indices", str(faces.dtype))
    if faces.size and (faces.min() < 0 or faces.max() >= n_verts):
        raise InputError(
            path, "f", f"vertex indices in [0, {n_verts})", (int(faces.min()), int(faces.max()))
        )

    # Part per vertex: the part whose joints carry most of its skinning weight (as for Anny).
    part_weight = weights @ np.eye(len(PART_NAMES))[JOINT_TO_PART]
    return SMPLModelData(
        v_template=v_template,
        shapedirs=np.ascontiguousarray(shapedirs[:, :, :num_betas]),
        posedirs=np.ascontiguousarray(posedirs.reshape(n_verts * 3, NUM_POSE_DIRS)),
        j_regressor=j_regressor,
        weights=weights,
        parents=parents,
        faces=faces.astype(np.int32),
        part_labels=part_weight.argmax(axis=1).astype(np.int16),
    )


def load_smpl_model(path: str | Path, num_betas: int = 10) -> SMPLModelData:
    """Read and validate one SMPL model file (.npz or .pkl); raises InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "an existing SMPL model file", "no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        raw = _load_npz(path)
    elif suffix == ".pkl":
        raw = _load_pickle(path)
    else:
        raise InputError(path, None, "an SMPL model file ending in .npz or .pkl", suffix)
    return _validate(path, raw, num_betas)


# -- the body model ------------------------------------------------------------------------------


class SMPLBody:
    """SMPL driven by canonical poses. `paths` maps "female", "male" and optionally "neutral"
    (used for a gender without a file of its own) to model files; each file is loaded on first
    use and kept. `num_betas` shape coefficients are used (the first ones of the file's)."""

    name = "smpl"
    shape_names: tuple[str, ...]

    def __init__(self, paths: dict[str, str | Path], num_betas: int = 10) -> None:
        if not paths:
            raise InputError(None, "paths", "at least one SMPL model file", paths)
        for key in paths:
            if key not in _PATH_KEYS:
                raise InputError(None, "paths", "keys 'female', 'male' or 'neutral'", key)
        if int(num_betas) < 1:
            raise InputError(
                None, "num_betas", "a positive number of shape coefficients", num_betas
            )
        self.paths = {key: Path(p) for key, p in paths.items()}
        self.num_betas = int(num_betas)
        self.shape_names = tuple(f"beta{i}" for i in range(self.num_betas))
        self._models: dict[Path, SMPLModelData] = {}
        self._lock = threading.Lock()

    def _model(self, gender: str) -> SMPLModelData:
        check_gender(gender)
        path = self.paths.get(gender, self.paths.get("neutral"))
        if path is None:
            raise InputError(
                None,
                f"paths.{gender}",
                f"an SMPL model file for '{gender}' (or a 'neutral' one)",
                None,
            )
        with self._lock:  # one load per file, shared by genders that use the same file
            model = self._models.get(path)
            if model is None:
                model = load_smpl_model(path, self.num_betas)
                self._models[path] = model
        return model

    def shape_range(self) -> dict[str, tuple[float, float]]:
        return dict.fromkeys(self.shape_names, BETA_RANGE)

    def _check_betas(self, shape: np.ndarray) -> np.ndarray:
        # Only finiteness: the range is what sampling draws from, not a limit of the model.
        betas = np.asarray(shape, dtype=np.float64)
        if betas.shape != (self.num_betas,):
            raise InputError(None, "shape", f"{self.num_betas} SMPL betas", betas.shape)
        if not np.all(np.isfinite(betas)):
            raise InputError(None, "shape", "finite betas", betas.tolist())
        return betas

    def rest_body(self, gender: str, shape: np.ndarray) -> RestBody:
        model = self._model(gender)
        betas = self._check_betas(shape)
        v_shaped, joints = model.shaped(betas)
        vertices = v_shaped @ SMPL_TO_WORLD.T
        joints = joints @ SMPL_TO_WORLD.T
        # Soles on the ground, pelvis above the origin.
        offset = np.array([-joints[0, 0], -joints[0, 1], -vertices[:, 2].min()])
        return RestBody(
            model=self.name,
            gender=gender,
            shape=betas.copy(),
            shape_names=self.shape_names,
            vertices=vertices + offset,
            faces=model.faces.copy(),
            joints=joints + offset,
            part_labels=model.part_labels.copy(),
            part_names=PART_NAMES,
        )

    def pose(self, rest: RestBody, poses: np.ndarray, trans: np.ndarray) -> PosedBody:
        if rest.model != self.name:
            raise InputError(None, "rest.model", f"'{self.name}'", rest.model)
        model = self._model(rest.gender)
        betas = self._check_betas(rest.shape)
        poses = np.asarray(poses, dtype=np.float64)
        trans = np.asarray(trans, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != NUM_JOINTS * 3:
            raise InputError(None, "poses", f"(F, {NUM_JOINTS * 3})", poses.shape)
        n_frames = poses.shape[0]
        if trans.shape != (n_frames, 3):
            raise InputError(None, "trans", f"({n_frames}, 3)", trans.shape)

        v_shaped, joints = model.shaped(betas)
        rot = axis_angle_to_matrix(poses.reshape(n_frames, NUM_JOINTS, 3))
        # Pose blend shapes depend on joints 1..23 only, so the root conversion cannot touch them.
        pose_feature = (rot[:, 1:] - np.eye(3)).reshape(n_frames, NUM_POSE_DIRS)
        rot[:, 0] = rot[:, 0] @ SMPL_TO_WORLD  # the canonical root acts on the upright body

        world_rot = np.empty_like(rot)
        world_pos = np.empty((n_frames, NUM_JOINTS, 3))
        world_rot[:, 0] = rot[:, 0]
        world_pos[:, 0] = joints[0]
        for j in range(1, NUM_JOINTS):
            p = model.parents[j]
            world_rot[:, j] = world_rot[:, p] @ rot[:, j]
            world_pos[:, j] = world_pos[:, p] + world_rot[:, p] @ (joints[j] - joints[p])
        # Bone transforms taking rest-pose points to posed points: x -> R (x - J) + posed J.
        offsets = world_pos - np.einsum("fjab,jb->fja", world_rot, joints)
        bones = np.concatenate([world_rot, offsets[..., None]], axis=-1).reshape(
            n_frames, NUM_JOINTS, 12
        )
        shift = trans - world_pos[:, 0]  # the posed pelvis lands at trans

        n_verts = v_shaped.shape[0]
        vertices = np.empty((n_frames, n_verts, 3), dtype=np.float32)
        chunk = max(1, _CHUNK_BYTES // (n_verts * 12 * 8))
        for start in range(0, n_frames, chunk):
            sl = slice(start, start + chunk)
            v_posed = v_shaped + (pose_feature[sl] @ model.posedirs.T).reshape(-1, n_verts, 3)
            blended = (model.weights @ bones[sl]).reshape(-1, n_verts, 3, 4)
            posed = (blended[..., :3] @ v_posed[..., None])[..., 0] + blended[..., 3]
            vertices[sl] = posed + shift[sl, None, :]
        return PosedBody(
            vertices=vertices,
            joints=(world_pos + shift[:, None, :]).astype(np.float32),
            skinning=None,
        )
