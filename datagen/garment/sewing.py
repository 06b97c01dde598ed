"""Stitching: strips of well-shaped triangles between vertex chains, and sewing an upper garment to
a lower one (top + trousers -> jumpsuit, top + skirt -> dress).

`bridge_chains` triangulates the band between two chains of vertices by dynamic programming over
the choice of which chain advances next (the classic contour-lofting formulation), minimising a
cost that grows steeply as a triangle's smallest angle shrinks. It is how build.py stitches the
rows of a template together and how `sew` joins a hem loop to a waist loop whose vertex counts
differ.
"""

from __future__ import annotations

import numpy as np

from datagen.errors import InputError
from datagen.garment.template import Axis, GarmentTemplate, RowSet

# -- strips ------------------------------------------------------------------------------------


def _tri_cost(p: np.ndarray, q: np.ndarray, r: np.ndarray, ref: float) -> np.ndarray:
    """Cost of triangles (p, q, r) (arrays (..., 3)): large for small angles and long edges."""
    p, q, r = np.broadcast_arrays(p, q, r)
    a = np.linalg.norm(q - r, axis=-1)
    b = np.linalg.norm(p - r, axis=-1)
    c = np.linalg.norm(p - q, axis=-1)
    lengths = np.stack([a, b, c], axis=-1)
    srt = np.sort(lengths, axis=-1)
    shortest, mid, longest = srt[..., 0], srt[..., 1], srt[..., 2]
    cos = (mid**2 + longest**2 - shortest**2) / np.maximum(2 * mid * longest, 1e-300)
    sin = np.sqrt(np.clip(1 - cos**2, 0.0, 1.0))
    return (0.866 / np.maximum(sin, 1e-4)) ** 4 + 0.25 * (longest / ref) ** 2


def bridge_chains(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles (K, 3) filling the band between open chains a and b of vertex ids.

    The band runs from the edge a[0]-b[0] to the edge a[-1]-b[-1]; either end may be a single
    shared vertex (a[0] == b[0] or a[-1] == b[-1]). Chain a is traversed forwards and chain b
    backwards by the triangles, so a band between two rows given in the same direction is
    consistently wound.
    """
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    shared_start = a[0] == b[0]
    shared_end = a[-1] == b[-1]
    tris: list[tuple[int, int, int]] = []
    if shared_start:
        if len(a) < 2 or len(b) < 2:
            raise ValueError("chains sharing a vertex need at least 2 vertices each")
        tris.append((a[0], a[1], b[1]))
        a0, b0 = 1, 1
    else:
        a0, b0 = 0, 0
    a1, b1 = len(a) - 1, len(b) - 1
    if shared_end:
        a1, b1 = a1 - 1, b1 - 1
    if a1 < a0 or b1 < b0:
        raise ValueError("chains too short for the shared ends")
    pa, pb = points[a[a0 : a1 + 1]], points[b[b0 : b1 + 1]]
    n, m = len(pa), len(pb)
    steps = np.concatenate(
        [np.linalg.norm(np.diff(pa, axis=0), axis=1), np.linalg.norm(np.diff(pb, axis=0), axis=1)]
    )
    ref = float(np.median(steps)) if len(steps) else 1.0
    cost_a = _tri_cost(pa[:-1, None], pa[1:, None], pb[None, :], ref)  # (n-1, m): a advances
    cost_b = _tri_cost(pa[:, None], pb[None, :-1], pb[None, 1:], ref)  # (n, m-1): b advances
    big = np.inf
    d = np.full((n, m), big)
    from_a = np.zeros((n, m), dtype=bool)
    for i in range(n):
        if i == 0:
            base = np.full(m, big)
            base[0] = 0.0
        else:
            base = d[i - 1] + cost_a[i - 1]
        if m > 1:
            s = np.concatenate([[0.0], np.cumsum(cost_b[i])])
            d[i] = s + np.minimum.accumulate(base - s)
            via_b = np.concatenate([[big], d[i, :-1] + cost_b[i]])
            from_a[i] = base <= via_b
        else:
            d[i] = base
            from_a[i] = True
    i, j = n - 1, m - 1
    path: list[tuple[int, int, int]] = []
    while i > 0 or j > 0:
        if i > 0 and (from_a[i, j] or j == 0):
            path.append((a0 + i - 1, a0 + i, -(b0 + j) - 1))
            i -= 1
        else:
            path.append((a0 + i, -(b0 + j) - 1, -(b0 + j - 1) - 1))
            j -= 1
    for x, y, z in reversed(path):
        ids = [a[v] if v >= 0 else b[-v - 1] for v in (x, y, z)]
        tris.append((ids[0], ids[1], ids[2]))
    if shared_end:
        tris.append((a[-2], a[-1], b[-2]))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def bridge_loops(
    points: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    anchors: list[tuple[int, int]] | None = None,
) -> np.ndarray:
    """Triangles between two closed loops given in the same rotational direction.

    `anchors` are pairs (index into a, index into b) that must be joined by an edge, in order
    along both loops; by default the first vertex of a is joined to its nearest vertex of b.
    """
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    if not anchors:
        k = int(np.argmin(np.linalg.norm(points[b] - points[a[0]], axis=1)))
        anchors = [(0, k)]
    out = []
    for n_anchor, (ia, jb) in enumerate(anchors):
        ia2, jb2 = anchors[(n_anchor + 1) % len(anchors)]
        seg_a = _cyclic(a, ia, ia2)
        seg_b = _cyclic(b, jb, jb2)
        out.append(bridge_chains(points, seg_a, seg_b))
    return np.concatenate(out)


def _cyclic(loop: np.ndarray, i: int, j: int) -> np.ndarray:
    """loop[i..j] inclusive, wrapping; the whole loop plus its first vertex when i == j."""
    n = len(loop)
    if j <= i:
        j += n
    return loop[np.arange(i, j + 1) % n]


# -- sewing ------------------------------------------------------------------------------------

SEW_KINDS = {"jumpsuit": "trousers", "dress": "skirt"}


def _resample_loop(points: np.ndarray, n: int, start: np.ndarray) -> np.ndarray:
    """n points evenly spaced along a closed polyline, the first nearest to `start`."""
    from datagen.garment.patterns import arclength, point_at, project_arclength

    s0 = project_arclength(points, start)
    total = arclength(points)[-1]
    return point_at(points, s0 + np.linspace(0.0, total, n, endpoint=False))


def _orient_like(loop: np.ndarray, points: np.ndarray, axis_dir: np.ndarray) -> np.ndarray:
    """The loop in counter-clockwise order about axis_dir."""
    p = points[loop]
    c = p.mean(axis=0)
    turn = np.cross(p - c, np.roll(p, -1, axis=0) - c).sum(axis=0)
    return loop if turn @ axis_dir > 0 else loop[::-1]


def sew(upper: GarmentTemplate, lower: GarmentTemplate, kind: str) -> GarmentTemplate:
    """One full-body garment: the upper garment's torso is trimmed to end a row above the lower
    garment's waist, and its hem loop is stitched to the waist loop by a band of triangles (with
    intermediate rows when the two loops are far apart). The lower garment's waist loop becomes
    the closed path `paths["waist"]` along the seam.

    `kind` is "jumpsuit" (upper + trousers) or "dress" (upper + skirt). Sew before cutting the
    upper's torso: an upper whose hem already ends above the lower's waist cannot be stitched.
    """
    if kind not in SEW_KINDS:
        raise InputError(None, "kind", " or ".join(repr(k) for k in SEW_KINDS), kind)
    if upper.category != "upper" or "hem" not in upper.loops or "torso" not in upper.rows:
        raise InputError(
            upper.meta.get("source", upper.name),
            "category",
            "an upper-body template with a hem loop and torso rows",
            upper.name,
        )
    if lower.category != "lower" or "waist" not in lower.loops:
        raise InputError(
            lower.meta.get("source", lower.name),
            "category",
            "a lower-body template with a waist loop",
            lower.name,
        )
    want = SEW_KINDS[kind]
    if lower.meta.get("template", lower.name) != want:
        raise InputError(
            lower.meta.get("source", lower.name), "name", f"a {want} for a {kind}", lower.name
        )
    if "shirt" == upper.name or "front_edge_l" in upper.loops:
        raise InputError(
            upper.meta.get("source", upper.name),
            "name",
            "a closed upper garment (not an open shirt)",
            upper.name,
        )
    from datagen.garment.cutting import cut_axis

    waist = lower.vertices[lower.loops["waist"]]
    z_waist = float(waist[:, 2].mean())
    axis = upper.axes["torso"]
    rows = upper.rows["torso"]
    x_waist = float((np.array([0.0, 0.0, z_waist]) - axis.origin) @ axis.direction)
    spacing = float(np.median(np.diff(rows.x))) if len(rows.x) > 1 else upper.resolution
    # Keep the rows at least 0.6 row spacings above the waist.
    keep_until = x_waist - 0.6 * spacing
    if rows.x[-1] < keep_until - 1.5 * spacing:
        raise InputError(
            upper.meta.get("source", upper.name),
            "loops.hem",
            f"a hem at or below the waist of the {want} (z <= {z_waist + 1.5 * spacing:.3f} m); "
            "sew before cutting the torso",
            f"hem at z = {float(upper.vertices[upper.loops['hem']][:, 2].mean()):.3f} m",
        )
    up = cut_axis(upper, "torso", keep_until) if rows.x[-1] > keep_until else upper.copy()
    lo = lower.copy()
    n_up = up.n_vertices
    vertices = np.vstack([up.vertices, lo.vertices])
    down = np.array([0.0, 0.0, -1.0])
    hem = _orient_like(up.loops["hem"], up.vertices, down)
    wst = _orient_like(lo.loops["waist"], lo.vertices, down) + n_up
    # Intermediate rows when the hem and the waist are more than ~1.5 spacings apart.
    gap = float(np.abs(vertices[hem][:, 2].mean() - vertices[wst][:, 2].mean()))
    radial = abs(
        np.linalg.norm(vertices[hem] - vertices[hem].mean(axis=0), axis=1).mean()
        - np.linalg.norm(vertices[wst] - vertices[wst].mean(axis=0), axis=1).mean()
    )
    n_mid = max(0, int(np.ceil(np.hypot(gap, radial) / (1.1 * spacing))) - 1)
    chains = [hem]
    new_points = []
    next_id = len(vertices)
    for k in range(1, n_mid + 1):
        t = k / (n_mid + 1)
        n_pts = int(round((1 - t) * len(hem) + t * len(wst)))
        pa = _resample_loop(vertices[hem], n_pts, vertices[hem[0]])
        pb = _resample_loop(vertices[wst], n_pts, pa[0])
        pts = (1 - t) * pa + t * pb
        ids = np.arange(next_id, next_id + n_pts)
        next_id += n_pts
        new_points.append(pts)
        chains.append(ids)
    chains.append(wst)
    if new_points:
        vertices = np.vstack([vertices, *new_points])
    band = [bridge_loops(vertices, chains[k], chains[k + 1]) for k in range(len(chains) - 1)]
    band_faces = np.concatenate(band)
    faces = np.vstack([up.faces, lo.faces + n_up, band_faces]).astype(np.int64)
    # Orient the band like the garments: their faces traverse the shared loop edges opposite.
    faces = _orient_band(faces, len(up.faces) + len(lo.faces))
    names = list(up.region_names)
    for nm in lo.region_names:
        if nm not in names:
            names.append(nm)
    remap = np.array([names.index(nm) for nm in lo.region_names], dtype=np.int16)
    n_new = len(vertices) - n_up - lo.n_vertices
    band_region = names.index("torso") if "torso" in names else 0
    regions = np.concatenate(
        [up.regions, remap[lo.regions], np.full(n_new, band_region, dtype=np.int16)]
    ).astype(np.int16)
    loops = {k: v for k, v in up.loops.items() if k != "hem"}
    loops.update({k: v + n_up for k, v in lo.loops.items() if k != "waist"})
    axes = {
        k: Axis(a.origin.copy(), a.direction.copy(), a.length, a.region) for k, a in up.axes.items()
    }
    axes.update(
        {
            k: Axis(a.origin.copy(), a.direction.copy(), a.length, a.region)
            for k, a in lo.axes.items()
        }
    )
    rows = {
        k: RowSet(r.x.copy(), [v.copy() for v in r.vertices], r.min_width, r.max_width)
        for k, r in up.rows.items()
        if k != "torso"
    }
    rows.update(
        {
            k: RowSet(r.x.copy(), [v + n_up for v in r.vertices], r.min_width, r.max_width)
            for k, r in lo.rows.items()
        }
    )
    axes.pop("torso", None)
    cut_lines = {k: dict(c) for k, c in up.cut_lines.items() if c["axis"] in axes}
    cut_lines.update({k: dict(c) for k, c in lo.cut_lines.items()})
    uv = None
    if up.uv is not None and lo.uv is not None:
        shift = np.array([up.uv[:, 0].max() - lo.uv[:, 0].min() + 0.1, 0.0])
        mid_uv = np.zeros((n_new, 2))
        if n_new:
            mid_uv[:] = up.uv[hem].mean(axis=0)
        uv = np.vstack([up.uv, lo.uv + shift, mid_uv])
    panel = None
    panel_names = tuple(up.panel_names) + tuple(lo.panel_names)
    if up.panel is not None and lo.panel is not None:
        panel = np.concatenate(
            [
                up.panel,
                lo.panel + len(up.panel_names),
                np.full(n_new, up.panel[hem[0]], dtype=np.int16),
            ]
        ).astype(np.int16)
    # The lower garment's waistband is now a seam inside the garment, not a boundary loop; it
    # stays as a closed path so the fitted garment can attach it to the body and make it elastic.
    paths = {"waist": wst.copy()}
    meta = {
        "template": kind,
        "parts": [up.meta.get("template", up.name), lo.meta.get("template", lo.name)],
        "upper": up.meta,
        "lower": lo.meta,
        "seam_rows": int(n_mid),
    }
    return GarmentTemplate(
        vertices=vertices,
        faces=faces.astype(np.int32),
        name=kind,
        category="full",
        gender=up.gender,
        loops=loops,
        region_names=tuple(names),
        regions=regions,
        axes=axes,
        cut_lines=cut_lines,
        uv=uv,
        panel=panel,
        body=up.body,
        resolution=up.resolution,
        meta=meta,
        rows=rows,
        paths=paths,
        open_loops=tuple(r for r in up.open_loops if r in loops)
        + tuple(r for r in lo.open_loops if r in loops),
        panel_names=panel_names,
    )


def _orient_band(faces: np.ndarray, n_fixed: int) -> np.ndarray:
    """Flip the faces after `n_fixed` (a band built between loops) so that they agree with the
    orientation of the fixed faces along shared edges, propagating through the band."""
    faces = faces.copy()
    fixed_dir: dict[tuple[int, int], bool] = {}
    for f in faces[:n_fixed]:
        for k in range(3):
            fixed_dir[(int(f[k]), int(f[(k + 1) % 3]))] = True
    band = list(range(n_fixed, len(faces)))
    # Half-edge -> face lookup inside the band for propagation.
    decided: dict[int, bool] = {}
    pending = set(band)
    while pending:
        progressed = False
        for fi in sorted(pending):
            f = faces[fi]
            hes = [(int(f[k]), int(f[(k + 1) % 3])) for k in range(3)]
            vote = 0
            for a, b in hes:
                if (a, b) in fixed_dir:
                    vote -= 1  # same direction as a fixed face: must flip
                elif (b, a) in fixed_dir:
                    vote += 1
            if vote != 0:
                if vote < 0:
                    faces[fi] = faces[fi][::-1]
                f = faces[fi]
                for k in range(3):
                    fixed_dir[(int(f[k]), int(f[(k + 1) % 3]))] = True
                decided[fi] = True
                pending.discard(fi)
                progressed = True
        if not progressed:
            raise ValueError("band faces are not connected to the garments")
    return faces
