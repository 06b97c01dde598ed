"""Synthetic shards for the reader, validator and export tests, without the simulator or a body
model: a small tube-shaped "body" skinned to a few bones, one or two tube garments around it that
follow the body with a smooth ripple, QA series in the ranges the simulator produces. Everything
is written through the real ShardWriter + write_record, so the files are what a run writes.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import h5py
import numpy as np

from datagen.body.parts import PART_NAMES
from datagen.io.shard import ShardWriter, write_record
from datagen.pipeline.stages import SequenceRecord
from datagen.sim.fabrics import FABRICS
from datagen.skinning import apply_linear_skinning, apply_sparse_offsets
from datagen.spec import GarmentSpec, MotionSpec, OutfitSpec, SceneSpec
from datagen.types import (
    BodySequence,
    Garment,
    LinearSkinning,
    RestBody,
    SelfCollisionReport,
    SimResult,
)

SEED = 7
SHAPE_NAMES = ("age", "muscle", "weight", "height", "proportions")
QA_SERIES = ("strain_mean", "strain_max", "strain_p999", "over_strain_share", "inside_share",
             "deep_share", "kinetic_energy")
N_BONES = 5
# name -> (category/variant, fabric, layer, radius, z range)
GARMENTS = {
    "upper": ("tshirt", "cotton", 1, 0.19, (0.95, 1.45)),
    "lower": ("trousers", "denim", 0, 0.18, (0.35, 1.00)),
}


def tube(radius: float, z0: float, z1: float, rings: int, segments: int,
         capped: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder grid (rings x segments vertices) with outward-facing triangles; `capped`
    closes both ends with a fan around a centre vertex."""
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    z = np.linspace(z0, z1, rings)
    # A body-like waist: the radius narrows a little in the middle.
    r = radius * (1.0 - 0.15 * np.sin(np.linspace(0.0, np.pi, rings)))
    v = np.stack([
        (r[:, None] * np.cos(angle)[None, :]).ravel(),
        (r[:, None] * np.sin(angle)[None, :]).ravel(),
        np.repeat(z, segments),
    ], axis=1)
    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [(a, b, d), (a, d, c)]
    if capped:
        bottom, top = len(v), len(v) + 1
        v = np.concatenate([v, [[0.0, 0.0, z0], [0.0, 0.0, z1]]])
        last = (rings - 1) * segments
        for j in range(segments):
            faces.append((bottom, (j + 1) % segments, j))
            faces.append((top, last + j, last + (j + 1) % segments))
    return v, np.asarray(faces, dtype=np.int32)


def _rotation_z(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    rot = np.zeros(angle.shape + (3, 3))
    rot[..., 0, 0], rot[..., 0, 1], rot[..., 1, 0], rot[..., 1, 1] = c, -s, s, c
    rot[..., 2, 2] = 1.0
    return rot


@dataclass
class SyntheticSequence:
    """One sequence's record plus what the tests compare against."""

    record: SequenceRecord
    frames: int
    lead_in: int
    body_vertices: np.ndarray  # (F, V, 3) float32, output frames only


def make_record(index: int, frames: int = 10, lead_in: int = 3,
                garments: tuple[str, ...] = ("upper", "lower"), seed: int = SEED,
                split: str = "train", noise: float = 2e-4) -> SyntheticSequence:
    """A finished sequence: ~200 body vertices on 5 bones with random weights, sparse repair
    offsets, and per-frame garment positions (a smooth ripple plus Gaussian `noise` in metres,
    standing in for a simulation's fine detail) with QA series."""
    rng = np.random.default_rng(1000 * seed + index)
    n_all = lead_in + frames
    # Body: a capped tube of 10 rings x 20 segments (202 vertices, 400 triangles), 1.7 m tall.
    rest_v, body_faces = tube(0.15, 0.0, 1.7, 10, 20, capped=True)
    n_v = len(rest_v)
    joints_rest = np.stack([np.zeros(24), np.zeros(24), np.linspace(0.1, 1.6, 24)], axis=1)
    rest = RestBody(
        model="anny", gender=("female", "male")[index % 2],
        shape=rng.normal(size=5), shape_names=SHAPE_NAMES, vertices=rest_v, faces=body_faces,
        joints=joints_rest, part_labels=rng.integers(0, 20, n_v).astype(np.int16),
        part_names=PART_NAMES,
    )
    t = np.arange(n_all) / 30.0
    trans = np.stack([0.8 * t, 0.02 * np.sin(4 * t), 0.95 + 0.01 * np.sin(8 * t)], axis=1)
    poses = rng.normal(scale=0.1, size=(n_all, 72))
    # Bones turn a little about z (more for the upper ones) and follow the pelvis.
    turn = 0.2 * np.sin(3 * t)[:, None] * np.linspace(0.2, 1.0, N_BONES)[None, :]
    transforms = np.zeros((n_all, N_BONES, 3, 4))
    transforms[..., :3] = _rotation_z(turn)
    transforms[..., 3] = trans[:, None, :] - np.array([0.0, 0.0, 0.95])
    # As Anny does: rounded to float32 once, because the shard stores them so.
    transforms = transforms.astype(np.float32).astype(np.float64)
    k = 3
    bones = np.stack([rng.choice(N_BONES, k, replace=False) for _ in range(n_v)]).astype(np.int32)
    weights = rng.random((n_v, k)).astype(np.float32)
    weights /= weights.sum(axis=1, keepdims=True)
    skin = LinearSkinning(rest_vertices=rest_v, weights=weights, bones=bones,
                          transforms=transforms)
    vertices = apply_linear_skinning(skin)
    # Sparse self-collision repairs, some in the lead-in (the writer drops those).
    n_rep = 12
    rep_f = np.sort(rng.integers(0, n_all, n_rep)).astype(np.int32)
    rep_v = rng.choice(n_v, n_rep, replace=False).astype(np.int32)
    rep_o = rng.normal(scale=0.003, size=(n_rep, 3)).astype(np.float32)
    apply_sparse_offsets(vertices, rep_f, rep_v, rep_o)
    body_joints = (joints_rest[None] + trans[:, None, :] - [0.0, 0.0, 0.95]).astype(np.float32)
    body = BodySequence(
        rest=rest, poses=poses, trans=trans, fps=30.0, action="walk", motion_source="procedural",
        lead_in_frames=lead_in, joints=body_joints, vertices=vertices, skinning=skin,
        repair_frames=rep_f, repair_vertices=rep_v, repair_offsets=rep_o,
        self_collision=SelfCollisionReport(frames_checked=n_all, repaired_vertices=n_rep),
        collider_face_mask=rng.random(len(body_faces)) > 0.1,
    )
    # Garments: tubes around the body that ride with the pelvis, with a smooth ripple.
    outfit, sim_vertices, specs = [], {}, []
    out_t = t[lead_in:]
    for name in garments:
        variant, fabric, layer, radius, (z0, z1) = GARMENTS[name]
        g_rest, g_faces = tube(radius, z0, z1, 8, 30)
        n_g = len(g_rest)
        rings = {"hem": np.arange(30), "neck" if name == "upper" else "waist": n_g - 30 +
                 np.arange(30)}
        phase = g_rest[:, 2][None, :] * 9.0 - 5.0 * out_t[:, None]
        ripple = 0.006 * np.sin(phase)[..., None] * np.array([1.0, 1.0, 0.3])
        pos = g_rest[None] + trans[lead_in:, None, :] - [0.0, 0.0, 0.95] + ripple
        pos = pos + rng.normal(scale=noise, size=pos.shape)
        sim_vertices[name] = pos.astype(np.float32)
        outfit.append(Garment(
            name=name, category=variant, vertices=g_rest * 1.01, faces=g_faces, fabric=fabric,
            rest_vertices=g_rest, uv=g_rest[:, [0, 2]].copy(), loops=rings,
            regions=(np.arange(n_g) // 60).astype(np.int16),
            region_names=("a", "b", "c", "d"), elastic=("hem",) if name == "lower" else (),
            tightness=(0.1, -0.2), layer=layer,
            meta={"template": "tshirt" if name == "upper" else "trousers", "variant": variant},
        ))
        specs.append(GarmentSpec(name=name, template=outfit[-1].meta["template"],
                                 variant=variant, fabric=fabric, layer=layer))
    ramp = np.linspace(0.5, 1.0, frames).astype(np.float32)
    qa = {
        "strain_mean": 0.01 * ramp, "strain_max": 0.09 * ramp, "strain_p999": 0.06 * ramp,
        "over_strain_share": np.zeros(frames, np.float32), "inside_share": 0.02 * ramp,
        "deep_share": 0.002 * ramp, "kinetic_energy": 0.4 * ramp,
    }
    report = {"solver": "xpbd", "quality": "default", "substeps": 8, "iterations": 4,
              "effects": ["body_collision", "gravity"], "wall_time_s": 1.5, "retries": 0,
              "frames": frames, "vertices": sum(len(g.vertices) for g in outfit),
              "fabrics": {g.fabric: asdict(FABRICS[g.fabric]) for g in outfit}}
    sim = SimResult(garment_names=list(garments), vertices=sim_vertices, qa=qa, report=report)
    spec = SceneSpec(
        dataset_seed=seed, sequence_index=index, sequence_id=f"{seed}-{index:06d}", split=split,
        motion=MotionSpec(frames=frames, lead_in=lead_in),
        outfit=OutfitSpec(garments=tuple(specs), tightness=(0.1, -0.2)),
    )
    record = SequenceRecord(spec=spec, status="ok", body=body, garments=outfit, sim=sim,
                            timings={"body": 0.1, "outfit": 0.2, "simulate": 1.5})
    return SyntheticSequence(record, frames, lead_in, vertices[lead_in:].copy())


def make_rejected(index: int, seed: int = SEED) -> SequenceRecord:
    spec = SceneSpec(dataset_seed=seed, sequence_index=index, sequence_id=f"{seed}-{index:06d}")
    return SequenceRecord(spec=spec, status="rejected", stage="simulate",
                          reason="unstable at frame 4: velocity guard", frames=(2, 4),
                          timings={"body": 0.1})


def write_shard(path: str | Path, records: list[SequenceRecord], store_body_vertices: bool = False,
                quantize: bool = False) -> Path:
    with ShardWriter(path) as writer:
        for record in records:
            write_record(writer, record, store_body_vertices=store_body_vertices,
                         quantize=quantize)
    return Path(path)


def manifest_rows(directory: str | Path) -> list[dict]:
    """The manifest as docs/shard-format.md describes it, rebuilt from the shards."""
    rows = []
    for shard in sorted(Path(directory).glob("*.h5")):
        with h5py.File(shard, "r") as f:
            for sid, g in f["sequences"].items():
                spec = json.loads(g.attrs["spec"])
                garments = g.get("garments", {})
                rows.append({
                    "id": sid, "index": spec["sequence_index"], "shard": shard.name,
                    "status": "ok", "reason": None, "split": str(g.attrs["split"]),
                    "garments": [str(garments[n].attrs["type"]) for n in garments],
                    "fabrics": [str(garments[n].attrs["fabric"]) for n in garments],
                    "action": str(g.attrs["action"]), "frames": int(g.attrs["frames"]),
                    "qa": {k: float(np.max(v[()])) for k, v in g["qa"].items()}
                    if "qa" in g else {},
                    "wall_time": float(sum(json.loads(g.attrs["timings"]).values())),
                })
            for sid, g in f.get("rejected", {}).items():
                spec = json.loads(g.attrs["spec"])
                rows.append({
                    "id": sid, "index": spec["sequence_index"], "shard": shard.name,
                    "status": "rejected", "reason": str(g.attrs["reason"]),
                    "split": spec["split"], "garments": [], "fabrics": [], "action": "",
                    "frames": 0, "qa": {},
                    "wall_time": float(sum(json.loads(g.attrs["timings"]).values())),
                })
    rows.sort(key=lambda r: r["index"])
    return rows


def write_manifest(directory: str | Path, rows: list[dict] | None = None) -> Path:
    path = Path(directory) / "manifest.jsonl"
    rows = manifest_rows(directory) if rows is None else rows
    path.write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
    return path


@dataclass
class SyntheticDataset:
    root: Path
    sequences: dict[str, SyntheticSequence]  # finished sequences by id
    rejected: list[str]
    shards: list[Path]


def make_dataset(root: str | Path, store_body_vertices: bool = False, quantize: bool = False,
                 frames: int = 10) -> SyntheticDataset:
    """Two shards: the first with two sequences (two garments, one garment) and a rejection,
    the second with one sequence (a test-split single garment); plus the manifest."""
    root = Path(root)
    s0 = make_record(0, frames=frames)
    s1 = make_record(1, frames=frames + 2, garments=("upper",))
    s3 = make_record(3, frames=frames, garments=("lower",), split="test")
    rej = make_rejected(2)
    shards = [
        write_shard(root / "shard-00000.h5", [s0.record, s1.record, rej], store_body_vertices,
                    quantize),
        write_shard(root / "shard-00001.h5", [s3.record], store_body_vertices, quantize),
    ]
    write_manifest(root)
    seqs = {s.record.spec.sequence_id: s for s in (s0, s1, s3)}
    return SyntheticDataset(root, seqs, [rej.spec.sequence_id], shards)
