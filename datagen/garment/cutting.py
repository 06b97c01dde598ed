"""Cutting: sleeve, leg, torso (hem) and skirt lengths, and the upper-body variants.

A length cut keeps the rows of an axis up to the one nearest to the requested length (metres along
the axis from its origin) and removes every row beyond it, so the new end is a clean closed loop
and the garment stays one manifold piece. Upper-body templates come in variants (CLOTH3D cuts a
t-shirt template into t-shirts, shirts, polos...):

- ``tshirt``: plain, only lengths;
- ``shirt``: open front, a slit along the front centre line from the neck to the hem, leaving two
  front edges (``front_edge_l``, ``front_edge_r``) a few millimetres apart;
- ``polo``: a placket, a slit from the neck down the front centre line ``placket`` metres long;
- ``top``: the sleeveless top is its own template and only gets a hem length.

The sidecar data (loops, regions, axes, cut lines, rows, uv, panels) follows the renumbered
vertices.
"""

from __future__ import annotations

import numpy as np

from datagen.errors import InputError
from datagen.garment.template import (
    Axis,
    GarmentTemplate,
    RowSet,
    boundary_loops,
)

VARIANTS: dict[str, tuple[str, ...]] = {
    "tshirt": ("tshirt", "shirt", "polo"),
    "top": ("top",),
    "trousers": ("trousers",),
    "skirt": ("skirt",),
}
# Which cut lines a variant uses (left/right pairs get one shared length when sampled).
CUT_AXES: dict[str, tuple[str, ...]] = {
    "tshirt": ("sleeve_l", "sleeve_r", "torso"),
    "shirt": ("sleeve_l", "sleeve_r", "torso"),
    "polo": ("sleeve_l", "sleeve_r", "torso"),
    "top": ("torso",),
    "trousers": ("leg_l", "leg_r"),
    "skirt": ("skirt",),
}
# Sampling ranges per variant and cut line group, as fractions of the template's cut line range
# [min, max] (docs/templates.md): sleeves from cap sleeves to full length, trousers from shorts
# to full length, skirts from mini to long, hems anywhere in the template's range; shirts are
# not cropped and polos have short or elbow sleeves.
CUT_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "tshirt": {"sleeve": (0.0, 1.0), "torso": (0.0, 1.0)},
    "shirt": {"sleeve": (0.0, 1.0), "torso": (0.35, 1.0)},
    "polo": {"sleeve": (0.0, 0.55), "torso": (0.25, 1.0), "placket": (0.10, 0.16)},
    "top": {"torso": (0.0, 1.0)},
    "trousers": {"leg": (0.0, 1.0)},
    "skirt": {"skirt": (0.0, 1.0)},
}
SLIT_GAP = 0.0025  # m: each front edge of a slit moves this far from the centre line
DEFAULT_PLACKET = 0.13


def _group(line: str) -> str:
    return line.split("_")[0]


def _source(t: GarmentTemplate) -> str:
    return str(t.meta.get("source", t.name))


def subset(t: GarmentTemplate, keep: np.ndarray) -> tuple[GarmentTemplate, np.ndarray]:
    """The template restricted to the vertices in the boolean mask `keep` (faces with a removed
    vertex go too; vertices left without faces are removed as well), and the old -> new vertex id
    map (-1 for removed vertices). Loops and rows that lost vertices are dropped: callers rebuild
    the ones they changed."""
    faces = t.faces[keep[t.faces].all(axis=1)]
    used = np.zeros(t.n_vertices, dtype=bool)
    used[faces.ravel()] = True
    keep = keep & used
    new_id = np.full(t.n_vertices, -1, dtype=np.int64)
    new_id[keep] = np.arange(int(keep.sum()))
    out = t.copy()
    out.vertices = t.vertices[keep]
    out.faces = new_id[faces].astype(np.int32)
    out.regions = None if t.regions is None else t.regions[keep]
    out.uv = None if t.uv is None else t.uv[keep]
    out.panel = None if t.panel is None else t.panel[keep]
    out.loops = {k: new_id[v] for k, v in t.loops.items() if np.all(keep[v])}
    rows = {}
    for name, rs in t.rows.items():
        kept = [k for k, ids in enumerate(rs.vertices) if np.all(keep[ids])]
        rows[name] = RowSet(
            rs.x[kept],
            [new_id[rs.vertices[k]] for k in kept],
            None if rs.min_width is None else rs.min_width[kept],
            None if rs.max_width is None else rs.max_width[kept],
        )
    out.rows = rows
    paths = {}
    for name, path in t.paths.items():
        # A path keeps its prefix of surviving vertices.
        alive = keep[path]
        stop = int(np.argmin(alive)) if not alive.all() else len(path)
        if stop >= 2:
            paths[name] = new_id[path[:stop]]
    out.paths = paths
    return out, new_id


def _loop_like(t: GarmentTemplate, ids: np.ndarray) -> np.ndarray:
    """The boundary loop of `t` with the same vertex set as `ids`, in boundary order."""
    target = set(int(i) for i in ids)
    for loop in boundary_loops(t.faces):
        if set(loop.tolist()) == target:
            return loop
    raise ValueError("the row is not a boundary loop")


def cut_axis(t: GarmentTemplate, axis_name: str, length: float) -> GarmentTemplate:
    """Keep the rows of `axis_name` up to the one nearest to `length` metres along the axis and
    remove the rest of the garment beyond it."""
    if axis_name not in t.axes or axis_name not in t.rows:
        raise InputError(
            _source(t), f"axes.{axis_name}", "an axis with rows to cut along", "missing"
        )
    rows = t.rows[axis_name]
    if len(rows.x) == 0:
        raise InputError(_source(t), f"rows.{axis_name}", "at least one row", "none")
    k_last = int(np.argmin(np.abs(rows.x - length)))
    if k_last == len(rows.x) - 1:
        return t.copy()
    end_role = None
    last_set = set(int(i) for i in rows.vertices[-1])
    for role, loop in t.loops.items():
        if set(int(i) for i in loop) == last_set:
            end_role = role
    keep = np.ones(t.n_vertices, dtype=bool)
    for ids in rows.vertices[k_last + 1 :]:
        keep[ids] = False
    kept_row = rows.vertices[k_last]
    # Whatever else of the axis's region lies beyond the kept row goes with the removed rows.
    axis = t.axes[axis_name]
    beyond = axis.position(t.vertices) > rows.x[k_last] + 1e-9
    keep &= ~(beyond & t.region_mask(axis.region))
    keep[kept_row] = True
    out, new_id = subset(t, keep)
    new_row = new_id[kept_row]
    if end_role is not None:
        out.loops[end_role] = _loop_like(out, new_row)
    ax = out.axes[axis_name]
    out.axes[axis_name] = Axis(ax.origin, ax.direction, float(rows.x[k_last]), ax.region)
    for line in out.cut_lines.values():
        if line["axis"] == axis_name:
            line["max"] = min(line["max"], float(rows.x[k_last]))
            line["min"] = min(line["min"], line["max"])
    return out


def _slit(t: GarmentTemplate, variant: str, placket: float) -> GarmentTemplate:
    """Open the front along paths.front_centre: all the way for a shirt, `placket` metres down
    from the neck for a polo."""
    source = _source(t)
    if "front_centre" not in t.paths:
        raise InputError(
            source,
            "paths.front_centre",
            f"the front centre line (neck to hem) that a {variant} is cut along",
            "missing",
        )
    path = np.asarray(t.paths["front_centre"], dtype=np.int64)
    neck, hem = t.loops.get("neck"), t.loops.get("hem")
    if neck is None or path[0] not in set(neck.tolist()):
        raise InputError(
            source, "paths.front_centre", "a path starting on the neck loop", int(path[0])
        )
    if variant == "shirt":
        if hem is None or path[-1] not in set(hem.tolist()):
            raise InputError(
                source, "paths.front_centre", "a path ending on the hem loop", int(path[-1])
            )
        split = path  # every vertex of the line is split
        gap = np.full(len(path), SLIT_GAP)
    else:
        steps = np.linalg.norm(np.diff(t.vertices[path], axis=0), axis=1)
        along = np.concatenate([[0.0], np.cumsum(steps)])
        end = int(np.argmin(np.abs(along - placket)))
        end = max(2, min(end, len(path) - 2))
        split = path[:end]  # the end vertex stays whole: the slit closes there
        gap = SLIT_GAP * (1.0 - along[:end] / along[end])
    # Faces on the right of the line (x < 0) get the copies.
    out = t.copy()
    n = t.n_vertices
    copies = np.arange(n, n + len(split))
    copy_of = dict(zip(split.tolist(), copies.tolist(), strict=True))
    centre_x = t.vertices[t.faces].mean(axis=1)[:, 0]
    faces = out.faces.astype(np.int64)
    for fi in np.flatnonzero(np.isin(faces, split).any(axis=1) & (centre_x < 0)):
        faces[fi] = [copy_of.get(int(v), int(v)) for v in faces[fi]]
    out.faces = faces.astype(np.int32)
    right = t.vertices[split].copy()
    right[:, 0] -= gap
    out.vertices = np.vstack([t.vertices, right])
    out.vertices[split, 0] += gap
    out.regions = None if t.regions is None else np.concatenate([t.regions, t.regions[split]])
    out.uv = None if t.uv is None else np.vstack([t.uv, t.uv[split]])
    out.panel = None if t.panel is None else np.concatenate([t.panel, t.panel[split]])
    out.paths = {}
    # Rows through the line now have both copies; keep them in row order (left copy first).
    for rs in out.rows.values():
        new_rows = []
        for ids in rs.vertices:
            ids = list(ids)
            for v in [v for v in ids if v in copy_of]:
                k = ids.index(v)
                ids.insert(k + 1, copy_of[v])
            new_rows.append(np.asarray(ids, dtype=np.int64))
        rs.vertices = new_rows
    loops = boundary_loops(out.faces)
    if variant == "shirt":
        (big,) = [lp for lp in loops if path[0] in set(lp.tolist())]
        corners = {int(path[0]), copy_of[int(path[0])], int(path[-1]), copy_of[int(path[-1])]}
        pieces = _split_loop(big, corners)
        old_neck, old_hem = set(neck.tolist()), set(hem.tolist())
        named = {}
        for piece in pieces:
            inner = set(piece[1:-1].tolist())
            if inner & old_neck:
                named["neck"] = piece
            elif inner & old_hem:
                named["hem"] = piece
            else:
                # The original vertices stay on the left; the copies went right.
                named["front_edge_l" if int(piece[len(piece) // 2]) < n else "front_edge_r"] = piece
        others = {k: v for k, v in out.loops.items() if k not in ("neck", "hem")}
        out.loops = {**others, **named}
        out.open_loops = ("neck", "hem", "front_edge_l", "front_edge_r")
    else:
        (neck_loop,) = [lp for lp in loops if path[0] in set(lp.tolist())]
        out.loops["neck"] = neck_loop
        end_v = int(path[len(split)])
        # The two sides of the placket, from the neckline down to where the slit closes.
        out.loops["placket_l"] = np.r_[split, end_v]
        out.loops["placket_r"] = np.r_[copies, end_v]
        out.open_loops = ("placket_l", "placket_r")
    return out


def _split_loop(loop: np.ndarray, corners: set[int]) -> list[np.ndarray]:
    """Cut a closed loop at the corner vertices into open pieces (each includes both corners)."""
    at = [i for i, v in enumerate(loop) if int(v) in corners]
    pieces = []
    for k, i in enumerate(at):
        j = at[(k + 1) % len(at)]
        idx = np.arange(i, j + 1 if j > i else j + len(loop) + 1) % len(loop)
        pieces.append(loop[idx])
    return pieces


def cut(t: GarmentTemplate, lengths: dict[str, float], variant: str) -> GarmentTemplate:
    """A cut copy of `t`: `lengths` maps cut line names (sleeve_l, sleeve_r, torso, leg_l, leg_r,
    skirt; plus "placket" for a polo) to metres along their axes; `variant` is tshirt, shirt or
    polo for the t-shirt template, and the template's own name otherwise."""
    name = t.meta.get("template", t.name)
    source = _source(t)
    allowed = VARIANTS.get(name, (name,))
    if variant not in allowed:
        raise InputError(source, "variant", " or ".join(repr(v) for v in allowed), variant)
    if t.meta.get("cut"):
        raise InputError(source, "meta.cut", "an uncut template (cut once)", t.meta["cut"])
    out = t.copy()
    placket = float(lengths.get("placket", DEFAULT_PLACKET))
    for line_name, length in lengths.items():
        if line_name == "placket":
            if variant != "polo":
                raise InputError(
                    source, "lengths.placket", "a placket length only for a polo", variant
                )
            continue
        if line_name not in t.cut_lines:
            raise InputError(
                source,
                f"lengths.{line_name}",
                f"one of the cut lines ({', '.join(t.cut_lines)})",
                line_name,
            )
        line = t.cut_lines[line_name]
        if not (line["min"] - 1e-6 <= length <= line["max"] + 1e-6):
            raise InputError(
                source,
                f"lengths.{line_name}",
                f"a length in [{line['min']:.3f}, {line['max']:.3f}] m",
                length,
            )
        out = cut_axis(out, line["axis"], float(length))
    if variant in ("shirt", "polo"):
        out = _slit(out, variant, placket)
    out.name = variant
    out.meta["template"] = name
    out.meta["cut"] = {"variant": variant, "lengths": {k: float(v) for k, v in lengths.items()}}
    return out


def sample_cuts(rng: np.random.Generator, t: GarmentTemplate, variant: str) -> dict[str, float]:
    """Lengths for every cut line the variant uses, uniform in CUT_RANGES (fractions of each cut
    line's [min, max]); left and right share one length."""
    ranges = CUT_RANGES.get(variant)
    if ranges is None:
        raise InputError(_source(t), "variant", " or ".join(repr(v) for v in CUT_RANGES), variant)
    out: dict[str, float] = {}
    drawn: dict[str, float] = {}
    for line in CUT_AXES[variant]:
        if line not in t.cut_lines:
            continue
        group = _group(line)
        if group not in drawn:
            lo, hi = ranges[group]
            drawn[group] = float(rng.uniform(lo, hi))
        c = t.cut_lines[line]
        out[line] = c["min"] + drawn[group] * (c["max"] - c["min"])
    if variant == "polo":
        out["placket"] = float(rng.uniform(*ranges["placket"]))
    return out
