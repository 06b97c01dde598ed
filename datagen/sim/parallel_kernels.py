"""Kernels for parallel backends (a GPU, or several CPU threads) where the serial form is one
task or sums in the order threads run, or where a launch per effect costs more than the work:
the xpbd solver's substep start and its iterations' sweeps (one launch each), its strain limit
after contact (coloured sweeps), self-collision (self_collide_parallel), vertex normals of the
inner garment and of the body collider (vertex_normals_gathered below), the outer garments'
pushes (contact_kernels.collide_layers summing in fixed point), and the explicit solver's forces
(gathered per vertex).

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

from datagen.sim.contact_kernels import collide_one, vertex_normal_finish_one
from datagen.sim.grid_kernels import sort_cells
from datagen.sim.kernel_common import F1, I1, I2, I3, I4, V3, V4, V8, lerp3, vec3
from datagen.sim.kernels import (
    bend_force,
    bend_gs_one,
    colour_range,
    limit_after_contact_one,
    predict_one,
    pressure_face_vector,
    spring_force,
    spring_gs_one,
)
from datagen.sim.precision import REAL, VEC4
from datagen.sim.self_collision_kernels import self_cell, self_pair_scan

# -- the xpbd substep in few launches ------------------------------------------------------------
# A parallel backend pays for each launch from Python whatever the work (a GPU: 6-12 us on the
# device, more in Taichi's Python; docs/benchmarks.md), and the per-effect kernels took about 37
# a substep at 40x8 (predict, pins, a fill per multiplier array, then per iteration the bending
# and one launch per spring set). These two kernels do the same work, element for element and in
# the same order, in 1 + iterations launches: profiled frames still run the per-effect kernels,
# which measure each effect's cost.


@ti.func
def pressure_gathered_one(i: ti.i32, x: V3, faces: I3, starts: I1, entries: I1, air: V4):
    """kernels.set_pressure_vectors for vertex i, summing its own faces (entry 3 t + k: corner
    k of face t is this vertex), so the sum does not depend on how threads are scheduled."""
    total = vec3(0.0)
    for q in range(starts[i], starts[i + 1]):
        f = faces[entries[q] // 3]
        total += pressure_face_vector(x, f[0], f[1], f[2])
    air[i] = VEC4(air[i][0], total[0], total[1], total[2])


@ti.kernel
def set_pressure_vectors_gathered(x: V3, faces: I3, starts: I1, entries: I1, air: V4):
    for i in air:
        pressure_gathered_one(i, x, faces, starts, entries, air)


@ti.kernel
def xpbd_substep_begin(
    x: V3,
    xp: V3,
    v: V3,
    w: F1,
    air: V4,
    faces: I3,
    face_starts: I1,
    face_entries: I1,
    gravity: vec3,
    wind: vec3,
    h: REAL,
    pin_idx: I1,
    pin_t0: V3,
    pin_t1: V3,
    n_pins: ti.i32,
    s1: REAL,
    lam: F1,
    lam_b: V3,
    use_gravity: ti.template(),
    use_air: ti.template(),
    use_pressure: ti.template(),
):
    """The pressure drag's vectors (set_pressure_vectors_gathered, where it is on), then
    kernels.predict, then the pins at their targets (kernels.apply_pins), then the spring and
    bending multipliers at zero."""
    if ti.static(use_pressure):
        for i in x:
            pressure_gathered_one(i, x, faces, face_starts, face_entries, air)
    for i in x:
        predict_one(i, x, xp, v, w, air, gravity, wind, h, use_gravity, use_air,
                    use_pressure)
    for p in range(n_pins):
        x[pin_idx[p]] = lerp3(pin_t0[p], pin_t1[p], s1)
    for e in lam:
        lam[e] = 0.0
    for b in lam_b:
        lam_b[b] = vec3(0.0)


@ti.kernel
def xpbd_iteration_coloured(
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    terms: V8,
    lam: F1,
    spring_order: I1,
    spring_ranges: I2,
    bends: I4,
    kk: V8,
    bstep: V4,
    lam_b: V3,
    bend_order: I1,
    bend_ptr: I1,
    reverse: ti.i32,
    omega: REAL,
    omega_b: REAL,
    n_bend_colours: ti.template(),
    n_spring_colours: ti.template(),
):
    """One iteration's sweeps: kernels.bends_coloured (`bend_order` by colour, every bend or
    the stiff ones, at `omega_b`), then every spring set's kernels.springs_coloured over the
    fused springs (solvers.XPBDSolver._build_fused). `spring_ranges` holds each colour's slice
    of `spring_order`, the sets one after another: first in forward order (n_spring_colours
    rows), then in reverse order, where each set sweeps its colours backwards."""
    for c in ti.static(range(n_bend_colours)):
        r = colour_range(c, n_bend_colours, reverse, bend_ptr)
        for k in range(r[0], r[1]):
            bend_gs_one(bend_order[k], x, xp, bends, kk, bstep, lam_b, omega_b)
    for c in ti.static(range(n_spring_colours)):
        r = spring_ranges[reverse * n_spring_colours + c]
        for k in range(r[0], r[1]):
            spring_gs_one(spring_order[k], x, xp, w, springs, terms, lam, omega)


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


# Cells per block of the hashed grid's prefix sum (self_collide_parallel): each block is summed
# by one thread, then the blocks' totals by one (a few hundred steps each instead of one thread
# walking every cell).
SCAN_BLOCK = 256


@ti.kernel
def self_collide_parallel(x: V3, xp: V3, w: F1, owner: I1, rest: V3, counts: I1, starts: I1,
                          items: I1, scan: I1, push: V3, inv_cell: REAL, mask: ti.i32,
                          radius: REAL, min_rest: REAL, recover: REAL):
    """self_collision_kernels.self_collide on a parallel backend. The hashed grid is built in
    parallel: counts by atomic adds, a blocked prefix sum (`scan`: one entry per SCAN_BLOCK cells,
    and one), the vertices filed by atomic cursors and each cell's list then sorted by index, so the
    grid and every sum below are the same on any number of threads. Then each vertex's push
    (self_pair_scan) from the positions as they are, and all pushes at once (Jacobi with
    averaging: a vertex pressed by a whole layer moves once, not once per neighbour)."""
    n_cells = mask + 1
    for c in range(n_cells):
        counts[c] = 0
    for i in x:
        ti.atomic_add(counts[self_cell(x[i], inv_cell, mask)], 1)
    for b in range((n_cells + SCAN_BLOCK - 1) // SCAN_BLOCK):
        total = 0
        for c in range(b * SCAN_BLOCK, ti.min((b + 1) * SCAN_BLOCK, n_cells)):
            total += counts[c]
            starts[c + 1] = total  # within the block, for now
    for _ in range(1):
        starts[0] = 0
        scan[0] = 0
        for b in range((n_cells + SCAN_BLOCK - 1) // SCAN_BLOCK):
            scan[b + 1] = scan[b] + starts[ti.min((b + 1) * SCAN_BLOCK, n_cells)]
    for c in range(n_cells):
        starts[c + 1] += scan[c // SCAN_BLOCK]
        counts[c] = 0
    for i in x:
        c = self_cell(x[i], inv_cell, mask)
        items[starts[c] + ti.atomic_add(counts[c], 1)] = i
    sort_cells(starts, items, n_cells)
    for i in x:
        push[i] = self_pair_scan(i, x, xp, w, owner, rest, starts, items, inv_cell, mask,
                                 radius, min_rest, recover, False)
    for i in x:
        x[i] += push[i]


# -- garment-garment collision -------------------------------------------------------------------
# The serial form (contact_kernels.vertex_normals, contact_kernels.collide_layers) adds into shared
# vertices from a loop over faces or outer vertices; in parallel those float sums come out in the
# order threads run, so two runs of the same input differ at the last bit and a contact-rich scene
# amplifies that (the layered hard case on a GPU: 8.7 mm apart after the settle, 9 cm by the end).
# Here each inner vertex gathers its faces' normals itself; the pushes are summed in fixed point by
# contact_kernels.collide_layers (`exact`).


@ti.kernel
def vertex_normals_gathered(x: V3, faces: I3, starts: I1, entries: I1, nrm: V3):
    """contact_kernels.vertex_normals with each vertex summing its own faces' area-weighted normals
    (entry 3 t + k: corner k of face t is this vertex): one thread per sum, so the sums do not
    depend on how threads are scheduled. (They are not the serial form's bit for bit: the
    compiler may reassociate a sum in a loop.)"""
    for i in nrm:
        total = vec3(0.0)
        for q in range(starts[i], starts[i + 1]):
            f = faces[entries[q] // 3]
            total += (x[f[1]] - x[f[0]]).cross(x[f[2]] - x[f[0]])
        nrm[i] = total
    for i in nrm:
        vertex_normal_finish_one(i, nrm)


# -- the explicit solver's forces ----------------------------------------------------------------
# kernels.spring_forces and bend_forces add each element's force into its vertices from a
# parallel loop: summed in thread order. Here each vertex sums the forces of its own elements
# (CSR lists: solvers._vertex_lists_nd), computing each element once per vertex it has.


@ti.kernel
def spring_forces_gathered(x: V3, v: V3, f: V3, springs: I2, rest: F1, k_t: F1, k_c: F1,
                           beta: F1, starts: I1, entries: I1):
    """Entries below the spring count are springs whose first vertex this is, the others
    (minus the count) those whose second vertex it is."""
    n_springs = springs.shape[0]
    for i in f:
        total = vec3(0.0)
        for q in range(starts[i], starts[i + 1]):
            k = entries[q]
            if k < n_springs:
                total += spring_force(x, v, springs, rest, k_t, k_c, beta, k)
            else:
                total -= spring_force(x, v, springs, rest, k_t, k_c, beta, k - n_springs)
        f[i] += total


@ti.kernel
def bend_forces_gathered(x: V3, v: V3, f: V3, bends: I4, kw: V4, stiff: F1, beta: F1,
                         starts: I1, entries: I1):
    """Entry 4 b + q: vertex q of bending stencil b is this one."""
    for i in f:
        total = vec3(0.0)
        for q in range(starts[i], starts[i + 1]):
            b = entries[q] // 4
            total -= kw[b][entries[q] % 4] * bend_force(x, v, bends, kw, stiff, beta, b)
        f[i] += total
