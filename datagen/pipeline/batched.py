"""Several sequences simulated as one batch: how a dataset run uses a GPU.

One scene on a GPU is bound by kernel launches and runs slower than on one CPU core; a batch of
scenes shares every launch (datagen.sim.batch, docs/simulator.md "Batches"). Here a worker's
group of sequences goes through the body and outfit stages one by one, as in
`stages.run_sequence`, and then through the simulator together: the sequences whose scenes can
share a solver (the same simulation settings, timeline and vertex-wide effects) as one batch
each; a sequence that can share with none is simulated as an unbatched one is. Each sequence is
then judged on its own exactly as an unbatched one is: a result that breaks a QA bound, or a
scene the batch could not keep stable, is simulated again alone up the escalation ladder
(`stages.simulate_within_bounds`). So a batch changes what a sequence costs, its substeps (a
frame the strain refinement refines is refined for every scene of the batch) and its rounding,
never which bounds it meets.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

from datagen.errors import RejectedSequence
from datagen.pipeline.stages import (
    SequenceRecord,
    mark_rejected,
    run_sequence,
    sim_options_from_spec,
    simulate_within_bounds,
    simulation_runs,
)
from datagen.recipe import BodyConfig
from datagen.spec import SceneSpec, SimSpec

if TYPE_CHECKING:
    from datagen.sim.simulate import SimOptions


def run_sequences_batched(specs: list[SceneSpec], body_model,
                          body_config: BodyConfig | None = None, base_dir: Path | None = None,
                          templates_dir: Path | None = None,
                          fabrics: dict | None = None,
                          guards: bool = False) -> list[SequenceRecord]:
    """Run the sequences end to end, their simulations batched (module docstring); the records
    in the order of `specs`. Each record's `simulate` timing is its share of its batch's time
    plus any run of its own."""
    records = [run_sequence(spec, body_model, body_config, base_dir, templates_dir,
                            simulate_cloth=False, fabrics=fabrics) for spec in specs]
    to_simulate = [r for r in records if r.status == "ok" and r.garments]
    by_settings: dict[SimSpec, list[SequenceRecord]] = {}
    for record in to_simulate:
        by_settings.setdefault(record.spec.simulation, []).append(record)
    for same_settings in by_settings.values():
        _simulate_together(same_settings, sim_options_from_spec(same_settings[0].spec, fabrics,
                                                                guards))
    return records


def _simulate_together(records: list[SequenceRecord], options: SimOptions) -> None:
    from datagen.sim.batch import batchable_groups, body_scene, simulate_batch

    scenes = [body_scene(r.garments, r.body) for r in records]
    for group in batchable_groups(scenes, options):
        t = time.perf_counter()
        if len(group) == 1:  # simulated as an unbatched run is: the same data
            outcomes = [None]
        else:
            outcomes = simulate_batch([scenes[k] for k in group], options)
        share = (time.perf_counter() - t) / len(group)
        for k, outcome in zip(group, outcomes, strict=True):
            record = records[k]
            t = time.perf_counter()
            try:
                record.sim = simulate_within_bounds(record.garments, record.body, options,
                                                    first=outcome)
                record.sim_runs = simulation_runs(record.sim)
            except RejectedSequence as exc:
                mark_rejected(record, exc)
            record.timings["simulate"] = share + time.perf_counter() - t
