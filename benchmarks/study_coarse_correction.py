"""What a coarse correction of the springs would buy the xpbd solver: a study, not a product path.

A Gauss-Seidel sweep moves a correction about one spring along the cloth, so the long-range
part of a substep's tension (a hanging tube's weight carried up to its pins) is what two
sweeps leave unsolved, and at fewer substeps that is error (docs/simulator.md, "Warm-started
multipliers": a carried multiplier restores that load but is an explicit force step and runs
away). This study adds, inside each substep, the second level of a two-level solver instead:
after an iteration's spring sweeps, the linearised system of every spring set together,

    (J W J^T + D) dl = s,   D = alpha~ / (1 + gamma),   s = residual / (1 + gamma)

(J: the springs' directions at the current positions, W: inverse masses, the residual
-C - alpha~ lambda - gamma J (x - x_prev) that each sweep zeroes one spring at a time), is
projected on a coarse space and solved there exactly: dl = P dmu with P^T (J W J^T + D) P dmu
= P^T s, the positions moving by dx = W J^T P dmu, so positions and multipliers stay
consistent as the sweeps keep them. P gives each chain of L springs along a fibre (a spring's
best-aligned neighbour at each end, where that choice is mutual: study_warm_start's _Fibres)
one multiplier increment. A Galerkin correction is the energy-norm projection of the
linearised substep's own error on the coarse space, a convergent step of the substep's solve,
not a force carried in time; on a straight chain its displacement telescopes to the chain's
ends, so the chain acts as one long spring.

Variants: that system solved exactly over chains of L ("exact, chains of L": numpy and
scipy's sparse LU, the matrix built and factored at every correction, as it follows the
springs' directions); one Gauss-Seidel sweep over the chains of each of several lengths in
turn ("sweeps ...": a Taichi kernel, chain_kernels.py, the form a product would take); the
bending block's Galerkin correction over patches of stencils ("bending patches"); and the
bounds: the fine spring system solved exactly ("exact springs", P = I) and the bending block
solved exactly (study_bend_block's, "exact bending"). Each runs on the xpbd solver's
per-effect kernels against bench_sim's float64 references over the predictable horizon, and
its cheapest setting within Blender's error over the scene's 60 frames, to see whether it
stays stable. Every setting within Blender's error is then projected into the fused kernel
(the product's fused frame at that setting, timed, plus its chain sweeps and bending work at
the kernels' own times) and set against the product at bench_sim's setting at Blender's
error, timed in the same run. Last, `frame_parts` splits the product's tube frame at 20, 10
and 6 substeps into the solver's frame, the collider's frame, QA and the frame loop, with the
strain limit after contact as it is and capped at one sweep.

    python -m benchmarks.study_coarse_correction [--refs DIR]

References are bench_sim's; with DIR they are kept there (each costs minutes). About 33
minutes on 2 cores with the references kept; its tables are in docs/simulator.md ("A coarse
correction of the springs").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

import datagen.sim.simulate as simulate_module
from benchmarks import chain_kernels as CK
from benchmarks.bench_sim import PEER_JSON
from benchmarks.study_bend_block import (
    ExactBendBlock,
    SweepsXPBD,
    bend_compliance,
    solve_against_sweep,
)
from benchmarks.study_warm_start import (
    LONG_FRAMES,
    _Fibres,
    print_error_table,
    run_or_runaway,
    study_scene,
)
from datagen.sim import kernel_common as KC
from datagen.sim import kernels as K
from datagen.sim.effects import Effects
from datagen.sim.fabrics import FABRICS
from datagen.sim.model import build_cloth_model
from datagen.sim.precision import NP_REAL
from datagen.sim.solvers import SolverSettings, XPBDSolver, make_solver
from datagen.study.metrics import rms_distance
from datagen.study.run import run_ours
from datagen.study.scenes import FPS, build_scene

COMMAND = "python -m benchmarks.study_coarse_correction"
SCENES = [("tube_cylinder", "5k", "cotton"), ("tube_cylinder", "5k", "denim")]
SETTINGS = [(20, 2), (15, 2), (12, 2), (10, 2), (8, 2), (6, 2), (10, 1)]
# (name, kind, chain lengths, iterations after whose sweeps the correction runs: "all" or
# "first"): "exact" solves the Galerkin system over chains of the first length; "sweep" runs
# one Gauss-Seidel sweep over the chains of each length in turn.
VARIANTS = [("cold", "", (), ""),
            ("exact, chains of 8", "exact", (8,), "all"),
            ("exact springs", "exact", (1,), "all"),
            ("sweeps 8", "sweep", (8,), "all"),
            ("sweeps 64, 16, 4", "sweep", (64, 16, 4), "all"),
            ("sweeps 4, 16, 64, 16, 4", "sweep", (4, 16, 64, 16, 4), "all"),
            ("sweeps 64, 16, 4, first", "sweep", (64, 16, 4), "first"),
            ("sweeps 64, 16, 4, bend patches 3", "sweep", (64, 16, 4), "all", 3.0),
            ("sweeps 64, 16, 4, exact bending", "sweep", (64, 16, 4), "all", -1.0),
            ("exact springs, exact bending", "exact", (1,), "all", -1.0)]


def fibre_runs(springs: np.ndarray, x: np.ndarray, length: int) -> list[list[int]]:
    """Runs of consecutive springs along a fibre (mutual best-aligned neighbours), each in path
    order and at most `length` long; a last run shorter than half of it joins the one before."""
    m = len(springs)
    if length <= 1:
        return [[a] for a in range(m)]
    nb = _Fibres(springs, x).neighbour
    links: list[list[int]] = [[] for _ in range(m)]
    for a in range(m):
        for b in nb[a]:
            if b >= 0 and a in nb[b] and b not in links[a]:
                links[a].append(int(b))
    seen = np.zeros(m, bool)
    out: list[list[int]] = []
    # Paths from their ends first, then what is left (closed loops, such as a tube's hoops).
    starts = [a for a in range(m) if len(links[a]) < 2] + list(range(m))
    for start in starts:
        if seen[start]:
            continue
        path, prev, cur = [], -1, start
        while cur >= 0 and not seen[cur]:
            path.append(cur)
            seen[cur] = True
            nxt = [b for b in links[cur] if b != prev and not seen[b]]
            prev, cur = cur, (nxt[0] if nxt else -1)
        runs = [path[k:k + length] for k in range(0, len(path), length)]
        if len(runs) > 1 and len(runs[-1]) < length / 2:
            runs[-2].extend(runs.pop())
        out.extend(runs)
    return out


def fibre_chains(springs: np.ndarray, x: np.ndarray, length: int) -> np.ndarray:
    """Each spring's run (fibre_runs) as a label."""
    chain = np.empty(len(springs), np.int64)
    for label, run in enumerate(fibre_runs(springs, x, length)):
        chain[run] = label
    return chain


class ChainLevel:
    """One spring set's runs of one length as the chain kernel reads them: CSR over runs,
    members in path order, each oriented along the path (flip)."""

    def __init__(self, springs: np.ndarray, x: np.ndarray, length: int) -> None:
        runs = fibre_runs(springs, x, length)
        members = np.concatenate([np.asarray(r, np.int32) for r in runs])
        flip = np.zeros(len(members), np.int32)
        k = 0
        for run in runs:
            for pos, e in enumerate(run):
                if pos + 1 < len(run):  # b_k is the vertex shared with the next member
                    shared = set(springs[e]) & set(springs[run[pos + 1]])
                    flip[k] = int(springs[e][0] in shared)
                else:  # a_k is the vertex shared with the previous one
                    shared = set(springs[e]) & set(springs[run[pos - 1]]) if pos else set()
                    flip[k] = int(springs[e][1] in shared)
                k += 1
        ptr = np.concatenate([[0], np.cumsum([len(r) for r in runs])]).astype(np.int32)
        self.n_runs = len(runs)
        self.ptr = ti.ndarray(ti.i32, len(ptr))
        self.ptr.from_numpy(ptr)
        self.members = ti.ndarray(ti.i32, len(members))
        self.members.from_numpy(members)
        self.flip = ti.ndarray(ti.i32, len(flip))
        self.flip.from_numpy(flip)


class CoarseSprings:
    """Every spring set's springs with their chains: the prolongation P (springs x chains)."""

    def __init__(self, solver, length: int) -> None:
        x = solver.x.to_numpy().astype(np.float64)
        parts, chains, offset = [], [], 0
        for s in solver.sets.values():
            springs = s.springs.to_numpy()
            c = fibre_chains(springs, x, length)
            parts.append(springs)
            chains.append(c + offset)
            offset += int(c.max()) + 1
        self.springs = np.concatenate(parts)
        m = len(self.springs)
        self.P = sp.csr_matrix((np.ones(m), (np.arange(m), np.concatenate(chains))),
                               shape=(m, offset))

    def correct(self, solver, h: float) -> None:
        """One Galerkin correction of the substep's linearised spring system."""
        x = solver.x.to_numpy().astype(np.float64)
        xp = solver.xp.to_numpy().astype(np.float64)
        w = solver.w_np.astype(np.float64)
        sets = list(solver.sets.values())
        lam = np.concatenate([s.lam.to_numpy() for s in sets]).astype(np.float64)
        rest = np.concatenate([s.rest.to_numpy() for s in sets]).astype(np.float64)
        comp_t, comp_c = (np.concatenate(parts)
                          for parts in zip(*(CK.compliances_np(s) for s in sets), strict=True))
        beta = np.concatenate([s.beta.to_numpy() for s in sets]).astype(np.float64)
        i, j = self.springs.T
        d = x[j] - x[i]
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        n = d / length[:, None]
        c = length - rest
        alpha = np.where(c < 0, comp_c, comp_t) / (h * h)
        gamma = beta / h
        live = (w[i] + w[j]) > 0
        rate = (n * ((x[j] - xp[j]) - (x[i] - xp[i]))).sum(axis=1)
        s_rhs = np.where(live, (-c - alpha * lam - gamma * rate) / (1.0 + gamma), 0.0)
        dinv = alpha / (1.0 + gamma)
        m, nv = len(i), len(x)
        rows = np.repeat(np.arange(m), 6)
        cols = np.stack([3 * i, 3 * i + 1, 3 * i + 2, 3 * j, 3 * j + 1, 3 * j + 2], axis=1).ravel()
        vals = np.concatenate([-n, n], axis=1).ravel()
        J = sp.csr_matrix((vals, (rows, cols)), shape=(m, 3 * nv))
        G = (J.T @ self.P).tocsr()  # 3n x chains
        Wg = sp.diags(np.repeat(w, 3)) @ G
        A = (G.T @ Wg + sp.diags(self.P.T @ dinv)).tocsc()
        dmu = spla.splu(A, permc_spec="MMD_AT_PLUS_A").solve(self.P.T @ s_rhs)
        dl = self.P @ dmu
        x += (Wg @ dmu).reshape(-1, 3)
        solver.x.from_numpy(x.astype(NP_REAL))
        start = 0
        for s in sets:
            s.lam.from_numpy((lam[start:start + s.count] + dl[start:start + s.count])
                             .astype(NP_REAL))
            start += s.count


class CoarseBends:
    """The bending stencils in patches (a voxel of `size` times the median edge, by the
    stencil's rest centre): the bending block's Galerkin system over the patches, each patch
    one multiplier increment (a vector, as a stencil's). Our bending is linear in the positions
    with constant weights, so the coarse matrix P^T (B W B^T + D) P is constant for a step size
    and factored once (per coordinate the same matrix)."""

    def __init__(self, solver, size: float) -> None:
        x = solver.model.x0.astype(np.float64)
        bends = solver.bends_np
        kw = solver.kw.to_numpy().astype(np.float64)
        nb, n = len(bends), solver.n
        self.B = sp.csr_matrix((kw.ravel(), (np.repeat(np.arange(nb), 4), bends.ravel())),
                               shape=(nb, n))
        edge = np.median(np.linalg.norm(x[bends[:, 1]] - x[bends[:, 0]], axis=1))
        cell = np.floor(x[bends].mean(axis=1) / (size * edge)).astype(np.int64)
        _, label = np.unique(cell, axis=0, return_inverse=True)
        label = label.ravel()
        self.P = sp.csr_matrix((np.ones(nb), (np.arange(nb), label)), shape=(nb, label.max() + 1))
        self.WBtP = (sp.diags(solver.w_np.astype(np.float64)) @ self.B.T @ self.P).tocsr()
        self.alpha_unit = bend_compliance(solver)
        self.beta = solver.bbeta.to_numpy().astype(np.float64)
        self.h = 0.0

    def correct(self, solver, h: float) -> None:
        alpha = self.alpha_unit / (h * h)
        gamma = self.beta / h
        if h != self.h:
            self.h = h
            d = alpha / (1.0 + gamma)
            a = (self.P.T @ self.B) @ self.WBtP + sp.diags(self.P.T @ d)
            self.lu = spla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A")
        x = solver.x.to_numpy().astype(np.float64)
        xp = solver.xp.to_numpy().astype(np.float64)
        lam = solver.lam_b.to_numpy().astype(np.float64)
        residual = -(self.B @ x + alpha[:, None] * lam + gamma[:, None] * (self.B @ (x - xp)))
        dmu = self.lu.solve(self.P.T @ (residual / (1.0 + gamma)[:, None]))
        solver.x.from_numpy((x + self.WBtP @ dmu).astype(NP_REAL))
        solver.lam_b.from_numpy((lam + self.P @ dmu).astype(NP_REAL))


class CoarseXPBD(SweepsXPBD):
    """xpbd on its per-effect kernels with a coarse spring correction after the spring sweeps
    of every iteration (`when` "all") or of the first only ("first"): the exact Galerkin solve
    over chains of `lengths[0]` (`kind` "exact"), or one Gauss-Seidel sweep over the chains of
    each length in `lengths`, in that order (`kind` "sweep", Taichi: chain_kernels.py)."""

    kind = ""
    lengths: tuple[int, ...] = ()
    when = "all"
    bend_patch = 0.0  # the bending's patch size in edges (CoarseBends); 0: none; < 0: exact

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        self._coarse: CoarseSprings | None = None
        self._coarse_bends: CoarseBends | None = None
        self._exact_bends: ExactBendBlock | None = None
        self._levels: dict[str, list[ChainLevel]] | None = None
        self._it, self._h, self._reverse = 0, 0.0, 0
        self._last_set = next(reversed(self.sets))  # the correction follows its sweep

    def _bending_sweep(self, h, it, reverse, sor) -> None:
        self._it, self._h, self._reverse = it, h, reverse
        if self.bend_patch < 0:  # the bending block solved exactly instead (study_bend_block)
            if self._exact_bends is None or self._exact_bends.h != h:
                self._exact_bends = ExactBendBlock(self, h)
            self._exact_bends.solve(self)
        else:
            super()._bending_sweep(h, it, reverse, sor)

    def _run(self, effect, fn, *args) -> None:
        super()._run(effect, fn, *args)
        if ((self.kind or self.bend_patch) and fn is K.springs_gauss_seidel
                and effect == self._last_set
                and (self.when == "all" or self._it == 0)):
            if self.kind == "exact":
                if self._coarse is None:
                    self._coarse = CoarseSprings(self, self.lengths[0])
                self._coarse.correct(self, self._h)
            elif self.kind == "sweep":
                self._chain_sweeps()
            if self.bend_patch > 0 and self.n_bends:
                if self._coarse_bends is None:
                    self._coarse_bends = CoarseBends(self, self.bend_patch)
                self._coarse_bends.correct(self, self._h)

    def _chain_sweeps(self) -> None:
        if self._levels is None:
            x = self.x.to_numpy().astype(np.float64)
            self._levels = {name: [ChainLevel(s.springs.to_numpy(), x, n) for n in self.lengths]
                            for name, s in self.sets.items()}
            self._dirs = {name: ti.ndarray(KC.vec3, s.count) for name, s in self.sets.items()}
            self._compliances = {name: CK.set_compliances(s) for name, s in self.sets.items()}
        for level in range(len(self.lengths)):
            for name, s in self.sets.items():
                c = self._levels[name][level]
                super()._run("chains", CK.chains_gauss_seidel, self.x, self.xp, self.w,
                             s.springs, s.rest, *self._compliances[name], s.beta, s.lam, c.ptr,
                             c.members, c.flip, self._dirs[name], self._h, self._reverse,
                             1.0)


def _use(kind: str, lengths: tuple[int, ...], when: str, bend_patch: float = 0.0) -> None:
    def make(name, model, effects, settings):
        solver = CoarseXPBD(model, effects, settings)
        solver.kind, solver.lengths, solver.when = kind, lengths, when
        solver.bend_patch = bend_patch
        return solver

    simulate_module.make_solver = make


def chain_sweep_ms(scene_name: str, resolution: str, fabric: str, lengths: tuple[int, ...],
                   substeps: int, repeats: int = 200) -> tuple[float, float, float]:
    """Milliseconds of one Gauss-Seidel sweep over every spring set, of one chain sweep of
    every level in `lengths` over every set, and of one bending sweep over every stencil, each
    kernel launched from Python at the scene's step (the chain kernel would run inside the
    fused frame kernel, without its launches)."""
    scene = build_scene(scene_name, fabric, resolution, frames=1)
    model = build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])
    solver = XPBDSolver(model, Effects(pins=bool(len(model.pinned))),
                        SolverSettings(substeps=substeps, iterations=2))
    h = 1.0 / FPS / substeps
    solver._use_step(h)  # the springs' and bends' terms for this step
    x = solver.x.to_numpy().astype(np.float64)
    springs, chains = [], []
    for s in solver.sets.values():
        springs.append((s.springs, s.terms, s.lam))
        dirs = ti.ndarray(KC.vec3, s.count)
        compliances = CK.set_compliances(s)
        for n in lengths:
            c = ChainLevel(s.springs.to_numpy(), x, n)
            chains.append((s.springs, s.rest, *compliances, s.beta, s.lam, c.ptr,
                           c.members, c.flip, dirs))

    def sweep() -> None:
        for args in springs:
            K.springs_gauss_seidel(solver.x, solver.xp, solver.w, *args, 0, 1.0)

    def chain() -> None:
        for args in chains:
            CK.chains_gauss_seidel(solver.x, solver.xp, solver.w, *args, h, 0, 1.0)

    def bend() -> None:
        K.bends_gauss_seidel(*solver._bend_args(), solver.stiff_bends, 0, 0, 1.0, False)

    out = []
    for fn in (sweep, chain, bend):
        fn()  # compiled before it is timed
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        ti.sync()
        out.append(1000 * (time.perf_counter() - t) / repeats)
    return out[0], out[1], out[2]


FRAME_SETTINGS = ["20x2", "10x2", "6x2"]


def frame_parts(fabric: str, after_contact_sweeps: int) -> list[dict]:
    """Where a fused frame's time goes on the tube at FRAME_SETTINGS (60 frames, the second of
    two runs each): the solver's frame (advance_frame: the substeps), the collider's frame
    (_set_body), the QA and outputs (_record), and the rest of the frame loop (its guards,
    state reads and the full search every fifth frame), in ms per frame, and the run's largest
    p99.9 strain (what the QA bound measures); with the strain limit after contact capped at
    `after_contact_sweeps` sweeps a substep (a module constant read when the kernels compile,
    so each cap runs in a process of its own: --frame-parts)."""
    from benchmarks.study_body_frame import time_frame_parts

    K.AFTER_CONTACT_SWEEPS = after_contact_sweeps
    scene = build_scene("tube_cylinder", fabric, "5k", frames=LONG_FRAMES)
    rows = []
    for setting in FRAME_SETTINGS:
        sub, it = (int(k) for k in setting.split("x"))
        _timed(scene, sub, it)
        spent: dict[str, float] = {}
        simulate_module.make_solver = make_solver
        with time_frame_parts(spent):
            run = run_ours(scene, "xpbd", sub, it)
        rate = run.seconds_per_simulated_second
        ms = {k: 1000 * v / LONG_FRAMES for k, v in spent.items()}
        rows.append({"setting": setting, "s_per_sim_s": rate, "solver": ms["solver"],
                     "strain_p999": float(run.qa["strain_p999"].max()),
                     "collider": ms["collider"], "record": ms["qa"],
                     "rest": ms["loop"] - ms["solver"] - ms["collider"]})
    return rows


def _frame_parts_table(fabrics: list[str]) -> None:
    import subprocess
    import sys

    print("\n| scene | after-contact sweeps | setting | s/sim-s | ms a frame | solver's frame | "
          "collider's frame | QA and outputs | rest of the loop | strain p99.9 (bound) |")
    print("|---" * 10 + "|")
    for fabric in fabrics:
        for cap in (K.AFTER_CONTACT_SWEEPS, 1):
            out = subprocess.run([sys.executable, "-m", "benchmarks.study_coarse_correction",
                                  "--frame-parts", f"{fabric}:{cap}"], capture_output=True,
                                 text=True, check=True).stdout
            for r in json.loads(out.strip().splitlines()[-1]):
                print(f"| tube_cylinder 5k {fabric} | {cap} | {r['setting']} | "
                      f"{r['s_per_sim_s']:.3f} | {1000 * r['s_per_sim_s'] / FPS:.1f} | "
                      f"{r['solver']:.1f} | {r['collider']:.1f} | {r['record']:.1f} | "
                      f"{r['rest']:.1f} | {r['strain_p999']:.3f} ({FABRICS[fabric].max_strain}) |",
                      flush=True)


def _timed(scene, sub: int, it: int) -> float:
    """Seconds per simulated second of the product's fused xpbd at sub x it (60 frames)."""
    simulate_module.make_solver = make_solver
    return run_ours(scene, "xpbd", sub, it).seconds_per_simulated_second


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--refs", type=Path, help="keep the float64 references in this folder")
    parser.add_argument("--variants", help="semicolon-separated names (default: all)")
    parser.add_argument("--fabrics", default="cotton,denim", help="comma-separated")
    parser.add_argument("--settings", help="e.g. 15x2,10x2 (default: all)")
    parser.add_argument("--frame-parts", metavar="FABRIC:SWEEPS",
                        help="only print frame_parts' JSON (the study runs it this way)")
    args = parser.parse_args()
    if args.frame_parts:
        fabric, cap = args.frame_parts.split(":")
        print(json.dumps(frame_parts(fabric, int(cap))))
        return
    settings = ([tuple(int(k) for k in s.split("x")) for s in args.settings.split(",")]
                if args.settings else SETTINGS)
    variants = [v for v in VARIANTS
                if not args.variants or v[0] in args.variants.split(";")]
    peer = {(r["scene"], r["fabric"]): r for r in json.loads(PEER_JSON.read_text())["rows"]}
    errors, long_runs, costs = {}, {}, []
    scenes = [sc for sc in SCENES if sc[2] in args.fabrics.split(",")]
    for scene_name, resolution, fabric in scenes:
        t0 = time.perf_counter()
        ref, horizon, short, long = study_scene(scene_name, resolution, fabric, args.refs)
        row = peer[(f"{scene_name} {resolution}", fabric)]
        bound = row["blender_err_mm"]
        candidates = []
        for name, kind, lengths, when, *patch in variants:
            _use(kind, lengths, when, *patch)
            for sub, it in settings:
                positions, why = run_or_runaway(short, sub, it)
                e = None if positions is None else 1000 * rms_distance(positions, ref, horizon)
                errors[(fabric, name, sub, it)] = (e, why)
                print(f"  {fabric} {name} {sub}x{it}: {e if e is None else round(e, 2)} {why}",
                      flush=True)
                if e is not None and e <= bound and kind != "exact":
                    candidates.append((name, kind, lengths, when, patch, sub, it, e))
        # What each candidate within Blender's error would cost in the fused kernel: the
        # product's frame at its setting, timed, plus its chain sweeps (and, with bending
        # patches, at least one bending sweep for their residual) at the kernels' own times.
        cold_steps = row["at_error"]["steps"]
        s0, i0 = (int(k) for k in cold_steps.split("x"))
        cold = _timed(long, s0, i0)
        kernel_ms: dict = {}
        for name, kind, lengths, when, patch, sub, it, e in candidates:
            if lengths not in kernel_ms:
                kernel_ms[lengths] = chain_sweep_ms(scene_name, resolution, fabric, lengths, sub)
            sweep_ms, chain_ms, bend_ms = kernel_ms[lengths]
            per_correction = (chain_ms if kind else 0.0) + (bend_ms if patch and patch[0] > 0
                                                            else 0.0)
            corrections = it if when == "all" else 1
            extra = corrections * per_correction
            if patch and patch[0] < 0:  # an exact bending solve in place of each bending sweep
                if "bend_solve" not in kernel_ms:
                    cost = solve_against_sweep(scene_name, resolution, fabric, sub)
                    kernel_ms["bend_solve"] = cost["solve_ms"] - cost["sweep_ms"]
                extra += it * kernel_ms["bend_solve"]
            fused = _timed(long, sub, it)
            projected = fused + sub * FPS * extra / 1000.0
            costs.append((scene_name, resolution, fabric, name, f"{sub}x{it}", e, fused,
                          projected, cold_steps, cold, sweep_ms, chain_ms, bend_ms,
                          row["at_error"]["speedup"]))
        # The cheapest by projection (or by steps where nothing is projected) over 60 frames.
        for name, kind, lengths, when, *patch in variants:
            mine = [c for c in costs if c[2] == fabric and c[3] == name]
            within = [(s, i) for s, i in settings if errors[(fabric, name, s, i)][0] is not None
                      and errors[(fabric, name, s, i)][0] <= bound]
            if (kind or patch) and within:
                sub, it = (tuple(int(k) for k in min(mine, key=lambda c: c[7])[4].split("x"))
                           if mine else min(within, key=lambda si: si[0] * si[1]))
                _use(kind, lengths, when, *patch)
                positions, why = run_or_runaway(long, sub, it)
                long_runs[(fabric, name)] = (f"{sub}x{it}", why or "ran")
        simulate_module.make_solver = make_solver
        print(f"{scene_name} {resolution} {fabric}: horizon {horizon}, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    print(f"\nCommand: `{COMMAND}`\n")
    print_error_table(scenes, "correction", [v[0] for v in variants], settings, errors,
                      long_runs, lambda n, r, f: peer[(f"{n} {r}", f)]["blender_err_mm"])
    print("\n| scene | correction | setting | error mm | fused frame alone s/sim-s | "
          "projected s/sim-s | product at Blender's error | its s/sim-s | gain | "
          "against Blender | spring sweep ms | chain levels ms | bending sweep ms |")
    print("|---" * 13 + "|")
    for (scene_name, resolution, fabric, name, setting, e, fused, projected, cold_steps, cold,
         sweep_ms, chain_ms, bend_ms, speedup) in costs:
        gain = cold / projected
        print(f"| {scene_name} {resolution} {fabric} | {name} | {setting} | {e:.2f} | "
              f"{fused:.3f} | {projected:.3f} | {cold_steps} | {cold:.3f} | {gain:.2f}x | "
              f"{speedup * gain:.1f}x | {sweep_ms:.3f} | {chain_ms:.3f} | {bend_ms:.3f} |")
    _frame_parts_table([f for *_, f in scenes])


if __name__ == "__main__":
    main()
