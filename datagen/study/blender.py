"""Blender's cloth as the peer: the same study scene, simulated by Blender 3.4 headless.

Blender is found on the PATH (Debian's `blender` package); when it is missing the caller is told
so and skips the peer. Blender never becomes a dependency of the project.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from datagen.sim.fabrics import BLENDER_PRESETS, get_fabric
from datagen.sim.simulate import attach_pins
from datagen.study.run import Run
from datagen.study.scenes import StudyScene

SCRIPT = Path(__file__).with_name("blender_scene.py")

# Blender holds cloth at 8/9 of (the cloth's collision distance + the collider's outer
# thickness) from a collider (`min_distance` in its collision.c) and detects contact at the
# sum. The study's peer runs a cushion of 5 mm + 10 mm (13.3 mm at rest) where ours is the
# fabric's thickness (4-5 mm), so a garment draped by ours starts inside Blender's cushion.
BLENDER_REST_FRACTION = 8.0 / 9.0
BLENDER_MIN_OUTER = 0.001  # the smallest collider outer thickness Blender accepts
STUDY_CONTACT = {"collision_distance": 0.005, "collider_thickness": 0.01}


def contact_settings(fabric: str, matched: bool = False) -> dict[str, float]:
    """Blender's collision distance and collider outer thickness: the study's cushion, or with
    `matched` one that rests cloth at our fabric's thickness, as ours does."""
    thickness = get_fabric(fabric).thickness
    if not matched:
        return {"collision_distance": max(thickness, STUDY_CONTACT["collision_distance"]),
                "collider_thickness": STUDY_CONTACT["collider_thickness"]}
    return {"collision_distance": thickness / BLENDER_REST_FRACTION - BLENDER_MIN_OUTER,
            "collider_thickness": BLENDER_MIN_OUTER}


def blender_executable() -> str | None:
    return shutil.which("blender")


def blender_version() -> str:
    exe = blender_executable()
    if exe is None:
        return "absent"
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60)
    return out.stdout.splitlines()[0].strip() if out.stdout else "unknown"


def scene_input(scene: StudyScene, quality: int, matched_contact: bool = False) -> dict:
    """The npz payload for blender_scene.py; `matched_contact`: see contact_settings."""
    x0 = np.concatenate([g.vertices for g in scene.garments]).astype(np.float64)
    # The body scenes start draped (stretched under gravity): Blender takes its rest lengths and
    # angles from a shape key holding the garments' rest metric, as ours does.
    rest = np.concatenate([g.rest for g in scene.garments]).astype(np.float64)
    faces, offset = [], 0
    pinned = []
    for g in scene.garments:
        faces.append(np.asarray(g.faces) + offset)
        if g.pinned is not None:
            pinned.append(np.asarray(g.pinned) + offset)
        offset += len(g.vertices)
    track = scene.track
    collider = track.vertices
    frames = len(collider) - 1
    pinned = np.concatenate(pinned) if pinned else np.zeros(0, np.int64)
    pin_frames = np.zeros((frames + 1, len(pinned), 3))
    if len(pinned):
        pins = attach_pins(x0[pinned], collider[0].astype(np.float64), track.faces,
                           track.face_mask)
        pin_frames = np.array([pins.targets(collider[f].astype(np.float64), track.faces)
                               for f in range(frames + 1)])
    fabric = scene.garments[0].fabric
    preset = BLENDER_PRESETS[fabric]
    used = np.flatnonzero(track.face_mask)
    return dict(
        cloth_vertices=x0, rest_vertices=rest, cloth_faces=np.concatenate(faces),
        collider_frames=collider,
        collider_faces=track.faces[used], fps=track.fps, frames=frames, quality=quality,
        mass=preset.mass, tension=preset.tension, compression=preset.compression,
        shear=preset.shear, bending=preset.bending, tension_damping=preset.tension_damping,
        compression_damping=preset.compression_damping, shear_damping=preset.shear_damping,
        air_damping=preset.air_damping, bending_damping=preset.bending_damping,
        collision_quality=2, self_collision=False, collider_friction=5.0,
        **contact_settings(fabric, matched_contact),
        pinned=pinned, pin_frames=pin_frames,
    )


def run_blender(scene: StudyScene, quality: int, timeout: float = 3600.0,
                threads: int | None = None, matched_contact: bool = False) -> Run:
    """The scene in headless Blender at `quality` steps per frame, timed by Blender's own frame
    times; `threads` sets Blender's thread count (`-t`; None: its default, every core) and its
    OpenMP threads with it: `-t` alone leaves OpenMP a thread per core, and two Blenders at
    `-t 1` side by side on two cores then ran 7x slower each (4k sheet: 98 s instead of 14)."""
    exe = blender_executable()
    if exe is None:
        raise RuntimeError("Blender is not installed (apt-get install blender)")
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **scene_input(scene, quality, matched_contact))
        cores = ["-t", str(threads)] if threads else []
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)} if threads else None
        r = subprocess.run([exe, "-b", *cores, "--factory-startup", "--python-exit-code", "1",
                            "--python", str(SCRIPT), "--", str(src), str(dst)],
                           capture_output=True, text=True, timeout=timeout, env=env)
        if r.returncode != 0 or not dst.exists():
            raise RuntimeError(f"Blender failed: {r.stderr[-500:]}")
        d = np.load(dst)
        positions = d["positions"].astype(np.float64)
        # Frame 1 is the start state: setting it builds Blender's cloth, its set-up.
        setup = float(d["frame_seconds"][0])
        wall = float(d["frame_seconds"][1:].sum())
    frames = len(positions) - 1
    return Run(f"blender q{quality}", positions, wall, frames / scene.track.fps, {}, setup)
