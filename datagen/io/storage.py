"""Storage figures of garment positions: bytes on disk per vertex per frame, and the error of
quantised storage against lossless storage of the same data.

`get_storage_size()` is what HDF5 allocated for a dataset's chunks after compression, so the
figures are what a dataset costs on disk (group and attribute overhead excluded).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from datagen.io.reader import shard_paths
from datagen.io.shard import read_positions


@dataclass
class PositionStorage:
    """Garment positions of one shard (or a dataset's shards)."""

    bytes: int  # on disk, after compression
    vertex_frames: int  # sum over garments of frames x vertices
    quantized: int  # garments stored as int16
    lossless: int  # garments stored as float32

    @property
    def bytes_per_vertex_frame(self) -> float:
        return self.bytes / self.vertex_frames if self.vertex_frames else float("nan")


def position_storage(path: str | Path) -> PositionStorage:
    """Sums over every garment `vertices` dataset of a shard or a dataset folder."""
    total = PositionStorage(0, 0, 0, 0)
    for shard in shard_paths(path):
        with h5py.File(shard, "r") as f:
            for seq in f["sequences"].values():
                for garment in seq.get("garments", {}).values():
                    if "vertices" not in garment:
                        continue
                    ds = garment["vertices"]
                    total.bytes += ds.id.get_storage_size()
                    total.vertex_frames += ds.shape[0] * ds.shape[1]
                    if "quantized_step" in ds.attrs:
                        total.quantized += 1
                    else:
                        total.lossless += 1
    return total


def bytes_per_vertex_frame(path: str | Path) -> float:
    """On-disk bytes of garment positions per vertex per frame (raw: 12 lossless, 6 int16)."""
    return position_storage(path).bytes_per_vertex_frame


def quantization_error(lossless: str | Path, quantized: str | Path) -> float:
    """Largest distance along any axis (m) between the positions of two shards, or dataset
    folders, that hold the same sequences: one written lossless, the other quantised."""
    worst = 0.0
    a_files = {p.name: p for p in shard_paths(lossless)}
    b_files = {p.name: p for p in shard_paths(quantized)}
    if len(a_files) == 1 and len(b_files) == 1:  # two single files may have different names
        a_files = {"": next(iter(a_files.values()))}
        b_files = {"": next(iter(b_files.values()))}
    if set(a_files) != set(b_files):
        raise ValueError("the two datasets do not hold the same shards")
    for name, a_path in a_files.items():
        with h5py.File(a_path, "r") as fa, h5py.File(b_files[name], "r") as fb:
            if set(fa["sequences"]) != set(fb["sequences"]):
                raise ValueError(f"{name or a_path}: the shards hold different sequences")
            for sid, seq in fa["sequences"].items():
                for gname, garment in seq.get("garments", {}).items():
                    if "vertices" not in garment:
                        continue
                    other = fb["sequences"][sid]["garments"][gname]
                    d = read_positions(garment, "vertices") - read_positions(other, "vertices")
                    worst = max(worst, float(np.abs(d).max(initial=0.0)))
    return worst
