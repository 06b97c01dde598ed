"""One sequence through every stage: spec -> body -> outfit -> simulation -> a record to write.

This is the only place (with the CLI) that composes the stages; each stage knows only the
hand-off types of datagen.types.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from datagen.environment import environment
from datagen.errors import BoundBroken, RejectedSequence, SlidOffShoulders
from datagen.recipe import BodyConfig
from datagen.spec import SceneSpec
from datagen.types import BodySequence, Garment, Motion, SimResult

if TYPE_CHECKING:
    from datagen.qa import Breach
    from datagen.sim.fabrics import Fabric
    from datagen.sim.simulate import ColliderTrack, SimOptions


@dataclass
class SequenceRecord:
    """What a worker hands back for one sequence: the data to write, or why it was rejected."""

    spec: SceneSpec
    status: str  # "ok" | "rejected"
    body: BodySequence | None = None
    garments: list[Garment] | None = None
    sim: SimResult | None = None
    stage: str | None = None  # where a rejection happened
    reason: str | None = None
    frames: tuple[int, int] | None = None
    timings: dict[str, float] = field(default_factory=dict)
    # Cloth simulations run for it: 1, more where it was simulated again at finer steps
    # (simulate_within_bounds), also when it was rejected in the end; 0 before simulation.
    sim_runs: int = 0
    # The machine and package versions of the worker that made it (datagen.environment).
    environment: dict[str, object] = field(default_factory=dict)


def sim_options_from_spec(spec: SceneSpec, fabrics: dict | None = None,
                          guards: bool = False):
    """The simulator's options for a scene; `guards` where the caller rejects a sequence whose
    garment slid off the shoulders or broke a QA bound: its runs stop at the first such frame
    (SimOptions.neckline_guard and bound_guard)."""
    from datagen.sim.simulate import SimOptions

    s = spec.simulation
    return SimOptions(solver=s.solver, quality=s.quality, substeps=s.substeps,
                      iterations=s.iterations, effects=s.effects,
                      wind=tuple(s.wind) if s.wind else None, fabrics=dict(fabrics or {}),
                      settle_seconds=s.settle_seconds, neckline_guard=guards,
                      bound_guard=guards)


def run_sequence(
    spec: SceneSpec,
    body_model,
    body_config: BodyConfig | None = None,
    base_dir: Path | None = None,
    templates_dir: Path | None = None,
    simulate_cloth: bool = True,
    fabrics: dict | None = None,
    motion_hook: Callable[[Motion], Motion] | None = None,
    garment_hook: Callable[[list[Garment], BodySequence], list[Garment]] | None = None,
    guards: bool = False,
) -> SequenceRecord:
    """Run one sequence end to end. A RejectedSequence becomes a rejected record; any other
    error propagates (it is a bug or bad input, not a property of the scene). The hooks alter
    the motion or the fitted garments on their way (the hard cases inject faults with them).
    `guards`: stop a run at the first frame where its garment slid off the shoulders
    or its QA broke a bound (SimOptions.neckline_guard and bound_guard), where the caller's
    gate rejects such a sequence."""
    from datagen.body.sequence import build_body_sequence
    from datagen.garment.outfit import dropped_parts_for, make_outfit
    from datagen.motion.load import motion_from_spec

    record = SequenceRecord(spec=spec, status="ok", environment=environment())
    config = body_config or BodyConfig()
    try:
        t = time.perf_counter()
        motion = motion_from_spec(spec.motion, base_dir)
        if motion_hook is not None:
            motion = motion_hook(motion)
        dropped = dropped_parts_for(spec.outfit) if config.drop_unreached_parts else frozenset()
        record.body = build_body_sequence(spec.subject, motion, spec.motion.lead_in, body_model,
                                          config, dropped)
        record.timings["body"] = time.perf_counter() - t
        if spec.outfit.garments:
            t = time.perf_counter()
            record.garments = make_outfit(spec.outfit, record.body.rest, body_model,
                                          templates_dir)
            if garment_hook is not None:
                record.garments = garment_hook(record.garments, record.body)
            record.timings["outfit"] = time.perf_counter() - t
            if simulate_cloth:
                t = time.perf_counter()
                try:
                    record.sim = simulate_within_bounds(record.garments, record.body,
                                                        sim_options_from_spec(
                                                            spec, fabrics, guards))
                finally:
                    record.timings["simulate"] = time.perf_counter() - t
                record.sim_runs = simulation_runs(record.sim)
    except RejectedSequence as exc:
        mark_rejected(record, exc)
    return record


def simulation_runs(sim: SimResult) -> int:
    """How many times simulate_within_bounds simulated the sequence to get `sim`: 1, plus each
    run it did not keep (the escalations)."""
    return 1 + len(sim.report.get("escalations") or [])


def mark_rejected(record: SequenceRecord, exc: RejectedSequence) -> None:
    """Turn a record into the rejection `exc` names (its data dropped, its timings kept)."""
    record.status = "rejected"
    record.stage, record.reason, record.frames = exc.stage, exc.reason, exc.frames
    if exc.stage in ("simulate", "qa"):  # raised in the simulation stage (a "qa" one: its guard)
        record.sim_runs = exc.runs
    record.body = record.garments = record.sim = None


# Past the top quality preset a sequence gets one more run at this multiple of the preset's
# steps: the fast kick lands on either side of its bounds at 40x8 as rounding changes
# (0.086-0.131 % of edges over, the bound 0.1 %) and passes at 80x16 (0.084 %, 0.24 % of
# vertices too deep; docs/simulator.md, "Escalation").
ESCALATION_PAST_TOP = 2


def next_rung(options: SimOptions, fps: float | None = None) -> SimOptions | None:
    """The escalation ladder's next options after a run at `options` broke a bound or was
    rejected as unstable: SimOptions.escalated() (the next quality preset up, plain sweeps),
    and from the top preset, once, its steps at output rate `fps` (None: PRESET_FPS) times
    ESCALATION_PAST_TOP, sweeps as plain. None from steps the caller (or that last rung)
    gave."""
    from datagen.sim.simulate import PRESET_FPS, QUALITY_PRESETS

    up = options.escalated()
    if up is not None or options.substeps is not None or options.iterations is not None:
        return up
    if options.quality not in QUALITY_PRESETS.get(options.solver, {}):
        return None
    sub, it = options.resolve_steps(PRESET_FPS if fps is None else fps)
    return replace(options, substeps=ESCALATION_PAST_TOP * sub,
                   iterations=ESCALATION_PAST_TOP * it, sor=options.escalated_sor())


def simulate_within_bounds(garments: list[Garment], body: BodySequence | ColliderTrack | None,
                           options: SimOptions,
                           first: SimResult | RejectedSequence | None = None) -> SimResult:
    """Simulate the garments; a run that breaks a physical-validity bound (datagen.qa) or is
    rejected as unstable is simulated again at next_rung() (the next quality preset up, plain
    sweeps; past the top preset, once, its steps doubled), up that ladder until a run
    keeps its bounds or there is no rung left, and the last run is the result. Only the
    sequences that need it pay for the finer steps: the fast kick's trousers break the strain
    bound at `default` 20x4 in one frame of the kick (a chaotic frame: more substeps for that
    frame alone do not help), and pass at 40x8 or, as rounding falls, at 80x16
    (docs/simulator.md, "Escalation"). A garment that slid off the shoulders (a finished run's
    slid_off_in, or a run the neckline guard stopped, SlidOffShoulders) goes up the presets
    but not past the top: finer steps keep some straps on that coarse ones let slide, and the
    rung past the top is for a kick's chaotic strain (docs/simulator.md, "A slide stops the
    run"). The result's report names the first run's settings and
    why it was not kept (`escalated_from`) and every run not kept (`escalations`); a rejection
    at the last rung names them all. `first`: the first run's outcome where it was simulated
    already (in a batch, datagen.pipeline.batched), which is then judged instead of simulating
    again."""
    from datagen import qa
    from datagen.sim.simulate import output_fps, simulate

    dropped: list[dict] = []  # the runs not kept: settings, reason, wall time
    fps = output_fps(body)
    current, outcome = options, first
    while True:
        up = next_rung(current, fps)
        settings = f"{current.solver} {current.steps_label(fps)}"
        try:
            if isinstance(outcome, RejectedSequence):
                raise outcome
            sim = simulate(garments, body, current) if outcome is None else outcome
        except RejectedSequence as exc:
            if isinstance(exc, SlidOffShoulders):
                up = current.escalated()  # up the presets, not past the top (docstring)
            elif isinstance(exc, BoundBroken):
                # Stopped at its first frame over a bound (SimOptions.bound_guard): up the
                # ladder as a finished run over it would go, the frame's overlap noted as the
                # gate notes it.
                exc = BoundBroken(exc.reason + flexion_overlap_note(body, [exc.frames[0]]),
                                  exc.frames)
            elif exc.stage != "simulate":
                up = None
            if up is None:
                if not dropped:
                    raise exc from None
                raise RejectedSequence(exc.stage, exc.reason + _runs_note(
                    current.steps_label(fps), dropped), exc.frames,
                    runs=len(dropped) + 1) from None
            dropped.append({"settings": settings, "reason": exc.reason, "wall_time_s": None})
        else:
            found = qa.breaches(sim.qa)
            if not found:
                found = slid_off_in(garments, sim, body)
                up = current.escalated() if found else up
            if not found or up is None:
                if dropped:
                    sim.report["escalated_from"] = dropped[0]
                    sim.report["escalations"] = dropped
                return sim
            found = [with_where(b, garments, sim, body, current.fabrics) for b in found]
            dropped.append({"settings": settings, "reason": "; ".join(b.reason for b in found),
                            "wall_time_s": float(sim.report["wall_time_s"])})
        current, outcome = up, None


def _runs_note(last: str, dropped: list[dict]) -> str:
    """'; simulated again at LAST, after the run at A: why' (one run not kept), or '...after
    the runs at A (why) and at B (why)' (several)."""
    if len(dropped) == 1:
        return f"; simulated again at {last}, after the run at {dropped[0]['settings']}: " \
               f"{dropped[0]['reason']}"
    runs = [f"at {d['settings']} ({d['reason']})" for d in dropped]
    return f"; simulated again at {last}, after the runs {', '.join(runs[:-1])} and {runs[-1]}"


def escalation_note(sim: SimResult | None) -> str:
    """'; simulated again at ..., after the run(s) at ...: why' where a sequence was simulated
    again (simulate_within_bounds), empty otherwise: a QA rejection's reason says every run."""
    first = sim.report.get("escalated_from") if sim is not None else None
    if first is None:
        return ""
    rep = sim.report
    last = f"{rep['quality']} {rep['substeps']}x{rep['iterations']}, sor {rep['sor']:g}"
    return _runs_note(last, rep.get("escalations") or [first])


def reject_over_qa_bounds(record: SequenceRecord) -> SequenceRecord:
    """The dataset's QA gate: a simulated sequence that breaks a physical-validity bound
    (datagen.qa) becomes a rejected record, stage "qa", with the bound, the value and the frame,
    instead of training data that `datagen validate` would fail."""
    found, reason = over_qa_bounds(record)
    if not found:
        return record
    frame = found[0].frame
    return SequenceRecord(
        spec=record.spec, status="rejected", stage="qa",
        reason=reason, frames=(frame, frame), timings=record.timings,
        sim_runs=record.sim_runs, environment=record.environment)


def over_qa_bounds(record: SequenceRecord,
                   fabrics: Mapping[str, Fabric] | None = None) -> tuple[list[Breach], str]:
    """The physical-validity bounds (datagen.qa) that a simulated record breaks, and the reason
    a rejection gives for them (empty where none). `fabrics`: user fabrics by name, for a
    scene that uses them (`datagen simulate --fabrics-file`)."""
    from datagen import qa

    if record.status != "ok" or record.sim is None or not record.garments:
        return [], ""
    found = ([with_where(b, record.garments, record.sim, record.body, fabrics)
              for b in qa.breaches(record.sim.qa)]
             + buried_at_flexed_joints(record, fabrics) + slipped_necklines(record))
    if not found:
        return [], ""
    return found, "; ".join(b.reason for b in found) + flexion_overlap_note(
        record.body, [b.frame for b in found]) + escalation_note(record.sim)


def with_where(breach: Breach, garments: list[Garment], sim: SimResult,
               body: BodySequence | ColliderTrack | None,
               fabrics: Mapping[str, Fabric] | None) -> Breach:
    """A strain breach of a finished run `sim` with where it lies at its frame
    (simulate.where_strained, as a guarded run's reason has it); other breaches as they are
    (the depth series' per-vertex flags are not kept after a run)."""
    if breach.series != "over_strain_share":
        return breach
    from datagen.sim.fabrics import get_fabric
    from datagen.sim.model import build_cloth_model
    from datagen.sim.simulate import where_strained

    frame = breach.frame
    model = build_cloth_model([(g, get_fabric(g.fabric, dict(fabrics or {}))) for g in garments])
    x = np.concatenate([sim.vertices[g.name][frame] for g in garments]).astype(np.float64)
    body_x = parts = None
    if body is not None:
        body_x = body.vertices[body.lead_in_frames + frame]
        parts = (body.rest.part_labels if isinstance(body, BodySequence)
                 else body.vertex_parts)
    return replace(breach, where=where_strained(model, garments, x, body_x, parts))


def record_buried_share(record: SequenceRecord, frames: np.ndarray | None = None,
                        fabrics: Mapping[str, Fabric] | None = None) -> np.ndarray:
    """qa.buried_share of a finished record at the given output frames (default: all), in the
    garment with the most: every garment's vertices, each held to its fabric's thickness,
    against the whole body (all its triangles, the parts the collider leaves out included)."""
    from datagen import qa
    from datagen.sim.fabrics import get_fabric

    sim, body = record.sim, record.body
    out = np.arange(len(next(iter(sim.vertices.values())))) if frames is None else frames
    out = np.asarray(out, dtype=np.int64)
    cloth = np.concatenate([sim.vertices[g.name][out] for g in record.garments], axis=1)
    extra = dict(fabrics or {})
    thickness = np.concatenate([np.full(len(g.vertices), get_fabric(g.fabric, extra).thickness)
                                for g in record.garments])
    ends = np.cumsum([len(g.vertices) for g in record.garments]).tolist()
    return qa.buried_share(cloth, thickness, body.vertices[body.lead_in_frames + out],
                           body.rest.faces, list(zip([0, *ends[:-1]], ends, strict=True)))


def buried_at_flexed_joints(record: SequenceRecord,
                            fabrics: Mapping[str, Fabric] | None = None) -> list[Breach]:
    """The depth bound judged by the body's volume (qa.buried_share), in the output frames
    where the body stage found skinning sinking parts into each other across a flexed joint:
    there cloth is left inside one part while outside the part it tracks (docs/simulator.md,
    the fast kick). The simulator's deep_share reads the same volume at every frame (since
    2026-12-07), through the collider it checks; this is libigl's verdict, independent of it.
    Only those frames, because it costs about 0.1 s a frame; elsewhere the hard cases check."""
    from datagen import qa
    from datagen.qa import Breach

    report = getattr(record.body, "self_collision", None)
    found = getattr(report, "flexion_overlap_frames", None)
    if not found:
        return []
    lead_in = int(record.body.lead_in_frames)
    n_out = len(next(iter(record.sim.vertices.values())))
    frames = np.array(sorted({int(f) - lead_in for f in found} & set(range(n_out))), dtype=np.int64)
    if len(frames) == 0:
        return []
    share = record_buried_share(record, frames, fabrics)
    k = int(np.argmax(share))
    if share[k] <= qa.DEEP_SHARE_MAX:
        return []
    return [Breach("buried_share", float(share[k]), int(frames[k]), qa.DEEP_SHARE_MAX,
                   "cloth inside the body's volume deeper than its thickness where skinning "
                   "sank its parts into each other")]


def slipped_necklines(record: SequenceRecord) -> list[Breach]:
    """The garments whose neckline slid off the shoulders (qa.neckline_slip over
    qa.NECKLINE_SLIP_MAX in an output frame), each with its worst frame. A loose open shirt or a
    strap jumpsuit can slide off a moving body and hang at the elbows: physically possible,
    but not the worn garment a dataset's sequence is meant to show, and no other bound sees it
    (docs/simulator.md, "Garments that slide off")."""
    if record.sim is None or not record.garments:
        return []
    return slid_off_in(record.garments, record.sim, record.body)


def slid_off_in(garments: list[Garment], sim: SimResult,
                body: BodySequence | ColliderTrack | None) -> list[Breach]:
    """slipped_necklines of a simulation `sim` of `garments` on `body` (a body sequence, or a
    track with its neck joint; none for other colliders)."""
    from datagen import qa
    from datagen.sim.simulate import necklines_off

    if body is None:  # cloth on a bare collider: no neck joint
        return []
    if isinstance(body, BodySequence):
        neck, rest_neck = body.joints[:, qa.NECK_JOINT], body.rest.joints[qa.NECK_JOINT]
    else:
        neck, rest_neck = body.neck, body.rest_neck
    if neck is None or rest_neck is None or not sim.vertices:
        return []
    lead_in = int(body.lead_in_frames)
    n_frames = len(next(iter(sim.vertices.values())))
    return [b for _, b in necklines_off(garments, lambda k, g, loop: sim.vertices[g.name][:, loop],
                                        neck[lead_in:lead_in + n_frames], rest_neck)]


def flexion_overlap_note(body: BodySequence | None, frames: list[int]) -> str:
    """Where one of the output `frames` that broke a bound is one in which the body's parts
    still intersect across a flexed joint after the body stage separated them
    (SelfCollisionReport.flexion_residual_frames), say so: cloth caught in the body's own
    overlap cannot be outside it. Empty otherwise."""
    report = getattr(body, "self_collision", None)
    residual = getattr(report, "flexion_residual_frames", None)
    if not residual:
        return ""
    lead_in = int(body.lead_in_frames)
    overlapping = {int(f) - lead_in for f in residual}
    frames = sorted({int(f) for f in frames if int(f) in overlapping})
    if not frames:
        return ""
    where = f"frame {frames[0]}" if len(frames) == 1 else (
        "frames " + ", ".join(str(f) for f in frames[:-1]) + f" and {frames[-1]}")
    # The joints folding in those frames, where the report has them per joint.
    by_joint = getattr(report, "flexion_overlap_by_joint", None) or {}
    joints = [j for j, folds in by_joint.items()
              if any(int(f) - lead_in in frames for f in folds)] or ["hip, knee or elbow"]
    return (f"; at {where} the body's parts still intersect across a flexed joint "
            f"({', '.join(joints)}; skinning sank them up to "
            f"{100 * report.flexion_overlap_max_depth:.1f} cm "
            f"deep in this sequence, and separating them left "
            f"{report.flexion_residual_pairs} triangle pairs crossing)")
