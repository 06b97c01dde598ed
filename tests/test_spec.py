"""SceneSpec round trips, deterministic sampling, strict recipes."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from datagen.errors import InputError
from datagen.recipe import load_recipe
from datagen.sampling import sample_scene
from datagen.spec import SceneSpec

RECIPE = """
name: t
seed: 1234
sequences: 50
subject:
  female_fraction: 0.6666667
motion:
  actions: {walk: 2, run: 1, spin: 1}
  frames: 60
"""


@pytest.fixture
def recipe_path(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text(RECIPE)
    return p


def test_json_round_trip(recipe_path):
    loaded = load_recipe(recipe_path)
    for i in range(10):
        spec = sample_scene(loaded, i)
        text = spec.to_json()
        back = SceneSpec.from_json(text)
        assert back == spec
        assert back.to_json() == text


def test_same_seed_same_bytes_across_processes(recipe_path):
    """Two fresh interpreters produce byte-identical spec JSON for the same seed and index."""
    code = textwrap.dedent(
        f"""
        from datagen.recipe import load_recipe
        from datagen.sampling import sample_scene
        loaded = load_recipe({str(recipe_path)!r})
        print("\\n".join(sample_scene(loaded, i).to_json() for i in range(20)))
        """
    )
    outs = [
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        ).stdout
        for _ in range(2)
    ]
    assert outs[0] == outs[1]
    assert len(outs[0].splitlines()) == 20
    # and the in-process result agrees
    loaded = load_recipe(recipe_path)
    assert outs[0].splitlines()[3] == sample_scene(loaded, 3).to_json()


def test_sections_draw_independently(recipe_path, tmp_path):
    """Changing the motion section does not change the subjects that were drawn."""
    other = tmp_path / "o.yaml"
    other.write_text(RECIPE.replace("{walk: 2, run: 1, spin: 1}", "{jump: 1}"))
    a, b = load_recipe(recipe_path), load_recipe(other)
    for i in range(5):
        assert sample_scene(a, i).subject == sample_scene(b, i).subject
        assert sample_scene(b, i).motion.action == "jump"


def test_distributions(recipe_path):
    loaded = load_recipe(recipe_path)
    specs = [sample_scene(loaded, i) for i in range(600)]
    female = sum(s.subject.gender == "female" for s in specs) / len(specs)
    assert abs(female - 2 / 3) < 0.06  # 2:1, several standard errors
    test = sum(s.split == "test" for s in specs) / len(specs)
    assert abs(test - 0.2) < 0.05
    ages = [s.subject.shape["age"] for s in specs]
    assert 0.77 <= min(ages) and max(ages) <= 0.90
    weights = [s.subject.shape["weight"] for s in specs]
    assert min(weights) < 0.05 and max(weights) > 0.95  # the full range is used
    walks = sum(s.motion.action == "walk" for s in specs) / len(specs)
    assert abs(walks - 0.5) < 0.07


@pytest.mark.parametrize(
    "patch, field",
    [
        ("seed: 1234", "colour"),  # unknown top-level key (added below)
        ("  frames: 60", "motion.frames"),
        ("  actions: {walk: 2, run: 1, spin: 1}", "motion.actions.moonwalk"),
        ("  female_fraction: 0.6666667", "subject.female_fraction"),
        ("seed: 1234", "simulation.effects"),
        ("seed: 1234", "simulation.settle_seconds"),
        ("seed: 1234", "body.flexion_gap"),
    ],
)
def test_bad_recipes_name_the_field(tmp_path, patch, field):
    replacement = {
        "colour": "seed: 1234\ncolour: blue",
        "motion.frames": "  frames: -5",
        "motion.actions.moonwalk": "  actions: {moonwalk: 1}",
        "subject.female_fraction": "  female_fraction: 1.5",
        "simulation.effects": "seed: 1234\nsimulation: {effects: 'auto,self_collision'}",
        # NaN passes every range check (each comparison is false): rejected as not finite.
        "simulation.settle_seconds": "seed: 1234\nsimulation: {settle_seconds: .nan}",
        "body.flexion_gap": "seed: 1234\nbody: {flexion_gap: 0.5}",
    }[field]
    p = tmp_path / "bad.yaml"
    p.write_text(RECIPE.replace(patch, replacement))
    with pytest.raises(InputError) as exc:
        loaded = load_recipe(p)
        sample_scene(loaded, 0)
    assert field in str(exc.value)
    assert "bad.yaml" in str(exc.value)


def test_a_recipe_whose_wind_would_do_nothing_is_refused(tmp_path):
    """Wind blows at the recipe's velocity: naming it with none would blow still air. And it
    pushes on panels by pressure drag alone: a recipe that keeps wind and drops that law would
    blow nothing either."""
    p = tmp_path / "bad.yaml"
    p.write_text(RECIPE.replace("seed: 1234", "seed: 1234\nsimulation: {effects: 'auto,+wind'}"))
    with pytest.raises(InputError, match=r"bad.yaml: field 'simulation.effects': expected wind "
                                         r"only with a wind velocity"):
        load_recipe(p)
    p.write_text(RECIPE.replace("seed: 1234", "seed: 1234\nsimulation: {effects: 'auto,+wind', "
                                              "wind: [2.0, 0.0, 0.0]}"))
    assert load_recipe(p).recipe.simulation.effects == "auto,+wind"
    p.write_text(RECIPE.replace("seed: 1234", "seed: 1234\nsimulation: {effects: "
                                              "'auto,-pressure_drag', wind: [2.0, 0.0, 0.0]}"))
    with pytest.raises(InputError, match=r"bad.yaml: field 'simulation.effects': expected wind "
                                         r"together with pressure_drag"):
        load_recipe(p)


def test_yaml_reads_exponent_floats_as_yaml_1_2_does(tmp_path):
    """PyYAML alone reads `1e-3` and `2.5E4` as strings (YAML 1.1 wants a dot and a signed
    exponent); the recipe loader reads them as numbers, and leaves strings and ints alone."""
    from datagen.config import load_yaml

    p = tmp_path / "numbers.yaml"
    p.write_text("a: 1e-3\nb: 2.5E4\nc: -.5e+2\nd: 12\ne: 1e\nf: '1e3'\ng: 1_000\n")
    data = load_yaml(p)
    assert data == {"a": 0.001, "b": 25000.0, "c": -50.0, "d": 12, "e": "1e", "f": "1e3",
                    "g": 1000}
    assert isinstance(data["d"], int)
    p.write_text(RECIPE.replace("seed: 1234", "seed: 1234\nsimulation: {settle_seconds: 5e-1}"))
    assert load_recipe(p).recipe.simulation.settle_seconds == 0.5


def test_spec_json_errors():
    with pytest.raises(InputError, match="schema_version"):
        SceneSpec.from_json('{"schema_version": 99}')
    spec = SceneSpec(dataset_seed=1, sequence_index=0, sequence_id="1-000000")
    data = spec.to_json().replace('"split":"train"', '"split":"train","extra":1')
    with pytest.raises(InputError, match="extra"):
        SceneSpec.from_json(data)
