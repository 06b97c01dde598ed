"""docs/accuracy-vs-time.md from a study's rows and summary: the reference's convergence, the
table, the plot, the presets with their figures, and Blender's series beside ours."""

from __future__ import annotations

import shutil
from datetime import date
from pathlib import Path

import numpy as np

from datagen.study.sweep import CHAOS_MM, CONVERGED_MM, TWIN_METRES, Row


def _fmt(x: float, digits: int = 2) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def preset_rows(rows: list[Row], presets: dict[str, tuple[int, int]]) -> list[tuple[str, Row]]:
    out = []
    for name, (sub, it) in presets.items():
        for r in rows:
            if (r.series, r.substeps, r.iterations) == ("xpbd", sub, it) and r.status == "ok" \
                    and r.note == "":
                out.append((name, r))
    return out


def comparison(rows: list[Row], presets: dict[str, tuple[int, int]]) -> list[str]:
    """Per scene: the default preset against the cheapest Blender run with an error no lower."""
    lines = []
    for scene, fabric in sorted({(r.scene, r.fabric) for r in rows}):
        ours = [r for name, r in preset_rows(rows, presets) if name == "default"
                and (r.scene, r.fabric) == (scene, fabric)]
        peer = [r for r in rows if r.series == "blender" and (r.scene, r.fabric) == (scene,
                                                                                    fabric)]
        if not ours or not peer:
            continue
        d = ours[0]
        at_least = [b for b in peer if b.rms_mm >= d.rms_mm]
        if at_least:
            b = min(at_least, key=lambda r: r.seconds_per_sim_second)
            ratio = b.seconds_per_sim_second / d.seconds_per_sim_second
            verdict = "meets" if ratio >= 20 else "misses"
            lines.append(
                f"- {scene}, {fabric}: `default` {_fmt(d.rms_mm)} mm at "
                f"{_fmt(d.seconds_per_sim_second)} s per simulated second; Blender quality "
                f"{b.substeps} {_fmt(b.rms_mm)} mm at {_fmt(b.seconds_per_sim_second)} s: "
                f"**{ratio:.1f}x** faster at equal or lower error ({verdict} the 20x target)."
            )
        else:
            best = min(peer, key=lambda r: r.rms_mm)
            lines.append(
                f"- {scene}, {fabric}: `default` {_fmt(d.rms_mm)} mm at "
                f"{_fmt(d.seconds_per_sim_second)} s per simulated second; every Blender run "
                f"has a lower error (best: quality {best.substeps}, {_fmt(best.rms_mm)} mm at "
                f"{_fmt(best.seconds_per_sim_second)} s), so the target's condition is not met.")
    return lines


def write_report(doc: Path, out: Path, rows: list[Row], summary: dict,
                 presets: dict[str, tuple[int, int]], command: str) -> None:
    doc.parent.mkdir(parents=True, exist_ok=True)
    png = doc.with_suffix(".png")
    if (out / "accuracy-vs-time.png").resolve() != png.resolve():
        shutil.copyfile(out / "accuracy-vs-time.png", png)
    lines = [
        "# What accuracy costs in time",
        "",
        f"Written by `{command}` on {date.today().isoformat()} "
        f"({'quick' if summary['quick'] else 'full'} plan, {summary['minutes']:.0f} min; "
        f"Blender: {summary['blender']}). The CSV and the summary are in the command's output "
        "folder. Times are wall-clock seconds per simulated second on this machine; each scene "
        "and fabric (its reference, our runs and Blender's) was measured in one run, and the "
        "minutes are the sum over those runs.",
        *([] if not summary.get("missing_parts") else [
            "",
            f"**Partial: {len(summary['missing_parts'])} scene/fabric part(s) of the plan are "
            f"not measured yet: {', '.join(summary['missing_parts'])}.** The run keeps "
            "finished parts; running the same command again measures the rest."]),
        "",
        "## The converged reference",
        "",
        f"Per scene, the implicit solver in float64 at doubling substeps until halving the step "
        f"changes the trajectory by less than {CONVERGED_MM} mm RMS over the predictable "
        "horizon (next section); the change over the whole first second, chaos included, is "
        "beside it:",
        "",
        "| scene/fabric | substeps | run s | RMS to the previous level, predictable horizon "
        "(mm) | same, first second (mm) |",
        "|---|---|---|---|---|",
    ]
    for key, ladder in summary["ladders"].items():
        for e in ladder:
            if "failed" in e:
                lines.append(f"| {key} | {e['substeps']} | failed: {e['failed']} | | |")
                continue
            lines.append(f"| {key} | {e['substeps']} | {e['seconds']:.0f} | "
                         f"{_fmt(e.get('rms_to_previous_mm', np.nan), 3)} | "
                         f"{_fmt(e.get('rms_1s_to_previous_mm', np.nan), 3)} |")
    lines += [
        "",
        "## Why the error is measured over the predictable horizon",
        "",
        f"Cloth that folds on contact is chaotic: a twin of the reference started "
        f"{TWIN_METRES * 1e6:.0f} micrometre away leaves it by more than {CHAOS_MM:.0f} mm RMS "
        "after the frames below, whatever the step. A difference after that measures the "
        "scene's chaos, not a solver's discretisation error, so `rms_mm` (the plot's y axis) "
        "is taken over the predictable frames; `rms_1s_mm` over the first second is in the "
        "table too, and the final drape (`final_mm`) is what a static scene comes to.",
        "",
        "| scene/fabric | predictable frames (30 fps) |",
        "|---|---|",
    ]
    for key, frames in summary.get("predictable_frames", {}).items():
        lines.append(f"| {key} | {frames} |")
    lines += ["", "## The plot", "", f"![accuracy against time]({png.name})", "",
              "## The table", "",
              "| scene | fabric | resolution | series | substeps | iterations | vertices | "
              "s/sim-s | RMS mm (predictable) | RMS mm (1 s) | max mm | final mm | "
              "strain p99.9 | deep share | note |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        series = "blender q" + str(r.substeps) if r.series == "blender" else r.series
        lines.append(
            f"| {r.scene} | {r.fabric} | {r.resolution} | {series} | {r.substeps} | "
            f"{r.iterations} | {r.vertices} | {_fmt(r.seconds_per_sim_second)} | "
            f"{_fmt(r.rms_mm)} | {_fmt(r.rms_1s_mm)} | {_fmt(r.max_mm)} | {_fmt(r.final_mm)} | "
            f"{_fmt(r.strain_p999, 3)} | {_fmt(r.deep_share, 4)} | {r.status} {r.note} |")
    lines += ["", "## The presets", "",
              "| preset | substeps x iterations | scene/fabric | s/sim-s | RMS mm |",
              "|---|---|---|---|---|"]
    for name, r in preset_rows(rows, presets):
        lines.append(f"| {name} | {r.substeps}x{r.iterations} | {r.scene}/{r.fabric} "
                     f"{r.resolution} | {_fmt(r.seconds_per_sim_second)} | {_fmt(r.rms_mm)} |")
    lines += ["", "## Blender beside ours", ""]
    gap = summary.get("blender_vs_ours_mm", {})
    if not gap:
        lines.append("Blender was not run (not installed, or `--no-blender`).")
    else:
        lines.append("Blender's error is against its own highest affordable quality; the "
                     "distance between that converged run and ours is the model difference:")
        lines.append("")
        for key, mm in gap.items():
            lines.append(f"- {key}: Blender converged vs ours converged {_fmt(mm, 1)} mm RMS "
                         "over the predictable horizon")
        lines += ["", *comparison(rows, presets)]
    doc.write_text("\n".join(lines) + "\n")
