"""Shaping (Eq. 3.1), cutting (lengths and variants) and sewing of the shipped templates."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from datagen.body.anny_model import NEUTRAL_SHAPE
from datagen.errors import InputError
from datagen.garment.cutting import CUT_RANGES, cut, sample_cuts
from datagen.garment.sewing import sew
from datagen.garment.shaping import (
    BLEND,
    SHAPING_RANGES,
    measure_widths,
    row_widths,
    sample_shaping,
    shape,
    target_widths,
    width_profile,
)
from datagen.garment.template import (
    BodyProximity,
    boundary_loops,
    check_mesh,
    check_sidecar,
    check_template,
    connected_pieces,
    edge_table,
    load_template,
)

TEMPLATES = Path(__file__).resolve().parents[1] / "templates"
PROPERTY = settings(
    deadline=None,
    max_examples=8,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
SHAPED = {"tshirt": ("sleeve_l", "sleeve_r"), "trousers": ("leg_l", "leg_r"), "skirt": ("skirt",)}


@functools.cache
def _templates() -> dict:
    # A cache, not a fixture: hypothesis would print a fixture's (huge) repr on failure.
    return {
        (g, n): load_template(TEMPLATES / g / f"{n}.obj")
        for g in ("female", "male")
        for n in ("tshirt", "top", "trousers", "skirt")
    }


@functools.cache
def _bodies() -> dict:
    from datagen.body.anny_model import default_body_model

    out = {}
    for g in ("female", "male"):
        rest = default_body_model().rest_body(g, NEUTRAL_SHAPE)
        out[g] = BodyProximity(rest.vertices, rest.faces)
    return out


@pytest.fixture(scope="module")
def tpl():
    return _templates()


@pytest.fixture(scope="module")
def bodies():
    return _bodies()


def _assert_one_manifold_piece(t):
    f = t.faces.astype(np.int64)
    _, counts, _ = edge_table(f)
    assert counts.max() <= 2
    assert len(np.unique(connected_pieces(t.n_vertices, f))) == 1


def _widths_between_rows(t, axis_name, kind):
    """Measured widths at midpoints between rows beyond the blend zone, and those x."""
    x = t.rows[axis_name].x
    mid = 0.5 * (x[1:] + x[:-1])
    mid = mid[mid > BLEND[kind] + 0.005]
    return mid, measure_widths(t, axis_name, mid)


# -- shaping -----------------------------------------------------------------------------------


@pytest.mark.parametrize("gender", ["female", "male"])
@pytest.mark.parametrize("name", ["tshirt", "trousers", "skirt"])
def test_sampled_shaping_follows_w(tpl, name, gender):
    """Cross-section widths of the shaped garment follow the sampled W(x) within 5 %."""
    t = tpl[(gender, name)]
    rng = np.random.default_rng(7)
    kind = {"tshirt": "sleeve", "trousers": "leg", "skirt": "skirt"}[name]
    for _ in range(3):
        params = sample_shaping(rng, t)
        assert set(params) == set(SHAPED[name])
        p = params[SHAPED[name][0]]
        if name == "skirt":
            assert p["a1"] > 0 and p["a2"] == 0
        else:
            assert p["a1"] < 0 < p["a2"]
        s = shape(t, params)
        for axis_name in SHAPED[name]:
            assert s.meta["shaping"][axis_name]["clamped_rows"] == []
            x, measured = _widths_between_rows(s, axis_name, kind)
            expected = width_profile(params[axis_name], x)
            np.testing.assert_array_less(np.abs(measured / expected - 1.0), 0.05)
        _assert_one_manifold_piece(s)


@PROPERTY
@given(
    name=st.sampled_from(["tshirt", "trousers", "skirt"]),
    gender=st.sampled_from(["female", "male"]),
    u=st.tuples(*[st.floats(0.0, 1.0) for _ in range(4)]),
)
def test_shaping_over_the_ranges(name, gender, u):
    """Anywhere in SHAPING_RANGES: the widths follow W(x), clamped only where a row would come
    within 7 mm of the body (or meet the other leg), the mesh stays valid and off the body."""
    t = _templates()[(gender, name)]
    r = SHAPING_RANGES[name]
    axis0 = SHAPED[name][0]
    kind = {"tshirt": "sleeve", "trousers": "leg", "skirt": "skirt"}[name]
    p = {
        "a1": r["a1"][0] + u[0] * (r["a1"][1] - r["a1"][0]),
        "a2": r["a2"][0] + u[1] * (r["a2"][1] - r["a2"][0]),
        "x_off": (r["x_off"][0] + u[2] * (r["x_off"][1] - r["x_off"][0])) * t.axes[axis0].length,
        "W0": (r["w0"][0] + u[3] * (r["w0"][1] - r["w0"][0])) * row_widths(t, axis0)[0],
    }
    params = {a: dict(p) for a in SHAPED[name]}
    s = shape(t, params)
    for axis_name in SHAPED[name]:
        target, clamped = target_widths(t, axis_name, p)
        rows = t.rows[axis_name]
        got = row_widths(s, axis_name)
        np.testing.assert_allclose(got, target, rtol=1e-9)
        free = (rows.x > BLEND[kind]) & ~clamped
        np.testing.assert_allclose(got[free], width_profile(p, rows.x[free]), rtol=0.05)
        assert s.meta["shaping"][axis_name]["clamped_rows"] == np.flatnonzero(clamped).tolist()
    problems = check_mesh("shaped.obj", s.vertices, s.faces, intersections=True)
    assert [q for q in problems if "mean edge" not in q] == []
    d = _bodies()[gender].signed_distance(s.vertices)
    assert d.min() >= 0.005


def test_shaping_rejects_bad_parameters(tpl):
    t = tpl[("female", "skirt")]
    with pytest.raises(InputError, match="a1 > a2 = 0"):
        shape(t, {"skirt": {"a1": -0.1, "a2": 0.0, "x_off": 0.0, "W0": 0.3}})
    with pytest.raises(InputError, match="shaping axes"):
        shape(t, {"sleeve_l": {"a1": -0.1, "a2": 0.1, "x_off": 0.1, "W0": 0.1}})
    tee = tpl[("female", "tshirt")]
    with pytest.raises(InputError, match="a1 <= 0 <= a2"):
        shape(tee, {"sleeve_l": {"a1": 0.1, "a2": 0.1, "x_off": 0.1, "W0": 0.15}})


# -- cutting -----------------------------------------------------------------------------------


def _end_position(t, axis_name):
    rows = t.rows[axis_name]
    return float(t.axes[axis_name].position(t.vertices[rows.vertices[-1]]).mean())


def _check_cut(t, c, lengths, variant):
    _assert_one_manifold_piece(c)
    assert check_sidecar("cut.json", c) == []
    for line, length in lengths.items():
        if line == "placket":
            continue
        axis = t.cut_lines[line]["axis"]
        # Within one edge length (in fact within half a row spacing: the nearest row is kept).
        assert abs(_end_position(c, axis) - length) <= 0.5 * t.resolution, (line, length)
        end = set(c.rows[axis].vertices[-1].tolist())
        if variant == "shirt" and axis == "torso":
            # An open shirt's hem runs from one front edge to the other.
            assert end == set(c.loops["hem"].tolist())
        else:
            # The end of the axis is a closed boundary loop of the cut garment.
            assert any(set(lp.tolist()) == end for lp in boundary_loops(c.faces))
    closed = [k for k in c.loops if k not in c.open_loops]
    for role in closed:
        loop = c.loops[role]
        assert len(loop) >= 3
    assert c.name == variant


@PROPERTY
@given(
    case=st.sampled_from(
        [
            ("tshirt", "tshirt"),
            ("tshirt", "shirt"),
            ("tshirt", "polo"),
            ("top", "top"),
            ("trousers", "trousers"),
            ("skirt", "skirt"),
        ]
    ),
    gender=st.sampled_from(["female", "male"]),
    u=st.floats(0.0, 1.0),
    v=st.floats(0.0, 1.0),
)
def test_cuts_over_the_ranges(case, gender, u, v):
    """Lengths anywhere in the cut ranges: whole rows go, the ends are closed loops within one
    edge length of the requested length, and the garment stays one manifold piece."""
    name, variant = case
    t = _templates()[(gender, name)]
    lengths = {}
    for line, c in t.cut_lines.items():
        frac = u if line.startswith(("sleeve", "leg", "skirt")) else v
        lo, hi = CUT_RANGES[variant].get(line.split("_")[0], (0.0, 1.0))
        lengths[line] = c["min"] + (lo + frac * (hi - lo)) * (c["max"] - c["min"])
    out = cut(t, lengths, variant)
    _check_cut(t, out, lengths, variant)
    assert [q for q in check_mesh("cut.obj", out.vertices, out.faces, t.resolution) if q] == []


@pytest.mark.parametrize("variant", ["tshirt", "shirt", "polo"])
def test_upper_variants(tpl, bodies, variant):
    t = tpl[("male", "tshirt")]
    rng = np.random.default_rng(3)
    lengths = sample_cuts(rng, t, variant)
    out = cut(t, lengths, variant)
    assert check_template(out, body=bodies["male"]) == []
    loops = boundary_loops(out.faces)
    if variant == "shirt":
        # Open front: neck, front edges and hem make one boundary loop; two front edges.
        assert len(loops) == 3  # the front opening and the two sleeve ends
        for side in ("front_edge_l", "front_edge_r"):
            edge = out.vertices[out.loops[side]]
            assert np.ptp(edge[:, 2]) > 0.3  # runs from the neck down to the hem
            assert np.all(np.abs(edge[:, 0]) < 0.01)
        gap = out.vertices[out.loops["front_edge_l"]][:, 0] - 0.0
        assert np.all(gap > 0)
    elif variant == "polo":
        assert len(loops) == 4
        placket = out.vertices[out.loops["placket_l"]]
        assert 0.08 < np.ptp(placket[:, 2]) < 0.2
    else:
        assert len(loops) == 4
    assert out.meta["cut"]["variant"] == variant


def test_cut_rejects_bad_requests(tpl):
    t = tpl[("female", "tshirt")]
    with pytest.raises(InputError, match="variant"):
        cut(t, {}, "skirt")
    with pytest.raises(InputError, match="lengths.sleeve_l"):
        cut(t, {"sleeve_l": 5.0}, "tshirt")
    with pytest.raises(InputError, match="cut lines"):
        cut(t, {"leg_l": 0.3}, "tshirt")


def test_sample_cuts_is_symmetric_and_in_range(tpl):
    rng = np.random.default_rng(0)
    for (_, name), t in tpl.items():
        for variant in {"tshirt": ("tshirt", "shirt", "polo")}.get(name, (name,)):
            lengths = sample_cuts(rng, t, variant)
            for line, length in lengths.items():
                if line == "placket":
                    continue
                c = t.cut_lines[line]
                assert c["min"] <= length <= c["max"]
            if "sleeve_l" in lengths:
                assert lengths["sleeve_l"] == lengths["sleeve_r"]
            if "leg_l" in lengths:
                assert lengths["leg_l"] == lengths["leg_r"]


# -- sewing ------------------------------------------------------------------------------------


@pytest.mark.parametrize("gender", ["female", "male"])
@pytest.mark.parametrize("kind,lower", [("jumpsuit", "trousers"), ("dress", "skirt")])
def test_sewing(tpl, bodies, gender, kind, lower):
    top, low = tpl[(gender, "top")], tpl[(gender, lower)]
    rng = np.random.default_rng(11)
    low = shape(low, sample_shaping(rng, low))
    low = cut(low, sample_cuts(rng, low, lower), lower)
    out = sew(top, low, kind)
    _assert_one_manifold_piece(out)
    assert out.name == kind and out.category == "full"
    assert check_template(out, body=bodies[gender]) == []
    assert "waist" not in out.loops and "neck" in out.loops
    # The lower garment's waistband survives as a closed seam path: the same vertices, now
    # interior (every edge of the ring has two faces), so the outfit can attach it to the body.
    seam = out.paths["waist"]
    np.testing.assert_allclose(
        np.sort(out.vertices[seam][:, 2]), np.sort(low.vertices[low.loops["waist"]][:, 2])
    )
    edges, counts, _ = edge_table(out.faces)
    ring = {tuple(sorted(p)) for p in zip(seam, np.roll(seam, -1), strict=True)}
    two_faced = {tuple(e) for e, c in zip(edges.tolist(), counts, strict=True) if c == 2}
    assert ring <= two_faced
    assert set(out.region_names) >= {"torso", "straps"}


def test_sewing_a_cropped_top_is_refused(tpl):
    top = tpl[("female", "top")]
    short = cut(top, {"torso": top.cut_lines["torso"]["min"]}, "top")
    with pytest.raises(InputError, match="sew before cutting"):
        sew(short, tpl[("female", "skirt")], "dress")
    with pytest.raises(InputError, match="jumpsuit"):
        sew(top, tpl[("female", "trousers")], "overall")
