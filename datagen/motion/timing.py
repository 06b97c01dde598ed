"""Time handling of canonical motions: resampling, windowing, and the lead-in from rest."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from datagen.errors import InputError
from datagen.rotations import slerp_axis_angle
from datagen.skeleton import NUM_JOINTS
from datagen.types import Motion


def resample(motion: Motion, fps: float) -> Motion:
    """The same motion sampled at `fps`: quaternion slerp per joint, linear root translation."""
    if fps <= 0:
        raise InputError(motion.source, "fps", "a positive frame rate", fps)
    if abs(fps - motion.fps) < 1e-9:
        return motion
    t_src = np.arange(motion.n_frames) / motion.fps
    n_out = int(np.floor(motion.duration * fps + 1e-9)) + 1
    t_dst = np.arange(n_out) / fps
    poses = slerp_axis_angle(motion.poses.reshape(-1, NUM_JOINTS, 3), t_src, t_dst)
    trans = np.stack([np.interp(t_dst, t_src, motion.trans[:, k]) for k in range(3)], axis=1)
    return Motion(
        poses=poses.reshape(n_out, NUM_JOINTS * 3),
        trans=trans,
        fps=fps,
        label=motion.label,
        source=motion.source,
        pelvis_height=motion.pelvis_height,
    )


def window(motion: Motion, start: int, n_frames: int) -> Motion:
    """Frames [start, start + n_frames) of a motion; an error if the motion is too short."""
    if start < 0 or n_frames <= 0:
        raise InputError(motion.source, "window", "start >= 0 and frames > 0", (start, n_frames))
    if start + n_frames > motion.n_frames:
        raise InputError(
            motion.source,
            "frames",
            f"at most {motion.n_frames - start} frames from frame {start} "
            f"({motion.n_frames} at {motion.fps:g} fps)",
            n_frames,
        )
    sl = slice(start, start + n_frames)
    return Motion(
        poses=motion.poses[sl].copy(),
        trans=motion.trans[sl].copy(),
        fps=motion.fps,
        label=motion.label,
        source=motion.source,
        pelvis_height=motion.pelvis_height,
    )


def _heading_only(root_aa: np.ndarray) -> np.ndarray:
    """The rotation about world z contained in a root rotation (so the rest pose faces the same
    way as the motion's first frame)."""
    r = Rotation.from_rotvec(root_aa)
    forward = r.apply([0.0, -1.0, 0.0])  # the body faces -y at rest
    yaw = np.arctan2(forward[0], -forward[1])
    return Rotation.from_euler("z", yaw).as_rotvec()


def rest_pose_for(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """The T-pose (72,) facing the motion's initial heading, and its pelvis position (3,)."""
    pose = np.zeros(NUM_JOINTS * 3)
    pose[:3] = _heading_only(motion.poses[0, :3])
    trans = np.array([motion.trans[0, 0], motion.trans[0, 1], motion.pelvis_height])
    return pose, trans


def add_lead_in(motion: Motion, n_frames: int) -> Motion:
    """Prepend `n_frames` that move smoothly from the rest T-pose into the motion's first frame.

    Rotations ease with a smoothstep (zero angular velocity at the rest end); the pelvis follows a
    cubic Hermite curve that starts at rest and arrives with the motion's initial velocity, so a
    walk does not start with a jerk.
    """
    if n_frames <= 0:
        return motion
    rest_pose, rest_trans = rest_pose_for(motion)
    s = np.arange(n_frames) / n_frames  # excludes 1: frame n_frames is the motion's first frame
    ease = s * s * (3.0 - 2.0 * s)
    both = np.stack([rest_pose, motion.poses[0]]).reshape(2, NUM_JOINTS, 3)
    poses = slerp_axis_angle(both, np.array([0.0, 1.0]), ease).reshape(n_frames, NUM_JOINTS * 3)

    duration = n_frames / motion.fps
    if motion.n_frames > 1:
        v1 = (motion.trans[1] - motion.trans[0]) * motion.fps
    else:
        v1 = np.zeros(3)
    p1 = motion.trans[0]
    # Start half a lead-in "behind" along the initial velocity, at standing height.
    p0 = np.array([p1[0] - 0.5 * v1[0] * duration, p1[1] - 0.5 * v1[1] * duration, rest_trans[2]])
    h00 = 2 * s**3 - 3 * s**2 + 1
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    trans = h00[:, None] * p0 + h01[:, None] * p1 + h11[:, None] * (v1 * duration)
    return Motion(
        poses=np.concatenate([poses, motion.poses]),
        trans=np.concatenate([trans, motion.trans]),
        fps=motion.fps,
        label=motion.label,
        source=motion.source,
        pelvis_height=motion.pelvis_height,
    )


def retarget_root(motion: Motion, pelvis_height: float) -> Motion:
    """Scale the root trajectory to a subject whose standing pelvis is `pelvis_height` high, so
    foot contacts stay consistent for taller or shorter bodies."""
    scale = pelvis_height / motion.pelvis_height
    return Motion(
        poses=motion.poses,
        trans=motion.trans * scale,
        fps=motion.fps,
        label=motion.label,
        source=motion.source,
        pelvis_height=pelvis_height,
    )


# The fastest a person's pelvis moves (sprinters reach about 12 m/s); a faster frame-to-frame
# step is a glitch in the capture (a dropped frame, a wrapped coordinate), not a motion.
MAX_ROOT_SPEED = 12.0  # m/s


def check_root_speed(motion: Motion, limit: float = MAX_ROOT_SPEED) -> None:
    """Reject a motion whose root jumps faster than a body can move: the body and the cloth
    would have to teleport. Raises RejectedSequence naming the frame and the speed."""
    from datagen.errors import RejectedSequence

    if motion.n_frames < 2:
        return
    step = np.linalg.norm(np.diff(motion.trans, axis=0), axis=1)
    speed = step * motion.fps
    worst = int(np.argmax(speed))
    if speed[worst] > limit:
        raise RejectedSequence(
            "motion",
            f"the root moves {step[worst]:.2f} m between frames {worst} and {worst + 1} "
            f"({speed[worst]:.1f} m/s, over the {limit:g} m/s a body can move): a glitch in "
            f"the motion ({motion.source})",
            (worst, worst + 1),
        )
