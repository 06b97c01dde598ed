"""Accuracy measures against a reference trajectory."""

from __future__ import annotations

import numpy as np


def rms_by_frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F,) RMS over vertices of the distance between two trajectories, frame by frame."""
    d = np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1)
    return np.sqrt(np.mean(d * d, axis=-1))


def rms_distance(a: np.ndarray, b: np.ndarray, frames: int | None = None) -> float:
    """RMS over frames and vertices of the distance between two trajectories (F, V, 3)."""
    sl = slice(0, frames)
    d = np.linalg.norm(np.asarray(a)[sl] - np.asarray(b)[sl], axis=-1)
    return float(np.sqrt(np.mean(d * d)))


def max_distance(a: np.ndarray, b: np.ndarray, frames: int | None = None) -> float:
    sl = slice(0, frames)
    return float(np.linalg.norm(np.asarray(a)[sl] - np.asarray(b)[sl], axis=-1).max())


def final_distance(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance of the last frames (the drape the scene comes to rest in)."""
    return rms_distance(np.asarray(a)[-1:], np.asarray(b)[-1:])
