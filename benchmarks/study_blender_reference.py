"""How converged is Blender's reference on a body scene? A study, not a product path.

The accuracy study measures Blender's error at its timed qualities (5, 10, 20 steps a frame)
against its own quality 320 run. On the sheets quality 160 is 0.3-0.9 mm from 320, but on the
body scenes 8-11 mm (docs/accuracy-vs-time.md), so 320 itself may be that far from converged,
and Blender's error at quality 5 (31-37 mm there) would carry that uncertainty. This runs one
study part's scene in Blender at the timed qualities and at 160, 320 and 640 (or the
qualities given), over the part's predictable horizon (from the study's summary, or
`--horizon` for a scene that is not a part), and prints each run's distance from every run at
quality 320 or more and each halving (q against 2q), RMS mm over that horizon as the study
measures it, and the largest share of cloth vertices inside the body and deeper than the
fabric's thickness in any frame (the QA's deep_share).

    python -m benchmarks.study_blender_reference --part tshirt_walk/denim

`--contact matched` gives Blender a cushion that rests the cloth at our fabric's thickness
instead of the study's 13.3 mm (datagen.study.blender.contact_settings): the body scenes start
draped by ours, partly inside the study's cushion, and Blender's push out of it grows with its
steps. `--twin Q` also runs quality Q from a start moved by 1 um, the spread Blender's own
chaos gives over the horizon.

About 15 minutes for the denim t-shirt (11 frames) at the default qualities, 640 alone 7;
`--qualities ... 1280` adds 14. Matched, Blender runs 1.6-1.9x faster: qualities 5 to 320 and a
twin at 80 took 6 minutes. `--keep` keeps each run in the study cache
(datagen.study.cache, under the scene's sources) for later calls. Run it alone (Blender uses
both cores). Its figures are quoted in the study's state note (docs/accuracy-vs-time.md).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.common import REPO, machine
from datagen.sim.fabrics import get_fabric
from datagen.study import blender as peer
from datagen.study.cache import cached
from datagen.study.metrics import rms_distance, scene_penetration
from datagen.study.run import Run
from datagen.study.scenes import build_scene
from datagen.study.sweep import TWIN_METRES

SUMMARY = REPO / "benchmarks" / "results" / "accuracy" / "summary.json"
RESULTS = REPO / "benchmarks" / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", default="tshirt_walk/denim", help="scene/fabric of the study")
    parser.add_argument("--qualities", type=int, nargs="+", default=[5, 10, 20, 160, 320, 640])
    parser.add_argument("--keep", action="store_true",
                        help="keep each Blender run in the study cache and reuse it in a later "
                             "call on the same part, horizon and sources")
    parser.add_argument("--contact", choices=["study", "matched"], default="study",
                        help="Blender's contact cushion: the study's (13.3 mm at rest), or "
                             "matched to our fabric's thickness (datagen.study.blender."
                             "contact_settings)")
    parser.add_argument("--twin", type=int, default=None, metavar="QUALITY",
                        help="also run QUALITY with the start moved by 1 um (build_scene's "
                             "perturb): the spread that Blender's own chaos gives")
    parser.add_argument("--horizon", type=int, default=None,
                        help="frames to measure over, for a scene that is not a study part "
                             "(bench_sim's tube_cylinder: its horizon in docs/benchmarks.md)")
    args = parser.parse_args()
    summary = json.loads(SUMMARY.read_text())
    if args.horizon is None and args.part not in summary["predictable_frames"]:
        raise SystemExit(f"{SUMMARY}: field 'predictable_frames' has no part {args.part!r} "
                         f"(parts: {', '.join(summary['predictable_frames'])}); give --horizon")
    horizon = args.horizon or summary["predictable_frames"][args.part]
    scene_name, fabric = args.part.split("/")
    # The study's scene cut to its horizon: frames past it do not change the ones before.
    scene = build_scene(scene_name, fabric, frames=horizon)
    matched = args.contact == "matched"
    thickness = get_fabric(fabric).thickness

    def blender_run(q: int, perturb: float = 0.0) -> Run:
        t = time.perf_counter()
        moved = build_scene(scene_name, fabric, frames=horizon, perturb=perturb) if perturb \
            else scene

        def blender() -> dict[str, np.ndarray]:
            run = peer.run_blender(moved, q, timeout=4 * 3600.0, matched_contact=matched)
            return {"positions": run.positions, "wall": np.float64(run.wall),
                    "simulated": np.float64(run.simulated)}

        key = {"blender_run": scene_name, "fabric": fabric, "frames": horizon, "quality": q,
               "contact": args.contact, "perturb": perturb}
        d = cached(key, blender, use_cache=args.keep)
        run = Run(f"blender q{q}", d["positions"], float(d["wall"]), float(d["simulated"]), {})
        print(f"q{q}{' twin' if perturb else ''}: {run.seconds_per_simulated_second:.1f} s per "
              f"simulated second ({time.perf_counter() - t:.0f} s)", flush=True)
        return run

    runs = {q: blender_run(q) for q in sorted(args.qualities)}
    marks = [q for q in runs if q >= 320] or [max(runs)]  # the candidate references
    rows = []
    for q, run in runs.items():
        inside, deep = scene_penetration(run.positions, scene, horizon)
        row = {"quality": q, "s_per_sim_s": run.seconds_per_simulated_second,
               "inside_share_max": inside, "deep_share_max": deep}
        for m in marks:
            row[f"mm_to_q{m}"] = 1000 * rms_distance(run.positions, runs[m].positions, horizon)
        if 2 * q in runs:
            row["halving_mm"] = 1000 * rms_distance(run.positions, runs[2 * q].positions,
                                                    horizon)
        rows.append(row)
    twin = {}
    if args.twin is not None:
        twin_run = blender_run(args.twin, TWIN_METRES)
        base = runs.get(args.twin) or blender_run(args.twin)
        twin = {"twin": {"quality": args.twin, "perturb_m": TWIN_METRES,
                         "mm": 1000 * rms_distance(twin_run.positions, base.positions, horizon)}}
    suffix = "-matched" if matched else ""
    out = RESULTS / f"blender_reference-{scene_name}-{fabric}{suffix}.json"
    out.write_text(json.dumps({"part": args.part, "horizon_frames": horizon,
                               "contact": peer.contact_settings(fabric, matched),
                               "blender": peer.blender_version(), "machine": machine(),
                               "date": time.strftime("%Y-%m-%d"), "rows": rows, **twin},
                              indent=1) + "\n")
    head = " | ".join(f"mm to q{m}" for m in marks)
    print(f"\n{args.part}, {horizon} frames, {peer.blender_version()}, {machine()}\n")
    print(f"| quality | s per simulated second | {head} | q against 2q mm | most vertices "
          f"inside the body % | most deeper than {1000 * thickness:.1f} mm % |")
    print("|---" * (5 + len(marks)) + "|")
    for row in rows:
        cells = " | ".join(f"{row[f'mm_to_q{m}']:.2f}" for m in marks)
        halving = f"{row['halving_mm']:.2f}" if "halving_mm" in row else ""
        print(f"| {row['quality']} | {row['s_per_sim_s']:.1f} | {cells} | {halving} | "
              f"{100 * row['inside_share_max']:.2f} | {100 * row['deep_share_max']:.2f} |")
    if twin:
        print(f"\nq{args.twin} against its twin started {1e6 * TWIN_METRES:.0f} um away: "
              f"{twin['twin']['mm']:.2f} mm")
    print(f"\nWritten to {out.relative_to(REPO)}.")


if __name__ == "__main__":
    main()
