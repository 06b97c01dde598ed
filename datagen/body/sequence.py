"""The body stage: subject + motion -> a self-collision-free BodySequence (or a rejection)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from datagen.body.arm_clearance import ARM_PARTS, clear_arms
from datagen.body.base import BodyModel
from datagen.body.flexion import separate_flexed_parts
from datagen.body.parts import (
    FLEXION_JOINTS,
    FLEXION_PAIRS,
    FLEXION_REST_RADIUS,
    PART_INDEX,
    flexion_joint,
)
from datagen.body.selfcollision import (
    LOCAL_RADIUS,
    SelfCollisionDetector,
    classify,
    repair_contact,
)
from datagen.errors import InputError, RejectedSequence
from datagen.motion.timing import add_lead_in, check_root_speed, retarget_root
from datagen.recipe import BodyConfig
from datagen.spec import SubjectSpec
from datagen.types import BodySequence, Motion, RestBody, SelfCollisionReport


def shape_vector(model: BodyModel, subject: SubjectSpec) -> np.ndarray:
    """The subject's shape parameters in the model's order; every name must be known."""
    names = tuple(model.shape_names)
    unknown = set(subject.shape) - set(names)
    if unknown:
        raise InputError(
            None,
            f"subject.shape.{sorted(unknown)[0]}",
            f"a shape parameter of {model.name} ({', '.join(names)})",
            "unknown",
        )
    defaults = getattr(model, "default_shape", None)
    out = np.zeros(len(names)) if defaults is None else np.array(defaults(), dtype=np.float64)
    for i, name in enumerate(names):
        if name in subject.shape:
            out[i] = subject.shape[name]
    return out


def _detector(rest: RestBody, ignore: frozenset[str] = frozenset(),
              pairs: tuple[tuple[str, str], ...] | None = None,
              local_radius: float = LOCAL_RADIUS) -> SelfCollisionDetector:
    # From this subject's own rest pose, every time (5 ms): which triangles count as "local" to
    # each other depends on it. One detector per topology, from the first subject a process
    # built, made a sequence's contacts, repairs and report depend on what that process had
    # built before (a 1 m kick read 1105 flexion pairs after another subject, 1160 alone).
    return SelfCollisionDetector(rest.faces, rest.part_labels, rest.vertices, ignore,
                                 pairs=pairs, local_radius=local_radius)


def _clearance_detector(rest: RestBody, repair_detector: SelfCollisionDetector,
                        repair_ignored: frozenset[str],
                        collider_dropped: frozenset[str]) -> SelfCollisionDetector:
    """The arm fit's detector: the repair's, but seeing every arm part that stays in the cloth
    collider. A hand is not repaired (resting on a thigh is a pose), yet a capture subject's
    hands, swinging close to its own thighs, sank 3 cm into a broader subject's: the trousers
    between had no room, and the cloth, pushed out of each surface into the other, ran away
    (docs/simulator.md, "A hand sunk into a thigh")."""
    arms = frozenset().union(*ARM_PARTS.values())
    ignored = repair_ignored - (arms - collider_dropped)
    return repair_detector if ignored == repair_ignored else _detector(rest, ignored)


def repair_self_collisions(
    vertices: np.ndarray,
    rest: RestBody,
    config: BodyConfig,
    ignore: frozenset[str],
    contacts=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, SelfCollisionReport]:
    """Detect, classify and repair; returns sparse offsets (frames, vertices, offsets) and the
    report, or raises RejectedSequence. `vertices` (F, V, 3) is modified in place."""
    det = _detector(rest, ignore)
    if contacts is None:
        contacts = det.detect(vertices)
    report = SelfCollisionReport(frames_checked=len(vertices), dropped_parts=tuple(sorted(ignore)))
    report.intersecting_pairs = sum(c.n_pairs for c in contacts)
    report.frames_with_contact = len({c.frame for c in contacts})
    by_pair: dict[str, int] = defaultdict(int)
    for c in contacts:
        by_pair[c.pair_name] += c.n_pairs
    report.by_part_pair = dict(sorted(by_pair.items()))
    verdict = classify(contacts, config.max_solvable_extent, config.max_solvable_depth)
    if verdict.fatal:
        reason, frames = verdict.reason()
        raise RejectedSequence("body", reason, frames)
    offsets: dict[tuple[int, int], np.ndarray] = {}
    pending = verdict.solvable
    for _ in range(3):  # a repair can uncover a neighbouring contact; a few passes settle it
        if not pending:
            break
        for contact in pending:
            frame_vertices = vertices[contact.frame]
            for v, off in repair_contact(
                frame_vertices,
                rest.faces,
                rest.part_labels,
                contact,
                config.repair_gap,
                rest.vertices,
            ).items():
                frame_vertices[v] += off.astype(np.float32)
                key = (contact.frame, v)
                offsets[key] = offsets.get(key, 0.0) + off
        frames = np.unique([c.frame for c in pending])
        pending = det.detect(vertices[frames], frames=frames)
    report.residual_pairs = sum(c.n_pairs for c in pending)
    if offsets:
        keys = sorted(offsets)
        rep_f = np.array([k[0] for k in keys], dtype=np.int32)
        rep_v = np.array([k[1] for k in keys], dtype=np.int32)
        rep_o = np.array([offsets[k] for k in keys], dtype=np.float32)
        report.repaired_vertices = len(keys)
        report.max_repair_offset = float(np.linalg.norm(rep_o, axis=1).max())
    else:
        rep_f = np.zeros(0, np.int32)
        rep_v = np.zeros(0, np.int32)
        rep_o = np.zeros((0, 3), np.float32)
    return rep_f, rep_v, rep_o, report


def separate_flexion(vertices: np.ndarray, rest: RestBody, config: BodyConfig,
                     report: SelfCollisionReport) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find where skinning sinks a part into its neighbour across a flexed joint
    (parts.FLEXION_SIDES), move both surfaces to a shared contact surface in those frames and the
    frames either side (datagen.body.flexion), and fill the report's flexion fields. Returns the
    sparse offsets; `vertices` (F, V, 3) is modified in place."""
    det = _detector(rest, pairs=FLEXION_PAIRS, local_radius=FLEXION_REST_RADIUS)
    contacts = det.detect(vertices)
    report.flexion_overlap_frames = sorted({int(c.frame) for c in contacts})
    by_joint: dict[int, set[int]] = defaultdict(set)
    for c in contacts:
        by_joint[flexion_joint(c.part_a, c.part_b)].add(int(c.frame))
    report.flexion_overlap_by_joint = {FLEXION_JOINTS[j]: sorted(by_joint[j])
                                       for j in sorted(by_joint)}
    report.flexion_overlap_max_extent = max((c.extent for c in contacts), default=0.0)
    report.flexion_overlap_max_depth = max((c.depth for c in contacts), default=0.0)
    empty = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
    if not contacts or config.flexion_gap is None:
        report.flexion_residual_frames = list(report.flexion_overlap_frames)
        report.flexion_residual_pairs = sum(c.n_pairs for c in contacts)
        return empty
    # Each joint in its frames and the frames either side too: where the surfaces come within
    # the gap but do not yet cross, so that the correction does not start at full size from one
    # frame to the next.
    found = np.array(report.flexion_overlap_frames)
    joints_at: dict[int, set[int]] = defaultdict(set)
    for joint, joint_frames in by_joint.items():
        for f in joint_frames:
            for g in range(max(f - 1, 0), min(f + 2, len(vertices))):
                joints_at[g].add(joint)
    frames = {f: frozenset(js) for f, js in joints_at.items()}
    rep_f, rep_v, rep_o = separate_flexed_parts(vertices, rest, frames, config.flexion_gap)
    residual = det.detect(vertices[found], frames=found)
    report.flexion_residual_frames = sorted({int(c.frame) for c in residual})
    report.flexion_residual_pairs = sum(c.n_pairs for c in residual)
    report.flexion_separated_vertices = len(rep_v)
    report.flexion_max_offset = float(np.linalg.norm(rep_o, axis=1).max(initial=0.0))
    return rep_f, rep_v, rep_o


def _merge_offsets(*parts: tuple[np.ndarray, np.ndarray, np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One sparse offset per (frame, vertex), sorted: the sum of every part's offsets there."""
    frames = np.concatenate([p[0] for p in parts]).astype(np.int64)
    verts = np.concatenate([p[1] for p in parts]).astype(np.int64)
    offs = np.concatenate([p[2] for p in parts]).astype(np.float64)
    if len(frames) == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
    keys, inverse = np.unique(np.stack([frames, verts], axis=1), axis=0, return_inverse=True)
    summed = np.zeros((len(keys), 3))
    np.add.at(summed, inverse.ravel(), offs)
    return keys[:, 0].astype(np.int32), keys[:, 1].astype(np.int32), summed.astype(np.float32)


def build_body_sequence(
    subject: SubjectSpec,
    motion: Motion,
    lead_in: int,
    model: BodyModel,
    config: BodyConfig,
    dropped_parts: frozenset[str] = frozenset({"head"}),
) -> BodySequence:
    """Pose the subject through `motion` (reference skeleton, no lead-in yet), add the lead-in
    from rest, and repair or reject body self-collisions. Retries with a thinner body when the
    config allows it; the stored shape is the one actually used."""
    check_root_speed(motion)
    unknown = [p for p in dropped_parts if p not in PART_INDEX]
    if unknown:
        raise InputError(None, "dropped_parts", "body part names", unknown)
    # The cloth collider leaves out what the outfit never reaches; self-contact repair also
    # ignores the parts whose contacts are poses rather than errors.
    collider_dropped = frozenset(dropped_parts)
    dropped_parts = collider_dropped | frozenset(config.unrepaired_parts)
    shape = shape_vector(model, subject)
    last_error: RejectedSequence | None = None
    for attempt in range(config.thinner_retries + 1):
        if attempt > 0:
            thinner = getattr(model, "thinner_shape", None)
            if thinner is None:
                break
            shape = thinner(shape)
        rest = model.rest_body(subject.gender, shape)
        moved = add_lead_in(retarget_root(motion, rest.pelvis_height), lead_in)
        poses = moved.poses
        det = _detector(rest, dropped_parts)
        if config.arm_clearance:
            poses, added, posed = clear_arms(
                model, rest, poses, moved.trans, _clearance_detector(rest, det, dropped_parts,
                                                                     collider_dropped),
                config.repair_gap, moved.fps
            )
        else:
            added = np.zeros((2, len(poses)))
            posed = model.pose(rest, poses, moved.trans)
        vertices = posed.vertices
        try:
            rep_f, rep_v, rep_o, report = repair_self_collisions(
                vertices, rest, config, dropped_parts
            )
        except RejectedSequence as exc:
            last_error = exc
            continue
        flexion = separate_flexion(vertices, rest, config, report)
        if len(flexion[0]):
            # The separation moves the parts at a joint by up to a few cm, after the repair
            # measured its residual: the report's is that of the body as it leaves the stage,
            # in every frame either step touched (none new in 11 sequences of the two recipes,
            # 2026-12-01).
            touched = np.unique(np.concatenate([rep_f, flexion[0]]))
            report.residual_pairs = sum(
                c.n_pairs for c in det.detect(vertices[touched], frames=touched))
        rep_f, rep_v, rep_o = _merge_offsets((rep_f, rep_v, rep_o), flexion)
        report.arm_clearance_max_deg = float(np.degrees(added.max(initial=0.0)))
        report.arm_clearance_frames = int(np.count_nonzero(added.max(axis=0) > 0))
        report.thinner_retries = attempt
        part_of_face = rest.part_labels[rest.faces[:, 0]]
        dropped_ids = [PART_INDEX[p] for p in collider_dropped]
        return BodySequence(
            rest=rest,
            poses=poses,
            trans=moved.trans,
            fps=moved.fps,
            action=motion.label,
            motion_source=motion.source,
            lead_in_frames=lead_in,
            joints=posed.joints,
            vertices=vertices,
            skinning=posed.skinning,
            repair_frames=rep_f,
            repair_vertices=rep_v,
            repair_offsets=rep_o,
            self_collision=report,
            collider_face_mask=~np.isin(part_of_face, dropped_ids),
        )
    assert last_error is not None
    raise last_error
