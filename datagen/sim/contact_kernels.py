"""Contact of cloth with a surface: the body (each vertex against its tracked closest triangle,
with thickness, friction and recovery from penetration) and the inner garment of a layered
outfit (a point-triangle contact that pushes the inner garment back), and the vertex normals
the layers' contact reads."""

import taichi as ti

from datagen.sim.kernel_common import (
    F1,
    I1,
    I3,
    V3,
    closest_on_triangle,
    lerp3,
    plane_barycentric,
    vec3,
)
from datagen.sim.precision import REAL, VEC4

WALK_STEPS = 8  # most triangles a cloth vertex's walk to its closest body triangle visits


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
