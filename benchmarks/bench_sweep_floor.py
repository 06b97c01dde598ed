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
is at this machine's limit for its instructions, and only other instructions would make it
faster: fewer (SIMD across independent elements), or fewer of them on each update's chain of
dependent operations, which the CPU cannot overlap (the arithmetic floor runs the product's own
update, so it moves with it: on 2026-12-07 the spring update's division and its strain limit's
branch came off that chain, and the update ran 1.25x faster), or fewer sweeps. What SIMD
would buy is timed for the springs in the same turns: the springs in colour order (no two of a
colour sharing a vertex) one at a time, and LANES at a time with lane arithmetic
(`lane_sweeps`).

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
from datagen.sim import kernel_common as KC
from datagen.sim import kernels as K
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.kernel_common import F1, GUARD, I1, I2, I4, V3, V4, V8
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import REAL, VEC3, VEC4
from datagen.sim.simulate import OVER_RELAXATION
from datagen.sim.solvers import (
    SolverSettings,
    XPBDSolver,
    _nd,
    colour_order,
    wavefront_order,
)
from datagen.study.scenes import FPS, build_scene

# (No `from __future__ import annotations`: Taichi reads the kernels' annotations.)
COMMAND = "python -m benchmarks.bench_sweep_floor"
SCENES = [("sheet_sphere", "cotton", "10k"), ("tube_cylinder", "cotton", "5k"),
          ("tshirt_walk", "cotton", "")]
SUBSTEPS, ITERATIONS = 20, 4  # the `default` preset: the step the sweeps run at
SPRING_SWEEPS_A_FRAME = SUBSTEPS * ITERATIONS  # every spring set, each iteration of each substep
REPEATS = 200  # sweeps a timed kernel runs
ROUNDS = 9  # the settings timed in turns this many times; the median is reported
PATCH_VERTICES = 200  # the arithmetic floor's patch: its positions and springs fit in L1


@ti.kernel
def sweeps(reps: ti.i32, x: V3, xp: V3, w: F1, springs: I2, terms: V8, lam: F1, omega: REAL):
    """`reps` forward Gauss-Seidel sweeps of the product's spring update."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for e in range(springs.shape[0]):
            K.spring_gs_one(e, x, xp, w, springs, terms, lam, omega)


@ti.kernel
def touches(reps: ti.i32, zero: REAL, x: V3, xp: V3, w: F1, springs: I2, terms: V8,
            lam: F1):
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
            t = terms[e]
            a = (((t[0] + t[1]) + (t[2] + t[3])) + ((t[4] + t[5]) + (t[6] + t[7]))
                 + (lam[e] + (w[i] + w[j])))
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


LANES = 8  # springs a lane sweep updates at once (AVX2: eight float32 lanes)


@ti.kernel
def lane_sweeps(reps: ti.i32, x: V3, xp: V3, w: F1, springs: I2, terms: V8, lam: F1,
                groups: I1, omega: REAL):
    """`reps` sweeps of the product's spring update (kernels.spring_delta's arithmetic) over
    `groups`: LANES springs at a time, indices into the set's arrays (-1: an empty lane), no two
    of a group sharing a vertex (a colour's springs), so the group's springs are gathered into
    lanes, updated with lane arithmetic (selects for the update's branches) and scattered back.
    Each spring's floats are its scalar update's but for the compiler's contractions; the
    sweep's order is the colours', not the product's."""
    ti.loop_config(serialize=True)
    for _ in range(reps):
        for g in range(groups.shape[0] // LANES):
            e = ti.Vector([0] * LANES, ti.i32)
            d = ti.Matrix([[0.0] * LANES] * 3, REAL)
            rel = ti.Matrix([[0.0] * LANES] * 3, REAL)
            wi = ti.Vector([0.0] * LANES, REAL)
            wj = ti.Vector([0.0] * LANES, REAL)
            t = ti.Matrix([[0.0] * LANES] * 8, REAL)  # the springs' terms (K.ST_*), by row
            la = ti.Vector([0.0] * LANES, REAL)
            for q in ti.static(range(LANES)):
                # Branch-free: an empty lane reads spring 0 and is masked (its weights and its
                # inverse mass sum zero).
                e[q] = ti.max(groups[g * LANES + q], 0)
                valid = ti.select(groups[g * LANES + q] >= 0, 1.0, 0.0)
                i = springs[e[q]][0]
                j = springs[e[q]][1]
                for c in ti.static(range(3)):
                    d[c, q] = x[j][c] - x[i][c]
                    rel[c, q] = (x[j][c] - xp[j][c]) - (x[i][c] - xp[i][c])
                wi[q] = w[i] * valid
                wj[q] = w[j] * valid
                for r in ti.static(range(8)):
                    t[r, q] = terms[e[q]][r]
                t[K.ST_INV_W, q] *= valid
                la[q] = lam[e[q]]
            len2 = d[0, :] * d[0, :] + d[1, :] * d[1, :] + d[2, :] * d[2, :]
            ok = (t[K.ST_INV_W, :] > 0.0) & (len2 > 1e-18)
            rate_len = d[0, :] * rel[0, :] + d[1, :] * rel[1, :] + d[2, :] * rel[2, :]
            length = ti.sqrt(ti.select(ok, len2, 1.0))
            inv_len = 1.0 / length
            c_len = length - t[K.ST_REST, :]
            neg = c_len < 0.0
            alpha = ti.select(neg, t[K.ST_ALPHA_C, :], t[K.ST_ALPHA_T, :])
            inv_den = ti.select(neg, t[K.ST_INV_DEN_C, :], t[K.ST_INV_DEN_T, :])
            dl = omega * (-c_len - alpha * la - t[K.ST_GAMMA, :] * rate_len * inv_len) * inv_den
            dl = ti.select(ok, dl, 0.0)
            move = ti.min(dl, (t[K.ST_LIMIT, :] - length) * t[K.ST_INV_W, :])
            step = ti.select(ok, move * inv_len, 0.0)
            for q in ti.static(range(LANES)):
                # An empty lane's weights are zero, so it moves nothing and adds nothing.
                i = springs[e[q]][0]
                j = springs[e[q]][1]
                lam[e[q]] += dl[q]
                n = KC.vec3(d[0, q], d[1, q], d[2, q]) * step[q]
                x[i] -= wi[q] * n
                x[j] += wj[q] * n


def lane_groups(springs: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The set's springs in colour order (solvers.colour_order) and their lane groups: each
    colour's springs LANES at a time, a colour's last group padded with -1 (indices into the
    colour-ordered arrays)."""
    order, ptr = colour_order(springs, n_vertices)
    groups = []
    for c in range(len(ptr) - 1):
        members = np.arange(ptr[c], ptr[c + 1])
        pad = -len(members) % LANES
        groups.append(np.concatenate([members, np.full(pad, -1)]))
    return order, np.concatenate(groups).astype(np.int32) if groups else np.zeros(0, np.int32)


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


def _subset(a, index: np.ndarray, dtype):
    return _nd(dtype, a.to_numpy()[index])


def _spring_subset(arrays: tuple, index: np.ndarray) -> tuple:
    """A spring set's arrays (springs, per-step terms, multipliers) at `index`, in its
    order."""
    springs, terms, lam = arrays
    return (_subset(springs, index, ti.math.ivec2), _subset(terms, index, GUARD),
            _subset(lam, index, REAL))


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
    solver._use_step(h)  # the springs' and bends' terms for this step
    omega = OVER_RELAXATION["xpbd"]  # the forward sweeps' over-relaxation (the default)
    x, xp, w = solver.x, solver.xp, solver.w
    disc = patch_vertices(x.to_numpy())
    label = f"{scene_name} {resolution}".strip()
    rows = []

    sets = [(s.springs, s.terms, s.lam) for s in solver.sets.values()]
    patch_sets = []
    for arrays in sets:
        index = patch_elements(arrays[0].to_numpy(), disc, model.n_vertices)
        if len(index):
            patch_sets.append(_spring_subset(arrays, index))
    n, n_patch = (sum(s[0].shape[0] for s in ss) for ss in (sets, patch_sets))
    patch_reps = max(1, REPEATS * n // max(1, n_patch))
    coloured, lane_slots = [], 0
    for arrays in sets:
        order, groups = lane_groups(arrays[0].to_numpy(), model.n_vertices)
        coloured.append((_spring_subset(arrays, order), _nd(ti.i32, groups)))
        lane_slots += len(groups)
    rows.append({"scene": label, "fabric": fabric, "elements": "springs", "count": n, **_timed({
        "product": (lambda: [sweeps(REPEATS, x, xp, w, *a, omega) for a in sets],
                    n * REPEATS),
        "memory floor": (lambda: [touches(REPEATS, 0.0, x, xp, w, *a) for a in sets],
                         n * REPEATS),
        "arithmetic floor": (lambda: [sweeps(patch_reps, x, xp, w, *a, omega)
                                      for a in patch_sets], n_patch * patch_reps),
        "colour order": (lambda: [sweeps(REPEATS, x, xp, w, *a, omega)
                                  for a, _ in coloured], n * REPEATS),
        f"colour order, {LANES} lanes": (
            lambda: [lane_sweeps(REPEATS, x, xp, w, *a, g, omega) for a, g in coloured],
            n * REPEATS),
    }), "lanes used": n / max(1, lane_slots)})

    bends = (solver.bends, solver.bend_kk, solver.bend_step, solver.lam_b)
    n = solver.n_bends
    index = patch_elements(solver.bends_np, disc, model.n_vertices)
    patch = (_subset(solver.bends, index, ti.math.ivec4), _subset(solver.bend_kk, index, GUARD),
             _subset(solver.bend_step, index, VEC4), _subset(solver.lam_b, index, VEC3))
    bend_patch_reps = max(1, REPEATS * n // max(1, len(index)))
    rows.append({"scene": label, "fabric": fabric, "elements": "bending stencils", "count": n,
                 **_timed({
        "product": (lambda: bend_sweeps(REPEATS, x, xp, *bends, omega), n * REPEATS),
        "memory floor": (lambda: bend_touches(REPEATS, 0.0, x, xp, *bends), n * REPEATS),
        "arithmetic floor": (lambda: bend_sweeps(bend_patch_reps, x, xp, *patch, omega),
                             len(index) * bend_patch_reps),
    })})
    if not np.isfinite(x.to_numpy()).all():
        raise RuntimeError(f"{scene_name}: the timed sweeps left non-finite positions")
    return rows


def report(rows: list[dict]) -> str:
    lines = [
        f"Each scene's springs (the xpbd solver's spring sets) and bending stencils, in the "
        f"solver's sweep order, one thread, {REPEATS} forward sweeps a timed kernel at the "
        f"`default` step ({SUBSTEPS}x{ITERATIONS}), every setting timed in turns {ROUNDS} "
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
    lanes = f"colour order, {LANES} lanes"
    lines += [
        "",
        f"What fewer instructions would buy: the springs swept in colour order (another "
        f"Gauss-Seidel order, so another trajectory), one spring at a time and {LANES} at a "
        f"time (`lane_sweeps`: a colour's springs gathered into lanes, updated with lane "
        f"arithmetic, scattered back; the same floats as one at a time within rounding), timed "
        f"in turns with the settings above.",
        "",
        f"| scene | springs | colour order ns | {LANES} lanes ns | lanes used "
        f"| {LANES} lanes against the product |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        if lanes not in r:
            continue
        sp = r["spread"]
        cells = [f"{r[k]:.1f} ({sp[k][0]:.1f}-{sp[k][1]:.1f})" for k in ("colour order", lanes)]
        lines.append(f"| {r['scene']} ({r['fabric']}) | {r['count']} | {' | '.join(cells)} "
                     f"| {100 * r['lanes used']:.1f} % | {r['product'] / r[lanes]:.2f}x |")
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
