"""Floating-point precision of the simulator, fixed once per process.

Float32 in production (memory traffic dominates the cost); float64 for converged reference runs,
where float32 round-off at tiny time steps would masquerade as discretisation error. Set
`DATAGEN_SIM_FP64=1` before the simulator is imported (the accuracy study starts its reference
runs in such processes).
"""

import os

import numpy as np
import taichi as ti

FP64 = os.environ.get("DATAGEN_SIM_FP64", "0") not in ("", "0", "false", "False")
REAL = ti.f64 if FP64 else ti.f32
NP_REAL = np.float64 if FP64 else np.float32
VEC3 = ti.types.vector(3, REAL)
VEC4 = ti.types.vector(4, REAL)
MAT3 = ti.types.matrix(3, 3, REAL)
