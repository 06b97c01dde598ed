"""The moving body as a collider: triangles (masked to the parts a garment can reach), their
edge adjacency for surface tracking, per-frame vertex normals, and a uniform grid for the global
closest-triangle search."""

from __future__ import annotations

import numpy as np
import taichi as ti

from datagen.sim import kernels as K
from datagen.sim.backend import init_taichi
from datagen.sim.precision import NP_REAL, VEC3


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3) of one frame."""
    t = vertices[faces]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        for c in range(3):
            n[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=len(vertices))
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.maximum(norm, 1e-20)).astype(NP_REAL)


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


class BodyCollider:
    """Holds the body's frames on the device; one instance per scene."""

    def __init__(
        self, faces: np.ndarray, face_mask: np.ndarray, n_vertices: int, cell: float = 0.025
    ) -> None:
        init_taichi()
        self.faces_np = np.asarray(faces, dtype=np.int32)
        self.mask_np = np.asarray(face_mask, dtype=bool)
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
        self._n_cells_alloc = 0
        self.counts = self.starts = self.items = None
        self._items_alloc = 0
        self._prev = None

    def set_frames(self, v0: np.ndarray, v1: np.ndarray, nrm0=None, nrm1=None) -> None:
        """Body positions at the start and end of the coming frame (interpolated in between)."""
        self.v0_np = np.asarray(v0, dtype=NP_REAL)
        self.v1_np = np.asarray(v1, dtype=NP_REAL)
        self.b0.from_numpy(self.v0_np)
        self.b1.from_numpy(self.v1_np)
        if nrm0 is None:
            nrm0 = vertex_normals(self.v0_np, self.faces_np)
        if nrm1 is None:
            nrm1 = vertex_normals(self.v1_np, self.faces_np)
        self.n0.from_numpy(nrm0)
        self.n1.from_numpy(nrm1)
        self._build_grid()

    def _build_grid(self) -> None:
        used = self.faces_np[self.mask_np]
        pts = np.concatenate([self.v0_np[used.ravel()], self.v1_np[used.ravel()]])
        lo = pts.min(axis=0) - self.cell
        hi = pts.max(axis=0) + self.cell
        dims = np.maximum(np.ceil((hi - lo) / self.cell).astype(np.int64), 1)
        n_cells = int(np.prod(dims))
        if n_cells + 1 > self._n_cells_alloc:
            self._n_cells_alloc = int((n_cells + 1) * 1.5)
            self.counts = ti.ndarray(ti.i32, self._n_cells_alloc)
            self.starts = ti.ndarray(ti.i32, self._n_cells_alloc + 1)
            self.counts.fill(0)
        self.origin = VEC3(*lo.astype(NP_REAL))
        self.inv_cell = float(1.0 / self.cell)
        self.dims = ti.math.ivec3(*dims.astype(np.int32))
        K.grid_count(
            self.b0,
            self.b1,
            self.faces,
            self.mask,
            self.origin,
            self.inv_cell,
            self.dims,
            self.counts,
        )
        K.grid_prefix(self.counts, self.starts, n_cells)
        total = int(self.starts[n_cells])
        if total > self._items_alloc:
            self._items_alloc = int(total * 1.5) + 16
            self.items = ti.ndarray(ti.i32, self._items_alloc)
        K.grid_fill(
            self.b0,
            self.b1,
            self.faces,
            self.mask,
            self.origin,
            self.inv_cell,
            self.dims,
            self.counts,
            self.starts,
            self.items,
        )
        # grid_fill used counts as cursors; they must be zero for the next frame's counting.
        self.counts.fill(0)

    def nearest(self, x, w, tri, s: float, only_untracked: bool = False) -> None:
        """Reset each cloth vertex's tracked triangle to the closest one within a grid cell
        (or only find one for vertices that track none)."""
        K.grid_nearest(
            x,
            w,
            self.b0,
            self.b1,
            self.faces,
            self.origin,
            self.inv_cell,
            self.dims,
            self.starts,
            self.items,
            float(s),
            float(self.cell),
            tri,
            int(only_untracked),
        )
