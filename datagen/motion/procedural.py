"""The procedural action library: the embedded default motion source.

Every action is a deterministic function of time built from sinusoids, smootherstep keyframes,
quintic (C2) blends and ballistic arcs, with the legs solved by analytic inverse kinematics, so
joint angular velocities and accelerations are continuous. A sampler picks the parameters
(`action_parameters(name)`: default, min, max, unit, doc; uniform draws in [min, max] are all
valid); `generate` adds no randomness. Motions are expressed on the reference skeleton
(`datagen.skeleton.REFERENCE_REST_JOINTS`), facing -y at `direction` 0, the pelvis starting above
the origin, soles on the ground z = 0; `Motion.pelvis_height` is the reference pelvis height.

Common parameters (defaults and ranges in `action_parameters(name)`):

- `speed`: a tempo multiplier (1 = the default tempo, 0.6 to 1.6), except for `walk` (0.5 to
  2.0 m/s, default 1.3) and `run` (2.0 to 4.5 m/s, default 3.0) where it is the speed in m/s.
- `amplitude`: scales the action's joint excursions (1 = default, 0.5 to 1.5).
- `direction`: heading in degrees about +z; 0 faces -y, 90 faces +x (the rest body's left).

Actions:

- `idle`: standing with breathing, a slow weight shift and small arm and head motion.
- `walk`: a walking gait at `speed` m/s (stride frequency and stance fraction follow the speed);
  `amplitude` scales arm swing and pelvis and torso motion; `turn` (-30 to 30 deg/s) curves the
  path.
  Footsteps are planted along the path and each foot rolls heel - flat - ball - toe-off; the legs
  reach them by inverse kinematics and the pelvis rides as high as the stance legs allow, so the
  stance foot does not slide while the root advances at exactly `speed`; where the weight
  passes from one leg to the other that height is rounded so the pelvis accelerates
  vertically by at most 0.45 g either way (a walker's ground force: 0.55-1.45 body weights).
- `run`: a running gait with a flight phase between steps; parameters as `walk`. The pelvis
  flies ballistically from each toe-off to the next touch-down, at heights that the knee's
  flexion there sets, and over each stance the ground pushes it with a smooth force that
  turns the landing into the next take-off (a runner's 7 cm of rise and fall; the stance knee
  bends at most 54-58 degrees). In swing the foot turns toes-down about its ankle where it
  would pass 15 degrees of dorsiflexion, nearing 25 at most (a runner's swing: 10-20 degrees).
- `jump`: stand, countermovement, push-off, ballistic flight, landing absorption, recovery,
  repeated; `height` (0.05 to 0.4 m, default 0.2) is how far the soles clear the ground at the
  apex, `distance` (0 to 0.8 m) how far forward each jump goes, `amplitude` scales the crouch
  depth and the arm swing. The ground pushes the pelvis with at most 3 body weights at the
  take-off and 4 at the landing: where a shallow crouch would push or land too hard the crouch
  or the landing goes deeper and lasts longer. The trunk's lean and the arms' swing keep their
  angular acceleration within 60 and 150 rad/s^2 and the arms' speed within 15 rad/s (a swing
  the keys would make more abrupt falls short of its key), so the neck and head stay within
  CMU's jumps' accelerations.
- `spin`: a turn in place on the balls of the feet at `revs` (0.25 to 2.5, default 1)
  revolutions per second, counter-clockwise seen from above (mirror for the other sense);
  `speed` sets the tempo of the small bounce and arm motion.
- `arm_raise`: raise both arms over the head and lower them; `plane` 0 raises them sideways,
  1 forwards; `amplitude` (0.3 to 1.1) 1 lifts the hands above the head.
- `wave`: raise one forearm and wave (2 Hz at tempo 1); `side` in [0, 1]: < 0.5 waves the right
  hand, >= 0.5 the left (numeric so that uniform sampling picks either half the time).
- `squat`: repeated squats; `depth` (0.1 to 0.45 m, default 0.3) is how far the pelvis drops.
- `kick`: shift the weight, chamber, front kick to `height` (0.3 to 1.0 m of the ankle above the
  ground, default 0.7), retract and step back; `side` as for `wave` (right leg by default).
- `dance`: a step-touch loop: side-to-side sway with a bounce on every beat, toe taps, torso
  twist and alternating arm pumps; `speed` 1 is 120 beats per minute.

Feet on the ground are placed exactly by the leg inverse kinematics (they do not slide or sink).
Poses keep a natural rest stance: arms hang about 28 degrees away from the body with the elbows
bent 15 degrees (so they clear the torso of heavy bodies), knees slightly bent, feet a little
apart. Episodic actions (jump, squat, kick, arm_raise, wave) start from that stance and repeat
with a fixed period; cyclic ones (idle, walk, run, spin, dance) start mid-cycle.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import grey_dilation, grey_erosion

from datagen.errors import InputError
from datagen.rotations import matrix_to_axis_angle
from datagen.skeleton import (
    JOINT_INDEX,
    MIRROR,
    NUM_JOINTS,
    REFERENCE_PELVIS_HEIGHT,
    REFERENCE_REST_JOINTS,
    mirror_poses,
    world_axes_to_local,
)
from datagen.types import Motion

GRAVITY = 9.81
_REST = REFERENCE_REST_JOINTS
_J = JOINT_INDEX
_DEG = math.pi / 180.0

# Heights above the sole of the ankle and ball (the `foot` joint) in the reference rest pose.
ANKLE_HEIGHT = float(_REST[_J["left_ankle"], 2] + REFERENCE_PELVIS_HEIGHT)
BALL_HEIGHT = float(_REST[_J["left_foot"], 2] + REFERENCE_PELVIS_HEIGHT)

# Left-leg segment vectors at rest (the skeleton is left/right symmetric).
_HIP_OFFSET = _REST[_J["left_hip"]] - _REST[_J["pelvis"]]
_THIGH = _REST[_J["left_knee"]] - _REST[_J["left_hip"]]
_SHIN = _REST[_J["left_ankle"]] - _REST[_J["left_knee"]]
_FOOT = _REST[_J["left_foot"]] - _REST[_J["left_ankle"]]
_X_FLIP = np.array([-1.0, 1.0, 1.0])

# Rest stance: arms 62 degrees below horizontal (28 degrees of abduction), elbows bent 15
# degrees, knees slightly bent; the feet stay where the rest skeleton has them.
ARM_DOWN = 62.0 * _DEG
ARM_FORWARD = 4.0 * _DEG
ELBOW_FLEX = 15.0 * _DEG
STAND_DROP = 0.008  # m the standing pelvis sits below the rest height (soft knees)
PELVIS_STAND = REFERENCE_PELVIS_HEIGHT - STAND_DROP
_BALL_REST = _REST[_J["left_foot"]] - _REST[_J["pelvis"]]  # ball relative to the pelvis


@dataclass(frozen=True)
class ParamSpec:
    """One action parameter: its default, valid range [min, max], unit and meaning."""

    default: float
    min: float
    max: float
    unit: str
    doc: str


@dataclass(frozen=True)
class Action:
    """A labelled procedural action."""

    name: str
    doc: str
    params: dict[str, ParamSpec]
    build: Callable[[np.ndarray, float, dict[str, float]], _Built] = field(repr=False)


@dataclass
class _Built:
    rot: np.ndarray  # (F, 24, 3, 3) local rotations; the root excludes the heading
    trans: np.ndarray  # (F, 3) pelvis position in the heading frame (or world, see `world`)
    yaw: np.ndarray  # (F,) extra heading about z, radians (on top of `direction`)
    world: bool = False  # trans and yaw already include `direction`


# -- smooth building blocks -------------------------------------------------------------------


def _rot(axis: int, angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about a coordinate axis (0 = x, 1 = y, 2 = z)."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    i, j = ((1, 2), (2, 0), (0, 1))[axis]
    m[..., axis, axis] = 1.0
    m[..., i, i] = c
    m[..., j, j] = c
    m[..., i, j] = -s
    m[..., j, i] = s
    return m


def _rx(a):
    return _rot(0, a)


def _ry(a):
    return _rot(1, a)


def _rz(a):
    return _rot(2, a)


# Conjugation by the x-reflection: a left-side rotation -> the mirrored right-side rotation.
_MIRROR_SIGN = np.array([[1.0, -1.0, -1.0], [-1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])


# The peak acceleration and speed of a smootherstep over a unit step in a unit time.
_SMOOTHERSTEP_PEAK = 10.0 / math.sqrt(3.0)
_SMOOTHERSTEP_PEAK_SPEED = 15.0 / 8.0


def _smootherstep(x: np.ndarray | float) -> np.ndarray:
    """0 -> 1 with zero first and second derivatives at both ends (C2 when clamped)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _compact(x: np.ndarray) -> np.ndarray:
    """(1 - x^2)^3 on |x| < 1, else 0: a C2 bump with compact support."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(np.abs(x) < 1.0, (1.0 - np.minimum(x * x, 1.0)) ** 3, 0.0)


def _keys(t: np.ndarray, times, values, period: float | None = None) -> np.ndarray:
    """Smootherstep interpolation through key values (zero velocity and acceleration at every
    key, so the curve is C2); `values` (K,) or (K, D). Periodic in `period` if given."""
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if period is not None:
        t = np.mod(t, period)
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    span = times[idx + 1] - times[idx]
    w = _smootherstep((t - times[idx]) / np.where(span > 0, span, 1.0))
    if values.ndim > 1:
        w = w[:, None]
    return values[idx] + (values[idx + 1] - values[idx]) * w


def _quintic(t: np.ndarray, t0: float, t1: float, start, end) -> np.ndarray:
    """Quintic Hermite segment on [t0, t1] from (position, velocity, acceleration) `start` to
    `end`; clamped outside the interval to the end values (callers only use it inside)."""
    h = t1 - t0
    s = np.clip((np.asarray(t, dtype=np.float64) - t0) / h, 0.0, 1.0)
    p0, v0, a0 = start
    p1, v1, a1 = end
    s2, s3 = s * s, s * s * s
    s4, s5 = s3 * s, s3 * s2
    h00 = 1 - 10 * s3 + 15 * s4 - 6 * s5
    h10 = s - 6 * s3 + 8 * s4 - 3 * s5
    h20 = 0.5 * s2 - 1.5 * s3 + 1.5 * s4 - 0.5 * s5
    h01 = 10 * s3 - 15 * s4 + 6 * s5
    h11 = -4 * s3 + 7 * s4 - 3 * s5
    h21 = 0.5 * s3 - s4 + 0.5 * s5
    return h00 * p0 + h10 * h * v0 + h20 * h * h * a0 + h01 * p1 + h11 * h * v1 + h21 * h * h * a1


def _softmin(h: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth minimum over the last axis (never above the true minimum) and its weights."""
    m = h.min(axis=-1, keepdims=True)
    e = np.exp(-(h - m) / tau)
    total = e.sum(axis=-1, keepdims=True)
    return (m - tau * np.log(total))[..., 0], e / total


# -- anatomical joint rotations (left side; the right side is the mirror image) ---------------


def _shoulder(down, fwd=0.0, ext=0.0, horiz=0.0):
    """Shoulder from the T-pose: external rotation about the arm, lowering in the frontal plane
    (`down` from horizontal), forward swing about x, then a horizontal swing forward."""
    return _rz(-np.asarray(horiz)) @ _rx(-np.asarray(fwd)) @ _ry(down) @ _rx(-np.asarray(ext))


def _elbow(flex):
    return _rz(-np.asarray(flex))


def _trunk(flex=0.0, lat=0.0, twist=0.0):
    """Spine, neck or root: forward flexion, lateral bend to the left, twist to the left."""
    return _rz(twist) @ _ry(lat) @ _rx(flex)


class _Pose:
    """Local joint rotations (F, 24, 3, 3), identity (T-pose) unless set."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.rot = np.broadcast_to(np.eye(3), (n, NUM_JOINTS, 3, 3)).copy()

    def set(self, name: str, m: np.ndarray) -> None:
        self.rot[:, _J[name]] = np.broadcast_to(m, (self.n, 3, 3))

    def arms(self, left: dict, right: dict) -> None:
        """Shoulders and elbows from keyword angles (radians, see `_shoulder`), left convention."""
        for side, a in (("left", left), ("right", right)):
            sh = _shoulder(
                a.get("down", ARM_DOWN),
                a.get("fwd", ARM_FORWARD),
                a.get("ext", 0.0),
                a.get("horiz", 0.0),
            )
            el = _elbow(a.get("elbow", ELBOW_FLEX))
            if side == "right":
                sh = np.broadcast_to(sh, (self.n, 3, 3)) * _MIRROR_SIGN
                el = np.broadcast_to(el, (self.n, 3, 3)) * _MIRROR_SIGN
            self.set(f"{side}_shoulder", sh)
            self.set(f"{side}_elbow", el)
            if "collar" in a:  # shrug: raise the shoulder girdle
                col = _ry(-np.asarray(a["collar"]))
                self.set(
                    f"{side}_collar",
                    col if side == "left" else np.broadcast_to(col, (self.n, 3, 3)) * _MIRROR_SIGN,
                )

    def spine(self, flex=0.0, lat=0.0, twist=0.0, head_flex=0.0, head_twist=0.0) -> None:
        """Distribute a torso bend over the three spine joints; the head counteracts part of it."""
        third = _trunk(np.asarray(flex) / 3, np.asarray(lat) / 3, np.asarray(twist) / 3)
        for name in ("spine1", "spine2", "spine3"):
            self.set(name, third)
        self.set("neck", _trunk(np.asarray(head_flex) / 2, 0.0, np.asarray(head_twist) / 2))
        self.set("head", _trunk(np.asarray(head_flex) / 2, 0.0, np.asarray(head_twist) / 2))


# -- legs: analytic inverse kinematics --------------------------------------------------------

_T_YZ = _THIGH[1:]
_S_YZ = _SHIN[1:]
_QX = float(_THIGH[0] + _SHIN[0])
_T_LEN = float(np.linalg.norm(_T_YZ))
_S_LEN = float(np.linalg.norm(_S_YZ))
# The rest thigh and shin are not collinear: the rest knee is already bent by _GAMMA0 in the
# sagittal plane, and knee flexion kappa bends it to _GAMMA0 + kappa.
_GAMMA0 = float(np.arctan2(_S_YZ[1], _S_YZ[0]) - np.arctan2(_T_YZ[1], _T_YZ[0]))
_LEG_MAX = math.sqrt(_QX**2 + (_T_LEN + _S_LEN) ** 2)
# Beyond _LEG_SOFT the reach saturates smoothly (tanh) towards _LEG_CAP: targets slightly out of
# reach are approached without a locked knee or a kink in the joint angles.
_LEG_SOFT = _LEG_MAX - 0.006
_LEG_CAP = _LEG_MAX - 0.0015


def _leg_length(knee: np.ndarray | float) -> np.ndarray:
    """Hip-to-ankle distance of the reference leg at knee flexion `knee` (radians)."""
    c, s = np.cos(knee), np.sin(knee)
    qy = _T_YZ[0] + c * _S_YZ[0] - s * _S_YZ[1]
    qz = _T_YZ[1] + s * _S_YZ[0] + c * _S_YZ[1]
    return np.sqrt(_QX**2 + qy * qy + qz * qz)


def _leg_ik(
    d: np.ndarray, ext: np.ndarray, reach: float = _LEG_SOFT
) -> tuple[np.ndarray, np.ndarray]:
    """Left hip and knee rotations that put the ankle at `d` (F, 3) from the hip (pelvis axes),
    with hip external rotation `ext` (F,): hip = Rz(ext) Ry(abduction) Rx(flexion), knee =
    Rx(kappa); the knee always bends forwards. Targets farther than `reach` are approached
    softly (tanh) up to _LEG_CAP."""
    d = (_rz(-ext) @ d[..., None])[..., 0]
    length = np.linalg.norm(d, axis=-1)
    m = _LEG_CAP - reach
    soft = np.where(length > reach, reach + m * np.tanh((length - reach) / m), length)
    d = d * (soft / np.maximum(length, 1e-9))[:, None]
    cos_g = (soft**2 - _QX**2 - _T_LEN**2 - _S_LEN**2) / (2.0 * _T_LEN * _S_LEN)
    kappa = np.arccos(np.clip(cos_g, -1.0, 1.0)) - _GAMMA0
    c, s = np.cos(kappa), np.sin(kappa)
    qy = _T_YZ[0] + c * _S_YZ[0] - s * _S_YZ[1]
    qz = _T_YZ[1] + s * _S_YZ[0] + c * _S_YZ[1]
    ry = d[:, 1]
    rz = -np.sqrt(np.maximum(qy * qy + qz * qz - ry * ry, 1e-12))
    beta = np.arctan2(rz, ry) - np.arctan2(qz, qy)  # about x, in the (y, z) plane
    alpha = np.arctan2(d[:, 0], d[:, 2]) - np.arctan2(_QX, rz)  # about y, in the (z, x) plane
    return _rz(ext) @ _ry(alpha) @ _rx(beta), _rx(kappa)


def _solve_legs(
    pose: _Pose,
    root: np.ndarray,
    pelvis: np.ndarray,
    ankles: np.ndarray,
    feet: np.ndarray,
    toes: np.ndarray,
    hip_ext: np.ndarray | None = None,
    reach: float = _LEG_SOFT,
) -> None:
    """Set hips, knees, ankles and toes so that the ankles reach `ankles` (2, F, 3) (left, right;
    world) with feet oriented `feet` (2, F, 3, 3) (world), given the root rotation (F, 3, 3) and
    pelvis position (F, 3). `toes` (2, F) bends the toes up (they stay flat when the heel rises);
    `hip_ext` (2, F, left convention) turns each knee outwards; targets beyond `reach` are
    approached softly (_leg_ik)."""
    n = pose.n
    hip_ext = np.zeros((2, n)) if hip_ext is None else np.broadcast_to(hip_ext, (2, n))
    root_t = np.swapaxes(root, -1, -2)
    for k, side in enumerate(("left", "right")):
        flip = _X_FLIP if k else np.ones(3)
        hip = pelvis + root @ (_HIP_OFFSET * flip)
        d = (root_t @ (ankles[k] - hip)[..., None])[..., 0] * flip  # left convention
        hip_rot, knee_rot = _leg_ik(d, hip_ext[k], reach)
        if k:
            hip_rot = hip_rot * _MIRROR_SIGN
            knee_rot = knee_rot * _MIRROR_SIGN
        chain = root @ hip_rot @ knee_rot
        pose.set(f"{side}_hip", hip_rot)
        pose.set(f"{side}_knee", knee_rot)
        pose.set(f"{side}_ankle", np.swapaxes(chain, -1, -2) @ feet[k])
        pose.set(f"{side}_foot", _rx(-np.asarray(toes[k])))


def _ankle_offset(pitch: np.ndarray | float) -> np.ndarray:
    """Ankle position relative to the ball when the (left) foot pitches heel-up about the ball."""
    return _rx(pitch) @ (-_FOOT)


def _legs(
    pose: _Pose,
    root: np.ndarray,
    pelvis: np.ndarray,
    balls: np.ndarray,
    pitch: np.ndarray | float,
    foot_yaw: np.ndarray | float = 0.0,
    toes: np.ndarray | None = None,
) -> None:
    """Legs for feet standing on their balls at `balls` (2, F, 3) (world), heels raised by
    `pitch` (2, F) about the ball, toes turned out by `foot_yaw` (2, F, left convention); the
    knees follow the feet. Toes stay flat on the ground unless `toes` says otherwise."""
    n = pose.n
    pitch = np.broadcast_to(pitch, (2, n))
    toes = pitch if toes is None else toes
    foot_yaw = np.broadcast_to(foot_yaw, (2, n))
    feet = np.empty((2, n, 3, 3))
    ankles = np.empty((2, n, 3))
    for k in range(2):
        flip = _X_FLIP if k else np.ones(3)
        feet[k] = _rz(foot_yaw[k] * (-1.0 if k else 1.0)) @ _rx(pitch[k])
        ankles[k] = balls[k] - feet[k] @ (_FOOT * flip)
    _solve_legs(pose, root, pelvis, ankles, feet, toes, foot_yaw)


def _stance_balls(n: int, width: float = 0.0, forward: float = 0.0) -> np.ndarray:
    """Ball positions (2, F, 3) of a standing stance under a pelvis at the origin."""
    left = np.array([_BALL_REST[0] + width, _BALL_REST[1] - forward, BALL_HEIGHT])
    balls = np.stack([left, left * _X_FLIP])
    return np.repeat(balls[:, None, :], n, axis=1)


def _pelvis_for_pitch(pitch: float) -> float:
    """Standing pelvis height with both heels raised by `pitch` (on the balls of the feet)."""
    return PELVIS_STAND + float(_ankle_offset(pitch)[2] - _ankle_offset(0.0)[2])


def _standing(n: int) -> tuple[_Pose, np.ndarray, np.ndarray]:
    """The rest stance for `n` frames: pose (arms set), root rotation, pelvis position."""
    pose = _Pose(n)
    pose.arms({}, {})
    root = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    pelvis = np.tile([0.0, 0.0, PELVIS_STAND], (n, 1))
    return pose, root, pelvis


def _finish(pose: _Pose, root: np.ndarray, pelvis: np.ndarray, yaw=None) -> _Built:
    pose.set("pelvis", root)
    n = pose.n
    return _Built(pose.rot, pelvis, np.zeros(n) if yaw is None else np.broadcast_to(yaw, (n,)))


# -- actions ----------------------------------------------------------------------------------


def _build_idle(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, a = len(t), p["amplitude"]
    w = 2.0 * np.pi * p["speed"] * t
    pose, root, pelvis = _standing(n)
    # A slow weight shift (8 s), breathing (4 s), and incommensurate small head motion.
    shift = np.sin(w / 8.0)
    pelvis[:, 0] += 0.02 * a * shift
    pelvis[:, 2] -= 0.004 * a * (1.0 - np.cos(w / 4.0)) + 0.004 * a * shift**2
    root = _trunk(
        0.5 * _DEG * a * np.sin(w / 4.0), -1.5 * _DEG * a * shift, 2.0 * _DEG * a * np.sin(w / 11.0)
    )
    pose.spine(
        flex=1.5 * _DEG * a * np.sin(w / 4.0 + 1.0),
        lat=2.0 * _DEG * a * shift,
        twist=-2.0 * _DEG * a * np.sin(w / 11.0),
        head_flex=3.0 * _DEG * a * np.sin(w / 7.0),
        head_twist=6.0 * _DEG * a * np.sin(w / 9.0),
    )
    arm = 3.0 * _DEG * a * np.sin(w / 8.0 + 0.5)
    pose.arms(
        {"fwd": ARM_FORWARD + arm, "elbow": ELBOW_FLEX + 0.5 * arm},
        {"fwd": ARM_FORWARD - arm, "elbow": ELBOW_FLEX + 0.5 * arm},
    )
    _legs(pose, root, pelvis, _stance_balls(n), 0.0)
    return _finish(pose, root, pelvis)


# Gaits: footsteps are planted along the path and the legs reach them by inverse kinematics, so
# the stance foot never slides and the pelvis advances at exactly `speed`. Each foot rolls over
# the ground: it lands on the heel (toes up), rotates flat about the heel, the contact moves to
# the ball while flat, and the heel rises about the ball until toe-off.
_HEEL_SOLE = np.array([0.0, 0.05, -ANKLE_HEIGHT])  # from the ankle, left foot, flat
_BALL_SOLE = _FOOT  # the ball pivots about its joint


@dataclass(frozen=True)
class _GaitStyle:
    freq: tuple[float, float]  # stride frequency, Hz: [0] + [1] * speed
    stance: tuple[float, float]  # fraction of the stride a foot is on the ground
    width: float  # ankle distance from the line of progression, m
    toe_out: float  # deg
    heel_strike: float  # foot pitch at touchdown, deg (toes up)
    toe_off: float  # foot pitch at toe-off, deg (heel up)
    flat: tuple[float, float]  # fractions of stance when the foot is flat: [start, heel-off]
    lift: tuple[float, float]  # peak ankle lift in swing, m: [0] + [1] * speed
    knee: float  # walking: stance knee flexion at full reach, deg (sets the pelvis height)
    sway: float  # lateral pelvis sway towards the stance foot, m
    pelvis_yaw: float  # deg
    pelvis_roll: float  # deg
    lean: tuple[float, float]  # forward lean, deg: [0] + [1] * speed
    arm_swing: tuple[float, float]  # deg: [0] + [1] * speed
    arm_fwd: float  # deg
    elbow: float  # deg
    elbow_swing: float  # deg
    # Walking's swing timing: 0 = smootherstep, up to 30 = brisker lift-off and landing
    skew: float
    # Swing-phase ankle dorsiflexion, deg: where a soft limit starts and the ceiling it nears
    # (_limit_swing_dorsiflexion); None leaves the swing foot as the footstep plan pitches it.
    swing_dorsiflexion: tuple[float, float] | None = None
    # Running (None: walking): the knee's flexion at touch-down and at toe-off, deg, which set
    # the pelvis height there (_run_height).
    stance_knee: tuple[float, float] | None = None
    # Running: how high the swing ankle stays above its path late in the swing before it comes
    # down to land (m): a runner's foot does not skim the ground ahead of the hip.
    landing_height: float = 0.0


_WALK = _GaitStyle(
    freq=(0.5, 0.37),
    stance=(0.62, -0.04),
    width=0.11,
    toe_out=6.0,
    heel_strike=15.0,
    toe_off=70.0,
    flat=(0.15, 0.55),
    lift=(0.08, 0.03),
    knee=8.0,
    sway=0.02,
    pelvis_yaw=5.0,
    pelvis_roll=3.0,
    lean=(1.0, 1.0),
    arm_swing=(6.0, 8.0),
    arm_fwd=2.0,
    elbow=16.0,
    elbow_swing=12.0,
    skew=24.0,
)
_RUN = _GaitStyle(
    freq=(1.15, 0.10),
    stance=(0.46, -0.035),
    width=0.08,
    toe_out=4.0,
    heel_strike=5.0,
    toe_off=45.0,
    flat=(0.25, 0.5),
    lift=(0.06, 0.06),
    knee=0.0,
    sway=0.01,
    pelvis_yaw=6.0,
    pelvis_roll=3.0,
    lean=(4.0, 1.5),
    arm_swing=(18.0, 4.0),
    arm_fwd=-8.0,
    elbow=85.0,
    elbow_swing=15.0,
    skew=0.0,  # unused: a run's swing has its own timing (_feet_plan)
    # The plan pitches the swing foot in the world, and a runner's knee folds to 100-120 deg in
    # swing, so the ankle came out 48 deg dorsiflexed at 3 m/s and 68 at 4.5 (running swing
    # peaks at 10-20 deg): the foot's top sank into the shin and swallowed trouser hems.
    swing_dorsiflexion=(15.0, 25.0),
    # Flexion from the rest pose's knee, which is itself bent about 10 deg: 25-30 deg between
    # thigh and shin at touch-down and toe-off (a runner's: about 20 and 20-25).
    stance_knee=(15.0, 18.0),
    landing_height=0.05,
)
# Running: the landing height's rise after toe-off and its fall before touch-down, in fractions
# of the swing; the heel's rise at toe-off, in units of its mean rate since heel-off.
_LANDING_RISE, _LANDING_FALL = 0.3, 0.3
_TOE_OFF_RATE = 1.5
_TAKE_OFF_RISE = 0.01
_GAIT_START = 0.25  # the first frame's phase in the stride (0 = left heel strike)
# Walking: the largest vertical acceleration of the pelvis either way (m/s^2): a ground force
# within 0.55-1.45 body weights (a walker's peaks: about 1.2 at an ordinary pace, 1.5 at 2 m/s;
# its dip at mid-stance 0.6-0.7). The vault's bound is sampled at _ENVELOPE_RATE (Hz) for it,
# and varies by less than _VAULT_RANGE (m) over a stride.
WALK_ACCELERATION_MAX = 0.45 * GRAVITY
_ENVELOPE_RATE = 480.0
_VAULT_RANGE = 0.08


def _path(t: np.ndarray, speed: float, yaw0: float, turn: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (F, 2) and headings (F,) along a straight or circular path at `speed`, starting
    at the origin with heading `yaw0`, turning at `turn` rad/s."""
    psi = yaw0 + turn * t
    if abs(turn) < 1e-9:
        xy = np.column_stack([np.sin(yaw0) * speed * t, -np.cos(yaw0) * speed * t])
    else:
        r = speed / turn
        xy = np.column_stack([r * (np.cos(yaw0) - np.cos(psi)), r * (np.sin(yaw0) - np.sin(psi))])
    return xy, psi


def _feet_plan(
    t: np.ndarray, style: _GaitStyle, speed: float, yaw0: float, turn: float, back: float
) -> dict[str, np.ndarray]:
    """Footstep targets: ankles (2, F, 3), foot rotations (2, F, 3, 3), toe bends (2, F),
    ground-contact weights (2, F), foot yaws (2, F), and the stride phase (F,)."""
    freq = style.freq[0] + style.freq[1] * speed
    period = 1.0 / freq
    beta = style.stance[0] + style.stance[1] * speed
    cyc = t * freq + _GAIT_START
    n = len(t)
    out = {k: np.empty((2, n)) for k in ("toe", "contact", "yaw", "swing")}
    out["ankle"] = np.empty((2, n, 3))
    out["foot"] = np.empty((2, n, 3, 3))
    out["phase"] = cyc
    lift_peak = style.lift[0] + style.lift[1] * speed
    hs, to = style.heel_strike * _DEG, style.toe_off * _DEG
    f0, f1 = style.flat
    for k in range(2):
        side = -1.0 if k else 1.0
        flip = _X_FLIP if k else np.ones(3)
        ck = cyc + 0.5 * k
        i = np.floor(ck)
        u = ck - i
        prints = []
        for step in (i, i + 1):
            # The foot is flat under the hip region at mid-stance of step `step`.
            t_mid = (step + 0.5 * beta - 0.5 * k - _GAIT_START) * period
            xy, psi = _path(t_mid, speed, yaw0, turn)
            yaw = psi + side * style.toe_out * _DEG
            lateral = _rz(psi) @ np.array([side * style.width, back, 0.0])
            ankle = np.column_stack([xy, np.zeros(n)]) + lateral
            rz = _rz(yaw)
            heel = ankle + rz @ (_HEEL_SOLE * flip * [1, 1, 0])
            ball = ankle + rz @ (_BALL_SOLE * flip * [1, 1, 0])  # ground projections
            prints.append((heel, ball, yaw))
        (heel0, ball0, yaw0_), (heel1, _, yaw1_) = prints
        stance = u < beta
        s_st = np.clip(u / beta, 0.0, 1.0)
        s_sw = np.clip((u - beta) / (1.0 - beta), 0.0, 1.0)
        pitch = np.where(
            stance,
            _keys(s_st, [0.0, f0, f1, 1.0], [-hs, 0.0, 0.0, to]),
            _keys(s_sw, [0.0, 0.25, 0.6, 1.0], [to, to + 10 * _DEG, 0.0, -hs]),
        )
        if style.stance_knee is not None:
            # Running: the heel still rises as the ball leaves the ground (the push-off's
            # plantarflexion goes on through toe-off), so that the foot, not the knee, takes
            # up the hip's rise there; walking's foot pauses at toe-off.
            up, sw_peak = f1 * beta, beta + 0.25 * (1.0 - beta)
            rate = _TOE_OFF_RATE * to / (beta - up)
            push = (u >= up) & (u < beta)
            pitch = np.where(push, _quintic(u, up, beta, (0.0, 0.0, 0.0), (to, rate, 0.0)), pitch)
            rise = (u >= beta) & (u < sw_peak)
            pitch = np.where(rise, _quintic(u, beta, sw_peak, (to, rate, 0.0),
                                            (to + 10 * _DEG, 0.0, 0.0)), pitch)
        roll = np.where(stance, _smootherstep((s_st - f0) / (f1 - f0)), 1.0 - _smootherstep(s_sw))
        if style.stance_knee is None:
            # Skewed smootherstep (still C2, monotonic): the foot leaves and arrives briskly, so
            # it neither trails far behind the hip after toe-off nor reaches far ahead before
            # landing.
            blend = _smootherstep(s_sw) + style.skew * s_sw**3 * (1 - s_sw) ** 3 * (1 - 2 * s_sw)
        else:
            # Running: smoothstep, which arrives at its footprint with the foot still braking
            # (C1 at touch-down). A smootherstep's foot is nearly there by 80 % of the swing,
            # while the hip, in flight, is half a metre behind: out of reach for a runner's
            # pelvis height, which is what kept the run crouched.
            blend = s_sw * s_sw * (3.0 - 2.0 * s_sw)
        blend = blend[:, None]
        pivot = np.where(
            stance[:, None],
            heel0 + roll[:, None] * (ball0 - heel0),
            ball0 + blend * (heel1 - ball0),
        )
        # Swing lift: a C2 bump peaking at a third of the swing (the foot clears early).
        bump = s_sw**3 * (1.0 - s_sw) ** 6 / (2.0**6 / 3.0**9)
        # Running: the foot stays up late in the swing and comes down over its last part.
        bump = bump + style.landing_height / lift_peak * (
            _smootherstep(s_sw / _LANDING_RISE) * _smootherstep((1.0 - s_sw) / _LANDING_FALL)
        )
        # The heel pivots on its sole point, the ball on its joint (the toes carry it).
        pivot[:, 2] = roll * BALL_HEIGHT + np.where(stance, 0.0, lift_peak * bump)
        yaw = np.where(stance, yaw0_, yaw0_ + blend[:, 0] * (yaw1_ - yaw0_))
        foot = _rz(yaw) @ _rx(pitch)
        sole = (roll[:, None] * _BALL_SOLE + (1.0 - roll[:, None]) * _HEEL_SOLE) * flip
        out["ankle"][k] = pivot - (foot @ sole[..., None])[..., 0]
        out["foot"][k] = foot
        out["toe"][k] = np.maximum(pitch, 0.0) * np.where(
            stance, 1.0, 1.0 - _smootherstep(s_sw / 0.6)
        )
        out["yaw"][k] = yaw
        # Which legs bound the pelvis height: 1 in stance, dipping to 0 in early swing and back
        # to 1 in late swing, so the pelvis is low enough when the swing leg reaches to land.
        out["contact"][k] = 1.0 - _compact((s_sw - 0.4) / 0.4) * (~stance)
        # How free the foot is to turn about its ankle: 0 on the ground and at lift-off and
        # touch-down (the plan's pitches there meet the ground), 1 in mid-swing; C2.
        out["swing"][k] = np.where(
            stance, 0.0, _smootherstep(s_sw / 0.25) * _smootherstep((1.0 - s_sw) / 0.25)
        )
    return out


def _gait_root(
    t: np.ndarray, plan: dict, style: _GaitStyle, speed: float, amp: float, yaw0: float, turn: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pelvis rotation (F, 3, 3, world), horizontal position (F, 2) and the pelvis yaw (F,)."""
    phi = 2 * np.pi * plan["phase"]
    beta = style.stance[0] + style.stance[1] * speed
    xy, psi = _path(t, speed, yaw0, turn)
    d = _DEG
    osc_yaw = -style.pelvis_yaw * d * amp * np.cos(phi)  # the leading leg's hip forward
    roll = style.pelvis_roll * d * amp * np.cos(phi - np.pi * (1 + beta))  # swing side drops
    lean = (style.lean[0] + style.lean[1] * speed) * d
    root = _rz(psi) @ _trunk(0.5 * lean, roll, osc_yaw)
    sway = style.sway * amp * np.cos(phi - np.pi * beta)  # over the stance foot
    xy = xy + np.column_stack([np.cos(psi), np.sin(psi)]) * sway[:, None]
    return root, xy, psi + osc_yaw


def _gait_back(style: _GaitStyle, speed: float) -> float:
    """How far behind the hip the flat foot sits at mid-stance (m): the foot lands ahead of the
    hip by about a third of the pelvis travel during stance and leaves (rolled onto its ball, heel
    high, knee bent) a little further behind."""
    freq = style.freq[0] + style.freq[1] * speed
    travel = speed * (style.stance[0] + style.stance[1] * speed) / freq
    return 0.17 * travel - 0.023 * style.heel_strike / 15.0


def _hip_room(plan: dict, root: np.ndarray, xy: np.ndarray, k: int, length) -> np.ndarray:
    """(F,) the pelvis height at which leg k's hip is `length` (scalar or (F,)) from its ankle
    target."""
    hip = root @ (_HIP_OFFSET * (_X_FLIP if k else np.ones(3)))
    ankle = plan["ankle"][k]
    horiz = np.sum((ankle[:, :2] - xy - hip[:, :2]) ** 2, axis=-1)
    return ankle[:, 2] - hip[:, 2] + np.sqrt(np.maximum(length**2 - horiz, 0.01))


def _reach_height(plan: dict, root: np.ndarray, xy: np.ndarray, knee: float) -> np.ndarray:
    """Per leg (2, F): the highest pelvis that still reaches the ankle target with the knee bent
    by `knee`; a swing leg only has to be within reach."""
    out = np.empty((2, len(xy)))
    for k in range(2):
        length = _leg_length(knee) + (1.0 - plan["contact"][k]) * (
            _LEG_SOFT - 0.002 - _leg_length(knee)
        )
        out[k] = _hip_room(plan, root, xy, k, length)
    return out


def _vault_height(plan: dict, root: np.ndarray, xy: np.ndarray, style: _GaitStyle) -> np.ndarray:
    """Walking's upper bound on the pelvis: vault over the stance leg, never above standing
    height."""
    reach = _reach_height(plan, root, xy, style.knee * _DEG)
    cap = np.full(len(xy), PELVIS_STAND + 0.01)
    return _softmin(np.stack([reach[0], reach[1], cap], axis=-1), 0.015)[0]


def _envelope_reach(curvature: float) -> float:
    """How far (s) a parabolic envelope of `curvature` reaches over a bound that varies by less
    than _VAULT_RANGE: no sample farther away can win."""
    return math.sqrt(2.0 * _VAULT_RANGE / curvature)


def _parabola(dt: float, curvature: float) -> np.ndarray:
    """curvature (t - s)^2 / 2 over the offsets of a uniform grid of spacing `dt` that the
    envelope reaches: the structuring element of scipy's grey erosion and dilation."""
    width = int(math.ceil(_envelope_reach(curvature) / dt))
    return 0.5 * curvature * (np.arange(-width, width + 1) * dt) ** 2


def _walk_height(
    t: np.ndarray, style: _GaitStyle, speed: float, amp: float, yaw0: float, turn: float,
    back: float, bound: np.ndarray,
) -> np.ndarray:
    """Walking: the pelvis height (F,) at times `t`, under the vault's bound there (`bound`,
    _vault_height). The vault alone meets the next stance leg's arc in a kink at every double
    support, where the pelvis stopped falling and rose again within 50 ms (2 g upward at 1.8
    m/s), and rounds onto the standing cap over the stance leg (1.5 g downward); a walker's
    ground force stays within 0.55-1.45 body weights. So the height is the bound's
    Lasry-Lions regularisation: its lower parabolic envelope at curvature a/2, then the upper
    one of that at curvature a (a = WALK_ACCELERATION_MAX): never above the bound, and its
    vertical acceleration within +-a. The arcs, which curve down at about v^2 / leg, are kept
    where they are gentler than that. The bound is sampled on a fixed grid of absolute times
    (_ENVELOPE_RATE), so the height does not depend on the frame rate."""
    a = WALK_ACCELERATION_MAX
    margin = _envelope_reach(0.5 * a) + _envelope_reach(a)  # s: both envelopes' reach
    k0 = math.floor((float(t[0]) - margin) * _ENVELOPE_RATE)
    k1 = math.ceil((float(t[-1]) + margin) * _ENVELOPE_RATE)
    grid = np.arange(k0, k1 + 1) / _ENVELOPE_RATE
    plan = _feet_plan(grid, style, speed, yaw0, turn, back)
    root, xy, _ = _gait_root(grid, plan, style, speed, amp, yaw0, turn)
    dt = 1.0 / _ENVELOPE_RATE
    # The lower envelope is a grey erosion by the parabola (min of values + parabola), the
    # upper one a grey dilation (max of values - parabola); beyond the grid nothing competes.
    curve_up = _parabola(dt, 0.5 * a)
    lower = grey_erosion(_vault_height(plan, root, xy, style), structure=-curve_up,
                         mode="constant", cval=np.inf)
    curve_down = _parabola(dt, a)
    smooth = grey_dilation(lower, structure=-curve_down, mode="constant", cval=-np.inf)
    # Between grid samples the bound can dip by a fraction of a millimetre below the samples'
    # interpolation; the minimum keeps the legs within reach there.
    return np.minimum(bound, np.interp(t, grid, smooth))


def _run_height(
    t: np.ndarray, style: _GaitStyle, speed: float, amp: float, yaw0: float, turn: float,
    back: float,
) -> np.ndarray:
    """Running: the pelvis height (F,), taken for the body's centre of mass. At each touch-down
    and toe-off it is where the landing or leaving leg reaches its footstep with the knee at the
    style's flexion there; in each flight it is ballistic (gravity alone) between them; over
    each stance the ground pushes up with a smooth force that is zero at touch-down and toe-off
    (a half sine, skewed by a full one to meet the toe-off height): its impulse turns the
    landing's fall into the next take-off, and the path is C2 throughout."""
    freq = style.freq[0] + style.freq[1] * speed
    beta = style.stance[0] + style.stance[1] * speed
    cyc = t * freq + _GAIT_START
    half = np.floor(cyc / 0.5)  # half-strides: leg (half mod 2) is on the ground, then flight
    n = np.arange(half.min() - 1, half.max() + 2)  # the half-strides around every frame
    legs = (n % 2).astype(int)
    t_on = (0.5 * n - _GAIT_START) / freq
    t_off = (0.5 * n + beta - _GAIT_START) / freq
    # Every touch-down and toe-off at once: the height at which its leg reaches the footstep.
    events = np.concatenate([t_on, t_off])
    plan = _feet_plan(events, style, speed, yaw0, turn, back)
    root, xy, _ = _gait_root(events, plan, style, speed, amp, yaw0, turn)
    knee_on, knee_off = (a * _DEG for a in style.stance_knee)
    length = np.repeat(_leg_length(np.array([knee_on, knee_off])), len(n))
    leg = np.concatenate([legs, legs])
    room = np.where(leg == 0, _hip_room(plan, root, xy, 0, length),
                    _hip_room(plan, root, xy, 1, length))
    z_on, z_off = room[: len(n)], room[len(n):]
    # A slow run's toe-off foot, up on its ball close behind the hip, would lift the pelvis
    # well above touch-down's; the body leaves no higher than it landed (+ _TAKE_OFF_RISE).
    z_off = np.minimum(z_off, z_on + _TAKE_OFF_RISE)
    flight = (0.5 - beta) / freq
    # Flight n leaves at (t_off[n], z_off[n]) and lands at (t_on[n + 1], z_on[n + 1]).
    v_off = (z_on[1:] - z_off[:-1]) / flight + 0.5 * GRAVITY * flight
    v_on = v_off - GRAVITY * flight
    out = np.empty(len(t))
    i = (half - n[0]).astype(int)  # each frame's half-stride, as an index into n
    tau = t - t_off[i]
    air = tau >= 0.0
    j = i[air]
    out[air] = z_off[j] + v_off[j] * tau[air] - 0.5 * GRAVITY * tau[air] ** 2
    # Stance m: z'' = -g + a sin(pi s) + b sin(2 pi s), s = (t - t_on) / T: a from the impulse
    # (v_on -> v_off), b from the height it must end at; both vanish at the ends (z'' = -g).
    m = i[~air]
    period = beta / freq
    tt = t[~air] - t_on[m]
    v0 = v_on[m - 1]
    a = (v_off[m] - v0 + GRAVITY * period) * np.pi / (2.0 * period)
    free = z_on[m] + v0 * period - 0.5 * GRAVITY * period**2 + a * period**2 / np.pi
    b = (z_off[m] - free) * 2.0 * np.pi / period**2
    w1, w2 = np.pi / period, 2.0 * np.pi / period
    out[~air] = (z_on[m] + v0 * tt - 0.5 * GRAVITY * tt**2
                 + a / w1 * (tt - np.sin(w1 * tt) / w1) + b / w2 * (tt - np.sin(w2 * tt) / w2))
    return out


def _build_gait(style: _GaitStyle, t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    speed, amp = float(p["speed"]), float(p["amplitude"])
    yaw0 = p["direction"] * _DEG
    turn = p.get("turn", 0.0) * _DEG
    back = _gait_back(style, speed)
    plan = _feet_plan(t, style, speed, yaw0, turn, back)
    root, xy, pelvis_yaw = _gait_root(t, plan, style, speed, amp, yaw0, turn)
    reach = _LEG_SOFT
    if style.stance_knee is None:
        z = _walk_height(t, style, speed, amp, yaw0, turn, back,
                         _vault_height(plan, root, xy, style))
    else:
        z = _run_height(t, style, speed, amp, yaw0, turn, back)
        # The swing leg's footstep plan is in the world, and a flight carries the hip over it:
        # late in the swing the foot passes out of reach by up to a centimetre. From the
        # stance's straightest knee on, the leg nears full extension softly instead of at the
        # last millimetres, which jerked the knee; the stance stays within it, so it is exact.
        reach = float(_leg_length(min(style.stance_knee) * _DEG))
    pelvis = np.column_stack([xy, z])
    pose = _Pose(len(t))
    hip_ext = np.stack([plan["yaw"][0] - pelvis_yaw, -(plan["yaw"][1] - pelvis_yaw)])
    _solve_legs(pose, root, pelvis, plan["ankle"], plan["foot"], plan["toe"], hip_ext, reach)
    if style.swing_dorsiflexion is not None:
        _limit_swing_dorsiflexion(pose, plan["swing"], *style.swing_dorsiflexion)
    # Arms swing against the legs; the chest counter-rotates the pelvis; the head stays level.
    phi = 2 * np.pi * plan["phase"]
    d = _DEG
    swing = (style.arm_swing[0] + style.arm_swing[1] * speed) * amp * np.cos(phi - 0.15)
    lean = (style.lean[0] + style.lean[1] * speed) * d
    pose.arms(
        {
            "fwd": (style.arm_fwd - swing) * d,
            "down": ARM_DOWN + 2 * d,
            "elbow": (style.elbow + style.elbow_swing * (0.5 - 0.5 * np.cos(phi - 0.15))) * d,
        },
        {
            "fwd": (style.arm_fwd + swing) * d,
            "down": ARM_DOWN + 2 * d,
            "elbow": (style.elbow + style.elbow_swing * (0.5 + 0.5 * np.cos(phi - 0.15))) * d,
        },
    )
    twist = style.pelvis_yaw * d * amp * 1.4 * np.cos(phi)
    pose.spine(
        flex=0.5 * lean + 1.0 * d * amp * np.cos(2 * phi),
        twist=twist,
        head_flex=-0.5 * lean,
        head_twist=-0.4 * twist,
    )
    pose.set("pelvis", root)
    return _Built(pose.rot, pelvis, np.zeros(len(t)), world=True)


def _ankle_dorsiflexion(ankle_rot: np.ndarray) -> np.ndarray:
    """Dorsiflexion (radians, toes up positive) of ankle rotations (..., 3, 3) relative to the
    shin (local, world axes): the turn of the rest foot's ankle-to-ball direction about the
    lateral axis. Either leg: a turn about x is the same in the mirror image."""
    b = ankle_rot @ _FOOT
    a = _FOOT
    return -np.arctan2(a[1] * b[..., 2] - a[2] * b[..., 1], a[1] * b[..., 1] + a[2] * b[..., 2])


def _limit_swing_dorsiflexion(pose: _Pose, swing: np.ndarray, start: float, ceiling: float):
    """Turn each swing foot toes-down about its ankle where its dorsiflexion passes `start`
    (deg), so that it nears `ceiling` smoothly (tanh, C2 at `start`), weighted by `swing` (2, F:
    0 on the ground, 1 in mid-swing). The ankle stays where the legs put it; only the foot
    turns."""
    lo, span = start * _DEG, (ceiling - start) * _DEG
    for k, side in enumerate(("left", "right")):
        j = _J[f"{side}_ankle"]
        over = np.maximum(_ankle_dorsiflexion(pose.rot[:, j]) - lo, 0.0)
        excess = swing[k] * (over - span * np.tanh(over / span))
        pose.rot[:, j] = _rx(excess) @ pose.rot[:, j]


def _build_walk(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    return _build_gait(_WALK, t, fps, p)


def _build_run(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    return _build_gait(_RUN, t, fps, p)


# Jump: a virtual pelvis height z_v sets the legs as if the feet stood on the ground; on the
# ground the pelvis is at z_v, in the air it follows a ballistic arc and the feet are lifted by the
# difference. Above standing height z_v raises the heels; in the air the legs first finish their
# extension, then tuck (which lifts the feet), then reach for the ground. z_v is C2 everywhere,
# and so are the joint angles.
_HEEL_LEVER = float(np.hypot(_FOOT[1], _FOOT[2]))  # ankle to ball, in the sagittal plane
_HEEL_PHASE = float(np.arctan2(-_FOOT[2], -_FOOT[1]))  # its elevation with the foot flat
_HEEL_START = PELVIS_STAND + 0.004  # standing upright, the heels start to rise around here
_HEEL_SOFT = 0.012  # m, softness of that start
# Through the take-off and the touch-down the knees hand the leg's lengthening over to the
# heels; at the pelvis's speed there (up to 2.8 m/s) a 12 mm onset took 5 ms and jerked the
# knees at 250-300 m/s^2. The onset's softness grows with that speed, to span this time.
_HEEL_SOFT_TIME = 0.015  # s
# The virtual height's largest acceleration between the extension after take-off and the
# tuck at the apex (m/s^2).
_TUCK_ACCELERATION = 45.0
# The ground's largest push on the pelvis, in body weights (|a + g| / g): a maximal
# countermovement or standing long jump pushes with about 2-2.8, a landing from a jump ranges
# from about 2.5 (soft) to 6 (stiff); CMU's jumps reach 3.1-4.9 at the pelvis.
JUMP_PUSH_FORCE_MAX = 3.0
JUMP_LANDING_FORCE_MAX = 4.0
# The trunk's lean and the arms' swing are keyed in time; where keys come too close for these
# angular accelerations (rad/s^2) and, for the arms, speed (rad/s), the swing falls short of
# its key instead (_limited_keys). The trunk's bound keeps the neck within about 30 m/s^2 of the
# pelvis (CMU's jumps: 42-63 at the neck); the arms' keep the default jump's full swing (13.9
# rad/s at most; a countermovement jump's arms peak at about 12-17) and bring the hands of the
# most abrupt parameters from 275 to 190 m/s^2 (CMU's jumps: 47-128).
JUMP_TRUNK_ANGULAR_ACCELERATION_MAX = 60.0
JUMP_ARM_ANGULAR_ACCELERATION_MAX = 150.0
JUMP_ARM_ANGULAR_SPEED_MAX = 15.0


def _heel_pitch(
    root: np.ndarray, pelvis: np.ndarray, balls: np.ndarray, soft: np.ndarray | float = _HEEL_SOFT
) -> np.ndarray:
    """Heel raise (2, F) about the balls that keeps each leg no longer than when standing
    (knees as in the rest stance) however high or far the pelvis is; a softplus of softness
    `soft` (m, scalar or (F,)) makes the onset smooth, and below the onset the knees bend
    instead."""
    rest = _REST[_J["left_ankle"]] - _REST[_J["left_hip"]]
    length = math.hypot(rest[0], rest[1], _HEEL_START + _HIP_OFFSET[2] - ANKLE_HEIGHT)
    out = np.empty(balls.shape[:2])
    for k in range(2):
        flip = _X_FLIP if k else np.ones(3)
        hip = pelvis + root @ (_HIP_OFFSET * flip)
        pitch = np.zeros(len(pelvis))
        for _ in range(2):  # the ankle moves over the ball as the heel rises: refine once
            ankle = balls[k] + (_ankle_offset(pitch) * flip)
            horiz = np.sum((hip[:, :2] - ankle[:, :2]) ** 2, axis=-1)
            need = hip[:, 2] - np.sqrt(np.maximum(length**2 - horiz, 0.01)) - ANKLE_HEIGHT
            rise = soft * np.logaddexp(0.0, need / soft)
            cap = np.stack([-_FOOT[2] + rise, np.full(len(rise), 0.98 * _HEEL_LEVER)], -1)
            height = _softmin(cap, 0.004)[0]  # at most about 70 degrees, without a kink
            pitch = np.arcsin(height / _HEEL_LEVER) - _HEEL_PHASE
        out[k] = pitch
    return out


def _ground_time(dist: float, v: float) -> float:
    """Duration of a ground phase covering `dist` from rest to speed `v`, arriving with
    acceleration -g (at take-off the ground force has faded to zero; landing is its mirror):
    the quartic with those end conditions has this length."""
    a = GRAVITY / 12.0
    return (-v / 2.0 + math.sqrt(v * v / 4.0 + 4.0 * a * dist)) / (2.0 * a)


def _ground_depth(duration: float, v: float) -> float:
    """The distance the pelvis covers in a ground phase of `duration` (inverse of
    _ground_time)."""
    return GRAVITY * duration**2 / 12.0 + 0.5 * v * duration


_GROUND_S = np.linspace(0.0, 1.0, 65)


def _ground_force(duration: float, v: float, vh: float) -> float:
    """Peak ground force (in body weights) of a ground phase of `duration` from rest to
    vertical speed `v` and horizontal speed `vh`: the vertical quartic's acceleration is
    2g s + 6 (v / T) s (1 - s) - 3 g s^2 at s = t / T, the horizontal quintic's (smootherstep
    speed) 30 (vh / T) s^2 (1 - s)^2."""
    s = _GROUND_S
    up = GRAVITY + 2.0 * GRAVITY * s + 6.0 * v / duration * s * (1.0 - s) - 3.0 * GRAVITY * s * s
    forward = 30.0 * vh / duration * (s * (1.0 - s)) ** 2
    return float(np.hypot(up, forward).max()) / GRAVITY


def _bisect(holds: Callable[[float], bool], lo: float, hi: float) -> tuple[float, float]:
    """(lo, hi) halved 40 times around where `holds` changes: it holds at the lo end (or at
    the bound given) and not at the hi end."""
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if holds(mid) else (lo, mid)
    return lo, hi


def _bounded_ground_time(dist: float, v: float, vh: float, force: float) -> float:
    """The duration of a ground phase covering at least `dist` whose peak force stays within
    `force` body weights: _ground_time's, or longer (and deeper) where that one is too stiff."""
    lo = _ground_time(dist, v)
    if _ground_force(lo, v, vh) <= force:
        return lo
    hi = 2.0 * lo
    while _ground_force(hi, v, vh) > force:
        hi *= 2.0
    # The force falls as the phase lengthens.
    return _bisect(lambda t: _ground_force(t, v, vh) > force, lo, hi)[1]


def _jump_flight(height: float, ext: float, tuck: float) -> tuple[float, float, float, float]:
    """Take-off speed, flight time, extension time and tuck time for a given tuck depth."""
    v0 = math.sqrt(2.0 * GRAVITY * max(height - tuck, 1e-4))
    t_fly = 2.0 * v0 / GRAVITY
    # After take-off the extension slows from v0 to rest over `ext`, starting at -g.
    a = GRAVITY / 12.0
    t_ext = (v0 / 2.0 - math.sqrt(max(v0 * v0 / 4.0 - 4.0 * a * ext, 0.0))) / (2.0 * a)
    t_ext = min(t_ext, 0.3 * t_fly)
    return v0, t_fly, t_ext, 0.5 * t_fly - t_ext


def _air_legs(height: float) -> tuple[float, float]:
    """How far the legs extend after take-off and tuck at the apex (m of virtual height).

    Just after take-off the legs finish extending (heels up to about 45 degrees), then tuck at
    the apex, which gives part of the clearance: as deep as the time in the air allows a gentle
    tuck (what 15 m/s^2 covers over the time to the apex), at most 45 % of the height. And the
    virtual height must get from the extension down to the tuck within _TUCK_ACCELERATION: a
    low jump's short flight leaves no time for a tuck, and less for the extension, which
    shrinks too (a 5 cm hop had swung the knees at 150 m/s^2)."""

    def room(ext: float, tuck: float) -> float:
        t_tuck = _jump_flight(height, ext, tuck)[3]
        reach = t_tuck**2 / _SMOOTHERSTEP_PEAK  # the distance a unit acceleration covers
        return min(15.0 * reach - tuck, _TUCK_ACCELERATION * reach - (ext + tuck))

    ext = min(0.065, 0.015 + 0.25 * height)
    if room(ext, 0.0) < 0.0:  # the room shrinks as the extension grows
        return _bisect(lambda e: room(e, 0.0) >= 0.0, 0.0, ext)[0], 0.0
    # The affordable tuck shrinks as the tuck deepens.
    return ext, _bisect(lambda tuck: room(ext, tuck) >= 0.0, 0.0, 0.45 * height)[0]


def _jump_timeline(p: dict[str, float]) -> dict[str, float]:
    tempo, height = p["speed"], p["height"]
    # Take-off: heels about 10 degrees up; lower for forward jumps (the body leans forward).
    z_to = _HEEL_START + 0.02 - 0.06 * p["distance"]
    ext, tuck = _air_legs(height)
    v0, t_fly, t_ext, _ = _jump_flight(height, ext, tuck)
    depth = (0.14 + 0.25 * height) * p["amplitude"]
    k = {
        "z_to": z_to,
        "z_max": z_to + ext,
        "z_tuck": z_to - tuck,
        "v0": v0,
        "t_fly": t_fly,
        "t_ext": t_ext,
        "z_low": PELVIS_STAND - depth,
        "z_land": PELVIS_STAND - 0.8 * depth,
    }
    # The crouch and the landing are as deep as `amplitude` asks, or deeper where the ground
    # force would pass JUMP_PUSH_FORCE_MAX or JUMP_LANDING_FORCE_MAX: a shallow crouch before
    # a high or long jump pushes for too short a time. The forward speed depends on both
    # durations, which it lengthens in turn: a few rounds settle it.
    dist = p["distance"]
    t_push, t_land = _ground_time(z_to - k["z_low"], v0), _ground_time(z_to - k["z_land"], v0)
    vh = dist / (t_fly + 0.5 * (t_push + t_land))
    for _ in range(4):
        t_push = _bounded_ground_time(z_to - k["z_low"], v0, vh, JUMP_PUSH_FORCE_MAX)
        t_land = _bounded_ground_time(z_to - k["z_land"], v0, vh, JUMP_LANDING_FORCE_MAX)
        vh = dist / (t_fly + 0.5 * (t_push + t_land))
    k["t_push"], k["t_land"], k["vh"] = t_push, t_land, vh
    k["z_low"] = z_to - _ground_depth(t_push, v0)
    k["z_land"] = z_to - _ground_depth(t_land, v0)
    k["hold"] = 0.3 / tempo
    k["bottom"] = k["hold"] + 0.5 / tempo
    k["takeoff"] = k["bottom"] + k["t_push"]
    k["touch"] = k["takeoff"] + t_fly
    k["absorbed"] = k["touch"] + k["t_land"]
    k["stand"] = k["absorbed"] + 0.55 / tempo
    k["period"] = k["stand"] + 0.25 / tempo
    return k


def _jump_heights(tc: np.ndarray, k: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Real and virtual pelvis heights at cycle times `tc`."""
    zs, v0, g = PELVIS_STAND, k["v0"], GRAVITY
    z_low, z_land, z_to = k["z_low"], k["z_land"], k["z_to"]
    t_to, t_td, t_fly, t_ext = k["takeoff"], k["touch"], k["t_fly"], k["t_ext"]
    z = np.full(len(tc), zs)
    mid = t_to + 0.5 * t_fly
    segments = [  # (start, end, start state, end state): position, velocity, acceleration
        (k["hold"], k["bottom"], (zs, 0, 0), (z_low, 0, 0)),  # countermovement
        (k["bottom"], t_to, (z_low, 0, 0), (z_to, v0, -g)),  # push-off
        (t_to, t_to + t_ext, (z_to, v0, -g), (k["z_max"], 0, 0)),  # legs finish extending
        (t_to + t_ext, mid, (k["z_max"], 0, 0), (k["z_tuck"], 0, 0)),  # tuck
        (mid, t_td - t_ext, (k["z_tuck"], 0, 0), (k["z_max"], 0, 0)),  # reach down
        (t_td - t_ext, t_td, (k["z_max"], 0, 0), (z_to, -v0, -g)),  # meet the ground
        (t_td, k["absorbed"], (z_to, -v0, -g), (z_land, 0, 0)),  # landing absorption
        (k["absorbed"], k["stand"], (z_land, 0, 0), (zs, 0, 0)),  # stand up
    ]
    for a, b, s0, s1 in segments:
        m = (tc >= a) & (tc < b)
        z[m] = _quintic(tc[m], a, b, s0, s1)
    zv = z.copy()
    m = (tc >= t_to) & (tc < t_td)
    tau = tc[m] - t_to
    z[m] = z_to + v0 * tau - 0.5 * g * tau * tau
    return z, zv


def _limited_keys(
    times, values: np.ndarray, curvature: float, speed: float = math.inf
) -> np.ndarray:
    """Key values for _keys whose every segment accelerates by at most `curvature` and moves at
    most at `speed` (a smootherstep's peaks are _SMOOTHERSTEP_PEAK |dv| / dt^2 and
    _SMOOTHERSTEP_PEAK_SPEED |dv| / dt): a key that its neighbours' spacing would make too
    abrupt to reach moves toward them instead, so the swing falls short of it. The first and
    last keys (the rest pose) stay. Alternate sweeps clamp each key to its neighbours' reach
    until none moves; a key only ever moves toward its neighbours, so this ends, and keys
    within reach are kept as they are."""
    dt = np.diff(np.asarray(times, dtype=np.float64))
    reach = np.minimum(curvature * dt**2 / _SMOOTHERSTEP_PEAK,
                       speed * dt / _SMOOTHERSTEP_PEAK_SPEED)
    out = np.array(values, dtype=np.float64)
    last = len(out) - 1
    for _ in range(4 * len(out)):
        before = out.copy()
        for i in range(1, last):
            out[i] = np.clip(out[i], out[i - 1] - reach[i - 1], out[i - 1] + reach[i - 1])
        for i in range(last - 1, 0, -1):
            out[i] = np.clip(out[i], out[i + 1] - reach[i], out[i + 1] + reach[i])
        if np.array_equal(out, before):
            break
    return out


def _jump_swing_keys(
    k: dict[str, float], amp: float, dist: float
) -> tuple[list[float], np.ndarray, list[float], np.ndarray]:
    """The trunk's lean and the arms' swing as keys (cycle times, radians), before
    _limited_keys: lean and hips back in the crouches; the arms swing back, then up through the
    take-off."""
    t_h, t_b, t_to, t_td = k["hold"], k["bottom"], k["takeoff"], k["touch"]
    t_ab, t_st, period, t_fly = k["absorbed"], k["stand"], k["period"], k["t_fly"]
    t_down = t_b - t_h
    lean_max = (40 * (0.6 + 0.4 * amp) + 12 * dist) * _DEG
    lean_times = [0, t_h, t_b - 0.2 * t_down, t_to, t_td, t_ab, t_st, period]
    lean = lean_max * np.array([0, 0, 1, 0.25, 0.15, 0.8, 0, 0])
    arm_times = [
        0,
        t_h,
        t_b - 0.1 * t_down,
        t_to + 0.35 * t_fly,
        t_td - 0.1 * t_fly,
        t_ab + 0.3 * (t_st - t_ab),
        t_st + 0.4 * (period - t_st),
        period,
    ]
    arm = amp * _DEG * np.array([0, 0, -40, 110, 60, 35, 0, 0])
    return lean_times, lean, arm_times, arm


def _build_jump(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    k = _jump_timeline(p)
    n, amp = len(t), p["amplitude"]
    period = k["period"]
    cycle = np.floor(t / period)
    tc = t - cycle * period
    z, zv = _jump_heights(tc, k)
    t_b, t_to, t_td, t_ab = k["bottom"], k["takeoff"], k["touch"], k["absorbed"]

    # Forward travel: speed up during the push, constant in the air, brake while landing.
    dist, vh = p["distance"], k["vh"]
    y_to = -0.5 * vh * k["t_push"]
    y_td = y_to - vh * k["t_fly"]
    y = np.zeros(n)
    m = (tc >= t_b) & (tc < t_to)
    y[m] = _quintic(tc[m], t_b, t_to, (0, 0, 0), (y_to, -vh, 0))
    m = (tc >= t_to) & (tc < t_td)
    y[m] = y_to - vh * (tc[m] - t_to)
    m = tc >= t_td
    y[m] = _quintic(tc[m], t_td, t_ab, (y_td, -vh, 0), (-dist, 0, 0))
    y -= dist * cycle
    feet_y = -dist * (cycle + _smootherstep((tc - t_to) / (t_td - t_to)))

    lean_times, lean_keys, arm_times, arm_keys = _jump_swing_keys(k, amp, dist)
    lean = _keys(tc, lean_times, _limited_keys(lean_times, lean_keys,
                                               JUMP_TRUNK_ANGULAR_ACCELERATION_MAX))
    back = 0.08 * (0.6 + 0.4 * amp) * lean / lean_keys.max()
    arm = _keys(tc, arm_times, _limited_keys(arm_times, arm_keys,
                                             JUMP_ARM_ANGULAR_ACCELERATION_MAX,
                                             JUMP_ARM_ANGULAR_SPEED_MAX))
    soft_abs = np.sqrt(arm * arm + (10 * _DEG) ** 2) - 10 * _DEG  # no kink at zero
    arms = {
        "fwd": ARM_FORWARD + arm,
        "down": ARM_DOWN - 0.075 * (arm + soft_abs),
        "elbow": ELBOW_FLEX + 0.1 * soft_abs,
    }
    pose = _Pose(n)
    pose.arms(arms, arms)
    pose.spine(flex=0.35 * lean, head_flex=-0.5 * lean)
    root = _trunk(0.65 * lean)
    balls = _stance_balls(n)
    balls[:, :, 1] += feet_y
    # Toes point in the air (a C2 bump over the flight), otherwise the heels follow z_v.
    air = _compact((tc - 0.5 * (t_to + t_td)) / (0.5 * (t_td - t_to)))
    virtual = np.column_stack([np.zeros(n), y + back, zv])
    h = 1e-3  # s: the virtual height's rate, by central difference of the exact curve
    rate = (_jump_heights(tc + h, k)[1] - _jump_heights(tc - h, k)[1]) / (2.0 * h)
    soft = np.hypot(_HEEL_SOFT, _HEEL_SOFT_TIME * rate)
    heel = _heel_pitch(root, virtual, balls, soft)
    pitch = heel + air * (40.0 * _DEG - 0.6 * heel)  # never below the heel pitch (leg length)
    _legs(pose, root, virtual, balls, pitch)
    return _finish(pose, root, np.column_stack([np.zeros(n), y + back, z]))


def _build_spin(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, amp = len(t), p["amplitude"]
    w = 2 * np.pi * p["speed"] * t
    heel = 18.0 * _DEG
    pose = _Pose(n)
    bounce = 0.012 * amp * (1 - np.cos(2 * w)) / 2
    pelvis = np.tile([0.0, 0.0, _pelvis_for_pitch(heel) - 0.035], (n, 1))
    pelvis[:, 2] -= bounce
    root = np.broadcast_to(_trunk(3 * _DEG), (n, 3, 3))  # a slight forward lean
    arm = amp * (1 - np.cos(w)) / 2
    arms = {
        "down": ARM_DOWN - (12 + 18 * arm) * _DEG,
        "fwd": (15 + 10 * arm) * _DEG,
        "elbow": (40 + 25 * arm) * _DEG,
    }
    pose.arms(arms, arms)
    pose.spine(flex=2 * _DEG)
    balls = _stance_balls(n, width=-0.05, forward=0.0)
    _legs(pose, root, pelvis, balls, heel, foot_yaw=np.full((2, n), 4 * _DEG))
    yaw = 2 * np.pi * p["revs"] * t
    return _finish(pose, root, pelvis, yaw)


def _build_arm_raise(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, amp, tempo = len(t), p["amplitude"], p["speed"]
    times = np.array([0.0, 0.4, 1.7, 2.2, 3.5]) / tempo
    raise_ = _keys(t, times, [0, 0, 1, 1, 0], period=times[-1])
    pose, root, pelvis = _standing(n)
    top = -80.0 * _DEG
    lift = amp * raise_
    down = ARM_DOWN + (top - ARM_DOWN) * lift
    plane = p["plane"]
    # Forward raise: swing the arm about x; sideways: lower it less in the frontal plane.
    fwd = ARM_FORWARD + plane * lift * (170 * _DEG - ARM_FORWARD)
    down = (1 - plane) * down + plane * ARM_DOWN
    arms = {
        "down": down,
        "fwd": fwd,
        "elbow": ELBOW_FLEX * (1 - 0.7 * lift),
        "collar": 12 * _DEG * lift**2,
    }
    pose.arms(arms, arms)
    pose.spine(flex=-4 * _DEG * lift, head_flex=-6 * _DEG * lift)
    _legs(pose, root, pelvis, _stance_balls(n), 0.0)
    return _finish(pose, root, pelvis)


def _side_is_left(value: float) -> bool:
    return value >= 0.5


def _build_wave(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, amp, tempo = len(t), p["amplitude"], p["speed"]
    times = np.array([0.0, 0.3, 1.0, 3.0, 3.7, 4.1]) / tempo
    up = _keys(t, times, [0, 0, 1, 1, 0, 0], period=times[-1])
    tc = np.mod(t, times[-1])
    # Waving (2 Hz at tempo 1) fades in and out inside the raised window.
    env = _smootherstep((tc - times[2] + 0.25 / tempo) / (0.4 / tempo)) * _smootherstep(
        (times[3] + 0.25 / tempo - tc) / (0.4 / tempo)
    )
    osc = 25 * _DEG * amp * env * np.sin(2 * np.pi * 2.0 * tempo * (tc - times[2]))
    pose, root, pelvis = _standing(n)
    waving = {
        "down": ARM_DOWN + (-15 * _DEG - ARM_DOWN) * up,
        "ext": 85 * _DEG * up,
        "horiz": 15 * _DEG * up,
        "fwd": ARM_FORWARD * (1 - up),
        "elbow": ELBOW_FLEX + (70 * _DEG - ELBOW_FLEX) * up + osc,
    }
    rest = {}
    lean = 2.5 * _DEG * up
    if _side_is_left(p["side"]):
        pose.arms(waving, rest)
        sign = 1.0
    else:
        pose.arms(rest, waving)
        sign = -1.0
    pose.spine(lat=-sign * lean, head_flex=-3 * _DEG * up, head_twist=sign * 8 * _DEG * up)
    pelvis[:, 0] -= sign * 0.015 * up
    _legs(pose, root, pelvis, _stance_balls(n), 0.0)
    return _finish(pose, root, pelvis)


def _build_squat(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, amp, tempo = len(t), p["amplitude"], p["speed"]
    times = np.array([0.0, 0.5, 1.7, 2.1, 3.3]) / tempo
    s = _keys(t, times, [0, 0, 1, 1, 0], period=times[-1])
    depth = p["depth"]
    pose, root, pelvis = _standing(n)
    frac = s * depth / 0.45
    pelvis[:, 2] -= depth * s
    pelvis[:, 1] += 0.16 * frac  # hips back
    root = _trunk(38 * _DEG * frac)
    arm = 80 * _DEG * amp * s
    arms = {"fwd": ARM_FORWARD + arm, "down": ARM_DOWN - 0.25 * arm, "elbow": ELBOW_FLEX}
    pose.arms(arms, arms)
    pose.spine(flex=8 * _DEG * frac, head_flex=-25 * _DEG * frac)
    balls = _stance_balls(n, width=0.03)
    _legs(pose, root, pelvis, balls, 0.0, foot_yaw=np.full((2, n), 8 * _DEG * frac))
    return _finish(pose, root, pelvis)


def _build_kick(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    """A right-leg front kick (the left one is its mirror image)."""
    n, amp, tempo = len(t), p["amplitude"], p["speed"]
    times = np.array([0.0, 0.2, 0.55, 0.8, 1.0, 1.2, 1.45, 1.8, 2.0]) / tempo
    period = times[-1]
    # 0 stand, 1 weight on the left, 2 chamber, 3 extended, 4 re-chamber, 5 foot down,
    # 6 weight centred, 7 rest.
    shift = _keys(t, times, [0, 0, 1, 1, 1, 1, 1, 0, 0], period)
    pose, root, pelvis = _standing(n)
    # The extended leg points from the (shifted, leaning, turned) right hip towards `height`.
    lean_back, turn = -12 * _DEG * amp, 10 * _DEG * amp
    hip = np.array([0.075, 0.0, PELVIS_STAND - 0.02]) + _trunk(lean_back, 4 * _DEG, turn) @ (
        _HIP_OFFSET * _X_FLIP
    )
    reach = _LEG_SOFT - 0.03
    elev = math.asin(float(np.clip((p["height"] - hip[2]) / reach, -0.9, 0.95)))
    rest_ankle = np.array([-(_REST[_J["left_ankle"], 0]), _REST[_J["left_ankle"], 1], ANKLE_HEIGHT])
    # Ankle targets of the kicking (right) foot, relative to its place on the ground.
    ext_target = hip + reach * np.array([0.0, -math.cos(elev), math.sin(elev)]) - rest_ankle
    chamber = np.array([0.02, -0.25, 0.42])
    path = _keys(
        t,
        times,
        np.array(
            [
                np.zeros(3),
                np.zeros(3),
                np.zeros(3),
                chamber,
                ext_target,
                chamber,
                np.zeros(3),
                np.zeros(3),
                np.zeros(3),
            ]
        ),
        period,
    )
    foot_pitch = _keys(
        t, times, [0, 0, 0, 35 * _DEG, -(elev + 5 * _DEG), 35 * _DEG, 0, 0, 0], period
    )
    kick = _keys(t, times, [0, 0, 0, 0.5, 1, 0.5, 0, 0, 0], period)
    pelvis[:, 0] += 0.075 * shift
    pelvis[:, 2] -= 0.02 * shift
    root = _trunk(lean_back * kick, 4 * _DEG * shift, turn * kick)
    guard = {
        "down": ARM_DOWN - 20 * _DEG * shift * amp,
        "fwd": ARM_FORWARD + 25 * _DEG * shift * amp,
        "elbow": ELBOW_FLEX + 55 * _DEG * shift * amp,
    }
    pose.arms({**guard, "horiz": 10 * _DEG * kick * amp}, guard)
    pose.spine(
        flex=6 * _DEG * kick * amp,
        lat=-3 * _DEG * shift,
        twist=-8 * _DEG * kick * amp,
        head_flex=5 * _DEG * kick,
        head_twist=-4 * _DEG * kick * amp,
    )
    balls = _stance_balls(n)
    # The kicking foot is placed by its ankle: convert the ankle path to a ball position.
    foot_world = _rx(foot_pitch)
    ankle = rest_ankle + path
    balls[1] = ankle + foot_world @ (_FOOT * _X_FLIP)
    pitch = np.stack([np.zeros(n), foot_pitch])
    _legs(pose, root, pelvis, balls, pitch, toes=np.zeros((2, n)))
    built = _finish(pose, root, pelvis)
    if _side_is_left(p["side"]):
        built = _mirror_built(built)
    return built


def _build_dance(t: np.ndarray, fps: float, p: dict[str, float]) -> _Built:
    n, amp, tempo = len(t), p["amplitude"], p["speed"]
    phi = 2 * np.pi * 0.5 * tempo * t  # one cycle = 4 beats at 120 bpm
    sway = np.sin(phi)
    pose, root, pelvis = _standing(n)
    pelvis[:, 0] += 0.06 * amp * sway
    bounce = 0.5 - 0.5 * np.cos(4 * phi)  # down on every beat
    pelvis[:, 2] -= 0.03 + 0.03 * amp * bounce
    root = _trunk(3 * _DEG, -5 * _DEG * amp * sway, 10 * _DEG * amp * np.sin(phi - 0.4))
    # The unweighted foot taps: it lifts and rises onto its ball as the weight leaves it.
    tap_l = _compact((sway + 1.0) / 0.75)  # weight on the right (sway < 0): left foot free
    tap_r = _compact((sway - 1.0) / 0.75)
    balls = _stance_balls(n, width=0.05)
    balls[0, :, 2] += 0.05 * amp * tap_l
    balls[1, :, 2] += 0.05 * amp * tap_r
    balls[0, :, 0] -= 0.04 * amp * tap_l
    balls[1, :, 0] += 0.04 * amp * tap_r
    pitch = np.stack([30 * _DEG * tap_l, 30 * _DEG * tap_r])
    pump = np.sin(2 * phi)
    pose.arms(
        {
            "down": ARM_DOWN - 25 * _DEG * amp * (0.6 + 0.4 * pump),
            "fwd": (25 + 30 * amp * pump) * _DEG,
            "elbow": (75 + 20 * pump) * _DEG,
        },
        {
            "down": ARM_DOWN - 25 * _DEG * amp * (0.6 - 0.4 * pump),
            "fwd": (25 - 30 * amp * pump) * _DEG,
            "elbow": (75 - 20 * pump) * _DEG,
        },
    )
    pose.spine(
        flex=4 * _DEG * bounce * amp,
        lat=6 * _DEG * amp * sway,
        twist=-12 * _DEG * amp * np.sin(phi - 0.4),
        head_flex=-6 * _DEG * amp * bounce,
        head_twist=10 * _DEG * amp * sway,
    )
    _legs(pose, root, pelvis, balls, pitch, foot_yaw=np.full((2, n), 6 * _DEG))
    return _finish(pose, root, pelvis)


def _mirror_built(b: _Built) -> _Built:
    """Left-right mirror image of a built motion (in its heading frame)."""
    rot = b.rot[:, list(MIRROR)] * _MIRROR_SIGN
    trans = b.trans * _X_FLIP
    return _Built(rot, trans, -b.yaw, b.world)


# -- registry ---------------------------------------------------------------------------------


def _common(speed: ParamSpec) -> dict[str, ParamSpec]:
    return {
        "speed": speed,
        "amplitude": ParamSpec(1.0, 0.5, 1.5, "x", "scales the joint excursions (1 = default)"),
        "direction": ParamSpec(
            0.0, -180.0, 180.0, "deg", "heading about +z; 0 faces -y, 90 faces +x"
        ),
    }


_TEMPO = ParamSpec(1.0, 0.6, 1.6, "x", "tempo multiplier (1 = default timing)")
_SIDE_DOC = "which side: < 0.5 right, >= 0.5 left (mirroring also swaps it)"

ACTIONS: dict[str, Action] = {
    "idle": Action("idle", "standing, breathing, slow weight shift", _common(_TEMPO), _build_idle),
    "walk": Action(
        "walk",
        "walking gait on planted footsteps",
        {
            **_common(ParamSpec(1.3, 0.5, 2.0, "m/s", "walking speed")),
            "turn": ParamSpec(0.0, -30.0, 30.0, "deg/s", "turning rate (positive: to the left)"),
        },
        _build_walk,
    ),
    "run": Action(
        "run",
        "running gait with flight phases, on planted footsteps",
        {
            **_common(ParamSpec(3.0, 2.0, 4.5, "m/s", "running speed")),
            "turn": ParamSpec(0.0, -30.0, 30.0, "deg/s", "turning rate (positive: to the left)"),
        },
        _build_run,
    ),
    "jump": Action(
        "jump",
        "countermovement jump with ballistic flight, repeated",
        {
            **_common(_TEMPO),
            "height": ParamSpec(0.2, 0.05, 0.4, "m", "sole clearance at the apex"),
            "distance": ParamSpec(0.0, 0.0, 0.8, "m", "forward travel per jump"),
        },
        _build_jump,
    ),
    "spin": Action(
        "spin",
        "turn in place on the balls of the feet",
        {
            **_common(_TEMPO),
            "revs": ParamSpec(
                1.0, 0.25, 2.5, "rev/s", "revolutions per second (counter-clockwise)"
            ),
        },
        _build_spin,
    ),
    "arm_raise": Action(
        "arm_raise",
        "raise both arms over the head and lower them",
        {
            **_common(_TEMPO),
            "amplitude": ParamSpec(1.0, 0.3, 1.1, "x", "fraction of the full raise (1: overhead)"),
            "plane": ParamSpec(0.0, 0.0, 1.0, "", "0 raises sideways, 1 forwards"),
        },
        _build_arm_raise,
    ),
    "wave": Action(
        "wave",
        "raise one forearm and wave",
        {**_common(_TEMPO), "side": ParamSpec(0.0, 0.0, 1.0, "", _SIDE_DOC)},
        _build_wave,
    ),
    "squat": Action(
        "squat",
        "repeated squats, heels down",
        {**_common(_TEMPO), "depth": ParamSpec(0.3, 0.1, 0.45, "m", "pelvis drop")},
        _build_squat,
    ),
    "kick": Action(
        "kick",
        "front kick with weight shift, chamber and retraction",
        {
            **_common(_TEMPO),
            "height": ParamSpec(0.7, 0.3, 1.0, "m", "ankle height at full extension"),
            "side": ParamSpec(0.0, 0.0, 1.0, "", _SIDE_DOC),
        },
        _build_kick,
    ),
    "dance": Action(
        "dance", "step-touch dance loop (speed 1 = 120 bpm)", _common(_TEMPO), _build_dance
    ),
}


def action_parameters(name: str) -> dict[str, ParamSpec]:
    """The parameters of an action: name -> ParamSpec(default, min, max, unit, doc)."""
    return dict(_action(name).params)


def _action(name: str) -> Action:
    if name not in ACTIONS:
        raise InputError(
            None, "motion.action", f"one of the actions {', '.join(sorted(ACTIONS))}", name
        )
    return ACTIONS[name]


def resolve_params(action: str, params: dict | None = None) -> dict[str, float]:
    """Defaults filled in and every value checked against its range."""
    specs = _action(action).params
    out = {k: float(s.default) for k, s in specs.items()}
    for key, value in (params or {}).items():
        if key not in specs:
            raise InputError(
                None,
                f"motion.params.{key}",
                f"a parameter of {action} ({', '.join(sorted(specs))})",
                key,
            )
        spec = specs[key]
        ok = isinstance(value, int | float | np.integer | np.floating) and not isinstance(
            value, bool
        )
        if not ok or not math.isfinite(float(value)) or not spec.min <= value <= spec.max:
            raise InputError(
                None,
                f"motion.params.{key}",
                f"a number in the range [{spec.min:g}, {spec.max:g}] {spec.unit}".rstrip(),
                value,
            )
        out[key] = float(value)
    return out


def generate(
    action: str, n_frames: int, fps: float, params: dict | None = None, mirror: bool = False
) -> Motion:
    """`n_frames` frames of a procedural action at `fps` (deterministic).

    Raises InputError for an unknown action ("motion.action"), an unknown parameter or a value
    out of its range ("motion.params.<name>"), or a bad frame count or rate."""
    spec = _action(action)
    values = resolve_params(action, params)
    if isinstance(n_frames, bool) or not isinstance(n_frames, int | np.integer) or n_frames < 1:
        raise InputError(None, "motion.frames", "a positive number of frames", n_frames)
    if not isinstance(fps, int | float | np.integer | np.floating) or not (
        math.isfinite(fps) and fps > 0
    ):
        raise InputError(None, "motion.fps", "a positive frame rate", fps)
    t = np.arange(int(n_frames)) / float(fps)
    built = spec.build(t, float(fps), values)
    rot = np.array(built.rot, dtype=np.float64)
    trans = np.array(built.trans, dtype=np.float64)
    if built.world:
        yaw = np.asarray(built.yaw, dtype=np.float64)
    else:
        heading = values["direction"] * _DEG
        yaw = heading + np.asarray(built.yaw, dtype=np.float64)
        trans = (_rz(heading) @ trans[..., None])[..., 0]
    rot[:, 0] = _rz(yaw) @ rot[:, 0]
    # Built in world axes; the canonical format expresses child joints in SMPL's axes.
    poses = matrix_to_axis_angle(world_axes_to_local(rot)).reshape(len(t), NUM_JOINTS * 3)
    if mirror:
        poses = mirror_poses(poses)
        trans = trans * _X_FLIP
    return Motion(
        poses=poses,
        trans=trans,
        fps=float(fps),
        label=action,
        source="procedural",
        pelvis_height=REFERENCE_PELVIS_HEIGHT,
    )
