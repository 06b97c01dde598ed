"""Hand-off types between the pipeline stages: plain dataclasses of numpy arrays.

Every stage imports this module and nothing of the other stages (docs/architecture.md). Arrays
are float64 where they describe inputs and references, float32 for per-frame geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Motion:
    """A canonical pose sequence (see datagen.skeleton for the conventions).

    `trans` refers to a skeleton whose standing pelvis is `pelvis_height` metres above the soles;
    the body stage rescales it to each subject so that feet keep their contacts.
    """

    poses: np.ndarray  # (F, 72) float64
    trans: np.ndarray  # (F, 3) float64, pelvis world position, ground at z = 0
    fps: float
    label: str  # action label, e.g. "walk"
    source: str  # "procedural", "bvh:<file>", "amass:<file>"
    pelvis_height: float  # metres, of the skeleton `trans` refers to

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64)
        self.trans = np.asarray(self.trans, dtype=np.float64)
        if self.poses.ndim != 2 or self.poses.shape[1] != 72:
            raise ValueError(f"poses must be (F, 72), got {self.poses.shape}")
        if self.trans.shape != (self.poses.shape[0], 3):
            raise ValueError(f"trans must be ({self.poses.shape[0]}, 3), got {self.trans.shape}")

    @property
    def n_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def duration(self) -> float:
        return (self.n_frames - 1) / self.fps


@dataclass
class RestBody:
    """One subject in the canonical T-pose: what garments are fitted to."""

    model: str  # body model name, e.g. "anny"
    gender: str  # "female" | "male"
    shape: np.ndarray  # (S,) float64, the model's own shape parameters
    shape_names: tuple[str, ...]
    vertices: np.ndarray  # (V, 3) float64, T-pose, soles at z = 0, pelvis above the origin
    faces: np.ndarray  # (T, 3) int32
    joints: np.ndarray  # (24, 3) float64, T-pose joint positions in the same frame as vertices
    part_labels: np.ndarray  # (V,) int16, index into part_names
    part_names: tuple[str, ...]

    @property
    def pelvis_height(self) -> float:
        return float(self.joints[0, 2] - self.vertices[:, 2].min())


@dataclass
class LinearSkinning:
    """Enough to rebuild posed body vertices exactly without the body model:
    v[f, i] = sum_k weights[i, k] * (transforms[f, bones[i, k]] @ [rest[i], 1]) + corrections."""

    rest_vertices: np.ndarray  # (V, 3) float64, the model's own rest pose
    weights: np.ndarray  # (V, K) float32
    bones: np.ndarray  # (V, K) int32
    transforms: np.ndarray  # (F, B, 3, 4) float64


@dataclass
class SelfCollisionReport:
    """What the self-collision stage found and did, per sequence."""

    frames_checked: int = 0
    frames_with_contact: int = 0
    intersecting_pairs: int = 0  # triangle pairs over all frames, before repair
    repaired_vertices: int = 0  # distinct (frame, vertex) moved by the repair
    max_repair_offset: float = 0.0  # metres
    residual_pairs: int = 0  # after repair and the flexion separation, in the frames they moved
    by_part_pair: dict[str, int] = field(default_factory=dict)
    dropped_parts: tuple[str, ...] = ()
    arm_clearance_max_deg: float = 0.0  # largest abduction added to fit the arms to the torso
    arm_clearance_frames: int = 0
    thinner_retries: int = 0
    # Frames (of `vertices`, lead-in included) where skinning sank a part into its neighbour
    # across a flexed joint (datagen.body.parts.FLEXION_SIDES: a thigh into the lower torso, a
    # calf into its thigh, a forearm into its upper arm), those frames per joint (by
    # parts.FLEXION_JOINTS' names, only joints that fold), with the largest overlap's extent
    # and depth, estimated as for self-collisions; the body stage then moves both surfaces to a
    # shared contact surface (datagen.body.flexion): vertices moved, the largest move, and the
    # frames and triangle pairs that still intersect afterwards (cloth caught there cannot be
    # outside the body).
    flexion_overlap_frames: list[int] = field(default_factory=list)
    flexion_overlap_by_joint: dict[str, list[int]] = field(default_factory=dict)
    flexion_overlap_max_extent: float = 0.0  # metres
    flexion_overlap_max_depth: float = 0.0  # metres
    flexion_separated_vertices: int = 0  # distinct (frame, vertex) moved
    flexion_max_offset: float = 0.0  # metres
    flexion_residual_frames: list[int] = field(default_factory=list)
    flexion_residual_pairs: int = 0

    def as_dict(self) -> dict:
        return {
            "frames_checked": self.frames_checked,
            "frames_with_contact": self.frames_with_contact,
            "intersecting_pairs": self.intersecting_pairs,
            "repaired_vertices": self.repaired_vertices,
            "max_repair_offset": self.max_repair_offset,
            "residual_pairs": self.residual_pairs,
            "by_part_pair": dict(self.by_part_pair),
            "dropped_parts": list(self.dropped_parts),
            "arm_clearance_max_deg": self.arm_clearance_max_deg,
            "arm_clearance_frames": self.arm_clearance_frames,
            "thinner_retries": self.thinner_retries,
            "flexion_overlap_frames": list(self.flexion_overlap_frames),
            "flexion_overlap_by_joint": {k: list(v) for k, v in
                                         self.flexion_overlap_by_joint.items()},
            "flexion_overlap_max_extent": self.flexion_overlap_max_extent,
            "flexion_overlap_max_depth": self.flexion_overlap_max_depth,
            "flexion_separated_vertices": self.flexion_separated_vertices,
            "flexion_max_offset": self.flexion_max_offset,
            "flexion_residual_frames": list(self.flexion_residual_frames),
            "flexion_residual_pairs": self.flexion_residual_pairs,
        }


@dataclass
class BodySequence:
    """The body stage's result: a subject moving through a motion, self-collisions repaired.

    `vertices` are what the simulator collides with and what is stored; the skinning plus the
    sparse repair offsets rebuild them exactly.
    """

    rest: RestBody
    poses: np.ndarray  # (F, 72) float64, canonical
    trans: np.ndarray  # (F, 3) float64, pelvis world position for this subject
    fps: float
    action: str
    motion_source: str
    lead_in_frames: int  # the first frames blend from the rest pose into the motion
    joints: np.ndarray  # (F, 24, 3) float32
    vertices: np.ndarray  # (F, V, 3) float32, repaired
    skinning: LinearSkinning | None  # None when the model is not pure LBS (e.g. SMPL)
    repair_frames: np.ndarray  # (K,) int32: sparse repair offsets (frame, vertex, offset)
    repair_vertices: np.ndarray  # (K,) int32
    repair_offsets: np.ndarray  # (K, 3) float32
    self_collision: SelfCollisionReport
    collider_face_mask: np.ndarray  # (T,) bool: faces the cloth collides with

    @property
    def n_frames(self) -> int:
        return int(self.poses.shape[0])


@dataclass
class Garment:
    """One piece of clothing fitted to a subject in the T-pose: what the simulator starts from.

    `vertices` are the initial 3D positions around the rest body; the rest metric (edge lengths,
    areas) comes from `rest_vertices`, which differ from `vertices` only where the garment is
    deliberately pre-stretched or shrunk (e.g. elastic bands); `uv` are the flat pattern
    coordinates (metres) that give the fabric's warp and weft directions, when known.
    """

    name: str  # unique within the outfit
    category: str  # tshirt, shirt, polo, top, trousers, skirt, jumpsuit, dress, sheet, ...
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (T, 3) int32
    fabric: str
    rest_vertices: np.ndarray | None = None  # (V, 3); None: the rest metric is `vertices`
    uv: np.ndarray | None = None  # (V, 2) pattern coordinates, metres
    loops: dict[str, np.ndarray] = field(default_factory=dict)  # role -> ordered vertex ids
    regions: np.ndarray | None = None  # (V,) int16 into region_names
    region_names: tuple[str, ...] = ()
    elastic: tuple[str, ...] = ()  # loop roles with elastic bands
    pinned: np.ndarray | None = None  # vertex ids attached to the body (e.g. a waistband)
    tightness: tuple[float, float] = (0.0, 0.0)
    layer: int = 0  # 0 = innermost
    seams: np.ndarray | None = None  # (K, 2) vertex pairs pulled together (panels being sewn)
    meta: dict = field(default_factory=dict)  # shaping/cut parameters, template name, ...

    @property
    def rest(self) -> np.ndarray:
        return self.vertices if self.rest_vertices is None else self.rest_vertices


@dataclass
class SimResult:
    """The simulation stage's result: garment vertices at the output frame rate (lead-in frames
    excluded), per-frame QA series and a report of what ran and what it cost."""

    garment_names: list[str]
    vertices: dict[str, np.ndarray]  # name -> (F, V, 3) float32
    qa: dict[str, np.ndarray]  # series name -> (F,) float32
    report: dict  # solver, substeps, iterations, effects, costs, wall time, retries
