"""Taichi kernels of the cloth solvers. Data lives in ndarrays owned by the solver objects.

Every effect has its own kernel (or compile-time branch), so an effect that a scene does not need
is neither compiled nor launched. Constraint sweeps come in two flavours: Gauss-Seidel (serial,
the CPU default) and coloured Gauss-Seidel (one parallel loop per colour, for GPU backends).
"""

import taichi as ti

from datagen.sim import fold_fields as FF
from datagen.sim.model import PRESSURE_DRAG, PRESSURE_OFF, PRESSURE_OUTER_FACE
from datagen.sim.precision import REAL, VEC3, VEC4

vec3 = VEC3
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
V4 = ti.types.ndarray(dtype=VEC4, ndim=1)
# A search guard per cloth vertex (see nearest_one): where the vertex was searched, the odometer
# then, the grid's number, the frame fraction, the fastest corner among the cells' triangles,
# and for a vertex the search found a triangle for, its part and how far the nearest surface of
# another part facing it was (G_OTHER: 1 + part + distance; 0 for a search that found none).
GUARD = ti.types.vector(8, REAL)
G_ODO, G_TAG, G_TIME, G_SPEED, G_OTHER = 3, 4, 5, 6, 7
# The per-triangle box of a collider grid (tbox, written by grid_count) keeps the triangle's
# body part in its last slot (T_PART), set once: -1 where the collider has no parts (a sphere, a
# garment under another), so no guard there is of the tracked kind.
T_PART = 7
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
V8 = ti.types.ndarray(dtype=GUARD, ndim=1)
F1 = ti.types.ndarray(dtype=REAL, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I2 = ti.types.ndarray(dtype=ti.math.ivec2, ndim=1)
I3 = ti.types.ndarray(dtype=ti.math.ivec3, ndim=1)
I4 = ti.types.ndarray(dtype=ti.math.ivec4, ndim=1)

WALK_STEPS = 8  # most triangles a cloth vertex's walk to its closest body triangle visits
# The strain limit's sweeps after contact (limit_after_contact_one): until no spring is more
# than the tolerance (relative) past its limit, at most this many. Over-relaxed constraint
# sweeps leave them more to do: at 4, 2 % of a tight sleeve's edges stayed up to 3 % past its
# limit (tests/test_sim_physics.py) and the heavy body's hard case failed; 16 full sweeps cost
# the walking t-shirt 3 % more time (xpbd's later sweeps visit only what moved: cheaper still).
AFTER_CONTACT_SWEEPS = 16
AFTER_CONTACT_TOLERANCE = 1e-3


# -- geometry ----------------------------------------------------------------------------------
@ti.func
def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3) -> VEC4:
    """Barycentric (u, v, w) of the closest point of triangle abc to p, and its squared
    distance (Ericson, Real-Time Collision Detection 5.1.5, written from the math)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab.dot(ap)
    d2 = ac.dot(ap)
    bary = vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = ab.dot(bp)
    d4 = ac.dot(bp)
    cp = p - c
    d5 = ab.dot(cp)
    d6 = ac.dot(cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d1 <= 0.0 and d2 <= 0.0:
        bary = vec3(1.0, 0.0, 0.0)
    elif d3 >= 0.0 and d4 <= d3:
        bary = vec3(0.0, 1.0, 0.0)
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        bary = vec3(1.0 - t, t, 0.0)
    elif d6 >= 0.0 and d5 <= d6:
        bary = vec3(0.0, 0.0, 1.0)
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        bary = vec3(1.0 - t, 0.0, t)
    elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        bary = vec3(0.0, 1.0 - t, t)
    else:
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        bary = vec3(1.0 - v - w, v, w)
    q = bary[0] * a + bary[1] * b + bary[2] * c
    return VEC4(bary[0], bary[1], bary[2], (p - q).norm_sqr())


@ti.func
def plane_barycentric(p: vec3, a: vec3, b: vec3, c: vec3) -> vec3:
    """Barycentric coordinates of p projected onto the plane of abc (may be negative)."""
    v0 = b - a
    v1 = c - a
    v2 = p - a
    d00 = v0.dot(v0)
    d01 = v0.dot(v1)
    d11 = v1.dot(v1)
    d20 = v2.dot(v0)
    d21 = v2.dot(v1)
    den = d00 * d11 - d01 * d01
    out = vec3(1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)
    if den > 1e-20:
        v = (d11 * d20 - d01 * d21) / den
        w = (d00 * d21 - d01 * d20) / den
        out = vec3(1.0 - v - w, v, w)
    return out


@ti.func
def lerp3(a: vec3, b: vec3, s: REAL) -> vec3:
    return a + s * (b - a)


# -- integration -------------------------------------------------------------------------------
# Each vertex's air terms, `air` (V4): its linear drag coefficient (kg/s: Blender's air damping
# times its rest area) and its pressure-drag vector (kg/m: 1/2 rho C_d times its vector area,
# a third of each adjacent face's area along the face's normal, at the substep's start; zero
# where pressure drag is off). See air_velocity and pressure_face_add.
@ti.func
def air_velocity(vi: vec3, air: VEC4, wi: REAL, wind: vec3, h: REAL, use_air: ti.template(),
                 use_pressure: ti.template()) -> vec3:
    """The velocity after a step h of air drag, relative to the wind: the linear drag, then the
    pressure drag -c |v_n| v_n n on the velocity's normal part v_n. Each implicit in the velocity
    it damps (with |v_n| taken at the step's start for the quadratic term), so neither can
    reverse a velocity at any step. `use_pressure` (model.PRESSURE_*): off, on both faces, or
    on the outer face only (cloth on a body: only a panel moving along its outward normal
    meets the free stream)."""
    if ti.static(use_air):
        vi = wind + (vi - wind) / (1.0 + h * air[0] * wi)
    if ti.static(use_pressure != PRESSURE_OFF):
        cn = vec3(air[1], air[2], air[3])
        c = cn.norm()
        if c > 0.0:
            n = cn / c
            vn = (vi - wind).dot(n)
            if ti.static(use_pressure == PRESSURE_OUTER_FACE):
                vn = ti.max(vn, 0.0)  # the inner face is sheltered by the body
            vi += (vn / (1.0 + h * c * ti.abs(vn) * wi) - vn) * n
    return vi


@ti.func
def predict_one(
    i: ti.i32,
    x: V3,
    xp: V3,
    v: V3,
    w: F1,
    air: V4,
    gravity: vec3,
    wind: vec3,
    h: REAL,
    use_gravity: ti.template(),
    use_air: ti.template(),
    use_pressure: ti.template(),
):
    """Start of a substep: remember positions, apply external forces, move ballistically."""
    xp[i] = x[i]
    if w[i] > 0.0:
        vi = air_velocity(v[i], air[i], w[i], wind, h, use_air, use_pressure)
        if ti.static(use_gravity):
            vi += h * gravity
        v[i] = vi
        x[i] += h * vi


@ti.kernel
def predict(
    x: V3,
    xp: V3,
    v: V3,
    w: F1,
    air: V4,
    gravity: vec3,
    wind: vec3,
    h: REAL,
    use_gravity: ti.template(),
    use_air: ti.template(),
    use_pressure: ti.template(),
):
    for i in x:
        predict_one(i, x, xp, v, w, air, gravity, wind, h, use_gravity, use_air, use_pressure)


@ti.func
def finish_one(i: ti.i32, x: V3, xp: V3, v: V3, w: F1, contact_n: V3, contact_v: V3, h: REAL):
    """End of a substep: velocities from positions; contacts do not bounce (inelastic)."""
    vi = (x[i] - xp[i]) / h
    if w[i] > 0.0:
        n = contact_n[i]
        if n.norm_sqr() > 0.0:
            vn = (vi - contact_v[i]).dot(n)
            if vn > 0.0:
                vi -= vn * n
    v[i] = vi


@ti.kernel
def finish_contacts(x: V3, xp: V3, v: V3, w: F1, contact_n: V3, contact_v: V3, h: REAL):
    """For force-based solvers: only vertices a contact moved take their velocity from positions
    (elsewhere re-deriving it from float positions would add round-off to every step)."""
    for i in x:
        if contact_n[i].norm_sqr() > 0.0:
            finish_one(i, x, xp, v, w, contact_n, contact_v, h)


@ti.kernel
def finish(x: V3, xp: V3, v: V3, w: F1, contact_n: V3, contact_v: V3, h: REAL):
    for i in x:
        finish_one(i, x, xp, v, w, contact_n, contact_v, h)


# -- XPBD constraints --------------------------------------------------------------------------
@ti.kernel
def clear_vec3(a: V3):
    for i in a:
        a[i] = vec3(0.0)


@ti.func
def spring_alpha_gamma(e: ti.i32, c: REAL, comp_t: F1, comp_c: F1, beta: F1,
                       inv_h: REAL) -> ti.types.vector(2, REAL):
    """Spring e's XPBD compliance over h^2 (its tension or compression compliance, as its
    constraint c is positive or negative) and its damping over h."""
    alpha = comp_t[e]
    if c < 0.0:
        alpha = comp_c[e]
    return ti.types.vector(2, REAL)(alpha * inv_h * inv_h, beta[e] * inv_h)


@ti.func
def spring_delta(
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    rest: F1,
    limit: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    e: ti.i32,
    inv_h: REAL,
    omega: REAL,
) -> VEC4:
    """XPBD update of spring e: (displacement along n, dlambda) with n from x_i to x_j, the
    compliant part over-relaxed by omega. Past its limit length the spring is inextensible: the
    displacement also removes the excess, exactly (strain limiting; the multiplier keeps only
    the compliant part): an over-relaxed inequality would overshoot into compression."""
    i = springs[e][0]
    j = springs[e][1]
    out = VEC4(0.0)
    wsum = w[i] + w[j]
    d = x[j] - x[i]
    length = d.norm()
    if wsum > 0.0 and length > 1e-9:
        n = d / length
        c = length - rest[e]
        ag = spring_alpha_gamma(e, c, comp_t, comp_c, beta, inv_h)
        alpha, gamma = ag[0], ag[1]
        rate = n.dot((x[j] - xp[j]) - (x[i] - xp[i]))
        dl = omega * (-c - alpha * lam[e] - gamma * rate) / ((1.0 + gamma) * wsum + alpha)
        move = dl
        after = length + wsum * dl
        if after > limit[e]:
            move += (limit[e] - after) / wsum
        out = VEC4(move * n, dl)
    return out


@ti.func
def sweep_order(k: ti.i32, n: ti.i32, reverse: ti.i32) -> ti.i32:
    """The k-th element of a Gauss-Seidel sweep over n, backwards when `reverse`."""
    e = k
    if reverse != 0:
        e = n - 1 - k
    return e


@ti.func
def spring_gs_one(
    e: ti.i32,
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    rest: F1,
    limit: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    inv_h: REAL,
    omega: REAL,
):
    r = spring_delta(x, xp, w, springs, rest, limit, comp_t, comp_c, beta, lam, e, inv_h, omega)
    lam[e] += r[3]
    i = springs[e][0]
    j = springs[e][1]
    dx = vec3(r[0], r[1], r[2])
    x[i] -= w[i] * dx
    x[j] += w[j] * dx


@ti.kernel
def springs_gauss_seidel(
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    rest: F1,
    limit: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    h: REAL,
    reverse: ti.i32,
    omega: REAL,
):
    n_springs = springs.shape[0]
    inv_h = 1.0 / h
    ti.loop_config(serialize=True)
    for k in range(n_springs):
        e = sweep_order(k, n_springs, reverse)
        spring_gs_one(e, x, xp, w, springs, rest, limit, comp_t, comp_c, beta, lam, inv_h, omega)


@ti.kernel
def limit_strain(x: V3, v: V3, w: F1, springs: I2, limit: F1, h: REAL, reverse: ti.i32) -> REAL:
    """One Gauss-Seidel sweep of strain limiting for the force-based solvers (Provot 1995):
    every spring longer than its limit is shortened to it, the ends moving by their inverse
    masses, and the move enters the velocity as in a position-based step. Returns the largest
    excess met, relative to the limit, so the caller can sweep until it is negligible."""
    worst = 0.0
    n_springs = springs.shape[0]
    ti.loop_config(serialize=True)
    for k in range(n_springs):
        e = sweep_order(k, n_springs, reverse)
        i = springs[e][0]
        j = springs[e][1]
        d = x[j] - x[i]
        length = d.norm()
        wsum = w[i] + w[j]
        if length > limit[e] and wsum > 0.0:
            worst = ti.max(worst, length / limit[e] - 1.0)
            move = (length - limit[e]) / (wsum * length) * d
            x[i] += w[i] * move
            x[j] -= w[j] * move
            v[i] += w[i] * move / h
            v[j] -= w[j] * move / h
    return worst


@ti.func
def limit_after_contact_one(
    e: ti.i32, x: V3, w: F1, springs: I2, limit: F1, contact_n: V3
) -> REAL:
    """Shorten spring e to its limit length if contact left it longer, moving a vertex in
    contact only along the body (never into it).

    Contact comes after the strain limit in a substep, and static friction puts a vertex back
    where the body carried it, which undoes the limit's last correction: fabric held by friction
    on skin stayed past the limit where the skin stretched (a raised arm's sleeves, a crouching
    back). At the limit the fabric is inextensible, its tension beyond any Coulomb bound, so
    the limit wins over friction; the normal part of contact still wins over the limit."""
    i = springs[e][0]
    j = springs[e][1]
    d = x[j] - x[i]
    length = d.norm()
    wsum = w[i] + w[j]
    excess = 0.0
    if length > limit[e] and wsum > 0.0:
        excess = length / limit[e] - 1.0
        move = (length - limit[e]) / (wsum * length) * d
        mi = w[i] * move
        mj = -w[j] * move
        ni = contact_n[i]
        nj = contact_n[j]
        mi -= ti.min(0.0, mi.dot(ni)) * ni  # a zero normal (no contact) changes nothing
        mj -= ti.min(0.0, mj.dot(nj)) * nj
        x[i] += mi
        x[j] += mj
    return excess


@ti.kernel
def limit_after_contact(
    x: V3, w: F1, springs: I2, limit: F1, contact_n: V3, reverse: ti.i32
) -> REAL:
    """One sweep of limit_after_contact_one; returns the largest excess met (relative)."""
    worst = 0.0
    n_springs = springs.shape[0]
    ti.loop_config(serialize=True)
    for k in range(n_springs):
        e = sweep_order(k, n_springs, reverse)
        worst = ti.max(worst, limit_after_contact_one(e, x, w, springs, limit, contact_n))
    return worst


@ti.func
def _enqueue(v: ti.i32, lists: I1, flags: ti.i32, items: ti.i32, counter: ti.i32):
    """Append vertex v to the list at lists[items:], whose length is lists[counter], unless its
    flag (lists[flags + v]) says it is there."""
    if lists[flags + v] == 0:
        lists[flags + v] = 1
        lists[items + lists[counter]] = v
        lists[counter] += 1


@ti.func
def _limit_and_enqueue(
    e: ti.i32, x: V3, w: F1, springs: I2, limit: F1, contact_n: V3, lists: I1, items: ti.i32
) -> REAL:
    """limit_after_contact_one on spring e; ends it moved join the next sweep's list (at
    `items`) and the list of moved vertices. Returns the excess it met."""
    nv = x.shape[0]
    excess = limit_after_contact_one(e, x, w, springs, limit, contact_n)
    if excess > 0.0:
        for end in ti.static(range(2)):
            v = springs[e][end]
            _enqueue(v, lists, 0, items, 5 * nv)
            _enqueue(v, lists, nv, 4 * nv, 5 * nv + 1)
    return excess


@ti.func
def limit_after_contact_active(
    x: V3, w: F1, springs: I2, limit: F1, contact_n: V3, adj: I1, lists: I1
) -> ti.i32:
    """The strain limit after contact (limit_after_contact_one) to AFTER_CONTACT_TOLERANCE,
    visiting after the first sweep only the springs at vertices the previous sweep moved.

    A spring whose ends have not moved since it was last checked is as it was then: within its
    limit, or shortened to it (and then its ends moved). So a later sweep needs only the springs
    around the moved vertices: it reaches the state and the stopping test of a full sweep for
    the cost of the springs contact left stretched instead of all of them.
    `adj`: each vertex's springs (CSR: n + 1 offsets, then spring indices), then the order of the
    first sweep (a spring index each: the model's order, not the wavefront order of the
    constraint sweeps, see XPBDSolver._init_active_limit). `lists` (5 n + 2,
    see XPBDSolver._init_active_limit): queued flags, moved flags, the queue's two halves (this
    sweep's vertices and the next's), the vertices the limit moved (for contact afterwards),
    and two counters (the next sweep's list, the moved list). Returns how many moved; the
    caller clears their flags (moved_by_limit)."""
    nv = x.shape[0]
    lists[5 * nv] = 0
    lists[5 * nv + 1] = 0
    cur = 2 * nv
    worst = 0.0
    n_springs = springs.shape[0]
    first = nv + 1 + 2 * n_springs  # in adj: the first sweep's order
    for k in range(n_springs):
        e = adj[first + k]
        worst = ti.max(worst, _limit_and_enqueue(e, x, w, springs, limit, contact_n, lists, cur))
    cur_len = lists[5 * nv]
    sweep = 1
    while worst >= AFTER_CONTACT_TOLERANCE and sweep < AFTER_CONTACT_SWEEPS and cur_len > 0:
        worst = 0.0
        nxt = 5 * nv - cur  # the other half
        lists[5 * nv] = 0
        for q in range(cur_len):
            v = lists[cur + sweep_order(q, cur_len, sweep % 2)]
            lists[v] = 0
            for a in range(adj[v], adj[v + 1]):
                e = adj[nv + 1 + a]
                worst = ti.max(
                    worst, _limit_and_enqueue(e, x, w, springs, limit, contact_n, lists, nxt)
                )
        cur = nxt
        cur_len = lists[5 * nv]
        sweep += 1
    for q in range(cur_len):  # left queued when the tolerance or the cap stopped the sweeps
        lists[lists[cur + q]] = 0
    return lists[5 * nv + 1]


@ti.func
def moved_by_limit(q: ti.i32, nv: ti.i32, lists: I1) -> ti.i32:
    """The q-th vertex limit_after_contact_active moved (of nv cloth vertices), its flag
    cleared."""
    i = lists[4 * nv + q]
    lists[nv + i] = 0
    return i


@ti.func
def bend_delta(x: V3, xp: V3, bends: I4, kk: V8, bstep: V4, lam_b: V3, b: ti.i32) -> vec3:
    """XPBD update of the (linear, vector-valued) bending constraint b: its dlambda. `kk[b]`
    holds the stencil's weights k and then each vertex's inverse mass times its weight;
    `bstep[b]` the step's compliance over h^2, damping over h and the inverse of the update's
    denominator (XPBDSolver._use_step; zero where all four vertices are pinned). With these
    per step the sweep leaves no division and no inverse mass to gather: a tube's bends, each
    sharing a vertex with the one before, swept in 11.1 ns a stencil instead of 14.8. (The
    damping's rate stays k . (x - xp): written as c - k . xp it was 1 ns faster, but the two
    large terms cancel, and in float32 the tube then left the old trajectory 0.19 mm at frame
    1, where rounding alone moves it microns.)"""
    s = bends[b]
    k = kk[b]
    p = bstep[b]
    c = k[0] * x[s[0]] + k[1] * x[s[1]] + k[2] * x[s[2]] + k[3] * x[s[3]]
    rate = (
        k[0] * (x[s[0]] - xp[s[0]])
        + k[1] * (x[s[1]] - xp[s[1]])
        + k[2] * (x[s[2]] - xp[s[2]])
        + k[3] * (x[s[3]] - xp[s[3]])
    )
    return p[2] * (-c - p[0] * lam_b[b] - p[1] * rate)


@ti.func
def bend_gs_one(
    b: ti.i32, x: V3, xp: V3, bends: I4, kk: V8, bstep: V4, lam_b: V3, omega: REAL,
):
    dl = omega * bend_delta(x, xp, bends, kk, bstep, lam_b, b)
    lam_b[b] += dl
    s = bends[b]
    k = kk[b]
    for q in ti.static(range(4)):
        x[s[q]] += k[4 + q] * dl


@ti.kernel
def bends_gauss_seidel(
    x: V3,
    xp: V3,
    bends: I4,
    kk: V8,
    bstep: V4,
    lam_b: V3,
    listed: I1,
    n_listed: ti.i32,
    reverse: ti.i32,
    omega: REAL,
    only_listed: ti.template(),
):
    """A Gauss-Seidel sweep over every bend, or with `only_listed` over the first n_listed
    bends of `listed` (the stiff ones, in a substep's later sweeps)."""
    n = bends.shape[0]
    if ti.static(only_listed):
        n = n_listed
    ti.loop_config(serialize=True)
    for m in range(n):
        b = sweep_order(m, n, reverse)
        if ti.static(only_listed):
            b = listed[b]
        bend_gs_one(b, x, xp, bends, kk, bstep, lam_b, omega)


# Coloured Gauss-Seidel (parallel backends): the elements of a sweep are grouped by colour, no
# two elements of a colour sharing a vertex, and each colour is one parallel loop. Within a colour
# the updates are independent, so the sweep is exact Gauss-Seidel in colour order and its result
# does not depend on how threads split a loop. (Jacobi sweeps, which this replaced, converge far
# slower per sweep: at the default 20x4 a silk strap top slid down to the waist.) The colours
# are unrolled at compile time, so each loop is a top-level, parallel loop of its own.
@ti.func
def colour_range(c: ti.i32, n_colours: ti.i32, reverse: ti.i32, colour_ptr: I1) -> ti.math.ivec2:
    """The slice of the colour-sorted order holding the c-th colour swept (backwards when
    `reverse`)."""
    cc = c
    if reverse != 0:
        cc = n_colours - 1 - c
    return ti.math.ivec2(colour_ptr[cc], colour_ptr[cc + 1])


@ti.kernel
def springs_coloured(
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    rest: F1,
    limit: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    order: I1,
    colour_ptr: I1,
    h: REAL,
    reverse: ti.i32,
    omega: REAL,
    n_colours: ti.template(),
):
    """springs_gauss_seidel as one parallel loop per colour (`order`: spring indices sorted by
    colour, `colour_ptr`: n_colours + 1 offsets)."""
    for c in ti.static(range(n_colours)):
        r = colour_range(c, n_colours, reverse, colour_ptr)
        for k in range(r[0], r[1]):
            spring_gs_one(order[k], x, xp, w, springs, rest, limit, comp_t, comp_c, beta, lam,
                          1.0 / h, omega)


@ti.kernel
def bends_coloured(
    x: V3,
    xp: V3,
    bends: I4,
    kk: V8,
    bstep: V4,
    lam_b: V3,
    order: I1,
    colour_ptr: I1,
    reverse: ti.i32,
    omega: REAL,
    n_colours: ti.template(),
):
    """bends_gauss_seidel as one parallel loop per colour (`order`: the bends swept, sorted by
    colour; every bend, or the stiff ones)."""
    for c in ti.static(range(n_colours)):
        r = colour_range(c, n_colours, reverse, colour_ptr)
        for k in range(r[0], r[1]):
            bend_gs_one(order[k], x, xp, bends, kk, bstep, lam_b, omega)


@ti.kernel
def wavefront_levels(elements: I1, width: ti.i32, last: I1, level: I1):
    """Each element's wavefront level (solvers.wavefront_order): one more than the highest
    level among the earlier elements that share a vertex with it. `elements` holds `width`
    vertex indices per element; `last` (one per vertex, zeros) is the running maximum."""
    ti.loop_config(serialize=True)
    for e in range(level.shape[0]):
        lv = 0
        for q in range(width):
            lv = ti.max(lv, last[elements[e * width + q]])
        lv += 1
        level[e] = lv
        for q in range(width):
            last[elements[e * width + q]] = lv


# -- explicit forces ---------------------------------------------------------------------------
@ti.func
def spring_force(x: V3, v: V3, springs: I2, rest: F1, k_t: F1, k_c: F1, beta: F1,
                 e: ti.i32) -> vec3:
    """Spring e's force on its first vertex (its second takes the opposite)."""
    i = springs[e][0]
    j = springs[e][1]
    d = x[j] - x[i]
    length = d.norm()
    fe = vec3(0.0)
    if length > 1e-9:
        n = d / length
        c = length - rest[e]
        k = k_t[e]
        if c < 0.0:
            k = k_c[e]
        fe = (k * c + beta[e] * k * n.dot(v[j] - v[i])) * n
    return fe


@ti.func
def bend_force(x: V3, v: V3, bends: I4, kw: V4, stiff: F1, beta: F1, b: ti.i32) -> vec3:
    """Bending stencil b's generalised force: its q-th vertex takes -kw[b][q] times it."""
    s = bends[b]
    k = kw[b]
    c = k[0] * x[s[0]] + k[1] * x[s[1]] + k[2] * x[s[2]] + k[3] * x[s[3]]
    cv = k[0] * v[s[0]] + k[1] * v[s[1]] + k[2] * v[s[2]] + k[3] * v[s[3]]
    return stiff[b] * (c + beta[b] * cv)


@ti.kernel
def spring_forces(x: V3, v: V3, f: V3, springs: I2, rest: F1, k_t: F1, k_c: F1, beta: F1):
    for e in range(springs.shape[0]):
        fe = spring_force(x, v, springs, rest, k_t, k_c, beta, e)
        f[springs[e][0]] += fe
        f[springs[e][1]] -= fe


@ti.kernel
def bend_forces(x: V3, v: V3, f: V3, bends: I4, kw: V4, stiff: F1, beta: F1):
    for b in range(bends.shape[0]):
        g = bend_force(x, v, bends, kw, stiff, beta, b)
        for q in ti.static(range(4)):
            f[bends[b][q]] -= kw[b][q] * g


@ti.kernel
def explicit_update(
    x: V3,
    xp: V3,
    v: V3,
    f: V3,
    w: F1,
    air: V4,
    gravity: vec3,
    wind: vec3,
    h: REAL,
    use_gravity: ti.template(),
    use_air: ti.template(),
    use_pressure: ti.template(),
):
    """Semi-implicit (symplectic) Euler: v += h a; x += h v."""
    for i in x:
        xp[i] = x[i]
        if w[i] > 0.0:
            vi = air_velocity(v[i] + h * w[i] * f[i], air[i], w[i], wind, h, use_air,
                              use_pressure)
            if ti.static(use_gravity):
                vi += h * gravity
            v[i] = vi
            x[i] += h * vi
        f[i] = vec3(0.0)


@ti.func
def pressure_face_vector(x: V3, a: ti.i32, b: ti.i32, c: ti.i32) -> vec3:
    """What face (a, b, c) adds to each corner's pressure-drag vector: a third of its area
    along its normal (|cross| / 6) times 1/2 rho C_d."""
    return (PRESSURE_DRAG / 6.0) * (x[b] - x[a]).cross(x[c] - x[a])


@ti.func
def pressure_clear_one(i: ti.i32, air: V4):
    air[i] = VEC4(air[i][0], 0.0, 0.0, 0.0)


@ti.func
def pressure_face_add(a: ti.i32, b: ti.i32, c: ti.i32, x: V3, air: V4):
    cn = pressure_face_vector(x, a, b, c)
    add = VEC4(0.0, cn[0], cn[1], cn[2])
    air[a] += add
    air[b] += add
    air[c] += add


@ti.kernel
def set_pressure_vectors(x: V3, faces: I3, air: V4):
    """Every vertex's pressure-drag vector at positions x (air_velocity), the faces added in
    order into their corners: serial backends (parallel_kernels.set_pressure_vectors_gathered
    sums per vertex instead). The fused frame kernel does the same, in the same order."""
    ti.loop_config(serialize=True)
    for i in range(air.shape[0]):
        pressure_clear_one(i, air)
    ti.loop_config(serialize=True)
    for t in range(faces.shape[0]):
        f = faces[t]
        pressure_face_add(f[0], f[1], f[2], x, air)


@ti.kernel
def pressure_drag(v: V3, air: V4, w: F1, wind: vec3, h: REAL, use_pressure: ti.template()):
    """Pressure drag alone (air_velocity) for a step h: the implicit solver's, split off before
    its Newton solve, which takes the linear drag into its potential."""
    for i in v:
        if w[i] > 0.0:
            v[i] = air_velocity(v[i], air[i], w[i], wind, h, False, use_pressure)


# -- pins --------------------------------------------------------------------------------------
@ti.kernel
def apply_pins(x: V3, pin_idx: I1, t0: V3, t1: V3, s: REAL):
    for p in pin_idx:
        x[pin_idx[p]] = lerp3(t0[p], t1[p], s)


@ti.func
def tether_one(t: ti.i32, x: V3, tethers: I2, length: F1):
    """Pull a vertex that is farther from its pin than the strain limit allows back onto
    that distance (the pin, weightless, stays)."""
    i = tethers[t][0]
    d = x[i] - x[tethers[t][1]]
    dl = d.norm()
    if dl > length[t]:
        x[i] -= (1.0 - length[t] / dl) * d


@ti.kernel
def apply_tethers(x: V3, tethers: I2, length: F1):
    for t in tethers:
        tether_one(t, x, tethers, length)


# -- body collision ----------------------------------------------------------------------------
@ti.func
def collide_one(
    i: ti.i32,
    x: V3,
    xp: V3,
    w: F1,
    tri: I1,
    faces: I3,
    fadj: I3,
    b0: V3,
    b1: V3,
    n0: V3,
    n1: V3,
    s0: REAL,
    s1: REAL,
    thickness: F1,
    friction: F1,
    recover: REAL,
    release: REAL,
    contact_n: V3,
    contact_v: V3,
    h: REAL,
    use_friction: ti.template(),
    open_surface: ti.template() = False,
):
    """Keep cloth vertex i `thickness` outside the moving body surface (interpolated between
    frame positions b0 -> b1 at fractions s0 -> s1 of the frame), with Coulomb friction.

    The vertex tracks its closest body triangle: a walk across edges towards the projection of
    the vertex keeps it current as the body moves; the grid search resets it. On an
    `open_surface` (a garment under another) a vertex whose projection lies beyond a border
    edge is off the surface and gets no contact: the side of a border has no meaning, and a
    t-shirt just above a skirt's waistband was pushed out along it and held there.
    """
    t = tri[i]
    if w[i] > 0.0 and t >= 0:
        p = x[i]
        a = vec3(0.0)
        b = vec3(0.0)
        c = vec3(0.0)
        inside = False
        off_border = False
        for step in range(WALK_STEPS):
            f = faces[t]
            a = lerp3(b0[f[0]], b1[f[0]], s1)
            b = lerp3(b0[f[1]], b1[f[1]], s1)
            c = lerp3(b0[f[2]], b1[f[2]], s1)
            bc = plane_barycentric(p, a, b, c)
            m = 0
            if bc[1] < bc[m]:
                m = 1
            if bc[2] < bc[m]:
                m = 2
            inside = bc[m] >= 0.0
            nxt = -1
            # A small tolerance stops the walk from circling a vertex whose neighbourhood no
            # triangle plane contains the projection of; the clamped closest point is right.
            if bc[m] < -0.02:
                nxt = fadj[t][m]
                off_border = nxt < 0
            # The walk ends on the triangle whose corners it evaluated: stepping on after the
            # last one left a, b, c one triangle behind t, and the contact then took its
            # normal and the body's velocity (q at the end minus the other triangle's point at
            # the start: 110 m/s where the body moved 1.4 m/s) from two different triangles.
            if nxt < 0 or step == WALK_STEPS - 1:
                break
            off_border = False
            t = nxt
        tri[i] = t
        # Most tracked vertices hover clear of the body: when the projection falls inside the
        # triangle, the distance to its plane is the distance to the triangle, and a vertex
        # well beyond the thickness needs neither the closest point nor the contact response.
        nf = (b - a).cross(c - a)
        nfl = nf.norm()
        far = False
        if inside and nfl > 1e-20:
            height = (p - a).dot(nf) / nfl
            far = height > 2.0 * thickness[i] + 1e-3
            if height > release:
                tri[i] = -1  # far from the body now: the grid search picks it up again
        if ti.static(open_surface):
            far = far or off_border
        if not far:
            _collide_tracked(i, x, xp, faces, b0, b1, n0, n1, s0, s1, thickness, friction,
                             recover, release, contact_n, contact_v, h, tri, t, p, a, b, c,
                             use_friction)


@ti.func
def _collide_tracked(
    i: ti.i32,
    x: V3,
    xp: V3,
    faces: I3,
    b0: V3,
    b1: V3,
    n0: V3,
    n1: V3,
    s0: REAL,
    s1: REAL,
    thickness: F1,
    friction: F1,
    recover: REAL,
    release: REAL,
    contact_n: V3,
    contact_v: V3,
    h: REAL,
    tri: I1,
    t: ti.i32,
    p: vec3,
    a: vec3,
    b: vec3,
    c: vec3,
    use_friction: ti.template(),
):
    """The contact response of cloth vertex i against its tracked triangle t (corners a, b, c
    at the substep's end)."""
    f = faces[t]
    r = closest_on_triangle(p, a, b, c)
    if r[3] > release * release:
        tri[i] = -1  # far from the body now: the grid search picks it up again
    q = r[0] * a + r[1] * b + r[2] * c
    nrm = (
        r[0] * lerp3(n0[f[0]], n1[f[0]], s1)
        + r[1] * lerp3(n0[f[1]], n1[f[1]], s1)
        + r[2] * lerp3(n0[f[2]], n1[f[2]], s1)
    )
    nl = nrm.norm()
    if nl > 1e-12:
        nrm /= nl
        sd = (p - q).dot(nrm)
        thick = thickness[i]
        qa = (
            r[0] * lerp3(b0[f[0]], b1[f[0]], s0)
            + r[1] * lerp3(b0[f[1]], b1[f[1]], s0)
            + r[2] * lerp3(b0[f[2]], b1[f[2]], s0)
        )
        # A vertex that was outside at the start of the substep is projected fully (a new
        # contact); one that was already inside (a garment that starts in the body)
        # recovers gradually so it does not shoot out.
        target = thick
        sd_prev = (xp[i] - qa).dot(nrm)
        if sd_prev < 0.0:
            target = ti.min(thick, sd_prev + recover)
        if sd < target:
            dq = q - qa
            push = target - sd
            p += push * nrm
            if ti.static(use_friction):
                rel = (p - xp[i]) - dq
                tang = rel - rel.dot(nrm) * nrm
                lt = tang.norm()
                # Coulomb's bound is the normal impulse: the part of the push that undoes this
                # substep's motion into the body. Moving a vertex that started inside (or
                # within the thickness) back out is a position correction, not an impulse; it
                # is the same distance per substep at any step, so counted here it made the
                # friction per second grow with the substeps (the references' skirt differed
                # more between 40 and 80 substeps than between 20 and 40).
                inward = ti.max(0.0, ti.min(sd_prev, target) - sd)  # <= push: target - sd
                limit = friction[i] * inward
                if lt > 1e-12:
                    p -= tang * ti.min(1.0, limit / lt)
            x[i] = p
            contact_n[i] = nrm
            contact_v[i] = dq / h


# On one CPU thread a parallel loop still starts as a task on Taichi's thread pool, about 45 us
# whatever its size (a 5k-vertex copy: 68 us parallel, 23 us serialized; Taichi's own
# from_numpy and copy_from 92 and 73 us). The frame's small passes therefore take a `serialize`
# flag, which serial backends set (backend.serial()), and copy through these kernels.
@ti.kernel
def copy_in(src: V3, dst: V3, serialize: ti.template()):
    """dst = src, for vec3 arrays (src may be a host array: a CPU reads it in place)."""
    ti.loop_config(serialize=serialize)
    for i in range(src.shape[0]):
        dst[i] = src[i]


@ti.kernel
def copy_in_at(src: V3, dst: V3, offset: ti.i32, serialize: ti.template()):
    """dst[offset:offset + len(src)] = src, for vec3 arrays."""
    ti.loop_config(serialize=serialize)
    for i in range(src.shape[0]):
        dst[offset + i] = src[i]


@ti.kernel
def copy_tracking(tri: I1, guard: V8, tri_out: I1, guard_out: V8, serialize: ti.template()):
    """tri_out, guard_out = tri, guard: a frame's snapshot of the collision tracking (for a
    retry) and its restore, in one launch."""
    ti.loop_config(serialize=serialize)
    for i in range(tri.shape[0]):
        tri_out[i] = tri[i]
        guard_out[i] = guard[i]


@ti.kernel
def read_state(x: V3, v: V3, out: ti.types.ndarray(dtype=ti.f64, ndim=3),
               serialize: ti.template()):
    """Positions and velocities into out[0] and out[1] (a host array, float64): one launch
    instead of two device-to-host copies and two conversions (0.2 ms a frame). `serialize` on
    serial backends (see copy_in)."""
    ti.loop_config(serialize=serialize)
    for i in range(x.shape[0]):
        for c in ti.static(range(3)):
            out[0, i, c] = ti.cast(x[i][c], ti.f64)
            out[1, i, c] = ti.cast(v[i][c], ti.f64)


@ti.kernel
def clear_contacts(contact_n: V3, contact_v: V3):
    for i in contact_n:
        contact_n[i] = vec3(0.0)
        contact_v[i] = vec3(0.0)


@ti.kernel
def collide_body(
    x: V3,
    xp: V3,
    w: F1,
    tri: I1,
    faces: I3,
    fadj: I3,
    bs0: V3,
    bs1: V3,
    ns1: V3,
    thickness: F1,
    friction: F1,
    recover: REAL,
    release: REAL,
    contact_n: V3,
    contact_v: V3,
    h: REAL,
    use_friction: ti.template(),
):
    """collide_one for every cloth vertex against the body at the substep's start and end, bs0
    and bs1, with its normals at the end ns1 (interpolate_body): taken at the literal fractions
    0 and 1, as xpbd_frame takes it, so that the per-effect path compiles the fused kernel's
    arithmetic."""
    for i in x:
        collide_one(i, x, xp, w, tri, faces, fadj, bs0, bs1, ns1, ns1, 0.0, 1.0, thickness,
                    friction, recover, release, contact_n, contact_v, h, use_friction)


# -- garment-garment collision (layered outfits) -----------------------------------------------
# Outer garments collide with the inner garment's surface where the inner garment is now (its
# vertices were stepped earlier in the same substep), and push it back: a point-triangle
# contact shared by inverse mass, as in position-based dynamics. With the inner surface moved
# along a path predicted at the frame's start and deaf to the outer garment, a skirt flaring
# under a t-shirt's hem at a jump's take-off stretched the t-shirt's torso 37 % (1.8 % of its
# edges past cotton's bound) where it pressed back on nothing.
@ti.func
def vertex_normal_clear_one(i: ti.i32, nrm: V3):
    nrm[i] = vec3(0.0)


@ti.func
def vertex_normal_add_one(t: ti.i32, x: V3, faces: I3, nrm: V3):
    """Add face t's area-weighted normal to its corners."""
    f = faces[t]
    fn = (x[f[1]] - x[f[0]]).cross(x[f[2]] - x[f[0]])
    for k in ti.static(range(3)):
        nrm[f[k]] += fn


@ti.func
def vertex_normal_finish_one(i: ti.i32, nrm: V3):
    length = nrm[i].norm()
    if length > 1e-20:
        nrm[i] /= length


@ti.kernel
def vertex_normals(x: V3, faces: I3, nrm: V3):
    """Area-weighted vertex normals of the surface `faces` at positions x (zero on vertices no
    face uses): the inner garment's at its current positions, the body collider's per frame.
    Serial backends only: the faces add into shared vertices in the order threads run
    (parallel_kernels.vertex_normals_gathered sums per vertex instead)."""
    # Serialized, the adds are plain stores instead of atomics: 4x faster on one CPU thread
    # (0.4 ms for a body's 27k faces); and a parallel loop costs about 45 us to start there.
    ti.loop_config(serialize=True)
    for i in range(nrm.shape[0]):
        vertex_normal_clear_one(i, nrm)
    ti.loop_config(serialize=True)
    for t in range(faces.shape[0]):
        vertex_normal_add_one(t, x, faces, nrm)
    ti.loop_config(serialize=True)
    for i in range(nrm.shape[0]):
        vertex_normal_finish_one(i, nrm)


# Parallel backends sum the outer garments' pushes on an inner vertex in fixed point
# (REACT_UNITS per metre, 64-bit integers): threads add them in whatever order they run, and
# integer sums do not depend on it, where float sums do (on a GPU the layered hard case ran
# 8.7 mm apart by the end of the settle in two runs of the same input). 2^-36 m is far below a
# float32 position's resolution, and 2^27 m of range is ample. (64-bit integer atomics: CUDA
# and the CPU have them; a backend without them would need another order-independent sum.)
REACT_UNITS = 2.0**36
REACT_EXACT = ti.types.vector(4, ti.i64)


@ti.func
def add_react_exact(react: ti.template(), j: ti.i32, push: vec3):
    for c in ti.static(range(3)):
        ti.atomic_add(react[j][c], ti.cast(ti.round(push[c] * REACT_UNITS), ti.i64))
    ti.atomic_add(react[j][3], ti.cast(1, ti.i64))


@ti.func
def collide_layer_one(
    i: ti.i32,
    x: V3,
    xp: V3,
    w: F1,
    l_w: F1,
    tri: I1,
    faces: I3,
    fadj: I3,
    nrm: V3,
    thickness: F1,
    friction: F1,
    recover: REAL,
    release: REAL,
    contact_n: V3,
    contact_v: V3,
    h: REAL,
    react: ti.template(),
    count: F1,
    use_friction: ti.template(),
    exact: ti.template(),
):
    """Outer vertex i (l_w > 0) against the inner garment's surface, from its positions at the
    substep's start (xp) to now (x), then the momentum exchange: the part of the push that
    undoes this substep's approach is shared with the triangle's corners by inverse mass, so
    both sides end the contact moving together (inelastic). Their share goes to `react`,
    applied once every outer vertex is done, so the result does not depend on the order.

    The rest of the push (keeping the thickness, recovering from an earlier penetration) stays
    with the outer vertex, as against the body: shared, it is a position correction of up to
    the thickness per substep that turns into velocity on the inner side (2.4 m/s at 20
    substeps), and it pumped a skirt under a t-shirt until it ran away. A corner the body held
    this substep (it has a contact normal) takes no share: the body carries that load."""
    before = x[i]
    collide_one(i, x, xp, l_w, tri, faces, fadj, xp, x, nrm, nrm, 0.0, 1.0, thickness,
                friction, recover, release, contact_n, contact_v, h, use_friction, True)
    t = tri[i]
    if t >= 0 and (x[i] - before).norm_sqr() > 0.0:
        f = faces[t]
        r = closest_on_triangle(before, x[f[0]], x[f[1]], x[f[2]])
        n = r[0] * nrm[f[0]] + r[1] * nrm[f[1]] + r[2] * nrm[f[2]]
        nl = n.norm()
        if nl > 1e-12:
            n /= nl
            q = r[0] * x[f[0]] + r[1] * x[f[1]] + r[2] * x[f[2]]
            qa = r[0] * xp[f[0]] + r[1] * xp[f[1]] + r[2] * xp[f[2]]
            sd = (before - q).dot(n)
            sd_prev = (xp[i] - qa).dot(n)
            inward = ti.max(0.0, ti.min(sd_prev, thickness[i]) - sd)
            # Mass splitting (Tonge et al. 2012): a corner pushed by c outer vertices lends
            # each of them 1/c of its mass (c from the previous substep), and moves by the mean
            # of their pushes; momentum is conserved and the sum does not overshoot.
            wr = vec3(0.0)
            for k in ti.static(range(3)):
                if contact_n[f[k]].norm_sqr() == 0.0:
                    wr[k] = w[f[k]] * ti.max(1.0, count[f[k]])
            denom = w[i] + r[0] * r[0] * wr[0] + r[1] * r[1] * wr[1] + r[2] * r[2] * wr[2]
            if inward > 0.0 and denom > 0.0:
                x[i] -= n * (inward * (1.0 - w[i] / denom))
                for k in ti.static(range(3)):
                    if wr[k] > 0.0:
                        push = -n * (inward * r[k] * wr[k] / denom)
                        if ti.static(exact):
                            add_react_exact(react, f[k], push)
                        else:
                            react[f[k]] += VEC4(push[0], push[1], push[2], 1.0)


@ti.func
def apply_react_one(i: ti.i32, x: V3, react: ti.template(), count: F1, exact: ti.template()):
    """Move an inner vertex by the mean of the pushes it received, and keep their number for
    the next substep's mass splitting. (Summed with each outer vertex asking as if alone, the
    pushes overshot threefold and set the two garments oscillating.) `exact`: the pushes were
    summed in fixed point (add_react_exact)."""
    if ti.static(exact):
        c = ti.cast(react[i][3], REAL)
        if c > 0.0:
            total = vec3(ti.cast(react[i][0], REAL), ti.cast(react[i][1], REAL),
                         ti.cast(react[i][2], REAL))
            x[i] += total / (REACT_UNITS * c)
        count[i] = c
        react[i] = REACT_EXACT(0)
    else:
        c = react[i][3]
        if c > 0.0:
            x[i] += vec3(react[i][0], react[i][1], react[i][2]) / c
        count[i] = c
        react[i] = VEC4(0.0)


@ti.kernel
def collide_layers(
    x: V3,
    xp: V3,
    w: F1,
    l_w: F1,
    tri: I1,
    faces: I3,
    fadj: I3,
    nrm: V3,
    thickness: F1,
    friction: F1,
    recover: REAL,
    release: REAL,
    contact_n: V3,
    contact_v: V3,
    h: REAL,
    react: ti.types.ndarray(ndim=1),
    count: F1,
    use_friction: ti.template(),
    exact: ti.template(),
):
    """Outer garments against the inner one (collide_layer_one), then the pushes they gave it.
    `exact` (parallel backends): `react` holds REACT_EXACT integers, summed in fixed point."""
    for i in x:
        collide_layer_one(i, x, xp, w, l_w, tri, faces, fadj, nrm, thickness, friction, recover,
                          release, contact_n, contact_v, h, react, count, use_friction, exact)
    for i in x:
        apply_react_one(i, x, react, count, exact)


@ti.kernel
def collider_bounds(b0: V3, b1: V3, shift: vec3, used: I1, box: V3, serialize: ti.template()):
    """box[0], box[1]: the lowest and highest corner of the `used` collider vertices at both
    b0 and b1 - shift (the grid's extent, in its coordinates, which move with the body's mean
    motion `shift` over the frame: count_triangle). Minima and maxima do not depend on the
    order threads run; `serialize` on a serial backend makes the atomics plain (numpy took 1
    ms for a body: it reduces the first axis of an (N, 3) array slowly)."""
    box[0] = vec3(3.0e38)
    box[1] = vec3(-3.0e38)
    ti.loop_config(serialize=serialize)
    for k in range(used.shape[0]):
        i = used[k]
        for c in ti.static(range(3)):
            ti.atomic_min(box[0][c], ti.min(b0[i][c], b1[i][c] - shift[c]))
            ti.atomic_max(box[1][c], ti.max(b0[i][c], b1[i][c] - shift[c]))


@ti.func
def first_cell(lo: vec3, origin: vec3, inv_cell: REAL) -> ti.math.ivec3:
    """The lowest grid cell of a box whose low corner is `lo`: grid_count and grid_fill file a
    triangle from here, and nearest_one measures it in the first of these cells it scans."""
    return ti.max(ti.cast(ti.floor((lo - origin) * inv_cell), ti.i32), 0)


@ti.func
def scanned_first(c: ti.math.ivec3, block: ti.math.ivec3, lo: vec3, origin: vec3,
                  inv_cell: REAL) -> bool:
    """Whether cell c is the first of a block of cells from corner `block` (scanned x, y, z
    from the lowest) that holds the triangle whose swept box starts at `lo`: searches measure a
    triangle filed in several of them there only."""
    c0 = first_cell(lo, origin, inv_cell)
    first = True
    for k in ti.static(range(3)):
        if c[k] != c0[k] and c[k] != block[k]:
            first = False
    return first


# The body grid is dense (`dims` cells along x, y, z) where that is small, which a body alone
# always is; a batch's lattice (datagen.sim.batch) spans every scene's motion and is hashed
# instead: dims = (0, table size - 1, 0), each cell's triangles in the bucket its coordinates
# hash to (hash_cell), shared with whatever other cells hash there. A search then also meets
# triangles of other cells, which its distance bounds cull.
@ti.func
def last_cell(hi: vec3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3) -> ti.math.ivec3:
    """The highest grid cell of a box whose high corner is `hi` (within a dense grid)."""
    c = ti.cast(ti.floor((hi - origin) * inv_cell), ti.i32)
    if dims[0] > 0:
        c = ti.min(c, dims - 1)
    return c


@ti.func
def grid_cell(c: ti.math.ivec3, dims: ti.math.ivec3) -> ti.i32:
    """Where cell c's triangles are listed: its index in a dense grid (-1 outside it), or its
    hash bucket."""
    cid = -1
    if dims[0] > 0:
        if (c[0] >= 0 and c[1] >= 0 and c[2] >= 0 and c[0] < dims[0] and c[1] < dims[1]
                and c[2] < dims[2]):
            cid = (c[0] * dims[1] + c[1]) * dims[2] + c[2]
    else:
        cid = hash_cell(c, dims[1])
    return cid


@ti.func
def count_triangle(
    t: ti.i32, b0: V3, b1: V3, shift0: vec3, shift1: vec3, faces: I3, origin: vec3,
    inv_cell: REAL, dims: ti.math.ivec3, counts: I1, travel: F1, bulge: F1, tbox: V8,
):
    """Triangle t's box swept from b0 - shift0 to b1 - shift1 into tbox[t], and one more in
    each cell it overlaps (grid_count). The grid's coordinates move with the body's mean motion
    over the frame (`shift`): a point p at frame fraction s is at p - shift s in them, and a
    body vertex's path b0 + (b1 - b0) s is at b0 + (b1 - shift - b0) s, a straight line from b0
    to b1 - shift whose box holds it all the way (shift0 = 0, shift1 = shift). A walking
    body's triangles sweep 4 cm a frame in the world, mostly with the torso: their boxes in
    moving coordinates fill 31 % fewer cells, and cloth that moves with the body stays near
    the cells its search scanned (nearest_one's guards). The depth QA's grid files the boxes
    at the frame's end (b0 = b1, shift0 = shift1 = shift). The body's vertices follow cubic
    paths, not the chords (interpolate_body_one): each box grows by the most its corners' paths
    stray from their chords (`bulge`, Collider.path_bounds; zero for the end grid), and
    `travel` bounds their speed along the paths."""
    f = faces[t]
    a0, a1, a2 = b0[f[0]] - shift0, b0[f[1]] - shift0, b0[f[2]] - shift0
    e0, e1, e2 = b1[f[0]] - shift1, b1[f[1]] - shift1, b1[f[2]] - shift1
    pad = ti.max(bulge[f[0]], bulge[f[1]], bulge[f[2]])
    lo = ti.min(ti.min(ti.min(a0, a1), ti.min(a2, e0)), ti.min(e1, e2)) - pad
    hi = ti.max(ti.max(ti.max(a0, a1), ti.max(a2, e0)), ti.max(e1, e2)) + pad
    speed = ti.max(travel[f[0]], travel[f[1]], travel[f[2]])
    tbox[t] = GUARD(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], speed, tbox[t][T_PART])
    c0 = first_cell(lo, origin, inv_cell)
    c1 = last_cell(hi, origin, inv_cell, dims)
    for cx in range(c0[0], c1[0] + 1):
        for cy in range(c0[1], c1[1] + 1):
            for cz in range(c0[2], c1[2] + 1):
                ti.atomic_add(counts[grid_cell(ti.math.ivec3(cx, cy, cz), dims)], 1)


@ti.func
def count_triangles(
    b0: V3, b1: V3, shift0: vec3, shift1: vec3, faces: I3, mask: I1, origin: vec3,
    inv_cell: REAL, dims: ti.math.ivec3, counts: I1, travel: F1, bulge: F1, tbox: V8,
    serialize: ti.template(),
):
    """count_triangle for every triangle the mask keeps: grid_count's loop, and the first of
    grid_build_serial's."""
    ti.loop_config(serialize=serialize)
    for t in range(faces.shape[0]):
        if mask[t] != 0:
            count_triangle(t, b0, b1, shift0, shift1, faces, origin, inv_cell, dims, counts,
                           travel, bulge, tbox)


@ti.kernel
def grid_count(
    b0: V3,
    b1: V3,
    shift0: vec3,
    shift1: vec3,
    faces: I3,
    mask: I1,
    origin: vec3,
    inv_cell: REAL,
    dims: ti.math.ivec3,
    counts: I1,
    travel: F1,
    bulge: F1,
    tbox: V8,
    serialize: ti.template(),
):
    """Count each cell's triangles (boxes swept over the frame, count_triangle), and keep each
    triangle's box and fastest corner's `travel` in `tbox` (lo xyz, hi xyz, travel, 0) for
    nearest_one. `serialize` on a serial backend: the counts' atomic adds become plain ones (a
    walking body's grid counted in 0.6 ms instead of 1.1)."""
    count_triangles(b0, b1, shift0, shift1, faces, mask, origin, inv_cell, dims, counts, travel,
                    bulge, tbox, serialize)


# Cells per block of the grid's prefix sum: blocks are summed in parallel, their sums prefixed
# serially, then each block filled in parallel. A serial pass over every cell was cheap for one
# body on a CPU, but a batch's lattice has millions of cells (datagen.sim.batch), and one GPU
# thread walking them would take longer than the frame's simulation.
PREFIX_BLOCK = 1024


@ti.kernel
def prefix_block_sums(counts: I1, block_starts: I1, n: ti.i32):
    """block_starts[b + 1] = the sum of block b's counts (block_starts[0] is left to
    prefix_blocks)."""
    for b in range((n + PREFIX_BLOCK - 1) // PREFIX_BLOCK):
        total = 0
        for c in range(b * PREFIX_BLOCK, ti.min((b + 1) * PREFIX_BLOCK, n)):
            total += counts[c]
        block_starts[b + 1] = total


@ti.kernel
def prefix_blocks(block_starts: I1, n_blocks: ti.i32):
    """The blocks' sums into their exclusive prefix, in place (serial: a thousandth of the
    cells)."""
    ti.loop_config(serialize=True)
    for b in range(n_blocks):
        if b == 0:
            block_starts[0] = 0
        block_starts[b + 1] += block_starts[b]


@ti.kernel
def prefix_fill(counts: I1, block_starts: I1, starts: I1, n: ti.i32):
    """Each block's exclusive prefix from its start, and its counts cleared (grid_fill uses
    them as cursors); starts[n] is the total."""
    for b in range((n + PREFIX_BLOCK - 1) // PREFIX_BLOCK):
        run = block_starts[b]
        for c in range(b * PREFIX_BLOCK, ti.min((b + 1) * PREFIX_BLOCK, n)):
            starts[c] = run
            run += counts[c]
            counts[c] = 0
    starts[n] = block_starts[(n + PREFIX_BLOCK - 1) // PREFIX_BLOCK]


def grid_prefix(counts, starts, n_cells: int, block_starts) -> None:
    """Exclusive prefix sum of the first n_cells counts into starts (n_cells + 1 entries), the
    counts cleared; `block_starts` holds at least n_cells / PREFIX_BLOCK + 2 entries."""
    n_blocks = -(-n_cells // PREFIX_BLOCK)
    prefix_block_sums(counts, block_starts, n_cells)
    prefix_blocks(block_starts, n_blocks)
    prefix_fill(counts, block_starts, starts, n_cells)


@ti.func
def file_triangle(
    t: ti.i32, tbox: V8, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3, counts: I1,
    starts: I1, items: I1, step: ti.template(),
):
    """File triangle t in each cell its box overlaps, at the cell's cursor in `counts`, which
    moves by `step`: +1 fills a cell upwards from its start (cursors from zero), -1 downwards
    from its end (cursors from the cell's count, which end at zero)."""
    tb = tbox[t]
    lo = vec3(tb[0], tb[1], tb[2])
    hi = vec3(tb[3], tb[4], tb[5])
    c0 = first_cell(lo, origin, inv_cell)
    c1 = last_cell(hi, origin, inv_cell, dims)
    for cx in range(c0[0], c1[0] + 1):
        for cy in range(c0[1], c1[1] + 1):
            for cz in range(c0[2], c1[2] + 1):
                cell = grid_cell(ti.math.ivec3(cx, cy, cz), dims)
                slot = ti.atomic_add(counts[cell], step)
                if ti.static(step < 0):
                    slot += step
                items[starts[cell] + slot] = t


@ti.kernel
def grid_fill(
    mask: I1,
    tbox: V8,
    origin: vec3,
    inv_cell: REAL,
    dims: ti.math.ivec3,
    counts: I1,
    starts: I1,
    items: I1,
    serialize: ti.template(),
):
    """File each triangle in the cells its box (from grid_count's `tbox`) overlaps; serialized
    as grid_count (a serial fill also files each cell's triangles in index order)."""
    ti.loop_config(serialize=serialize)
    for t in range(mask.shape[0]):
        if mask[t] != 0:
            file_triangle(t, tbox, origin, inv_cell, dims, counts, starts, items, 1)


@ti.kernel
def grid_build_serial(
    b0: V3,
    b1: V3,
    shift0: vec3,
    shift1: vec3,
    faces: I3,
    mask: I1,
    origin: vec3,
    inv_cell: REAL,
    dims: ti.math.ivec3,
    n_cells: ti.i32,
    counts: I1,
    travel: F1,
    bulge: F1,
    tbox: V8,
    starts: I1,
    items: I1,
) -> ti.i32:
    """grid_count, grid_prefix and grid_fill in one launch, for serial backends (their seven
    launches and a read of the total cost about 0.8 ms a frame in Taichi's Python there; this one
    0.1-0.2 ms for the tube's cylinder). The same grid to the last entry: triangles filed in
    descending order, each cell filled downwards from its end, list each cell in ascending
    order as the serial grid_fill does. Returns the number of entries; where `items` is too
    short for them nothing is filed (the caller grows it and calls again). `counts` end at zero
    either way."""
    count_triangles(b0, b1, shift0, shift1, faces, mask, origin, inv_cell, dims, counts, travel,
                    bulge, tbox, True)
    run = 0
    ti.loop_config(serialize=True)
    for c in range(n_cells):
        starts[c] = run
        run += counts[c]
    starts[n_cells] = run
    if run > items.shape[0]:
        for c in range(n_cells):
            counts[c] = 0
    else:
        n_faces = faces.shape[0]
        for m in range(n_faces):
            t = n_faces - 1 - m
            if mask[t] != 0:
                file_triangle(t, tbox, origin, inv_cell, dims, counts, starts, items, -1)
    return run


@ti.func
def sort_cells(starts: I1, items: I1, n_cells: ti.i32):
    """Each cell's list of a grid (items[starts[c]:starts[c + 1]]) in ascending order, one
    cell per thread: a grid filled by atomic cursors lists a cell in whatever order threads
    reached it. Insertion sort: a cell holds a few entries."""
    for c in range(n_cells):
        for q in range(starts[c] + 1, starts[c + 1]):
            v = items[q]
            k = q
            while k > starts[c] and items[k - 1] > v:
                items[k] = items[k - 1]
                k -= 1
            items[k] = v


@ti.kernel
def grid_sort(starts: I1, items: I1, n_cells: ti.i32):
    """Each cell's triangles in index order (sort_cells). The closest-triangle search keeps
    the first of equally near triangles (the several that share a vertex nearest a point), so
    after a parallel grid_fill a GPU's contacts, and a chaotic sequence with them, could differ
    from run to run. A serial fill already files them in index order (the caller skips this
    there)."""
    sort_cells(starts, items, n_cells)


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


# -- one launch per frame (CPU) ----------------------------------------------------------------
# Scalars of the fused frame kernel, packed into two small arrays: a kernel takes at most 64
# argument elements on the x64 backend, and the fused kernel needs every array of the solver.
P_H, P_OMEGA, P_RECOVER, P_ODO, P_CELL, P_INV_CELL = range(6)
P_GRAVITY, P_WIND, P_ORIGIN, P_L_ORIGIN = 6, 9, 12, 15  # 3 values each
P_S_INV_CELL, P_S_RADIUS, P_S_MIN_REST, P_L_INV_CELL, P_L_CELL, P_TRAVEL = range(18, 24)
P_L_ODO, P_L_TRAVEL, P_TAG, P_L_TAG = 24, 25, 26, 27
P_SHIFT, P_L_SHIFT = 28, 31  # 3 values each
P_OMEGA_REVERSE = 34  # the reverse sweeps' over-relaxation (XPBDSolver._sweep_sor)
P_SIZE = 35
Q_N_SUB, Q_N_ITER, Q_SWEEP0, Q_N_SETS, Q_N_BENDS, Q_N_PINS, Q_S_MASK = range(7)
Q_DIMS, Q_L_DIMS = 7, 10  # 3 values each
Q_N_TETHERS = 13
Q_N_STIFF_BENDS = 14
Q_FACES, Q_N_FACES = 15, 16  # the cloth's faces in `adj` (pressure drag): first entry, count
Q_SIZE = 17


@ti.kernel
def limit_after_contact_listed(
    x: V3, w: F1, springs: I2, limit: F1, contact_n: V3, adj: I1, lists: I1
) -> ti.i32:
    """limit_after_contact_active in a launch of its own (per-effect runs); collide_listed
    then clears the moved vertices' flags. One serial task: its sweeps append to shared lists,
    which a parallel loop would corrupt."""
    n_moved = 0
    ti.loop_config(serialize=True)
    for _ in range(1):
        n_moved = limit_after_contact_active(x, w, springs, limit, contact_n, adj, lists)
    return n_moved


@ti.func
def hermite3(a: vec3, b: vec3, ma: vec3, mb: vec3, s: REAL) -> vec3:
    """The cubic Hermite curve from a to b with end tangents ma, mb (per frame) at fraction s,
    written as the chord's lerp plus the tangents' departure from the chord: where ma = mb =
    b - a it is the lerp, and at rest (all equal, tangents zero) exactly a."""
    d = b - a
    return lerp3(a, b, s) + (s * (1.0 - s)) * ((1.0 - s) * (ma - d) - s * (mb - d))


@ti.func
def interpolate_body_one(j: ti.i32, b0: V3, b1: V3, n0: V3, n1: V3, s0: REAL, s1: REAL,
                         bs0: V3, bs1: V3, ns1: V3):
    """Body vertex j at a substep's start and end, and its normal at the end. The positions
    follow the frame's cubic Hermite path (Collider.set_frames keeps the frame's end tangents
    in bs0 after the body's vertices: bs0[n + j] at its start, bs0[2n + j] at its end), so the
    body's velocity is continuous across frames: along the frames' chords it jumped at each
    one, and cloth held by friction slipped at every jump (docs/simulator.md, "The body's path
    within a frame"). Normals stay linear: they only give directions."""
    nb = b0.shape[0]
    ma = bs0[nb + j]
    mb = bs0[2 * nb + j]
    bs0[j] = hermite3(b0[j], b1[j], ma, mb, s0)
    bs1[j] = hermite3(b0[j], b1[j], ma, mb, s1)
    ns1[j] = lerp3(n0[j], n1[j], s1)


@ti.kernel
def interpolate_body(b0: V3, b1: V3, n0: V3, n1: V3, used: I1, s0: REAL, s1: REAL, bs0: V3,
                     bs1: V3, ns1: V3, serialize: ti.template()):
    """interpolate_body_one at the colliding faces' vertices, as xpbd_frame does each substep
    (collide_body and collide_listed then take them)."""
    ti.loop_config(serialize=serialize)
    for u in range(used.shape[0]):
        interpolate_body_one(used[u], b0, b1, n0, n1, s0, s1, bs0, bs1, ns1)


@ti.kernel
def collide_listed(
    x: V3, xp: V3, w: F1, tri: I1, faces: I3, fadj: I3, bs0: V3, bs1: V3, ns1: V3,
    thickness: F1, friction: F1, recover: REAL, release: REAL, contact_n: V3, contact_v: V3,
    h: REAL, lists: I1, n_moved: ti.i32, use_collision: ti.template(),
):
    """Contact without friction for the vertices limit_after_contact_active moved, clearing
    their flags; the body as collide_body takes it."""
    ti.loop_config(serialize=True)
    for q in range(n_moved):
        i = moved_by_limit(q, x.shape[0], lists)
        if ti.static(use_collision):
            collide_one(i, x, xp, w, tri, faces, fadj, bs0, bs1, ns1, ns1, 0.0, 1.0, thickness,
                        friction, recover, release, contact_n, contact_v, h, False)


@ti.kernel
def xpbd_frame(
    x: V3,
    xp: V3,
    v: V3,
    w: F1,
    air: V4,
    springs: I2,
    rest: F1,
    limit: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    set_ranges: I2,
    bends: I4,
    bend_kk: V8,
    bend_step: V4,
    lam_b: V3,
    stiff_bends: I1,
    pin_idx: I1,
    pin_t0: V3,
    pin_t1: V3,
    tethers: I2,
    tether_len: F1,
    tri: I1,
    faces: I3,
    fadj: I3,
    b0: V3,
    b1: V3,
    n0: V3,
    n1: V3,
    bs0: V3,
    bs1: V3,
    ns1: V3,
    body_used: I1,
    thickness: F1,
    friction: F1,
    contact_n: V3,
    contact_v: V3,
    starts: I1,
    items: I1,
    guard: V8,
    tbox: V8,
    s_owner: I1,
    s_rest: V3,
    s_counts: I1,
    s_starts: I1,
    s_items: I1,
    l_w: F1,
    l_tri: I1,
    l_guard: V8,
    l_tbox: V8,
    l_faces: I3,
    l_fadj: I3,
    l_b0: V3,
    l_b1: V3,
    l_nrm: V3,
    l_react: V4,
    l_count: F1,
    l_starts: I1,
    l_items: I1,
    adj: I1,
    lists: I1,
    P: F1,
    Q: I1,
    use_gravity: ti.template(),
    use_air: ti.template(),
    use_pressure: ti.template(),
    use_collision: ti.template(),
    use_friction: ti.template(),
    use_layers: ti.template(),
    use_self: ti.template(),
):
    """All substeps of one frame of the XPBD solver in one serial launch: the same per-element
    functions, in the same order, as the per-effect kernels (which profiling runs use), without
    a Python round trip per kernel. Its 64 non-template arguments are Taichi's limit on x64: a
    new array has to share one with another (as `adj` and `lists` pack several)."""
    h = P[P_H]
    inv_h = 1.0 / h  # the sweeps scale compliance and damping by it, never dividing by h
    omega = P[P_OMEGA]
    omega_reverse = P[P_OMEGA_REVERSE]
    recover = P[P_RECOVER]
    odo0 = P[P_ODO]
    body_travel = P[P_TRAVEL]
    cell = P[P_CELL]
    inv_cell = P[P_INV_CELL]
    gravity = vec3(P[P_GRAVITY], P[P_GRAVITY + 1], P[P_GRAVITY + 2])
    wind = vec3(P[P_WIND], P[P_WIND + 1], P[P_WIND + 2])
    origin = vec3(P[P_ORIGIN], P[P_ORIGIN + 1], P[P_ORIGIN + 2])
    l_origin = vec3(P[P_L_ORIGIN], P[P_L_ORIGIN + 1], P[P_L_ORIGIN + 2])
    s_inv_cell = P[P_S_INV_CELL]
    s_radius = P[P_S_RADIUS]
    s_min_rest = P[P_S_MIN_REST]
    l_inv_cell = P[P_L_INV_CELL]
    l_cell = P[P_L_CELL]
    l_odo0 = P[P_L_ODO]
    l_travel = P[P_L_TRAVEL]
    tag = P[P_TAG]
    l_tag = P[P_L_TAG]
    shift = vec3(P[P_SHIFT], P[P_SHIFT + 1], P[P_SHIFT + 2])
    l_shift = vec3(P[P_L_SHIFT], P[P_L_SHIFT + 1], P[P_L_SHIFT + 2])
    n_sub = Q[Q_N_SUB]
    n_iter = Q[Q_N_ITER]
    sweep0 = Q[Q_SWEEP0]
    n_sets = Q[Q_N_SETS]
    n_bends = Q[Q_N_BENDS]
    n_stiff = Q[Q_N_STIFF_BENDS]
    n_pins = Q[Q_N_PINS]
    n_tethers = Q[Q_N_TETHERS]
    s_mask = Q[Q_S_MASK]
    dims = ti.math.ivec3(Q[Q_DIMS], Q[Q_DIMS + 1], Q[Q_DIMS + 2])
    l_dims = ti.math.ivec3(Q[Q_L_DIMS], Q[Q_L_DIMS + 1], Q[Q_L_DIMS + 2])
    n = x.shape[0]
    ti.loop_config(serialize=True)
    for k in range(n_sub):
        s0 = k / n_sub
        s1 = (k + 1) / n_sub
        if ti.static(use_pressure):  # as set_pressure_vectors, in the same order
            for i in range(n):
                pressure_clear_one(i, air)
            for t in range(Q[Q_N_FACES]):
                q = Q[Q_FACES] + 3 * t
                pressure_face_add(adj[q], adj[q + 1], adj[q + 2], x, air)
        for i in range(n):
            predict_one(i, x, xp, v, w, air, gravity, wind, h, use_gravity, use_air,
                        use_pressure)
        # Pinned vertices reach their targets before the constraints, which then pull the
        # fabric after them (moved afterwards, they would leave the edges next to them stretched).
        for p in range(n_pins):
            x[pin_idx[p]] = lerp3(pin_t0[p], pin_t1[p], s1)
        for e in range(springs.shape[0]):
            lam[e] = 0.0
        for b in range(n_bends):
            lam_b[b] = vec3(0.0)
        for it in range(n_iter):
            reverse = (sweep0 + k * n_iter + it) % 2
            omega_s = omega  # this sweep's over-relaxation, by direction
            if reverse != 0:
                omega_s = omega_reverse
            # Bending before the springs: every bend in the first sweep, the stiff ones in every
            # sweep (see XPBDSolver.substep).
            nb = n_bends
            if it > 0:
                nb = n_stiff
            # The stiff bends' later sweeps are plain Gauss-Seidel: over-relaxed, their damping
            # (which reads the earlier sweeps' displacement as velocity) ran the fast kick's
            # trousers away (83 m/s at frame 35).
            omega_b = omega_s
            if it > 0:
                omega_b = 1.0
            for m in range(nb):
                b = sweep_order(m, nb, reverse)
                if it > 0:
                    b = stiff_bends[b]
                bend_gs_one(b, x, xp, bends, bend_kk, bend_step, lam_b, omega_b)
            for si in range(n_sets):
                lo = set_ranges[si][0]
                hi = set_ranges[si][1]
                for m in range(hi - lo):
                    e = lo + m
                    if reverse != 0:
                        e = hi - 1 - m
                    spring_gs_one(
                        e, x, xp, w, springs, rest, limit, comp_t, comp_c, beta, lam, inv_h,
                        omega_s,
                    )
        # After the sweeps: what they left beyond a tether goes back onto it before contact.
        for t in range(n_tethers):
            tether_one(t, x, tethers, tether_len)
        if ti.static(use_collision):
            # The body at this substep's start and end, once, instead of per cloth vertex, at
            # the colliding faces' vertices (a walking body's 9,313 of 13,348).
            for u in range(body_used.shape[0]):
                interpolate_body_one(body_used[u], b0, b1, n0, n1, s0, s1, bs0, bs1, ns1)
            for i in range(n):
                contact_n[i] = vec3(0.0)
                contact_v[i] = vec3(0.0)
            for i in range(n):
                nearest_one(
                    i, x, w, bs1, bs1, faces, origin, inv_cell, dims, starts, items, 1.0, cell,
                    tri, SEARCH_UNTRACKED, guard, odo0 + s1 * body_travel, tag, s1, shift, tbox,
                    P, P_SIZE,
                )
            for i in range(n):
                collide_one(
                    i,
                    x,
                    xp,
                    w,
                    tri,
                    faces,
                    fadj,
                    bs0,
                    bs1,
                    ns1,
                    ns1,
                    0.0,
                    1.0,
                    thickness,
                    friction,
                    recover,
                    2.0 * cell,
                    contact_n,
                    contact_v,
                    h,
                    use_friction,
                )
        if ti.static(use_layers):
            # Outer garments against the inner one's surface: candidates from its path predicted
            # for the frame, contact against where it is now, both pushed back.
            for i in range(n):
                nearest_one(
                    i, x, l_w, l_b0, l_b1, l_faces, l_origin, l_inv_cell, l_dims, l_starts,
                    l_items, s1, l_cell, l_tri, SEARCH_UNTRACKED, l_guard,
                    l_odo0 + s1 * l_travel, l_tag, s1, l_shift, l_tbox, P, -1,
                )
            for i in range(n):
                vertex_normal_clear_one(i, l_nrm)
            for t in range(l_faces.shape[0]):
                vertex_normal_add_one(t, x, l_faces, l_nrm)
            for i in range(n):
                vertex_normal_finish_one(i, l_nrm)
            for i in range(n):
                collide_layer_one(
                    i, x, xp, w, l_w, l_tri, l_faces, l_fadj, l_nrm, thickness, friction,
                    recover, 2.0 * l_cell, contact_n, contact_v, h, l_react, l_count,
                    use_friction, False,
                )
            for i in range(n):
                apply_react_one(i, x, l_react, l_count, False)
        if ti.static(use_self):
            self_hash_build(x, s_counts, s_starts, s_items, s_inv_cell, s_mask)
            for i in range(n):
                self_collide_one(
                    i, x, xp, w, s_owner, s_rest, s_starts, s_items, s_inv_cell, s_mask,
                    s_radius, s_min_rest, recover,
                )
        if ti.static(use_collision or use_layers):
            n_moved = 0
            if n_sets > 0:
                n_moved = limit_after_contact_active(x, w, springs, limit, contact_n, adj, lists)
            for q in range(n_moved):
                i = moved_by_limit(q, n, lists)
                if ti.static(use_collision):
                    # Contact again, without friction, for what the limit moved into the body
                    # (see ClothSolver._limit_after_contact).
                    collide_one(
                        i, x, xp, w, tri, faces, fadj, bs0, bs1, ns1, ns1, 0.0, 1.0,
                        thickness, friction, recover, 2.0 * cell, contact_n, contact_v, h,
                        False,
                    )
        for i in range(n):
            finish_one(i, x, xp, v, w, contact_n, contact_v, h)


@ti.func
def hint_bound(p: vec3, t: ti.i32, b: V3, faces: I3, mask: I1, best: REAL, best_t: ti.i32):
    """The nearer of the best so far (squared distance, triangle) and hint triangle t, which
    counts only if it is a filed triangle."""
    if t >= 0 and t < faces.shape[0]:
        if mask[t] != 0:
            f = faces[t]
            r = closest_on_triangle(p, b[f[0]], b[f[1]], b[f[2]])
            if r[3] < best:
                best = r[3]
                best_t = t
    return best, best_t


# -- inside or outside, beyond a cell of the surface ---------------------------------------------
# The depth QA's search finds no filed triangle within a cell for a point more than a cell deep
# inside the body as for one a cell away outside it. A closed collider (the whole body mesh, which
# is watertight) answers which by counting the crossings of a ray from the point along RAY_AXIS
# with its triangles, filed in columns across the ray (column_grid_build): +1 where the ray leaves
# the surface, -1 where it enters, so the sum is the point's winding number (two where the body's
# own skinning overlaps, still inside). The ray runs along y, a standing body's front-to-back
# axis, its thinnest: the columns then hold the fewest triangles.
RAY_AXIS = 1
_RI = (RAY_AXIS + 1) % 3  # the columns' two coordinates, cyclic after the ray's (so that a
_RJ = (RAY_AXIS + 2) % 3  # triangle's projected area has the sign of its normal along the ray)


@ti.func
def column_index(p: vec3, origin: vec3, inv_cell: REAL) -> ti.math.ivec2:
    """The column coordinates of point p (column_grid_build's), unbounded."""
    return ti.math.ivec2(ti.cast(ti.floor((p[_RI] - origin[_RI]) * inv_cell), ti.i32),
                         ti.cast(ti.floor((p[_RJ] - origin[_RJ]) * inv_cell), ti.i32))


@ti.func
def column_of(p: vec3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3) -> ti.i32:
    """The column holding point p, or -1 outside the grid."""
    ij = column_index(p, origin, inv_cell)
    c = -1
    if 0 <= ij[0] < dims[0] and 0 <= ij[1] < dims[1]:
        c = ij[0] * dims[1] + ij[1]
    return c


@ti.func
def triangle_columns(b: V3, f: ti.math.ivec3, origin: vec3, inv_cell: REAL,
                     dims: ti.math.ivec3) -> ti.math.ivec4:
    """The columns a triangle's projected box overlaps: (first, last) of each coordinate."""
    lo = column_index(ti.min(b[f[0]], b[f[1]], b[f[2]]), origin, inv_cell)
    hi = column_index(ti.max(b[f[0]], b[f[1]], b[f[2]]), origin, inv_cell)
    return ti.math.ivec4(ti.max(lo[0], 0), ti.min(hi[0], dims[0] - 1),
                         ti.max(lo[1], 0), ti.min(hi[1], dims[1] - 1))


@ti.func
def count_columns(b: V3, faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3,
                  counts: I1, spans: I4, serialize: ti.template()):
    """Each column's number of triangles (column_grid_build), from zero, and each triangle's
    columns in `spans`."""
    ti.loop_config(serialize=serialize)
    for c in range(dims[0] * dims[1]):
        counts[c] = 0
    ti.loop_config(serialize=serialize)
    for t in range(faces.shape[0]):
        span = triangle_columns(b, faces[t], origin, inv_cell, dims)
        spans[t] = span
        for i in range(span[0], span[1] + 1):
            for j in range(span[2], span[3] + 1):
                ti.atomic_add(counts[i * dims[1] + j], 1)


@ti.func
def fill_columns(spans: I4, dims: ti.math.ivec3, counts: I1, starts: I1, items: I1,
                 serialize: ti.template()):
    """File each triangle in its columns from their starts, `counts` zero on entry (cursors).
    The order of a column's list does not matter: its crossings are summed as integers."""
    ti.loop_config(serialize=serialize)
    for t in range(spans.shape[0]):
        span = spans[t]
        for i in range(span[0], span[1] + 1):
            for j in range(span[2], span[3] + 1):
                c = i * dims[1] + j
                items[starts[c] + ti.atomic_add(counts[c], 1)] = t


@ti.kernel
def column_grid_build(b: V3, faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3,
                      counts: I1, starts: I1, spans: I4, items: I1) -> ti.i32:
    """File every triangle of the collider at `b` in each column (a square of the plane across
    RAY_AXIS, `dims[0]` x `dims[1]` of them from `origin`) its projected box overlaps, in one
    launch, for serial backends (`spans`: scratch, a triangle's columns between the count and
    the fill). Returns the number of entries; where `items` is too short for them nothing is
    filed (the caller grows it and calls again). Parallel backends count (column_count), sum
    (grid_prefix) and fill (column_fill) in three launches."""
    count_columns(b, faces, origin, inv_cell, dims, counts, spans, True)
    n_cols = dims[0] * dims[1]
    run = 0
    ti.loop_config(serialize=True)
    for c in range(n_cols):
        starts[c] = run
        run += counts[c]
        counts[c] = 0  # the fill's cursors
    starts[n_cols] = run
    if run <= items.shape[0]:
        fill_columns(spans, dims, counts, starts, items, True)
    return run


@ti.kernel
def column_count(b: V3, faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3,
                 counts: I1, spans: I4):
    count_columns(b, faces, origin, inv_cell, dims, counts, spans, False)


@ti.kernel
def column_fill(spans: I4, dims: ti.math.ivec3, counts: I1, starts: I1, items: I1):
    fill_columns(spans, dims, counts, starts, items, False)


@ti.func
def edge_side(u: vec3, v: vec3, p: vec3, iu: ti.i32, iv: ti.i32) -> REAL:
    """Which side of the projected edge u -> v (body vertices iu, iv) point p lies on (the
    plane across RAY_AXIS; positive to the left), never zero. Evaluated from the lower-numbered
    end, so that the two triangles sharing an edge, which run it in opposite directions, get
    exactly opposite values; a point on the edge is given to one of them, as if moved by an
    infinitesimal step along the column's first coordinate, or its second where the edge runs
    along the first (a ray through an edge or a vertex then crosses the surface once)."""
    sign = 1.0
    a = u
    e = v
    if iv < iu:
        sign = -1.0
        a = v
        e = u
    s = (e[_RI] - a[_RI]) * (p[_RJ] - a[_RJ]) - (e[_RJ] - a[_RJ]) * (p[_RI] - a[_RI])
    if s == 0.0:
        s = -(e[_RJ] - a[_RJ])
        if s == 0.0:
            s = e[_RI] - a[_RI]
    return sign * s


@ti.func
def winding_along_ray(p: vec3, b: V3, faces: I3, starts: I1, items: I1, origin: vec3,
                      inv_cell: REAL, dims: ti.math.ivec3) -> ti.i32:
    """The winding number of the collider at `b` (closed, outward) around point p: its signed
    crossings with the ray from p along +RAY_AXIS, through the triangles of p's column."""
    w = 0
    c = column_of(p, origin, inv_cell, dims)
    if c >= 0:
        for q in range(starts[c], starts[c + 1]):
            t = items[q]
            f = faces[t]
            ta = b[f[0]]
            tb = b[f[1]]
            tc = b[f[2]]
            # Most of a column's triangles miss the ray: their box does (a point on the box's
            # edge goes on to the exact test).
            lo = ti.min(ta, tb, tc)
            hi = ti.max(ta, tb, tc)
            if (hi[RAY_AXIS] > p[RAY_AXIS] and lo[_RI] <= p[_RI] <= hi[_RI]
                    and lo[_RJ] <= p[_RJ] <= hi[_RJ]):
                s0 = edge_side(tb, tc, p, f[1], f[2])
                s1 = edge_side(tc, ta, p, f[2], f[0])
                s2 = edge_side(ta, tb, p, f[0], f[1])
                # Inside the projected triangle: on the same side of its three edges.
                if (s0 > 0 and s1 > 0 and s2 > 0) or (s0 < 0 and s1 < 0 and s2 < 0):
                    area = s0 + s1 + s2
                    along = (s0 * ta[RAY_AXIS] + s1 * tb[RAY_AXIS] + s2 * tc[RAY_AXIS]) / area
                    if along > p[RAY_AXIS]:
                        w += 1 if area > 0 else -1
    return w


@ti.kernel
def grid_signed_distance(x: V3, hint: I1, last: I1, b: V3, n: V3, faces: I3, mask: I1,
                         origin: vec3, inv_cell: REAL, dims: ti.math.ivec3, shift: vec3,
                         starts: I1, items: I1, tbox: V8, far: REAL, out: F1,
                         closed: ti.template(), col_starts: I1, col_items: I1, col_origin: vec3,
                         col_inv_cell: REAL, col_dims: ti.math.ivec3, outward: ti.i32,
                         serialize: ti.template()):
    """Signed distance of each point to its closest collider triangle at the end of the frame
    (`b`, vertex normals `n` for the sign), searching the 27 grid cells around it. Where no
    triangle is within `far` (one cell): `far`, or `-far` inside a `closed` collider (the
    winding number of its whole mesh, `outward` 1 or -1 as its triangles face, through the
    column grid `col_*` of column_grid_build). The grid (`starts`, `items`, `tbox`) must file each
    triangle in the cells of its box at `b`, in the grid's coordinates (b - shift: the frame's
    end in coordinates that move with the body's mean motion, count_triangle): BodyCollider
    passes its grid of the end boxes, which fills about half the cells that the solver's boxes
    swept over the frame do. Two hints per point (a triangle, or -1) only start the search:
    `hint` (the depth QA passes the solver's tracked triangles) and `last`, the closest triangle
    of the previous call, which the call then overwrites (the cloth that the solver does not
    track, within a cell of the body, moves less than a cell a frame). The nearer one bounds the
    search, so that a point a few millimetres from the body scans the one to four cells within
    that distance instead of 27: a third of the time on a walking t-shirt and half on a draped
    sheet. A hint that is not a filed triangle (`mask`) is ignored, and the result does not
    depend on the hints, except between equally near triangles. `serialize` on serial backends
    (see copy_in)."""
    ti.loop_config(serialize=serialize)
    for i in range(x.shape[0]):
        p = x[i]
        best, best_t = hint_bound(p, hint[i], b, faces, mask, far * far, -1)
        best, best_t = hint_bound(p, last[i], b, faces, mask, best, best_t)
        reach = ti.sqrt(best) + 1e-6
        bound = reach * reach
        # Only the cells within `reach` of p, of the 27 around it: where the hint tracks the
        # body a millimetre away, one to four instead of 27.
        p_grid = p - shift
        cell = ti.cast(ti.floor((p_grid - origin) * inv_cell), ti.i32)
        lo = ti.max(ti.cast(ti.floor((p_grid - reach - origin) * inv_cell), ti.i32), cell - 1)
        hi = ti.min(ti.cast(ti.floor((p_grid + reach - origin) * inv_cell), ti.i32), cell + 1)
        # Nested loops, in the order a flat index would give: one index divided by the
        # runtime spans cost three integer divisions a cell, 40 % of a far point's scan.
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                for cz in range(lo[2], hi[2] + 1):
                    c = ti.math.ivec3(cx, cy, cz)
                    cid = grid_cell(c, dims)
                    if cid >= 0:
                        for q in range(starts[cid], starts[cid + 1]):
                            t = items[q]
                            tb = tbox[t]
                            swept = ti.max(vec3(tb[0], tb[1], tb[2]) - p_grid, 0.0,
                                           p_grid - vec3(tb[3], tb[4], tb[5]))
                            if (swept.norm_sqr() <= bound
                                    and scanned_first(c, lo, vec3(tb[0], tb[1], tb[2]), origin,
                                                      inv_cell)):
                                f = faces[t]
                                ta = b[f[0]]
                                tb_ = b[f[1]]
                                tc = b[f[2]]
                                box = ti.max(ti.min(ta, tb_, tc) - p, 0.0,
                                             p - ti.max(ta, tb_, tc))
                                if box.norm_sqr() <= bound:
                                    r = closest_on_triangle(p, ta, tb_, tc)
                                    if r[3] < best:
                                        best = r[3]
                                        best_t = t
                                        reach = ti.sqrt(best) + 1e-6
                                        bound = reach * reach
        last[i] = best_t
        d = far
        if best_t < 0:
            # Nothing filed within a cell: a cell or more from the surface, on the side the
            # ray's crossings give (a collider that is not closed has no inside to count).
            if ti.static(closed):
                if outward * winding_along_ray(p, b, faces, col_starts, col_items, col_origin,
                                               col_inv_cell, col_dims) > 0:
                    d = -far
        else:
            f = faces[best_t]
            r = closest_on_triangle(p, b[f[0]], b[f[1]], b[f[2]])
            q = r[0] * b[f[0]] + r[1] * b[f[1]] + r[2] * b[f[2]]
            nrm = r[0] * n[f[0]] + r[1] * n[f[1]] + r[2] * n[f[2]]
            nl = nrm.norm()
            if nl > 1e-12:
                d = (p - q).dot(nrm / nl)
        out[i] = d


# -- cloth self-collision ----------------------------------------------------------------------
@ti.func
def hash_cell(c: ti.math.ivec3, mask: ti.i32) -> ti.i32:
    return ((c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)) & mask


@ti.func
def self_cell(p: vec3, inv_cell: REAL, mask: ti.i32) -> ti.i32:
    """The hashed self-collision cell holding point p."""
    return hash_cell(ti.cast(ti.floor(p * inv_cell), ti.i32), mask)


@ti.func
def self_hash_build(x: V3, counts: I1, starts: I1, items: I1, inv_cell: REAL, mask: ti.i32):
    """Counting sort of the cloth vertices into a hashed grid (serial loops: called from serial
    kernels, or as separate tasks by `self_collide`)."""
    for c in range(mask + 1):
        counts[c] = 0
    for i in range(x.shape[0]):
        c = self_cell(x[i], inv_cell, mask)
        counts[c] += 1
    starts[0] = 0
    for c in range(mask + 1):
        starts[c + 1] = starts[c] + counts[c]
        counts[c] = 0
    for i in range(x.shape[0]):
        c = self_cell(x[i], inv_cell, mask)
        items[starts[c] + counts[c]] = i
        counts[c] += 1


@ti.func
def self_pair_target(d_start: vec3, radius: REAL, recover: REAL) -> REAL:
    """The distance self-collision restores between two vertices of a fold that were `d_start`
    apart at the substep's start: the radius for a new approach, else `recover` farther than
    they were (a bounded speed of separation)."""
    target = radius
    d0 = d_start.norm_sqr()
    if d0 < radius * radius:
        target = ti.min(radius, ti.sqrt(d0) + recover)
    return target


@ti.func
def self_collide_one(i: ti.i32, x: V3, xp: V3, w: F1, owner: I1, rest: V3, starts: I1,
                     items: I1, inv_cell: REAL, mask: ti.i32, radius: REAL, min_rest: REAL,
                     recover: REAL):
    """Push vertex i and nearby vertices of the same garment apart to `radius`, unless they are
    near each other in the rest shape too (neighbours in the fabric, not a fold). A pair that
    came closer than `radius` during this substep is pushed apart to it (the approach undone);
    one already closer at the substep's start (xp) only to `recover` farther than it was then
    (self_pair_target), as a vertex inside the body recovers: pushed fully every substep, a
    fold held crushed by the body or another garment turned the same millimetres per substep
    into a speed that grew with the substeps (a cropped top tucked at a waistband in a kick: 20
    m/s at 160 substeps a frame, where 40 ran at 5).

    Cells are 2 * `radius` wide, so the neighbours within `radius` lie in the 2 x 2 x 2 cells
    that the box of half-width `radius` around the vertex touches: 8 cells instead of 27 of
    `radius`-wide cells, 40 % fewer candidates, and the pass 2.5x faster (the skirt-like tube,
    5,100 vertices: 1.3 -> 0.5 ms). Distances are compared squared; the square root is taken
    only for a pair that is pushed."""
    xi = x[i]
    oi = owner[i]
    r2 = radius * radius
    lo = ti.cast(ti.floor((xi - radius) * inv_cell), ti.i32)
    for nb in range(8):
        c = hash_cell(lo + ti.math.ivec3(nb // 4, (nb // 2) % 2, nb % 2), mask)
        for q in range(starts[c], starts[c + 1]):
            j = items[q]
            if j > i:
                d = x[j] - xi
                d2 = d.norm_sqr()
                if d2 < r2 and d2 > 1e-18 and owner[j] == oi:
                    wsum = w[i] + w[j]
                    if wsum > 0.0 and (rest[j] - rest[i]).norm() > min_rest:
                        dist = ti.sqrt(d2)
                        target = self_pair_target(xp[j] - xp[i], radius, recover)
                        if dist < target:
                            corr = (target - dist) / (dist * wsum) * d
                            x[i] -= w[i] * corr
                            x[j] += w[j] * corr
                            xi = x[i]


@ti.kernel
def self_collide(x: V3, xp: V3, w: F1, owner: I1, rest: V3, counts: I1, starts: I1,
                 items: I1, inv_cell: REAL, mask: ti.i32, radius: REAL, min_rest: REAL,
                 recover: REAL):
    ti.loop_config(serialize=True)
    for _ in range(1):
        self_hash_build(x, counts, starts, items, inv_cell, mask)
        for i in range(x.shape[0]):
            self_collide_one(i, x, xp, w, owner, rest, starts, items, inv_cell, mask, radius,
                             min_rest, recover)
