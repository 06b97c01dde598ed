"""Each cloth vertex's closest collider triangle: a search of the grid's cells around it, guarded
so that a vertex is searched again only once it or the body may have moved far enough, and the
folding parts' fields (datagen.sim.fold_fields) that catch a part closing onto cloth."""

import taichi as ti

from datagen.sim import fold_fields as FF
from datagen.sim.grid_kernels import T_PART, grid_cell, scanned_first
from datagen.sim.kernel_common import (
    F1,
    G_ODO,
    G_OTHER,
    G_SPEED,
    G_TAG,
    G_TIME,
    GUARD,
    I1,
    I3,
    V3,
    V8,
    closest_on_triangle,
    lerp3,
    vec3,
)
from datagen.sim.precision import REAL

# Another body part counts as a facing surface when its triangle's normal is more than 60
# degrees from the tracked triangle's (the forearm folding onto the upper arm, the arm passing
# the torso; not the next part along a limb, whose triangles at the joint are aligned).
FACING_COS = 0.5
# A tracked vertex is searched again once a facing surface of another part may have come this
# close (m): before it can reach the contact band of any built-in fabric (2 x 4 mm of cotton).
OTHER_SURFACE_ZONE = 0.008
# G_OTHER's distance part when no facing surface of another part was within the searched cell
# (a cell, GRID_CELL, is far below it: the guard packs the distance after the part's integer).
OTHER_NONE = 0.75
# A folding part's field (fold_near) counts a vertex this deep inside it as caught by it: deeper
# is the body's own overlap at the joint, where no search decides better.
FOLD_DEPTH = 0.03
# ...and searches it once the field puts a folding part's facing surface this much within a
# cell (the search's reach, where other_surface finds it): a margin for the field's error.
FOLD_TRIGGER = 0.005
# A folding part traps cloth closing face to face onto it (a thigh's underside onto the calf,
# its front onto the belly): the lookup counts its surface where the normals are more than 107
# degrees apart. Where the two meet at about a right angle (the crease at the hip) the part
# guard's own search of the cell sees it; searching there at the lookup's word as well (with
# FACING_COS) strained the fast kick's crotch, 0.36 % of its edges over their bound at 20x4.
FOLD_FACING_COS = -0.3

# Which cloth vertices a closest-triangle search visits (nearest_one's `which`). The frames'
# full searches visit only the tracked ones: an untracked vertex is searched at every substep
# anyway, unless its guard proves it far (visiting the untracked too was half of a walking
# t-shirt's full search, which runs every fifth frame).
SEARCH_ALL = 0
SEARCH_UNTRACKED = 1
SEARCH_TRACKED = 2


@ti.func
def nearest_one(
    i: ti.i32,
    x: V3,
    w: F1,
    b0: V3,
    b1: V3,
    faces: I3,
    origin: vec3,
    inv_cell: REAL,
    dims: ti.math.ivec3,
    starts: I1,
    items: I1,
    s: REAL,
    max_dist: REAL,
    tri: I1,
    which: ti.i32,
    guard: V8,
    odo: REAL,
    grid_tag: REAL,
    s_frame: REAL,
    shift: vec3,
    tbox: V8,
    fold: F1,
    fold_at: ti.i32,
):
    """The closest collider triangle to cloth vertex i within `max_dist` (else -1), at body
    positions interpolated at fraction s, searching the 27 grid cells around the vertex (in the
    grid's coordinates, which move with the body's mean motion over the frame, `shift`: the
    vertex at p - shift s_frame; count_triangle). `which` vertices are searched (SEARCH_ALL,
    SEARCH_UNTRACKED or SEARCH_TRACKED; the others keep their triangle or none). With
    SEARCH_UNTRACKED, a vertex whose last search found nothing is not searched again while it
    provably cannot be near: that search showed no triangle within `max_dist` of guard.xyz,
    and since then
    - the vertex has moved |x - guard.xyz| and the triangles at most |odo - guard.odo|, `odo`
      bounding how far the body's fastest vertex has travelled (its path's speed bound per
      frame, summed); or,
    - the grid is still the one searched (guard.tag == grid_tag; grids are numbered and the
      numbers never repeat). It holds each triangle's box swept over the whole frame, so while
      the vertex stays within half of `max_dist` of where it was searched in the grid's
      coordinates, which move with the body's mean motion over the frame (`shift`), only the
      searched cells' triangles can come near, and they can close in by no more than the
      vertex's and their own motion relative to that mean motion: the vertex's
      |x - guard.xyz - shift * (s_frame - guard.time)|, theirs the fastest corner's speed
      relative to that mean motion (a bound over its path within the frame,
      collider.path_bounds, kept per triangle in `tbox` with its box: grid_count) times the
      frame fraction since. `s_frame` is the fraction of the frame the body is at.
    The odometer counts the fastest limb, and on a walking body it had every loose vertex
    searched again at almost every substep: half of an xpbd frame. Cloth near the torso moves
    with it, so the local, relative bound holds for several substeps (in world coordinates the
    cloth left the searched cells within a third of a frame, and a fifth of the loose vertices
    were searched again at every substep).

    A tracked vertex follows its triangle's surface, and another body part closing in is not
    on that surface: a sleeve in the elbow's crook, 15-40 mm from the upper arm it tracked, was
    swallowed whole by the forearm folding onto it (the two overlap there), and the sleeve's
    edges then crossed the forearm. So where the collider has parts (T_PART), a search that
    finds a triangle also measures how near the nearest facing triangle of another part is,
    within the cell (`other_surface`), and keeps it in the guard (G_OTHER). Where there is
    one, SEARCH_UNTRACKED searches the tracked vertex again once the same two proofs, with that
    distance less OTHER_SURFACE_ZONE as the budget, no longer show it farther than the zone,
    and at once when its triangle is now of another part (a walk across the joint), so the
    vertex tracks the other surface before it can pass. A vertex with no facing surface within
    the cell is not guarded in general: it waits for the frames' full search
    (SimOptions.search_every), and a surface that comes from beyond the cell faster than that
    can still pass it (guarding those too, against the odometer or the local bound, searched a
    walking t-shirt's tracked vertices again several times a frame: 50 % more time). Where the
    body folds across a joint (the body stage's flexion frames, hip, knee, elbow: `fold`, the
    fold fields from fold[fold_at], none where fold_at < 0 or they are empty), such a vertex
    looks the parts folding onto its own up in their distance fields (fold_near) and is searched
    once one closing face to face is within the cell; between lookups it keeps, in its guard
    (G_SPEED < 0), how much farther they were and how fast they can close in, and is not looked
    up again while that holds.
    """
    clear = False  # an untracked vertex provably far: not searched
    again = False  # a tracked vertex that another part may have come near: searched
    if w[i] > 0.0 and which == SEARCH_UNTRACKED:
        g = guard[i]
        if tri[i] < 0:
            # A tracked vertex's guard (G_OTHER > 0) proves nothing once it is released.
            budget = 0.5 * max_dist if g[G_OTHER] == 0.0 else -1.0
            clear = guard_holds(x[i], g, budget, budget, odo, grid_tag, s_frame, shift)
        elif g[G_OTHER] > 0.0:
            part = ti.floor(g[G_OTHER])
            other = g[G_OTHER] - part
            budget = other - OTHER_SURFACE_ZONE
            if part - 1.0 != tbox[tri[i]][T_PART]:
                budget = -1.0  # the walk crossed to another part: what faces it is unknown
            if other < OTHER_NONE or budget < 0.0:
                # The searched cells must hold what can come within the budget: the vertex
                # stays within max_dist - budget of where it was searched.
                again = not guard_holds(x[i], g, budget, max_dist - budget, odo, grid_tag,
                                        s_frame, shift)
            elif fold_at >= 0 and fold[fold_at + FF.B_N] > 0.0:
                # Nothing faced it within a cell when searched, but a part folding onto its
                # own may have come from farther since (fold_near), unless its last lookup
                # still shows it farther than a cell.
                n_slots = ti.cast(fold[fold_at + FF.B_SLOTS], ti.i32)
                p_own = ti.cast(part - 1.0, ti.i32)
                own = -1
                if p_own < n_slots:
                    own = ti.cast(fold[fold_at + FF.B_TABLES + FF.T_OWN * n_slots + p_own],
                                  ti.i32) - 1
                if own >= 0:
                    oh = fold_at + FF.B_TABLES + 3 * n_slots + FF.HEADER * own
                    own_shift = vec3(fold[oh + FF.H_SHIFT], fold[oh + FF.H_SHIFT + 1],
                                     fold[oh + FF.H_SHIFT + 2])
                    held = False
                    if g[G_SPEED] < 0.0 and g[G_TAG] == grid_tag:
                        since = s_frame - g[G_TIME]
                        closing = ((x[i] - vec3(g[0], g[1], g[2]) - own_shift * since).norm()
                                   + g[G_ODO] * ti.abs(since))
                        held = closing < -1.0 - g[G_SPEED]
                    if not held:
                        f = faces[tri[i]]
                        a = lerp3(b0[f[0]], b1[f[0]], s)
                        nb = (lerp3(b0[f[1]], b1[f[1]], s) - a).cross(
                            lerp3(b0[f[2]], b1[f[2]], s) - a)
                        r = fold_near(x[i], part - 1.0, nb, s_frame, fold, fold_at, max_dist,
                                      own_shift)
                        if r[0] > 0.0:
                            again = True
                        else:
                            p = x[i]
                            guard[i] = GUARD(p[0], p[1], p[2], r[2], grid_tag, s_frame,
                                             -1.0 - r[1], g[G_OTHER])
    searched = which == SEARCH_ALL or (which == SEARCH_UNTRACKED) == (tri[i] < 0) or again
    if w[i] > 0.0 and searched and not clear:
        p = x[i]
        p_grid = p - shift * s_frame  # in the grid's coordinates (count_triangle)
        cell = ti.cast(ti.floor((p_grid - origin) * inv_cell), ti.i32)
        best = max_dist * max_dist
        # A triangle whose box is farther than the best so far is not measured: the same
        # triangle wins as when every one is (a 1 um margin covers rounding). Most searches
        # find nothing within max_dist (cloth away from the body) and measured every triangle
        # of 27 cells: a third of a walking t-shirt's substep.
        bound = (max_dist + 1e-6) * (max_dist + 1e-6)
        best_t = -1
        fastest = ti.cast(0.0, REAL)
        for nb in range(27):  # a dynamic loop: unrolling 27 copies makes compiles slow
            c = cell + ti.math.ivec3(nb // 9 - 1, (nb // 3) % 3 - 1, nb % 3 - 1)
            cid = grid_cell(c, dims)
            if cid >= 0:
                for q in range(starts[cid], starts[cid + 1]):
                    t = items[q]
                    tb = tbox[t]
                    fastest = ti.max(fastest, tb[6])
                    # The box swept over the frame holds the one at s: a triangle whose swept
                    # box is beyond the bound is culled without reading its corners (most
                    # are: the same ones are measured, in the same order, as without it).
                    swept = ti.max(vec3(tb[0], tb[1], tb[2]) - p_grid, 0.0,
                                   p_grid - vec3(tb[3], tb[4], tb[5]))
                    # A triangle filed in several of the 27 cells is measured in the first
                    # one scanned (the lowest corner of its cells within the block): the same
                    # triangles in the same order as measuring every copy, without repeating
                    # a near one's closest point up to eight times.
                    first = scanned_first(c, cell - 1, vec3(tb[0], tb[1], tb[2]), origin,
                                          inv_cell)
                    if first and swept.norm_sqr() <= bound:
                        f = faces[t]
                        a = lerp3(b0[f[0]], b1[f[0]], s)
                        b = lerp3(b0[f[1]], b1[f[1]], s)
                        cc = lerp3(b0[f[2]], b1[f[2]], s)
                        box = ti.max(ti.min(a, b, cc) - p, 0.0, p - ti.max(a, b, cc))
                        if box.norm_sqr() <= bound:
                            r = closest_on_triangle(p, a, b, cc)
                            # Of equally near triangles a dense grid keeps the first scanned; a
                            # hashed one scans in another order, so it keeps the lowest index.
                            if r[3] < best or (dims[0] == 0 and r[3] == best and t < best_t):
                                best = r[3]
                                best_t = t
                                reach = ti.sqrt(best) + 1e-6
                                bound = reach * reach
        tri[i] = best_t
        if best_t < 0:
            guard[i] = GUARD(p[0], p[1], p[2], odo, grid_tag, s_frame, fastest, 0.0)
        elif tbox[best_t][T_PART] >= 0.0:
            part = tbox[best_t][T_PART]
            other = other_surface(p, p_grid, best_t, part, b0, b1, faces, origin, inv_cell,
                                  dims, starts, items, s, max_dist, tbox,
                                  which == SEARCH_TRACKED)
            guard[i] = GUARD(p[0], p[1], p[2], odo, grid_tag, s_frame, fastest,
                             1.0 + part + other)


@ti.func
def quat_matrix(q: ti.math.vec4) -> ti.types.matrix(3, 3, REAL):
    """The rotation of a unit quaternion (w, x, y, z)."""
    w, a, b, c = q[0], q[1], q[2], q[3]
    return ti.Matrix([
        [1.0 - 2.0 * (b * b + c * c), 2.0 * (a * b - c * w), 2.0 * (a * c + b * w)],
        [2.0 * (a * b + c * w), 1.0 - 2.0 * (a * a + c * c), 2.0 * (b * c - a * w)],
        [2.0 * (a * c - b * w), 2.0 * (b * c + a * w), 1.0 - 2.0 * (a * a + b * b)],
    ], dt=REAL)


@ti.func
def fold_near(p: vec3, part: REAL, nb: vec3, s_frame: REAL, fold: F1, at: ti.i32,
              reach: REAL, own_shift: vec3) -> vec3:
    """Whether the surface of a body part that folds onto `part` in this frame (the fold
    fields, datagen.sim.fold_fields, from fold[at]) is within FOLD_TRIGGER of `reach` of p
    and faces the tracked triangle's normal nb (FOLD_FACING_COS), or has p inside it by less than
    FOLD_DEPTH: one transform into the part's own frame, interpolated at the frame fraction
    s_frame, and one trilinear lookup per folding part. Returned as (found, budget, speed):
    found 1 or 0; else how much farther than that the folding parts are (negative where one is
    near but not facing), and how fast (per frame) they can close in on a vertex that moves
    with its own part (`own_shift`, its centre's motion over the frame): the differences of
    their centres' motions from it plus their vertices' travel about their centres."""
    found = 0
    budget = ti.cast(1.0, REAL)
    speed = ti.cast(0.0, REAL)
    n_slots = ti.cast(fold[at + FF.B_SLOTS], ti.i32)
    index = ti.cast(part, ti.i32)
    bits = 0  # the slots folding onto the part, from its scene's first (`base`)
    base = 0
    if index < n_slots:
        bits = ti.cast(fold[at + FF.B_TABLES + FF.T_PARTNERS * n_slots + index], ti.i32)
        base = ti.cast(fold[at + FF.B_TABLES + FF.T_BASE * n_slots + index], ti.i32)
    for k in range(FF.MAX_FIELDS):
        if found != 0 or bits >> k == 0:
            break
        if (bits >> k) & 1 != 0:
            h = at + FF.B_TABLES + 3 * n_slots + FF.HEADER * (base + k)  # FF.fields_at
            shift = vec3(fold[h + FF.H_SHIFT], fold[h + FF.H_SHIFT + 1],
                         fold[h + FF.H_SHIFT + 2])
            speed = ti.max(speed, (shift - own_shift).norm() + fold[h + FF.H_TRAVEL])
            q0 = ti.math.vec4(fold[h + FF.H_Q0], fold[h + FF.H_Q0 + 1], fold[h + FF.H_Q0 + 2],
                              fold[h + FF.H_Q0 + 3])
            q1 = ti.math.vec4(fold[h + FF.H_Q1], fold[h + FF.H_Q1 + 1], fold[h + FF.H_Q1 + 2],
                              fold[h + FF.H_Q1 + 3])
            q = q0 + (q1 - q0) * s_frame
            rot = quat_matrix(q / q.norm())
            c = vec3(fold[h + FF.H_C0], fold[h + FF.H_C0 + 1], fold[h + FF.H_C0 + 2])
            c = c + (vec3(fold[h + FF.H_C1], fold[h + FF.H_C1 + 1], fold[h + FF.H_C1 + 2])
                     - c) * s_frame
            y = rot.transpose() @ (p - c)
            # Lattice coordinates first, the grid's first point subtracted in integers: the
            # cell and its weights t are the same however far the grid reaches.
            lattice = y * fold[h + FF.H_INV_CELL]
            cell = ti.cast(ti.floor(lattice), ti.i32)
            first = ti.math.ivec3(ti.cast(fold[h + FF.H_ORIGIN], ti.i32),
                                  ti.cast(fold[h + FF.H_ORIGIN + 1], ti.i32),
                                  ti.cast(fold[h + FF.H_ORIGIN + 2], ti.i32))
            i0 = cell - first
            g = lattice - ti.cast(first, REAL)
            nx = ti.cast(fold[h + FF.H_DIMS], ti.i32)
            ny = ti.cast(fold[h + FF.H_DIMS + 1], ti.i32)
            nz = ti.cast(fold[h + FF.H_DIMS + 2], ti.i32)
            top = vec3(ti.cast(nx - 1, REAL), ti.cast(ny - 1, REAL), ti.cast(nz - 1, REAL))
            if (i0[0] < 0 or i0[0] >= nx - 1 or i0[1] < 0 or i0[1] >= ny - 1
                    or i0[2] < 0 or i0[2] >= nz - 1):
                # Outside the grid: the part is FIELD_MARGIN inside it in every frame sampled.
                out = ti.max(-g, 0.0, g - top).norm() / fold[h + FF.H_INV_CELL]
                budget = ti.min(budget, out + FF.FIELD_MARGIN - reach + FOLD_TRIGGER)
            else:
                t = lattice - ti.cast(cell, REAL)
                data = at + ti.cast(fold[h + FF.H_DATA], ti.i32)
                d = ti.cast(0.0, REAL)
                grad = vec3(0.0)
                for corner in ti.static(range(8)):
                    dx, dy, dz = corner >> 2, (corner >> 1) & 1, corner & 1
                    cid = ((i0[0] + dx) * ny + i0[1] + dy) * nz + i0[2] + dz
                    v0 = fold[data + 2 * cid]
                    val = v0 + (fold[data + 2 * cid + 1] - v0) * s_frame
                    wx = dx * t[0] + (1 - dx) * (1.0 - t[0])
                    wy = dy * t[1] + (1 - dy) * (1.0 - t[1])
                    wz = dz * t[2] + (1 - dz) * (1.0 - t[2])
                    d += wx * wy * wz * val
                    grad += val * vec3((2 * dx - 1) * wy * wz, (2 * dy - 1) * wx * wz,
                                       (2 * dz - 1) * wx * wy)
                budget = ti.min(budget, d - reach + FOLD_TRIGGER)
                if d > -FOLD_DEPTH and d < reach - FOLD_TRIGGER:
                    n_world = rot @ grad
                    if n_world.dot(nb) < FOLD_FACING_COS * n_world.norm() * nb.norm():
                        found = 1
                    else:
                        budget = -1.0
                elif d <= -FOLD_DEPTH:
                    budget = -1.0
    return vec3(ti.cast(found, REAL), budget, speed)


@ti.func
def guard_holds(p: vec3, g: GUARD, budget: REAL, local: REAL, odo: REAL, grid_tag: REAL,
                s_frame: REAL, shift: vec3) -> ti.i32:
    """Whether guard g still proves that nothing it guards against has come within `budget`
    of the vertex at p: by the odometer, or, on the grid it was searched on and while the
    vertex stayed within `local` of where it was in the grid's coordinates (which move with
    the body's mean motion), by the motions relative to that mean (nearest_one)."""
    drift = p - vec3(g[0], g[1], g[2])
    holds = drift.norm() + ti.abs(odo - g[G_ODO]) < budget
    if g[G_TAG] == grid_tag:
        since = s_frame - g[G_TIME]
        relative = (drift - shift * since).norm()
        if relative < local:
            holds = holds or relative + g[G_SPEED] * ti.abs(since) < budget
    return holds


@ti.func
def other_surface(p: vec3, p_grid: vec3, best_t: ti.i32, part: REAL, b0: V3, b1: V3,
                  faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3, starts: I1,
                  items: I1, s: REAL, reach: REAL, tbox: V8, both_ends: ti.i32) -> REAL:
    """How far from p the nearest triangle of a body part other than `part` that faces the
    tracked triangle best_t is (FACING_COS), if it is within `reach` (m, below OTHER_NONE; the
    27 cells around p, at p_grid in the grid's coordinates, hold every triangle nearer than a
    cell), else OTHER_NONE. With `both_ends` (the frame's full search, which measures the
    cloth where it is at the frame's start against the body at s, its end) the nearer of that
    and the triangle at the frame's start: at the end alone, a thigh passing the other one 4-5
    cm a frame was out of reach of the trouser leg between them, which kept no guard against
    it and was gone through; at the start alone, a block sliding onto cloth at 0.5 m/s came
    from beyond the cell unguarded."""
    f = faces[best_t]
    a = lerp3(b0[f[0]], b1[f[0]], s)
    nb = (lerp3(b0[f[1]], b1[f[1]], s) - a).cross(lerp3(b0[f[2]], b1[f[2]], s) - a)
    nbl = nb.norm()
    best = reach * reach
    cell = ti.cast(ti.floor((p_grid - origin) * inv_cell), ti.i32)
    for k in range(27):
        c = cell + ti.math.ivec3(k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1)
        cid = grid_cell(c, dims)
        if cid >= 0:
            for q in range(starts[cid], starts[cid + 1]):
                t = items[q]
                tb = tbox[t]
                if tb[T_PART] != part:
                    lo = vec3(tb[0], tb[1], tb[2])
                    hi = vec3(tb[3], tb[4], tb[5])
                    near = ti.max(lo - p_grid, 0.0, p_grid - hi).norm_sqr()
                    if both_ends:
                        # At the frame's start the grid's coordinates are the world's.
                        near = ti.min(near, ti.max(lo - p, 0.0, p - hi).norm_sqr())
                    if near < best:
                        g = faces[t]
                        ta = lerp3(b0[g[0]], b1[g[0]], s)
                        tb_ = lerp3(b0[g[1]], b1[g[1]], s)
                        tc = lerp3(b0[g[2]], b1[g[2]], s)
                        nt = (tb_ - ta).cross(tc - ta)
                        if nt.dot(nb) < FACING_COS * nt.norm() * nbl:
                            r = closest_on_triangle(p, ta, tb_, tc)
                            best = ti.min(best, r[3])
                            if both_ends:
                                r0 = closest_on_triangle(p, b0[g[0]], b0[g[1]], b0[g[2]])
                                best = ti.min(best, r0[3])
    found = ti.cast(OTHER_NONE, REAL)
    if best < reach * reach:
        found = ti.sqrt(best)
    return found


@ti.kernel
def grid_nearest(
    x: V3,
    w: F1,
    b0: V3,
    b1: V3,
    faces: I3,
    origin: vec3,
    inv_cell: REAL,
    dims: ti.math.ivec3,
    starts: I1,
    items: I1,
    s: REAL,
    max_dist: REAL,
    tri: I1,
    which: ti.i32,
    guard: V8,
    odo: REAL,
    grid_tag: REAL,
    shift: vec3,
    tbox: V8,
    fold: F1,
    fold_at: ti.i32,
):
    for i in x:
        nearest_one(
            i,
            x,
            w,
            b0,
            b1,
            faces,
            origin,
            inv_cell,
            dims,
            starts,
            items,
            s,
            max_dist,
            tri,
            which,
            guard,
            odo,
            grid_tag,
            s,
            shift,
            tbox,
            fold,
            fold_at,
        )


@ti.kernel
def nearest_untracked(x: V3, w: F1, bs1: V3, faces: I3, origin: vec3, inv_cell: REAL,
                      dims: ti.math.ivec3, starts: I1, items: I1, cell: REAL, tri: I1,
                      guard: V8, odo0: REAL, travel: REAL, grid_tag: REAL, s1: REAL,
                      shift: vec3, tbox: V8, fold: F1, fold_at: ti.i32):
    """A substep's search of the untracked vertices as xpbd_frame runs it: the body at the
    substep's end from interpolate_body, the odometer odo0 + s1 travel computed here (computed
    in Python it rounded differently, and a guard's test could come out the other way)."""
    for i in x:
        nearest_one(i, x, w, bs1, bs1, faces, origin, inv_cell, dims, starts, items, 1.0, cell,
                    tri, SEARCH_UNTRACKED, guard, odo0 + s1 * travel, grid_tag, s1, shift,
                    tbox, fold, fold_at)
