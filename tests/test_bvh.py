"""BVH import: the shared CMU clips, and golden retargeting checks on small synthetic files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from datagen.errors import InputError
from datagen.motion.bvh import (
    JOINT_MAPS,
    detect_convention,
    load_bvh,
    lowest_sole_height,
    parse_bvh,
)
from datagen.skeleton import JOINT_INDEX, REFERENCE_PELVIS_HEIGHT, REFERENCE_REST_JOINTS
from datagen.skeleton import forward_kinematics as canonical_fk

EXPECTED_CONVENTION = {"mb": "motionbuilder", "daz": "daz", "asf": "asf"}
# 07_12_daz's raw capture does not keep its feet on one floor (checked in the test below).
UNGROUNDED_RAW = {"07_12_daz.bvh"}


@pytest.fixture(scope="module")
def cmu_imports(cmu_dir: Path) -> dict[str, tuple]:
    files = sorted(cmu_dir.glob("*.bvh"))
    assert len(files) >= 10, f"expected the 10 shared CMU clips in {cmu_dir}"
    return {f.name: (f, parse_bvh(f), load_bvh(f)) for f in files}


# ---------------------------------------------------------------------------------------------
# Real CMU clips


def test_cmu_clips_import_to_finite_canonical_poses(cmu_imports):
    for name, (path, clip, motion) in cmu_imports.items():
        assert motion.poses.shape == (motion.n_frames, 72), name
        assert np.all(np.isfinite(motion.poses)) and np.all(np.isfinite(motion.trans)), name
        assert motion.source == f"bvh:{name}" and motion.label == path.stem
        assert motion.pelvis_height == REFERENCE_PELVIS_HEIGHT
        # Native frame rate, snapped from the written frame time (.0083333 -> 120).
        assert motion.fps == pytest.approx(round(1.0 / clip.frame_time)), name


def test_cmu_convention_detected_from_hierarchy(cmu_imports):
    for name, (_, clip, _) in cmu_imports.items():
        hint = name.removesuffix(".bvh").rsplit("_", 1)[1]
        assert detect_convention(clip.names) == EXPECTED_CONVENTION[hint], name
    assert detect_convention(["root", "bone1", "bone2"]) is None


def test_motionbuilder_clips_lose_only_their_added_tpose(cmu_imports):
    """MotionBuilder files lose their added T-pose frame; Daz files their converter's snap from
    the rest pose into the capture (a few frames, at most 0.1 s, after which joints move at
    human speeds); ASF-named files keep every frame."""
    from datagen.rotations import angular_velocity

    for name, (_, clip, motion) in cmu_imports.items():
        written = clip.frames.shape[0]
        convention = detect_convention(clip.names)
        if convention == "motionbuilder":
            assert motion.n_frames == written - 1, name
        elif convention == "daz":
            dropped = written - motion.n_frames
            assert 1 <= dropped <= 12, (name, dropped)
            speed = angular_velocity(motion.poses[:12].reshape(-1, 24, 3), motion.fps).max()
            assert speed < 25.0, (name, speed)
        else:
            assert motion.n_frames == written, name


def test_cmu_pelvis_height_and_feet_on_the_ground(cmu_imports):
    for name, (_, _, motion) in cmu_imports.items():
        lowest = lowest_sole_height(motion.poses, motion.trans)
        standing = np.abs(lowest) < 0.03
        assert standing.mean() > 0.1, name
        pelvis = float(np.median(motion.trans[standing, 2]))
        assert 0.8 <= pelvis <= 1.15, (name, pelvis)
        # Grounded by a low percentile: hardly any frame sinks into the floor...
        assert np.mean(lowest < -0.05) < 0.02, name
        # ... and the feet touch the floor in most frames (jumps leave it).
        if name not in UNGROUNDED_RAW:
            assert np.mean(np.abs(lowest) < 0.05) > 0.6, (name, np.mean(np.abs(lowest) < 0.05))


def _raw_joint_heights(clip, joint_names: list[str]) -> np.ndarray:
    """Independent FK of the raw BVH (y up): heights (F, k) of the named joints, BVH units."""
    n = clip.frames.shape[0]
    world = {}
    pos = {}
    for j, parent in enumerate(clip.parents):
        cols = [
            clip.channel_start[j] + k
            for k, c in enumerate(clip.channels[j])
            if c.lower().endswith("rotation")
        ]
        order = "".join(clip.channels[j][k - clip.channel_start[j]][0].upper() for k in cols)
        local = Rotation.from_euler(order, clip.frames[:, cols], degrees=True).as_matrix()
        if parent < 0:
            world[j], pos[j] = local, clip.frames[:, :3]
        else:
            world[j] = world[parent] @ local
            pos[j] = pos[parent] + world[parent] @ clip.offsets[j]
    return np.stack([pos[clip.names.index(n)][:, 1] for n in joint_names], axis=1).reshape(n, -1)


def test_ungrounded_exception_is_the_raw_capture(cmu_imports):
    """07_12_daz is exempt from the feet check because its own lowest ankle wanders ~20 cm."""
    for name in UNGROUNDED_RAW:
        _, clip, _ = cmu_imports[name]
        rest = clip.rest_positions()
        leg = np.linalg.norm(rest[clip.names.index("lShin")] - rest[clip.names.index("lThigh")])
        leg += np.linalg.norm(rest[clip.names.index("lFoot")] - rest[clip.names.index("lShin")])
        ref = REFERENCE_REST_JOINTS
        to_m = (np.linalg.norm(ref[4] - ref[1]) + np.linalg.norm(ref[7] - ref[4])) / leg
        lowest = _raw_joint_heights(clip, ["lFoot", "rFoot"]).min(axis=1) * to_m
        assert np.percentile(lowest, 95) - np.percentile(lowest, 5) > 0.15


# The clavicle joints of every convention, as the importer maps them to the collars.
CLAVICLES = {name.lower() for joints in JOINT_MAPS.values()
             for collar in ("left_collar", "right_collar") for name in joints[collar]}


def test_cmu_shoulders_sit_where_the_reference_skeleton_puts_them(cmu_imports):
    """The clips' clavicle channels are all zero (to 1e-13 degrees), so in every frame each
    shoulder sits at its reference offset from the chest (spine3). Until 2026-12-04 the collars
    were calibrated by their bones' rest directions, and the MotionBuilder and ASF clips, whose
    clavicles are drawn 14-20 degrees up, held their shoulders 6-7 cm too high for their whole
    length (a leather dress's straps then broke the strain bound on every frame); the Daz ones
    about 1.5 cm too low."""
    rest = REFERENCE_REST_JOINTS
    spine3 = JOINT_INDEX["spine3"]
    for name, (_, clip, motion) in cmu_imports.items():
        clavicles = [j for j, n in enumerate(clip.names) if n.lower() in CLAVICLES]
        assert len(clavicles) == 2, name
        for j in clavicles:
            start = clip.channel_start[j]
            assert np.abs(clip.frames[:, start:start + len(clip.channels[j])]).max() < 1e-9, name
        world, joints = canonical_fk(motion.poses, motion.trans, rest)
        for side in ("left", "right"):
            j = JOINT_INDEX[f"{side}_shoulder"]
            in_chest = np.einsum("fji,fj->fi", world[:, spine3], joints[:, j] - joints[:, spine3])
            off = np.abs(in_chest - (rest[j] - rest[spine3])).max()
            assert off < 1e-3, (name, side, off)


def test_import_speed(cmu_dir: Path):
    """Importing a long clip (2397 frames, 316k channel values) costs at most 15 times reading
    its numbers with numpy, the least any importer does, measured in the same run (measured
    4.5 times on 2 cores: 0.62 s against 0.14 s). The median of three of each, as the machine
    is shared (benchmarks.common.timed)."""
    from benchmarks.common import timed
    path = cmu_dir / "13_10_daz.bvh"

    def numbers() -> np.ndarray:
        text = path.read_text()
        return np.array(text.split("Frame Time:")[1].split("\n", 1)[1].split(), dtype=float)

    motion = load_bvh(path)
    assert 2397 - 12 <= motion.n_frames < 2397  # the Daz snap into the capture is dropped
    assert numbers().size == 2397 * 132  # the peer reads every frame's 132 channels
    (ours, _), (peer, _) = timed(lambda: load_bvh(path)), timed(numbers)
    assert ours < 15 * peer, f"13_10_daz.bvh took {ours:.2f} s, numpy reads it in {peer:.2f} s"


# ---------------------------------------------------------------------------------------------
# Synthetic BVH files: y up, facing +z, the body's left at +x, centimetres.

# (name, parent, offset); End Site offsets in END_SITES.
T_POSE = [
    ("Hips", None, (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "Hips", (9.0, -5.0, 0.0)),
    ("LeftLeg", "LeftUpLeg", (0.0, -43.0, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -43.0, 0.0)),
    ("LeftToeBase", "LeftFoot", (0.0, -6.0, 12.0)),
    ("RightUpLeg", "Hips", (-9.0, -5.0, 0.0)),
    ("RightLeg", "RightUpLeg", (0.0, -43.0, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -43.0, 0.0)),
    ("RightToeBase", "RightFoot", (0.0, -6.0, 12.0)),
    ("LowerBack", "Hips", (0.0, 0.0, 0.0)),
    ("Spine", "LowerBack", (0.0, 12.0, 0.0)),
    ("Spine1", "Spine", (0.0, 12.0, 0.0)),
    ("Neck", "Spine1", (0.0, 16.0, 0.0)),
    ("Head", "Neck", (0.0, 10.0, 0.0)),
    ("LeftShoulder", "Spine1", (3.0, 12.0, 0.0)),
    ("LeftArm", "LeftShoulder", (14.0, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (27.0, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (23.0, 0.0, 0.0)),
    ("RightShoulder", "Spine1", (-3.0, 12.0, 0.0)),
    ("RightArm", "RightShoulder", (-14.0, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-27.0, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-23.0, 0.0, 0.0)),
]
END_SITES = {
    "LeftToeBase": (0.0, 0.0, 5.0),
    "RightToeBase": (0.0, 0.0, 5.0),
    "Head": (0.0, 10.0, 0.0),
    "LeftHand": (10.0, 0.0, 0.0),
    "RightHand": (-10.0, 0.0, 0.0),
}
NAMES = [n for n, _, _ in T_POSE]
ARM_SEGMENTS = ("LeftForeArm", "LeftHand", "RightForeArm", "RightHand")  # arm-chain offsets
# A-pose: the arms 45 degrees down (about +/-z in the BVH frame).
Q_LEFT = Rotation.from_euler("z", -45, degrees=True)
Q_RIGHT = Rotation.from_euler("z", 45, degrees=True)


def bvh_text(
    frames: list[dict[str, Rotation]],
    root_pos: np.ndarray,
    order: str = "ZXY",
    scale: float = 1.0,
    names: dict[str, str] | None = None,
    a_pose: bool = False,
    frame_time: str = "0.0333333",
    joint_positions: bool = False,
    clavicle_lift: float = 0.0,
) -> str:
    """A BVH file of the T_POSE skeleton (or its A-pose variant), local rotations per frame;
    `clavicle_lift` (degrees) draws the clavicle bones that far up from flat, as CMU's are."""
    rename = names or {}
    kids: dict[str | None, list[str]] = {}
    for n, p, _ in T_POSE:
        kids.setdefault(p, []).append(n)
    offsets = {n: np.array(o) * scale for n, _, o in T_POSE}
    ends = {n: np.array(o) * scale for n, o in END_SITES.items()}
    if a_pose:
        for n in ARM_SEGMENTS:
            offsets[n] = (Q_LEFT if n.startswith("Left") else Q_RIGHT).apply(offsets[n])
        ends["LeftHand"] = Q_LEFT.apply(ends["LeftHand"])
        ends["RightHand"] = Q_RIGHT.apply(ends["RightHand"])
    for n, sign in (("LeftArm", 1.0), ("RightArm", -1.0)):
        offsets[n] = Rotation.from_euler("z", sign * clavicle_lift, degrees=True).apply(offsets[n])
    rot_channels = " ".join(f"{a}rotation" for a in order)
    lines = ["HIERARCHY"]

    def emit(n: str, depth: int) -> None:
        pad = "\t" * depth
        head = "ROOT" if depth == 0 else "JOINT"
        lines.append(f"{pad}{head} {rename.get(n, n)}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {' '.join(f'{v:.10f}' for v in offsets[n])}")
        if depth == 0 or joint_positions:
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
        else:
            lines.append(f"{pad}\tCHANNELS 3 {rot_channels}")
        for k in kids.get(n, []):
            emit(k, depth + 1)
        if n in ends:
            lines.append(f"{pad}\tEnd Site")
            lines.append(f"{pad}\t{{")
            lines.append(f"{pad}\t\tOFFSET {' '.join(f'{v:.10f}' for v in ends[n])}")
            lines.append(f"{pad}\t}}")
        lines.append(f"{pad}}}")

    emit("Hips", 0)
    order_in_file: list[str] = []

    def collect(n: str) -> None:
        order_in_file.append(n)
        for k in kids.get(n, []):
            collect(k)

    collect("Hips")
    lines += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {frame_time}"]
    for f, frame in enumerate(frames):
        values = list(np.asarray(root_pos[f]) * scale)
        for n in order_in_file:
            if joint_positions and n != "Hips":
                values += list(offsets[n])
            rot = frame.get(n, Rotation.identity())
            values += list(rot.as_euler(order, degrees=True))
        lines.append(" ".join(f"{v:.10f}" for v in values))
    return "\n".join(lines) + "\n"


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def random_frames(n: int, seed: int = 0) -> list[dict[str, Rotation]]:
    rng = np.random.default_rng(seed)
    return [
        {name: Rotation.from_rotvec(rng.normal(scale=0.4, size=3)) for name in NAMES}
        for _ in range(n)
    ]


def random_root(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([0.0, 95.0, 0.0]) + np.cumsum(rng.normal(scale=2.0, size=(n, 3)), axis=0)


def same_rotations(poses_a: np.ndarray, poses_b: np.ndarray, atol: float = 1e-6) -> bool:
    ra = Rotation.from_rotvec(poses_a.reshape(-1, 3)).as_matrix()
    rb = Rotation.from_rotvec(poses_b.reshape(-1, 3)).as_matrix()
    return bool(np.allclose(ra, rb, atol=atol))


def test_golden_elbow_bend(tmp_path: Path):
    """Frame 0 rest, frame 1: left elbow 90 degrees about BVH +y, right elbow 30 about BVH +z.

    Canonical child rotations are expressed in SMPL's body axes (datagen.skeleton), which are the
    BVH's (y up, facing +z): on a skeleton whose arms are the canonical T-pose arms the BVH local
    rotation comes out verbatim. In the world (z up) BVH +y is our +z."""
    frames = [
        {},
        {
            "LeftForeArm": Rotation.from_euler("y", 90, degrees=True),
            "RightForeArm": Rotation.from_euler("z", 30, degrees=True),
        },
    ]
    root = np.array([[0.0, 95.0, 0.0], [0.0, 95.0, 0.0]])
    motion = load_bvh(write(tmp_path, "bend.bvh", bvh_text(frames, root)))
    # Whole-degree frames everywhere: frame 0 is not taken for an added T-pose.
    assert motion.n_frames == 2
    p = motion.poses.reshape(2, 24, 3)
    np.testing.assert_allclose(p[1, JOINT_INDEX["left_elbow"]], [0, np.pi / 2, 0], atol=1e-6)
    np.testing.assert_allclose(p[1, JOINT_INDEX["right_elbow"]], [0, 0, np.pi / 6], atol=1e-6)
    # The arms of this skeleton are canonical T-pose arms: at rest the joints below the shoulders
    # are zero (the shoulders are not: they undo the chest's calibration, this spine being
    # straighter than the reference one).
    for j in ("left_elbow", "left_wrist", "right_elbow", "right_wrist"):
        np.testing.assert_allclose(p[0, JOINT_INDEX[j]], 0.0, atol=1e-9)
    # Nothing else moved.
    others = [
        j for j in range(24) if j not in (JOINT_INDEX["left_elbow"], JOINT_INDEX["right_elbow"])
    ]
    np.testing.assert_allclose(p[1, others], p[0, others], atol=1e-9)
    # In the world the left forearm turned about +z: from +x to +y (BVH: from +x to -z, behind
    # the body); the right one about -y (BVH +z): from -x towards -z (down).
    world, joints = canonical_fk(motion.poses, motion.trans, REFERENCE_REST_JOINTS)
    forearm = joints[1, JOINT_INDEX["left_wrist"]] - joints[1, JOINT_INDEX["left_elbow"]]
    np.testing.assert_allclose(forearm / np.linalg.norm(forearm), [0, 1, 0], atol=1e-6)
    forearm = joints[1, JOINT_INDEX["right_wrist"]] - joints[1, JOINT_INDEX["right_elbow"]]
    expected = [-np.cos(np.pi / 6), 0, -np.sin(np.pi / 6)]
    np.testing.assert_allclose(forearm / np.linalg.norm(forearm), expected, atol=1e-6)
    np.testing.assert_allclose(
        world[1, JOINT_INDEX["left_elbow"]],
        Rotation.from_euler("z", 90, degrees=True).as_matrix(),
        atol=1e-6,
    )


def test_a_collar_follows_its_clavicle_from_the_bvh_rest_pose(tmp_path: Path):
    """However the skeleton draws its clavicle bones (flat, or 20 degrees up as CMU's are), a
    collar is neutral at the BVH rest pose and turns as far as its clavicle turns from it: a
    15 degree shrug of the left clavicle raises the left shoulder about 3.8 cm (0.143 m of
    reference collar, from 6.3 degrees down to 8.7 up) and leaves the right one where it was."""
    frames = [{}, {"LeftShoulder": Rotation.from_euler("z", 15, degrees=True)}]
    root = np.array([[0.0, 95.0, 0.0], [0.0, 95.0, 0.0]])
    motions = [load_bvh(write(tmp_path, f"lift{lift}.bvh",
                              bvh_text(frames, root, clavicle_lift=lift)))
               for lift in (0.0, 20.0)]
    assert same_rotations(motions[0].poses, motions[1].poses)
    for motion in motions:
        p = motion.poses.reshape(2, 24, 3)
        for side in ("left", "right"):
            np.testing.assert_allclose(p[0, JOINT_INDEX[f"{side}_collar"]], 0.0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(p[1, JOINT_INDEX["left_collar"]]),
                                   np.radians(15), atol=1e-6)
        np.testing.assert_allclose(p[1, JOINT_INDEX["right_collar"]], 0.0, atol=1e-9)
        _, joints = canonical_fk(motion.poses, motion.trans, REFERENCE_REST_JOINTS)
        rise = joints[1, :, 2] - joints[0, :, 2]
        assert 0.036 < rise[JOINT_INDEX["left_shoulder"]] < 0.040
        np.testing.assert_allclose(rise[JOINT_INDEX["right_shoulder"]], 0.0, atol=1e-9)


def test_a_pose_rest_gives_the_same_world_arms_as_t_pose(tmp_path: Path):
    n = 4
    t_frames = random_frames(n, seed=3)
    for f in t_frames:  # a non-zero root rotation keeps frame 0 a real frame
        f["Hips"] = Rotation.from_euler("y", 10.5, degrees=True) * f["Hips"]
    a_frames = []
    for f in t_frames:
        g = dict(f)
        for side, q in (("Left", Q_LEFT), ("Right", Q_RIGHT)):
            # Same world segments: W_A = W_T Q^T along the arm chain.
            g[f"{side}Arm"] = f[f"{side}Arm"] * q.inv()
            g[f"{side}ForeArm"] = q * f[f"{side}ForeArm"] * q.inv()
            g[f"{side}Hand"] = q * f[f"{side}Hand"] * q.inv()
        a_frames.append(g)
    root = random_root(n)
    t_motion = load_bvh(write(tmp_path, "t.bvh", bvh_text(t_frames, root)))
    a_motion = load_bvh(write(tmp_path, "a.bvh", bvh_text(a_frames, root, a_pose=True)))
    assert t_motion.n_frames == a_motion.n_frames == n
    _, jt = canonical_fk(t_motion.poses, t_motion.trans, REFERENCE_REST_JOINTS)
    _, ja = canonical_fk(a_motion.poses, a_motion.trans, REFERENCE_REST_JOINTS)
    for side in ("left", "right"):
        chain = [f"{side}_shoulder", f"{side}_elbow", f"{side}_wrist", f"{side}_hand"]
        for a, b in zip(chain[:-1], chain[1:], strict=True):
            dt = jt[:, JOINT_INDEX[b]] - jt[:, JOINT_INDEX[a]]
            da = ja[:, JOINT_INDEX[b]] - ja[:, JOINT_INDEX[a]]
            np.testing.assert_allclose(da, dt, atol=1e-6)
    assert same_rotations(a_motion.poses, t_motion.poses)
    # And the arms really moved (the check is not between two rest poses).
    assert np.abs(t_motion.poses.reshape(n, 24, 3)[:, JOINT_INDEX["left_shoulder"]]).max() > 0.1


def test_channel_order_does_not_change_the_motion(tmp_path: Path):
    frames = random_frames(5, seed=7)
    root = random_root(5)
    zxy = load_bvh(write(tmp_path, "zxy.bvh", bvh_text(frames, root, order="ZXY")))
    xyz = load_bvh(write(tmp_path, "xyz.bvh", bvh_text(frames, root, order="XYZ")))
    assert zxy.n_frames == xyz.n_frames == 5
    assert same_rotations(zxy.poses, xyz.poses)
    np.testing.assert_allclose(zxy.trans, xyz.trans, atol=1e-9)
    # The orders really differ in the file: the same Euler numbers read as XYZ give another pose.
    text = bvh_text(frames, root, order="ZXY").replace(
        "Zrotation Xrotation Yrotation", "Xrotation Yrotation Zrotation"
    )
    misread = load_bvh(write(tmp_path, "misread.bvh", text))
    assert not same_rotations(misread.poses, zxy.poses, atol=1e-3)


def test_position_channels_on_every_joint(tmp_path: Path):
    frames = random_frames(4, seed=13)
    root = random_root(4)
    three = load_bvh(write(tmp_path, "three.bvh", bvh_text(frames, root)))
    six_text = bvh_text(frames, root, joint_positions=True)
    assert six_text.count("CHANNELS 6") == len(NAMES)
    six = load_bvh(write(tmp_path, "six.bvh", "\ufeff" + six_text.replace("\n", "\r\n")))
    assert six.n_frames == 4
    assert same_rotations(six.poses, three.poses)
    np.testing.assert_allclose(six.trans, three.trans, atol=1e-9)


def test_units_come_from_the_skeleton(tmp_path: Path):
    frames = random_frames(6, seed=11)
    root = random_root(6)
    cm = load_bvh(write(tmp_path, "cm.bvh", bvh_text(frames, root)))
    mm = load_bvh(write(tmp_path, "mm.bvh", bvh_text(frames, root, scale=10.0)))
    np.testing.assert_allclose(mm.trans, cm.trans, atol=1e-9)
    assert same_rotations(mm.poses, cm.poses)
    # Leg 86 units here vs the reference's 0.861 m: horizontal travel in metres ~ units / 100.
    travel_units = np.linalg.norm(root[-1, [0, 2]] - root[0, [0, 2]])
    travel_m = np.linalg.norm(cm.trans[-1, :2] - cm.trans[0, :2])
    ref_leg = np.linalg.norm(REFERENCE_REST_JOINTS[4] - REFERENCE_REST_JOINTS[1]) + np.linalg.norm(
        REFERENCE_REST_JOINTS[7] - REFERENCE_REST_JOINTS[4]
    )
    assert travel_m == pytest.approx(travel_units * ref_leg / 86.0, rel=1e-9)


def test_joint_map_overrides_detection(tmp_path: Path):
    frames = random_frames(3, seed=5)
    root = random_root(3)
    rename = {n: f"bone{k}" for k, n in enumerate(NAMES)}
    path = write(tmp_path, "renamed.bvh", bvh_text(frames, root, names=rename))
    reference = load_bvh(write(tmp_path, "named.bvh", bvh_text(frames, root)))
    canon = {
        "pelvis": "Hips",
        "left_hip": "LeftUpLeg",
        "left_knee": "LeftLeg",
        "left_ankle": "LeftFoot",
        "left_foot": "LeftToeBase",
        "right_hip": "RightUpLeg",
        "right_knee": "RightLeg",
        "right_ankle": "RightFoot",
        "right_foot": "RightToeBase",
        "spine1": "LowerBack",
        "spine2": "Spine",
        "spine3": "Spine1",
        "neck": "Neck",
        "head": "Head",
        "left_collar": "LeftShoulder",
        "left_shoulder": "LeftArm",
        "left_elbow": "LeftForeArm",
        "left_wrist": "LeftHand",
        "right_collar": "RightShoulder",
        "right_shoulder": "RightArm",
        "right_elbow": "RightForeArm",
        "right_wrist": "RightHand",
    }
    mapped = load_bvh(path, joint_map={c: rename[b] for c, b in canon.items()}, label="walk")
    assert mapped.label == "walk"
    assert same_rotations(mapped.poses, reference.poses)
    np.testing.assert_allclose(mapped.trans, reference.trans, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Errors


def _assert_input_error(exc: pytest.ExceptionInfo, path: Path, field: str) -> None:
    message = str(exc.value)
    assert path.name in message, message
    assert field in message, message


def test_truncated_file(tmp_path: Path, cmu_dir: Path):
    text = (cmu_dir / "02_03_daz.bvh").read_text()
    motion_at = text.index("MOTION")
    cut = write(tmp_path, "cut.bvh", text[: motion_at + (len(text) - motion_at) // 2])
    with pytest.raises(InputError) as exc:
        load_bvh(cut)
    _assert_input_error(exc, cut, "MOTION frame")
    # Cut at a line end: fewer frame lines than 'Frames:' says.
    lines = text.splitlines(keepends=True)
    short = write(tmp_path, "short.bvh", "".join(lines[:-10]))
    with pytest.raises(InputError) as exc:
        load_bvh(short)
    _assert_input_error(exc, short, "MOTION frame")
    assert "truncated" in str(exc.value)


def test_unknown_skeleton_needs_a_joint_map(tmp_path: Path):
    rename = {n: f"bone{k}" for k, n in enumerate(NAMES)}
    path = write(tmp_path, "bones.bvh", bvh_text([{}], np.zeros((1, 3)), names=rename))
    with pytest.raises(InputError) as exc:
        load_bvh(path)
    _assert_input_error(exc, path, "HIERARCHY")
    assert "joint map" in str(exc.value)


def test_joint_map_naming_a_missing_joint(tmp_path: Path):
    path = write(tmp_path, "named.bvh", bvh_text([{}], np.zeros((1, 3))))
    with pytest.raises(InputError) as exc:
        load_bvh(path, joint_map={"pelvis": "Hips", "left_knee": "LeftKnee"})
    _assert_input_error(exc, path, "joint_map")
    assert "LeftKnee" in str(exc.value)
    with pytest.raises(InputError) as exc:
        load_bvh(path, joint_map={"left_toe": "LeftToeBase"})
    _assert_input_error(exc, path, "joint_map")


def _edit_frame(text: str, frame: int, edit) -> str:
    """Apply `edit` to the value list of one frame line (0-based) of a bvh_text file."""
    lines = text.splitlines()
    first = lines.index("MOTION") + 3
    values = lines[first + frame].split()
    lines[first + frame] = " ".join(edit(values))
    return "\n".join(lines) + "\n"


MUTATIONS = {
    # id: (edit of the file text, field the message must name)
    "no-motion": (lambda t: t.replace("MOTION\n", ""), "MOTION"),
    # An empty file or another format is named as such, not as a BVH missing its MOTION.
    "empty": (lambda t: "", "HIERARCHY"),
    "not-bvh": (lambda t: '{"poses": [[0, 0, 0]]}\n', "HIERARCHY"),
    "unbalanced": (lambda t: t.replace("End Site\n", "End Site\n{\n", 1), "HIERARCHY"),
    "channel-count": (lambda t: t.replace("CHANNELS 3 Z", "CHANNELS 4 Z", 1), "HIERARCHY"),
    "frame-time": (lambda t: t.replace("Frame Time: 0.0333333", "Frame Time: 0"), "Frame Time"),
    "frame-count": (lambda t: t.replace("Frames: 3", "Frames: three"), "Frames"),
    "non-finite": (
        lambda t: _edit_frame(t, 1, lambda v: v[:1] + ["nan"] + v[2:]),
        "MOTION frame 2",
    ),
    "extra-value": (lambda t: _edit_frame(t, 1, lambda v: v + ["1.0"]), "MOTION frame 2"),
    "not-a-number": (lambda t: _edit_frame(t, 2, lambda v: v[:-1] + ["x"]), "MOTION frame 3"),
}


@pytest.mark.parametrize("mutation", sorted(MUTATIONS))
def test_malformed_files(tmp_path: Path, mutation: str):
    edit, field = MUTATIONS[mutation]
    text = bvh_text([{}, {}, {}], np.array([[0.0, 95.0, 0.0]] * 3))
    assert load_bvh(write(tmp_path, "good.bvh", text)).n_frames == 3
    bad = edit(text)
    assert bad != text
    path = write(tmp_path, "bad.bvh", bad)
    with pytest.raises(InputError) as exc:
        load_bvh(path)
    _assert_input_error(exc, path, field)
