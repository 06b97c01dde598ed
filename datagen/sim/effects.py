"""Physical effects and the rules that derive a scene's effects from its content.

The rules (docs/simulator.md, "Effects"):
- gravity, stretch, shear, bending, air drag: always, for any cloth;
- body collision: when there is a body; friction: with body collision and a fabric friction > 0;
- garment-garment collision: only when the outfit has two or more garments;
- self-collision: only for loose garments that can fold onto themselves (skirts, dresses, and any
  garment with a loose fit, tightness < -0.5 on the size axis); a tight top needs none;
- elastic rings: only when a garment has elastic loops;
- pins: only when a garment has pinned vertices (waistbands attached to the body);
- wind: only when the scene asks for it (a wind velocity); naming it in a request without one
  is refused (it would blow still air);
- pressure drag (air pushing on each panel, quadratic in its speed along its normal; on cloth
  worn on a body, on the panels' outer faces only): with wind, and otherwise only when asked
  (`auto,+pressure_drag`). Wind is air pushing on panels, and it acts only through this law
  (the linear drag is Blender's damping, relative to still air), so wind without pressure drag
  is refused. In still air, Blender's linear drag is CLOTH3D's model of the air, and
  docs/simulator.md ("Open shirts on the move") has what the quadratic one changes there.
`--effects all` turns everything on that the scene can support; an explicit list overrides;
`auto` or `all` followed by `-name` / `+name` items changes that base (`auto,-self_collision`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from datagen.errors import InputError

EFFECT_NAMES = (
    "gravity",
    "stretch",
    "shear",
    "bending",
    "body_collision",
    "friction",
    "garment_collision",
    "self_collision",
    "elastic",
    "pins",
    "air_drag",
    "pressure_drag",
    "wind",
)
LOOSE_CATEGORIES = frozenset({"skirt", "dress"})
LOOSE_TIGHTNESS = -0.5


@dataclass(frozen=True)
class Effects:
    gravity: bool = True
    stretch: bool = True
    shear: bool = True
    bending: bool = True
    body_collision: bool = True
    friction: bool = True
    garment_collision: bool = False
    self_collision: bool = False
    elastic: bool = False
    pins: bool = False
    air_drag: bool = True
    pressure_drag: bool = False
    wind: bool = False

    def enabled(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name)]


@dataclass(frozen=True)
class SceneContent:
    """What the rules look at."""

    has_body: bool
    n_garments: int
    categories: tuple[str, ...]
    tightness: tuple[tuple[float, float], ...]
    has_elastic: bool
    has_pins: bool
    wants_wind: bool
    max_friction: float


def auto_effects(scene: SceneContent) -> Effects:
    loose = any(
        cat in LOOSE_CATEGORIES or tight[0] < LOOSE_TIGHTNESS
        for cat, tight in zip(scene.categories, scene.tightness, strict=True)
    )
    return Effects(
        body_collision=scene.has_body,
        friction=scene.has_body and scene.max_friction > 0,
        garment_collision=scene.n_garments >= 2,
        self_collision=loose,
        elastic=scene.has_elastic,
        pins=scene.has_pins,
        pressure_drag=scene.wants_wind,
        wind=scene.wants_wind,
    )


def split_effects_request(request: str | tuple[str, ...] | list[str]) -> tuple[str, list[str]]:
    """Check an effects request's syntax: ('auto' | 'all', ['+name' | '-name', ...]) for a base
    with changes, or ('', [name, ...]) for a plain list. Raises InputError (field 'effects',
    no source: callers that read a file add theirs) naming the first bad item."""
    names = request.split(",") if isinstance(request, str) else list(request)
    names = [n.strip() for n in names if n.strip()]
    # A name given twice ('stretch,stretch', 'auto,+wind,-wind') is a slip whose intent the
    # order would decide silently.
    named = [n.lstrip("+-") for n in names]
    twice = [n for k, n in enumerate(names) if named[k] in named[:k]]
    if twice:
        raise InputError(None, "effects", "each effect named once", twice[0])
    if names and names[0] in ("auto", "all"):
        bad = [n for n in names[1:] if n[:1] not in "+-" or n[1:] not in EFFECT_NAMES]
        if bad:
            raise InputError(
                None, "effects",
                f"after '{names[0]}', items '+name' or '-name' with a name among "
                f"{', '.join(EFFECT_NAMES)}", bad[0],
            )
        return names[0], names[1:]
    unknown = [n for n in names if n not in EFFECT_NAMES]
    if unknown or not names:
        raise InputError(
            None, "effects", f"auto, all, or a list of {', '.join(EFFECT_NAMES)}",
            unknown[0] if unknown else request,
        )
    return "", names


def check_wind_request(request: str | tuple[str, ...] | list[str], has_wind: bool) -> None:
    """Refuse a request whose wind would silently do nothing: one that names wind ('+wind', or
    'wind' in a list) for a scene without a wind velocity (the kernels would blow still air;
    'all' turns every kernel on, wind's too, as a measure of what they cost), and, in a scene
    with one, a request that keeps wind but not pressure drag, the only law wind acts by."""
    _check_wind(*split_effects_request(request), has_wind)


def _check_wind(base: str, names: list[str], has_wind: bool) -> None:
    """check_wind_request on a request already split by split_effects_request."""
    if ("+wind" if base else "wind") in names and not has_wind:
        raise InputError(
            None, "effects",
            "wind only with a wind velocity (--wind x,y,z; a recipe's simulation.wind)", "wind"
        )
    if not has_wind:
        return
    wind_on = "-wind" not in names if base else "wind" in names
    pressure_on = "-pressure_drag" not in names if base else "pressure_drag" in names
    if wind_on and not pressure_on:
        hint = f" ({base},-wind,-pressure_drag drops both)" if base else ""
        raise InputError(
            None, "effects",
            f"wind together with pressure_drag, the law wind pushes on panels by{hint}",
            "-pressure_drag" if base else "wind",
        )


def wind_blows(wind) -> bool:
    """Whether a wind velocity (x, y, z, or None) blows at all."""
    return wind is not None and any(abs(w) > 0 for w in wind)


def resolve_effects(request: str | tuple[str, ...] | list[str], scene: SceneContent) -> Effects:
    """'auto' applies the rules, 'all' enables every supported effect, a list is taken as is
    (effects the scene cannot have, like body collision without a body, are an error).
    'auto' or 'all' followed by '-name' / '+name' items changes that base: 'auto,-self_collision'
    is the scene's own effects without self-collision."""
    base, names = split_effects_request(request)
    _check_wind(base, names, scene.wants_wind)
    if not base:
        chosen = set(names)
    else:
        chosen = set((auto_effects(scene) if base == "auto" else _all_effects(scene)).enabled())
        for change in names:
            (chosen.add if change[0] == "+" else chosen.discard)(change[1:])
    if "body_collision" in chosen and not scene.has_body:
        raise InputError(
            None, "effects", "body_collision only in a scene with a body", "body_collision"
        )
    if "friction" in chosen and "body_collision" not in chosen:
        # Friction acts in body contact: without it there is nothing to rub. Name the fix for a
        # request that removed body_collision from a base which has friction.
        hint = f" ({base},-body_collision,-friction drops both)" if base else ""
        raise InputError(None, "effects", f"friction together with body_collision{hint}",
                         "friction")
    return Effects(**{name: name in chosen for name in EFFECT_NAMES})


def _all_effects(scene: SceneContent) -> Effects:
    """Every effect the scene can support."""
    return Effects(
        body_collision=scene.has_body,
        friction=scene.has_body,
        garment_collision=scene.n_garments >= 2,
        self_collision=True,
        elastic=scene.has_elastic,
        pins=scene.has_pins,
        pressure_drag=True,
        wind=True,
    )
