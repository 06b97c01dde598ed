"""How far friction-held cloth creeps on a shaken body, per solver and step: a study.

A silk strip hangs over a fixed drum, its long side at 90 % of the length Coulomb friction can
hold (`scenes.capstan_hold_limit`; `tests/test_sim_physics.py` checks the limit itself). The
drum then moves up and down as a walking torso does (peak acceleration 3 m/s^2 at 1.8 Hz, the
step rate of a brisk walk) for 2 s. An inextensible belt would not move: every load on it,
weight and inertia, scales with the effective gravity g + a, so the ratio friction must hold
stays what it was at rest. An elastic one creeps a little (its tails stretch and shorten with
the load, and the wrap's ends slip to follow). The table gives how far the short end rose, per
solver and step, and the wall time of each run; a second block repeats three settings with the
fabric ten times stiffer in stretch, to tell the elastic creep from the solver's.

This is the load that holds an open shirt or a strap top on the shoulders (docs/simulator.md,
"Friction on a curved body"). About 4 minutes on one core.

    python -m benchmarks.study_friction_creep
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

COMMAND = "python -m benchmarks.study_friction_creep"
MU, SHORT, RADIUS = 0.3, 0.2, 0.1
SHARE = 0.9  # of the hold limit
PEAK, HZ, SECONDS, FPS = 3.0, 1.8, 2.0, 30.0
# (solver, substeps, iterations): None takes the solver's preset of that name.
SETTINGS = [
    ("xpbd", 10, 2), ("xpbd", 20, 2), ("xpbd", 20, 4), ("xpbd", 20, 8), ("xpbd", 40, 2),
    ("xpbd", 40, 4), ("xpbd", 40, 8), ("implicit", 5, 10), ("implicit", 50, 20),
    ("explicit", 400, 1),
]
STIFF_SETTINGS = [("xpbd", 20, 4), ("xpbd", 40, 8), ("implicit", 50, 20)]


def creep(solver: str, substeps: int, iterations: int, stiffness: float = 1.0) -> dict:
    """One run: the short end's rise over the shaken seconds (m), its wall time, or the reason
    it was rejected."""
    from datagen.errors import RejectedSequence
    from datagen.sim.fabrics import FABRICS
    from datagen.sim.scenes import capstan_hold_limit, drum, strip_over_drum
    from datagen.sim.simulate import ColliderTrack, SimOptions, simulate

    silk = replace(FABRICS["silk"], friction=MU, air_drag=0.0)
    silk = replace(silk, stretch=silk.stretch * stiffness,
                   compression=silk.compression * stiffness)
    wrap = RADIUS + silk.thickness
    strip = strip_over_drum(SHORT, SHARE * capstan_hold_limit(MU, SHORT, wrap), wrap,
                            fabric="study_silk")
    drum_v, drum_f = drum(RADIUS)
    t = np.arange(int(SECONDS * FPS) + 1) / FPS
    omega = 2 * np.pi * HZ
    lift = PEAK / omega**2 * (1 - np.cos(omega * t))
    frames = drum_v[None] + lift[:, None, None] * np.array([0.0, 0.0, 1.0])
    track = ColliderTrack(frames, drum_f, np.ones(len(drum_f), bool), FPS)
    options = SimOptions(solver=solver, substeps=substeps, iterations=iterations,
                         settle_seconds=0.5, fabrics={"study_silk": silk})
    start = time.perf_counter()
    try:
        x = simulate([strip], track, options).vertices["strip"]
    except RejectedSequence as e:
        return {"rise": None, "seconds": time.perf_counter() - start, "note": e.reason}
    seconds = time.perf_counter() - start
    short_end = x[:, strip.uv[:, 1] == 0.0, 2].mean(axis=1) - lift  # its first row
    return {"rise": float(short_end[-1] - short_end[0]), "seconds": seconds, "note": ""}


def _row(solver: str, substeps: int, iterations: int, r: dict) -> str:
    rise = "slid off" if r["rise"] is None else f"{1000 * r['rise']:.1f}"
    return (f"| {solver} | {substeps}x{iterations} | {rise} | {r['seconds']:.1f} | "
            f"{r['note'] or '-'} |")


def main() -> None:
    from datagen.sim.backend import init_taichi

    init_taichi(threads=1)
    head = ("| solver | substeps x iterations | short end's rise mm | wall s | note |\n"
            "|---|---|---|---|---|")
    print(f"Command: `{COMMAND}`\n\nsilk, mu {MU}, long side at {SHARE} of the hold limit, "
          f"drum shaken {PEAK} m/s^2 at {HZ} Hz for {SECONDS} s\n\n{head}", flush=True)
    for setting in SETTINGS:
        print(_row(*setting, creep(*setting)), flush=True)
    print(f"\nThe same, stretch and compression 10x stiffer\n\n{head}", flush=True)
    for setting in STIFF_SETTINGS:
        print(_row(*setting, creep(*setting, stiffness=10.0)), flush=True)


if __name__ == "__main__":
    main()
