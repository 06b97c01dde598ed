"""Taichi start-up, once per process.

On this project's 2-core CPUs a dataset run uses one single-threaded simulation per worker
process (one serial launch per frame); one-off runs may use more threads. The same kernels run on
a GPU backend (`DATAGEN_TI_ARCH=cuda`) and on more than one CPU thread (`DATAGEN_TI_THREADS`),
where `serial()` is False and constraint sweeps switch to coloured Gauss-Seidel: one parallel
loop per colour of constraints that share no vertex. `DATAGEN_TI_PROFILER=1` turns on Taichi's
kernel profiler (ti.profiler), which times every kernel on the device.

Kernels compile with fast math (LLVM may fuse a multiply and an add into one rounding, FMA),
and where it fuses depends on how the compiler sees the whole kernel: the fused frame kernel
and the per-effect kernels that compute the same steps part by a few float32 steps, which a
chaotic scene then grows like any rounding (the 5k tube on its swinging cylinder: 0.3 um at
frame 2, 19 um at frame 4). `DATAGEN_TI_IEEE=1` compiles without fast math, where each
operation rounds on its own and two code paths that compute the same operations in the same
order agree to the last bit: the tests compare the paths that way (tests/conftest.py,
`in_ieee_process`). It costs a walking frame about 4-6 %, so it is not the default.
"""

from __future__ import annotations

import os

_STATE: dict = {}
IEEE_ENV = "DATAGEN_TI_IEEE"


def _flag(name: str) -> bool:
    """An environment switch: set to anything but "" or "0"."""
    return os.environ.get(name, "0") not in ("", "0")


def ieee() -> bool:
    """True when this process compiles its kernels without fast math (IEEE_ENV)."""
    return _flag(IEEE_ENV)


def init_taichi(arch: str | None = None, threads: int | None = None) -> None:
    """Initialise Taichi if it is not yet (later calls are no-ops)."""
    if _STATE.get("ready"):
        return
    import taichi as ti

    from datagen.sim.precision import REAL

    arch = arch or os.environ.get("DATAGEN_TI_ARCH", "cpu")
    if threads is None:
        threads = int(os.environ.get("DATAGEN_TI_THREADS", "1"))
    kwargs = dict(
        offline_cache=True,
        fast_math=not ieee(),
        log_level=ti.ERROR,
        default_fp=REAL,
        random_seed=0,
        kernel_profiler=_flag("DATAGEN_TI_PROFILER"),
    )
    if arch == "cpu":
        # Taichi's control-flow-graph pass (store forwarding and dead stores over the whole
        # kernel) costs far more than it gives on the one-launch frame kernels, whose every
        # substep, effect and search is one function: off, the walking t-shirt's frame kernel
        # compiled in 2-3 s instead of 16-20 s and ran as fast (paired runs, medians of the
        # ratio 0.97-1.02; docs/simulator.md, "Compile time"). LLVM still optimises the
        # result. Not measured on a GPU, so left as it was there.
        ti.init(arch=ti.cpu, cpu_max_num_threads=max(1, threads), cfg_optimization=False,
                **kwargs)
    else:
        ti.init(arch=getattr(ti, arch), **kwargs)
    _STATE.update(ready=True, arch=arch, threads=threads)


def serial() -> bool:
    """True when constraint sweeps run as exact Gauss-Seidel (CPU, one thread)."""
    init_taichi()
    return _STATE["arch"] == "cpu" and _STATE["threads"] == 1


def arch() -> str:
    init_taichi()
    return _STATE["arch"]
