"""The cloth simulator on a GPU: our default solver on a machine's GPU against one thread of the
same machine's CPU, timed in one run.

On a GPU (or several CPU threads) the xpbd sweeps are coloured Gauss-Seidel (docs/simulator.md)
and each preset runs twice the substeps and iterations; on one CPU thread, the serial sweeps in
one launch per frame. Both run the same scenes with the peer's effects (bench_sim), over
RATE_FRAMES frames after their kernels are compiled.

This project's machines have no GPU, so the benchmark has two halves:

    python -m benchmarks.bench_gpu --save-scenes SCENES  # here: the body scenes (Anny)
    python -m benchmarks.bench_gpu --run OUT_DIR --scenes SCENES  # on the GPU machine
    python -m benchmarks.bench_gpu --repeat OUT_DIR --scenes SCENES  # on the GPU machine
    python -m benchmarks.bench_gpu --report OUT_DIR      # here: errors, docs/benchmarks.md

`--run` starts one process per backend (both at once: the CPU run takes one core of many) and
writes their figures and trajectories to OUT_DIR, with batches of copies of the 4k and 10k
sheets (`batch`) and of 5k denim tubes through datagen.sim.batch (`batch_tubes`: what a batch
of scenes with moving colliders costs); `--report` sets each peer scene's cost per scene in
its largest batch against Blender (through one CPU thread, measured on both machines). A run
folder may hold a mode's files from an earlier run, named in carried.json; the report labels
them. `--modes` runs some of the modes (RUN_MODES, in that order), `--deadline S` starts none
after S seconds less what it needs, and `--pack FILE.tgz` packs the folder after each mode: a
machine lent for a few minutes then returns what finished (on an H200, 2026-12-04: the modes
before `hard` took 290 s, `hard` 137 s). `--repeat` (a call of its own: about four
minutes on an H100) simulates the 4k sheet and the saved hard cases twice each on the GPU from
the same input and compares the trajectories frame by frame: the same seed must give the same
data there too. `--report` measures each trajectory against
the float64 reference of bench_sim (implicit, REF_SUBSTEPS per frame, over the predictable
horizon), computed here, and writes the section. The scenes with a body (the walking t-shirt,
HARD_CASES) are pickled here by `--save-scenes`: their bodies come from Anny, which the GPU
machine need not have.
The GPU machine needs Taichi, trimesh, rtree and libigl besides what its image holds (carried
there as unpacked wheels for its Python: the wheels of the four, without Taichi's C API and
libigl's headers and static libraries, fit with the scenes in a call's 64 MiB as an xz tarball);
the figures of the last run, with their errors, are in benchmarks/results/gpu/summary.json.
The report chains a batch to Blender through bench_sim's peer rows (sim_peer.json) only where
both ran the same simulator: the same sources, or sources whose default peer runs are bit for
bit bench_sim's (its `behaviour` digest, computed again here at the GPU run's sources).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

COMMAND = "python -m benchmarks.bench_gpu"
REPO = Path(__file__).resolve().parents[1]
# (scene, fabric, resolution): the peer scenes of bench_sim that span its sizes and stiffness.
CASES = [("sheet_sphere", "cotton", "4k"), ("sheet_sphere", "cotton", "10k"),
         ("tube_cylinder", "denim", "5k")]
TSHIRT = ("tshirt_walk", "cotton", "")
# Hard cases (pipelines/hard_cases.yaml, full versions) run on both backends: the layered outfit
# (garment-garment collision) and the fast kick, the hardest for the strain bound.
HARD_CASES = ("tshirt_over_trousers", "fast_kick")
PROFILE_FRAMES = 5
RATE_FRAMES = int(os.environ.get("DATAGEN_BENCH_GPU_FRAMES", "30"))  # a quick check sets fewer
ERROR_FRAMES = 16
# Batches: copies of the cotton sheet on its sphere, 1.5 m apart, simulated as one scene
# (their cloth and spheres never meet): how a GPU's cost grows with the work in each launch.
# As long as the error horizon, so that the first scene of the largest batch is measured
# against the reference like a scene run alone.
BATCH_FRAMES = ERROR_FRAMES
BATCHES = {"cuda": {"4k": (1, 4, 16, 64), "10k": (1, 16, 64)},
           "cpu": {"4k": (1, 4, 16), "10k": (1, 4)}}
# Batches of body-like scenes through datagen.sim.batch: denim tubes on their swinging cylinders,
# every other one swung the opposite way (each scene a collider of its own in the batch's one).
TUBE_BATCHES = {"cuda": (1, 4, 16, 64), "cpu": (1, 4)}
REF_SUBSTEPS = 160


def batched_sheets(copies: int, frames: int, res: str = "4k"):
    """`copies` cotton sheets of a study resolution falling on their spheres, side by side, as
    one study scene; the first at the place of the study's own sheet."""
    from dataclasses import replace

    from datagen.sim.scenes import grid_sheet, icosphere
    from datagen.sim.simulate import ColliderTrack
    from datagen.study.scenes import FPS, SHEET_SIZES, StudyScene

    sheets, verts, faces = [], [], []
    for k in range(copies):
        shift = np.array([1.5 * k, 0.0, 0.0])
        sheet = grid_sheet(SHEET_SIZES[res], 1.0, 0.5, name=f"sheet{k}", fabric="cotton")
        sheets.append(replace(sheet, vertices=sheet.vertices + shift))
        sv, sf = icosphere(0.25, 4)
        faces.append(sf + sum(len(v) for v in verts))
        verts.append(sv + shift)
    sv, sf = np.concatenate(verts), np.concatenate(faces)
    track = ColliderTrack(np.repeat(sv[None], frames + 1, axis=0), sf, np.ones(len(sf), bool),
                          FPS)
    return StudyScene("sheet_batch", "cotton", f"{copies}x{res}", sheets, track, frames, frames,
                      frames)


def tube_batch_rows(arch: str, frames: int) -> tuple[list[dict], np.ndarray]:
    """Each batch of TUBE_BATCHES[arch] timed through simulate_batch after a batch of two has
    compiled the kernels; per batch the rate, each scene's worst strain and depth, and whether
    any scene had to be simulated alone. Also the first scene's trajectory in the largest batch
    (swung as the study's own tube), for its error against the reference."""
    from datagen.sim.batch import BatchScene, simulate_batch
    from datagen.sim.simulate import SimOptions
    from datagen.study.run import PEER_EFFECTS
    from datagen.study.scenes import FPS, mirrored_track, tube_cylinder

    scene = tube_cylinder("denim", "5k", frames=frames)
    track = scene.track
    mirrored = mirrored_track(track)
    options = SimOptions(solver="xpbd", frames=frames, profile_every=0, settle_seconds=0.0,
                         strain_refinements=0, effects=PEER_EFFECTS)

    def batch(copies: int):
        return [BatchScene(scene.garments, mirrored if k % 2 else track) for k in range(copies)]

    simulate_batch(batch(2), options)  # compiles the kernels
    rows = []
    for copies in TUBE_BATCHES[arch]:
        t = time.perf_counter()
        results = simulate_batch(batch(copies), options)
        wall = time.perf_counter() - t
        rows.append({"copies": copies, "vertices": copies * scene.n_vertices,
                     "s_per_sim_s": wall / (frames / FPS),
                     "alone": sum(bool(r.report["batch"]["alone"]) for r in results),
                     "strain_p999_max": max(float(r.qa["strain_p999"].max()) for r in results),
                     "deep_max": max(float(r.qa["deep_share"].max()) for r in results)})
        print(json.dumps(rows[-1]), flush=True)
    first = np.concatenate([results[0].vertices[g.name] for g in scene.garments], axis=1)
    return rows, first.astype(np.float32)


def save_scenes(folder: Path) -> None:
    """The body scenes, made here (Anny): the walking t-shirt's study scene, and each hard
    case's garments, body sequence and simulation options as the pipeline hands them to the
    simulator (pipeline.stages.run_sequence without its simulation)."""
    import pickle
    from dataclasses import replace

    from datagen.body.anny_model import default_body_model
    from datagen.pipeline.hard_cases import case_spec, load_hard_cases
    from datagen.pipeline.stages import run_sequence, sim_options_from_spec
    from datagen.study.scenes import build_scene

    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "tshirt.pkl", "wb") as f:
        pickle.dump(build_scene(TSHIRT[0], TSHIRT[1], frames=RATE_FRAMES), f, protocol=5)
    cases = load_hard_cases(REPO / "pipelines" / "hard_cases.yaml")
    model = default_body_model()
    for case in (c for c in cases.cases if c.name in HARD_CASES):
        spec = case_spec(case, False, cases)
        record = run_sequence(spec, model, base_dir=REPO, simulate_cloth=False)
        body = replace(record.body, skinning=None)  # the simulator reads the vertices
        with open(folder / f"hard_{case.name}.pkl", "wb") as f:
            pickle.dump({"name": case.name, "garments": record.garments, "body": body,
                         "options": sim_options_from_spec(spec)}, f, protocol=5)


def _saved_hard_cases(scenes: Path | None):
    """(name, saved input) of each of HARD_CASES that --save-scenes pickled into `scenes`."""
    import pickle

    for name in HARD_CASES:
        path = scenes / f"hard_{name}.pkl" if scenes else None
        if path and path.exists():
            with open(path, "rb") as f:
                yield name, pickle.load(f)


def _hard_case_rows(scenes: Path) -> list[dict]:
    """Each saved hard case through the simulator on this process's backend, judged as
    bench_hard_cases judges it."""
    from types import SimpleNamespace

    from datagen.errors import RejectedSequence
    from datagen.pipeline.hard_cases import judge, load_hard_cases
    from datagen.pipeline.stages import simulate_within_bounds

    cases = {c.name: c for c in load_hard_cases(REPO / "pipelines" / "hard_cases.yaml").cases}
    rows = []
    for name, saved in _saved_hard_cases(scenes):
        t = time.perf_counter()
        escalated = None
        try:
            sim = simulate_within_bounds(saved["garments"], saved["body"], saved["options"])
            record = SimpleNamespace(status="ok", sim=sim, garments=saved["garments"],
                                     body=saved["body"])
            escalated = sim.report.get("escalated_from")
        except RejectedSequence as exc:
            record = SimpleNamespace(status="rejected", stage=exc.stage, reason=exc.reason)
        result = judge(cases[name], record)
        rows.append({"case": name, "passed": result.passed, "detail": result.detail,
                     "frames": result.frames, "vertices": result.vertices,
                     "retries": result.retries, "strain_p999_max": result.strain_p999_max,
                     "strain_share_max": result.strain_share_max,
                     "deep_share_max": result.deep_share_max,
                     "kinetic_per_kg_max": result.kinetic_per_kg_max,
                     "escalated_from": escalated,
                     "wall_s": time.perf_counter() - t})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def _repeat_rows(scenes: Path | None) -> list[dict]:
    """The 4k cotton sheet (the peer's effects) and each saved hard case simulated twice in this
    process from the same input: the first frame at which the two runs differ, if any."""
    from datagen.sim.simulate import SimOptions, simulate
    from datagen.study.run import PEER_EFFECTS
    from datagen.study.scenes import build_scene

    sheet = build_scene("sheet_sphere", "cotton", "4k", frames=RATE_FRAMES)
    inputs = [("sheet_sphere 4k cotton", sheet.garments, sheet.track,
               SimOptions(effects=PEER_EFFECTS, frames=RATE_FRAMES, profile_every=0,
                          strain_refinements=0, settle_seconds=0.0))]
    inputs += [(name, saved["garments"], saved["body"], saved["options"])
               for name, saved in _saved_hard_cases(scenes)]
    rows = []
    for name, garments, body, options in inputs:
        runs, walls, qa = [], [], []
        for _ in range(2):
            t = time.perf_counter()
            sim = simulate(garments, body, options)
            walls.append(time.perf_counter() - t)
            runs.append(np.concatenate([sim.vertices[g] for g in sim.garment_names], axis=1))
            qa.append({"over_strain_max": float(np.max(sim.qa["over_strain_share"])),
                       "deep_max": float(np.max(sim.qa["deep_share"]))})
        gap = np.abs(runs[1].astype(np.float64) - runs[0]).max(axis=(1, 2))
        differing = np.flatnonzero(gap)
        rows.append({"case": name, "frames": len(gap), "vertices": runs[0].shape[1],
                     "identical": len(differing) == 0,
                     "first_differing_frame": int(differing[0]) if len(differing) else None,
                     "max_gap_mm": 1000 * float(gap.max()), "wall_s": walls, "qa": qa})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def python_launches(run) -> int:
    """How many Taichi kernels `run()` calls from Python (each call pays Taichi's argument
    handling and a launch, whatever the work: what binds one scene on a GPU)."""
    import taichi.lang.kernel_impl as kernel_impl

    calls = 0
    original = kernel_impl.Kernel.__call__

    def counted(self, *args, **kwargs):
        nonlocal calls
        calls += 1
        return original(self, *args, **kwargs)

    kernel_impl.Kernel.__call__ = counted
    try:
        run()
    finally:
        kernel_impl.Kernel.__call__ = original
    return calls


def _worker(arch: str, out: Path, scenes: Path | None, mode: str) -> None:
    """Run every case on one backend in this process (Taichi's backend is fixed per process).
    Modes: `cases` (CASES and the t-shirt); `profile`, the first case over PROFILE_FRAMES with
    Taichi's kernel profiler (how much of the wall time the device spends in kernels, and in
    which); `batch`, batched_sheets at each of BATCHES; `serial_limit`, the first case with the
    strain limit after contact in its serial form (one task) instead of coloured sweeps;
    `hard`, HARD_CASES from `scenes`; `batch_tubes`, tube_batch_rows; `self_collision`, the
    5k cotton tube with its own effects and without self-collision; `repeat`, _repeat_rows."""
    os.environ["DATAGEN_TI_ARCH"] = arch
    profile = mode == "profile"
    if profile:
        os.environ["DATAGEN_TI_PROFILER"] = "1"
    import pickle

    import taichi as ti

    from datagen.sim.backend import arch as backend_arch
    from datagen.sim.backend import serial
    from datagen.sim.simulate import PARALLEL_QUALITY_PRESETS, QUALITY_PRESETS, ColliderTrack
    from datagen.study import run as study_run
    from datagen.study.run import run_ours
    from datagen.study.scenes import build_scene

    presets = QUALITY_PRESETS if serial() else PARALLEL_QUALITY_PRESETS
    sub, it = presets["xpbd"]["default"]

    def fresh_run(scene, **kw):
        # run_ours warms up once per scene name: each run here compiles its own kernels (a
        # parallel backend's sweeps are compiled per count of colours) before it is timed.
        study_run._WARM.clear()
        return run_ours(scene, "xpbd", sub, it, **kw)
    cases = [(name, fabric, res, None) for name, fabric, res in CASES]
    tshirt = scenes / "tshirt.pkl" if scenes else None
    if tshirt and tshirt.exists():
        cases.append((*TSHIRT, tshirt))
    if mode == "hard":
        out.write_text(json.dumps(_hard_case_rows(scenes), indent=1))
        return
    if mode == "repeat":
        out.write_text(json.dumps(_repeat_rows(scenes), indent=1))
        return
    if mode == "self_collision":  # the skirt-like tube with its own effects, and without one
        rows = []
        for effects in ("auto", "auto,-self_collision"):
            scene = build_scene("tube_cylinder", "cotton", "5k", frames=RATE_FRAMES)
            run = fresh_run(scene, effects=effects)
            rows.append({"effects": effects, "s_per_sim_s": run.seconds_per_simulated_second,
                         "strain_p999_max": float(np.max(run.qa["strain_p999"])),
                         "deep_max": float(np.max(run.qa["deep_share"])),
                         "finite": bool(np.isfinite(run.positions).all())})
            print(json.dumps(rows[-1]), flush=True)
        out.write_text(json.dumps(rows, indent=1))
        return
    if mode == "batch":
        rows, arrays = [], {}
        for res, counts in BATCHES[arch].items():
            for copies in counts:
                scene = batched_sheets(copies, BATCH_FRAMES, res)
                run = fresh_run(scene)
                rows.append({"res": res, "copies": copies, "vertices": scene.n_vertices,
                             "s_per_sim_s": run.seconds_per_simulated_second,
                             "finite": bool(np.isfinite(run.positions).all()),
                             "strain_p999_max": float(np.max(run.qa["strain_p999"]))})
                print(json.dumps(rows[-1]), flush=True)
            # The first sheet of the largest batch, for its error against the reference.
            n_first = scene.garments[0].vertices.shape[0]
            arrays[f"sheet_sphere_cotton_{res}"] = run.positions[:, :n_first].astype(np.float32)
        np.savez_compressed(out.with_suffix(".npz"), **arrays)
        out.write_text(json.dumps(rows, indent=1))
        return
    if mode == "batch_tubes":
        rows, first = tube_batch_rows(arch, BATCH_FRAMES)
        np.savez_compressed(out.with_suffix(".npz"), tube_cylinder_denim_5k=first)
        out.write_text(json.dumps(rows, indent=1))
        return
    if mode == "serial_limit":
        from datagen.sim.solvers import XPBDSolver

        def listed(self, collider, h):
            self._limit_after_contact_listed(collider, h, collider is not None)

        XPBDSolver._limit_after_contact_coloured = listed
        cases = cases[:1]
    if profile:
        name, fabric, res, _ = cases[0]
        scene = build_scene(name, fabric, res, frames=PROFILE_FRAMES)
        fresh_run(scene)  # compiles
        ti.profiler.clear_kernel_profiler_info()
        run = run_ours(scene, "xpbd", sub, it)
        ti.sync()
        kernels = ti.profiler.get_kernel_profiler_total_time()
        # Counted in a run of its own (the count's wrapper would add to the timed one).
        calls = python_launches(lambda: run_ours(scene, "xpbd", sub, it))
        out.write_text(json.dumps({"arch": backend_arch(), "scene": f"{name} {res} {fabric}",
                                   "frames": PROFILE_FRAMES, "substeps": sub,
                                   "wall": run.wall, "kernel_time": kernels,
                                   "python_launches_per_substep":
                                       calls / (PROFILE_FRAMES * sub)}))
        ti.profiler.print_kernel_profiler_info("count")
        return
    rows, arrays = [], {}
    for name, fabric, res, path in cases:
        if path:
            with open(path, "rb") as f:
                scene = pickle.load(f)
            track = scene.track
            scene.track = ColliderTrack(track.vertices[: RATE_FRAMES + 1], track.faces,
                                        track.face_mask, track.fps)
            scene.frames = RATE_FRAMES
        else:
            scene = build_scene(name, fabric, res, frames=RATE_FRAMES)
        t = time.perf_counter()
        run = fresh_run(scene)
        key = f"{name}_{fabric}_{res}"
        rows.append({
            "key": key, "name": name, "res": res, "scene": f"{name} {res}".strip(),
            "fabric": fabric,
            "vertices": scene.n_vertices, "arch": backend_arch(), "substeps": sub,
            "iterations": it, "wall": run.wall, "simulated": run.simulated,
            "s_per_sim_s": run.seconds_per_simulated_second,
            "with_compile_s": time.perf_counter() - t,
            "finite": bool(np.isfinite(run.positions).all()),
            "strain_p999_max": float(np.max(run.qa["strain_p999"])),
            "over_strain_max": float(np.max(run.qa["over_strain_share"])),
            "deep_max": float(np.max(run.qa["deep_share"])),
            "ke_max": float(np.max(run.qa["kinetic_energy"])),
        })
        arrays[key] = run.positions[: ERROR_FRAMES + 1].astype(np.float32)
        print(json.dumps(rows[-1]), flush=True)
    np.savez_compressed(out.with_suffix(".npz"), **arrays)
    out.write_text(json.dumps(rows, indent=1))


def _both_backends(mode: str, out_dir: Path, scenes: Path | None, env: dict) -> None:
    """A worker mode on the GPU and on one CPU thread at once, each in a process of its own."""
    procs = []
    for arch in ("cuda", "cpu"):
        name = arch if mode == "cases" else f"{mode}_{arch}"
        cmd = [sys.executable, "-m", "benchmarks.bench_gpu", "--worker", arch, "--mode", mode,
               "--out", str(out_dir / f"{name}.json")]
        if scenes:
            cmd += ["--scenes", str(scenes)]
        procs.append(subprocess.Popen(cmd, env=env))
    codes = [p.wait() for p in procs]
    if any(codes):
        raise SystemExit(f"a backend's {mode} run failed (exit codes {codes})")


# --run's modes in the order they run: the ones the report needs first, so that a run cut
# short by a machine's lease still makes a report (`--deadline`); the hard cases last, the
# longest (about 3.5 minutes on an H200), and only with saved scenes.
RUN_MODES = ("cases", "batch", "batch_tubes", "profile", "serial_limit", "self_collision",
             "hard")
# Alone on the GPU: the profiler would slow the timed runs, and the serial limit's cost is the
# GPU's question.
GPU_ONLY_MODES = ("profile", "serial_limit")
HARD_MODE_SECONDS = 240.0  # what `hard` needs of the deadline to be started


def run_all(out_dir: Path, scenes: Path | None, modes: tuple[str, ...] = RUN_MODES,
            deadline: float | None = None, pack: Path | None = None) -> None:
    """The measurements of `modes`, in RUN_MODES' order, both backends at once where both run.
    With `deadline` (seconds from the start) a mode is not started once too little is left
    (HARD_MODE_SECONDS for the hard cases, 20 s for the others); with `pack` (a .tgz path) the
    folder is packed there after each mode, so that what finished comes back from a machine
    whose lease ends mid-run."""
    import tarfile

    from datagen.study.cache import source_digest

    unknown = sorted(set(modes) - set(RUN_MODES))
    if unknown:
        raise SystemExit(f"--modes: unknown {', '.join(unknown)}; expected some of "
                         f"{', '.join(RUN_MODES)}")
    start = time.monotonic()
    out_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONWARNINGS="ignore", PYTHONUNBUFFERED="1")
    machine = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                             capture_output=True, text=True).stdout.strip()
    (out_dir / "machine.json").write_text(json.dumps(
        {"gpu": machine, "cpu_cores": os.cpu_count(), "date": time.strftime("%Y-%m-%d"),
         "python": sys.version.split()[0], "source": source_digest()}))
    for mode in (m for m in RUN_MODES if m in modes):
        if mode == "hard" and not scenes:
            print("hard: skipped (no --scenes)", flush=True)
            continue
        left = None if deadline is None else deadline - (time.monotonic() - start)
        if left is not None and left < (HARD_MODE_SECONDS if mode == "hard" else 20.0):
            print(f"{mode}: skipped, {left:.0f} s of the deadline left", flush=True)
            continue
        t = time.monotonic()
        if mode in GPU_ONLY_MODES:
            subprocess.run([sys.executable, "-m", "benchmarks.bench_gpu", "--worker", "cuda",
                            "--mode", mode, "--out", str(out_dir / f"{mode}.json")], env=env,
                           check=True)
        else:
            _both_backends(mode, out_dir, scenes, env)
        print(f"{mode}: {time.monotonic() - t:.0f} s", flush=True)
        if pack is not None:
            with tarfile.open(pack, "w:gz") as tar:
                tar.add(out_dir, arcname=out_dir.name)


def _reference(row: dict, out_dir: Path) -> tuple[np.ndarray, int]:
    """The float64 reference of a case and its predictable horizon (bench_sim's), kept in
    out_dir as ref_<key>.npz: each costs minutes here."""
    from benchmarks.bench_sim import float64_reference

    return float64_reference(row["name"], row["fabric"], row["res"],
                             cache=out_dir / f"ref_{row['key']}.npz")


def tube_batch_lines(out_dir: Path) -> list[str]:
    """The table of the `batch_tubes` runs, where the folder has them."""
    runs = {a: json.loads((out_dir / f"batch_tubes_{a}.json").read_text())
            for a in ("cuda", "cpu") if (out_dir / f"batch_tubes_{a}.json").exists()}
    if "cuda" not in runs:
        return []
    cpu = {b["copies"]: b for b in runs.get("cpu", [])}
    lines = [
        "",
        f"Batches of body-like scenes (`datagen.sim.batch`): 5k denim tubes on their swinging "
        f"cylinders, every other one swung the other way, each on its own cell of the batch, "
        f"{BATCH_FRAMES} frames (the CPU's, on one thread, at the same time):",
        "",
        "| scenes | vertices | GPU s/sim-s | GPU s/sim-s per scene | CPU s/sim-s | "
        "simulated alone | strain p99.9 max | too deep max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for b in runs["cuda"]:
        c = cpu.get(b["copies"])
        on_cpu = f"{c['s_per_sim_s']:.2f}" if c else "-"
        lines.append(f"| {b['copies']} | {b['vertices']} | {b['s_per_sim_s']:.2f} | "
                     f"{b['s_per_sim_s'] / b['copies']:.3f} | {on_cpu} | {b['alone']} | "
                     f"{b['strain_p999_max']:.3f} | {100 * b['deep_max']:.2f} % |")
    return lines


def _verdict(row: dict) -> str:
    """A hard case's verdict, with its escalation where it was simulated again."""
    if not row["passed"]:
        return "FAIL: " + row["detail"]
    return "pass: " + row["detail"] if row.get("escalated_from") else "pass"


def blender_rows(source: str) -> tuple[str, dict[tuple[str, str], dict], str]:
    """bench_sim's peer rows as its last full run wrote them (its date, and per scene and
    fabric our one-thread rate, Blender's rate and Blender's error), and how they are known to
    describe the GPU run's simulator: Blender cannot run on the GPU machine, so a batch is
    compared with it through one CPU thread, measured on both. The chain holds only where both
    ran the same simulator: the same sources (`source`: the GPU run's digest), or sources that
    differ while our default solver's peer runs stay bit for bit as bench_sim's were
    (bench_sim.peer_behaviour, computed here, at the GPU run's sources)."""
    from benchmarks.bench_sim import PEER_JSON, peer_behaviour
    from datagen.study.cache import source_digest

    data = json.loads(PEER_JSON.read_text())
    how = f"the same simulator sources ({source})"
    if data["source"] != source:
        recorded = data.get("behaviour")
        here = source_digest()
        today = peer_behaviour() if recorded and here == source else None
        if today is None or today != recorded:
            raise SystemExit(
                f"{PEER_JSON}: field 'source': bench_sim's peer rows ({data['date']}) were "
                f"measured with simulator sources {data['source']}, the GPU run with {source}"
                + (f" (this checkout: {here})" if here != source else "")
                + (f", and our peer runs do not behave as then (behaviour {today}, then "
                   f"{recorded})" if today else "")
                + "; a batch is set against Blender through one CPU thread of each, so both "
                "must run the same simulator: run bench_sim at the GPU run's sources, or the "
                "GPU run at bench_sim's")
        how = (f"simulator sources {data['source']} for bench_sim and {source} for the GPU run, "
               f"whose default peer runs are bit for bit the same: bench_sim.peer_behaviour "
               f"{today}")
    rows = {(r["scene"], r["fabric"]): {"ours": r["ours_s_per_sim_s"],
                                        "blender": r["blender_s_per_sim_s"],
                                        "blender_error_mm": r["blender_err_mm"]}
            for r in data["rows"]}
    return data["date"], rows, how


def batch_against_blender(out_dir: Path, batches: dict) -> list[dict]:
    """Per peer scene, the largest GPU batch's cost per scene against one CPU thread of the
    same machine running the scene alone (same run), chained with bench_sim's ratio of
    Blender's rate to one thread of ours here; and the error of the batch's first scene
    (where the run saved it) against the scene's float64 reference."""
    from datagen.study.metrics import rms_distance

    machine = json.loads((out_dir / "machine.json").read_text())
    date, blender, how = blender_rows(machine["source"])
    tubes = {a: json.loads((out_dir / f"batch_tubes_{a}.json").read_text())
             for a in ("cuda", "cpu") if (out_dir / f"batch_tubes_{a}.json").exists()}

    def sheets(arch: str, res: str) -> list[dict]:
        return [b for b in batches[arch] if b["res"] == res]

    groups = [(("sheet_sphere", "cotton", res), sheets("cuda", res), sheets("cpu", res))
              for res in ("4k", "10k")]
    if len(tubes) == 2:
        groups.append((("tube_cylinder", "denim", "5k"), tubes["cuda"], tubes["cpu"]))
    out = []
    for (name, fabric, res), gpu, cpu in groups:
        alone = [b for b in cpu if b["copies"] == 1]
        peer = blender.get((f"{name} {res}", fabric))
        if not gpu or not alone or peer is None:
            continue
        g = gpu[-1]
        per_scene = g["s_per_sim_s"] / g["copies"]
        key = f"{name}_{fabric}_{res}"
        error = float("nan")
        npz = out_dir / ("batch_tubes_cuda.npz" if name == "tube_cylinder" else "batch_cuda.npz")
        first = np.load(npz) if npz.exists() else {}
        if key in first:
            ref, h = _reference({"key": key, "name": name, "fabric": fabric, "res": res},
                                out_dir)
            error = 1000 * rms_distance(first[key].astype(np.float64), ref, h)
        gpu_over_cpu = alone[0]["s_per_sim_s"] / per_scene
        out.append({"scene": f"{name} {res}", "fabric": fabric, "copies": g["copies"],
                    "gpu_per_scene": per_scene, "cpu_alone": alone[0]["s_per_sim_s"],
                    "ours_here": peer["ours"], "blender_here": peer["blender"],
                    "blender_date": date, "same_simulator": how,
                    "chained": gpu_over_cpu * peer["blender"] / peer["ours"],
                    "gpu_error_mm": error, "blender_error_mm": peer["blender_error_mm"]})
    return out


def per_scene_lines(rows: list[dict]) -> list[str]:
    """The table of batch_against_blender, and what it does and does not say."""
    if not rows:
        return []
    lines = [
        "",
        "Per scene in the largest batch, against Blender: Blender cannot run on the GPU machine "
        "(it reaches no package registry, and Blender's packages are larger than what can be "
        "carried to it), so the GPU's cost per scene is set against one CPU "
        "thread of that machine simulating the scene alone (the serial `default`, in the same "
        "run), and that thread's kind against Blender through bench_sim's first table, measured "
        f"here on {rows[0]['blender_date']} (our one thread and Blender, in one run; "
        f"{rows[0]['same_simulator']}): the "
        "estimate is GPU/CPU-thread there times Blender/ours here. The GPU error is the "
        "batch's first scene against the scene's float64 reference (as in the first table); "
        "Blender's is bench_sim's, at its quality 5.",
        "",
        "| scene | fabric | scenes in the batch | GPU s/sim-s per scene | CPU thread, alone | "
        "GPU / CPU thread | ours here | Blender here | estimate: Blender's s/sim-s over the "
        "GPU's per scene | GPU error mm | Blender error mm |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['fabric']} | {r['copies']} | {r['gpu_per_scene']:.3f} | "
            f"{r['cpu_alone']:.2f} | {r['cpu_alone'] / r['gpu_per_scene']:.1f}x | "
            f"{r['ours_here']:.2f} | {r['blender_here']:.2f} | {r['chained']:.0f}x | "
            f"{r['gpu_error_mm']:.2f} | {r['blender_error_mm']:.2f} |")
    low = min(rows, key=lambda r: r["chained"])
    within = all(r["gpu_error_mm"] <= r["blender_error_mm"] for r in rows)
    lines += [
        "",
        f"In batches every peer scene is simulated at an estimated {low['chained']:.0f}x "
        f"Blender's rate or more (least: {low['scene']} {low['fabric']})"
        + (", each with an error no larger than Blender's" if within else
           ", but not every one with an error no larger than Blender's")
        + ". That is throughput, not the issue's per-scene target: each scene of a batch "
        "takes the batch's whole time, and one scene alone on the GPU is slower than one CPU "
        "thread (the first table). A dataset run batches its sequences with `datagen "
        "dataset --batch N` (datagen.pipeline.batched), not yet timed on a GPU.",
    ]
    return lines


def repeat_lines(rows: list[dict]) -> list[str]:
    """The report's table of a --repeat run."""
    lines = [
        "",
        f"The same input twice on the GPU (`{COMMAND} --repeat`, a call of its own; each pair "
        "in one process, compared frame by frame):",
        "",
        "| case | frames | vertices | same trajectory | first differing frame | "
        "largest gap mm | edges over bound (max), runs | wall s, runs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        first = "-" if r["first_differing_frame"] is None else r["first_differing_frame"]
        over = ", ".join(f"{100 * q['over_strain_max']:.3f} %" for q in r["qa"])
        walls = ", ".join(f"{w:.0f}" for w in r["wall_s"])
        lines.append(f"| {r['case']} | {r['frames']} | {r['vertices']} | "
                     f"{'yes' if r['identical'] else 'NO'} | {first} | "
                     f"{r['max_gap_mm']:.3g} | {over} | {walls} |")
    return lines


def report(out_dir: Path) -> None:
    """The section of docs/benchmarks.md from a --run folder, and the figures with their errors
    as summary.json in it."""
    from benchmarks.common import write_section
    from datagen.qa import DEEP_SHARE_MAX, STRAIN_SHARE_MAX
    from datagen.study.metrics import rms_distance

    def load(name: str):
        return json.loads((out_dir / f"{name}.json").read_text())

    rows = {a: load(a) for a in ("cuda", "cpu")}
    pos = {a: np.load(out_dir / f"{a}.npz") for a in ("cuda", "cpu")}
    machine, profile, limit = load("machine"), load("profile"), load("serial_limit")[0]
    # Modes not repeated in this run, their files copied from an earlier one (carried.json:
    # {"from": "<date, device>", "modes": [...]}), so that a short device call need not redo
    # them; their figures are labelled with the run they come from.
    carried = load("carried") if (out_dir / "carried.json").exists() else {}

    def earlier(mode: str) -> str:
        if mode not in carried.get("modes", ()):
            return ""
        return f"; from the run of {carried['from']}, not repeated in this one"
    batches = {a: load(f"batch_{a}") for a in ("cuda", "cpu")}
    g0, c0 = rows["cuda"][0], rows["cpu"][0]
    lines = [
        f"Measured on {machine['gpu']} and one thread of the same machine's CPU "
        f"({machine['cpu_cores']} cores), {machine['date']}, in one call (`{COMMAND} --run`), "
        f"{RATE_FRAMES} frames at 30 fps after compiling; the GPU and CPU runs at once (the CPU "
        "run takes one core of many). GPU: xpbd with coloured sweeps at the parallel `default` "
        f"preset ({g0['substeps']} substeps x {g0['iterations']} iterations, docs/simulator.md); "
        f"CPU: the serial sweeps at `default` ({c0['substeps']}x{c0['iterations']}) in one "
        "launch per frame. Both with the peer's effects (bench_sim). Errors: RMS distance to "
        f"bench_sim's float64 implicit reference ({REF_SUBSTEPS} substeps) over its predictable "
        f"horizon, computed on this project's machine (`{COMMAND} --report`).",
        "",
        "| scene | fabric | vertices | GPU s/sim-s | CPU s/sim-s | GPU rate / CPU rate | "
        "GPU error mm | CPU error mm | horizon (frames) | GPU strain p99.9 | CPU strain p99.9 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    summary = []
    for g, c in zip(rows["cuda"], rows["cpu"], strict=True):
        eg = ec = float("nan")
        h = "-"
        if not g["key"].startswith("tshirt"):
            ref, h = _reference(g, out_dir)
            eg, ec = (1000 * rms_distance(pos[a][g["key"]].astype(np.float64), ref, h)
                      for a in ("cuda", "cpu"))
        summary.append({"gpu": g, "cpu": c, "gpu_error_mm": eg, "cpu_error_mm": ec,
                        "horizon": h})
        lines.append(
            f"| {g['scene']} | {g['fabric']} | {g['vertices']} | {g['s_per_sim_s']:.2f} | "
            f"{c['s_per_sim_s']:.2f} | {c['s_per_sim_s'] / g['s_per_sim_s']:.2f}x | "
            f"{eg:.2f} | {ec:.2f} | {h} | {g['strain_p999_max']:.3f} | "
            f"{c['strain_p999_max']:.3f} |")
    share = profile["kernel_time"] / profile["wall"]
    # Counted since 2026-12-05 (runs before it: one per effect and sweep, 30-40).
    per_substep = profile.get("python_launches_per_substep")
    calls = "30-40" if per_substep is None else f"{per_substep:.1f}"
    bodies = [(label, r) for g, c in zip(rows["cuda"], rows["cpu"], strict=True)
              if g["key"].startswith("tshirt") for label, r in (("GPU", g), ("CPU", c))]
    if bodies:
        worst = ", ".join(f"{label} {100 * r['over_strain_max']:.3f} % of edges over the "
                          f"strain bound and {100 * r['deep_max']:.3f} % of vertices too deep"
                          for label, r in bodies)
        lines += ["", "The walking t-shirt has no float64 reference here (hours of CPU); at "
                  f"most, in any frame: {worst} (bounds: {100 * STRAIN_SHARE_MAX:g} % and "
                  f"{100 * DEEP_SHARE_MAX:g} %)."]
    lines += [
        "",
        f"Where the GPU's time goes (Taichi's kernel profiler, {profile['scene']}, "
        f"{profile['frames']} frames): the device ran kernels for {profile['kernel_time']:.2f} "
        f"of {profile['wall']:.2f} s ({100 * share:.0f} %), 6-12 us a kernel whether it "
        f"moves a thousand springs or none; the rest is launching them: {calls} calls from "
        "Python a substep (each a few kernels, one a colour). The "
        "strain limit after contact as one serial task (the CPU's form; the serial_limit run, "
        f"alone on the GPU{earlier('serial_limit')}) ran the same scene at "
        f"{limit['s_per_sim_s']:.2f} s/sim-s against "
        f"{g0['s_per_sim_s']:.2f} with coloured sweeps.",
        "",
        f"Batches: copies of the cotton sheet on its sphere side by side as one scene, "
        f"{BATCH_FRAMES} frames (the GPU's and the CPU's batches at once):",
        "",
        "| sheet | copies | vertices | GPU s/sim-s | CPU s/sim-s | GPU s/sim-s per copy | "
        "GPU rate / CPU rate |",
        "|---|---|---|---|---|---|---|",
    ]
    cpu_batch = {(b["res"], b["copies"]): b for b in batches["cpu"]}
    for b in batches["cuda"]:
        cb = cpu_batch.get((b["res"], b["copies"]))
        cpu = f"{cb['s_per_sim_s']:.2f}" if cb else "-"
        ratio = f"{cb['s_per_sim_s'] / b['s_per_sim_s']:.2f}x" if cb else "-"
        lines.append(f"| {b['res']} | {b['copies']} | {b['vertices']} | "
                     f"{b['s_per_sim_s']:.2f} | {cpu} | {b['s_per_sim_s'] / b['copies']:.3f} | "
                     f"{ratio} |")
    lines += tube_batch_lines(out_dir)
    per_scene = batch_against_blender(out_dir, batches)
    lines += per_scene_lines(per_scene)
    hard = {a: load(f"hard_{a}") for a in ("cuda", "cpu")
            if (out_dir / f"hard_{a}.json").exists()}
    if hard:
        lines += [
            "",
            "Hard cases (pipelines/hard_cases.yaml, full versions, judged as bench_hard_cases "
            f"judges them; both backends at once, in a call of their own{earlier('hard')}):",
            "",
            "| case | backend | vertices | edges over bound (max) | vertices too deep (max) | "
            "strain p99.9 | KE max J/kg | retries | wall s | verdict |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for g, c in zip(hard["cuda"], hard["cpu"], strict=True):
            for label, r in (("GPU", g), ("CPU, one thread", c)):
                lines.append(
                    f"| {r['case']} | {label} | {r['vertices']} | "
                    f"{100 * r['strain_share_max']:.3f} % | {100 * r['deep_share_max']:.3f} % | "
                    f"{r['strain_p999_max']:.3f} | {r['kinetic_per_kg_max']:.2f} | "
                    f"{r['retries']} | {r['wall_s']:.0f} | "
                    f"{_verdict(r)} |")
    own = {a: load(f"self_collision_{a}") for a in ("cuda", "cpu")
           if (out_dir / f"self_collision_{a}.json").exists()}
    if own:
        g, c = ({r["effects"]: r["s_per_sim_s"] for r in own[a]} for a in ("cuda", "cpu"))
        lines += [
            "",
            "Self-collision (the 5k cotton tube with its own effects"
            f"{earlier('self_collision')}): GPU "
            f"{g['auto']:.2f} s/sim-s against {g['auto,-self_collision']:.2f} without it "
            f"({g['auto'] / g['auto,-self_collision']:.2f}x), CPU {c['auto']:.2f} against "
            f"{c['auto,-self_collision']:.2f} ({c['auto'] / c['auto,-self_collision']:.2f}x).",
        ]
    widest = [b for b in batches["cuda"] if b["res"] == "4k"][-1]
    ratios = [r["cpu"]["s_per_sim_s"] / r["gpu"]["s_per_sim_s"] for r in summary]
    one_cpu = cpu_batch[("4k", 1)]["s_per_sim_s"]
    lines += [
        "",
        f"One scene on the GPU is {min(ratios):.2f}-{max(ratios):.2f}x "
        "the rate of one CPU thread on the scenes of the first table (4k-12k vertices): "
        "launch-bound, slower than the serial path at each of their sizes. Batched, the GPU's "
        f"cost hardly grows: {widest['copies']} sheets at once "
        f"cost {widest['s_per_sim_s'] / widest['copies']:.3f} s per simulated second each, "
        f"{one_cpu * widest['copies'] / widest['s_per_sim_s']:.1f}x one CPU thread's rate "
        "for one sheet (measured in the same run).",
    ]
    faster = [(g, c) for g, c in zip(hard.get("cuda", []), hard.get("cpu", []), strict=True)
              if g["wall_s"] < c["wall_s"]]
    lines += [f"Of the hard cases, {g['case']} ({g['vertices']} vertices) ran faster on the GPU "
              f"({g['wall_s']:.0f} against {c['wall_s']:.0f} s)." for g, c in faster]
    if (out_dir / "repeat_cuda.json").exists():  # a table last: text after it would join it
        lines += repeat_lines(load("repeat_cuda"))
    (out_dir / "summary.json").write_text(json.dumps(
        {"machine": machine, "cases": summary, "profile": profile, "serial_limit": limit,
         "batches": batches, "per_scene_in_batches": per_scene, "hard_cases": hard,
         "self_collision": own, "carried": carried}, indent=1))
    write_section("gpu", "Cloth simulator on a GPU", "\n".join(lines),
                  f"{COMMAND} --run DIR (on the GPU machine), then {COMMAND} --report DIR")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, help="run both backends, figures into this folder")
    parser.add_argument("--modes", default=",".join(RUN_MODES),
                        help="with --run: the modes to run, comma-separated (default: all)")
    parser.add_argument("--deadline", type=float,
                        help="with --run: seconds after which no further mode is started")
    parser.add_argument("--pack", type=Path,
                        help="with --run: pack the folder into this .tgz after each mode")
    parser.add_argument("--repeat", type=Path,
                        help="on the GPU: each case twice from the same input, into this folder")
    parser.add_argument("--report", type=Path, help="write the section from a --run folder")
    parser.add_argument("--worker", choices=["cuda", "cpu"], help=argparse.SUPPRESS)
    parser.add_argument("--mode", default="cases", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--scenes", type=Path,
                        help="with --run: the folder --save-scenes wrote (body scenes)")
    parser.add_argument("--save-scenes", type=Path,
                        help="pickle the body scenes into this folder (needs Anny)")
    args = parser.parse_args(argv)
    if args.worker:
        _worker(args.worker, args.out, args.scenes, args.mode)
    elif args.run:
        run_all(args.run, args.scenes, tuple(m for m in args.modes.split(",") if m),
                args.deadline, args.pack)
    elif args.repeat:
        args.repeat.mkdir(parents=True, exist_ok=True)
        _worker("cuda", args.repeat / "repeat_cuda.json", args.scenes, "repeat")
    elif args.report:
        report(args.report)
    elif args.save_scenes:
        save_scenes(args.save_scenes)
    else:
        parser.error("one of --run, --repeat, --report or --save-scenes")


if __name__ == "__main__":
    main()
