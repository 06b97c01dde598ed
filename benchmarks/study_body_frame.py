"""Where a body scene's frame goes: a study, not a product path.

The accuracy study's body parts (the spinning skirt, the walking t-shirt) are where our rate
against Blender is furthest from the 20x target (docs/accuracy-vs-time.md), and the tube
study (study_coarse_correction's `frame_parts`) does not say why. This one runs the product's
xpbd solver on the study's body scenes, cotton, at the study's settings, with the study's
effects (run.PEER_EFFECTS), and prints for each setting:

- the fused frame's time, ms a frame (one thread, after a warm-up run that compiles), split
  into the solver's frame (the substeps), the full search of the tracked vertices every
  fifth frame (per frame), the collider's frame (the body's poses and grid), the QA and
  outputs, the rest of the frame loop (its guards and state reads), and the set-up before the
  first frame (the model, the collider, the pins and the solver: the study and bench_sim time
  it with the run, where Blender's time leaves out its first frame, which builds its cloth),
  spread over the run's frames; and the run's largest p99.9 strain against the fabric's
  bound;
- the same with the strain limit after contact capped at one sweep a substep (a module
  constant read when the kernels compile, so in a process of its own), as the tube study does;
- the split of a frame between the effects, from a run on the per-effect kernels (each
  launch timed: slower than the fused frame, so read the shares, not the sums), with the body
  collision split into the grid search (the untracked vertices at every substep, the tracked
  ones every fifth frame) and the contact;
- the study's own error at that setting (accuracy.csv, against the float64 reference), for
  what the time buys.

    python -m benchmarks.study_body_frame

About 2 minutes on 2 cores; run it alone (it times). Its table is in docs/simulator.md
("Where a body frame goes").
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

COMMAND = "python -m benchmarks.study_body_frame"
SCENES = ["skirt_body", "tshirt_walk"]
FABRIC = "cotton"
SETTINGS = [(5, 1), (10, 2), (20, 2), (20, 4)]
STUDY_CSV = Path(__file__).parent / "results" / "accuracy" / "accuracy.csv"


@contextlib.contextmanager
def split_body_collision(spent: dict[str, float]) -> Iterator[None]:
    """Within the block, time the per-effect path's body-collision launches by what they do:
    the grid search (`collider.nearest`) and the rest (the contact and its clearing), into
    `spent` (s)."""
    from datagen.sim import solvers

    run = solvers.ClothSolver._run

    def timed_run(self, effect: str, fn, *args) -> None:
        t = time.perf_counter()
        run(self, effect, fn, *args)
        if effect == "body_collision":
            part = "search" if getattr(fn, "__name__", "") == "nearest" else "contact"
            spent[part] += time.perf_counter() - t

    with mock.patch.object(solvers.ClothSolver, "_run", timed_run):
        yield


@contextlib.contextmanager
def time_frame_parts(spent: dict[str, float]) -> Iterator[None]:
    """Within the block, time the fused frame's parts into `spent` (s): the solver's frame
    (the substeps), the full search, the collider's frame (the body's poses and grid) and the
    QA and outputs, as study_coarse_correction's frame_parts does for the tube, and the frame
    loop's advances (`loop`, which holds all but the QA). Each part starts at zero."""
    spent.update(dict.fromkeys(("solver", "search", "collider", "qa", "loop"), 0.0))
    from datagen.sim import simulate as simulate_module
    from datagen.sim import solvers

    def timed(cls, name: str, part: str):
        method = getattr(cls, name)

        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            out = method(*args, **kwargs)
            spent[part] += time.perf_counter() - t
            return out

        return mock.patch.object(cls, name, wrapper)

    with (timed(solvers.XPBDSolver, "advance_frame", "solver"),
          timed(solvers.XPBDSolver, "search", "search"),
          timed(simulate_module._Simulation, "_set_body", "collider"),
          timed(simulate_module._Simulation, "_record", "qa"),
          # The frame loop's advances: what is outside them and the QA is the set-up.
          timed(simulate_module._Simulation, "_advance", "loop")):
        yield


def measure(scene_name: str, cap: int | None, per_effect: bool) -> list[dict]:
    """Every setting of SETTINGS on one study scene, in this process. `cap` sets the
    after-contact sweeps (before any kernel compiles)."""
    from datagen.sim import kernels as K
    from datagen.study.scenes import build_scene

    if cap is not None:
        K.AFTER_CONTACT_SWEEPS = cap
    scene = build_scene(scene_name, FABRIC)
    return [{"scene": scene_name, "cap": cap, **measure_setting(scene, sub, it, per_effect)}
            for sub, it in SETTINGS]


def measure_setting(scene, sub: int, it: int, per_effect: bool) -> dict:
    """One setting on a study scene (study.scenes.StudyScene): the fused frame timed and split
    into its parts (ms a frame), its largest p99.9 strain and the fabric's bound, and with
    `per_effect` a run on the per-effect kernels: its ms a frame, each effect's, and the body
    collision's search and contact."""
    from datagen.errors import RejectedSequence
    from datagen.sim.fabrics import get_fabric
    from datagen.sim.simulate import SimOptions, simulate
    from datagen.study.run import PEER_EFFECTS, run_ours

    run_ours(scene, "xpbd", sub, it)  # compiles this setting's kernels
    parts: dict[str, float] = {}
    with time_frame_parts(parts):
        run = run_ours(scene, "xpbd", sub, it)
    frames = len(run.positions) - 1
    # The whole run, its set-up too: the table splits it, the set-up its own column.
    row = {"setting": f"{sub}x{it}", "ms_frame": 1000 * (run.wall + run.setup) / frames,
           **{f"{k}_ms": 1000 * v / frames for k, v in parts.items()},
           "strain_p999": float(run.qa["strain_p999"].max()),
           "bound": min(get_fabric(g.fabric).max_strain for g in scene.garments)}
    if per_effect:
        options = SimOptions(solver="xpbd", substeps=sub, iterations=it, effects=PEER_EFFECTS,
                             frames=scene.frames, profile_every=1, strain_refinements=0,
                             settle_seconds=0.0)
        spent = {"search": 0.0, "contact": 0.0}
        try:
            with split_body_collision(spent):
                t = time.perf_counter()
                result = simulate(scene.garments, scene.track, options)
                wall = time.perf_counter() - t
        except RejectedSequence as exc:
            # The per-effect kernels round differently from the fused frame (fast math), and
            # at the coarsest settings, where the cloth is far past its bound anyway, one path
            # can cross a guard the other does not: the row says so instead of ending the study.
            row["per_effect_rejected"] = exc.reason
            return row
        frames = result.report["frames"] - 1
        row["per_effect_ms_frame"] = 1000 * wall / frames
        row["effects_ms"] = {k: 1000 * v / frames
                             for k, v in result.report["effect_costs_s"].items()}
        row["effect_search_ms"] = 1000 * spent["search"] / frames
        row["effect_contact_ms"] = 1000 * spent["contact"] / frames
    return row


def _in_process(scene_name: str, cap: int | None, per_effect: bool) -> list[dict]:
    """measure() in a fresh process: the cap is read when the kernels compile."""
    args = [sys.executable, "-m", "benchmarks.study_body_frame", "--measure", scene_name,
            "--cap", str(cap if cap is not None else 0)]
    if per_effect:
        args.append("--per-effect")
    out = subprocess.run(args, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def study_errors() -> dict[tuple[str, str], float]:
    """The accuracy study's xpbd error (mm, against its float64 reference) by scene and
    setting, for FABRIC."""
    errors = {}
    if STUDY_CSV.exists():
        with STUDY_CSV.open() as f:
            for r in csv.DictReader(f):
                if r["series"] == "xpbd" and r["fabric"] == FABRIC and not r["resolution"]:
                    errors[(r["scene"], f"{r['substeps']}x{r['iterations']}")] = float(
                        r["rms_mm"]) if r["status"] == "ok" else float("nan")
    return errors


def _share(ms: float, total: float) -> str:
    return f"{ms:.1f} ({100 * ms / total:.0f} %)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    parser.add_argument("--cap", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--per-effect", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--scenes", default=",".join(SCENES))
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure, args.cap or None, args.per_effect)))
        return
    errors = study_errors()
    print(f"Command: `{COMMAND}`\n")
    print("| scene | setting | study error mm | ms a frame | solver's frame | full search | "
          "collider's frame | "
          "QA and outputs | rest of the loop | set-up | strain p99.9 (bound) | "
          "one after-contact sweep: ms a frame | its strain p99.9 |")
    print("|---" * 13 + "|")
    split = []
    for scene_name in args.scenes.split(","):
        product = _in_process(scene_name, None, per_effect=True)
        capped = _in_process(scene_name, 1, per_effect=False)
        for row, cap_row in zip(product, capped, strict=True):
            rest = row["loop_ms"] - row["solver_ms"] - row["search_ms"] - row["collider_ms"]
            setup = row["ms_frame"] - row["loop_ms"] - row["qa_ms"]
            print(f"| {scene_name} {FABRIC} | {row['setting']} | "
                  f"{errors.get((scene_name, row['setting']), float('nan')):.1f} | "
                  f"{row['ms_frame']:.1f} | {row['solver_ms']:.1f} | {row['search_ms']:.1f} | "
                  f"{row['collider_ms']:.1f} | "
                  f"{row['qa_ms']:.1f} | {rest:.1f} | {setup:.1f} | "
                  f"{row['strain_p999']:.3f} ({row['bound']}) | "
                  f"{cap_row['ms_frame']:.1f} | {cap_row['strain_p999']:.3f} |", flush=True)
            split.append(row)
    # The per-effect kernels' split: each launch timed on its own, slower than the fused
    # frame (read the shares).
    print("\n| scene | setting | per-effect frame ms | springs and bending | strain limit | "
          "body search | body contact | other effects, the frame loop and the set-up |")
    print("|---" * 8 + "|")
    for row in split:
        if "per_effect_rejected" in row:
            print(f"| {row['scene']} {FABRIC} | {row['setting']} | rejected by the guards: "
                  f"{row['per_effect_rejected']} | | | | | |", flush=True)
            continue
        e = row["effects_ms"]
        springs = sum(e.get(k, 0.0) for k in ("stretch", "shear", "bending"))
        limit = e.get("strain_limit", 0.0)
        total = row["per_effect_ms_frame"]
        other = total - springs - limit - row["effect_search_ms"] - row["effect_contact_ms"]
        print(f"| {row['scene']} {FABRIC} | {row['setting']} | {total:.1f} | "
              f"{_share(springs, total)} | {_share(limit, total)} | "
              f"{_share(row['effect_search_ms'], total)} | "
              f"{_share(row['effect_contact_ms'], total)} | "
              f"{_share(other, total)} |", flush=True)


if __name__ == "__main__":
    main()
