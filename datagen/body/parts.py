"""Body parts: about 20 regions of the canonical skeleton, shared by every body model.

Used for self-collision classes (which parts may touch), for dropping unreachable parts from the
cloth collider, and as the segmentation that GCVAE-style models pool over.
"""

from __future__ import annotations

import numpy as np

from datagen.skeleton import JOINT_INDEX, NUM_JOINTS

PART_NAMES: tuple[str, ...] = (
    "pelvis",
    "thigh_l",
    "thigh_r",
    "spine_lower",
    "shin_l",
    "shin_r",
    "spine_mid",
    "foot_l",
    "foot_r",
    "chest",
    "neck",
    "collar_l",
    "collar_r",
    "head",
    "upperarm_l",
    "upperarm_r",
    "forearm_l",
    "forearm_r",
    "hand_l",
    "hand_r",
)
PART_INDEX = {name: i for i, name in enumerate(PART_NAMES)}

# Canonical joint -> the part its rotation moves.
_JOINT_PART = {
    "pelvis": "pelvis",
    "left_hip": "thigh_l",
    "right_hip": "thigh_r",
    "spine1": "spine_lower",
    "left_knee": "shin_l",
    "right_knee": "shin_r",
    "spine2": "spine_mid",
    "left_ankle": "foot_l",
    "right_ankle": "foot_r",
    "spine3": "chest",
    "left_foot": "foot_l",
    "right_foot": "foot_r",
    "neck": "neck",
    "left_collar": "collar_l",
    "right_collar": "collar_r",
    "head": "head",
    "left_shoulder": "upperarm_l",
    "right_shoulder": "upperarm_r",
    "left_elbow": "forearm_l",
    "right_elbow": "forearm_r",
    "left_wrist": "hand_l",
    "right_wrist": "hand_r",
    "left_hand": "hand_l",
    "right_hand": "hand_r",
}
JOINT_TO_PART = np.array(
    [PART_INDEX[_JOINT_PART[name]] for name in sorted(JOINT_INDEX, key=JOINT_INDEX.get)],
    dtype=np.int16,
)
assert len(JOINT_TO_PART) == NUM_JOINTS

TORSO = frozenset({"pelvis", "spine_lower", "spine_mid", "chest", "neck", "collar_l", "collar_r"})

# Parts that meet at a joint, or belong to the torso: contact between them is normal anatomy.
_NEIGHBOUR_PAIRS = {
    ("pelvis", "thigh_l"),
    ("pelvis", "thigh_r"),
    ("thigh_l", "shin_l"),
    ("thigh_r", "shin_r"),
    ("shin_l", "foot_l"),
    ("shin_r", "foot_r"),
    ("neck", "head"),
    ("collar_l", "upperarm_l"),
    ("collar_r", "upperarm_r"),
    ("upperarm_l", "forearm_l"),
    ("upperarm_r", "forearm_r"),
    ("forearm_l", "hand_l"),
    ("forearm_r", "hand_r"),
    ("spine_lower", "thigh_l"),
    ("spine_lower", "thigh_r"),
    ("chest", "upperarm_l"),
    ("chest", "upperarm_r"),
}


def part_neighbours() -> np.ndarray:
    """(P, P) bool: True where contact between the two parts is not a self-collision."""
    n = len(PART_NAMES)
    nb = np.eye(n, dtype=bool)
    for a in TORSO:
        for b in TORSO:
            nb[PART_INDEX[a], PART_INDEX[b]] = True
    for a, b in _NEIGHBOUR_PAIRS:
        nb[PART_INDEX[a], PART_INDEX[b]] = nb[PART_INDEX[b], PART_INDEX[a]] = True
    return nb


# Where small intersections are expected and repairable (thesis 3.3.1: armpits and crotch, and
# arms resting against the hips): an arm against the torso or a thigh, the thighs against each
# other. Anything else (an arm against a shin, a hand in the head) is incompatible.
_ARMS = ("upperarm_l", "upperarm_r", "forearm_l", "forearm_r")
_ARM_TARGETS = (
    "pelvis",
    "spine_lower",
    "spine_mid",
    "chest",
    "collar_l",
    "collar_r",
    "thigh_l",
    "thigh_r",
)
SOLVABLE_PAIRS = frozenset(
    {frozenset({arm, other}) for arm in _ARMS for other in _ARM_TARGETS}
    | {frozenset({"thigh_l", "thigh_r"})}
) - {frozenset({"upperarm_l", "collar_l"}), frozenset({"upperarm_r", "collar_r"})}

# Parts joined at a joint that linear blend skinning sinks into each other at strong flexion: a
# thigh into the lower torso (a kick's chamber, a squat), a calf into its thigh (a deep knee
# bend), a forearm into its biceps (a runner's or a waving arm's bent elbow: 2 cm deep in
# `make dataset`'s run). They are skeleton neighbours, so the self-collision repair leaves them
# alone; the body stage moves both surfaces to a shared contact surface instead
# (datagen.body.flexion). Each entry is two sides, each one or more parts, and is named by its
# joint in FLEXION_JOINTS. Triangles closer than FLEXION_REST_RADIUS at rest are the skin
# bending at the joint, not an overlap.
_LOWER_TORSO = ("pelvis", "spine_lower")
FLEXION_SIDES: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = (
    (_LOWER_TORSO, ("thigh_l",)),
    (_LOWER_TORSO, ("thigh_r",)),
    (("thigh_l",), ("shin_l",)),
    (("thigh_r",), ("shin_r",)),
    (("upperarm_l",), ("forearm_l",)),
    (("upperarm_r",), ("forearm_r",)),
)
FLEXION_JOINTS: tuple[str, ...] = ("hip_l", "hip_r", "knee_l", "knee_r", "elbow_l", "elbow_r")
# The same as part pairs, for the self-collision detector.
FLEXION_PAIRS: tuple[tuple[str, str], ...] = tuple(
    (a, b) for side_a, side_b in FLEXION_SIDES for a in side_a for b in side_b
)
FLEXION_REST_RADIUS = 0.08  # metres


def flexion_joint(part_a: int, part_b: int) -> int:
    """The index in FLEXION_SIDES (and FLEXION_JOINTS) of the joint across which two parts (by
    PART_INDEX) fold onto each other."""
    names = {PART_NAMES[part_a], PART_NAMES[part_b]}
    for joint, (side_a, side_b) in enumerate(FLEXION_SIDES):
        if any(names == {a, b} for a in side_a for b in side_b):
            return joint
    raise ValueError(f"{sorted(names)} do not fold across one of {FLEXION_JOINTS}")

# Which part yields in a repair: the first of a pair in this order moves (both thighs share).
MOVABLE_ORDER = ("forearm_l", "forearm_r", "upperarm_l", "upperarm_r", "thigh_l", "thigh_r")
