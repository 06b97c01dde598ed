"""Anny (naver/anny, Apache-2.0 code, CC0 assets) as the embedded default body model.

Anny's rig has 104 bones and rests in an A-pose. Canonical poses drive it through a retargeting
map (docs/architecture.md, "Retargeting"):

1. Both skeletons meet in a common T-pose: the arm chain of Anny's rest pose is rotated about the
   shoulder, elbow and wrist so that each limb segment points straight out along +-x. These
   per-bone world rotations C_b are computed once per subject.
2. Each Anny bone follows one canonical joint j(b): its world orientation is G_j(b) C_b, where G_j
   is the canonical joint's world rotation relative to the T-pose. Bones without a partner of
   their own (twist bones, spine05, fingers, toes) follow the joint of their chain, i.e. they keep
   their rest orientation relative to their parent.
3. Each bone head follows its parent's transform, so the mapped bone heads land exactly on the
   canonical joints' forward-kinematics positions.

Anny's first instantiation builds a cache (~1 minute, in ANNY_CACHE_DIR or ~/.cache/anny); one
model is built per process and reused. Processes that start at once on a fresh machine (a dataset
run's workers, the test suite's) take turns at it under a file lock in that folder; a folder
the process cannot write to (a cache built beforehand and shared read-only) is read as it is.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from pathlib import Path

import numpy as np
from filelock import FileLock

from datagen.body.base import PosedBody, check_gender
from datagen.body.parts import JOINT_TO_PART, PART_NAMES
from datagen.errors import InputError
from datagen.rotations import rotation_between
from datagen.skeleton import JOINT_INDEX, NUM_JOINTS, forward_kinematics
from datagen.skinning import apply_linear_skinning
from datagen.types import LinearSkinning, RestBody

ANNY_TOPOLOGY = "anny-noeyes-notongue"  # one watertight piece: no eyes or tongue inside the head
SHAPE_NAMES: tuple[str, ...] = ("age", "muscle", "weight", "height", "proportions")
# Adults only: Anny's morphological-age calibration puts 18 years at age 0.77 and about 83 years
# at 0.90; the garment templates are adult clothes. The other phenotypes use their whole range.
SHAPE_RANGE: dict[str, tuple[float, float]] = {
    "age": (0.77, 0.90),
    "muscle": (0.0, 1.0),
    "weight": (0.0, 1.0),
    "height": (0.0, 1.0),
    "proportions": (0.0, 1.0),
}
NEUTRAL_SHAPE = np.array([0.8, 0.5, 0.5, 0.5, 0.5])
GENDER_VALUE = {"female": 1.0, "male": 0.0}  # Anny's gender phenotype: 0 = male, 1 = female

# The Anny bone whose head defines each canonical joint.
JOINT_BONE: dict[str, str] = {
    "pelvis": "root",
    "left_hip": "upperleg01.L",
    "right_hip": "upperleg01.R",
    "spine1": "spine03",
    "left_knee": "lowerleg01.L",
    "right_knee": "lowerleg01.R",
    "spine2": "spine02",
    "left_ankle": "foot.L",
    "right_ankle": "foot.R",
    "spine3": "spine01",
    "left_foot": "toe3-1.L",
    "right_foot": "toe3-1.R",
    "neck": "neck01",
    "left_collar": "clavicle.L",
    "right_collar": "clavicle.R",
    "head": "head",
    "left_shoulder": "upperarm01.L",
    "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L",
    "right_elbow": "lowerarm01.R",
    "left_wrist": "wrist.L",
    "right_wrist": "wrist.R",
    "left_hand": "finger3-1.L",
    "right_hand": "finger3-1.R",
}

# Bones where the A-pose -> T-pose correction pivots, and the bone whose head the segment points to.
_T_POSE_PIVOTS = {
    f"{bone}.{side}": (f"{target}.{side}", 1.0 if side == "L" else -1.0)
    for side in ("L", "R")
    for bone, target in (
        ("upperarm01", "lowerarm01"),
        ("lowerarm01", "wrist"),
        ("wrist", "finger3-1"),
    )
}


def _bone_joint(label: str) -> str:
    """The canonical joint an Anny bone follows."""
    side = "left" if label.endswith(".L") else "right" if label.endswith(".R") else None
    base = label.split(".")[0]
    if base in ("root", "spine05", "spine04") or base == "pelvis":
        return "pelvis"
    if base == "spine03":
        return "spine1"
    if base == "spine02":
        return "spine2"
    if base == "spine01":
        return "spine3"
    if base.startswith("neck"):
        return "neck"
    if base in ("head", "eye", "jaw") or base.startswith("tongue"):
        return "head"
    if side is None:
        raise ValueError(f"unmapped Anny bone {label}")
    if base in ("clavicle", "shoulder01"):
        return f"{side}_collar"
    if base.startswith("upperarm"):
        return f"{side}_shoulder"
    if base.startswith("lowerarm"):
        return f"{side}_elbow"
    if base == "wrist" or base.startswith("metacarpal"):
        return f"{side}_wrist"
    if base.startswith("finger"):
        return f"{side}_hand"
    if base.startswith("upperleg"):
        return f"{side}_hip"
    if base.startswith("lowerleg"):
        return f"{side}_knee"
    if base == "foot":
        return f"{side}_ankle"
    if base.startswith("toe"):
        return f"{side}_foot"
    raise ValueError(f"unmapped Anny bone {label}")


_MODEL_LOCK = threading.Lock()


@functools.cache
def _anny_model():
    """The Anny model, built once per process (the first build caches data on disk)."""
    import anny  # imported lazily: it pulls torch and takes a moment
    from anny.paths import get_anny_cache_path

    # Anny checks for its cache file and then writes it in place, without a lock: a second
    # process starting meanwhile would build it again over the first's or read it half-written.
    cache = get_anny_cache_path()
    with _MODEL_LOCK, _build_lock(cache):
        model = anny.Anny(topology=ANNY_TOPOLOGY, skinning_method="lbs")
        share_cache_files(cache)
        return model


def share_cache_files(cache: Path) -> None:
    """Give the cache files this process owns the read permissions its umask allows new files.
    Anny writes them readable by their owner alone (mode 0600), so a cache built to be shared
    (a cluster's, built beforehand and read by other accounts) could be read by nobody else.
    Only read bits are added; files of other owners (a shared cache's) are left as they are."""
    umask = os.umask(0o022)  # the only way to read it; put back at once (callers hold a lock)
    os.umask(umask)
    readable = 0o444 & ~umask
    for path in cache.rglob("*"):
        if not path.is_file():
            continue
        info = path.stat()
        if info.st_uid == os.getuid() and info.st_mode & readable != readable:
            path.chmod(info.st_mode | readable)


def _build_lock(cache: Path) -> contextlib.AbstractContextManager:
    """The file lock under which processes take turns building Anny's cache in `cache`; none
    where this process cannot write there (a cache built beforehand and shared read-only, as on
    a cluster): nothing can be built there, so there is nothing to take turns at, and Anny reads
    what is there."""
    if not cache.is_dir():
        try:
            cache.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(None, "ANNY_CACHE_DIR",
                             f"a folder this process can create for Anny's cache ({exc})",
                             str(cache)) from exc
    if not os.access(cache, os.W_OK):
        return contextlib.nullcontext()
    return FileLock(cache / "datagen-build.lock")


class _Subject:
    """Anny internals for one shape: A-pose rest geometry and the T-pose correction."""

    def __init__(self, rest_vertices, heads, corrections, t_heads, offset):
        self.rest_vertices = rest_vertices  # (V, 3) A-pose, Anny's frame
        self.heads = heads  # (B, 3) A-pose bone heads
        self.corrections = corrections  # (B, 3, 3) world rotation rest -> T-pose
        self.t_heads = t_heads  # (B, 3) T-pose bone heads, Anny's frame
        self.offset = offset  # (3,) Anny frame -> RestBody frame (soles at 0, pelvis above 0)


class AnnyBody:
    """The default body model. Build one per process; it is cheap after the first."""

    name = "anny"
    shape_names = SHAPE_NAMES

    def __init__(self) -> None:
        model = _anny_model()
        self.bone_labels: list[str] = list(model.bone_labels)
        self.bone_parents = np.asarray(model.bone_parents, dtype=np.int64)
        if any(p >= i for i, p in enumerate(self.bone_parents) if i > 0):
            raise RuntimeError("Anny bones are not in parent-first order")
        self.faces = model.faces.detach().cpu().numpy().astype(np.int32)
        self.skin_weights = model.vertex_bone_weights.detach().cpu().numpy().astype(np.float32)
        self.skin_bones = model.vertex_bone_indices.detach().cpu().numpy().astype(np.int32)
        self.bone_joint = np.array(
            [JOINT_INDEX[_bone_joint(label)] for label in self.bone_labels], dtype=np.int64
        )
        self.joint_bone = np.array(
            [
                self.bone_labels.index(JOINT_BONE[name])
                for name in sorted(JOINT_INDEX, key=JOINT_INDEX.get)
            ]
        )
        # Part label per vertex: the part whose joints carry most of the vertex's skinning weight.
        n_parts = len(PART_NAMES)
        part_of_bone = JOINT_TO_PART[self.bone_joint]
        part_weight = np.zeros((len(self.skin_weights), n_parts))
        np.add.at(
            part_weight,
            (
                np.repeat(np.arange(len(self.skin_weights)), self.skin_weights.shape[1]),
                part_of_bone[self.skin_bones].ravel(),
            ),
            self.skin_weights.ravel(),
        )
        self.part_labels = part_weight.argmax(axis=1).astype(np.int16)
        self._subjects: dict[tuple, _Subject] = {}

    # -- shape ---------------------------------------------------------------------------------
    def shape_range(self) -> dict[str, tuple[float, float]]:
        return dict(SHAPE_RANGE)

    def _check_shape(self, shape: np.ndarray, extrapolate: bool = False) -> np.ndarray:
        shape = np.asarray(shape, dtype=np.float64)
        if shape.shape != (len(SHAPE_NAMES),):
            raise InputError(
                None, "shape", f"{len(SHAPE_NAMES)} Anny phenotypes {SHAPE_NAMES}", shape.shape
            )
        for name, value in zip(SHAPE_NAMES, shape, strict=True):
            lo, hi = (-0.5, 1.5) if extrapolate else (0.0, 1.0)
            if not (lo <= value <= hi) or not np.isfinite(value):
                raise InputError(None, f"shape.{name}", f"a value in [{lo}, {hi}]", float(value))
        return shape

    def _subject(self, gender: str, shape: np.ndarray) -> _Subject:
        key = (gender, shape.tobytes())
        subject = self._subjects.get(key)
        if subject is None:
            subject = self._build_subject(gender, shape)
            if len(self._subjects) > 64:
                self._subjects.clear()
            self._subjects[key] = subject
        return subject

    def _build_subject(self, gender: str, shape: np.ndarray) -> _Subject:
        import torch

        model = _anny_model()
        kwargs = {"gender": GENDER_VALUE[gender]}
        kwargs.update({name: float(v) for name, v in zip(SHAPE_NAMES, shape, strict=True)})
        # Phenotypes beyond [0, 1] (garment bodies of loose fits) extrapolate the blendshapes
        # linearly; inside the range this changes nothing.
        outside = bool(np.any((shape < 0.0) | (shape > 1.0)))
        previous = model.extrapolate_phenotypes
        model.extrapolate_phenotypes = outside
        # On one thread, whatever the process's: torch's reductions split by thread, so the
        # rest shape rounded differently with two threads than in a Dask worker (which runs
        # torch on one), and the cloth, chaotic, took that 1e-7 to 2.4 cm apart in 6 frames.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with torch.no_grad():
                out = model(phenotype_kwargs=kwargs)
        finally:
            model.extrapolate_phenotypes = previous
            torch.set_num_threads(threads)
        rest = out["rest_vertices"][0].double().cpu().numpy()
        heads = out["rest_bone_heads"][0].double().cpu().numpy()
        n_bones = len(self.bone_labels)
        corrections = np.tile(np.eye(3), (n_bones, 1, 1))
        t_heads = heads.copy()
        for b in range(1, n_bones):
            p = self.bone_parents[b]
            corrections[b] = corrections[p]
            t_heads[b] = t_heads[p] + corrections[p] @ (heads[b] - heads[p])
            pivot = _T_POSE_PIVOTS.get(self.bone_labels[b])
            if pivot is not None:
                target_label, sign = pivot
                target = self.bone_labels.index(target_label)
                direction = corrections[b] @ (heads[target] - heads[b])
                corrections[b] = rotation_between(direction, [sign, 0.0, 0.0]) @ corrections[b]
        subject = _Subject(rest, heads, corrections, t_heads, np.zeros(3))
        t_pose = self._skin(subject, corrections[None], t_heads[None])[0]
        root = t_heads[0]
        subject.offset = np.array([-root[0], -root[1], -float(t_pose[:, 2].min())])
        return subject

    def default_shape(self) -> np.ndarray:
        return NEUTRAL_SHAPE.copy()

    def thinner_shape(self, shape: np.ndarray) -> np.ndarray:
        """A thinner variant for the self-collision retry: less weight and muscle."""
        out = np.array(shape, dtype=np.float64, copy=True)
        out[SHAPE_NAMES.index("weight")] = max(0.0, out[SHAPE_NAMES.index("weight")] - 0.3)
        out[SHAPE_NAMES.index("muscle")] = max(0.0, out[SHAPE_NAMES.index("muscle")] - 0.2)
        return out

    # -- rest and posing -----------------------------------------------------------------------
    def rest_body(self, gender: str, shape: np.ndarray, extrapolate: bool = False) -> RestBody:
        """The subject in the T-pose. `extrapolate` admits phenotypes in [-0.5, 1.5] (bodies a
        loose garment is made for), beyond Anny's calibrated range."""
        check_gender(gender)
        shape = self._check_shape(shape, extrapolate)
        subject = self._subject(gender, shape)
        t_pose = self._skin(subject, subject.corrections[None], subject.t_heads[None])[0]
        offset = subject.offset
        joints = subject.t_heads[self.joint_bone] + offset
        return RestBody(
            model=self.name,
            gender=gender,
            shape=shape.copy(),
            shape_names=SHAPE_NAMES,
            vertices=t_pose.astype(np.float64) + offset,
            faces=self.faces.copy(),
            joints=joints,
            part_labels=self.part_labels.copy(),
            part_names=PART_NAMES,
        )

    def _transforms(
        self, subject: _Subject, orientations: np.ndarray, heads: np.ndarray
    ) -> np.ndarray:
        """(F, B, 3, 4) bone transforms mapping Anny rest space to world, given bone world
        orientations (F, B, 3, 3) relative to Anny's rest and posed bone heads (F, B, 3)."""
        rot = orientations
        trans = heads - np.einsum("fbij,bj->fbi", rot, subject.heads)
        out = np.concatenate([rot, trans[..., None]], axis=-1)
        # Rounded to float32 once: the shard stores them so, and the reader must rebuild exactly.
        return out.astype(np.float32).astype(np.float64)

    def _skin(self, subject: _Subject, orientations: np.ndarray, heads: np.ndarray) -> np.ndarray:
        skin = self._linear_skinning(subject, orientations, heads)
        return apply_linear_skinning(skin)

    def _linear_skinning(self, subject, orientations, heads) -> LinearSkinning:
        return LinearSkinning(
            rest_vertices=subject.rest_vertices,
            weights=self.skin_weights,
            bones=self.skin_bones,
            transforms=self._transforms(subject, orientations, heads),
        )

    def pose(self, rest: RestBody, poses: np.ndarray, trans: np.ndarray) -> PosedBody:
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, NUM_JOINTS * 3)
        trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
        subject = self._subject(rest.gender, np.asarray(rest.shape, dtype=np.float64))
        world_rot, joints = forward_kinematics(poses, trans, rest.joints)
        n_frames = poses.shape[0]
        n_bones = len(self.bone_labels)
        orient = np.einsum("fbij,bjk->fbik", world_rot[:, self.bone_joint], subject.corrections)
        heads = np.empty((n_frames, n_bones, 3))
        heads[:, 0] = trans
        for b in range(1, n_bones):
            p = self.bone_parents[b]
            heads[:, b] = heads[:, p] + orient[:, p] @ (subject.heads[b] - subject.heads[p])
        skin = self._linear_skinning(subject, orient, heads)
        vertices = apply_linear_skinning(skin)
        return PosedBody(vertices=vertices, joints=joints.astype(np.float32), skinning=skin)


@functools.cache
def default_body_model() -> AnnyBody:
    return AnnyBody()


def reference_rest_joints() -> tuple[np.ndarray, float]:
    """T-pose joints of the reference body (female, age 0.8, other phenotypes 0.5), pelvis at the
    origin, and its pelvis height: the constants in datagen.skeleton."""
    body = default_body_model()
    rest = body.rest_body("female", NEUTRAL_SHAPE)
    joints = rest.joints - rest.joints[0]
    return joints, rest.pelvis_height


if __name__ == "__main__":
    import sys

    if "--reference-skeleton" in sys.argv:
        joints, height = reference_rest_joints()
        print("REFERENCE_REST_JOINTS = np.array(\n    [")
        for row in joints:
            print("        [" + ", ".join(f"{v:.4f}" for v in row) + "],")
        print("    ]\n)")
        print(f"REFERENCE_PELVIS_HEIGHT = {height:.4f}")
