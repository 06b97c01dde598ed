"""An outfit fitted to a subject, written out to look at and reuse (`datagen garments`).

Per garment an OBJ of its start positions on the subject's rest body and a JSON sidecar with
what the simulator needs beyond the mesh (fabric, loops, regions, pins, elastic ends, layer, the
rest shape where it differs); the subject's rest body as body.obj; the scene spec as
outfit.json (everything sampled, reusable with `--spec`); and preview.png, a front and side view.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from datagen.spec import SceneSpec
from datagen.types import Garment, RestBody

FITTED_FORMAT = "datagen-fitted-garment/1"


def fitted_sidecar(g: Garment) -> dict:
    """The JSON sidecar of a fitted garment (documented in docs/templates.md)."""
    out = {
        "format": FITTED_FORMAT,
        "name": g.name,
        "category": g.category,
        "fabric": g.fabric,
        "layer": int(g.layer),
        "tightness": [float(t) for t in g.tightness],
        "elastic": list(g.elastic),
        "pinned": [] if g.pinned is None else [int(i) for i in g.pinned],
        "loops": {role: [int(i) for i in ids] for role, ids in sorted(g.loops.items())},
        "region_names": list(g.region_names),
        "regions": [] if g.regions is None else [int(r) for r in g.regions],
        "meta": g.meta,
    }
    if g.rest_vertices is not None:
        out["rest_vertices"] = np.round(np.asarray(g.rest_vertices), 6).tolist()
    return out


def write_fitted_outfit(
    out: str | Path, spec: SceneSpec, rest: RestBody, garments: list[Garment], height: int = 640
) -> list[Path]:
    """Write the outfit folder; returns the files written."""
    from datagen.garment.template import write_obj
    from datagen.render import BODY_COLOUR, GARMENT_COLOURS, MeshLayer, render_views, save_png

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for g in garments:
        obj = out / f"{g.name}.obj"
        write_obj(obj, g.vertices, g.faces, f"datagen fitted garment {g.name} ({g.category})")
        side = out / f"{g.name}.json"
        side.write_text(json.dumps(fitted_sidecar(g), indent=1))
        written += [obj, side]
    body = out / "body.obj"
    write_obj(body, rest.vertices, rest.faces, f"datagen rest body ({rest.gender})")
    spec_path = out / "outfit.json"
    spec_path.write_text(json.dumps(json.loads(spec.to_json()), indent=1, sort_keys=True))
    layers = [MeshLayer(rest.vertices, rest.faces, BODY_COLOUR)]
    for k, g in enumerate(garments):
        layers.append(MeshLayer(g.vertices, g.faces, GARMENT_COLOURS[k % len(GARMENT_COLOURS)],
                                two_sided=True))
    preview = out / "preview.png"
    save_png(preview, render_views(layers, ("front", "side"), height))
    return written + [body, spec_path, preview]


def spec_for_seed(seed: int, pipeline: str | Path | None) -> SceneSpec:
    """The scene spec a recipe (default: the built-in defaults) draws for `seed`."""
    from datagen.recipe import LoadedRecipe, Recipe, load_recipe
    from datagen.sampling import sample_scene

    if pipeline:
        loaded = load_recipe(pipeline)
        loaded = LoadedRecipe(replace(loaded.recipe, seed=seed), loaded.path)
    else:
        # An empty outfit section means a body-only dataset; any key turns on the outfit stage
        # with CLOTH3D's rules for the rest.
        rules = {"full_body_probability": 0.3}
        loaded = LoadedRecipe(Recipe(name="garments", seed=seed, sequences=1, outfit=rules),
                              Path.cwd() / "garments.yaml")
    return sample_scene(loaded, 0)


def load_spec(path: str | Path) -> SceneSpec:
    return SceneSpec.from_json(Path(path).read_text(), str(path))
