"""`datagen validate` on clean and damaged synthetic datasets: every kind of damage is reported
with the file and the sequence, never as a traceback, and makes the command exit non-zero."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import h5py
import numpy as np
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))
import shard_factory as sf  # noqa: E402

from datagen.io.commands import validate as validate_command  # noqa: E402
from datagen.io.validate import Problem, validate, validate_report  # noqa: E402


def run_cli(*args) -> tuple[int, str]:
    group = click.Group(commands={"validate": validate_command})
    result = CliRunner().invoke(group, ["validate", *map(str, args)])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result.exit_code, result.output


def errors(problems: list[Problem]) -> list[Problem]:
    return [p for p in problems if p.severity == "error"]


def only_error(problems: list[Problem]) -> Problem:
    errs = errors(problems)
    assert len(errs) == 1, "\n".join(map(str, problems))
    return errs[0]


@pytest.fixture
def dataset(tmp_path) -> sf.SyntheticDataset:
    return sf.make_dataset(tmp_path / "ds")


@pytest.mark.parametrize("kwargs", [{}, dict(store_body_vertices=True, quantize=True)])
def test_clean_dataset_passes(tmp_path, kwargs):
    ds = sf.make_dataset(tmp_path, **kwargs)
    report = validate_report(ds.root)
    assert report.problems == [] and report.ok
    assert (len(report.shards), report.sequences, report.rejected) == (2, 3, 1)
    assert validate(ds.shards[0]) == []
    code, out = run_cli(ds.root)
    assert code == 0 and out.startswith("OK: 2 shard(s), 3 sequence(s), 1 rejected")
    code, out = run_cli(ds.root, "--json")
    assert code == 0 and json.loads(out)["ok"] is True


def test_flipped_byte(dataset):
    shard = dataset.shards[0]
    with h5py.File(shard, "r+") as f:  # bypasses the writer: the checksum is not updated
        ds = f["sequences/7-000000/garments/upper/vertices"]
        frame = ds[4]
        frame.view(np.uint32)[17, 1] ^= 1 << 12
        ds[4] = frame
    p = only_error(validate(dataset.root))
    assert (p.file, p.sequence) == (str(shard), "7-000000")
    assert "garments/upper/vertices" in p.message and "checksum" in p.message
    code, out = run_cli(dataset.root)
    assert code == 1
    assert f"error: {shard}: 7-000000: garments/upper/vertices: checksum mismatch" in out
    assert "FAILED" in out and "1 error(s)" in out
    report = json.loads(run_cli(dataset.root, "--json")[1])
    assert report["ok"] is False and report["problems"][0]["sequence"] == "7-000000"


def test_flipped_byte_in_body_skinning(dataset):
    with h5py.File(dataset.shards[1], "r+") as f:
        ds = f["sequences/7-000003/body/skinning/weights"]
        w = ds[()]
        w[5, 0] = np.nextafter(w[5, 0], np.float32(1))
        ds[...] = w
    p = only_error(validate(dataset.root))
    assert p.sequence == "7-000003" and "body/skinning/weights: checksum" in p.message


def test_truncated_shard(dataset):
    shard = dataset.shards[0]
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])
    problems = validate(dataset.root)
    p = only_error(problems)  # one problem for the file; its manifest rows add none
    assert p.file == str(shard) and p.sequence is None
    assert "unreadable shard" in p.message and "truncated" in p.message
    code, out = run_cli(dataset.root)
    assert code == 1 and "Traceback" not in out and str(shard) in out
    assert only_error(validate(shard)).file == str(shard)  # the file on its own
    code, out = run_cli(shard)
    assert code == 1 and "unreadable shard" in out
    size = len(data)
    assert f"truncated, {size // 2} of {size} bytes" in p.message


def test_a_shard_reader_says_why_a_file_is_unreadable(dataset, tmp_path):
    """Reading (inspect, export, preview, the trainers) says what validate says: h5py's reason,
    not its first words ("Unable to synchronously open file")."""
    from datagen.errors import InputError
    from datagen.io.shard import ShardReader

    shard = dataset.shards[0]
    data = shard.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[:1000])
    with pytest.raises(InputError, match=f"cut.h5.*truncated, 1000 of {len(data)} bytes"):
        ShardReader(cut)
    text = tmp_path / "notes.h5"
    text.write_text("not a shard")
    with pytest.raises(InputError, match="file signature not found .not an HDF5 file"):
        ShardReader(text)


def test_not_hdf5(tmp_path):
    bogus = tmp_path / "x.h5"
    bogus.write_text("hello")
    p = only_error(validate(bogus))
    assert p.file == str(bogus) and "unreadable shard" in p.message


def test_other_format_version(dataset):
    shard = dataset.shards[1]
    with h5py.File(shard, "r+") as f:
        f.attrs["format_version"] = 2
    p = only_error(validate(dataset.root))
    assert p.file == str(shard) and "format_version is 2" in p.message
    assert run_cli(dataset.root)[0] == 1


def _rows(ds: sf.SyntheticDataset) -> list[dict]:
    return [json.loads(line) for line in (ds.root / "manifest.jsonl").read_text().splitlines()]


def test_manifest_wrong_shard(dataset):
    rows = _rows(dataset)
    for row in rows:
        if row["id"] == "7-000001":
            row["shard"] = "shard-00001.h5"
    sf.write_manifest(dataset.root, rows)
    p = only_error(validate(dataset.root))
    assert p.file.endswith("manifest.jsonl") and p.sequence == "7-000001"
    assert "listed in shard-00001.h5 but it is in shard-00000.h5" in p.message
    code, out = run_cli(dataset.root)
    assert code == 1 and "7-000001" in out


def test_manifest_missing_sequence(dataset):
    rows = [r for r in _rows(dataset) if r["id"] != "7-000003"]
    sf.write_manifest(dataset.root, rows)
    p = only_error(validate(dataset.root))
    assert p.sequence == "7-000003" and "in shard-00001.h5 but missing from the manifest" in \
        p.message
    assert run_cli(dataset.root)[0] == 1


def test_manifest_duplicate_and_unknown_rows(dataset):
    rows = _rows(dataset)
    ghost = dict(rows[0], id="7-000009", index=9)
    flipped = dict(rows[2], status="ok")  # 7-000002 is rejected in its shard
    assert rows[2]["id"] == "7-000002"
    sf.write_manifest(dataset.root, rows[:2] + [flipped] + rows[3:] + [rows[1], ghost])
    problems = errors(validate(dataset.root))
    text = "\n".join(map(str, problems))
    assert len(problems) == 3, text
    by_id = {p.sequence: p.message for p in problems}
    assert "listed 2 times (lines 2, 5)" in by_id["7-000001"]
    assert "not in shard-00000.h5" in by_id["7-000009"]
    assert "status 'ok' but shard-00000.h5 has it rejected" in by_id["7-000002"]


def test_manifest_missing_file(dataset):
    (dataset.root / "manifest.jsonl").unlink()
    p = only_error(validate(dataset.root))
    assert p.file.endswith("manifest.jsonl") and "missing" in p.message


def test_sequence_in_two_shards(dataset):
    sf.write_shard(dataset.root / "shard-00002.h5", [sf.make_record(3, garments=("lower",),
                                                                    split="test").record])
    p = only_error(validate(dataset.root))
    assert p.file.endswith("shard-00002.h5") and p.sequence == "7-000003"
    assert "also in shard-00001.h5" in p.message


def test_tmp_leftover_is_a_warning(dataset):
    tmp = dataset.root / "shard-00002.h5.tmp"
    tmp.write_bytes(b"\x89HDF partial")
    report = validate_report(dataset.root)
    assert report.ok and [p.file for p in report.warnings] == [str(tmp)]
    code, out = run_cli(dataset.root)
    assert code == 0 and f"warning: {tmp}: leftover temporary file" in out
    assert "0 error(s), 1 warning(s)" in out


def _single(tmp_path, edit, quantize=False) -> list[Problem]:
    synth = sf.make_record(0)
    edit(synth.record)
    path = sf.write_shard(tmp_path / "one.h5", [synth.record], quantize=quantize)
    return validate(path)


def test_qa_limits(tmp_path):
    def deep(record):
        record.sim.qa["deep_share"][6] = 0.05

    p = only_error(_single(tmp_path, deep))
    assert p.sequence == "7-000000"
    assert "qa/deep_share reaches 0.05 at frame 6" in p.message and "0.01" in p.message
    (tmp_path / "one.h5").unlink()

    def strain(record):  # 0.3 % of the springs beyond their own fabric's max_strain
        record.sim.qa["over_strain_share"][:] = 0.003
        record.sim.qa["kinetic_energy"][2] = -1.0

    problems = _single(tmp_path, strain)
    messages = " | ".join(p.message for p in errors(problems))
    assert len(errors(problems)) == 2, messages
    assert "qa/over_strain_share reaches 0.003" in messages and "max_strain; bound 0.001" \
        in messages
    assert "qa/kinetic_energy: negative" in messages
    as_warnings = validate(tmp_path / "one.h5", qa="warning")
    assert len(as_warnings) == 2 and not errors(as_warnings)
    assert validate(tmp_path / "one.h5", qa="off") == []
    code, _ = run_cli(tmp_path / "one.h5", "--qa", "warning")
    assert code == 0


def test_strain_holds_each_spring_to_its_own_fabric_and_stored_fabrics_are_checked(tmp_path):
    """The strain bound is each spring's own fabric's max_strain, as simulated
    (qa/over_strain_share): a stiff garment over its bound breaks it even where a looser
    neighbour's bound is not reached (the 99.9th percentile of all springs against the loosest
    bound, the check before, let that through). A shard stores each garment's fabric as
    simulated (@fabric_parameters, from the sim report): a user's fabric is accepted, a
    built-in simulated with other values than this datagen's is a warning, and damaged
    parameters are errors naming the garment and field."""
    from dataclasses import asdict, replace

    from datagen.sim.fabrics import FABRICS

    def wearing(fabric, over_share=0.0):
        def edit(record):
            for g in record.garments:
                g.fabric = fabric.name
            record.sim.report["fabrics"] = {fabric.name: asdict(fabric)}
            record.sim.qa["strain_p999"][:] = 0.3
            record.sim.qa["over_strain_share"][:] = over_share
        return edit

    def check(edit) -> list[Problem]:
        path = tmp_path / "one.h5"
        path.unlink(missing_ok=True)
        return _single(tmp_path, edit)

    loose = replace(FABRICS["cotton"], name="jersey", max_strain=0.4, source="my.yaml")
    problems = check(wearing(loose))
    assert problems == [], problems
    with h5py.File(tmp_path / "one.h5") as f:
        stored = f["sequences/7-000000/garments/upper"].attrs["fabric_parameters"]
        assert json.loads(stored) == asdict(loose)
    p = only_error(check(wearing(loose, over_share=0.0015)))
    assert "qa/over_strain_share reaches 0.0015" in p.message and "bound 0.001" in p.message
    # Cotton as another version simulated it: a warning that the values differ.
    other_cotton = replace(FABRICS["cotton"], max_strain=0.35)
    problems = check(wearing(other_cotton))
    assert not errors(problems), problems
    assert any("'cotton' was simulated with other values than this datagen's built-in"
               in p.message for p in problems), problems

    # A shard written before the parameters were stored is judged by the same series.
    def unstored(record):
        wearing(loose, over_share=0.0015)(record)
        del record.sim.report["fabrics"]
    assert "qa/over_strain_share reaches 0.0015" in only_error(check(unstored)).message
    # Damaged parameters are named by garment and field, with the QA off too.
    check(wearing(loose))
    with h5py.File(tmp_path / "one.h5", "r+") as f:
        params = asdict(loose) | {"max_strain": "loose"}
        f["sequences/7-000000/garments/lower"].attrs["fabric_parameters"] = json.dumps(params)
    for qa in ("error", "off"):
        p = only_error(validate(tmp_path / "one.h5", qa=qa))
        assert ("garments/lower/@fabric_parameters.max_strain': expected a number, got 'loose'"
                in p.message), p.message


def test_shapes_indices_and_finiteness(tmp_path):
    def damage(record):
        record.garments[0].faces[7, 2] = 9999  # upper: past its 240 vertices
        record.sim.vertices["lower"][2, 5, 0] = np.nan
        record.sim.vertices["upper"] = record.sim.vertices["upper"][:-1]  # a frame short

    problems = errors(_single(tmp_path, damage))
    text = "\n".join(map(str, problems))
    assert len(problems) == 3, text
    assert "garments/upper/faces: indices in [0, 9999], expected [0, 239]" in text
    assert "garments/lower/vertices: non-finite values" in text
    assert "garments/upper/vertices: shape (9, 240, 3), expected (10, 240, 3)" in text
    assert all(p.sequence == "7-000000" for p in problems)


def test_missing_path_and_empty_folder(tmp_path):
    assert "no shard files" in only_error(validate(tmp_path)).message
    code, out = run_cli(tmp_path / "nope")
    assert code == 2 and "does not exist" in out


def test_qa_gate_rejects_what_validate_would_fail(tmp_path):
    """A dataset run's QA gate (recipe `simulation.qa: reject`) turns a sequence over a bound
    into a rejected record that names the bound, the value and the frame; the shard it makes
    passes strict validation, and a sequence within the bounds goes through untouched."""
    from datagen.pipeline.stages import reject_over_qa_bounds

    within = sf.make_record(0).record
    assert reject_over_qa_bounds(within) is within

    over = sf.make_record(1).record
    over.sim.qa["over_strain_share"][4] = 0.004
    over.sim.qa["deep_share"][7] = 0.02
    rejected = reject_over_qa_bounds(over)
    assert rejected.status == "rejected" and rejected.stage == "qa"
    assert rejected.frames == (7, 7)  # the first breach listed: deep_share
    assert rejected.body is None and rejected.sim is None and rejected.garments is None
    assert ("cloth deeper in the body than its thickness (qa/deep_share 0.02 at frame 7, "
            "bound 0.01)") in rejected.reason
    assert ("fabric springs strained beyond their fabric's max_strain (qa/over_strain_share "
            "0.004 at frame 4, bound 0.001)") in rejected.reason
    path = sf.write_shard(tmp_path / "gated.h5", [within, rejected])
    assert validate(path) == []
    with h5py.File(path, "r") as f:
        (name,) = list(f["rejected"])
        assert f["rejected"][name].attrs["stage"] == "qa"


def test_qa_gate_names_the_bodys_residual_flexion_overlap_at_the_breach_frame():
    """A sequence over a QA bound in a frame where the body's parts still intersect across a
    flexed joint after the body stage separated them (body frames count the lead-in, QA frames
    do not) is rejected with a reason that says so; a breach in another frame is not blamed on
    the body."""
    from datagen.pipeline.stages import reject_over_qa_bounds

    made = sf.make_record(1)
    record = made.record
    report = record.body.self_collision
    report.flexion_overlap_frames = [made.lead_in + k for k in range(2, 8)]
    report.flexion_overlap_by_joint = {"hip_l": [made.lead_in + k for k in range(2, 8)],
                                       "elbow_r": [made.lead_in + k for k in range(6, 8)]}
    report.flexion_residual_frames = [made.lead_in + 4, made.lead_in + 5]
    report.flexion_overlap_max_depth = 0.0844
    report.flexion_residual_pairs = 7
    record.sim.qa["over_strain_share"][4] = 0.004
    reason = reject_over_qa_bounds(record).reason
    # It names the joints folding in the breach's frame: the left hip, not the right elbow.
    assert reason.endswith("; at frame 4 the body's parts still intersect across a flexed joint "
                           "(hip_l; skinning sank them up to 8.4 cm deep in this "
                           "sequence, and separating them left 7 triangle pairs crossing)")
    # An overlap the body stage separated is not blamed: only what is left of it.
    other = sf.make_record(1).record
    other.body.self_collision.flexion_overlap_frames = [made.lead_in + 4]
    other.body.self_collision.flexion_residual_frames = [made.lead_in + 6]
    other.sim.qa["over_strain_share"][4] = 0.004
    assert "joint" not in reject_over_qa_bounds(other).reason


def test_qa_gate_judges_cloth_by_the_bodys_volume_where_a_joint_was_flexed():
    """Where the body stage found skinning sinking parts into each other, the gate also judges
    depth by the body's volume (qa.buried_share), which the simulator's nearest-triangle series
    cannot: cloth pushed 10 cm inside the synthetic body (a capped tube of radius 15 cm) in
    such a frame rejects the sequence, naming the share, the frame and the bound. Outside those
    frames the volume is not computed (it costs 0.1 s a frame), so the same cloth there passes
    the gate: the nearest-triangle series, which the gate does read, say nothing."""
    from datagen.pipeline.stages import reject_over_qa_bounds

    def buried_at(frame: int, flexed: list[int]):
        made = sf.make_record(2)
        record = made.record
        record.body.self_collision.flexion_overlap_frames = [made.lead_in + f for f in flexed]
        upper = record.sim.vertices["upper"]
        sunk = np.arange(0, upper.shape[1], 20)  # 5 % of the t-shirt's vertices
        centre = made.body_vertices[frame].mean(axis=0)
        upper[frame, sunk, :2] = centre[:2] + 0.05 * (upper[frame, sunk, :2] - centre[:2]) / 0.19
        return reject_over_qa_bounds(record)

    rejected = buried_at(4, [3, 4, 5])
    assert rejected.status == "rejected" and rejected.stage == "qa"
    assert rejected.frames == (4, 4)
    assert rejected.reason.startswith(
        "cloth inside the body's volume deeper than its thickness where skinning sank its parts "
        "into each other (qa/buried_share 0."), rejected.reason
    assert "at frame 4, bound 0.01)" in rejected.reason
    assert buried_at(4, [6, 7]).status == "ok"


def test_neckline_slip_measures_how_far_a_neckline_left_the_neck():
    """qa.neckline_slip, checked by hand: a ring of radius 10 cm around the neck joint at its
    height lies 10 cm from it; dropped 25 cm down the body it lies sqrt(0.1^2 + 0.25^2) =
    26.93 cm away, 16.93 cm farther, at every vertex. A ring that turns and travels with the
    joint (a body walking and turning in its neckline) has not slipped at all."""
    from datagen.qa import neckline_slip

    angle = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    ring = np.stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), np.zeros(24)], axis=1)
    neck = np.array([0.0, 0.0, 1.45])
    frames = np.stack([ring + neck, ring + neck - [0.0, 0.0, 0.25]])
    slip = neckline_slip(frames, ring + neck, np.stack([neck, neck]), neck)
    assert slip == pytest.approx([0.0, 0.169258], abs=1e-6)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = np.array([2.0, -1.0, 0.05])
    carried = neckline_slip((ring @ turn.T + neck + moved)[None], ring + neck,
                            (neck + moved)[None], neck)
    assert carried == pytest.approx([0.0], abs=1e-9)
    with pytest.raises(ValueError, match="must match"):
        neckline_slip(frames, ring[:5], np.stack([neck, neck]), neck)


def test_where_on_body_names_the_parts_nearest_the_cloth_most_first():
    """qa.where_on_body, checked by hand: a body of two parts, a thigh (part 1) along x < 0
    and a shin (part 4) along x > 0. Three points over the shin and one over the thigh read
    shin 75 %, thigh 25 %; a point between the thigh's last vertex and the middle counts for
    the thigh; a tie is named in part order; the third part is left out at
    most=2; no points, no words. The guard's reasons carry it (test_escalation)."""
    from datagen.body.parts import PART_NAMES
    from datagen.qa import where_on_body

    x = np.linspace(-0.5, 0.5, 11)
    body = np.stack([x, np.zeros(11), np.zeros(11)], axis=1)
    parts = np.where(x < 0.0, 1, 4)
    parts[5] = 9  # the vertex at x = 0: the chest, say
    assert (PART_NAMES[1], PART_NAMES[4], PART_NAMES[9]) == ("thigh_l", "shin_l", "chest")
    over = np.array([[0.31, 0.0, 0.01], [0.42, 0.01, 0.0], [0.18, -0.01, 0.0],
                     [-0.33, 0.0, 0.02]])
    assert where_on_body(over, body, parts, PART_NAMES) == "shin_l 75 %, thigh_l 25 %"
    assert where_on_body([[-0.14, 0.0, 0.0]], body, parts, PART_NAMES) == "thigh_l 100 %"
    tie = np.array([[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0], [0.01, 0.0, 0.0]])
    assert where_on_body(tie, body, parts, PART_NAMES) == "thigh_l 33 %, shin_l 33 %"
    assert where_on_body(tie, body, parts, PART_NAMES, most=3) == \
        "thigh_l 33 %, shin_l 33 %, chest 33 %"
    assert where_on_body(np.zeros((0, 3)), body, parts, PART_NAMES) == ""


def test_a_rejection_as_unstable_says_which_neckline_had_slid_off_first():
    """simulate.slid_necklines_note, the clause a rejection as unstable ends with: the ring of
    the test above, as the neckline of a top that comes second in the outfit (its rows after
    a 5-vertex garment without one). Dropped 25 cm (16.93 cm of slip, under the 20 cm bound)
    nothing is said; dropped 40 cm, sqrt(0.1^2 + 0.4^2) - 0.1 = 31.23 cm, it is named. A
    track without a neck joint (a bare sphere) says nothing. (The CLOTH3D sample's sequence 3
    ran away at the elbow once its strap top had slid off: docs/simulator.md.)"""
    from types import SimpleNamespace

    from datagen.sim.simulate import slid_necklines, slid_necklines_note
    from datagen.types import Garment

    angle = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    ring = np.stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), np.zeros(24)], axis=1)
    neck = np.array([0.0, 0.0, 1.45])
    faces = np.zeros((0, 3), np.int32)
    other = Garment("lower", "trousers", np.zeros((5, 3)), faces, "denim")
    top = Garment("upper", "top", ring + neck, faces, "cotton", loops={"neck": np.arange(24)})
    track = SimpleNamespace(neck=np.repeat(neck[None], 3, axis=0), rest_neck=neck,
                            lead_in_frames=1)
    ranges = [(0, 5), (5, 29)]

    def outfit(drop):
        return np.concatenate([np.full((5, 3), 9.0), ring + neck - [0.0, 0.0, drop]])

    assert slid_necklines_note([other, top], ranges, outfit(0.25), track, 2) == ""
    assert slid_necklines_note([other, top], ranges, outfit(0.40), track, 2) == (
        "; the top's neckline had slid 0.31 m off the shoulders by then")
    bare = SimpleNamespace(neck=None, rest_neck=None)  # a sphere's track
    assert slid_necklines_note([other, top], ranges, outfit(0.40), bare, 2) == ""
    # What the note and the simulator's neckline guard read: the garment and its breach, at
    # the output frame (body frame 2 less the track's lead-in of 1).
    ((garment, breach),) = slid_necklines([other, top], ranges, outfit(0.40), track, 2)
    assert garment is top and breach.frame == 1
    assert breach.value == pytest.approx(np.hypot(0.1, 0.4) - 0.1, abs=1e-6)
    assert slid_necklines([other, top], ranges, outfit(0.25), track, 2) == []


def _slipped_record():
    """A synthetic sequence whose t-shirt's neckline is off to one side at frame 6: the
    synthetic body's neck joint lies 0.57 m below that neckline (its joints are spread evenly
    up the body), so a 0.6 m move takes it 0.2-0.4 m farther away."""
    record = sf.make_record(1).record
    record.sim.vertices["upper"][6, record.garments[0].loops["neck"], 0] += 0.6
    return record


def test_qa_gate_rejects_a_garment_that_slid_off_the_shoulders():
    """A neckline that has left the neck (an open shirt sliding down the arms: the sweeps of
    2026-12-04 found such sequences written as valid) is rejected by the gate, naming the
    garment, the value, the frame and the bound; the same neckline riding on the body is not."""
    from datagen.pipeline.stages import reject_over_qa_bounds

    rejected = reject_over_qa_bounds(_slipped_record())
    assert rejected.status == "rejected" and rejected.stage == "qa"
    assert rejected.frames == (6, 6)
    assert rejected.reason.startswith(
        "the tshirt's neckline slid off the shoulders (qa/neckline_slip 0."), rejected.reason
    assert rejected.reason.endswith("at frame 6, bound 0.2)"), rejected.reason
    within = sf.make_record(1).record
    assert reject_over_qa_bounds(within) is within


def test_validate_finds_a_garment_that_slid_off_the_shoulders(tmp_path):
    """A shard written with the gate off (`qa: keep`) that holds a garment off the shoulders
    fails validation with the gate's bound, judged from the stored frames (quantised ones
    decoded), and passes with `--qa warning`, which reports it as a warning."""
    record = _slipped_record()
    for quantize in (False, True):
        path = sf.write_shard(tmp_path / f"slip-{quantize}.h5", [record], quantize=quantize)
        (problem,) = validate(path)
        assert problem.message.startswith(
            "garments/upper: qa/neckline_slip reaches 0."), problem.message
        assert problem.message.endswith(
            "at frame 6 (the tshirt's neckline slid off the shoulders; bound 0.2)")
        (warning,) = validate(path, qa="warning")
        assert warning.severity == "warning"


def test_recipe_qa_policy_is_checked(tmp_path):
    from datagen.errors import InputError
    from datagen.recipe import load_recipe

    text = (Path(__file__).parents[1] / "pipelines" / "default.yaml").read_text()
    assert "  qa: reject" in text
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("  qa: reject", "  qa: drop"))
    with pytest.raises(InputError) as exc:
        load_recipe(bad)
    message = str(exc.value)
    assert "bad.yaml" in message and "simulation.qa" in message and "reject, keep" in message
