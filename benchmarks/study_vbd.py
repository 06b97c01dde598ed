"""Vertex Block Descent against the xpbd solver: a study, not a product path.

DESIGN §4.4 names projective dynamics, XPBD and VBD as the candidates for the fast solver; the
project measured the first two (benchmarks/study_prefactored_implicit.py is projective dynamics
read as a quasi-Newton method) and chose XPBD. This measures the third. Vertex Block Descent
(Chen, Macklin, Yang, Kavan and others, SIGGRAPH 2024) minimises each step's incremental
potential, the implicit solver's,

    1/(2h^2) |x - x_n - h v_n|_M^2 + E(x) - f_ext . x + damping,

by Gauss-Seidel over vertices: each vertex in turn takes one Newton step on its own 3x3 block
(inertia, air drag, its springs' gradient and Hessian blocks with their Rayleigh damping, its
bending stencils'), the others held. Its fixed point is the implicit solver's backward Euler
step (the test checks it), so its errors measure how far its iterations leave each step from
solved, in the model the references solve. Options: Chebyshev acceleration of the iterations
(Wang 2015, as the VBD paper uses it, rho the spectral radius guessed) and sweeps in
alternating directions. Strain limit, contact and velocities are the implicit solver's (after
the solve, by projection), as in the prefactored study.

It prints each variant's RMS error against bench_sim's float64 references over the predictable
horizon, picks per scene the variant with the fewest vertex sweeps per simulated second whose
error is no larger than Blender's (bench_sim's, from sim_peer.json), and times it against the
xpbd setting bench_sim found at Blender's error in the same run. Each step's iterations are one
serial Taichi launch; the rest of the step runs on the per-effect path, so the study's time
bounds a fused form from above. It also times one vertex sweep launched alone: a simulated
second's sweeps at that time bound a fused form from below.

    python -m benchmarks.study_vbd [--refs DIR]

`--refs DIR` keeps the float64 references there (minutes each).
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import taichi as ti

import datagen.sim.simulate as simulate_module
from benchmarks.bench_sim import ERROR_FRAMES, PEER_JSON, float64_reference
from datagen.sim import implicit_kernels as IK
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.implicit import ImplicitSolver
from datagen.sim.kernel_common import F1, I1, I2, I4, V3, V4, vec3
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import REAL
from datagen.sim.solvers import SolverSettings, _nd, make_solver
from datagen.study.metrics import rms_distance
from datagen.study.run import run_ours
from datagen.study.scenes import build_scene

COMMAND = "python -m benchmarks.study_vbd"
SCENES = [("tube_cylinder", "5k", "cotton"), ("tube_cylinder", "5k", "denim"),
          ("sheet_sphere", "4k", "cotton"), ("sheet_sphere", "4k", "denim")]
# (steps per frame, iterations per step, Chebyshev rho; 0 is plain)
VARIANTS = [(5, 8, 0.0), (5, 32, 0.0), (5, 128, 0.0), (10, 8, 0.0), (10, 32, 0.0),
            (20, 4, 0.0), (20, 16, 0.0), (5, 32, 0.95), (5, 128, 0.97), (10, 16, 0.9),
            (10, 32, 0.95), (20, 8, 0.9)]
TIMED_FRAMES = 30
I2v = ti.types.ndarray(dtype=ti.math.ivec2, ndim=1)


@ti.func
def vertex_block(i: ti.i32, x: V3, xn: V3, vn: V3, mass: F1, drag: F1, springs: I2, rest: F1,
                 k_t: F1, k_c: F1, beta: F1, bends: I4, kw: V4, stiff: F1, bbeta: F1,
                 s_ptr: I1, s_adj: I2v, b_ptr: I1, b_adj: I2v, h: REAL, gravity: vec3,
                 use_gravity: ti.template(), use_air: ti.template()) -> vec3:
    """Vertex i's Newton step on the incremental potential, the other vertices held: the
    gradient and Hessian are gradient_all's and the preconditioner's terms at i."""
    m = mass[i]
    g = m * (x[i] - xn[i] - h * vn[i]) / (h * h)
    dd = m / (h * h)
    if ti.static(use_gravity):
        g -= m * gravity
    if ti.static(use_air):
        g += drag[i] * (x[i] - xn[i]) / h
        dd += drag[i] / h
    hess = dd * ti.Matrix.identity(REAL, 3)
    for a in range(s_ptr[i], s_ptr[i + 1]):
        e = s_adj[a][0]
        a0 = springs[e][0]
        a1 = springs[e][1]
        d = x[a1] - x[a0]
        length = d.norm()
        if length > 1e-9:
            n = d / length
            c = length - rest[e]
            k = k_t[e]
            if c < 0.0:
                k = k_c[e]
            rate = n.dot((x[a1] - xn[a1]) - (x[a0] - xn[a0])) / h
            fe = (k * c + beta[e] * k * rate) * n  # on the first end
            if s_adj[a][1] == 0:
                g -= fe
            else:
                g += fe
            # IK.spring_block's Hessian (its compressive part dropped), from this norm
            nn = n.outer_product(n)
            coef = ti.max(1.0 - rest[e] / length, 0.0)
            hess += k * ((1.0 + beta[e] / h) * nn + coef * (ti.Matrix.identity(REAL, 3) - nn))
    for a in range(b_ptr[i], b_ptr[i + 1]):
        b = b_adj[a][0]
        q = b_adj[a][1]
        s = bends[b]
        k = kw[b]
        c = k[0] * x[s[0]] + k[1] * x[s[1]] + k[2] * x[s[2]] + k[3] * x[s[3]]
        cv = (k[0] * (x[s[0]] - xn[s[0]]) + k[1] * (x[s[1]] - xn[s[1]])
              + k[2] * (x[s[2]] - xn[s[2]]) + k[3] * (x[s[3]] - xn[s[3]])) / h
        g += k[q] * stiff[b] * (c + bbeta[b] * cv)
        hess += stiff[b] * (1.0 + bbeta[b] / h) * k[q] * k[q] * ti.Matrix.identity(REAL, 3)
    return -(hess.inverse() @ g)


@ti.kernel
def vbd_iterations(x: V3, xn: V3, vn: V3, mass: F1, drag: F1, pinned: I1, springs: I2,
                   rest: F1, k_t: F1, k_c: F1, beta: F1, bends: I4, kw: V4, stiff: F1,
                   bbeta: F1, s_ptr: I1, s_adj: I2v, b_ptr: I1, b_adj: I2v, x_old: V3,
                   x_new: V3, h: REAL, iterations: ti.i32, rho: REAL, alternate: ti.i32,
                   gravity: vec3, use_gravity: ti.template(), use_air: ti.template()):
    """A step's VBD iterations in one serial task. With rho > 0 each iteration's result is
    Chebyshev-extrapolated from the one two before (x_old) and the one before (x_new)."""
    n = x.shape[0]
    omega = 1.0
    ti.loop_config(serialize=True)
    for it in range(iterations):
        if rho > 0.0:
            for i in range(n):
                x_new[i] = x[i]  # the iterate before this iteration
        for m in range(n):
            i = m
            if alternate != 0 and it % 2 == 1:
                i = n - 1 - m
            if pinned[i] == 0:
                x[i] += vertex_block(i, x, xn, vn, mass, drag, springs, rest, k_t, k_c, beta,
                                     bends, kw, stiff, bbeta, s_ptr, s_adj, b_ptr, b_adj, h,
                                     gravity, use_gravity, use_air)
        if rho > 0.0:
            if it == 1:
                omega = 2.0 / (2.0 - rho * rho)
            elif it > 1:
                omega = 4.0 / (4.0 - rho * rho * omega)
            if it > 0:
                for i in range(n):
                    if pinned[i] == 0:
                        x[i] = omega * (x[i] - x_old[i]) + x_old[i]
            for i in range(n):
                x_old[i] = x_new[i]


def incidence(pairs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR of each vertex's elements: offsets (n + 1) and (element, slot) rows."""
    rows, slots = np.nonzero(np.ones_like(pairs, dtype=bool))
    verts = pairs[rows, slots]
    order = np.argsort(verts, kind="stable")
    ptr = np.zeros(n + 1, np.int32)
    np.add.at(ptr, verts + 1, 1)
    return np.cumsum(ptr).astype(np.int32), np.stack([rows, slots], 1)[order].astype(np.int32)


class VBDSolver(ImplicitSolver):
    """Each step's incremental potential minimised by `iterations` VBD sweeps (the module's
    docstring); the rest of the step is the implicit solver's."""

    rho = 0.0
    alternate = True

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        if effects.wind:
            raise ValueError("the study's VBD has no wind (the peer scenes have none)")
        n = self.n
        sptr, sadj = incidence(self.all_springs.to_numpy()[: self.n_springs], n)
        bends = (self.bends_np if self.n_bends else np.zeros((0, 4), np.int32))
        bptr, badj = incidence(bends, n)
        self.s_ptr = _nd(ti.i32, sptr)
        self.s_adj = _nd(ti.math.ivec2, sadj if len(sadj) else np.zeros((1, 2), np.int32))
        self.b_ptr = _nd(ti.i32, bptr)
        self.b_adj = _nd(ti.math.ivec2, badj if len(badj) else np.zeros((1, 2), np.int32))
        self.x_old = ti.ndarray(vec3, n)
        self.x_new = ti.ndarray(vec3, n)
        self.use_air = bool(effects.air_drag)

    def iterate(self, h: float, iterations: int) -> None:
        vbd_iterations(self.x, self.xn, self.v, self.mass, self.drag, self.pinned,
                       self.all_springs, self.all_rest, self.all_kt, self.all_kc, self.all_beta,
                       self.bends, self.kw, self.bstiff, self.bbeta, self.s_ptr, self.s_adj,
                       self.b_ptr, self.b_adj, self.x_old, self.x_new, h, iterations,
                       self.rho, int(self.alternate), self.gravity, self.effects.gravity,
                       self.use_air)

    def _solve(self, h: float, s1: float) -> tuple:
        IK.inertial_guess(self.x, self.xn, self.v, self.pinned, h)
        self.xp.copy_from(self.xn)
        self._pins(s1)
        self.iterate(h, max(1, self.settings.iterations))
        return self.xp, h


def use(rho: float) -> None:
    """Let `simulate` build the study's solver wherever it is asked for the implicit one."""
    def make(name, model, effects, settings):
        if name != "implicit":
            return make_solver(name, model, effects, settings)
        solver = VBDSolver(model, effects, settings)
        solver.rho = rho
        return solver

    simulate_module.make_solver = make


def sweep_costs(scene_name: str, resolution: str, fabric: str) -> dict:
    """Milliseconds of one VBD vertex sweep, launched alone, at 5 steps a frame (the launch
    itself measured with one sweep and subtracted)."""
    scene = build_scene(scene_name, fabric, resolution, frames=1)
    model = build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])
    solver = VBDSolver(model, Effects(pins=bool(len(model.pinned))), SolverSettings())
    h = 1.0 / 30.0 / 5
    x0 = solver.x.to_numpy()
    out = {}
    for sweeps in (1, 41):
        solver.iterate(h, sweeps)
        t = time.perf_counter()
        for _ in range(20):
            solver.iterate(h, sweeps)
        out[sweeps] = 1000 * (time.perf_counter() - t) / 20
        solver.x.from_numpy(x0)
    return {"sweep_ms": (out[41] - out[1]) / 40, "launch_ms": out[1] - (out[41] - out[1]) / 40}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--refs", type=Path, help="keep the float64 references in this folder")
    parser.add_argument("--scenes", default="", help="comma-separated scene_res_fabric subset")
    args = parser.parse_args()
    peer = json.loads(PEER_JSON.read_text())
    blender = {(r["scene"], r["fabric"]): r for r in peer["rows"]}
    wanted = {s for s in args.scenes.split(",") if s}
    rows = []
    for scene_name, resolution, fabric in SCENES:
        if wanted and f"{scene_name}_{resolution}_{fabric}" not in wanted:
            continue
        t0 = time.perf_counter()
        b = blender[(f"{scene_name} {resolution}", fabric)]
        cache = args.refs / f"{scene_name}_{resolution}_{fabric}.npz" if args.refs else None
        ref, horizon = float64_reference(scene_name, fabric, resolution, cache)
        short = build_scene(scene_name, fabric, resolution, frames=ERROR_FRAMES)
        errors = {}
        for sub, it, rho in VARIANTS:
            use(rho)
            run = run_ours(short, "implicit", sub, it)
            errors[(sub, it, rho)] = 1000 * rms_distance(run.positions, ref, horizon)
            print(f"  {sub}x{it} rho {rho}: {errors[(sub, it, rho)]:.2f} mm", flush=True)
        within = [v for v in VARIANTS if errors[v] <= b["blender_err_mean_mm"]]
        best = min(within, key=lambda v: (v[0] * v[1], v[0])) if within else None
        timed = build_scene(scene_name, fabric, resolution, frames=TIMED_FRAMES)
        x_sub, x_it = map(int, b["at_error"]["steps"].split("x"))
        simulate_module.make_solver = make_solver
        xpbd_s = run_ours(timed, "xpbd", x_sub, x_it).seconds_per_simulated_second
        ours_s, strain = float("nan"), float("nan")
        if best is not None:
            use(best[2])
            run = run_ours(timed, "implicit", best[0], best[1])
            ours_s = run.seconds_per_simulated_second
            strain = float(np.max(run.qa["strain_p999"]))
            simulate_module.make_solver = make_solver
        rows.append({"scene": f"{scene_name} {resolution}", "fabric": fabric,
                     "horizon": horizon, "errors": errors, "best": best, "blender": b,
                     "xpbd_s": xpbd_s, "ours_s": ours_s, "strain": strain,
                     "sweep": sweep_costs(scene_name, resolution, fabric)})
        print(f"{scene_name} {resolution} {fabric}: {time.perf_counter() - t0:.0f} s", flush=True)
    report(rows, peer)


def _name(v: tuple) -> str:
    sub, it, rho = v
    return f"{sub}x{it}" + (f" cheb {rho}" if rho else "")


def report(rows: list[dict], peer: dict) -> None:
    print(f"\nCommand: `{COMMAND}`; Blender's figures and the xpbd settings at Blender's error "
          f"from bench_sim's run of {peer['date']} (benchmarks/results/sim_peer.json).\n")
    header = [_name(v) for v in VARIANTS]
    print("| scene | fabric | horizon | Blender q5 | xpbd at Blender's error | "
          + " | ".join(header) + " |")
    print("|---" * (5 + len(header)) + "|")
    for r in rows:
        at = r["blender"]["at_error"]
        cells = " | ".join(f"{r['errors'][v]:.1f}" for v in VARIANTS)
        print(f"| {r['scene']} | {r['fabric']} | {r['horizon']} | "
              f"{r['blender']['blender_err_mean_mm']:.2f} | {at['steps']} {at['err_mm']:.2f} | "
              f"{cells} |")
    print("\n| scene | fabric | fewest sweeps within Blender's error | error mm | study s/sim-s "
          "| strain p99.9 | xpbd at Blender's error | xpbd s/sim-s | study / xpbd | "
          "one vertex sweep ms | its sweeps alone s/sim-s | sweeps alone / xpbd |")
    print("|---" * 12 + "|")
    for r in rows:
        at = r["blender"]["at_error"]
        sweep = r["sweep"]["sweep_ms"]
        if r["best"] is None:
            print(f"| {r['scene']} | {r['fabric']} | none | | | | {at['steps']} | "
                  f"{r['xpbd_s']:.2f} | | {sweep:.3f} | | |")
            continue
        sub, it, _ = r["best"]
        alone = 30 * sub * it * sweep / 1000
        print(f"| {r['scene']} | {r['fabric']} | {_name(r['best'])} | "
              f"{r['errors'][r['best']]:.2f} | {r['ours_s']:.2f} | {r['strain']:.3f} | "
              f"{at['steps']} | {r['xpbd_s']:.2f} | {r['xpbd_s'] / r['ours_s']:.2f}x | "
              f"{sweep:.3f} | {alone:.2f} | {r['xpbd_s'] / alone:.2f}x |")


if __name__ == "__main__":
    main()
