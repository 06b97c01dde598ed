"""The folding parts' distance fields (datagen.sim.fold_fields): frames, values, blob layout."""

import numpy as np
import taichi as ti
from scipy.spatial.transform import Rotation

from datagen.sim import fold_fields as FF
from datagen.sim import kernel_common as KC
from datagen.sim import search_kernels as SK
from datagen.sim.precision import NP_REAL, REAL, VEC3
from datagen.sim.scenes import icosphere


@ti.kernel
def _look_up(points: KC.V3, part: REAL, normal: VEC3, s_frame: REAL, fold: KC.F1, reach: REAL,
             out: KC.V3):
    """search_kernels.fold_near at each point, as the part guard asks it of a tracked vertex.
    (Taichi reads the annotations: this module has no `from __future__ import annotations`.)"""
    for i in points:
        out[i] = SK.fold_near(points[i], part, normal, s_frame, fold, 0, reach, VEC3(0.0))


def _ball_and_plate(n_frames: int = 8):
    """A 10 cm ball (part 0) turning 6 degrees a frame about z and moving 3 cm a frame along
    x, over a static square plate (part 1) 40 cm wide at z = 0."""
    bv, bf = icosphere(0.1, subdivisions=3)
    pv = np.array([[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.2, 0.2, 0.0], [-0.2, 0.2, 0.0]])
    pf = np.array([[0, 1, 2], [0, 2, 3]])
    centres = np.array([[0.03 * f, 0.0, 0.25] for f in range(n_frames)])
    rots = [Rotation.from_euler("z", 6.0 * f, degrees=True) for f in range(n_frames)]
    frames = np.array([np.concatenate([rots[f].apply(bv) + centres[f], pv])
                       for f in range(n_frames)])
    faces = np.concatenate([bf, pf + len(bv)])
    parts = np.r_[np.zeros(len(bf), int), np.ones(len(pf), int)]
    return frames, faces, parts, centres, rots


def test_fields_run_in_and_just_before_the_fold_frames_only():
    frames, faces, parts, *_ = _ball_and_plate()
    fields = FF.FoldFields(frames, faces, parts, [(("ball",), ("plate",), frozenset({5}))],
                           {"ball": 0, "plate": 1})
    active = [f0 for f0 in range(7) if fields.blob(f0, f0 + 1) is not None]
    # FOLD_LEAD_FRAMES (2) frames before the fold frame 5, and the frame that ends in it.
    assert active == [2, 3, 4, 5]


def test_a_fields_values_are_the_distance_to_its_part_in_the_parts_own_frame():
    frames, faces, parts, centres, rots = _ball_and_plate()
    fields = FF.FoldFields(frames, faces, parts, [(("ball",), ("plate",), frozenset({4}))],
                           {"ball": 0, "plate": 1})
    blob = fields.blob(3, 4)
    assert blob[FF.B_N] == 2
    # Each part's partners are the other side's fields, its own slot its own field.
    assert FF.read_partners(blob, 0) == [1] and FF.read_partners(blob, 1) == [0]
    assert FF.read_own(blob, 0) == 0 and FF.read_own(blob, 1) == 1
    h = FF.header(blob, 0)  # the ball's
    assert blob[h + FF.H_PART] == 0
    # The frame's two ends: the ball's rotation since the first frame, its centre, its motion.
    for q_at, c_at, f in ((FF.H_Q0, FF.H_C0, 3), (FF.H_Q1, FF.H_C1, 4)):
        w, x, y, z = blob[h + q_at:h + q_at + 4]
        assert Rotation.from_quat([x, y, z, w]).approx_equal(rots[f], atol=1e-6)
        np.testing.assert_allclose(blob[h + c_at:h + c_at + 3], centres[f], atol=1e-3)
    np.testing.assert_allclose(blob[h + FF.H_SHIFT:h + FF.H_SHIFT + 3], [0.03, 0.0, 0.0],
                               atol=1e-6)
    # Turning 6 degrees about its centre moves the ball's equator 2 sin(3 deg) x 10 cm.
    assert abs(blob[h + FF.H_TRAVEL] - 0.2 * np.sin(np.radians(3.0))) < 1e-3
    # The values: grid points' signed distance to the ball (negative inside), both ends side by
    # side; the ball in its own frame is the same ball, so both ends agree.
    dims = blob[h + FF.H_DIMS:h + FF.H_DIMS + 3].astype(int)
    origin = blob[h + FF.H_ORIGIN:h + FF.H_ORIGIN + 3] * FF.FIELD_CELL  # stored in cells
    data = blob[int(blob[h + FF.H_DATA]):][:2 * dims.prod()].reshape(*dims, 2)
    axes = [origin[d] + np.arange(dims[d]) / blob[h + FF.H_INV_CELL] for d in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    exact = np.linalg.norm(grid, axis=-1) - 0.1
    near = np.abs(exact) < 0.03
    assert np.abs(data[..., 0][near] - exact[near]).max() < 2e-3  # the mesh is not a sphere
    np.testing.assert_allclose(data[..., 0], data[..., 1], atol=1e-5)
    # The grid reaches FIELD_MARGIN beyond the ball on every side.
    assert origin.max() <= -0.1 - FF.FIELD_MARGIN + 1e-9


def test_a_frame_carries_the_fields_of_the_joints_folding_in_it_only():
    """A running arm's elbows fold in most frames and its hips in a few: the legs' fields are
    sampled and looked up only where the hips fold. Here the ball folds onto the plate at frame
    6 and onto a second plate (part 2) at frame 3: a frame's blob lists the parts of the joints
    folding in it or just after it, with partners and own slots of those alone."""
    frames, faces, parts, *_ = _ball_and_plate()
    second = frames[:, -4:] + np.array([0.0, 0.0, 0.5])
    frames = np.concatenate([frames, second], axis=1)
    faces = np.concatenate([faces, faces[-2:] + 4])
    parts = np.r_[parts, 2, 2]
    names = {"ball": 0, "plate": 1, "lid": 2}
    fields = FF.FoldFields(frames, faces, parts,
                           [(("ball",), ("plate",), frozenset({6})),
                            (("ball",), ("lid",), frozenset({3}))], names)

    def slots(f0):
        blob = fields.blob(f0, f0 + 1)
        if blob is None:
            return None
        n = int(blob[FF.B_N])
        return [int(blob[FF.header(blob, k) + FF.H_PART]) for k in range(n)], blob

    # A frame f0 -> f0 + 1 carries a joint folding at f0 to f0 + 1 + FOLD_LEAD_FRAMES.
    assert slots(0)[0] == [0, 2] and slots(2)[0] == [0, 2]
    assert slots(3)[0] == [0, 1, 2]  # in the lid's fold and leading into the plate's
    assert slots(4)[0] == [0, 1] and slots(6)[0] == [0, 1]
    order, blob = slots(4)
    # The ball's partner is the plate's slot (1), the plate's the ball's (0); the lid, not
    # folding, has neither partners nor a slot, and no table entry at all.
    assert FF.read_partners(blob, 0) == [1] and FF.read_partners(blob, 1) == [0]
    assert FF.read_partners(blob, 2) == [] and FF.read_own(blob, 2) is None
    assert blob[FF.B_SLOTS] == 2
    assert FF.read_own(blob, 0) == 0 and FF.read_own(blob, 1) == 1
    # In frame 3 the ball folds onto both: its partners are the plate's and the lid's slots.
    assert FF.read_partners(slots(3)[1], 0) == [1, 2]


def test_a_fields_grid_holds_its_part_with_the_margin_in_every_frame_a_blob_samples():
    """A lookup outside a field's grid reads the part as at least FIELD_MARGIN away, which
    holds only where the part lies that far inside the grid in every frame a blob samples,
    the frame's end included: the last frame f0 -> f0 + 1 that carries a fold at frame g ends
    at g + 1. A ball that grows by a fifth of its radius a frame (as skinning swells a part
    about the joint) folding at frame 4: its grid once left out frame 5's ball, which then lay
    1.5 cm inside the grid's edge instead of 3.5."""
    frames, faces, parts, centres, rots = _ball_and_plate()
    n_ball = len(frames[0]) - 4
    for f in range(len(frames)):
        local = frames[f, :n_ball] - centres[f]
        frames[f, :n_ball] = local * (1.0 + 0.2 * f) + centres[f]
    fields = FF.FoldFields(frames, faces, parts, [(("ball",), ("plate",), frozenset({4}))],
                           {"ball": 0, "plate": 1})
    sampled = 0
    for f0 in range(len(frames) - 1):
        blob = fields.blob(f0, f0 + 1)
        if blob is None:
            continue
        h = FF.header(blob, 0)  # the ball's
        origin = blob[h + FF.H_ORIGIN:h + FF.H_ORIGIN + 3] * FF.FIELD_CELL
        top = origin + (blob[h + FF.H_DIMS:h + FF.H_DIMS + 3] - 1) * FF.FIELD_CELL
        for f in (f0, f0 + 1):
            local = fields._fit(0, f)[2]
            assert np.all(local.min(axis=0) >= origin + FF.FIELD_MARGIN - 1e-9), (f0, f)
            assert np.all(local.max(axis=0) <= top - FF.FIELD_MARGIN + 1e-9), (f0, f)
            sampled += 1
    assert sampled == 8  # f0 = 1 .. 4, both ends


def test_a_frames_fields_do_not_depend_on_folds_later_in_the_sequence():
    """A part's grid spans every frame it is sampled in, so a fold later in the sequence
    widens it. The grid lies on the FIELD_CELL lattice in the part's frame (its first point
    stored in whole cells): a frame's grid points, and so its values, are the same bit for bit
    whether or not the sequence goes on to that fold, and a sequence cut short simulates as
    the long one's prefix. Here the ball folds at frame 3, and in the long sequence again at
    frame 7, where it has swollen by 40 % (as skinning swells a part about its joint)."""
    frames, faces, parts, centres, _ = _ball_and_plate(10)
    n_ball = len(frames[0]) - 4
    for f in (6, 7, 8, 9):
        frames[f, :n_ball] = (frames[f, :n_ball] - centres[f]) * 1.4 + centres[f]
    names = {"ball": 0, "plate": 1}
    short = FF.FoldFields(frames[:6], faces, parts, [(("ball",), ("plate",), frozenset({3}))],
                          names)
    long = FF.FoldFields(frames, faces, parts, [(("ball",), ("plate",), frozenset({3, 7}))],
                         names)

    def grid(fields, f0):
        blob = fields.blob(f0, f0 + 1)
        h = FF.header(blob, 0)  # the ball's
        first = blob[h + FF.H_ORIGIN:h + FF.H_ORIGIN + 3]
        dims = blob[h + FF.H_DIMS:h + FF.H_DIMS + 3].astype(int)
        data = blob[int(blob[h + FF.H_DATA]):][:2 * dims.prod()].reshape(*dims, 2)
        return first.astype(int), dims, data

    for f0 in (1, 2, 3):
        first_s, dims_s, data_s = grid(short, f0)
        first_l, dims_l, data_l = grid(long, f0)
        assert np.all(first_l <= first_s) and np.all(first_l + dims_l >= first_s + dims_s)
        assert np.any(dims_l > dims_s)  # the swollen ball widened the long sequence's grid
        at = first_s - first_l  # the short grid's points in the long one
        inner = data_l[at[0]:at[0] + dims_s[0], at[1]:at[1] + dims_s[1], at[2]:at[2] + dims_s[2]]
        np.testing.assert_array_equal(inner, data_s)

    # The guard's lookup (search_kernels.fold_near) for a vertex on the plate: whether the ball's
    # facing surface is near, and where it is not, how much farther it is. Inside the short
    # grid both answers agree bit for bit; beyond it the long grid reads the distance where
    # the short one bounds it, but neither finds the ball there.
    from datagen.sim.backend import init_taichi

    init_taichi()
    rng = np.random.default_rng(7)
    rot, centre, _ = short._fit(0, 2)  # the ball's frame at frame 2, where s_frame is 0
    local = rng.uniform(-0.2, 0.2, (4000, 3))
    points = (centre + local @ rot.T).astype(NP_REAL)
    answers = []
    for fields in (short, long):
        blob = fields.blob(2, 3).astype(NP_REAL)
        fold, at, out = ti.ndarray(REAL, len(blob)), ti.ndarray(VEC3, len(points)), (
            ti.ndarray(VEC3, len(points)))
        fold.from_numpy(blob)
        at.from_numpy(points)
        _look_up(at, 1.0, ti.math.vec3(0.0, 0.0, 1.0), 0.0, fold, 0.025, out)
        answers.append(out.to_numpy())
    (found_s, budget_s, _), (found_l, budget_l, _) = (a.T for a in answers)
    np.testing.assert_array_equal(found_s, found_l)
    assert 50 < found_s.sum() < len(points) / 2  # the ball's underside is near some of them
    first, dims, _ = grid(short, 2)
    cells = np.floor(local / FF.FIELD_CELL) - first
    inside = np.all((cells >= 0) & (cells < dims - 1), axis=1)
    assert inside.sum() > len(points) / 4
    np.testing.assert_array_equal(budget_s[inside], budget_l[inside])
