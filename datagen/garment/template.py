"""Garment templates: the mesh + sidecar data model, its files, and the checks a template must pass.

A template is an OBJ (vertices in metres, triangles) beside a JSON sidecar with the same stem that
names its boundary loops, per-vertex regions, the shaping axes, the cut lines, the rows of vertices
perpendicular to each axis, and the flat pattern coordinates (docs/templates.md describes every
field). `check_template` reports every problem of a template as one precise line naming the file,
what is wrong and where; `datagen templates check` prints them.

This module knows no body model: clearance is checked against body arrays that the caller passes
(the CLI loads the rest body named in the sidecar).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from datagen.errors import InputError

FORMAT = "datagen-garment-template"
VERSION = 1
MIN_CLEARANCE = 0.005  # m: the gap a template keeps from its rest body everywhere
MIN_ANGLE = 20.0  # degrees
EDGE_TOLERANCE = 0.30  # the mean edge length is within 30 % of the resolution
CATEGORIES = ("upper", "lower", "full")

# Boundary loops each garment must name (loops of a user's template may add others).
REQUIRED_LOOPS: dict[str, tuple[str, ...]] = {
    "tshirt": ("neck", "hem", "sleeve_l_end", "sleeve_r_end"),
    "polo": ("neck", "hem", "sleeve_l_end", "sleeve_r_end"),
    "shirt": ("neck", "hem", "sleeve_l_end", "sleeve_r_end", "front_edge_l", "front_edge_r"),
    "top": ("neck", "hem", "armhole_l", "armhole_r"),
    "trousers": ("waist", "leg_l_end", "leg_r_end"),
    "skirt": ("waist", "hem"),
    "jumpsuit": ("neck", "leg_l_end", "leg_r_end"),
    "dress": ("neck", "hem"),
}


@dataclass
class Axis:
    """A shaping/cutting axis: x = (p - origin) . direction is the distance along it."""

    origin: np.ndarray  # (3,)
    direction: np.ndarray  # (3,) unit
    length: float  # m, from the origin to the garment's end along the axis
    region: str  # the region whose rows lie along this axis

    def position(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.direction


@dataclass
class RowSet:
    """Rows of vertices perpendicular to one axis, ordered along it (row 0 at the junction)."""

    x: np.ndarray  # (R,) m along the axis
    vertices: list[np.ndarray]  # R ordered closed loops of vertex ids
    min_width: np.ndarray | None = None  # (R,) m: narrowest width keeping clearance to the body
    max_width: np.ndarray | None = None  # (R,) m: widest before the row meets another part


@dataclass
class GarmentTemplate:
    vertices: np.ndarray  # (V, 3) float64, metres, around the rest body in the T-pose
    faces: np.ndarray  # (T, 3) int32, normals pointing away from the body
    name: str  # tshirt, top, trousers, skirt; after cutting/sewing: shirt, polo, jumpsuit, dress
    category: str  # "upper" | "lower" | "full" (sewn)
    gender: str
    loops: dict[str, np.ndarray] = field(default_factory=dict)  # role -> ordered vertex ids
    region_names: tuple[str, ...] = ()
    regions: np.ndarray | None = None  # (V,) int16 into region_names
    axes: dict[str, Axis] = field(default_factory=dict)
    cut_lines: dict[str, dict] = field(default_factory=dict)  # name -> {axis, min, max}
    uv: np.ndarray | None = None  # (V, 2) flat pattern coordinates, metres
    panel: np.ndarray | None = None  # (V,) int16 panel id
    body: dict = field(default_factory=dict)  # {"model", "gender", "shape": {name: value}}
    resolution: float = 0.01
    meta: dict = field(default_factory=dict)
    rows: dict[str, RowSet] = field(default_factory=dict)  # axis name -> rows along it
    paths: dict[str, np.ndarray] = field(default_factory=dict)  # e.g. front_centre, neck->hem
    open_loops: tuple[str, ...] = ()  # loop roles that are open boundary paths
    panel_names: tuple[str, ...] = ()

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    def region_mask(self, name: str) -> np.ndarray:
        if self.regions is None or name not in self.region_names:
            return np.zeros(self.n_vertices, dtype=bool)
        return self.regions == self.region_names.index(name)

    def copy(self) -> GarmentTemplate:
        return replace(
            self,
            vertices=self.vertices.copy(),
            faces=self.faces.copy(),
            loops={k: v.copy() for k, v in self.loops.items()},
            regions=None if self.regions is None else self.regions.copy(),
            axes={
                k: Axis(a.origin.copy(), a.direction.copy(), a.length, a.region)
                for k, a in self.axes.items()
            },
            cut_lines={k: dict(v) for k, v in self.cut_lines.items()},
            uv=None if self.uv is None else self.uv.copy(),
            panel=None if self.panel is None else self.panel.copy(),
            body=json.loads(json.dumps(self.body)),
            meta=json.loads(json.dumps(self.meta)),
            rows={
                k: RowSet(
                    r.x.copy(),
                    [v.copy() for v in r.vertices],
                    None if r.min_width is None else r.min_width.copy(),
                    None if r.max_width is None else r.max_width.copy(),
                )
                for k, r in self.rows.items()
            },
            paths={k: v.copy() for k, v in self.paths.items()},
        )


# -- files -------------------------------------------------------------------------------------


def template_paths(path: str | Path) -> tuple[Path, Path]:
    """(obj, json) paths of a template given either file or the common stem."""
    path = Path(path)
    if path.suffix.lower() in (".obj", ".json"):
        stem = path.with_suffix("")
    else:
        stem = path
    return stem.with_suffix(".obj"), stem.with_suffix(".json")


def expand_template_paths(paths: Iterable[str | Path]) -> list[tuple[Path, Path]]:
    """(obj, json) of every template the paths name, in order, each once: a file or stem names
    one (checked later, so a missing one is reported as such), a folder every .obj under it
    (`datagen templates check templates/*` checks both genders' folders)."""
    out: list[tuple[Path, Path]] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(path.rglob("*.obj"))
            if not found:
                raise InputError(path, None, "a folder holding template .obj files",
                                 "no .obj file in it")
            out += [template_paths(p) for p in found]
        else:
            out.append(template_paths(path))
    return list(dict.fromkeys(out))


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an OBJ file (polygons are split into fans; uv/normal indices and
    other statements are ignored)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "an existing OBJ file", "no such file")
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                try:
                    verts.append([float(p) for p in parts[1:4]])
                except ValueError:
                    raise InputError(
                        path, f"line {lineno}", "a vertex 'v x y z'", line.strip()
                    ) from None
                if len(verts[-1]) != 3:
                    raise InputError(path, f"line {lineno}", "a vertex 'v x y z'", line.strip())
                if not all(math.isfinite(c) for c in verts[-1]):
                    raise InputError(path, f"line {lineno}", "a vertex of finite coordinates",
                                     line.strip())
            elif parts[0] == "f":
                try:
                    ids = [int(p.split("/")[0]) for p in parts[1:]]
                except ValueError:
                    raise InputError(
                        path, f"line {lineno}", "a face 'f i j k'", line.strip()
                    ) from None
                if len(ids) < 3:
                    raise InputError(path, f"line {lineno}", "a face of 3+ vertices", line.strip())
                n_seen = len(verts)
                ids = [i - 1 if i > 0 else n_seen + i for i in ids]  # 1-based or relative
                for k in range(1, len(ids) - 1):
                    faces.append([ids[0], ids[k], ids[k + 1]])
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return v, f


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, header: str = "") -> None:
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces)]
    Path(path).write_text("\n".join(lines) + "\n")


def _ids(value) -> list[int]:
    return [int(i) for i in np.asarray(value).ravel()]


def sidecar_dict(t: GarmentTemplate) -> dict:
    """The JSON sidecar of a template (docs/templates.md, "Sidecar")."""
    out: dict = {
        "format": FORMAT,
        "version": VERSION,
        "name": t.name,
        "category": t.category,
        "gender": t.gender,
        "units": "m",
        "resolution": float(t.resolution),
        "body": t.body,
        "vertex_count": t.n_vertices,
        "face_count": int(len(t.faces)),
        "loops": {k: _ids(v) for k, v in t.loops.items()},
        "open_loops": list(t.open_loops),
        "regions": {
            "names": list(t.region_names),
            "labels": _ids(t.regions) if t.regions is not None else [],
        },
        "axes": {
            k: {
                "origin": [round(float(c), 6) for c in a.origin],
                "direction": [round(float(c), 8) for c in a.direction],
                "length": round(float(a.length), 6),
                "region": a.region,
            }
            for k, a in t.axes.items()
        },
        "cut_lines": {
            k: {
                "axis": c["axis"],
                "min": round(float(c["min"]), 6),
                "max": round(float(c["max"]), 6),
            }
            for k, c in t.cut_lines.items()
        },
        "rows": {
            k: {
                "x": [round(float(x), 6) for x in r.x],
                "min_width": None
                if r.min_width is None
                else [round(float(w), 6) for w in r.min_width],
                "max_width": None
                if r.max_width is None
                else [round(float(w), 6) for w in r.max_width],
                "vertices": [_ids(row) for row in r.vertices],
            }
            for k, r in t.rows.items()
        },
        "paths": {k: _ids(v) for k, v in t.paths.items()},
        "panel_names": list(t.panel_names),
        "panel": _ids(t.panel) if t.panel is not None else None,
        "uv": None if t.uv is None else [[round(float(a), 5), round(float(b), 5)] for a, b in t.uv],
        "meta": t.meta,
    }
    return out


def save_template(t: GarmentTemplate, path: str | Path) -> tuple[Path, Path]:
    """Write `path`.obj and `path`.json (any suffix of `path` is replaced)."""
    obj_path, json_path = template_paths(path)
    obj_path.parent.mkdir(parents=True, exist_ok=True)
    header = (
        f"datagen garment template '{t.name}' ({t.gender}), metres, z up, facing -y\n"
        f"sidecar: {json_path.name}"
    )
    write_obj(obj_path, t.vertices, t.faces, header)
    text = json.dumps(sidecar_dict(t), separators=(",", ":"))
    # One top-level key per line keeps diffs of the committed data readable.
    data = json.loads(text)
    body = ",\n".join(
        f"{json.dumps(k)}:{json.dumps(v, separators=(',', ':'))}" for k, v in data.items()
    )
    json_path.write_text("{\n" + body + "\n}\n")
    return obj_path, json_path


def _need(data: dict, key: str, source: Path, expected: str):
    if key not in data:
        raise InputError(source, key, expected, "missing")
    return data[key]


def load_sidecar(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "an existing JSON sidecar beside the OBJ", "no such file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"line {exc.lineno}", "valid JSON", exc.msg) from None
    if not isinstance(data, dict):
        raise InputError(path, None, "a JSON object", type(data).__name__)
    fmt = _need(data, "format", path, f"'{FORMAT}'")
    if fmt != FORMAT:
        raise InputError(path, "format", f"'{FORMAT}'", fmt)
    version = _need(data, "version", path, f"{VERSION}")
    if version != VERSION:
        raise InputError(path, "version", f"{VERSION}", version)
    units = data.get("units", "m")
    if units != "m":
        raise InputError(path, "units", "'m' (metres)", units)
    return data


def template_from_dict(
    data: dict, vertices: np.ndarray, faces: np.ndarray, source: Path
) -> GarmentTemplate:
    """Build a template from a parsed sidecar and its mesh. Only the types and shapes are checked
    here; `check_template` checks the contents."""

    def arr_ids(value, field_name: str) -> np.ndarray:
        try:
            return np.asarray(value, dtype=np.int64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(source, field_name, "a list of vertex ids", value) from None

    name = _need(data, "name", source, "the garment name")
    category = _need(data, "category", source, "'upper' or 'lower'")
    if category not in CATEGORIES:
        raise InputError(source, "category", " or ".join(repr(c) for c in CATEGORIES), category)
    loops_raw = data.get("loops", {})
    if not isinstance(loops_raw, dict):
        raise InputError(source, "loops", "a mapping of role -> vertex ids", loops_raw)
    loops = {str(k): arr_ids(v, f"loops.{k}") for k, v in loops_raw.items()}
    regions_raw = data.get("regions", {}) or {}
    region_names = tuple(regions_raw.get("names", []))
    labels = regions_raw.get("labels")
    regions = arr_ids(labels, "regions.labels").astype(np.int16) if labels else None
    axes = {}
    for k, a in (data.get("axes") or {}).items():
        try:
            origin = np.asarray(a["origin"], dtype=np.float64).reshape(3)
            direction = np.asarray(a["direction"], dtype=np.float64).reshape(3)
            axes[str(k)] = Axis(origin, direction, float(a["length"]), str(a["region"]))
        except (KeyError, TypeError, ValueError):
            raise InputError(
                source, f"axes.{k}", "{origin: [x,y,z], direction: [x,y,z], length, region}", a
            ) from None
    cut_lines = {}
    for k, c in (data.get("cut_lines") or {}).items():
        try:
            cut_lines[str(k)] = {
                "axis": str(c["axis"]),
                "min": float(c["min"]),
                "max": float(c["max"]),
            }
        except (KeyError, TypeError, ValueError):
            raise InputError(source, f"cut_lines.{k}", "{axis, min, max}", c) from None
    rows = {}
    for k, r in (data.get("rows") or {}).items():
        try:
            xs = np.asarray(r["x"], dtype=np.float64)
            verts = [arr_ids(row, f"rows.{k}.vertices") for row in r["vertices"]]
            lo, hi = r.get("min_width"), r.get("max_width")
            rows[str(k)] = RowSet(
                xs,
                verts,
                None if lo is None else np.asarray(lo, dtype=float),
                None if hi is None else np.asarray(hi, dtype=float),
            )
        except (KeyError, TypeError, ValueError):
            raise InputError(source, f"rows.{k}", "{x: [...], vertices: [[...], ...]}", r) from None
        if len(xs) != len(verts):
            raise InputError(source, f"rows.{k}", f"{len(xs)} rows of vertices", len(verts))
    uv_raw = data.get("uv")
    uv = None
    if uv_raw is not None:
        try:
            uv = np.asarray(uv_raw, dtype=np.float64).reshape(-1, 2)
        except (TypeError, ValueError):
            raise InputError(
                source, "uv", "a list of [u, v] pairs", type(uv_raw).__name__
            ) from None
    panel_raw = data.get("panel")
    panel = None if panel_raw is None else arr_ids(panel_raw, "panel").astype(np.int16)
    return GarmentTemplate(
        vertices=np.asarray(vertices, dtype=np.float64),
        faces=np.asarray(faces, dtype=np.int32).reshape(-1, 3),
        name=str(name),
        category=str(category),
        gender=str(data.get("gender", "")),
        loops=loops,
        region_names=region_names,
        regions=regions,
        axes=axes,
        cut_lines=cut_lines,
        uv=uv,
        panel=panel,
        body=dict(data.get("body") or {}),
        resolution=float(data.get("resolution", 0.01)),
        meta=dict(data.get("meta") or {}),
        rows=rows,
        paths={str(k): arr_ids(v, f"paths.{k}") for k, v in (data.get("paths") or {}).items()},
        open_loops=tuple(data.get("open_loops") or ()),
        panel_names=tuple(data.get("panel_names") or ()),
    )


def load_template(path: str | Path) -> GarmentTemplate:
    """Load a template from its OBJ or JSON path (or their common stem)."""
    obj_path, json_path = template_paths(path)
    data = load_sidecar(json_path)
    vertices, faces = read_obj(obj_path)
    t = template_from_dict(data, vertices, faces, json_path)
    t.meta.setdefault("source", str(obj_path))
    return t


def to_garment(t: GarmentTemplate, fabric: str, name: str | None = None):
    """The simulator's hand-off type for this template (rest metric = the template's geometry)."""
    from datagen.types import Garment

    meta = dict(t.meta)
    meta.setdefault("template", t.meta.get("template", t.name))
    return Garment(
        name=name or t.name,
        category=t.name,
        vertices=t.vertices.copy(),
        faces=t.faces.astype(np.int32).copy(),
        fabric=fabric,
        uv=None if t.uv is None else t.uv.copy(),
        loops={k: v.copy() for k, v in t.loops.items()},
        regions=None if t.regions is None else t.regions.astype(np.int16).copy(),
        region_names=tuple(t.region_names),
        meta=meta,
    )


# -- mesh analysis -----------------------------------------------------------------------------


def edge_table(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) sorted, the number of faces on each, and per directed
    half-edge (3T,) its edge id (face t's half-edges are 3t, 3t+1, 3t+2)."""
    f = np.asarray(faces, dtype=np.int64)
    half = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    key = np.sort(half, axis=1)
    edges, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return edges, counts, inverse.reshape(-1)


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Directed boundary half-edges (B, 2), in the direction their face traverses them."""
    f = np.asarray(faces, dtype=np.int64)
    half = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    _, counts, inverse = edge_table(f)
    return half[counts[inverse] == 1]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops as ordered vertex ids (on a vertex-manifold boundary)."""
    half = boundary_edges(faces)
    nxt: dict[int, int] = {}
    for a, b in half:
        nxt[int(a)] = int(b)
    loops = []
    seen: set[int] = set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        cur = nxt[start]
        while cur != start and cur in nxt and cur not in seen:
            loop.append(cur)
            seen.add(cur)
            cur = nxt[cur]
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def connected_pieces(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Component label per face (faces sharing an edge or a vertex are connected)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    _, labels = connected_components(graph, directed=False)
    return labels[f[:, 0]]


def triangle_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, 3) interior angles in degrees."""
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    out = np.empty(p.shape[:2])
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(
            np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300
        )
        out[:, k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = np.asarray(vertices)[np.asarray(faces)]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = np.asarray(vertices)[np.asarray(faces)]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def _orient(a, b, c, d):
    """Signed volume det[b-a, c-a, d-a] (row-wise)."""
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)


def self_intersections(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(K, 2) pairs of faces that share no vertex and cross each other (an edge of one passes
    through the interior of the other)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tri = v[f]
    centre = tri.mean(axis=1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    tree = cKDTree(centre)
    # Candidates: centres closer than the sum of the reaches. Most faces are of a similar size;
    # the few large ones (a user's mesh may have some) are paired separately so that one big
    # face does not make every pair a candidate.
    small = reach <= 3.0 * float(np.median(reach))
    r_small = float(reach[small].max()) if small.any() else 0.0
    found = [tree.query_pairs(2.0 * r_small + 1e-12, output_type="ndarray")]
    big = np.flatnonzero(~small)
    if len(big):
        hits = tree.query_ball_point(centre[big], reach[big] + float(reach.max()) + 1e-12)
        found += [
            np.array([[min(b, k), max(b, k)] for k in hit if k != b], dtype=np.int64).reshape(-1, 2)
            for b, hit in zip(big, hits, strict=True)
        ]
    pairs = np.unique(np.concatenate(found).reshape(-1, 2), axis=0)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    i, j = pairs[:, 0], pairs[:, 1]
    keep = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    shared = (f[i][:, :, None] == f[j][:, None, :]).any(axis=(1, 2))
    pairs = pairs[keep & ~shared]
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    scale = float(np.mean(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1))) ** 3
    eps = 1e-10 * scale

    def crosses(seg, tris):
        # seg: (P, 2, 3) segments, tris: (P, 3, 3)
        p, q = seg[:, 0], seg[:, 1]
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        s1 = _orient(a, b, c, p)
        s2 = _orient(a, b, c, q)
        opposite = ((s1 > eps) & (s2 < -eps)) | ((s1 < -eps) & (s2 > eps))
        o1 = _orient(p, q, a, b)
        o2 = _orient(p, q, b, c)
        o3 = _orient(p, q, c, a)
        inside = ((o1 > eps) & (o2 > eps) & (o3 > eps)) | ((o1 < -eps) & (o2 < -eps) & (o3 < -eps))
        return opposite & inside

    hit = np.zeros(len(pairs), dtype=bool)
    ti, tj = tri[pairs[:, 0]], tri[pairs[:, 1]]
    for k in range(3):
        e_i = np.stack([ti[:, k], ti[:, (k + 1) % 3]], axis=1)
        e_j = np.stack([tj[:, k], tj[:, (k + 1) % 3]], axis=1)
        hit |= crosses(e_i, tj)
        hit |= crosses(e_j, ti)
    return pairs[hit]


class BodyProximity:
    """Signed distances from points to a closed body mesh: a k-d tree over a dense sampling of the
    surface finds candidates, exact point-triangle distances settle the close ones."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, spacing: float = 0.004) -> None:
        import trimesh
        from scipy.spatial import cKDTree

        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        sv, sf = trimesh.remesh.subdivide_to_size(self.vertices, self.faces, max_edge=spacing)
        dense = trimesh.Trimesh(sv, sf, process=False)
        self.points = np.asarray(dense.vertices)
        self.normals = np.asarray(dense.vertex_normals)
        self.spacing = spacing
        self.tree = cKDTree(self.points)

    def signed_distance(self, points: np.ndarray, exact_below: float = 0.012) -> np.ndarray:
        """Positive outside the body, negative inside; exact where |d| < exact_below."""
        import trimesh

        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        d, idx = self.tree.query(pts)
        sign = np.sign(np.einsum("ij,ij->i", pts - self.points[idx], self.normals[idx]))
        sign[sign == 0] = 1.0
        out = d * sign
        near = np.flatnonzero(d < exact_below)
        if len(near):
            closest, dist, tri = trimesh.proximity.closest_point(self.mesh, pts[near])
            normal = self.mesh.face_normals[tri]
            s = np.sign(np.einsum("ij,ij->i", pts[near] - closest, normal))
            s[s == 0] = 1.0
            out[near] = dist * s
        return out

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest dense surface sample (positions, outward normals) of each point."""
        _, idx = self.tree.query(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        return self.points[idx], self.normals[idx]


# -- checks ------------------------------------------------------------------------------------


def _units_problem(obj_name: str, vertices: np.ndarray) -> str | None:
    if len(vertices) == 0:
        return f"{obj_name}: the mesh has no vertices"
    ext = vertices.max(axis=0) - vertices.min(axis=0)
    size = float(ext.max())
    if 0.2 <= size <= 2.0:
        return None
    shown = " x ".join(f"{e:.3g}" for e in ext)
    if 20.0 <= size <= 200.0:
        hint = "looks like centimetres"
    elif 200.0 < size <= 2000.0:
        hint = "looks like millimetres"
    elif 2.0 < size < 20.0:
        hint = "looks like decimetres or a scaled mesh"
    else:
        hint = "not a garment-sized mesh"
    return f"{obj_name}: bounding box {shown} units, expected metres (a garment is 0.2-2 m): {hint}"


def check_mesh(
    obj_name: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    resolution: float | None = None,
    intersections: bool = True,
) -> list[str]:
    """Topology and element-quality problems of a garment mesh."""
    problems: list[str] = []
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return [f"{obj_name}: the mesh has no faces"]
    bad = np.flatnonzero((f < 0).any(axis=1) | (f >= len(v)).any(axis=1))
    if len(bad):
        return [
            f"{obj_name}: {len(bad)} faces name vertices outside 1..{len(v)} "
            f"(first: face {bad[0]} with vertices {f[bad[0]].tolist()})"
        ]
    units = _units_problem(obj_name, v)
    if units:
        problems.append(units)
    repeated = np.flatnonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]))
    if len(repeated):
        problems.append(
            f"{obj_name}: {len(repeated)} degenerate faces repeat a vertex "
            f"(first: face {repeated[0]})"
        )
    unused = np.setdiff1d(np.arange(len(v)), f.ravel())
    if len(unused):
        problems.append(
            f"{obj_name}: {len(unused)} vertices are used by no face (first: vertex {unused[0]})"
        )
    edges, counts, inverse = edge_table(f)
    nm = np.flatnonzero(counts > 2)
    if len(nm):
        a, b = edges[nm[0]]
        problems.append(
            f"{obj_name}: {len(nm)} non-manifold edges (first at vertices {a}-{b}, "
            f"shared by {counts[nm[0]]} faces)"
        )
    # Orientation: the two faces of an interior edge traverse it in opposite directions.
    half = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    forward = half[:, 0] < half[:, 1]
    fwd_count = np.bincount(inverse, weights=forward, minlength=len(edges))
    two = counts == 2
    same_dir = two & ((fwd_count == 2) | (fwd_count == 0))
    if np.any(same_dir):
        k = np.flatnonzero(same_dir)
        a, b = edges[k[0]]
        problems.append(
            f"{obj_name}: inconsistent face orientation at {len(k)} edges "
            f"(first at vertices {a}-{b})"
        )
    pieces = connected_pieces(len(v), f)
    n_pieces = len(np.unique(pieces))
    if n_pieces != 1:
        sizes = np.bincount(pieces)
        sizes = sorted(sizes[sizes > 0].tolist(), reverse=True)
        problems.append(
            f"{obj_name}: {n_pieces} connected pieces, expected exactly 1 "
            f"(faces per piece: {', '.join(str(s) for s in sizes[:6])})"
        )
    areas = triangle_areas(v, f)
    lengths = np.linalg.norm(v[edges[:, 1]] - v[edges[:, 0]], axis=1)
    mean_edge = float(lengths.mean())
    tiny = np.flatnonzero(areas < 1e-3 * mean_edge**2)
    if len(tiny):
        problems.append(
            f"{obj_name}: {len(tiny)} near-zero-area triangles (first: face {tiny[0]}, "
            f"area {areas[tiny[0]]:.2e} m^2)"
        )
    angles = triangle_angles(v, f).min(axis=1)
    worst = int(np.argmin(angles))
    if angles[worst] < MIN_ANGLE:
        n_bad = int(np.sum(angles < MIN_ANGLE))
        c = v[f[worst]].mean(axis=0)
        problems.append(
            f"{obj_name}: {n_bad} triangles with an angle below {MIN_ANGLE:g} degrees "
            f"(worst {angles[worst]:.1f} at face {worst}, near ({c[0]:.3f}, {c[1]:.3f}, "
            f"{c[2]:.3f}))"
        )
    if resolution:
        if abs(mean_edge - resolution) > EDGE_TOLERANCE * resolution:
            problems.append(
                f"{obj_name}: mean edge length {mean_edge:.4f} m, expected within "
                f"{EDGE_TOLERANCE:.0%} of the resolution {resolution:g} m"
            )
    if intersections and not nm.size and units is None:
        pairs = self_intersections(v, f)
        if len(pairs):
            problems.append(
                f"{obj_name}: {len(pairs)} self-intersecting triangle pairs "
                f"(first: faces {pairs[0, 0]} and {pairs[0, 1]})"
            )
    return problems


def check_clearance(
    obj_name: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    body: BodyProximity,
    min_clearance: float = MIN_CLEARANCE,
) -> list[str]:
    """Penetration and clearance below `min_clearance` at vertices and face centres, and normals
    that point towards the body."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    problems = []
    centres = v[f].mean(axis=1)
    d_v = body.signed_distance(v)
    d_c = body.signed_distance(centres)
    inside = np.flatnonzero(d_v < 0)
    if len(inside):
        k = inside[np.argmin(d_v[inside])]
        p = v[k]
        problems.append(
            f"{obj_name}: {len(inside)} vertices inside the body (deepest: vertex {k} at "
            f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}), {-1000 * d_v[k]:.1f} mm deep)"
        )
    low = np.flatnonzero((d_v >= 0) & (d_v < min_clearance))
    if len(low):
        k = low[np.argmin(d_v[low])]
        p = v[k]
        problems.append(
            f"{obj_name}: clearance to the body {1000 * d_v[k]:.1f} mm at vertex {k} "
            f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}), expected >= {1000 * min_clearance:.0f} mm "
            f"({len(low)} vertices below)"
        )
    low_c = np.flatnonzero(d_c < min_clearance)
    if len(low_c) and not len(low) and not len(inside):
        k = low_c[np.argmin(d_c[low_c])]
        problems.append(
            f"{obj_name}: clearance to the body {1000 * d_c[k]:.1f} mm at the centre of face {k}, "
            f"expected >= {1000 * min_clearance:.0f} mm ({len(low_c)} faces below)"
        )
    # Normals point away from the body: compare with the direction from the nearest body point.
    q, _ = body.nearest(centres)
    normals = face_normals(v, f)
    towards = np.einsum("ij,ij->i", normals, centres - q) < 0
    share = float(np.mean(towards))
    if share > 0.05:
        k = int(np.flatnonzero(towards)[0])
        problems.append(
            f"{obj_name}: {100 * share:.0f}% of the face normals point towards the body "
            f"(first: face {k}); they must point away from it"
        )
    return problems


def _loop_problems(json_name: str, t: GarmentTemplate) -> list[str]:
    problems = []
    n = t.n_vertices
    f = np.asarray(t.faces, dtype=np.int64)
    half = boundary_edges(f) if len(f) else np.zeros((0, 2), dtype=np.int64)
    boundary_set = {(int(a), int(b)) for a, b in half} | {(int(b), int(a)) for a, b in half}
    boundary_vertices = set(half.ravel().tolist())
    required = REQUIRED_LOOPS.get(t.name)
    if required:
        for role in required:
            if role not in t.loops:
                problems.append(
                    f"{json_name}: loops has no '{role}', required for a {t.name} "
                    f"(has: {', '.join(sorted(t.loops)) or 'none'})"
                )
    for role in t.open_loops:
        if role not in t.loops:
            problems.append(f"{json_name}: open_loops names '{role}', which loops does not have")
    covered: set[tuple[int, int]] = set()
    for role, loop in t.loops.items():
        loop = np.asarray(loop, dtype=np.int64)
        if len(loop) < 3 and role not in t.open_loops:
            problems.append(f"{json_name}: loops.{role} has {len(loop)} vertices, expected >= 3")
            continue
        out = loop[(loop < 0) | (loop >= n)]
        if len(out):
            problems.append(
                f"{json_name}: loops.{role} names vertex {int(out[0])}, the mesh has {n} vertices"
            )
            continue
        off = [int(i) for i in loop if int(i) not in boundary_vertices]
        if off:
            problems.append(
                f"{json_name}: loops.{role} is not on the boundary: vertex {off[0]} is interior "
                f"({len(off)} of {len(loop)} vertices)"
            )
            continue
        closed = role not in t.open_loops
        pairs = list(zip(loop[:-1], loop[1:], strict=True))
        if closed:
            pairs.append((loop[-1], loop[0]))
        gaps = [(int(a), int(b)) for a, b in pairs if (int(a), int(b)) not in boundary_set]
        if gaps:
            a, b = gaps[0]
            what = (
                "not closed" if closed and gaps[-1] == (int(loop[-1]), int(loop[0])) else ("broken")
            )
            problems.append(
                f"{json_name}: loops.{role} is {what}: vertices {a} and {b} are not joined by a "
                f"boundary edge ({len(gaps)} gaps)"
            )
            continue
        covered |= {(int(a), int(b)) for a, b in pairs} | {(int(b), int(a)) for a, b in pairs}
    if not problems and t.loops:
        missing = [tuple(e) for e in half.tolist() if (int(e[0]), int(e[1])) not in covered]
        if missing:
            a, b = missing[0]
            p = t.vertices[a]
            problems.append(
                f"{json_name}: {len(missing)} boundary edges belong to no named loop (first at "
                f"vertices {a}-{b} near ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}))"
            )
    return problems


def check_sidecar(json_name: str, t: GarmentTemplate) -> list[str]:
    """Consistency of the sidecar with the mesh."""
    problems = _loop_problems(json_name, t)
    n = t.n_vertices
    if t.regions is None or not len(t.region_names):
        problems.append(f"{json_name}: regions has no names or labels")
    else:
        if len(t.regions) != n:
            problems.append(
                f"{json_name}: regions.labels has {len(t.regions)} entries, the mesh has {n} "
                f"vertices"
            )
        elif len(t.regions) and (t.regions.min() < 0 or t.regions.max() >= len(t.region_names)):
            k = int(np.flatnonzero((t.regions < 0) | (t.regions >= len(t.region_names)))[0])
            problems.append(
                f"{json_name}: regions.labels[{k}] = {int(t.regions[k])}, expected 0.."
                f"{len(t.region_names) - 1} (an index into regions.names)"
            )
    for name, axis in t.axes.items():
        norm = float(np.linalg.norm(axis.direction))
        if abs(norm - 1.0) > 1e-4:
            problems.append(f"{json_name}: axes.{name}.direction has length {norm:.4f}, expected 1")
        if not axis.length > 0:
            problems.append(f"{json_name}: axes.{name}.length is {axis.length}, expected > 0")
        if axis.region not in t.region_names:
            problems.append(
                f"{json_name}: axes.{name}.region '{axis.region}' is not in regions.names"
            )
    for name, c in t.cut_lines.items():
        if c["axis"] not in t.axes:
            problems.append(f"{json_name}: cut_lines.{name}.axis '{c['axis']}' is not in axes")
            continue
        length = t.axes[c["axis"]].length
        if not (0 <= c["min"] <= c["max"] <= length + 1e-6):
            problems.append(
                f"{json_name}: cut_lines.{name} spans {c['min']:.3f}..{c['max']:.3f} m, expected "
                f"0 <= min <= max <= the axis length {length:.3f} m"
            )
    for name, rows in t.rows.items():
        if name not in t.axes:
            problems.append(f"{json_name}: rows.{name} belongs to no axis")
        for k, row in enumerate(rows.vertices):
            if len(row) and (row.min() < 0 or row.max() >= n):
                bad = int(row[(row < 0) | (row >= n)][0])
                problems.append(
                    f"{json_name}: rows.{name}.vertices[{k}] names vertex {bad}, the mesh has "
                    f"{n} vertices"
                )
                break
        if len(rows.x) > 1 and np.any(np.diff(rows.x) <= 0):
            problems.append(f"{json_name}: rows.{name}.x is not increasing along the axis")
        for field_name in ("min_width", "max_width"):
            w = getattr(rows, field_name)
            if w is not None and len(w) != len(rows.x):
                problems.append(
                    f"{json_name}: rows.{name}.{field_name} has {len(w)} entries for "
                    f"{len(rows.x)} rows"
                )
    for name, path in t.paths.items():
        if len(path) and (path.min() < 0 or path.max() >= n):
            problems.append(f"{json_name}: paths.{name} names a vertex outside 0..{n - 1}")
    if t.uv is not None and len(t.uv) != n:
        problems.append(f"{json_name}: uv has {len(t.uv)} entries, the mesh has {n} vertices")
    if t.panel is not None and len(t.panel) != n:
        problems.append(f"{json_name}: panel has {len(t.panel)} entries, the mesh has {n} vertices")
    return problems


def check_template(
    path_or_template: str | Path | GarmentTemplate,
    body_vertices: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    body: BodyProximity | None = None,
) -> list[str]:
    """Every problem of a template, one precise line each (an empty list: the template is fine).

    Checks the files and the sidecar's fields, topology (edge-manifold, one piece, consistent
    orientation), element quality (minimum angle, mean edge length against `resolution`, no
    near-zero-area triangles), self-intersections, loops (closed, on the boundary, every boundary
    edge named), regions, axes, cut lines, rows, and, when a body is given (arrays or a prepared
    `BodyProximity`), clearance >= 5 mm everywhere and normals pointing away from the body.
    """
    if isinstance(path_or_template, GarmentTemplate):
        t = path_or_template
        source = t.meta.get("source")
        stem = Path(source).with_suffix("") if source else Path(t.name)
        obj_name, json_name = f"{stem.name}.obj", f"{stem.name}.json"
    else:
        obj_path, json_path = template_paths(path_or_template)
        obj_name, json_name = obj_path.name, json_path.name
        try:
            data = load_sidecar(json_path)
            v, f = read_obj(obj_path)
        except InputError as exc:
            return [str(exc)]
        count = data.get("vertex_count")
        if count is not None and count != len(v):
            return [
                f"{json_name}: vertex_count is {count}, {obj_name} has {len(v)} vertices "
                f"(the sidecar belongs to another mesh)"
            ]
        try:
            t = template_from_dict(data, v, f, json_path)
        except InputError as exc:
            return [str(exc)]
    problems = check_mesh(obj_name, t.vertices, t.faces, t.resolution)
    problems += check_sidecar(json_name, t)
    fatal = any(("non-manifold" in p or "outside 1.." in p or "units" in p) for p in problems)
    if not fatal:
        if body is None and body_vertices is not None and body_faces is not None:
            body = BodyProximity(body_vertices, body_faces)
        if body is not None:
            problems += check_clearance(obj_name, t.vertices, t.faces, body)
    return problems


def mesh_stats(t: GarmentTemplate, body: BodyProximity | None = None) -> dict:
    """Numbers reported by `datagen templates build/check` and docs/templates.md."""
    edges, _, _ = edge_table(t.faces)
    lengths = np.linalg.norm(t.vertices[edges[:, 1]] - t.vertices[edges[:, 0]], axis=1)
    out = {
        "vertices": t.n_vertices,
        "faces": int(len(t.faces)),
        "mean_edge": float(lengths.mean()),
        "min_angle": float(triangle_angles(t.vertices, t.faces).min()),
    }
    if body is not None:
        centres = t.vertices[t.faces].mean(axis=1)
        d = np.concatenate([body.signed_distance(t.vertices), body.signed_distance(centres)])
        out["min_clearance"] = float(d.min())
    return out
