"""Runs four small scenes in a process of its own, for tests/test_sim_physics.py: Taichi's thread
count is fixed once per process (DATAGEN_TI_THREADS), and sweeps are coloured where it is above
one (a GPU's form of the solver, run on this CPU's threads).

Usage: python tests/parallel_sweeps.py MODE OUT.npz, MODE one of
  serial    the CPU default (one thread, Gauss-Seidel sweeps in one launch per frame)
  coloured  the parallel backend's kernels on one thread: backend.serial() overridden (every
            module reads it through the backend module), so that the two runs launch
            the same kernels (the collider's serial forms, its one-launch grid and serialized
            passes, may round differently on some CPUs: the coarse tube 0.2 mm apart at frame
            12 on one AMD EPYC)
  threads   coloured sweeps on two threads (DATAGEN_TI_THREADS=2 set by the caller), over the
            first frames of each scene only (THREADS_FRAMES: a shorter run's frames, but for
            its last on a collider track, whose path ends on a one-sided tangent, are the
            longer run's first ones, bit for bit, so the race check needs no full run; the
            physics is asserted on the coloured run, which must equal it), and
            test_sim_batch's three scenes batched, against each simulated alone where the
            batch put it and against the batch on a hashed body grid
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

# Frames per scene: the full runs, and the prefixes the two-thread run repeats.
FRAMES = {"sheet": 30, "tube": 12}
THREADS_FRAMES = {"sheet": 10, "tube": 4}


def main(mode: str, out: str) -> None:
    from datagen.sim import backend, solvers
    from datagen.sim import simulate as simulate_module  # imports every module that reads it

    if mode == "coloured":  # every kernel, sweeps and presets a parallel backend gets
        backend.serial = lambda: False
        assert not simulate_module.backend.serial()
    from datagen.sim.scenes import grid_sheet
    from datagen.sim.scenes import tube as tube_garment
    from datagen.sim.simulate import SimOptions, simulate
    from datagen.study.scenes import build_scene

    frames = THREADS_FRAMES if mode == "threads" else FRAMES
    # A 1 m leather sheet pinned along one edge swings down (pins, tethers, stiff bends).
    sheet = grid_sheet(40, 1.0, 1.5, fabric="leather")
    sheet.pinned = np.flatnonzero(np.isclose(sheet.vertices[:, 0], -0.5))
    options = SimOptions(frames=frames["sheet"], settle_seconds=0.0,
                         effects=("all", "-pressure_drag"), strain_refinements=0)
    swing = simulate([sheet], None, options)
    # A skirt-like cotton tube on a swinging, twisting cylinder (body contact, friction,
    # the closest-triangle search, self-collision).
    scene = build_scene("tube_cylinder", "cotton", "coarse", frames=frames["tube"])
    tube = simulate(scene.garments, scene.track,
                    SimOptions(frames=scene.frames, settle_seconds=0.0, strain_refinements=0))
    # Two coaxial tubes on the same cylinder, the outer one (layer 1) pressing on the inner
    # (garment-garment collision: the inner surface's normals and the pushes it takes).
    inner = tube_garment(0.112, 0.30, 48, 16, top=0.58, name="inner", flare=0.03)
    inner.pinned = inner.loops["waist"]
    outer = replace(tube_garment(0.118, 0.24, 48, 12, top=0.575, name="outer", flare=0.03), layer=1)
    outer.pinned = outer.loops["waist"]
    layered = simulate([inner, outer], scene.track,
                       SimOptions(frames=scene.frames, settle_seconds=0.0, strain_refinements=0))
    # The explicit baseline on the tube, 4 frames (its forces gathered per vertex there).
    short = build_scene("tube_cylinder", "cotton", "coarse", frames=4)
    explicit = simulate(short.garments, short.track,
                        SimOptions(solver="explicit", substeps=400, iterations=1, frames=4,
                                   settle_seconds=0.0, strain_refinements=0))
    batch_gaps = _batch_gaps() if mode == "threads" else []
    hashed_gaps = _hashed_gaps() if mode == "threads" else []
    np.savez(
        out,
        batch_gaps=batch_gaps,
        hashed_gaps=hashed_gaps,
        explicit=explicit.vertices[short.garments[0].name],
        layers=np.concatenate([layered.vertices["inner"], layered.vertices["outer"]], axis=1),
        layers_faces=inner.faces,
        layers_effects=layered.report["effects"],
        serial=solvers.backend.serial(),
        steps=[swing.report["substeps"], swing.report["iterations"]],
        sheet=swing.vertices[sheet.name],
        sheet_strain=swing.qa["strain_p999"],
        tube=tube.vertices[scene.garments[0].name],
        tube_strain=tube.qa["strain_p999"],
        tube_deep=tube.qa["deep_share"],
    )


def _batch_gaps() -> list[float]:
    """Per scene of test_sim_batch's batch, the largest distance between its batched and its
    solo run (at the batch's place) in any frame."""
    from test_sim_batch import batch_scenes, batched_against_alone

    rows = batched_against_alone(batch_scenes())
    assert not any(result.report["batch"]["alone"] for result, _, _ in rows)
    return [gap for _, _, gap in rows]


def _hashed_gaps() -> list[float]:
    """Per scene of test_sim_batch's batch, the largest distance in any frame between its run
    on a hashed body grid (forced, one bucket per triangle: cells share buckets, filled by
    parallel threads) and on the dense one."""
    from test_sim_batch import OPTIONS, batch_scenes

    from datagen.sim import collider
    from datagen.sim.batch import simulate_batch

    scenes = batch_scenes()
    dense = simulate_batch(scenes, OPTIONS)
    collider.DENSE_GRID_CELLS, collider.HASH_BUCKETS_PER_TRIANGLE = 0, 1
    hashed = simulate_batch(scenes, OPTIONS)
    names = [s.garments[0].name for s in scenes]
    return [float(np.abs(a.vertices[n] - b.vertices[n]).max())
            for n, a, b in zip(names, dense, hashed, strict=True)]


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
