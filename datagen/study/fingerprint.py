"""What the simulator does on a study part, as a digest: its behavioural fingerprint.

A part of the full study takes up to an hour and a half on 2 cores, so the whole study spans
sessions. A part is keyed by a digest of the simulator's sources (`cache.source_digest`), and
any edit under `datagen/sim` makes it stale, even one that cannot reach the part's scene (a
kernel compiled only for layered outfits). The fingerprint says whether the simulator still
does the same thing on that scene: short runs of every solver series the plan measures (its
cheapest configuration and the one with the most iterations), and of
the float64 reference, from the scene's own start; their trajectories' bytes are hashed. A part
whose fingerprint equals today's is carried over as measured by today's simulator.

It is evidence, not proof: a change that leaves these few frames bit-identical but changes
later frames, or only other settings, would slip through, so the page names the parts carried
over by fingerprint. The digest depends on this machine's floating point (another CPU may
differ), which only ever reads as a change; parts record the machine that measured them
(`study.machine`) and the page names those measured elsewhere, so such a change can be read.
"""

from __future__ import annotations

import functools
import hashlib

import numpy as np

# Frames per run: enough for contact, the strain limit and friction to act (the body scenes'
# garments start on the body; the sheet reaches its sphere at about 0.25 s, frame 8), few
# enough that a part's fingerprint costs about a minute.
FINGERPRINT_FRAMES = {"sheet_sphere": 12}
BODY_FRAMES = 3


def fingerprint_frames(scene_name: str) -> int:
    return FINGERPRINT_FRAMES.get(scene_name, BODY_FRAMES)


def scene_fingerprint(scene, configs: dict[str, list[tuple[int, int]]]) -> str:
    """Digest of the trajectories of each solver at its first (cheapest) configuration over
    the scene's frames (build it with fingerprint_frames), run in this process (float32)."""
    from datagen.errors import RejectedSequence
    from datagen.study.run import run_ours

    h = hashlib.sha256()
    for solver, settings in sorted(configs.items()):
        for substeps, iterations in fingerprint_configs(settings):
            h.update(f"{solver} {substeps}x{iterations}".encode())
            try:
                run = run_ours(scene, solver, substeps, iterations)
            except RejectedSequence as exc:  # a rejection is behaviour too
                h.update(str(exc).encode())
                continue
            h.update(np.ascontiguousarray(run.positions, np.float64).tobytes())
    return h.hexdigest()[:16]


def effects_key(scene_name: str, resolution: str, fabric: str) -> dict:
    """The part's run.peer_effects_key, for every study cache key of its runs."""
    return dict(_effects_key(scene_name, resolution, fabric))


@functools.cache
def _effects_key(scene_name: str, resolution: str, fabric: str) -> tuple:
    """As effects_key, built once per part (a scene build), as items: a cached dict could be
    changed by a caller."""
    from datagen.study.run import peer_effects_key
    from datagen.study.scenes import build_scene

    scene = build_scene(scene_name, fabric, resolution, frames=fingerprint_frames(scene_name))
    return tuple(peer_effects_key(scene).items())


def fingerprint_configs(settings: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """A series' cheapest configuration and the first with the most iterations: what the later
    sweeps of a substep do (stiff bending swept again, 29b9dd5) never shows at one iteration,
    and the fingerprint of 5x1 alone carried every part over that change."""
    most = max(settings, key=lambda c: c[1])
    return [settings[0]] if most == settings[0] else [settings[0], most]


def part_fingerprint(scene_name: str, resolution: str, fabric: str, plan) -> str:
    """The fingerprint of one part of `plan` (a sweep.Plan): its scene's solver series and
    the first rung of its float64 reference ladder. Cached per source digest: computed once
    for each version of the simulator."""
    from datagen.study.cache import cached
    from datagen.study.scenes import build_scene

    def compute() -> dict[str, np.ndarray]:
        frames = fingerprint_frames(scene_name)
        ours = scene_fingerprint(build_scene(scene_name, fabric, resolution, frames=frames),
                                 plan.configs)
        ref = _reference_start(scene_name, resolution, fabric, plan)
        h = hashlib.sha256(ours.encode())
        h.update(np.ascontiguousarray(ref, np.float64).tobytes())
        return {"digest": _text(h.hexdigest()[:16])}

    key = {"fingerprint": 2, "scene": scene_name, "resolution": resolution, "fabric": fabric,
           "configs": {solver: [list(x) for x in fingerprint_configs(c)]
                       for solver, c in plan.configs.items()},
           "reference_start": plan.start_for(scene_name), "frames": fingerprint_frames(scene_name),
           **effects_key(scene_name, resolution, fabric)}
    return bytes(cached(key, compute)["digest"]).decode()


def reference_fingerprint(scene_name: str, resolution: str, fabric: str, plan) -> str:
    """The fingerprint of a part's float64 reference alone (its ladder's first rung over the
    scene's first frames): a simulator change that leaves it equal (one to the xpbd solver)
    leaves the reference ladder as it was. Cached per source digest."""
    from datagen.study.cache import cached

    def compute() -> dict[str, np.ndarray]:
        ref = _reference_start(scene_name, resolution, fabric, plan)
        digest = hashlib.sha256(np.ascontiguousarray(ref, np.float64).tobytes())
        return {"digest": _text(digest.hexdigest()[:16])}

    key = {"reference_fingerprint": 1, "scene": scene_name, "resolution": resolution,
           "fabric": fabric, "reference_start": plan.start_for(scene_name),
           "frames": fingerprint_frames(scene_name), **effects_key(scene_name, resolution, fabric)}
    return bytes(cached(key, compute)["digest"]).decode()


def _reference_start(scene_name: str, resolution: str, fabric: str, plan) -> np.ndarray:
    """The reference ladder's first rung over the fingerprint's frames (float64, in a worker
    process), cached per source digest: both fingerprints above read it."""
    from datagen.study.cache import cached
    from datagen.study.sweep import run_worker

    def compute() -> dict[str, np.ndarray]:
        return {"positions": run_worker(
            scene_name, fabric, resolution, "implicit", plan.start_for(scene_name), 20,
            fp64=True, frames=fingerprint_frames(scene_name))["positions"]}

    key = {"reference_start_run": 1, "scene": scene_name, "resolution": resolution,
           "fabric": fabric, "substeps": plan.start_for(scene_name),
           "frames": fingerprint_frames(scene_name), **effects_key(scene_name, resolution, fabric)}
    return cached(key, compute)["positions"]


def _text(digest: str) -> np.ndarray:
    return np.frombuffer(digest.encode(), np.uint8)
