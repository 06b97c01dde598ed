"""What every cloth kernel module shares: the ndarray types its kernels take (at the process's
precision, datagen.sim.precision), the collision search's per-vertex guard, and point-triangle
geometry."""

import taichi as ti

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
V8 = ti.types.ndarray(dtype=GUARD, ndim=1)
F1 = ti.types.ndarray(dtype=REAL, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I2 = ti.types.ndarray(dtype=ti.math.ivec2, ndim=1)
I3 = ti.types.ndarray(dtype=ti.math.ivec3, ndim=1)
I4 = ti.types.ndarray(dtype=ti.math.ivec4, ndim=1)


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
