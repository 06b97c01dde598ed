"""Blender's cushion on bench_sim's peer scenes: a study, not a product path.

Blender holds cloth at 8/9 of (its collision distance + the collider's outer thickness) from a
collider; the peer gives it the study's 5 + 10 mm (13.3 mm at rest), three times our fabric's
thickness. This runs each peer scene at Blender's default quality with that cushion and with
one matched to ours (datagen.study.blender.contact_settings) over bench_sim's timed frames, and
prints Blender's rate and the largest share of cloth vertices inside the collider and deeper
than the fabric's thickness in any frame (the QA's bound on the latter is 1 %): whether the
thinner cushion, which Blender runs faster, still keeps the cloth out at that quality.

    python -m benchmarks.study_blender_contact

About 8 minutes, alone (Blender uses both cores). Writes
benchmarks/results/blender_contact.json; its figures are quoted in bench_sim's note on
Blender's cushion and in the accuracy study's state note.
"""

from __future__ import annotations

import json
import time

from benchmarks.bench_sim import BLENDER_QUALITY, FABRICS, PEER_SCENES, RATE_FRAMES
from benchmarks.common import REPO, machine
from datagen.study import blender as peer
from datagen.study.metrics import scene_penetration
from datagen.study.scenes import build_scene

OUT = REPO / "benchmarks" / "results" / "blender_contact.json"


def main() -> None:
    rows = []
    for scene_name, resolution in PEER_SCENES:
        for fabric in FABRICS:
            scene = build_scene(scene_name, fabric, resolution, frames=RATE_FRAMES)
            for matched in (False, True):
                run = peer.run_blender(scene, BLENDER_QUALITY, matched_contact=matched)
                inside, deep = scene_penetration(run.positions, scene)
                rows.append({"scene": f"{scene_name} {resolution}", "fabric": fabric,
                             "contact": "matched" if matched else "study",
                             **peer.contact_settings(fabric, matched),
                             "s_per_sim_s": run.seconds_per_simulated_second,
                             "inside_share_max": inside, "deep_share_max": deep})
                print(rows[-1], flush=True)
    OUT.write_text(json.dumps({"quality": BLENDER_QUALITY, "frames": RATE_FRAMES,
                               "blender": peer.blender_version(), "machine": machine(),
                               "date": time.strftime("%Y-%m-%d"), "rows": rows},
                              indent=1) + "\n")
    print(f"\nBlender at quality {BLENDER_QUALITY}, {RATE_FRAMES} frames, "
          f"{peer.blender_version()}, {machine()}\n")
    print("| scene | fabric | cushion | s per simulated second | most vertices inside % | "
          "most deeper than the thickness % |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['fabric']} | {r['contact']} | {r['s_per_sim_s']:.2f} | "
              f"{100 * r['inside_share_max']:.2f} | {100 * r['deep_share_max']:.2f} |")
    print(f"\nWritten to {OUT.relative_to(REPO)}.")


if __name__ == "__main__":
    main()
