"""The simulator's hard cases (pipelines/hard_cases.yaml): scenes a dataset run will meet sooner
or later, each run through the real pipeline and judged.

A case passes when it ends finite, with at most 0.1 % of each garment's fabric edges beyond the
fabric's strain bound and at most 1 % of each garment's vertices deeper than the thickness in
every output frame, and a
bounded kinetic energy; or, where the case says rejection is the right answer, when it is
rejected at the expected stage with a reason that says so. Tests run the short versions
(`short` frames), the benchmark the full ones.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from datagen.config import check_range, from_mapping, load_yaml
from datagen.errors import InputError
from datagen.qa import DEEP_SHARE_MAX, STRAIN_SHARE_MAX  # per frame after the lead-in
from datagen.spec import (
    GarmentSpec,
    MotionSpec,
    OutfitSpec,
    SceneSpec,
    SimSpec,
    SubjectSpec,
    require_lead_in,
)
from datagen.types import BodySequence, Garment, Motion

# Kinetic energy per kilogram of cloth: the cloth moves with a body whose limbs reach about
# 10 m/s; an average cloth speed of 10 m/s would be a blow-up, not a motion.
KINETIC_PER_KG_MAX = 0.5 * 10.0**2


@dataclass(frozen=True)
class CaseGarment:
    template: str
    variant: str = ""
    fabric: str = "cotton"
    cuts: dict[str, float] = field(default_factory=dict)
    elastic: dict[str, bool] = field(default_factory=dict)
    layer: int = 0


@dataclass(frozen=True)
class RootJump:
    frame: int
    metres: float


@dataclass(frozen=True)
class Case:
    name: str
    why: str
    garments: list[CaseGarment]
    gender: str = "female"
    shape: dict[str, float] = field(default_factory=dict)
    motion: MotionSpec = field(default_factory=MotionSpec)
    tightness: tuple[float, float] = (0.0, 0.0)
    sewn: str | None = None
    start_inside: float = 0.0  # metres: part of the garment starts this far inside the body
    defects: bool = False  # zero-length edges, needle triangles, duplicate vertices
    root_jump: RootJump | None = None
    wind: tuple[float, float, float] | None = None  # m/s: the scene's wind (SimSpec.wind)
    expect: str = "ok"  # "ok" or "rejected"
    reason: str = ""  # a rejection: words its reason must contain
    short_frames: int | None = None  # the tests' version (default: the file's `short_frames`)

    def validate(self, source, path: str) -> None:
        if self.expect not in ("ok", "rejected"):
            raise InputError(source, f"{path}.expect", "ok or rejected", self.expect)
        if self.expect == "rejected" and not self.reason:
            raise InputError(source, f"{path}.reason", "the words a rejection must contain", "")
        check_range(self.start_inside, 0.0, 0.05, source, f"{path}.start_inside")
        require_lead_in(self.motion.lead_in, source, f"{path}.motion.lead_in")


@dataclass(frozen=True)
class HardCases:
    cases: list[Case]
    short_frames: int = 12
    short_lead_in: int = 8


@dataclass
class CaseResult:
    name: str
    expect: str
    status: str  # ok | rejected
    passed: bool
    detail: str
    frames: int = 0
    vertices: int = 0
    wall_s: float = 0.0
    strain_share_max: float = float("nan")
    strain_p999_max: float = float("nan")
    deep_share_max: float = float("nan")
    # inside the body's volume, the union of its parts, by libigl (qa.buried_share): the same
    # verdict as deep_share's since 2026-12-07, independent of the simulator's collider
    buried_share_max: float = float("nan")
    kinetic_per_kg_max: float = float("nan")
    retries: int = 0


def load_hard_cases(path: str | Path) -> HardCases:
    path = Path(path)
    return from_mapping(HardCases, load_yaml(path), path)


def case_spec(case: Case, short: bool, cases: HardCases, sim: SimSpec | None = None) -> SceneSpec:
    motion = case.motion
    if short:
        motion = replace(motion, frames=min(motion.frames, case.short_frames or cases.short_frames),
                         lead_in=min(motion.lead_in, cases.short_lead_in))
    garments = tuple(
        GarmentSpec(name=f"{g.template}{k}" if len(case.garments) > 1 else g.template,
                    template=g.template, variant=g.variant or g.template, fabric=g.fabric,
                    cuts=dict(g.cuts), elastic=dict(g.elastic), layer=g.layer)
        for k, g in enumerate(case.garments)
    )
    simulation = sim or SimSpec()
    if case.wind is not None:
        simulation = replace(simulation, wind=tuple(case.wind))
    return SceneSpec(
        dataset_seed=0, sequence_index=0, sequence_id=f"hard-{case.name}",
        subject=SubjectSpec(gender=case.gender, shape=dict(case.shape)),
        motion=motion,
        outfit=OutfitSpec(garments=garments, tightness=tuple(case.tightness), sewn=case.sewn),
        simulation=simulation,
    )


# -- faults the cases inject ---------------------------------------------------------------------
def jump_root(jump: RootJump):
    def hook(motion: Motion) -> Motion:
        trans = motion.trans.copy()
        trans[jump.frame:, 0] += jump.metres
        return replace(motion, trans=trans)

    return hook


def push_inside(depth: float):
    """Move the garment vertices nearest the chest (or the hips) `depth` inside the body."""

    def hook(garments: list[Garment], body: BodySequence) -> list[Garment]:
        import trimesh

        rest = body.rest
        mesh = trimesh.Trimesh(rest.vertices, rest.faces, process=False)
        out = []
        for g in garments:
            closest, _, tri = trimesh.proximity.closest_point(mesh, g.vertices)
            centre = g.vertices[np.argmin(g.vertices[:, 1])]  # the front-most point
            patch = np.linalg.norm(g.vertices - centre, axis=1) < 0.08
            normals = mesh.face_normals[tri]
            moved = g.vertices.copy()
            moved[patch] = closest[patch] - depth * normals[patch]
            out.append(replace(g, vertices=moved))
        return out

    return hook


def add_defects(seed: int = 0, count: int = 12):
    """Zero-length edges, needle triangles and duplicate vertices, in both the start and the rest
    shape, as a careless export would leave them."""

    def hook(garments: list[Garment], body: BodySequence) -> list[Garment]:
        del body
        rng = np.random.default_rng(seed)
        out = []
        for g in garments:
            v, rest = g.vertices.copy(), g.rest.copy()
            faces = g.faces.copy()
            pinned = set() if g.pinned is None else set(int(i) for i in g.pinned)
            picks = rng.choice(len(faces), 3 * count, replace=False)
            collapse, needle, dup = np.split(picks, 3)
            for t in collapse:  # one edge of the triangle collapses to zero length
                a, b = int(faces[t, 0]), int(faces[t, 1])
                if b not in pinned:
                    v[b], rest[b] = v[a], rest[a]
            for t in needle:  # the third corner moves onto its opposite edge (1 % off it)
                a, b, c = (int(i) for i in faces[t])
                if c in pinned:
                    continue
                for arr in (v, rest):
                    mid = 0.5 * (arr[a] + arr[b])
                    arr[c] = mid + 0.01 * (arr[c] - mid)
            extra_v, extra_r = [], []
            for t in dup:  # a corner becomes a separate vertex at the same place (a crack)
                a = int(faces[t, 0])
                faces[t, 0] = len(v) + len(extra_v)
                extra_v.append(v[a])
                extra_r.append(rest[a])
            n_new = len(extra_v)
            regions = None if g.regions is None else np.concatenate(
                [g.regions, g.regions[faces[dup, 1]]])
            uv = None if g.uv is None else np.concatenate([g.uv, g.uv[faces[dup, 1]]])
            out.append(replace(
                g, vertices=np.concatenate([v, np.asarray(extra_v).reshape(n_new, 3)]),
                rest_vertices=np.concatenate([rest, np.asarray(extra_r).reshape(n_new, 3)]),
                faces=faces, regions=regions, uv=uv,
            ))
        return out

    return hook


# -- running and judging -------------------------------------------------------------------------
def judge(case: Case, record) -> CaseResult:
    from datagen.pipeline.stages import escalation_note, flexion_overlap_note, record_buried_share

    res = CaseResult(case.name, case.expect, record.status, False, "")
    if record.status != "ok":
        res.detail = f"rejected at {record.stage}: {record.reason}"
        res.passed = case.expect == "rejected" and case.reason.lower() in record.reason.lower()
        if case.expect == "ok":
            res.detail = "expected to finish, but " + res.detail
        return res
    if case.expect == "rejected":
        res.detail = f"expected a rejection ({case.reason!r}), but it finished"
        return res
    sim = record.sim
    qa = sim.qa
    mass = _cloth_mass(record)
    finite = all(np.all(np.isfinite(v)) for v in sim.vertices.values())
    res.frames = int(sim.report["frames"])
    res.vertices = int(sim.report["vertices"])
    res.retries = int(sim.report["retries"])
    res.strain_share_max = float(qa["over_strain_share"].max())
    res.strain_p999_max = float(qa["strain_p999"].max())
    res.deep_share_max = float(qa["deep_share"].max()) if "deep_share" in qa else 0.0
    res.kinetic_per_kg_max = float(qa["kinetic_energy"].max()) / mass
    buried = record_buried_share(record)
    res.buried_share_max = float(buried.max())
    problems = []
    worst = []  # the frames where a bound broke
    if not finite:
        problems.append("non-finite positions")
    if res.strain_share_max > STRAIN_SHARE_MAX:
        problems.append(f"{100 * res.strain_share_max:.2f} % of a garment's edges beyond the "
                        "strain bound")
        worst.append(int(np.argmax(qa["over_strain_share"])))
    if res.deep_share_max > DEEP_SHARE_MAX:
        problems.append(f"{100 * res.deep_share_max:.2f} % of a garment's vertices deeper than "
                        "the thickness")
        worst.append(int(np.argmax(qa["deep_share"])))
    if res.buried_share_max > DEEP_SHARE_MAX:
        problems.append(f"{100 * res.buried_share_max:.2f} % of a garment's vertices deeper "
                        "than the thickness inside the body's volume (its parts' union)")
        worst.append(int(np.argmax(buried)))
    if res.kinetic_per_kg_max > KINETIC_PER_KG_MAX:
        problems.append(f"kinetic energy {res.kinetic_per_kg_max:.1f} J/kg")
    res.passed = not problems
    res.detail = "; ".join(problems) or "finite, strain and penetration within bounds"
    if problems:
        res.detail += flexion_overlap_note(getattr(record, "body", None), worst)
    res.detail += escalation_note(sim)
    return res


def _cloth_mass(record) -> float:
    from datagen.sim.fabrics import get_fabric
    from datagen.sim.model import triangle_areas

    total = 0.0
    for g in record.garments:
        total += get_fabric(g.fabric).density * float(triangle_areas(g.rest, g.faces).sum())
    return total


def run_case(case: Case, cases: HardCases, body_model, base_dir: Path, short: bool,
             sim: SimSpec | None = None) -> CaseResult:
    from datagen.pipeline.stages import run_sequence

    spec = case_spec(case, short, cases, sim)
    motion_hook = jump_root(case.root_jump) if case.root_jump else None
    hooks = []
    if case.start_inside > 0:
        hooks.append(push_inside(case.start_inside))
    if case.defects:
        hooks.append(add_defects())

    def garment_hook(garments, body):
        for hook in hooks:
            garments = hook(garments, body)
        return garments

    t = time.perf_counter()
    record = run_sequence(spec, body_model, base_dir=base_dir, motion_hook=motion_hook,
                          garment_hook=garment_hook if hooks else None)
    result = judge(case, record)
    result.wall_s = time.perf_counter() - t
    return result


def results_markdown(results: list[CaseResult]) -> str:
    rows = ["| case | expected | outcome | frames | vertices | retries | max strain p99.9 | "
            "edges over bound (max) | vertices too deep (max) | too deep in the body's volume "
            "(max) | KE max J/kg | wall s | verdict |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        rows.append(
            f"| {r.name} | {r.expect} | {r.detail} | {r.frames} | {r.vertices} | {r.retries} | "
            f"{r.strain_p999_max:.3f} | {100 * r.strain_share_max:.3f} % | "
            f"{100 * r.deep_share_max:.3f} % | {100 * r.buried_share_max:.3f} % | "
            f"{r.kinetic_per_kg_max:.2f} | {r.wall_s:.0f} | "
            f"{'pass' if r.passed else 'FAIL'} |"
        )
    return "\n".join(rows)
