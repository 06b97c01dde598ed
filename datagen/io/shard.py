"""HDF5 shards: many sequences per file, one group per sequence (docs/shard-format.md).

A shard is written under a temporary name and renamed when complete, so a crash never leaves a
half-written file under a final name. Every dataset carries a SHA-256 of its bytes so that
`datagen validate` can detect corruption.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from datagen.environment import environment
from datagen.errors import InputError
from datagen.skinning import apply_linear_skinning, apply_sparse_offsets
from datagen.spec import SceneSpec
from datagen.types import BodySequence, Garment, LinearSkinning

FORMAT = "datagen-shard"
FORMAT_VERSION = 1
TMP_SUFFIX = ".tmp"
SHARD_SUFFIX = ".h5"  # what a dataset folder's shards end in


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("datagen")
    except Exception:  # noqa: BLE001 - running from a source tree
        return "0+unknown"


def dataset_digest(data: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(data).tobytes()).hexdigest()


def write_array(
    group: h5py.Group, name: str, data: np.ndarray, per_frame: bool = False, **attrs: Any
) -> h5py.Dataset:
    """A dataset with its checksum; per-frame arrays are chunked one frame per chunk and
    compressed (lossless gzip + shuffle)."""
    data = np.asarray(data)
    kwargs: dict[str, Any] = {}
    if per_frame and data.ndim >= 2 and data.shape[0] > 0:
        kwargs = dict(
            chunks=(1,) + data.shape[1:], compression="gzip", compression_opts=4, shuffle=True
        )
    elif data.size > 4096:
        kwargs = dict(compression="gzip", compression_opts=4, shuffle=True)
    ds = group.create_dataset(name, data=data, **kwargs)
    ds.attrs["sha256"] = dataset_digest(data)
    for k, v in attrs.items():
        ds.attrs[k] = v
    return ds


class ShardWriter:
    """Collects sequences into one shard file; the file appears under `path` only on close()."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + TMP_SUFFIX)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(self.tmp_path, "w")
        self._file.attrs["format"] = FORMAT
        self._file.attrs["format_version"] = FORMAT_VERSION
        self._file.attrs["datagen_version"] = _version()
        self._file.create_group("sequences")
        self._closed = False

    def sequence_group(self, spec: SceneSpec) -> h5py.Group:
        group = self._file["sequences"].create_group(spec.sequence_id)
        group.attrs["spec"] = spec.to_json()
        group.attrs["split"] = spec.split
        return group

    def add_body(self, group: h5py.Group, body: BodySequence, store_vertices: bool = False) -> None:
        write_body(group, body, store_vertices)

    def close(self) -> Path:
        """Flush and move the file to its final name."""
        if not self._closed:
            self._file.close()
            os.replace(self.tmp_path, self.path)
            self._closed = True
        return self.path

    def abort(self) -> None:
        if not self._closed:
            self._file.close()
            self.tmp_path.unlink(missing_ok=True)
            self._closed = True

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_body(group: h5py.Group, body: BodySequence, store_vertices: bool = False) -> None:
    """The body of a sequence, lead-in frames excluded (they exist only to start the cloth)."""
    start = body.lead_in_frames
    g = group.create_group("body")
    rest = body.rest
    g.attrs["model"] = rest.model
    g.attrs["gender"] = rest.gender
    g.attrs["shape_names"] = list(rest.shape_names)
    g.attrs["part_names"] = list(rest.part_names)
    g.attrs["action"] = body.action
    g.attrs["motion_source"] = body.motion_source
    g.attrs["fps"] = body.fps
    g.attrs["lead_in_frames"] = body.lead_in_frames
    g.attrs["self_collision"] = json.dumps(body.self_collision.as_dict(), sort_keys=True)
    group.attrs["action"] = body.action
    group.attrs["fps"] = body.fps
    group.attrs["frames"] = body.n_frames - start
    write_array(g, "poses", body.poses[start:].astype(np.float64))
    write_array(g, "trans", body.trans[start:].astype(np.float64))
    write_array(g, "shape", np.asarray(rest.shape, dtype=np.float64))
    write_array(g, "faces", rest.faces.astype(np.int32))
    write_array(g, "rest_vertices", rest.vertices.astype(np.float32))
    write_array(g, "rest_joints", rest.joints.astype(np.float32))
    write_array(g, "part_labels", rest.part_labels.astype(np.int16))
    write_array(g, "collider_face_mask", body.collider_face_mask.astype(bool))
    write_array(g, "joints", body.joints[start:].astype(np.float32), per_frame=True)
    keep = body.repair_frames >= start
    if body.skinning is not None and not store_vertices:
        g.attrs["storage"] = "skinning"
        skin = body.skinning
        s = g.create_group("skinning")
        write_array(s, "rest_vertices", skin.rest_vertices.astype(np.float64))
        write_array(s, "weights", skin.weights.astype(np.float32))
        write_array(s, "bones", skin.bones.astype(np.int32))
        write_array(s, "transforms", skin.transforms[start:].astype(np.float32), per_frame=True)
        write_array(s, "repair_frame", (body.repair_frames[keep] - start).astype(np.int32))
        write_array(s, "repair_vertex", body.repair_vertices[keep].astype(np.int32))
        write_array(s, "repair_offset", body.repair_offsets[keep].astype(np.float32))
    else:
        g.attrs["storage"] = "vertices"
        write_array(g, "vertices", body.vertices[start:].astype(np.float32), per_frame=True)


def h5py_reason(exc: BaseException) -> str:
    """The reason inside an h5py error ("Unable to synchronously open file (reason)")."""
    text = str(exc)
    if "(" in text and text.endswith(")"):
        text = text[text.index("(") + 1:-1]
    return text or type(exc).__name__


def unreadable_reason(exc: BaseException) -> str:
    """Why h5py could not open a shard, in words: a truncated file says how much of it is
    there; anything else, h5py's reason and what it usually means."""
    text = h5py_reason(exc)
    sizes = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", text)
    if sizes:
        return f"truncated, {sizes[1]} of {sizes[2]} bytes (an interrupted copy or a full disk?)"
    return f"{text} (not an HDF5 file, or a damaged one)"


class ShardReader:
    """Read access to one shard; checks the format on open."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, None, "an existing shard file", "no such file")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise InputError(self.path, None, "a readable HDF5 shard", unreadable_reason(exc)
                             ) from None
        fmt = self._file.attrs.get("format")
        if fmt != FORMAT:
            self._file.close()
            raise InputError(self.path, "format", f"'{FORMAT}'", fmt)
        version = int(self._file.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            self._file.close()
            raise InputError(
                self.path, "format_version", f"{FORMAT_VERSION} (this datagen)", version
            )

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ShardReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def file(self) -> h5py.File:
        return self._file

    def sequence_ids(self) -> list[str]:
        return sorted(self._file["sequences"].keys())

    def group(self, seq_id: str) -> h5py.Group:
        try:
            return self._file["sequences"][seq_id]
        except KeyError:
            raise InputError(
                self.path, f"sequences/{seq_id}", "an existing sequence", "missing"
            ) from None

    def spec(self, seq_id: str) -> SceneSpec:
        return SceneSpec.from_json(self.group(seq_id).attrs["spec"], source=str(self.path))

    def body_vertices(self, seq_id: str, frames: slice | None = None) -> np.ndarray:
        """Posed body vertices (F, V, 3) float32, rebuilt from skinning when stored so."""
        g = self.group(seq_id)["body"]
        frames = frames or slice(None)
        if g.attrs["storage"] == "vertices":
            return g["vertices"][frames]
        s = g["skinning"]
        transforms = s["transforms"][frames].astype(np.float64)
        skin = LinearSkinning(
            rest_vertices=s["rest_vertices"][()],
            weights=s["weights"][()],
            bones=s["bones"][()],
            transforms=transforms,
        )
        vertices = apply_linear_skinning(skin)
        first = range(len(g["poses"]))[frames]
        rf, rv, ro = s["repair_frame"][()], s["repair_vertex"][()], s["repair_offset"][()]
        if len(rf):
            sel = np.isin(rf, np.asarray(first))
            index = {f: i for i, f in enumerate(first)}
            local = np.array([index[f] for f in rf[sel]], dtype=np.int64)
            apply_sparse_offsets(vertices, local, rv[sel], ro[sel])
        return vertices


@contextmanager
def open_shard(path: str | Path) -> Iterator[ShardReader]:
    reader = ShardReader(path)
    try:
        yield reader
    finally:
        reader.close()


def describe(path: str | Path) -> dict:
    """Everything a shard holds, as plain data: attributes, and per dataset its shape and dtype."""

    def attrs_of(obj) -> dict:
        out = {}
        for k, v in obj.attrs.items():
            if isinstance(v, np.ndarray):
                v = v.tolist()
            elif isinstance(v, (np.integer, np.floating, np.bool_)):
                v = v.item()
            elif isinstance(v, bytes):
                v = v.decode()
            if k == "spec" and isinstance(v, str):
                v = json.loads(v)
            out[k] = v
        return out

    def walk(group: h5py.Group) -> dict:
        node: dict[str, Any] = {"attrs": attrs_of(group), "groups": {}, "datasets": {}}
        for name, item in group.items():
            if isinstance(item, h5py.Group):
                node["groups"][name] = walk(item)
            else:
                node["datasets"][name] = {
                    "shape": list(item.shape),
                    "dtype": str(item.dtype),
                    "attrs": {k: v for k, v in attrs_of(item).items() if k != "sha256"},
                }
        return node

    with open_shard(path) as reader:
        tree = walk(reader.file)
        tree["file"] = str(path)
        tree["sequences"] = reader.sequence_ids()
    return tree


# -- garments, simulation report, QA, rejections ----------------------------------------------
QUANT_STEP = 1e-4  # m: quantised positions are multiples of this relative to the pelvis


def write_positions(group: h5py.Group, name: str, positions: np.ndarray,
                    reference: np.ndarray | None, quantize: bool) -> None:
    """Per-frame positions (F, V, 3): float32 (lossless), or int16 multiples of QUANT_STEP
    relative to a per-frame reference point (the pelvis), max error QUANT_STEP / 2."""
    positions = np.asarray(positions, dtype=np.float32)
    if not quantize:
        write_array(group, name, positions, per_frame=True)
        return
    ref = np.zeros((len(positions), 3)) if reference is None else np.asarray(reference)
    rel = (positions.astype(np.float64) - ref[:, None, :]) / QUANT_STEP
    if np.abs(rel).max() > 32767:
        raise ValueError(f"{name}: a vertex is over 3.2 m from the reference point")
    q = np.round(rel).astype(np.int16)
    write_array(group, name, q, per_frame=True, quantized_step=QUANT_STEP,
                reference="body/trans")


def read_positions(group: h5py.Group, name: str, frames=slice(None)) -> np.ndarray:
    ds = group[name]
    data = ds[frames]
    step = ds.attrs.get("quantized_step")
    if step is None:
        return data
    sequence = group.parent.parent  # /sequences/<id>/garments/<name>
    trans = sequence["body"]["trans"][frames]
    return (data.astype(np.float64) * float(step) + trans[..., None, :]).astype(np.float32)


def garment_type(garment: Garment) -> str:
    """The `type` a garment is written with: its upper-body cut (shirt, polo...) or its
    template's category (spec.OutfitSpec.worn gives the same from a scene spec)."""
    return (garment.meta or {}).get("variant") or garment.category


def write_garments(group: h5py.Group, garments, sim, trans: np.ndarray, quantize: bool) -> None:
    g_root = group.create_group("garments")
    for garment in garments:
        g = g_root.create_group(garment.name)
        g.attrs["type"] = garment_type(garment)
        g.attrs["category"] = garment.category
        g.attrs["fabric"] = garment.fabric
        if sim is not None and garment.fabric in sim.report.get("fabrics", {}):
            g.attrs["fabric_parameters"] = json.dumps(sim.report["fabrics"][garment.fabric],
                                                      sort_keys=True)
        g.attrs["tightness"] = np.asarray(garment.tightness, dtype=np.float64)
        g.attrs["elastic"] = list(garment.elastic)
        g.attrs["layer"] = garment.layer
        g.attrs["meta"] = json.dumps(garment.meta, sort_keys=True)
        write_array(g, "faces", np.asarray(garment.faces, dtype=np.int32))
        write_array(g, "rest_vertices", np.asarray(garment.rest, dtype=np.float32))
        write_array(g, "start_vertices", np.asarray(garment.vertices, dtype=np.float32))
        if garment.uv is not None:
            write_array(g, "uv", np.asarray(garment.uv, dtype=np.float32))
        if garment.regions is not None:
            write_array(g, "regions", np.asarray(garment.regions, dtype=np.int16))
            g.attrs["region_names"] = list(garment.region_names)
        loops = g.create_group("loops")
        for role, ids in garment.loops.items():
            write_array(loops, role, np.asarray(ids, dtype=np.int32))
        if sim is not None:
            write_positions(g, "vertices", sim.vertices[garment.name], trans, quantize)
    if sim is not None:
        s = group.create_group("sim")
        s.attrs["report"] = json.dumps(sim.report, sort_keys=True, default=float)
        for key in ("solver", "quality", "substeps", "iterations", "retries", "wall_time_s"):
            s.attrs[key] = sim.report[key]
        s.attrs["effects"] = list(sim.report["effects"])
        qa = group.create_group("qa")
        for name, series in sim.qa.items():
            write_array(qa, name, np.asarray(series, dtype=np.float32))


def _environment_json(record) -> str:
    """The environment of the worker that made the record (datagen.environment); this
    process's for a record that carries none (one built by hand, not by run_sequence)."""
    return json.dumps(record.environment or environment(), sort_keys=True)


def write_record(writer: ShardWriter, record, store_body_vertices: bool = False,
                 quantize: bool = False) -> None:
    """A finished sequence (its group) or a rejection (under /rejected, with the reason)."""
    if record.status != "ok":
        rej = writer._file.require_group("rejected").create_group(record.spec.sequence_id)
        rej.attrs["spec"] = record.spec.to_json()
        rej.attrs["stage"] = record.stage or ""
        rej.attrs["reason"] = record.reason or ""
        rej.attrs["frames"] = np.asarray(record.frames if record.frames else (-1, -1))
        rej.attrs["timings"] = json.dumps(record.timings, sort_keys=True)
        rej.attrs["environment"] = _environment_json(record)
        return
    group = writer.sequence_group(record.spec)
    group.attrs["timings"] = json.dumps(record.timings, sort_keys=True)
    group.attrs["environment"] = _environment_json(record)
    write_body(group, record.body, store_body_vertices)
    if record.garments:
        trans = record.body.trans[record.body.lead_in_frames:]
        write_garments(group, record.garments, record.sim, trans, quantize)
