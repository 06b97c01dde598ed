"""The xpbd solver's strain limit after contact on parallel backends (a GPU, or several CPU
threads): coloured sweeps instead of one serial task.

The serial form (kernels.limit_after_contact_active) appends to shared lists, so it runs as one
task on one thread: on a GPU that is one GPU thread walking every limited spring, in every
substep (the 4k sheet ran 1.8x slower that way on an H200, docs/benchmarks.md). Here each sweep
is coloured like the constraint sweeps (no two springs of a colour share a vertex, each colour a
parallel loop), so it is exact Gauss-Seidel in colour order and gives the same result on any
number of threads. Sweeps run, as in the serial form, until no spring is
AFTER_CONTACT_TOLERANCE past its limit or AFTER_CONTACT_SWEEPS have run: each returns the
largest excess it met, which waits for the device, but a parallel backend is bound by launches,
not by the device, and most substeps stop after the first sweep.
"""

import taichi as ti

from datagen.sim.kernels import (
    F1,
    I1,
    I2,
    I3,
    V3,
    collide_one,
    colour_range,
    limit_after_contact_one,
)
from datagen.sim.precision import REAL


@ti.kernel
def limit_sweep_coloured(
    x: V3,
    w: F1,
    springs: I2,
    limit: F1,
    contact_n: V3,
    order: I1,
    colour_ptr: I1,
    worst: F1,
    moved: I1,
    reverse: ti.i32,
    n_colours: ti.template(),
) -> REAL:
    """One sweep of kernels.limit_after_contact_one over the limited springs (`order`, sorted
    by colour); returns the largest excess it met (relative to the limit; `worst`, one entry,
    collects it). `moved` flags the vertices the limit moved (for contact afterwards)."""
    for _ in range(1):
        worst[0] = 0.0
    for c in ti.static(range(n_colours)):
        r = colour_range(c, n_colours, reverse, colour_ptr)
        for k in range(r[0], r[1]):
            e = order[k]
            excess = limit_after_contact_one(e, x, w, springs, limit, contact_n)
            if excess > 0.0:
                ti.atomic_max(worst[0], excess)
                moved[springs[e][0]] = 1
                moved[springs[e][1]] = 1
    return worst[0]


@ti.kernel
def collide_moved(
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
    moved: I1,
    use_collision: ti.template(),
):
    """Contact without friction for the vertices the limit moved, clearing their flags (the
    parallel form of kernels.collide_listed: each vertex's contact is its own)."""
    for i in x:
        if moved[i] != 0:
            moved[i] = 0
            if ti.static(use_collision):
                collide_one(i, x, xp, w, tri, faces, fadj, b0, b1, n0, n1, s0, s1, thickness,
                            friction, recover, release, contact_n, contact_v, h, False)
