"""Taichi kernels of the implicit (backward Euler, Newton-PCG) solver. Matrix-free: the Hessian
is applied spring by spring and stencil by stencil, never assembled.

`newton_solve` runs a whole substep's Newton iterations, each with its conjugate-gradient solve,
in one serial launch (the reference runs take many small steps; a Python round trip per CG
iteration would dominate them). The per-element work lives in functions shared by nothing else.
"""

import taichi as ti

from datagen.sim.kernel_common import F1, I1, I2, I4, V3, V4, vec3
from datagen.sim.precision import MAT3, REAL

mat3 = MAT3
M3 = ti.types.ndarray(dtype=mat3, ndim=1)

# Scalars and counts of `newton_solve`, packed (a kernel takes at most 64 argument elements).
P_H, P_GRAVITY, P_TOL, P_CG_TOL = 0, 1, 4, 5
P_SIZE = 6
Q_N_SPRINGS, Q_N_BENDS, Q_NEWTON_MAX, Q_CG_MAX, Q_FORCING = range(5)
Q_SIZE = 5
S_NEWTON, S_CG, S_UNCONVERGED = range(3)  # statistics written back


@ti.func
def spring_hessian(d: vec3, rest: REAL, k: REAL) -> mat3:
    """Hessian block of 1/2 k (|d| - rest)^2, projected to be positive semi-definite."""
    length = d.norm()
    out = ti.Matrix.zero(REAL, 3, 3)
    if length > 1e-9:
        n = d / length
        nn = n.outer_product(n)
        coef = ti.max(1.0 - rest / length, 0.0)  # the compressive part is indefinite: dropped
        out = k * (nn + coef * (ti.Matrix.identity(REAL, 3) - nn))
    return out


@ti.func
def spring_block(x: V3, springs: I2, rest: F1, k_t: F1, k_c: F1, beta: F1, e: ti.i32,
                 h: REAL) -> mat3:
    """Stiffness plus damping (divided by h) Hessian block of spring e."""
    i = springs[e][0]
    j = springs[e][1]
    d = x[j] - x[i]
    length = d.norm()
    k = k_t[e]
    if length < rest[e]:
        k = k_c[e]
    hb = spring_hessian(d, rest[e], k)
    if length > 1e-9:
        n = d / length
        hb += beta[e] * k / h * n.outer_product(n)
    return hb


@ti.func
def gradient_all(x: V3, xn: V3, vn: V3, mass: F1, drag: F1, g: V3, springs: I2, rest: F1,
                 k_t: F1, k_c: F1, beta: F1, bends: I4, kw: V4, stiff: F1, bbeta: F1,
                 gravity: vec3, h: REAL, n_springs: ti.i32, n_bends: ti.i32,
                 use_gravity: ti.template(), use_air: ti.template()):
    """Gradient of the incremental potential: inertia, gravity, air drag, springs (with their
    Rayleigh damping), bending."""
    for i in range(x.shape[0]):
        gi = mass[i] * (x[i] - xn[i] - h * vn[i]) / (h * h)
        if ti.static(use_gravity):
            gi -= mass[i] * gravity
        if ti.static(use_air):
            gi += drag[i] * (x[i] - xn[i]) / h  # still air: wind acts by pressure_drag
        g[i] = gi
    for e in range(n_springs):
        i = springs[e][0]
        j = springs[e][1]
        d = x[j] - x[i]
        length = d.norm()
        if length > 1e-9:
            n = d / length
            c = length - rest[e]
            k = k_t[e]
            if c < 0.0:
                k = k_c[e]
            rate = n.dot((x[j] - xn[j]) - (x[i] - xn[i])) / h
            fe = (k * c + beta[e] * k * rate) * n  # force on i (pulls towards j when stretched)
            g[i] -= fe
            g[j] += fe
    for b in range(n_bends):
        s = bends[b]
        k = kw[b]
        c = k[0] * x[s[0]] + k[1] * x[s[1]] + k[2] * x[s[2]] + k[3] * x[s[3]]
        cv = (k[0] * (x[s[0]] - xn[s[0]]) + k[1] * (x[s[1]] - xn[s[1]])
              + k[2] * (x[s[2]] - xn[s[2]]) + k[3] * (x[s[3]] - xn[s[3]])) / h
        gb = stiff[b] * (c + bbeta[b] * cv)
        for q in ti.static(range(4)):
            g[s[q]] += k[q] * gb


@ti.func
def preconditioner(x: V3, mass: F1, drag: F1, diag: M3, blocks: M3, pinned: I1, springs: I2,
                   rest: F1, k_t: F1, k_c: F1, beta: F1, bends: I4, kw: V4, stiff: F1,
                   bbeta: F1, h: REAL, n_springs: ti.i32, n_bends: ti.i32,
                   use_air: ti.template()):
    """Inverses of the Hessian's 3x3 diagonal blocks (block Jacobi); zero on pinned vertices.
    Each spring's Hessian block is kept in `blocks` for the CG iterations of this Newton step
    (recomputing it in every Hessian product cost a norm and two outer products per spring)."""
    for i in range(x.shape[0]):
        dd = mass[i] / (h * h)
        if ti.static(use_air):
            dd += drag[i] / h
        diag[i] = dd * ti.Matrix.identity(REAL, 3)
    for e in range(n_springs):
        hb = spring_block(x, springs, rest, k_t, k_c, beta, e, h)
        blocks[e] = hb
        diag[springs[e][0]] += hb
        diag[springs[e][1]] += hb
    for b in range(n_bends):
        s = bends[b]
        k = kw[b]
        coef = stiff[b] * (1.0 + bbeta[b] / h)
        for q in ti.static(range(4)):
            diag[s[q]] += coef * k[q] * k[q] * ti.Matrix.identity(REAL, 3)
    for i in range(x.shape[0]):
        if pinned[i] != 0:
            diag[i] = ti.Matrix.zero(REAL, 3, 3)
        else:
            diag[i] = diag[i].inverse()


@ti.func
def hessian_times(mass: F1, drag: F1, p: V3, out: V3, pinned: I1, springs: I2, blocks: M3,
                  bends: I4, kw: V4, stiff: F1, bbeta: F1, h: REAL, n_springs: ti.i32,
                  n_bends: ti.i32, use_air: ti.template()):
    for i in range(p.shape[0]):
        dd = mass[i] / (h * h)
        if ti.static(use_air):
            dd += drag[i] / h
        out[i] = dd * p[i]
    for e in range(n_springs):
        r = blocks[e] @ (p[springs[e][0]] - p[springs[e][1]])
        out[springs[e][0]] += r
        out[springs[e][1]] -= r
    for b in range(n_bends):
        s = bends[b]
        k = kw[b]
        cp = k[0] * p[s[0]] + k[1] * p[s[1]] + k[2] * p[s[2]] + k[3] * p[s[3]]
        coef = stiff[b] * (1.0 + bbeta[b] / h)
        for q in ti.static(range(4)):
            out[s[q]] += coef * k[q] * cp
    for i in range(p.shape[0]):
        if pinned[i] != 0:
            out[i] = p[i]  # Dirichlet rows: pinned vertices do not move in the solve


@ti.kernel
def newton_solve(
    x: V3, xn: V3, vn: V3, mass: F1, drag: F1, pinned: I1,
    g: V3, r: V3, z: V3, p: V3, hp: V3, dx: V3, diag: M3, blocks: M3,
    springs: I2, rest: F1, k_t: F1, k_c: F1, beta: F1,
    bends: I4, kw: V4, stiff: F1, bbeta: F1,
    P: F1, Q: I1, stats: I1,
    use_gravity: ti.template(), use_air: ti.template(),
):  # fmt: skip
    """Backward Euler for one substep: Newton from the current x (the caller sets the inertial
    guess and the pinned positions), each step solved by block-Jacobi preconditioned CG with
    pinned vertices filtered out (Baraff & Witkin), until the update is below the tolerance."""
    h = P[P_H]
    gravity = vec3(P[P_GRAVITY], P[P_GRAVITY + 1], P[P_GRAVITY + 2])
    tol = P[P_TOL]
    cg_tol = P[P_CG_TOL]
    n_springs = Q[Q_N_SPRINGS]
    n_bends = Q[Q_N_BENDS]
    n = x.shape[0]
    rz_last = ti.cast(0.0, ti.f64)  # the previous Newton step's preconditioned gradient norm^2
    tight = False  # forcing: the last steps are solved exactly
    ti.loop_config(serialize=True)
    for _newton in range(Q[Q_NEWTON_MAX]):
        gradient_all(x, xn, vn, mass, drag, g, springs, rest, k_t, k_c, beta, bends, kw, stiff,
                     bbeta, gravity, h, n_springs, n_bends, use_gravity, use_air)
        preconditioner(x, mass, drag, diag, blocks, pinned, springs, rest, k_t, k_c, beta, bends,
                       kw, stiff, bbeta, h, n_springs, n_bends, use_air)
        rz = ti.cast(0.0, ti.f64)
        for i in range(n):
            ri = -g[i]
            if pinned[i] != 0:
                ri = vec3(0.0)
            r[i] = ri
            dx[i] = vec3(0.0)
            zi = diag[i] @ ri
            z[i] = zi
            p[i] = zi
            rz += ti.cast(ri.dot(zi), ti.f64)
        rz0 = rz
        # Inexact Newton (Eisenstat & Walker's second forcing term, when Q_FORCING is set): the
        # CG solve of a Newton step far from the solution only needs to be as accurate as that
        # step is useful; the tolerance tightens as the gradient falls. Newton still stops on
        # its update, so the converged answer is the same at a fraction of the CG iterations.
        eta = ti.cast(cg_tol, ti.f64)
        if Q[Q_FORCING] != 0 and not tight:
            eta = 0.5
            if rz_last > 0.0:
                eta = ti.min(0.5, ti.max(cg_tol, 0.9 * rz0 / rz_last))
        rz_last = rz0
        it = 0
        while it < Q[Q_CG_MAX] and rz > eta * eta * rz0 and rz > 1e-30:
            hessian_times(mass, drag, p, hp, pinned, springs, blocks, bends, kw, stiff, bbeta, h,
                          n_springs, n_bends, use_air)
            php = ti.cast(0.0, ti.f64)
            for i in range(n):
                php += ti.cast(p[i].dot(hp[i]), ti.f64)
            if php <= 0.0:
                break
            alpha = rz / php
            rz_new = ti.cast(0.0, ti.f64)
            for i in range(n):
                dx[i] += ti.cast(alpha, REAL) * p[i]
                r[i] -= ti.cast(alpha, REAL) * hp[i]
                z[i] = diag[i] @ r[i]
                rz_new += ti.cast(r[i].dot(z[i]), ti.f64)
            beta_cg = rz_new / rz
            for i in range(n):
                p[i] = z[i] + ti.cast(beta_cg, REAL) * p[i]
            rz = rz_new
            it += 1
        stats[S_CG] += it
        if it >= Q[Q_CG_MAX]:
            stats[S_UNCONVERGED] += 1
        step = 0.0
        for i in range(n):
            x[i] += dx[i]
            step = ti.max(step, dx[i].norm())
        stats[S_NEWTON] += 1
        if step < tol and (tight or Q[Q_FORCING] == 0):
            break
        # Close to the answer, solve exactly again: a loose last solve would stop Newton with
        # an error a few times the tolerance, which over a reference's thousands of steps
        # adds up (0.26 mm after 25 frames of the walking t-shirt).
        if step < 10.0 * tol:
            tight = True


@ti.kernel
def inertial_guess(x: V3, xn: V3, vn: V3, pinned: I1, h: REAL):
    for i in x:
        xn[i] = x[i]
        if pinned[i] == 0:
            x[i] = x[i] + h * vn[i]
