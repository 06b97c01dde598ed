"""Settle a garment on a static body: used to sew template panels together around the rest body
and to let a garment relax before its sequence starts."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from datagen.sim.collider import BodyCollider
from datagen.sim.effects import Effects
from datagen.sim.fabrics import Fabric, get_fabric
from datagen.sim.model import build_cloth_model
from datagen.sim.solvers import SolverSettings, make_solver
from datagen.types import Garment


def drape(
    garment: Garment,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    frames: int = 60,
    fps: float = 30.0,
    substeps: int = 20,
    gravity: bool = False,
    fabric: Fabric | None = None,
    air_drag: float = 2.0,
    thickness: float | None = None,
) -> np.ndarray:
    """Final positions (V, 3) of `garment` after `frames` of simulation around the static body.

    Seams (`garment.seams`) are pulled closed; a strong air drag (kg/(m^2 s), well above any
    fabric's) removes the motion so the result is a rest state, not a snapshot of a swing.
    """
    fab = fabric or get_fabric(garment.fabric)
    fab = replace(fab, air_drag=max(fab.air_drag, air_drag))
    if thickness is not None:
        fab = replace(fab, thickness=thickness)
    model = build_cloth_model([(garment, fab)])
    collider = BodyCollider(body_faces, np.ones(len(body_faces), dtype=bool), len(body_vertices))
    effects = Effects(gravity=gravity, friction=True)
    solver = make_solver("xpbd", model, effects, SolverSettings(substeps=substeps))
    h = 1.0 / fps / substeps
    collider.set_frames(body_vertices, body_vertices)
    for _ in range(frames):
        solver.search(collider, 1.0)
        solver.advance_frame(collider, substeps, h)
    x, _ = solver.get_state()
    return x
