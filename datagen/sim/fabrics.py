"""Fabrics: physical, resolution-independent parameters derived from Blender's cloth presets.

Blender's presets (scripts/presets/cloth/*.py in Blender 3.4) give a per-vertex mass and spring
constants that Blender divides by the average spring length, in an internal time unit of one
frame. Their behaviour therefore changes with the mesh resolution. We convert them once, at the
reference edge length of CLOTH3D's garments (h0 = 1 cm) and CLOTH3D's 30 fps, into quantities
per unit area, and our mass-spring model then scales them per element so a fabric behaves the
same at any resolution (docs/fabrics.md has the table and the derivation):

- areal density       rho  = s_mass * m_blender                       (kg/m^2)
- stretch stiffness   Y    = 3 * s_mass * h0 * k_blender * fps^2      (N/m), per spring
                       k_e  = Y * A_e / L_e^2 (A_e: area attributed to the edge)
- bending rigidity    B    = s_mass * h0^3 * b_blender * fps^2 / 10   (N m)
- Rayleigh damping    beta = damping_blender * h0 / (k_blender * fps) (s), c_e = beta * k_e
  (Blender divides stiffness, not damping, by the spring length)
- bending damping     beta_b = bending_damping_blender * 10 ms        (s): Blender's angular
  bending damping acts on wing-vertex speeds and has no per-area equivalent; this choice keeps
  bending waves of a few centimetres under-critically damped, as in Blender's cotton
- air drag            d    = 0.01 * air_blender * fps * s_mass        (kg/(m^2 s))

with s_mass = 0.5 m^-2 chosen so that cotton weighs 150 g/m^2, a real shirting weight; the other
densities then come out as real fabrics too (silk 75, denim 500 g/m^2). Only ratios of stiffness
to mass shape the motion, so this scale does not change Blender's dynamics at h0.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from datagen.config import check_range, from_mapping, load_yaml
from datagen.errors import InputError

REFERENCE_EDGE = 0.01  # m, CLOTH3D's garment resolution
REFERENCE_FPS = 30.0  # Blender's cloth time unit is one frame
MASS_SCALE = 0.5  # m^-2: Blender vertex mass -> areal density


@dataclass(frozen=True)
class BlenderPreset:
    """The values of a Blender 3.4 cloth preset file."""

    quality: int
    mass: float
    tension: float
    compression: float
    shear: float
    bending: float
    tension_damping: float
    compression_damping: float
    shear_damping: float
    air_damping: float
    bending_damping: float = 0.5  # DNA default; the presets do not set it


BLENDER_PRESETS: dict[str, BlenderPreset] = {
    "cotton": BlenderPreset(5, 0.3, 15, 15, 15, 0.5, 5, 5, 5, 1.0),
    "denim": BlenderPreset(12, 1.0, 40, 40, 40, 10, 25, 25, 25, 1.0),
    "leather": BlenderPreset(15, 0.4, 80, 80, 80, 150, 25, 25, 25, 1.0),
    "rubber": BlenderPreset(7, 3.0, 15, 15, 15, 25, 25, 25, 25, 1.0),
    "silk": BlenderPreset(5, 0.15, 5, 5, 5, 0.05, 0, 0, 0, 1.0),
}


@dataclass(frozen=True)
class Fabric:
    """A fabric in SI units per unit area; see the module docstring for the conversion."""

    name: str
    density: float  # kg/m^2
    stretch: float  # N/m, tension stiffness of warp/weft (structural) springs
    compression: float  # N/m, stiffness of structural springs when shorter than rest
    shear: float  # N/m, stiffness of diagonal (shear) springs
    bending: float  # N m, bending rigidity
    stretch_damping: float  # s, Rayleigh factor on stretch/shear springs
    bending_damping: float  # s, Rayleigh factor on bending
    air_drag: float  # kg/(m^2 s), linear drag on velocity (still air: wind acts by pressure)
    friction: float = 0.3  # Coulomb coefficient against the body
    thickness: float = 0.004  # m, kept between cloth and body (and between layers)
    max_strain: float = 0.25  # QA: the edge strain this fabric should stay within
    source: str = "user"

    def validate(self, source, path: str) -> None:
        for name in ("density", "stretch", "compression", "shear"):
            check_range(getattr(self, name), 1e-9, None, source, f"{path}.{name}")
        for name in ("bending", "stretch_damping", "bending_damping", "air_drag", "friction"):
            check_range(getattr(self, name), 0.0, None, source, f"{path}.{name}")
        check_range(self.thickness, 1e-4, 0.05, source, f"{path}.thickness")
        # A bound of 0 (inextensible) cannot be met in floating point: every sequence would run
        # the top preset at many times the cost and still break it (a t-shirt at 0: strain
        # 0.002 after 40x8, 73 s for one frame).
        check_range(self.max_strain, 1e-3, 10.0, source, f"{path}.max_strain")


def fabric_from_blender(name: str, preset: BlenderPreset, **overrides) -> Fabric:
    h0, fps, s = REFERENCE_EDGE, REFERENCE_FPS, MASS_SCALE

    def stiff(k: float) -> float:
        return 3.0 * s * h0 * k * fps**2

    def damp(c: float, k: float) -> float:
        return c * h0 / (k * fps) if k > 0 else 0.0

    fabric = Fabric(
        name=name,
        density=s * preset.mass,
        stretch=stiff(preset.tension),
        compression=stiff(preset.compression),
        shear=stiff(preset.shear),
        bending=s * h0**3 * preset.bending * fps**2 / 10.0,
        stretch_damping=damp(preset.tension_damping, preset.tension),
        bending_damping=preset.bending_damping * 0.01,
        air_drag=0.01 * preset.air_damping * fps * s,
        source=f"Blender 3.4 preset '{name}'",
    )
    return replace(fabric, **overrides)


# Thicker, stiffer fabrics keep a larger gap; strain bounds follow each fabric's stiffness
# (a soft silk may stretch more under the same load than leather). Friction against skin sits
# at the upper end of measured textile-on-skin values (about 0.3-0.9, higher on moist skin):
# a shoulder strap rests on Anny's trapezius, sloped at about 35 degrees, and at mu 0.2-0.5 the
# straps of a top slid down the arms during the lead-in (tests/test_sim_dressing.py).
FABRICS: dict[str, Fabric] = {
    "cotton": fabric_from_blender(
        "cotton", BLENDER_PRESETS["cotton"], friction=0.6, thickness=0.004, max_strain=0.25
    ),
    "silk": fabric_from_blender(
        "silk", BLENDER_PRESETS["silk"], friction=0.6, thickness=0.003, max_strain=0.35
    ),
    "denim": fabric_from_blender(
        "denim", BLENDER_PRESETS["denim"], friction=0.7, thickness=0.005, max_strain=0.20
    ),
    "leather": fabric_from_blender(
        "leather", BLENDER_PRESETS["leather"], friction=0.7, thickness=0.006, max_strain=0.15
    ),
    "rubber": fabric_from_blender(
        "rubber", BLENDER_PRESETS["rubber"], friction=1.0, thickness=0.005, max_strain=0.40
    ),
}


def load_fabrics(path: str | Path) -> dict[str, Fabric]:
    """User fabrics from YAML: `fabrics: {name: {density: ..., stretch: ..., ...}}`; each may
    start from a built-in with `base: cotton` and override some values."""
    path = Path(path)
    data = load_yaml(path)
    if set(data) - {"fabrics"}:
        raise InputError(path, sorted(set(data) - {"fabrics"})[0],
                         "only the top-level key 'fabrics' (fabrics: {name: {...}})")
    raw = data.get("fabrics") or {}
    if not isinstance(raw, dict):
        raise InputError(path, "fabrics", "a mapping of fabric name -> parameters", raw)
    out: dict[str, Fabric] = {}
    for name, values in raw.items():
        if not isinstance(values, dict):
            raise InputError(path, f"fabrics.{name}", "a mapping of parameters", values)
        if name in FABRICS:
            # A shard records a fabric by name: a user "cotton" would read as the built-in.
            raise InputError(path, f"fabrics.{name}",
                             f"a name other than the built-in fabrics ({', '.join(FABRICS)}); "
                             f"to change one, name the result and start from it "
                             f"(my_{name}: {{base: {name}, ...}})", name)
        values = dict(values)
        base = values.pop("base", None)
        if base is not None:
            if base not in FABRICS:
                raise InputError(
                    path, f"fabrics.{name}.base", f"a built-in fabric ({', '.join(FABRICS)})", base
                )
            merged = {k: getattr(FABRICS[base], k) for k in Fabric.__dataclass_fields__}
            merged.update(values)
            merged["name"] = name
            merged["source"] = f"{path.name} (from {base})"
            values = merged
        else:
            values.setdefault("name", name)
            values.setdefault("source", path.name)
        out[name] = from_mapping(Fabric, values, path, f"fabrics.{name}")
    return out


def get_fabric(name: str, extra: dict[str, Fabric] | None = None) -> Fabric:
    table = {**FABRICS, **(extra or {})}
    if name not in table:
        raise InputError(None, "fabric", f"one of {', '.join(sorted(table))}", name)
    return table[name]


def fabric_table_markdown() -> str:
    """The built-in fabrics as a markdown table (docs/fabrics.md embeds it; a test keeps it in
    sync)."""
    head = (
        "| fabric | density kg/m^2 | stretch N/m | compression N/m | shear N/m | bending N m | "
        "stretch damping s | bending damping s | air drag kg/(m^2 s) | friction | thickness mm "
        "| max strain |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = []
    for f in FABRICS.values():
        rows.append(
            f"| {f.name} | {f.density:.3f} | {f.stretch:.1f} | {f.compression:.1f} | "
            f"{f.shear:.1f} | {f.bending:.3g} | {f.stretch_damping:.3g} | "
            f"{f.bending_damping:.3g} | {f.air_drag:.3f} | {f.friction:.2f} | "
            f"{f.thickness * 1000:.1f} | {f.max_strain:.2f} |"
        )
    return head + "\n".join(rows) + "\n"


def preset_table_markdown() -> str:
    head = (
        "| preset | quality | mass | tension | compression | shear | bending | tension damp. | "
        "compr. damp. | shear damp. | air | bending damp. |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = [
        f"| {name} | {p.quality} | {p.mass} | {p.tension} | {p.compression} | {p.shear} | "
        f"{p.bending} | {p.tension_damping} | {p.compression_damping} | {p.shear_damping} | "
        f"{p.air_damping} | {p.bending_damping} |"
        for name, p in BLENDER_PRESETS.items()
    ]
    return head + "\n".join(rows) + "\n"
