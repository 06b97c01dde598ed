"""The body stage: Anny retargeting, skinning, self-collision detection and repair."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.body.anny_model import NEUTRAL_SHAPE
from datagen.body.parts import PART_INDEX, PART_NAMES
from datagen.body.selfcollision import SelfCollisionDetector, classify, repair_contact
from datagen.body.sequence import repair_self_collisions
from datagen.errors import RejectedSequence
from datagen.recipe import BodyConfig
from datagen.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from datagen.skeleton import (
    JOINT_INDEX,
    NUM_JOINTS,
    REFERENCE_PELVIS_HEIGHT,
    REFERENCE_REST_JOINTS,
    forward_kinematics,
    world_axes_to_local,
)


@pytest.fixture(scope="module")
def rest(body_model):
    return body_model.rest_body("female", NEUTRAL_SHAPE)


def pose_from_world_axes(rotations: dict[str, np.ndarray], n_frames: int = 1) -> np.ndarray:
    """Canonical poses from local rotations written in world axes (easier to reason about)."""
    local = np.tile(np.eye(3), (n_frames, NUM_JOINTS, 1, 1))
    for name, aa in rotations.items():
        local[:, JOINT_INDEX[name]] = axis_angle_to_matrix(np.asarray(aa, dtype=np.float64))
    return matrix_to_axis_angle(world_axes_to_local(local)).reshape(n_frames, NUM_JOINTS * 3)


def test_reference_skeleton_matches_anny(body_model):
    """The reference skeleton constants in datagen.skeleton are Anny's neutral T-pose."""
    from datagen.body.anny_model import reference_rest_joints

    joints, height = reference_rest_joints()
    assert np.abs(joints - REFERENCE_REST_JOINTS).max() < 1e-3
    assert abs(height - REFERENCE_PELVIS_HEIGHT) < 1e-3


def test_rest_body_is_a_t_pose(rest):
    v, j = rest.vertices, rest.joints
    assert abs(v[:, 2].min()) < 1e-9  # soles on the ground
    assert abs(j[0, 0]) < 1e-9 and abs(j[0, 1]) < 1e-9
    for side, sign in (("left", 1), ("right", -1)):
        arm = j[JOINT_INDEX[f"{side}_wrist"]] - j[JOINT_INDEX[f"{side}_shoulder"]]
        assert sign * arm[0] > 0.4 and abs(arm[2]) < 1e-6 and abs(arm[1]) < 1e-6
    assert 1.5 < v[:, 2].max() < 1.95  # an adult's height
    # the body faces -y: the toes are in front of the ankles
    assert j[JOINT_INDEX["left_foot"], 1] < j[JOINT_INDEX["left_ankle"], 1]
    assert set(np.unique(rest.part_labels)) == set(range(len(PART_NAMES)))


def _part_rotation(rest_pts: np.ndarray, posed_pts: np.ndarray) -> np.ndarray:
    """Best rigid rotation (Kabsch) taking a part's rest vertices to its posed vertices."""
    a = rest_pts - rest_pts.mean(axis=0)
    b = posed_pts - posed_pts.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1, 1, d]) @ u.T


@pytest.mark.parametrize(
    "joint, child, part, axis_angle",
    [
        ("left_shoulder", "left_elbow", "upperarm_l", [0.0, 1.1, 0.0]),  # arm down 63 degrees
        ("right_shoulder", "right_elbow", "upperarm_r", [0.0, 0.0, 0.9]),  # arm forward
        ("left_elbow", "left_wrist", "forearm_l", [0.0, 0.0, 1.2]),  # forearm bends forward
        ("right_hip", "right_knee", "thigh_r", [-0.8, 0.0, 0.0]),  # leg forward
        ("left_knee", "left_ankle", "shin_l", [1.1, 0.0, 0.0]),  # knee flexion
        ("spine1", "spine2", "spine_mid", [0.5, 0.0, 0.0]),  # bend forward
    ],
)
def test_retargeting_limb_directions(body_model, rest, joint, child, part, axis_angle):
    """Rotating one canonical joint moves the matching Anny limb so that its direction agrees
    with the canonical skeleton's limb within 3 degrees."""
    poses = pose_from_world_axes({joint: axis_angle})
    trans = rest.joints[None, 0]
    posed = body_model.pose(rest, poses, trans)
    _, joints = forward_kinematics(poses, trans, rest.joints)
    j, c = JOINT_INDEX[joint], JOINT_INDEX[child]
    canon_rest = rest.joints[c] - rest.joints[j]
    canon_posed = joints[0, c] - joints[0, j]
    # the canonical limb really moved
    assert (
        np.degrees(
            np.arccos(
                np.dot(canon_rest, canon_posed)
                / np.linalg.norm(canon_rest)
                / np.linalg.norm(canon_posed)
            )
        )
        > 25
    )
    # the Anny limb: the rigid motion of the part's vertices that skin mostly to it
    mask = rest.part_labels == PART_INDEX[part]
    rot = _part_rotation(rest.vertices[mask], posed.vertices[0][mask].astype(np.float64))
    mesh_dir = rot @ canon_rest
    cos = np.dot(mesh_dir, canon_posed) / np.linalg.norm(mesh_dir) / np.linalg.norm(canon_posed)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 3.0


def test_skinning_matches_annys_own(body_model, rest):
    """Our linear blend skinning of the retargeted bones equals Anny's own skinning when Anny is
    given the same bone world poses."""
    import torch

    from datagen.body.anny_model import GENDER_VALUE, SHAPE_NAMES, _anny_model

    rng = np.random.default_rng(3)
    poses = pose_from_world_axes(
        {
            "left_shoulder": [0, 0.9, 0.2],
            "right_elbow": [0, 0, -1.0],
            "spine2": [0.3, 0.1, 0],
            "left_knee": [0.9, 0, 0],
        }
    )
    poses[:, :3] = rng.normal(size=3) * 0.3
    trans = rest.joints[None, 0] + np.array([0.1, -0.2, 0.05])
    ours = body_model.pose(rest, poses, trans)
    model = _anny_model()
    kwargs = {"gender": GENDER_VALUE["female"]}
    kwargs.update(dict(zip(SHAPE_NAMES, map(float, NEUTRAL_SHAPE), strict=True)))
    with torch.no_grad():
        coeffs = model.get_phenotype_blendshape_coefficients(**kwargs)
        rest_model = model.get_rest_model(coeffs)
        rest_poses = rest_model["rest_bone_poses"][0].double().numpy()  # (B, 4, 4)
    t = ours.skinning.transforms[0]  # (B, 3, 4): world = T @ rest
    world = np.tile(np.eye(4), (len(t), 1, 1))
    world[:, :3, :] = np.einsum("bij,bjk->bik", t, rest_poses)
    with torch.no_grad():
        out = model(
            pose_parameters=torch.from_numpy(world)[None].to(model.dtype),
            phenotype_kwargs=kwargs,
            pose_parameterization="world",
        )
    theirs = out["vertices"][0].double().numpy()
    assert np.abs(theirs - ours.vertices[0]).max() < 2e-4


# -- self-collision ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def detector(rest):
    return SelfCollisionDetector(rest.faces, rest.part_labels, rest.vertices)


def test_rest_pose_has_no_self_intersection(detector, rest):
    assert detector.detect(rest.vertices[None].astype(np.float32)) == []


def test_forearm_through_torso_is_found_and_rejected(body_model, rest, detector):
    # Arm down along the side, forearm turned inwards through the waist.
    poses = pose_from_world_axes(
        {"left_shoulder": [0.0, 1.45, 0.0], "left_elbow": [0.0, np.pi - 1.45, 0.0]}
    )
    posed = body_model.pose(rest, poses, rest.joints[None, 0])
    contacts = detector.detect(posed.vertices)
    names = {c.pair_name for c in contacts}
    assert any("forearm_l" in n for n in names), names
    verdict = classify(contacts, BodyConfig().max_solvable_extent, BodyConfig().max_solvable_depth)
    assert verdict.fatal
    reason, frames = verdict.reason()
    assert ("forearm_l" in reason or "hand_l" in reason) and frames == (0, 0)
    assert any("forearm_l" in c.pair_name and c.depth > 0.03 for c in verdict.fatal)
    with pytest.raises(RejectedSequence, match="forearm_l"):
        repair_self_collisions(posed.vertices.copy(), rest, BodyConfig(), frozenset())


def _gap(vertices, rest, a: str, b: str, near: np.ndarray) -> float:
    """Smallest distance from part a's vertices near `near` to part b's triangles, over the
    vertices and triangles that lie apart in the rest pose (the ones that meet at the shoulder
    are the same skin, not a gap)."""
    import trimesh
    from scipy.spatial import cKDTree

    from datagen.body.selfcollision import LOCAL_RADIUS

    faces, labels = rest.faces, rest.part_labels
    fb = faces[labels[faces[:, 0]] == PART_INDEX[b]]
    va = np.flatnonzero(
        (labels == PART_INDEX[a]) & (np.linalg.norm(vertices - near, axis=1) < 0.15)
    )
    rest_b = rest.vertices[np.unique(fb)]
    far = cKDTree(rest_b).query(rest.vertices[va])[0] > LOCAL_RADIUS
    va = va[far]
    mesh_b = trimesh.Trimesh(vertices, fb, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh_b, vertices[va])
    return float(dist.min())


def test_armpit_repair_leaves_a_4mm_gap(body_model, rest, detector):
    """Arms pressed to the sides: a small armpit intersection, repaired with >= 4 mm gap."""
    # keep the hands off the thighs: bend the elbows forward
    poses2 = pose_from_world_axes(
        {
            "left_shoulder": [0.0, 1.5, 0.0],
            "right_shoulder": [0.0, -1.5, 0.0],
            "left_elbow": [0.0, 0.0, 1.3],
            "right_elbow": [0.0, 0.0, -1.3],
        }
    )
    posed = body_model.pose(rest, poses2, rest.joints[None, 0])
    v = posed.vertices.copy()
    contacts = [c for c in detector.detect(v) if "upperarm_l" in c.pair_name]
    assert contacts, "the test pose should press the upper arm into the torso"
    contact = contacts[0]
    other = (
        PART_NAMES[contact.part_b]
        if PART_NAMES[contact.part_a] == "upperarm_l"
        else PART_NAMES[contact.part_a]
    )
    centre = v[0][rest.faces[contact.tri_a].ravel()].mean(axis=0)
    before = _gap(v[0].astype(np.float64), rest, "upperarm_l", other, centre)
    assert before < 0.002  # touching or inside
    offsets = repair_contact(v[0], rest.faces, rest.part_labels, contact, 0.004, rest.vertices)
    fixed = v[0].astype(np.float64).copy()
    for i, off in offsets.items():
        fixed[i] += off
    after = _gap(fixed, rest, "upperarm_l", other, centre)
    assert after >= 0.004 - 2e-4
    assert not [
        c
        for c in detector.detect(fixed[None].astype(np.float32))
        if c.pair_name == contact.pair_name
    ]
    # the arm moved, the torso did not
    moved = np.array(list(offsets))
    assert np.all(rest.part_labels[moved] == PART_INDEX["upperarm_l"])
    # and the surface stays smooth: no offset jumps between neighbouring vertices by > 1 cm
    assert max(np.linalg.norm(o) for o in offsets.values()) < 0.05


def test_full_repair_pipeline(body_model, rest):
    poses = pose_from_world_axes(
        {
            "left_shoulder": [0.0, 1.5, 0.0],
            "right_shoulder": [0.0, -1.5, 0.0],
            "left_elbow": [0.0, 0.0, 1.3],
            "right_elbow": [0.0, 0.0, -1.3],
        },
        n_frames=3,
    )
    posed = body_model.pose(rest, poses, np.repeat(rest.joints[None, 0], 3, axis=0))
    v = posed.vertices.copy()
    rf, rv, ro, report = repair_self_collisions(v, rest, BodyConfig(), frozenset())
    assert report.frames_with_contact == 3
    assert report.repaired_vertices > 0 and len(rf) == report.repaired_vertices
    assert report.residual_pairs == 0
    # the sparse offsets rebuild the repaired vertices exactly from the unrepaired ones
    rebuilt = posed.vertices.copy()
    np.add.at(rebuilt, (rf, rv), ro)
    assert np.abs(rebuilt - v).max() < 1e-5


def test_flexed_hip_and_knee_are_separated_at_a_shared_contact_surface(body_model):
    """Skinning sinks a raised thigh into the belly and the calf into the hamstring during a
    high kick's extension and re-chamber (never in a walk); the body stage finds it, moves both
    surfaces to a contact surface between them, and stores the moves with the sparse repair
    offsets. Afterwards almost no vertex of those parts lies inside another part, few triangle
    pairs still cross, the surface does not fold over, and the offsets rebuild the vertices."""
    import json

    import igl

    from datagen.body.flexion import FlexionSeparator
    from datagen.body.parts import FLEXION_PAIRS, FLEXION_REST_RADIUS
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.load import motion_from_spec
    from datagen.spec import MotionSpec, SubjectSpec

    def build(action, params, frames, config=None):
        spec = MotionSpec(action=action, params=params, frames=frames)
        return build_body_sequence(SubjectSpec(gender="male"), motion_from_spec(spec, None), 0,
                                   body_model, config or BodyConfig())

    kick = build("kick", {"height": 1.0}, 45)  # the first kick: chamber at 0.55 s, down at 1.45 s
    report = kick.self_collision
    found = report.flexion_overlap_frames
    assert found, "a 1 m kick sinks the thigh into the belly"
    assert min(found) >= int(0.55 * 30) and max(found) <= int(1.45 * 30), found
    assert report.flexion_overlap_max_extent > 0.10 and report.flexion_overlap_max_depth > 0.05
    assert json.loads(json.dumps(report.as_dict()))["flexion_overlap_frames"] == found
    # Per joint: the kicking leg's hip and knee, whose frames together are the overlap frames.
    by_joint = report.flexion_overlap_by_joint
    assert set(by_joint) == {"hip_r", "knee_r"}, by_joint
    assert sorted(set().union(*map(set, by_joint.values()))) == found

    rest = kick.rest
    skinned = body_model.pose(rest, kick.poses, kick.trans).vertices
    faces = rest.faces.astype(np.int64)
    hips_and_legs = np.isin(rest.part_labels, [PART_INDEX[p] for p in (
        "pelvis", "spine_lower", "thigh_l", "thigh_r", "shin_l", "shin_r")])
    separator = FlexionSeparator(rest, 0.01)

    def inside_another_part(v):
        v = v.astype(np.float64)
        probe = v + 1e-3 * separator.vertex_normals(v)
        return int(np.count_nonzero(igl.fast_winding_number(v, faces, probe)[hips_and_legs] > 0.5))

    before = sum(inside_another_part(skinned[f]) for f in found)
    after = sum(inside_another_part(kick.vertices[f]) for f in found)
    assert before > 500 and after < 0.25 * before, (before, after)
    detector = SelfCollisionDetector(rest.faces, rest.part_labels, rest.vertices,
                                     pairs=FLEXION_PAIRS, local_radius=FLEXION_REST_RADIUS)
    pairs_before = sum(c.n_pairs for c in detector.detect(skinned[found]))
    assert report.flexion_residual_pairs < 0.1 * pairs_before, (report.flexion_residual_pairs,
                                                                 pairs_before)
    assert 0.01 < report.flexion_max_offset < 0.15

    # The surface stays a surface: few triangles turn over (the moved ones number thousands).
    def face_normals(v):
        t = v[:, faces]
        return np.cross(t[:, :, 1] - t[:, :, 0], t[:, :, 2] - t[:, :, 0])

    turned = np.einsum("fti,fti->ft", face_normals(skinned[found]),
                       face_normals(kick.vertices[found]))
    assert np.count_nonzero(turned < 0) < 20 * len(found)
    # The sparse offsets (the self-collision repair's and the separation's) rebuild the vertices.
    rebuilt = skinned.copy()
    np.add.at(rebuilt, (kick.repair_frames, kick.repair_vertices), kick.repair_offsets)
    assert np.abs(rebuilt - kick.vertices).max() < 1e-5
    assert len(kick.repair_vertices) >= report.flexion_separated_vertices > 0

    # flexion_gap null leaves the overlap as skinning made it, and says so.
    left = build("kick", {"height": 1.0}, 45, BodyConfig(flexion_gap=None)).self_collision
    assert left.flexion_residual_frames == found and left.flexion_separated_vertices == 0
    assert left.flexion_residual_pairs == pairs_before
    walk = build("walk", {}, 45).self_collision
    assert walk.flexion_overlap_frames == [] and walk.flexion_separated_vertices == 0


def test_bent_elbows_are_separated_and_reported_per_joint(body_model):
    """A run's swinging arms bend the elbows to 100 degrees, where skinning sinks the forearm
    into the biceps (about 1 cm at the forearm's deepest vertex). The body stage reports those
    frames under each elbow and separates the two parts there as at the hip and knee; a wave's
    arm, lifted and bent on one side only, folds at that elbow only."""
    import igl

    from datagen.body.flexion import FlexionSeparator
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.load import motion_from_spec
    from datagen.spec import MotionSpec, SubjectSpec

    def build(action, config=None):
        spec = MotionSpec(action=action, frames=45)
        return build_body_sequence(SubjectSpec(gender="male"), motion_from_spec(spec, None), 0,
                                   body_model, config or BodyConfig())

    run = build("run")
    report = run.self_collision
    by_joint = report.flexion_overlap_by_joint
    assert len(by_joint.get("elbow_l", [])) > 10 and len(by_joint.get("elbow_r", [])) > 10
    assert report.flexion_residual_pairs == 0

    rest = run.rest
    skinned = body_model.pose(rest, run.poses, run.trans).vertices
    faces = rest.faces.astype(np.int64)
    separator = FlexionSeparator(rest, 0.01)

    def forearm_depth(v, side):
        """How deep the forearm's deepest vertex is inside its upper arm (0 if none is)."""
        v = v.astype(np.float64)
        forearm = np.flatnonzero(rest.part_labels == PART_INDEX[f"forearm_{side}"])
        probe = v[forearm] + 1e-3 * separator.vertex_normals(v)[forearm]
        inside = forearm[igl.fast_winding_number(v, faces, probe) > 0.5]
        upper = faces[separator.tri_part == PART_INDEX[f"upperarm_{side}"]]
        if len(inside) == 0:
            return 0.0
        sd, *_ = igl.signed_distance(v[inside], v, upper)
        return float(max(0.0, -sd.min()))

    for side in ("l", "r"):
        frames = by_joint[f"elbow_{side}"]
        before = max(forearm_depth(skinned[f], side) for f in frames)
        after = max(forearm_depth(run.vertices[f], side) for f in frames)
        assert before > 0.005 and after < 0.001, (side, before, after)
    wave = build("wave").self_collision.flexion_overlap_by_joint
    assert set(wave) == {"elbow_r"}, wave


def test_the_reported_residual_is_the_bodys_after_the_flexion_separation(body_model,
                                                                        monkeypatch):
    """The repair measures its residual intersections before the flexion separation moves the
    parts at a joint; the report's residual is that of the body as it leaves the stage. A
    separation that, besides its own work, sinks the right forearm into the chest in its first
    frame (as no real one did in 11 sequences of the two recipes) shows in `residual_pairs`,
    which counts exactly what the detector finds in the final body; before, it said 0."""
    from datagen.body import sequence
    from datagen.body.sequence import _detector, build_body_sequence
    from datagen.motion.load import motion_from_spec
    from datagen.spec import MotionSpec, SubjectSpec

    real = sequence.separate_flexed_parts

    sunk = []

    def and_a_forearm_in_the_chest(vertices, rest, frames, gap):
        rep_f, rep_v, rep_o = real(vertices, rest, frames, gap)
        f = min(frames)
        forearm = np.flatnonzero(rest.part_labels == PART_INDEX["forearm_r"])
        chest = np.flatnonzero(rest.part_labels == PART_INDEX["chest"])
        sink = vertices[f, chest].mean(axis=0) - vertices[f, forearm].mean(axis=0)
        vertices[f, forearm] += sink
        sunk.append(f)
        return (np.r_[rep_f, np.full(len(forearm), f, np.int32)], np.r_[rep_v, forearm],
                np.r_[rep_o, np.tile(sink, (len(forearm), 1)).astype(np.float32)])

    monkeypatch.setattr(sequence, "separate_flexed_parts", and_a_forearm_in_the_chest)
    body = build_body_sequence(SubjectSpec(gender="male"),
                               motion_from_spec(MotionSpec(action="run", frames=12), None), 0,
                               body_model, BodyConfig())
    report = body.self_collision
    assert report.flexion_overlap_frames  # the run's elbows fold: the separation ran
    final = _detector(body.rest, frozenset(report.dropped_parts)).detect(body.vertices)
    assert {c.frame for c in final} == set(sunk)
    assert report.residual_pairs == sum(c.n_pairs for c in final) > 0


def test_the_rest_body_does_not_depend_on_torchs_thread_count(body_model):
    """Anny's blendshapes are a torch computation whose reductions split by thread: with two
    threads a subject's rest shape rounded 7e-18 m away from one thread's, and a Dask worker
    (torch on one thread) then wrote cloth up to 2.4 cm from a local process's after 6 frames
    (chaos amplifies it). The model runs on one thread, so both give the same body bit for bit,
    and the caller's thread count is left as it was."""
    import torch

    from datagen.body.anny_model import NEUTRAL_SHAPE

    threads = torch.get_num_threads()
    bodies = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            body_model._subjects.clear()  # the subject cache would hand back the first
            bodies.append(body_model.rest_body("female", NEUTRAL_SHAPE.copy()).vertices)
            assert torch.get_num_threads() == n
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_array_equal(bodies[0], bodies[1])


def test_a_sequences_body_does_not_depend_on_the_subjects_built_before_it(body_model):
    """The self-collision detector's notion of which triangles are local to each other comes
    from the subject's own rest pose. It was kept per topology from the first subject a process
    built, so a dataset worker's bodies, their repairs and reports depended on the sequences it
    had built before: a 1 m kick counted 1105 crossing flexion pairs after a heavy female
    subject, 1160 on its own (a test worker's order showed it)."""
    from datagen.body.parts import FLEXION_PAIRS, FLEXION_REST_RADIUS
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.load import motion_from_spec
    from datagen.spec import MotionSpec, SubjectSpec

    kick = motion_from_spec(MotionSpec(action="kick", params={"height": 1.0}, frames=45), None)
    config = BodyConfig(flexion_gap=None)  # the overlap as skinning made it, counted
    heavy = SubjectSpec(gender="female", shape={"weight": 1.0, "muscle": 1.0, "height": 0.0})
    build_body_sequence(heavy, kick, 0, body_model, config)
    seq = build_body_sequence(SubjectSpec(gender="male"), kick, 0, body_model, config)
    own = SelfCollisionDetector(seq.rest.faces, seq.rest.part_labels, seq.rest.vertices,
                                pairs=FLEXION_PAIRS, local_radius=FLEXION_REST_RADIUS)
    contacts = own.detect(body_model.pose(seq.rest, seq.poses, seq.trans).vertices)
    report = seq.self_collision
    assert report.flexion_overlap_frames == sorted({int(c.frame) for c in contacts})
    assert report.flexion_residual_pairs == sum(c.n_pairs for c in contacts) > 0


def test_procedural_actions_are_mostly_intersection_free(body_model):
    """At default parameters, >= 95 % of 100 sampled bodies move through the procedural actions
    without body self-intersection (the figures are printed; docs/benchmarks.md records them).

    Counted over the parts whose contacts are repaired (not the hands, feet and head: their
    contacts are poses), after the body stage fits the arms to the subject's girth, before any
    mesh repair. The raw figure (no arm fit) is reported beside it."""
    from datagen.body.anny_model import SHAPE_NAMES, SHAPE_RANGE
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.procedural import ACTIONS, generate
    from datagen.spec import SubjectSpec

    rng = np.random.default_rng(2026)
    actions = sorted(ACTIONS)
    clean = raw_clean = 0
    n = 100
    for k in range(n):
        gender = "female" if rng.random() < 2 / 3 else "male"
        shape = {name: float(rng.uniform(*SHAPE_RANGE[name])) for name in SHAPE_NAMES}
        motion = generate(actions[k % len(actions)], 60, 10.0)  # 6 s, every 3rd frame at 30 fps
        # Counted before any change to the mesh: the flexion separation is tested above.
        config = BodyConfig(thinner_retries=0, flexion_gap=None)
        try:
            seq = build_body_sequence(
                SubjectSpec(gender=gender, shape=shape), motion, 0, body_model, config
            )
        except RejectedSequence:
            continue
        sc = seq.self_collision
        clean += sc.frames_with_contact == 0
        raw_clean += sc.frames_with_contact == 0 and sc.arm_clearance_frames == 0
    print(
        f"\nprocedural actions: {clean}/{n} bodies intersection-free after the arm fit, "
        f"{raw_clean}/{n} without any adjustment"
    )
    assert clean >= 95


def test_anny_cache_folders_the_process_cannot_write_or_create(tmp_path, monkeypatch):
    """Processes take turns building Anny's cache under a file lock in its folder. A cache
    built beforehand and shared read-only (a cluster's) cannot hold the lock's file, and
    nothing can be built there: it is read without the lock, where the lock's file failed to be
    created before. A folder that cannot be created is an error naming ANNY_CACHE_DIR."""
    import os

    from filelock import FileLock

    from datagen.body import anny_model
    from datagen.errors import InputError

    writable = tmp_path / "cache"
    assert isinstance(anny_model._build_lock(writable), FileLock) and writable.is_dir()
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o555)
    if os.geteuid() == 0:  # root writes anywhere: ask as anyone else would be answered
        monkeypatch.setattr(anny_model.os, "access",
                            lambda p, mode: not (mode & os.W_OK and not os.stat(p).st_mode
                                                 & 0o200))
    with anny_model._build_lock(shared):
        pass
    assert list(shared.iterdir()) == []  # no lock file written
    (tmp_path / "a_file").write_text("")
    with pytest.raises(InputError, match="ANNY_CACHE_DIR.*a folder this process can create"):
        anny_model._build_lock(tmp_path / "a_file" / "anny")


def test_anny_cache_files_are_readable_as_the_umask_allows(tmp_path, body_model):
    """Anny writes its cache files readable by their owner alone (0600); a cache built to be
    shared read-only (a cluster's) must be readable by the others the umask lets read: the
    files this process owns gain the read bits the umask allows, and nothing else changes."""
    import os
    import stat

    from anny.paths import get_anny_cache_path

    from datagen.body.anny_model import share_cache_files

    cache = tmp_path / "cache"
    (cache / "v1").mkdir(parents=True)
    data = cache / "v1" / "load_data.safetensors"
    data.write_bytes(b"x")
    data.chmod(0o600)
    script = cache / "tool.sh"
    script.write_bytes(b"x")
    script.chmod(0o700)
    umask = os.umask(0o027)
    try:
        share_cache_files(cache)
    finally:
        os.umask(umask)
    assert stat.S_IMODE(data.stat().st_mode) == 0o640
    assert stat.S_IMODE(script.stat().st_mode) == 0o740  # read bits only: no execute, no write
    # The session's real cache, built (or read) by the model this suite uses.
    readable = 0o444 & ~umask
    files = [p for p in get_anny_cache_path().rglob("*.safetensors")
             if p.stat().st_uid == os.getuid()]
    assert files, "the session's Anny cache holds no data files"
    for path in files:
        assert path.stat().st_mode & readable == readable, path


def _hand_clearance(body, side: str) -> float:
    """Least signed distance (m) of a hand's vertices to the torso, hips and thighs over a
    sequence's frames: negative where the hand sinks into them."""
    import igl

    from datagen.body.arm_clearance import BODY_PARTS

    faces, labels = body.rest.faces, body.rest.part_labels
    face_parts = labels[faces[:, 0]]
    trunk = faces[np.isin(face_parts, [PART_INDEX[p] for p in BODY_PARTS])].astype(np.int64)
    hand = np.unique(faces[face_parts == PART_INDEX[f"hand_{side}"]])
    return min(float(igl.signed_distance(v[hand].astype(np.float64), v.astype(np.float64),
                                         trunk)[0].min()) for v in body.vertices)


def test_hands_in_the_cloth_collider_are_cleared_of_the_thighs(body_model):
    """CMU 12_01's capture subject swings its hands close to its own thighs; on a broader
    subject (the default recipe's seed 606, sequence 0) they sank 27 and 38 mm into the thighs
    and hips, with leather trousers between that had no room: every run ran away. Hands are not
    repaired (a hand on a thigh is a pose), but the arm fit clears them, as it clears the arms,
    wherever they stay in the cloth collider, and leaves them where the outfit drops them."""
    from pathlib import Path

    import datagen
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.load import motion_from_spec
    from datagen.spec import MotionSpec, SubjectSpec

    subject = SubjectSpec(gender="female", shape={
        "age": 0.808971, "muscle": 0.230475, "weight": 0.069486, "height": 0.205981,
        "proportions": 0.674336})
    spec = MotionSpec(source="bvh", action="12_01_mb", file="data/mocap/cmu/12_01_mb.bvh",
                      start=0.490497, frames=90)
    motion = motion_from_spec(spec, Path(datagen.__file__).parent)
    config = BodyConfig()
    worn = build_body_sequence(subject, motion, spec.lead_in, body_model, config,
                               frozenset({"head"}))
    for side in "lr":
        assert _hand_clearance(worn, side) >= config.repair_gap, side
    bare = build_body_sequence(subject, motion, spec.lead_in, body_model, config,
                               frozenset({"head", "hand_l", "hand_r"}))
    assert _hand_clearance(bare, "r") < -0.02
