"""Pipeline recipes (`pipelines/*.yaml`): what a dataset run draws its sequences from.

Every key is documented in docs/recipes.md; an unknown key or an impossible value is an error
naming the file and the key.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass, field
from pathlib import Path

from datagen.config import check_range, from_mapping, load_yaml
from datagen.errors import InputError
from datagen.qa import QA_POLICIES
from datagen.spec import require_lead_in


@dataclass(frozen=True)
class SubjectConfig:
    model: str = "anny"
    female_fraction: float = 2.0 / 3.0  # CLOTH3D: 2:1 female:male
    # Optional narrower ranges per shape parameter (within the model's valid range).
    shape: dict[str, tuple[float, float]] = field(default_factory=dict)

    def validate(self, source, path: str) -> None:
        check_range(self.female_fraction, 0.0, 1.0, source, f"{path}.female_fraction")
        for name, (lo, hi) in self.shape.items():
            if lo > hi:
                raise InputError(
                    source, f"{path}.shape.{name}", "[low, high] with low <= high", [lo, hi]
                )


@dataclass(frozen=True)
class MotionConfig:
    # Weight of each motion source; sources with weight 0 are never drawn.
    sources: dict[str, float] = field(default_factory=lambda: {"procedural": 1.0})
    # Procedural actions and their weights.
    actions: dict[str, float] = field(default_factory=lambda: {"walk": 1.0})
    randomize_params: bool = True  # draw procedural parameters uniformly in their ranges
    bvh_files: list[str] = field(default_factory=list)  # globs, relative to the recipe file
    amass_files: list[str] = field(default_factory=list)
    mirror_probability: float = 0.5
    frames: int = 90
    fps: float = 30.0
    lead_in: int = 15

    def validate(self, source, path: str) -> None:
        if self.frames <= 0:
            raise InputError(source, f"{path}.frames", "a positive number of frames", self.frames)
        if self.fps <= 0:
            raise InputError(source, f"{path}.fps", "a positive frame rate", self.fps)
        require_lead_in(self.lead_in, source, f"{path}.lead_in")  # every recipe dresses
        check_range(self.mirror_probability, 0.0, 1.0, source, f"{path}.mirror_probability")
        for name, w in self.sources.items():
            if name not in ("procedural", "bvh", "amass"):
                raise InputError(
                    source, f"{path}.sources.{name}", "one of procedural, bvh, amass", name
                )
            check_range(w, 0.0, None, source, f"{path}.sources.{name}")
        if sum(self.sources.values()) <= 0:
            raise InputError(
                source, f"{path}.sources", "at least one positive weight", self.sources
            )
        for name, w in self.actions.items():
            check_range(w, 0.0, None, source, f"{path}.actions.{name}")
        if self.sources.get("procedural", 0) > 0 and sum(self.actions.values()) <= 0:
            raise InputError(
                source, f"{path}.actions", "at least one positive weight", self.actions
            )
        if self.sources.get("bvh", 0) > 0 and not self.bvh_files:
            raise InputError(source, f"{path}.bvh_files", "BVH files for the bvh source", [])
        if self.sources.get("amass", 0) > 0 and not self.amass_files:
            raise InputError(source, f"{path}.amass_files", "npz files for the amass source", [])


@dataclass(frozen=True)
class BodyConfig:
    repair_gap: float = 0.004  # thesis 3.3.1: 4 mm so that a folded cloth fits
    max_solvable_extent: float = 0.30  # metres: larger intersections are not "small"
    max_solvable_depth: float = 0.03
    drop_unreached_parts: bool = True  # parts the outfit never reaches leave the collider
    # Parts whose contacts with other parts are neither repaired nor a reason to reject (a hand
    # resting on a thigh is a pose, not an error); they stay in the cloth collider only when the
    # outfit reaches them (outfit.dropped_parts_for: today all but the head), and the arm fit
    # (arm_clearance) clears the hands that stay, which leave the cloth between no room.
    unrepaired_parts: list[str] = field(
        default_factory=lambda: ["hand_l", "hand_r", "foot_l", "foot_r", "head"]
    )
    arm_clearance: bool = True  # abduct arms (hands too) that would sit in a broad subject's trunk
    thinner_retries: int = 1  # retries with a thinner body before rejecting
    # Where skinning sinks a part into its neighbour across a flexed joint (hip, knee), both
    # surfaces meet at a shared contact surface this far apart (datagen.body.flexion): room for
    # the cloth caught between them. null leaves the overlap as skinning made it.
    flexion_gap: float | None = 0.01

    def validate(self, source, path: str) -> None:
        check_range(self.repair_gap, 0.0, 0.05, source, f"{path}.repair_gap")
        check_range(self.max_solvable_extent, 0.0, 1.0, source, f"{path}.max_solvable_extent")
        check_range(self.max_solvable_depth, 0.0, 1.0, source, f"{path}.max_solvable_depth")
        check_range(self.thinner_retries, 0, 5, source, f"{path}.thinner_retries")
        if self.flexion_gap is not None:
            check_range(self.flexion_gap, 0.0, 0.05, source, f"{path}.flexion_gap")
        from datagen.body.parts import PART_NAMES

        for name in self.unrepaired_parts:
            if name not in PART_NAMES:
                raise InputError(
                    source,
                    f"{path}.unrepaired_parts",
                    f"body parts ({', '.join(PART_NAMES)})",
                    name,
                )


@dataclass(frozen=True)
class SimulationConfig:
    solver: str = "xpbd"
    quality: str = "default"
    effects: str | tuple[str, ...] = "auto"
    wind: tuple[float, float, float] | None = None
    settle_seconds: float = 0.5  # the outfit settles on the rest pose before the lead-in
    # A sequence over a physical-validity bound (datagen.qa): rejected with its reason, or kept
    # (written, and flagged by `datagen validate`; `--qa warning` lets it pass).
    qa: str = "reject"

    def validate(self, source, path: str) -> None:
        from datagen.sim.simulate import QUALITY_PRESETS

        if self.solver not in QUALITY_PRESETS:
            raise InputError(source, f"{path}.solver", f"one of {', '.join(QUALITY_PRESETS)}",
                             self.solver)
        if self.quality not in QUALITY_PRESETS[self.solver]:
            raise InputError(source, f"{path}.quality",
                             f"one of {', '.join(QUALITY_PRESETS[self.solver])}", self.quality)
        check_range(self.settle_seconds, 0.0, 10.0, source, f"{path}.settle_seconds")
        if self.qa not in QA_POLICIES:
            raise InputError(source, f"{path}.qa", f"one of {', '.join(QA_POLICIES)}", self.qa)
        from datagen.sim.effects import check_wind_request, wind_blows

        try:
            check_wind_request(self.effects, wind_blows(self.wind))
        except InputError as exc:
            raise InputError(source, f"{path}.effects", exc.expected, exc.got) from None


@dataclass(frozen=True)
class StorageConfig:
    shard_size: int = 4  # sequences per shard file
    quantize: bool = False  # lossy 16-bit positions (docs/shard-format.md)
    store_body_vertices: bool = False  # else the body is stored as skinning + repair offsets

    def validate(self, source, path: str) -> None:
        check_range(self.shard_size, 1, None, source, f"{path}.shard_size")


@dataclass(frozen=True)
class Recipe:
    name: str
    seed: int
    sequences: int
    test_fraction: float = 0.2  # CLOTH3D: 80/20 split by sequence
    subject: SubjectConfig = field(default_factory=SubjectConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    outfit: dict = field(default_factory=dict)  # parsed by datagen.garment (OutfitConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)

    def validate(self, source, path: str) -> None:
        if self.sequences < 0:
            raise InputError(source, "sequences", "0 or more sequences", self.sequences)
        if self.seed < 0:
            raise InputError(source, "seed", "a non-negative integer", self.seed)
        check_range(self.test_fraction, 0.0, 1.0, source, "test_fraction")


@dataclass(frozen=True)
class LoadedRecipe:
    recipe: Recipe
    path: Path  # the YAML file; relative file globs resolve against its folder

    @property
    def base_dir(self) -> Path:
        return self.path.parent

    def motion_files(self, source: str) -> list[str]:
        """Sorted motion files for a source, as paths relative to the recipe folder when they
        lie below it (so scene specs do not depend on where the checkout is)."""
        patterns = (
            self.recipe.motion.bvh_files if source == "bvh" else self.recipe.motion.amass_files
        )
        files: set[str] = set()
        for pattern in patterns:
            full = pattern if Path(pattern).is_absolute() else str(self.base_dir / pattern)
            matches = sorted(glob.glob(full))
            if not matches:
                raise InputError(
                    self.path, f"motion.{source}_files", "a pattern matching files", pattern
                )
            for m in matches:
                p = Path(m).resolve()
                try:
                    files.add(str(Path(m).relative_to(self.base_dir)))
                except ValueError:
                    files.add(str(p))
        return sorted(files)


def load_recipe(path: str | Path) -> LoadedRecipe:
    path = Path(path)
    data = load_yaml(path)
    recipe = from_mapping(Recipe, data, path)
    return LoadedRecipe(recipe=recipe, path=path)
