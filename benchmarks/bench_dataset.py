"""Dataset-run benchmark: what `make dataset` costs and what the full CLOTH3D recipe would.

1. The default recipe (`pipelines/default.yaml`) end to end, as `make dataset` runs it (one
   worker process per core): wall time, sequences per hour, the share of each stage.
2. The projected cost of `pipelines/cloth3d.yaml`: a few of its sequences, drawn by its own
   sampler at their full length, each run in one single-threaded process (one core); the mean
   core-seconds per sequence times the recipe's sequence count, in core-hours.
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


def cloth3d_sample(k: int) -> dict:
    """Core-seconds per sequence of the CLOTH3D recipe, from k of its sequences."""
    from datagen.pipeline.dataset import compute_sequence
    from datagen.pipeline.stages import escalation_note
    from datagen.recipe import load_recipe

    recipe = REPO / "pipelines" / "cloth3d.yaml"
    loaded = load_recipe(recipe)
    times, frames, status = [], [], Counter()
    for index in range(k):
        t = time.perf_counter()
        record = compute_sequence(str(recipe), index)
        times.append(time.perf_counter() - t)
        frames.append(record.spec.motion.frames)
        status[record.status] += 1
        print(f"cloth3d sequence {index}: {record.status} in {times[-1]:.0f} s "
              f"({record.reason or 'ok'}{escalation_note(record.sim)})", flush=True)
    return {"times": times, "frames": frames, "status": status,
            "sequences": loaded.recipe.sequences}


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
    parser.add_argument("--cloth3d-samples", type=int, default=2)
    args = parser.parse_args(argv if argv is not None else [])

    scratch = Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    try:
        run = run_default(scratch / "data", args.workers, args.n)
        sample = cloth3d_sample(args.cloth3d_samples) if args.cloth3d_samples else None
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
        mean = statistics.mean(sample["times"])
        core_hours = mean * sample["sequences"] / 3600.0
        lines += [
            "",
            f"### Projected cost of `pipelines/cloth3d.yaml` ({sample['sequences']} sequences)\n",
            "| measure | value |\n|---|---|",
            f"| sequences run (drawn by the recipe, full length) | {len(sample['times'])} "
            f"({', '.join(str(f) for f in sample['frames'])} frames; "
            f"{sample['status']['ok']} finished) |",
            f"| core-seconds per sequence | mean {mean:.0f}, range "
            f"{min(sample['times']):.0f}-{max(sample['times']):.0f} |",
            f"| projected cost | **{core_hours:,.0f} core-hours** "
            f"({core_hours / 24:,.0f} core-days) |",
            "",
            f"A projection from {len(sample['times'])} sequences: outfits range from one "
            "garment to a layered pair and the cost follows the garment vertex count and the "
            "motion, so the sample's range spans "
            f"{min(sample['times']) * sample['sequences'] / 3600:,.0f}-"
            f"{max(sample['times']) * sample['sequences'] / 3600:,.0f} core-hours; "
            "`--cloth3d-samples N` narrows it.",
        ]
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
