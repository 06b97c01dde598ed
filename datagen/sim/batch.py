"""Several scenes simulated as one: a batch for backends where a launch costs more than its work.

On a GPU one scene of 4k-12k vertices is bound by kernel launches (docs/simulator.md, "On a
GPU"): a launch costs about the same for a thousand springs as for a hundred thousand. A batch
puts its scenes side by side, each on a cell of a lattice in the horizontal plane, and runs them
in one solver with one collider (their bodies' triangles together), so every launch serves all
of them. The scenes never meet: each cell is wider than its scene by a margin, and a batch in
which some scene's cloth left its cell is not trusted (see below).

What a scene gets is what it would get alone, but for rounding: the same solver, settings and
effects (scenes whose resolved effects differ are refused), its own QA series and its own energy
guards, its speed limit from its own collider (simulate._Part). Shared by the batch: the
substeps of a frame that a guard redoes (every scene redoes it) and the collider's grid. A
batch that is rejected, or in which a scene's cloth left its cell, is simulated again scene by
scene, so one bad scene costs the others only time; each result's report says which.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from datagen.errors import InputError, RejectedSequence
from datagen.sim.effects import resolve_effects
from datagen.sim.fabrics import get_fabric
from datagen.sim.fold_fields import JoinedFoldFields
from datagen.sim.simulate import (
    ColliderTrack,
    SimOptions,
    body_start_transform,
    scene_content,
    simulate,
    simulate_parts,
    track_of,
)
from datagen.types import BodySequence, Garment, SimResult

# Horizontal room (m) added to the widest scene's box to make a lattice cell: a scene's cloth
# may leave its own box (a skirt flaring out in a spin) by up to half of it, less SEPARATION.
BATCH_MARGIN = 0.5
# Effects that act only on elements a scene may lack (pinned vertices, elastic loops, an outer
# layer): the batch runs them if any scene needs them, and they leave the others as they are.
# Every other effect acts on every vertex and must be the same for all scenes.
ELEMENT_EFFECTS = ("pins", "elastic", "garment_collision")
# How close (m) a scene's cloth may come to its cell's edge. Two scenes then stay at least twice
# this apart, beyond the reach of any contact search (the body grid's 2 cells, 5 cm).
SEPARATION = 0.1


@dataclass
class BatchScene:
    """One scene of a batch: its garments (names unique within it) on its collider track."""

    garments: list[Garment]
    track: ColliderTrack


@dataclass
class BatchLayout:
    """Where each scene of a batch sits: the shift added to its positions and its cell's
    horizontal bounds (after the shift)."""

    offsets: np.ndarray  # (N, 3)
    cells: np.ndarray  # (N, 2, 2): per scene, (x, y) low and (x, y) high


def body_scene(garments: list[Garment], body: BodySequence) -> BatchScene:
    """Garments fitted to a body sequence's rest body as a batch scene: moved with the body to
    where its sequence starts, as `simulate` moves them, on the body's collider track."""
    rot, shift = body_start_transform(body)
    moved = [replace(g, vertices=np.asarray(g.vertices, dtype=np.float64) @ rot.T + shift)
             for g in garments]
    return BatchScene(moved, track_of(body))


def scene_box(scene: BatchScene) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the collider over all its frames and of the garments carried along with it:
    their start swept by the collider's box centre's travel from the first frame."""
    frames = np.asarray(scene.track.vertices, dtype=np.float64)
    lows, highs = frames.min(axis=1), frames.max(axis=1)
    travel = 0.5 * (lows + highs) - 0.5 * (lows[0] + highs[0])  # (F, 3)
    cloth = np.concatenate([np.asarray(g.vertices, dtype=np.float64) for g in scene.garments])
    lo = np.minimum(lows.min(axis=0), cloth.min(axis=0) + travel.min(axis=0))
    hi = np.maximum(highs.max(axis=0), cloth.max(axis=0) + travel.max(axis=0))
    return lo, hi


def lay_out(scenes: list[BatchScene], margin: float = BATCH_MARGIN) -> BatchLayout:
    """A square lattice of equal cells, as many columns as rows (or one more), centred on the
    origin; each scene centred on its cell (heights unchanged), in order along the rows."""
    if margin <= 2.0 * SEPARATION:
        raise InputError(None, "margin", f"more than {2.0 * SEPARATION} m", margin)
    boxes = [scene_box(s) for s in scenes]
    size = np.max([hi[:2] - lo[:2] for lo, hi in boxes], axis=0) + margin
    columns = math.ceil(math.sqrt(len(scenes)))
    rows = math.ceil(len(scenes) / columns)
    corner = -0.5 * size * np.array([columns, rows])
    offsets = np.zeros((len(scenes), 3))
    cells = np.zeros((len(scenes), 2, 2))
    for k, (lo, hi) in enumerate(boxes):
        low = corner + size * np.array([k % columns, k // columns])
        offsets[k, :2] = low + 0.5 * size - 0.5 * (lo[:2] + hi[:2])
        cells[k] = (low, low + size)
    return BatchLayout(offsets, cells)


TIMELINE = ("fps", "n_frames", "lead_in_frames")  # what every scene of a batch shares


def shared_effects(scene: BatchScene, options: SimOptions) -> list[str]:
    """The effects a scene resolves to that act on every vertex: those must be the same for
    every scene of a batch (ELEMENT_EFFECTS may differ)."""
    fabrics = [get_fabric(g.fabric, options.fabrics) for g in scene.garments]
    content = scene_content(scene.garments, True, options.wind, fabrics)
    return [e for e in resolve_effects(options.effects, content).enabled()
            if e not in ELEMENT_EFFECTS]


def batchable_groups(scenes: list[BatchScene], options: SimOptions) -> list[list[int]]:
    """The scenes split into groups that can each be one batch (the same timeline and the same
    shared effects), as indices in the given order; groups in the order of their first scene."""
    groups: dict[tuple, list[int]] = {}
    for k, scene in enumerate(scenes):
        key = (tuple(getattr(scene.track, f) for f in TIMELINE),
               tuple(shared_effects(scene, options)))
        groups.setdefault(key, []).append(k)
    return list(groups.values())


def _check(scenes: list[BatchScene], options: SimOptions) -> None:
    """Scenes that cannot share a solver are refused, naming the first that differs from
    scene 0 and how."""
    if not scenes:
        raise InputError(None, "scenes", "at least one scene", "none")
    first = scenes[0].track
    effects = []
    for k, scene in enumerate(scenes):
        if not scene.garments:
            raise InputError(None, f"scenes[{k}].garments", "at least one garment", "none")
        names = [g.name for g in scene.garments]
        if len(set(names)) != len(names):
            raise InputError(None, f"scenes[{k}].garments", "unique garment names", names)
        track = scene.track
        for field in TIMELINE:
            if getattr(track, field) != getattr(first, field):
                raise InputError(None, f"scenes[{k}].track.{field}",
                                 f"{getattr(first, field)}, as scene 0's (one timeline a batch)",
                                 getattr(track, field))
        effects.append(shared_effects(scene, options))
        if effects[k] != effects[0]:
            raise InputError(None, f"scenes[{k}] effects",
                             f"scene 0's {effects[0]} (one solver runs the effects that act on "
                             f"every vertex for all scenes)", effects[k])


def _joined(scenes: list[BatchScene], layout: BatchLayout):
    """The batch as one scene: garments renamed 'k:name' and shifted, the collider tracks
    shifted and concatenated; and each scene's ranges of garments and collider vertices."""
    garments, parts, verts, faces, masks = [], [], [], [], []
    n_body = 0
    for k, (scene, shift) in enumerate(zip(scenes, layout.offsets, strict=True)):
        start = len(garments)
        for g in scene.garments:
            rest = None if g.rest_vertices is None else g.rest_vertices + shift
            garments.append(replace(g, name=f"{k}:{g.name}", vertices=g.vertices + shift,
                                    rest_vertices=rest))
        track = scene.track
        parts.append((start, len(garments), n_body, n_body + track.vertices.shape[1]))
        verts.append(np.asarray(track.vertices, dtype=np.float64) + shift)
        faces.append(np.asarray(track.faces) + n_body)
        masks.append(np.asarray(track.face_mask, dtype=bool))
        n_body += track.vertices.shape[1]
    first = scenes[0].track
    # Parts are kept where every scene has them: each scene's body is guarded as it is alone.
    # Each scene's parts are numbered after the last scene's, so that the fold fields' tables
    # (indexed by part) tell one scene's thigh from another's.
    face_parts = [s.track.face_parts for s in scenes]
    joined_parts = fields = None
    if not any(p is None for p in face_parts):
        stride = 1 + max(int(np.max(p, initial=0)) for p in face_parts)
        joined_parts = np.concatenate([np.asarray(p) + k * stride
                                       for k, p in enumerate(face_parts)])
        folding = [(s.track.fold_fields, k * stride, shift)
                   for k, (s, shift) in enumerate(zip(scenes, layout.offsets, strict=True))
                   if s.track.fold_fields is not None]
        fields = JoinedFoldFields(folding) if folding else None
    track = ColliderTrack(np.concatenate(verts, axis=1), np.concatenate(faces),
                          np.concatenate(masks), first.fps, first.lead_in_frames, joined_parts,
                          fields)
    return garments, track, parts


def _left_cell(result: SimResult, scene: BatchScene, k: int, layout: BatchLayout) -> bool:
    """Whether scene k's cloth came within SEPARATION of its cell's edge in any output frame."""
    low, high = layout.cells[k] + np.array([[SEPARATION], [-SEPARATION]])
    for g in scene.garments:
        xy = result.vertices[f"{k}:{g.name}"][..., :2]
        if np.any(xy < low) or np.any(xy > high):
            return True
    return False


def simulate_batch(scenes: list[BatchScene], options: SimOptions | None = None,
                   margin: float = BATCH_MARGIN) -> list[SimResult | RejectedSequence]:
    """Simulate the scenes as one batch (module docstring). Returns, per scene, its result (its
    garments under their own names, at their own positions) or the RejectedSequence it met when
    simulated alone."""
    options = options or SimOptions()
    _check(scenes, options)
    layout = lay_out(scenes, margin)
    garments, track, parts = _joined(scenes, layout)
    why = None
    try:
        joint, part_qa = simulate_parts(garments, track, options, parts)
    except RejectedSequence as error:
        why = f"the batch was rejected ({error})"
    else:
        left = [k for k, s in enumerate(scenes) if _left_cell(joint, s, k, layout)]
        if left:
            why = f"scenes {left} left their lattice cells"
    if why is not None:
        return [_alone(scene, options, k, len(scenes), why) for k, scene in enumerate(scenes)]
    return [_split(joint, part_qa[k], scene, k, layout.offsets[k], len(scenes))
            for k, scene in enumerate(scenes)]


def _split(joint: SimResult, qa: dict, scene: BatchScene, k: int, shift: np.ndarray,
           n: int) -> SimResult:
    """Scene k's share of the batch's result, moved back to where the scene was given."""
    names = [g.name for g in scene.garments]
    vertices = {
        name: (joint.vertices[f"{k}:{name}"] - shift).astype(np.float32) for name in names
    }
    report = dict(joint.report)
    report["vertices"] = int(sum(len(g.vertices) for g in scene.garments))
    report["fabrics"] = {g.fabric: joint.report["fabrics"][g.fabric] for g in scene.garments}
    report["batch"] = {"scenes": n, "index": k, "alone": False,
                       "batch_vertices": joint.report["vertices"]}
    return SimResult(garment_names=names, vertices=vertices, qa=qa, report=report)


def _alone(scene: BatchScene, options: SimOptions, k: int, n: int,
           why: str) -> SimResult | RejectedSequence:
    try:
        result = simulate(scene.garments, scene.track, options)
    except RejectedSequence as error:
        return error
    result.report["batch"] = {"scenes": n, "index": k, "alone": True, "why": why}
    return result
