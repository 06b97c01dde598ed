"""Backward Euler solved to a tolerance: Newton's method with block-Jacobi preconditioned
conjugate gradients, pins handled by filtering (Baraff & Witkin 1998). The reference solver
that the others are measured against (docs/accuracy-vs-time.md).

Each substep minimises the incremental potential
    1/(2h^2) |x - x_n - h v_n|_M^2 + E(x) - f_ext . x + damping,
with the springs' Rayleigh damping and the air drag linearised in (x - x_n) / h; the pressure
drag, where it is on, acts on the velocity before the solve (split off, implicit in itself:
kernels.pressure_drag). The strain
limit and then contact are resolved after the solve by the same projections the other solvers
use, so all solvers share one fabric and one collision model.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from datagen.sim import implicit_kernels as IK
from datagen.sim import kernels as K
from datagen.sim.precision import NP_REAL, REAL, VEC3, VEC4
from datagen.sim.solvers import ClothSolver, _nd


class ImplicitSolver(ClothSolver):
    name = "implicit"

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        n = self.n
        self.xn = _nd(VEC3, model.x0.astype(NP_REAL))
        self.g = ti.ndarray(VEC3, n)
        self.r = ti.ndarray(VEC3, n)
        self.z = ti.ndarray(VEC3, n)
        self.p = ti.ndarray(VEC3, n)
        self.hp = ti.ndarray(VEC3, n)
        self.dx = ti.ndarray(VEC3, n)
        self.diag = ti.ndarray(IK.mat3, n)
        self.mass = _nd(REAL, model.mass.astype(NP_REAL))
        self.drag = _nd(REAL, model.air_drag.astype(NP_REAL))  # the potential's linear drag
        pinned = np.zeros(n, np.int32)
        if self.n_pins:
            pinned[model.pinned] = 1
        self.pinned = _nd(ti.i32, pinned)
        # All active springs as one set: the implicit solve treats them alike.
        names = list(self.sets)
        if names:
            cat = {
                k: np.concatenate(
                    [getattr(self.sets[s], k).to_numpy()[: self.sets[s].count] for s in names]
                )
                for k in ("rest", "k_t", "k_c", "beta")
            }
            sp = np.concatenate(
                [self.sets[s].springs.to_numpy()[: self.sets[s].count] for s in names]
            )
        else:
            cat = {k: np.zeros(0, NP_REAL) for k in ("rest", "k_t", "k_c", "beta")}
            sp = np.zeros((0, 2), np.int32)
        self.n_springs = len(sp)
        self.blocks = ti.ndarray(IK.mat3, max(1, len(sp)))
        self.all_springs = _nd(ti.math.ivec2, sp.astype(np.int32))
        self.all_rest = _nd(REAL, cat["rest"])
        self.all_kt = _nd(REAL, cat["k_t"])
        self.all_kc = _nd(REAL, cat["k_c"])
        self.all_beta = _nd(REAL, cat["beta"])
        if not self.n_bends:
            self.bends = _nd(ti.math.ivec4, np.zeros((1, 4), np.int32))
            self.kw = _nd(VEC4, np.zeros((1, 4), NP_REAL))
            self.bstiff = _nd(REAL, np.zeros(1, NP_REAL))
            self.bbeta = _nd(REAL, np.zeros(1, NP_REAL))
        self.P = ti.ndarray(REAL, IK.P_SIZE)
        self.Q = ti.ndarray(ti.i32, IK.Q_SIZE)
        self.stats = _nd(ti.i32, np.zeros(3, np.int32))

    def substep(self, h: float, collider, s0: float, s1: float) -> None:
        import time

        self._pressure_vectors()
        if self.use_pressure:
            self._run("pressure_drag", K.pressure_drag, self.v, self.air, self.w, self.wind, h,
                      self.use_pressure)
        t = time.perf_counter()
        start, h_velocity = self._solve(h, s1)
        self.costs["implicit_solve"] += time.perf_counter() - t
        self.launches["implicit_solve"] += 1
        self._limit_strain(h)
        self._pins(s1)
        self._collide(collider, s0, s1, h)
        self._cloth_collisions(h, s0, s1)
        self._limit_after_contact(collider, h)
        self._run("integration", K.finish, self.x, start, self.v, self.w, self.contact_n,
                  self.contact_v, h_velocity)

    def _solve(self, h: float, s1: float) -> tuple:
        """The step's solve, from the pinned targets at s1; returns what the velocity after the
        projections is taken from: (x - start) / h_velocity (here the step's start and h;
        benchmarks/study_prefactored_implicit.py's BDF2 differs)."""
        IK.inertial_guess(self.x, self.xn, self.v, self.pinned, h)
        self.xp.copy_from(self.xn)
        self._pins(s1)
        st = self.settings
        P = np.zeros(IK.P_SIZE, NP_REAL)
        P[IK.P_H] = h
        P[IK.P_GRAVITY : IK.P_GRAVITY + 3] = st.gravity
        P[IK.P_TOL] = st.tolerance
        P[IK.P_CG_TOL] = st.cg_tolerance
        Q = np.zeros(IK.Q_SIZE, np.int32)
        Q[IK.Q_N_SPRINGS] = self.n_springs
        Q[IK.Q_N_BENDS] = self.n_bends
        Q[IK.Q_NEWTON_MAX] = max(1, st.iterations)
        Q[IK.Q_CG_MAX] = st.cg_max_iterations
        Q[IK.Q_FORCING] = int(st.cg_forcing)
        self.P.from_numpy(P)
        self.Q.from_numpy(Q)
        IK.newton_solve(
            self.x, self.xn, self.v, self.mass, self.drag, self.pinned,
            self.g, self.r, self.z, self.p, self.hp, self.dx, self.diag, self.blocks,
            self.all_springs, self.all_rest, self.all_kt, self.all_kc, self.all_beta,
            self.bends, self.kw, self.bstiff, self.bbeta,
            self.P, self.Q, self.stats,
            self.effects.gravity, self.effects.air_drag,
        )  # fmt: skip
        return self.xp, h

    @property
    def newton_iterations(self) -> int:
        return int(self.stats.to_numpy()[IK.S_NEWTON])

    @property
    def cg_iterations(self) -> int:
        return int(self.stats.to_numpy()[IK.S_CG])

    @property
    def unconverged(self) -> int:
        return int(self.stats.to_numpy()[IK.S_UNCONVERGED])
