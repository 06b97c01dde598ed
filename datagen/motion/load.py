"""MotionSpec -> canonical Motion on the reference skeleton, at the spec's fps and length."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from datagen.errors import InputError
from datagen.motion.timing import resample, window
from datagen.skeleton import mirror_poses
from datagen.spec import MotionSpec
from datagen.types import Motion


def resolve_motion_file(file: str, base_dir: Path | None) -> Path:
    path = Path(file)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if not path.is_file():
        raise InputError(file, "motion.file", "an existing motion file", "no such file")
    return path


def mirror_motion(motion: Motion) -> Motion:
    trans = motion.trans.copy()
    trans[:, 0] *= -1.0
    return Motion(
        poses=mirror_poses(motion.poses),
        trans=trans,
        fps=motion.fps,
        label=motion.label,
        source=motion.source,
        pelvis_height=motion.pelvis_height,
    )


def motion_from_spec(spec: MotionSpec, base_dir: Path | None = None) -> Motion:
    """The motion a spec describes, `spec.frames` frames at `spec.fps` (lead-in not included)."""
    if spec.source == "procedural":
        from datagen.motion.procedural import generate

        return generate(spec.action, spec.frames, spec.fps, dict(spec.params), mirror=spec.mirror)
    path = resolve_motion_file(spec.file or "", base_dir)
    if spec.source == "bvh":
        from datagen.motion.bvh import load_bvh

        full = load_bvh(path, label=spec.action)
    else:
        from datagen.motion.amass import load_amass

        full = load_amass(path, label=spec.action)
    full = resample(full, spec.fps)
    if full.n_frames < spec.frames:
        raise InputError(
            path,
            "motion.frames",
            f"at most {full.n_frames} frames ({full.duration:.2f} s at {spec.fps:g} fps)",
            spec.frames,
        )
    start = int(np.floor(spec.start * (full.n_frames - spec.frames) + 0.5))
    clip = window(full, start, spec.frames)
    return mirror_motion(clip) if spec.mirror else clip
