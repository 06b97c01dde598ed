"""`datagen body` and `datagen inspect` end to end, and their handling of bad input."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import shard_factory as sf  # noqa: E402
from test_smpl import make_model  # noqa: E402

DATAGEN = [sys.executable, "-m", "datagen.cli"]


def run(*args, cwd=None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run(
        [*DATAGEN, *map(str, args)], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


def test_body_walk_and_inspect(tmp_path):
    out = tmp_path / "b.h5"
    r = run("body", "--motion", "walk", "--frames", 120, "--out", out)
    assert r.returncode == 0, r.stderr
    r = run("inspect", out, "--json")
    assert r.returncode == 0, r.stderr
    tree = json.loads(r.stdout)
    (seq,) = tree["sequences"]
    body = tree["groups"]["sequences"]["groups"][seq]["groups"]["body"]
    assert body["datasets"]["poses"]["shape"] == [120, 72]
    assert body["datasets"]["trans"]["shape"] == [120, 3]
    assert body["attrs"]["model"] == "anny"
    assert body["attrs"]["shape_names"] == ["age", "muscle", "weight", "height", "proportions"]
    text = run("inspect", out)
    assert "poses (120, 72) float64" in text.stdout
    # A dataset folder is not a shard: the answer names one of its shards and what describes
    # the folder, in one line.
    r = run("inspect", tmp_path)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode != 0 and len(lines) == 1, r.stderr
    assert lines[0] == (f"error: {tmp_path}: expected a shard file, e.g. {out} (a dataset "
                        "folder is described by its card, README.md, and checked by "
                        "`datagen validate`), got 'a folder'")


def test_body_from_bvh(tmp_path, cmu_dir):
    out = tmp_path / "c.h5"
    r = run("body", "--bvh", cmu_dir / "02_04_daz.bvh", "--frames", 120, "--out", out)
    assert r.returncode == 0, r.stderr
    from datagen.io.shard import ShardReader

    with ShardReader(out) as reader:
        (seq,) = reader.sequence_ids()
        g = reader.group(seq)
        assert g["body"]["poses"].shape == (120, 72)
        assert g.attrs["action"] == "02_04_daz"
        v = reader.body_vertices(seq)
        assert v.shape == (120, 13348, 3) and np.isfinite(v).all()
        assert abs(float(v[:, :, 2].min())) < 0.08  # feet near the ground


def _bad_inputs(tmp_path: Path, cmu_dir: Path) -> dict[str, tuple[list, str]]:
    """name -> (CLI arguments, text the error line must contain)."""
    text = (cmu_dir / "12_01_mb.bvh").read_text()
    truncated = tmp_path / "truncated.bvh"
    truncated.write_text(text[: len(text) // 2])
    unknown = tmp_path / "robot.bvh"
    unknown.write_text(
        "HIERARCHY\nROOT base\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition "
        "Zrotation Xrotation Yrotation\n JOINT arm\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation "
        "Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 2\n"
        "Frame Time: 0.0333\n0 0 0 0 0 0 0 0 0\n0 0 0 0 0 0 0 0 0\n"
    )
    no_poses = tmp_path / "no_poses.npz"
    np.savez(no_poses, trans=np.zeros((10, 3)), mocap_framerate=30.0)
    bad_smpl = tmp_path / "bad_smpl.npz"
    arrays = make_model()
    arrays["weights"] = arrays["weights"][:, :23]
    np.savez(bad_smpl, **arrays)
    evil = tmp_path / "evil.pkl"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    evil.write_bytes(pickle.dumps(dict(make_model(), v_template=Evil()), protocol=2))
    yaml_key = tmp_path / "recipe.yaml"
    yaml_key.write_text("name: x\nseed: 1\nsequences: 2\nmotoin: {frames: 10}\n")
    return {
        "truncated bvh": (["--bvh", truncated], "truncated.bvh"),
        "unknown skeleton": (["--bvh", unknown], "robot.bvh"),
        "npz without poses": (["--amass", no_poses], "no_poses.npz: field 'poses'"),
        "smpl wrong shapes": (
            ["--body-model", "smpl", "--smpl-model", bad_smpl],
            "bad_smpl.npz: field 'weights'",
        ),
        "foreign pickle": (
            ["--body-model", "smpl", "--smpl-model", evil],
            "evil.pkl: field 'pickle'",
        ),
        "yaml unknown key": (["--pipeline", yaml_key], "recipe.yaml: field 'motoin'"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "truncated bvh",
        "unknown skeleton",
        "npz without poses",
        "smpl wrong shapes",
        "foreign pickle",
        "yaml unknown key",
    ],
)
def test_bad_input_is_one_line_and_leaves_nothing(tmp_path, cmu_dir, case):
    args, expected = _bad_inputs(tmp_path, cmu_dir)[case]
    out = tmp_path / "out.h5"
    frames = [] if "--pipeline" in args else ["--frames", 30]  # a recipe draws its own
    r = run("body", *args, *frames, "--out", out)
    assert r.returncode != 0
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and expected in lines[0], lines[0]
    assert "Traceback" not in r.stderr
    assert not out.exists() and not Path(str(out) + ".tmp").exists()
    assert not (tmp_path / "pwned").exists()


def test_help_is_useful():
    r = run("--help")
    assert r.returncode == 0 and "body" in r.stdout and "inspect" in r.stdout
    r = run("body", "--help")
    for option in ("--motion", "--bvh", "--amass", "--frames", "--gender", "--out"):
        assert option in r.stdout


@pytest.mark.parametrize("command", ["body", "simulate", "garments"])
def test_a_negative_seed_is_refused_by_name(tmp_path, command):
    """Seeds seed numpy's generators, which take non-negative integers only: -1 ended
    `datagen simulate` and `datagen garments` in a numpy traceback after the body model had
    loaded."""
    out = tmp_path / ("out" if command == "garments" else "out.h5")
    r = run(command, "--seed", -1, "--out", out)
    assert r.returncode == 2
    assert "Invalid value for '--seed'" in r.stderr and "-1" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists()


@pytest.mark.parametrize("command, option, name, expected", [
    ("simulate", "--preview", "s.mp4", "a .gif (animated) or .png"),
    ("simulate", "--out", "s.hdf5", "a shard file name ending in .h5"),
    ("body", "--out", "b.txt", "a shard file name ending in .h5"),
    ("preview", "--out", "p.jpg", "a .gif (animated) or .png"),
])
def test_an_output_name_no_writer_or_reader_takes_is_refused_before_any_work(
        tmp_path, monkeypatch, command, option, name, expected):
    """`datagen simulate --preview s.mp4` ran the whole scene, wrote the shard and then ended in
    imageio's traceback; a shard named s.hdf5 was written where a folder's reader and `datagen
    validate` (*.h5) never look. Both are refused as the command line is read."""
    from click.testing import CliRunner

    import datagen.body.anny_model as anny_model
    from datagen.cli import main

    def no_work():
        raise AssertionError(f"the body model was built before {option} was checked")

    monkeypatch.setattr(anny_model, "default_body_model", no_work)
    target = tmp_path / name
    args = {"simulate": ["simulate", "--out", str(tmp_path / "s.h5")],
            "body": ["body"], "preview": ["preview", str(tmp_path)]}[command]
    result = CliRunner().invoke(main, [*args, option, str(target)])
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '{option}'" in result.output and expected in result.output
    assert repr(str(target)) in result.output
    assert not any(tmp_path.iterdir())


def test_body_options_the_recipe_draws_are_refused_with_a_pipeline(tmp_path):
    """With --pipeline the recipe draws the subject and the motion's length: --seed and
    --frames were ignored without a word, and --index -1 ended in a numpy traceback."""
    out = tmp_path / "out.h5"
    recipe = Path(__file__).parents[1] / "pipelines" / "default.yaml"
    r = run("body", "--pipeline", recipe, "--frames", 3, "--seed", 4, "--out", out)
    assert r.returncode == 2
    assert "--seed and --frames cannot be used with --pipeline" in r.stderr, r.stderr
    r = run("body", "--pipeline", recipe, "--index", -1, "--out", out)
    assert r.returncode == 2 and "Invalid value for '--index'" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    r = run("body", "--pipeline", recipe, "--fps", 60, "--out", out)
    assert r.returncode == 2, r.stderr
    assert "--fps cannot be used with --pipeline" in r.stderr, r.stderr


def test_a_motion_given_with_a_pipeline_keeps_the_recipes_rate_and_lead_in(tmp_path):
    """--motion with --pipeline changes the motion's source only: its frames, rate and lead-in
    stay the recipe's (the override was drawn at 30 fps with a 15-frame lead-in)."""
    from datagen.io.shard import ShardReader

    text = (Path(__file__).parents[1] / "pipelines" / "default.yaml").read_text()
    text = (text.replace("frames: 90 ", "frames: 4 ").replace("fps: 30", "fps: 20")
            .replace("lead_in: 15 ", "lead_in: 3 ")
            .replace("sources: {procedural: 3, bvh: 1}", "sources: {procedural: 1}"))
    recipe = tmp_path / "slow.yaml"
    recipe.write_text(text)
    out = tmp_path / "b.h5"
    r = run("body", "--pipeline", recipe, "--motion", "jump", "--store-vertices", "--out", out)
    assert r.returncode == 0, r.stderr
    with ShardReader(out) as reader:
        (seq,) = reader.sequence_ids()
        g = reader.group(seq)
        assert (g.attrs["fps"], g.attrs["action"]) == (20.0, "jump")
        assert g["body"]["poses"].shape == (4, 72)


def test_the_output_rate_reaches_the_scene_with_a_lead_in_as_long_in_time(monkeypatch, tmp_path):
    """`simulate --fps`: the motion is drawn at that rate and its lead-in from rest lasts the
    default's 0.5 s (15 frames at 30 fps, 30 at 60, 12 at 24)."""
    from click.testing import CliRunner

    import datagen.body.anny_model as anny_model
    import datagen.pipeline.stages as stages
    from datagen.cli import main

    monkeypatch.setattr(anny_model, "default_body_model", lambda: None)
    motions = []

    def spy(spec, model, fabrics=None):
        motions.append(spec.motion)
        record = sf.make_record(0).record
        record.sim.report["simulated_seconds_per_wall_second"] = 1.0
        return record

    monkeypatch.setattr(stages, "run_sequence", spy)
    for fps in ("60", "24", "30"):
        result = CliRunner().invoke(main, ["simulate", "--fps", fps, "--frames", "4",
                                           "--out", str(tmp_path / f"{fps}.h5")])
        assert result.exit_code == 0, result.output
    assert [(m.fps, m.frames, m.lead_in) for m in motions] == [
        (60.0, 4, 30), (24.0, 4, 12), (30.0, 4, 15)]
    result = CliRunner().invoke(main, ["simulate", "--fps", "0", "--out", str(tmp_path / "0.h5")])
    assert result.exit_code == 2 and "Invalid value for '--fps'" in result.output


@pytest.mark.parametrize("wind", ["nan,0,0", "1,inf,0", "1,2"])
def test_a_wind_that_is_not_three_finite_numbers_is_refused(tmp_path, wind):
    """float() takes 'nan': a NaN wind was accepted, and the scene then ran without wind
    (its strength compared false against zero) and said nothing."""
    out = tmp_path / "out.h5"
    r = run("simulate", "--wind", wind, "--frames", 1, "--out", out)
    assert r.returncode == 2
    assert "Invalid value for --wind" in r.stderr and repr(wind) in r.stderr, r.stderr
    assert not out.exists()


def test_an_smpl_model_file_without_the_smpl_body_model_is_refused(tmp_path):
    """`--smpl-model FILE` alone ran Anny and left the user's model file unread, silently."""
    model = tmp_path / "model.npz"
    np.savez(model, v_template=np.zeros((4, 3)))
    out = tmp_path / "out.h5"
    r = run("body", "--smpl-model", model, "--frames", 1, "--out", out)
    assert r.returncode == 2
    assert "--smpl-model is read with --body-model smpl only (the body model is anny)" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


def test_a_subject_its_motion_drives_into_itself_is_refused_with_what_to_do(tmp_path):
    """The body stage rejects a subject whose motion puts one body part deep inside another
    (beyond what its repair may move). A one-scene command says so in one line, names the
    parts and frames, and says what the user can change: --seed draws the subject, and another
    subject performs the same motion. Seed 15's heavy, muscular subject in the procedural jump
    drives the upper arm 3-6 cm into the torso at the armpit as the arms swing up for take-off
    (2 of seeds 0-19 were so in the jump, none in the other actions: 2026-12-05); seed 16's
    does not."""
    out = tmp_path / "b.h5"
    r = run("body", "--seed", 15, "--motion", "jump", "--frames", 40, "--out", out)
    assert r.returncode == 2
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error: rejected at body: body self-intersection spine_mid/"
                               "upperarm_"), lines[0]
    assert "(frames 4" in lines[0]  # the take-off, after the 15 frames of lead-in
    assert lines[0].endswith("another --seed draws another subject"), lines[0]
    assert not out.exists() and not Path(str(out) + ".tmp").exists()
    r = run("body", "--seed", 16, "--motion", "jump", "--frames", 40, "--out", out)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("stage, hinted", [("body", True), ("simulate", False)])
def test_simulate_says_where_a_scene_was_rejected_and_what_to_change(tmp_path, monkeypatch,
                                                                     stage, hinted):
    """`datagen simulate` turns a rejected scene into one error line with the stage, the reason
    and the frames; only a rejection at the body stage is the subject's, so only there does it
    point to --seed. (The scene is the pipeline's record, rejected as the stage would: the test
    is about the command's message.)"""
    from click.testing import CliRunner

    import datagen.body.anny_model as anny_model
    import datagen.pipeline.stages as stages
    from datagen.cli import main
    from datagen.errors import RejectedSequence

    def rejected(spec, model, fabrics=None):
        record = stages.SequenceRecord(spec=spec, status="ok")
        stages.mark_rejected(record, RejectedSequence(stage, "why it was", (47, 50)))
        return record

    monkeypatch.setattr(anny_model, "default_body_model", lambda: None)
    monkeypatch.setattr(stages, "run_sequence", rejected)
    out = tmp_path / "s.h5"
    result = CliRunner().invoke(main, ["simulate", "--out", str(out)])
    assert result.exit_code == 2
    line = f"error: scene rejected at {stage}: why it was (frames 47-50)"
    if hinted:
        line += ("; the subject that --seed draws cannot perform this motion within the body "
                 "stage's bounds (docs/recipes.md, `body`); another --seed draws another subject")
    assert result.stderr.strip() == line
    assert not out.exists()
