"""Building the shipped garment templates from patterns drafted on Anny's neutral rest body.

Each template is assembled from panels made of rows (docs/templates.md, "How templates are made"):

- tshirt: front and back bodice panels (horizontal rows from the hem up to the armpit), a yoke
  over the shoulders made of columns in planes x = const (front panel up to the shoulder seam,
  back panel down from it) with the neck opening cut out, and two sleeves (rows in planes
  perpendicular to the arm) set into the armholes;
- top: the bodice panels up to the armpit line and two shoulder straps (columns over the
  shoulders);
- trousers: four panels (front/back x left/right): horizontal rows from the waist down to the
  crotch, the crotch seam, then each leg's rows perpendicular to the leg axis;
- skirt: front and back A-line panels: horizontal rows from the waist down, flaring.

Rows that meet along a seam share their vertices (the seam is welded by construction) and
consecutive rows are stitched by sewing.bridge_chains, so the result is one manifold piece whose
rows lie in planes perpendicular to the shaping axes: a length cut removes whole rows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datagen.garment import patterns as P
from datagen.garment.sewing import bridge_chains, bridge_loops
from datagen.garment.template import (
    Axis,
    BodyProximity,
    GarmentTemplate,
    RowSet,
    boundary_loops,
    edge_table,
    face_normals,
)
from datagen.skeleton import JOINT_INDEX
from datagen.types import RestBody

TEMPLATE_NAMES = ("tshirt", "top", "trousers", "skirt")
GENDERS = ("female", "male")
# Edge length of the shipped templates (about 1 cm, as CLOTH3D's garments): 6-14k vertices per
# garment. `datagen templates build --resolution` makes coarser or finer sets.
SHIPPED_RESOLUTION = 0.01
ROW_FACTOR = 0.87  # row spacing / resolution: near-equilateral triangles between rows
MIN_BUILD_CLEARANCE = 0.008  # m: vertices are pushed out to this (the check demands 5 mm)
MIN_SHAPED_CLEARANCE = 0.007  # m: shaping never narrows a row below this clearance
SHAPED_AXES = ("sleeve_l", "sleeve_r", "leg_l", "leg_r", "skirt")

# Ease (m) added around the body's convex cross-section, per garment and place: a tee a few cm
# looser than the chest, trousers not skin-tight, a snug waistband.
EASE = {
    "tshirt": {"torso": 0.025, "yoke": 0.012, "armhole": 0.016, "sleeve": 0.02},
    "top": {"torso": 0.015, "strap": 0.008},
    "trousers": {"waist": 0.010, "hips": 0.016, "leg": 0.022},
    "skirt": {"waist": 0.010, "hips": 0.018},
}
TORSO_TAPER = {"tshirt": 0.006, "top": 0.012, "trousers": 0.006}  # per row: a bodice (or the
# hips) may be at most this much narrower than the row above it, so cloth hangs from the bust
SLEEVE_TAPER = 0.025  # per row: how fast the sleeve narrows from the armhole to follow the arm
LEG_TAPER = 0.012  # per row: trouser legs hang rather than following the calf and ankle
SKIRT_FLARE = np.tan(np.radians(9.0))  # the skirt's panels flare by this much per metre of drop


@dataclass
class Landmarks:
    """Body measurements the patterns are drafted from (all in the rest body's frame)."""

    shoulder: np.ndarray  # left shoulder joint
    wrist_x: float
    armhole_x: float  # |x| of the armhole plane
    armpit_z: float  # height of the armhole's bottom
    neck_centre: np.ndarray  # (x=0, y, z) of the neck base
    neck_axis: np.ndarray  # unit direction from the neck joint to the head joint (leans forward)
    neck_half_width: float
    neck_front: float  # distance from the neck centre to the front of the neck
    neck_back: float
    waist_z: float
    crotch_z: float
    crotch_gap: float  # half the distance between the inner thighs at crotch_z
    hip: dict  # side -> hip joint
    ankle: dict  # side -> ankle joint
    hem_z: float  # the tee/top's full length


def measure(rest: RestBody, cloud: P.BodyCloud) -> Landmarks:
    j = rest.joints
    pts = cloud.points
    shoulder = j[JOINT_INDEX["left_shoulder"]]
    arms = cloud.parts("upperarm_l", "upperarm_r", "forearm_l", "forearm_r", "hand_l", "hand_r")
    # Armhole: the innermost plane x = xa beyond which only the arm lies above the armpit, with
    # the torso's side (plus a margin) inside it.
    armhole_x = armpit_z = None
    upper = pts[:, 2] > shoulder[2] - 0.3
    for xa in np.arange(shoulder[0] - 0.03, shoulder[0] + 0.10, 0.002):
        beyond = upper & (pts[:, 0] >= xa) & (pts[:, 0] <= xa + 0.05)
        z_low = pts[beyond, 2].min() - EASE["tshirt"]["armhole"]
        band = (pts[:, 2] > z_low - 0.03) & (pts[:, 2] < z_low + 0.005)
        side = np.abs(pts[band, 0]).max()
        if side + 0.012 <= xa:
            armhole_x, armpit_z = float(xa), float(z_low)
            break
    if armhole_x is None:
        raise RuntimeError("could not find the armpit of the rest body")
    # Neck: its section a little above the neck joint (lower down it merges with the shoulders).
    zn = j[JOINT_INDEX["neck"], 2]
    neck = pts[
        (np.abs(pts[:, 2] - zn - 0.03) < 0.005)
        & (np.abs(pts[:, 0]) < 0.12)
        & ~arms
        & ~cloud.parts("head")
    ]
    # Its depth at the base (front of the throat to the back of the neck), near the midline.
    base = pts[(np.abs(pts[:, 2] - zn) < 0.01) & (np.abs(pts[:, 0]) < 0.04) & cloud.parts("neck")]
    yc = 0.5 * (base[:, 1].min() + base[:, 1].max())
    # Waist of trousers and skirts: a mid-rise waistband a little above the pelvis joint.
    pelvis = j[JOINT_INDEX["pelvis"]]
    waist_z = float(pelvis[2] + 0.075)
    # Crotch seam: the highest height where the thighs are far enough apart for two layers of
    # fabric with clearance, and below the crotch itself.
    legs = ~arms & (pts[:, 2] < pelvis[2])
    crotch_z = None
    for z in np.arange(pelvis[2] - 0.05, pelvis[2] - 0.35, -0.0025):
        sl = legs & (np.abs(pts[:, 2] - z) < 0.004) & (np.abs(pts[:, 0]) < 0.12)
        near = pts[sl]
        if len(near) == 0:
            continue
        gap = np.abs(near[:, 0]).min()
        if gap >= 0.018:
            crotch_z = float(z - 0.01)
            break
    if crotch_z is None:
        raise RuntimeError("could not find the crotch of the rest body")
    sl = legs & (np.abs(pts[:, 2] - crotch_z) < 0.004) & (np.abs(pts[:, 0]) < 0.12)
    crotch_gap = float(np.abs(pts[sl, 0]).min())
    return Landmarks(
        shoulder=shoulder,
        wrist_x=float(j[JOINT_INDEX["left_wrist"], 0]),
        armhole_x=armhole_x,
        armpit_z=armpit_z,
        neck_centre=np.array([0.0, yc, zn]),
        neck_axis=(j[JOINT_INDEX["head"]] - j[JOINT_INDEX["neck"]])
        / np.linalg.norm(j[JOINT_INDEX["head"]] - j[JOINT_INDEX["neck"]]),
        neck_half_width=float(np.abs(neck[:, 0]).max()),
        neck_front=float(yc - base[:, 1].min()),
        neck_back=float(base[:, 1].max() - yc),
        waist_z=waist_z,
        crotch_z=crotch_z,
        crotch_gap=crotch_gap,
        hip={s: j[JOINT_INDEX[f"{s}_hip"]] for s in ("left", "right")},
        ankle={s: j[JOINT_INDEX[f"{s}_ankle"]] for s in ("left", "right")},
        hem_z=float(crotch_z + 0.03),
    )


# -- mesh assembly -----------------------------------------------------------------------------


class Builder:
    """Vertices (with region and panel labels and pattern coordinates) and faces being stitched."""

    def __init__(self) -> None:
        self.points = np.zeros((0, 3))
        self.region: list[str] = []
        self.panel: list[str] = []
        self.uv = np.zeros((0, 2))
        self.faces: list[np.ndarray] = []

    def add(
        self,
        pts: np.ndarray,
        region: str,
        panel: str | list[str] = "",
        uv: np.ndarray | None = None,
    ) -> np.ndarray:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        ids = np.arange(len(self.points), len(self.points) + len(pts))
        self.points = np.vstack([self.points, pts])
        self.region += [region] * len(pts)
        self.panel += [panel] * len(pts) if isinstance(panel, str) else list(panel)
        uv = (
            np.zeros((len(pts), 2))
            if uv is None
            else np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        )
        self.uv = np.vstack([self.uv, uv])
        return ids

    def chains(self, a, b) -> None:
        self.faces.append(bridge_chains(self.points, np.asarray(a), np.asarray(b)))

    def loops(self, a, b, anchors=None) -> None:
        self.faces.append(bridge_loops(self.points, np.asarray(a), np.asarray(b), anchors))

    def face_array(self) -> np.ndarray:
        return np.concatenate(self.faces).astype(np.int64)


def _anchor_pairs(a_anchor: list[int], b_anchor: list[int]) -> list[tuple[int, int]]:
    return list(zip(a_anchor, b_anchor, strict=True))


def _start_at(poly: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The closed polygon re-started at its point nearest to `point` (inserted as a vertex)."""
    s0 = P.project_arclength(poly, point)
    cum = P.arclength(poly)
    p0 = P.point_at(poly, np.array([s0]))[0]
    k = min(int(np.searchsorted(cum, s0, side="right")), len(poly))  # first vertex after it
    order = np.r_[np.arange(k, len(poly)), np.arange(0, k)]
    out = np.vstack([p0, poly[order]])
    keep = np.r_[True, np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-9]
    out = out[keep]
    if np.linalg.norm(out[-1] - out[0]) <= 1e-9:
        out = out[:-1]
    return out


def _torso_anchors(poly: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """A horizontal (x, y) row polygon, counter-clockwise seen from above, started at its front
    centre (x = 0, y < 0), and the arc lengths of its front centre, left side (max x), back centre
    and right side (min x): the anchors that keep rows symmetric and the front centre line a chain
    of edges."""
    poly = _ccw(poly)
    front = _crossing(poly, -1.0)
    poly = _start_at(poly, front)
    back = _crossing(poly, 1.0)
    # The sides: where the polygon crosses the line midway between the front and back centres
    # (stable from row to row even where a side is straight).
    mid = 0.5 * (front[1] + back[1])
    left = _crossing(poly, 1.0, 1, mid)
    right = _crossing(poly, -1.0, 1, mid)
    return poly, [
        0.0,
        P.project_arclength(poly, left),
        P.project_arclength(poly, back),
        P.project_arclength(poly, right),
    ]


def _crossing(poly: np.ndarray, side: float, coord: int = 0, value: float = 0.0) -> np.ndarray:
    """Where a convex 2D polygon crosses the line p[coord] = value: the crossing with the smaller
    other coordinate (side < 0) or the larger one (side > 0)."""
    pts = np.vstack([poly, poly[:1]])
    other = 1 - coord
    out = []
    for p, q in zip(pts[:-1], pts[1:], strict=True):
        if (p[coord] <= value < q[coord]) or (q[coord] <= value < p[coord]):
            t = (value - p[coord]) / (q[coord] - p[coord])
            out.append(p + t * (q - p))
    out = np.asarray(out)
    return out[np.argmin(out[:, other])] if side < 0 else out[np.argmax(out[:, other])]


def _horizontal_frame(z: float) -> P.PlaneFrame:
    # e1 = x, e2 = y: 2D coordinates are simply (x, y) for rows at height z.
    return P.PlaneFrame(
        np.array([0.0, 0.0, z]),
        np.array([0.0, 0.0, 1.0]),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 1.0, 0.0]),
    )


def _column_frame(x: float) -> P.PlaneFrame:
    # Planes x = const with 2D coordinates (y, z).
    return P.PlaneFrame(
        np.array([x, 0.0, 0.0]),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 1.0, 0.0]),
        np.array([0.0, 0.0, 1.0]),
    )


def _row_vertices(poly2d: np.ndarray, frame: P.PlaneFrame, spacing: float, anchors: list[float]):
    pts, idx = P.sample_polyline(poly2d, spacing, anchors)
    return frame.to3d(pts), idx


def _ccw(poly: np.ndarray) -> np.ndarray:
    return poly if P.signed_area(poly) > 0 else poly[::-1]


# -- the torso (tshirt and top) -----------------------------------------------------------------


def _torso_rows(
    b: Builder,
    cloud: P.BodyCloud,
    top_ids: np.ndarray,
    top_anchor: list[int],
    z0: float,
    z_end: float,
    d: float,
    s: float,
    ease: float,
    arms: np.ndarray | None = None,
    taper: float = 0.006,
    side_limit: float | None = None,
) -> tuple[list[np.ndarray], list[int], list[float]]:
    """Horizontal rows hanging from the row `top_ids` at height z0 down to z_end; returns the
    rows (the top one first), the front-centre vertex of each, and their heights."""
    if arms is None:
        arms = cloud.parts("upperarm_l", "upperarm_r", "forearm_l", "forearm_r", "hand_l", "hand_r")
    prev = b.points[top_ids][:, :2]
    rows = [top_ids]
    fronts = [int(top_ids[top_anchor[0]])]
    heights = [z0]
    prev_anchor = top_anchor
    n = int(np.floor((z0 - z_end) / d + 0.5))
    for k in range(1, n + 1):
        z = z0 - k * d
        frame = _horizontal_frame(z)
        sec = P.section(cloud, frame, 0.6 * d + 0.002, ease, ~arms)
        c = prev.mean(axis=0)
        hang = P.scale_about(prev, c, 1.0 - taper)
        poly = P.union_hull(sec, hang)
        if side_limit is not None:
            # Under the arms the sides widen at most 1 in 2 below the armhole, so the bodice
            # does not bulge out under the sleeve.
            reach = side_limit + 0.5 * (z0 - z)
            for normal in ([1.0, 0.0], [-1.0, 0.0]):
                poly = P.clip_convex(poly, np.array(normal), reach)
        poly, anchors = _torso_anchors(poly)
        pts, idx = _row_vertices(poly, frame, s, anchors)
        uv, panel = _ring_uv(pts, idx, np.full(len(pts), z), 1.2)
        ids = b.add(pts, "torso", panel, uv)
        b.loops(rows[-1], ids, _anchor_pairs(prev_anchor, idx))
        rows.append(ids)
        fronts.append(int(ids[idx[0]]))
        heights.append(z)
        prev, prev_anchor = poly, idx
    return rows, fronts, heights


def _front_back(pts: np.ndarray) -> list[str]:
    return ["front" if p[1] < 0.0 else "back" for p in pts]


# -- tshirt -------------------------------------------------------------------------------------


def _arc_over(poly: np.ndarray, z0: float) -> np.ndarray:
    """The part of a convex (y, z) polygon clipped at z >= z0 that runs from its front-bottom
    corner over the top to its back-bottom corner (dense, front first)."""
    poly = _ccw(poly)
    on_bottom = np.abs(poly[:, 1] - z0) < 1e-9
    k_front = int(np.flatnonzero(on_bottom)[np.argmin(poly[on_bottom, 0])])
    k_back = int(np.flatnonzero(on_bottom)[np.argmax(poly[on_bottom, 0])])
    # Counter-clockwise in (y, z) runs front-bottom -> back-bottom along the bottom edge, so the
    # arc over the top is the clockwise way from the front corner to the back corner.
    order = []
    k = k_front
    while True:
        order.append(k)
        if k == k_back:
            break
        k = (k - 1) % len(poly)
    arc = poly[order]
    dense = P.point_at(arc, np.arange(0, P.perimeter(arc, False), 0.002), closed=False)
    return np.vstack([dense, arc[-1:]])


def _neck_hole(lm: Landmarks) -> tuple[float, float, float]:
    """Semi-axes (x, front, back) of the neck opening seen from above."""
    return (lm.neck_half_width + 0.026, lm.neck_front + 0.018, lm.neck_back + 0.022)


def _in_neck(p: np.ndarray, lm: Landmarks, za: float) -> np.ndarray:
    """Points inside the neck opening's footprint: an elliptic cylinder along the (forward
    leaning) neck, seen along the neck, above the armpit line."""
    a, bf, bb = _neck_hole(lm)
    # Slide each point along the neck's axis to the height of the neck centre (below the neck's
    # base the footprint goes straight down, not on into the upper back).
    along = np.maximum((p[:, 2] - lm.neck_centre[2]) / lm.neck_axis[2], -0.03)
    dy = p[:, 1] - along * lm.neck_axis[1] - lm.neck_centre[1]
    b = np.where(dy < 0, bf, bb)
    inside = ((p[:, 0] / a) ** 2 + (dy / b) ** 2 < 1.0) & (p[:, 2] > za + 0.03)
    # Nothing of the garment reaches above the neck joint: the head and upper neck never count.
    return inside | (p[:, 2] > lm.neck_centre[2] + 0.015)


def build_tshirt(rest: RestBody, cloud: P.BodyCloud, lm: Landmarks, h: float) -> GarmentTemplate:
    ease = EASE["tshirt"]
    d = ROW_FACTOR * h
    b = Builder()
    xa, za = lm.armhole_x, lm.armpit_z
    n_half = max(2, int(round(xa / d)))
    dc = xa / n_half
    xs = np.arange(-n_half + 1, n_half) * dc  # yoke columns; the armholes are at +-xa
    body = ~cloud.parts("head")
    # The armpit line: a horizontal section just under the arms, clipped at the armhole planes.
    frame = _horizontal_frame(za + 0.01)
    line = P.section(
        cloud, frame, 0.02, ease["yoke"] + 0.004, body & (np.abs(cloud.points[:, 0]) < xa)
    )
    line = P.clip_convex(P.clip_convex(line, np.array([1.0, 0.0]), xa), np.array([-1.0, 0.0]), xa)

    def ends(x: float) -> tuple[float, float]:
        ys = _vertical_crossings(line, x)
        return float(ys.min()), float(ys.max())

    # Columns of the yoke and the two armholes.
    in_neck = _in_neck(cloud.points, lm, za)  # the neck opening's footprint, seen from above
    columns: list[np.ndarray] = []
    for x in xs:
        frame = _column_frame(x)
        yf, yb = ends(x)
        sec = P.section(
            cloud,
            frame,
            0.6 * dc + 0.002,
            ease["yoke"],
            body & ~in_neck & (cloud.points[:, 2] > za - 0.02),
        )
        poly = P.union_hull(sec, np.array([[yf, za], [yb, za]]))
        poly = P.clip_convex(poly, np.array([0.0, -1.0]), -za)
        arc = _arc_over(poly, za)
        columns.append(np.column_stack([np.full(len(arc), x), arc]))
    armholes = {}
    for side in (1.0, -1.0):
        x = side * xa
        frame = _column_frame(x)
        neighbour = columns[-1] if side > 0 else columns[0]
        sec = P.section(
            cloud, frame, 0.6 * dc + 0.002, ease["armhole"], body & (cloud.points[:, 2] > za - 0.02)
        )
        poly = P.union_hull(sec, neighbour[[0, -1]][:, 1:])
        poly = P.clip_convex(poly, np.array([0.0, -1.0]), -za)
        armholes[side] = np.column_stack(
            [np.full(len(_arc_over(poly, za)), x), _arc_over(poly, za)]
        )
    return _assemble_tshirt(b, rest, cloud, lm, h, xs, columns, armholes)


def _vertical_crossings(poly: np.ndarray, x: float) -> np.ndarray:
    pts = np.vstack([poly, poly[:1]])
    ys = []
    for p, q in zip(pts[:-1], pts[1:], strict=True):
        if (p[0] - x) * (q[0] - x) <= 0 and p[0] != q[0]:
            t = (x - p[0]) / (q[0] - p[0])
            ys.append(p[1] + t * (q[1] - p[1]))
    return np.asarray(ys)


@dataclass
class _Col:
    x: float
    chain: np.ndarray | None  # whole column (front corner -> back corner), or None if split
    front: np.ndarray | None = None  # front piece (front corner -> neckline)
    back: np.ndarray | None = None  # back piece (neckline -> back corner)

    @property
    def first(self) -> int:
        return int((self.chain if self.chain is not None else self.front)[0])

    @property
    def last(self) -> int:
        return int((self.chain if self.chain is not None else self.back)[-1])


def _deepen_neckline(holes: list, step: float, spacing: float) -> list:
    """Where the neckline drops faster than `step` (arc length) from one cut column to the next,
    lower the shallower column's neckline (never raise one: the opening may only grow, so the
    columns never cover the neck that was left out of them). Steep necklines would otherwise cut
    the band between two columns into slivers. Each piece's length is then rounded down to whole
    vertex spacings, so the neckline vertices of neighbouring columns line up in rows.
    `holes` holds (start, end, arc length) per column, or None; returns (start, end) or None."""
    lo = [h[0] if h else None for h in holes]
    back = [h[2] - h[1] if h else None for h in holes]  # length of the back piece
    for _ in range(len(holes)):
        changed = False
        for j in range(len(holes)):
            for k in (j - 1, j + 1):
                if lo[j] is None or not 0 <= k < len(holes) or lo[k] is None:
                    continue
                if lo[j] > lo[k] + step:
                    lo[j], changed = lo[k] + step, True
                if back[j] > back[k] + step:
                    back[j], changed = back[k] + step, True
        if not changed:
            break
    out = []
    for j, h in enumerate(holes):
        if h is None:
            out.append(None)
            continue
        front_len = spacing * max(1.0, np.floor(lo[j] / spacing))
        back_len = spacing * max(1.0, np.floor(back[j] / spacing))
        out.append((front_len, h[2] - back_len))
    return out


def _nearest_index(b: Builder, chain: np.ndarray, vertex: int) -> int:
    return int(np.argmin(np.linalg.norm(b.points[chain] - b.points[vertex], axis=1)))


def _bridge_columns(b: Builder, left: _Col, right: _Col, t_front: np.ndarray, t_back: np.ndarray):
    """Stitch the band between two neighbouring columns; t_front runs along the armpit line from
    the left column's front end to the right one's, t_back from the right back end to the left.

    Where a column is cut by the neck opening, the band is stitched from the armpit line up to the
    neckline on the front and on the back separately; where the neckline is steep the longer
    chain is stitched only up to its vertex nearest to the other chain's end and the rest of it
    becomes part of the neckline.
    """
    tf, tb = list(t_front[:-1]), list(t_back[1:])
    if left.chain is not None and right.chain is not None:
        b.chains(left.chain, np.r_[tf, right.chain, tb])
        return
    lf = left.chain if left.chain is not None else left.front
    rf = right.chain if right.chain is not None else right.front
    lb = left.chain if left.chain is not None else left.back
    rb = right.chain if right.chain is not None else right.back
    # Only a chain that ends at the neckline can mark where its partner stops.
    cut_left, cut_right = left.chain is None, right.chain is None
    # Front: chains from the shared front corner up towards the neckline.
    a, c = lf, np.r_[tf, rf]
    ka = _nearest_index(b, a, c[-1]) if cut_right else len(a) - 1
    kc = _nearest_index(b, c, a[-1]) if cut_left else len(c) - 1
    b.chains(a[: ka + 1], c[: kc + 1])
    # Back: chains from the neckline down to the shared back corner.
    a, c = lb, np.r_[rb, tb]
    ka = _nearest_index(b, a, c[0]) if cut_right else 0
    kc = _nearest_index(b, c, a[0]) if cut_left else 0
    b.chains(a[ka:], c[kc:])


def _column_piece(
    b: Builder,
    arc: np.ndarray,
    lo: float,
    hi: float,
    first: int | None,
    last: int | None,
    s: float,
    za: float,
) -> np.ndarray:
    """Vertices every ~s along arc[lo..hi] (arc length), reusing the given end vertices."""
    cum = P.arclength(arc, closed=False)
    part = arc[(cum >= lo - 1e-12) & (cum <= hi + 1e-12)]
    ends = P.point_at(arc, np.array([lo, hi]), False)
    part = np.vstack([ends[0], part, ends[1]])
    pts, _ = P.sample_polyline(part, s, None, closed=False)
    uv, panels = _column_uv(pts, arc, za, 1.2)
    ids = np.empty(len(pts), dtype=np.int64)
    inner = slice(1 if first is not None else 0, len(pts) - 1 if last is not None else len(pts))
    ids[inner] = b.add(pts[inner], "torso", panels[inner], uv[inner])
    if first is not None:
        ids[0] = first
    if last is not None:
        ids[-1] = last
    return ids


def _segment_points(p: np.ndarray, q: np.ndarray, s: float) -> np.ndarray:
    """Points strictly between p and q, about s apart."""
    n = max(1, int(round(np.linalg.norm(q - p) / s)))
    t = np.arange(1, n)[:, None] / n
    return p + t * (q - p)


def _assemble_tshirt(b, rest, cloud, lm, h, xs, columns, armholes) -> GarmentTemplate:
    ease = EASE["tshirt"]
    d, s = ROW_FACTOR * h, h
    za = lm.armpit_z
    j0 = int(np.argmin(np.abs(xs)))
    # Neck opening on the central columns: the arc-length interval of each arc inside it.
    holes: list = []
    for arc in columns:
        inside = _in_neck(arc, lm, za)
        if not inside.any():
            holes.append(None)
            continue
        cum = P.arclength(arc, closed=False)
        k = np.flatnonzero(inside)
        holes.append((float(cum[k[0]]), float(cum[k[-1]]), float(cum[-1])))
    holes = _deepen_neckline(holes, 1.2 * (xs[1] - xs[0]), s)
    # The armpit line: column ends, armhole bottoms and points between them, counter-clockwise
    # seen from above starting at the front centre.
    keys: list[tuple[str, object, np.ndarray]] = []
    order_front = list(range(j0, len(xs)))
    for j in order_front:
        keys.append(("front", j, columns[j][0]))
    keys.append(("arm_front", 1.0, armholes[1.0][0]))
    keys.append(("arm_back", 1.0, armholes[1.0][-1]))
    for j in range(len(xs) - 1, -1, -1):
        keys.append(("back", j, columns[j][-1]))
    keys.append(("arm_back", -1.0, armholes[-1.0][-1]))
    keys.append(("arm_front", -1.0, armholes[-1.0][0]))
    for j in range(0, j0):
        keys.append(("front", j, columns[j][0]))
    t_ids: list[int] = []
    key_id: dict[tuple[str, object], int] = {}
    flat_mid: dict[float, int] = {}
    for n_key, (kind, which, p) in enumerate(keys):
        region = "torso"
        vid = int(b.add(p, region, "front" if kind in ("front", "arm_front") else "back")[0])
        key_id[(kind, which)] = vid
        t_ids.append(vid)
        q = keys[(n_key + 1) % len(keys)][2]
        between = _segment_points(p, q, s)
        flat = kind.startswith("arm_") and keys[(n_key + 1) % len(keys)][0].startswith("arm_")
        if len(between):
            ids = b.add(between, "torso", _front_back(between))
            t_ids += ids.tolist()
            if flat:
                flat_mid[which] = int(ids[len(ids) // 2])
        elif flat:
            raise RuntimeError("armhole bottom too short")
    t_ids_arr = np.asarray(t_ids)
    pos = {v: i for i, v in enumerate(t_ids)}
    ring_anchor = [
        pos[key_id[("front", j0)]],
        pos[flat_mid[1.0]],
        pos[key_id[("back", j0)]],
        pos[flat_mid[-1.0]],
    ]
    b.uv[t_ids_arr], ring_panel = _ring_uv(
        b.points[t_ids_arr], ring_anchor, np.full(len(t_ids), za), 1.2
    )
    for v, p in zip(t_ids, ring_panel, strict=True):
        b.panel[v] = p

    def t_chain(v_from: int, v_to: int) -> np.ndarray:
        i, k = pos[v_from], pos[v_to]
        if k < i:
            k += len(t_ids)
        return t_ids_arr[np.arange(i, k + 1) % len(t_ids)]

    # Column vertices.
    cols: list[_Col] = []
    for j, arc in enumerate(columns):
        vf, vb = key_id[("front", j)], key_id[("back", j)]
        cum = P.arclength(arc, closed=False)

        hole = holes[j]
        if hole is None:
            cols.append(_Col(xs[j], _column_piece(b, arc, 0.0, cum[-1], vf, vb, s, za)))
        else:
            cols.append(
                _Col(
                    xs[j],
                    None,
                    _column_piece(b, arc, 0.0, hole[0], vf, None, s, za),
                    _column_piece(b, arc, hole[1], cum[-1], None, vb, s, za),
                )
            )
    arm_chain = {}
    for side, arc in armholes.items():
        vf, vb = key_id[("arm_front", side)], key_id[("arm_back", side)]
        pts, _ = P.sample_polyline(arc, s, None, closed=False)
        region = "sleeve_l" if side > 0 else "sleeve_r"
        inner = b.add(pts[1:-1], region, region)
        arm_chain[side] = np.r_[vf, inner, vb]
    # Stitch the yoke: armhole(-), columns, armhole(+).
    seq = [_Col(-lm.armhole_x, arm_chain[-1.0])] + cols + [_Col(lm.armhole_x, arm_chain[1.0])]
    for left, right in zip(seq[:-1], seq[1:], strict=True):
        _bridge_columns(
            b, left, right, t_chain(left.first, right.first), t_chain(right.last, left.last)
        )
    # Bodice rows hanging from the armpit line.
    anchors = [
        pos[key_id[("front", j0)]],
        pos[flat_mid[1.0]],
        pos[key_id[("back", j0)]],
        pos[flat_mid[-1.0]],
    ]
    t_anchor = sorted(anchors)
    if t_anchor != anchors:
        raise RuntimeError("armpit line anchors out of order")
    torso_rows, fronts, heights = _torso_rows(
        b,
        cloud,
        t_ids_arr,
        anchors,
        za,
        lm.hem_z,
        d,
        s,
        ease["torso"],
        taper=TORSO_TAPER["tshirt"],
        side_limit=lm.armhole_x,
    )
    # Sleeves.
    arm_c = np.array([lm.shoulder[1], lm.shoulder[2]])
    above = cloud.points[:, 2] > za - 0.03  # the arms, not the hips below them
    sleeve_rows = {}
    for side in (1.0, -1.0):
        region = "sleeve_l" if side > 0 else "sleeve_r"
        x0 = side * lm.armhole_x
        chain = arm_chain[side]
        if side > 0:
            bottom = t_chain(key_id[("arm_front", side)], key_id[("arm_back", side)])
        else:
            bottom = t_chain(key_id[("arm_back", side)], key_id[("arm_front", side)])[::-1]
        loop = np.r_[
            bottom, chain[-2:0:-1]
        ]  # (y, z) counter-clockwise: bottom front->back, top back->front
        k0 = int(
            np.argmin(
                np.abs(b.points[loop][:, 1] - arm_c[0]) + 10 * (b.points[loop][:, 2] > za + 1e-6)
            )
        )
        loop = np.roll(loop, -k0)
        top = int(
            np.argmin(
                np.abs(b.points[loop][:, 1] - arm_c[0]) + 10 * (b.points[loop][:, 2] < arm_c[1])
            )
        )
        prev_poly = b.points[loop][:, 1:]
        prev_ids, prev_anchor = loop, [0, top]
        arc_ids = np.isin(loop, chain[1:-1])
        b.uv[loop[arc_ids]] = _sleeve_uv(b.points[loop], 0.0, side)[arc_ids]
        rows = [loop]
        xk = [0.0]
        n_rows = int(np.floor((lm.wrist_x - 0.01 - lm.armhole_x) / d))
        for k in range(1, n_rows + 1):
            x = x0 + side * k * d
            frame = _column_frame(x)
            sec = P.section(cloud, frame, 0.6 * d + 0.002, ease["sleeve"], above)
            hang = P.scale_about(prev_poly, arm_c, 1.0 - SLEEVE_TAPER)
            poly = _ccw(P.union_hull(sec, hang))
            poly = _start_at(poly, _crossing(poly, -1.0, 0, arm_c[0]))
            s_top = P.project_arclength(poly, _crossing(poly, 1.0, 0, arm_c[0]))
            pts, idx = _row_vertices(poly, frame, s, [0.0, s_top])
            ids = b.add(pts, region, region, _sleeve_uv(pts, k * d, side))
            b.loops(prev_ids, ids, _anchor_pairs(prev_anchor, idx))
            prev_poly, prev_ids, prev_anchor = poly, ids, idx
            rows.append(ids)
            xk.append(k * d)
        sleeve_rows[region] = (rows, np.asarray(xk))
    z_sh = float(lm.shoulder[2])
    yc = float(lm.neck_centre[1])
    axes = {
        "torso": Axis(
            np.array([0.0, yc, z_sh]), np.array([0.0, 0.0, -1.0]), z_sh - heights[-1], "torso"
        )
    }
    rows = {"torso": RowSet(z_sh - np.asarray(heights), torso_rows)}
    loops = {"hem": torso_rows[-1]}
    for side, region in ((1.0, "sleeve_l"), (-1.0, "sleeve_r")):
        srows, xk = sleeve_rows[region]
        axes[region] = Axis(
            np.array([side * lm.armhole_x, lm.shoulder[1], lm.shoulder[2]]),
            np.array([side, 0.0, 0.0]),
            float(xk[-1]),
            region,
        )
        rows[region] = RowSet(xk, srows)
        loops[f"{region}_end"] = srows[-1]
    cut_lines = {
        "sleeve_l": {"axis": "sleeve_l", "min": 0.04, "max": axes["sleeve_l"].length},
        "sleeve_r": {"axis": "sleeve_r", "min": 0.04, "max": axes["sleeve_r"].length},
        "torso": {"axis": "torso", "min": float(z_sh - za + 0.12), "max": axes["torso"].length},
    }
    centre_col = cols[j0]
    front_path = np.r_[centre_col.front[::-1], fronts[1:]] if centre_col.front is not None else None
    paths = {"front_centre": front_path} if front_path is not None else {}
    return _finish(
        b,
        rest,
        "tshirt",
        "upper",
        h,
        loops,
        "neck",
        axes,
        rows,
        cut_lines,
        paths,
        ("torso", "sleeve_l", "sleeve_r"),
        lm,
    )


# -- finishing ----------------------------------------------------------------------------------


def orient_faces(faces: np.ndarray) -> np.ndarray:
    """Faces re-wound so that every interior edge is traversed in opposite directions by its two
    faces (breadth-first over each connected piece)."""
    faces = np.asarray(faces, dtype=np.int64).copy()
    edges, counts, inverse = edge_table(faces)
    per_edge: list[list[int]] = [[] for _ in range(len(edges))]
    for h_id, e in enumerate(inverse):
        per_edge[e].append(h_id // 3)
    neighbours: list[list[int]] = [[] for _ in range(len(faces))]
    for fs in per_edge:
        if len(fs) == 2:
            neighbours[fs[0]].append(fs[1])
            neighbours[fs[1]].append(fs[0])
    seen = np.zeros(len(faces), dtype=bool)

    def directed(f):
        return {(int(f[0]), int(f[1])), (int(f[1]), int(f[2])), (int(f[2]), int(f[0]))}

    for start in range(len(faces)):
        if seen[start]:
            continue
        seen[start] = True
        queue = [start]
        while queue:
            fi = queue.pop()
            mine = directed(faces[fi])
            for g in neighbours[fi]:
                if seen[g]:
                    continue
                if directed(faces[g]) & mine:
                    faces[g] = faces[g][::-1]
                seen[g] = True
                queue.append(g)
    return faces


def row_width(points: np.ndarray) -> float:
    """Width of a row: its perimeter / pi (the diameter of a circle as long), whatever its shape."""
    return P.perimeter(points) / np.pi


def _min_widths(points, axis: Axis, rows: RowSet, prox: BodyProximity) -> np.ndarray:
    """Per row, the narrowest width that radial scaling about the axis can give it while every
    vertex keeps MIN_SHAPED_CLEARANCE from the body (bisection on the scale)."""
    out = np.empty(len(rows.x))
    for k, (x, ids) in enumerate(zip(rows.x, rows.vertices, strict=True)):
        p = points[ids]
        c = axis.origin + x * axis.direction
        lo, hi = 0.2, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            d = prox.signed_distance(c + mid * (p - c), exact_below=0.0)
            lo, hi = (lo, mid) if d.min() >= MIN_SHAPED_CLEARANCE else (mid, hi)
        out[k] = hi * row_width(p)
    return out


def _max_widths(points, axis: Axis, rows: RowSet, gap: float = 0.004) -> np.ndarray:
    """Per leg row, the widest width before radial scaling brings its inner side within `gap` of
    the middle plane x = 0 (where the other leg is)."""
    out = np.empty(len(rows.x))
    sign = np.sign(axis.origin[0])
    for k, (x, ids) in enumerate(zip(rows.x, rows.vertices, strict=True)):
        p = points[ids]
        c = axis.origin + x * axis.direction
        inner = sign * (p[:, 0] - c[0])  # < 0 towards the middle
        reach = -inner.min()
        limit = sign * c[0] - gap
        out[k] = row_width(p) * max(1.0, limit / reach) if reach > 0 else 10.0
    return out


def _push_out(b: Builder, prox: BodyProximity, iterations: int = 3) -> None:
    """Move the few vertices closer than MIN_BUILD_CLEARANCE to the body straight away from it (a
    safety net: the drafted rows already keep their ease)."""
    for _ in range(iterations):
        d = prox.signed_distance(b.points)
        near = np.flatnonzero(d < MIN_BUILD_CLEARANCE)
        if not len(near):
            return
        q, n = prox.nearest(b.points[near])
        b.points[near] += (MIN_BUILD_CLEARANCE + 0.001 - d[near])[:, None] * n


def _edge_keys(chain: np.ndarray) -> set[tuple[int, int]]:
    return {
        (min(int(a), int(c)), max(int(a), int(c)))
        for a, c in zip(chain[:-1], chain[1:], strict=True)
    }


def _min_angle(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> float:
    angles = []
    for a, c, e in ((p, q, r), (q, r, p), (r, p, q)):
        u, w = c - a, e - a
        cos = u @ w / max(np.linalg.norm(u) * np.linalg.norm(w), 1e-300)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return min(angles)


def improve_by_flips(
    points: np.ndarray, faces: np.ndarray, protected: set, threshold: float = 30.0, passes: int = 4
) -> np.ndarray:
    """Flip interior edges of triangles with an angle below `threshold` where the flip raises the
    smaller minimum angle of the two triangles and keeps them facing the same way. Edges in
    `protected` (rows, paths) are never flipped, so rows stay closed chains of edges."""
    faces = np.asarray(faces, dtype=np.int64).copy()
    from datagen.garment.template import triangle_angles

    for _ in range(passes):
        bad = np.flatnonzero(triangle_angles(points, faces).min(axis=1) < threshold)
        if not len(bad):
            break
        edge_faces: dict[tuple[int, int], list[int]] = {}
        for fi, f in enumerate(faces):
            for k in range(3):
                key = (min(f[k], f[(k + 1) % 3]), max(f[k], f[(k + 1) % 3]))
                edge_faces.setdefault(key, []).append(fi)
        changed = False
        touched: set[int] = set()
        for fi in bad:
            if fi in touched:
                continue
            f = faces[fi]
            for k in range(3):
                a, c = int(f[k]), int(f[(k + 1) % 3])
                key = (min(a, c), max(a, c))
                pair = edge_faces.get(key, [])
                if key in protected or len(pair) != 2:
                    continue
                gi = pair[0] if pair[1] == fi else pair[1]
                if gi in touched:
                    continue
                e = int(f[(k + 2) % 3])  # opposite a-c in face fi, which runs a -> c
                g = faces[gi]
                d = int(next(v for v in g if v not in (a, c)))
                if (min(e, d), max(e, d)) in edge_faces:
                    continue
                before = min(_min_angle(*points[[a, c, e]]), _min_angle(*points[[c, a, d]]))
                t1, t2 = (a, d, e), (d, c, e)
                after = min(_min_angle(*points[list(t1)]), _min_angle(*points[list(t2)]))
                if after <= before + 1.0:
                    continue
                n_old = np.cross(points[c] - points[a], points[e] - points[a])
                n1 = np.cross(points[d] - points[a], points[e] - points[a])
                n2 = np.cross(points[c] - points[d], points[e] - points[d])
                if n1 @ n_old <= 0 or n2 @ n_old <= 0:
                    continue
                faces[fi], faces[gi] = t1, t2
                edge_faces[(min(e, d), max(e, d))] = [fi, gi]  # no second flip makes it again
                touched |= {fi, gi}
                changed = True
                break
        if not changed:
            break
    return faces


def _finish(
    b: Builder,
    rest: RestBody,
    name: str,
    category: str,
    h: float,
    loops_from_rows: dict[str, np.ndarray],
    leftover_role: str | None,
    axes: dict[str, Axis],
    rows: dict[str, RowSet],
    cut_lines: dict,
    paths: dict[str, np.ndarray],
    region_names: tuple[str, ...],
    lm: Landmarks,
    extra_roles: dict[str, callable] | None = None,
) -> GarmentTemplate:
    faces = orient_faces(b.face_array())
    # Chain ends that a steep neckline left unstitched belong to no face: drop them.
    used = np.zeros(len(b.points), dtype=bool)
    used[faces.ravel()] = True
    if not used.all():
        new_id = np.cumsum(used) - 1
        new_id[~used] = -1
        faces = new_id[faces]
        b.points, b.uv = b.points[used], b.uv[used]
        b.region = [r for r, u in zip(b.region, used, strict=True) if u]
        b.panel = [p for p, u in zip(b.panel, used, strict=True) if u]
        for rs in rows.values():
            rs.vertices = [new_id[r] for r in rs.vertices]
        loops_from_rows = {k: new_id[v] for k, v in loops_from_rows.items()}
        for k, path in list(paths.items()):
            mapped = new_id[path]
            cut = np.flatnonzero(mapped < 0)
            paths[k] = mapped[cut[-1] + 1 :] if len(cut) else mapped
    prox = BodyProximity(rest.vertices, rest.faces)
    _push_out(b, prox)
    # Moving vertices can thin a few triangles; flips (never of row edges) restore them.
    protected = set()
    for rs in rows.values():
        for ids in rs.vertices:
            protected |= _edge_keys(np.r_[ids, ids[:1]])
    for path in paths.values():
        protected |= _edge_keys(path)
    faces = improve_by_flips(b.points, faces, protected)
    centres = b.points[faces].mean(axis=1)
    q, _ = prox.nearest(centres)
    if np.sum(np.einsum("ij,ij->i", face_normals(b.points, faces), centres - q)) < 0:
        faces = faces[:, ::-1]
    loops: dict[str, np.ndarray] = {}
    found = boundary_loops(faces)
    used = set()
    for role, row in loops_from_rows.items():
        target = set(int(i) for i in row)
        for k, loop in enumerate(found):
            if set(loop.tolist()) == target:
                loops[role] = loop
                used.add(k)
                break
        else:
            raise RuntimeError(f"{name}: row for loop '{role}' is not a boundary loop")
    rest_loops = [loop for k, loop in enumerate(found) if k not in used]
    if extra_roles:
        for role, pick in extra_roles.items():
            k = pick(b.points, rest_loops)
            loops[role] = rest_loops.pop(k)
    if leftover_role is not None:
        if len(rest_loops) != 1:
            raise RuntimeError(f"{name}: expected one more boundary loop, found {len(rest_loops)}")
        loops[leftover_role] = rest_loops[0]
    elif rest_loops:
        raise RuntimeError(f"{name}: {len(rest_loops)} unexpected boundary loops")
    regions = np.array([region_names.index(r) for r in b.region], dtype=np.int16)
    panel_names = tuple(dict.fromkeys(b.panel))
    panel = np.array([panel_names.index(p) for p in b.panel], dtype=np.int16)
    for axis_name in SHAPED_AXES:
        if axis_name in rows:
            rows[axis_name].min_width = _min_widths(
                b.points, axes[axis_name], rows[axis_name], prox
            )
            if axis_name.startswith("leg_"):
                rows[axis_name].max_width = _max_widths(b.points, axes[axis_name], rows[axis_name])
    shape = {n: float(v) for n, v in zip(rest.shape_names, rest.shape, strict=True)}
    t = GarmentTemplate(
        vertices=b.points.copy(),
        faces=faces.astype(np.int32),
        name=name,
        category=category,
        gender=rest.gender,
        loops=loops,
        region_names=region_names,
        regions=regions,
        axes=axes,
        cut_lines=cut_lines,
        uv=b.uv.copy(),
        panel=panel,
        body={"model": rest.model, "gender": rest.gender, "shape": shape},
        resolution=float(h),
        meta={"template": name, "builder": "datagen.garment.build"},
        rows=rows,
        paths=paths,
        panel_names=panel_names,
    )
    return t


# -- top ----------------------------------------------------------------------------------------


def _horizontal_row(
    cloud: P.BodyCloud,
    z: float,
    half: float,
    ease: float,
    mask: np.ndarray,
    prev: np.ndarray | None = None,
    taper: float = 0.0,
    flare: float = 0.0,
) -> tuple[np.ndarray, list[float]]:
    """A horizontal row polygon (x, y) at height z: the body section grown by `ease`, hanging from
    (or flaring out of) the previous row, started at its front centre, with its anchors."""
    sec = P.section(cloud, _horizontal_frame(z), half, ease, mask)
    hang = None
    if prev is not None:
        hang = P.scale_about(prev, prev.mean(axis=0), 1.0 - taper) if taper else prev
        if flare:
            hang = P.offset_convex(hang, flare)
    return _torso_anchors(P.union_hull(sec, hang))


def _ring_uv(pts: np.ndarray, anchor: list[int], v: np.ndarray, back_shift: float):
    """Pattern coordinates of a ring sampled from its front centre with anchors (front, left,
    back, right): u is the arc length from the front (or back) centre, positive towards +x."""
    closed = np.vstack([pts, pts[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed[:, :3], axis=0), axis=1))])
    total = s[-1]
    s = s[:-1]
    s_left, s_back, s_right = s[anchor[1]], s[anchor[2]], s[anchor[3]]
    u = np.empty(len(pts))
    panel = []
    for i, si in enumerate(s):
        if si <= s_left:
            u[i], p = si, "front"
        elif si <= s_back:
            u[i], p = back_shift + (s_back - si), "back"
        elif si <= s_right:
            u[i], p = back_shift - (si - s_back), "back"
        else:
            u[i], p = -(total - si), "front"
        panel.append(p)
    return np.column_stack([u, v]), panel


def build_top(rest: RestBody, cloud: P.BodyCloud, lm: Landmarks, h: float) -> GarmentTemplate:
    ease = EASE["top"]
    d, s = ROW_FACTOR * h, h
    b = Builder()
    za = lm.armpit_z
    body = ~cloud.parts("head")
    arms = cloud.parts("upperarm_l", "upperarm_r", "forearm_l", "forearm_r", "hand_l", "hand_r")
    inside = body & (np.abs(cloud.points[:, 0]) < lm.armhole_x)
    line = P.section(cloud, _horizontal_frame(za + 0.01), 0.02, ease["torso"], inside)
    line, anchors = _torso_anchors(line)
    # Shoulder straps: four columns each side, centred midway along the shoulder.
    n_half = max(2, int(round(lm.armhole_x / d)))
    dc = lm.armhole_x / n_half
    centre = lm.neck_half_width + 0.045
    strap_x = [side * (centre + (i - 1.5) * dc) for side in (-1.0, 1.0) for i in range(4)]
    strap_x = sorted(strap_x)
    arcs, ends = [], []
    for x in strap_x:
        ys = _vertical_crossings(line, x)
        pinned = np.array([[ys.min(), za], [ys.max(), za]])
        sec = P.section(
            cloud,
            _column_frame(x),
            0.6 * dc + 0.002,
            ease["strap"],
            body & (cloud.points[:, 2] > za - 0.02),
        )
        poly = P.clip_convex(P.union_hull(sec, pinned), np.array([0.0, -1.0]), -za)
        arc = _arc_over(poly, za)
        arcs.append(np.column_stack([np.full(len(arc), x), arc]))
        ends += [
            P.project_arclength(line, np.array([x, ys.min()])),
            P.project_arclength(line, np.array([x, ys.max()])),
        ]
    marks = sorted(set([round(a, 9) for a in anchors + ends]))
    pts2, idx = P.sample_polyline(line, s, marks)
    mark_index = dict(zip(marks, idx, strict=True))
    t_pts = _horizontal_frame(za).to3d(pts2)
    t_anchor = [mark_index[round(a, 9)] for a in anchors]
    uv, panel = _ring_uv(t_pts, t_anchor, np.full(len(t_pts), za), 1.2)
    t_ids = b.add(t_pts, "torso", panel, uv)
    pos = {int(v): i for i, v in enumerate(t_ids)}

    def t_chain(v_from: int, v_to: int) -> np.ndarray:
        i, k = pos[v_from], pos[v_to]
        if k < i:
            k += len(t_ids)
        return t_ids[np.arange(i, k + 1) % len(t_ids)]

    cols = []
    for n_col, arc in enumerate(arcs):
        vf = int(t_ids[mark_index[round(ends[2 * n_col], 9)]])
        vb = int(t_ids[mark_index[round(ends[2 * n_col + 1], 9)]])
        pts, _ = P.sample_polyline(arc, s, None, closed=False)
        uv, panel = _column_uv(pts, arc, za, 1.2)
        inner = b.add(pts[1:-1], "straps", panel[1:-1], uv[1:-1])
        cols.append(_Col(float(arc[0, 0]), np.r_[vf, inner, vb]))
    for left, right in zip(cols[:-1], cols[1:], strict=True):
        if abs(right.x - left.x) > 1.5 * dc:
            continue  # between the two straps: the neckline
        _bridge_columns(
            b, left, right, t_chain(left.first, right.first), t_chain(right.last, left.last)
        )
    torso_rows, fronts, heights = _torso_rows(
        b, cloud, t_ids, t_anchor, za, lm.hem_z, d, s, ease["torso"], arms, TORSO_TAPER["top"]
    )
    z_sh = float(lm.shoulder[2])
    axes = {
        "torso": Axis(
            np.array([0.0, float(lm.neck_centre[1]), z_sh]),
            np.array([0.0, 0.0, -1.0]),
            z_sh - heights[-1],
            "torso",
        )
    }
    rows = {"torso": RowSet(z_sh - np.asarray(heights), torso_rows)}
    cut_lines = {
        "torso": {"axis": "torso", "min": float(z_sh - za + 0.12), "max": axes["torso"].length}
    }
    picks = {
        "armhole_l": lambda pts, loops: int(np.argmax([pts[lp][:, 0].mean() for lp in loops])),
        "armhole_r": lambda pts, loops: int(np.argmin([pts[lp][:, 0].mean() for lp in loops])),
    }
    return _finish(
        b,
        rest,
        "top",
        "upper",
        h,
        {"hem": torso_rows[-1]},
        "neck",
        axes,
        rows,
        cut_lines,
        {"front_centre": np.asarray(fronts)},
        ("torso", "straps"),
        lm,
        extra_roles=picks,
    )


def _sleeve_uv(pts: np.ndarray, x: float, side: float) -> np.ndarray:
    """Sleeve panel coordinates of a ring that starts at its underarm seam: u along the arm,
    v the arc length around it."""
    closed = np.vstack([pts, pts[:1]])
    v = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])[:-1]
    return np.column_stack([np.full(len(pts), (2.2 if side > 0 else 3.0) + x), v])


def _column_uv(pts: np.ndarray, arc: np.ndarray, z0: float, back_shift: float):
    """Pattern coordinates along a column: u = x, v = z0 + arc length from its nearer end (the
    front panel up to the top of the arc, the back panel from there)."""
    cum = P.arclength(arc, closed=False)
    s_top = cum[int(np.argmax(arc[:, 2]))]
    uv, panel = [], []
    for p in pts:
        sp = P.project_arclength(arc, p, closed=False)
        if sp <= s_top:
            uv.append([p[0], z0 + sp])
            panel.append("front")
        else:
            uv.append([back_shift + p[0], z0 + (cum[-1] - sp)])
            panel.append("back")
    return np.asarray(uv), panel


# -- trousers -----------------------------------------------------------------------------------


def _leg_axis(lm: Landmarks, side: str) -> tuple[np.ndarray, np.ndarray]:
    """The leg's axis (hip joint to ankle joint, pointing down) and its point at crotch height."""
    hip, ankle = lm.hip[side], lm.ankle[side]
    u = (ankle - hip) / np.linalg.norm(ankle - hip)
    origin = hip + u * (hip[2] - lm.crotch_z) / -u[2]
    return origin, u


def build_trousers(rest: RestBody, cloud: P.BodyCloud, lm: Landmarks, h: float) -> GarmentTemplate:
    ease = EASE["trousers"]
    d, s = ROW_FACTOR * h, h
    b = Builder()
    arms = cloud.parts("upperarm_l", "upperarm_r", "forearm_l", "forearm_r", "hand_l", "hand_r")
    # Hips: horizontal rows from the waistband down to the crotch seam.
    n_hips = max(2, int(round((lm.waist_z - lm.crotch_z) / d)))
    dz = (lm.waist_z - lm.crotch_z) / n_hips
    hips_rows, prev, prev_anchor, anchors = [], None, None, None
    for k in range(n_hips + 1):
        z = lm.waist_z - k * dz
        e = ease["waist"] + (ease["hips"] - ease["waist"]) * min(1.0, k * dz / 0.06)
        poly, marks = _horizontal_row(
            cloud, z, 0.6 * dz + 0.002, e, ~arms, prev, TORSO_TAPER["trousers"]
        )
        pts, idx = _row_vertices(poly, _horizontal_frame(z), s, marks)
        uv, panel = _ring_uv(pts, idx, np.full(len(pts), z), 1.2)
        panel = [f"{p}_{'l' if q[0] >= 0 else 'r'}" for p, q in zip(panel, pts, strict=True)]
        ids = b.add(pts, "hips", panel, uv)
        if hips_rows:
            b.loops(hips_rows[-1], ids, _anchor_pairs(prev_anchor, idx))
        hips_rows.append(ids)
        prev, prev_anchor = poly, idx
    crotch, anchors = hips_rows[-1], prev_anchor
    front, back = int(crotch[anchors[0]]), int(crotch[anchors[2]])
    line = _segment_points(b.points[back], b.points[front], s)  # back -> front along x = 0
    line_uv = np.column_stack([np.zeros(len(line)), np.full(len(line), lm.crotch_z)])
    line_ids = b.add(line, "hips", "front_l", line_uv)
    k_mid = anchors[2]
    d_loops = {
        "left": np.r_[crotch[: k_mid + 1], line_ids],  # front -> left side -> back -> front
        "right": np.r_[crotch[k_mid:], crotch[0], line_ids[::-1]],
    }
    axes, rows, loops = {}, {}, {"waist": hips_rows[0]}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        region = "leg_l" if sign > 0 else "leg_r"
        origin, u = _leg_axis(lm, side)
        x_end = (origin[2] - (lm.ankle[side][2] + 0.035)) / -u[2]
        n_rows = int(np.floor(x_end / d))
        x_gap = max(0.004, 0.5 * lm.crotch_gap - 0.004)
        mask = ~arms & (sign * cloud.points[:, 0] > 0) & (cloud.points[:, 2] < lm.crotch_z + 0.05)
        # Anchor the crotch loop where the leg's centre line crosses it (front and back), like
        # the leg rows below, so both halves of each band have matching lengths.
        prev_ids = d_loops[side]
        ring = b.points[prev_ids][:, :2]
        k_front = int(np.argmin(np.linalg.norm(ring - _crossing(ring, -1.0, 0, origin[0]), axis=1)))
        prev_ids = np.roll(prev_ids, -k_front)
        ring = b.points[prev_ids][:, :2]
        k_back = int(np.argmin(np.linalg.norm(ring - _crossing(ring, 1.0, 0, origin[0]), axis=1)))
        prev_anchor = [0, k_back]
        prev_pts = b.points[prev_ids]
        rows_side, xs = [prev_ids], [0.0]
        for k in range(1, n_rows + 1):
            xk = k * d
            w = min(1.0, xk / 0.08)
            n = (1 - w) * np.array([0.0, 0.0, -1.0]) + w * u
            frame = P.PlaneFrame.make(origin + xk * u, -n)  # normal up: rows run like the hips'
            e = ease["leg"]
            normal2d = -sign * np.array([frame.e1[0], frame.e2[0]])
            c2d = sign * frame.origin[0] - x_gap
            sec = P.section(cloud, frame, 0.6 * d + 0.002, e, mask, [(normal2d, c2d)])
            hang = P.scale_about(frame.to2d(prev_pts), np.zeros(2), 1.0 - LEG_TAPER)
            poly = P.clip_convex(_ccw(P.union_hull(sec, hang)), normal2d, c2d)
            front_pt = _crossing(poly, -1.0, 0, 0.0)
            poly = _start_at(poly, front_pt)
            s_back = P.project_arclength(poly, _crossing(poly, 1.0, 0, 0.0))
            pts2, idx = P.sample_polyline(poly, s, [0.0, s_back])
            pts = frame.to3d(pts2)
            uv, panel = _leg_uv(pts2, idx, lm.crotch_z - xk, sign)
            ids = b.add(pts, region, panel, uv)
            b.loops(prev_ids, ids, _anchor_pairs(prev_anchor, idx))
            rows_side.append(ids)
            xs.append(xk)
            prev_ids, prev_anchor, prev_pts = ids, idx, pts
        axes[region] = Axis(origin, u, float(xs[-1]), region)
        rows[region] = RowSet(np.asarray(xs), rows_side)
        loops[f"{region}_end"] = rows_side[-1]
    cut_lines = {r: {"axis": r, "min": 0.06, "max": axes[r].length} for r in ("leg_l", "leg_r")}
    return _finish(
        b,
        rest,
        "trousers",
        "lower",
        h,
        loops,
        None,
        axes,
        rows,
        cut_lines,
        {},
        ("hips", "leg_l", "leg_r"),
        lm,
    )


def _leg_uv(pts2: np.ndarray, idx: list[int], v: float, sign: float):
    """Leg rows (2D in the row's frame, started at the front crease line): the front panel is the
    half in front of the leg's centre, u the arc length from the front (or back) crease line;
    v = the height of the crotch seam minus the distance down the leg."""
    closed = np.vstack([pts2, pts2[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    total, s = s[-1], s[:-1]
    s_back = s[idx[1]]
    tag = "l" if sign > 0 else "r"
    front = pts2[:, 1] < 0.0
    u = np.where(front, np.where(s <= total / 2, s, s - total), 1.2 + (s - s_back)) + 0.15 * sign
    panel = [f"front_{tag}" if f else f"back_{tag}" for f in front]
    return np.column_stack([u, np.full(len(pts2), v)]), panel


# -- skirt --------------------------------------------------------------------------------------


def build_skirt(rest: RestBody, cloud: P.BodyCloud, lm: Landmarks, h: float) -> GarmentTemplate:
    ease = EASE["skirt"]
    d, s = ROW_FACTOR * h, h
    b = Builder()
    arms = cloud.parts("upperarm_l", "upperarm_r", "forearm_l", "forearm_r", "hand_l", "hand_r")
    z_hem = float(lm.ankle["left"][2] + 0.25)
    n = max(2, int(round((lm.waist_z - z_hem) / d)))
    dz = (lm.waist_z - z_hem) / n
    rows_ids, heights, fronts = [], [], []
    prev, prev_anchor = None, None
    for k in range(n + 1):
        z = lm.waist_z - k * dz
        e = ease["waist"] + (ease["hips"] - ease["waist"]) * min(1.0, k * dz / 0.06)
        poly, marks = _horizontal_row(
            cloud, z, 0.6 * dz + 0.002, e, ~arms, prev, flare=SKIRT_FLARE * dz
        )
        pts, idx = _row_vertices(poly, _horizontal_frame(z), s, marks)
        uv, panel = _ring_uv(pts, idx, np.full(len(pts), z), 2.5)
        ids = b.add(pts, "skirt", panel, uv)
        if rows_ids:
            b.loops(rows_ids[-1], ids, _anchor_pairs(prev_anchor, idx))
        rows_ids.append(ids)
        heights.append(z)
        fronts.append(int(ids[idx[0]]))
        prev, prev_anchor = poly, idx
    yc = float(b.points[rows_ids[0]][:, 1].mean())
    axes = {
        "skirt": Axis(
            np.array([0.0, yc, lm.waist_z]),
            np.array([0.0, 0.0, -1.0]),
            lm.waist_z - heights[-1],
            "skirt",
        )
    }
    rows = {"skirt": RowSet(lm.waist_z - np.asarray(heights), rows_ids)}
    mini = lm.waist_z - (lm.crotch_z - 0.10)
    cut_lines = {"skirt": {"axis": "skirt", "min": float(mini), "max": axes["skirt"].length}}
    return _finish(
        b,
        rest,
        "skirt",
        "lower",
        h,
        {"waist": rows_ids[0], "hem": rows_ids[-1]},
        None,
        axes,
        rows,
        cut_lines,
        {"front_centre": np.asarray(fronts)},
        ("skirt",),
        lm,
    )


# -- building everything ------------------------------------------------------------------------

BUILDERS = {
    "tshirt": build_tshirt,
    "top": build_top,
    "trousers": build_trousers,
    "skirt": build_skirt,
}


def build_template(
    name: str,
    rest: RestBody,
    resolution: float = SHIPPED_RESOLUTION,
    cloud: P.BodyCloud | None = None,
) -> GarmentTemplate:
    """One template drafted on `rest` (a rest body in the canonical T-pose)."""
    if name not in BUILDERS:
        raise ValueError(f"unknown template {name!r}; known: {', '.join(BUILDERS)}")
    cloud = cloud or P.BodyCloud(rest)
    lm = measure(rest, cloud)
    t = BUILDERS[name](rest, cloud, lm, resolution)
    t.meta["landmarks"] = {
        "armhole_x": round(lm.armhole_x, 5),
        "armpit_z": round(lm.armpit_z, 5),
        "waist_z": round(lm.waist_z, 5),
        "crotch_z": round(lm.crotch_z, 5),
    }
    return t


def build_all(
    out_dir: str | Path,
    resolution: float = SHIPPED_RESOLUTION,
    names=TEMPLATE_NAMES,
    genders=GENDERS,
    report=None,
) -> list[dict]:
    """Build and save every template; returns one summary per template (mesh_stats + time)."""
    from datagen.body.anny_model import NEUTRAL_SHAPE, default_body_model
    from datagen.garment.template import mesh_stats, save_template

    model = default_body_model()
    out = []
    for gender in genders:
        rest = model.rest_body(gender, NEUTRAL_SHAPE)
        cloud = P.BodyCloud(rest)
        prox = BodyProximity(rest.vertices, rest.faces)
        for name in names:
            t0 = time.perf_counter()
            t = build_template(name, rest, resolution, cloud)
            seconds = time.perf_counter() - t0
            obj, _ = save_template(t, Path(out_dir) / gender / name)
            stats = mesh_stats(t, prox)
            stats.update({"name": name, "gender": gender, "seconds": seconds, "path": str(obj)})
            out.append(stats)
            if report:
                report(stats)
    return out
