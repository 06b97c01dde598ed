"""Linear blend skinning shared by the body stage and the shard reader.

Both call this one function so that a shard's body rebuilds bit-for-bit what the pipeline
simulated against (same operations in the same order, float64, cast to float32 at the end).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from datagen.types import LinearSkinning

_FRAME_CHUNK = 32  # bounds the (V, 12 * chunk) float64 temporary to ~40 MB for 13k vertices


def skinning_matrix(weights: np.ndarray, bones: np.ndarray, n_bones: int) -> sp.csr_matrix:
    """(V, B) sparse matrix of blend weights."""
    n_vertices, k = weights.shape
    rows = np.repeat(np.arange(n_vertices), k)
    w = weights.astype(np.float64).ravel()
    keep = w != 0.0
    return sp.csr_matrix((w[keep], (rows[keep], bones.ravel()[keep])), shape=(n_vertices, n_bones))


def apply_linear_skinning(skin: LinearSkinning) -> np.ndarray:
    """Posed vertices (F, V, 3) float32 from rest vertices, blend weights and bone transforms."""
    transforms = np.asarray(skin.transforms, dtype=np.float64)
    n_frames, n_bones = transforms.shape[:2]
    matrix = skinning_matrix(skin.weights, skin.bones, n_bones)
    rest = np.asarray(skin.rest_vertices, dtype=np.float64)
    n_vertices = rest.shape[0]
    out = np.empty((n_frames, n_vertices, 3), dtype=np.float32)
    for start in range(0, n_frames, _FRAME_CHUNK):
        stop = min(start + _FRAME_CHUNK, n_frames)
        chunk = transforms[start:stop]  # (C, B, 3, 4)
        c = stop - start
        # Blend the 3x4 transforms per vertex: (V, B) @ (B, C*12) -> (V, C, 3, 4).
        flat = np.ascontiguousarray(chunk.transpose(1, 0, 2, 3).reshape(n_bones, c * 12))
        blended = (matrix @ flat).reshape(n_vertices, c, 3, 4)
        posed = np.einsum("vcij,vj->cvi", blended[..., :3], rest) + blended[..., 3].transpose(
            1, 0, 2
        )
        out[start:stop] = posed.astype(np.float32)
    return out


def apply_sparse_offsets(
    vertices: np.ndarray, frames: np.ndarray, indices: np.ndarray, offsets: np.ndarray
) -> None:
    """Add per-(frame, vertex) offsets in place (the self-collision repair)."""
    if len(frames):
        np.add.at(vertices, (frames, indices), offsets.astype(np.float32))
