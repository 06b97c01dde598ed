"""Shaping (CLOTH3D, thesis Eq. 3.1): the width of sleeves, trouser legs and skirts along axes.

Along each shaping axis the cross-section width becomes

    W(x) = a1 * x + a2 * max(0, x - x_off) + W0

with x the distance along the axis from its origin (the armhole for sleeves, the top of the leg at
the crotch seam for trouser legs, the waistband for skirts). Sleeves and legs have a1 < 0 < a2
(narrowing towards the wrist or ankle, possibly widening again after x_off); skirts have
a1 > a2 = 0 (always widening towards the hem).

The width of a row is its perimeter / pi: the diameter of a circle of the same girth, so it does
not depend on the row's shape or on a direction. Each row is scaled radially about its point on
the axis to reach W(x); over the first `BLEND` metres the scale blends from 1 (smoothstep) so the
junction with the torso or hips stays where it is. A row is never made narrower than its
`min_width` (the width at which it would come within 7 mm of the rest body) nor wider than its
`max_width` (trouser legs meeting each other); `sample_shaping` draws only parameters that stay
within both, so the sampled W(x) is followed exactly outside the blend zone.
"""

from __future__ import annotations

import numpy as np

from datagen.errors import InputError
from datagen.garment.template import GarmentTemplate

SHAPED_AXES = {"sleeve": ("sleeve_l", "sleeve_r"), "leg": ("leg_l", "leg_r"), "skirt": ("skirt",)}

# Per garment: a1, a2 (width change per metre along the axis), x_off as a fraction of the axis
# length, and W0 as a ratio to the template's own width at x = 0 (docs/templates.md gives the
# reasons for each range).
SHAPING_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "tshirt": {"a1": (-0.15, -0.01), "a2": (0.01, 0.25), "x_off": (0.25, 0.95), "w0": (0.95, 1.15)},
    "trousers": {
        "a1": (-0.17, -0.02),
        "a2": (0.01, 0.20),
        "x_off": (0.25, 0.95),
        "w0": (0.95, 1.05),
    },
    "skirt": {"a1": (0.45, 0.90), "a2": (0.0, 0.0), "x_off": (0.0, 0.0), "w0": (0.95, 1.05)},
}
# Metres over which the shaping scale blends in from the junction.
BLEND = {"sleeve": 0.05, "leg": 0.08, "skirt": 0.05}


def _kind(axis_name: str) -> str:
    for kind, names in SHAPED_AXES.items():
        if axis_name in names:
            return kind
    raise KeyError(axis_name)


def row_widths(t: GarmentTemplate, axis_name: str) -> np.ndarray:
    """Width (perimeter / pi) of every row along an axis."""
    rows = t.rows[axis_name]
    out = np.empty(len(rows.x))
    for k, ids in enumerate(rows.vertices):
        p = t.vertices[ids]
        out[k] = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum() / np.pi
    return out


def width_profile(params: dict, x: np.ndarray) -> np.ndarray:
    """W(x) of Eq. 3.1."""
    x = np.asarray(x, dtype=np.float64)
    return params["a1"] * x + params["a2"] * np.maximum(0.0, x - params["x_off"]) + params["W0"]


def _blend(x: np.ndarray, length: float) -> np.ndarray:
    t = np.clip(np.asarray(x) / length, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def shapable_axes(t: GarmentTemplate) -> list[str]:
    return [a for names in SHAPED_AXES.values() for a in names if a in t.axes and a in t.rows]


def _check_params(t: GarmentTemplate, axis_name: str, p: dict) -> None:
    source = t.meta.get("source", t.name)
    if axis_name not in shapable_axes(t):
        raise InputError(
            source,
            f"shaping.{axis_name}",
            f"one of the template's shaping axes ({', '.join(shapable_axes(t))})",
            axis_name,
        )
    for key in ("a1", "a2", "x_off", "W0"):
        if key not in p or not np.isfinite(p[key]):
            raise InputError(
                source, f"shaping.{axis_name}.{key}", "a finite number", p.get(key, "missing")
            )
    kind = _kind(axis_name)
    if kind == "skirt" and not (p["a1"] > 0 and p["a2"] == 0):
        raise InputError(
            source, f"shaping.{axis_name}", "a1 > a2 = 0 for a skirt", (p["a1"], p["a2"])
        )
    if kind != "skirt" and not (p["a1"] <= 0 <= p["a2"]):
        raise InputError(
            source, f"shaping.{axis_name}", "a1 <= 0 <= a2 for sleeves and legs", (p["a1"], p["a2"])
        )
    if p["W0"] <= 0:
        raise InputError(source, f"shaping.{axis_name}.W0", "a positive width", p["W0"])


def target_widths(
    t: GarmentTemplate, axis_name: str, params: dict
) -> tuple[np.ndarray, np.ndarray]:
    """Per row: the width shaping gives it (blended, clamped) and whether it was clamped."""
    rows = t.rows[axis_name]
    w = row_widths(t, axis_name)
    want = width_profile(params, rows.x)
    beta = _blend(rows.x, BLEND[_kind(axis_name)])
    target = w + beta * (want - w)
    lo = rows.min_width if rows.min_width is not None else np.zeros_like(w)
    hi = rows.max_width if rows.max_width is not None else np.full_like(w, np.inf)
    # Rows already outside their limits (in the blend zone) keep their own width.
    lo = np.minimum(lo, w)
    hi = np.maximum(hi, w)
    clamped = (target < lo - 1e-9) | (target > hi + 1e-9)
    return np.clip(target, lo, hi), clamped


def shape(t: GarmentTemplate, params: dict[str, dict]) -> GarmentTemplate:
    """A shaped copy of `t`: `params` maps axis names (sleeve_l, sleeve_r, leg_l, leg_r, skirt) to
    {"a1", "a2", "x_off", "W0"} (metres and metres per metre). Axes not named are left as they
    are. Rows that would come too close to the body or to the other leg are clamped; the copy's
    meta["shaping"] records the parameters and any clamped rows."""
    out = t.copy()
    record = {}
    for axis_name, p in params.items():
        p = {k: float(v) for k, v in p.items()}
        _check_params(t, axis_name, p)
        axis, rows = t.axes[axis_name], t.rows[axis_name]
        target, clamped = target_widths(t, axis_name, p)
        w = row_widths(t, axis_name)
        for k, (x, ids) in enumerate(zip(rows.x, rows.vertices, strict=True)):
            scale = target[k] / w[k]
            if abs(scale - 1.0) < 1e-12:
                continue
            c = axis.origin + x * axis.direction
            out.vertices[ids] = c + scale * (t.vertices[ids] - c)
        record[axis_name] = dict(p, clamped_rows=[int(k) for k in np.flatnonzero(clamped)])
    out.meta["shaping"] = record
    return out


def sample_shaping(rng: np.random.Generator, t: GarmentTemplate, tries: int = 200) -> dict:
    """Parameters for every shaping axis of `t`, uniform in SHAPING_RANGES (restricted to draws
    whose W(x) stays within every row's min/max width beyond the blend zone; left and right
    sleeves or legs share one draw, as real garments are symmetric)."""
    name = t.meta.get("template", t.name)
    axes = shapable_axes(t)
    if not axes:
        return {}
    kinds = {_kind(a) for a in axes}
    key = {"sleeve": "tshirt", "leg": "trousers", "skirt": "skirt"}
    out: dict[str, dict] = {}
    for kind in sorted(kinds):
        ranges = SHAPING_RANGES.get(name if name in SHAPING_RANGES else key[kind])
        names = [a for a in axes if _kind(a) == kind]
        ref = names[0]
        w0 = row_widths(t, ref)[0]
        length = t.axes[ref].length
        for _ in range(tries):
            p = {
                "a1": float(rng.uniform(*ranges["a1"])),
                "a2": float(rng.uniform(*ranges["a2"])),
                "x_off": float(rng.uniform(*ranges["x_off"]) * length),
                "W0": float(rng.uniform(*ranges["w0"]) * w0),
            }
            if all(not target_widths(t, a, p)[1].any() for a in names):
                break
        for a in names:
            out[a] = dict(p)
    return out


def measure_widths(t: GarmentTemplate, axis_name: str, xs) -> np.ndarray:
    """Widths (perimeter / pi) of the garment's cross-sections by planes perpendicular to an axis
    at distances `xs` along it, counting only faces of the axis's region (independent of the row
    structure: the tests use it to check shaping)."""
    import trimesh

    axis = t.axes[axis_name]
    region = t.region_mask(axis.region)
    faces = t.faces[region[t.faces].any(axis=1)]
    mesh = trimesh.Trimesh(t.vertices, faces, process=False)
    out = []
    for x in np.atleast_1d(np.asarray(xs, dtype=np.float64)):
        x = min(x, axis.length - 1e-4)  # a plane through the end row itself grazes the boundary
        origin = axis.origin + x * axis.direction
        segs = trimesh.intersections.mesh_plane(mesh, axis.direction, origin)
        if len(segs) == 0:
            out.append(np.nan)
            continue
        # Keep the loop around the axis (a plane may graze other parts of the region).
        mid = segs.mean(axis=1)
        radial = mid - origin - np.outer((mid - origin) @ axis.direction, axis.direction)
        dist = np.linalg.norm(radial, axis=1)
        keep = dist < 3.0 * np.median(dist)
        out.append(float(np.linalg.norm(segs[keep, 1] - segs[keep, 0], axis=1).sum() / np.pi))
    return np.asarray(out)
