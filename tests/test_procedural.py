"""The procedural action library: registry, validation, determinism, smoothness, foot contact,
jump ballistics, spin heading, mirroring, rest stance and speed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from scipy.spatial.transform import Rotation

from datagen.errors import InputError
from datagen.motion import procedural
from datagen.motion.procedural import ACTIONS, action_parameters, generate
from datagen.rotations import axis_angle_to_matrix
from datagen.skeleton import (
    JOINT_INDEX,
    MIRROR,
    REFERENCE_PELVIS_HEIGHT,
    REFERENCE_REST_JOINTS,
    forward_kinematics,
    mirror_poses,
)

J = JOINT_INDEX
ANKLE_REF = REFERENCE_REST_JOINTS[J["left_ankle"], 2] + REFERENCE_PELVIS_HEIGHT
BALL_REF = REFERENCE_REST_JOINTS[J["left_foot"], 2] + REFERENCE_PELVIS_HEIGHT
REQUIRED = ("walk", "run", "jump", "spin", "arm_raise", "wave", "squat", "kick", "dance")

# Physiological bounds on joint angular acceleration (rad/s^2). Measured peaks (120 fps) at the
# default parameters: walk ~330, run ~600, jump ~700 (ankle and knee around take-off), kick ~380,
# wave ~80, dance ~50, the others below 30. Fast running, high kicks and jumps at the ends of
# their ranges reach ~1500; elite sprint and kick data peak at a few thousand.
BOUND_DEFAULT = 900.0
BOUND_ANY = 2500.0


def joints(motion) -> np.ndarray:
    return forward_kinematics(motion.poses, motion.trans, REFERENCE_REST_JOINTS)[1]


def sole_heights(motion) -> np.ndarray:
    """(F, 2, 2) estimated height above the ground of (ankle, ball) for (left, right)."""
    j = joints(motion)
    feet = [(J["left_ankle"], J["left_foot"]), (J["right_ankle"], J["right_foot"])]
    return np.stack(
        [np.stack([j[:, a, 2] - ANKLE_REF, j[:, b, 2] - BALL_REF], -1) for a, b in feet], 1
    )


def max_angular_acceleration(motion) -> float:
    """Largest change of per-joint angular velocity (rad/s^2) over all joints and frames."""
    r = axis_angle_to_matrix(motion.poses.reshape(-1, 24, 3))
    rel = np.einsum("fjba,fjbc->fjac", r[:-1], r[1:])  # R_f^T R_{f+1}
    omega = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec().reshape(-1, 24, 3)
    omega *= motion.fps
    return float(np.linalg.norm(np.diff(omega, axis=0), axis=-1).max() * motion.fps)


def heading(motion) -> np.ndarray:
    """Unwrapped yaw of the body's facing direction (0 = facing -y), radians."""
    fwd = axis_angle_to_matrix(motion.poses[:, :3]) @ np.array([0.0, -1.0, 0.0])
    return np.unwrap(np.arctan2(fwd[:, 0], -fwd[:, 1]))


def random_params(name: str, rng: np.random.Generator) -> dict[str, float]:
    return {k: float(rng.uniform(s.min, s.max)) for k, s in action_parameters(name).items()}


# -- registry and validation ------------------------------------------------------------------


def test_registry_has_the_actions_and_documented_parameters():
    assert len(ACTIONS) >= 8
    assert set(REQUIRED) <= set(ACTIONS)
    for name in ACTIONS:
        specs = action_parameters(name)
        assert {"speed", "amplitude", "direction"} <= set(specs)
        for spec in specs.values():
            assert spec.min < spec.max
            assert spec.min <= spec.default <= spec.max
            assert spec.doc
        assert specs["direction"].min <= -180 and specs["direction"].max >= 180
    assert action_parameters("walk")["speed"].unit == "m/s"
    assert action_parameters("spin")["revs"].max >= 2.0
    assert "height" in action_parameters("jump")
    assert "side" in action_parameters("kick")


@pytest.mark.parametrize("name", sorted(ACTIONS))
@pytest.mark.parametrize("n_frames", [1, 2, 90, 300])
def test_every_action_generates_finite_arrays(name, n_frames):
    m = generate(name, n_frames, 30.0)
    assert m.poses.shape == (n_frames, 72) and m.trans.shape == (n_frames, 3)
    assert np.isfinite(m.poses).all() and np.isfinite(m.trans).all()
    assert m.label == name and m.source == "procedural" and m.fps == 30.0
    assert m.pelvis_height == REFERENCE_PELVIS_HEIGHT


def test_unknown_action_names_the_field_and_the_known_actions():
    with pytest.raises(InputError) as err:
        generate("moonwalk", 10, 30.0)
    assert err.value.field == "motion.action"
    assert "walk" in err.value.expected and "dance" in err.value.expected
    with pytest.raises(InputError):
        action_parameters("moonwalk")


def test_parameter_errors_name_the_field():
    with pytest.raises(InputError) as err:
        generate("walk", 10, 30.0, {"sped": 1.0})
    assert err.value.field == "motion.params.sped"
    with pytest.raises(InputError) as err:
        generate("walk", 10, 30.0, {"speed": 9.0})
    assert err.value.field == "motion.params.speed"
    assert "range" in err.value.expected and err.value.got == 9.0
    for bad in (float("nan"), "fast", True, None):
        with pytest.raises(InputError) as err:
            generate("spin", 10, 30.0, {"revs": bad})
        assert err.value.field == "motion.params.revs"
    with pytest.raises(InputError) as err:
        generate("walk", 0, 30.0)
    assert err.value.field == "motion.frames"
    with pytest.raises(InputError) as err:
        generate("walk", 10, 0.0)
    assert err.value.field == "motion.fps"


def test_bounds_are_inclusive_and_defaults_fill_in():
    spec = action_parameters("jump")["height"]
    for value in (spec.min, spec.max):
        assert np.isfinite(generate("jump", 5, 30.0, {"height": value}).poses).all()
    a = generate("jump", 40, 30.0)
    b = generate("jump", 40, 30.0, {"height": spec.default})
    np.testing.assert_array_equal(a.poses, b.poses)


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_deterministic(name):
    params = random_params(name, np.random.default_rng(7))
    a = generate(name, 120, 30.0, params, mirror=True)
    b = generate(name, 120, 30.0, dict(params), mirror=True)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.trans, b.trans)


# -- smoothness -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_angular_acceleration_bounded_and_not_growing_with_fps(name):
    acc = {
        fps: max_angular_acceleration(generate(name, int(6 * fps), float(fps)))
        for fps in (30, 120, 240)
    }
    assert acc[30] < BOUND_DEFAULT and acc[120] < BOUND_DEFAULT, acc
    # A jump in angular velocity makes this grow in proportion to the frame rate (x4, then x2);
    # a smooth peak is only resolved better (30 fps undersamples the sharpest ones).
    assert acc[120] < 2.2 * acc[30] + 20.0, acc
    assert acc[240] < 1.15 * acc[120] + 20.0, acc


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_smooth_over_random_parameters(name):
    rng = np.random.default_rng(11)
    for _ in range(3):
        params = random_params(name, rng)
        a60 = max_angular_acceleration(generate(name, 240, 60.0, params))
        a120 = max_angular_acceleration(generate(name, 480, 120.0, params))
        assert a120 < BOUND_ANY, (params, a120)
        assert a120 < 1.5 * a60 + 20.0, (params, a60, a120)


# -- ground contact ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_feet_stay_above_the_ground(name):
    rng = np.random.default_rng(3)
    for params in ({}, random_params(name, rng), random_params(name, rng)):
        low = sole_heights(generate(name, 200, 30.0, params)).min(axis=(1, 2))
        assert low.min() > -0.01, (params, low.min())
        if name not in ("jump", "run"):  # always standing on something
            assert low.max() < 0.01, (params, low.max())


def planted_speeds(motion, margin: float = 0.025) -> np.ndarray:
    """Horizontal speeds of each foot's lowest point while it is planted: below 2 mm for at
    least `margin` seconds on either side (lift-off and touch-down frames excluded)."""
    j = joints(motion)
    h = sole_heights(motion)
    points = [(J["left_ankle"], J["left_foot"]), (J["right_ankle"], J["right_foot"])]
    r = max(1, round(margin * motion.fps))
    out = []
    for k, pair in enumerate(points):
        planted = binary_erosion(h[:, k].min(-1) < 0.002, np.ones(2 * r + 1, bool))
        for f in np.flatnonzero(planted[:-1] & planted[1:]):
            p = pair[int(h[f, k, 1] < h[f, k, 0])]
            out.append(np.linalg.norm(j[f + 1, p, :2] - j[f, p, :2]) * motion.fps)
    return np.array(out)


@pytest.mark.parametrize(
    "name,speed",
    [("walk", 0.5), ("walk", 1.3), ("walk", 2.0), ("run", 2.0), ("run", 3.0), ("run", 4.5)],
)
def test_stance_foot_does_not_slide_and_body_advances(name, speed):
    m = generate(name, 960, 120.0, {"speed": speed, "direction": 30.0})
    slide = planted_speeds(m)
    assert slide.size > 0.1 * m.n_frames
    assert slide.max() < 0.05, slide.max()  # m/s
    travel = m.trans[-1, :2] - m.trans[0, :2]
    assert np.linalg.norm(travel) / m.duration == pytest.approx(speed, rel=0.02)
    # Walking direction follows `direction` (0 faces -y, 90 faces +x).
    assert np.degrees(np.arctan2(travel[0], -travel[1])) == pytest.approx(30.0, abs=1.0)
    assert np.degrees(heading(m)).mean() == pytest.approx(30.0, abs=2.0)
    # Each stride lifts the swing foot clear of the ground.
    assert sole_heights(m).min(-1).max() > 0.05


def test_walk_turns_at_the_requested_rate():
    m = generate("walk", 240, 30.0, {"turn": 20.0})
    turned = np.degrees(heading(m)[-1] - heading(m)[0])
    assert turned == pytest.approx(20.0 * m.duration, abs=6.0)  # pelvis yaw sways +-5 deg
    assert planted_speeds(generate("walk", 960, 120.0, {"turn": 20.0})).max() < 0.05


def joint_angle_deg(points: np.ndarray, a: str, at: str, b: str) -> np.ndarray:
    """The angle (deg) at joint `at` between the directions to joints `a` and `b`."""
    u = points[..., J[a], :] - points[..., J[at], :]
    w = points[..., J[b], :] - points[..., J[at], :]
    cos = np.sum(u * w, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(w, axis=-1)
    return np.degrees(np.arccos(cos))


def ankle_dorsiflexion_deg(motion, side: str) -> np.ndarray:
    """(F,) dorsiflexion from the joints alone: the rest angle between shin and foot (knee to
    ankle, ankle to ball) less the frame's."""
    names = (f"{side}_knee", f"{side}_ankle", f"{side}_foot")
    return joint_angle_deg(REFERENCE_REST_JOINTS, *names) - joint_angle_deg(joints(motion), *names)


def knee_flexion_deg(motion, side: str) -> np.ndarray:
    """(F,) the angle between thigh and shin (0 = straight), from the joints alone."""
    return 180.0 - joint_angle_deg(joints(motion), f"{side}_hip", f"{side}_knee", f"{side}_ankle")


def running_legs(speed: float):
    """(motion, side, that foot's lowest sole point above the ground (F,)) for each leg of a
    4 s run at `speed`, 120 fps, mirrored so that the right leg's plan is checked too."""
    m = generate("run", 480, 120.0, {"speed": speed}, mirror=True)
    h = sole_heights(m)
    return [(m, side, h[:, k].min(-1)) for k, side in enumerate(("left", "right"))]


@pytest.mark.parametrize("speed", [2.0, 3.0, 4.5])
def test_running_swing_ankle_stays_in_its_range(speed):
    # Running swing dorsiflexes the ankle 10-20 deg; the footstep plan's swing pitch on a knee
    # folded to 120 deg gave 37, 48 and 68 deg at these speeds, where Anny's foot sinks into
    # its shin (a trouser hem there was swallowed: docs/simulator.md, "The ankle").
    for m, side, sole in running_legs(speed):
        dorsi = ankle_dorsiflexion_deg(m, side)
        airborne = sole > 0.03
        assert airborne.sum() > 0.2 * m.n_frames
        assert dorsi[airborne].max() < 26.0, dorsi[airborne].max()
        assert dorsi[airborne].max() > 15.0  # the foot still comes up to clear the ground


@pytest.mark.parametrize("speed", [2.0, 3.0, 4.5])
def test_running_knees_are_a_runners(speed):
    # A runner's stance knee bends 40-50 deg at most and the swing knee folds to 90-120; the
    # old pelvis height (a bob about the lowest height the swing leg could reach its footstep
    # from) bent the stance knee to 59, 72 and 88 deg at these speeds (docs/simulator.md, "The
    # running gait"). Measured now: 54, 56 and 58; swing 105, 109 and 115.
    for m, side, sole in running_legs(speed):
        flexion = knee_flexion_deg(m, side)
        planted = sole < 0.002
        assert planted.sum() > 0.2 * m.n_frames
        assert flexion[planted].max() < 60.0, flexion[planted].max()
        assert 95.0 < flexion[~planted].max() < 120.0, flexion[~planted].max()


@pytest.mark.parametrize("speed", [2.0, 3.0, 4.5])
def test_running_flight_is_ballistic(speed):
    # Between a toe-off and the other foot's touch-down nothing but gravity acts on the body:
    # the pelvis (standing in for the centre of mass) falls at g. Before, it bobbed on a
    # sinusoid, whose flight curved at 2-4 m/s^2. Its rise and fall stay a runner's 5-10 cm.
    m = generate("run", 480, 120.0, {"speed": speed})
    airborne = (sole_heights(m).min(-1) > 0.006).all(-1)  # both feet clear of the ground
    z = m.trans[:, 2]
    curvature = (z[2:] - 2.0 * z[1:-1] + z[:-2]) * m.fps**2
    flight = airborne[:-2] & airborne[1:-1] & airborne[2:]
    assert flight.sum() > 0.05 * m.n_frames
    np.testing.assert_allclose(curvature[flight], -9.81, atol=0.05)
    assert 0.05 < z.max() - z.min() < 0.10, z.max() - z.min()
    # On the ground it only pushes, peaking at a runner's 2-3.5 body weights (measured 2.3-3.1).
    body_weights = (curvature + 9.81) / 9.81
    assert body_weights.min() > -1e-3 and 2.0 < body_weights.max() < 3.5, body_weights.max()


@pytest.mark.parametrize("speed", [0.8, 1.4, 2.0])
def test_walking_pelvis_pushes_like_a_walker(speed):
    # A walker's ground force stays within about 0.55-1.45 body weights, so the pelvis (standing
    # in for the centre of mass) accelerates vertically by at most about 0.45 g either way. The
    # vault over each stance leg alone kinked at every double support: 2 g upward at 1.8 m/s,
    # and the rounding onto the standing cap 1.5 g downward, which shook loose shirts off the
    # shoulders (docs/simulator.md, "The walk's double support"). It still rises and falls.
    m = generate("walk", 480, 120.0, {"speed": speed, "turn": 0.0})
    z = m.trans[:, 2]
    curvature = (z[2:] - 2.0 * z[1:-1] + z[:-2]) * m.fps**2
    assert np.abs(curvature).max() <= procedural.WALK_ACCELERATION_MAX + 0.05, np.abs(
        curvature).max()
    assert z.max() - z.min() > 0.005 + 0.02 * (speed - 0.8), z.max() - z.min()
    # The same heights at any frame rate: 30 fps samples every fourth frame of 120 fps.
    slow = generate("walk", 120, 30.0, {"speed": speed, "turn": 0.0})
    np.testing.assert_allclose(slow.trans[:, 2], z[::4][:120], atol=1e-9)


# -- jump and spin ----------------------------------------------------------------------------


@pytest.mark.parametrize("height", [0.05, 0.1, 0.2, 0.35])
def test_jump_is_ballistic_with_crouch_and_landing(height):
    fps = 240.0
    m = generate("jump", int(2.6 * fps), fps, {"height": height})
    low = sole_heights(m).min(axis=(1, 2))
    air = np.flatnonzero(low > 0.01)
    assert air.size > 0
    takeoff, touchdown = air[0], air[-1]
    assert np.all(np.diff(air) == 1)  # one flight per cycle
    # The lowest sole clears the ground by about the requested height.
    assert low.max() == pytest.approx(height, abs=0.02)
    # Root vertical acceleration in flight is -g.
    z = m.trans[:, 2]
    acc = np.diff(z, 2)[air[1:-1] - 1] * fps**2
    assert np.abs(acc + 9.81).max() < 0.5
    # Crouch before take-off, absorb after landing.
    stand = z[0]
    assert z[:takeoff].min() < stand - 0.1
    assert z[touchdown:].min() < stand - 0.08
    assert abs(z[-1] - stand) < 0.02  # and stand up again


# The corners of the jump's parameter box: tempo, amplitude (crouch depth, arm swing), height
# and distance at their extremes.
JUMP_CORNERS = [
    {"speed": s, "amplitude": a, "height": h, "distance": d}
    for s in (0.6, 1.6) for a in (0.5, 1.5) for h in (0.05, 0.2, 0.4) for d in (0.0, 0.8)
]


def test_jump_stays_within_the_accelerations_of_real_jumps():
    # Before, a shallow crouch before a long jump pushed for 73 ms and landed in 54 (6 and 12.7
    # body weights), the trunk's lean was keyed over the landing's 0.05-0.1 s (the neck at up to
    # 350 m/s^2, the head 420), the knees handed the take-off over to the heels in 5 ms (250 m/s^2)
    # and the arms swung through 225 degrees in 0.4 s and up to 165 degrees in a 0.2 s flight
    # (hands 310 m/s^2). CMU's jumps (13_11, 02_04, 01_01, 13_10; 40 ms box) peak at 32-39 m/s^2
    # at the pelvis, 42-63 at the neck, 43-79 at the head, 48-106 at the knees and 47-128 at the
    # hands (docs/simulator.md, "The jump's accelerations").
    fps = 120.0
    worst = {"neck": 0.0, "head": 0.0, "left_knee": 0.0, "left_hand": 0.0}
    for params in JUMP_CORNERS:
        k = procedural._jump_timeline(procedural.resolve_params("jump", params))
        m = generate("jump", int(k["period"] * fps) + 2, fps, params)
        x = joints(m)
        acc = np.linalg.norm((x[2:] - 2.0 * x[1:-1] + x[:-2]) * fps**2, axis=-1)
        t = np.arange(1, len(x) - 1) / fps
        force = np.linalg.norm((m.trans[2:] - 2.0 * m.trans[1:-1] + m.trans[:-2]) * fps**2
                               + [0.0, 0.0, 9.81], axis=-1) / 9.81
        push = (t > k["bottom"]) & (t < k["takeoff"])
        land = (t > k["touch"]) & (t < k["absorbed"])
        # The pelvis stands in for the centre of mass; the hips' shift back with the lean adds a
        # little to the landing.
        assert force[push].max() < procedural.JUMP_PUSH_FORCE_MAX + 0.1, (params, force[push].max())
        assert force[land].max() < procedural.JUMP_LANDING_FORCE_MAX + 0.3, (
            params, force[land].max())
        for name in worst:
            if name == "left_knee" and params["height"] < 0.1:
                continue  # a 5 cm hop's short flight still swings the knees at up to 220
            worst[name] = max(worst[name], float(acc[:, J[name]].max()))
    # Second differences at 120 fps without CMU's box: the knees of a long 0.4 m jump reaching
    # for the ground come to 145 (77 through the box).
    assert worst["neck"] < 50.0 and worst["head"] < 55.0, worst
    assert worst["left_knee"] < 150.0 and worst["left_hand"] < 200.0, worst


def test_jump_keeps_its_swing_where_the_keys_are_gentle():
    # The bounds on the trunk's and the arms' swing only shorten swings that the keys would make
    # too abrupt: keys within reach are kept exactly (the default jump's arms are as they
    # were), and a key out of reach moves only as far as the bounds need.
    times = [0.0, 0.3, 0.75, 1.1, 1.5, 2.0]
    gentle = np.radians([0.0, 0.0, -40.0, 110.0, 35.0, 0.0])
    np.testing.assert_array_equal(procedural._limited_keys(times, gentle, 150.0, 15.0), gentle)
    abrupt = procedural._limited_keys(times, 1.5 * gentle, 150.0, 15.0)
    dt, dv = np.diff(times), np.abs(np.diff(abrupt))
    assert np.all(dv * procedural._SMOOTHERSTEP_PEAK / dt**2 <= 150.0 + 1e-9)
    assert np.all(dv * 1.875 / dt <= 15.0 + 1e-9)
    assert abrupt[0] == 0.0 and abrupt[-1] == 0.0
    assert np.degrees(abrupt[3]) == pytest.approx(np.degrees(abrupt[2]) + np.degrees(
        15.0 * 0.35 / 1.875), abs=1e-6)  # the up-swing at the speed bound, from the back-swing
    k = procedural._jump_timeline(procedural.resolve_params("jump", {}))
    _, _, arm_times, arm = procedural._jump_swing_keys(k, 1.0, 0.0)
    np.testing.assert_array_equal(
        procedural._limited_keys(arm_times, arm, procedural.JUMP_ARM_ANGULAR_ACCELERATION_MAX,
                                 procedural.JUMP_ARM_ANGULAR_SPEED_MAX), arm)
    # Every bound is a function of the parameters, not of the sampling: 30 fps samples are every
    # fourth 120 fps sample.
    params = {"amplitude": 1.5, "distance": 0.8, "height": 0.05, "speed": 1.6}
    fast, slow = generate("jump", 240, 120.0, params), generate("jump", 60, 30.0, params)
    np.testing.assert_allclose(slow.poses, fast.poses[::4], atol=1e-9)
    np.testing.assert_allclose(slow.trans, fast.trans[::4], atol=1e-9)


def test_jump_forward_travels():
    m = generate("jump", 300, 30.0, {"distance": 0.5})
    period = procedural._jump_timeline(procedural.resolve_params("jump", {"distance": 0.5}))
    cycle = round(period["period"] * 30)
    assert m.trans[cycle, 1] - m.trans[0, 1] == pytest.approx(-0.5, abs=0.02)


@pytest.mark.parametrize("revs", [0.5, 1.0, 2.0, 2.5])
def test_spin_heading_advances_at_revs_per_second(revs):
    m = generate("spin", 121, 30.0, {"revs": revs, "direction": 40.0})
    turned = heading(m)[-1] - heading(m)[0]
    assert turned == pytest.approx(revs * m.duration * 2 * np.pi, rel=0.03)
    assert np.degrees(heading(m)[0]) == pytest.approx(40.0, abs=1.0)
    low = sole_heights(m).min(axis=(1, 2))
    assert low.min() > -0.01 and low.max() < 0.01
    assert np.ptp(m.trans[:, :2], axis=0).max() < 0.01  # in place


# -- mirroring, stance, speed -----------------------------------------------------------------


@pytest.mark.parametrize("name", ["walk", "kick", "wave", "spin"])
def test_mirror_is_the_left_right_mirror_image(name):
    a = generate(name, 60, 30.0)
    b = generate(name, 60, 30.0, mirror=True)
    np.testing.assert_allclose(b.poses, mirror_poses(a.poses), atol=1e-12)
    np.testing.assert_allclose(b.trans, a.trans * [-1.0, 1.0, 1.0])
    # Geometrically: joints swap sides and x flips.
    ja, jb = joints(a), joints(b)
    np.testing.assert_allclose(jb, ja[:, list(MIRROR)] * [-1.0, 1.0, 1.0], atol=1e-9)


def test_side_parameter_swaps_the_limb():
    right = joints(generate("kick", 60, 30.0, {"side": 0.0}))
    left = joints(generate("kick", 60, 30.0, {"side": 1.0}))
    assert right[:, J["right_ankle"], 2].max() > 0.5 > right[:, J["left_ankle"], 2].max()
    assert left[:, J["left_ankle"], 2].max() > 0.5 > left[:, J["right_ankle"], 2].max()
    wave_r = joints(generate("wave", 60, 30.0, {"side": 0.2}))
    assert wave_r[-1, J["right_wrist"], 2] > wave_r[-1, J["head"], 2]


def arm_angles(j: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Upper-arm angle from straight down and elbow flexion, degrees."""
    sh, el, wr = (j[:, J[f"{side}_{n}"]] for n in ("shoulder", "elbow", "wrist"))
    upper, fore = el - sh, wr - el
    down = np.degrees(np.arccos(-upper[:, 2] / np.linalg.norm(upper, axis=1)))
    cos = (
        np.einsum("fi,fi->f", upper, fore)
        / np.linalg.norm(upper, axis=1)
        / np.linalg.norm(fore, axis=1)
    )
    return down, np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.mark.parametrize("name", sorted(ACTIONS))
def test_natural_stance_not_t_pose(name):
    m = generate(name, 150, 30.0)
    j = joints(m)
    for side in ("left", "right"):
        down, elbow = arm_angles(j, side)
        if name not in ("spin", "dance", "run"):  # these start mid-motion with arms bent
            assert 20 < down[0] < 40 and 8 < elbow[0] < 25  # hanging, clear of the torso
        # Never a T-pose (arms horizontal and straight), except passing through it in a raise.
        t_pose = (np.abs(down - 90) < 12) & (elbow < 12)
        if name != "arm_raise":
            assert not t_pose.any()
    # Legs slightly apart, upright, knees within anatomical range.
    apart = np.linalg.norm(j[:, J["left_ankle"], :2] - j[:, J["right_ankle"], :2], axis=1)
    assert apart[0] > 0.15
    assert (j[:, J["head"], 2] - j[:, J["pelvis"], 2]).min() > 0.45
    knee = np.degrees(Rotation.from_rotvec(m.poses[:, 3 * J["left_knee"] :][:, :3]).magnitude())
    assert knee.max() < 140


def test_hands_clear_the_torso_in_the_rest_stance():
    j = joints(generate("idle", 90, 30.0))
    for side in ("left", "right"):
        for part in ("elbow", "wrist"):
            lateral = np.abs(j[:, J[f"{side}_{part}"], 0] - j[:, J["pelvis"], 0])
            assert lateral.min() > 0.25  # hips of heavy bodies reach ~0.2 m from the midline


def test_generating_300_frames_is_fast():
    """Generating 300 frames of an action costs at most 20 times the forward kinematics of the
    frames it made (the body stage's first step), measured in the same run: 2.7-4.6 times on
    2 cores (20-27 ms against 5-8 ms). The median of three of each, as the machine is shared
    (benchmarks.common.timed)."""
    from functools import partial

    from benchmarks.common import timed

    for name in sorted(ACTIONS):
        params = random_params(name, np.random.default_rng(5))
        motion = generate(name, 300, 30.0, params)
        ours, _ = timed(partial(generate, name, 300, 30.0, params))
        peer, _ = timed(partial(forward_kinematics, motion.poses, motion.trans,
                                REFERENCE_REST_JOINTS))
        assert ours < 20 * peer, f"{name}: {ours * 1e3:.1f} ms, its kinematics {peer * 1e3:.1f} ms"
