"""Dataset-run benchmark: what `make dataset` costs and what the full CLOTH3D recipe would.

1. The default recipe (`pipelines/default.yaml`) end to end, as `make dataset` runs it (one
   worker process per core): wall time, sequences per hour, the share of each stage.
2. The projected cost of `pipelines/cloth3d.yaml`: its first sequences (24 by default), drawn
   by its own sampler at their full length, each in a single-threaded process, one per core
   as a dataset run has them; the mean core-seconds per sequence (with its 95 % interval)
   times the recipe's sequence count, in core-hours, and how many were simulated again.
3. Storage: the garment positions of the default run written again, lossless and quantised, in
   bytes per garment vertex per frame, with the quantised mode's largest error (target: at most
   4 bytes at 0.1 mm).

Times are this machine's; the stage shares and the storage ratio are the figures that carry
over to another one.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path

import h5py

from benchmarks.common import REPO, write_section

COMMAND = "python -m benchmarks.bench_dataset"
QUANT_TARGET_BYTES = 4.0
QUANT_TARGET_ERROR = 1e-4  # m


def run_default(out: Path, workers: int, n: int | None) -> dict:
    from datagen.pipeline.dataset import run_dataset

    t = time.perf_counter()
    rows = run_dataset(REPO / "pipelines" / "default.yaml", out, n=n, workers=workers,
                       progress=True)
    wall = time.perf_counter() - t
    status = Counter(r["status"] for r in rows)
    stages: Counter = Counter()
    for shard in sorted(out.glob("*.h5")):
        with h5py.File(shard, "r") as f:
            groups = [*f.get("sequences", {}).values(), *f.get("rejected", {}).values()]
            for group in groups:
                stages.update(json.loads(group.attrs["timings"]))
    return {"rows": rows, "wall": wall, "status": status, "stages": stages, "workers": workers}


def _timed_sequence(recipe: str, index: int) -> dict:
    """Sequence `index` of the recipe in this (single-threaded) worker: its core-seconds and
    what happened to it."""
    from datagen.pipeline.dataset import compute_sequence
    from datagen.pipeline.stages import escalation_note

    t = time.perf_counter()
    record = compute_sequence(recipe, index)
    seconds = time.perf_counter() - t
    rep = record.sim.report if record.sim is not None else {}
    return {"index": index, "seconds": seconds, "frames": record.spec.motion.frames,
            # Simulated more than once: escalated, whether kept in the end or rejected (a
            # rejected record keeps no report: until 2026-12-05 those were counted as not).
            "status": record.status, "escalated": record.sim_runs > 1,
            "retries": int(rep.get("retries", 0)),
            # A record rejected after simulation (the QA gate) keeps no garments: count them
            # from its spec (pieces sewn into one garment share its name), vertices unknown.
            "garments": (len(record.garments) if record.garments is not None
                         else len({g.name for g in record.spec.outfit.garments})),
            "vertices": (sum(len(g.vertices) for g in record.garments)
                         if record.garments is not None else None),
            "note": f"{record.reason or 'ok'}{escalation_note(record.sim)}"}


def cloth3d_sample(k: int, workers: int) -> dict:
    """Core-seconds per sequence of the CLOTH3D recipe, from its first k sequences, run as a
    dataset run runs them: one single-threaded process per core (two simulations at once do
    not slow each other on this machine: docs/simulator.md)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from datagen.pipeline.dataset import worker_state
    from datagen.recipe import load_recipe

    recipe = str(REPO / "pipelines" / "cloth3d.yaml")
    loaded = load_recipe(recipe)
    ctx = multiprocessing.get_context("spawn")  # no fork: Taichi and torch hold threads
    # Each worker builds its body model and Taichi before its sequences are timed: a dataset
    # run pays that once per worker, not once per sequence.
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=worker_state,
                             initargs=(recipe,)) as pool:
        runs = []
        for run in pool.map(_timed_sequence, [recipe] * k, range(k)):
            runs.append(run)
            print(f"cloth3d sequence {run['index']}: {run['status']} in {run['seconds']:.0f} s, "
                  f"{run['garments']} garment(s), {run['vertices']} vertices, {run['frames']} "
                  f"frames ({run['note']})",
                  flush=True)
    return {"runs": runs, "sequences": loaded.recipe.sequences}


def projection_lines(sample: dict) -> list[str]:
    """The projected cost's section: the mean core-seconds per sequence with its 95 %
    interval (Student's t over the sample), times the recipe's sequence count."""
    from scipy import stats

    runs, n_total = sample["runs"], sample["sequences"]
    times = [r["seconds"] for r in runs]
    n = len(times)
    mean = statistics.mean(times)
    half = (stats.t.ppf(0.975, n - 1) * statistics.stdev(times) / n ** 0.5) if n > 1 else 0.0
    hours = mean * n_total / 3600.0
    lo, hi = (mean - half) * n_total / 3600.0, (mean + half) * n_total / 3600.0
    escalated = [r for r in runs if r["escalated"]]
    rejected = [r for r in runs if r["status"] != "ok"]
    # The recipe's count is of sequences run, and the QA gate drops some: what a user plans
    # with is how many get written, so the written share comes with its binomial interval
    # (Wilson's, which stays inside 0-1 for small samples and shares near 1).
    written = n - len(rejected)
    share = written / n
    share_ci = stats.binomtest(written, n).proportion_ci(confidence_level=0.95, method="wilson")
    esc_share = sum(r["seconds"] for r in escalated) / sum(times)
    by_garments = Counter(r["garments"] for r in runs)
    frames = sorted({r["frames"] for r in runs})
    vertices = [r["vertices"] for r in runs if r["vertices"] is not None] or [0]
    lines = [
        f"### Projected cost of `pipelines/cloth3d.yaml` ({n_total} sequences)\n",
        "| measure | value |\n|---|---|",
        f"| sequences run (the recipe's first {n}, full length, one single-threaded process "
        f"per core) | {n}: {written} finished, "
        f"{len(rejected)} rejected; "
        + ", ".join(f"{c} with {g} garment{'s' if g > 1 else ''}"
                    for g, c in sorted(by_garments.items()))
        + f" ({min(vertices):,}-{max(vertices):,} garment vertices); "
        + f"{frames[0]}" + (f"-{frames[-1]}" if len(frames) > 1 else "") + " frames |",
        f"| core-seconds per sequence | mean {mean:.0f} (95 % interval {mean - half:.0f}-"
        f"{mean + half:.0f}), median {statistics.median(times):.0f}, range "
        f"{min(times):.0f}-{max(times):.0f} |",
        f"| simulated again at finer steps (escalation) | {len(escalated)} of {n} "
        f"({100 * esc_share:.0f} % of the sample's core-seconds) |",
        f"| frames retried at smaller steps (stability guard), in the runs kept | "
        f"{sum(r['retries'] for r in runs)} in {sum(r['retries'] > 0 for r in runs)} "
        "sequences |",
        f"| projected cost | **{hours:,.0f} core-hours** ({hours / 24:,.0f} core-days; "
        f"95 % interval {lo:,.0f}-{hi:,.0f}) |",
        f"| written (not rejected) | {written} of {n}, {100 * share:.0f} % (95 % interval "
        f"{100 * share_ci.low:.0f}-{100 * share_ci.high:.0f} %, Wilson's): the recipe's "
        f"{n_total:,} would write about **{share * n_total:,.0f}** "
        f"({share_ci.low * n_total:,.0f}-{share_ci.high * n_total:,.0f}) |",
        f"| to write {n_total:,} at the sample's share | "
        + (f"about {n_total / share:,.0f} sequences run, {hours / share:,.0f} core-hours |"
           if written else "none written in the sample |"),
        "",
        "The interval is the mean's (the sample's spread over the square root of its size, "
        "Student's t): it narrows with `--cloth3d-samples N`, as does the written share's "
        "(the QA gate's rejections: docs/simulator.md, \"Known losses\"). Outfits range "
        "from one garment "
        "to a layered pair, and a sequence's cost follows its garment vertex count, its motion "
        "and whether it had to be simulated again.",
    ]
    for r in escalated + [r for r in rejected if not r["escalated"]]:
        lines.append(f"- sequence {r['index']}: {r['status']}, {r['seconds']:.0f} s ({r['note']})")
    return lines


def storage_figures(dataset: Path, scratch: Path) -> dict:
    """Every garment trajectory of the dataset written again in both modes."""
    from datagen.io.shard import read_positions, write_positions
    from datagen.io.storage import position_storage, quantization_error

    out = {}
    for mode in ("lossless", "quantised"):
        folder = scratch / mode
        folder.mkdir(parents=True)
        for shard in sorted(dataset.glob("*.h5")):
            with h5py.File(shard, "r") as src, h5py.File(folder / shard.name, "w") as dst:
                for sid, seq in src.get("sequences", {}).items():
                    group = dst.create_group(f"sequences/{sid}")
                    trans = seq["body"]["trans"][...]
                    group.create_dataset("body/trans", data=trans)
                    for name, garment in seq.get("garments", {}).items():
                        if "vertices" not in garment:
                            continue
                        g = group.create_group(f"garments/{name}")
                        write_positions(g, "vertices", read_positions(garment, "vertices"),
                                        trans, mode == "quantised")
        out[mode] = position_storage(folder)
    out["error"] = quantization_error(scratch / "lossless", scratch / "quantised")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=None, help="default-recipe sequences (all)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    # 24: the first 16 held 2 of the recipe's slides and the first 24 held 6 (2026-12-06), so
    # 16 made the written share look better than it is; 8 more sequences cost about 9 minutes.
    parser.add_argument("--cloth3d-samples", type=int, default=24)
    args = parser.parse_args(argv if argv is not None else [])

    scratch = Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    try:
        run = run_default(scratch / "data", args.workers, args.n)
        sample = (cloth3d_sample(args.cloth3d_samples, args.workers) if args.cloth3d_samples
                  else None)
        store = storage_figures(scratch / "data", scratch / "storage")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    n_run = len(run["rows"])
    wall = run["wall"]
    per_hour = n_run / wall * 3600.0
    stage_total = sum(run["stages"].values()) or 1.0
    shares = ", ".join(f"{name} {100 * v / stage_total:.0f} %"
                       for name, v in run["stages"].most_common())
    lines = [
        f"### `make dataset` (the default recipe, {n_run} sequences, {run['workers']} worker "
        "processes)\n",
        "| measure | value |\n|---|---|",
        f"| wall time, start to card | {wall / 60:.1f} min |",
        f"| sequences per hour (finished or rejected) | {per_hour:.1f} |",
        f"| finished / rejected | {run['status']['ok']} / {run['status']['rejected']} |",
        f"| worker time by stage | {shares} |",
        "",
        f"Target: the default recipe in under 15 minutes on 2 cores: "
        f"**{'meets' if wall <= 900 else 'misses'}** it ({wall / 60:.1f} min).",
    ]
    if sample:
        lines += [""] + projection_lines(sample)
    lossless, quant = store["lossless"], store["quantised"]
    b_q = quant.bytes_per_vertex_frame
    quant_ok = b_q <= QUANT_TARGET_BYTES and store["error"] <= QUANT_TARGET_ERROR
    lines += [
        "",
        "### Storage of garment positions (the default run's trajectories)\n",
        "| mode | bytes per vertex per frame | largest error |\n|---|---|---|",
        f"| lossless (float32, gzip, chunk per frame) | "
        f"{lossless.bytes_per_vertex_frame:.2f} | 0 |",
        f"| quantised (int16 steps of 0.1 mm from the pelvis, gzip) | {b_q:.2f} | "
        f"{store['error'] * 1000:.3f} mm |",
        "",
        f"Target: quantised at most {QUANT_TARGET_BYTES:.0f} bytes at 0.1 mm: "
        f"**{'meets' if quant_ok else 'misses'}** it ({b_q:.2f} bytes, "
        f"{store['error'] * 1000:.3f} mm; the raw sizes are 12 and 6).",
    ]
    write_section("dataset", "Dataset runs", "\n".join(lines), COMMAND)


if __name__ == "__main__":
    main()
