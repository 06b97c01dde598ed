"""Outfits: sampling them into the SceneSpec (CLOTH3D's rules) and assembling the garments.

Rules (thesis 3.3.2-3.3.3, docs/recipes.md "outfit"):
- one upper and one lower garment, or one full-body garment (a top sewn to trousers is a
  jumpsuit, to a skirt a dress);
- fabrics cotton, silk, denim, leather; upper-body garments only cotton or silk;
- each sleeve end and each leg end is elastic with probability 0.5, and so is the waist of a
  full-body garment;
- tightness gamma in [-1.5, 0.5]^2 per outfit (biased to loose: tight clothes move less);
- when an upper and a lower garment overlap, the upper one is the outer layer;
- the waist of a lower garment is attached to the body (a waistband); full-body garments hang
  from the shoulders.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datagen.config import check_range, from_mapping
from datagen.errors import InputError
from datagen.spec import GarmentSpec, OutfitSpec, SubjectSpec
from datagen.types import Garment, RestBody

UPPER_TEMPLATES = {"tshirt": "tshirt", "shirt": "tshirt", "polo": "tshirt", "top": "top"}
LOWER_TEMPLATES = ("trousers", "skirt")
FULL_BODY = {"jumpsuit": "trousers", "dress": "skirt"}  # sewn from a top and this
FABRICS = ("cotton", "silk", "denim", "leather")
UPPER_FABRICS = ("cotton", "silk")
ELASTIC_ROLES = ("sleeve_l_end", "sleeve_r_end", "leg_l_end", "leg_r_end")


def default_templates_dir() -> Path:
    env = os.environ.get("DATAGEN_TEMPLATES")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "templates"


@dataclass(frozen=True)
class OutfitConfig:
    templates: str = ""  # folder of templates/<gender>/<name>.obj; "" = the shipped ones
    full_body_probability: float = 0.3
    upper: dict[str, float] = field(
        default_factory=lambda: {"tshirt": 0.4, "shirt": 0.15, "polo": 0.15, "top": 0.3}
    )
    lower: dict[str, float] = field(default_factory=lambda: {"trousers": 0.5, "skirt": 0.5})
    full: dict[str, float] = field(default_factory=lambda: {"jumpsuit": 0.5, "dress": 0.5})
    # Skirts and dresses for male subjects too? CLOTH3D's male outfits had none.
    male_skirts: bool = False
    fabrics: dict[str, float] = field(default_factory=lambda: {name: 1.0 for name in FABRICS})
    upper_fabrics: dict[str, float] = field(
        default_factory=lambda: {name: 1.0 for name in UPPER_FABRICS}
    )
    elastic_probability: float = 0.5
    tightness: tuple[tuple[float, float], tuple[float, float]] = ((-1.5, 0.5), (-1.5, 0.5))
    randomize_shape: bool = True
    randomize_cuts: bool = True

    def validate(self, source, path: str) -> None:
        check_range(self.full_body_probability, 0.0, 1.0, source, f"{path}.full_body_probability")
        check_range(self.elastic_probability, 0.0, 1.0, source, f"{path}.elastic_probability")
        for key, table, allowed in (
            ("upper", self.upper, UPPER_TEMPLATES),
            ("lower", self.lower, LOWER_TEMPLATES),
            ("full", self.full, FULL_BODY),
            ("fabrics", self.fabrics, FABRICS),
            ("upper_fabrics", self.upper_fabrics, UPPER_FABRICS),
        ):
            for name, weight in table.items():
                if name not in allowed:
                    raise InputError(
                        source, f"{path}.{key}.{name}", f"one of {', '.join(allowed)}", name
                    )
                check_range(weight, 0.0, None, source, f"{path}.{key}.{name}")
            if table and sum(table.values()) <= 0:
                raise InputError(source, f"{path}.{key}", "at least one positive weight", table)
        for k, (lo, hi) in enumerate(self.tightness):
            if not (-3.0 <= lo <= hi <= 3.0):
                raise InputError(
                    source, f"{path}.tightness[{k}]", "[low, high] within [-3, 3]", [lo, hi]
                )


def outfit_config(loaded) -> OutfitConfig:
    return from_mapping(OutfitConfig, dict(loaded.recipe.outfit), loaded.path, "outfit")


def _choose(rng: np.random.Generator, weights: dict[str, float]) -> str:
    names = sorted(k for k, w in weights.items() if w > 0)
    w = np.array([weights[k] for k in names], dtype=np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _r(x: float) -> float:
    return float(round(float(x), 6))


@functools.cache
def _template(templates_dir: str, gender: str, name: str):
    from datagen.garment.template import load_template

    path = Path(templates_dir) / gender / f"{name}.obj"
    if not path.is_file():
        raise InputError(path, "outfit.templates", "a template OBJ + JSON sidecar", "missing")
    return load_template(path)


def _part_spec(
    rng,
    cfg: OutfitConfig,
    templates_dir: str,
    gender: str,
    name: str,
    template: str,
    variant: str,
    fabric: str,
    layer: int,
    elastic_roles: tuple[str, ...],
    keep_torso: bool = False,
) -> GarmentSpec:
    from datagen.garment.cutting import sample_cuts
    from datagen.garment.shaping import sample_shaping

    t = _template(templates_dir, gender, template)
    shaping = sample_shaping(rng, t) if cfg.randomize_shape else {}
    cuts = sample_cuts(rng, t, variant) if cfg.randomize_cuts else {}
    if keep_torso:
        # The bodice of a jumpsuit or dress is trimmed to the waist when it is sewn on; a hem cut
        # first could end above the waist.
        cuts.pop("torso", None)
    elastic = {role: bool(rng.random() < cfg.elastic_probability) for role in elastic_roles}
    return GarmentSpec(
        name=name,
        template=template,
        variant=variant,
        fabric=fabric,
        shaping=flatten_shaping(shaping),
        cuts={k: _r(v) for k, v in sorted(cuts.items())},
        elastic=elastic,
        layer=layer,
    )


def flatten_shaping(shaping: dict[str, dict[str, float]]) -> dict[str, float]:
    """Shaping parameters per axis as flat "axis.parameter" keys (the scene spec holds floats)."""
    return {
        f"{axis}.{name}": _r(value)
        for axis, params in sorted(shaping.items())
        for name, value in sorted(params.items())
    }


def unflatten_shaping(flat: dict[str, float]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for key, value in flat.items():
        axis, _, name = key.partition(".")
        out.setdefault(axis, {})[name] = float(value)
    return out


def sample_outfit(loaded, rng: np.random.Generator, subject: SubjectSpec) -> OutfitSpec:
    """An outfit drawn from the recipe's outfit section (section stream of the SceneSpec)."""
    cfg = outfit_config(loaded)
    templates_dir = str(resolve_templates_dir(cfg.templates, loaded.base_dir))
    gender = subject.gender
    male_limited = gender == "male" and not cfg.male_skirts
    tight = tuple(_r(rng.uniform(lo, hi)) for lo, hi in cfg.tightness)
    full_weights = dict(cfg.full)
    lower_weights = dict(cfg.lower)
    if male_limited:
        full_weights.pop("dress", None)
        lower_weights.pop("skirt", None)
    full = bool(rng.random() < cfg.full_body_probability) and sum(full_weights.values()) > 0
    if full:
        kind = _choose(rng, full_weights)
        fabric = _choose(rng, cfg.fabrics)
        upper = _part_spec(
            rng, cfg, templates_dir, gender, kind, "top", "top", fabric, 0, (), keep_torso=True
        )
        lower_roles = ELASTIC_ROLES[2:] if kind == "jumpsuit" else ()
        lower = _part_spec(
            rng,
            cfg,
            templates_dir,
            gender,
            kind,
            FULL_BODY[kind],
            FULL_BODY[kind],
            fabric,
            0,
            lower_roles,
        )
        waist = {"waist": bool(rng.random() < cfg.elastic_probability)}
        lower = GarmentSpec(**{**lower.__dict__, "elastic": {**lower.elastic, **waist}})
        return OutfitSpec(garments=(upper, lower), tightness=tight, sewn=kind)
    variant = _choose(rng, cfg.upper)
    upper_roles = ELASTIC_ROLES[:2] if UPPER_TEMPLATES[variant] == "tshirt" else ()
    upper = _part_spec(
        rng,
        cfg,
        templates_dir,
        gender,
        "upper",
        UPPER_TEMPLATES[variant],
        variant,
        _choose(rng, cfg.upper_fabrics),
        1,
        upper_roles,
    )
    lower_t = _choose(rng, lower_weights)
    lower_roles = ELASTIC_ROLES[2:] if lower_t == "trousers" else ()
    lower = _part_spec(
        rng,
        cfg,
        templates_dir,
        gender,
        "lower",
        lower_t,
        lower_t,
        _choose(rng, cfg.fabrics),
        0,
        lower_roles,
    )
    return OutfitSpec(garments=(upper, lower), tightness=tight, sewn=None)


def resolve_templates_dir(templates: str, base_dir: Path | None) -> Path:
    if not templates:
        return default_templates_dir()
    path = Path(templates)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return path


# -- assembly ----------------------------------------------------------------------------------
def dropped_parts_for(outfit: OutfitSpec) -> frozenset[str]:
    """Body parts this outfit never reaches, left out of the cloth collider (design 4.1). Only
    the head: arms hanging by the sides brush skirts and trousers whatever the sleeves, long
    sleeves reach the hands and long legs the feet, so the rest of the body stays."""
    del outfit  # every outfit reaches the same parts today
    return frozenset({"head"})


def make_outfit(
    outfit: OutfitSpec, subject: RestBody, body_model, templates_dir: str | Path | None = None
) -> list[Garment]:
    """The garments of an outfit spec, shaped, cut, sewn and resized to the subject's rest body
    (T-pose, as the body model gives it)."""
    from datagen.body.anny_model import NEUTRAL_SHAPE
    from datagen.garment.cutting import cut
    from datagen.garment.resize import (
        bodice_tightness,
        garment_body_shape,
        resize,
        yoke_tightness,
    )
    from datagen.garment.sewing import sew
    from datagen.garment.shaping import shape
    from datagen.garment.template import to_garment

    templates_dir = str(templates_dir or default_templates_dir())
    gender = subject.gender
    parts = []
    for g in outfit.garments:
        t = _template(templates_dir, gender, g.template)
        t = shape(t, unflatten_shaping(g.shaping)) if g.shaping else t
        t = cut(t, dict(g.cuts), g.variant) if (g.cuts or g.variant != g.template) else t
        parts.append((g, t))
    if outfit.sewn:
        (gu, tu), (gl, tl) = parts
        sewn_t = sew(tu, tl, outfit.sewn)
        spec = GarmentSpec(
            name=outfit.sewn,
            template=outfit.sewn,
            variant=outfit.sewn,
            fabric=gl.fabric,
            elastic={**gu.elastic, **gl.elastic},
            layer=0,
        )
        parts = [(spec, sewn_t)]
    template_body = body_model.rest_body(gender, NEUTRAL_SHAPE)

    def sized(tightness: tuple[float, float]) -> RestBody:
        """The body a garment of that tightness is cut for (the subject with the offsets)."""
        return body_model.rest_body(
            gender, garment_body_shape(subject.shape, subject.shape_names, tightness),
            extrapolate=True)

    def body_for(tightness: tuple[float, float] | None) -> RestBody | None:
        if tightness is None:
            return None
        return subject if tightness == (0.0, 0.0) else sized(tightness)

    garment_body = sized(outfit.tightness)
    yoke_body = body_for(yoke_tightness(outfit.tightness))
    bodice_body = body_for(bodice_tightness(outfit.tightness))
    garments = []
    for spec, t in parts:
        # A garment hung from a waistband and the shoulders: its bodice as long as the torso.
        hung_twice = t.category == "full" and "waist" in t.paths
        start, rest = resize(t.vertices, t.faces, template_body, subject, garment_body,
                             yoke_body, bodice_body if hung_twice else None)
        garment = to_garment(t, spec.fabric, spec.name)
        garment.vertices = start
        garment.rest_vertices = rest
        if outfit.sewn and "waist" in t.paths:
            # The sewn-in waistband of the lower garment: attached and (when sampled) elastic
            # like the waist of the lower garment it was made from.
            garment.loops["waist"] = np.asarray(t.paths["waist"])
        garment.elastic = tuple(
            r for r, on in sorted(spec.elastic.items()) if on and r in garment.loops
        )
        garment.tightness = tuple(outfit.tightness)
        garment.layer = spec.layer
        # A waistband holds what hangs from the waist: lower garments and sewn full-body ones.
        if t.category in ("lower", "full") and "waist" in garment.loops:
            garment.pinned = np.asarray(garment.loops["waist"])
        garment.meta = {
            "template": spec.template,
            "variant": spec.variant,
            "shaping": dict(spec.shaping),
            "cuts": dict(spec.cuts),
        }
        garments.append(garment)
    return garments
