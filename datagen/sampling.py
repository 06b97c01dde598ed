"""Recipe + (dataset seed, sequence index) -> SceneSpec. Pure and deterministic.

Each section of the spec draws from its own stream, `SeedSequence(seed, spawn_key=(index, k))`,
so adding an option to one section never changes what another section samples. No global state
is touched.
"""

from __future__ import annotations

import numpy as np

from datagen.errors import InputError
from datagen.recipe import LoadedRecipe
from datagen.spec import MotionSpec, OutfitSpec, SceneSpec, SimSpec, SubjectSpec

# Stream numbers of the spec sections (never renumber: it would change every dataset).
_SPLIT, _SUBJECT, _MOTION, _OUTFIT, _SIMULATION = range(5)


def section_rng(seed: int, index: int, section: int) -> np.random.Generator:
    return np.random.Generator(
        np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(index, section)))
    )


def sequence_id(seed: int, index: int) -> str:
    return f"{seed}-{index:06d}"


def _choose(rng: np.random.Generator, weights: dict[str, float]) -> str:
    names = sorted(k for k, w in weights.items() if w > 0)
    w = np.array([weights[k] for k in names], dtype=np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _round(x: float) -> float:
    # Rounded so that the JSON stays short and readable; far below any physical tolerance.
    return float(round(float(x), 6))


def body_shape_ranges(model: str) -> tuple[tuple[str, ...], dict[str, tuple[float, float]]]:
    """Shape parameter names and valid ranges of a body model, without instantiating it."""
    if model == "anny":
        from datagen.body.anny_model import SHAPE_NAMES, SHAPE_RANGE

        return SHAPE_NAMES, dict(SHAPE_RANGE)
    if model == "smpl":
        names = tuple(f"beta{i}" for i in range(10))
        return names, {n: (-3.0, 3.0) for n in names}
    raise InputError(None, "subject.model", "'anny' or 'smpl'", model)


def sample_subject(loaded: LoadedRecipe, rng: np.random.Generator) -> SubjectSpec:
    cfg = loaded.recipe.subject
    names, valid = body_shape_ranges(cfg.model)
    for name, (lo, hi) in cfg.shape.items():
        if name not in valid:
            raise InputError(
                loaded.path,
                f"subject.shape.{name}",
                f"a shape parameter of {cfg.model} ({', '.join(names)})",
                name,
            )
        vlo, vhi = valid[name]
        if lo < vlo or hi > vhi:
            raise InputError(
                loaded.path,
                f"subject.shape.{name}",
                f"a range within the valid [{vlo}, {vhi}]",
                [lo, hi],
            )
    gender = "female" if rng.random() < cfg.female_fraction else "male"
    shape = {}
    for name in names:
        lo, hi = cfg.shape.get(name, valid[name])
        shape[name] = _round(rng.uniform(lo, hi))
    return SubjectSpec(model=cfg.model, gender=gender, shape=shape)


def sample_motion(loaded: LoadedRecipe, rng: np.random.Generator) -> MotionSpec:
    cfg = loaded.recipe.motion
    source = _choose(rng, cfg.sources)
    mirror = bool(rng.random() < cfg.mirror_probability)
    common = dict(frames=cfg.frames, fps=cfg.fps, lead_in=cfg.lead_in, mirror=mirror)
    if source == "procedural":
        from datagen.motion.procedural import ACTIONS, action_parameters

        for name in cfg.actions:
            if name not in ACTIONS:
                raise InputError(
                    loaded.path,
                    f"motion.actions.{name}",
                    f"one of the actions {', '.join(sorted(ACTIONS))}",
                    name,
                )
        action = _choose(rng, cfg.actions)
        params = {}
        for pname, spec in sorted(action_parameters(action).items()):
            value = rng.uniform(spec.min, spec.max) if cfg.randomize_params else spec.default
            params[pname] = _round(value)
        return MotionSpec(source="procedural", action=action, params=params, **common)
    files = loaded.motion_files(source)
    file = files[int(rng.integers(len(files)))]
    start = _round(rng.random())
    from pathlib import Path

    return MotionSpec(source=source, action=Path(file).stem, file=file, start=start, **common)


def sample_simulation(loaded: LoadedRecipe, rng: np.random.Generator) -> SimSpec:
    cfg = loaded.recipe.simulation
    return SimSpec(solver=cfg.solver, quality=cfg.quality, effects=cfg.effects, wind=cfg.wind,
                   settle_seconds=cfg.settle_seconds)


def sample_outfit(
    loaded: LoadedRecipe, rng: np.random.Generator, subject: SubjectSpec
) -> OutfitSpec:
    if not loaded.recipe.outfit:  # a body-only dataset
        return OutfitSpec()
    from datagen.garment.outfit import sample_outfit as sample

    return sample(loaded, rng, subject)


def sample_scene(loaded: LoadedRecipe, index: int) -> SceneSpec:
    """The SceneSpec of sequence `index` of the recipe's dataset."""
    recipe = loaded.recipe
    seed = recipe.seed
    split_rng = section_rng(seed, index, _SPLIT)
    split = "test" if split_rng.random() < recipe.test_fraction else "train"
    subject = sample_subject(loaded, section_rng(seed, index, _SUBJECT))
    motion = sample_motion(loaded, section_rng(seed, index, _MOTION))
    outfit = sample_outfit(loaded, section_rng(seed, index, _OUTFIT), subject)
    simulation = sample_simulation(loaded, section_rng(seed, index, _SIMULATION))
    return SceneSpec(
        dataset_seed=seed,
        sequence_index=index,
        sequence_id=sequence_id(seed, index),
        split=split,
        subject=subject,
        motion=motion,
        outfit=outfit,
        simulation=simulation,
    )
