"""The simulator's hard cases (pipelines/hard_cases.yaml), short versions, at default settings.

Every case must end finite, with no more than 1 % of vertices deeper than the thickness in any
frame and a bounded kinetic energy, or be rejected for the reason the case expects. The strain
criterion (at most 0.1 % of fabric edges beyond the fabric's bound) holds as well.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datagen.errors import InputError
from datagen.pipeline.hard_cases import (
    DEEP_SHARE_MAX,
    KINETIC_PER_KG_MAX,
    STRAIN_SHARE_MAX,
    load_hard_cases,
    run_case,
)

REPO = Path(__file__).resolve().parents[1]

CASES_FILE = REPO / "pipelines" / "hard_cases.yaml"
CASES = load_hard_cases(CASES_FILE)
# Every short case now meets the strain criterion too (at most 0.1 % of fabric edges past the
# bound). Until 2026-11-23 the denim t-shirt (0.101 %) and the heavy body at its tightest fit
# (0.2-1.6 %) did not: contact friction put edges back past the strain limit where the skin
# stretched under them; the strain limit now has the last word over friction
# (kernels.limit_after_contact_one). The full versions' figures are in docs/benchmarks.md.


@pytest.mark.parametrize("case", CASES.cases, ids=[c.name for c in CASES.cases])
def test_hard_case(case, body_model):
    result = run_case(case, CASES, body_model, CASES_FILE.parent, short=True)
    if case.expect == "rejected":
        assert result.passed, result.detail
        assert result.status == "rejected"
        return
    assert result.status == "ok", result.detail
    assert np.isfinite(result.strain_p999_max), result.detail
    assert result.deep_share_max <= DEEP_SHARE_MAX, result.detail
    assert result.kinetic_per_kg_max <= KINETIC_PER_KG_MAX, result.detail
    assert result.strain_share_max <= STRAIN_SHARE_MAX, result.detail
    assert result.passed, result.detail


def test_every_issue_case_is_in_the_file():
    names = {c.name for c in CASES.cases}
    required = {"leather_trousers", "denim_tshirt", "long_skirt_spin", "jump_landing",
                "fast_kick", "heavy_body_tightest_fit", "thin_tall_body_tightest_fit",
                "starts_inside_body", "tshirt_over_trousers", "degenerate_template",
                "thirty_seconds", "root_teleport"}
    assert required <= names
    assert sum(c.motion.source == "bvh" for c in CASES.cases) >= 4  # the CMU jump clips


def test_bad_case_file_names_the_field(tmp_path):
    bad = tmp_path / "cases.yaml"
    bad.write_text("cases:\n  - name: x\n    why: y\n    garments: [{template: tshirt}]\n"
                   "    expect: maybe\n")
    with pytest.raises(InputError, match=r"cases\[0\]\.expect"):
        load_hard_cases(bad)
