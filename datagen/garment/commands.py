"""`datagen templates build|check`: rebuild the shipped garment templates, validate any template.

Registered in datagen/cli.py with `main.add_command(templates)`. Heavy imports happen inside the
commands so `--help` stays instant.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from datagen.errors import DatagenError

DEFAULT_OUT = Path(__file__).resolve().parents[2] / "templates"


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def templates() -> None:
    """Garment templates: build the shipped ones, check any OBJ + JSON sidecar pair."""


@templates.command()
@click.option(
    "--resolution",
    default=0.01,  # build.SHIPPED_RESOLUTION (not imported: the CLI must start fast)
    show_default=True,
    type=click.FloatRange(min=0.004, max=0.05),
    help="Target edge length in metres.",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False),
    default=str(DEFAULT_OUT),
    show_default=True,
    help="Directory that receives <gender>/<name>.obj and .json.",
)
@click.option(
    "--only",
    multiple=True,
    type=click.Choice(["tshirt", "top", "trousers", "skirt"]),
    help="Build only these garments (repeatable; default: all four).",
)
@click.option(
    "--gender",
    "genders",
    multiple=True,
    type=click.Choice(["female", "male"]),
    help="Build only for these genders (repeatable; default: both).",
)
def build(resolution: float, out: str, only: tuple[str, ...], genders: tuple[str, ...]) -> None:
    """Draft every template on Anny's neutral rest body (female and male) and write them, with a
    line of statistics per template. Takes a minute or two."""
    from datagen.garment.build import GENDERS, TEMPLATE_NAMES, build_all

    start = time.perf_counter()
    click.echo(f"building garment templates at {resolution:g} m into {out}", err=True)

    def report(s: dict) -> None:
        click.echo(
            f"{s['gender']:>6} {s['name']:<8} {s['vertices']:>6} vertices {s['faces']:>6} faces  "
            f"mean edge {1000 * s['mean_edge']:.2f} mm  min angle {s['min_angle']:.1f} deg  "
            f"min clearance {1000 * s['min_clearance']:.1f} mm  {s['seconds']:.1f} s  {s['path']}"
        )

    try:
        build_all(out, resolution, only or TEMPLATE_NAMES, genders or GENDERS, report)
    except DatagenError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    click.echo(f"done in {time.perf_counter() - start:.0f} s", err=True)


@templates.command()
@click.argument("paths", nargs=-1, required=True, type=click.Path())
@click.option(
    "--body",
    "body_obj",
    type=click.Path(dir_okay=False),
    help="Check clearance against this body mesh (OBJ, metres, same frame) instead of the rest "
    "body named in each sidecar.",
)
@click.option(
    "--no-body",
    is_flag=True,
    help="Skip the clearance check.",
)
def check(paths: tuple[str, ...], body_obj: str | None, no_body: bool) -> None:
    """Check templates (each PATH an .obj, a .json, their common stem, or a folder: every .obj
    under it): topology, element quality, self-intersections, the sidecar's loops/regions/axes/
    rows, and clearance from the rest body the sidecar names (or --body). Prints OK or every
    problem; exits non-zero on any problem."""
    from datagen.garment.template import (
        BodyProximity,
        check_template,
        expand_template_paths,
        load_sidecar,
        read_obj,
    )

    try:
        targets = expand_template_paths(paths)
    except DatagenError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)

    bodies: dict[str, BodyProximity] = {}
    explicit = None
    if body_obj and not no_body:
        try:
            bv, bf = read_obj(body_obj)
        except DatagenError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
        explicit = BodyProximity(bv, bf)
    failed = 0
    for obj_path, json_path in targets:
        body = explicit
        note = ""
        if not no_body and explicit is None:
            try:
                spec = load_sidecar(json_path).get("body") or {}
                key = repr(sorted(spec.items(), key=lambda kv: kv[0]))
                if key not in bodies and spec:
                    bodies[key] = _body_proximity(spec, json_path)
                body = bodies.get(key)
                if body is None:
                    note = " (clearance not checked: the sidecar names no body)"
            except DatagenError as exc:
                click.echo(f"{obj_path}: {exc}")
                failed += 1
                continue
        problems = check_template(obj_path, body=body)
        if problems:
            failed += 1
            click.echo(f"{obj_path}: {len(problems)} problem{'s' if len(problems) > 1 else ''}")
            for problem in problems:
                click.echo(f"  {problem}")
        else:
            click.echo(f"{obj_path}: OK{note}")
    if failed:
        click.echo(f"{failed} of {len(targets)} templates have problems", err=True)
        sys.exit(1)


def _body_proximity(spec: dict, source: Path):
    """The rest body a sidecar names ({"model": "anny", "gender", "shape": {name: value}})."""
    from datagen.errors import InputError
    from datagen.garment.template import BodyProximity

    model = spec.get("model")
    if model != "anny":
        raise InputError(source, "body.model", "'anny' (the embedded body model)", model)
    from datagen.body.anny_model import NEUTRAL_SHAPE, SHAPE_NAMES, default_body_model

    gender = spec.get("gender")
    if gender not in ("female", "male"):
        raise InputError(source, "body.gender", "'female' or 'male'", gender)
    shape_spec = spec.get("shape") or {}
    shape = NEUTRAL_SHAPE.copy()
    for k, name in enumerate(SHAPE_NAMES):
        if name in shape_spec:
            shape[k] = float(shape_spec[name])
    unknown = sorted(set(shape_spec) - set(SHAPE_NAMES))
    if unknown:
        raise InputError(
            source, f"body.shape.{unknown[0]}", f"one of {', '.join(SHAPE_NAMES)}", unknown[0]
        )
    rest = default_body_model().rest_body(gender, shape)
    return BodyProximity(rest.vertices, rest.faces)


@click.command()
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="Draws the subject and the outfit.")
@click.option(
    "--spec",
    "spec_path",
    type=click.Path(dir_okay=False, exists=True),
    help="A scene spec JSON (an outfit.json written by this command, or a dataset's spec) "
    "instead of drawing one.",
)
@click.option(
    "--pipeline",
    type=click.Path(dir_okay=False, exists=True),
    help="Draw with this recipe's outfit and subject rules (default: the built-in defaults).",
)
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
def garments(seed: int, spec_path: str | None, pipeline: str | None, out: str) -> None:
    """Draw an outfit by CLOTH3D's rules (or take --spec), fit it to the subject's rest body and
    write each garment (OBJ + JSON sidecar), body.obj, outfit.json and preview.png."""
    from datagen.body.anny_model import default_body_model
    from datagen.body.sequence import shape_vector
    from datagen.garment.fitted import load_spec, spec_for_seed, write_fitted_outfit
    from datagen.garment.outfit import make_outfit

    try:
        spec = load_spec(spec_path) if spec_path else spec_for_seed(seed, pipeline)
        model = default_body_model()
        rest = model.rest_body(spec.subject.gender, shape_vector(model, spec.subject))
        start = time.perf_counter()
        fitted = make_outfit(spec.outfit, rest, model)
        seconds = time.perf_counter() - start
        write_fitted_outfit(out, spec, rest, fitted)
    except DatagenError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    parts = ", ".join(
        f"{g.name} ({g.meta.get('variant', g.category)}, {g.fabric}, {len(g.vertices)} vertices)"
        for g in fitted
    )
    click.echo(
        f"{out}: {spec.subject.gender} subject, {parts}; fitted in {seconds:.2f} s "
        f"(tightness {spec.outfit.tightness[0]:+.2f}, {spec.outfit.tightness[1]:+.2f})"
    )
