"""Exports of simulated sequences: OBJ per frame, PC2 point caches, PLY.

PC2 is the point cache CLOTH3D shipped (header `POINTCACHE2\\0`, version 1, point count, start
frame, sample rate, sample count, then float32 xyz per point per sample); Blender's Mesh Cache
modifier plays it on an OBJ of the same mesh imported with "Keep Vert Order".
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

PC2_HEADER = struct.Struct("<12siiffi")


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    path = Path(path)
    lines = ["# datagen export"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, np.float64)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces, np.int64)]
    path.write_text("\n".join(lines) + "\n")


def write_obj_sequence(directory: str | Path, name: str, frames: np.ndarray,
                       faces: np.ndarray) -> list[Path]:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for f, v in enumerate(frames):
        p = directory / f"{name}_{f:04d}.obj"
        write_obj(p, v, faces)
        paths.append(p)
    return paths


def write_pc2(path: str | Path, frames: np.ndarray, fps: float = 30.0, start: float = 0.0) -> None:
    frames = np.asarray(frames, dtype="<f4")
    n_samples, n_points, _ = frames.shape
    with open(path, "wb") as f:
        f.write(PC2_HEADER.pack(b"POINTCACHE2\0", 1, n_points, float(start), 1.0, n_samples))
        f.write(frames.tobytes())
    del fps  # PC2 stores frames, not seconds: one sample per frame


def read_pc2(path: str | Path) -> np.ndarray:
    data = Path(path).read_bytes()
    magic, version, n_points, _start, _rate, n_samples = PC2_HEADER.unpack_from(data, 0)
    if magic != b"POINTCACHE2\0" or version != 1:
        raise ValueError(f"{path}: not a PC2 file")
    body = np.frombuffer(data, dtype="<f4", offset=PC2_HEADER.size)
    return body.reshape(n_samples, n_points, 3).copy()


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY (float32 vertices, int32 triangles)."""
    v = np.asarray(vertices, dtype="<f4")
    f = np.asarray(faces, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment datagen export\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    rows = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    rows["n"] = 3
    rows["idx"] = f
    with open(path, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(v.tobytes())
        out.write(rows.tobytes())
