"""`make bench`: every benchmark in turn; each writes its own section of docs/benchmarks.md.

`--quick` leaves out the long ones (the full hard cases and the dataset runs; the accuracy study
is its own command, `datagen bench accuracy`). `bench_gpu` is not among them: it runs on a machine
with a GPU (its docstring says how)."""

from __future__ import annotations

import argparse
import importlib
import time

BENCHMARKS = [
    ("bench_body", False),
    ("bench_outfits", False),
    ("bench_sim", False),
    ("bench_sweep_floor", False),
    ("bench_hard_cases", True),
    ("bench_dataset", True),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="skip the long benchmarks")
    parser.add_argument("names", nargs="*", help="run only these (e.g. bench_sim)")
    args = parser.parse_args()
    for name, long in BENCHMARKS:
        if args.names and name not in args.names:
            continue
        if args.quick and long:
            print(f"-- {name}: skipped (--quick)")
            continue
        print(f"-- {name}", flush=True)
        t = time.perf_counter()
        importlib.import_module(f"benchmarks.{name}").main([])
        print(f"-- {name}: {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
