"""Distance fields of the body parts that fold onto each other across a joint (the hip, the
knee and the elbow: datagen.body.parts.FLEXION_SIDES), in each part's own moving frame, for the
frames in which the body stage found them folding at that joint.

Why: a tracked cloth vertex follows its own triangle's surface, and the part guard
(search_kernels.nearest_one) searches it again only when the last search saw another part's facing
surface within a grid cell. A thigh closing over trousers that track the calf or the belly
arrives from farther than a cell between full searches and swallows them (the fast kick). Proofs
that nothing comes near over a frame scanned triangles over regions that grow with the limb's
motion and made a running sequence four to seven times slower (docs/simulator.md). Here the
question "how near is a folding part's surface" is one rigid transform and one trilinear lookup:

- each part's frame is the rigid fit (Kabsch) of its vertices to where they were in the track's
  first frame; within a frame the rotation is interpolated (normalised quaternion lerp) and the
  centre linearly;
- a frame's fields are those of the joints folding in or just after it (FOLD_LEAD_FRAMES), so
  a running arm's bent elbows cost its legs nothing;
- in that frame, the part's own triangles are sampled once per body frame as a signed distance
  (pseudonormal sign; the patch is open at the joint) on a fixed grid per part, on the lattice
  of FIELD_CELL in its own frame (so that a frame's values do not depend on later folds), and
  within a frame the two ends' values are interpolated linearly. Skinning's deviation from the
  rigid motion near the joint (5-10 cm) is in the sampled surface, not in the transform.

The fields travel to the kernels as one float array (`FoldFields.blob`, layout below), appended
to the fused frame kernel's scalar array, which has no argument left.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

FIELD_CELL = 0.015  # metres: trilinear interpolation of a limb's distance, a few mm off at most
# The grid reaches this far beyond a part's surface in every frame it is sampled in: the
# trigger distance (a collider cell, 25 mm) and a margin.
FIELD_MARGIN = 0.035
# The field runs this many frames before a fold: the parts close in before skinning sinks them
# into each other.
FOLD_LEAD_FRAMES = 2
# Blob layout (offsets from the blob's start): the number of fields, the number S of body-part
# slots, then three tables of S entries indexed by body part: the bits of the field slots that
# fold onto the part, counted from the part's base slot (T_PARTNERS); that base slot
# (T_BASE); and the part's own field's slot plus one (T_OWN, 0: none), whose motion the
# vertices tracking it move with (search_kernels.nearest_one). Then per field HEADER values and the
# data, each grid point's values at the frame's two ends side by side. A batch of scenes
# (JoinedFoldFields) numbers each scene's parts apart and puts its fields in consecutive slots
# from its base, so a part's partners, always of its own scene, fit in MAX_FIELDS bits however
# many scenes fold at once.
B_N, B_SLOTS, B_TABLES = 0, 1, 2
T_PARTNERS, T_BASE, T_OWN = 0, 1, 2  # the tables, each S long, in this order from B_TABLES


def fields_at(n_slots: int) -> int:
    """Where the first field's header starts in a blob with `n_slots` part slots."""
    return B_TABLES + 3 * n_slots


# Per field: its part, the grid (its first point in cells of the FIELD_CELL lattice, integers;
# 1 / cell; dimensions), the frame's two ends (rotation as a quaternion, centre), the centre's
# motion over the frame, the most any of the part's vertices moves relative to it, and where
# its data starts.
(H_PART, H_ORIGIN, H_INV_CELL, H_DIMS, H_Q0, H_C0, H_Q1, H_C1, H_SHIFT, H_TRAVEL, H_DATA) = (
    0, 1, 4, 5, 8, 12, 15, 19, 22, 25, 26)
HEADER = 27
MAX_FIELDS = 16  # partner bits are a float32's exact integer bits


def _kabsch(ref: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation R and centres (c_ref, c_cur) with cur ~ R (ref - c_ref) + c_cur."""
    c_ref = ref.mean(axis=0)
    c_cur = cur.mean(axis=0)
    h = (ref - c_ref).T @ (cur - c_cur)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, c_ref, c_cur


def _quaternion(rot: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    return np.array([w, x, y, z])


class FoldFields:
    """Per body frame, the folding parts' frames and distance fields, computed on demand."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, face_parts: np.ndarray,
                 folds: list[tuple[tuple[str, ...], tuple[str, ...], frozenset[int]]],
                 part_index: dict[str, int]) -> None:
        """`folds`: per joint that folds, its two sides' part names and the body frames it
        folds in (the body stage's flexion overlap frames at that joint)."""
        self.vertices = vertices
        self.faces = np.asarray(faces, dtype=np.int64)
        self.face_parts = np.asarray(face_parts)
        n_frames = vertices.shape[0]
        # Per joint: its two sides (part indices) and the frames it folds in.
        self.joints = [([part_index[p] for p in side_a], [part_index[p] for p in side_b],
                        frozenset(int(f) for f in frames))
                       for side_a, side_b, frames in folds]
        parts: list[int] = []
        for a, b, _ in self.joints:
            for p in a + b:
                if p not in parts:
                    parts.append(p)
        if len(parts) > MAX_FIELDS:
            raise ValueError(f"FoldFields: {len(parts)} folding parts, at most {MAX_FIELDS}")
        self.parts = parts
        # Each part's triangles (re-indexed to its own vertices) and the frames it is sampled in.
        self.tris: list[np.ndarray] = []
        self.verts: list[np.ndarray] = []
        for p in parts:
            tri = self.faces[self.face_parts == p]
            used, local = np.unique(tri, return_inverse=True)
            self.verts.append(used)
            self.tris.append(local.reshape(-1, 3))
        sampled: list[set[int]] = [set() for _ in parts]
        # A joint folding at frame g is in the blobs of the frames f0 -> f0 + 1 from
        # f0 = g - FOLD_LEAD_FRAMES - 1 to g (`folding`), each sampled at both ends.
        for a, b, frames in self.joints:
            for f in {f for g in frames for f in range(g - FOLD_LEAD_FRAMES - 1, g + 2)
                      if 0 <= f < n_frames}:
                for p in a + b:
                    sampled[parts.index(p)].add(f)
        # A fixed grid per part over every frame's surface it is sampled in, in its own frame,
        # on the FIELD_CELL lattice there: a point's eight neighbours and their values are then
        # the same whatever frames widen the box, so a frame's lookups do not depend on folds
        # later in the sequence (a sequence cut short is the long one's prefix).
        self.boxes: list[tuple[np.ndarray, np.ndarray]] = []  # (first point in cells, dims)
        for k in range(len(parts)):
            lo = np.full(3, np.inf)
            hi = np.full(3, -np.inf)
            for f in sorted(sampled[k]):
                local = self._fit(k, f)[2]
                lo = np.minimum(lo, local.min(axis=0))
                hi = np.maximum(hi, local.max(axis=0))
            first = np.floor((lo - FIELD_MARGIN) / FIELD_CELL).astype(np.int64)
            last = np.ceil((hi + FIELD_MARGIN) / FIELD_CELL).astype(np.int64)
            self.boxes.append((first, last - first + 1))
        self._cache: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = (
            OrderedDict())

    def _fit(self, k: int, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Part k's frame at body frame f, its rigid fit to the first frame (rotation, centre),
        and its vertices in that frame (the first frame's pose, centred)."""
        ref = np.asarray(self.vertices[0][self.verts[k]], dtype=np.float64)
        cur = np.asarray(self.vertices[f][self.verts[k]], dtype=np.float64)
        rot, _, c_cur = _kabsch(ref, cur)
        return rot, c_cur, (cur - c_cur) @ rot

    def _sample(self, k: int, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Part k's (quaternion, centre, field values) at body frame f."""
        import igl

        key = (k, f)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        rot, c_cur, local = self._fit(k, f)
        first, dims = self.boxes[k]
        # Integer lattice indices times the cell: a point's coordinates are the same in any box.
        axes = [FIELD_CELL * (first[d] + np.arange(dims[d])) for d in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        sd, *_ = igl.signed_distance(grid, np.ascontiguousarray(local),
                                     np.ascontiguousarray(self.tris[k]),
                                     sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
        out = (_quaternion(rot), c_cur, np.asarray(sd, dtype=np.float64))
        self._cache[key] = out
        # Three body frames of every part: a frame's two ends and the next frame's end.
        while len(self._cache) > 3 * len(self.parts):
            self._cache.popitem(last=False)
        return out

    def folding(self, f0: int, f1: int) -> list[int]:
        """The joints (indices into `folds`) folding in the frame f0 -> f1 or just after it."""
        window = range(f0, f1 + FOLD_LEAD_FRAMES + 1)
        return [j for j, (_, _, frames) in enumerate(self.joints)
                if any(f in frames for f in window)]

    def frame(self, f0: int, f1: int) -> FrameFields | None:
        """The fields of the frame f0 -> f1, or None outside a fold: those of the parts folding
        at the joints that fold in it or just after it, ready to pack."""
        joints = self.folding(f0, f1)
        if not joints:
            return None
        fields: list[int] = []  # indices into self.parts, in slot order
        partners: dict[int, set[int]] = {}
        for j in joints:
            a, b, _ = self.joints[j]
            for p in a + b:
                if self.parts.index(p) not in fields:
                    fields.append(self.parts.index(p))
            for p in a:
                partners.setdefault(p, set()).update(b)
            for p in b:
                partners.setdefault(p, set()).update(a)
        headers, data = [], []
        for k in fields:
            a = self._sample(k, f0)
            b = self._sample(k, f1)
            first, dims = self.boxes[k]
            h = np.zeros(HEADER)
            h[H_PART] = self.parts[k]
            h[H_ORIGIN:H_ORIGIN + 3] = first
            h[H_INV_CELL] = 1.0 / FIELD_CELL
            h[H_DIMS:H_DIMS + 3] = dims
            h[H_Q0:H_Q0 + 4] = a[0]
            h[H_C0:H_C0 + 3] = a[1]
            q1 = b[0]
            if np.dot(q1, a[0]) < 0.0:
                q1 = -q1  # the short way round
            h[H_Q1:H_Q1 + 4] = q1
            h[H_C1:H_C1 + 3] = b[1]
            shift = b[1] - a[1]
            h[H_SHIFT:H_SHIFT + 3] = shift
            moved = (np.asarray(self.vertices[f1][self.verts[k]], dtype=np.float64)
                     - np.asarray(self.vertices[f0][self.verts[k]], dtype=np.float64) - shift)
            h[H_TRAVEL] = float(np.sqrt(np.einsum("ij,ij->i", moved, moved).max()))
            headers.append(h)
            # The two ends side by side: a lookup reads both from one cache line.
            data.append(np.stack([a[2], b[2]], axis=1).ravel())
        return FrameFields([self.parts[k] for k in fields], headers, data, partners)

    def blob(self, f0: int, f1: int) -> np.ndarray | None:
        """The kernels' array for the frame f0 -> f1 (`frame`, packed), or None outside a fold."""
        fields = self.frame(f0, f1)
        return None if fields is None else pack([(fields, 0, np.zeros(3))])


@dataclass
class FrameFields:
    """One scene's fold fields for one frame: per field (slot order) its part, header (as in
    the blob, but H_DATA) and data; and per folding part the parts folding onto it."""

    parts: list[int]
    headers: list[np.ndarray]
    data: list[np.ndarray]
    partners: dict[int, set[int]]


def pack(scenes: list[tuple[FrameFields, int, np.ndarray]]) -> np.ndarray:
    """The kernels' array (layout above) for the frame fields of one scene or of several
    side by side: per scene its fields, the number added to its part numbers and the shift
    added to its positions."""
    # Every part with partners has a field of its own: the fields' parts bound the tables.
    n_slots = 1 + max(max(f.parts) + offset for f, offset, _ in scenes)
    n_fields = sum(len(f.parts) for f, _, _ in scenes)
    start = fields_at(n_slots)
    head = np.zeros(start + HEADER * n_fields)
    head[B_N] = n_fields
    head[B_SLOTS] = n_slots
    table = {t: B_TABLES + t * n_slots for t in (T_PARTNERS, T_BASE, T_OWN)}
    chunks = [head]
    at = len(head)
    base = 0
    for fields, offset, shift in scenes:
        for p, others in fields.partners.items():
            head[table[T_PARTNERS] + offset + p] = sum(1 << fields.parts.index(o) for o in others)
            head[table[T_BASE] + offset + p] = base
        for slot, (p, h, data) in enumerate(zip(fields.parts, fields.headers, fields.data,
                                                strict=True)):
            head[table[T_OWN] + offset + p] = base + slot + 1
            out = start + HEADER * (base + slot)
            head[out:out + HEADER] = h
            head[out + H_PART] = offset + p
            for centre in (H_C0, H_C1):  # the shift moves the part's frame, not its field
                head[out + centre:out + centre + 3] += shift
            head[out + H_DATA] = at
            chunks.append(data)
            at += len(data)
        base += len(fields.parts)
    return np.concatenate(chunks)


def read_partners(blob: np.ndarray, part: int) -> list[int]:
    """The field slots folding onto `part` in a packed blob (what search_kernels.fold_near
    reads)."""
    n_slots = int(blob[B_SLOTS])
    if part >= n_slots:
        return []
    bits = int(blob[B_TABLES + T_PARTNERS * n_slots + part])
    base = int(blob[B_TABLES + T_BASE * n_slots + part])
    return [base + k for k in range(MAX_FIELDS) if (bits >> k) & 1]


def read_own(blob: np.ndarray, part: int) -> int | None:
    """`part`'s own field slot in a packed blob, None where it has none."""
    n_slots = int(blob[B_SLOTS])
    own = int(blob[B_TABLES + T_OWN * n_slots + part]) - 1 if part < n_slots else -1
    return None if own < 0 else own


def header(blob: np.ndarray, slot: int) -> int:
    """Where field `slot`'s header starts in a packed blob."""
    return fields_at(int(blob[B_SLOTS])) + HEADER * slot


class JoinedFoldFields:
    """The fold fields of a batch's scenes (datagen.sim.batch), each scene's parts numbered
    from its own offset and its positions shifted as the batch shifts them."""

    def __init__(self, scenes: list[tuple[FoldFields, int, np.ndarray]]) -> None:
        self.scenes = [(fields, offset, np.asarray(shift, dtype=np.float64))
                       for fields, offset, shift in scenes]

    def blob(self, f0: int, f1: int) -> np.ndarray | None:
        """The kernels' array for the frame f0 -> f1, or None where no scene folds in it."""
        frames = [(fields.frame(f0, f1), offset, shift) for fields, offset, shift in self.scenes]
        folding = [(f, offset, shift) for f, offset, shift in frames if f is not None]
        return pack(folding) if folding else None
