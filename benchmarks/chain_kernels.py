"""Taichi kernel of benchmarks/study_coarse_correction.py: a Gauss-Seidel sweep over chains of
springs, each chain one coarse unknown (a study, not a product path).

A chain is a run of springs along a fibre, listed in path order and oriented along the path:
member k goes from vertex a_k to b_k = a_(k+1). One coarse update adds the same dmu to every
member's multiplier and moves the vertices by W J^T P dmu, so it is the exact (linearised)
solve of the substep's spring system restricted to that one direction: dmu = sum of the members'
XPBD residuals (each over 1 + gamma) over P^T (J W J^T + D) P. On a straight chain the interior
vertices' moves cancel and the chain acts as one long spring, which is what carries a load
along a fibre in one update instead of one spring per sweep.
"""

import numpy as np
import taichi as ti

from datagen.sim.kernel_common import F1, I1, I2, V3, vec3
from datagen.sim.kernels import sweep_order
from datagen.sim.precision import NP_REAL, REAL
from datagen.sim.solvers import _nd


def set_compliances(spring_set) -> tuple[ti.Ndarray, ti.Ndarray]:
    """A solver spring set's tension and compression compliances (1 / stiffness) as device
    arrays, in the set's order: the chain sweep's inputs (the product's sweeps read per-step
    terms instead, `solvers.spring_step_terms`)."""
    comp_t, comp_c = compliances_np(spring_set)
    return _nd(REAL, comp_t.astype(NP_REAL)), _nd(REAL, comp_c.astype(NP_REAL))


def compliances_np(spring_set) -> tuple[np.ndarray, np.ndarray]:
    """The same compliances as float64 numpy arrays."""
    return 1.0 / spring_set.model_arrays["k_t"], 1.0 / spring_set.model_arrays["k_c"]


@ti.func
def spring_alpha_gamma(e: ti.i32, c: REAL, comp_t: F1, comp_c: F1, beta: F1,
                       inv_h: REAL) -> ti.types.vector(2, REAL):
    """Spring e's XPBD compliance over h^2 (its tension or compression compliance, as its
    constraint c is positive or negative) and its damping over h."""
    alpha = comp_t[e]
    if c < 0.0:
        alpha = comp_c[e]
    return ti.types.vector(2, REAL)(alpha * inv_h * inv_h, beta[e] * inv_h)


@ti.kernel
def chains_gauss_seidel(
    x: V3,
    xp: V3,
    w: F1,
    springs: I2,
    rest: F1,
    comp_t: F1,
    comp_c: F1,
    beta: F1,
    lam: F1,
    ptr: I1,
    members: I1,
    flip: I1,
    dirs: V3,
    h: REAL,
    reverse: ti.i32,
    omega: REAL,
):
    """One sweep over the chains of one spring set (members: spring ids in path order, flip:
    1 where the spring's stored order runs against the path; dirs: scratch, one per spring)."""
    n_chains = ptr.shape[0] - 1
    inv_h = 1.0 / h
    ti.loop_config(serialize=True)
    for q in range(n_chains):
        c_id = sweep_order(q, n_chains, reverse)
        total = 0.0
        diag = 0.0
        prev = vec3(0.0)
        first = ptr[c_id]
        last = ptr[c_id + 1]
        for k in range(first, last):
            e = members[k]
            a = springs[e][flip[k]]
            b = springs[e][1 - flip[k]]
            d = x[b] - x[a]
            length = d.norm()
            n = vec3(0.0)
            if length > 1e-9:
                n = d / length
            dirs[e] = n
            c = length - rest[e]
            ag = spring_alpha_gamma(e, c, comp_t, comp_c, beta, inv_h)
            alpha, gamma = ag[0], ag[1]
            if w[a] + w[b] > 0.0:
                rate = n.dot((x[b] - xp[b]) - (x[a] - xp[a]))
                total += (-c - alpha * lam[e] - gamma * rate) / (1.0 + gamma)
            diag += alpha / (1.0 + gamma)
            # J^T P at a_k: the outward direction of member k there, less member k-1's inward.
            g = prev - n
            diag += w[a] * g.norm_sqr()
            prev = n
        e_last = members[last - 1]
        b_last = springs[e_last][1 - flip[last - 1]]
        diag += w[b_last] * prev.norm_sqr()
        if diag > 0.0:
            dmu = omega * total / diag
            for k in range(first, last):
                e = members[k]
                a = springs[e][flip[k]]
                b = springs[e][1 - flip[k]]
                lam[e] += dmu
                x[a] -= w[a] * dmu * dirs[e]
                x[b] += w[b] * dmu * dirs[e]
