"""The physical-validity bounds a simulated sequence must meet to be training data.

One definition for everyone who judges a sequence: `datagen validate` checks written shards
against it, and a dataset run (recipe `simulation.qa: reject`) rejects a sequence that breaks it
before writing, so a dataset's shards pass validation by construction and every sequence that
did not make it is listed with its reason.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from datagen.sim.fabrics import Fabric

DEEP_SHARE_MAX = 0.01  # share of garment vertices deeper in the body than the fabric thickness
QA_POLICIES = ("reject", "keep")  # what a dataset run does with a sequence over a bound


@dataclass(frozen=True)
class Breach:
    """A QA series over its bound: the worst frame (after the lead-in) and its value."""

    series: str
    value: float
    frame: int
    limit: float
    what: str  # the bound in words, without figures (a dataset card counts rejections by it)

    def __str__(self) -> str:
        return (f"qa/{self.series} reaches {self.value:.4g} at frame {self.frame} "
                f"({self.what}; bound {self.limit:g})")

    @property
    def reason(self) -> str:
        return (f"{self.what} (qa/{self.series} {self.value:.4g} at frame {self.frame}, "
                f"bound {self.limit:g})")


def strain_limit(fabric_names: Iterable[str],
                 user_fabrics: Mapping[str, Fabric] | None = None) -> float | None:
    """The largest max_strain of a sequence's fabrics (built-in, or the user's by name): the
    QA series cover all garments together, so a stiffer garment's bound would flag its softer
    neighbour's strain. None when there are no garments."""
    from datagen.sim.fabrics import get_fabric

    extra = dict(user_fabrics or {})
    limits = [get_fabric(name, extra).max_strain for name in fabric_names]
    return max(limits) if limits else None


def breaches(series: Mapping[str, np.ndarray], limit: float | None) -> list[Breach]:
    """The bounds that the per-frame QA series break: cloth deeper in the body than its
    thickness (deep_share) and fabric strain (strain_p999 against `limit`)."""
    out = []

    def check(name: str, bound: float | None, what: str) -> None:
        values = series.get(name)
        if values is None or bound is None:
            return
        values = np.asarray(values, dtype=np.float64)
        if values.size and values.max() > bound:
            k = int(np.argmax(values))
            out.append(Breach(name, float(values[k]), k, bound, what))

    check("deep_share", DEEP_SHARE_MAX, "cloth deeper in the body than its thickness")
    check("strain_p999", limit, "strain over the fabrics' max_strain")
    return out
