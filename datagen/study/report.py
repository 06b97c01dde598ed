"""docs/accuracy-vs-time.md from a study's rows and summary: the reference's convergence, the
table, the plot, the presets with their figures, and Blender's series beside ours.

The reading that rows cannot give is written by hand, so that a regenerated page keeps it: the
study's present state (which parts stand for today's simulator, what the figures say) in
OUT/state.md (STATE_NOTE), placed before the scenes; how it got there (each re-measurement and
what changed before it, leads found outside the table) in OUT/history.md (HISTORY_NOTE), placed
last, so that a reader meets the results before the log."""

from __future__ import annotations

import shutil
from datetime import date
from pathlib import Path

import numpy as np

from datagen.sim.simulate import FINER_STEPS
from datagen.study.run import PEER_EFFECTS
from datagen.study.scenes import START_SUBSTEPS
from datagen.study.sweep import (
    CHAOS_MM,
    CONVERGED_MM,
    NOT_RECORDED,
    TWIN_METRES,
    Row,
    pareto,
)

STATE_NOTE = "state.md"
HISTORY_NOTE = "history.md"


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
            line = (
                f"- {scene}, {fabric}: `default` {_fmt(d.rms_mm)} mm at "
                f"{_fmt(d.seconds_per_sim_second)} s per simulated second; Blender quality "
                f"{b.substeps} {_fmt(b.rms_mm)} mm at {_fmt(b.seconds_per_sim_second)} s: "
                f"**{ratio:.1f}x** faster at equal or lower error ({verdict} the 20x target)."
            )
            # Why: how much of the default's time buys accuracy beyond Blender's, i.e. what our
            # cheapest run on the same mesh at Blender's error would give.
            c = cheapest_within([r for r in rows if (r.scene, r.fabric) == (scene, fabric)
                                 and r.series != "blender" and r.note == ""], b.rms_mm)
            if ratio < 20 and c is not None:
                line += (f" Part of the gap is accuracy: the default's error is "
                         f"{b.rms_mm / max(d.rms_mm, 1e-9):.1f}x lower than Blender's; at "
                         f"Blender's error our cheapest run on this mesh is "
                         f"{_label(c)} ({_fmt(c.rms_mm)} mm at "
                         f"{_fmt(c.seconds_per_sim_second)} s), "
                         f"{b.seconds_per_sim_second / c.seconds_per_sim_second:.1f}x faster.")
            lines.append(line)
        else:
            best = min(peer, key=lambda r: r.rms_mm)
            lines.append(
                f"- {scene}, {fabric}: `default` {_fmt(d.rms_mm)} mm at "
                f"{_fmt(d.seconds_per_sim_second)} s per simulated second; every Blender run "
                f"has a lower error (best: quality {best.substeps}, {_fmt(best.rms_mm)} mm at "
                f"{_fmt(best.seconds_per_sim_second)} s), so the target's condition is not met.")
    return lines


def equal_error_speed(rows: list[Row]) -> list[str]:
    """A table: for each Blender run, our cheapest xpbd run on the scene's own mesh whose error
    is no larger, and how much faster it is. This is the speed at equal accuracy, whatever
    the presets; a Blender run that none of ours matches says so."""
    lines = ["| scene/fabric | Blender | its error mm | its s/sim-s | our cheapest run at that "
             "error or lower | our error mm | our s/sim-s | speed ratio |",
             "|---|---|---|---|---|---|---|---|"]
    for scene, fabric in sorted({(r.scene, r.fabric) for r in rows}):
        mine = [r for r in rows if (r.scene, r.fabric) == (scene, fabric) and _measured(r)]
        ours = [r for r in mine if r.series == "xpbd" and not _other_mesh(r)
                and _at_stated_steps(r)]
        for b in sorted((r for r in mine if r.series == "blender"), key=lambda r: r.substeps):
            head = (f"| {scene}/{fabric} | q{b.substeps} | {_fmt(b.rms_mm)} | "
                    f"{_fmt(b.seconds_per_sim_second)} | ")
            c = cheapest_within(ours, b.rms_mm)
            if c is None:
                lines.append(head + "none of ours is this close | | | |")
                continue
            lines.append(head + f"{_label(c)} | {_fmt(c.rms_mm)} | "
                         f"{_fmt(c.seconds_per_sim_second)} | "
                         f"{b.seconds_per_sim_second / c.seconds_per_sim_second:.1f}x |")
    return lines if len(lines) > 2 else []


def cheapest_within(runs: list[Row], error_mm: float) -> Row | None:
    """The fastest measured run with an error no larger than `error_mm`, or None."""
    good = [r for r in runs if _measured(r) and r.rms_mm <= error_mm]
    return min(good, key=lambda r: r.seconds_per_sim_second) if good else None


def _other_mesh(r: Row) -> bool:
    """A run on another mesh resolution than the scene's own (measured at its vertices)."""
    return r.note.startswith("measured at the reference")


def _at_stated_steps(r: Row) -> bool:
    """Whether the run kept its stated steps in every frame. The stability guard's retries
    (and the frames they hold) run finer, and the row's note says how many frames did: its
    time and error are not its steps' (an explicit 200x1 that retried every frame was the
    400x1 run plus the failed tries)."""
    return FINER_STEPS not in r.note


def _label(r: Row) -> str:
    if r.series == "blender":
        return f"Blender q{r.substeps}"
    extra = f" {r.resolution}" if _other_mesh(r) else ""
    return f"{r.series} {r.substeps}x{r.iterations}{extra}"


def _measured(r: Row) -> bool:
    return r.status == "ok" and np.isfinite(r.rms_mm) and np.isfinite(r.seconds_per_sim_second)


def convergence_order(rows: list[Row]) -> float | None:
    """Slope p of error ~ substeps^-p over xpbd runs with one iteration at the scene's own
    resolution (least squares in log-log), or None with fewer than three such runs."""
    pts = [(r.substeps, r.rms_mm) for r in rows if r.series == "xpbd" and r.iterations == 1
           and r.note == "" and _measured(r) and r.rms_mm > 0]
    if len(pts) < 3:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(-np.polyfit(x, y, 1)[0])


def reading(rows: list[Row], presets: dict[str, tuple[int, int]]) -> list[str]:
    """What each scene's rows say, computed from them: the front, how the error falls with
    substeps, substeps against iterations at equal work, mesh resolution, the presets' places
    and Blender's own convergence."""
    lines: list[str] = []
    for scene, fabric in sorted({(r.scene, r.fabric) for r in rows}):
        mine = [r for r in rows if (r.scene, r.fabric) == (scene, fabric) and _measured(r)]
        if not mine:
            continue
        lines += [f"### {scene}, {fabric}", ""]
        # The presets choose steps for a given mesh: the front is drawn among the runs on the
        # scene's own mesh; other meshes have their own bullet.
        same = [r for r in mine if not _other_mesh(r) and _at_stated_steps(r)]
        front = [same[i] for i in pareto([(r.seconds_per_sim_second, r.rms_mm) for r in same])]
        mesh = f" ({same[0].resolution})" if same[0].resolution else ""
        lines.append(f"- **Front** on the scene's mesh{mesh}, the runs that no other run beats "
                     "in both time and error: "
                     + ", ".join(f"{_label(r)} ({_fmt(r.seconds_per_sim_second)} s, "
                                 f"{_fmt(r.rms_mm)} mm)" for r in front) + ".")
        order = convergence_order(mine)
        if order is not None:
            lines.append(f"- **Substeps.** With one iteration, xpbd's error falls as "
                         f"substeps^-{order:.2f} (least squares over its Nx1 runs): halving "
                         f"the step divides the error by {2 ** order:.1f}.")
        own = {(r.substeps, r.iterations): r for r in mine if r.series == "xpbd"
               and r.note == ""}
        pairs = [(a, b) for a in own.values() for b in own.values()
                 if a.substeps == 2 * b.substeps and b.iterations == 2 * a.iterations]
        if pairs:
            wins = sum(a.rms_mm < b.rms_mm for a, b in pairs)
            faster = sum(a.seconds_per_sim_second < b.seconds_per_sim_second for a, b in pairs)
            lines.append(
                f"- **Substeps or iterations.** At equal sweeps per frame, twice the substeps "
                f"with half the iterations was closer to the reference in {wins} of "
                f"{len(pairs)} pairs and faster in {faster} ("
                + "; ".join(f"{_label(a)} {_fmt(a.rms_mm)} mm against {_label(b)} "
                            f"{_fmt(b.rms_mm)} mm" for a, b in pairs) + ").")
        other = [r for r in mine if _other_mesh(r)]
        if other:
            parts = []
            for r in other:
                base = own.get((r.substeps, r.iterations))
                if base is not None:
                    parts.append(f"{r.resolution} {r.substeps}x{r.iterations}: "
                                 f"{r.rms_mm / base.rms_mm:.2f}x the error in "
                                 f"{r.seconds_per_sim_second / base.seconds_per_sim_second:.2f}x "
                                 "the time")
            if parts:
                lines.append(f"- **Resolution** (other meshes measured at the reference mesh's "
                             f"vertices, against the same steps on {same[0].resolution}): "
                             + "; ".join(parts) + ".")
            coarser = [r for r in other if r.vertices < same[0].vertices
                       and (b := own.get((r.substeps, r.iterations))) is not None
                       and r.rms_mm < b.rms_mm]
            if coarser:
                lines.append(
                    "  A coarser mesh comes closer to the fine reference than the fine mesh "
                    "itself at the same steps: at these steps xpbd's error is mostly its "
                    "unconverged constraint solve, whose convergence per sweep slows as the "
                    "mesh has more vertices across it, rather than the coarser mesh's spatial "
                    "error.")
        for name, r in preset_rows(mine, presets):
            if r.note:
                continue
            better = [o for o in same if o.seconds_per_sim_second < r.seconds_per_sim_second
                      and o.rms_mm < r.rms_mm]
            if not better:
                lines.append(f"- **`{name}`** ({r.substeps}x{r.iterations}) is on the front.")
            else:
                b = min(better, key=lambda o: o.rms_mm)
                lines.append(
                    f"- **`{name}`** ({r.substeps}x{r.iterations}) is off the front: "
                    f"{_label(b)} is {r.seconds_per_sim_second / b.seconds_per_sim_second:.2f}x "
                    f"faster with {_fmt(b.rms_mm)} mm against {_fmt(r.rms_mm)} mm.")
        peer = sorted((r for r in mine if r.series == "blender"), key=lambda r: r.substeps)
        if len(peer) > 1:
            trend = ", ".join(f"q{r.substeps} {_fmt(r.rms_mm)} mm" for r in peer)
            monotone = all(a.rms_mm > b.rms_mm for a, b in zip(peer, peer[1:], strict=False))
            lines.append(
                f"- **Blender** against its own converged run: {trend}"
                + ("." if monotone else
                   " (it does not fall as the quality rises: over this horizon Blender's runs "
                   "do not converge towards its highest quality)."))
        lines.append("")
    return lines


def _machine_lines(elsewhere: dict[str, str]) -> list[str]:
    """The page's note on parts measured on other machines, or on machines not recorded."""
    unrecorded = [key for key, machine in elsewhere.items() if machine == NOT_RECORDED]
    recorded = {key: machine for key, machine in elsewhere.items() if machine != NOT_RECORDED}
    lines = []
    if recorded:
        lines += ["", "**Measured on another machine: " + "; ".join(
            f"{key} ({machine})" for key, machine in recorded.items()) + ".** Their times and "
            "errors are that machine's (each part's ratios set both simulators against each "
            "other in its own run). Taichi compiles for the CPU it runs on, and a chaotic "
            "scene's trajectory, its predictable horizon and so its errors move with the "
            "rounding; the fingerprint that carries a part over reads that rounding, so here "
            "such a part may read as measured with an earlier simulator when only the machine "
            "differs."]
    if unrecorded:
        lines += ["", f"**Machine not recorded: {', '.join(unrecorded)}** (measured before "
                  "parts recorded the machine that measured them, 2026-11-29)."]
    return lines


def cushion_text(contact: dict | None) -> str:
    """Which contact cushion a part's Blender runs had (datagen.study.contact)."""
    if contact is None:
        return "Blender's cushion the study's, 13.3 mm (the part predates the cushion rule)"
    if contact["matched_deep_share"] is None:  # a plan without the rule: no trial
        return "Blender's cushion the study's, 13.3 mm (the plan's, for every part)"
    trial = (f"its quality 5 let {100 * contact['matched_deep_share']:.2f} % of the garment "
             "deeper than the thickness")
    if contact["contact"] == "matched":
        return f"Blender's cushion matched to our thickness ({trial})"
    return f"Blender's cushion the study's, 13.3 mm (matched to our thickness, {trial})"


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
        f"folder. Times are wall-clock seconds per simulated second on this machine "
        f"({summary.get('this_machine', NOT_RECORDED)}) unless a part is named below as "
        "measured elsewhere; each scene "
        "and fabric (its reference, our runs and Blender's) was measured in one run, and the "
        "minutes are the sum over those runs. Ours runs on one thread (a dataset run gives "
        "each core a simulation of its own); Blender with its default threads, which use both "
        "cores (the tube at quality 5 runs 1.2x faster than with `-t 1`). Each simulator's "
        "frames are timed and its set-up is not (ours: the model, collider, pins and solver "
        "before the first frame; Blender: its first frame, which builds its cloth).",
        *([] if not summary.get("missing_parts") else [
            "",
            f"**Partial: {len(summary['missing_parts'])} scene/fabric part(s) of the plan are "
            f"not measured yet: {', '.join(summary['missing_parts'])}.** The run keeps "
            "finished parts; running the same command again measures the rest. The body "
            "scenes' parts cost most: their float64 reference ladders step 11-12k vertices in "
            "contact with the body at up to "
            f"{max(s['substeps'] for ladder in summary['ladders'].values() for s in ladder)} "
            "substeps."]),
        *([] if not summary.get("earlier_simulator_parts") else [
            "",
            f"**Measured with an earlier version of the simulator: "
            f"{', '.join(summary['earlier_simulator_parts'])}.** Their figures (errors and "
            "times) stand for that version; `--part` measures them again with this one."]),
        *([] if not summary.get("earlier_blender_converged") else [
            "",
            "**Blender's rows against an earlier converged run: " + ", ".join(
                f"{key} (quality {q})" for key, q in summary["earlier_blender_converged"].items())
            + ".** Their Blender errors are measured against that quality, not against this "
            "plan's, and their halving was not checked."]),
        *([] if not summary.get("earlier_blender_contact") else [
            "",
            "**Blender with the study's cushion everywhere: "
            + ", ".join(summary["earlier_blender_contact"]) + ".** These parts were measured "
            "before the plan chose Blender's cushion per part (`datagen.study.contact`): their "
            "Blender runs hold the cloth 13.3 mm from the collider, not at our thickness, even "
            "where Blender's quality 5 keeps the cloth out with the matched cushion. `--part` "
            "measures them under the rule."]),
        *([] if not summary.get("carried_over_parts") else [
            "",
            f"**Carried over: {', '.join(summary['carried_over_parts'])}** were measured "
            "before the simulator's latest source changes, which leave their scenes' "
            "trajectories bit-identical (`datagen.study.fingerprint`: every solver series at "
            "its cheapest settings and the reference's first rung, over the scene's first "
            "frames), so they stand for today's simulator."]),
        *([] if not summary.get("timed_with_setup_parts") else [
            "",
            f"**Ours timed with its set-up: {', '.join(summary['timed_with_setup_parts'])}.** "
            "These parts were measured before 2026-11-28's change of timing: our runs' times "
            "include the set-up before the first frame (the model, collider, pins and solver; "
            "4-8 % of a run), Blender's leave out its first frame, which builds its cloth. Their "
            "speed ratios against Blender are that much low; their errors stand. `--part` "
            "measures them again, each simulator's frames timed alike."]),
        *([] if not summary.get("earlier_reference_parts") else [
            "",
            f"**References from an earlier run: "
            f"{', '.join(summary['earlier_reference_parts'])}.** Their float64 reference "
            "ladders were measured with earlier simulator sources (named in the summary) whose "
            "reference behaves as today's on the scene (`datagen.study.fingerprint."
            "reference_fingerprint`), and were read from the study cache; the ladders' run "
            "times are that run's. Every other figure of these parts was measured in their own "
            "run."]),
        *_machine_lines(summary.get("other_machine_parts", {})),
        *([] if not (out / STATE_NOTE).is_file() else [
            "", (out / STATE_NOTE).read_text().strip("\n")]),
        "",
        "## The scenes",
        "",
        "- `sheet_sphere`: a 1 m sheet released 25 cm above a 0.5 m sphere; it falls, hits at "
        "about 0.25 s and drapes (60 frames; the 4k mesh is the reference's, the coarse and 10k "
        "meshes are measured at its material points).",
        "- `skirt_body`: the skirt template, its waist pinned, on the neutral female body "
        "spinning; `tshirt_walk`: the t-shirt template on the same body walking (30 frames "
        "each). Both start when the body's lead-in from the rest pose ends, from one settled "
        "state: the garment settled on the rest pose, carried through the lead-in and settled "
        "again, at rest, on the motion's first pose, all by the implicit solver at the "
        f"ladder's first rung, {START_SUBSTEPS} substeps "
        "(`datagen.study.scenes.settled_start`): an equilibrium of the reference's own model, "
        "so the reference does not start with a snap that each step size damps differently. "
        "At the implicit solver's `default` preset (5 substeps) the contact projection "
        "stretched the t-shirt's armpits and neck past cotton's bound (0.25) at the p99.9 "
        "edge, hence the ladder's first rung for the start. Every solver "
        "limits fabric strain at 90 % of the bound (docs/simulator.md), so all of them, the "
        "reference included, simulate one model. Every run, Blender's included, starts from "
        "that state with the "
        "template's rest metric, so the measured second compares solvers on the same motion, "
        "not on how each settled the garment.",
        "",
        "## The converged reference",
        "",
        f"Per scene, the implicit solver in float64 at doubling substeps until halving the step "
        f"changes the trajectory by less than {CONVERGED_MM} mm RMS over the predictable "
        "horizon (next section: the shortest over the rungs' twins); the change over the whole "
        "first second, chaos included, is beside it:",
        "",
        "| scene/fabric | substeps | run s | its twin's predictable frames | RMS to the "
        "previous level, predictable horizon (mm) | same, first second (mm) |",
        "|---|---|---|---|---|---|",
    ]
    for key, ladder in summary["ladders"].items():
        for e in ladder:
            if "failed" in e:
                lines.append(f"| {key} | {e['substeps']} | failed: {e['failed']} | | | |")
                continue
            lines.append(f"| {key} | {e['substeps']} | {e['seconds']:.0f} | "
                         f"{e['predictable_frames']} | "
                         f"{_fmt(e.get('rms_to_previous_mm', np.nan), 3)} | "
                         f"{_fmt(e.get('rms_1s_to_previous_mm', np.nan), 3)} |")
    unconverged = [(key, ladder[-1]) for key, ladder in summary["ladders"].items()
                   if ladder and ladder[-1].get("rms_to_previous_mm", 0.0) >= CONVERGED_MM]
    for key, last in unconverged:
        lines += ["", f"**{key}: not converged.** Its last halving, to {last['substeps']} "
                  f"substeps, still changed the trajectory by {last['rms_to_previous_mm']:.2f} "
                  f"mm RMS (the criterion is {CONVERGED_MM} mm): its errors below are against "
                  "the finest rung it reached, and are uncertain by about that much."]
    lines += [
        "",
        "## Why the error is measured over the predictable horizon",
        "",
        f"Cloth that folds on contact is chaotic: a twin of the reference started "
        f"{TWIN_METRES * 1e6:.0f} micrometre away leaves it by more than {CHAOS_MM:.0f} mm RMS "
        "after the frames below, and the sooner the finer the step (less numerical damping: "
        "the horizon is the shortest over the rungs' twins). A difference after that measures the "
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
    lines += ["", "## Reading the study", "",
              "Computed from the table by `datagen.study.report.reading`: where each scene's "
              "front lies, what substeps and iterations buy, and where the presets sit.", "",
              *reading(rows, presets)]
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
        lines.append("Both run the same effects: ours the scene's own without self-collision "
                     f"(`--effects {PEER_EFFECTS}`), which Blender's peer scene leaves off. "
                     "Blender's error is against its own highest affordable quality; the "
                     "distance between that converged run and ours is the model difference:")
        lines.append("")
        halvings = summary.get("blender_halving", {})
        for key, mm in gap.items():
            half = halvings.get(key)
            check = (f"; Blender quality {half['quality']} against its quality "
                     f"{half['against']} (is that run converged?) {_fmt(half['mm'], 2)} mm"
                     if half else "; Blender's halving not measured (the part predates it)")
            lines.append(f"- {key}: Blender converged vs ours converged {_fmt(mm, 1)} mm RMS "
                         f"over the predictable horizon{check}; "
                         + cushion_text(summary.get("blender_contact", {}).get(key)))
        lines += ["", *comparison(rows, presets)]
        table = equal_error_speed(rows)
        if table:
            lines += ["", "At equal error, whatever the presets: for each Blender run, our "
                      "fastest xpbd run on the same mesh that is at least as close to its own "
                      "reference.", "", *table]
    if (out / HISTORY_NOTE).is_file():
        lines += ["", "## How the study got here", "",
                  "Each re-measurement, newest first, with what changed in the simulator before "
                  "it; figures quoted here are those of their day, the tables above are "
                  "today's.", "", (out / HISTORY_NOTE).read_text().strip("\n")]
    doc.write_text("\n".join(lines) + "\n")
