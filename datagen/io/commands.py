"""`datagen validate`, `datagen export` and `datagen preview`: commands on written datasets.

Registered on the main group by datagen/cli.py (`main.add_command(...)`). Heavy imports happen
inside the commands so that `datagen --help` stays instant.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from datagen.cli_paths import preview_path
from datagen.errors import DatagenError, user_errors

EXPORT_FORMATS = ("obj", "pc2", "ply")


def _sequence_of(reader, sequence: str | None) -> str:
    """The requested sequence, or the only one when none is named."""
    from datagen.errors import InputError

    if sequence is not None:
        reader.shard_of(sequence)  # a one-line error naming the known ids when unknown
        return sequence
    ids = reader.sequence_ids()
    if len(ids) != 1:
        shown = ", ".join(ids[:5]) + (", ..." if len(ids) > 5 else "")
        raise InputError(reader.path, "--sequence", f"a sequence id ({shown})",
                         None if ids else "no sequences")
    return ids[0]


_SEQUENCE_HELP = "Sequence id, e.g. 7-000003 (may be left out when FILE holds only one)."


@click.command("validate")
@click.argument("path", type=click.Path(exists=True))
@click.option("--json", "as_json", is_flag=True, help="Print a JSON report instead of text.")
@click.option("--qa", type=click.Choice(["error", "warning", "off"]), default="error",
              show_default=True,
              help="How to treat QA series beyond their limits (deep penetration, strain over "
                   "the fabric's max_strain, negative energy).")
@user_errors
def validate(path: str, as_json: bool, qa: str) -> None:
    """Check a dataset folder or one shard: format version, every dataset's SHA-256, shapes and
    dtypes, finite values, QA limits, and that manifest.jsonl agrees with the shards.

    Prints one line per problem (file, sequence, what is wrong) and a summary; exits 1 when
    there are errors. Leftover *.tmp files are warnings.
    """
    from datagen.io.validate import validate_report

    report = validate_report(path, qa=qa)
    if as_json:
        click.echo(json.dumps(report.as_dict(), indent=1))
    else:
        for problem in report.problems:
            click.echo(str(problem))
        click.echo(report.summary())
    if not report.ok:
        sys.exit(1)


@click.command("export")
@click.argument("file", type=click.Path(exists=True))
@click.option("--sequence", "sequence", default=None, help=_SEQUENCE_HELP)
@click.option("--format", "fmt", type=click.Choice(EXPORT_FORMATS), required=True,
              help="obj: one OBJ per frame per mesh; pc2: one point cache per mesh plus its "
                   "OBJ; ply: one binary PLY per frame per mesh.")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Output folder (created).")
@click.option("--body/--no-body", default=True, show_default=True,
              help="Export the posed body too.")
@user_errors
def export(file: str, sequence: str | None, fmt: str, out: str, body: bool) -> None:
    """Export one sequence's garments (and body) from a shard or a dataset folder.

    \b
    Files in --out, per mesh NAME (each garment, and `body`):
      obj  NAME_0000.obj, NAME_0001.obj, ...   one per frame
      ply  NAME_0000.ply, ...                  one per frame, binary
      pc2  NAME.pc2 + NAME.obj                 a point cache and the mesh at frame 0

    \b
    Playing a PC2 in Blender: import NAME.obj keeping the vertex order (Blender 4 does;
    older importers need "Keep Vert Order" and no splitting) with Up axis Z and Forward
    axis Y (the data is z-up, in metres), add a Mesh Cache modifier, set its format to PC2
    and its file path to NAME.pc2. The cache holds one sample per stored frame, from 0.
    """
    from datagen.io.export import write_obj, write_obj_sequence, write_pc2, write_ply
    from datagen.io.reader import DatasetReader

    out_dir = Path(out)
    with DatasetReader(file) as reader:
        sid = _sequence_of(reader, sequence)
        meshes = {name: (g["vertices"], g["faces"])
                  for name, g in reader.garments(sid).items() if "vertices" in g}
        if body:
            b = reader.body(sid)
            meshes["body"] = (b["vertices"], b["faces"])
        fps = float(reader.info(sid)["fps"])
    if not meshes:
        raise DatagenError(f"{file}: sequence {sid} has no simulated garments and --no-body")
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name, (frames, faces) in meshes.items():
        if fmt == "obj":
            written += write_obj_sequence(out_dir, name, frames, faces)
        elif fmt == "ply":
            for f, vertices in enumerate(frames):
                path = out_dir / f"{name}_{f:04d}.ply"
                write_ply(path, vertices, faces)
                written.append(path)
        else:
            write_pc2(out_dir / f"{name}.pc2", frames, fps=fps)
            write_obj(out_dir / f"{name}.obj", frames[0], faces)
            written += [out_dir / f"{name}.pc2", out_dir / f"{name}.obj"]
    n_frames = len(next(iter(meshes.values()))[0])
    click.echo(f"wrote {len(written)} {fmt} file(s) to {out_dir}: sequence {sid}, "
               f"{n_frames} frames, meshes {', '.join(meshes)}")


@click.command("preview")
@click.argument("file", type=click.Path(exists=True))
@click.option("--sequence", "sequence", default=None, help=_SEQUENCE_HELP)
@click.option("--out", required=True, type=click.Path(dir_okay=False), callback=preview_path,
              help="X.gif (animated) or X.png (a 2x2 grid of four frames).")
@click.option("--every", default=2, show_default=True, type=click.IntRange(min=1),
              help="GIF: render every N-th frame.")
@click.option("--height", default=320, show_default=True, type=click.IntRange(min=16),
              help="Height of each picture in pixels.")
@user_errors
def preview(file: str, sequence: str | None, out: str, every: int, height: int) -> None:
    """Render a stored sequence, body and garments, from the front and the side."""
    from datagen.io.reader import DatasetReader
    from datagen.render import BODY_COLOUR, GARMENT_COLOURS, MeshLayer, write_preview

    with DatasetReader(file) as reader:
        sid = _sequence_of(reader, sequence)
        body = reader.body(sid)
        garments = [g for g in reader.garments(sid).values() if "vertices" in g]
    n = len(body["vertices"])

    def layers(f: int) -> list[MeshLayer]:
        out_layers = [MeshLayer(body["vertices"][f], body["faces"], BODY_COLOUR)]
        for k, g in enumerate(garments):
            colour = GARMENT_COLOURS[k % len(GARMENT_COLOURS)]
            out_layers.append(MeshLayer(g["vertices"][f], g["faces"], colour, two_sided=True))
        return out_layers

    picks = write_preview(out, layers, n, body["fps"], every, height)
    click.echo(f"wrote {out}: sequence {sid}, frames {', '.join(map(str, picks[:8]))}"
               f"{', ...' if len(picks) > 8 else ''} of {n}")


COMMANDS = (validate, export, preview)
