"""The depth QA: on a closed body, whether each cloth vertex is inside its volume at a frame's
end (the winding number of a ray through a column grid) and, for the few inside, the distance to
the grid's closest triangle within a reach of at most a cell (grid_inside_depth); on a collider
that is not closed, each vertex's signed distance by that triangle (grid_signed_distance)."""

import taichi as ti

from datagen.sim.grid_kernels import grid_cell, scanned_first
from datagen.sim.kernel_common import F1, I1, I3, I4, V3, V8, closest_on_triangle, vec3
from datagen.sim.precision import REAL


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
                  counts: I1, spans: I4, along: F1, serialize: ti.template()):
    """Each column's number of triangles (column_grid_build), from zero, each triangle's
    columns in `spans`, and each column's lowest and highest coordinate along the ray of its
    triangles in `along` (2c, 2c + 1; an empty column's lowest above its highest)."""
    ti.loop_config(serialize=serialize)
    for c in range(dims[0] * dims[1]):
        counts[c] = 0
        along[2 * c] = 1e30
        along[2 * c + 1] = -1e30
    ti.loop_config(serialize=serialize)
    for t in range(faces.shape[0]):
        f = faces[t]
        span = triangle_columns(b, f, origin, inv_cell, dims)
        spans[t] = span
        box = item_box(b, f)  # [5] and [0]: its lowest and highest along the ray
        for i in range(span[0], span[1] + 1):
            for j in range(span[2], span[3] + 1):
                c = i * dims[1] + j
                ti.atomic_add(counts[c], 1)
                ti.atomic_min(along[2 * c], box[5])
                ti.atomic_max(along[2 * c + 1], box[0])


@ti.func
def fill_columns(b: V3, faces: I3, spans: I4, dims: ti.math.ivec3, counts: I1, starts: I1,
                 items: I1, boxes: V8, serialize: ti.template()):
    """File each triangle in its columns from their starts, `counts` zero on entry (cursors),
    with its box beside it in `boxes` (item_box). The order of a column's list does not
    matter: its crossings are summed as integers."""
    ti.loop_config(serialize=serialize)
    for t in range(spans.shape[0]):
        span = spans[t]
        box = item_box(b, faces[t])
        for i in range(span[0], span[1] + 1):
            for j in range(span[2], span[3] + 1):
                c = i * dims[1] + j
                k = starts[c] + ti.atomic_add(counts[c], 1)
                items[k] = t
                boxes[k] = box


@ti.func
def item_box(b: V3, f: ti.math.ivec3):
    """A filed triangle's box as the ray test reads it, beside the triangle in its column's
    list: its highest coordinate along the ray, its lowest and highest of each of the
    columns' two coordinates, and its lowest along the ray. A column's scan rejects most
    triangles on it alone, reading the list in order instead of each triangle's corners."""
    lo = ti.min(b[f[0]], b[f[1]], b[f[2]])
    hi = ti.max(b[f[0]], b[f[1]], b[f[2]])
    return ti.Vector([hi[RAY_AXIS], lo[_RI], hi[_RI], lo[_RJ], hi[_RJ], lo[RAY_AXIS], 0.0, 0.0],
                     dt=REAL)


@ti.kernel
def column_grid_build(b: V3, faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3,
                      counts: I1, starts: I1, spans: I4, along: F1, items: I1,
                      boxes: V8) -> ti.i32:
    """File every triangle of the collider at `b` in each column (a square of the plane across
    RAY_AXIS, `dims[0]` x `dims[1]` of them from `origin`) its projected box overlaps, in one
    launch, for serial backends (`spans`: scratch, a triangle's columns between the count and
    the fill). Returns the number of entries; where `items` is too short for them nothing is
    filed (the caller grows it and calls again). Parallel backends count (column_count), sum
    (grid_prefix) and fill (column_fill) in three launches."""
    count_columns(b, faces, origin, inv_cell, dims, counts, spans, along, True)
    n_cols = dims[0] * dims[1]
    run = 0
    ti.loop_config(serialize=True)
    for c in range(n_cols):
        starts[c] = run
        run += counts[c]
        counts[c] = 0  # the fill's cursors
    starts[n_cols] = run
    if run <= items.shape[0]:
        fill_columns(b, faces, spans, dims, counts, starts, items, boxes, True)
    return run


@ti.kernel
def column_count(b: V3, faces: I3, origin: vec3, inv_cell: REAL, dims: ti.math.ivec3,
                 counts: I1, spans: I4, along: F1):
    count_columns(b, faces, origin, inv_cell, dims, counts, spans, along, False)


@ti.kernel
def column_fill(b: V3, faces: I3, spans: I4, dims: ti.math.ivec3, counts: I1, starts: I1,
                items: I1, boxes: V8):
    fill_columns(b, faces, spans, dims, counts, starts, items, boxes, False)


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
def winding_along_ray(p: vec3, b: V3, faces: I3, starts: I1, items: I1, boxes: V8,
                      along_col: F1, origin: vec3, inv_cell: REAL,
                      dims: ti.math.ivec3) -> ti.i32:
    """The winding number of the collider at `b` (closed, outward) around point p: its signed
    crossings with a ray from p along RAY_AXIS, through the triangles of p's column (`boxes`
    beside them, item_box). Zero without a scan beyond the column's triangles along the ray
    (`along_col`): past the highest the ray meets none, and before the lowest it crosses the
    closed surface all the way through, leaving it as often as it enters. Within them the ray
    runs towards the nearer end, along +RAY_AXIS or -RAY_AXIS (either gives the winding
    number): from cloth just outside the body it then meets the one near surface instead of
    crossing the body to its far side."""
    w = 0
    c = column_of(p, origin, inv_cell, dims)
    lowest = 0.0
    highest = 0.0
    if c >= 0:
        lowest = along_col[2 * c]
        highest = along_col[2 * c + 1]
    h = p[RAY_AXIS]
    if c >= 0 and lowest <= h < highest:
        up = highest - h <= h - lowest
        for q in range(starts[c], starts[c + 1]):
            # Most of a column's triangles miss the ray: their box does (a point on the box's
            # edge goes on to the exact test).
            box = boxes[q]
            if ((box[0] > h if up else box[5] < h) and box[1] <= p[_RI] <= box[2]
                    and box[3] <= p[_RJ] <= box[4]):
                t = items[q]
                f = faces[t]
                ta = b[f[0]]
                tb = b[f[1]]
                tc = b[f[2]]
                s0 = edge_side(tb, tc, p, f[1], f[2])
                s1 = edge_side(tc, ta, p, f[2], f[0])
                s2 = edge_side(ta, tb, p, f[0], f[1])
                # Inside the projected triangle: on the same side of its three edges.
                if (s0 > 0 and s1 > 0 and s2 > 0) or (s0 < 0 and s1 < 0 and s2 < 0):
                    area = s0 + s1 + s2
                    along = (s0 * ta[RAY_AXIS] + s1 * tb[RAY_AXIS] + s2 * tc[RAY_AXIS]) / area
                    # Leaving the surface along the ray: +1 upwards where the triangle faces
                    # +RAY_AXIS, downwards where it faces the other way.
                    if up and along > h:
                        w += 1 if area > 0 else -1
                    elif not up and along < h:
                        w += -1 if area > 0 else 1
    return w


@ti.func
def nearest_filed(p: vec3, hint_t: ti.i32, last_t: ti.i32, b: V3, faces: I3, mask: I1,
                  origin: vec3, inv_cell: REAL, dims: ti.math.ivec3, shift: vec3, starts: I1,
                  items: I1, tbox: V8, far: REAL):
    """The squared distance from p to its closest filed triangle within `far` (at most a
    cell) and that triangle, or (far^2, -1) where none is: grid_signed_distance's search.
    The grid's boxes (`tbox`) need only hold each triangle at the frame's end, in the grid's
    coordinates (b - shift): the end boxes, or boxes swept over the frame that contain them.
    The nearer of the two hint triangles bounds the search (see grid_signed_distance)."""
    best, best_t = hint_bound(p, hint_t, b, faces, mask, far * far, -1)
    best, best_t = hint_bound(p, last_t, b, faces, mask, best, best_t)
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
    return best, best_t


@ti.kernel
def grid_signed_distance(x: V3, hint: I1, last: I1, b: V3, n: V3, faces: I3, mask: I1,
                         origin: vec3, inv_cell: REAL, dims: ti.math.ivec3, shift: vec3,
                         starts: I1, items: I1, tbox: V8, far: REAL, out: F1,
                         closed: ti.template(), col_starts: I1, col_items: I1, col_boxes: V8,
                         col_along: F1, col_origin: vec3, col_inv_cell: REAL,
                         col_dims: ti.math.ivec3, outward: ti.i32, serialize: ti.template()):
    """Signed distance of each point to its closest collider triangle at the end of the frame (`b`,
    vertex normals `n` for the sign), searching the grid cells within `far` of it (of the 27 around
    it). Where no triangle is within `far` (at most one cell): `far`, or `-far` inside a `closed`
    collider (the winding number of its whole mesh, `outward` 1 or -1 as its triangles face, through
    the column grid `col_*` of column_grid_build). The grid (`starts`, `items`, `tbox`) must file
    each triangle in the cells of its box at `b`, in the grid's coordinates (b - shift: the frame's
    end in coordinates that move with the body's mean motion, count_triangle): BodyCollider passes
    its grid of the end boxes, which fills about half the cells that the solver's boxes swept over
    the frame do. Two hints per point (a triangle, or -1) only start the search: `hint` (the depth
    QA passes the solver's tracked triangles) and `last`, the closest triangle of the previous call,
    which the call then overwrites (the cloth that the solver does not track, within a cell of the
    body, moves less than a cell a frame). The nearer one bounds the search, so that a point a few
    millimetres from the body scans the one to four cells within that distance instead of 27: a
    third of the time on a walking t-shirt and half on a draped sheet. A hint that is not a filed
    triangle (`mask`) is ignored, and the result does not depend on the hints, except between
    equally near triangles. `serialize` on serial backends (see copy_in)."""
    ti.loop_config(serialize=serialize)
    for i in range(x.shape[0]):
        p = x[i]
        best, best_t = nearest_filed(p, hint[i], last[i], b, faces, mask, origin, inv_cell, dims,
                                     shift, starts, items, tbox, far)
        last[i] = best_t
        d = far
        if best_t < 0:
            # Nothing filed within `far`: that far or more from the surface, on the side the
            # ray's crossings give (a collider that is not closed has no inside to count).
            if ti.static(closed):
                if outward * winding_along_ray(p, b, faces, col_starts, col_items, col_boxes,
                                               col_along, col_origin, col_inv_cell,
                                               col_dims) > 0:
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


@ti.kernel
def grid_inside_depth(x: V3, hint: I1, last: I1, b: V3, faces: I3, mask: I1, origin: vec3,
                      inv_cell: REAL, dims: ti.math.ivec3, shift: vec3, starts: I1, items: I1,
                      tbox: V8, far: REAL, out: F1, col_starts: I1, col_items: I1,
                      col_boxes: V8, col_along: F1, col_origin: vec3, col_inv_cell: REAL,
                      col_dims: ti.math.ivec3, outward: ti.i32, serialize: ti.template()):
    """How deep inside a closed collider at the frame's end (`b`) each point is: -1 outside
    (the winding number of the whole mesh through the column grid `col_*`, as
    grid_signed_distance's beyond its reach, `outward` 1 or -1 as the triangles face), and
    inside its distance to the closest filed triangle within `far`, or `far` where none is that
    near. Inside is the volume of the whole mesh, so a point inside one part of a body that
    passes through another is inside, whichever part's triangle is nearest (qa.buried_share's
    volume; grid_signed_distance signs a point within its reach by that triangle's normal and
    reads it as outside). Only the few points inside are searched for: cloth on the body lies
    outside it, and its search, bounded by the hints `hint` and `last` (which the call
    overwrites for the points inside) as in grid_signed_distance, may read the grid of boxes
    swept over the frame (`tbox`, in the coordinates b - shift) instead of one built of the
    end boxes. `serialize` on serial backends (see copy_in)."""
    ti.loop_config(serialize=serialize)
    for i in range(x.shape[0]):
        p = x[i]
        d = -1.0
        if outward * winding_along_ray(p, b, faces, col_starts, col_items, col_boxes,
                                       col_along, col_origin, col_inv_cell, col_dims) > 0:
            best, best_t = nearest_filed(p, hint[i], last[i], b, faces, mask, origin, inv_cell,
                                         dims, shift, starts, items, tbox, far)
            last[i] = best_t
            d = far
            if best_t >= 0:
                d = ti.sqrt(best)
        out[i] = d
