"""Dataset runs: many sequences, resumable, sharded, on local processes or a Dask cluster.

- Sequence ids are stable: `<seed>-<index>`; shard k holds indices [k*S, (k+1)*S).
- A shard is written whole (`shard-k.h5.tmp`, renamed when complete) once all its sequences are
  finished or rejected; a re-run skips every shard that exists, deletes leftover `.tmp` files and
  recomputes only the missing shards, so nothing is done twice and nothing half-written stays.
  At most one shard's worth of work per worker is lost to a crash.
- Rejected sequences are stored in their shard (`/rejected`) with the reason, so they are not
  retried; the manifest and the dataset card are rebuilt from the shards.
- One writer (this process) writes every shard; workers only compute.
"""

from __future__ import annotations

import json
import os
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from datagen.errors import InputError
from datagen.io.shard import (
    FORMAT,
    FORMAT_VERSION,
    SHARD_SUFFIX,
    TMP_SUFFIX,
    ShardWriter,
    write_record,
)
from datagen.recipe import LoadedRecipe, load_recipe
from datagen.spec import SceneSpec

MANIFEST = "manifest.jsonl"
DATASET_INFO = "dataset.json"
CARD = "README.md"
SHARD_GLOB = "shard-*" + SHARD_SUFFIX  # the shards this run writes (shard_name)


def shard_name(k: int) -> str:
    return f"shard-{k:05d}{SHARD_SUFFIX}"


# -- workers -----------------------------------------------------------------------------------
_WORKER: dict = {}


def worker_state(recipe_path: str) -> dict:
    """Per-process state: the recipe and the body model, built once per worker (and Taichi on
    one thread). A pool's initializer may call it so that no sequence pays for it."""
    state = _WORKER.get(recipe_path)
    if state is None:
        from datagen.body.anny_model import default_body_model
        from datagen.sim.backend import init_taichi

        init_taichi(threads=1)
        loaded = load_recipe(recipe_path)
        state = {"loaded": loaded, "model": default_body_model()}
        _WORKER[recipe_path] = state
    return state


def _templates_dir(loaded: LoadedRecipe) -> Path | None:
    from datagen.garment.outfit import outfit_config, resolve_templates_dir

    if not loaded.recipe.outfit:
        return None
    return resolve_templates_dir(outfit_config(loaded).templates, loaded.base_dir)


def _rejects(loaded: LoadedRecipe) -> bool:
    """Whether the recipe's QA gate rejects a sequence over a bound (simulation.qa)."""
    return loaded.recipe.simulation.qa == "reject"


def _qa_gate(loaded: LoadedRecipe, record):
    from datagen.pipeline.stages import reject_over_qa_bounds

    return reject_over_qa_bounds(record) if _rejects(loaded) else record


def compute_sequence(recipe_path: str, index: int):
    """Run sequence `index` of the recipe (in any process): a SequenceRecord."""
    from datagen.pipeline.stages import run_sequence
    from datagen.sampling import sample_scene

    state = worker_state(recipe_path)
    loaded: LoadedRecipe = state["loaded"]
    record = run_sequence(sample_scene(loaded, index), state["model"], loaded.recipe.body,
                          loaded.base_dir, _templates_dir(loaded),
                          guards=_rejects(loaded))
    return _qa_gate(loaded, record)


def compute_sequences(recipe_path: str, indices: list[int]) -> list:
    """Run sequences `indices` of the recipe (in any process), their simulations batched
    (datagen.pipeline.batched) where there are several: their SequenceRecords in order."""
    if len(indices) == 1:
        return [compute_sequence(recipe_path, indices[0])]
    from datagen.pipeline.batched import run_sequences_batched
    from datagen.sampling import sample_scene

    state = worker_state(recipe_path)
    loaded: LoadedRecipe = state["loaded"]
    records = run_sequences_batched([sample_scene(loaded, i) for i in indices], state["model"],
                                    loaded.recipe.body, loaded.base_dir, _templates_dir(loaded),
                                    guards=_rejects(loaded))
    return [_qa_gate(loaded, r) for r in records]


# -- the output folder -------------------------------------------------------------------------
@dataclass
class DatasetState:
    out: Path
    shard_size: int
    n_sequences: int

    @property
    def n_shards(self) -> int:
        return (self.n_sequences + self.shard_size - 1) // self.shard_size

    def indices(self, k: int) -> range:
        return range(k * self.shard_size, min((k + 1) * self.shard_size, self.n_sequences))


def prepare_output(out: Path, loaded: LoadedRecipe, shard_size: int, n: int) -> DatasetState:
    """Check that `out` is new or holds this same dataset; clear half-written files."""
    out.mkdir(parents=True, exist_ok=True)
    info = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "recipe": loaded.recipe.name,
        "seed": loaded.recipe.seed,
        "shard_size": shard_size,
    }
    info_path = out / DATASET_INFO
    if info_path.exists():
        try:
            existing = json.loads(info_path.read_text())
        except json.JSONDecodeError:
            raise InputError(info_path, None, "a dataset.json written by datagen",
                             "unreadable JSON") from None
        for key in ("format", "format_version", "recipe", "seed", "shard_size"):
            if existing.get(key) != info[key]:
                raise InputError(
                    info_path, key,
                    f"{info[key]!r} to resume this run (the folder holds another dataset; "
                    "choose a new --out)", existing.get(key))
    else:
        for shard in out.glob(SHARD_GLOB):
            _check_foreign_shard(shard)
    for tmp in out.glob("*" + TMP_SUFFIX):
        tmp.unlink()  # a shard whose writing was interrupted: it is recomputed
    _write_json_atomic(info_path, info)
    return DatasetState(out=out, shard_size=shard_size, n_sequences=n)


def _check_foreign_shard(path: Path) -> None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            version = int(f.attrs.get("format_version", -1))
            fmt = f.attrs.get("format")
    except OSError:
        raise InputError(path, None, "a readable shard, or an empty output folder",
                         "unreadable file") from None
    if fmt != FORMAT or version != FORMAT_VERSION:
        raise InputError(path, "format_version",
                         f"{FORMAT} version {FORMAT_VERSION} (or an empty output folder)", version)


def _write_json_atomic(path: Path, data) -> None:
    tmp = path.with_name(path.name + TMP_SUFFIX)
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def finished_shards(state: DatasetState) -> set[int]:
    done = set()
    for k in range(state.n_shards):
        if (state.out / shard_name(k)).exists():
            done.add(k)
    return done


# -- manifest and card -------------------------------------------------------------------------
def manifest_rows(out: Path) -> list[dict]:
    import h5py

    rows = []
    for shard in sorted(out.glob(SHARD_GLOB)):
        with h5py.File(shard, "r") as f:
            for seq_id, g in f.get("sequences", {}).items():
                spec = json.loads(g.attrs["spec"])
                garments = g.get("garments", {})
                qa = {k: float(v[()].max()) for k, v in g.get("qa", {}).items()}
                timings = json.loads(g.attrs.get("timings", "{}"))
                report = json.loads(g["sim"].attrs["report"]) if "sim" in g else {}
                rows.append({
                    "id": seq_id, "index": spec["sequence_index"], "shard": shard.name,
                    "status": "ok", "reason": None, "split": spec["split"],
                    # simulated again at finer steps (stages.simulate_within_bounds): why
                    "escalated": (report.get("escalated_from") or {}).get("reason"),
                    "garments": [str(garments[n].attrs["type"]) for n in garments],
                    "fabrics": [str(garments[n].attrs["fabric"]) for n in garments],
                    "action": spec["motion"]["action"], "frames": int(g.attrs["frames"]),
                    "qa": qa, "wall_time": float(sum(timings.values())),
                    "environment": _environment_label(g),
                })
            for seq_id, g in f.get("rejected", {}).items():
                spec = SceneSpec.from_json(g.attrs["spec"], str(shard))
                timings = json.loads(g.attrs.get("timings", "{}"))
                # The types and fabrics its garments would have been written with, so that a
                # type's rejections count against it (an open shirt is a "shirt", not the
                # "tshirt" template it is cut from; a jumpsuit one garment, not two).
                worn = spec.outfit.worn()
                rows.append({
                    "id": seq_id, "index": spec.sequence_index, "shard": shard.name,
                    "status": "rejected", "reason": f"{g.attrs['stage']}: {g.attrs['reason']}",
                    "split": spec.split,
                    "garments": [kind for _, kind, _ in worn],
                    "fabrics": [fabric for _, _, fabric in worn],
                    "action": spec.motion.action, "frames": 0, "qa": {},
                    "wall_time": float(sum(timings.values())),
                    "environment": _environment_label(g),
                })
    rows.sort(key=lambda r: r["index"])
    return rows


def _environment_label(group) -> str | None:
    """'CPU; python X; anny X, datagen X, ...' (packages as stored, by name) from a sequence's
    `environment` attribute (the worker that made it: datagen.environment); None for a shard
    written before it existed."""
    text = group.attrs.get("environment")
    if text is None:
        return None
    env = json.loads(text)
    packages = ", ".join(f"{k} {v}" for k, v in env["packages"].items() if v is not None)
    return f"{env['cpu']}; python {env['python']}; {packages}"


def write_manifest(out: Path) -> list[dict]:
    rows = manifest_rows(out)
    tmp = out / (MANIFEST + TMP_SUFFIX)
    tmp.write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
    os.replace(tmp, out / MANIFEST)
    return rows


def write_card(out: Path, loaded: LoadedRecipe, rows: list[dict], wall: float | None,
               workers: int) -> None:
    ok = [r for r in rows if r["status"] == "ok"]
    rejected = [r for r in rows if r["status"] == "rejected"]

    def table(counter: Counter, title: str) -> str:
        lines = [f"| {title} | sequences |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in sorted(counter.items())]
        return "\n".join(lines)

    def against_rejected(values, title: str) -> str:
        """Written and rejected sequences by each of `values(row)` (counted once a sequence):
        the gate drops some kinds more often than others (an open shirt slides off a runner's
        shoulders), and what is written is then not the recipe's mix."""
        written = Counter(v for r in ok for v in set(values(r)))
        dropped = Counter(v for r in rejected for v in set(values(r)))
        lines = [f"| {title} | sequences | rejected |", "|---|---|---|"]
        lines += [f"| {k} | {written[k]} | {dropped[k]} |"
                  for k in sorted(written.keys() | dropped.keys())]
        return "\n".join(lines)

    size = sum(p.stat().st_size for p in out.glob(SHARD_GLOB))
    frames = sum(r["frames"] for r in ok)
    fps = loaded.recipe.motion.fps
    qa_deep = max((r["qa"].get("deep_share", 0.0) for r in ok), default=0.0)
    qa_strain = max((r["qa"].get("strain_p999", 0.0) for r in ok), default=0.0)
    qa_over = max((r["qa"].get("over_strain_share", 0.0) for r in ok), default=0.0)
    compute = sum(r["wall_time"] for r in rows)
    lines = [
        f"# Dataset `{loaded.recipe.name}`",
        "",
        f"Made by datagen from `{loaded.path.name}` (seed {loaded.recipe.seed}). Layout: "
        "docs/shard-format.md of the datagen repository; read it with "
        "`datagen.io.reader.DatasetReader` or `GarmentDataset`.",
        "",
        f"- sequences: {len(ok)} finished, {len(rejected)} rejected, of "
        f"{loaded.recipe.sequences} in the recipe",
        f"- frames: {frames} ({frames / fps:.1f} s at {fps:g} fps)",
        f"- storage: {size / 2**20:.1f} MiB in {len(list(out.glob(SHARD_GLOB)))} shards",
        f"- compute: {compute / 60:.1f} min of sequence work"
        + (f"; this run took {wall / 60:.1f} min on {workers} worker(s), "
           f"{len(rows) / max(wall, 1e-9) * 3600:.0f} sequences per hour" if wall else ""),
        f"- QA over all frames: worst 99.9th-percentile strain {qa_strain:.3f}, worst share of "
        f"a garment's springs beyond their fabric's max_strain {qa_over:.4f}, worst share of a "
        f"garment's vertices deeper than the fabric thickness in the body {qa_deep:.4f}",
        f"- simulated again one quality preset up after a first run broke a bound or went "
        f"unstable: {sum(1 for r in ok if r.get('escalated'))} of the finished",
        "",
        "## Splits", "", table(Counter(r["split"] for r in ok), "split"), "",
        "## Garment types", "",
        "Sequences written with a garment of each type, fabric and action, and those rejected "
        "(the Rejections section below says why).", "",
        against_rejected(lambda r: r["garments"], "type"), "",
        "## Fabrics", "", against_rejected(lambda r: r["fabrics"], "fabric"), "",
        "## Actions", "", against_rejected(lambda r: [r["action"]], "action"), "",
        "## Made on", "",
        "The machine and package versions of the workers that made the sequences, written "
        "and rejected (each sequence's `environment` attribute). The same seed gives the same "
        "data on the same machine and software; elsewhere float rounding differs, and a "
        "chaotic frame can amplify it.", "",
        against_rejected(lambda r: [r["environment"] or "not recorded"], "environment"), "",
        "## Rejections", "",
    ]
    if rejected:
        lines += [table(Counter(r["reason"].split(" (")[0] for r in rejected), "reason")]
    else:
        lines += ["None."]
    (out / CARD).write_text("\n".join(lines) + "\n")


# -- the run -----------------------------------------------------------------------------------
def check_recipe_clips(loaded: LoadedRecipe) -> None:
    """Every motion clip the recipe lists is long enough for its sequences."""
    from datagen.motion.load import check_clip_lengths

    motion = loaded.recipe.motion
    for source in ("bvh", "amass"):
        if motion.sources.get(source, 0) > 0:
            check_clip_lengths(source, loaded.motion_files(source), loaded.base_dir,
                               motion.frames, motion.fps, loaded.path)


def run_dataset(recipe_path: str | Path, out: str | Path, n: int | None = None,
                workers: int = 1, scheduler: str | None = None, shard_size: int | None = None,
                progress: bool = True, batch: int = 1) -> list[dict]:
    """Run (or resume) a dataset; returns the manifest rows. `batch`: sequences a worker
    simulates at once (datagen.pipeline.batched; for GPUs, where one scene is launch-bound)."""
    recipe_path = str(Path(recipe_path).resolve())
    loaded = load_recipe(recipe_path)
    n = loaded.recipe.sequences if n is None else n
    if n < 0:
        raise InputError(None, "--n", "0 or more sequences", n)
    size = shard_size or loaded.recipe.storage.shard_size
    if not 1 <= batch <= size:
        raise InputError(None, "--batch", f"1 to the shard size ({size}) sequences a batch: "
                         "batches never span shards, so a resumed run batches as the first "
                         "did (raise --shard-size for larger batches)", batch)
    state = prepare_output(Path(out), loaded, size, n)
    # Sample every spec up front: bad recipe values fail here, before any work is spent.
    from datagen.sampling import sample_scene

    for index in range(n):
        sample_scene(loaded, index)
    check_recipe_clips(loaded)
    done = finished_shards(state)
    pending = [k for k in range(state.n_shards) if k not in done]
    todo = [i for k in pending for i in state.indices(k)]
    t0 = time.time()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, initial=n - len(todo), unit="seq", desc="sequences",
                   dynamic_ncols=True)
    counts = Counter()
    waiting: dict[int, dict[int, object]] = {k: {} for k in pending}

    def finish(record) -> None:
        index = record.spec.sequence_index
        k = index // size
        waiting[k][index] = record
        counts[record.status] += 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(ok=counts["ok"], rejected=counts["rejected"])
        if len(waiting[k]) == len(state.indices(k)):
            with ShardWriter(state.out / shard_name(k)) as writer:
                for i in state.indices(k):
                    write_record(writer, waiting[k][i],
                                 loaded.recipe.storage.store_body_vertices,
                                 loaded.recipe.storage.quantize)
            del waiting[k]
            write_manifest(state.out)

    # Each shard's sequences in batches of consecutive indices: the same batches whichever
    # shards a resumed run finds done, so the same seed gives the same data.
    chunks = [list(state.indices(k)[i:i + batch])
              for k in pending for i in range(0, len(state.indices(k)), batch)]
    try:
        if scheduler:
            _run_dask(scheduler, recipe_path, chunks, finish)
        elif workers <= 1:
            for chunk in chunks:
                for record in compute_sequences(recipe_path, chunk):
                    finish(record)
        else:
            _run_processes(workers, recipe_path, chunks, finish)
    finally:
        if bar is not None:
            bar.close()
    rows = write_manifest(state.out)
    write_card(state.out, loaded, rows, time.time() - t0 if todo else None,
               workers if not scheduler else 0)
    return rows


def _run_processes(workers: int, recipe_path: str, chunks: list[list[int]], finish) -> None:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = multiprocessing.get_context("spawn")  # no fork: Taichi and torch hold threads
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        queue = list(chunks)
        running = set()
        while queue or running:
            while queue and len(running) < 2 * workers:  # a short queue keeps memory flat
                running.add(pool.submit(compute_sequences, recipe_path, queue.pop(0)))
            finished, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                for record in fut.result():
                    finish(record)


def _run_dask(address: str, recipe_path: str, chunks: list[list[int]], finish) -> None:
    from distributed import Client, as_completed

    try:
        client = Client(address)
    except (OSError, ValueError) as exc:  # unreachable, or not an address: not a traceback
        raise InputError(None, "--scheduler", f"the address of a running Dask scheduler, "
                         f"tcp://host:port ({exc})", address) from None
    with client:
        futures = [client.submit(compute_sequences, recipe_path, c, pure=False) for c in chunks]
        for fut in as_completed(futures):
            for record in fut.result():
                finish(record)
