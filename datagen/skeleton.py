"""The canonical 24-joint skeleton that every motion source and body model speaks.

Conventions (docs/architecture.md, "Conventions"):

- World: right-handed, z up, metres; the ground is the plane z = 0.
- `poses (F, 72)`: axis-angle per joint. Joints 1..23 use SMPL's numbers exactly: each is a
  rotation relative to the parent, expressed in the axes of SMPL's body frame (y up, facing +z),
  so AMASS and CLOTH3D joint rotations are used verbatim.
- The root (joint 0) rotates the upright body in the z-up world: zero means standing upright,
  facing -y, the body's left at +x (the SMPL body after CLOTH3D's root rotation of +90 degrees
  about x). SMPL/AMASS/CLOTH3D roots convert with `smpl_root_to_canonical`.
- Pose zero is the T-pose.
- `trans (F, 3)`: the world position of the pelvis joint (not SMPL's offset-from-template).

In world axes, a child's local rotation L_j is S L_j S^T with S = SMPL_TO_WORLD; the helpers
`local_to_world_axes` and `world_axes_to_local` convert, and `forward_kinematics` applies it.
"""

from __future__ import annotations

import numpy as np

from datagen.rotations import axis_angle_to_matrix, matrix_to_axis_angle

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)
NUM_JOINTS = len(JOINT_NAMES)
PARENTS: tuple[int, ...] = (
    -1,
    0,
    0,
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    9,
    9,
    12,
    13,
    14,
    16,
    17,
    18,
    19,
    20,
    21,
)
JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}

# Left/right pairs, for mirroring motions.
MIRROR = tuple(
    JOINT_INDEX[n.replace("left_", "right_")]
    if n.startswith("left_")
    else JOINT_INDEX[n.replace("right_", "left_")]
    if n.startswith("right_")
    else i
    for i, n in enumerate(JOINT_NAMES)
)

# Rotation taking SMPL's body frame (y up, facing +z) to ours (z up, facing -y).
SMPL_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# T-pose joint positions of the reference body (Anny, female, every other phenotype 0.5, adult
# age 0.8), pelvis at the origin. Motion sources use it for bone directions and for the pelvis
# height their root trajectory refers to; each subject's own skeleton comes from its body model.
# Regenerate with `python -m datagen.body.anny_model --reference-skeleton` (a test checks it).
REFERENCE_REST_JOINTS = np.array(
    [
        [0.0000, 0.0000, 0.0000],
        [0.1043, 0.0070, -0.0145],
        [-0.1043, 0.0070, -0.0145],
        [0.0000, 0.0264, 0.1474],
        [0.1391, -0.0244, -0.4420],
        [-0.1391, -0.0244, -0.4420],
        [0.0000, 0.0149, 0.2461],
        [0.1836, 0.0162, -0.8686],
        [-0.1836, 0.0162, -0.8686],
        [0.0000, 0.0115, 0.3889],
        [0.1933, -0.1293, -0.9269],
        [-0.1933, -0.1293, -0.9269],
        [0.0000, 0.0047, 0.5502],
        [0.0248, -0.0137, 0.4732],
        [-0.0248, -0.0137, 0.4732],
        [0.0000, -0.0312, 0.6556],
        [0.1680, -0.0142, 0.4575],
        [-0.1680, -0.0142, 0.4575],
        [0.4427, -0.0142, 0.4575],
        [-0.4427, -0.0142, 0.4575],
        [0.6725, -0.0142, 0.4575],
        [-0.6725, -0.0142, 0.4575],
        [0.7799, -0.0142, 0.4575],
        [-0.7799, -0.0142, 0.4575],
    ]
)
REFERENCE_PELVIS_HEIGHT = 0.9524


def forward_kinematics(
    poses: np.ndarray, trans: np.ndarray, rest_joints: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World rotations (F, 24, 3, 3) and joint positions (F, 24, 3) of a canonical pose sequence.

    `rest_joints` (24, 3) is the T-pose skeleton; only offsets between joints matter, the pelvis is
    placed at `trans`.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, NUM_JOINTS, 3)
    trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
    local = local_to_world_axes(axis_angle_to_matrix(poses))  # (F, 24, 3, 3)
    n_frames = poses.shape[0]
    world_rot = np.empty_like(local)
    world_pos = np.empty((n_frames, NUM_JOINTS, 3))
    world_rot[:, 0] = local[:, 0]
    world_pos[:, 0] = trans
    for j in range(1, NUM_JOINTS):
        p = PARENTS[j]
        world_rot[:, j] = world_rot[:, p] @ local[:, j]
        offset = rest_joints[j] - rest_joints[p]
        world_pos[:, j] = world_pos[:, p] + world_rot[:, p] @ offset
    return world_rot, world_pos


def local_to_world_axes(local: np.ndarray) -> np.ndarray:
    """Canonical local rotation matrices (..., 24, 3, 3) -> the same rotations in world axes
    (the root is already in world axes; children are conjugated by SMPL_TO_WORLD)."""
    out = np.array(local, dtype=np.float64, copy=True)
    out[..., 1:, :, :] = SMPL_TO_WORLD @ out[..., 1:, :, :] @ SMPL_TO_WORLD.T
    return out


def world_axes_to_local(rot: np.ndarray) -> np.ndarray:
    """Inverse of `local_to_world_axes`: rotations relative to the parent expressed in world axes
    (..., 24, 3, 3) -> canonical local rotation matrices."""
    out = np.array(rot, dtype=np.float64, copy=True)
    out[..., 1:, :, :] = SMPL_TO_WORLD.T @ out[..., 1:, :, :] @ SMPL_TO_WORLD
    return out


def world_to_local(world_rot: np.ndarray) -> np.ndarray:
    """World joint rotations (F, 24, 3, 3) -> canonical poses (F, 72)."""
    local = np.empty_like(world_rot)
    local[:, 0] = world_rot[:, 0]
    for j in range(1, NUM_JOINTS):
        p = PARENTS[j]
        local[:, j] = np.swapaxes(world_rot[:, p], -1, -2) @ world_rot[:, j]
    local = world_axes_to_local(local)
    return matrix_to_axis_angle(local).reshape(world_rot.shape[0], NUM_JOINTS * 3)


def smpl_root_to_canonical(poses: np.ndarray) -> np.ndarray:
    """SMPL/AMASS/CLOTH3D poses (root acts on the y-up SMPL body) -> canonical (root acts on the
    z-up body). Only the root rotation changes: R_ours = R_smpl @ SMPL_TO_WORLD^T."""
    out = np.array(poses, dtype=np.float64, copy=True).reshape(-1, NUM_JOINTS * 3)
    root = axis_angle_to_matrix(out[:, :3])
    out[:, :3] = matrix_to_axis_angle(root @ SMPL_TO_WORLD.T)
    return out


def canonical_root_to_smpl(poses: np.ndarray) -> np.ndarray:
    """Inverse of `smpl_root_to_canonical` (for users who drive an SMPL model with our poses)."""
    out = np.array(poses, dtype=np.float64, copy=True).reshape(-1, NUM_JOINTS * 3)
    root = axis_angle_to_matrix(out[:, :3])
    out[:, :3] = matrix_to_axis_angle(root @ SMPL_TO_WORLD)
    return out


def mirror_poses(poses: np.ndarray) -> np.ndarray:
    """Mirror a pose sequence left <-> right (reflection through the x = 0 plane)."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, NUM_JOINTS, 3)
    out = p[:, list(MIRROR)].copy()
    # Reflecting x (in both frames: SMPL_TO_WORLD fixes the x axis): an axis-angle vector, a
    # pseudo-vector, maps (x, y, z) -> (x, -y, -z).
    out[..., 1] *= -1.0
    out[..., 2] *= -1.0
    return out.reshape(-1, NUM_JOINTS * 3)
