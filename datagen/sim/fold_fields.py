"""Distance fields of the body parts that fold onto each other across a joint (the hip, the
knee and the elbow: datagen.body.parts.FLEXION_SIDES), in each part's own moving frame, for the
frames in which the body stage found them folding at that joint.

Why: a tracked cloth vertex follows its own triangle's surface, and the part guard
(kernels.nearest_one) searches it again only when the last search saw another part's facing
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
  (pseudonormal sign; the patch is open at the joint) on a fixed grid per part (FIELD_CELL), and
  within a frame the two ends' values are interpolated linearly. Skinning's deviation from the
  rigid motion near the joint (5-10 cm) is in the sampled surface, not in the transform.

The fields travel to the kernels as one float array (`FoldFields.blob`, layout below), appended
to the fused frame kernel's scalar array, which has no argument left.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

FIELD_CELL = 0.015  # metres: trilinear interpolation of a limb's distance, a few mm off at most
# The grid reaches this far beyond a part's surface in every frame it is sampled in: the
# trigger distance (a collider cell, 25 mm) and a margin.
FIELD_MARGIN = 0.035
# The field runs this many frames before a fold: the parts close in before skinning sinks them
# into each other.
FOLD_LEAD_FRAMES = 2
# Blob layout (offsets from the blob's start): the number of fields, then per body part the
# bits of the field slots that fold onto it (PART_SLOTS entries), then per field HEADER values
# and the data, each grid point's values at the frame's two ends side by side.
# Then per body part its own field's slot plus one (0: none), whose motion the vertices
# tracking it move with (kernels.fold_guard).
PART_SLOTS = 32
B_N, B_PARTNERS = 0, 1
B_OWN = B_PARTNERS + PART_SLOTS
B_FIELDS = B_OWN + PART_SLOTS
# Per field: its part, the grid (origin, 1 / cell, dimensions), the frame's two ends (rotation
# as a quaternion, centre), the centre's motion over the frame, the most any of the part's
# vertices moves relative to it, and where its data starts.
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
        for a, b, frames in self.joints:
            for f in {f for g in frames for f in range(g - FOLD_LEAD_FRAMES - 1, g + 1)
                      if 0 <= f < n_frames}:
                for p in a + b:
                    sampled[parts.index(p)].add(f)
        self.frames = sorted(set().union(*sampled)) if sampled else []
        # A fixed grid per part over every frame's surface it is sampled in, in its own frame.
        self.boxes = []
        for k in range(len(parts)):
            lo = np.full(3, np.inf)
            hi = np.full(3, -np.inf)
            for f in sorted(sampled[k]):
                local = self._fit(k, f)[2]
                lo = np.minimum(lo, local.min(axis=0))
                hi = np.maximum(hi, local.max(axis=0))
            lo -= FIELD_MARGIN
            hi += FIELD_MARGIN
            dims = np.ceil((hi - lo) / FIELD_CELL).astype(np.int64) + 1
            self.boxes.append((lo, dims))
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
        lo, dims = self.boxes[k]
        axes = [lo[d] + FIELD_CELL * np.arange(dims[d]) for d in range(3)]
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

    def blob(self, f0: int, f1: int) -> np.ndarray | None:
        """The kernels' array for the frame f0 -> f1, or None outside a fold: the fields of the
        parts folding at the joints that fold in it or just after it."""
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
        head = np.zeros(B_FIELDS + HEADER * len(fields))
        head[B_N] = len(fields)
        for slot, k in enumerate(fields):
            head[B_OWN + self.parts[k] % PART_SLOTS] = slot + 1
        for p, others in partners.items():
            head[B_PARTNERS + p % PART_SLOTS] = sum(
                1 << fields.index(self.parts.index(o)) for o in others)
        chunks = [head]
        at = len(head)
        for slot, k in enumerate(fields):
            a = self._sample(k, f0)
            b = self._sample(k, f1)
            lo, dims = self.boxes[k]
            h = B_FIELDS + HEADER * slot
            head[h + H_PART] = self.parts[k]
            head[h + H_ORIGIN:h + H_ORIGIN + 3] = lo
            head[h + H_INV_CELL] = 1.0 / FIELD_CELL
            head[h + H_DIMS:h + H_DIMS + 3] = dims
            head[h + H_Q0:h + H_Q0 + 4] = a[0]
            head[h + H_C0:h + H_C0 + 3] = a[1]
            q1 = b[0]
            if np.dot(q1, a[0]) < 0.0:
                q1 = -q1  # the short way round
            head[h + H_Q1:h + H_Q1 + 4] = q1
            head[h + H_C1:h + H_C1 + 3] = b[1]
            shift = b[1] - a[1]
            head[h + H_SHIFT:h + H_SHIFT + 3] = shift
            moved = (np.asarray(self.vertices[f1][self.verts[k]], dtype=np.float64)
                     - np.asarray(self.vertices[f0][self.verts[k]], dtype=np.float64) - shift)
            head[h + H_TRAVEL] = float(np.sqrt(np.einsum("ij,ij->i", moved, moved).max()))
            head[h + H_DATA] = at
            # The two ends side by side: a lookup reads both from one cache line.
            chunks.append(np.stack([a[2], b[2]], axis=1).ravel())
            at += 2 * len(a[2])
        return np.concatenate(chunks)
