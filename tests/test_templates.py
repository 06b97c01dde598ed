"""Garment templates: the shipped ones keep their guarantees, files round-trip, bad ones are
reported precisely (docs/templates.md)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from datagen.body.anny_model import NEUTRAL_SHAPE
from datagen.errors import InputError
from datagen.garment.build import SHIPPED_RESOLUTION
from datagen.garment.template import (
    MIN_ANGLE,
    BodyProximity,
    boundary_loops,
    check_template,
    connected_pieces,
    edge_table,
    load_template,
    read_obj,
    save_template,
    to_garment,
    triangle_angles,
    write_obj,
)

REPO = Path(__file__).resolve().parents[1]
TEMPLATES = REPO / "templates"
NAMES = ("tshirt", "top", "trousers", "skirt")
GENDERS = ("female", "male")
SHIPPED = [(g, n) for g in GENDERS for n in NAMES]


@pytest.fixture(scope="module")
def rest_bodies(body_model):
    return {g: body_model.rest_body(g, NEUTRAL_SHAPE) for g in GENDERS}


@pytest.fixture(scope="module")
def proximity(rest_bodies):
    return {g: BodyProximity(r.vertices, r.faces) for g, r in rest_bodies.items()}


@pytest.fixture(scope="module")
def shipped():
    return {(g, n): load_template(TEMPLATES / g / f"{n}.obj") for g, n in SHIPPED}


@pytest.mark.parametrize("gender,name", SHIPPED)
def test_shipped_template_passes_check(gender, name, proximity):
    problems = check_template(TEMPLATES / gender / f"{name}.obj", body=proximity[gender])
    assert problems == []


@pytest.mark.parametrize("gender,name", SHIPPED)
def test_shipped_template_guarantees(gender, name, shipped, proximity):
    t = shipped[(gender, name)]
    v, f = t.vertices, t.faces.astype(np.int64)
    edges, counts, _ = edge_table(f)
    assert counts.max() <= 2, "edge-manifold"
    assert len(np.unique(connected_pieces(len(v), f))) == 1, "one piece"
    assert triangle_angles(v, f).min() >= MIN_ANGLE
    lengths = np.linalg.norm(v[edges[:, 1]] - v[edges[:, 0]], axis=1)
    assert abs(lengths.mean() - SHIPPED_RESOLUTION) <= 0.3 * SHIPPED_RESOLUTION
    assert t.resolution == pytest.approx(SHIPPED_RESOLUTION)
    body = proximity[gender]
    clearance = np.concatenate([body.signed_distance(v), body.signed_distance(v[f].mean(axis=1))])
    assert clearance.min() >= 0.005
    # Not a shrink-wrapped copy of the body: on average the cloth stands well off it.
    assert np.median(clearance) > 0.012
    # Sidecar essentials.
    assert t.category == ("upper" if name in ("tshirt", "top") else "lower")
    assert t.gender == gender
    assert t.body["model"] == "anny" and t.body["gender"] == gender
    assert t.uv is not None and t.uv.shape == (len(v), 2)
    assert t.panel is not None and len(t.panel) == len(v)
    assert len(t.regions) == len(v)


@pytest.mark.parametrize("gender,name", SHIPPED)
def test_rows_are_planar_and_perpendicular(gender, name, shipped):
    """Rows of vertices lie in planes perpendicular to their axis (beyond the few rows where
    trouser legs turn from the horizontal crotch seam to the leg's direction), so a length cut
    removes whole rows and leaves a clean loop."""
    t = shipped[(gender, name)]
    for axis_name, rows in t.rows.items():
        axis = t.axes[axis_name]
        assert np.all(np.diff(rows.x) > 0)
        for x, ids in zip(rows.x, rows.vertices, strict=True):
            pos = axis.position(t.vertices[ids])
            if axis_name.startswith("leg_") and x < 0.08:
                assert np.ptp(pos) < 0.03
                continue
            assert np.abs(pos - x).max() < 1e-3, (axis_name, x)
        # The end row is the boundary loop at the axis's end.
        end = set(rows.vertices[-1].tolist())
        assert any(set(loop.tolist()) == end for loop in boundary_loops(t.faces))


def _section_girth(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points[:, :2]).area)


def test_fit_is_believable(shipped, rest_bodies):
    """Ease like real clothes: a tee a few cm looser than the chest, trousers not skin-tight,
    a long skirt flaring out from the hips."""
    for gender in GENDERS:
        body = rest_bodies[gender].vertices
        tee = shipped[(gender, "tshirt")]
        # Chest: the torso row with the largest girth (the bust), against the body there.
        rows = tee.rows["torso"]
        girths = [_section_girth(tee.vertices[ids]) for ids in rows.vertices]
        k = int(np.argmax(girths))
        z = tee.vertices[rows.vertices[k]][:, 2].mean()
        chest = body[(np.abs(body[:, 2] - z) < 0.01) & (np.abs(body[:, 0]) < 0.25)]
        ease = girths[k] - _section_girth(chest)
        assert 0.08 < ease < 0.30, ease
        trousers = shipped[(gender, "trousers")]
        legs = trousers.rows["leg_l"]
        mid = len(legs.x) // 3  # mid-thigh
        ids = legs.vertices[mid]
        leg_z = trousers.vertices[ids][:, 2].mean()
        thigh = body[(np.abs(body[:, 2] - leg_z) < 0.01) & (body[:, 0] > 0.01)]
        leg_ease = _section_girth(trousers.vertices[ids]) - _section_girth(thigh)
        assert 0.06 < leg_ease < 0.30, leg_ease
        skirt = shipped[(gender, "skirt")]
        srows = skirt.rows["skirt"]
        hip = max(
            _section_girth(skirt.vertices[ids]) for ids in srows.vertices[: len(srows.x) // 3]
        )
        hem = _section_girth(skirt.vertices[srows.vertices[-1]])
        assert hem > 1.3 * hip


def test_loops_and_cut_lines_of_shipped_templates(shipped):
    roles = {
        "tshirt": {"neck", "hem", "sleeve_l_end", "sleeve_r_end"},
        "top": {"neck", "hem", "armhole_l", "armhole_r"},
        "trousers": {"waist", "leg_l_end", "leg_r_end"},
        "skirt": {"waist", "hem"},
    }
    axes = {
        "tshirt": {"torso", "sleeve_l", "sleeve_r"},
        "top": {"torso"},
        "trousers": {"leg_l", "leg_r"},
        "skirt": {"skirt"},
    }
    for (_, name), t in shipped.items():
        assert set(t.loops) == roles[name]
        assert set(t.axes) == axes[name]
        assert set(t.cut_lines) == axes[name]
        for line in t.cut_lines.values():
            assert 0 <= line["min"] < line["max"] <= t.axes[line["axis"]].length + 1e-9
        for axis in t.axes.values():
            assert np.linalg.norm(axis.direction) == pytest.approx(1.0)
            assert axis.region in t.region_names
    # Left and right are mirror images.
    t = shipped[("female", "tshirt")]
    assert t.axes["sleeve_l"].length == pytest.approx(t.axes["sleeve_r"].length)
    mirrored = t.vertices * [-1.0, 1.0, 1.0]
    from scipy.spatial import cKDTree

    assert cKDTree(t.vertices).query(mirrored)[0].max() < 1e-6


def test_save_load_round_trip(shipped, tmp_path):
    t = shipped[("female", "top")]
    obj, js = save_template(t, tmp_path / "copy")
    u = load_template(js)
    assert obj.exists() and js.exists()
    np.testing.assert_allclose(u.vertices, t.vertices, atol=1e-6)
    np.testing.assert_array_equal(u.faces, t.faces)
    assert set(u.loops) == set(t.loops)
    for k in t.loops:
        np.testing.assert_array_equal(u.loops[k], t.loops[k])
    np.testing.assert_array_equal(u.regions, t.regions)
    assert u.region_names == t.region_names
    np.testing.assert_allclose(u.uv, t.uv, atol=1e-5)
    assert u.axes["torso"].length == pytest.approx(t.axes["torso"].length, abs=1e-6)
    assert len(u.rows["torso"].vertices) == len(t.rows["torso"].vertices)
    data = json.loads(js.read_text())
    assert data["format"] == "datagen-garment-template" and data["version"] == 1
    assert data["units"] == "m"


def test_to_garment(shipped):
    t = shipped[("male", "trousers")]
    g = to_garment(t, "denim")
    assert g.name == "trousers" and g.category == "trousers" and g.fabric == "denim"
    assert g.vertices.shape == t.vertices.shape and g.faces.dtype == np.int32
    assert g.region_names == ("hips", "leg_l", "leg_r")
    assert set(g.loops) == {"waist", "leg_l_end", "leg_r_end"}
    assert g.uv.shape == (t.n_vertices, 2)


# -- broken templates --------------------------------------------------------------------------


def _copy(src: Path, dst_dir: Path, stem: str = "tshirt") -> tuple[Path, Path]:
    obj, js = dst_dir / f"{stem}.obj", dst_dir / f"{stem}.json"
    shutil.copy(src.with_suffix(".obj"), obj)
    shutil.copy(src.with_suffix(".json"), js)
    return obj, js


def test_non_manifold_edges_are_reported(shipped, tmp_path):
    t = shipped[("female", "top")]
    f = t.faces.astype(np.int64)
    a, b = f[100, 0], f[100, 1]  # an interior edge: two faces already
    v = np.vstack([t.vertices, t.vertices[[a, b]].mean(axis=0) + [0, 0, 0.01]])
    faces = np.vstack([f, [[a, b, len(v) - 1]]])
    write_obj(tmp_path / "top.obj", v, faces)
    data = json.loads((TEMPLATES / "female" / "top.json").read_text())
    data["vertex_count"] = len(v)
    data["regions"]["labels"].append(0)
    (tmp_path / "top.json").write_text(json.dumps(data))
    problems = check_template(tmp_path / "top.obj")
    lo, hi = sorted((int(a), int(b)))
    assert any(
        p.startswith("top.obj: 1 non-manifold edges") and f"vertices {lo}-{hi}" in p
        for p in problems
    ), problems


def test_sidecar_naming_missing_vertex_or_loop(tmp_path):
    obj, js = _copy(TEMPLATES / "female" / "tshirt", tmp_path)
    data = json.loads(js.read_text())
    n = data["vertex_count"]
    data["loops"]["sleeve_l_end"][3] = 99999
    del data["loops"]["neck"]
    js.write_text(json.dumps(data))
    problems = check_template(obj)
    assert f"tshirt.json: loops.sleeve_l_end names vertex 99999, the mesh has {n} vertices" in (
        problems
    ), problems
    assert any(p.startswith("tshirt.json: loops has no 'neck'") for p in problems), problems


def test_loop_not_on_the_boundary_and_wrong_regions(shipped, tmp_path):
    obj, js = _copy(TEMPLATES / "female" / "tshirt", tmp_path)
    data = json.loads(js.read_text())
    t = shipped[("female", "tshirt")]
    data["loops"]["hem"] = t.rows["torso"].vertices[10].tolist()  # an interior row
    data["regions"]["labels"] = data["regions"]["labels"][:-5]
    js.write_text(json.dumps(data))
    problems = check_template(obj)
    assert any("loops.hem is not on the boundary" in p for p in problems), problems
    assert any(
        f"regions.labels has {t.n_vertices - 5} entries, the mesh has {t.n_vertices}" in p
        for p in problems
    ), problems


def test_centimetres_are_reported(shipped, tmp_path):
    t = shipped[("female", "skirt")]
    write_obj(tmp_path / "skirt.obj", t.vertices * 100.0, t.faces)
    shutil.copy(TEMPLATES / "female" / "skirt.json", tmp_path / "skirt.json")
    problems = check_template(tmp_path / "skirt.obj")
    assert any(
        p.startswith("skirt.obj: bounding box") and "looks like centimetres" in p for p in problems
    ), problems


def _strip(centre: np.ndarray, width: float = 0.2, n_across: int = 8):
    """A triangulated strip of the given centre line (K, 3), `width` wide along y."""
    k = len(centre)
    ys = np.linspace(-width / 2, width / 2, n_across)
    v = np.repeat(centre, n_across, axis=0)
    v[:, 1] += np.tile(ys, k)
    faces = []
    for i in range(k - 1):
        for j in range(n_across - 1):
            a, b = i * n_across + j, (i + 1) * n_across + j
            faces += [[a, b, a + 1], [a + 1, b, b + 1]]
    return v, np.asarray(faces)


def test_self_intersecting_panels_are_reported(tmp_path):
    # A strip whose centre line is a figure of eight: its two passes cross at the middle (where
    # no vertex lies, so the crossing is transversal).
    t = np.linspace(-0.1, 0.85, 97)
    centre = np.stack(
        [0.4 * np.sin(2 * np.pi * t), np.zeros_like(t), 0.2 * np.sin(4 * np.pi * t)], axis=1
    )
    v, f = _strip(centre)
    write_obj(tmp_path / "panel.obj", v, f)
    sidecar = {
        "format": "datagen-garment-template",
        "version": 1,
        "name": "panel",
        "category": "upper",
        "units": "m",
        "resolution": 0.025,
        "loops": {},
        "regions": {"names": ["panel"], "labels": [0] * len(v)},
    }
    (tmp_path / "panel.json").write_text(json.dumps(sidecar))
    problems = check_template(tmp_path / "panel.obj")
    assert any(
        p.startswith("panel.obj:") and "self-intersecting triangle pairs (first: faces" in p
        for p in problems
    ), problems


def test_missing_and_bad_files(tmp_path):
    problems = check_template(tmp_path / "nothing.obj")
    assert len(problems) == 1 and "nothing.json" in problems[0]
    (tmp_path / "bad.json").write_text("{ not json")
    write_obj(tmp_path / "bad.obj", np.eye(3), np.array([[0, 1, 2]]))
    problems = check_template(tmp_path / "bad.obj")
    assert len(problems) == 1 and "valid JSON" in problems[0]
    # A NaN coordinate is named by its line; it read as a bounding box of "nan" units before.
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"nan.obj: field 'line 3': expected a vertex of "
                                         r"finite coordinates, got 'v nan 1 0'"):
        read_obj(tmp_path / "nan.obj")


def test_cli_check(shipped, tmp_path):
    from click.testing import CliRunner

    from datagen.garment.commands import templates

    runner = CliRunner()
    good = TEMPLATES / "female" / "top.obj"
    result = runner.invoke(templates, ["check", str(good)])
    assert result.exit_code == 0, result.output
    assert result.output.strip().endswith("top.obj: OK")
    obj, js = _copy(TEMPLATES / "female" / "top", tmp_path, "top")
    t = shipped[("female", "top")]
    write_obj(obj, t.vertices * 100.0, t.faces)
    result = runner.invoke(templates, ["check", "--no-body", str(good), str(obj)])
    assert result.exit_code == 1
    assert "top.obj: OK" in result.output and "looks like centimetres" in result.output
    # A folder stands for every template under it (`datagen templates check templates/*`), each
    # checked once even when the folder and a file in it are both named.
    (tmp_path / "sub").mkdir()
    _copy(TEMPLATES / "female" / "top", tmp_path / "sub", "top")
    result = runner.invoke(templates, ["check", "--no-body", str(tmp_path), str(obj)])
    assert result.exit_code == 1
    assert result.output.count("top.obj: OK") == 1 and result.output.count("centimetres") == 1
    assert "1 of 2 templates have problems" in result.output
    (tmp_path / "empty").mkdir()
    result = runner.invoke(templates, ["check", str(tmp_path / "empty")])
    assert result.exit_code == 2 and "empty" in result.output
    assert "expected a folder holding template .obj files" in result.output


def test_low_resolution_build(rest_bodies):
    """`templates build --resolution` changes the edge length; the guarantees hold."""
    from datagen.garment.build import build_template

    rest = rest_bodies["female"]
    t = build_template("top", rest, resolution=0.02)
    assert t.resolution == 0.02
    problems = check_template(t, rest.vertices, rest.faces)
    assert problems == []
