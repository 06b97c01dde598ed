"""Drafting patterns on the rest body: cross-sections, ease, and rows of evenly spaced vertices.

A garment is drafted as rows of closed (or open) polygons in planes perpendicular to its axes,
like a tailor's measurements taken every centimetre: the body is cut by the row's plane, the cut
is wrapped by its convex hull (cloth bridges hollows), grown by the ease of the garment at that
place (a Minkowski offset), and constrained by the rows before it (cloth hangs from the bust, a
skirt flares from the hips). Each polygon is then sampled with vertices every `resolution`
metres; build.py stitches consecutive rows with strips of triangles (sewing.bridge_chains).

Everything here is plain numpy on convex polygons in a plane frame (`PlaneFrame`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from datagen.types import RestBody

# -- plane frames ------------------------------------------------------------------------------


@dataclass
class PlaneFrame:
    """A plane with an orthonormal basis: e1 x e2 = normal, so loops that are counter-clockwise
    in (e1, e2) turn positively about the normal."""

    origin: np.ndarray
    normal: np.ndarray
    e1: np.ndarray
    e2: np.ndarray

    @staticmethod
    def make(origin, normal, towards=None) -> PlaneFrame:
        """Frame whose e1 is `towards` (default: world x, or y if the normal is along x) projected
        into the plane."""
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        if towards is None:
            towards = [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]
        t = np.asarray(towards, dtype=np.float64)
        e1 = t - (t @ n) * n
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        return PlaneFrame(np.asarray(origin, dtype=np.float64), n, e1, e2)

    def to2d(self, p: np.ndarray) -> np.ndarray:
        d = np.asarray(p, dtype=np.float64) - self.origin
        return np.stack([d @ self.e1, d @ self.e2], axis=-1)

    def to3d(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        return self.origin + q[..., :1] * self.e1 + q[..., 1:2] * self.e2

    def height(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, dtype=np.float64) - self.origin) @ self.normal


# -- convex polygons ---------------------------------------------------------------------------


def hull2d(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (K, 2) of 2D points."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        raise ValueError("a hull needs at least 3 points")
    hull = ConvexHull(pts)
    return pts[hull.vertices]  # scipy returns 2D hulls counter-clockwise


def offset_convex(poly: np.ndarray, r: float, n_arc: int = 24) -> np.ndarray:
    """Minkowski sum of a convex polygon with a disk of radius r (polygonal, circumscribed so the
    result contains the true offset)."""
    if r <= 0:
        return poly
    ang = np.linspace(0.0, 2 * np.pi, n_arc, endpoint=False)
    # Circumscribe the disk so every edge of the sampled offset lies outside the true offset.
    disk = (r / np.cos(np.pi / n_arc)) * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return hull2d((poly[:, None, :] + disk[None]).reshape(-1, 2))


def clip_convex(poly: np.ndarray, normal: np.ndarray, c: float) -> np.ndarray:
    """Keep the part of a convex polygon where normal . p <= c (Sutherland-Hodgman)."""
    n = np.asarray(normal, dtype=np.float64)
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        dp, dq = p @ n - c, q @ n - c
        if dp <= 0:
            out.append(p)
        if (dp < 0 < dq) or (dq < 0 < dp):
            t = dp / (dp - dq)
            out.append(p + t * (q - p))
    return np.asarray(out)


def scale_about(poly: np.ndarray, centre: np.ndarray, s: float) -> np.ndarray:
    return centre + s * (np.asarray(poly) - centre)


def perimeter(poly: np.ndarray, closed: bool = True) -> float:
    d = np.diff(np.vstack([poly, poly[:1]]) if closed else poly, axis=0)
    return float(np.linalg.norm(d, axis=1).sum())


def signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def arclength(poly: np.ndarray, closed: bool = True) -> np.ndarray:
    """Cumulative arc length at each vertex (and, for a closed polygon, the total appended)."""
    pts = np.vstack([poly, poly[:1]]) if closed else poly
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def point_at(poly: np.ndarray, s: np.ndarray, closed: bool = True) -> np.ndarray:
    """Points at arc lengths s along a polyline (wrapping for closed ones)."""
    pts = np.vstack([poly, poly[:1]]) if closed else np.asarray(poly)
    cum = arclength(poly, closed)
    s = np.asarray(s, dtype=np.float64)
    if closed:
        s = np.mod(s, cum[-1])
    s = np.clip(s, 0.0, cum[-1])
    seg = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(pts) - 2)
    t = (s - cum[seg]) / np.maximum(cum[seg + 1] - cum[seg], 1e-300)
    return pts[seg] + t[..., None] * (pts[seg + 1] - pts[seg])


def project_arclength(poly: np.ndarray, p: np.ndarray, closed: bool = True) -> float:
    """Arc length of the point of the polyline nearest to p."""
    pts = np.vstack([poly, poly[:1]]) if closed else np.asarray(poly)
    a, b = pts[:-1], pts[1:]
    ab = b - a
    t = np.clip(
        np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1
    )
    d = np.linalg.norm(a + t[:, None] * ab - p, axis=1)
    k = int(np.argmin(d))
    cum = arclength(poly, closed)
    return float(cum[k] + t[k] * (cum[k + 1] - cum[k]))


def sample_polyline(
    poly: np.ndarray, spacing: float, anchors: list[float] | None = None, closed: bool = True
) -> tuple[np.ndarray, list[int]]:
    """Points every ~`spacing` along a polyline that include the given anchor arc lengths (sorted
    ascending; for open polylines both ends are always included). Returns the points and the index
    of each anchor among them."""
    cum = arclength(poly, closed)
    total = cum[-1]
    if closed:
        marks = sorted(float(a) % total for a in (anchors or [0.0]))
        spans = [
            (marks[i], marks[(i + 1) % len(marks)] + (total if i == len(marks) - 1 else 0.0))
            for i in range(len(marks))
        ]
    else:
        marks = sorted({0.0, total, *[min(max(float(a), 0.0), total) for a in (anchors or [])]})
        spans = list(zip(marks[:-1], marks[1:], strict=True))
    s_all: list[float] = []
    anchor_index: list[int] = []
    for lo, hi in spans:
        anchor_index.append(len(s_all))
        n = max(1, int(round((hi - lo) / spacing)))
        s_all.extend(np.linspace(lo, hi, n + 1)[:-1].tolist())
    if not closed:
        anchor_index.append(len(s_all))
        s_all.append(total)
    return point_at(poly, np.asarray(s_all), closed), anchor_index


# -- the body as a point cloud -----------------------------------------------------------------


class BodyCloud:
    """The rest body's surface sampled every few millimetres, with part labels, for slicing."""

    def __init__(self, rest: RestBody, spacing: float = 0.005) -> None:
        import trimesh
        from scipy.spatial import cKDTree

        self.rest = rest
        sv, sf = trimesh.remesh.subdivide_to_size(rest.vertices, rest.faces, max_edge=spacing)
        self.points = np.asarray(sv)
        _, nearest = cKDTree(rest.vertices).query(self.points)
        self.labels = np.asarray(rest.part_labels)[nearest]
        self.part_names = rest.part_names

    def parts(self, *names: str) -> np.ndarray:
        ids = [self.part_names.index(n) for n in names]
        return np.isin(self.labels, ids)

    def slab(self, frame: PlaneFrame, half: float, mask: np.ndarray | None = None) -> np.ndarray:
        """2D coordinates of the body points within `half` of the plane."""
        pts = self.points if mask is None else self.points[mask]
        h = frame.height(pts)
        return frame.to2d(pts[np.abs(h) <= half])


def section(
    cloud: BodyCloud,
    frame: PlaneFrame,
    half: float,
    ease: float,
    mask: np.ndarray | None = None,
    keep: list[tuple[np.ndarray, float]] | None = None,
) -> np.ndarray | None:
    """Convex cross-section of the body around a plane, grown by `ease`, clipped by half-planes
    (normal, c) in `keep`. None when the slab holds too few points."""
    pts = cloud.slab(frame, half, mask)
    if len(pts) < 3:
        return None
    if keep:
        for normal, c in keep:
            pts = pts[pts @ normal <= c + ease]
        if len(pts) < 3:
            return None
    poly = offset_convex(hull2d(pts), ease)
    if keep:
        for normal, c in keep:
            poly = clip_convex(poly, normal, c)
    return poly


def union_hull(*polys: np.ndarray | None) -> np.ndarray:
    pts = np.vstack([p for p in polys if p is not None and len(p)])
    return hull2d(pts)
