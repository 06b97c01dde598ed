"""The static cloth model: particles, masses, springs by type, bending stencils, pins, elastics.

Built once per scene from the outfit's garments (numpy); the solvers only read it.

Resolution independence (docs/fabrics.md):
- vertex mass = density * (one third of the adjacent rest triangle areas);
- spring stiffness k_e = Y * A_e / L_e^2, with A_e one third of the adjacent triangle areas and
  Y the fabric's stretch (warp/weft edges) or shear (diagonal edges) stiffness in N/m, so a
  sheet's membrane stiffness does not depend on how finely it is meshed;
- bending: a quadratic isometric model (after Bergou et al. 2006) on each interior edge,
  E = 1/2 * B / (A0 + A1) * |sum_k K_k x_k|^2, whose stencil weights K come from the flat rest
  geometry of the two triangles (|sum K x| = theta |e| for a small fold theta); B is the bending
  rigidity in N m, and the energy of a sheet rolled to radius R tends to B * area / (2 R^2) at
  any resolution and triangulation (tests/test_sim_model.py checks it).

Degenerate elements (zero-length edges, needle or zero-area triangles, duplicated vertices in a
user's template) must not make the system infinitely stiff or a vertex massless: stiffness and
mass use floors relative to the garment's median edge (`DEGENERATE_FRACTION`), hinges whose
triangles are needles carry no bending, and the QA measures strain against the floored length.
The data is not changed; the model counts what it floored (`ClothModel.degenerate`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from datagen.errors import InputError
from datagen.sim.fabrics import Fabric
from datagen.types import Garment

STRUCTURAL, SHEAR, SEAM = 0, 1, 2
SEAM_STIFFNESS = 20.0  # sewing springs (zero rest length) are this many times the fabric's
ELASTIC_LENGTH = 0.85  # elastic bands gather the fabric: 15 % shorter rest length
ELASTIC_STIFFNESS = 5.0  # and stiffer than the fabric
# Floors for degenerate elements, as a fraction of the garment's median edge length: an edge
# shorter than this is as stiff as one of this length, a triangle smaller than its square (times
# the equilateral factor) weighs as much as one that size, and a hinge whose wing sits closer
# than this fraction of the hinge length to it (a needle) carries no bending.
DEGENERATE_FRACTION = 0.2
# Woven and knitted fabrics stiffen sharply once their yarns straighten; the linear springs of
# Blender's presets do not. Every solver therefore holds a fabric spring inextensible past
# this fraction of its fabric's max_strain (strain limiting, as in Provot 1995), below the QA
# bound so that the bound measures how well the limit held.
STRAIN_LIMIT_FRACTION = 0.9
NO_LIMIT = 1e6  # m: the limit length of springs that have none
# The pressure drag effect (kernels.air_velocity): air at rest pushes on a panel moving along
# its normal with 1/2 rho C_d |v_n| v_n per square metre of its current area. rho = 1.2 kg/m^3
# (air at 20 C, sea level); C_d = 1.2, a thin flat plate broadside to the flow (about 1.17 for
# a disc or a square, up to 2 for a long strip: the low end, as a garment's panels are curved
# and their edges leak). Blender's air damping, the linear `air_drag`, stands in for it in
# CLOTH3D and is 5x weaker at 1 m/s (docs/fabrics.md).
AIR_DENSITY = 1.2  # kg/m^3
PLATE_DRAG_COEFFICIENT = 1.2
PRESSURE_DRAG = 0.5 * AIR_DENSITY * PLATE_DRAG_COEFFICIENT  # kg/m^3
# How pressure drag treats a panel's two faces (the solvers' `use_pressure`, a compile-time
# switch of the kernels). Cloth worn on a body winds its faces outward (templates are checked
# for it, garment.template.check_template; scenes.py's sheets and tubes face away from their
# colliders), and its inner face looks onto the body, the air trapped against it and, downwind,
# the body's wake, which all move with the body: the free stream's quadratic drag meets only
# its outer face. So with body collision on, a panel takes pressure drag only while it moves
# outward relative to the air (v_n > 0, pushed back towards the body); free cloth takes it on
# both faces. Without the shelter a runner's strap top was pulled off its back by its own
# wake (docs/simulator.md, "Open shirts on the move").
PRESSURE_OFF, PRESSURE_BOTH_FACES, PRESSURE_OUTER_FACE = 0, 1, 2


@dataclass
class ClothModel:
    """Concatenated arrays of every garment of a scene."""

    x0: np.ndarray  # (V, 3) float64 initial positions
    rest_x: np.ndarray  # (V, 3) float64 rest shape (what "near in the fabric" is measured on)
    faces: np.ndarray  # (T, 3) int32
    mass: np.ndarray  # (V,) kg
    garment_of_vertex: np.ndarray  # (V,) int32
    garment_names: list[str]
    garment_ranges: list[tuple[int, int]]  # vertex range of each garment
    face_ranges: list[tuple[int, int]]
    springs: np.ndarray  # (E, 2) int32
    rest_length: np.ndarray  # (E,)
    k_tension: np.ndarray  # (E,) N/m
    k_compression: np.ndarray  # (E,)
    spring_beta: np.ndarray  # (E,) s, Rayleigh damping factor
    spring_kind: np.ndarray  # (E,) STRUCTURAL or SHEAR
    spring_elastic: np.ndarray  # (E,) bool
    bends: np.ndarray  # (B, 4) int32: hinge v0, v1, wings v2, v3
    bend_weights: np.ndarray  # (B, 4) K
    bend_stiffness: np.ndarray  # (B,) B_rigidity / (A0 + A1)
    bend_beta: np.ndarray  # (B,) s
    air_drag: np.ndarray  # (V,) kg/s: d * vertex area
    friction: np.ndarray  # (V,)
    thickness: np.ndarray  # (V,) m
    max_strain: np.ndarray  # (E,)
    pinned: np.ndarray  # (P,) vertex ids attached to the body
    fabrics: list[Fabric]
    layers: list[int] = None  # layer of each garment (0 = innermost)
    strain_length: np.ndarray = None  # (E,) the length strain is measured against (floored)
    degenerate: dict = None  # counts of floored elements: short edges, small triangles, needles

    @property
    def n_vertices(self) -> int:
        return len(self.x0)

    @functools.cached_property
    def fabric_springs(self) -> np.ndarray:
        """(E,) bool: the stretch and shear springs whose strain the QA measures (seams and
        elastic bands, meant to be stretched, excluded)."""
        return np.isin(self.spring_kind, (STRUCTURAL, SHEAR)) & ~self.spring_elastic

    @functools.cached_property
    def fabric_strain_terms(self) -> tuple[np.ndarray, ...]:
        """The fabric springs' (fabric_springs) first and second vertices, rest lengths, the
        lengths their strain is measured against, and their fabrics' max_strain: gathered once
        for the QA's strain, which reads them every frame."""
        select = self.fabric_springs
        e = self.springs[select]
        return (np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1]),
                self.rest_length[select], self.strain_length[select], self.max_strain[select])

    @functools.cached_property
    def limit_length(self) -> np.ndarray:
        """(E,) m: the length past which a fabric spring is held inextensible by the xpbd
        solver (STRAIN_LIMIT_FRACTION of its max_strain); seams and elastic bands have no limit."""
        limit = self.rest_length + STRAIN_LIMIT_FRACTION * self.max_strain * self.strain_length
        return np.where(self.fabric_springs, limit, NO_LIMIT)

    @functools.cached_property
    def tethers(self) -> tuple[np.ndarray, np.ndarray]:
        """Long-range attachments (Kim, Chentanez and Mueller 2012): per vertex reachable from a
        pinned one through strain-limited fabric springs, (K, 2) int32 (vertex, its nearest pin)
        and (K,) the largest distance between them that the strain limit allows: the shortest
        path of limit lengths. The bound follows from the limit (no chain of springs can reach
        farther), so holding it changes no model; it lets the xpbd solver stop a garment that
        hangs from its waistband in one projection, where Gauss-Seidel sweeps carry a jerk down
        a skirt one spring at a time and the skirt stretches past its bound meanwhile."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        empty = (np.zeros((0, 2), np.int32), np.zeros(0))
        if not len(self.pinned):
            return empty
        limited = self.limit_length < NO_LIMIT
        sp = self.springs[limited]
        n = self.n_vertices
        graph = coo_matrix((self.limit_length[limited], (sp[:, 0], sp[:, 1])), shape=(n, n))
        dist, _, source = dijkstra(graph.tocsr(), directed=False, indices=self.pinned,
                                   min_only=True, return_predecessors=True)
        pinned = np.zeros(n, dtype=bool)
        pinned[self.pinned] = True
        keep = np.flatnonzero(np.isfinite(dist) & ~pinned)
        if not len(keep):
            return empty
        pairs = np.stack([keep, source[keep]], axis=1).astype(np.int32)
        return pairs, dist[keep]

    @property
    def inv_mass(self) -> np.ndarray:
        w = 1.0 / self.mass
        w[self.pinned] = 0.0
        return w


def edges_of(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) and, per edge, its two adjacent faces (-1 if boundary)."""
    f = np.asarray(faces, dtype=np.int64)
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(len(f)), 3)
    key = np.sort(half, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, face_of = key[order], face_of[order]
    new = np.ones(len(key), dtype=bool)
    new[1:] = np.any(key[1:] != key[:-1], axis=1)
    edge_id = np.cumsum(new) - 1
    edges = key[new]
    adj = -np.ones((len(edges), 2), dtype=np.int64)
    first = np.flatnonzero(new)
    adj[:, 0] = face_of[first]
    second = np.flatnonzero(~new)
    adj[edge_id[second], 1] = face_of[second]
    return edges, adj


def triangle_areas(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = x[faces]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def bending_stencils(rest: np.ndarray, faces: np.ndarray, edges: np.ndarray, adj: np.ndarray):
    """Stencils (B, 4) and weights K (B, 4) of the interior edges, from the flat rest geometry.

    K is the affine dependency of the hinge and wing points unfolded into a plane, scaled so that
    |sum K x| equals theta * |e| for a small fold of angle theta about the hinge.
    """
    interior = adj[:, 1] >= 0
    e = edges[interior]
    f0 = faces[adj[interior, 0]]
    f1 = faces[adj[interior, 1]]
    # The wing vertex of each face: the one not on the hinge.
    w0 = f0[(f0 != e[:, :1]) & (f0 != e[:, 1:])]
    w1 = f1[(f1 != e[:, :1]) & (f1 != e[:, 1:])]
    p0, p1, p2, p3 = rest[e[:, 0]], rest[e[:, 1]], rest[w0], rest[w1]
    hinge = p1 - p0
    length = np.linalg.norm(hinge, axis=1)
    # A zero-length hinge (duplicate vertices) gets an arbitrary axis; it is dropped below.
    axis = hinge / np.maximum(length, 1e-300)[:, None]

    def unfold(p):
        rel = p - p0
        s = np.einsum("ij,ij->i", rel, axis)
        h = np.linalg.norm(rel - s[:, None] * axis, axis=1)
        return s, h

    s2, h2 = unfold(p2)
    s3, h3 = unfold(p3)
    typical = np.median(length) if len(length) else 1.0
    ok = (
        (h2 > DEGENERATE_FRACTION * np.minimum(length, typical))
        & (h3 > DEGENERATE_FRACTION * np.minimum(length, typical))
        & (length > DEGENERATE_FRACTION * typical)
    )
    k2 = length / np.where(ok, h2, 1.0)
    k3 = length / np.where(ok, h3, 1.0)
    k1 = -(k2 * s2 + k3 * s3) / np.where(ok, length, 1.0)
    k0 = -(k2 + k3) - k1
    stencils = np.stack([e[:, 0], e[:, 1], w0, w1], axis=1)[ok]
    weights = np.stack([k0, k1, k2, k3], axis=1)[ok]
    areas = (0.5 * length * (h2 + h3))[ok]
    return stencils.astype(np.int32), weights, areas


def _spring_kinds(uv: np.ndarray | None, edges: np.ndarray) -> np.ndarray:
    """Warp/weft edges are structural; edges near 45 degrees to the grain are shear."""
    if uv is None:
        return np.full(len(edges), STRUCTURAL, dtype=np.int8)
    d = uv[edges[:, 1]] - uv[edges[:, 0]]
    angle = np.degrees(np.arctan2(np.abs(d[:, 1]), np.abs(d[:, 0])))
    return np.where((angle > 22.5) & (angle < 67.5), SHEAR, STRUCTURAL).astype(np.int8)


def _loop_edges(loop: np.ndarray, edge_index: dict[tuple[int, int], int]) -> list[int]:
    out = []
    for a, b in zip(loop, np.roll(loop, -1), strict=True):
        key = (min(a, b), max(a, b))
        if key in edge_index:
            out.append(edge_index[key])
    return out


def build_cloth_model(garments: list[tuple[Garment, Fabric]]) -> ClothModel:
    xs, rests, faces, masses, gids, names, granges, franges = [], [], [], [], [], [], [], []
    springs, rest_len, kt, kc, beta, kind, elastic, maxs = [], [], [], [], [], [], [], []
    bends, bweights, bstiff, bbeta = [], [], [], []
    drag, fric, thick, pinned, fabrics = [], [], [], [], []
    strain_lens: list[np.ndarray] = []
    degenerate: dict[str, int] = {}
    offset = 0
    face_offset = 0
    for gi, (garment, fabric) in enumerate(garments):
        x = np.asarray(garment.vertices, dtype=np.float64)
        rest = np.asarray(garment.rest, dtype=np.float64)
        f = np.asarray(garment.faces, dtype=np.int64)
        n = len(x)
        e, adj = edges_of(f)
        length = np.linalg.norm(rest[e[:, 1]] - rest[e[:, 0]], axis=1)
        floor_len = DEGENERATE_FRACTION * float(np.median(length))
        floor_area = np.sqrt(3.0) / 4.0 * floor_len**2
        raw_areas = triangle_areas(rest, f)
        areas = np.maximum(raw_areas, floor_area)
        vertex_area = np.zeros(n)
        np.add.at(vertex_area, f.ravel(), np.repeat(areas / 3.0, 3))
        edge_area = areas[adj[:, 0]] / 3.0 + np.where(adj[:, 1] >= 0, areas[adj[:, 1]] / 3.0, 0.0)
        safe = np.maximum(length, floor_len)
        n_bends_full = int(np.count_nonzero(adj[:, 1] >= 0))
        k_kind = _spring_kinds(garment.uv, e)
        y_t = np.where(k_kind == SHEAR, fabric.shear, fabric.stretch)
        y_c = np.where(k_kind == SHEAR, fabric.shear, fabric.compression)
        k_t = y_t * edge_area / safe**2
        k_c = y_c * edge_area / safe**2
        is_elastic = np.zeros(len(e), dtype=bool)
        if garment.elastic:
            index = {(int(a), int(b)): i for i, (a, b) in enumerate(e)}
            for role in garment.elastic:
                ids = _loop_edges(np.asarray(garment.loops[role]), index)
                is_elastic[ids] = True
        length = np.where(is_elastic, length * ELASTIC_LENGTH, length)
        k_t = np.where(is_elastic, k_t * ELASTIC_STIFFNESS, k_t)
        k_c = np.where(is_elastic, k_c * ELASTIC_STIFFNESS, k_c)
        st, sw, sa = bending_stencils(rest, f, e, adj)
        counts = {
            "short_edges": int(np.count_nonzero(length < floor_len)),
            "small_triangles": int(np.count_nonzero(raw_areas < floor_area)),
            "hinges_without_bending": n_bends_full - len(st),
        }
        for key, value in counts.items():
            degenerate[key] = degenerate.get(key, 0) + value
        strain_len = safe  # strain, like stiffness, against the floored length
        if garment.seams is not None and len(garment.seams):
            # Sewing: zero-length springs between the panel edges being stitched.
            seam = np.asarray(garment.seams, dtype=np.int64)
            k_seam = np.full(len(seam), SEAM_STIFFNESS * fabric.stretch)
            e = np.concatenate([e, seam])
            length = np.concatenate([length, np.zeros(len(seam))])
            strain_len = np.concatenate([strain_len, np.full(len(seam), floor_len)])
            k_t = np.concatenate([k_t, k_seam])
            k_c = np.concatenate([k_c, k_seam])
            k_kind = np.concatenate([k_kind, np.full(len(seam), SEAM, dtype=np.int8)])
            is_elastic = np.concatenate([is_elastic, np.zeros(len(seam), dtype=bool)])

        xs.append(x)
        rests.append(rest)
        faces.append(f + offset)
        masses.append(fabric.density * vertex_area)
        gids.append(np.full(n, gi, dtype=np.int32))
        names.append(garment.name)
        granges.append((offset, offset + n))
        franges.append((face_offset, face_offset + len(f)))
        springs.append(e + offset)
        rest_len.append(length)
        strain_lens.append(strain_len)
        kt.append(k_t)
        kc.append(k_c)
        beta.append(np.full(len(e), fabric.stretch_damping))
        kind.append(k_kind)
        elastic.append(is_elastic)
        maxs.append(np.full(len(e), fabric.max_strain))
        bends.append(st + offset)
        bweights.append(sw)
        bstiff.append(fabric.bending / sa)
        bbeta.append(np.full(len(st), fabric.bending_damping))
        drag.append(fabric.air_drag * vertex_area)
        fric.append(np.full(n, fabric.friction))
        thick.append(np.full(n, fabric.thickness))
        if garment.pinned is not None and len(garment.pinned):
            pinned.append(np.asarray(garment.pinned, dtype=np.int64) + offset)
        fabrics.append(fabric)
        offset += n
        face_offset += len(f)

    mass = np.concatenate(masses)
    if np.any(mass <= 0):
        gi = int(np.concatenate(gids)[np.flatnonzero(mass <= 0)[0]])
        raise InputError(garments[gi][0].name, "faces",
                         "every vertex in at least one triangle", "an unreferenced vertex")
    return ClothModel(
        x0=np.concatenate(xs),
        rest_x=np.concatenate(rests),
        faces=np.concatenate(faces).astype(np.int32),
        mass=mass,
        garment_of_vertex=np.concatenate(gids),
        garment_names=names,
        garment_ranges=granges,
        face_ranges=franges,
        springs=np.concatenate(springs).astype(np.int32),
        rest_length=np.concatenate(rest_len),
        k_tension=np.concatenate(kt),
        k_compression=np.concatenate(kc),
        spring_beta=np.concatenate(beta),
        spring_kind=np.concatenate(kind),
        spring_elastic=np.concatenate(elastic),
        bends=np.concatenate(bends).astype(np.int32),
        bend_weights=np.concatenate(bweights),
        bend_stiffness=np.concatenate(bstiff),
        bend_beta=np.concatenate(bbeta),
        air_drag=np.concatenate(drag),
        friction=np.concatenate(fric),
        thickness=np.concatenate(thick),
        max_strain=np.concatenate(maxs),
        pinned=np.concatenate(pinned) if pinned else np.zeros(0, dtype=np.int64),
        fabrics=fabrics,
        layers=[g.layer for g, _ in garments],
        strain_length=np.concatenate(strain_lens),
        degenerate=degenerate,
    )
