"""SMPLBody on a small synthetic model written in the SMPL file formats (nothing is downloaded)."""

from __future__ import annotations

import builtins
import os
import pickle
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse

from datagen.body.parts import PART_INDEX, PART_NAMES
from datagen.body.smpl_model import SMPLBody
from datagen.errors import InputError
from datagen.skeleton import JOINT_INDEX, PARENTS, SMPL_TO_WORLD

N_BETAS = 10
# A crude humanoid in SMPL's frame: y up, facing +z, the body's left at +x. Metres.
JOINTS_SMPL = np.array(
    [
        [0.0, 0.90, 0.0],  # pelvis
        [0.09, 0.82, 0.0],  # left_hip
        [-0.09, 0.82, 0.0],
        [0.0, 1.00, -0.01],  # spine1
        [0.10, 0.46, 0.01],  # left_knee
        [-0.10, 0.46, 0.01],
        [0.0, 1.12, -0.01],  # spine2
        [0.10, 0.08, -0.02],  # left_ankle
        [-0.10, 0.08, -0.02],
        [0.0, 1.20, 0.0],  # spine3
        [0.11, 0.02, 0.10],  # left_foot (toes point forward, +z)
        [-0.11, 0.02, 0.10],
        [0.0, 1.45, -0.01],  # neck
        [0.07, 1.37, 0.0],  # left_collar
        [-0.07, 1.37, 0.0],
        [0.0, 1.55, 0.02],  # head
        [0.17, 1.40, 0.0],  # left_shoulder
        [-0.17, 1.40, 0.0],
        [0.44, 1.40, 0.0],  # left_elbow
        [-0.44, 1.40, 0.0],
        [0.68, 1.40, 0.0],  # left_wrist
        [-0.68, 1.40, 0.0],
        [0.78, 1.40, 0.0],  # left_hand
        [-0.78, 1.40, 0.0],
    ]
)
PER_BONE = 7


def make_model(seed: int = 0) -> dict[str, np.ndarray]:
    """Vertices along every bone, skinned to its two ends, plus a few around the head top."""
    rng = np.random.default_rng(seed)
    verts, weights = [], []
    for j in range(1, 24):
        p = PARENTS[j]
        for t in np.linspace(0.1, 0.95, PER_BONE):
            verts.append(
                JOINTS_SMPL[p] + t * (JOINTS_SMPL[j] - JOINTS_SMPL[p]) + rng.normal(0.0, 0.02, 3)
            )
            w = np.zeros(24)
            w[p], w[j] = 1.0 - t, t
            w[rng.integers(24)] += 0.05  # a little weight on some other joint
            weights.append(w)
    for _ in range(6):  # a skull above the head joint
        verts.append(JOINTS_SMPL[15] + [0.0, 0.12, 0.0] + rng.normal(0.0, 0.03, 3))
        w = np.zeros(24)
        w[15] = 1.0
        weights.append(w)
    v = np.array(verts)
    n_verts = len(v)
    weights = np.array(weights)
    weights /= weights.sum(axis=1, keepdims=True)
    # Joint regressor: each joint is a weighted mean of the vertices nearest to it.
    regressor = np.zeros((24, n_verts))
    for j in range(24):
        near = np.argsort(np.linalg.norm(v - JOINTS_SMPL[j], axis=1))[:5]
        regressor[j, near] = rng.uniform(0.5, 1.0, 5)
    regressor /= regressor.sum(axis=1, keepdims=True)
    kintree = np.array([[2**32 - 1, *PARENTS[1:]], list(range(24))], dtype=np.int64)
    return {
        "v_template": v,
        "shapedirs": rng.normal(0.0, 0.01, (n_verts, 3, N_BETAS)),
        "posedirs": rng.normal(0.0, 0.002, (n_verts, 3, 207)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": rng.integers(0, n_verts, (2 * n_verts, 3)).astype(np.uint32),
    }


class _FakeCh:
    """Pickled as `chumpy.ch.Ch` with a state like chumpy's (its value under 'x')."""

    __module__ = "chumpy.ch"
    __qualname__ = "Ch"

    def __init__(self, x: np.ndarray) -> None:
        self.x = x
        self._dirty_vars: set[str] = set()
        self._itr = None
        self._depends_on_deps: dict = {}
        self._make_dense = False
        self._make_sparse = False


def _dump_with_fake_chumpy(data: dict, path: Path) -> None:
    """Pickle under the class path chumpy.ch.Ch: pickle looks the class up by name, so a fake
    module stands in only while dumping (the loader must do without it)."""
    ch_module = types.ModuleType("chumpy.ch")
    ch_module.Ch = _FakeCh
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
        mp.setitem(sys.modules, "chumpy.ch", ch_module)
        path.write_bytes(pickle.dumps(data, protocol=2))  # protocol 2, as SMPL's files


@pytest.fixture(scope="module")
def model_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("smpl")
    arrays = make_model()
    files = {"npz": root / "model.npz", "pkl": root / "model.pkl"}
    np.savez(files["npz"], **arrays)
    files["pkl"].write_bytes(pickle.dumps(arrays, protocol=4))

    # J_regressor as CSC triplet keys in the npz.
    csc = scipy.sparse.csc_matrix(arrays["J_regressor"])
    sparse_npz = {k: v for k, v in arrays.items() if k != "J_regressor"}
    sparse_npz.update(
        J_regressor_data=csc.data,
        J_regressor_indices=csc.indices,
        J_regressor_indptr=csc.indptr,
        J_regressor_shape=np.array(csc.shape),
    )
    files["npz_csc"] = root / "model_csc.npz"
    np.savez(files["npz_csc"], **sparse_npz)

    # As SMPL ships it: chumpy arrays and a scipy CSC regressor.
    chumpy_like = dict(arrays, J_regressor=csc, bs_style="lbs", bs_type="lrotmin")
    for key in ("shapedirs", "posedirs", "v_template", "weights"):
        chumpy_like[key] = _FakeCh(arrays[key])
    files["pkl_chumpy"] = root / "model_chumpy.pkl"
    _dump_with_fake_chumpy(chumpy_like, files["pkl_chumpy"])
    assert "chumpy" not in sys.modules
    return files


# -- an independent reference SMPL ----------------------------------------------------------------


def rodrigues(aa: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(aa)
    if angle < 1e-12:
        return np.eye(3)
    k = aa / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def reference_pose(m: dict, betas: np.ndarray, pose: np.ndarray, trans: np.ndarray):
    """Plain SMPL for one frame in SMPL's frame, then placed in our world the documented way:
    root rotation R_canonical @ SMPL_TO_WORLD, posed pelvis moved to `trans`."""
    to_world = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    v_shaped = m["v_template"] + np.einsum("vcs,s->vc", m["shapedirs"], betas)
    joints = m["J_regressor"] @ v_shaped
    rots = [rodrigues(pose[3 * j : 3 * j + 3]) for j in range(24)]
    rots[0] = rots[0] @ to_world
    feature = np.concatenate([(rots[j] - np.eye(3)).ravel() for j in range(1, 24)])
    v_posed = v_shaped + np.einsum("vcp,p->vc", m["posedirs"], feature)
    chain = [None] * 24
    for j in range(24):
        local = np.eye(4)
        local[:3, :3] = rots[j]
        if j == 0:
            local[:3, 3] = joints[0]
            chain[j] = local
        else:
            local[:3, 3] = joints[j] - joints[PARENTS[j]]
            chain[j] = chain[PARENTS[j]] @ local
    posed_joints = np.array([g[:3, 3] for g in chain])
    out = np.zeros_like(v_posed)
    homog = np.hstack([v_posed, np.ones((len(v_posed), 1))])
    for j in range(24):
        bone = chain[j].copy()
        bone[:3, 3] -= chain[j][:3, :3] @ joints[j]  # relative to the rest joint
        out += m["weights"][:, j : j + 1] * (homog @ bone.T)[:, :3]
    shift = trans - posed_joints[0]
    return out + shift, posed_joints + shift


# -- tests ---------------------------------------------------------------------------------------


def test_formats_agree(model_files: dict[str, Path]) -> None:
    """npz, npz with a CSC regressor, plain pickle and SMPL-style chumpy/scipy pickle: same body."""
    rng = np.random.default_rng(1)
    betas = rng.uniform(-3, 3, N_BETAS)
    poses = rng.normal(0.0, 0.4, (3, 72))
    trans = rng.normal(0.0, 1.0, (3, 3))
    results = []
    for path in model_files.values():
        body = SMPLBody({"female": path, "male": path})
        rest = body.rest_body("female", betas)
        results.append((rest, body.pose(rest, poses, trans)))
    rest0, posed0 = results[0]
    for rest, posed in results[1:]:
        np.testing.assert_allclose(rest.vertices, rest0.vertices, atol=1e-12)
        np.testing.assert_array_equal(rest.faces, rest0.faces)
        np.testing.assert_array_equal(rest.part_labels, rest0.part_labels)
        np.testing.assert_allclose(posed.vertices, posed0.vertices, atol=1e-6)
        np.testing.assert_allclose(posed.joints, posed0.joints, atol=1e-6)
    assert "chumpy" not in sys.modules


def test_pose_matches_reference_lbs(model_files: dict[str, Path]) -> None:
    m = make_model()
    body = SMPLBody({"neutral": model_files["npz"]})
    rng = np.random.default_rng(2)
    for gender in ("female", "male"):
        betas = rng.uniform(-3, 3, N_BETAS)
        rest = body.rest_body(gender, betas)
        poses = rng.normal(0.0, 0.5, (4, 72))
        poses[:, :3] = rng.normal(0.0, 1.5, (4, 3))  # large root turns
        trans = rng.uniform(-2.0, 2.0, (4, 3))
        posed = body.pose(rest, poses, trans)
        assert posed.skinning is None
        assert posed.vertices.dtype == np.float32 and posed.joints.dtype == np.float32
        assert posed.vertices.shape == (4, len(m["v_template"]), 3)
        assert posed.joints.shape == (4, 24, 3)
        for f in range(4):
            ref_v, ref_j = reference_pose(m, betas, poses[f], trans[f])
            np.testing.assert_allclose(posed.vertices[f], ref_v, atol=1e-5)
            np.testing.assert_allclose(posed.joints[f], ref_j, atol=1e-5)
            np.testing.assert_allclose(posed.joints[f, 0], trans[f], atol=1e-6)


def test_zero_pose_at_pelvis_height_is_the_rest_body(model_files: dict[str, Path]) -> None:
    body = SMPLBody({"neutral": model_files["npz"]})
    rest = body.rest_body("male", np.linspace(-1, 1, N_BETAS))
    posed = body.pose(rest, np.zeros((2, 72)), np.tile(rest.joints[0], (2, 1)))
    np.testing.assert_allclose(posed.vertices[1], rest.vertices, atol=1e-6)
    np.testing.assert_allclose(posed.joints[1], rest.joints, atol=1e-6)


def test_rest_body_frame_and_labels(model_files: dict[str, Path]) -> None:
    m = make_model()
    body = SMPLBody({"female": model_files["pkl"], "male": model_files["npz"]})
    assert body.name == "smpl"
    assert body.shape_names == tuple(f"beta{i}" for i in range(N_BETAS))
    assert body.shape_range() == dict.fromkeys(body.shape_names, (-3.0, 3.0))
    rest = body.rest_body("female", np.zeros(N_BETAS))
    j = rest.joints
    assert rest.model == "smpl" and rest.gender == "female"
    assert rest.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)  # soles on the ground
    np.testing.assert_allclose(j[0, :2], 0.0, atol=1e-12)  # pelvis above the origin
    assert rest.pelvis_height > 0.5
    assert j[JOINT_INDEX["head"], 2] > j[0, 2] > j[JOINT_INDEX["left_ankle"], 2]  # z is up
    assert j[JOINT_INDEX["left_hip"], 0] > 0 > j[JOINT_INDEX["right_hip"], 0]  # left at +x
    assert j[JOINT_INDEX["left_foot"], 1] < j[JOINT_INDEX["left_ankle"], 1]  # facing -y
    # Same geometry as the template mapped by SMPL_TO_WORLD (a rigid move).
    expected = m["v_template"] @ SMPL_TO_WORLD.T
    np.testing.assert_allclose(rest.vertices - rest.vertices[0], expected - expected[0], atol=1e-12)
    assert rest.faces.dtype == np.int32 and rest.faces.shape == m["f"].shape
    assert rest.faces.min() >= 0 and rest.faces.max() < len(rest.vertices)
    assert rest.part_labels.dtype == np.int16 and rest.part_labels.shape == (len(rest.vertices),)
    assert rest.part_names == PART_NAMES
    assert set(rest.part_labels.tolist()) == set(range(len(PART_NAMES)))
    skull = rest.vertices[:, 2] > j[JOINT_INDEX["head"], 2] + 0.05
    assert skull.any() and np.all(rest.part_labels[skull] == PART_INDEX["head"])
    left_hand = np.argmin(np.linalg.norm(rest.vertices - j[JOINT_INDEX["left_hand"]], axis=1))
    assert rest.part_labels[left_hand] == PART_INDEX["hand_l"]
    assert rest.vertices[left_hand, 0] > 0.5


def test_fewer_betas_than_the_file(model_files: dict[str, Path]) -> None:
    full = SMPLBody({"neutral": model_files["npz"]})
    short = SMPLBody({"neutral": model_files["npz"]}, num_betas=4)
    betas = np.array([1.0, -2.0, 0.5, 3.0])
    a = short.rest_body("male", betas)
    b = full.rest_body("male", np.concatenate([betas, np.zeros(N_BETAS - 4)]))
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-12)
    with pytest.raises(InputError) as err:
        SMPLBody({"neutral": model_files["npz"]}, num_betas=N_BETAS + 1).rest_body(
            "male", np.zeros(N_BETAS + 1)
        )
    assert err.value.field == "shapedirs"
    with pytest.raises(InputError) as err:
        full.rest_body("male", np.zeros(3))
    assert err.value.field == "shape"


def test_paths_and_lazy_loading(tmp_path: Path, model_files: dict[str, Path]) -> None:
    body = SMPLBody({"female": model_files["npz"]})
    assert body._model("female") is body._model("female")  # loaded once
    with pytest.raises(InputError) as err:
        body.rest_body("male", np.zeros(N_BETAS))
    assert err.value.field == "paths.male"
    missing = tmp_path / "missing.pkl"
    lazy = SMPLBody({"neutral": missing})  # nothing is read yet
    with pytest.raises(InputError) as err:
        lazy.rest_body("female", np.zeros(N_BETAS))
    assert err.value.source == str(missing)
    with pytest.raises(InputError):
        SMPLBody({"child": model_files["npz"]})
    with pytest.raises(InputError):
        SMPLBody({"neutral": model_files["npz"]}).rest_body("other", np.zeros(N_BETAS))


class _Evil:
    def __init__(self, func, args) -> None:
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


@pytest.mark.parametrize("kind", ["os.system", "builtins.eval", "subprocess.call"])
def test_foreign_pickle_is_refused_before_running(tmp_path: Path, kind: str) -> None:
    marker = tmp_path / "pwned"
    command = f"echo pwned > {marker}"
    evil = {
        "os.system": _Evil(os.system, (command,)),
        "builtins.eval": _Evil(builtins.eval, (f"open({str(marker)!r}, 'w').write('pwned')",)),
        "subprocess.call": _Evil(subprocess.call, (["sh", "-c", command],)),
    }[kind]
    path = tmp_path / "model.pkl"
    path.write_bytes(pickle.dumps(dict(make_model(), v_template=evil), protocol=2))
    with pytest.raises(InputError) as err:
        SMPLBody({"neutral": path}).rest_body("female", np.zeros(N_BETAS))
    assert err.value.source == str(path)
    assert err.value.field == "pickle"
    assert err.value.got.split(".")[-1] == kind.split(".")[-1]  # os.system pickles as posix.system
    assert not marker.exists()


def _corrupt(arrays: dict, key: str, value) -> dict:
    out = dict(arrays)
    if value is None:
        del out[key]
    else:
        out[key] = value
    return out


@pytest.mark.parametrize(
    ("key", "change"),
    [
        ("weights", lambda m: m["weights"][:, :23]),
        ("weights", lambda m: m["weights"] * 2.0),
        ("posedirs", lambda m: m["posedirs"][:, :, :200]),
        ("shapedirs", lambda m: m["shapedirs"][:-1]),
        ("J_regressor", lambda m: m["J_regressor"][:23]),
        ("v_template", lambda m: m["v_template"][:, :2]),
        ("f", lambda m: m["f"] + len(m["v_template"])),
        ("kintree_table", lambda m: m["kintree_table"][:, ::-1]),
        ("J_regressor", lambda m: None),
        ("weights", lambda m: None),
    ],
)
@pytest.mark.parametrize("suffix", [".npz", ".pkl"])
def test_bad_arrays_name_file_and_key(tmp_path: Path, key: str, change, suffix: str) -> None:
    arrays = make_model()
    bad = _corrupt(arrays, key, change(arrays))
    path = tmp_path / f"bad{suffix}"
    if suffix == ".npz":
        np.savez(path, **bad)
    else:
        path.write_bytes(pickle.dumps(bad, protocol=2))
    with pytest.raises(InputError) as err:
        SMPLBody({"neutral": path}).rest_body("male", np.zeros(N_BETAS))
    assert err.value.source == str(path)
    assert err.value.field == key
    assert key in str(err.value)
