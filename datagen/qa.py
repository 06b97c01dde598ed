"""The physical-validity bounds a simulated sequence must meet to be training data.

One definition for everyone who judges a sequence: `datagen validate` checks written shards
against it, and a dataset run (recipe `simulation.qa: reject`) rejects a sequence that breaks it
before writing, so a dataset's shards pass validation by construction and every sequence that
did not make it is listed with its reason.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from datagen.skeleton import JOINT_NAMES

DEEP_SHARE_MAX = 0.01  # share of garment vertices deeper in the body than the fabric thickness
# The bound on stretch: at most this share of the fabric springs beyond their own fabric's
# max_strain in a frame (99.9 % within it). The simulator redoes frames over it (datagen.sim),
# and the dataset's gate, the hard cases and validation judge by it.
STRAIN_SHARE_MAX = 0.001
QA_POLICIES = ("reject", "keep")  # what a dataset run does with a sequence over a bound
# How much farther from the neck joint than where it was fitted a garment's neckline may lie
# (metres, the 90th percentile of its vertices): past it the garment has slid off the
# shoulders. Measured on the 73 garments with a neckline in make dataset's sequences, five more
# seeds of its recipe and four sequences of the CLOTH3D recipe (2026-12-04): worn ones reach at
# most 11 cm, a loose top's edge flapping in a jump 15; a denim dress's strap at the edge of
# the shoulder in a spin and an open shirt half off one shoulder 15-16 (these pass: the bound
# catches garments off the shoulders, not every strap that slides); a cropped polo's collar
# pulled off one shoulder by a spin 22, and open shirts and strap jumpsuits off both
# shoulders, hanging at the elbows, 24-34.
NECKLINE_SLIP_MAX = 0.20
NECK_JOINT = JOINT_NAMES.index("neck")  # the joint a neckline is measured from


@dataclass(frozen=True)
class Breach:
    """A QA series over its bound: the worst frame (after the lead-in) and its value."""

    series: str
    value: float
    frame: int
    limit: float
    what: str  # the bound in words, without figures (a dataset card counts rejections by it)
    where: str = ""  # which garment, and where on the body (where_on_body), where known

    def __str__(self) -> str:
        return (f"qa/{self.series} reaches {self.value:.4g} at frame {self.frame} "
                f"({self.what}; bound {self.limit:g})")

    @property
    def reason(self) -> str:
        where = f"; {self.where}" if self.where else ""
        return (f"{self.what} (qa/{self.series} {self.value:.4g} at frame {self.frame}, "
                f"bound {self.limit:g}{where})")


def where_on_body(points: np.ndarray, body: np.ndarray, vertex_parts: np.ndarray,
                  part_names: Sequence[str], most: int = 2) -> str:
    """The body parts nearest the cloth `points` (K, 3), by each point's nearest vertex of the
    `body` (V, 3) whose parts `vertex_parts` (V,) index `part_names`: the `most` most common
    with their shares, 'thigh_l 52 %, pelvis 29 %'. Empty for no points. Says where a bound
    broke, so a rejection names the limb or the fold instead of leaving it to a probe."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return ""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(np.asarray(body, dtype=np.float64)).query(points)
    parts, counts = np.unique(np.asarray(vertex_parts)[nearest], return_counts=True)
    order = np.lexsort((parts, -counts))[:most]  # most common first, ties by part number
    return ", ".join(f"{part_names[int(parts[k])]} {100.0 * counts[k] / len(points):.0f} %"
                     for k in order)


def buried_share(cloth: np.ndarray, thickness: np.ndarray, body: np.ndarray,
                 faces: np.ndarray, garments: Sequence[tuple[int, int]] | None = None
                 ) -> np.ndarray:
    """(F,) per frame, the share of cloth vertices inside the body's volume and farther than
    their fabric's thickness from every body triangle: in the garment that has the most where
    `garments` gives each garment's vertices lo:hi (the bound holds per garment, as the
    simulator's series do), else among all of them.

    Signing each vertex by its nearest body triangle cannot see cloth inside a part that passes
    through another: where a flexed thigh rises through the lower torso (linear blend skinning
    at the hip), belly fabric 5 mm outside the torso lies 18-70 mm inside the thigh and reads as
    outside. Here the volume is the union of the parts, inside where the generalised winding
    number (libigl's fast approximation) exceeds one half, and the depth is the distance to the
    nearest triangle of any part. The simulator's deep_share reads the same volume since
    2026-12-07 (its own ray count, distances to the colliding triangles only:
    BodyCollider.inside_depth); this is the check that does not depend on the collider.

    `cloth` (F, V, 3) every garment's vertices at the output frames, `thickness` (V,) metres,
    `body` (F, Vb, 3) the body at the same frames, `faces` (T, 3) all of the body's triangles
    (a closed surface). About 0.1 s a frame for 13k cloth and 27k body triangles on one core,
    so a dataset run does not compute it; the hard cases do (pipeline/hard_cases.py).
    """
    import igl

    cloth = np.asarray(cloth)
    body = np.asarray(body)
    thickness = np.asarray(thickness, dtype=np.float64)
    if cloth.shape[0] != body.shape[0] or cloth.shape[1] != thickness.shape[0]:
        raise ValueError(f"buried_share: cloth {cloth.shape}, thickness {thickness.shape} and "
                         f"body {body.shape} must have matching frames and vertices")
    groups = [(0, cloth.shape[1])] if garments is None else list(garments)
    if not groups or any(not 0 <= lo < hi <= cloth.shape[1] for lo, hi in groups):
        raise ValueError(f"buried_share: garments {groups} must be non-empty vertex ranges "
                         f"within the cloth's {cloth.shape[1]} vertices")
    tris = np.ascontiguousarray(faces, dtype=np.int64)
    out = np.zeros(cloth.shape[0])
    for f in range(cloth.shape[0]):
        sd, *_ = igl.signed_distance(np.ascontiguousarray(cloth[f], dtype=np.float64),
                                     np.ascontiguousarray(body[f], dtype=np.float64), tris,
                                     sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
        deep = sd < -thickness
        out[f] = max(float(np.mean(deep[lo:hi])) for lo, hi in groups)
    return out


def neckline_slip(neckline: np.ndarray, fitted: np.ndarray, neck: np.ndarray,
                  fitted_neck: np.ndarray) -> np.ndarray:
    """(F,) per frame, how much farther from the neck joint a garment's neckline lies than where
    it was fitted: the 90th percentile over the neckline's vertices of each one's distance to
    the joint less its distance in the fit. A distance to one joint does not depend on how the
    body turns or moves, so a neckline that rides on the shoulders stays within a few
    centimetres (the shoulders' skin moves as the arms go from the fit's T-pose to the
    motion's); one that slides off the shoulders moves 20-35 cm away.

    `neckline` (F, L, 3) the neckline's vertices at the output frames, `fitted` (L, 3) the same
    vertices as fitted to the rest body, `neck` (F, 3) the neck joint at those frames and
    `fitted_neck` (3,) the rest body's."""
    neckline = np.asarray(neckline, dtype=np.float64)
    fitted = np.asarray(fitted, dtype=np.float64)
    neck = np.asarray(neck, dtype=np.float64)
    if (neckline.ndim != 3 or neckline.shape[2] != 3 or fitted.shape != neckline.shape[1:]
            or neck.shape != (neckline.shape[0], 3) or np.shape(fitted_neck) != (3,)):
        raise ValueError(f"neckline_slip: neckline {neckline.shape} (F, L, 3), fitted "
                         f"{fitted.shape} (L, 3), neck {neck.shape} (F, 3) and fitted_neck "
                         f"{np.shape(fitted_neck)} (3,) must match")
    now = np.linalg.norm(neckline - neck[:, None, :], axis=2)
    then = np.linalg.norm(fitted - np.asarray(fitted_neck, dtype=np.float64), axis=1)
    return np.percentile(now - then[None, :], 90, axis=1)


def neckline_breach(neckline: np.ndarray, fitted: np.ndarray, neck: np.ndarray,
                    fitted_neck: np.ndarray, category: str) -> Breach | None:
    """A garment's neckline_slip over NECKLINE_SLIP_MAX, at its worst frame, or None: the one
    verdict of the dataset's gate (stages.slipped_necklines) and of validate. Arguments as
    neckline_slip's; `category` names the garment in the reason."""
    slip = neckline_slip(neckline, fitted, neck, fitted_neck)
    k = int(np.argmax(slip))
    if slip[k] <= NECKLINE_SLIP_MAX:
        return None
    return Breach("neckline_slip", float(slip[k]), k, NECKLINE_SLIP_MAX,
                  f"the {category}'s neckline slid off the shoulders")


def breaches(series: Mapping[str, np.ndarray]) -> list[Breach]:
    """The bounds that the per-frame QA series break: cloth deeper in the body than its
    thickness (deep_share) and fabric springs beyond their own fabric's max_strain
    (over_strain_share). Each spring is held to its own fabric: in an outfit of cotton
    (max_strain 0.25) and denim (0.20), denim strained to 0.24 breaks the bound. (A 99.9th
    percentile of all springs held to the loosest fabric's bound, the gate before 2026-11-30,
    let such a sequence through.)"""
    out = []

    def check(name: str, bound: float, what: str) -> None:
        values = series.get(name)
        if values is None:
            return
        values = np.asarray(values, dtype=np.float64)
        if values.size and values.max() > bound:
            k = int(np.argmax(values))
            out.append(Breach(name, float(values[k]), k, bound, what))

    check("deep_share", DEEP_SHARE_MAX, "cloth deeper in the body than its thickness")
    check("over_strain_share", STRAIN_SHARE_MAX,
          "fabric springs strained beyond their fabric's max_strain")
    return out
