"""Taichi kernels of the implicit (backward Euler, Newton-PCG) solver. Matrix-free: the Hessian
is applied spring by spring and stencil by stencil, never assembled."""

import taichi as ti

from datagen.sim.kernels import F1, I1, I2, I4, V3, V4, vec3
from datagen.sim.precision import MAT3, REAL

mat3 = MAT3
M3 = ti.types.ndarray(dtype=mat3, ndim=1)


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


@ti.kernel
def gradient(
    x: V3,
    xn: V3,
    vn: V3,
    mass: F1,
    drag: F1,
    pinned: I1,
    g: V3,
    gravity: vec3,
    wind: vec3,
    h: REAL,
    use_gravity: ti.template(),
    use_air: ti.template(),
):
    """Inertia, gravity and air drag part of the gradient (springs and bends add theirs)."""
    for i in x:
        gi = mass[i] * (x[i] - xn[i] - h * vn[i]) / (h * h)
        if ti.static(use_gravity):
            gi -= mass[i] * gravity
        if ti.static(use_air):
            gi += drag[i] * ((x[i] - xn[i]) / h - wind)
        g[i] = gi


@ti.kernel
def spring_gradient(
    x: V3, xn: V3, g: V3, springs: I2, rest: F1, k_t: F1, k_c: F1, beta: F1, h: REAL
):
    for e in range(springs.shape[0]):
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


@ti.kernel
def bend_gradient(x: V3, xn: V3, g: V3, bends: I4, kw: V4, stiff: F1, beta: F1, h: REAL):
    for b in range(bends.shape[0]):
        s = bends[b]
        k = kw[b]
        c = k[0] * x[s[0]] + k[1] * x[s[1]] + k[2] * x[s[2]] + k[3] * x[s[3]]
        cv = (
            k[0] * (x[s[0]] - xn[s[0]])
            + k[1] * (x[s[1]] - xn[s[1]])
            + k[2] * (x[s[2]] - xn[s[2]])
            + k[3] * (x[s[3]] - xn[s[3]])
        ) / h
        gb = stiff[b] * (c + beta[b] * cv)
        for q in ti.static(range(4)):
            g[s[q]] += k[q] * gb


@ti.kernel
def diagonal(
    x: V3,
    mass: F1,
    drag: F1,
    diag: M3,
    springs: I2,
    rest: F1,
    k_t: F1,
    k_c: F1,
    beta: F1,
    bends: I4,
    kw: V4,
    stiff: F1,
    bbeta: F1,
    h: REAL,
    n_springs: ti.i32,
    n_bends: ti.i32,
    use_air: ti.template(),
):
    """3x3 diagonal blocks of the Hessian, for the block-Jacobi preconditioner."""
    for i in x:
        dd = mass[i] / (h * h)
        if ti.static(use_air):
            dd += drag[i] / h
        diag[i] = dd * ti.Matrix.identity(REAL, 3)
    for e in range(n_springs):
        i = springs[e][0]
        j = springs[e][1]
        d = x[j] - x[i]
        k = k_t[e]
        if d.norm() < rest[e]:
            k = k_c[e]
        hb = spring_hessian(d, rest[e], k)
        length = d.norm()
        if length > 1e-9:
            n = d / length
            hb += beta[e] * k / h * n.outer_product(n)
        diag[i] += hb
        diag[j] += hb
    for b in range(n_bends):
        s = bends[b]
        k = kw[b]
        coef = stiff[b] * (1.0 + bbeta[b] / h)
        for q in ti.static(range(4)):
            diag[s[q]] += coef * k[q] * k[q] * ti.Matrix.identity(REAL, 3)


@ti.kernel
def invert_blocks(diag: M3, pinned: I1):
    for i in diag:
        if pinned[i] != 0:
            diag[i] = ti.Matrix.zero(REAL, 3, 3)
        else:
            diag[i] = diag[i].inverse()


@ti.kernel
def hessian_product(
    x: V3,
    mass: F1,
    drag: F1,
    p: V3,
    out: V3,
    springs: I2,
    rest: F1,
    k_t: F1,
    k_c: F1,
    beta: F1,
    bends: I4,
    kw: V4,
    stiff: F1,
    bbeta: F1,
    pinned: I1,
    h: REAL,
    n_springs: ti.i32,
    n_bends: ti.i32,
    use_air: ti.template(),
):
    for i in x:
        dd = mass[i] / (h * h)
        if ti.static(use_air):
            dd += drag[i] / h
        out[i] = dd * p[i]
    for e in range(n_springs):
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
        r = hb @ (p[i] - p[j])
        out[i] += r
        out[j] -= r
    for b in range(n_bends):
        s = bends[b]
        k = kw[b]
        cp = k[0] * p[s[0]] + k[1] * p[s[1]] + k[2] * p[s[2]] + k[3] * p[s[3]]
        coef = stiff[b] * (1.0 + bbeta[b] / h)
        for q in ti.static(range(4)):
            out[s[q]] += coef * k[q] * cp
    for i in x:
        if pinned[i] != 0:
            out[i] = p[i]


@ti.kernel
def precondition(diag: M3, r: V3, z: V3, pinned: I1):
    for i in r:
        if pinned[i] != 0:
            z[i] = vec3(0.0)
        else:
            z[i] = diag[i] @ r[i]


@ti.kernel
def dot(a: V3, b: V3) -> ti.f64:
    total = ti.cast(0.0, ti.f64)
    for i in a:
        total += ti.cast(a[i].dot(b[i]), ti.f64)
    return total


@ti.kernel
def axpy(y: V3, a: REAL, x: V3):
    """y += a x"""
    for i in y:
        y[i] += a * x[i]


@ti.kernel
def xpay(y: V3, a: REAL, x: V3):
    """y = x + a y"""
    for i in y:
        y[i] = x[i] + a * y[i]


@ti.kernel
def negate_filtered(src: V3, dst: V3, pinned: I1):
    for i in src:
        if pinned[i] != 0:
            dst[i] = vec3(0.0)
        else:
            dst[i] = -src[i]


@ti.kernel
def max_norm(a: V3) -> REAL:
    m = 0.0
    for i in a:
        ti.atomic_max(m, a[i].norm())
    return m


@ti.kernel
def inertial_guess(x: V3, xn: V3, vn: V3, pinned: I1, h: REAL):
    for i in x:
        xn[i] = x[i]
        if pinned[i] == 0:
            x[i] = x[i] + h * vn[i]
