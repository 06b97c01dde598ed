"""`datagen bench ...`: the studies that measure the simulator."""

from __future__ import annotations

from pathlib import Path

import click

REPO_DOC = Path(__file__).resolve().parents[2] / "docs" / "accuracy-vs-time.md"


@click.group()
def bench() -> None:
    """Studies of the simulator (accuracy against time)."""


@bench.command()
@click.option("--quick", is_flag=True, help="A small version (a coarse sheet, cotton) in minutes.")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Folder for accuracy.csv, summary.json and the plot.")
@click.option("--blender/--no-blender", default=True, show_default=True,
              help="Run Blender's series (skipped with a message when Blender is absent).")
@click.option("--doc", type=click.Path(dir_okay=False), default=None,
              help="Where the report goes (default: docs/accuracy-vs-time.md in a checkout, "
                   "else OUT/accuracy-vs-time.md; a --quick run writes to OUT so that it "
                   "never replaces the full study's page).")
@click.option("--report-only", is_flag=True,
              help="Run nothing: write the CSV, plot and report from the parts already "
                   "finished under OUT/parts (a stopped full run), naming the missing ones.")
@click.option("--part", "parts", multiple=True, metavar="SCENE/FABRIC",
              help="Measure only these parts of the plan (e.g. tshirt_walk/cotton; repeatable); "
                   "the others are reused when finished and listed as missing when not.")
def accuracy(quick: bool, out: str, blender: bool, doc: str | None, report_only: bool,
             parts: tuple[str, ...]) -> None:
    """Sweep solvers, substeps, iterations and resolutions against a converged reference.
    Each finished scene/fabric is kept under OUT/parts and reused by the next run."""
    from datagen.study.sweep import main_cli

    if doc is None and not quick and REPO_DOC.parent.is_dir():
        doc = str(REPO_DOC)  # otherwise main_cli writes OUT/accuracy-vs-time.md
    command = "datagen bench accuracy" + (" --quick" if quick else "") + f" --out {out}"
    summary = main_cli(out, quick, blender, doc, command, measure=not report_only,
                       only=set(parts) or None)
    click.echo(f"{out}: accuracy.csv, accuracy-vs-time.png; report {doc or out} "
               f"({summary['minutes']:.1f} min)")
