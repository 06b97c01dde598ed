"""Resizing a template garment to a subject (CLOTH3D thesis 3.3.2).

A template is built around the neutral rest body of its gender. Its fit to another subject comes
from the body's own shape change: every body vertex's displacement from the template body to a
target body (same topology, so vertex by vertex) is carried to the garment from the nearest body
points, then smoothed over the garment so that body details (muscles, breasts) do not print
through while the garment's own shape stays. The smoothing is a screened Laplacian solve, the
implicit limit of iterative Laplacian smoothing: a vertex near the skin keeps its body point's
displacement, one far from it (a flared hem, a loose sleeve) takes a smooth blend from the cloth
around it. Plain nearest-point transfer there jumps between body parts from one vertex to the
next (a hem between the knees collapsed to 5 % of its height on a short subject).

Two targets give the garment its two geometries (datagen.types.Garment):

- `rest_vertices`, the garment's rest shape (its size): the subject's shape with the tightness
  offsets gamma = (size, girth) in [-1.5, 0.5]^2 applied to the size and girth phenotypes
  (height and weight for Anny), in units of a sixth of their range (CLOTH3D's betas span
  [-3, 3], six units); negative gamma makes the garment for a bigger body: looser.
  The transfer follows the body's surface, which at the extremes of shape changes unevenly (a
  short subject's knees shrink vertically to half the body's mean scale, a heavy subject's inner
  thighs more): the rest shape is then graded (`grade`), as a pattern maker grades a size, so
  that no edge's scale change departs from the garment's mean by more than GRADING_BAND.
- `vertices`, the starting positions: the same transfer to the subject's own body, pushed out
  where needed so no vertex starts closer than CLEARANCE to the body. A tight garment thus starts
  stretched around the body and contracts onto it in the simulation; a loose one starts
  gathered and falls open.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from datagen.skeleton import JOINT_NAMES
from datagen.types import RestBody

CLEARANCE = 0.004  # m: starting gap to the subject's skin (the check requires 2 mm)
TIGHTNESS_SCALE = 1.0 / 6.0  # phenotype units per tightness unit (beta range 6 -> [0, 1])
SIZE_PARAMETER = "height"
GIRTH_PARAMETER = "weight"
NEIGHBOURS = 8  # body vertices averaged per garment vertex
# The screened smoothing: a vertex this far from the skin follows its body point with half the
# weight it has at the skin; SMOOTHING is the Laplacian's weight in edge lengths squared
# (diffusion over about sqrt(SMOOTHING) edges at the skin, growing with the distance).
FOLLOW_DISTANCE = 0.02  # m
SMOOTHING = 10.0
# Grading: every edge's scale change within this share of the garment's mean scale change (the
# garments issue asks for 30 %; the solve stops once every edge is within GRADING_BAND + 5 %,
# and 10 reweighted solves leave the extreme subjects within 25 %).
GRADING_BAND = 0.15
GRADING_ROUNDS = 10
GRADING_WEIGHT_GROWTH = 4.0  # an edge outside the band weighs this much more each round
GRADING_ANCHOR = 1e-3  # weight that holds each vertex to the transfer (edges weigh 1)
# The yoke's ramp from the shoulder joints out along the sleeves (yoke_weight).
YOKE_SLEEVE_RAMP = 0.06  # m


def garment_body_shape(
    shape: np.ndarray, names: tuple[str, ...], tightness: tuple[float, float]
) -> np.ndarray:
    """The shape the garment is made for: tightness offsets on the size and girth parameters."""
    out = np.array(shape, dtype=np.float64, copy=True)
    out[names.index(SIZE_PARAMETER)] -= TIGHTNESS_SCALE * tightness[0]
    out[names.index(GIRTH_PARAMETER)] -= TIGHTNESS_SCALE * tightness[1]
    return out


def yoke_tightness(tightness: tuple[float, float]) -> tuple[float, float] | None:
    """The tightness a garment's yoke is cut for, where it differs from the garment's: a loose
    garment (a negative offset) is loose in its girth and length but cut at the shoulders for
    the subject, as clothes are (a yoke a size too big sits further out on the shoulders'
    slope, and a strap top then slides off a moving body: docs/templates.md, "Resizing").
    None where the garment is nowhere loose."""
    yoke = (max(float(tightness[0]), 0.0), max(float(tightness[1]), 0.0))
    return None if yoke == (float(tightness[0]), float(tightness[1])) else yoke


def bodice_tightness(tightness: tuple[float, float]) -> tuple[float, float] | None:
    """The tightness of the bodice of a garment hung from both the shoulders and a waistband
    (a jumpsuit, a dress), where it differs from the garment's: loose in its girth, but as
    long as the subject's torso. A bodice cut for a taller body (a negative size offset)
    leaves its straps slack between the waistband and the shoulders, and nothing then holds
    them on. None where the garment is not loose in size."""
    size, girth = float(tightness[0]), float(tightness[1])
    return None if size >= 0.0 else (0.0, girth)


def vertex_neighbours(n_vertices: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR (pointer, index) of each vertex's mesh neighbours."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(np.concatenate([e, e[:, ::-1]]), axis=1), axis=0)
    both = np.concatenate([e, e[:, ::-1]])
    order = np.argsort(both[:, 0], kind="stable")
    both = both[order]
    ptr = np.zeros(n_vertices + 1, dtype=np.int64)
    np.add.at(ptr, both[:, 0] + 1, 1)
    return np.cumsum(ptr), both[:, 1]


def laplacian_smooth(
    values: np.ndarray, faces: np.ndarray, iterations: int, weight: float
) -> np.ndarray:
    """Iterative umbrella smoothing of a per-vertex field (V, k) over the mesh."""
    ptr, idx = vertex_neighbours(len(values), faces)
    counts = np.diff(ptr)
    owner = np.repeat(np.arange(len(values)), counts)
    out = np.array(values, dtype=np.float64, copy=True)
    for _ in range(iterations):
        mean = np.zeros_like(out)
        np.add.at(mean, owner, out[idx])
        mean /= np.maximum(counts, 1)[:, None]
        out = out + weight * (mean - out)
    return out


def graph_laplacian(n_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    """The mesh's uniform graph Laplacian (degree minus adjacency), positive semi-definite."""
    from datagen.sim.model import edges_of

    e = edges_of(faces)[0]
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    a = (a + a.T).tocsr()
    return (sp.diags(np.asarray(a.sum(axis=1)).ravel()) - a).tocsr()


class DisplacementTransfer:
    """The transfer of body displacements from `source_body` to a garment lying on it, set up
    once (nearest body points, the screened smoothing's factorised system) and applied to any
    number of target bodies of the same topology: an outfit's garment goes to the subject, to
    the size it is cut for and, for a loose garment, to the size of its yoke."""

    def __init__(self, garment: np.ndarray, faces: np.ndarray, source_body: np.ndarray) -> None:
        tree = cKDTree(source_body)
        dist, self._idx = tree.query(garment, k=NEIGHBOURS)
        w = 1.0 / np.maximum(dist, 1e-4) ** 2
        self._weights = w / w.sum(axis=1, keepdims=True)
        self._follow = 1.0 / (1.0 + (dist[:, 0] / FOLLOW_DISTANCE) ** 2)
        self._source = source_body
        system = sp.diags(self._follow) + SMOOTHING * graph_laplacian(len(garment), faces)
        self._solve = _spd_solver(system)

    def to(self, target_body: np.ndarray) -> np.ndarray:
        """(V, 3) each garment vertex's displacement towards `target_body`."""
        idx = self._idx
        body_disp = np.einsum("vk,vkd->vd", self._weights, target_body[idx] - self._source[idx])
        return self._solve(self._follow[:, None] * body_disp)


def transfer_displacement(
    garment: np.ndarray, faces: np.ndarray, source_body: np.ndarray, target_body: np.ndarray
) -> np.ndarray:
    """Per garment vertex, the displacement of its nearest body points, smoothed over the
    garment: minimises sum_i c_i |d_i - b_i|^2 + SMOOTHING * sum_edges |d_i - d_j|^2, where b_i
    is the body points' displacement and c_i = 1 / (1 + (distance to the skin /
    FOLLOW_DISTANCE)^2) says how much the vertex follows its body point."""
    return DisplacementTransfer(garment, faces, source_body).to(target_body)


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def yoke_weight(garment: np.ndarray, body: RestBody) -> np.ndarray:
    """(V,) per vertex of a garment lying on `body` (T-pose), 1 on its yoke (over the
    shoulders and around the neck, what the garment hangs from) and 0 below the chest and
    along the sleeves, with smooth ramps between: upwards from the chest joint to the
    shoulder joints' height, sideways over YOKE_SLEEVE_RAMP beyond the shoulder joints."""
    j = body.joints
    chest = j[JOINT_NAMES.index("spine3")]
    shoulders = j[[JOINT_NAMES.index("left_shoulder"), JOINT_NAMES.index("right_shoulder")]]
    centre_x = j[JOINT_NAMES.index("neck"), 0]
    shoulder_z = float(shoulders[:, 2].mean())
    half_width = float(np.abs(shoulders[:, 0] - centre_x).mean())
    up = _smoothstep((garment[:, 2] - chest[2]) / max(shoulder_z - chest[2], 1e-3))
    inside = 1.0 - _smoothstep((np.abs(garment[:, 0] - centre_x) - half_width)
                               / YOKE_SLEEVE_RAMP)
    return up * inside


def bodice_weight(garment: np.ndarray, body: RestBody) -> np.ndarray:
    """(V,) per vertex of a garment lying on `body` (T-pose), 1 above the waist (the spine
    joint above the pelvis) and 0 below the pelvis joint, with a smooth ramp between."""
    j = body.joints
    low, high = j[JOINT_NAMES.index("pelvis"), 2], j[JOINT_NAMES.index("spine1"), 2]
    return _smoothstep((garment[:, 2] - low) / max(high - low, 1e-3))


def _offset_to(body: RestBody, joint: str, to: np.ndarray) -> np.ndarray:
    """(3,) the translation that moves `body`'s `joint` to `to`."""
    return to - body.joints[JOINT_NAMES.index(joint)]


def grade(template_vertices: np.ndarray, resized: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The resized garment with every edge's scale change (its length over the template's)
    brought within GRADING_BAND of the mean scale change, the rest of the shape kept.

    A gradient-domain solve: positions whose edge vectors best match the current edges' with
    their lengths clamped to the band, held weakly to `resized`; reweighted least squares (an
    edge still outside the band weighs more each round) until every edge is within the band plus
    5 %, at most GRADING_ROUNDS solves. A garment already within it is returned unchanged."""
    from datagen.sim.model import edges_of

    e = edges_of(faces)[0]
    template_length = np.linalg.norm(template_vertices[e[:, 1]] - template_vertices[e[:, 0]],
                                     axis=1)
    has_scale = template_length > 1e-6  # a zero-length template edge has no scale to keep
    e, template_length = e[has_scale], template_length[has_scale]
    n, m = len(resized), len(e)
    incidence = sp.csr_matrix(
        (np.r_[np.ones(m), -np.ones(m)], (np.tile(np.arange(m), 2), np.r_[e[:, 1], e[:, 0]])),
        shape=(m, n))
    out = np.array(resized, dtype=np.float64, copy=True)
    weight = np.ones(m)
    for _ in range(GRADING_ROUNDS):
        d = out[e[:, 1]] - out[e[:, 0]]
        length = np.linalg.norm(d, axis=1)
        scale = length / template_length
        low, high = scale.mean() * (1.0 - GRADING_BAND), scale.mean() * (1.0 + GRADING_BAND)
        slack = 0.05 * scale.mean()
        if np.all((scale >= low - slack) & (scale <= high + slack)):
            break
        weight = np.where((scale < low) | (scale > high), weight * GRADING_WEIGHT_GROWTH, weight)
        target = d * (np.clip(scale, low, high) / np.maximum(scale, 1e-12))[:, None]
        system = incidence.T @ sp.diags(weight) @ incidence + GRADING_ANCHOR * sp.identity(n)
        solve = _spd_solver(system)
        rhs = incidence.T @ (weight[:, None] * target) + GRADING_ANCHOR * resized
        out = solve(np.asarray(rhs))
    return out


def _spd_solver(system: sp.spmatrix):
    """A solve function for a symmetric positive definite sparse system: SuperLU in symmetric
    mode (ordering on A + A^T, diagonal pivots), about half the time of its general default."""
    lu = splu(system.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
              options={"SymmetricMode": True})
    return lu.solve


def _pseudonormal_side(mesh, points: np.ndarray, closest: np.ndarray,
                       tri: np.ndarray) -> np.ndarray:
    """+1 outside, -1 inside: the side of the closest point's angle-weighted pseudonormal
    (Baerentzen and Aanaes 2005), exact for a closed, consistently oriented mesh: the face
    normal where the closest point lies inside a face, the sum of the two face normals at an
    edge, the angle-weighted vertex normal at a corner."""
    import trimesh

    fn = mesh.face_normals
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    on_zero = bary < 1e-7
    zeros = on_zero.sum(axis=1)
    normal = fn[tri].copy()
    edge_points = np.flatnonzero(zeros == 1)
    if len(edge_points):
        # trimesh lists face f's edges as (v0, v1), (v1, v2), (v2, v0): the one opposite corner
        # k is edge 3 f + (k + 1) % 3; its unique index comes from the mesh's cached inverse.
        inverse = mesh.edges_unique_inverse
        edge_normal = np.zeros((len(mesh.edges_unique), 3))
        np.add.at(edge_normal, inverse, np.repeat(fn, 3, axis=0))
        k = np.argmax(on_zero[edge_points], axis=1)
        normal[edge_points] = edge_normal[inverse[3 * tri[edge_points] + (k + 1) % 3]]
    corner_points = np.flatnonzero(zeros >= 2)
    if len(corner_points):  # trimesh's vertex normals are angle-weighted (and cached)
        corner = mesh.faces[tri[corner_points], np.argmax(bary[corner_points], axis=1)]
        normal[corner_points] = mesh.vertex_normals[corner]
    side = np.sign(np.einsum("ij,ij->i", points - closest, normal))
    return np.where(side < 0, -1.0, 1.0)


class BodySurface:
    """The rest body for closest-point queries: libigl's AABB tree (exact closest points, about
    ten times faster than trimesh's rtree search, which also missed the closest point on the
    body's smallest triangles by up to 0.1 mm) and the trimesh view that gives the normals for
    the inside/outside test."""

    def __init__(self, body: RestBody) -> None:
        import igl
        import trimesh

        # Copies: the cache compares them with the next body asked for.
        self.vertices = np.array(body.vertices, dtype=np.float64, order="C", copy=True)
        self.faces = np.array(body.faces, dtype=np.int64, order="C", copy=True)
        self.mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        self.tree = igl.AABB()
        self.tree.init(self.vertices, self.faces)

    def is_of(self, body: RestBody) -> bool:
        return (np.array_equal(self.vertices, body.vertices)
                and np.array_equal(self.faces, body.faces))

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(signed distance, positive outside; the face normal at the closest point)"""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        squared, tri, closest = self.tree.squared_distance(self.vertices, self.faces, points)
        side = _pseudonormal_side(self.mesh, points, closest, tri)
        return side * np.sqrt(squared), self.mesh.face_normals[tri]


_LAST_SURFACE: list[BodySurface] = []  # one entry: the last body asked for


def body_surface(body: RestBody) -> BodySurface:
    """The body's BodySurface, reused while the same body is asked for: an outfit's garments are
    all pushed clear of one subject."""
    if not (_LAST_SURFACE and _LAST_SURFACE[0].is_of(body)):
        _LAST_SURFACE[:] = [BodySurface(body)]
    return _LAST_SURFACE[0]


def body_signed_distance(points: np.ndarray, body: RestBody) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance to the (watertight) rest body, positive outside, and the surface normal at
    the closest point."""
    return body_surface(body).signed_distance(points)


class _ClearanceTracker:
    """Signed distances of moving points, queried again only where they could matter: the
    distance to the body changes by at most how far a point moved, so a point whose last known
    distance minus its movement since is still beyond `reach` needs no new query."""

    def __init__(self, points: np.ndarray, body: RestBody, reach: float) -> None:
        self.surface = body_surface(body)
        self.reach = reach
        self.sd = np.full(len(points), -np.inf)  # unknown: query everything the first time
        self.normals = np.zeros((len(points), 3))
        self.moved = np.zeros(len(points))

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a lower bound of the signed distance, exact where it is below `reach`; normals)"""
        ask = np.flatnonzero(self.sd - self.moved < self.reach)
        if len(ask):
            self.sd[ask], self.normals[ask] = self.surface.signed_distance(points[ask])
            self.moved[ask] = 0.0
        return self.sd - self.moved, self.normals

    def move(self, step: np.ndarray) -> None:
        self.moved += np.linalg.norm(step, axis=1)


def push_out(
    vertices: np.ndarray,
    faces: np.ndarray,
    body: RestBody,
    clearance: float = CLEARANCE,
    rounds: int = 6,
) -> np.ndarray:
    """Move vertices closer than `clearance` to the body (or inside it) outward along the body
    normal, spreading the move smoothly so the surface keeps its shape."""
    out = np.array(vertices, dtype=np.float64, copy=True)
    distances = _ClearanceTracker(out, body, reach=clearance + 0.005)
    for _ in range(rounds):
        sd, normals = distances.query(out)
        short = clearance + 0.001 - sd
        if np.all(short <= 0.001):
            return out  # every vertex at least `clearance` clear
        push = np.where(short > 0, short, 0.0)[:, None] * normals
        spread = laplacian_smooth(push, faces, 3, 0.5)
        # Never less than the local need: smoothing spreads, it must not undo.
        need = np.where(short > 0, short, 0.0)
        along = np.einsum("ij,ij->i", spread, normals)
        spread += np.maximum(need - along, 0.0)[:, None] * normals
        out += spread
        distances.move(spread)
    # Smoothing can leave a vertex in a crease short of its need: move those straight out.
    sd, normals = distances.query(out)
    short = np.maximum(clearance - sd, 0.0)
    out += short[:, None] * normals
    return out


def resize(
    template_vertices: np.ndarray,
    faces: np.ndarray,
    template_body: RestBody,
    subject: RestBody,
    garment_body: RestBody,
    yoke_body: RestBody | None = None,
    bodice_body: RestBody | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(starting positions, rest shape) of a template garment resized to `subject`, made for
    `garment_body` (the subject with the tightness offsets). Where given, `bodice_body` is the
    size of the part above the waist (bodice_weight, bodice_tightness) and `yoke_body` the
    size of the yoke (yoke_weight, yoke_tightness)."""
    transfer = DisplacementTransfer(template_vertices, faces, template_body.vertices)
    start = template_vertices + transfer.to(subject.vertices)
    size = transfer.to(garment_body.vertices)
    # Each finer size meets the one it is blended into at a joint of both (the waist, the
    # neck), so the larger size's extra length goes below it, not into the ramp between them.
    neck = garment_body.joints[JOINT_NAMES.index("neck")]
    if bodice_body is not None:
        shift = _offset_to(bodice_body, "spine1", garment_body.joints[JOINT_NAMES.index("spine1")])
        weight = bodice_weight(template_vertices, template_body)[:, None]
        size += weight * (transfer.to(bodice_body.vertices + shift) - size)
        neck = bodice_body.joints[JOINT_NAMES.index("neck")] + shift
    if yoke_body is not None:
        shift = _offset_to(yoke_body, "neck", neck)
        weight = yoke_weight(template_vertices, template_body)[:, None]
        size += weight * (transfer.to(yoke_body.vertices + shift) - size)
    rest = grade(template_vertices, template_vertices + size, faces)
    start = push_out(start, faces, subject)
    return start, rest
