"""DatasetReader and GarmentDataset against what the writer stored, and the storage figures."""

from __future__ import annotations

import pickle
import sys
from dataclasses import asdict
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import shard_factory as sf  # noqa: E402

from datagen.errors import InputError  # noqa: E402
from datagen.io.reader import FABRIC_ORDER, DatasetReader, collate_items  # noqa: E402
from datagen.io.shard import QUANT_STEP  # noqa: E402
from datagen.io.storage import (  # noqa: E402
    bytes_per_vertex_frame,
    position_storage,
    quantization_error,
)
from datagen.sim.fabrics import FABRICS  # noqa: E402

# Decoding int16 * step + pelvis in float64 and rounding to float32 adds float32 rounding of
# metre-sized values (~6e-8) to the half step.
QUANT_TOLERANCE = 0.5 * QUANT_STEP + 1e-6
MODES = {
    "skinning-lossless": dict(store_body_vertices=False, quantize=False),
    "vertices-lossless": dict(store_body_vertices=True, quantize=False),
    "skinning-quantised": dict(store_body_vertices=False, quantize=True),
    "vertices-quantised": dict(store_body_vertices=True, quantize=True),
}


@pytest.fixture(scope="module", params=list(MODES))
def dataset(request, tmp_path_factory) -> sf.SyntheticDataset:
    root = tmp_path_factory.mktemp(request.param)
    return sf.make_dataset(root, **MODES[request.param])


@pytest.fixture(scope="module")
def lossless(tmp_path_factory) -> sf.SyntheticDataset:
    return sf.make_dataset(tmp_path_factory.mktemp("lossless"))


def test_reader_round_trip(dataset):
    quantised = _is_quantised(dataset)
    with DatasetReader(dataset.root) as reader:
        assert reader.sequence_ids() == sorted(dataset.sequences)
        for sid, synth in dataset.sequences.items():
            record = synth.record
            lead = synth.lead_in
            assert reader.spec(sid) == record.spec
            body = reader.body(sid)
            # Rebuilt from skinning (or read back) equals what the pipeline simulated against.
            np.testing.assert_allclose(body["vertices"], synth.body_vertices, rtol=0, atol=1e-6)
            assert body["vertices"].dtype == np.float32
            np.testing.assert_array_equal(body["poses"], record.body.poses[lead:])
            np.testing.assert_array_equal(body["trans"], record.body.trans[lead:])
            np.testing.assert_array_equal(body["shape"], record.body.rest.shape)
            np.testing.assert_array_equal(body["faces"], record.body.rest.faces)
            np.testing.assert_array_equal(body["joints"], record.body.joints[lead:])
            assert body["shape_names"] == list(sf.SHAPE_NAMES)
            assert body["gender"] == record.body.rest.gender
            garments = reader.garments(sid)
            assert set(garments) == {g.name for g in record.garments}
            # innermost first
            assert [g["layer"] for g in garments.values()] == sorted(
                g["layer"] for g in garments.values())
            for g in record.garments:
                got = garments[g.name]
                want = record.sim.vertices[g.name]
                assert got["vertices"].shape == want.shape and got["vertices"].dtype == np.float32
                if quantised:
                    err = np.abs(got["vertices"] - want).max()
                    assert 0 < err <= QUANT_TOLERANCE
                else:
                    np.testing.assert_array_equal(got["vertices"], want)
                np.testing.assert_array_equal(got["faces"], g.faces)
                np.testing.assert_array_equal(got["rest_vertices"], g.rest.astype(np.float32))
                np.testing.assert_array_equal(got["uv"], g.uv.astype(np.float32))
                assert got["type"] == g.meta["variant"] and got["fabric"] == g.fabric
                assert got["fabric_parameters"] == asdict(FABRICS[g.fabric])
                assert tuple(got["tightness"]) == g.tightness and got["layer"] == g.layer
                assert got["elastic"] == list(g.elastic)
            qa = reader.qa(sid)
            assert set(qa) == set(sf.QA_SERIES)
            for name, series in record.sim.qa.items():
                np.testing.assert_array_equal(qa[name], series)
            assert reader.sim_report(sid) == record.sim.report
            assert reader.info(sid)["frames"] == synth.frames
        rejected = reader.rejected()
        assert list(rejected) == dataset.rejected
        rej = rejected[dataset.rejected[0]]
        assert rej["stage"] == "simulate" and rej["frames"] == (2, 4)
        assert "unstable" in rej["reason"]
        # Asking for a rejected sequence's data names its shard and says why it has none.
        with pytest.raises(InputError) as info:
            reader.body(dataset.rejected[0])
        assert info.value.source == rej["shard"] and info.value.field == "sequence"
        assert (f"{dataset.rejected[0]} was rejected (simulate: unstable at frame 4: velocity "
                "guard)") in str(info.value)
        handles = [r.file for r in reader._open.values()]
        assert handles and all(h.id.valid for h in handles)
    assert not any(h.id.valid for h in handles)  # closed by the with block


def _is_quantised(dataset: sf.SyntheticDataset) -> bool:
    with h5py.File(dataset.shards[0], "r") as f:
        return f["sequences/7-000000/garments/upper/vertices"].dtype == np.int16


def test_reader_single_shard_and_errors(lossless, tmp_path):
    with DatasetReader(lossless.shards[1]) as reader:
        assert reader.sequence_ids() == ["7-000003"]
        with pytest.raises(InputError, match="7-000003"):
            reader.body("7-000000")
    # the same sequence id in two shards is refused, naming both files
    sf.write_shard(tmp_path / "a.h5", [sf.make_record(1, garments=("upper",)).record])
    sf.write_shard(tmp_path / "b.h5", [sf.make_record(1, garments=("upper",)).record])
    with pytest.raises(InputError, match=r"b\.h5.*also in a\.h5"):
        DatasetReader(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "shard-00000.h5.tmp").write_bytes(b"")
    with pytest.raises(InputError, match="unfinished"):
        DatasetReader(empty)


# -- GarmentDataset ----------------------------------------------------------------------------
def _outfit(synth: sf.SyntheticSequence) -> tuple[list[str], np.ndarray]:
    garments = sorted(synth.record.garments, key=lambda g: (g.layer, g.name))
    names = [g.name for g in garments]
    return names, np.concatenate([synth.record.sim.vertices[n] for n in names], axis=1)


def test_dataset_frame_mode(lossless):
    from datagen.io.reader import GarmentDataset

    ds = GarmentDataset(lossless.root, mode="frame")
    frames = {sid: s.frames for sid, s in lossless.sequences.items()}
    assert len(ds) == sum(frames.values())
    assert isinstance(ds, torch.utils.data.Dataset)
    item = ds[13]  # 7-000000 has 10 frames: this is 7-000001, frame 3
    synth = lossless.sequences["7-000001"]
    assert item["sequence"] == "7-000001" and int(item["frame"]) == 3
    names, positions = _outfit(synth)
    assert item["garment_names"] == names == ["upper"]
    assert torch.equal(item["garment_vertices"], torch.from_numpy(positions[3]))
    assert item["pose"].shape == (72,) and item["trans"].shape == (3,)
    np.testing.assert_allclose(item["pose"].numpy(), synth.record.body.poses[synth.lead_in + 3],
                               rtol=1e-6)
    assert item["body_vertices"].shape == (202, 3)
    np.testing.assert_allclose(item["body_vertices"].numpy(), synth.body_vertices[3], atol=1e-6)
    assert item["body_faces"].dtype == torch.int64
    assert item["shape"].shape == (5,) and item["tightness"].shape == (2,)
    np.testing.assert_allclose(item["tightness"].numpy(), [0.1, -0.2], rtol=1e-6)
    assert item["fabrics"] == ["cotton"] and item["garment_types"] == ["tshirt"]
    assert item["fabric_onehot"].tolist() == [[0.0, 0.0, 0.0, 1.0]]
    assert item["fabric_parameters"] == [asdict(FABRICS["cotton"])]

    two = ds[0]  # 7-000000: lower (layer 0, denim) then upper (layer 1, cotton)
    assert two["garment_names"] == ["lower", "upper"]
    assert two["garment_offsets"].tolist() == [0, 240, 480]
    assert two["garment_face_offsets"].tolist() == [0, 420, 840]
    faces = two["garment_faces"]
    assert int(faces[:420].max()) < 240 <= int(faces[420:].min())
    assert two["fabric_onehot"][0, FABRIC_ORDER.index("denim")] == 1
    assert two["garment_template"].shape == (480, 3)


def test_a_shard_without_stored_fabric_values_reads_them_as_none(tmp_path):
    """Shards written before the fabrics' values were stored (@fabric_parameters) still read:
    the values are None, the fabric's name is there."""
    from datagen.io.reader import GarmentDataset

    synth = sf.make_record(0)
    del synth.record.sim.report["fabrics"]
    path = sf.write_shard(tmp_path / "old.h5", [synth.record])
    with DatasetReader(path) as reader:
        garments = reader.garments("7-000000")
    assert {g["fabric"] for g in garments.values()} == {"cotton", "denim"}
    assert all(g["fabric_parameters"] is None for g in garments.values())
    assert GarmentDataset(path)[0]["fabric_parameters"] == [None, None]


def test_dataset_clip_and_sequence_modes(lossless):
    from datagen.io.reader import GarmentDataset

    clips = GarmentDataset(lossless.root, mode="clip", clip_length=4, stride=3, body="joints")
    # 10 frames: clips at 0, 3, 6; 12 frames: 0, 3, 6 (9 would end past the last frame)
    assert [(ds_item[0], ds_item[1]) for ds_item in clips.items] == [
        (0, 0), (0, 3), (0, 6), (1, 0), (1, 3), (1, 6), (2, 0), (2, 3), (2, 6)]
    item = clips[4]
    synth = lossless.sequences["7-000001"]
    _, positions = _outfit(synth)
    assert item["garment_vertices"].shape == (4, 240, 3)
    assert torch.equal(item["garment_vertices"], torch.from_numpy(positions[3:7]))
    assert item["pose"].shape == (4, 72) and item["joints"].shape == (4, 24, 3)
    assert "body_vertices" not in item
    np.testing.assert_array_equal(item["joints"].numpy(), synth.record.body.joints[
        synth.lead_in + 3:synth.lead_in + 7])

    seqs = GarmentDataset(lossless.root, mode="sequence", body="none", split="test")
    assert len(seqs) == 1
    item = seqs[0]
    assert item["sequence"] == "7-000003"
    assert item["garment_vertices"].shape == (10, 240, 3)
    assert "joints" not in item and "body_vertices" not in item

    overlapping = GarmentDataset(lossless.root, mode="clip", clip_length=10, stride=1)
    assert len(overlapping) == 1 + 3 + 1


def _assert_same(a, b) -> None:
    assert type(a) is type(b)
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    else:
        assert a == b


@pytest.mark.parametrize("mode", ["frame", "clip", "sequence"])
def test_dataloader_workers_match(lossless, mode):
    from torch.utils.data import DataLoader

    from datagen.io.reader import GarmentDataset

    ds = GarmentDataset(lossless.root, mode=mode, clip_length=3)
    ds[0]  # the parent opens a file before the workers fork: they must not use it
    assert ds._files
    pickle.loads(pickle.dumps(ds))  # picklable for spawn-started workers, handles left out
    assert "_files" in pickle.loads(pickle.dumps(ds)).__dict__
    serial = list(DataLoader(ds, batch_size=4, collate_fn=collate_items, num_workers=0))
    parallel = list(DataLoader(ds, batch_size=4, collate_fn=collate_items, num_workers=2))
    assert len(serial) == len(parallel) == -(-len(ds) // 4)
    _assert_same(serial, parallel)
    if mode == "frame":
        # one outfit: torch's default collate stacks the items of a sequence
        one = GarmentDataset(lossless.root, mode=mode, sequences=["7-000003"])
        (batch,) = list(DataLoader(one, batch_size=10, num_workers=0))
        assert batch["garment_vertices"].shape == (10, 240, 3)


# -- storage figures ---------------------------------------------------------------------------
def test_storage_figures(tmp_path):
    records = [sf.make_record(i, frames=30).record for i in range(2)]
    exact = sf.write_shard(tmp_path / "exact.h5", records)
    exact_copy = sf.write_shard(tmp_path / "exact2.h5", records)
    quant = sf.write_shard(tmp_path / "quant.h5", records, quantize=True)
    assert quantization_error(exact, exact_copy) == 0.0  # lossless is exact
    error = quantization_error(exact, quant)
    assert 0.0 < error <= 1e-4  # 0.1 mm
    assert error <= QUANT_TOLERANCE
    lossless_bpvf = bytes_per_vertex_frame(exact)
    quant_bpvf = bytes_per_vertex_frame(quant)
    info = position_storage(quant)
    assert info.quantized == 4 and info.lossless == 0
    assert info.vertex_frames == 2 * 2 * 30 * 240
    assert 0 < quant_bpvf < lossless_bpvf <= 12.5  # raw float32 is 12 bytes
    assert quant_bpvf <= 6.5  # raw int16 is 6 bytes


def test_rejected_sequences_count_against_the_types_they_would_have_been_written_as(tmp_path):
    """The manifest names a rejected sequence's garments as a written one's (the shirt cut
    from the t-shirt template is a shirt; a jumpsuit one garment of its lower part's fabric),
    and the card counts the rejections by type, fabric and action beside the written."""
    from dataclasses import replace

    from datagen.pipeline.dataset import manifest_rows, write_card
    from datagen.recipe import load_recipe
    from datagen.spec import GarmentSpec, OutfitSpec

    shirt = OutfitSpec(garments=(
        GarmentSpec(name="upper", template="tshirt", variant="shirt", fabric="silk", layer=1),
        GarmentSpec(name="lower", template="trousers", variant="trousers", fabric="denim")))
    jumpsuit = OutfitSpec(garments=(
        GarmentSpec(name="upper", template="top", variant="top", fabric="cotton", layer=1),
        GarmentSpec(name="lower", template="trousers", variant="trousers", fabric="cotton")),
        sewn="jumpsuit")
    done = sf.make_record(0, frames=4, lead_in=2).record
    records = [done]
    for index, outfit in ((1, shirt), (2, jumpsuit)):
        rejected = sf.make_rejected(index)
        rejected.spec = replace(rejected.spec, outfit=outfit)
        records.append(rejected)
    sf.write_shard(tmp_path / "shard-00000.h5", records)
    rows = {row["index"]: row for row in manifest_rows(tmp_path)}
    assert (rows[1]["garments"], rows[1]["fabrics"]) == (["trousers", "shirt"], ["denim", "silk"])
    assert (rows[2]["garments"], rows[2]["fabrics"]) == (["jumpsuit"], ["cotton"])
    assert (rows[0]["garments"], rows[0]["fabrics"]) == (["trousers", "tshirt"],
                                                         ["denim", "cotton"])
    write_card(tmp_path, load_recipe(Path(__file__).resolve().parents[1] / "pipelines"
                                     / "default.yaml"), list(rows.values()), None, 1)
    card = (tmp_path / "README.md").read_text()
    # type | written | rejected; the jumpsuit's top and trousers are not garments of their own
    for line in ("| jumpsuit | 0 | 1 |", "| shirt | 0 | 1 |", "| trousers | 1 | 1 |",
                 "| tshirt | 1 | 0 |", "| cotton | 1 | 1 |", "| denim | 1 | 1 |",
                 "| silk | 0 | 1 |"):
        assert line in card, (line, card)
    assert "| top |" not in card


def test_each_sequence_records_the_environment_of_the_worker_that_made_it(tmp_path):
    """A cluster's workers can differ from the process that writes the shard: the record's
    environment (datagen.environment, taken where run_sequence ran) is what is stored, for
    finished and rejected sequences alike, and the manifest names it."""
    import json

    import numpy
    import taichi

    from datagen.environment import environment
    from datagen.pipeline.dataset import manifest_rows, write_card
    from datagen.recipe import load_recipe

    here = environment()
    assert here["packages"]["numpy"] == numpy.__version__
    assert here["packages"]["taichi"] == ".".join(map(str, taichi.__version__))
    assert here["python"] == ".".join(map(str, sys.version_info[:3]))
    worker = {**here, "cpu": "Worker CPU 9000", "packages": {**here["packages"], "anny": "9.9"}}
    done = sf.make_record(0, frames=4, lead_in=2, garments=("upper",)).record
    done.environment = worker
    rejected = sf.make_rejected(1)
    rejected.environment = worker
    sf.write_shard(tmp_path / "shard-00000.h5", [done, rejected])
    with h5py.File(tmp_path / "shard-00000.h5", "r") as f:
        for group in (f["sequences"][done.spec.sequence_id],
                      f["rejected"][rejected.spec.sequence_id]):
            assert json.loads(group.attrs["environment"]) == worker
    rows = manifest_rows(tmp_path)
    labels = {row["id"]: row["environment"] for row in rows}
    assert set(labels) == {done.spec.sequence_id, rejected.spec.sequence_id}
    for label in labels.values():
        assert label.startswith("Worker CPU 9000; python ") and "anny 9.9" in label
    # The card's "Made on" counts them as its other tables do: written | rejected.
    write_card(tmp_path, load_recipe(Path(__file__).resolve().parents[1] / "pipelines"
                                     / "default.yaml"), rows, None, 1)
    card = (tmp_path / "README.md").read_text()
    made_on = card.split("## Made on")[1].split("## Rejections")[0]
    assert "| environment | sequences | rejected |" in made_on, made_on
    assert f"| {labels[done.spec.sequence_id]} | 1 | 1 |" in made_on, made_on
