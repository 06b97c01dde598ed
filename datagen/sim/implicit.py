"""Backward Euler solved to a tolerance: Newton's method with block-Jacobi preconditioned
conjugate gradients, pins handled by filtering (Baraff & Witkin 1998). The reference solver
that the others are measured against (docs/accuracy-vs-time.md).

Each substep minimises the incremental potential
    1/(2h^2) |x - x_n - h v_n|_M^2 + E(x) - f_ext . x + damping,
with the springs' Rayleigh damping and the air drag linearised in (x - x_n) / h. Contact is
resolved after the solve by the same projection the other solvers use, so all solvers share
one collision model.
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
        self.newton_iterations = 0
        self.cg_iterations = 0
        self.unconverged = 0

    def _gradient(self, h: float) -> None:
        e = self.effects
        use_air = e.air_drag or e.wind
        IK.gradient(
            self.x,
            self.xn,
            self.v,
            self.mass,
            self.drag,
            self.pinned,
            self.g,
            self.gravity,
            self.wind,
            h,
            e.gravity,
            use_air,
        )
        if self.n_springs:
            IK.spring_gradient(
                self.x,
                self.xn,
                self.g,
                self.all_springs,
                self.all_rest,
                self.all_kt,
                self.all_kc,
                self.all_beta,
                h,
            )
        if self.n_bends:
            IK.bend_gradient(
                self.x, self.xn, self.g, self.bends, self.kw, self.bstiff, self.bbeta, h
            )

    def _hv(self, h: float) -> None:
        IK.hessian_product(
            self.x,
            self.mass,
            self.drag,
            self.p,
            self.hp,
            self.all_springs,
            self.all_rest,
            self.all_kt,
            self.all_kc,
            self.all_beta,
            self.bends,
            self.kw,
            self.bstiff,
            self.bbeta,
            self.pinned,
            h,
            self.n_springs,
            self.n_bends,
            self.effects.air_drag or self.effects.wind,
        )

    def _solve_newton_step(self, h: float) -> float:
        """One Newton step; returns the max vertex update (m)."""
        s = self.settings
        self._gradient(h)
        IK.diagonal(
            self.x,
            self.mass,
            self.drag,
            self.diag,
            self.all_springs,
            self.all_rest,
            self.all_kt,
            self.all_kc,
            self.all_beta,
            self.bends,
            self.kw,
            self.bstiff,
            self.bbeta,
            h,
            self.n_springs,
            self.n_bends,
            self.effects.air_drag or self.effects.wind,
        )
        IK.invert_blocks(self.diag, self.pinned)
        # CG on H dx = -g, starting from dx = 0.
        IK.negate_filtered(self.g, self.r, self.pinned)
        self.dx.fill(0.0)
        IK.precondition(self.diag, self.r, self.z, self.pinned)
        self.p.copy_from(self.z)
        rz = IK.dot(self.r, self.z)
        r0 = rz
        it = 0
        while it < s.cg_max_iterations and rz > (s.cg_tolerance**2) * r0 and rz > 1e-30:
            self._hv(h)
            php = IK.dot(self.p, self.hp)
            if php <= 0:
                break
            alpha = rz / php
            IK.axpy(self.dx, alpha, self.p)
            IK.axpy(self.r, -alpha, self.hp)
            IK.precondition(self.diag, self.r, self.z, self.pinned)
            rz_new = IK.dot(self.r, self.z)
            IK.xpay(self.p, rz_new / rz, self.z)
            rz = rz_new
            it += 1
        self.cg_iterations += it
        if it >= s.cg_max_iterations:
            self.unconverged += 1
        IK.axpy(self.x, 1.0, self.dx)
        return IK.max_norm(self.dx)

    def substep(self, h: float, collider, s0: float, s1: float) -> None:
        import time

        t = time.perf_counter()
        IK.inertial_guess(self.x, self.xn, self.v, self.pinned, h)
        self.xp.copy_from(self.xn)
        self._pins(s1)
        for _ in range(max(1, self.settings.iterations)):
            self.newton_iterations += 1
            if self._solve_newton_step(h) < self.settings.tolerance:
                break
        self.costs["implicit_solve"] += time.perf_counter() - t
        self._pins(s1)
        self._collide(collider, s0, s1, h)
        self._cloth_collisions(h)
        self._run(
            "integration",
            K.finish,
            self.x,
            self.xp,
            self.v,
            self.w,
            self.contact_n,
            self.contact_v,
            h,
        )
