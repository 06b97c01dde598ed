"""What holds an open shirt on a moving body: one change at a time, a study.

The scene is `datagen simulate --seed 3 --garment shirt --motion run --fabric cotton`: a tight
open cotton shirt (tightness 0.37, 0.37; sleeves cut near the elbow) on a 2.19 m woman running.
Each row changes one thing (the motion, the lead-in, an effect, the sleeves' shaping or
length, the garment's size, the fabric's friction, the closed cut) or two (a walk with the
air's pressure drag) and simulates 4 s at the `default` preset with no guard and no
escalation. The measure is the neckline's slip off
the shoulders (`qa.neckline_slip`, the dataset gate's: over 0.2 m the sequence is rejected)
at the first output frame, its largest, and the first frame over the bound
(docs/simulator.md, "Open shirts on the move").
About 7 minutes on 2 cores.

    python -m benchmarks.study_open_shirt
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

COMMAND = "python -m benchmarks.study_open_shirt"
SEED, FRAMES = 3, 120


@dataclass(frozen=True)
class Variant:
    """One row: the scene as drawn, with the fields that differ from it set."""

    row: str
    action: str = "run"
    params: dict = field(default_factory=dict)  # the motion's
    garment: str = "shirt"
    fabric: str = "cotton"
    lead_in: int = 15  # frames
    effects: str = "auto"
    sleeves: dict | None = None  # NARROW_SLEEVES-style shaping changes
    lengths: dict | None = None  # cut lengths (m) in place of the drawn ones
    tightness: tuple[float, float] | None = None  # in place of the drawn (0.37, 0.37)


NARROW_SLEEVES = {"W0": 0.85, "a1": -0.15, "a2": 0.01}  # W0 scaled; a1, a2 set
CAP_SLEEVES = {"sleeve_l": 0.04, "sleeve_r": 0.04}  # the shortest cut the template allows
LONG_SLEEVES = {"sleeve_l": 0.465, "sleeve_r": 0.465}  # near its longest (0.470)
VARIANTS = [
    Variant("as drawn: a run"),
    Variant("lead-in of 45 frames instead of 15", lead_in=45),
    Variant("without air drag", effects="auto,-air_drag"),
    Variant("with pressure drag", effects="auto,+pressure_drag"),
    Variant("arm swing and torso motion at half", params={"amplitude": 0.5}),
    Variant("running at 2 m/s", params={"speed": 2.0}),
    Variant("the narrowest sleeves (W0 x 0.85, a1 -0.15, a2 0.01)", sleeves=NARROW_SLEEVES),
    Variant("cap sleeves (cut at 0.04 m)", lengths=CAP_SLEEVES),
    Variant("full-length sleeves (cut at 0.465 m)", lengths=LONG_SLEEVES),
    Variant("cut for the subject (tightness 0, 0)", tightness=(0.0, 0.0)),
    Variant("cut a size bigger (tightness -0.5, -0.5)", tightness=(-0.5, -0.5)),
    Variant("friction 0.9", fabric="cotton_mu09"),
    Variant("friction 1.1", fabric="cotton_mu11"),
    Variant("friction 1.25", fabric="cotton_mu125"),
    Variant("friction 1.5", fabric="cotton_mu15"),
    Variant("the same garment closed (tshirt)", garment="tshirt"),
    Variant("standing (idle)", action="idle"),
    Variant("walking at 1.3 m/s", action="walk"),
    Variant("walking at 1.3 m/s, with pressure drag", action="walk",
            effects="auto,+pressure_drag"),
    Variant("walking at 0.6 m/s", action="walk", params={"speed": 0.6}),
    Variant("walking at 0.6 m/s, with pressure drag", action="walk", params={"speed": 0.6},
            effects="auto,+pressure_drag"),
    Variant("walking at 0.6 m/s, the narrowest sleeves", action="walk", params={"speed": 0.6},
            sleeves=NARROW_SLEEVES),
]


def _fabrics() -> dict:
    from datagen.sim.fabrics import FABRICS

    return {name: replace(FABRICS["cotton"], name=name, friction=mu)
            for name, mu in (("cotton_mu09", 0.9), ("cotton_mu11", 1.1), ("cotton_mu125", 1.25),
                             ("cotton_mu15", 1.5))}


def _narrowed(shaping: dict[str, float], change: dict[str, float]) -> dict[str, float]:
    out = dict(shaping)
    for side in ("sleeve_l", "sleeve_r"):
        for key, value in change.items():
            name = f"{side}.{key}"
            out[name] = out[name] * value if key == "W0" else value
    return out


def run_variant(variant: Variant) -> dict:
    """One row: the neckline slip's series summary and the wall time."""
    from datagen import qa
    from datagen.body.anny_model import default_body_model
    from datagen.cli import scene_with_outfit, single_scene_spec
    from datagen.pipeline.stages import run_sequence, sim_options_from_spec
    from datagen.sim.backend import init_taichi
    from datagen.sim.simulate import simulate

    init_taichi(threads=1)
    v = variant
    spec = single_scene_spec(SEED, v.action, None, None, FRAMES, None, 30.0, lead_in=v.lead_in)
    spec = scene_with_outfit(spec, v.garment, v.fabric, SEED)
    spec = replace(spec, motion=replace(spec.motion, params={**spec.motion.params, **v.params}))
    if v.effects != "auto":
        spec = replace(spec, simulation=replace(spec.simulation,
                                                effects=tuple(v.effects.split(","))))
    outfit = spec.outfit
    if v.sleeves or v.lengths:
        parts = tuple(replace(g, shaping=_narrowed(g.shaping, v.sleeves or {}),
                              cuts={**g.cuts, **(v.lengths or {})}) if g.name == "upper"
                      else g for g in outfit.garments)
        outfit = replace(outfit, garments=parts)
    if v.tightness is not None:
        outfit = replace(outfit, tightness=v.tightness)
    spec = replace(spec, outfit=outfit)
    # The pipeline's body and outfit stages; the cloth once, without the escalation ladder.
    record = run_sequence(spec, default_body_model(), simulate_cloth=False)
    if record.status != "ok":
        raise SystemExit(f"{v.row}: rejected at {record.stage}: {record.reason}")
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
            print(f"| {variant.row} | {r['first']:.3f} | {r['largest']:.3f} | {over} | "
                  f"{r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
