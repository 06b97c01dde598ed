"""How far the constraint sweeps are from this machine's limits: a benchmark of the solver's
inner loops against floors measured in the same run (DESIGN: speed against a peer, and against
the hardware limit).

The spring and bending sweeps are the largest part of a frame (docs/simulator.md, "The walking
outfit's rate and the machine": about three tenths and a tenth of a walking frame), so how
close they run to what the processor allows says how much faster the solver could go by tuning
them rather than by doing fewer sweeps. For each scene's springs (the solver's spring sets) and
bending stencils, in the solver's own sweep order, this times on one thread the product's
Gauss-Seidel update (`kernels.spring_gs_one`, `kernels.bend_gs_one`) in three settings, each
as one kernel that sweeps REPEATS times (no launch in the time):

- `product`: the sweep as a frame runs it, over all of the scene's elements;
- `memory floor`: the same loads and stores in the same order with the update's arithmetic
  taken out (what was loaded, summed in a shallow tree and written back times a zero the
  compiler cannot see): what the sweep's memory traffic costs alone, at the cache levels its
  arrays live in;
- `arithmetic floor`: the product's update over the elements of a small disc of the same cloth
  (PATCH_VERTICES vertices), every array it touches in the L1 cache, swept as often in its own
  wavefront order: what the update's instructions cost when no load waits on memory.

A sweep runs no faster than the larger floor, so `product / larger floor` near 1 says the sweep
is at this machine's limit for its instructions, and only fewer instructions (SIMD across
independent elements) or fewer sweeps would make it faster.

    python -m benchmarks.bench_sweep_floor

Under a minute on one core (the walking t-shirt's scene is built from the accuracy study's
cached settled start, or settled first: a few minutes more). Its table is written to
docs/benchmarks.md.
"""


import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import taichi as ti

from benchmarks.common import write_section
from datagen.sim import kernels as K
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.kernel_common import F1, GUARD, I2, I4, V3, V4, V8
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import REAL, VEC3, VEC4
from datagen.sim.simulate import OVER_RELAXATION
from datagen.sim.solvers import SolverSettings, XPBDSolver, wavefront_order
from datagen.study.scenes import FPS, build_scene

# (No `from __future__ import annotations`: Taichi reads the kernels' annotations.)
COMMAND = "python -m benchmarks.bench_sweep_floor"
SCENES = [("sheet_sphere", "cotton", "10k"), ("tube_cylinder", "cotton", "5k"),
          ("tshirt_walk", "cotton", "")]
SUBSTEPS, ITERATIONS = 20, 4  # the `default` preset: the step the sweeps run at
SPRING_SWEEPS_A_FRAME = SUBSTEPS * ITERATIONS  # every spring set, each iteration of each substep
REPEATS = 200  # sweeps a timed kernel runs
ROUNDS = 9  # the three settings timed in turns this many times; the median is reported
PATCH_VERTICES = 200  # the arithmetic floor's patch: its positions and springs fit in L1


@ti.kernel
def sweeps(reps: ti.i32, x: V3, xp: V3, w: F1, springs: I2, rest: F1, limit: F1, comp_t: F1,
           comp_c: F1, beta: F1, lam: F1, inv_h: REAL, omega: REAL):
    """`reps` forward Gauss-Seidel sweeps of the product's spring update."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for e in range(springs.shape[0]):
            K.spring_gs_one(e, x, xp, w, springs, rest, limit, comp_t, comp_c, beta, lam, inv_h,
                            omega)


@ti.kernel
def touches(reps: ti.i32, zero: REAL, x: V3, xp: V3, w: F1, springs: I2, rest: F1, limit: F1,
            comp_t: F1, comp_c: F1, beta: F1, lam: F1):
    """`reps` sweeps of the update's loads and stores alone: every value spring_gs_one reads,
    summed in a shallow tree (so that no long chain of additions stands in for the update's
    arithmetic), written back where it writes times `zero` (a runtime argument, so that the
    compiler keeps every load and store)."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for e in range(springs.shape[0]):
            i = springs[e][0]
            j = springs[e][1]
            v = (x[j] - x[i]) + (xp[j] - xp[i])
            a = ((rest[e] + limit[e]) + (comp_t[e] + comp_c[e])) + ((beta[e] + lam[e])
                                                                   + (w[i] + w[j]))
            s = (v[0] + v[1]) + (v[2] + a)
            lam[e] += zero * s
            x[i] -= zero * v
            x[j] += zero * v


@ti.kernel
def bend_sweeps(reps: ti.i32, x: V3, xp: V3, bends: I4, kk: V8, bstep: V4, lam_b: V3,
                omega: REAL):
    """`reps` forward Gauss-Seidel sweeps of the product's bending update."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for b in range(bends.shape[0]):
            K.bend_gs_one(b, x, xp, bends, kk, bstep, lam_b, omega)


@ti.kernel
def bend_touches(reps: ti.i32, zero: REAL, x: V3, xp: V3, bends: I4, kk: V8, bstep: V4,
                 lam_b: V3):
    """`reps` sweeps of the bending update's loads and stores alone (as `touches`)."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for b in range(bends.shape[0]):
            q = bends[b]
            k = kk[b]
            p = bstep[b]
            v = (((x[q[0]] + x[q[1]]) + (x[q[2]] + x[q[3]]))
                 + ((xp[q[0]] + xp[q[1]]) + (xp[q[2]] + xp[q[3]])))
            a = ((k[0] + k[1]) + (k[2] + k[3])) + ((k[4] + k[5]) + (k[6] + k[7]))
            d = v + (lam_b[b] + ti.Vector([a + p[0], p[1] + p[2], p[3]], REAL))
            lam_b[b] += zero * d
            for c in ti.static(range(4)):
                x[q[c]] += zero * d


def patch_vertices(x: np.ndarray) -> np.ndarray:
    """The PATCH_VERTICES vertices nearest the cloth's middle vertex (by index): a disc of
    cloth, whose springs are a small copy of the whole mesh's."""
    centre = x[len(x) // 2]
    return np.argsort(np.linalg.norm(x - centre, axis=1), kind="stable")[:PATCH_VERTICES]


def patch_elements(elements: np.ndarray, vertices: np.ndarray, n_vertices: int) -> np.ndarray:
    """The elements (springs, bending stencils: rows of vertex indices) with every vertex among
    `vertices`, in the wavefront order of their own (as the product's sweep orders the whole
    set): consecutive updates rarely share a vertex, so the CPU overlaps them as in the
    product; the whole set's order cut to the patch leaves a few elements a level, and each
    update would wait on the one before."""
    member = np.zeros(n_vertices, bool)
    member[vertices] = True
    inside = np.flatnonzero(member[elements].all(axis=1))
    return inside[wavefront_order(elements[inside], n_vertices)]


def _nd(dtype, data: np.ndarray):
    out = ti.ndarray(dtype, data.shape[0])
    out.from_numpy(data)
    return out


def _subset(a, index: np.ndarray, dtype):
    return _nd(dtype, a.to_numpy()[index])


def _timed(settings: dict[str, tuple[Callable[[], None], int]]) -> dict:
    """ns an element of each setting (fn, elements it updates), median over ROUNDS rounds taken
    in turns, and each one's range."""
    for fn, _ in settings.values():
        fn()  # compiled before it is timed
    ti.sync()
    times: dict[str, list[float]] = {name: [] for name in settings}
    for _ in range(ROUNDS):
        for name, (fn, count) in settings.items():
            t = time.perf_counter()
            fn()
            ti.sync()
            times[name].append(1e9 * (time.perf_counter() - t) / count)
    return {**{name: statistics.median(v) for name, v in times.items()},
            "spread": {name: (min(v), max(v)) for name, v in times.items()}}


def measure(scene_name: str, fabric: str, resolution: str) -> list[dict]:
    """The springs' and the bending stencils' rows for one scene."""
    scene = build_scene(scene_name, fabric, resolution, frames=1)
    model = build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])
    solver = XPBDSolver(model, Effects(pins=bool(len(model.pinned))),
                        SolverSettings(substeps=SUBSTEPS, iterations=ITERATIONS))
    h = 1.0 / FPS / SUBSTEPS
    solver._use_step(h)  # the bends' terms for this step
    omega = OVER_RELAXATION["xpbd"]  # the forward sweeps' over-relaxation (the default)
    x, xp, w = solver.x, solver.xp, solver.w
    disc = patch_vertices(x.to_numpy())
    label = f"{scene_name} {resolution}".strip()
    rows = []

    sets = [(s.springs, s.rest, s.limit, s.comp_t, s.comp_c, s.beta, s.lam)
            for s in solver.sets.values()]
    patch_sets = []
    for springs, *per_spring in sets:
        index = patch_elements(springs.to_numpy(), disc, model.n_vertices)
        if len(index):
            patch_sets.append((_subset(springs, index, ti.math.ivec2),)
                              + tuple(_subset(a, index, REAL) for a in per_spring))
    n, n_patch = (sum(s[0].shape[0] for s in ss) for ss in (sets, patch_sets))
    patch_reps = max(1, REPEATS * n // max(1, n_patch))
    rows.append({"scene": label, "fabric": fabric, "elements": "springs", "count": n, **_timed({
        "product": (lambda: [sweeps(REPEATS, x, xp, w, *a, 1.0 / h, omega) for a in sets],
                    n * REPEATS),
        "memory floor": (lambda: [touches(REPEATS, 0.0, x, xp, w, *a) for a in sets],
                         n * REPEATS),
        "arithmetic floor": (lambda: [sweeps(patch_reps, x, xp, w, *a, 1.0 / h, omega)
                                      for a in patch_sets], n_patch * patch_reps),
    })})

    bends = (solver.bends, solver.bend_kk, solver.bend_step, solver.lam_b)
    n = solver.n_bends
    index = patch_elements(solver.bends_np, disc, model.n_vertices)
    patch = (_subset(solver.bends, index, ti.math.ivec4), _subset(solver.bend_kk, index, GUARD),
             _subset(solver.bend_step, index, VEC4), _subset(solver.lam_b, index, VEC3))
    patch_reps = max(1, REPEATS * n // max(1, len(index)))
    rows.append({"scene": label, "fabric": fabric, "elements": "bending stencils", "count": n,
                 **_timed({
        "product": (lambda: bend_sweeps(REPEATS, x, xp, *bends, omega), n * REPEATS),
        "memory floor": (lambda: bend_touches(REPEATS, 0.0, x, xp, *bends), n * REPEATS),
        "arithmetic floor": (lambda: bend_sweeps(patch_reps, x, xp, *patch, omega),
                             len(index) * patch_reps),
    })})
    if not np.isfinite(x.to_numpy()).all():
        raise RuntimeError(f"{scene_name}: the timed sweeps left non-finite positions")
    return rows


def report(rows: list[dict]) -> str:
    lines = [
        f"Each scene's springs (the xpbd solver's spring sets) and bending stencils, in the "
        f"solver's sweep order, one thread, {REPEATS} forward sweeps a timed kernel at the "
        f"`default` step ({SUBSTEPS}x{ITERATIONS}), the three settings timed in turns {ROUNDS} "
        f"times: median ns an element (range in brackets). `memory floor`: the same loads and "
        f"stores without the update's arithmetic; `arithmetic floor`: the same update over "
        f"the elements of a disc of {PATCH_VERTICES} vertices, all in the L1 cache. 'ms a "
        f"sweep' is one sweep of every such element at the product's rate (a {SUBSTEPS}x"
        f"{ITERATIONS} frame sweeps the springs {SPRING_SWEEPS_A_FRAME} times, every bend "
        f"{SUBSTEPS} times and the stiff ones more).",
        "",
        "| scene | elements | count | product ns | memory floor ns | arithmetic floor ns "
        "| product / larger floor | ms a sweep |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sp = r["spread"]
        floor = max(r["memory floor"], r["arithmetic floor"])
        cells = [f"{r[k]:.1f} ({sp[k][0]:.1f}-{sp[k][1]:.1f})"
                 for k in ("product", "memory floor", "arithmetic floor")]
        lines.append(
            f"| {r['scene']} ({r['fabric']}) | {r['elements']} | {r['count']} "
            f"| {' | '.join(cells)} | {r['product'] / floor:.2f}x "
            f"| {r['product'] * r['count'] * 1e-6:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--no-write", action="store_true",
                        help="print the table without writing docs/benchmarks.md")
    args = parser.parse_args(argv)
    from datagen.sim.backend import init_taichi

    init_taichi()
    t = time.perf_counter()
    rows = [row for scene in SCENES for row in measure(*scene)]
    body = report(rows) + f"\n\n({(time.perf_counter() - t) / 60:.1f} min in all.)"
    if args.no_write:
        print(body)
    else:
        write_section("sweep_floor", "Cloth simulator: the constraint sweeps against the machine's "
                      "limits", body, COMMAND)


if __name__ == "__main__":
    main()
