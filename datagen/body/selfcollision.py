"""Body self-collision: detection, classification and repair (CLOTH3D thesis 3.3.1).

Intersecting body volumes make the cloth solver push in two directions at once, which corrupts
the whole garment, so the body is made intersection-free before it is simulated.

- Detection: per frame, triangle pairs that intersect, between parts that are not neighbours in
  the skeleton (datagen.body.parts) and that lie apart in the rest pose (folds within a few
  centimetres of a joint are skinning artefacts, not self-collisions). A broad phase keeps only
  the triangles inside the overlap of two parts' boxes; all frames are searched in one KD-tree
  per part pair, each frame shifted far apart along x.
- Classification: per frame and part pair, the intersection's extent and depth. Small ones between
  parts that meet at the armpits and the crotch are solvable; large ones, or ones between parts
  that should never meet (arm through torso, leg through leg), reject the sequence with the frame
  range and a reason. The parts the caller names are ignored (those dropped from the cloth
  collider, and those whose contacts are poses: hands, feet, head; BodyConfig.unrepaired_parts).
- Repair: the limb is pushed out of the torso (or the two thighs apart) along the contact normal,
  with a smooth falloff around the contact, until the gap is at least `gap` (4 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from datagen.body.parts import (
    MOVABLE_ORDER,
    PART_INDEX,
    PART_NAMES,
    SOLVABLE_PAIRS,
    part_neighbours,
)

LOCAL_RADIUS = 0.05  # metres: triangles this close in the rest pose may fold into each other
_FRAME_SHIFT = 100.0  # metres between frames in the batched KD-tree
_BOX_FRAMES = 16  # frames whose triangle corners are gathered at once for their boxes


@dataclass
class Contact:
    """The intersections between two parts in one frame."""

    frame: int
    part_a: int
    part_b: int
    tri_a: np.ndarray  # triangle indices of part a involved
    tri_b: np.ndarray
    n_pairs: int
    extent: float  # metres: diagonal of the box around the intersecting triangles
    depth: float  # metres: how far one part reaches behind the other's surface
    centre: np.ndarray  # (3,) middle of the intersecting triangles

    @property
    def pair_name(self) -> str:
        a, b = sorted((PART_NAMES[self.part_a], PART_NAMES[self.part_b]))
        return f"{a}/{b}"


class SelfCollisionDetector:
    """Finds body self-intersections in one subject's poses (its rest pose decides which triangles
    are local to each other)."""

    def __init__(
        self,
        faces: np.ndarray,
        part_labels: np.ndarray,
        rest_vertices: np.ndarray,
        ignore_parts: frozenset[str] = frozenset(),
        pairs: tuple[tuple[str, str], ...] | None = None,
        local_radius: float = LOCAL_RADIUS,
    ) -> None:
        """`pairs` (part names) replaces the default pairs, every two parts that are not skeleton
        neighbours; `local_radius` is how far apart at rest two triangles must be to count."""
        self.local_radius = local_radius
        self.faces = np.asarray(faces, dtype=np.int64)
        labels = np.asarray(part_labels)
        # A triangle belongs to the part most of its vertices belong to.
        fl = labels[self.faces]
        self.tri_part = np.where(fl[:, 1] == fl[:, 2], fl[:, 1], fl[:, 0]).astype(np.int64)
        self.rest_centroid = rest_vertices[self.faces].mean(axis=1)
        self.part_tris = [np.flatnonzero(self.tri_part == p) for p in range(len(PART_NAMES))]
        neighbours = part_neighbours()
        ignored = {PART_INDEX[p] for p in ignore_parts}
        if pairs is None:
            candidates = [
                (a, b)
                for a in range(len(PART_NAMES))
                for b in range(a + 1, len(PART_NAMES))
                if not neighbours[a, b]
            ]
        else:
            candidates = [tuple(sorted((PART_INDEX[a], PART_INDEX[b]))) for a, b in pairs]
        self.pairs = [
            (a, b)
            for a, b in candidates
            if a not in ignored
            and b not in ignored
            and len(self.part_tris[a])
            and len(self.part_tris[b])
        ]

    def detect(self, vertices: np.ndarray, frames: np.ndarray | None = None) -> list[Contact]:
        """Contacts in posed vertices (F, V, 3); `frames` labels them (default 0..F-1)."""
        vertices = np.asarray(vertices)
        frame_ids = np.arange(vertices.shape[0]) if frames is None else np.asarray(frames)
        contacts: list[Contact] = []
        for (a, b), (fa, ia, fb, ib) in self._broad_phase(vertices).items():
            pairs, corners_a, corners_b = self._candidate_pairs(vertices, fa, ia, fb, ib)
            if len(pairs) == 0:
                continue
            pf, pa, pb = pairs.T
            hit = triangles_intersect(corners_a, corners_b)
            if not hit.any():
                continue
            pf, pa, pb = pf[hit], pa[hit], pb[hit]
            for f in np.unique(pf):
                m = pf == f
                tri_f = vertices[f][self.faces].astype(np.float64)
                contacts.append(self._contact(tri_f, int(frame_ids[f]), a, b, pa[m], pb[m]))
        contacts.sort(key=lambda c: (c.frame, c.part_a, c.part_b))
        return contacts

    def _broad_phase(self, vertices: np.ndarray) -> dict[tuple[int, int], tuple[np.ndarray, ...]]:
        """Per part pair, the (frame, triangle) rows of each part whose box touches the overlap
        of the two parts' boxes in that frame: (frames a, triangles a, frames b, triangles b),
        by frame. A few frames at a time, into buffers reused from chunk to chunk: the whole
        sequence's triangle boxes at once (and before that its corners in float64, 0.6 GB for
        300 frames of the 27k-triangle body) spent most of the body stage's time on the first
        touch of freshly allocated pages, three calls a sequence."""
        n_tris = len(self.faces)
        corner = [np.empty((_BOX_FRAMES, n_tris, 3), vertices.dtype) for _ in range(3)]
        tmin = np.empty((_BOX_FRAMES, n_tris, 3), vertices.dtype)
        tmax = np.empty((_BOX_FRAMES, n_tris, 3), vertices.dtype)
        rows: dict[tuple[int, int], list[tuple[np.ndarray, ...]]] = {}
        for f0 in range(0, vertices.shape[0], _BOX_FRAMES):
            chunk = vertices[f0:f0 + _BOX_FRAMES]
            n = len(chunk)
            a_, b_, c_ = (np.take(chunk, self.faces[:, k], axis=1, out=corner[k][:n])
                          for k in range(3))
            # Corner by corner, elementwise: a reduction over the corner axis (length 3) runs
            # numpy's inner loop three elements at a time, ten times slower.
            lo_t = np.minimum(np.minimum(a_, b_, out=tmin[:n]), c_, out=tmin[:n])
            hi_t = np.maximum(np.maximum(a_, b_, out=tmax[:n]), c_, out=tmax[:n])
            # Per-part boxes per frame, once (the pair loop below only compares them).
            pmin = np.stack([lo_t[:, t].min(axis=1) if len(t) else np.full((n, 3), np.inf)
                             for t in self.part_tris], axis=1)
            pmax = np.stack([hi_t[:, t].max(axis=1) if len(t) else np.full((n, 3), -np.inf)
                             for t in self.part_tris], axis=1)
            for a, b in self.pairs:
                ta, tb = self.part_tris[a], self.part_tris[b]
                lo = np.maximum(pmin[:, a], pmin[:, b])
                hi = np.minimum(pmax[:, a], pmax[:, b])
                fr = np.flatnonzero(np.all(lo <= hi, axis=1))
                if len(fr) == 0:
                    continue
                # Triangles of each part whose box touches the overlap box, per frame
                # (indexing the part's triangles first: copying all triangles per pair would
                # dominate the cost).
                fi = fr[:, None]
                lo_f, hi_f = lo[fr, None], hi[fr, None]
                sel_a = np.all((hi_t[fi, ta[None]] >= lo_f) & (lo_t[fi, ta[None]] <= hi_f),
                               axis=2)
                sel_b = np.all((hi_t[fi, tb[None]] >= lo_f) & (lo_t[fi, tb[None]] <= hi_f),
                               axis=2)
                fa, ia = np.nonzero(sel_a)
                fb, ib = np.nonzero(sel_b)
                if len(fa) and len(fb):
                    rows.setdefault((a, b), []).append(
                        (f0 + fr[fa], ta[ia], f0 + fr[fb], tb[ib]))
        return {pair: tuple(np.concatenate(col) for col in zip(*found, strict=True))
                for pair, found in rows.items()}

    def _corners(self, vertices: np.ndarray, f: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) float64 corners of triangles t in frames f: only the candidates' are
        converted (the tests below are in float64)."""
        return vertices[f[:, None], self.faces[t]].astype(np.float64)

    def _candidate_pairs(self, vertices, fa, ia, fb, ib) -> tuple[np.ndarray, ...]:
        """(N, 3) rows (frame, tri_a, tri_b) whose bounding spheres overlap and that were apart
        in the rest pose, with the two triangles' (N, 3, 3) float64 corners (gathered here for
        every candidate, so the exact test reuses them)."""
        tri_a = self._corners(vertices, fa, ia)
        tri_b = self._corners(vertices, fb, ib)
        ca = tri_a.mean(axis=1)
        cb = tri_b.mean(axis=1)
        ra = np.linalg.norm(tri_a - ca[:, None], axis=2).max(axis=1)
        rb = np.linalg.norm(tri_b - cb[:, None], axis=2).max(axis=1)
        shift_a = ca.copy()
        shift_a[:, 0] += fa * _FRAME_SHIFT
        shift_b = cb.copy()
        shift_b[:, 0] += fb * _FRAME_SHIFT
        radius = float(ra.max() + rb.max())
        # Every pair within `radius`, as arrays (a ball query per point returns Python lists,
        # most of this function's time), in the order of a's rows, then b's.
        near = cKDTree(shift_a).sparse_distance_matrix(cKDTree(shift_b), radius,
                                                       output_type="ndarray")
        # The tree's own distance (between the frame-shifted centres, off by rounding at a few
        # 1e-12 m) drops the pairs beyond their own two radii before anything is gathered for
        # them (19 in 20 of a clip's pairs); the exact test below decides the rest.
        rows = near["i"].astype(np.int64)
        cols = near["j"].astype(np.int64)
        within = near["v"] <= ra[rows] + rb[cols] + 1e-9
        order = np.lexsort((cols[within], rows[within]))
        rows, cols = rows[within][order], cols[within][order]
        close = np.linalg.norm(ca[rows] - cb[cols], axis=1) <= ra[rows] + rb[cols]
        rows, cols = rows[close], cols[close]
        far_at_rest = (
            np.linalg.norm(self.rest_centroid[ia[rows]] - self.rest_centroid[ib[cols]], axis=1)
            > self.local_radius
        )
        rows, cols = rows[far_at_rest], cols[far_at_rest]
        return np.stack([fa[rows], ia[rows], ib[cols]], axis=1), tri_a[rows], tri_b[cols]

    def _contact(self, tri_f, frame, a, b, pa, pb) -> Contact:
        pts = np.concatenate([tri_f[pa].reshape(-1, 3), tri_f[pb].reshape(-1, 3)])
        extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        centre = pts.mean(axis=0)
        depth = self._depth(tri_f, a, b, centre, 0.5 * extent + 0.03)
        return Contact(frame, a, b, np.unique(pa), np.unique(pb), len(pa), extent, depth, centre)

    def _depth(self, tri_f, a: int, b: int, centre: np.ndarray, radius: float) -> float:
        """How far the vertices of either part near the contact reach behind the other part's
        local surface, the larger of the two. Each point is measured against the tangent plane
        of its nearest vertex of the other part (a cheap stand-in for the signed distance that
        is exact on flat patches and close on the body's gently curved ones)."""
        depth = 0.0
        near = {}
        for p in (a, b):
            t = self.part_tris[p]
            near[p] = t[np.linalg.norm(tri_f[t].mean(axis=1) - centre, axis=1) < radius]
        for src, dst in ((a, b), (b, a)):
            src_tris, dst_tris = near[src], near[dst]
            if len(src_tris) == 0 or len(dst_tris) == 0:
                continue
            pts = tri_f[src_tris].reshape(-1, 3)
            dtri = tri_f[dst_tris]
            fn = np.cross(dtri[:, 1] - dtri[:, 0], dtri[:, 2] - dtri[:, 0])
            anchor = dtri.mean(axis=1)
            normals = fn / (np.linalg.norm(fn, axis=1, keepdims=True) + 1e-20)
            _, idx = cKDTree(anchor).query(pts)
            sd = np.einsum("ij,ij->i", pts - anchor[idx], normals[idx])
            depth = max(depth, float(np.max(-sd, initial=0.0)))
        return depth


def triangles_intersect(t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """(N,) bool: whether triangle pairs (N, 3, 3) x (N, 3, 3) intersect (non-coplanar case).

    Two triangles intersect iff an edge of one crosses the other triangle.
    """
    hit = np.zeros(len(t1), dtype=bool)
    for a, b in ((t1, t2), (t2, t1)):
        for i in range(3):
            p = a[:, i]
            q = a[:, (i + 1) % 3]
            hit |= _segment_hits_triangle(p, q, b)
    return hit


def _segment_hits_triangle(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Moller-Trumbore with the ray parameter restricted to the segment [p, q]."""
    d = q - p
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - tri[:, 0]
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


# -- classification ----------------------------------------------------------------------------
@dataclass
class Verdict:
    solvable: list[Contact]
    fatal: list[Contact]

    def reason(self) -> tuple[str, tuple[int, int]]:
        """A one-line reason (the deepest fatal intersection) and the frames of that pair."""
        worst = max(self.fatal, key=lambda c: (c.depth, c.extent))
        same = [c for c in self.fatal if c.pair_name == worst.pair_name]
        frames = (min(c.frame for c in same), max(c.frame for c in same))
        pair = frozenset(worst.pair_name.split("/"))
        kind = "incompatible parts" if pair not in SOLVABLE_PAIRS else "too large"
        return (
            f"body self-intersection {worst.pair_name} ({kind}: extent "
            f"{worst.extent * 100:.1f} cm, depth {worst.depth * 100:.1f} cm)",
            frames,
        )


def classify(contacts: list[Contact], max_extent: float, max_depth: float) -> Verdict:
    solvable, fatal = [], []
    for c in contacts:
        pair = frozenset({PART_NAMES[c.part_a], PART_NAMES[c.part_b]})
        if pair in SOLVABLE_PAIRS and c.extent <= max_extent and c.depth <= max_depth:
            solvable.append(c)
        else:
            fatal.append(c)
    return Verdict(solvable, fatal)


# -- repair ------------------------------------------------------------------------------------
def _signed_distance(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of points to the closest of `tris` (outward = triangle normal side) and
    the normal of that triangle. Brute force over a local patch (a few hundred triangles)."""
    from trimesh.triangles import closest_point

    n_p, n_t = len(points), len(tris)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-20
    best = np.full(n_p, np.inf)
    best_sd = np.zeros(n_p)
    best_n = np.zeros((n_p, 3))
    chunk = max(1, 200_000 // max(n_t, 1))
    for s in range(0, n_p, chunk):
        pts = points[s : s + chunk]
        rep_pts = np.repeat(pts, n_t, axis=0)
        rep_tris = np.tile(tris, (len(pts), 1, 1))
        cp = closest_point(rep_tris, rep_pts).reshape(len(pts), n_t, 3)
        diff = pts[:, None] - cp
        dist = np.linalg.norm(diff, axis=2)
        k = dist.argmin(axis=1)
        rows = np.arange(len(pts))
        sign = np.sign(np.einsum("pk,pk->p", diff[rows, k], normals[k]))
        sign[sign == 0] = 1.0
        best[s : s + chunk] = dist[rows, k]
        best_sd[s : s + chunk] = sign * dist[rows, k]
        best_n[s : s + chunk] = normals[k]
    return best_sd, best_n


def repair_contact(
    vertices: np.ndarray,
    faces: np.ndarray,
    part_labels: np.ndarray,
    contact: Contact,
    gap: float,
    rest_vertices: np.ndarray,
    adjacency_radius: float = 0.04,
) -> dict[int, np.ndarray]:
    """Offsets {vertex: (3,)} that separate the two parts of `contact` by at least `gap`.

    The part that yields (datagen.body.parts.MOVABLE_ORDER: forearm before upper arm before
    thigh; both thighs share the push for a crotch contact) moves along the contact normal with
    a smooth falloff around the contact, so the surface stays smooth. Only vertices that lie
    apart from the other part in the rest pose are held to the gap (the skin where the parts
    join is the same surface). `vertices` is one frame (V, 3) and is not modified.
    """
    from scipy.spatial import cKDTree

    name_a, name_b = PART_NAMES[contact.part_a], PART_NAMES[contact.part_b]
    rank = {name: i for i, name in enumerate(MOVABLE_ORDER)}
    tri_a, tri_b = contact.tri_a, contact.tri_b
    if rank.get(name_b, 99) < rank.get(name_a, 99):
        name_a, name_b = name_b, name_a
        tri_a, tri_b = tri_b, tri_a
    # Thighs against each other share the push; otherwise only the higher-ranked part moves.
    both = {name_a, name_b} == {"thigh_l", "thigh_r"}
    pa, pb = PART_INDEX[name_a], PART_INDEX[name_b]
    labels = np.asarray(part_labels)

    v = vertices.astype(np.float64)
    tris = v[faces]
    center = np.concatenate([tris[tri_a].reshape(-1, 3), tris[tri_b].reshape(-1, 3)]).mean(axis=0)
    core = 0.5 * contact.extent
    radius = core + adjacency_radius
    cent = tris.mean(axis=1)
    near = np.linalg.norm(cent - center, axis=1) < radius + 0.03
    tri_part = labels[faces[:, 0]]
    patch_b = np.flatnonzero(near & (tri_part == pb))
    patch_a = np.flatnonzero(near & (tri_part == pa))
    if len(patch_b) == 0 or len(patch_a) == 0:
        return {}
    normal = np.cross(tris[tri_b, 1] - tris[tri_b, 0], tris[tri_b, 2] - tris[tri_b, 0]).sum(axis=0)
    n = normal / (np.linalg.norm(normal) + 1e-20)
    verts_a = np.unique(faces[patch_a])
    verts_a = verts_a[labels[verts_a] == pa]
    verts_b = np.unique(faces[patch_b])
    verts_b = verts_b[labels[verts_b] == pb]
    # Held to the gap: vertices of each part away from the other part in the rest pose.
    held_a = cKDTree(rest_vertices[verts_b]).query(rest_vertices[verts_a])[0] > LOCAL_RADIUS
    held_b = cKDTree(rest_vertices[verts_a]).query(rest_vertices[verts_b])[0] > LOCAL_RADIUS

    def falloff(points):
        d = np.linalg.norm(points - center, axis=1)
        s = np.clip((radius - d) / max(radius - core, 1e-6), 0.0, 1.0)
        return s * s * (3 - 2 * s)

    wa = falloff(v[verts_a])
    wb = falloff(v[verts_b])
    limit = contact.depth + gap + 0.02  # never push further than the intersection could need
    push = 0.0
    offsets_a = np.zeros((len(verts_a), 3))
    offsets_b = np.zeros((len(verts_b), 3))
    for _ in range(8):
        moved = v.copy()
        moved[verts_a] += offsets_a
        moved[verts_b] += offsets_b
        sd, _ = _signed_distance(moved[verts_a], moved[faces[patch_b]])
        # Only vertices inside the contact region (where the push is at least half) must meet
        # the gap; the falloff zone follows smoothly.
        short = np.where(held_a & (wa >= 0.5), gap - sd, 0.0)
        if both:
            sd_b, _ = _signed_distance(moved[verts_b], moved[faces[patch_a]])
            short_b = np.where(held_b & (wb >= 0.5), gap - sd_b, 0.0)
        else:
            short_b = np.zeros(len(verts_b))
        worst = max(
            float(np.max(short / np.maximum(wa, 0.5), initial=0.0)),
            float(np.max(short_b / np.maximum(wb, 0.5), initial=0.0)),
        )
        if worst <= 1e-5 or push >= limit:
            break
        push = min(push + worst, limit)
        if both:
            offsets_a = (0.5 * push * wa)[:, None] * n
            offsets_b = (-0.5 * push * wb)[:, None] * n
        else:
            offsets_a = (push * wa)[:, None] * n
    out: dict[int, np.ndarray] = {}
    for i, off in zip(verts_a, offsets_a, strict=True):
        if np.any(off != 0):
            out[int(i)] = off
    if both:
        for i, off in zip(verts_b, offsets_b, strict=True):
            if np.any(off != 0):
                out[int(i)] = out.get(int(i), 0) + off
    return out
