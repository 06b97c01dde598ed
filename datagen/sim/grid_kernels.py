"""The collider's uniform grid: each body triangle (or inner garment triangle) filed in the cells
its box over the frame overlaps, built in parallel (count, prefix sum, fill, sort) or serially.
The closest-triangle search (search_kernels) and the depth QA (depth_kernels) read it."""

import taichi as ti

from datagen.sim.kernel_common import F1, GUARD, I1, I3, V3, V8, vec3
from datagen.sim.precision import REAL

# The per-triangle box of a collider grid (tbox, written by grid_count) keeps the triangle's
# body part in its last slot (T_PART), set once: -1 where the collider has no parts (a sphere, a
# garment under another), so no guard there is of the tracked kind.
T_PART = 7


@ti.func
def hash_cell(c: ti.math.ivec3, mask: ti.i32) -> ti.i32:
    return ((c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)) & mask


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
