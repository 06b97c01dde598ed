"""SceneSpec: every random choice of one sequence, as data.

A SceneSpec is what the sampler produces from (recipe, dataset seed, sequence index) and what
every later stage consumes. Its JSON is canonical (sorted keys, no spaces, shortest float repr),
so the same seed gives byte-identical JSON on any machine and in any worker.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

from datagen.config import from_mapping, to_mapping
from datagen.errors import InputError

SCHEMA_VERSION = 1


@dataclass(frozen=True)
class SubjectSpec:
    model: str = "anny"
    gender: Literal["female", "male"] = "female"
    shape: dict[str, float] = field(default_factory=dict)  # parameter name -> value


def require_lead_in(lead_in: int, source, path: str) -> None:
    """A scene with garments needs a lead-in of at least one frame: the garments are fitted
    to the rest pose and settle on the body's frame 0, which is the rest pose only when a
    lead-in comes before the motion. With none they were dropped onto the motion's first pose
    (a walking t-shirt ran away at 150 m/s and was rejected after three runs). A body alone
    may start at the motion's first frame."""
    if lead_in < 1:
        raise InputError(source, path, "1 or more frames from the rest pose, to which the "
                         "garments are fitted, into the motion's first frame", lead_in)


@dataclass(frozen=True)
class MotionSpec:
    source: Literal["procedural", "bvh", "amass"] = "procedural"
    action: str = "walk"  # the label stored with the sequence
    params: dict[str, float] = field(default_factory=dict)  # procedural parameters
    file: str | None = None  # bvh/amass file
    start: float = 0.0  # window start as a fraction of the file's usable range, in [0, 1]
    mirror: bool = False
    frames: int = 90  # output frames, without the lead-in
    fps: float = 30.0
    lead_in: int = 15  # frames from the rest pose to the first frame

    def validate(self, source, path: str) -> None:
        if self.frames <= 0:
            raise InputError(source, f"{path}.frames", "a positive number of frames", self.frames)
        if self.fps <= 0:
            raise InputError(source, f"{path}.fps", "a positive frame rate", self.fps)
        if self.lead_in < 0:
            raise InputError(source, f"{path}.lead_in", "0 or more frames", self.lead_in)
        if not 0.0 <= self.start <= 1.0:
            raise InputError(source, f"{path}.start", "a fraction in [0, 1]", self.start)
        if self.source != "procedural" and not self.file:
            raise InputError(source, f"{path}.file", f"a {self.source} file path", self.file)


@dataclass(frozen=True)
class GarmentSpec:
    name: str  # unique within the outfit, e.g. "upper", "lower", "dress"
    template: str  # template name: tshirt, top, trousers, skirt
    variant: str = ""  # upper-body cut: tshirt, shirt, polo, top
    fabric: str = "cotton"
    shaping: dict[str, float] = field(default_factory=dict)  # Eq. 3.1 parameters per axis
    cuts: dict[str, float] = field(default_factory=dict)  # lengths, metres
    elastic: dict[str, bool] = field(default_factory=dict)  # boundary loop role -> elastic
    layer: int = 0  # 0 = innermost


@dataclass(frozen=True)
class OutfitSpec:
    garments: tuple[GarmentSpec, ...] = ()
    tightness: tuple[float, float] = (0.0, 0.0)  # gamma: offsets on size and girth
    sewn: Literal["jumpsuit", "dress"] | None = None

    def worn(self) -> tuple[tuple[str, str, str], ...]:
        """(name, type, fabric) of each garment the outfit stage makes from this spec, in a
        shard's order (by name): what a written sequence's garments record (io.shard: the
        upper-body cut, such as shirt or polo, else the template), for a sequence that was
        rejected before any was written. A sewn outfit is one garment of its lower part's
        fabric (garment.outfit.make_outfit)."""
        if self.sewn:
            return ((self.sewn, self.sewn, self.garments[-1].fabric),)
        return tuple(sorted((g.name, g.variant or g.template, g.fabric) for g in self.garments))


@dataclass(frozen=True)
class SimSpec:
    solver: str = "xpbd"
    quality: str = "default"  # preset name (docs/accuracy-vs-time.md)
    substeps: int | None = None  # None: from the quality preset
    iterations: int | None = None
    effects: str | tuple[str, ...] = "auto"
    wind: tuple[float, float, float] | None = None  # m/s; None: no wind
    settle_seconds: float = 0.5


@dataclass(frozen=True)
class SceneSpec:
    dataset_seed: int
    sequence_index: int
    sequence_id: str
    split: Literal["train", "test"] = "train"
    subject: SubjectSpec = field(default_factory=SubjectSpec)
    motion: MotionSpec = field(default_factory=MotionSpec)
    outfit: OutfitSpec = field(default_factory=OutfitSpec)
    simulation: SimSpec = field(default_factory=SimSpec)
    schema_version: int = SCHEMA_VERSION

    def to_json(self) -> str:
        return json.dumps(to_mapping(self), sort_keys=True, separators=(",", ":"))

    @staticmethod
    def from_json(text: str, source: str | None = None) -> SceneSpec:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(source, "spec", "valid JSON", str(exc)) from None
        if not isinstance(data, dict):
            raise InputError(source, "spec", "a JSON object", type(data).__name__)
        version = data.get("schema_version")
        if version != SCHEMA_VERSION:
            raise InputError(source, "spec.schema_version", f"{SCHEMA_VERSION}", version)
        return from_mapping(SceneSpec, data, source, "spec")
