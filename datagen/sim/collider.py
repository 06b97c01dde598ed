"""The moving body as a collider: triangles (masked to the parts a garment can reach), their
edge adjacency for surface tracking, per-frame vertex normals (computed on the device), and a
uniform grid (dense, or hashed where a batch's lattice would make it large) for the global
closest-triangle search."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import taichi as ti

from datagen.sim import backend
from datagen.sim import contact_kernels as CK
from datagen.sim import depth_kernels as DK
from datagen.sim import grid_kernels as GK
from datagen.sim import kernel_common as KC
from datagen.sim import kernels as K
from datagen.sim import parallel_kernels as PK
from datagen.sim import search_kernels as SK
from datagen.sim.backend import init_taichi
from datagen.sim.precision import NP_REAL, REAL, VEC3


def face_adjacency(faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(T, 3): the unmasked face across the edge opposite each corner, or -1."""
    n = len(faces)
    adj = -np.ones((n, 3), dtype=np.int32)
    edge_owner: dict[tuple[int, int], tuple[int, int]] = {}
    for t in np.flatnonzero(mask):
        f = faces[t]
        for k in range(3):
            a, b = int(f[(k + 1) % 3]), int(f[(k + 2) % 3])
            key = (a, b) if a < b else (b, a)
            other = edge_owner.get(key)
            if other is None:
                edge_owner[key] = (int(t), k)
            else:
                adj[t, k] = other[0]
                adj[other[0], other[1]] = t
    return adj


def closed_surface(faces: np.ndarray) -> bool:
    """Whether triangles `faces` close a surface with a consistent orientation: every directed
    edge once, and its reverse once (Anny's body mesh is watertight; a garment is not)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return False
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    forward = edges[:, 0] * n + edges[:, 1]
    backward = edges[:, 1] * n + edges[:, 0]
    forward.sort()
    backward.sort()
    return bool(np.all(forward[1:] != forward[:-1]) and np.array_equal(forward, backward))


# A frame tangent is at most this many times the shorter of the two frames' travels beside it
# (frame_tangents): a Catmull-Rom tangent next to a one-frame jump of a track (a teleport)
# would carry half the jump into the still frame before it: a bulge of 7 % of the jump (4/27
# of the half) ahead of the body and back.
# Where motion is smooth the two travels and the tangent are all alike, and the bound is idle.
TANGENT_TRAVEL_MAX = 3.0


def frame_tangents(frames: np.ndarray, k: int) -> np.ndarray:
    """(V, 3) each vertex's velocity at frame k of `frames` (F, V, 3), in metres per frame:
    the central difference (Catmull-Rom), one-sided at the track's ends, its length at most
    TANGENT_TRAVEL_MAX times the shorter travel of the frames either side. Consecutive frames'
    Hermite paths share it at their common frame, so the body's velocity is continuous."""
    n = len(frames)
    here = np.asarray(frames[k], dtype=np.float64)
    before = here - frames[k - 1] if k > 0 else None
    after = frames[k + 1] - here if k + 1 < n else None
    if before is None and after is None:
        return np.zeros_like(here)
    if before is None or after is None:
        return np.array(after if before is None else before, dtype=np.float64)
    m = 0.5 * (before + after)
    bound = TANGENT_TRAVEL_MAX * np.sqrt(np.minimum(np.einsum("ij,ij->i", before, before),
                                                    np.einsum("ij,ij->i", after, after)))
    length = np.sqrt(np.einsum("ij,ij->i", m, m))
    scale = np.where(length > bound, bound / np.maximum(length, 1e-300), 1.0)
    return m * scale[:, None]


def path_bounds(motion: np.ndarray, tangents: np.ndarray | None,
                shift: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per body vertex, bounds on its path over a frame that the collision search's proofs
    rest on: the square of its fastest speed, its fastest speed relative to the mean motion
    `shift` (both in metres per frame), and how far the path strays from the chord (metres).
    `motion` (3, V) is each vertex's chord v1 - v0, transposed; `tangents` (2, V, 3) its
    Hermite path's end tangents (kernels.hermite3), None for the chord itself.

    The path is a cubic Bezier curve with control points a, a + ma/3, b - mb/3, b, so its
    velocity is a quadratic one with control points ma, 3d - ma - mb and mb (d = b - a), and
    never faster than the fastest of these. Its departure from the chord is
    s(1-s)((1-s)(ma - d) - s(mb - d)), at most 4/27 (|ma - d| + |mb - d|). On a fast kick's
    foot or a spin's hands the path is up to 2.8 times as fast as the chord within a frame and
    strays up to 37 mm from it, more than the search's reach of a grid cell."""
    if tangents is None:
        speed_sq = np.einsum("ci,ci->i", motion, motion)
        relative = motion - shift[:, None]
        return (speed_sq, np.sqrt(np.einsum("ci,ci->i", relative, relative)),
                np.zeros(motion.shape[1]))
    start = np.ascontiguousarray(np.asarray(tangents[0], dtype=np.float64).T)
    end = np.ascontiguousarray(np.asarray(tangents[1], dtype=np.float64).T)
    middle = 3.0 * motion - start - end
    speed_sq = np.zeros(motion.shape[1])
    relative_sq = np.zeros(motion.shape[1])
    for c in (start, middle, end):
        speed_sq = np.maximum(speed_sq, np.einsum("ci,ci->i", c, c))
        r = c - shift[:, None]
        relative_sq = np.maximum(relative_sq, np.einsum("ci,ci->i", r, r))
    u, w = start - motion, end - motion
    bulge = (4.0 / 27.0) * (np.sqrt(np.einsum("ci,ci->i", u, u))
                            + np.sqrt(np.einsum("ci,ci->i", w, w)))
    return speed_sq, np.sqrt(relative_sq), bulge


# Grid numbers, unique across the colliders of a process (a retry solver is handed the guards
# that another solver's collider proved), and exact as float32 (2**24 grids before they repeat).
_GRID_TAGS = (1 + k % (2**24 - 1) for k in itertools.count())
# Edge (m) of the grid's cells. A grid spanning more cells than DENSE_GRID_CELLS is hashed
# (grid_kernels.grid_cell): one body spans about 10^5 cells, but a batch's lattice
# (datagen.sim.batch) spans every scene's whole motion, and 64 scenes of 10 s walks would need
# 1.4 billion dense cells (11 GB of counts and offsets, past int32 indices). A hashed grid has
# HASH_BUCKETS_PER_TRIANGLE buckets per colliding triangle (a power of two), whatever the extent.
GRID_CELL = 0.025
DENSE_GRID_CELLS = 2**22
HASH_BUCKETS_PER_TRIANGLE = 8
# The depth QA's inside test (depth_kernels.winding_along_ray) files the whole body in columns of
# this edge (m), across its ray. Half of it built the walking body's columns 1.3x slower (94k
# entries against 54k) and answered the t-shirt's points no faster.
COLUMN_CELL = GRID_CELL


@dataclass
class TriangleGrid:
    """One grid's device arrays: each triangle's box (`tbox`, kernel_common.GUARD: low and high
    corners, speed, body part), the triangles filed per cell (`starts`, `items`), and the
    build's scratch (`counts`, zero between builds; `block_starts`, the parallel prefix's)."""

    tbox: ti.Ndarray | None  # the column grid's: each triangle's columns (_column_grid)
    counts: ti.Ndarray | None = None
    starts: ti.Ndarray | None = None
    block_starts: ti.Ndarray | None = None
    items: ti.Ndarray | None = None
    n_cells_alloc: int = 0
    items_alloc: int = 0
    tag: int = 0  # the collider's grid_tag when this grid was built
    # the column grid's: each column's lowest and highest coordinate along the ray (2c, 2c + 1),
    # and each filed triangle's box beside it in `items` (depth_kernels.item_box)
    along: ti.Ndarray | None = None
    boxes: ti.Ndarray | None = None

    def reserve_cells(self, n_cells: int, block_sums: bool) -> None:
        """Room for `n_cells` cells' counts (zero) and starts, half as many again when they
        grow, and with `block_sums` for the parallel prefix's block sums
        (grid_kernels.grid_prefix)."""
        if n_cells + 1 <= self.n_cells_alloc:
            return
        self.n_cells_alloc = int((n_cells + 1) * 1.5)
        self.counts = ti.ndarray(ti.i32, self.n_cells_alloc)
        self.starts = ti.ndarray(ti.i32, self.n_cells_alloc + 1)
        if block_sums:
            self.block_starts = ti.ndarray(ti.i32, self.n_cells_alloc // GK.PREFIX_BLOCK + 2)
        self.counts.fill(0)

    def reserve_items(self, entries: int, spare: float = 1.5) -> bool:
        """Room for `entries` filed triangles (`spare` times as many when `items` grows);
        whether it grew (a one-launch build that found it short filed nothing: run it again)."""
        if self.items is not None and entries <= self.items_alloc:
            return False
        self.items_alloc = int(entries * spare) + 16
        self.items = ti.ndarray(ti.i32, self.items_alloc)
        return True


class BodyCollider:
    """Holds the body's frames on the device; one instance per scene."""

    def __init__(
        self, faces: np.ndarray, face_mask: np.ndarray, n_vertices: int, cell: float = GRID_CELL,
        normals: bool = True, face_parts: np.ndarray | None = None,
    ) -> None:
        """`face_parts`: each face's body part (ints from 0), or None for a collider that is one
        surface (a sphere, a garment under another). With parts, a cloth vertex is searched
        again when a facing surface of another part may come near it
        (search_kernels.nearest_one)."""
        init_taichi()
        # A layer collider reads its normals from the cloth each substep: none per frame.
        self.normals = normals
        self.faces_np = np.asarray(faces, dtype=np.int32)
        self.mask_np = np.asarray(face_mask, dtype=bool)
        # The body vertices of the colliding faces: the grid spans them (indexing every face
        # corner of a 27k-face body each frame cost a walking t-shirt 8 ms a frame).
        self.used_vertices = np.unique(self.faces_np[self.mask_np])
        self.used = ti.ndarray(ti.i32, max(len(self.used_vertices), 1))
        self.used.from_numpy(np.resize(self.used_vertices.astype(np.int32), self.used.shape[0]))
        # The grid's extent (grid_kernels.collider_bounds). Host arrays, read in place by kernels
        # on a CPU: a transfer to or from a device array costs 0.09 ms in Taichi's Python.
        self.box = np.zeros((2, 3), NP_REAL)
        # Parallel backends gather each vertex's face normals (datagen.sim.parallel_kernels).
        self.vertex_faces = None
        if normals and not backend.serial():
            from datagen.sim.solvers import _vertex_lists_nd

            self.vertex_faces = _vertex_lists_nd(self.faces_np.ravel(), n_vertices)
        # A hashed grid's buckets: a power of two, HASH_BUCKETS_PER_TRIANGLE per colliding face.
        wanted = HASH_BUCKETS_PER_TRIANGLE * max(int(self.mask_np.sum()), 512)
        self.hash_buckets = 1 << (wanted - 1).bit_length()
        self.n_vertices = n_vertices
        self.cell = cell
        self.faces = ti.ndarray(ti.math.ivec3, len(self.faces_np))
        self.faces.from_numpy(self.faces_np)
        self.fadj = ti.ndarray(ti.math.ivec3, len(self.faces_np))
        self.fadj.from_numpy(face_adjacency(self.faces_np, self.mask_np))
        self.mask = ti.ndarray(ti.i32, len(self.faces_np))
        self.mask.from_numpy(self.mask_np.astype(np.int32))
        self.b0 = ti.ndarray(VEC3, n_vertices)
        self.b1 = ti.ndarray(VEC3, n_vertices)
        self.n0 = ti.ndarray(VEC3, n_vertices)
        self.n1 = ti.ndarray(VEC3, n_vertices)
        # Scratch: the body interpolated to a substep's start and end (fused solver kernels).
        # bs0 also keeps the frame's path tangents after the vertices (set_frames), which the
        # interpolation reads (kernels.interpolate_body_one).
        self.bs0 = ti.ndarray(VEC3, 3 * n_vertices)
        self.bs1 = ti.ndarray(VEC3, n_vertices)
        self.ns1 = ti.ndarray(VEC3, n_vertices)
        self.relative_travel = np.zeros(n_vertices, NP_REAL)  # from the mean motion, per frame
        # How far each vertex's path strays from its chord over the frame (path_bounds): the
        # triangles' swept boxes grow by it. The frame's end grid has none.
        self.bulge = np.zeros(n_vertices, NP_REAL)
        self.no_bulge = np.zeros(n_vertices, NP_REAL)
        tbox = ti.ndarray(KC.GUARD, len(self.faces_np))  # per triangle (GK.grid_count)
        boxes = np.zeros((len(self.faces_np), KC.GUARD.n), NP_REAL)
        if face_parts is None:
            boxes[:, GK.T_PART] = -1.0
        else:
            face_parts = np.asarray(face_parts)
            if face_parts.shape != (len(self.faces_np),) or face_parts.min(initial=0) < 0:
                raise ValueError(f"face_parts: expected one part index >= 0 per face "
                                 f"({len(self.faces_np)}), got shape {face_parts.shape}")
            # The search guards pack a distance below a cell after the part (SK.OTHER_NONE).
            assert cell < SK.OTHER_NONE, cell
            boxes[:, GK.T_PART] = face_parts
        tbox.from_numpy(boxes)
        # Two grids over the same cells: `swept` files each triangle's box swept over the frame
        # (the solver's searches at any fraction of it); `end` its box at the frame's end only,
        # for the depth QA (signed_distance), built when asked for. A walking body's swept boxes
        # are filed 98k times for its 18.5k colliding triangles (143k before the cells moved
        # with the body: grid_kernels.count_triangle), its end boxes 52k times; the QA's search took
        # 24 ms a frame through the swept grid in fixed cells, 14 through the end grid (plus 2
        # to build it).
        end_tbox = ti.ndarray(KC.GUARD, len(self.faces_np))
        end_tbox.from_numpy(boxes)
        self.swept = TriangleGrid(tbox)
        self.end = TriangleGrid(end_tbox)
        self.n_cells = 0
        self.shift_np = np.zeros(3)
        self.shift = VEC3(0.0, 0.0, 0.0)  # shift_np as the kernels take it
        # The frame's fold fields (set_fold; datagen.sim.fold_fields): [0] where none.
        self.fold_np = np.zeros(1, NP_REAL)
        self.fold_nd = ti.ndarray(REAL, 1)
        self.fold_nd.from_numpy(self.fold_np)
        # The depth QA's inside test, for a closed collider: its column grid of the whole mesh
        # at the frame's end (built when asked for) and whether its triangles face outwards.
        self.closed = closed_surface(self.faces_np)
        self._columns: TriangleGrid | None = None
        self._columns_at = (-1, None)  # (grid_tag, origin, inverse column, dims) of the build
        self._outward = 0
        self._prev = None
        self._at_rest = False
        # this collider's grid's number (search_kernels.nearest_one's frame guards)
        self.grid_tag = 0

    # The solver's kernels take the swept grid's arrays.
    @property
    def starts(self) -> ti.Ndarray:
        return self.swept.starts

    @property
    def items(self) -> ti.Ndarray:
        return self.swept.items

    @property
    def counts(self) -> ti.Ndarray:
        return self.swept.counts

    @property
    def tbox(self) -> ti.Ndarray:
        return self.swept.tbox

    def set_frames(self, v0: np.ndarray, v1: np.ndarray,
                   tangents: np.ndarray | None = None) -> None:
        """Body positions at the start and end of the coming frame, and the path between them:
        `tangents` (2, V, 3), each vertex's velocity at the frame's start and end in metres per
        frame (frame_tangents), along which the contact kernels take the body within the frame
        (a cubic Hermite curve: kernels.interpolate_body_one); None for the chord, v1 - v0 at
        both ends (the straight line). Consecutive frames share a pose: when v0 is the previous
        call's v1, its arrays are reused instead of uploaded again."""
        v0 = np.asarray(v0, dtype=NP_REAL)
        v1 = np.asarray(v1, dtype=NP_REAL)
        prev = getattr(self, "v1_np", None)
        still = tangents is None or not np.any(tangents)
        if (
            self._at_rest
            and still
            and np.array_equal(prev, v0)
            and np.array_equal(v0, v1)
        ):
            return  # a collider at rest: the arrays and the grid of the last frame still hold
        if self.normals:  # a body (a layer collider's path is never interpolated)
            if tangents is None:
                tangents = np.broadcast_to(v1 - v0, (2, *v0.shape))
            path = np.ascontiguousarray(tangents, dtype=NP_REAL).reshape(-1, 3)
            K.copy_in_at(path, self.bs0, len(v0), backend.serial())
        if prev is not None and prev.shape == v0.shape and np.array_equal(prev, v0):
            self.b0, self.b1 = self.b1, self.b0
            self.n0, self.n1 = self.n1, self.n0
        else:
            K.copy_in(v0, self.b0, backend.serial())
            self._normals(self.b0, self.n0)
        self.v0_np, self.v1_np = v0, v1
        # numpy reduces along the first axis of an (N, 3) array ten times slower than along a
        # contiguous row: the motion is reduced transposed (a walking body's frame spent 1.7 ms
        # here, and its grid's bounds 1 ms).
        motion = np.ascontiguousarray((v1 - v0).T, dtype=np.float64)
        # The body's mean motion over the frame: cloth near the torso moves with it
        # (search_kernels.nearest_one's guards).
        self.shift_np = motion.mean(axis=1)
        self.shift = VEC3(*self.shift_np)
        bounds = path_bounds(motion, tangents if self.normals else None, self.shift_np)
        self.travel_sq, relative, bulge = bounds
        self.fastest_travel = float(np.sqrt(self.travel_sq.max()))
        self.relative_travel = relative.astype(NP_REAL)
        self.bulge = bulge.astype(NP_REAL)
        self._at_rest = bool(np.array_equal(v0, v1))
        if self._at_rest:
            K.copy_in(self.b0, self.b1, backend.serial())
            K.copy_in(self.n0, self.n1, backend.serial())
        else:
            K.copy_in(v1, self.b1, backend.serial())
            self._normals(self.b1, self.n1)
        self._build_grid()

    def set_fold(self, blob: np.ndarray | None) -> None:
        """The coming frame's fold fields (FoldFields.blob), None outside a fold: the part
        guard's lookup of folding parts (search_kernels.fold_near)."""
        if blob is None:
            if self.fold_np.shape[0] == 1 and self.fold_np[0] == 0.0:
                return
            blob = np.zeros(1)
        self.fold_np = np.asarray(blob, dtype=NP_REAL)
        if self.fold_nd.shape[0] != self.fold_np.shape[0]:
            self.fold_nd = ti.ndarray(REAL, self.fold_np.shape[0])
        self.fold_nd.from_numpy(self.fold_np)

    def _normals(self, b, n) -> None:
        """Area-weighted vertex normals n of the body at positions b (both on the device)."""
        if not self.normals:
            return
        if self.vertex_faces is None:
            CK.vertex_normals(b, self.faces, n)
        else:
            PK.vertex_normals_gathered(b, self.faces, *self.vertex_faces, n)

    def _build_grid(self) -> None:
        self.grid_tag = next(_GRID_TAGS)
        GK.collider_bounds(self.b0, self.b1, self.shift, self.used, self.box, backend.serial())
        # A cell's margin, and the path's widest departure from the chords (path_bounds).
        margin = self.cell + self.widest_bulge
        lo, hi = self.box[0] - margin, self.box[1] + margin
        dims = np.maximum(np.ceil((hi - lo) / self.cell).astype(np.int64), 1)
        n_cells = int(np.prod(dims))
        self.hashed = n_cells > DENSE_GRID_CELLS
        if self.hashed:
            n_cells = self.hash_buckets
            dims = np.array([0, n_cells - 1, 0], dtype=np.int64)  # grid_kernels.grid_cell
        self.n_cells = n_cells
        self.origin = VEC3(*lo.astype(NP_REAL))
        self.origin_np = lo.astype(np.float64)
        self.inv_cell = float(1.0 / self.cell)
        self.dims = ti.math.ivec3(*dims.astype(np.int32))
        self.dims_np = dims.astype(np.int32)
        self._fill(self.swept, self.b0, self.b1, VEC3(0.0, 0.0, 0.0), self.shift, self.bulge)

    def _end_grid(self) -> TriangleGrid:
        """The grid of the triangles' boxes at the frame's end (the swept one where the body
        is at rest over the frame), built once per frame."""
        if self._at_rest:
            return self.swept
        if self.end.tag != self.grid_tag:
            self._fill(self.end, self.b1, self.b1, self.shift, self.shift, self.no_bulge)
        return self.end

    def _fill(self, grid: TriangleGrid, b0, b1, shift0, shift1, bulge: np.ndarray) -> None:
        """File the triangles' boxes swept from b0 - shift0 to b1 - shift1, each grown by its
        vertices' `bulge`, into `grid` (this frame's cells, in coordinates that move with the
        body's mean motion: grid_kernels.count_triangle), growing its arrays where they are
        short."""
        n_cells = self.n_cells
        grid.tag = self.grid_tag
        grid.reserve_cells(n_cells, block_sums=not backend.serial())
        if backend.serial():
            # The grid in one launch (grid_kernels.grid_build_serial), again with a longer `items`
            # when it did not fit.
            grid.reserve_items(4 * len(self.faces_np), spare=1.0)  # a first guess, kept after
            args = (b0, b1, shift0, shift1, self.faces, self.mask, self.origin, self.inv_cell,
                    self.dims, n_cells, grid.counts, self.relative_travel, bulge, grid.tbox,
                    grid.starts)
            total = GK.grid_build_serial(*args, grid.items)
            if grid.reserve_items(total):
                GK.grid_build_serial(*args, grid.items)
            return
        # Parallel backends from here: the kernels' `serialize` flags are False (a test runs
        # these three kernels serialized to compare them with the one-launch serial grid).
        GK.grid_count(b0, b1, shift0, shift1, self.faces, self.mask, self.origin, self.inv_cell,
                     self.dims, grid.counts, self.relative_travel, bulge, grid.tbox, False)
        GK.grid_prefix(grid.counts, grid.starts, n_cells, grid.block_starts)
        grid.reserve_items(int(grid.starts[n_cells]))
        GK.grid_fill(self.mask, grid.tbox, self.origin, self.inv_cell, self.dims, grid.counts,
                    grid.starts, grid.items, False)
        GK.grid_sort(grid.starts, grid.items, n_cells)
        # grid_fill used counts as cursors; they must be zero for the next frame's counting.
        grid.counts.fill(0)

    def signed_distance(self, x: np.ndarray | ti.Ndarray, hint: ti.Ndarray | None = None,
                        within: float | None = None) -> np.ndarray:
        """Signed distance of points (N, 3) to the collider surface at the end of the current
        frame (positive outside), each by its closest triangle within `within` (default and
        at most a grid cell): beyond it, `within` outside and `-within` inside (by the winding
        of a closed collider). A caller that needs only which side points are on and whether
        they are deeper than some depth passes that depth: the search then scans the one to
        eight cells around a point instead of 27 (the depth QA's kernel: 9 -> 4.3 ms a frame on
        the walking t-shirt). `x` may be a Taichi array of vectors (the solver's positions, read in
        place: a copy in costs about 0.2 ms). `hint` (a Taichi i32 array of N triangles, or
        -1, such as the solver's tracked ones) and the closest triangles of the last call with
        as many points only speed the search up (depth_kernels.grid_signed_distance)."""
        reach, points = self._depth_query(x, within, "signed_distance")
        grid = self._end_grid()
        columns, origin, inv_column, dims = self._column_grid()
        # Without a hint the last call's triangles serve as both (measured twice: harmless).
        DK.grid_signed_distance(points, self._sd_last if hint is None else hint,
                               self._sd_last, self.b1, self.n1, self.faces, self.mask,
                               self.origin, self.inv_cell, self.dims, self.shift,
                               grid.starts, grid.items, grid.tbox, reach,
                               self._sd_out, self.closed, columns.starts, columns.items,
                               columns.boxes, columns.along, origin, inv_column, dims,
                               self._outward, backend.serial())
        return self._sd_out.to_numpy().astype(np.float64)

    def inside_depth(self, x: np.ndarray | ti.Ndarray, hint: ti.Ndarray | None = None,
                     within: float | None = None) -> np.ndarray:
        """How deep inside a closed collider at the end of the current frame each point (N, 3)
        is: -1 outside its volume (the whole mesh's winding number), and inside the distance to
        its closest filed triangle within `within` (default and at most a grid cell), or
        `within` where none is that near. What the depth QA asks (is a vertex inside, and
        deeper than its thickness?) for about half of signed_distance's cost (2026-12-07: 3.2
        against 7.2 ms a frame on the walking t-shirt, 1.0 against 1.9 on the 4k sheet): only
        the few points inside are searched for, in the solver's grid of swept boxes, so no grid
        of the end boxes is built (depth_kernels.grid_inside_depth). Inside is the volume,
        the union of a body's parts: a point inside a part that passes through another is
        inside, whichever part's triangle is nearest. Arguments as signed_distance's."""
        if not self.closed:
            raise ValueError("inside_depth: the collider is not a closed surface, so it has no "
                             "inside (signed_distance signs points by their nearest triangle)")
        reach, points = self._depth_query(x, within, "inside_depth")
        columns, origin, inv_column, dims = self._column_grid()
        grid = self.swept  # the end boxes lie within the swept ones (_fill)
        # Written to a host array, which a CPU kernel writes in place (a device array's read
        # back costs 0.15-0.5 ms a frame in Taichi's Python, a third of the call).
        out = np.empty(x.shape[0], dtype=NP_REAL)
        DK.grid_inside_depth(points, self._sd_last if hint is None else hint, self._sd_last,
                             self.b1, self.faces, self.mask, self.origin, self.inv_cell,
                             self.dims, self.shift, grid.starts, grid.items, grid.tbox, reach,
                             out, columns.starts, columns.items, columns.boxes, columns.along,
                             origin, inv_column, dims, self._outward, backend.serial())
        return out.astype(np.float64)

    def _depth_query(self, x: np.ndarray | ti.Ndarray, within: float | None,
                     caller: str) -> tuple[float, ti.Ndarray]:
        """signed_distance's and inside_depth's reach (checked) and points on the device, with
        the arrays the two keep per number of points (the last call's triangles, the output)."""
        reach = self.cell if within is None else float(within)
        if not 0.0 < reach <= self.cell:
            raise ValueError(f"{caller}: within must be in (0, {self.cell:g}] m (the "
                             f"grid's cell), got {within!r}")
        n = x.shape[0]
        if getattr(self, "_sd_n", None) != n:
            self._sd_n = n
            self._sd_x = None  # made when host points come (the simulator's never do)
            self._sd_last = ti.ndarray(ti.i32, n)
            self._sd_last.fill(-1)
            self._sd_out = ti.ndarray(REAL, n)
        points = x
        if not isinstance(x, ti.Ndarray):
            if self._sd_x is None:
                self._sd_x = ti.ndarray(VEC3, n)
            points = self._sd_x
            points.from_numpy(np.asarray(x, dtype=NP_REAL))
        return reach, points

    def _column_grid(self) -> tuple[TriangleGrid, VEC3, float, ti.math.ivec3]:
        """The whole mesh at the frame's end filed in columns across depth_kernels.RAY_AXIS
        (depth_kernels.column_grid_build), built once per frame, for signed_distance's inside test;
        an empty stand-in where the collider is not closed (the kernel then reads none)."""
        if self._columns is None:
            self._columns = TriangleGrid(tbox=None)
            self._columns.starts = ti.ndarray(ti.i32, 2)
            self._columns.items = ti.ndarray(ti.i32, 1)
            self._columns.starts.fill(0)
            self._columns.along = ti.ndarray(REAL, 2)
            self._columns.boxes = ti.ndarray(KC.GUARD, 1)
        if not self.closed:
            return self._columns, VEC3(0.0, 0.0, 0.0), 1.0, ti.math.ivec3(0, 0, 0)
        if self._columns_at[0] == self.grid_tag:
            return (self._columns, *self._columns_at[1:])
        if self._outward == 0:
            # The mesh's orientation, once: its signed volume (the divergence theorem).
            end = np.asarray(self.v1_np, dtype=np.float64)
            a, b, c = (end[self.faces_np[:, k]] for k in range(3))
            volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
            self._outward = 1 if volume > 0 else -1
        origin, inv_column, dims = self._column_extent()
        self._build_columns(origin, inv_column, dims)
        self._columns_at = (self.grid_tag, origin, inv_column, dims)
        return self._columns, origin, inv_column, dims

    def _column_extent(self) -> tuple[VEC3, float, ti.math.ivec3]:
        """The column grid's corner, inverse column edge and columns along each of its two
        axes, over the body at the frame's end."""
        axes = [(DK.RAY_AXIS + 1) % 3, (DK.RAY_AXIS + 2) % 3]
        # Reduced as rows (set_frames says why).
        rows = np.ascontiguousarray(np.asarray(self.v1_np).T, dtype=np.float64)
        lo = rows.min(axis=1) - COLUMN_CELL
        hi = rows.max(axis=1) + COLUMN_CELL
        column = COLUMN_CELL
        # A batch's lattice of bodies spans metres: columns grow there rather than past
        # DENSE_GRID_CELLS of them.
        while np.prod(np.ceil((hi - lo)[axes] / column)) > DENSE_GRID_CELLS:
            column *= 2.0
        n = np.maximum(np.ceil((hi - lo)[axes] / column).astype(np.int64), 1)
        return VEC3(*lo.astype(NP_REAL)), float(1.0 / column), ti.math.ivec3(int(n[0]),
                                                                              int(n[1]), 0)

    def _build_columns(self, origin: VEC3, inv_column: float, dims: ti.math.ivec3) -> None:
        """File the whole mesh at the frame's end in the columns, growing the arrays where
        they are short."""
        grid = self._columns
        n_cols = int(dims[0] * dims[1])
        grid.reserve_cells(n_cols, block_sums=not backend.serial())
        if grid.along.shape[0] < 2 * grid.n_cells_alloc:
            grid.along = ti.ndarray(REAL, 2 * grid.n_cells_alloc)
        grid.reserve_items(4 * len(self.faces_np), spare=1.0)  # a first guess, kept after
        if grid.tbox is None:
            grid.tbox = ti.ndarray(ti.math.ivec4, len(self.faces_np))  # the build's spans
        if backend.serial():
            args = (self.b1, self.faces, origin, inv_column, dims, grid.counts, grid.starts,
                    grid.tbox, grid.along)
            total = DK.column_grid_build(*args, grid.items, self._column_boxes())
            if grid.reserve_items(total):
                DK.column_grid_build(*args, grid.items, self._column_boxes())
        else:  # as _fill's parallel grid: count, prefix sum, fill
            DK.column_count(self.b1, self.faces, origin, inv_column, dims, grid.counts, grid.tbox,
                            grid.along)
            GK.grid_prefix(grid.counts, grid.starts, n_cols, grid.block_starts)
            grid.reserve_items(int(grid.starts[n_cols]))
            DK.column_fill(self.b1, self.faces, grid.tbox, dims, grid.counts, grid.starts,
                           grid.items, self._column_boxes())

    def _column_boxes(self) -> ti.Ndarray:
        """The column grid's item boxes, as long as its items (which a build may grow)."""
        grid = self._columns
        if grid.boxes.shape[0] != grid.items.shape[0]:
            grid.boxes = ti.ndarray(KC.GUARD, grid.items.shape[0])
        return grid.boxes

    def nearest(self, x, w, tri, s: float, which: int = SK.SEARCH_ALL, guard=None,
                odo: float = 0.0) -> None:
        """Reset the `which` cloth vertices' tracked triangles (search_kernels.SEARCH_ALL,
        SEARCH_UNTRACKED, SEARCH_TRACKED) to the closest one within a grid cell; untracked
        vertices that may not have come near are skipped (`guard` and `odo` as in
        search_kernels.nearest_one)."""
        if guard is None:
            guard = self._scratch_guard(x.shape[0])
        SK.grid_nearest(x, w, self.b0, self.b1, self.faces, self.origin, self.inv_cell,
                       self.dims, self.starts, self.items, float(s), float(self.cell), tri,
                       int(which), guard, float(odo), float(self.grid_tag),
                       self.shift, self.tbox, self.fold_nd, 0)

    def _scratch_guard(self, n: int):
        from datagen.sim.solvers import fresh_guards

        if getattr(self, "_guard_n", None) != n:
            self._guard_n = n
            self._guard = ti.ndarray(KC.GUARD, n)
        self._guard.from_numpy(fresh_guards(n))
        return self._guard

    @property
    def widest_bulge(self) -> float:
        """How far the body's paths stray from their chords in the current frame, at most
        (path_bounds): the grid's extent grows by it."""
        return float(self.bulge.max(initial=0.0))

    @property
    def max_speed(self) -> float:
        """A bound on the body's fastest vertex's speed along its path in the current frame
        (path_bounds), in metres per frame: at least the longest chord."""
        return self.fastest_travel

    def fastest_travel_among(self, vertices: slice) -> float:
        """A bound on how fast the fastest of `vertices` (a scene's body in a batch) moves
        along its path in the current frame (path_bounds), in metres per frame."""
        return float(np.sqrt(self.travel_sq[vertices].max()))
