"""Taichi kernels of the cloth solvers' steps: prediction and finishing, the XPBD constraint
sweeps and strain limits, explicit forces, air drag, pins and tethers, state copies, and the
fused frame kernel (`xpbd_frame`) that runs a whole frame in one launch on a CPU. Data lives in
ndarrays owned by the solver objects.

The kernels a step calls live by job: `kernel_common` (ndarray types, the search guard,
point-triangle geometry), `grid_kernels` (the collider's grid), `search_kernels` (each vertex's
closest collider triangle), `contact_kernels` (contact with the body and with an inner
garment), `depth_kernels` (the depth QA), `self_collision_kernels`, and `parallel_kernels` (the
forms of these for parallel backends).

Every effect has its own kernel (or compile-time branch), so an effect that a scene does not need
is neither compiled nor launched. Constraint sweeps come in two flavours: Gauss-Seidel (serial,
the CPU default) and coloured Gauss-Seidel (one parallel loop per colour, for GPU backends).
"""

import taichi as ti

from datagen.sim.contact_kernels import (
    apply_react_one,
    collide_layer_one,
    collide_one,
    vertex_normal_add_one,
    vertex_normal_clear_one,
    vertex_normal_finish_one,
)
from datagen.sim.kernel_common import F1, I1, I2, I3, I4, V3, V4, V8, lerp3, vec3
from datagen.sim.model import PRESSURE_DRAG, PRESSURE_OFF, PRESSURE_OUTER_FACE
from datagen.sim.precision import REAL, VEC4
from datagen.sim.search_kernels import SEARCH_UNTRACKED, nearest_one
from datagen.sim.self_collision_kernels import self_collide_one, self_hash_build

# The strain limit's sweeps after contact (limit_after_contact_one): until no spring is more
# than the tolerance (relative) past its limit, at most this many. Over-relaxed constraint
# sweeps leave them more to do: at 4, 2 % of a tight sleeve's edges stayed up to 3 % past its
# limit (tests/test_sim_physics.py) and the heavy body's hard case failed; 16 full sweeps cost
# the walking t-shirt 3 % more time (xpbd's later sweeps visit only what moved: cheaper still).
AFTER_CONTACT_SWEEPS = 16
AFTER_CONTACT_TOLERANCE = 1e-3


# -- integration -------------------------------------------------------------------------------
# Each vertex's air terms, `air` (V4): its linear drag coefficient (kg/s: Blender's air damping
# times its rest area) and its pressure-drag vector (kg/m: 1/2 rho C_d times its vector area,
# a third of each adjacent face's area along the face's normal, at the substep's start; zero
# where pressure drag is off). See air_velocity and pressure_face_add.
@ti.func
def air_velocity(vi: vec3, air: VEC4, wi: REAL, wind: vec3, h: REAL, use_air: ti.template(),
                 use_pressure: ti.template()) -> vec3:
    """The velocity after a step h of air drag: the linear drag, then the pressure drag
    -c |v_n| v_n n on the normal part v_n of the velocity relative to the wind. Each implicit in
    the velocity it damps (with |v_n| taken at the step's start for the quadratic term), so
    neither can reverse a velocity at any step. `use_pressure` (model.PRESSURE_*): off, on both
    faces, or on the outer face only (cloth on a body: only a panel moving along its outward
    normal meets the free stream).
    The linear drag is Blender's velocity damping, relative to still air, and wind acts only
    through the pressure, along each panel's normal, as Blender's wind does: taken relative to
    the wind, the linear drag also dragged every panel along its own plane, by 0.3 N/m^2 in a
    2 m/s wind, about twenty times the air's skin friction there (docs/fabrics.md)."""
    if ti.static(use_air):
        vi = vi / (1.0 + h * air[0] * wi)
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


# A spring's per-step terms (XPBDSolver._use_step: set once per step size, like the bends'),
# one vector of eight a spring, read by spring_delta: its rest and limit lengths, its tension
# and compression compliances over h^2, its damping over h, the inverses of the update's
# denominator (1 + gamma) (w_i + w_j) + alpha for either compliance, and of w_i + w_j (zero
# where both ends are pinned: nothing moves). The division by the denominator was on each
# update's chain of dependent operations, which is what a serial sweep waits on.
ST_REST, ST_LIMIT, ST_ALPHA_T, ST_ALPHA_C, ST_GAMMA, ST_INV_DEN_T, ST_INV_DEN_C, ST_INV_W = range(8)


@ti.func
def spring_delta(x: V3, xp: V3, w: F1, springs: I2, terms: V8, lam: F1, e: ti.i32,
                 omega: REAL) -> VEC4:
    """XPBD update of spring e: (its correction, along the spring from x_i to x_j, which each
    end takes times its inverse mass; dlambda), the compliant part over-relaxed by omega. The
    terms come from `terms[e]` (ST_*). Past its limit length the
    spring is inextensible: the displacement also removes the excess, exactly (strain limiting;
    the multiplier keeps only the compliant part): an over-relaxed inequality would overshoot
    into compression. Where the compliant move dl would leave the spring longer than its limit,
    length + (w_i + w_j) dl > limit, the move is the one that brings it to the limit, so the
    move is the lesser of the two: a min, where a branch on the length after the move put two
    more dependent operations on the update's chain."""
    i = springs[e][0]
    j = springs[e][1]
    p = terms[e]
    out = VEC4(0.0)
    xi = x[i]
    xj = x[j]
    d = xj - xi
    len2 = d.norm_sqr()
    if p[ST_INV_W] > 0.0 and len2 > 1e-18:
        # The rate along the spring, times its length: taken before the square root is done.
        rate_len = d.dot((xj - xp[j]) - (xi - xp[i]))
        length = ti.sqrt(len2)
        inv_len = 1.0 / length
        c = length - p[ST_REST]
        compressed = c < 0.0
        alpha = ti.select(compressed, p[ST_ALPHA_C], p[ST_ALPHA_T])
        inv_den = ti.select(compressed, p[ST_INV_DEN_C], p[ST_INV_DEN_T])
        dl = omega * (-c - alpha * lam[e] - p[ST_GAMMA] * rate_len * inv_len) * inv_den
        move = ti.min(dl, (p[ST_LIMIT] - length) * p[ST_INV_W])
        dx = (move * inv_len) * d
        out = VEC4(dx[0], dx[1], dx[2], dl)
    return out


@ti.func
def sweep_order(k: ti.i32, n: ti.i32, reverse: ti.i32) -> ti.i32:
    """The k-th element of a Gauss-Seidel sweep over n, backwards when `reverse`."""
    e = k
    if reverse != 0:
        e = n - 1 - k
    return e


@ti.func
def spring_gs_one(e: ti.i32, x: V3, xp: V3, w: F1, springs: I2, terms: V8, lam: F1,
                  omega: REAL):
    r = spring_delta(x, xp, w, springs, terms, lam, e, omega)
    lam[e] += r[3]
    i = springs[e][0]
    j = springs[e][1]
    dx = vec3(r[0], r[1], r[2])
    x[i] -= w[i] * dx
    x[j] += w[j] * dx


@ti.kernel
def springs_gauss_seidel(x: V3, xp: V3, w: F1, springs: I2, terms: V8, lam: F1,
                         reverse: ti.i32, omega: REAL):
    n_springs = springs.shape[0]
    ti.loop_config(serialize=True)
    for k in range(n_springs):
        e = sweep_order(k, n_springs, reverse)
        spring_gs_one(e, x, xp, w, springs, terms, lam, omega)


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
    terms: V8,
    lam: F1,
    order: I1,
    colour_ptr: I1,
    reverse: ti.i32,
    omega: REAL,
    n_colours: ti.template(),
):
    """springs_gauss_seidel as one parallel loop per colour (`order`: spring indices sorted by
    colour, `colour_ptr`: n_colours + 1 offsets)."""
    for c in ti.static(range(n_colours)):
        r = colour_range(c, n_colours, reverse, colour_ptr)
        for k in range(r[0], r[1]):
            spring_gs_one(order[k], x, xp, w, springs, terms, lam, omega)


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
    terms: V8,
    limit: F1,
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
    a Python round trip per kernel. Its 61 non-template arguments are near Taichi's limit on
    x64, 64: a new array may have to share one with another (as `adj` and `lists` pack
    several)."""
    h = P[P_H]
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
                    spring_gs_one(e, x, xp, w, springs, terms, lam, omega_s)
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
