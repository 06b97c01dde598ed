"""Dataset runs end to end: resume after SIGKILL, Dask against local processes, bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from datagen.errors import InputError
from datagen.io.validate import validate

TINY = """
name: tiny
seed: 11
sequences: {n}
subject:
  female_fraction: 0.6667
motion:
  actions: {{walk: 1, spin: 1, arm_raise: 1}}
  frames: 6
  lead_in: 3
outfit:
  full_body_probability: 0.3
simulation:
  quality: draft
  settle_seconds: 0.1
  qa: keep
storage:
  shard_size: 2
"""


def tiny_recipe(tmp_path: Path, n: int = 6) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(n=n))
    return path


def errors(path) -> list:
    """Integrity errors (the draft preset's QA limits are not what these tests are about)."""
    return [p for p in validate(path, qa="warning") if p.severity == "error"]


def run_cli(*args, timeout=900) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-m", "datagen.cli", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=timeout)


def test_resume_after_sigkill(tmp_path):
    recipe = tiny_recipe(tmp_path)
    out = tmp_path / "data"
    rng = np.random.default_rng(5)
    cmd = [sys.executable, "-m", "datagen.cli", "dataset", "--pipeline", str(recipe), "--out",
           str(out), "--workers", "1", "--no-progress"]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    for _kill in range(3):
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(float(rng.uniform(4.0, 20.0)))
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        # whatever was killed, every shard under a final name is complete
        for shard in out.glob("shard-*.h5"):
            with h5py.File(shard, "r") as f:
                assert f.attrs["format"] == "datagen-shard"
    r = run_cli("dataset", "--pipeline", recipe, "--out", out, "--workers", "1",
                "--no-progress")
    assert r.returncode == 0, r.stderr
    assert not list(out.glob("*.tmp"))
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    ids = [row["id"] for row in rows]
    assert sorted(ids) == [f"11-{i:06d}" for i in range(6)]  # every sequence exactly once
    assert errors(out) == []
    card = (out / "README.md").read_text()
    assert "Garment types" in card and "Fabrics" in card and "Actions" in card
    # every sequence was made here, by this machine and these versions
    from datagen.environment import environment

    here = environment()
    made_on = [line for line in card.splitlines()
               if line.startswith(f"| {here['cpu']}; python {here['python']}; ")]
    assert len(made_on) == 1 and made_on[0].endswith("| 6 | 0 |"), card
    assert f"taichi {here['packages']['taichi']}" in made_on[0]
    assert all(row["environment"] == rows[0]["environment"] for row in rows)
    # a run that has nothing left to do changes nothing
    before = {p.name: p.stat().st_mtime for p in out.glob("shard-*.h5")}
    r = run_cli("dataset", "--pipeline", recipe, "--out", out, "--workers", "1",
                "--no-progress")
    assert r.returncode == 0
    assert {p.name: p.stat().st_mtime for p in out.glob("shard-*.h5")} == before


def test_dask_cluster_matches_local_processes(tmp_path):
    from distributed import LocalCluster

    from datagen.io.reader import DatasetReader
    from datagen.pipeline.dataset import run_dataset

    recipe = tiny_recipe(tmp_path, n=3)
    local, remote = tmp_path / "local", tmp_path / "dask"
    run_dataset(recipe, local, workers=1, progress=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        run_dataset(recipe, remote, scheduler=cluster.scheduler_address, progress=False)
    with DatasetReader(local) as a, DatasetReader(remote) as b:
        assert a.sequence_ids() == b.sequence_ids()
        for seq in a.sequence_ids():
            assert a.spec(seq).to_json() == b.spec(seq).to_json()
            ga, gb = a.garments(seq), b.garments(seq)
            assert ga.keys() == gb.keys()
            for name in ga:
                np.testing.assert_allclose(ga[name]["vertices"], gb[name]["vertices"],
                                           atol=1e-4)
    assert errors(remote) == []


@pytest.mark.parametrize(
    "patch, field",
    [("  frames: 6", "motion.frames"), ("quality: draft", "simulation.qualty"),
     ("  full_body_probability: 0.3", "outfit.fabrics.tweed"), ("  lead_in: 3", "motion.lead_in")],
)
def test_bad_recipes_fail_before_any_work(tmp_path, patch, field):
    from datagen.pipeline.dataset import run_dataset

    text = TINY.format(n=2).replace(patch, {
        "motion.frames": "  frames: -6",
        "simulation.qualty": "qualty: draft",
        "outfit.fabrics.tweed": "  full_body_probability: 0.3\n  fabrics: {tweed: 1}",
        # The outfit is fitted to the rest pose: without a lead-in it is dropped onto the
        # motion's first pose (a walking t-shirt ran away at 150 m/s, rejected after 3 runs).
        "motion.lead_in": "  lead_in: 0",
    }[field])
    recipe = tmp_path / "bad.yaml"
    recipe.write_text(text)
    out = tmp_path / "out"
    with pytest.raises(InputError) as exc:
        run_dataset(recipe, out, workers=1, progress=False)
    assert field.split(".")[-1] in str(exc.value) and "bad.yaml" in str(exc.value)
    assert not list(out.glob("shard-*"))


def test_a_scheduler_address_that_is_not_one_is_named_not_a_traceback(tmp_path):
    """`--scheduler` that Dask cannot use (here not an address; an unreachable one takes the
    same path after Dask's 30 s connect timeout) ended in a raw ValueError or OSError
    traceback; it is an input error naming the option, and no shard is started."""
    r = run_cli("dataset", "--pipeline", tiny_recipe(tmp_path, n=2), "--out", tmp_path / "out",
                "--scheduler", "nonsense", "--no-progress", timeout=300)
    assert r.returncode == 2, r.stderr  # the CLI's exit status for bad input
    assert ("error: field '--scheduler': expected the address of a running Dask scheduler, "
            "tcp://host:port (missing port number in address 'nonsense'), got 'nonsense'"
            in r.stderr), r.stderr
    assert "Traceback" not in r.stderr
    assert not list((tmp_path / "out").glob("shard-*"))


def test_recipe_with_a_clip_too_short_fails_before_any_work(tmp_path, repo_dir):
    """CMU 02_03 lasts 1.4 s: a recipe asking for 90 frames at 30 fps names it at the start,
    rather than rejecting, one by one, the sequences that happen to draw it."""
    from datagen.pipeline.dataset import run_dataset

    clips = repo_dir / "datagen" / "data" / "mocap" / "cmu"
    text = TINY.format(n=2).replace("  frames: 6", "  frames: 90").replace(
        "  actions:", f"  sources: {{procedural: 1, bvh: 1}}\n  bvh_files: "
        f"['{clips / '12_01_mb.bvh'}', '{clips / '02_03_daz.bvh'}']\n  actions:")
    recipe = tmp_path / "clips.yaml"
    recipe.write_text(text)
    out = tmp_path / "out"
    with pytest.raises(InputError) as exc:
        run_dataset(recipe, out, workers=1, progress=False)
    message = str(exc.value)
    assert "clips.yaml" in message and "motion.bvh_files" in message
    assert "at least 90 frames" in message and "02_03_daz.bvh has 43 (1.40 s)" in message
    assert not list(out.glob("shard-*"))


def test_foreign_output_folder_is_refused_and_kept(tmp_path):
    from datagen.pipeline.dataset import run_dataset

    out = tmp_path / "out"
    out.mkdir()
    foreign = out / "shard-00000.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["format"] = "datagen-shard"
        f.attrs["format_version"] = 99
    before = foreign.read_bytes()
    with pytest.raises(InputError, match="format_version"):
        run_dataset(tiny_recipe(tmp_path), out, workers=1, progress=False)
    assert foreign.read_bytes() == before


def test_a_batched_run_judges_each_sequence_alone_and_resumes_to_the_same_data(tmp_path):
    """--batch 2: each shard's two sequences simulated as one batch (datagen.pipeline.batched,
    for GPUs). Every sequence is written valid, with the report naming its batch, whose
    vertices are the two sequences' together; a resumed run batches as the first did, so a
    recomputed shard holds the same data bit for bit; and a batch larger than a shard is
    refused before any work."""
    from datagen.io.reader import DatasetReader
    from datagen.pipeline.dataset import run_dataset

    recipe = tiny_recipe(tmp_path, n=4)
    with pytest.raises(InputError) as exc:
        run_dataset(recipe, tmp_path / "too_big", workers=1, progress=False, batch=3)
    assert "--batch" in str(exc.value) and "the shard size (2)" in str(exc.value)
    assert not list((tmp_path / "too_big").glob("shard-*"))

    alone, batched = tmp_path / "alone", tmp_path / "batched"
    run_dataset(recipe, alone, workers=1, progress=False)
    run_dataset(recipe, batched, workers=1, progress=False, batch=2)
    assert errors(batched) == []
    with DatasetReader(alone) as a, DatasetReader(batched) as b:
        ids = b.sequence_ids()
        assert ids == a.sequence_ids() == [f"11-{i:06d}" for i in range(4)]
        first = {seq: {name: g["vertices"].copy() for name, g in b.garments(seq).items()}
                 for seq in ids}
        for seq in ids:
            assert b.spec(seq).to_json() == a.spec(seq).to_json()
    reports, sizes = {}, {}
    for shard in sorted(batched.glob("shard-*.h5")):
        with h5py.File(shard, "r") as f:
            for seq, g in f["sequences"].items():
                reports[seq] = json.loads(g["sim"].attrs["report"])
                sizes[seq] = reports[seq]["vertices"]
    for k in range(2):  # shard k: sequences 2k and 2k + 1, one batch
        pair = [f"11-{i:06d}" for i in (2 * k, 2 * k + 1)]
        for index, seq in enumerate(pair):
            assert reports[seq]["batch"] == {"scenes": 2, "index": index, "alone": False,
                                             "batch_vertices": sizes[pair[0]] + sizes[pair[1]]}

    (batched / "shard-00001.h5").unlink()
    r = run_cli("dataset", "--pipeline", recipe, "--out", batched, "--workers", "1",
                "--batch", "2", "--no-progress")
    assert r.returncode == 0, r.stderr
    with DatasetReader(batched) as b:
        for seq in ids:
            for name, g in b.garments(seq).items():
                np.testing.assert_array_equal(g["vertices"], first[seq][name])


def test_sequences_that_share_no_batch_are_simulated_as_unbatched_ones(tmp_path, body_model):
    """Sequences whose simulation settings differ cannot share a solver: each is a group of one
    and is simulated exactly as an unbatched run simulates it, bit for bit."""
    from dataclasses import replace

    from datagen.pipeline.batched import run_sequences_batched
    from datagen.pipeline.stages import run_sequence
    from datagen.recipe import load_recipe
    from datagen.sampling import sample_scene

    loaded = load_recipe(tiny_recipe(tmp_path, n=2))
    a, b = sample_scene(loaded, 0), sample_scene(loaded, 1)
    b = replace(b, simulation=replace(b.simulation, substeps=12))
    batched = run_sequences_batched([a, b], body_model, loaded.recipe.body, loaded.base_dir)
    for spec, record in zip([a, b], batched, strict=True):
        alone = run_sequence(spec, body_model, loaded.recipe.body, loaded.base_dir)
        assert record.status == alone.status == "ok"
        assert "batch" not in record.sim.report
        assert record.sim.report["substeps"] == alone.sim.report["substeps"]
        for name, vertices in alone.sim.vertices.items():
            np.testing.assert_array_equal(record.sim.vertices[name], vertices)
