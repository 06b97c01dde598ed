"""What converging the bending would buy the xpbd solver: a study, not a product path.

The stiff fabrics' error at Blender's error level is set by the bending stencils (docs/simulator.md,
"Sweep order"): Gauss-Seidel sweeps settle a stencil's own error at once but carry a bend along
the cloth about one stencil per sweep, so the long, slow bending of a denim tube converges last.
Our bending constraints are linear in the positions with constant weights (C = sum_q k_q x_q),
so the whole bending block of a sweep can be solved exactly: with the springs held, the
multipliers' update dl satisfies (B W B^T + D) dl = s, D = alpha~ / (1 + gamma), which in primal
form is one linear system with a constant matrix (a mesh's 2-ring, factored once per step size):

    (M + B^T D^-1 B) dx = B^T D^-1 s,   dl = D^-1 (s - B dx),

so the positions and multipliers stay consistent (dx = W B^T dl), as Gauss-Seidel keeps them.
This study runs the xpbd solver's per-effect kernels with that exact block solve (scipy's sparse
LU, numpy transfers: error only, its times mean nothing) in place of the bending sweeps, in
every iteration or only in a substep's first, and sets the errors against the Gauss-Seidel
sweeps' on the same path. It also times one solve (3 right-hand sides) against one Gauss-Seidel
sweep over the same stencils, each from Python, so the cost of an exact block can be weighed.

    python -m benchmarks.study_bend_block

References: bench_sim's (float64_reference: our implicit solver in float64 at 160 substeps),
errors as RMS over the predictable horizon. About 10 minutes on 2 cores.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import datagen.sim.simulate as simulate_module
from benchmarks.bench_sim import ERROR_FRAMES, float64_reference
from datagen.sim import kernels as K
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import NP_REAL
from datagen.sim.solvers import ClothSolver, SolverSettings, XPBDSolver, make_solver
from datagen.study.metrics import rms_distance
from datagen.study.run import run_ours
from datagen.study.scenes import build_scene

COMMAND = "python -m benchmarks.study_bend_block"
SCENES = [("tube_cylinder", "5k", "denim"), ("tube_cylinder", "5k", "cotton"),
          ("sheet_sphere", "4k", "denim")]
# (bending, substeps, iterations): Gauss-Seidel sweeps ("sweeps"), the exact block in every
# iteration ("exact"), or in a substep's first iteration only, none after ("exact first").
VARIANTS = [("sweeps", 20, 2), ("sweeps", 30, 2), ("sweeps", 40, 2), ("exact", 15, 2),
            ("exact", 16, 2), ("exact", 20, 2), ("exact", 30, 2), ("exact first", 17, 2),
            ("exact first", 18, 2), ("exact first", 20, 2)]


def bend_compliance(solver: XPBDSolver) -> np.ndarray:
    """Each bending stencil's compliance (1 / stiffness), in the solver's sweep order, rounded
    to the solver's precision as its kernels see it (float64 for scipy)."""
    stiffness = solver.model.bend_stiffness[solver.bend_order]
    return (1.0 / stiffness).astype(NP_REAL).astype(np.float64)


class ExactBendBlock:
    """The bending block of one solver, factored for one step size."""

    def __init__(self, solver: XPBDSolver, h: float) -> None:
        self.h = h
        bends = solver.bends_np
        kw = solver.kw.to_numpy().astype(np.float64)
        w = solver.w_np.astype(np.float64)
        n_bends = len(bends)
        self.B = sp.csr_matrix((kw.ravel(), (np.repeat(np.arange(n_bends), 4), bends.ravel())),
                               shape=(n_bends, solver.n))
        self.free = np.flatnonzero(w > 0)  # pinned vertices do not move
        self.Bf = self.B[:, self.free].tocsr()
        self.alpha = bend_compliance(solver) / (h * h)
        self.gamma = solver.bbeta.to_numpy().astype(np.float64) / h
        self.d_inv = (1.0 + self.gamma) / self.alpha
        a = sp.diags(1.0 / w[self.free]) + self.Bf.T @ sp.diags(self.d_inv) @ self.Bf
        self.lu = spla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, solver: XPBDSolver) -> None:
        x = solver.x.to_numpy().astype(np.float64)
        xp = solver.xp.to_numpy().astype(np.float64)
        lam = solver.lam_b.to_numpy().astype(np.float64)
        residual = -(self.B @ x + self.alpha[:, None] * lam
                     + self.gamma[:, None] * (self.B @ (x - xp)))
        s = residual / (1.0 + self.gamma)[:, None]
        dx = self.lu.solve(self.Bf.T @ (s * self.d_inv[:, None]))
        dl = (s - self.Bf @ dx) * self.d_inv[:, None]
        x[self.free] += dx
        solver.x.from_numpy(x.astype(NP_REAL))
        solver.lam_b.from_numpy((lam + dl).astype(NP_REAL))


class SweepsXPBD(XPBDSolver):
    """xpbd as it is, on its per-effect kernels (the path the exact block replaces a part of)."""

    def advance_frame(self, collider, n_sub, h, profile=False, search=True) -> None:
        ClothSolver.advance_frame(self, collider, n_sub, h, True, search)


class BendBlockXPBD(SweepsXPBD):
    """xpbd on its per-effect kernels, its bending sweeps replaced by the exact block: in every
    iteration, or with `first_only` in a substep's first and none after."""

    first_only = False
    _block: ExactBendBlock | None = None

    def _bending_sweep(self, h: float, it: int, reverse: int, sor: float) -> None:
        if self._block is None or self._block.h != h:
            self._block = ExactBendBlock(self, h)
        if it == 0 or not self.first_only:
            self._block.solve(self)


def _use(variant: str) -> None:
    def make(name, model, effects, settings):
        if variant == "sweeps":
            return SweepsXPBD(model, effects, settings)
        solver = BendBlockXPBD(model, effects, settings)
        solver.first_only = variant == "exact first"
        return solver

    simulate_module.make_solver = make


def solve_against_sweep(scene_name: str, resolution: str, fabric: str, substeps: int) -> dict:
    """Milliseconds of one exact block solve and of one Gauss-Seidel sweep over every bend,
    each launched from Python, at the scene's step."""
    scene = build_scene(scene_name, fabric, resolution, frames=1)
    model = build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])
    solver = XPBDSolver(model, Effects(pins=bool(len(model.pinned))),
                        SolverSettings(substeps=substeps, iterations=2))
    h = 1.0 / 30.0 / substeps
    block = ExactBendBlock(solver, h)
    rhs = np.random.default_rng(0).normal(size=(len(block.free), 3))
    repeats = 200
    t = time.perf_counter()
    for _ in range(repeats):
        block.lu.solve(rhs)
    solve_ms = 1000 * (time.perf_counter() - t) / repeats
    solver._use_step(h)  # the bends' terms for this step
    args = (*solver._bend_args(), solver.stiff_bends, 0, 0, 1.0, False)  # every stencil
    K.bends_gauss_seidel(*args)  # compiled before it is timed
    t = time.perf_counter()
    for _ in range(repeats):
        K.bends_gauss_seidel(*args)
    sweep_ms = 1000 * (time.perf_counter() - t) / repeats
    factor = block.lu.L.nnz + block.lu.U.nnz
    return {"solve_ms": solve_ms, "sweep_ms": sweep_ms, "factor_nnz": factor,
            "bends": len(solver.bends_np), "vertices": solver.n}


def main() -> None:
    rows = []
    for scene_name, resolution, fabric in SCENES:
        t = time.perf_counter()
        ref, horizon = float64_reference(scene_name, fabric, resolution)
        scene = build_scene(scene_name, fabric, resolution, frames=ERROR_FRAMES)
        errors = []
        for variant, sub, it in VARIANTS:
            _use(variant)
            run = run_ours(scene, "xpbd", sub, it, label=f"{variant} {sub}x{it}")
            errors.append((variant, sub, it, 1000 * rms_distance(run.positions, ref, horizon)))
        simulate_module.make_solver = make_solver
        cost = solve_against_sweep(scene_name, resolution, fabric, 20)
        rows.append((scene_name, resolution, fabric, horizon, errors, cost))
        print(f"{scene_name} {resolution} {fabric}: horizon {horizon}, "
              f"{time.perf_counter() - t:.0f} s", flush=True)
    print(f"\nCommand: `{COMMAND}`\n")
    header = [f"{v} {s}x{i}" for v, s, i in VARIANTS]
    print("| scene | fabric | horizon | " + " | ".join(header) + " |")
    print("|---" * (3 + len(header)) + "|")
    for scene_name, resolution, fabric, horizon, errors, _ in rows:
        cells = " | ".join(f"{e:.1f}" for *_, e in errors)
        print(f"| {scene_name} {resolution} | {fabric} | {horizon} | {cells} |")
    print("\n| scene | vertices | bends | factor nonzeros | one exact solve ms | "
          "one bending sweep ms | ratio |")
    print("|---|---|---|---|---|---|---|")
    for scene_name, resolution, fabric, _, _, c in rows:
        print(f"| {scene_name} {resolution} {fabric} | {c['vertices']} | {c['bends']} | "
              f"{c['factor_nnz']} | {c['solve_ms']:.3f} | {c['sweep_ms']:.3f} | "
              f"{c['solve_ms'] / c['sweep_ms']:.1f}x |")


if __name__ == "__main__":
    main()
