"""Contact at strongly flexed joints: where linear blend skinning sinks one part into its
neighbour across a joint (the thigh into the belly at a kick's chamber or a squat, the calf into
the hamstring at a deep knee bend), both surfaces are moved to meet at a shared contact surface
with a small gap between them, in the spirit of implicit skinning's contact operator (Vaillant
et al. 2013).

The self-collision repair (selfcollision.py) cannot do this: it pushes one limb out of another
along one normal, which works for an arm against the torso but not for two parts joined at a
joint, whose overlap is the skin of the joint folding into itself. Projecting one part onto the
other collapses it (a vertical belly patch onto the horizontal top of a raised thigh becomes a
line); here each surface goes half way, onto the bisector of the two, so a patch is compressed
by at most the cosine of half the angle between them.

For each vertex of one side that lies inside the other side (the body's generalised winding
number at a point just outside the vertex, and the sign of its distance to the other side's
nearest triangle), or within `gap` of it where the two were apart at rest, with signed distance
`d` to the other side and unit normals `n_own` (its vertex normal) and `n_other` (the other
side's at the nearest point), one linearised step towards the level set where the two signed
distance fields differ by `gap`:

    offset = (gap - d) * g / max(|g|^2, 1/2),   g = n_other - n_own

moves it half of `gap - d` along each normal when the surfaces face each other and onto the
bisector when they meet at an angle. The corrections are spread over each part's neighbouring
vertices (a few Jacobi sweeps of the mesh's umbrella operator, within the part, the corrected
vertices held) so the surface stays smooth, and the step is repeated until nothing is inside.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from datagen.body.parts import FLEXION_REST_RADIUS, FLEXION_SIDES, PART_INDEX
from datagen.types import RestBody

_PROBE_OUT = 1e-3  # metres: the winding number is read this far outside each vertex
_MAX_DEPTH = 0.15  # metres: deeper than this is another part's far side, not an overlap
_ITERATIONS = 6
_SMOOTHING_SWEEPS = 4
_CONVERGED = 2e-3  # metres: the largest correction that ends the iteration (half the
# thinnest fabric's thickness, a fifth of the default gap)


class FlexionSeparator:
    """Built once per body topology and rest shape; `separate` works on posed frames."""

    def __init__(self, rest: RestBody, gap: float) -> None:
        self.gap = float(gap)
        self.faces = np.asarray(rest.faces, dtype=np.int64)
        labels = np.asarray(rest.part_labels)
        fl = labels[self.faces]
        # A triangle belongs to the part most of its vertices belong to (as in selfcollision).
        self.tri_part = np.where(fl[:, 1] == fl[:, 2], fl[:, 1], fl[:, 0])
        self.rest_vertices = np.asarray(rest.vertices, dtype=np.float64)
        self.rest_centroids = self.rest_vertices[self.faces].mean(axis=1)
        n_vertices = len(labels)
        # One group per side that takes part: its vertices, every triangle not its own (the
        # nearest of which must belong to a partner for the vertex to be corrected), and per
        # joint it folds at (FLEXION_SIDES' index) the partner side's parts.
        partners: dict[tuple[int, ...], dict[int, tuple[int, ...]]] = {}
        for joint, (side_a, side_b) in enumerate(FLEXION_SIDES):
            a = tuple(PART_INDEX[p] for p in side_a)
            b = tuple(PART_INDEX[p] for p in side_b)
            partners.setdefault(a, {})[joint] = b
            partners.setdefault(b, {})[joint] = a
        self.groups = [
            (np.flatnonzero(np.isin(labels, own)),
             np.flatnonzero(~np.isin(self.tri_part, own)),
             by_joint)
            for own, by_joint in partners.items()
        ]
        # Each group's partner vertices per joint, whose posed box bounds the candidates.
        self.partner_vertices = [{j: np.flatnonzero(np.isin(labels, other))
                                  for j, other in by_joint.items()}
                                 for _, _, by_joint in self.groups]
        # Vertex normals as one sparse product: vertex-by-triangle incidence.
        rows = self.faces.ravel()
        cols = np.repeat(np.arange(len(self.faces)), 3)
        self.incidence = sp.csr_matrix(
            (np.ones(len(rows)), (rows, cols)), shape=(n_vertices, len(self.faces)))
        # Smoothing stays within one side: an edge between two sides (the skin across the
        # joint) would average the two opposite pushes away.
        side_of = np.full(n_vertices, -1)
        for k, (own, _, _) in enumerate(self.groups):
            side_of[own] = k
        edges = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]],
                                self.faces[:, [2, 0]]])
        edges = edges[(side_of[edges[:, 0]] == side_of[edges[:, 1]]) & (side_of[edges[:, 0]] >= 0)]
        adjacency = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                  shape=(n_vertices, n_vertices)).tocsr()
        adjacency = ((adjacency + adjacency.T) > 0).astype(np.float64)
        degree = np.asarray(adjacency.sum(axis=1)).ravel()
        self.umbrella = sp.diags(1.0 / np.maximum(degree, 1.0)) @ adjacency

    def vertex_normals(self, v: np.ndarray) -> np.ndarray:
        f = self.faces
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        vn = self.incidence @ fn
        return vn / (np.linalg.norm(vn, axis=1, keepdims=True) + 1e-20)

    def corrections(self, v: np.ndarray, joints: frozenset[int]) -> np.ndarray:
        """(V, 3) one linearised step for every vertex inside, or within the gap of, its
        partner side across one of `joints` (FLEXION_SIDES' indices); zero elsewhere."""
        import igl

        gap = self.gap
        vn = self.vertex_normals(v)
        c = np.zeros_like(v)
        # Only vertices inside their partners' box (grown by the gap) can need a correction.
        candidates, active = [], []
        for (own, _, by_joint), partner_vertices in zip(self.groups, self.partner_vertices,
                                                       strict=True):
            folding = [j for j in by_joint if j in joints]
            active.append(np.array(sorted({p for j in folding for p in by_joint[j]})))
            if not folding:
                candidates.append(own[:0])
                continue
            pv = v[np.concatenate([partner_vertices[j] for j in folding])]
            lo, hi = pv.min(axis=0) - gap, pv.max(axis=0) + gap
            candidates.append(own[np.all((v[own] >= lo) & (v[own] <= hi), axis=1)])
        reach = _MAX_DEPTH + gap
        centroids = v[self.faces].mean(axis=1)
        measured = []  # per group: its candidates, their distances, nearest triangles and the
        # normals there, which of those triangles are a partner's, and which candidates lie
        # behind a partner's surface (to be confirmed by the winding number)
        for (_, foreign, _), partners, sel in zip(self.groups, active, candidates, strict=True):
            if len(sel) == 0:
                continue
            p = v[sel]
            near_box = np.all((centroids[foreign] >= p.min(axis=0) - reach)
                              & (centroids[foreign] <= p.max(axis=0) + reach), axis=1)
            tris = foreign[near_box]
            if len(tris) == 0:
                continue
            sd, idx, _, normal = igl.signed_distance(
                p, v, self.faces[tris], sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
            hit = tris[idx]
            to_partner = np.isin(self.tri_part[hit], partners)
            behind = to_partner & (sd < 0) & (sd > -_MAX_DEPTH)
            measured.append((sel, sd, hit, normal, to_partner, behind))
        # The winding number decides only what the distance puts behind a partner's surface: it
        # is read at those vertices alone, and not at all where there are none. Each point's
        # value is the same whichever others are asked (the tree is the mesh's), and building
        # that tree is most of the call's time.
        winding = np.zeros(len(v))
        asked = [sel[behind] for sel, _, _, _, _, behind in measured]
        queried = np.unique(np.concatenate(asked)) if asked else np.zeros(0, np.int64)
        if len(queried):
            winding[queried] = igl.fast_winding_number(
                v, self.faces, v[queried] + _PROBE_OUT * vn[queried])
        for sel, sd, hit, normal, to_partner, behind in measured:
            inside = behind & (winding[sel] > 0.5)
            # Within the gap counts only where the two were apart at rest: next to the joint
            # they are one skin.
            apart = np.linalg.norm(self.rest_vertices[sel] - self.rest_centroids[hit],
                                   axis=1) > FLEXION_REST_RADIUS
            close = to_partner & (sd >= 0) & (sd < gap) & apart
            move = inside | close
            g = normal[move] - vn[sel[move]]
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 0.5)
            c[sel[move]] += ((gap - sd[move]) / g2)[:, None] * g
        return c

    def separate(self, frame_vertices: np.ndarray, joints: frozenset[int]) -> np.ndarray:
        """(V, 3) offsets that separate the parts flexed at `joints` (FLEXION_SIDES' indices)
        in one posed frame."""
        v0 = np.asarray(frame_vertices, dtype=np.float64)
        offsets = np.zeros_like(v0)
        for _ in range(_ITERATIONS):
            c = self.corrections(v0 + offsets, joints)
            held = np.any(c != 0.0, axis=1)
            if not held.any():
                break
            spread = c.copy()
            for _ in range(_SMOOTHING_SWEEPS):
                spread = 0.5 * spread + 0.5 * (self.umbrella @ spread)
                spread[held] = c[held]
            offsets += spread
            if np.abs(c).max() < _CONVERGED:
                break
        return offsets


def separate_flexed_parts(
    vertices: np.ndarray, rest: RestBody, frames: dict[int, frozenset[int]], gap: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sparse offsets (frames, vertices, offsets) for the given frames of `vertices` (F, V, 3),
    each with the joints to separate in it (FLEXION_SIDES' indices); `vertices` is modified in
    place."""
    separator = FlexionSeparator(rest, gap)
    rep_f, rep_v, rep_o = [], [], []
    for f in sorted(frames):
        off = separator.separate(vertices[f], frames[f])
        moved = np.flatnonzero(np.any(off != 0.0, axis=1))
        vertices[f, moved] += off[moved].astype(vertices.dtype)
        rep_f.append(np.full(len(moved), f, dtype=np.int32))
        rep_v.append(moved.astype(np.int32))
        rep_o.append(off[moved].astype(np.float32))
    if not rep_f:
        return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
    return np.concatenate(rep_f), np.concatenate(rep_v), np.concatenate(rep_o)
