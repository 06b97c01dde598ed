"""Which CPU measured a result: a label for benchmark pages and study parts.

A study part's errors depend on the CPU as well as on the simulator: Taichi's LLVM compiles
for the host's instruction set, so two CPUs can round a float32 trajectory differently, and a
chaotic scene's predictable horizon moves with that (the walking cotton t-shirt's was 21 frames
on one machine and 17 on another). The label names the processor and a digest of its feature
flags, which is what the compiled code depends on; two machines with one label compile the same
code. Its times are the machine's too, so parts measured on different machines are set against
their peer only within their own run.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")


def _first_cpu(text: str) -> dict[str, str]:
    """The fields of /proc/cpuinfo's first processor block."""
    fields: dict[str, str] = {}
    for line in text.split("\n\n", 1)[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_label(cpuinfo: str | None = None) -> str:
    """The processor as "name (family F, model M, stepping S, flags DIGEST)" from Linux's
    /proc/cpuinfo (`cpuinfo` its text, read when None); elsewhere what `platform` knows."""
    if cpuinfo is None:
        cpuinfo = CPUINFO.read_text() if CPUINFO.exists() else ""
    cpu = _first_cpu(cpuinfo)
    name = cpu.get("model name") or cpu.get("Processor") or platform.processor() or "unknown CPU"
    details = [f"{key.split()[-1]} {cpu[key]}" for key in ("cpu family", "model", "stepping")
               if key in cpu]
    flags = cpu.get("flags") or cpu.get("Features")
    if flags:  # sorted: the kernel's order is not the hardware's
        digest = hashlib.sha256(" ".join(sorted(flags.split())).encode()).hexdigest()[:8]
        details.append(f"flags {digest}")
    return f"{name} ({', '.join(details)})" if details else name


@functools.cache
def this_machine() -> str:
    """This machine: architecture, processor, cores (what a benchmark page names)."""
    return f"{platform.machine()}, {cpu_label()}, {os.cpu_count()} cores"
