"""The simulator's hard cases (pipelines/hard_cases.yaml), short versions, at default settings.

Every case must end finite, with no more than 1 % of any garment's vertices deeper than the
thickness in any frame and a bounded kinetic energy, or be rejected for the reason the case
expects. The strain criterion (at most 0.1 % of a garment's fabric edges beyond the fabric's
bound) holds as well.
"""

from __future__ import annotations

from dataclasses import replace
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
    bad.write_text("cases:\n  - name: x\n    why: y\n    garments: [{template: tshirt}]\n"
                   "    motion: {lead_in: 0}\n")
    with pytest.raises(InputError, match=r"cases\[0\]\.motion\.lead_in.*1 or more frames"):
        load_hard_cases(bad)
    bad.write_text("cases:\n  - name: x\n    why: y\n    garments: [{template: tshirt}]\n"
                   "    wind: [15.0, .nan, 0.0]\n")
    with pytest.raises(InputError, match=r"cases\[0\]\.wind': expected a list of float or null, "
                                         r"got \[15.0, nan, 0.0\]"):
        load_hard_cases(bad)


def test_buried_share_sees_cloth_inside_a_part_that_passes_through_another():
    """Two closed boxes that overlap, as a flexed thigh and the lower torso do: a point inside
    box A, 5 cm from box B's face (on its outer side), is 45 cm inside A. Its nearest triangle is
    B's and says outside (the simulator's deep_share before it read the volume too);
    qa.buried_share says inside."""
    import igl
    import trimesh

    from datagen.qa import buried_share

    a = trimesh.creation.box(bounds=[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    b = trimesh.creation.box(bounds=[[0.5, 0.0, 0.0], [1.5, 1.0, 1.0]])
    body = np.concatenate([a.vertices, b.vertices])
    faces = np.concatenate([a.faces, b.faces + len(a.vertices)])
    points = np.array([
        [0.45, 0.5, 0.5],  # inside A, 5 cm outside B's face: buried
        [0.495, 0.5, 0.5],  # inside A, within the thickness of B's face: not
        [2.0, 0.5, 0.5],  # outside both
        [1.2, 0.5, 0.5],  # inside B, 20 cm outside A's face (its nearest): buried
    ])
    thickness = np.full(len(points), 0.01)
    nearest_sign, *_ = igl.signed_distance(points, body, faces.astype(np.int64),
                                          sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    assert nearest_sign[0] > 0  # the blind spot: read as outside by its nearest triangle
    per_point = [buried_share(points[None, [k]], thickness[[k]], body[None], faces)[0]
                 for k in range(len(points))]
    assert per_point == [1.0, 0.0, 0.0, 1.0]
    # (F, V, 3) over frames: the box moves away in the second frame, nothing is inside it then
    frames = np.stack([points, points])
    moved = np.stack([body, body + [0.0, 0.0, 10.0]])
    assert buried_share(frames, thickness, moved, faces).tolist() == [0.5, 0.0]
    # Per garment, the one with the most: the first point alone (all of it buried) and the
    # other three (a third), where all four together read a half.
    assert buried_share(frames, thickness, moved, faces, [(0, 1), (1, 4)]).tolist() == [1.0, 0.0]
    assert buried_share(frames, thickness, moved, faces, [(0, 2), (2, 4)]).tolist() == [0.5, 0.0]
    with pytest.raises(ValueError, match="matching frames"):
        buried_share(frames, thickness[:2], moved, faces)
    with pytest.raises(ValueError, match="within the cloth's 4 vertices"):
        buried_share(frames, thickness, moved, faces, [(0, 2), (2, 5)])


def test_heavy_walk_keeps_each_trouser_leg_out_of_the_other_thigh(body_model):
    """The heaviest body's thighs pass 1-2 cm apart as it walks. Its first 40 frames at the
    full lead-in (the short version's lead-in puts the pass elsewhere), judged as the full
    case is: at frames 36-40 the right thigh went through 150 vertices of the denim trousers
    (1.11 % of them, up to 31 mm deep, frame 39) while they tracked the left thigh. The frame's
    full search had measured how far the facing right thigh was at the frame's end only, 4-5
    cm further on, found it out of reach and left them unguarded until the next full search;
    now it takes the nearer of the frame's start and end (search_kernels.other_surface)."""
    case = next(c for c in CASES.cases if c.name == "heavy_body_tightest_fit")
    case = replace(case, motion=replace(case.motion, frames=40))
    result = run_case(case, CASES, body_model, CASES_FILE.parent, short=False)
    assert result.status == "ok", result.detail
    assert result.buried_share_max <= DEEP_SHARE_MAX, result.detail
    assert result.deep_share_max <= DEEP_SHARE_MAX, result.detail
    assert result.strain_share_max <= STRAIN_SHARE_MAX, result.detail
