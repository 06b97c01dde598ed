"""What an implicit step at Blender's step size would buy: a study, not a product path.

The xpbd solver needs 30 substeps of two sweeps to come as close to the 5k denim tube's
reference as Blender's quality 5 (five implicit steps a frame) comes to its own, because its
Gauss-Seidel sweeps leave each substep's equations far from solved (docs/simulator.md,
"Converging the bending"). Our own implicit solver, run to convergence at five steps a frame,
is 10.8 mm from the tube's reference against Blender's 35.6 mm: the error at Blender's step is
in the solve, not in the step. But Newton with block-Jacobi CG costs 43 s per simulated second
there, eight times Blender's time.

This study solves each step's incremental potential the way projective dynamics does for
springs (Liu, Bouaziz, Chenevier and Kavan 2013; as a quasi-Newton method, Liu, Bouaziz and
Kavan 2017): fixed-point iterations x <- x - A^-1 grad(x) with one constant matrix A per step
size, factored once,

    A = M / h^2 + D_air / h + sum_springs k (1 + beta / h) (e_i - e_j)(e_i - e_j)^T
        + sum_bends kb (1 + beta_b / h) w w^T,

isotropic (one scalar matrix for x, y and z), which bounds every spring's Hessian block from
above and is the bending's exact Hessian (our bending is linear). The iteration's fixed point
is the backward Euler step of the implicit solver; a few iterations leave it inexact. It also
tries BDF2 (second order, the same iteration with the step 2h/3 and the BDF2 inertial target),
whose free fall is exact where backward Euler's lags by g h t / 2: the sheets' error at a few
steps a frame is mostly that lag. Strain limit, contact and velocities are the implicit
solver's (after the solve, by projection).

It prints each variant's error against bench_sim's float64 references (RMS over the
predictable horizon), picks per peer scene the variant with the fewest solves per simulated
second whose error is no larger than Blender's (bench_sim's, from sim_peer.json), and times it
against the xpbd setting bench_sim found at Blender's error, in this run: the ratio, chained
with bench_sim's ratio of that setting to Blender, estimates the rate against Blender. The
study's iterations run from Python (a gradient launch, transfers and scipy's sparse LU solve
per iteration, the rest of the step on the per-effect path), so its times bound a fused form
from above; the cost of one iteration's parts is printed too.

    python -m benchmarks.study_prefactored_implicit [--refs DIR]

`--refs DIR` keeps the float64 references there (minutes each, the 10k sheets' longest); with
them kept the study takes about 2 minutes on 2 cores.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

import datagen.sim.simulate as simulate_module
from benchmarks.bench_sim import ERROR_FRAMES, PEER_JSON, float64_reference
from datagen.sim import implicit_kernels as IK
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.implicit import ImplicitSolver
from datagen.sim.kernel_common import F1, I1, I2, I4, V3, V4, vec3
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import NP_REAL, REAL
from datagen.sim.solvers import SolverSettings, make_solver
from datagen.study.metrics import rms_distance
from datagen.study.run import run_ours
from datagen.study.scenes import build_scene

COMMAND = "python -m benchmarks.study_prefactored_implicit"
SCENES = [("sheet_sphere", "4k", "cotton"), ("sheet_sphere", "4k", "denim"),
          ("sheet_sphere", "10k", "cotton"), ("sheet_sphere", "10k", "denim"),
          ("tube_cylinder", "5k", "cotton"), ("tube_cylinder", "5k", "denim")]
# (integrator, steps per frame, iterations per step)
VARIANTS = [("BE", 3, 1), ("BE", 3, 2), ("BE", 5, 1), ("BE", 5, 2), ("BE", 8, 2),
            ("BE", 10, 1), ("BE", 10, 2), ("BDF2", 1, 1), ("BDF2", 1, 2), ("BDF2", 2, 1),
            ("BDF2", 3, 1), ("BDF2", 5, 1), ("BDF2", 5, 2), ("BDF2", 8, 2), ("BDF2", 10, 2)]
TIMED_FRAMES = 30


@ti.kernel
def serial_gradient(x: V3, xn: V3, vn: V3, mass: F1, drag: F1, g: V3, springs: I2, rest: F1,
                    k_t: F1, k_c: F1, beta: F1, bends: I4, kw: V4, stiff: F1, bbeta: F1,
                    h: REAL, n_springs: ti.i32, n_bends: ti.i32, gravity: vec3,
                    use_gravity: ti.template(), use_air: ti.template()):
    """The incremental potential's gradient (the implicit solver's), in one serial task: in
    parallel loops its scattered sums would be atomic, which on the CPU cost 6x more."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        IK.gradient_all(x, xn, vn, mass, drag, g, springs, rest, k_t, k_c, beta, bends, kw,
                        stiff, bbeta, gravity, h, n_springs, n_bends, use_gravity,
                        use_air)


@ti.kernel
def predict(x: V3, v: V3, xd: V3, vd: V3, x_prev: V3, v_prev: V3, xp: V3, pinned: I1, h: REAL,
            second_order: ti.i32):
    """The step's start: xd and vd (x_n and v_n, or BDF2's (4 x_n - x_n-1) / 3 and
    (4 v_n - v_n-1) / 3), the guess xd + hs vd (hs = h, or 2h/3), and the last step's state."""
    for i in x:
        xi = x[i]
        vi = v[i]
        d = xi
        u = vi
        hs = h
        if second_order != 0:
            d = (4.0 * xi - x_prev[i]) / 3.0
            u = (4.0 * vi - v_prev[i]) / 3.0
            hs = 2.0 * h / 3.0
        x_prev[i] = xi
        v_prev[i] = vi
        xp[i] = xi
        xd[i] = d
        vd[i] = u
        if pinned[i] == 0:
            x[i] = d + hs * u


class PrefactoredImplicit(ImplicitSolver):
    """Backward Euler or BDF2, each step's incremental potential minimised by `iterations`
    fixed-point steps with a constant factored matrix (the module's docstring)."""

    bdf2 = False

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        if effects.wind:
            raise ValueError("the study's gradient has no wind (the peer scenes have none)")
        self.grad = ti.ndarray(vec3, self.n)
        self.v_target = ti.ndarray(vec3, self.n)
        self.free = np.flatnonzero(self.pinned.to_numpy() == 0)
        self._factors: dict[float, spla.SuperLU] = {}
        self.x_prev = ti.ndarray(vec3, self.n)  # x and v a step ago (BDF2)
        self.v_prev = ti.ndarray(vec3, self.n)
        self.steps = 0
        self.use_air = bool(effects.air_drag)

    def matrix(self, h: float) -> sp.csc_matrix:
        """A at step h, on the free vertices (pinned ones do not move in the solve)."""
        n = self.n
        diag = self.mass.to_numpy().astype(np.float64) / h**2
        if self.use_air:
            diag = diag + self.drag.to_numpy().astype(np.float64) / h
        m = self.n_springs
        ij = self.all_springs.to_numpy()[:m]
        k = np.maximum(self.all_kt.to_numpy()[:m], self.all_kc.to_numpy()[:m]).astype(np.float64)
        w = k * (1.0 + self.all_beta.to_numpy()[:m].astype(np.float64) / h)
        # springs: E^T W E with E the spring-vertex incidence (+1, -1); bends: B^T C B
        edges = np.repeat(np.arange(m), 2)
        e = sp.csr_matrix((np.tile([1.0, -1.0], m), (edges, ij.ravel())), shape=(m, n))
        a = sp.diags(diag) + e.T @ sp.diags(w) @ e
        if self.n_bends:
            kw = self.kw.to_numpy().astype(np.float64)
            coef = (self.bstiff.to_numpy().astype(np.float64)
                    * (1.0 + self.bbeta.to_numpy().astype(np.float64) / h))
            b = sp.csr_matrix((kw.ravel(), (np.repeat(np.arange(self.n_bends), 4),
                                            self.bends_np.ravel())), shape=(self.n_bends, n))
            a = a + b.T @ sp.diags(coef) @ b
        a = a.tocsr()
        return a[self.free][:, self.free].tocsc()

    def factor(self, h: float) -> spla.SuperLU:
        if h not in self._factors:
            self._factors[h] = spla.splu(self.matrix(h), permc_spec="MMD_AT_PLUS_A")
        return self._factors[h]

    def launch_gradient(self, h: float) -> None:
        serial_gradient(self.x, self.xn, self.v_target, self.mass, self.drag, self.grad,
                        self.all_springs, self.all_rest, self.all_kt, self.all_kc, self.all_beta,
                        self.bends, self.kw, self.bstiff, self.bbeta, h, self.n_springs,
                        self.n_bends, self.gravity, self.effects.gravity, self.use_air)

    def gradient(self, h: float) -> np.ndarray:
        self.launch_gradient(h)
        return self.grad.to_numpy().astype(np.float64)[self.free]

    def _solve(self, h: float, s1: float) -> tuple:
        # BDF2: x = x_hat + (2h/3)^2 a(x), x_hat = xd + (2h/3) vd, with the velocity after the
        # step (x - xd) / (2h/3); gradient_all takes (xd, vd, 2h/3) as it takes (x_n, v_n, h).
        second_order = self.bdf2 and self.steps > 0
        hs = 2 * h / 3 if second_order else h
        predict(self.x, self.v, self.xn, self.v_target, self.x_prev, self.v_prev, self.xp,
                self.pinned, h, int(second_order))
        self.steps += 1
        self._pins(s1)
        x = self.x.to_numpy().astype(np.float64)
        lu = self.factor(hs)
        for _ in range(max(1, self.settings.iterations)):
            x[self.free] -= lu.solve(self.gradient(hs))
            self.x.from_numpy(x.astype(NP_REAL))
        # velocity (x - xd) / hs: backward Euler's (x - x_n) / h, or BDF2's
        return self.xn, hs


BUILT: list[PrefactoredImplicit] = []  # the last run's solver (its costs)


def use(integrator: str) -> None:
    """Let `simulate` build the study's solver wherever it is asked for the implicit one."""
    def make(name, model, effects, settings):
        if name != "implicit":
            return make_solver(name, model, effects, settings)
        solver = PrefactoredImplicit(model, effects, settings)
        solver.bdf2 = integrator == "BDF2"
        BUILT[:] = [solver]
        return solver

    simulate_module.make_solver = make


def iteration_parts(scene_name: str, resolution: str, fabric: str, substeps: int) -> dict:
    """Milliseconds of one iteration's parts at the scene's step, each from Python."""
    scene = build_scene(scene_name, fabric, resolution, frames=1)
    model = build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])
    solver = PrefactoredImplicit(model, Effects(pins=bool(len(model.pinned))),
                                 SolverSettings(substeps=substeps))
    h = 1.0 / 30.0 / substeps
    t = time.perf_counter()
    lu = solver.factor(h)
    factor_ms = 1000 * (time.perf_counter() - t)
    repeats = 200
    solver.gradient(h)  # compiled before it is timed
    t = time.perf_counter()
    for _ in range(repeats):
        solver.launch_gradient(h)
    gradient_ms = 1000 * (time.perf_counter() - t) / repeats
    x = solver.x.to_numpy()
    t = time.perf_counter()
    for _ in range(repeats):
        solver.grad.to_numpy()
        solver.x.from_numpy(x)
    transfer_ms = 1000 * (time.perf_counter() - t) / repeats
    rhs = np.random.default_rng(0).normal(size=(len(solver.free), 3))
    t = time.perf_counter()
    for _ in range(repeats):
        lu.solve(rhs)
    solve_ms = 1000 * (time.perf_counter() - t) / repeats
    return {"gradient_ms": gradient_ms, "transfer_ms": transfer_ms, "solve_ms": solve_ms,
            "factor_nnz": lu.L.nnz + lu.U.nnz, "factor_ms": factor_ms}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--refs", type=Path, help="keep the float64 references in this folder")
    args = parser.parse_args()
    peer = json.loads(PEER_JSON.read_text())
    blender = {(r["scene"], r["fabric"]): r for r in peer["rows"]}
    rows = []
    for scene_name, resolution, fabric in SCENES:
        t0 = time.perf_counter()
        b = blender[(f"{scene_name} {resolution}", fabric)]
        cache = args.refs / f"{scene_name}_{resolution}_{fabric}.npz" if args.refs else None
        ref, horizon = float64_reference(scene_name, fabric, resolution, cache)
        short = build_scene(scene_name, fabric, resolution, frames=ERROR_FRAMES)
        errors = {}
        for integrator, sub, it in VARIANTS:
            use(integrator)
            run = run_ours(short, "implicit", sub, it)
            errors[(integrator, sub, it)] = 1000 * rms_distance(run.positions, ref, horizon)
        within = [v for v in VARIANTS if errors[v] <= b["blender_err_mm"]]
        best = min(within, key=lambda v: (v[1] * v[2], v[1])) if within else None
        timed = build_scene(scene_name, fabric, resolution, frames=TIMED_FRAMES)
        x_sub, x_it = map(int, b["at_error"]["steps"].split("x"))
        simulate_module.make_solver = make_solver
        xpbd_s = run_ours(timed, "xpbd", x_sub, x_it).seconds_per_simulated_second
        ours_s = float("nan")
        costs: dict[str, float] = {}
        if best is not None:
            use(best[0])
            run = run_ours(timed, "implicit", best[1], best[2])
            ours_s = run.seconds_per_simulated_second
            simulate_module.make_solver = make_solver
            solver = BUILT[0]
            seconds = run.simulated
            costs = {k: v / seconds for k, v in solver.costs.items()}
            costs["limit sweeps a step"] = solver.launches["strain_limit"] / solver.steps
            costs["strain p99.9"] = float(np.max(run.qa["strain_p999"]))
            costs["too deep"] = float(np.max(run.qa["deep_share"]))
        parts = iteration_parts(scene_name, resolution, fabric, best[1] if best else 5)
        rows.append({"scene": f"{scene_name} {resolution}", "fabric": fabric,
                     "horizon": horizon, "errors": errors, "best": best, "blender": b,
                     "xpbd_s": xpbd_s, "ours_s": ours_s, "parts": parts, "costs": costs})
        print(f"{scene_name} {resolution} {fabric}: {time.perf_counter() - t0:.0f} s", flush=True)
    report(rows, peer)


def report(rows: list[dict], peer: dict) -> None:
    print(f"\nCommand: `{COMMAND}`; Blender's figures and the xpbd settings at Blender's error "
          f"from bench_sim's run of {peer['date']} (benchmarks/results/sim_peer.json).\n")
    header = [f"{i} {s}x{n}" for i, s, n in VARIANTS]
    print("| scene | fabric | horizon | Blender q5 | " + " | ".join(header) + " |")
    print("|---" * (4 + len(header)) + "|")
    for r in rows:
        cells = " | ".join(f"{r['errors'][v]:.1f}" for v in VARIANTS)
        print(f"| {r['scene']} | {r['fabric']} | {r['horizon']} | "
              f"{r['blender']['blender_err_mm']:.1f} | {cells} |")
    print("\n| scene | fabric | fewest solves within Blender's error | error mm | study s/sim-s "
          "| xpbd at Blender's error | xpbd s/sim-s | study / xpbd | xpbd / Blender "
          "(bench_sim) | estimate against Blender | the solves alone against Blender |")
    print("|---" * 11 + "|")
    for r in rows:
        at = r["blender"]["at_error"]
        if r["best"] is None:
            print(f"| {r['scene']} | {r['fabric']} | none | | | {at['steps']} | "
                  f"{r['xpbd_s']:.2f} | | {at['speedup']:.1f}x | | |")
            continue
        integ, sub, it = r["best"]
        gain = r["xpbd_s"] / r["ours_s"]
        # a simulated second's solves, at the timed solve: what no fused form can go below
        solves_s = 30 * sub * it * r["parts"]["solve_ms"] / 1000
        print(f"| {r['scene']} | {r['fabric']} | {integ} {sub}x{it} | "
              f"{r['errors'][r['best']]:.2f} | {r['ours_s']:.2f} | {at['steps']} | "
              f"{r['xpbd_s']:.2f} | {gain:.2f}x | {at['speedup']:.1f}x | "
              f"{gain * at['speedup']:.1f}x | "
              f"{r['blender']['blender_s_per_sim_s'] / solves_s:.0f}x |")
    print("\n| scene | fabric | factor nonzeros | factoring ms | gradient launch ms | "
          "transfers ms | solve ms (3 right-hand sides) | study run: solve s/sim-s | "
          "strain limit | limit sweeps a step | body collision | strain p99.9 (max) | "
          "too deep (max) |")
    print("|---" * 13 + "|")
    for r in rows:
        p, c = r["parts"], r["costs"]
        print(f"| {r['scene']} | {r['fabric']} | {p['factor_nnz']} | {p['factor_ms']:.0f} | "
              f"{p['gradient_ms']:.3f} | "
              f"{p['transfer_ms']:.3f} | {p['solve_ms']:.3f} | "
              f"{c.get('implicit_solve', float('nan')):.3f} | "
              f"{c.get('strain_limit', float('nan')):.3f} | "
              f"{c.get('limit sweeps a step', float('nan')):.1f} | "
              f"{c.get('body_collision', float('nan')):.3f} | "
              f"{c.get('strain p99.9', float('nan')):.3f} | "
              f"{100 * c.get('too deep', float('nan')):.2f} % |")


if __name__ == "__main__":
    main()
