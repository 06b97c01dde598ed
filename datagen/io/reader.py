"""Reading datasets: a folder of shards (or one shard) as sequences, and a PyTorch Dataset.

`DatasetReader` gives plain numpy dicts per sequence (body, garments, QA) for analysis and export.
`GarmentDataset` serves frames, clips or whole sequences to a `torch.utils.data.DataLoader`.

Item layout of `GarmentDataset` (T = frames in the item: 1 is squeezed away in `frame` mode):

| key | value |
|---|---|
| `sequence` | str, the sequence id |
| `frame` | int64 scalar tensor: the item's first frame |
| `garment_vertices` | (V, 3) / (T, V, 3) float32: the outfit's garments concatenated |
| `garment_faces` | (Tg, 3) int64, indices into the concatenated vertices |
| `garment_template` | (V, 3) float32, the garments' `rest_vertices`, concatenated |
| `garment_offsets` | (G + 1,) int64: garment g owns vertices `offsets[g]:offsets[g + 1]` |
| `garment_face_offsets` | (G + 1,) int64: the same for faces |
| `garment_names`, `garment_types`, `fabrics` | list[str] of length G |
| `fabric_onehot` | (G, 4) float32 in FABRIC_ORDER (all zeros for other fabrics) |
| `fabric_parameters` | list of G dicts: each fabric's values as simulated (docs/fabrics.md) |
| `tightness` | (2,) float32, the outfit's tightness (gamma) |
| `pose` | (72,) / (T, 72) float32, canonical axis-angle pose |
| `trans` | (3,) / (T, 3) float32, pelvis position |
| `shape` | (S,) float32, body shape parameters |
| `gender` | str |
| `body_vertices` | (Vb, 3) / (T, Vb, 3) float32, posed body (`body="vertices"`, the default) |
| `body_faces` | (Tb, 3) int64 (`body="vertices"`) |
| `joints` | (24, 3) / (T, 24, 3) float32 (`body="joints"`) |

Garments are ordered innermost first (by `layer`, then name), the order DeePSD-style models
that treat an outfit as one mesh expect. Items of different sequences differ in vertex counts,
so batch them with `collate_items` (a list) unless every item shares one outfit.
`fabric_parameters` give physics-based losses (PBNS-style) the density, stiffnesses and bending
the data was simulated with; an entry is None in a shard written before they were stored.
"""

from __future__ import annotations

import json
import os
from collections import OrderedDict
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from datagen.errors import InputError
from datagen.io.shard import SHARD_SUFFIX, TMP_SUFFIX, ShardReader, read_positions
from datagen.spec import SceneSpec

# DeePSD's fabric encoding order; fabrics outside it (rubber, user fabrics) encode as zeros.
FABRIC_ORDER: tuple[str, ...] = ("leather", "silk", "denim", "cotton")
MODES = ("frame", "clip", "sequence")
BODY_OPTIONS = ("vertices", "joints", "none")


def fabric_onehot(fabric: str) -> np.ndarray:
    out = np.zeros(len(FABRIC_ORDER), dtype=np.float32)
    if fabric in FABRIC_ORDER:
        out[FABRIC_ORDER.index(fabric)] = 1.0
    return out


def fabric_parameters(garment: h5py.Group) -> dict | None:
    """The garment's fabric values as simulated (@fabric_parameters); None in a shard written
    before they were stored."""
    text = garment.attrs.get("fabric_parameters")
    return None if text is None else json.loads(_text(text))


def shard_paths(path: str | Path) -> list[Path]:
    """The shard files of a dataset folder (sorted; unfinished `.tmp` files are not shards),
    or the one file given."""
    path = Path(path)
    if path.is_dir():
        return sorted(p for p in path.glob("*" + SHARD_SUFFIX) if p.is_file())
    if path.is_file():
        return [path]
    raise InputError(path, None, "a shard file or a dataset folder", "no such file or folder")


def _text(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return [_text(v) for v in value.tolist()]
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    return value


def garment_order(garments: h5py.Group) -> list[str]:
    """Garment names innermost first (layer, then name): the order of concatenated outfits."""
    return sorted(garments, key=lambda n: (int(garments[n].attrs.get("layer", 0)), n))


class DatasetReader:
    """Sequences across the shards of a dataset folder (or one shard file), by id.

    The index (which shard holds which sequence) is built at construction; shards are then
    opened on first use and stay open until `close()` (or the end of a `with` block).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.shards = shard_paths(self.path)
        if not self.shards:
            unfinished = any(self.path.glob("*" + SHARD_SUFFIX + TMP_SUFFIX))
            raise InputError(self.path, None, "a folder with shard files (*.h5)",
                             "only unfinished *.h5.tmp files" if unfinished else "none")
        self._where: dict[str, Path] = {}
        self._rejected: dict[str, Path] = {}
        self._open: dict[Path, ShardReader] = {}
        for shard in self.shards:
            with ShardReader(shard) as reader:
                ids = reader.sequence_ids()
                rejected = sorted(reader.file.get("rejected", {}))
            for sid in ids:
                if sid in self._where:
                    raise InputError(shard, f"sequences/{sid}",
                                     f"a sequence id found in one shard only (also in "
                                     f"{self._where[sid].name})")
                self._where[sid] = shard
            for sid in rejected:
                self._rejected[sid] = shard

    # -- files ---------------------------------------------------------------------------------
    def close(self) -> None:
        for reader in self._open.values():
            reader.close()
        self._open.clear()

    def __enter__(self) -> DatasetReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, seq_id: object) -> bool:
        return seq_id in self._where

    def sequence_ids(self) -> list[str]:
        return sorted(self._where)

    def shard_of(self, seq_id: str) -> Path:
        try:
            return self._where[seq_id]
        except KeyError:
            known = ", ".join(self.sequence_ids()[:5])
            more = ", ..." if len(self._where) > 5 else ""
            if seq_id in self._rejected:
                # A rejected sequence is in a shard, without data: say so and why, rather than
                # let the id look mistyped.
                g = self._rejected_group(seq_id)
                why = f"{_text(g.attrs['stage'])}: {_text(g.attrs['reason'])}"
                raise InputError(self._rejected[seq_id], "sequence",
                                 f"a written sequence (one of {known}{more}); {seq_id} was "
                                 f"rejected ({why})", seq_id) from None
            raise InputError(self.path, "sequence", f"one of {known}{more}", seq_id) from None

    def _shard_reader(self, shard: Path) -> ShardReader:
        if shard not in self._open:
            self._open[shard] = ShardReader(shard)
        return self._open[shard]

    def reader(self, seq_id: str) -> ShardReader:
        return self._shard_reader(self.shard_of(seq_id))

    def _rejected_group(self, seq_id: str) -> h5py.Group:
        """The /rejected group of a sequence the gate rejected."""
        return self._shard_reader(self._rejected[seq_id]).file["rejected"][seq_id]

    def group(self, seq_id: str) -> h5py.Group:
        return self.reader(seq_id).group(seq_id)

    # -- content -------------------------------------------------------------------------------
    def spec(self, seq_id: str) -> SceneSpec:
        return self.reader(seq_id).spec(seq_id)

    def info(self, seq_id: str) -> dict:
        """The sequence's attributes: split, action, fps, frames, timings (parsed)."""
        g = self.group(seq_id)
        out = {k: _text(v) for k, v in g.attrs.items() if k != "spec"}
        if isinstance(out.get("timings"), str):
            out["timings"] = json.loads(out["timings"])
        out["shard"] = str(self.shard_of(seq_id))
        return out

    def body(self, seq_id: str, frames: slice = slice(None), vertices: bool = True) -> dict:
        """Body arrays of the (selected) frames; `vertices` are rebuilt from the skinning data
        when stored so (skip that with vertices=False)."""
        g = self.group(seq_id)["body"]
        out: dict[str, Any] = {
            "poses": g["poses"][frames],
            "trans": g["trans"][frames],
            "shape": g["shape"][()],
            "shape_names": _text(g.attrs["shape_names"]),
            "gender": _text(g.attrs["gender"]),
            "model": _text(g.attrs["model"]),
            "fps": float(g.attrs["fps"]),
            "storage": _text(g.attrs["storage"]),
            "faces": g["faces"][()],
            "rest_vertices": g["rest_vertices"][()],
            "rest_joints": g["rest_joints"][()],
            "part_labels": g["part_labels"][()],
            "part_names": _text(g.attrs["part_names"]),
            "joints": g["joints"][frames],
        }
        if vertices:
            out["vertices"] = self.reader(seq_id).body_vertices(seq_id, frames)
        return out

    def garments(self, seq_id: str, frames: slice = slice(None)) -> dict[str, dict]:
        """name -> garment arrays and attributes, innermost first; `vertices` (F, V, 3) float32
        are decoded when stored quantised."""
        seq = self.group(seq_id)
        if "garments" not in seq:
            return {}
        root = seq["garments"]
        out: dict[str, dict] = {}
        for name in garment_order(root):
            g = root[name]
            item: dict[str, Any] = {
                "faces": g["faces"][()],
                "rest_vertices": g["rest_vertices"][()],
                "start_vertices": g["start_vertices"][()],
                "uv": g["uv"][()] if "uv" in g else None,
                "regions": g["regions"][()] if "regions" in g else None,
                "loops": {role: ds[()] for role, ds in g["loops"].items()} if "loops" in g
                else {},
                "type": _text(g.attrs["type"]),
                "category": _text(g.attrs.get("category", g.attrs["type"])),
                "fabric": _text(g.attrs["fabric"]),
                "fabric_parameters": fabric_parameters(g),
                "tightness": np.asarray(g.attrs["tightness"], dtype=np.float64),
                "layer": int(g.attrs["layer"]),
                "elastic": list(_text(g.attrs.get("elastic", []))),
                "meta": json.loads(_text(g.attrs.get("meta", "{}"))),
            }
            if "vertices" in g:
                item["vertices"] = read_positions(g, "vertices", frames)
            out[name] = item
        return out

    def qa(self, seq_id: str) -> dict[str, np.ndarray]:
        """QA series (F,) by name; empty when the sequence was not simulated."""
        seq = self.group(seq_id)
        return {k: v[()] for k, v in seq["qa"].items()} if "qa" in seq else {}

    def sim_report(self, seq_id: str) -> dict:
        """The simulator's run report as written (solver, steps, effects and their cost,
        retries, escalation, fabrics; docs/shard-format.md); empty when not simulated."""
        seq = self.group(seq_id)
        return json.loads(_text(seq["sim"].attrs["report"])) if "sim" in seq else {}

    def rejected(self) -> dict[str, dict]:
        """id -> stage, reason, frames (first, last; -1 when not tied to frames), shard."""
        out = {}
        for sid, shard in sorted(self._rejected.items()):
            g = self._rejected_group(sid)
            out[sid] = {
                "stage": _text(g.attrs["stage"]),
                "reason": _text(g.attrs["reason"]),
                "frames": tuple(int(x) for x in g.attrs["frames"]),
                "spec": SceneSpec.from_json(_text(g.attrs["spec"]), source=str(shard)),
                "shard": str(shard),
            }
        return out


# -- PyTorch -----------------------------------------------------------------------------------
class _SequenceMeta:
    """What the index keeps per sequence: plain values only, so the Dataset pickles cheaply."""

    __slots__ = ("seq_id", "shard", "frames", "split")

    def __init__(self, seq_id: str, shard: str, frames: int, split: str) -> None:
        self.seq_id, self.shard, self.frames, self.split = seq_id, shard, frames, split


def collate_items(items: list[dict]) -> list[dict]:
    """A batch as a list of items (outfits differ in vertex count across sequences)."""
    return items


class _GarmentData:
    """Frames, clips or sequences of simulated garments for training (as `GarmentDataset`, a
    `torch.utils.data.Dataset`; torch is imported only when that name is first used).

    mode: `frame` (one frame per item; every `stride`-th frame, default all), `clip`
    (`clip_length` consecutive frames; clips start every `stride` frames, default
    `clip_length`, i.e. no overlap; a sequence shorter than a clip gives none) or `sequence`
    (all frames of a sequence). body: `vertices` (rebuilt posed body), `joints` or
    `none`. `split` keeps only `train` or `test` sequences; `sequences` a given list of ids.

    Safe with DataLoader workers: the object holds paths and the index only; each process opens
    its own files on first use (the process id is checked, so a handle opened before a fork is
    never used by a worker) and a pickled copy carries no handles.
    """

    def __init__(
        self,
        path: str | Path,
        mode: str = "frame",
        clip_length: int = 8,
        stride: int | None = None,
        body: str = "vertices",
        split: str | None = None,
        sequences: list[str] | None = None,
        static_cache: int = 8,
    ) -> None:
        if mode not in MODES:
            raise InputError(None, "mode", f"one of {', '.join(MODES)}", mode)
        if body not in BODY_OPTIONS:
            raise InputError(None, "body", f"one of {', '.join(BODY_OPTIONS)}", body)
        if clip_length < 1:
            raise InputError(None, "clip_length", "1 or more frames", clip_length)
        if stride is not None and stride < 1:
            raise InputError(None, "stride", "1 or more frames", stride)
        self.path = str(path)
        self.mode = mode
        self.clip_length = clip_length if mode == "clip" else 1
        self.stride = stride or self.clip_length
        self.body = body
        self.static_cache = static_cache
        wanted = set(sequences) if sequences is not None else None
        self.meta: list[_SequenceMeta] = []
        for shard in shard_paths(path):
            # Metadata only: sequence attributes, no dataset is read.
            with ShardReader(shard) as reader:
                for sid in reader.sequence_ids():
                    g = reader.group(sid)
                    if wanted is not None and sid not in wanted:
                        continue
                    garments = g.get("garments")
                    if not garments or not all("vertices" in garments[n] for n in garments):
                        continue  # a body-only or unsimulated sequence
                    seq_split = _text(g.attrs["split"])
                    if split is not None and seq_split != split:
                        continue
                    self.meta.append(_SequenceMeta(sid, str(shard), int(g.attrs["frames"]),
                                                   seq_split))
        self.meta.sort(key=lambda m: m.seq_id)
        # (sequence index, first frame) per item, as one array: a list of millions of tuples
        # would be copied page by page into every worker as their reference counts change.
        starts = []
        for k, m in enumerate(self.meta):
            first = [0] if mode == "sequence" else range(0, m.frames - self.clip_length + 1,
                                                          self.stride)
            starts.append(np.array([(k, f) for f in first], dtype=np.int64).reshape(-1, 2))
        self.items = np.concatenate(starts) if starts else np.zeros((0, 2), np.int64)
        self._pid: int | None = None
        self._files: dict[str, ShardReader] = {}
        self._inherited: list[ShardReader] = []
        self._static: OrderedDict[str, dict] = OrderedDict()

    # -- per-process file handles ---------------------------------------------------------------
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.update(_pid=None, _files={}, _static=OrderedDict(), _inherited=[])
        return state

    def _reader(self, shard: str) -> ShardReader:
        pid = os.getpid()
        if self._pid != pid:
            # A forked worker inherits the parent's handles: leave them alone (closing them
            # here would run HDF5 on state shared with the parent) and open its own.
            self._inherited += self._files.values()
            self._files, self._static, self._pid = {}, OrderedDict(), pid
        if shard not in self._files:
            self._files[shard] = ShardReader(shard)
        return self._files[shard]

    def close(self) -> None:
        """Close this process's files (they reopen on the next item)."""
        if self._pid == os.getpid():
            for reader in self._files.values():
                reader.close()
        self._files = {}
        self._static = OrderedDict()

    # -- items ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.items)

    def _statics(self, m: _SequenceMeta) -> dict:
        """Per-sequence arrays that do not change over frames, cached for a few sequences."""
        if m.seq_id in self._static:
            self._static.move_to_end(m.seq_id)
            return self._static[m.seq_id]
        import torch

        g = self._reader(m.shard).group(m.seq_id)
        root = g["garments"]
        names = garment_order(root)
        faces, templates, offsets, face_offsets = [], [], [0], [0]
        for name in names:
            gg = root[name]
            faces.append(gg["faces"][()].astype(np.int64) + offsets[-1])
            templates.append(gg["rest_vertices"][()])
            offsets.append(offsets[-1] + len(templates[-1]))
            face_offsets.append(face_offsets[-1] + len(faces[-1]))
        fabrics = [_text(root[n].attrs["fabric"]) for n in names]
        tightness = np.asarray(root[names[0]].attrs["tightness"], dtype=np.float32)
        b = g["body"]
        static = {
            "names": names,
            "garment_faces": torch.from_numpy(np.concatenate(faces)),
            "garment_template": torch.from_numpy(np.concatenate(templates).astype(np.float32)),
            "garment_offsets": torch.tensor(offsets, dtype=torch.int64),
            "garment_face_offsets": torch.tensor(face_offsets, dtype=torch.int64),
            "garment_types": [_text(root[n].attrs["type"]) for n in names],
            "fabrics": fabrics,
            "fabric_onehot": torch.from_numpy(np.stack([fabric_onehot(f) for f in fabrics])),
            "fabric_parameters": [fabric_parameters(root[n]) for n in names],
            "tightness": torch.from_numpy(tightness),
            "shape": torch.from_numpy(b["shape"][()].astype(np.float32)),
            "gender": _text(b.attrs["gender"]),
        }
        if self.body == "vertices":
            static["body_faces"] = torch.from_numpy(b["faces"][()].astype(np.int64))
        self._static[m.seq_id] = static
        while len(self._static) > self.static_cache:
            self._static.popitem(last=False)
        return static

    def __getitem__(self, index: int) -> dict:
        import torch

        k, first = (int(x) for x in self.items[index])
        m = self.meta[k]
        count = m.frames if self.mode == "sequence" else self.clip_length
        frames = slice(first, first + count)
        reader = self._reader(m.shard)
        g = reader.group(m.seq_id)
        static = self._statics(m)
        squeeze = self.mode == "frame"

        def tensor(a: np.ndarray) -> torch.Tensor:
            a = np.asarray(a, dtype=np.float32)
            return torch.from_numpy(a[0] if squeeze else a)

        garments = g["garments"]
        positions = np.concatenate(
            [read_positions(garments[n], "vertices", frames) for n in static["names"]], axis=1
        )
        item: dict[str, Any] = {
            "sequence": m.seq_id,
            "frame": torch.tensor(first, dtype=torch.int64),
            "garment_vertices": tensor(positions),
            "garment_names": list(static["names"]),
            "pose": tensor(g["body"]["poses"][frames]),
            "trans": tensor(g["body"]["trans"][frames]),
        }
        item.update({k: v for k, v in static.items() if k != "names"})
        if self.body == "vertices":
            item["body_vertices"] = tensor(reader.body_vertices(m.seq_id, frames))
        elif self.body == "joints":
            item["joints"] = tensor(g["body"]["joints"][frames])
        return item

    def describe(self) -> str:
        return (f"GarmentDataset({self.path!r}, mode={self.mode}, {len(self.meta)} sequences, "
                f"{len(self.items)} items)")

    __repr__ = describe


def __getattr__(name: str) -> Any:
    # GarmentDataset subclasses torch's Dataset, built on first use so that the CLI commands
    # that only read shards do not pay for importing torch. Pickle finds it by this name.
    if name == "GarmentDataset":
        from torch.utils.data import Dataset

        cls = type("GarmentDataset", (_GarmentData, Dataset), {"__module__": __name__})
        cls.__doc__ = _GarmentData.__doc__
        globals()["GarmentDataset"] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
