"""Rotation helpers in the canonical pose format (axis-angle, float64).

Thin wrappers over scipy's Rotation so that every module converts the same way; batched over any
leading shape.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices."""
    aa = np.asarray(aa, dtype=np.float64)
    flat = aa.reshape(-1, 3)
    mats = Rotation.from_rotvec(flat).as_matrix()
    return mats.reshape(aa.shape[:-1] + (3, 3))


def matrix_to_axis_angle(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle with angle in [0, pi]."""
    m = np.asarray(m, dtype=np.float64)
    flat = m.reshape(-1, 3, 3)
    aa = Rotation.from_matrix(flat).as_rotvec()
    return aa.reshape(m.shape[:-2] + (3,))


def axis_angle_to_quat(aa: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 4) unit quaternions, scalar last (x, y, z, w)."""
    aa = np.asarray(aa, dtype=np.float64)
    return Rotation.from_rotvec(aa.reshape(-1, 3)).as_quat().reshape(aa.shape[:-1] + (4,))


def quat_to_axis_angle(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_rotvec().reshape(q.shape[:-1] + (3,))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation matrix taking direction a onto direction b (both 3-vectors)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite directions: any perpendicular axis works.
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        return Rotation.from_rotvec(np.pi * perp).as_matrix()
    angle = np.arctan2(s, c)
    return Rotation.from_rotvec(axis / s * angle).as_matrix()


def slerp_axis_angle(poses: np.ndarray, t_src: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Resample per-joint rotations (F, J, 3) given at times t_src to times t_dst with slerp.

    Times outside [t_src[0], t_src[-1]] are clamped to the ends (no extrapolation of rotations).
    """
    poses = np.asarray(poses, dtype=np.float64)
    n_frames, n_joints, _ = poses.shape
    t_dst = np.clip(np.asarray(t_dst, dtype=np.float64), t_src[0], t_src[-1])
    if n_frames == 1:
        return np.repeat(poses, len(t_dst), axis=0)
    idx = np.clip(np.searchsorted(t_src, t_dst, side="right") - 1, 0, n_frames - 2)
    span = t_src[idx + 1] - t_src[idx]
    alpha = np.where(span > 0, (t_dst - t_src[idx]) / np.where(span > 0, span, 1.0), 0.0)
    q0 = axis_angle_to_quat(poses[idx])  # (T, J, 4)
    q1 = axis_angle_to_quat(poses[idx + 1])
    # Shortest arc: flip q1 where the dot product is negative.
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    a = alpha[:, None, None]
    small = sin_theta < 1e-8
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / np.where(small, 1.0, sin_theta))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1.0, sin_theta))
    q = w0 * q0 + w1 * q1
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_to_axis_angle(q)


def angular_velocity(poses: np.ndarray, fps: float) -> np.ndarray:
    """Relative-rotation angular speed (rad/s) between consecutive frames, shape (F-1, J)."""
    r = axis_angle_to_matrix(poses)
    rel = np.einsum("fjab,fjac->fjbc", r[:-1], r[1:])  # R_f^T R_{f+1}
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(cos) * fps
