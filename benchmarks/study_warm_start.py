"""What warm-started multipliers would buy the xpbd solver: a study, not a product path.

Each xpbd substep starts its multipliers at zero, so a hanging garment's tension is found
again every substep, and what the sweeps leave of it is sag (docs/simulator.md, "Warm-started
multipliers"). This study carries each spring's multiplier into the next substep instead,
filtered, and applies what it carries as a displacement before the first sweep (positions and
multipliers stay consistent: dx = W J^T lambda, as the sweeps keep them). Filters:

- `smooth xN`: each spring's multiplier averaged N times over the springs of its set that share
  an end, weighted by |cos|^8 of the angle between them (the load follows the fibres);
- `smooth x1 + bends`: one pass, and the bending stencils' multipliers carried raw at 0.7;
- `minmod`: a spring's multiplier carried only as far as its best-aligned neighbour at each
  end agrees (the smallest of the three where all share its sign, else nothing);
- `minmod in time`: as far as the spring's own multiplier of the substep before agrees;
- `smooth x2, residual factor`: two passes, scaled each substep by the factor that minimises
  the XPBD residual (each spring's over its Jacobi denominator) of the carried start.

A frame the solver retries starts cold. Runs on the xpbd solver's per-effect kernels (numpy
transfers: errors only, the times mean nothing), against bench_sim's float64 references over
the predictable horizon, and each variant's 60-frame run at the settings where it comes
within Blender's error, to see whether it stays stable.

    python -m benchmarks.study_warm_start [--refs DIR]

About 15 minutes on 2 cores with the references kept in DIR (each costs minutes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import datagen.sim.simulate as simulate_module
from benchmarks.bench_sim import ERROR_FRAMES, PEER_JSON, float64_reference
from benchmarks.chain_kernels import compliances_np
from benchmarks.study_bend_block import SweepsXPBD
from datagen.errors import RejectedSequence
from datagen.sim.precision import NP_REAL
from datagen.sim.solvers import make_solver
from datagen.study.metrics import rms_distance
from datagen.study.run import run_ours
from datagen.study.scenes import build_scene

COMMAND = "python -m benchmarks.study_warm_start"
SCENES = [("tube_cylinder", "5k", "cotton"), ("tube_cylinder", "5k", "denim")]
SETTINGS = [(20, 2), (15, 2), (12, 2), (10, 2)]
VARIANTS = ["cold", "smooth x1", "smooth x2", "smooth x1 + bends", "minmod", "minmod in time",
            "smooth x2, residual factor"]
ALIGNMENT_POWER = 8
BEND_FACTOR = 0.7
ALIGNED_COS = 0.9  # a neighbour continues a spring's fibre (minmod)
LONG_FRAMES = 60


def _minmod(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.where(a * b > 0, np.sign(a) * np.minimum(np.abs(a), np.abs(b)), 0.0)


class _Fibres:
    """One spring set's structure for the filters: an averaging operator over springs that
    share an end (|cos|^ALIGNMENT_POWER weights, rows summing to one) and each spring's
    best-aligned neighbour at each end (-1 where none is within ALIGNED_COS)."""

    def __init__(self, springs: np.ndarray, x: np.ndarray) -> None:
        m, n = len(springs), len(x)
        d = x[springs[:, 1]] - x[springs[:, 0]]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ends = sp.csr_matrix((np.ones(2 * m), (springs.T.ravel(), np.tile(np.arange(m), 2))),
                             shape=(n, m))
        share = (ends.T @ ends).tocoo()  # springs sharing a vertex, each with itself
        cos = np.abs((d[share.row] * d[share.col]).sum(axis=1))
        avg = sp.csr_matrix((cos**ALIGNMENT_POWER, (share.row, share.col)), shape=(m, m))
        self.average = sp.diags(1.0 / np.asarray(avg.sum(axis=1)).ravel()) @ avg
        self.springs = springs
        # Each spring's best-aligned other spring at each end: pairs sorted by alignment, the
        # last of each (spring, end) kept.
        e, f = share.row, share.col
        other = e != f
        e, f, cos = e[other], f[other], cos[other]
        self.neighbour = -np.ones((m, 2), np.int64)
        for end in range(2):
            v = springs[e, end]
            at_end = ((springs[f, 0] == v) | (springs[f, 1] == v)) & (cos > ALIGNED_COS)
            ee, ff, cc = e[at_end], f[at_end], cos[at_end]
            order = np.lexsort((cc, ee))
            ee, ff = ee[order], ff[order]
            last = np.r_[ee[1:] != ee[:-1], True]
            self.neighbour[ee[last], end] = ff[last]

    def minmod(self, lam: np.ndarray) -> np.ndarray:
        out = lam.copy()
        for end in range(2):
            nb = self.neighbour[:, end]
            out = _minmod(out, np.where(nb >= 0, lam[np.maximum(nb, 0)], lam))
        return out


class WarmStartXPBD(SweepsXPBD):
    """xpbd on its per-effect kernels, each substep starting from the last one's multipliers
    as `variant` filters them (the class docstring of the module)."""

    variant = "cold"
    log: list[float] | None = None  # the residual factors chosen, where that variant runs

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        self._fibres: dict[str, _Fibres] = {}
        self._last: dict | None = None  # the multipliers a substep ended with, and its step
        self._before: dict[str, np.ndarray] = {}  # the ones before them (minmod in time)

    def set_state(self, x, v) -> None:
        super().set_state(x, v)
        self._last, self._before = None, {}  # a retried frame starts cold

    def substep(self, h, collider, s0, s1) -> None:
        super().substep(h, collider, s0, s1)
        if self.variant != "cold":
            self._last = {"h": h, "bends": self.lam_b.to_numpy().astype(np.float64),
                          **{k: s.lam.to_numpy().astype(np.float64)
                             for k, s in self.sets.items()}}

    def _bending_sweep(self, h, it, reverse, sor) -> None:
        if it == 0 and self._last is not None:
            self._warm_start(h)
        super()._bending_sweep(h, it, reverse, sor)

    def _carried(self, name: str, lam: np.ndarray, x: np.ndarray) -> np.ndarray:
        if name not in self._fibres:
            self._fibres[name] = _Fibres(self.sets[name].springs.to_numpy(), x)
        fibres, v = self._fibres[name], self.variant
        if v == "minmod":
            return fibres.minmod(lam)
        if v == "minmod in time":
            before = self._before.get(name, np.zeros_like(lam))
            self._before[name] = lam
            return _minmod(lam, before)
        passes = 1 if v.startswith("smooth x1") else 2
        for _ in range(passes):
            lam = fibres.average @ lam
        return lam

    def _warm_start(self, h: float) -> None:
        """Carry the last substep's multipliers (scaled to this step: they are force times
        the step squared) and move the vertices by what they carry."""
        scale = (h / self._last["h"]) ** 2
        x = self.x.to_numpy().astype(np.float64)
        w = self.w_np.astype(np.float64)
        dx = np.zeros_like(x)
        carried = {}
        for name in self.sets:
            lam = scale * self._carried(name, self._last[name], x)
            springs = self._fibres[name].springs
            d = x[springs[:, 1]] - x[springs[:, 0]]
            move = lam[:, None] * d / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
            np.add.at(dx, springs[:, 0], -w[springs[:, 0], None] * move)
            np.add.at(dx, springs[:, 1], w[springs[:, 1], None] * move)
            carried[name] = lam
        bends = np.zeros_like(self._last["bends"])
        if self.variant.endswith("+ bends") and self.n_bends:
            bends = BEND_FACTOR * scale * self._last["bends"]
            kw = self.kw.to_numpy().astype(np.float64)
            for q in range(4):
                np.add.at(dx, self.bends_np[:, q], w[self.bends_np[:, q], None]
                          * kw[:, q, None] * bends)
        factor = 1.0
        if self.variant.endswith("residual factor"):
            xp = self.xp.to_numpy().astype(np.float64)
            r0 = self._residuals(x, xp, h, {k: 0.0 * v for k, v in carried.items()})
            dr = self._residuals(x + dx, xp, h, carried) - r0
            den = float(dr @ dr)
            factor = float(np.clip(-(r0 @ dr) / den, 0.0, 1.0)) if den > 0 else 0.0
            if self.log is not None:
                self.log.append(factor)
        for name, s in self.sets.items():
            s.lam.from_numpy((factor * carried[name]).astype(NP_REAL))
        if self.n_bends:
            self.lam_b.from_numpy((factor * bends).astype(NP_REAL))
        self.x.from_numpy((x + factor * dx).astype(NP_REAL))

    def _residuals(self, x: np.ndarray, xp: np.ndarray, h: float, lam: dict) -> np.ndarray:
        """Every spring's XPBD residual C + alpha~ lambda + gamma rate, over the square root of
        its Jacobi denominator."""
        out = []
        for name, s in self.sets.items():
            i, j = self._fibres[name].springs.T
            d = x[j] - x[i]
            length = np.linalg.norm(d, axis=1)
            c = length - s.rest.to_numpy()
            comp_t, comp_c = compliances_np(s)
            alpha = np.where(c < 0, comp_c, comp_t) / (h * h)
            gamma = s.beta.to_numpy() / h
            rate = ((d / np.maximum(length, 1e-12)[:, None])
                    * ((x[j] - xp[j]) - (x[i] - xp[i]))).sum(axis=1)
            wsum = self.w_np[i] + self.w_np[j]
            denominator = (1.0 + gamma) * wsum + alpha
            r = (c + alpha * lam[name] + gamma * rate) / np.sqrt(np.maximum(denominator, 1e-30))
            out.append(np.where(wsum > 0, r, 0.0))
        return np.concatenate(out)


def _use(variant: str, log: list | None = None) -> None:
    def make(name, model, effects, settings):
        solver = WarmStartXPBD(model, effects, settings)
        solver.variant, solver.log = variant, log
        return solver

    simulate_module.make_solver = make


def run_or_runaway(scene, sub: int, it: int) -> tuple[np.ndarray | None, str]:
    """The positions of an xpbd run at sub x it, or None and why it was rejected (the studies'
    variants run on the solver make_solver gives)."""
    try:
        run = run_ours(scene, "xpbd", sub, it)
    except RejectedSequence as exc:
        return None, exc.reason.split(",")[0].split(":")[-1].strip()
    return run.positions, ""


def study_scene(scene_name: str, resolution: str, fabric: str, refs: Path | None):
    """A peer scene's float64 reference and its horizon (kept in `refs` where given), and the
    scene for the error runs (ERROR_FRAMES) and for the long runs (LONG_FRAMES)."""
    cache = refs / f"{scene_name}_{resolution}_{fabric}.npz" if refs else None
    ref, horizon = float64_reference(scene_name, fabric, resolution, cache)
    return (ref, horizon, build_scene(scene_name, fabric, resolution, frames=ERROR_FRAMES),
            build_scene(scene_name, fabric, resolution, frames=LONG_FRAMES))


def print_error_table(scenes, column: str, names, settings, errors: dict, long_runs: dict,
                      bound) -> None:
    """The studies' error table: a row per scene and variant, RMS mm at each setting (or why
    it ran away) and its cheapest setting within Blender's error (`bound(scene_name,
    resolution, fabric)`) over LONG_FRAMES frames."""
    header = [f"{s}x{i}" for s, i in settings]
    print(f"| scene | {column} | " + " | ".join(header) + " | cheapest within Blender's error, "
          f"{LONG_FRAMES} frames |")
    print("|---" * (3 + len(header)) + "|")
    for scene_name, resolution, fabric in scenes:
        b = bound(scene_name, resolution, fabric)
        for name in names:
            cells = []
            for s, i in settings:
                e, why = errors[(fabric, name, s, i)]
                cells.append(f"{e:.2f}" if e is not None else f"runaway ({why})")
            setting, outcome = long_runs.get((fabric, name), ("-", "-"))
            print(f"| {scene_name} {resolution} {fabric} (Blender {b:.2f}) | {name} | "
                  + " | ".join(cells) + f" | {setting}: {outcome} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--refs", type=Path, help="keep the float64 references in this folder")
    args = parser.parse_args()
    blender = {(r["scene"], r["fabric"]): r["blender_err_mm"]
               for r in json.loads(PEER_JSON.read_text())["rows"]}
    errors, long_runs, factors = {}, {}, []
    for scene_name, resolution, fabric in SCENES:
        t0 = time.perf_counter()
        ref, horizon, short, long = study_scene(scene_name, resolution, fabric, args.refs)
        bound = blender[(f"{scene_name} {resolution}", fabric)]
        for variant in VARIANTS:
            _use(variant, factors if variant.endswith("residual factor") else None)
            for sub, it in SETTINGS:
                positions, why = run_or_runaway(short, sub, it)
                e = None if positions is None else 1000 * rms_distance(positions, ref, horizon)
                errors[(fabric, variant, sub, it)] = (e, why)
            within = [(s, i) for s, i in SETTINGS
                      if errors[(fabric, variant, s, i)][0] is not None
                      and errors[(fabric, variant, s, i)][0] <= bound]
            if variant != "cold" and within:  # the cheapest within Blender's error, for long
                sub, it = min(within)
                positions, why = run_or_runaway(long, sub, it)
                long_runs[(fabric, variant)] = (f"{sub}x{it}", why or "ran")
        simulate_module.make_solver = make_solver
        print(f"{scene_name} {resolution} {fabric}: horizon {horizon}, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    print(f"\nCommand: `{COMMAND}`\n")
    print_error_table(SCENES, "filter", VARIANTS, SETTINGS, errors, long_runs,
                      lambda n, r, f: blender[(f"{n} {r}", f)])
    if factors:
        print(f"\nresidual factors chosen: median {np.median(factors):.2f}, "
              f"5-95 % {np.percentile(factors, 5):.2f}-{np.percentile(factors, 95):.2f}")


if __name__ == "__main__":
    main()
