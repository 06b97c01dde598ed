"""The `datagen` command line. Heavy imports happen inside commands so `--help` is instant."""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import click

from datagen.cli_paths import preview_path, shard_path
from datagen.errors import DatagenError, InputError, RejectedSequence, user_errors


def body_rejection_hint(pipeline: bool) -> str:
    """What the user of a one-scene command can do when the body stage rejects the subject:
    only self-intersections beyond the body bounds reject there (body.sequence), so another
    subject may perform the same motion."""
    if pipeline:
        return ("the subject that --index draws cannot perform this motion within the body "
                "bounds of the recipe's `body` section (docs/recipes.md); another --index "
                "draws another subject")
    return ("the subject that --seed draws cannot perform this motion within the body stage's "
            "bounds (docs/recipes.md, `body`); another --seed draws another subject")


LOG_REDRAW_S = 10.0  # seconds between a progress bar's redraws when stderr is a file


class FrameBar:
    """A tqdm bar (on stderr) over the frames of each simulation run that it hears of
    (datagen.sim.progress): a new bar for each run, so an escalated sequence shows the run it
    did not keep and the one at finer steps."""

    def __init__(self) -> None:
        self.bar = None

    def __call__(self, done: int, total: int, settings: str) -> None:
        from tqdm import tqdm

        if self.bar is None or done == 1:  # a run's first frame: a new run
            self.close()
            # In a log (stderr not a terminal) each redraw is another ~100 characters, one
            # per frame: a redraw every ten seconds tells a log reader as much.
            self.bar = tqdm(total=total, unit="frame", desc=f"simulating ({settings})",
                            dynamic_ncols=True,
                            mininterval=0.1 if sys.stderr.isatty() else LOG_REDRAW_S)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="datagen")
def main() -> None:
    """CLOTH3D-style synthetic data: animated bodies, unique outfits, Taichi cloth, HDF5 shards.

    \b
    Typical use:
      datagen body --motion walk --frames 120 --out body.h5
      datagen inspect body.h5
    """


def _motion_options(func):
    func = click.option(
        "--amass",
        "amass",
        type=click.Path(dir_okay=False),
        help="AMASS-style .npz (poses, trans, mocap_framerate).",
    )(func)
    func = click.option(
        "--bvh",
        "bvh",
        type=click.Path(dir_okay=False),
        help="BVH motion capture file (MotionBuilder, Daz or ASF-named skeleton).",
    )(func)
    func = click.option(
        "--motion",
        "action",
        default=None,
        help="Procedural action (walk, run, jump, spin, ...). Default: walk.",
    )(func)
    return func


def _fps_option(func):
    return click.option(
        "--fps",
        type=click.FloatRange(min=0.0, min_open=True),
        default=30.0,
        show_default=True,
        help="Output frame rate. The motion is sampled at it, the lead-in from rest lasts as "
             "long at any rate (15 frames at 30 fps), and so do the simulator's steps.",
    )(func)


def single_scene_spec(
    seed: int,
    action: str | None,
    bvh: str | None,
    amass: str | None,
    frames: int,
    gender: str | None,
    fps: float = 30.0,
    lead_in: int | None = None,
):
    """The SceneSpec of a one-off scene from CLI options: the seed draws the subject, options
    fix the rest. `lead_in` in frames; None: as long in time as a recipe's default."""
    from dataclasses import replace

    from datagen.recipe import LoadedRecipe, MotionConfig, Recipe
    from datagen.sampling import sample_scene
    from datagen.spec import MotionSpec

    if lead_in is None:  # at least a frame: the outfit is fitted to the rest pose
        lead_in = max(1, round(MotionConfig.lead_in * fps / MotionConfig.fps))

    chosen = [x for x in (action, bvh, amass) if x]
    if len(chosen) > 1:
        raise click.UsageError("give at most one of --motion, --bvh, --amass")
    recipe = Recipe(
        name="single",
        seed=seed,
        sequences=1,
        test_fraction=0.0,
        motion=MotionConfig(
            frames=frames, fps=fps, lead_in=lead_in, randomize_params=False, mirror_probability=0.0
        ),
    )
    spec = sample_scene(LoadedRecipe(recipe, Path.cwd() / "cli.yaml"), 0)
    if bvh or amass:
        source = "bvh" if bvh else "amass"
        file = str(Path(bvh or amass).resolve())
        motion = MotionSpec(
            source=source,
            action=Path(file).stem,
            file=file,
            start=0.0,
            frames=frames,
            fps=fps,
            lead_in=lead_in,
        )
    else:
        from datagen.motion.procedural import ACTIONS, action_parameters

        name = action or "walk"
        if name not in ACTIONS:
            raise click.BadParameter(
                f"unknown action {name!r}; known: {', '.join(sorted(ACTIONS))}",
                param_hint="--motion",
            )
        params = {k: p.default for k, p in sorted(action_parameters(name).items())}
        motion = MotionSpec(
            source="procedural", action=name, params=params, frames=frames, fps=fps, lead_in=lead_in
        )
    subject = spec.subject if gender is None else replace(spec.subject, gender=gender)
    return replace(spec, motion=motion, subject=subject)


def body_model_from_options(name: str, smpl_model: str | None):
    """The body model a command runs with: Anny (embedded) or a user's SMPL file."""
    if name == "smpl":
        if not smpl_model:
            raise click.UsageError("--body-model smpl needs --smpl-model FILE (.npz or .pkl)")
        from datagen.body.smpl_model import SMPLBody

        return SMPLBody({"neutral": smpl_model})
    if smpl_model:
        # Anny would run and the user's model file go unread without a word.
        raise click.UsageError(f"--smpl-model is read with --body-model smpl only (the body "
                               f"model is {name}); add --body-model smpl")
    from datagen.body.anny_model import default_body_model

    return default_body_model()


@main.command()
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="Draws the subject's shape and gender.")
@click.option(
    "--pipeline",
    type=click.Path(dir_okay=False),
    help="Draw the whole scene from a recipe YAML (its seed) instead of --seed.",
)
@click.option("--index", default=0, show_default=True, type=click.IntRange(min=0),
              help="Sequence index within --pipeline.")
@_motion_options
@click.option(
    "--frames",
    default=120,
    show_default=True,
    type=click.IntRange(min=1),
    help="Output frames at --fps (a lead-in from rest is added before them).",
)
@_fps_option
@click.option(
    "--gender",
    type=click.Choice(["female", "male"]),
    default=None,
    help="Override the sampled gender.",
)
@click.option(
    "--body-model",
    type=click.Choice(["anny", "smpl"]),
    default="anny",
    show_default=True,
    help="Anny is embedded; SMPL needs your licensed model file.",
)
@click.option(
    "--smpl-model",
    type=click.Path(dir_okay=False),
    help="SMPL model file (.npz, or .pkl read by a restricted unpickler).",
)
@click.option(
    "--store-vertices",
    is_flag=True,
    help="Store posed body vertices instead of skinning data (larger).",
)
@click.option("--out", required=True, type=click.Path(dir_okay=False), callback=shard_path,
              help="Output shard (.h5).")
@user_errors
def body(
    seed,
    pipeline,
    index,
    action,
    bvh,
    amass,
    frames,
    fps,
    gender,
    body_model,
    smpl_model,
    store_vertices,
    out,
) -> None:
    """Write one body sequence (shape, motion, self-collisions repaired) to a shard."""
    from dataclasses import replace

    from datagen.body.sequence import build_body_sequence
    from datagen.io.shard import ShardWriter
    from datagen.motion.load import motion_from_spec
    from datagen.recipe import BodyConfig

    base_dir = None
    config = BodyConfig()
    ctx = click.get_current_context()
    given = [f"--{name}" for name in ("seed", "frames", "fps")
             if ctx.get_parameter_source(name) == click.core.ParameterSource.COMMANDLINE]
    if pipeline and given:
        # The recipe draws them; taking one silently would write a scene not asked for.
        raise click.UsageError(f"{' and '.join(given)} cannot be used with --pipeline, whose "
                               f"recipe draws the subject and sets the motion's length and "
                               f"frame rate")
    if pipeline:
        from datagen.recipe import load_recipe
        from datagen.sampling import sample_scene

        loaded = load_recipe(pipeline)
        spec = sample_scene(loaded, index)
        base_dir, config = loaded.base_dir, loaded.recipe.body
        if action or bvh or amass:
            # Only the motion's source changes: its length, rate and lead-in stay the recipe's.
            override = single_scene_spec(seed, action, bvh, amass, spec.motion.frames, gender,
                                         spec.motion.fps, spec.motion.lead_in)
            spec = replace(spec, motion=override.motion)
        if gender:
            spec = replace(spec, subject=replace(spec.subject, gender=gender))
    else:
        spec = single_scene_spec(seed, action, bvh, amass, frames, gender, fps)
    model = body_model_from_options(body_model, smpl_model)
    if body_model == "smpl":
        names = model.shape_names
        spec = replace(
            spec, subject=replace(spec.subject, model="smpl", shape={n: 0.0 for n in names})
        )
    motion = motion_from_spec(spec.motion, base_dir)
    try:
        seq = build_body_sequence(spec.subject, motion, spec.motion.lead_in, model, config)
    except RejectedSequence as exc:
        raise DatagenError(f"{exc}; {body_rejection_hint(bool(pipeline))}") from exc
    with ShardWriter(out) as writer:
        group = writer.sequence_group(spec)
        writer.add_body(group, seq, store_vertices=store_vertices)
    sc = seq.self_collision
    click.echo(
        f"wrote {out}: sequence {spec.sequence_id}, {spec.subject.gender}, action "
        f"{spec.motion.action}, {spec.motion.frames} frames; self-collision: "
        f"{sc.frames_with_contact} frames with contact, {sc.repaired_vertices} vertex repairs"
        + (f"; skinning sank parts into each other across a flexed joint in "
           f"{len(sc.flexion_overlap_frames)} frames ("
           + ", ".join(f"{j} {len(f)}" for j, f in sc.flexion_overlap_by_joint.items())
           + "; up to "
           f"{sc.flexion_overlap_max_depth * 100:.1f} cm deep), separated with "
           f"{sc.flexion_residual_pairs} triangle pairs left crossing"
           if sc.flexion_overlap_frames else "")
    )


GARMENT_TYPES = ("tshirt", "shirt", "polo", "top", "trousers", "skirt", "jumpsuit", "dress")


def scene_with_outfit(spec, garment: str | None, fabric: str | None, seed: int):
    """The spec with an outfit drawn by CLOTH3D's rules from `seed`, or with only `garment`."""
    from dataclasses import replace

    from datagen.garment.outfit import sample_outfit
    from datagen.recipe import LoadedRecipe, Recipe
    from datagen.sampling import section_rng

    outfit_cfg: dict = {}
    if garment in ("jumpsuit", "dress"):
        outfit_cfg = {"full_body_probability": 1.0, "full": {garment: 1.0}, "male_skirts": True}
    elif garment in ("tshirt", "shirt", "polo", "top"):
        outfit_cfg = {"full_body_probability": 0.0, "upper": {garment: 1.0}}
    elif garment in ("trousers", "skirt"):
        outfit_cfg = {"full_body_probability": 0.0, "lower": {garment: 1.0}, "male_skirts": True}
    else:
        outfit_cfg = {"male_skirts": False}
    loaded = LoadedRecipe(Recipe(name="single", seed=seed, sequences=1, outfit=outfit_cfg),
                          Path.cwd() / "cli.yaml")
    outfit = sample_outfit(loaded, section_rng(seed, 0, 3), spec.subject)
    parts = outfit.garments
    if garment in ("tshirt", "shirt", "polo", "top"):
        parts = tuple(g for g in parts if g.name == "upper")
    elif garment in ("trousers", "skirt"):
        parts = tuple(g for g in parts if g.name == "lower")
    if fabric:
        parts = tuple(replace(g, fabric=fabric) for g in parts)
    return replace(spec, outfit=replace(outfit, garments=parts))


@main.command()
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="Draws the subject and the outfit.")
@click.option("--fabric", default=None,
              help="Fabric of every garment: cotton, silk, denim, leather, rubber, or one from "
                   "--fabrics-file. Default: drawn by the CLOTH3D rules.")
@click.option("--fabrics-file", type=click.Path(dir_okay=False),
              help="YAML with user fabrics (docs/fabrics.md).")
@click.option("--garment", type=click.Choice(GARMENT_TYPES), default=None,
              help="Simulate only this garment. Default: a whole outfit drawn from --seed.")
@_motion_options
@click.option("--frames", default=60, show_default=True, type=click.IntRange(min=1),
              help="Output frames at --fps (after a lead-in from rest).")
@_fps_option
@click.option("--solver", type=click.Choice(["xpbd", "implicit", "explicit"]), default="xpbd",
              show_default=True)
@click.option("--quality", type=click.Choice(["draft", "default", "reference"]),
              default="default", show_default=True, help="Substeps/iterations preset.")
@click.option("--effects", default="auto", show_default=True,
              help="auto (derived from the scene), all, a comma list of effects, or auto or all "
                   "with changes (auto,-self_collision; auto,+pressure_drag adds the air's "
                   "quadratic drag on the panels).")
@click.option("--wind", default=None,
              help="Wind velocity 'x,y,z' in m/s (turns wind on, and with it the air's "
                   "pressure on the panels, pressure_drag, the law wind pushes by).")
@click.option("--out", required=True, type=click.Path(dir_okay=False), callback=shard_path,
              help="Output shard (.h5).")
@click.option("--export-obj", type=click.Path(file_okay=False),
              help="Also write every frame of every garment (and the body) as OBJ here.")
@click.option("--preview", type=click.Path(dir_okay=False), callback=preview_path,
              help="Also render the sequence: .gif (animated) or .png (a few frames).")
@user_errors
def simulate(seed, fabric, fabrics_file, garment, action, bvh, amass, frames, fps, solver,
             quality, effects, wind, out, export_obj, preview) -> None:
    """Simulate one scene end to end (body, outfit, cloth) and write it to a shard."""
    from dataclasses import replace

    from datagen.body.anny_model import default_body_model
    from datagen.io.shard import ShardWriter, write_record
    from datagen.pipeline.stages import run_sequence
    from datagen.sim.effects import check_wind_request, split_effects_request, wind_blows
    from datagen.sim.fabrics import get_fabric, load_fabrics
    from datagen.sim.progress import frame_progress

    user_fabrics = load_fabrics(fabrics_file) if fabrics_file else {}
    if fabric:
        get_fabric(fabric, user_fabrics)  # a clear error for an unknown name, before any work
    split_effects_request(effects)  # likewise for --effects
    spec = single_scene_spec(seed, action, bvh, amass, frames, None, fps)
    spec = scene_with_outfit(spec, garment, fabric, seed)
    wind_v = None
    if wind:
        try:
            wind_v = tuple(float(x) for x in wind.split(","))
        except ValueError:
            wind_v = ()
        # float() takes 'nan' and 'inf'; a NaN wind would read as no wind at all.
        if len(wind_v) != 3 or not all(math.isfinite(v) for v in wind_v):
            raise click.BadParameter(f"expected 'x,y,z' in m/s, three finite numbers, got "
                                     f"{wind!r}", param_hint="--wind")
    effect_req = effects if effects in ("auto", "all") else tuple(effects.split(","))
    check_wind_request(effect_req, wind_blows(wind_v))  # before any work too
    spec = replace(spec, simulation=replace(spec.simulation, solver=solver, quality=quality,
                                            effects=effect_req, wind=wind_v))
    bar = FrameBar()
    try:
        with frame_progress(bar):
            record = run_sequence(spec, default_body_model(), fabrics=user_fabrics)
    finally:
        bar.close()
    if record.status != "ok":
        where = f" (frames {record.frames[0]}-{record.frames[1]})" if record.frames else ""
        hint = f"; {body_rejection_hint(False)}" if record.stage == "body" else ""
        raise DatagenError(f"scene rejected at {record.stage}: {record.reason}{where}{hint}")
    with ShardWriter(out) as writer:
        write_record(writer, record)
    sim = record.sim
    from datagen.sim.simulate import finer_steps_note

    rep = sim.report
    finer = finer_steps_note(rep)
    names = ", ".join(f"{g.name} ({g.meta.get('variant', g.category)}, {g.fabric}, "
                      f"{len(g.vertices)} vertices)" for g in record.garments)
    click.echo(
        f"wrote {out}: {spec.motion.action}, {rep['frames']} frames; garments: {names}\n"
        f"  {rep['solver']} {rep['substeps']}x{rep['iterations']}, effects: "
        f"{', '.join(rep['effects'])}\n"
        f"  simulated {rep['simulated_seconds_per_wall_second']:.2f} s per wall-clock second "
        f"({rep['wall_time_s']:.1f} s), retries {rep['retries']}"
        f"{f' ({finer})' if finer else ''}; QA: max strain "
        f"{float(sim.qa['strain_p999'].max()):.3f} (99.9th pct), at most "
        f"{100 * float(sim.qa['over_strain_share'].max()):.3f} % of springs over their "
        f"fabric's max_strain, deepest penetration share "
        f"{float(sim.qa['deep_share'].max()):.4f}"
    )
    if rep.get("escalated_from"):
        from datagen.pipeline.stages import escalation_note

        click.echo("  " + escalation_note(sim).removeprefix("; "))
    from datagen.pipeline.stages import over_qa_bounds

    # Written all the same (it is the scene asked for), but never as if it were dataset-grade.
    breached, reason = over_qa_bounds(record, user_fabrics)
    if breached:
        click.echo(f"warning: {out} breaks a QA bound, and a dataset run would reject this "
                   f"scene (stage qa): {reason}", err=True)
    start = record.body.lead_in_frames
    if export_obj:
        from datagen.io.export import write_obj_sequence

        for g in record.garments:
            write_obj_sequence(export_obj, g.name, sim.vertices[g.name], g.faces)
        write_obj_sequence(export_obj, "body", record.body.vertices[start:],
                           record.body.rest.faces)
    if preview:
        from datagen.render import preview_record

        preview_record(preview, record)


@main.command()
@click.option("--pipeline", required=True, type=click.Path(dir_okay=False),
              help="Recipe YAML (pipelines/default.yaml, pipelines/cloth3d.yaml, ...).")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Dataset folder; an existing run of the same recipe is resumed.")
@click.option("--n", type=int, default=None, help="Number of sequences (default: the recipe's).")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Local worker processes (default: the number of cores).")
@click.option("--scheduler", default=None,
              help="Dask scheduler address (tcp://host:port) instead of local processes.")
@click.option("--shard-size", type=click.IntRange(min=1), default=None,
              help="Sequences per shard (default: the recipe's).")
@click.option("--batch", type=click.IntRange(min=1), default=1, show_default=True,
              help="Sequences each worker simulates at once as one batch: for a GPU "
                   "(DATAGEN_TI_ARCH=cuda), where one scene is bound by kernel launches; "
                   "1 on CPUs.")
@click.option("--progress/--no-progress", default=True, show_default=True)
@user_errors
def dataset(pipeline, out, n, workers, scheduler, shard_size, batch, progress) -> None:
    """Run a recipe into a folder of shards, with a manifest and a dataset card; resumable."""
    from datagen.pipeline.dataset import run_dataset

    workers = workers or max(1, os.cpu_count() or 1)
    rows = run_dataset(pipeline, out, n=n, workers=workers, scheduler=scheduler,
                       shard_size=shard_size, progress=progress, batch=batch)
    ok = sum(r["status"] == "ok" for r in rows)
    click.echo(f"{out}: {ok} sequences, {len(rows) - ok} rejected; card: {out}/README.md")


@main.command()
@click.argument("path", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
@user_errors
def inspect(path, as_json) -> None:
    """Print what a shard holds: sequences, groups, dataset shapes and attributes."""
    from datagen.io.reader import shard_paths
    from datagen.io.shard import describe

    if Path(path).is_dir():
        # A dataset folder holds many shards: point at one, and at what describes the folder.
        shards = shard_paths(path)
        example = f", e.g. {shards[0]}" if shards else ""
        raise InputError(path, None, f"a shard file{example} (a dataset folder is described "
                         "by its card, README.md, and checked by `datagen validate`)",
                         "a folder")
    tree = describe(path)
    if as_json:
        click.echo(json.dumps(tree, indent=1))
        return

    def show(node: dict, name: str, depth: int) -> None:
        pad = "  " * depth
        click.echo(f"{pad}{name}/")
        for k, v in node["attrs"].items():
            text = json.dumps(v) if not isinstance(v, str) else v
            if len(text) > 100:
                text = text[:97] + "..."
            click.echo(f"{pad}  @{k} = {text}")
        for dname, ds in node["datasets"].items():
            click.echo(f"{pad}  {dname} {tuple(ds['shape'])} {ds['dtype']}")
        for gname, g in node["groups"].items():
            show(g, gname, depth + 1)

    click.echo(f"{path}: {len(tree['sequences'])} sequence(s)")
    show(tree, "", 0)


def _register_subcommands() -> None:
    from datagen.garment.commands import garments, templates
    from datagen.io.commands import COMMANDS

    for command in COMMANDS:
        main.add_command(command)
    main.add_command(templates)
    main.add_command(garments)
    from datagen.study.commands import bench

    main.add_command(bench)


_register_subcommands()

if __name__ == "__main__":
    main()
