"""What holds an open shirt on a moving body: one change at a time, a study.

The scene is `datagen simulate --seed 3 --garment shirt --motion run --fabric cotton`: a tight
open cotton shirt (tightness 0.37, 0.37; sleeves cut near the elbow) on a 2.19 m woman running.
Each row changes one thing (the motion, the lead-in, an effect, the sleeves' shaping, the
fabric's friction, the garment's cut) and simulates 4 s at the `default` preset with no guard
and no escalation. The measure is the neckline's slip off the shoulders (`qa.neckline_slip`,
the dataset gate's: over 0.2 m the sequence is rejected) at the first output frame, its
largest, and the first frame over the bound (docs/simulator.md, "Open shirts on the move").
About 5 minutes on 2 cores.

    python -m benchmarks.study_open_shirt
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

COMMAND = "python -m benchmarks.study_open_shirt"
SEED, FRAMES = 3, 120
NARROW_SLEEVES = {"W0": 0.85, "a1": -0.15, "a2": 0.01}  # W0 scaled; a1, a2 set
# (row, action, motion params, garment, fabric, lead-in frames, effects, sleeve shaping)
VARIANTS = [
    ("as drawn: a run", "run", {}, "shirt", "cotton", 15, "auto", None),
    ("lead-in of 45 frames instead of 15", "run", {}, "shirt", "cotton", 45, "auto", None),
    ("without air drag", "run", {}, "shirt", "cotton", 15, "auto,-air_drag", None),
    ("arm swing and torso motion at half", "run", {"amplitude": 0.5}, "shirt", "cotton", 15,
     "auto", None),
    ("running at 2 m/s", "run", {"speed": 2.0}, "shirt", "cotton", 15, "auto", None),
    ("the narrowest sleeves (W0 x 0.85, a1 -0.15, a2 0.01)", "run", {}, "shirt", "cotton", 15,
     "auto", NARROW_SLEEVES),
    ("friction 0.9", "run", {}, "shirt", "cotton_mu09", 15, "auto", None),
    ("friction 1.5", "run", {}, "shirt", "cotton_mu15", 15, "auto", None),
    ("the same garment closed (tshirt)", "run", {}, "tshirt", "cotton", 15, "auto", None),
    ("standing (idle)", "idle", {}, "shirt", "cotton", 15, "auto", None),
    ("walking at 1.3 m/s", "walk", {}, "shirt", "cotton", 15, "auto", None),
    ("walking at 0.6 m/s", "walk", {"speed": 0.6}, "shirt", "cotton", 15, "auto", None),
    ("walking at 0.6 m/s, the narrowest sleeves", "walk", {"speed": 0.6}, "shirt", "cotton", 15,
     "auto", NARROW_SLEEVES),
]


def _fabrics() -> dict:
    from datagen.sim.fabrics import FABRICS

    return {"cotton_mu09": replace(FABRICS["cotton"], name="cotton_mu09", friction=0.9),
            "cotton_mu15": replace(FABRICS["cotton"], name="cotton_mu15", friction=1.5)}


def _narrowed(shaping: dict[str, float], change: dict[str, float]) -> dict[str, float]:
    out = dict(shaping)
    for side in ("sleeve_l", "sleeve_r"):
        for key, value in change.items():
            name = f"{side}.{key}"
            out[name] = out[name] * value if key == "W0" else value
    return out


def run_variant(variant: tuple) -> dict:
    """One row: the neckline slip's series summary and the wall time."""
    from datagen import qa
    from datagen.body.anny_model import default_body_model
    from datagen.cli import scene_with_outfit, single_scene_spec
    from datagen.pipeline.stages import run_sequence, sim_options_from_spec
    from datagen.sim.backend import init_taichi
    from datagen.sim.simulate import simulate

    init_taichi(threads=1)
    _, action, params, garment, fabric, lead_in, effects, sleeves = variant
    spec = single_scene_spec(SEED, action, None, None, FRAMES, None, 30.0, lead_in=lead_in)
    spec = scene_with_outfit(spec, garment, fabric, SEED)
    spec = replace(spec, motion=replace(spec.motion, params={**spec.motion.params, **params}))
    if effects != "auto":
        spec = replace(spec, simulation=replace(spec.simulation,
                                                effects=tuple(effects.split(","))))
    if sleeves:
        parts = tuple(replace(g, shaping=_narrowed(g.shaping, sleeves)) if g.name == "upper"
                      else g for g in spec.outfit.garments)
        spec = replace(spec, outfit=replace(spec.outfit, garments=parts))
    # The pipeline's body and outfit stages; the cloth once, without the escalation ladder.
    record = run_sequence(spec, default_body_model(), simulate_cloth=False)
    if record.status != "ok":
        raise SystemExit(f"{variant[0]}: rejected at {record.stage}: {record.reason}")
    body, garments = record.body, record.garments
    start = time.perf_counter()
    sim = simulate(garments, body, sim_options_from_spec(spec, _fabrics()))
    wall = time.perf_counter() - start
    shirt = next(g for g in garments if g.name == "upper")
    loop = np.asarray(shirt.loops["neck"], dtype=np.int64)
    positions = sim.vertices[shirt.name]
    neck = body.joints[body.lead_in_frames:body.lead_in_frames + len(positions), qa.NECK_JOINT]
    slip = qa.neckline_slip(positions[:, loop], shirt.vertices[loop], neck,
                            body.rest.joints[qa.NECK_JOINT])
    over = np.flatnonzero(slip > qa.NECKLINE_SLIP_MAX)
    return {"first": float(slip[0]), "largest": float(slip.max()),
            "over": int(over[0]) if len(over) else None, "seconds": wall}


def main() -> None:
    print(f"Command: `{COMMAND}`\n\n`datagen simulate --seed {SEED} --garment shirt --motion "
          f"run --fabric cotton`, one change at a time; {FRAMES} output frames at 30 fps, "
          "`default` 20x4, no guard or escalation\n\n"
          "| run | slip at frame 0 m | largest m | first frame over 0.2 m | wall s |\n"
          "|---|---|---|---|---|", flush=True)
    with ProcessPoolExecutor(2) as pool:
        for variant, r in zip(VARIANTS, pool.map(run_variant, VARIANTS), strict=True):
            over = "never" if r["over"] is None else str(r["over"])
            print(f"| {variant[0]} | {r['first']:.3f} | {r['largest']:.3f} | {over} | "
                  f"{r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
