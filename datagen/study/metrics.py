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


def collider_penetration(positions: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                         thickness: float, frames: int | None = None) -> tuple[float, float]:
    """The largest share, over frames 1..`frames` (all after the start by default), of cloth
    vertices inside the collider and of those deeper than `thickness` (the QA's deep_share),
    for a peer's trajectory (F, V, 3) against the collider's frames `vertices` (F, Vc, 3).
    Each vertex is signed by its closest triangle's outward normal, so a vertex that passed
    through a limb counts as outside of it: a lower bound."""
    import trimesh

    last = len(positions) - 1 if frames is None else frames
    inside = deep = 0.0
    for f in range(1, last + 1):
        mesh = trimesh.Trimesh(vertices[min(f, len(vertices) - 1)], faces, process=False)
        closest, _, tri = mesh.nearest.on_surface(positions[f])
        signed = np.einsum("ij,ij->i", positions[f] - closest, mesh.face_normals[tri])
        inside = max(inside, float(np.mean(signed < 0.0)))
        deep = max(deep, float(np.mean(signed < -thickness)))
    return inside, deep


def scene_penetration(positions: np.ndarray, scene,
                      frames: int | None = None) -> tuple[float, float]:
    """collider_penetration of a trajectory of a study scene (datagen.study.scenes.StudyScene)
    against its collider's used faces, at its fabric's thickness."""
    from datagen.sim.fabrics import get_fabric

    track = scene.track
    return collider_penetration(positions, track.vertices, track.faces[track.face_mask],
                                get_fabric(scene.fabric).thickness, frames)
