"""Arm clearance: fit a motion's arms to the subject's girth before any mesh repair.

Motions come from skeletons (capture subjects, the procedural reference body) whose arms hang
close to their own torso; on a broader subject the same joint angles put the arms inside the
torso, hips or thighs, several centimetres deep, which no local mesh repair can undo sensibly.
Here each arm is abducted about the shoulder, away from the torso, by the angle that clears the
deepest contact plus the repair gap, frame by frame, with the angle spread over neighbouring
frames so the arm does not pop. The adjusted poses are what is simulated and stored.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d, uniform_filter1d
from scipy.spatial.transform import Rotation

from datagen.body.parts import PART_NAMES
from datagen.rotations import matrix_to_axis_angle
from datagen.skeleton import JOINT_INDEX, SMPL_TO_WORLD, forward_kinematics

SIDES = {"left": 1.0, "right": -1.0}
ARM_PARTS = {
    "left": frozenset({"upperarm_l", "forearm_l", "hand_l"}),
    "right": frozenset({"upperarm_r", "forearm_r", "hand_r"}),
}
BODY_PARTS = frozenset({"pelvis", "spine_lower", "spine_mid", "chest", "thigh_l", "thigh_r"})
SMOOTH_SECONDS = 0.15  # the clearance angle ramps over about this long
MAX_ANGLE = np.radians(35.0)  # a clearance beyond this is not a fit, it is a different motion


def required_abduction(contacts, joints: np.ndarray, n_frames: int, gap: float) -> np.ndarray:
    """(2, F) angles (left, right) that clear each frame's deepest arm-body contact."""
    need = np.zeros((2, n_frames))
    for c in contacts:
        names = {PART_NAMES[c.part_a], PART_NAMES[c.part_b]}
        for k, side in enumerate(SIDES):
            if names & ARM_PARTS[side] and names & BODY_PARTS:
                shoulder = joints[c.frame, JOINT_INDEX[f"{side}_shoulder"]]
                lever = max(float(np.linalg.norm(c.centre - shoulder)), 0.08)
                angle = np.arctan2(c.depth + gap + 0.005, lever)
                need[k, c.frame] = max(need[k, c.frame], angle)
    return need


def smooth_angles(need: np.ndarray, fps: float) -> np.ndarray:
    """Spread each angle over neighbouring frames: never below the need, and ramped."""
    width = max(1, int(round(SMOOTH_SECONDS * fps)))
    grown = maximum_filter1d(need, size=2 * width + 1, axis=1, mode="nearest")
    ramped = uniform_filter1d(grown, size=2 * width + 1, axis=1, mode="nearest")
    return np.maximum(ramped, need)


def abduct_arms(
    poses: np.ndarray, trans: np.ndarray, rest_joints: np.ndarray, angles: np.ndarray
) -> np.ndarray:
    """Poses with each upper arm rotated about the shoulder, away from the torso's midline, by
    `angles` (2, F) radians (left, right)."""
    out = np.array(poses, dtype=np.float64, copy=True)
    world, joints = forward_kinematics(out, trans, rest_joints)
    chest = world[:, JOINT_INDEX["spine3"]]
    for k, (side, sign) in enumerate(SIDES.items()):
        if not np.any(angles[k] > 0):
            continue
        s, c = JOINT_INDEX[f"{side}_shoulder"], JOINT_INDEX[f"{side}_collar"]
        e = JOINT_INDEX[f"{side}_elbow"]
        arm = joints[:, e] - joints[:, s]
        arm /= np.linalg.norm(arm, axis=1, keepdims=True)
        outward = chest @ np.array([sign, 0.0, 0.0])
        axis = np.cross(arm, outward)
        norm = np.linalg.norm(axis, axis=1, keepdims=True)
        ok = (norm[:, 0] > 1e-3) & (angles[k] > 0)
        axis = np.where(ok[:, None], axis / np.maximum(norm, 1e-12), 0.0)
        turn = Rotation.from_rotvec(axis * angles[k][:, None]).as_matrix()
        new_world = turn @ world[:, s]
        local_world_axes = np.swapaxes(world[:, c], -1, -2) @ new_world
        local = SMPL_TO_WORLD.T @ local_world_axes @ SMPL_TO_WORLD
        out[:, 3 * s : 3 * s + 3] = np.where(
            ok[:, None], matrix_to_axis_angle(local), out[:, 3 * s : 3 * s + 3]
        )
    return out


def clear_arms(model, rest, poses, trans, detector, gap: float, fps: float, max_rounds: int = 4):
    """Poses whose arms clear the subject's torso, hips and thighs, the (2, F) total angles
    added, and the posed body of the final poses."""
    total = np.zeros((2, len(poses)))
    posed = model.pose(rest, poses, trans)
    for _ in range(max_rounds):
        contacts = detector.detect(posed.vertices)
        need = required_abduction(contacts, posed.joints, len(poses), gap)
        if not need.any():
            break
        step = smooth_angles(need, fps)
        step = np.minimum(step, np.maximum(MAX_ANGLE - total, 0.0))
        if not step.any():
            break
        poses = abduct_arms(poses, trans, rest.joints, step)
        total += step
        posed = model.pose(rest, poses, trans)
    return poses, total, posed
