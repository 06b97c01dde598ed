"""AMASS-style .npz import on small files written here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from datagen.errors import InputError
from datagen.motion.amass import load_amass
from datagen.motion.bvh import lowest_sole_height
from datagen.skeleton import (
    REFERENCE_PELVIS_HEIGHT,
    REFERENCE_REST_JOINTS,
    SMPL_TO_WORLD,
    canonical_root_to_smpl,
    forward_kinematics,
    smpl_root_to_canonical,
)

UPRIGHT_SMPL_ROOT = np.array([np.pi / 2, 0.0, 0.0])  # AMASS: +90 degrees about x stands SMPL up


def write_npz(tmp_path: Path, name: str = "clip.npz", **fields) -> Path:
    path = tmp_path / name
    np.savez(path, **fields)
    return path


def sample(n: int = 6, width: int = 72, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = rng.normal(scale=0.2, size=(n, width))
    poses[:, :3] = UPRIGHT_SMPL_ROOT + rng.normal(scale=0.1, size=(n, 3))
    trans = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0) + [0.3, -0.2, 0.9]
    return {
        "poses": poses,
        "trans": trans,
        "mocap_framerate": np.array(120.0),
        "betas": rng.normal(size=16),
        "gender": np.array("female"),
    }


def same_rotations(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> bool:
    ra = Rotation.from_rotvec(np.reshape(a, (-1, 3))).as_matrix()
    rb = Rotation.from_rotvec(np.reshape(b, (-1, 3))).as_matrix()
    return bool(np.allclose(ra, rb, atol=atol))


def test_round_trip(tmp_path: Path):
    data = sample()
    motion = load_amass(write_npz(tmp_path, **data))
    assert motion.n_frames == 6 and motion.fps == 120.0
    assert motion.source == "amass:clip.npz" and motion.label == "clip"
    assert motion.pelvis_height == REFERENCE_PELVIS_HEIGHT
    # Body joints verbatim, root through smpl_root_to_canonical.
    np.testing.assert_allclose(motion.poses[:, 3:], data["poses"][:, 3:], atol=1e-12)
    assert same_rotations(motion.poses[:, :3], smpl_root_to_canonical(data["poses"])[:, :3])
    # The root conversion is R_smpl @ SMPL_TO_WORLD^T, checked directly.
    root = Rotation.from_rotvec(data["poses"][:, :3]).as_matrix() @ SMPL_TO_WORLD.T
    np.testing.assert_allclose(
        Rotation.from_rotvec(motion.poses[:, :3]).as_matrix(), root, atol=1e-9
    )
    # trans: horizontal kept, vertical only shifted (grounded), by the shared grounding.
    np.testing.assert_allclose(motion.trans[:, :2], data["trans"][:, :2], atol=1e-12)
    shift = motion.trans[:, 2] - data["trans"][:, 2]
    np.testing.assert_allclose(shift, shift[0], atol=1e-12)
    lowest = lowest_sole_height(motion.poses, motion.trans)
    assert np.percentile(lowest, 5) == pytest.approx(0.0, abs=1e-9)
    assert load_amass(write_npz(tmp_path, **data), label="walk").label == "walk"


def test_root_conversion_of_identity_and_upright_roots(tmp_path: Path):
    """An identity SMPL root is the y-up body as is: in the z-up world it lies on its back
    (canonical root = -90 degrees about x, head towards +y). AMASS's upright bodies carry
    +90 degrees about x, which becomes the canonical identity: standing, facing -y."""
    poses = np.zeros((2, 72))
    poses[1, :3] = UPRIGHT_SMPL_ROOT
    motion = load_amass(
        write_npz(tmp_path, poses=poses, trans=np.zeros((2, 3)), mocap_framerate=30.0)
    )
    np.testing.assert_allclose(motion.poses[0, :3], [-np.pi / 2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(motion.poses[1, :3], 0.0, atol=1e-12)
    _, joints = forward_kinematics(motion.poses, motion.trans, REFERENCE_REST_JOINTS)
    head = joints[:, 15] - joints[:, 0]
    np.testing.assert_allclose(head[0] / np.linalg.norm(head[0]), [0, 1.0, 0.05], atol=0.01)
    np.testing.assert_allclose(head[1] / np.linalg.norm(head[1]), [0, -0.05, 1.0], atol=0.01)


def test_canonical_roots_convert_back_to_smpl():
    """Users who drive an SMPL body with our poses convert the root back: the canonical
    identity (standing, facing -y) is AMASS's upright +90 degrees about x, every root returns
    to the SMPL one it came from, and the other joints are untouched."""
    back = canonical_root_to_smpl(np.zeros((1, 72)))
    np.testing.assert_allclose(back[0, :3], UPRIGHT_SMPL_ROOT, atol=1e-12)
    np.testing.assert_allclose(back[0, 3:], 0.0)
    poses = sample(n=8)["poses"]
    poses[0, :3] = [0.0, 0.0, 3.0]  # near pi: the axis-angle form is not unique there
    again = canonical_root_to_smpl(smpl_root_to_canonical(poses))
    assert same_rotations(again[:, :3], poses[:, :3])
    np.testing.assert_array_equal(again[:, 3:], poses[:, 3:])


def test_upright_t_pose_stands_on_the_ground(tmp_path: Path):
    poses = np.zeros((3, 72))
    poses[:, :3] = UPRIGHT_SMPL_ROOT
    trans = np.array([[0.0, 0.0, 0.3], [0.1, 0.0, 0.3], [0.2, 0.0, 0.3]])
    motion = load_amass(write_npz(tmp_path, poses=poses, trans=trans, mocap_framerate=60))
    np.testing.assert_allclose(motion.trans[:, 2], REFERENCE_PELVIS_HEIGHT, atol=1e-9)


@pytest.mark.parametrize("width", [156, 165])
def test_smplh_and_smplx_widths(tmp_path: Path, width: int):
    data = sample(width=width, seed=width)
    motion = load_amass(write_npz(tmp_path, **data))
    np.testing.assert_allclose(motion.poses[:, 3:66], data["poses"][:, 3:66], atol=1e-12)
    np.testing.assert_allclose(motion.poses[:, 66:], 0.0)  # SMPL's hand joints: zero
    assert same_rotations(motion.poses[:, :3], smpl_root_to_canonical(data["poses"][:, :72])[:, :3])


def test_frame_rate_key_alias(tmp_path: Path):
    data = sample()
    data["mocap_frame_rate"] = data.pop("mocap_framerate") * 0.5
    assert load_amass(write_npz(tmp_path, **data)).fps == 60.0


def assert_input_error(path: Path, field: str | None) -> None:
    """Loading `path` raises InputError naming the file and, where given, the field."""
    with pytest.raises(InputError) as exc:
        load_amass(path)
    message = str(exc.value)
    assert path.name in message, message
    if field is not None:
        assert f"'{field}'" in message, message


def test_missing_poses(tmp_path: Path):
    data = sample()
    del data["poses"]
    path = write_npz(tmp_path, "noposes.npz", **data)
    assert_input_error(path, "poses")
    with pytest.raises(InputError, match="missing"):
        load_amass(path)


def test_mismatched_lengths(tmp_path: Path):
    data = sample()
    data["trans"] = data["trans"][:-1]
    assert_input_error(write_npz(tmp_path, "short.npz", **data), "trans")


@pytest.mark.parametrize("rate", [0.0, -30.0, np.nan])
def test_bad_frame_rate(tmp_path: Path, rate: float):
    data = sample()
    data["mocap_framerate"] = np.array(rate)
    assert_input_error(write_npz(tmp_path, "rate.npz", **data), "mocap_framerate")


def test_missing_frame_rate(tmp_path: Path):
    data = sample()
    del data["mocap_framerate"]
    assert_input_error(write_npz(tmp_path, "norate.npz", **data), "mocap_framerate")


def test_bad_shapes_and_values(tmp_path: Path):
    data = sample()
    narrow = dict(data, poses=data["poses"][:, :60])
    assert_input_error(write_npz(tmp_path, "narrow.npz", **narrow), "poses")
    flat = dict(data, poses=data["poses"][0])
    assert_input_error(write_npz(tmp_path, "flat.npz", **flat), "poses")
    nan = dict(data, trans=data["trans"].copy())
    nan["trans"][3, 1] = np.inf
    assert_input_error(write_npz(tmp_path, "inf.npz", **nan), "trans")
    text = dict(data, poses=np.array([["a"] * 72] * 6))
    assert_input_error(write_npz(tmp_path, "text.npz", **text), "poses")


def test_not_an_npz(tmp_path: Path):
    text = tmp_path / "notes.npz"
    text.write_text("poses, trans\n1, 2\n")
    assert_input_error(text, None)
    single = tmp_path / "array.npz"
    with single.open("wb") as f:
        np.save(f, np.zeros((3, 72)))
    assert_input_error(single, None)
    assert_input_error(tmp_path / "absent.npz", None)
