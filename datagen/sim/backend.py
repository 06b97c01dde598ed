"""Taichi start-up, once per process.

On this project's 2-core CPUs a dataset run uses one single-threaded simulation per worker
process (one serial launch per frame); one-off runs may use more threads. The same kernels run on
a GPU backend (`DATAGEN_TI_ARCH=cuda`) and on more than one CPU thread (`DATAGEN_TI_THREADS`),
where `serial()` is False and constraint sweeps switch to coloured Gauss-Seidel: one parallel
loop per colour of constraints that share no vertex. `DATAGEN_TI_PROFILER=1` turns on Taichi's
kernel profiler (ti.profiler), which times every kernel on the device.
"""

from __future__ import annotations

import os

_STATE: dict = {}


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
        log_level=ti.ERROR,
        default_fp=REAL,
        random_seed=0,
        kernel_profiler=os.environ.get("DATAGEN_TI_PROFILER", "0") not in ("", "0"),
    )
    if arch == "cpu":
        ti.init(arch=ti.cpu, cpu_max_num_threads=max(1, threads), **kwargs)
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
