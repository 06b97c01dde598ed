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


def _load_clip(source: str, path: Path, label: str) -> Motion:
    if source == "bvh":
        from datagen.motion.bvh import load_bvh

        return load_bvh(path, label=label)
    from datagen.motion.amass import load_amass

    return load_amass(path, label=label)


def check_clip_lengths(source: str, files: list[str], base_dir: Path | None, frames: int,
                       fps: float, recipe: Path | str | None = None) -> None:
    """Every clip a recipe may draw holds `frames` frames at `fps`: a dataset run finds a short
    clip before it starts, instead of rejecting the sequences that draw it one by one."""
    for file in files:
        path = resolve_motion_file(file, base_dir)
        clip = resample(_load_clip(source, path, path.stem), fps)
        if clip.n_frames < frames:
            raise InputError(
                recipe or path,
                f"motion.{source}_files",
                f"clips of at least {frames} frames at {fps:g} fps (motion.frames); {file} has "
                f"{clip.n_frames} ({clip.duration:.2f} s)",
                file,
            )


def motion_from_spec(spec: MotionSpec, base_dir: Path | None = None) -> Motion:
    """The motion a spec describes, `spec.frames` frames at `spec.fps` (lead-in not included)."""
    if spec.source == "procedural":
        from datagen.motion.procedural import generate

        return generate(spec.action, spec.frames, spec.fps, dict(spec.params), mirror=spec.mirror)
    path = resolve_motion_file(spec.file or "", base_dir)
    full = resample(_load_clip(spec.source, path, spec.action), spec.fps)
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
