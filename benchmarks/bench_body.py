"""Body stage benchmark: the body model's start-up, and a 300-frame body sequence with the
self-collision check (target: 5 s or less on this 2-core machine once the model is cached).

The peer in the same run is Anny's own skinning of the same 300 poses (its native forward pass),
so the report shows what the retargeting, the arm fit and the self-collision check add to
posing alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import timed, write_section

COMMAND = "python -m benchmarks.bench_body"
STARTUP = (
    "import time; t = time.perf_counter(); import anny; "
    "anny.Anny(topology='anny-noeyes-notongue', skinning_method='lbs'); "
    "print(time.perf_counter() - t)"
)


def startup_seconds(cache_dir: str) -> float:
    env = dict(os.environ, ANNY_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", STARTUP], env=env, capture_output=True,
                         text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    del argv
    with tempfile.TemporaryDirectory() as cache:
        first = startup_seconds(cache)
        cached = startup_seconds(cache)

    import torch

    from datagen.body.anny_model import (
        GENDER_VALUE,
        NEUTRAL_SHAPE,
        SHAPE_NAMES,
        _anny_model,
        default_body_model,
    )
    from datagen.body.sequence import build_body_sequence
    from datagen.motion.bvh import load_bvh
    from datagen.motion.procedural import generate
    from datagen.motion.timing import resample, window
    from datagen.recipe import BodyConfig
    from datagen.spec import SubjectSpec

    model = default_body_model()
    subject = SubjectSpec(gender="female", shape=dict(zip(SHAPE_NAMES, NEUTRAL_SHAPE.tolist(),
                                                          strict=True)))
    walk = generate("walk", 300, 30.0)
    cmu = window(resample(load_bvh(os.path.join(os.path.dirname(__file__), "..", "..", "shared",
                                                "mocap", "cmu", "01_01_mb.bvh")), 30.0), 0, 300)
    build_body_sequence(subject, generate("walk", 30, 30.0), 15, model, BodyConfig())  # warm up
    t_walk, seq = timed(lambda: build_body_sequence(subject, walk, 0, model, BodyConfig()))
    t_cmu, seq_cmu = timed(lambda: build_body_sequence(subject, cmu, 0, model, BodyConfig()))

    anny = _anny_model()
    kwargs = {"gender": GENDER_VALUE["female"], **dict(zip(SHAPE_NAMES, NEUTRAL_SHAPE.tolist(),
                                                           strict=True))}
    identity = torch.eye(4, dtype=anny.dtype).repeat(300, len(anny.bone_labels), 1, 1)

    def anny_native():
        with torch.no_grad():
            return anny(pose_parameters=identity, phenotype_kwargs=kwargs)

    t_native, _ = timed(anny_native)
    sc = seq.self_collision
    rows = [
        ("Anny first build (cache empty, fresh process)", f"{first:.1f} s", ""),
        ("Anny start-up with its cache (fresh process)", f"{cached:.1f} s", ""),
        ("300-frame procedural walk, body stage with self-collision check", f"{t_walk:.2f} s",
         f"{t_walk / t_native:.1f}x Anny's own skinning ({t_native:.2f} s)"),
        ("300 frames of CMU 01_01 (BVH), same", f"{t_cmu:.2f} s",
         f"{t_cmu / t_native:.1f}x; arm fit up to "
         f"{seq_cmu.self_collision.arm_clearance_max_deg:.0f} deg, "
         f"{seq_cmu.self_collision.repaired_vertices} vertex repairs"),
    ]
    table = "| measure | time | relative |\n|---|---|---|\n" + "\n".join(
        f"| {a} | {b} | {c} |" for a, b, c in rows)
    verdict = "meets" if t_walk <= 5.0 else "misses"
    body = (
        f"{table}\n\nTarget: a 300-frame body sequence with the self-collision check in 5 s or "
        f"less once the model is cached: **{verdict}** it ({t_walk:.2f} s for the walk; "
        f"{sc.frames_checked} frames checked, {sc.frames_with_contact} with contact).\n"
    )
    write_section("body", "Body stage", body, COMMAND)


if __name__ == "__main__":
    t0 = time.time()
    main()
    print(f"bench_body done in {time.time() - t0:.0f} s", file=sys.stderr)
    np.set_printoptions()
