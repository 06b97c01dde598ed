"""How often a scene needs the escalation at the default settings, and what it costs: a study.

A sequence that breaks a QA bound or runs away at `default` is simulated again, whole, at finer
steps with plain sweeps (docs/simulator.md, "Escalation"): it is kept, but costs several runs.
This runs grids of single-garment cotton scenes through the real pipeline (body, outfit,
simulation with escalation), 60 frames each, one single-threaded process per core, and prints
each scene's outcome and wall time, then per grid how many escalated and what share of the
grid's time they took.

    python -m benchmarks.study_escalations [--workers N]

The default grids: every procedural action with a t-shirt, a long-sleeved shirt, trousers and a
dress (seed 0), and the run with a shirt and a polo over seeds 0-8, where the first grid found
the one escalation (about 7 min on 2 cores).
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor

COMMAND = "python -m benchmarks.study_escalations"
FRAMES = 60
_MODEL: list = []  # the worker's body model, built once


def _warm() -> None:
    from datagen.body.anny_model import default_body_model
    from datagen.sim.backend import init_taichi

    init_taichi(threads=1)
    _MODEL.append(default_body_model())


def scene_outcome(job: tuple[str, str, int]) -> dict:
    """One scene (action, garment, seed) through the pipeline, as `datagen simulate` runs it."""
    from datagen.cli import scene_with_outfit, single_scene_spec
    from datagen.pipeline.stages import escalation_note, run_sequence

    action, garment, seed = job
    spec = scene_with_outfit(single_scene_spec(seed, action, None, None, FRAMES, None),
                             garment, "cotton", seed)
    t = time.perf_counter()
    record = run_sequence(spec, _MODEL[0])
    seconds = time.perf_counter() - t
    report = record.sim.report if record.sim is not None else {}
    return {"action": action, "garment": garment, "seed": seed, "status": record.status,
            "seconds": seconds, "retries": int(report.get("retries", 0)),
            "escalated": bool(report.get("escalated_from")),
            "note": (record.reason or "") + escalation_note(record.sim)}


def grids() -> list[tuple[str, list[tuple[str, str, int]]]]:
    from datagen.motion.procedural import ACTIONS

    return [
        ("every action, seed 0", list(itertools.product(
            sorted(ACTIONS), ["tshirt", "shirt", "trousers", "dress"], [0]))),
        ("run, sleeved tops, seeds 0-8", list(itertools.product(
            ["run"], ["shirt", "polo"], range(9)))),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    ctx = multiprocessing.get_context("spawn")  # no fork: Taichi and torch hold threads
    summary = []
    with ProcessPoolExecutor(args.workers, mp_context=ctx, initializer=_warm) as pool:
        for name, jobs in grids():
            print(f"\n{name}\n\n| action | garment | seed | outcome | wall s | retried frames "
                  "| escalation |\n|---|---|---|---|---|---|---|")
            rows = []
            for r in pool.map(scene_outcome, jobs):
                rows.append(r)
                print(f"| {r['action']} | {r['garment']} | {r['seed']} | {r['status']} | "
                      f"{r['seconds']:.1f} | {r['retries']} | "
                      f"{r['note'].removeprefix('; ') or '-'} |", flush=True)
            summary.append((name, rows))
    print(f"\nCommand: `{COMMAND}`\n\n| grid | scenes | escalated | rejected | their share of "
          "the grid's time | an escalated scene against the grid's median |\n"
          "|---|---|---|---|---|---|")
    for name, rows in summary:
        times = sorted(r["seconds"] for r in rows)
        median = times[len(times) // 2]
        esc = [r for r in rows if r["escalated"]]
        share = sum(r["seconds"] for r in esc) / sum(times)
        ratios = ", ".join(f"{r['seconds'] / median:.1f}x" for r in esc) or "-"
        print(f"| {name} | {len(rows)} | {len(esc)} | "
              f"{sum(r['status'] != 'ok' for r in rows)} | {100 * share:.0f} % | {ratios} |")


if __name__ == "__main__":
    main()
