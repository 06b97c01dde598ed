"""Hard cases of the simulator, full versions (pipelines/hard_cases.yaml), at the default
settings: each case's verdict and QA figures go to docs/benchmarks.md.

The tests run the short versions of the same cases (tests/test_hard_cases.py); this runs the
whole motions, including the 30-second sequence and the CMU jump clips.
"""

from __future__ import annotations

import argparse
import os
import time

from benchmarks.common import REPO, write_section
from datagen.pipeline.hard_cases import (
    DEEP_SHARE_MAX,
    KINETIC_PER_KG_MAX,
    STRAIN_SHARE_MAX,
    load_hard_cases,
    results_markdown,
    run_case,
)

COMMAND = "python -m benchmarks.bench_hard_cases"
CASES = REPO / "pipelines" / "hard_cases.yaml"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", nargs="*", default=None, help="case names to run")
    args = parser.parse_args(argv)
    os.environ.setdefault("PYTHONWARNINGS", "ignore")
    from datagen.body.anny_model import default_body_model

    cases = load_hard_cases(CASES)
    model = default_body_model()
    results, t0 = [], time.perf_counter()
    for case in cases.cases:
        if args.only and case.name not in args.only:
            continue
        result = run_case(case, cases, model, CASES.parent, short=False)
        print(f"{case.name}: {'pass' if result.passed else 'FAIL'} - {result.detail} "
              f"({result.wall_s:.0f} s)", flush=True)
        results.append(result)
    passed = sum(r.passed for r in results)
    body = (
        f"Full versions of the {len(results)} cases in `pipelines/hard_cases.yaml`, each through "
        "the real pipeline at the default settings (xpbd, quality `default`; a run that breaks "
        "a bound is simulated again at finer steps, as in a dataset run: docs/simulator.md, "
        "\"Escalation\"). A case passes when "
        f"it ends finite with at most {100 * STRAIN_SHARE_MAX:.1f} % of each garment's fabric "
        f"edges beyond the fabric's strain bound and at most {100 * DEEP_SHARE_MAX:.0f} % of "
        "each garment's vertices deeper than the thickness in every output frame (the columns "
        "give the garment with the most), by the simulator's deep_share (inside the body's "
        "volume by its ray count, deep by the distance to the nearest colliding triangle; "
        "before 2026-12-07 signed by that triangle alone) and by libigl's reading of the "
        "body's volume, the union of its parts, with distances to every triangle "
        "(`qa.buried_share`, the column \"too deep in the body's volume\"), and kinetic energy "
        "under "
        f"{KINETIC_PER_KG_MAX:.0f} "
        "J/kg of cloth; or, where it expects a rejection, when it is rejected for the stated "
        "reason.\n\n"
        f"{passed} of {len(results)} pass ({(time.perf_counter() - t0) / 60:.1f} min in all).\n\n"
        + results_markdown(results)
    )
    if not args.only:
        write_section("hard_cases", "Simulator hard cases (full versions)", body, COMMAND)
    else:
        print(body)


if __name__ == "__main__":
    main()
