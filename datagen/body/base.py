"""The interface every body model implements, and shape sampling."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from datagen.types import LinearSkinning, RestBody


@dataclass
class PosedBody:
    vertices: np.ndarray  # (F, V, 3) float32
    joints: np.ndarray  # (F, 24, 3) float32
    skinning: LinearSkinning | None  # how to rebuild `vertices` without the model, if LBS


class BodyModel(Protocol):
    """A body model driven by canonical poses (datagen.skeleton)."""

    name: str
    shape_names: tuple[str, ...]

    def shape_range(self) -> dict[str, tuple[float, float]]:
        """The valid range of each shape parameter (what sampling draws from)."""
        ...

    def rest_body(self, gender: str, shape: np.ndarray) -> RestBody:
        """The subject in the canonical T-pose, soles at z = 0."""
        ...

    def pose(self, rest: RestBody, poses: np.ndarray, trans: np.ndarray) -> PosedBody:
        """Skin the subject with canonical poses (F, 72) and pelvis positions (F, 3)."""
        ...


GENDERS = ("female", "male")


def check_gender(gender: str, source: str | None = None) -> str:
    from datagen.errors import InputError

    if gender not in GENDERS:
        raise InputError(source, "gender", "'female' or 'male'", gender)
    return gender
