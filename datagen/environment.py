"""Where a sequence was made: the machine and the versions of what computed it.

The same seed gives the same scene spec everywhere, and the same data on the same machine and
software. Across CPUs and library versions float rounding differs (torch's kernels in the body
model, the LLVM code Taichi generates), and a chaotic frame amplifies it: the full fast kick
(docs/simulator.md, "Escalation") took another path on another machine from the same sources.
So each sequence records the environment of the worker that made it (a cluster's nodes can
differ), and a result that does not reproduce can be traced to what changed.
"""

from __future__ import annotations

import functools
import os
import platform
from importlib.metadata import PackageNotFoundError, version

# The packages whose arithmetic reaches the data (body model, geometry, solver, storage).
PACKAGES = ("datagen", "anny", "torch", "taichi", "numpy", "scipy", "trimesh", "libigl", "h5py")


def _cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what the platform module says."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _package_version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=1)
def environment() -> dict[str, object]:
    """This process's machine and package versions (JSON-ready; None for a package that is not
    installed). Cached: it does not change while a worker runs."""
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "packages": {name: _package_version(name) for name in PACKAGES},
    }
