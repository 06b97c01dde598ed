"""Outfit stage benchmark: the time to generate one outfit (shape, cut, sew, resize to the
subject, push clear of the body) for outfits the default recipe draws (target: 2 s or less on
2 cores). The peer in the same run is the body model building the same subjects' rest bodies,
the other half of a scene's set-up."""

from __future__ import annotations

import statistics
import time

import numpy as np

from benchmarks.common import REPO, write_section

COMMAND = "python -m benchmarks.bench_outfits"
OUTFITS = 20


def main(argv: list[str] | None = None) -> None:
    del argv
    from datagen.body.anny_model import SHAPE_NAMES, default_body_model
    from datagen.garment.outfit import make_outfit
    from datagen.recipe import load_recipe
    from datagen.sampling import sample_scene

    loaded = load_recipe(REPO / "pipelines" / "default.yaml")
    model = default_body_model()
    spec0 = sample_scene(loaded, 0)  # warm the template cache outside the timing
    rest0 = model.rest_body(spec0.subject.gender,
                            np.array([spec0.subject.shape[n] for n in SHAPE_NAMES]))
    make_outfit(spec0.outfit, rest0, model)
    outfit_times, body_times, vertices = [], [], []
    for i in range(1, OUTFITS + 1):
        spec = sample_scene(loaded, i)
        t = time.perf_counter()
        rest = model.rest_body(spec.subject.gender,
                               np.array([spec.subject.shape[n] for n in SHAPE_NAMES]))
        body_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        garments = make_outfit(spec.outfit, rest, model)
        outfit_times.append(time.perf_counter() - t)
        vertices.append(sum(len(g.vertices) for g in garments))
    med, worst = statistics.median(outfit_times), max(outfit_times)
    body_med = statistics.median(body_times)
    body = (
        f"{OUTFITS} outfits drawn by `pipelines/default.yaml` (1 cm templates, "
        f"{min(vertices)}-{max(vertices)} garment vertices per outfit).\n\n"
        "| measure | median | max | relative |\n|---|---|---|---|\n"
        f"| one outfit (shape, cut, sew, resize, push clear) | {med:.2f} s | {worst:.2f} s | "
        f"{med / body_med:.1f}x the rest body |\n"
        f"| the subject's rest body (Anny) | {body_med:.2f} s | {max(body_times):.2f} s | 1.0 |\n"
        f"\nTarget: one outfit in 2 s or less: **{'meets' if worst <= 2.0 else 'misses'}** it "
        f"(slowest {worst:.2f} s)."
    )
    write_section("outfits", "Outfit stage", body, COMMAND)


if __name__ == "__main__":
    main()
