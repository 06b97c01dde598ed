"""A body part folding onto cloth from beyond a grid cell (the fast kick's thigh closing over
trousers that track the calf), as a small scene: used by tests/test_sim_physics.py alone and by
tests/test_sim_batch.py in a batch."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen.sim.fabrics import FABRICS
from datagen.sim.simulate import ColliderTrack
from datagen.types import Garment

LENGTH, WIDTH, THICK = 0.45, 0.3, 0.04  # the plate (m)
HINGE = np.array([0.06, 0.0, 0.5])
ANGLES = np.radians(np.r_[np.linspace(90.0, 0.0, 9), np.zeros(6)])


def _rotation(a: float) -> np.ndarray:  # 90 degrees: horizontal, its face down
    return np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0],
                     [np.sin(a), 0.0, np.cos(a)]])


@dataclass
class PlateFold:
    leg: Garment
    track: ColliderTrack

    def swallowed(self, frames: np.ndarray, shift: np.ndarray | None = None) -> list[int]:
        """Per frame of the leg's simulated positions (F, V, 3), how many of its free vertices
        are inside the plate deeper than the thickness; `shift`: where the scene was moved."""
        depth = FABRICS["cotton"].thickness
        free = np.setdiff1d(np.arange(len(self.leg.vertices)), self.leg.pinned)
        hinge = HINGE if shift is None else HINGE + shift
        counts = []
        for a, x in zip(ANGLES, np.asarray(frames, dtype=np.float64)[:, free], strict=True):
            local = (x - hinge) @ _rotation(a)
            inside = ((local[:, 0] > depth) & (local[:, 0] < THICK - depth)
                      & (np.abs(local[:, 1]) < WIDTH / 2 - depth)
                      & (local[:, 2] > -LENGTH + depth) & (local[:, 2] < -depth))
            counts.append(int(inside.sum()))
        return counts


def plate_folding_onto_trouser_leg(fold: bool) -> PlateFold:
    """A loose cotton tube (a trouser leg, radius 7 cm, its waist pinned) around a vertical
    limb (part 0, radius 5 cm), and a plate (part 1, 45 x 30 x 4 cm) hinged 1 cm outside the
    limb's top, as a thigh folds onto the calf with the body stage's 1 cm gap between them,
    swinging from horizontal down onto the limb's side over 8 frames (its far end at 1.8 m/s,
    6 cm a frame) and then holding. `fold`: whether the two parts fold onto each other in every
    frame (the body stage's flexion frames), so that the part guard looks the plate up in its
    distance field (datagen.sim.fold_fields)."""
    import trimesh

    from datagen.sim.fold_fields import FoldFields
    from datagen.sim.scenes import cylinder_mesh, tube

    lv, lf = cylinder_mesh(0.05, 0.6, sections=32, rings=24)
    plate = trimesh.creation.box(extents=(THICK, WIDTH, LENGTH))
    plate.apply_translation((THICK / 2, 0.0, -LENGTH / 2))  # its face at x = 0, hinge at 0
    pv, pf = trimesh.remesh.subdivide_to_size(plate.vertices, plate.faces, 0.02)
    vertices = np.array([np.concatenate([lv, pv @ _rotation(a).T + HINGE]) for a in ANGLES])
    faces = np.concatenate([lf, pf + len(lv)]).astype(np.int32)
    face_parts = np.r_[np.zeros(len(lf), int), np.ones(len(pf), int)]
    fields = FoldFields(vertices, faces, face_parts,
                        [(("limb",), ("plate",), frozenset(range(len(ANGLES))))],
                        {"limb": 0, "plate": 1}) if fold else None
    track = ColliderTrack(vertices, faces, np.ones(len(faces), bool), face_parts=face_parts,
                          fold_fields=fields)
    leg = tube(0.07, 0.35, 48, 18, top=0.45)
    leg.pinned = leg.loops["waist"]
    return PlateFold(leg, track)
