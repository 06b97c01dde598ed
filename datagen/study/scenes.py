"""Study scenes: deterministic cloth scenes that our solvers and Blender both simulate.

Each scene is rebuilt from its name, fabric and resolution alone, so a worker process (a float64
reference run, a Blender run) gets exactly the same geometry.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from datagen.sim.scenes import cylinder_mesh, grid_sheet, icosphere, tube
from datagen.sim.simulate import ColliderTrack, SimOptions
from datagen.types import Garment

FPS = 30.0
# Output frames after frame 0, by scene. The body scenes stop at the end of the measured second
# (their lead-in and settle come before it): every extra frame costs minutes of reference.
SCENE_FRAMES = {"sheet_sphere": 60, "tube_cylinder": 60, "skirt_body": 30, "tshirt_walk": 30}
SHEET_SIZES = {"coarse": 32, "4k": 64, "10k": 100}
TUBE_SIZES = {"coarse": (48, 24), "5k": (100, 50), "10k": (140, 70)}


@dataclass
class StudyScene:
    name: str
    fabric: str
    resolution: str
    garments: list[Garment]
    track: ColliderTrack
    frames: int  # output frames after frame 0
    horizon: int  # frames over which the dynamic error is measured
    static_from: int  # frames from which the cloth is (nearly) at rest: the final drape

    @property
    def n_vertices(self) -> int:
        return sum(len(g.vertices) for g in self.garments)


def sheet_sphere(fabric: str, resolution: str = "4k",
                 frames: int = SCENE_FRAMES["sheet_sphere"]) -> StudyScene:
    """A 1 m sheet released 25 cm above a 0.5 m sphere: it falls, hits at ~0.25 s and drapes."""
    n = SHEET_SIZES[resolution]
    sheet = grid_sheet(n, 1.0, 0.5, fabric=fabric)
    sv, sf = icosphere(0.25, 4)
    track = ColliderTrack(np.repeat(sv[None], frames + 1, axis=0), sf,
                          np.ones(len(sf), bool), FPS)
    return StudyScene("sheet_sphere", fabric, resolution, [sheet], track, frames, 30, frames)


def cylinder_motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sideways swing (15 cm at 1 Hz) and a twist (0.6 rad at 1 Hz) of the cylinder."""
    shift = np.stack([0.15 * np.sin(2 * np.pi * t), np.zeros_like(t), np.zeros_like(t)], axis=1)
    angle = 0.6 * np.sin(2 * np.pi * t)
    return shift, angle


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mirrored_track(track: ColliderTrack) -> ColliderTrack:
    """The track reflected in x (a swinging collider swings the other way), its faces turned to
    keep their normals outward: a second scene unlike the first for batches."""
    return ColliderTrack(track.vertices * np.array([-1.0, 1.0, 1.0]), track.faces[:, ::-1].copy(),
                         track.face_mask, track.fps, track.lead_in_frames)


def tube_cylinder(fabric: str, resolution: str = "5k",
                  frames: int = SCENE_FRAMES["tube_cylinder"]) -> StudyScene:
    """A skirt-like tube hanging from a swinging, twisting cylinder (its top ring pinned)."""
    around, along = TUBE_SIZES[resolution]
    cv, cf = cylinder_mesh(0.10, 0.6, sections=64, rings=30)
    skirt = tube(0.115, 0.40, around, along, top=0.58, fabric=fabric, flare=0.10)
    skirt.pinned = skirt.loops["waist"]
    t = np.arange(frames + 1) / FPS
    shift, angle = cylinder_motion(t)
    verts = np.array([cv @ _rz(a).T + s for s, a in zip(shift, angle, strict=True)])
    track = ColliderTrack(verts, cf, np.ones(len(cf), bool), FPS)
    return StudyScene("tube_cylinder", fabric, resolution, [skirt], track, frames, 30, frames)


@functools.cache
def _walking_body(action: str, frames: int, lead_in: int):
    from datagen.body.anny_model import NEUTRAL_SHAPE, SHAPE_NAMES, default_body_model
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.procedural import generate
    from datagen.recipe import BodyConfig
    from datagen.spec import SubjectSpec

    subject = SubjectSpec(gender="female",
                          shape=dict(zip(SHAPE_NAMES, NEUTRAL_SHAPE.tolist(), strict=True)))
    return build_body_sequence(subject, generate(action, frames, FPS), lead_in,
                               default_body_model(), BodyConfig(), frozenset({"head"}))


HOLD_SECONDS = 0.5  # the quasi-static settle on the motion's first pose
# The settled start's substeps per frame: the body ladders' first rung. At the `default`
# preset's 5, each substep's solve carries the cloth so far into the body that the contact
# projection, applied after the strain limit, stretches the neck and the armpits: the walking
# t-shirt's rest-pose settle ends at p99.9 strain 0.27, over cotton's bound of 0.25 (at most
# 0.60; 1.31 while the contact walk still mixed up triangles, when the whole start had 72
# edges over 100 %). At 20 it ended at most 14 % stretched.
START_SUBSTEPS = 20


def _body_track(body, first: int, end: int, lead_in: int = 0) -> ColliderTrack:
    """The body's frames first..end-1 as a collider track."""
    return ColliderTrack(body.vertices[first:end], body.rest.faces, body.collider_face_mask,
                         body.fps, lead_in)


def settled_start(name: str, garments: list[Garment], body) -> dict[str, np.ndarray]:
    """The cloth at rest on the body in the motion's first pose: the dataset's timeline (settle
    on the rest pose, the lead-in) and then a quasi-static settle on the first pose, all with
    the implicit solver's `default` preset at START_SUBSTEPS, cached on disk.

    Every run of a body scene starts from this one state, so the measured second compares
    solvers on the same motion rather than on how each settled the garment. It must be an
    equilibrium of the reference's own model: from a state the springs are not at rest in (the
    xpbd preset leaves cotton 28 % over its rest length at the p99.9 edge), the reference's
    backward Euler damps the snap back differently at every step size, and its ladder did not
    converge (the skirt's rungs 10..160 substeps stayed 4-6 mm apart). It is computed in a
    float32 process: a float64 study worker must find it cached."""
    import os

    from datagen.sim.simulate import body_start_transform, simulate
    from datagen.study.cache import cached

    lead_in = body.lead_in_frames

    def compute() -> dict[str, np.ndarray]:
        if os.environ.get("DATAGEN_SIM_FP64"):
            raise RuntimeError(f"the settled start of study scene {name} ({garments[0].fabric}) "
                               "is not cached: build the scene in a float32 process first")
        options = {"solver": "implicit", "quality": "default", "substeps": START_SUBSTEPS,
                   "profile_every": 0, "strain_refinements": 0}
        # The garments move with the body to where the lead-in starts and follow it ...
        rot, shift = body_start_transform(body)
        moved = [replace(g, vertices=g.vertices @ rot.T + shift, rest_vertices=g.rest)
                 for g in garments]
        lead = simulate(moved, _body_track(body, 0, lead_in + 1, lead_in),
                        SimOptions(**options))
        # ... then come to rest on the first pose (every settle frame starts at rest).
        placed = [replace(g, vertices=lead.vertices[g.name][0].astype(np.float64))
                  for g in moved]
        held = simulate(placed, _body_track(body, lead_in, lead_in + 1),
                        SimOptions(**options, settle_seconds=HOLD_SECONDS))
        return {g.name: held.vertices[g.name][0] for g in garments}

    key = {"settled_start": name, "fabric": garments[0].fabric, "lead_in": lead_in,
           "hold": HOLD_SECONDS, "substeps": START_SUBSTEPS, "strain_limit": "all solvers",
           "contact_walk": "ends on the triangle it evaluated"}
    return {k: v.astype(np.float64) for k, v in cached(key, compute).items()}


def garment_on_body(name: str, template: str, action: str, fabric: str,
                    frames: int = SCENE_FRAMES["tshirt_walk"],
                    body_parts: bool = False) -> StudyScene:
    """A shipped template (neutral female body, no shaping or cuts) on a body moving through a
    procedural action. The scene starts when the lead-in ends, from the settled start (see
    settled_start): the cloth at rest, draped on the body in the motion's first pose. Its rest
    metric stays the template's. `body_parts`: the collider knows the body's parts, as a
    dataset's does (simulate.track_of); the accuracy study's scenes were measured without them
    (their start is the same either way)."""
    from datagen.body.anny_model import default_body_model
    from datagen.garment.outfit import make_outfit
    from datagen.spec import GarmentSpec, OutfitSpec

    lead_in = 10
    body = _walking_body(action, frames + 1, lead_in)
    spec = GarmentSpec(name=template, template=template, variant=template, fabric=fabric)
    outfit = OutfitSpec(garments=(spec,), tightness=(-0.5, -0.5))
    fitted = make_outfit(outfit, body.rest, default_body_model())
    start = settled_start(name, fitted, body)
    placed = [replace(g, vertices=start[g.name], rest_vertices=g.rest) for g in fitted]
    track = _body_track(body, lead_in, len(body.vertices))
    if body_parts:
        track = replace(track, face_parts=body.rest.part_labels[body.rest.faces[:, 0]])
    return StudyScene(name, fabric, "1cm", placed, track, frames, 30, frames)


def build_scene(name: str, fabric: str, resolution: str = "", frames: int | None = None,
                perturb: float = 0.0, body_parts: bool = False) -> StudyScene:
    """A study scene by name. `frames` shortens or lengthens it; `perturb` (metres) moves every
    cloth vertex of the start by that distance in a fixed random direction: the twin run that
    shows how soon the scene's chaos makes trajectories unpredictable. `body_parts`: a body
    scene's collider knows the body's parts (garment_on_body)."""
    extra = {"frames": frames if frames is not None else SCENE_FRAMES.get(name, 60)}
    if name == "sheet_sphere":
        scene = sheet_sphere(fabric, resolution or "4k", **extra)
    elif name == "tube_cylinder":
        scene = tube_cylinder(fabric, resolution or "5k", **extra)
    elif name == "skirt_body":
        scene = garment_on_body("skirt_body", "skirt", "spin", fabric, **extra,
                                body_parts=body_parts)
    elif name == "tshirt_walk":
        scene = garment_on_body("tshirt_walk", "tshirt", "walk", fabric, **extra,
                                body_parts=body_parts)
    else:
        raise ValueError(f"unknown study scene {name}")
    if perturb:
        rng = np.random.default_rng(12345)
        moved = []
        for g in scene.garments:
            d = rng.normal(size=g.vertices.shape)
            d *= perturb / np.linalg.norm(d, axis=1, keepdims=True)
            moved.append(replace(g, vertices=g.vertices + d))
        scene.garments = moved
    return scene
