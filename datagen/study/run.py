"""Run a study scene with one solver configuration; the trajectory and what it cost."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from datagen.errors import RejectedSequence
from datagen.sim.effects import resolve_effects
from datagen.sim.fabrics import get_fabric
from datagen.sim.simulate import (
    ColliderTrack,
    SimOptions,
    finer_steps_note,
    scene_content,
    simulate,
)
from datagen.study.scenes import StudyScene


@dataclass
class Run:
    label: str
    positions: np.ndarray  # (F + 1, V, 3) float64, frame 0 = the start
    # Seconds of the frames. The set-up before the first frame is timed apart, for ours and
    # Blender alike (ours: the model, collider, pins and solver; Blender: its first frame,
    # which builds its cloth): the two set-ups are not the same work.
    wall: float
    simulated: float  # seconds of simulated time
    qa: dict
    setup: float = 0.0
    # What a study row says of a run whose frames did not all run at its stated steps (the
    # stability guard's retries and holds; the study refines no frame for strain), else ''.
    note: str = ""

    @property
    def seconds_per_simulated_second(self) -> float:
        return self.wall / self.simulated


_WARM: set = set()
# The effects ours runs in the study and in bench_sim: the scene's own without self-collision,
# which Blender's peer scene leaves off (blender.scene_input), so that both simulators run
# the same simulation. Timing ours with an effect the peer does not run (self-collision was
# 30 % of the skirt-like tube's time) would compare two different simulations.
PEER_EFFECTS = "auto,-self_collision"


def peer_effects_key(scene: StudyScene) -> dict:
    """What the study cache's key of a run of `scene` with PEER_EFFECTS adds: nothing where
    they are the scene's own effects (what every run cached before PEER_EFFECTS ran), else the
    effects by name, so that a trajectory cached with the scene's own effects (the skirt's
    self-collision) is never read for one without."""
    fabrics = [get_fabric(g.fabric) for g in scene.garments]
    content = scene_content(scene.garments, scene.track is not None, None, fabrics)
    peer = resolve_effects(PEER_EFFECTS, content)
    return {} if peer == resolve_effects("auto", content) else {"effects": tuple(peer.enabled())}


def run_ours(scene: StudyScene, solver: str, substeps: int, iterations: int,
             label: str = "", settings=None, effects: str = PEER_EFFECTS,
             speed_limit: float | None = None,
             on_warm: Callable[[], object] | None = None) -> Run:
    """Simulate the scene; `settings` (a SolverSettings) may set the implicit tolerances and
    `speed_limit` the runaway guard (SimOptions.speed_limit). `on_warm` is called once the
    kernels are compiled, just before the timed run (bench_sim starts two runs together)."""
    extra = {} if speed_limit is None else {"speed_limit": speed_limit}
    if settings is not None:
        extra.update(tolerance=settings.tolerance, cg_tolerance=settings.cg_tolerance,
                     cg_max_iterations=settings.cg_max_iterations,
                     cg_forcing=settings.cg_forcing)
    # The study measures fixed settings: no frame is redone for its strain (dataset runs do
    # that; its cost shows in benchmarks/bench_dataset.py).
    options = SimOptions(solver=solver, substeps=substeps, iterations=iterations,
                         effects=effects, frames=scene.frames, profile_every=0,
                         strain_refinements=0, settle_seconds=0.0, **extra)
    key = (scene.name, solver, effects)
    if key not in _WARM:
        # Compile the kernels first (Taichi compiles on first launch): time only simulation.
        # Two frames at the run's own steps: at 2 substeps the explicit solver blows up on the
        # 1 cm body scenes, and a rejected warm-up must not stand for the run itself.
        track = scene.track
        short = ColliderTrack(track.vertices[:3], track.faces, track.face_mask, track.fps)
        warm = SimOptions(solver=solver, substeps=substeps, iterations=iterations,
                          effects=effects, profile_every=0, settle_seconds=0.0,
                          strain_refinements=0, **extra)
        try:
            simulate(scene.garments, short, warm)
        except RejectedSequence:
            pass  # the kernels are compiled; the measured run decides
        _WARM.add(key)
    if on_warm is not None:
        on_warm()
    result = simulate(scene.garments, scene.track, options)
    positions = np.concatenate([result.vertices[g.name] for g in scene.garments], axis=1)
    simulated = (len(positions) - 1) / scene.track.fps
    return Run(label or f"{solver} {substeps}x{iterations}", positions.astype(np.float64),
               result.report["frames_time_s"], simulated,
               {k: np.asarray(v) for k, v in result.qa.items()},
               setup=result.report["setup_time_s"], note=finer_steps_note(result.report))
