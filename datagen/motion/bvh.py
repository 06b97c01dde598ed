"""BVH motion capture -> canonical `Motion` (datagen.skeleton conventions) at the file's frame rate.

Parsing: any channel order and count (the root with 6 channels, joints with 3 or 6, position
channels on non-root joints, `End Site` blocks). Euler channels are intrinsic in the order written
("Zrotation Xrotation Yrotation" -> Rz @ Rx @ Ry, degrees); a joint's world rotation is
parent_world @ local. Position channels of non-root joints are parsed but unused (only rotations
and the pelvis position are retargeted). The root position is its position channels (its OFFSET
where it has none).

Skeleton conventions (detected from the HIERARCHY's joint names, never from the file name):
"motionbuilder" (cgspeed MotionBuilder-friendly: Hips, LeftUpLeg, ...), "daz" (cgspeed
Daz-friendly: hip, abdomen, chest, lThigh, lShldr, ...) and "asf" (CMU ASF names: hip, lfemur,
ltibia, lhumerus, ...). Each canonical joint is driven by the BVH joint whose rotation moves that
canonical joint's segment (`JOINT_MAPS`):

- MotionBuilder and ASF are the same CMU skeleton under two namings. Spine: LowerBack/lowerback ->
  spine1, Spine/upperback -> spine2, Spine1/thorax -> spine3 (the clavicles hang from it, as the
  canonical collars hang from spine3). Neck: Neck/lowerneck, the joint at the base of the neck
  where the canonical neck sits; the upper-neck rotation (Neck1/upperneck) then shows up in the
  head's rotation relative to the neck (the head's world rotation is exact either way). Hands:
  LeftHand/lwrist -> wrist, LeftFingerBase/lhand (the joint that moves the fingers) -> hand.
- Daz has two spine joints (abdomen, chest) for three canonical ones and no toe joint:
  abdomen -> spine1, chest -> spine3 (the collars hang from it), and spine2 takes half of the
  rotation between spine1 and spine3 (see below); left/right_foot have no partner and stay identity
  relative to the ankle. The hand joint is the middle finger's base (lMid1/rMid1), the best stand-in
  for the knuckles. Buttock joints are folded into the thighs (world rotations are composed).

Canonical joints without a partner: a joint with a mapped descendant along its primary chain takes
an even share of the rotation between its nearest mapped ancestor and that descendant (world
rotations slerped), so a bend spreads over the spine; any other stays identity relative to its
parent. A user `joint_map` (canonical name -> BVH joint name) replaces the detected map and follows
the same rules (pelvis defaults to the BVH root).

Retargeting (rest-pose aware): for canonical joint j driven by BVH joint b, d_j is the canonical
rest direction of j's segment (towards its primary child; pelvis -> spine1, spine3 -> neck; fixed
directions for leaves: head +z, left hand +x, right hand -x, feet -y) and o_b the BVH rest
direction of the same segment in our frame (towards the BVH joint mapped to j's canonical child; if
that one sits on b, the next mapped joint down the canonical chain; for leaves, b's end site or its
only child). C_j = rotation_between(d_j, o_b) and the canonical world rotation is
G_j(t) = A W_b(t) A^T C_j, with A the change of axes BVH (x, y, z) -> ours (x, -z, y) (CMU BVH are
y-up, facing +z, the body's left at +x). So the result does not depend on whether the BVH rest
pose is a T-pose. `skeleton.world_to_local` turns the world rotations G into canonical poses
(whatever axes the canonical child rotations are expressed in). Where b has no usable
direction (e.g. Daz's head, whose only children are the eyes), C_j is the rest rotation of j's
nearest mapped ancestor: the joint is neutral relative to it when the BVH is at rest. The collars
(REST_NEUTRAL) take that rule too, whatever their bones' directions: a clavicle's rest direction
is how the skeleton was drawn, not a pose, so a collar is neutral relative to the chest where
the BVH's clavicle is at rest (the shared CMU clips' clavicle channels are all zero).

Frames: cgspeed MotionBuilder-friendly files start with an added T-pose frame. It is detected
from its content (root rotation zero, every rotation channel a whole number of degrees within
45 degrees of zero, as the converter writes it, while later frames are real capture) and dropped;
real first frames are kept. (cgspeed Daz-friendly files start with their rest pose and ~5 frames
that snap into the motion within 40 ms; they are kept as written, so callers wanting a clean start
should window past the first frames.)
Frame times written with few digits (.0083333) are snapped to the whole frame rate they round to.
Extra frame lines beyond `Frames:` are ignored; fewer are an error.

Scale and ground: BVH units -> metres by the ratio of the reference hip->knee + knee->ankle length
(REFERENCE_REST_JOINTS) to the BVH's (averaged over the mapped sides). The root translation is
scaled by it; then the motion is grounded: per frame the lowest sole estimate from forward
kinematics of the canonical poses on the reference skeleton (`lowest_sole_height`), and the 5th
percentile of that goes to z = 0, so jumps still leave the ground. `pelvis_height` is
REFERENCE_PELVIS_HEIGHT.
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from datagen.errors import InputError
from datagen.rotations import rotation_between
from datagen.skeleton import (
    JOINT_INDEX,
    JOINT_NAMES,
    NUM_JOINTS,
    PARENTS,
    REFERENCE_PELVIS_HEIGHT,
    REFERENCE_REST_JOINTS,
    SMPL_TO_WORLD,
    forward_kinematics,
    world_to_local,
)
from datagen.types import Motion

# BVH (x, y, z) -> ours (x, -z, y): y-up facing +z -> z-up facing -y (the same change as SMPL's).
BVH_TO_WORLD = SMPL_TO_WORLD

# canonical joint -> candidate BVH joint names, first present wins (matched case-insensitively).
# Absent joints are left unmapped (see the module docstring); `_SIGNATURES` must all be present.
JOINT_MAPS: dict[str, dict[str, tuple[str, ...]]] = {
    "motionbuilder": {
        "pelvis": ("Hips",),
        "left_hip": ("LeftUpLeg",),
        "right_hip": ("RightUpLeg",),
        "spine1": ("LowerBack",),
        "left_knee": ("LeftLeg",),
        "right_knee": ("RightLeg",),
        "spine2": ("Spine",),
        "left_ankle": ("LeftFoot",),
        "right_ankle": ("RightFoot",),
        "spine3": ("Spine1",),
        "left_foot": ("LeftToeBase",),
        "right_foot": ("RightToeBase",),
        "neck": ("Neck", "Neck1"),
        "left_collar": ("LeftShoulder",),
        "right_collar": ("RightShoulder",),
        "head": ("Head",),
        "left_shoulder": ("LeftArm",),
        "right_shoulder": ("RightArm",),
        "left_elbow": ("LeftForeArm",),
        "right_elbow": ("RightForeArm",),
        "left_wrist": ("LeftHand",),
        "right_wrist": ("RightHand",),
        "left_hand": ("LeftFingerBase", "LeftHandIndex1", "LFingers"),
        "right_hand": ("RightFingerBase", "RightHandIndex1", "RFingers"),
    },
    "daz": {
        "pelvis": ("hip",),
        "left_hip": ("lThigh",),
        "right_hip": ("rThigh",),
        "spine1": ("abdomen",),
        "left_knee": ("lShin",),
        "right_knee": ("rShin",),
        "left_ankle": ("lFoot",),
        "right_ankle": ("rFoot",),
        "spine3": ("chest",),
        "neck": ("neck",),
        "left_collar": ("lCollar",),
        "right_collar": ("rCollar",),
        "head": ("head",),
        "left_shoulder": ("lShldr",),
        "right_shoulder": ("rShldr",),
        "left_elbow": ("lForeArm",),
        "right_elbow": ("rForeArm",),
        "left_wrist": ("lHand",),
        "right_wrist": ("rHand",),
        "left_hand": ("lMid1",),
        "right_hand": ("rMid1",),
    },
    "asf": {
        "pelvis": ("hip", "root", "Hips"),
        "left_hip": ("lfemur",),
        "right_hip": ("rfemur",),
        "spine1": ("lowerback",),
        "left_knee": ("ltibia",),
        "right_knee": ("rtibia",),
        "spine2": ("upperback",),
        "left_ankle": ("lfoot",),
        "right_ankle": ("rfoot",),
        "spine3": ("thorax",),
        "left_foot": ("ltoes",),
        "right_foot": ("rtoes",),
        "neck": ("lowerneck", "upperneck"),
        "left_collar": ("lclavicle",),
        "right_collar": ("rclavicle",),
        "head": ("head",),
        "left_shoulder": ("lhumerus",),
        "right_shoulder": ("rhumerus",),
        "left_elbow": ("lradius",),
        "right_elbow": ("rradius",),
        "left_wrist": ("lwrist",),
        "right_wrist": ("rwrist",),
        "left_hand": ("lhand",),
        "right_hand": ("rhand",),
    },
}

# Joints that identify a convention (all must be present); the legs and arms every map needs.
_SIGNATURES: dict[str, tuple[str, ...]] = {
    "motionbuilder": (
        "Hips",
        "LeftUpLeg",
        "LeftLeg",
        "LeftFoot",
        "RightUpLeg",
        "RightLeg",
        "RightFoot",
        "LeftArm",
        "LeftForeArm",
        "RightArm",
        "RightForeArm",
    ),
    "daz": (
        "hip",
        "abdomen",
        "chest",
        "lThigh",
        "lShin",
        "lFoot",
        "rThigh",
        "rShin",
        "rFoot",
        "lShldr",
        "lForeArm",
        "rShldr",
        "rForeArm",
    ),
    "asf": (
        "lfemur",
        "ltibia",
        "lfoot",
        "rfemur",
        "rtibia",
        "rfoot",
        "lhumerus",
        "lradius",
        "rhumerus",
        "rradius",
    ),
}

# Segment directions of canonical leaves (no child joint): the head points up, hands outwards,
# feet forwards (the body faces -y).
_LEAF_DIRECTIONS = {
    "head": (0.0, 0.0, 1.0),
    "left_hand": (1.0, 0.0, 0.0),
    "right_hand": (-1.0, 0.0, 0.0),
    "left_foot": (0.0, -1.0, 0.0),
    "right_foot": (0.0, -1.0, 0.0),
}


def _primary_children() -> tuple[int | None, ...]:
    """The child whose direction defines each canonical joint's segment (None for leaves)."""
    out: list[int | None] = []
    for j in range(NUM_JOINTS):
        kids = [c for c in range(NUM_JOINTS) if PARENTS[c] == j]
        if JOINT_NAMES[j] == "pelvis":
            out.append(JOINT_INDEX["spine1"])
        elif JOINT_NAMES[j] == "spine3":
            out.append(JOINT_INDEX["neck"])
        else:
            out.append(kids[0] if kids else None)
    return tuple(out)


_PRIMARY_CHILD = _primary_children()

# Joints whose BVH rest pose is their neutral pose, not a direction to match. A clavicle bone's
# rest direction is how the skeleton was drawn, not a pose: CMU's (MotionBuilder and ASF) runs
# from the neck's base 14-20 degrees up to the shoulder, Daz's from the chest 12 down, the
# reference collar's 6 down, each in a T-pose. Matched by direction, every CMU MotionBuilder and
# ASF clip held its shoulders shrugged 6-7 cm for its whole length.
REST_NEUTRAL = frozenset({"left_collar", "right_collar"})

# Heights above the soles, in the reference T-pose, of the joints the sole estimate uses.
_SOLE_JOINTS = np.array(
    [JOINT_INDEX[n] for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]
)
_SOLE_OFFSETS = REFERENCE_REST_JOINTS[_SOLE_JOINTS, 2] + REFERENCE_PELVIS_HEIGHT

_ROTATION_CHANNELS = {"xrotation": "X", "yrotation": "Y", "zrotation": "Z"}
_POSITION_CHANNELS = {"xposition": 0, "yposition": 1, "zposition": 2}


@dataclass
class BvhClip:
    """A parsed BVH file: hierarchy (parents listed before children) and raw channel values."""

    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (J, 3) BVH units
    channels: list[list[str]]  # per joint, e.g. ["Xposition", ..., "Zrotation"]
    channel_start: list[int]  # index of each joint's first channel in a frame line
    end_sites: dict[int, list[np.ndarray]] = field(default_factory=dict)
    frames: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (F, C)
    frame_time: float = 0.0

    @property
    def n_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    def children(self, j: int) -> list[int]:
        return [k for k, p in enumerate(self.parents) if p == j]

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions with every rotation at identity, BVH frame and units."""
        pos = np.zeros((len(self.names), 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos


# ---------------------------------------------------------------------------------------------
# Parsing


def _float(tok: str, path: Path, field_: str, expected: str) -> float:
    try:
        return float(tok)
    except ValueError:
        raise InputError(path, field_, expected, tok) from None


def _check_start(text: str, path: Path) -> None:
    """An empty file or another format fails here, before its missing MOTION is blamed."""
    first = text.split(maxsplit=1)[:1]
    if not first or first[0].upper() != "HIERARCHY":
        raise InputError(
            path,
            "HIERARCHY",
            "a BVH file starting with 'HIERARCHY'",
            first[0][:40] if first else "an empty file",
        )


def _parse_hierarchy(text: str, path: Path) -> BvhClip:
    """The skeleton of `text`, which _check_start found to begin with HIERARCHY."""
    tokens = text.split()
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray | None] = []
    channels: list[list[str]] = []
    end_sites: dict[int, list[np.ndarray]] = {}
    # Stack of open blocks: a joint index, or ("end", owner joint) for End Site blocks.
    stack: list[int | tuple[str, int]] = []
    pending: int | tuple[str, int] | None = None  # a block named but whose '{' is not read yet
    end_offset: np.ndarray | None = None
    i = 1
    n = len(tokens)

    def need(k: int, what: str) -> None:
        if i + k >= n:
            raise InputError(path, "HIERARCHY", what, "end of HIERARCHY")

    while i < n:
        tok = tokens[i]
        key = tok.upper()
        if pending is not None and tok != "{":
            raise InputError(path, "HIERARCHY", "'{' after a joint or End Site name", tok)
        if key in ("ROOT", "JOINT"):
            need(1, f"a joint name after {tok}")
            if key == "ROOT" and (stack or names):
                raise InputError(path, "HIERARCHY", "a single ROOT joint", f"ROOT {tokens[i + 1]}")
            if key == "JOINT" and (not stack or not isinstance(stack[-1], int)):
                raise InputError(
                    path, "HIERARCHY", "JOINT inside a joint's braces", f"JOINT {tokens[i + 1]}"
                )
            names.append(tokens[i + 1])
            parents.append(stack[-1] if stack else -1)  # type: ignore[arg-type]
            offsets.append(None)
            channels.append([])
            pending = len(names) - 1
            i += 2
        elif key == "END":
            if i + 1 >= n or tokens[i + 1].upper() != "SITE" or not stack:
                raise InputError(path, "HIERARCHY", "'End Site' inside a joint's braces", tok)
            if not isinstance(stack[-1], int):
                raise InputError(path, "HIERARCHY", "End Site inside a joint's braces", "End Site")
            pending = ("end", stack[-1])
            end_offset = None
            i += 2
        elif tok == "{":
            if pending is None:
                raise InputError(
                    path,
                    "HIERARCHY",
                    "'{' only after a joint or End Site name",
                    "'{' without a name",
                )
            stack.append(pending)
            pending = None
            i += 1
        elif tok == "}":
            if not stack:
                raise InputError(path, "HIERARCHY", "balanced braces", "an unmatched '}'")
            top = stack.pop()
            if isinstance(top, tuple):
                end_sites.setdefault(top[1], []).append(
                    end_offset if end_offset is not None else np.zeros(3)
                )
            elif offsets[top] is None:
                raise InputError(path, "HIERARCHY", f"an OFFSET for joint '{names[top]}'", "none")
            i += 1
        elif key == "OFFSET":
            need(3, "three numbers after OFFSET")
            if not stack:
                raise InputError(path, "HIERARCHY", "OFFSET inside a joint's braces", "OFFSET")
            vec = np.array(
                [
                    _float(t, path, "HIERARCHY", "three numbers after OFFSET")
                    for t in tokens[i + 1 : i + 4]
                ]
            )
            if not np.all(np.isfinite(vec)):
                raise InputError(path, "HIERARCHY", "finite OFFSET values", vec.tolist())
            top = stack[-1]
            if isinstance(top, tuple):
                end_offset = vec
            else:
                offsets[top] = vec
            i += 4
        elif key == "CHANNELS":
            if not stack or not isinstance(stack[-1], int):
                raise InputError(path, "HIERARCHY", "CHANNELS inside a joint's braces", "CHANNELS")
            joint = stack[-1]
            need(1, "a channel count after CHANNELS")
            try:
                count = int(tokens[i + 1])
            except ValueError:
                raise InputError(
                    path,
                    "HIERARCHY",
                    f"a channel count after CHANNELS of joint '{names[joint]}'",
                    tokens[i + 1],
                ) from None
            listed = tokens[i + 2 : i + 2 + count]
            valid = [
                t
                for t in itertools.takewhile(
                    lambda t: t.lower() in _ROTATION_CHANNELS or t.lower() in _POSITION_CHANNELS,
                    listed,
                )
            ]
            after = tokens[i + 2 + count] if i + 2 + count < n else ""
            if (
                count < 0
                or len(valid) != count
                or (after.lower() in _ROTATION_CHANNELS or after.lower() in _POSITION_CHANNELS)
            ):
                got = " ".join(tokens[i : i + 2 + max(count, 0) + 1])
                raise InputError(
                    path,
                    "HIERARCHY",
                    f"{count} channel names after 'CHANNELS {count}' of joint '{names[joint]}'",
                    got,
                )
            channels[joint] = list(valid)
            i += 2 + count
        else:
            raise InputError(
                path, "HIERARCHY", "ROOT, JOINT, End Site, OFFSET, CHANNELS or braces", tok
            )
    if pending is not None or stack:
        raise InputError(
            path,
            "HIERARCHY",
            "balanced braces: every '{' closed by '}'",
            f"{len(stack)} block(s) still open at MOTION",
        )
    if not names:
        raise InputError(path, "HIERARCHY", "a ROOT joint", "none")
    starts = list(itertools.accumulate([0] + [len(c) for c in channels[:-1]]))
    return BvhClip(
        names=names,
        parents=parents,
        offsets=np.array(offsets, dtype=np.float64),
        channels=channels,
        channel_start=starts,
        end_sites=end_sites,
    )


_MOTION_RE = re.compile(r"^[ \t]*MOTION[ \t]*\r?$", re.MULTILINE)


def parse_bvh(path: str | Path) -> BvhClip:
    """Parse a BVH file (hierarchy and raw frame values); InputError on any malformed part."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")  # some exporters write a BOM
    except OSError as e:
        raise InputError(path, None, "a readable BVH file", e.strerror or str(e)) from None
    _check_start(text, path)
    m = _MOTION_RE.search(text)
    if m is None:
        raise InputError(path, "MOTION", "a MOTION section after the HIERARCHY", "missing")
    clip = _parse_hierarchy(text[: m.start()], path)

    lines = [ln for ln in text[m.end() :].splitlines() if ln.strip()]
    fm = re.match(r"\s*Frames:\s*(\S+)\s*$", lines[0]) if lines else None
    if fm is None:
        raise InputError(
            path,
            "Frames",
            "a 'Frames: <count>' line after MOTION",
            lines[0].strip() if lines else "end of file",
        )
    try:
        n_frames = int(fm.group(1))
    except ValueError:
        raise InputError(path, "Frames", "a whole number of frames", fm.group(1)) from None
    if n_frames < 1:
        raise InputError(path, "Frames", "at least one frame", n_frames)
    tm = re.match(r"\s*Frame\s+Time:\s*(\S+)\s*$", lines[1]) if len(lines) > 1 else None
    if tm is None:
        raise InputError(
            path,
            "Frame Time",
            "a 'Frame Time: <seconds>' line after Frames",
            lines[1].strip() if len(lines) > 1 else "end of file",
        )
    frame_time = _float(tm.group(1), path, "Frame Time", "a frame time in seconds")
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise InputError(path, "Frame Time", "a positive frame time in seconds", frame_time)

    n_ch = clip.n_channels
    rows = [ln.split() for ln in lines[2 : 2 + n_frames]]
    for k, row in enumerate(rows):
        if len(row) != n_ch:
            raise InputError(
                path,
                f"MOTION frame {k + 1}",
                f"{n_ch} values, one per channel of the HIERARCHY",
                f"{len(row)} values",
            )
    if len(rows) < n_frames:
        raise InputError(
            path,
            f"MOTION frame {len(rows) + 1}",
            f"{n_frames} frame lines as 'Frames:' says (file truncated?)",
            f"{len(rows)} frame lines",
        )
    try:
        frames = np.array(list(itertools.chain.from_iterable(rows)), dtype=np.float64)
    except ValueError:
        for k, row in enumerate(rows):  # slow path, only to name the culprit
            for tok in row:
                _float(tok, path, f"MOTION frame {k + 1}", "numbers")
        raise
    frames = frames.reshape(n_frames, n_ch)
    bad = ~np.isfinite(frames)
    if bad.any():
        k = int(np.argmax(bad.any(axis=1)))
        raise InputError(
            path, f"MOTION frame {k + 1}", "finite numbers", float(frames[k][bad[k]][0])
        )
    clip.frames = frames
    clip.frame_time = frame_time
    return clip


# ---------------------------------------------------------------------------------------------
# Forward kinematics of the BVH


def _local_rotations(clip: BvhClip, j: int, frames: np.ndarray) -> np.ndarray | None:
    """(F, 3, 3) local rotation of joint j from its rotation channels, None if it has none."""
    order = ""
    cols = []
    for k, ch in enumerate(clip.channels[j]):
        axis = _ROTATION_CHANNELS.get(ch.lower())
        if axis is not None:
            order += axis
            cols.append(clip.channel_start[j] + k)
    if not order:
        return None
    # Upper-case sequence = intrinsic rotations in the order written.
    return Rotation.from_euler(order, frames[:, cols], degrees=True).as_matrix()


def _world_rotations(clip: BvhClip, frames: np.ndarray, needed: set[int]) -> dict[int, np.ndarray]:
    """World rotations (F, 3, 3) of the needed joints and their ancestors, BVH frame."""
    keep: set[int] = set()
    for j in needed:
        while j >= 0 and j not in keep:
            keep.add(j)
            j = clip.parents[j]
    eye = np.broadcast_to(np.eye(3), (frames.shape[0], 3, 3))
    world: dict[int, np.ndarray] = {}
    for j in sorted(keep):  # parents are listed before their children
        local = _local_rotations(clip, j, frames)
        p = clip.parents[j]
        parent = world[p] if p >= 0 else eye
        world[j] = parent if local is None else parent @ local
    return world


def _joint_positions(
    clip: BvhClip, frames: np.ndarray, j: int, world: dict[int, np.ndarray]
) -> np.ndarray:
    """(F, 3) world position of joint j, BVH frame and units (position channels override the
    OFFSET axis by axis)."""
    chain = []
    while j >= 0:
        chain.append(j)
        j = clip.parents[j]
    pos = np.zeros((frames.shape[0], 3))
    for j in reversed(chain):
        local = np.broadcast_to(clip.offsets[j], (frames.shape[0], 3)).copy()
        for k, ch in enumerate(clip.channels[j]):
            axis = _POSITION_CHANNELS.get(ch.lower())
            if axis is not None:
                local[:, axis] = frames[:, clip.channel_start[j] + k]
        p = clip.parents[j]
        pos = local if p < 0 else pos + np.einsum("fab,fb->fa", world[p], local)
    return pos


# ---------------------------------------------------------------------------------------------
# Conventions and joint maps


def detect_convention(joint_names: list[str] | tuple[str, ...]) -> str | None:
    """ "motionbuilder", "daz" or "asf" from a BVH hierarchy's joint names; None if unknown."""
    present = {n.lower() for n in joint_names}
    for name, sig in _SIGNATURES.items():
        if all(s.lower() in present for s in sig):
            return name
    return None


def _resolve_map(clip: BvhClip, path: Path, joint_map: dict[str, str] | None) -> dict[int, int]:
    """canonical joint index -> BVH joint index."""
    lookup: dict[str, int] = {}
    for k, n in enumerate(clip.names):
        lookup.setdefault(n, k)
    lower: dict[str, int] = {}
    for k, n in enumerate(clip.names):
        lower.setdefault(n.lower(), k)
    out: dict[int, int] = {}
    if joint_map is not None:
        for canon, bvh_name in joint_map.items():
            if canon not in JOINT_INDEX:
                raise InputError(
                    path, "joint_map", "canonical joint names (skeleton.JOINT_NAMES)", canon
                )
            k = lookup.get(bvh_name, lower.get(str(bvh_name).lower()))
            if k is None:
                raise InputError(
                    path, "joint_map", f"a joint of the file's HIERARCHY for '{canon}'", bvh_name
                )
            out[JOINT_INDEX[canon]] = k
    else:
        convention = detect_convention(clip.names)
        if convention is None:
            raise InputError(
                path,
                "HIERARCHY",
                "a known skeleton (MotionBuilder, Daz or ASF-named joints) or a joint map",
                clip.names[:6],
            )
        for canon, candidates in JOINT_MAPS[convention].items():
            for cand in candidates:
                if cand.lower() in lower:
                    out[JOINT_INDEX[canon]] = lower[cand.lower()]
                    break
    out.setdefault(0, 0)  # the pelvis defaults to the BVH root
    return out


# ---------------------------------------------------------------------------------------------
# Retargeting


def _descend_direction(clip: BvhClip, rest: np.ndarray, b: int, eps: float) -> np.ndarray | None:
    """Rest direction (BVH frame) from b to its end site or only child, skipping zero-length
    links; None when b branches (e.g. a head whose children are the eyes)."""
    k = b
    while True:
        kids = clip.children(k)
        if len(kids) == 1:
            k = kids[0]
            v = rest[k] - rest[b]
            if np.linalg.norm(v) > eps:
                return v
            continue
        if not kids and k in clip.end_sites:
            v = rest[k] + clip.end_sites[k][0] - rest[b]
            return v if np.linalg.norm(v) > eps else None
        return None


def _segment_directions(clip: BvhClip, mapping: dict[int, int], rest: np.ndarray, j: int,
                        eps: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Canonical joint j's segment: its canonical rest direction and the BVH rest direction of
    the same segment (towards the BVH joint mapped to j's first mapped canonical descendant off
    j's BVH joint, else down the BVH chain from it), or None where the BVH gives none."""
    b = mapping[j]
    c = _PRIMARY_CHILD[j]
    while c is not None:  # down the canonical chain to the first mapped joint off b
        if c in mapping and np.linalg.norm(rest[mapping[c]] - rest[b]) > eps:
            return REFERENCE_REST_JOINTS[c] - REFERENCE_REST_JOINTS[j], rest[mapping[c]] - rest[b]
        c = _PRIMARY_CHILD[c]
    o = _descend_direction(clip, rest, b, eps)
    if o is None:
        return None
    child = _PRIMARY_CHILD[j]
    d = (np.array(_LEAF_DIRECTIONS[JOINT_NAMES[j]]) if child is None
         else REFERENCE_REST_JOINTS[child] - REFERENCE_REST_JOINTS[j])
    return d, o


def _calibrations(clip: BvhClip, mapping: dict[int, int]) -> dict[int, np.ndarray]:
    """C_j for every mapped canonical joint: canonical rest direction -> BVH rest direction;
    for the collars (REST_NEUTRAL) and joints whose segment the BVH does not give, neutral
    relative to the nearest mapped ancestor at the BVH rest pose."""
    rest = clip.rest_positions()
    eps = 1e-6 * max(float(np.abs(clip.offsets).max()), 1e-12)
    calib: dict[int, np.ndarray] = {}
    for j in sorted(mapping):
        segment = None
        if JOINT_NAMES[j] not in REST_NEUTRAL:
            segment = _segment_directions(clip, mapping, rest, j, eps)
        if segment is not None:
            d, o = segment
            calib[j] = rotation_between(d, BVH_TO_WORLD @ o)
        elif j == 0:
            calib[j] = np.eye(3)
        else:
            a = PARENTS[j]
            while a not in mapping:
                a = PARENTS[a]
            calib[j] = calib[a]
    return calib


def _depth(j: int) -> int:
    d = 0
    while PARENTS[j] >= 0:
        j = PARENTS[j]
        d += 1
    return d


def _canonical_world(world_by_joint: dict[int, np.ndarray], n_frames: int) -> np.ndarray:
    """Fill unmapped canonical joints: share of a chain's rotation, else identity to the parent."""
    g = np.empty((n_frames, NUM_JOINTS, 3, 3))
    for j in range(NUM_JOINTS):
        if j in world_by_joint:
            g[:, j] = world_by_joint[j]
            continue
        a = PARENTS[j]
        while a not in world_by_joint:
            a = PARENTS[a]
        d = _PRIMARY_CHILD[j]
        while d is not None and d not in world_by_joint:
            d = _PRIMARY_CHILD[d]
        if d is None:
            g[:, j] = g[:, PARENTS[j]]
            continue
        frac = (_depth(j) - _depth(a)) / (_depth(d) - _depth(a))
        rel = np.swapaxes(g[:, a], -1, -2) @ world_by_joint[d]
        share = Rotation.from_rotvec(frac * Rotation.from_matrix(rel).as_rotvec()).as_matrix()
        g[:, j] = g[:, a] @ share
    return g


def _leg_length_bvh(rest: np.ndarray, mapping: dict[int, int]) -> float | None:
    lengths = []
    for side in ("left", "right"):
        idx = [JOINT_INDEX[f"{side}_{n}"] for n in ("hip", "knee", "ankle")]
        if all(i in mapping for i in idx):
            p = rest[[mapping[i] for i in idx]]
            lengths.append(np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[1]))
    if not lengths or min(lengths) <= 0:
        return None
    return float(np.mean(lengths))


def _reference_leg_length() -> float:
    r = REFERENCE_REST_JOINTS
    lengths = [
        np.linalg.norm(r[JOINT_INDEX[f"{s}_knee"]] - r[JOINT_INDEX[f"{s}_hip"]])
        + np.linalg.norm(r[JOINT_INDEX[f"{s}_ankle"]] - r[JOINT_INDEX[f"{s}_knee"]])
        for s in ("left", "right")
    ]
    return float(np.mean(lengths))


def _has_added_tpose(clip: BvhClip) -> bool:
    """The cgspeed MotionBuilder-friendly converter prepends a T-pose: zero root rotation and
    whole-degree joint corrections (e.g. legs straightened by 17 degrees); real capture follows."""
    frames = clip.frames
    if frames.shape[0] < 2:
        return False
    rot_cols = [
        clip.channel_start[j] + k
        for j in range(len(clip.names))
        for k, ch in enumerate(clip.channels[j])
        if ch.lower() in _ROTATION_CHANNELS
    ]
    root_cols = [
        clip.channel_start[0] + k
        for k, ch in enumerate(clip.channels[0])
        if ch.lower() in _ROTATION_CHANNELS
    ]
    if not rot_cols:
        return False
    first = frames[0, rot_cols]
    later = frames[1:, rot_cols]
    whole_first = bool(
        np.all(np.abs(first - np.round(first)) < 1e-6) and np.all(np.abs(first) <= 45.0)
    )
    root_zero = bool(np.all(np.abs(frames[0, root_cols]) < 1e-6))
    later_real = bool(np.any(np.abs(later - np.round(later)) > 1e-6))
    return whole_first and root_zero and later_real


def _snap_fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    whole = round(fps)
    return float(whole) if whole > 0 and abs(fps - whole) < 1e-4 * fps else fps


# ---------------------------------------------------------------------------------------------
# Grounding (shared with the AMASS importer)


def lowest_sole_height(poses: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """(F,) per frame the lowest sole estimate (metres, world z) of canonical poses on the
    reference skeleton: ankle z minus the reference ankle height above the sole, and toe-joint z
    minus the reference foot-joint height, the lowest of both feet."""
    _, joints = forward_kinematics(poses, trans, REFERENCE_REST_JOINTS)
    return (joints[:, _SOLE_JOINTS, 2] - _SOLE_OFFSETS).min(axis=1)


def ground_trans(poses: np.ndarray, trans: np.ndarray, percentile: float = 5.0) -> np.ndarray:
    """`trans` shifted vertically so that the `percentile` of the per-frame lowest sole is at
    z = 0 (a low percentile, not the minimum: outliers do not lift the clip, jumps stay jumps)."""
    trans = np.array(trans, dtype=np.float64, copy=True)
    lowest = lowest_sole_height(poses, trans)
    trans[:, 2] -= float(np.percentile(lowest, percentile))
    return trans


# ---------------------------------------------------------------------------------------------


# A leading "snap" into the capture: the Daz-friendly converter starts from its rest pose (zero
# root rotation) and reaches the first captured pose within a few frames (50 rad/s joint speeds),
# some of its clips with a root glitch too. No body moves like that; in Daz-friendly files these
# frames are dropped (at most 0.1 s).
SNAP_ANGULAR_SPEED = 20.0  # rad/s
SNAP_ROOT_SPEED = 10.0  # m/s
SNAP_MAX_SECONDS = 0.1


def leading_snap_frames(poses: np.ndarray, trans: np.ndarray, fps: float) -> int:
    """How many frames at the start belong to a converter's snap into the capture."""
    from datagen.rotations import angular_velocity

    limit = min(int(round(SNAP_MAX_SECONDS * fps)), len(poses) - 1)
    if limit <= 0:
        return 0
    ang = angular_velocity(poses[: limit + 1].reshape(-1, 24, 3), fps).max(axis=1)
    root = np.linalg.norm(np.diff(trans[: limit + 1], axis=0), axis=1) * fps
    k = 0
    while k < limit and (ang[k] > SNAP_ANGULAR_SPEED or root[k] > SNAP_ROOT_SPEED):
        k += 1
    return k


def load_bvh(
    path: str | Path,
    joint_map: dict[str, str] | None = None,
    label: str | None = None,
) -> Motion:
    """A BVH file as a canonical Motion at the file's own frame rate (see the module docstring).

    A converter's snap into the capture at the start (`leading_snap_frames`) is dropped."""
    path = Path(path)
    clip = parse_bvh(path)
    mapping = _resolve_map(clip, path, joint_map)

    rest = clip.rest_positions()
    leg = _leg_length_bvh(rest, mapping)
    if leg is None:
        raise InputError(
            path,
            "joint_map",
            "hip, knee and ankle joints of one leg (the scale comes from the leg)",
            sorted(JOINT_NAMES[j] for j in mapping),
        )
    scale = _reference_leg_length() / leg

    frames = clip.frames[1:] if _has_added_tpose(clip) else clip.frames
    n_frames = frames.shape[0]
    calib = _calibrations(clip, mapping)
    world = _world_rotations(clip, frames, set(mapping.values()))

    a = BVH_TO_WORLD
    canonical = {j: a @ world[b] @ a.T @ calib[j] for j, b in mapping.items()}
    g = _canonical_world(canonical, n_frames)
    poses = world_to_local(g)

    pelvis = _joint_positions(clip, frames, mapping[0], world)
    trans = scale * pelvis @ a.T
    fps = _snap_fps(clip.frame_time)
    convention = detect_convention(clip.names) if joint_map is None else None
    snap = 0
    root_rot = [
        clip.channel_start[0] + k
        for k, c in enumerate(clip.channels[0])
        if c.lower().endswith("rotation")
    ]
    if convention == "daz" and np.all(np.abs(frames[0, root_rot]) < 1e-6):
        snap = leading_snap_frames(poses, trans, fps)
    poses, trans = poses[snap:], trans[snap:]
    trans = ground_trans(poses, trans)
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(trans))):
        raise InputError(
            path, "MOTION", "rotations and positions that give a finite pose", "non-finite result"
        )
    return Motion(
        poses=poses,
        trans=trans,
        fps=fps,
        label=label if label is not None else path.stem,
        source=f"bvh:{path.name}",
        pelvis_height=REFERENCE_PELVIS_HEIGHT,
    )
