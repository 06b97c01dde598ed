"""Shared helpers: timing, and writing a benchmark's section of docs/benchmarks.md."""

from __future__ import annotations

import platform
import re
import statistics
import time
from collections.abc import Callable
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "docs" / "benchmarks.md"
HEADER = """# Benchmarks

Each section is written by the benchmark named in it (`make bench` runs them all). Times are
wall-clock on the machine named in the section; where a target is a speed, the section also
reports the ratio to a peer measured in the same run, because these machines are shared and
noisy.
"""


def timed(fn: Callable, repeat: int = 3) -> tuple[float, object]:
    """Median wall time of `repeat` calls, and the last result."""
    times, result = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


def machine() -> str:
    """The machine a section names: its processor (datagen.study.machine) and Python."""
    from datagen.study.machine import this_machine

    return f"{this_machine()}, Python {platform.python_version()}"


def write_section(name: str, title: str, body: str, command: str) -> None:
    """Replace (or append) the section `name` of docs/benchmarks.md."""
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    text = REPORT.read_text() if REPORT.exists() else HEADER
    start, end = f"<!-- bench:{name}:start -->", f"<!-- bench:{name}:end -->"
    section = (
        f"{start}\n## {title}\n\n"
        f"Command: `{command}` ({date.today().isoformat()}, {machine()})\n\n"
        f"{body.strip()}\n{end}"
    )
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: section, text)
    else:
        text = text.rstrip() + "\n\n" + section + "\n"
    REPORT.write_text(text)
    print(section)
