"""Cloth self-collision: a spatial hash of the cloth's vertices, and a push apart of vertices that
come closer than the radius and were not that close at rest."""

import taichi as ti

from datagen.sim.grid_kernels import hash_cell
from datagen.sim.kernel_common import F1, I1, V3, vec3
from datagen.sim.precision import REAL


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
def self_pair_scan(i: ti.i32, x: V3, xp: V3, w: F1, owner: I1, rest: V3, starts: I1, items: I1,
                   inv_cell: REAL, mask: ti.i32, radius: REAL, min_rest: REAL, recover: REAL,
                   apply: ti.template()) -> vec3:
    """The pairs of vertex i with nearby vertices of the same garment that are closer than
    `radius` and were not that close at rest (neighbours in the fabric, not a fold), each
    pushed apart along the pair to self_pair_target.

    `apply` (the serial form, self_collide_one): each pair with a higher index is pushed at
    once, both ends weighted by their inverse masses, so later pairs see the move (Gauss-Seidel);
    returns zero. Otherwise (the parallel form, parallel_kernels.self_collide_parallel): nothing
    is written; returns vertex i's share of the pushes of all its pairs, averaged over them, from
    the positions as they are (Jacobi).

    Cells are 2 * `radius` wide, so the neighbours within `radius` lie in the 2 x 2 x 2 cells
    that the box of half-width `radius` around the vertex touches: 8 cells instead of 27 of
    `radius`-wide cells, 40 % fewer candidates, and the pass 2.5x faster (the skirt-like tube,
    5,100 vertices: 1.3 -> 0.5 ms). Distances are compared squared; the square root is taken
    only for a pair that is pushed."""
    xi = x[i]
    oi = owner[i]
    r2 = radius * radius
    lo = ti.cast(ti.floor((xi - radius) * inv_cell), ti.i32)
    total = vec3(0.0)
    pairs = 0
    for nb in range(8):
        c = hash_cell(lo + ti.math.ivec3(nb // 4, (nb // 2) % 2, nb % 2), mask)
        for q in range(starts[c], starts[c + 1]):
            j = items[q]
            other = j != i
            if ti.static(apply):
                other = j > i  # each pair once: from its lower index
            if other:
                d = x[j] - xi
                d2 = d.norm_sqr()
                if d2 < r2 and d2 > 1e-18 and owner[j] == oi:
                    wsum = w[i] + w[j]
                    if wsum > 0.0 and (rest[j] - rest[i]).norm() > min_rest:
                        dist = ti.sqrt(d2)
                        target = self_pair_target(xp[j] - xp[i], radius, recover)
                        if dist < target:
                            corr = (target - dist) / (dist * wsum) * d
                            if ti.static(apply):
                                x[i] -= w[i] * corr
                                x[j] += w[j] * corr
                                xi = x[i]
                            else:
                                total -= w[i] * corr
                                pairs += 1
    if pairs > 1:
        total /= pairs
    return total


@ti.func
def self_collide_one(i: ti.i32, x: V3, xp: V3, w: F1, owner: I1, rest: V3, starts: I1,
                     items: I1, inv_cell: REAL, mask: ti.i32, radius: REAL, min_rest: REAL,
                     recover: REAL):
    """Push vertex i and nearby vertices of the same garment apart to `radius`, unless they are
    near each other in the rest shape too (self_pair_scan, pushing each pair at once). A pair
    that came closer than `radius` during this substep is pushed apart to it (the approach
    undone); one already closer at the substep's start (xp) only to `recover` farther than it
    was then (self_pair_target), as a vertex inside the body recovers: pushed fully every
    substep, a fold held crushed by the body or another garment turned the same millimetres per
    substep into a speed that grew with the substeps (a cropped top tucked at a waistband in a
    kick: 20 m/s at 160 substeps a frame, where 40 ran at 5)."""
    self_pair_scan(i, x, xp, w, owner, rest, starts, items, inv_cell, mask, radius, min_rest,
                   recover, True)


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
