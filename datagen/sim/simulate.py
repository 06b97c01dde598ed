"""The simulation stage: an outfit on a moving body -> per-frame garment vertices and QA.

Timeline: the outfit settles on the body in its rest pose, follows the lead-in from rest to the
sequence's first frame, then the sequence; frames after the lead-in are the output (at the body
sequence's frame rate). Each frame is guarded: non-finite positions, runaway speeds or a kinetic
energy blow-up make the frame run again from its start with twice, then four times the substeps;
a frame that still fails rejects the sequence with the reason instead of writing it. The frames
after a retry start at the substeps that held, for a while, before the coarser step is tried
again (RETRY_HOLD).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from datagen.errors import BoundBroken, InputError, RejectedSequence, SlidOffShoulders
from datagen.qa import STRAIN_SHARE_MAX, Breach, breaches
from datagen.sim import backend
from datagen.sim.collider import BodyCollider, frame_tangents
from datagen.sim.effects import Effects, SceneContent, resolve_effects, wind_blows
from datagen.sim.fabrics import Fabric, get_fabric
from datagen.sim.fold_fields import FoldFields, JoinedFoldFields
from datagen.sim.model import ClothModel, build_cloth_model
from datagen.sim.progress import report_frame
from datagen.sim.solvers import SolverSettings, make_solver
from datagen.spec import require_lead_in
from datagen.types import BodySequence, Garment, SimResult

# Quality presets per solver: substeps per frame at PRESET_FPS and iterations
# (docs/accuracy-vs-time.md says where each sits on the measured accuracy/time front).
QUALITY_PRESETS: dict[str, dict[str, tuple[int, int]]] = {
    "xpbd": {"draft": (10, 2), "default": (20, 4), "reference": (40, 8)},
    "explicit": {"draft": (200, 1), "default": (400, 1), "reference": (2000, 1)},
    "implicit": {"draft": (2, 4), "default": (10, 10), "reference": (50, 20)},
}
# The implicit default was 5x10 until 2026-12-05. Its steps were too large to carry a walking
# garment's contact: the walking t-shirt ended 0.57 % of its edges over cotton's strain bound
# (the QA allows 0.1 %). At 10x10 it ends at 0.014 %. Newton also converges in fewer
# iterations per step there: on the 5k cotton tube 10x10 ran 1.7x faster than 5x10, on the
# 4k denim sheet as fast, and on the walking t-shirt 1.25x slower (docs/simulator.md).
# On a parallel backend (a GPU, or more than one CPU thread: backend.serial() is False) xpbd's
# sweeps are coloured (solvers.XPBDSolver), and a coloured sweep carries a correction fewer
# springs along than a serial sweep in mesh order. Each preset there runs twice the substeps and
# twice the iterations: the least measured to keep the serial preset's error or less on the
# three peer scenes (docs/simulator.md).
PARALLEL_QUALITY_PRESETS: dict[str, dict[str, tuple[int, int]]] = {
    "xpbd": {"draft": (20, 4), "default": (40, 8), "reference": (80, 16)},
}
# Over-relaxation of each solver's Gauss-Seidel sweeps (SolverSettings.sor). For xpbd, 1.6
# roughly halves the default preset's error against the float64 reference at the same cost
# (cotton, 20x4: walking t-shirt 22.8 -> 12.0 mm, spinning skirt 56.2 -> 23.6 mm) and, with
# more sweeps of the limit after contact, passes 15 of the 16 full hard cases instead of 12;
# 1.8 gains little more at 20x4, loses at 40x4 and raises the skirt's strain (docs/simulator.md).
OVER_RELAXATION: dict[str, float] = {"xpbd": 1.6}
# ...but not in every sweep where a substep has only one. Over-relaxation maps the most local
# modes of stiff springs (those a plain sweep settles at once) to -(sor - 1) times themselves,
# and the corrections become velocity: with one sweep such a mode grows by a + sqrt(a^2 + a) a
# substep, a = sor - 1, which passes 1 at a = 1/3. At 1.6 a 10k cotton sheet at rest without
# gravity blew up within 5 frames at 10x1, and one falling freely was torn in its plane by 39 mm
# in 6 frames at 20x1. With k sweeps the factor is (1 - sor)^k: 0.36 in size at two (positive
# for these modes; other modes' phases could grow by 1.06 a substep, none measured at 10x2 to
# 40x2) and 0.13 at the default's four (docs/simulator.md, "Over-relaxation"). So with one
# sweep per substep every other sweep is plain (SolverSettings.plain_reverse): the plain one
# settles what the over-relaxed one flipped, and the rest keeps most of the gain (walking
# cotton t-shirt at 40x1: 18.1 mm from its reference, 28.0 with every sweep plain, 11.2 with
# every sweep over-relaxed).
# A sequence simulated again one preset up (SimOptions.escalated) sweeps without
# over-relaxation: the 1.6 that pays at 20x4 runs the fast kick's trousers away at 40x8 (88 m/s
# at frame 26), where plain sweeps pass it (docs/simulator.md, "Escalation").
ESCALATED_SOR = 1.0
# The output rate at which the presets' substeps, the full search's interval
# (SimOptions.search_every) and the strain refinement's rest (REFINE_REST) were tuned. At
# another rate they are scaled so that they stay the same in time: the step sets stability,
# accuracy and how far a limb moves in one, and the output rate should not. Kept per frame, a
# 15 fps walk in denim ran at twice the tuned step and had 8 of its frames redone for strain,
# and a 60 fps one cost 1.65x the 30 fps run per simulated second (docs/simulator.md, "The
# output rate").
PRESET_FPS = 30.0
# A scaled count within this fraction of a whole number is that number (29.97 fps: 20
# substeps, not 21).
RATE_TOLERANCE = 0.01
MAX_RETRIES = 2
# A frame that needed a retry to stay stable leaves the next ones starting at the substeps that
# held, for RETRY_HOLD frames (at PRESET_FPS), before the base substeps are tried again; each
# failed try doubles the hold. A step too coarse for the scene (the explicit draft on a walking
# t-shirt) otherwise fails once every frame: 49 retries in 49 frames, 1.5x the run's cost.
RETRY_HOLD = 10
REFINE_REST = 10  # frames (at PRESET_FPS) without strain refinement after one that did not help
# ...unless a frame ends with this multiple of the previous frame's over-strained share: a new
# event (a kick), not the persistent, slowly changing strain of a garment smaller than its body.
REST_BREAK = 1.5
SPEED_LIMIT = 15.0  # m/s: a cloth vertex faster than this and 3x the body's fastest is runaway
# A frame may give the cloth no more kinetic energy than gravity, what drives it (the body, wind,
# the recovery from penetration) and the elastic energy it releases can: ENERGY_SLACK times that
# bound (kinetic_energy_bound), plus the energy of every vertex at ENERGY_FLOOR_SPEED. More is
# the step adding energy of its own, an instability growing below the speed limit: an explicit
# run of a hanging sheet at too few substeps went from 0.0007 to 0.37 J in one frame, all of its
# vertices at 5-10 m/s, which the absolute guards let through.
ENERGY_SLACK = 2.0
ENERGY_FLOOR_SPEED = 0.1  # m/s
# The depth QA's search reaches this far past the thickest fabric: a vertex beyond its reach,
# measured as the reach itself in the kernel's float32, must still read deeper than any
# vertex's thickness.
DEPTH_QA_MARGIN = 1e-3  # m


def depth_qa_reach(thickness: np.ndarray, cell: float, closed: bool) -> float:
    """How far the depth QA searches for each vertex's closest body triangle: just past the
    thickest fabric (DEPTH_QA_MARGIN) on a closed collider, whose winding number tells inside
    from outside beyond the reach; a whole grid cell on one that is not closed, which reads
    everything beyond the reach as outside."""
    if not closed:
        return cell
    return min(float(np.max(thickness)) + DEPTH_QA_MARGIN, cell)


def output_fps(body: BodySequence | ColliderTrack | None) -> float:
    """The output rate of a simulation on `body` (PRESET_FPS in free space)."""
    return body.fps if body is not None else PRESET_FPS


def _rate_ratio(fps: float) -> float:
    if not fps > 0:
        raise InputError(None, "fps", "a positive frame rate", fps)
    return fps / PRESET_FPS


def _whole(x: float, up: bool) -> int:
    """x as a whole number: the nearest where within RATE_TOLERANCE of it, else rounded up (or
    down)."""
    near = round(x)
    if abs(x - near) <= RATE_TOLERANCE * x:
        return near
    return math.ceil(x) if up else math.floor(x)


def substeps_at(fps: float, substeps_at_preset_fps: int) -> int:
    """Substeps per frame at output rate `fps` for a count tuned at PRESET_FPS: the same step
    in time, rounded to more substeps, so that a step is never longer than tuned (by more than
    RATE_TOLERANCE)."""
    return max(1, _whole(substeps_at_preset_fps / _rate_ratio(fps), up=True))


def interval_at(fps: float, frames_at_preset_fps: int) -> int:
    """Frames between two events at output rate `fps` for an interval tuned at PRESET_FPS: the
    same interval in time, rounded to fewer frames, so that it is never longer than tuned (by
    more than RATE_TOLERANCE), but at least one frame."""
    return max(1, _whole(frames_at_preset_fps * _rate_ratio(fps), up=False))


@dataclass
class SimOptions:
    solver: str = "xpbd"
    quality: str = "default"
    substeps: int | None = None
    iterations: int | None = None
    sor: float | None = None  # over-relaxation; None: the solver's (OVER_RELAXATION)
    effects: str | tuple[str, ...] = "auto"
    wind: tuple[float, float, float] | None = None
    settle_seconds: float = 0.5
    fabrics: dict[str, Fabric] = field(default_factory=dict)  # user fabrics by name
    profile_every: int = 30  # frames between per-effect cost samples (fused solvers)
    search_every: int = 5  # frames between full closest-triangle searches, at PRESET_FPS
    # Times a frame may be redone with twice the substeps while its strain is over the bound:
    # stiff fabrics pulled by fast limbs need more substeps than the preset in some frames only.
    strain_refinements: int = 2
    frames: int = 30  # output frames of a scene without a collider track
    tolerance: float = 1e-5  # implicit: Newton stops below this update (m)
    cg_tolerance: float = 1e-4  # implicit: relative residual of each CG solve
    cg_max_iterations: int = 200
    cg_forcing: bool = False  # implicit: inexact Newton (SolverSettings.cg_forcing)
    # m/s: a cloth vertex faster than this (and 3x the body's fastest) is a runaway. Converged
    # references raise it: a free corner of a heavy sheet whips past 15 m/s for a frame when the
    # step is so fine that backward Euler no longer damps it (the study's denim sheet, 16.7 m/s
    # at 160 substeps, back under 4 m/s two frames later).
    speed_limit: float = SPEED_LIMIT
    # Stop a run at the first output frame where a garment's neckline has slid off the
    # shoulders (qa.neckline_breach), raising SlidOffShoulders: the dataset's gate rejects such
    # a run whatever follows, so its remaining frames would be spent for nothing. Dataset runs
    # whose recipe rejects (simulation.qa) set it; a scene simulated to look at runs to its end.
    neckline_guard: bool = False
    # Stop a run at the first output frame whose QA breaks a bound (qa.breaches: cloth deeper
    # in the body than its thickness, springs past their fabric's strain bound), raising
    # BoundBroken: the escalation ladder simulates such a run again at finer steps whatever
    # follows, and the gate rejects it at the last rung. Set with neckline_guard; inert in a
    # batch of scenes (one scene's breach must not stop the others).
    bound_guard: bool = False

    def resolve_steps(self, fps: float = PRESET_FPS) -> tuple[int, int]:
        """(substeps per frame, iterations) at output rate `fps`: the caller's, else the
        preset's, its substeps scaled from PRESET_FPS (substeps_at)."""
        presets = QUALITY_PRESETS.get(self.solver)
        if presets is None:
            raise InputError(None, "solver", f"one of {', '.join(QUALITY_PRESETS)}", self.solver)
        if self.quality not in presets:
            raise InputError(None, "quality", f"one of {', '.join(presets)}", self.quality)
        if self.solver in PARALLEL_QUALITY_PRESETS and not backend.serial():
            presets = PARALLEL_QUALITY_PRESETS[self.solver]
        sub, it = presets[self.quality]
        return self.substeps or substeps_at(fps, sub), self.iterations or it

    def escalated(self) -> SimOptions | None:
        """The options a sequence is simulated again with when its run breaks a
        physical-validity bound or is rejected as unstable (datagen.pipeline.stages): the next
        quality preset up, with plain Gauss-Seidel sweeps (ESCALATED_SOR) unless the caller
        chose an over-relaxation. None at the top preset, or when the caller gave the steps."""
        if self.substeps is not None or self.iterations is not None:
            return None
        names = list(QUALITY_PRESETS.get(self.solver, {}))
        above = names.index(self.quality) + 1 if self.quality in names else len(names)
        if above >= len(names):
            return None
        return replace(self, quality=names[above], sor=self.escalated_sor())

    def escalated_sor(self) -> float | None:
        """The over-relaxation of an escalated run: the caller's, else plain sweeps
        (ESCALATED_SOR) for a solver that over-relaxes."""
        if self.sor is not None or self.solver not in OVER_RELAXATION:
            return self.sor
        return ESCALATED_SOR

    def steps_label(self, fps: float = PRESET_FPS) -> str:
        """'default 20x4, sor 1.6': the settings a run of these options used at output rate
        `fps`, in words."""
        sub, it = self.resolve_steps(fps)
        alternate = ", every other sweep plain" if self.plain_reverse_sweeps() else ""
        return f"{self.quality} {sub}x{it}, sor {self.resolve_sor():g}{alternate}"

    def plain_reverse_sweeps(self) -> bool:
        """Whether sweeps in reverse order are plain: with the solver's own over-relaxation
        and one sweep per substep, where over-relaxing every sweep grows float rounding into a
        tear (OVER_RELAXATION). A caller's `sor` applies to every sweep."""
        return (self.sor is None and self.solver in OVER_RELAXATION
                and self.resolve_steps()[1] == 1)

    def resolve_sor(self) -> float:
        """The caller's over-relaxation, else the solver's."""
        sor = self.sor
        if sor is None:
            sor = OVER_RELAXATION.get(self.solver, 1.0)
        if not 0.0 < sor < 2.0:  # successive over-relaxation diverges outside (0, 2)
            raise InputError(None, "sor", "an over-relaxation factor in (0, 2)", sor)
        return sor


@dataclass
class _Pins:
    """Pinned cloth vertices attached to body triangles: a barycentric point on the triangle and
    the offset to the cloth vertex in the triangle's own frame, so the pin follows the surface
    exactly where the body moves rigidly and smoothly where it deforms."""

    triangles: np.ndarray  # (P,)
    bary: np.ndarray  # (P, 3)
    local: np.ndarray  # (P, 3) offset in the triangle frame (edge, side, normal)

    @staticmethod
    def frames(corners: np.ndarray) -> np.ndarray:
        """(P, 3, 3) orthonormal frames (rows: edge, in-plane side, normal) of triangles."""
        e1 = corners[:, 1] - corners[:, 0]
        n = np.cross(e1, corners[:, 2] - corners[:, 0])
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True) + 1e-20
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-20
        return np.stack([e1, np.cross(n, e1), n], axis=1)

    def targets(self, body: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The pins' positions (P, 3), float64, on the body pose `body` (V, 3)."""
        corners = body[faces[self.triangles]].astype(np.float64)  # only the pins' corners
        point = np.einsum("pk,pkd->pd", self.bary, corners)
        return point + np.einsum("pid,pi->pd", self.frames(corners), self.local)


def attach_pins(points: np.ndarray, body: np.ndarray, faces: np.ndarray,
                mask: np.ndarray) -> _Pins | None:
    """Attach cloth points to their closest (collider) body triangles in the given body pose."""
    import trimesh

    if len(points) == 0:
        return None
    used = np.flatnonzero(mask)
    mesh = trimesh.Trimesh(body, faces[used], process=False)
    closest, _, tri = trimesh.proximity.closest_point(mesh, points)
    tri_full = used[tri]
    corners = body[faces[tri_full]]
    bary = trimesh.triangles.points_to_barycentric(corners, closest)
    local = np.einsum("pid,pd->pi", _Pins.frames(corners), points - closest)
    return _Pins(tri_full, bary, local)


def scene_content(garments: list[Garment], has_body: bool, wind, fabrics) -> SceneContent:
    return SceneContent(
        has_body=has_body,
        n_garments=len(garments),
        categories=tuple(g.category for g in garments),
        tightness=tuple(tuple(g.tightness) for g in garments),
        has_elastic=any(g.elastic for g in garments),
        has_pins=any(g.pinned is not None and len(g.pinned) for g in garments),
        wants_wind=wind_blows(wind),
        max_friction=max(f.friction for f in fabrics),
    )


def _fabric_strain(model: ClothModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Strain of the fabric springs (ClothModel.fabric_springs) and whether each is beyond its
    fabric's bound."""
    first, second, rest, scale, bound = model.fabric_strain_terms
    # Coordinates as rows: numpy sums along a contiguous row far faster than across the short
    # axis of an (N, 3) array (a walking t-shirt's frame spent 1.6 ms here).
    xt = np.ascontiguousarray(x.T)
    d = xt[:, second] - xt[:, first]
    length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    strain = (length - rest) / scale
    return strain, strain > bound


def where_strained(model: ClothModel, garments: list[Garment], x: np.ndarray,
                   body: np.ndarray | None, vertex_parts: np.ndarray | None,
                   over: np.ndarray | None = None) -> str:
    """Where the strain bound broke at positions x: the garment with the largest share of its
    fabric springs over their bound (`over`, each spring's flag as _fabric_strain gives it;
    None: measured here), how many, and the body parts nearest their midpoints
    (qa.where_on_body) where a `body` (V, 3) and its `vertex_parts` are given."""
    if over is None:
        over = _fabric_strain(model, x)[1]
    first, second = model.fabric_strain_terms[:2]
    per_garment = _garments_within(model, 0, model.n_vertices, first)
    k = int(np.argmax([over[springs].mean() for _, _, springs in per_garment]))
    springs = per_garment[k][2][over[per_garment[k][2]]]
    return _where(garments[k], "springs over", 0.5 * (x[first[springs]] + x[second[springs]]),
                  body, vertex_parts)


def where_deep(model: ClothModel, garments: list[Garment], x: np.ndarray, deep: np.ndarray,
               body: np.ndarray | None, vertex_parts: np.ndarray | None) -> str:
    """where_strained for the depth bound: `deep` flags each vertex too deep."""
    ranges = model.garment_ranges
    k = int(np.argmax([deep[lo:hi].mean() for lo, hi in ranges]))
    lo, hi = ranges[k]
    return _where(garments[k], "vertices too deep", x[lo:hi][deep[lo:hi]], body, vertex_parts)


def _where(garment: Garment, what: str, points: np.ndarray, body: np.ndarray | None,
           vertex_parts: np.ndarray | None) -> str:
    from datagen.body.parts import PART_NAMES
    from datagen.qa import where_on_body

    if len(points) == 0:  # positions that break nothing (a record whose series were set)
        return ""
    out = f"the {garment.fabric} {garment.category} '{garment.name}', {len(points)} {what}"
    if body is None or vertex_parts is None:
        return out
    return out + ", nearest " + where_on_body(points, body, vertex_parts, PART_NAMES)


def _row_norms(a: np.ndarray) -> np.ndarray:
    """|a_i| of an (N, 3) array (np.linalg.norm(a, axis=1), five times faster)."""
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def kinetic_energy(model: ClothModel, v: np.ndarray, lo: int = 0, hi: int | None = None) -> float:
    """Kinetic energy (J) of the vertices lo:hi (all by default)."""
    return 0.5 * float(np.einsum("i,ij,ij->", model.mass[lo:hi], v[lo:hi], v[lo:hi]))


def elastic_energy(model: ClothModel, x: np.ndarray, springs: np.ndarray | slice = slice(None),
                   bends: np.ndarray | slice = slice(None)) -> float:
    """Energy stored in the springs and bending stencils at positions x (J); `springs` and
    `bends` select some of them (a part of a batch: _Part)."""
    e = model.springs[springs]
    stretch = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1) - model.rest_length[springs]
    k = np.where(stretch > 0, model.k_tension[springs], model.k_compression[springs])
    curvature = np.einsum("bk,bkd->bd", model.bend_weights[bends], x[model.bends[bends]])
    return float(0.5 * np.sum(k * stretch**2)
                 + 0.5 * np.sum(model.bend_stiffness[bends]
                                * np.sum(curvature * curvature, axis=1)))


# The words of finer_steps_note that mark a run that did not keep its stated steps (the
# accuracy study's report finds such rows by them in their saved notes).
FINER_STEPS = "at finer steps"


def finer_steps_note(report: dict) -> str:
    """'N frames at finer steps, up to M substeps' for a run report where frames ran at more
    substeps than the run's own, else '' (reports of runs before 2026-12-06 lack the count)."""
    n = int(report.get("frames_at_finer_steps", 0))
    if n == 0:
        return ""
    return f"{n} frames {FINER_STEPS}, up to {report['frame_substeps_max']} substeps"


def kinetic_energy_bound(ke0: float, mass: float, dt: float, gravity: float,
                         drive_speed: float) -> float:
    """The most kinetic energy a cloth of total `mass` with kinetic energy `ke0` can have `dt`
    later when no vertex gains more speed than gravity gives it plus `drive_speed` (the fastest
    thing pushing or pulling it). Gravity alone: dKE/dt = g sum(m_i v_iz) <= g sqrt(2 M KE), so
    sqrt(KE) grows by at most g dt sqrt(M / 2); a driver adds its speed the same way. Internal
    forces only exchange kinetic and elastic energy (the caller adds what was released)."""
    return (np.sqrt(ke0) + np.sqrt(0.5 * mass) * (gravity * dt + drive_speed)) ** 2


def _first_vertex_within(first_vertex: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """The springs or stencils (by their first vertex) that lie in the vertices lo:hi: an
    element never spans two garments."""
    return np.flatnonzero((first_vertex >= lo) & (first_vertex < hi))


def _garments_within(model: ClothModel, lo: int, hi: int,
                     first: np.ndarray) -> tuple[tuple[int, int, np.ndarray], ...]:
    """Each garment in the vertices lo:hi: its range and its fabric springs (`first`: each
    fabric spring's first vertex)."""
    return tuple((g0, g1, _first_vertex_within(first, g0, g1))
                 for g0, g1 in model.garment_ranges if lo <= g0 and g1 <= hi)


@dataclass
class _Part:
    """The vertices of one scene of a batch (datagen.sim.batch), or all of a simulation's: the
    QA series and the energy guards are computed per part, so a scene in a batch is measured
    and guarded as if simulated alone. `fabric` selects its springs among _fabric_strain's,
    `springs` and `bends` among the model's (slices over everything for a whole)."""

    lo: int
    hi: int
    fabric: np.ndarray | slice
    springs: np.ndarray | slice
    bends: np.ndarray | slice
    mass: float
    # Each of its garments: its vertices lo:hi and its fabric springs among _fabric_strain's.
    # The QA's bounds hold per garment: a small top 5 % inside the body over trousers of ten
    # times its vertices reads 0.5 % over the outfit, and a garment of the training data is
    # one garment.
    garments: tuple[tuple[int, int, np.ndarray], ...] = ()
    # Its collider's vertices (a scene's body in a batch).
    body: slice = field(default_factory=lambda: slice(None))
    label: str = ""  # prefixed to a guard's reason ("scene 3: ")

    @staticmethod
    def whole(model: ClothModel) -> _Part:
        everything = slice(None)
        first = model.springs[model.fabric_springs][:, 0]
        return _Part(0, model.n_vertices, everything, everything, everything,
                     float(model.mass.sum()), _garments_within(model, 0, model.n_vertices, first))

    @staticmethod
    def of(model: ClothModel, lo: int, hi: int, body: slice, label: str) -> _Part:
        first = model.springs[model.fabric_springs][:, 0]
        return _Part(lo, hi, _first_vertex_within(first, lo, hi),
                     _first_vertex_within(model.springs[:, 0], lo, hi),
                     _first_vertex_within(model.bends[:, 0], lo, hi),
                     float(model.mass[lo:hi].sum()), _garments_within(model, lo, hi, first),
                     body, label)

    def over_strain_share(self, over: np.ndarray) -> float:
        """The largest share of a garment's fabric springs beyond their bound (`over`, as
        _fabric_strain gives it)."""
        return max(float(over[springs].mean()) for _, _, springs in self.garments)

    def deep_share(self, deep: np.ndarray) -> float:
        """The largest share of a garment's vertices that `deep` (every vertex's) flags."""
        return max(float(deep[lo:hi].mean()) for lo, hi, _ in self.garments)

    def kinetic_energy(self, model: ClothModel, v: np.ndarray) -> float:
        return kinetic_energy(model, v, self.lo, self.hi)


def _qa(model: ClothModel, part: _Part, v: np.ndarray,
        inside_deep: tuple[np.ndarray, np.ndarray] | None,
        fabric_strain: tuple[np.ndarray, np.ndarray]) -> dict:
    """One frame's QA values of a part; `inside_deep` flags every vertex inside the body and
    deeper than its thickness (None: no body), `fabric_strain` is _fabric_strain's."""
    strain = fabric_strain[0][part.fabric]
    out = {
        "strain_mean": float(np.mean(np.abs(strain))),
        "strain_max": float(strain.max()),
        "strain_p999": float(np.percentile(strain, 99.9)),
        "over_strain_share": part.over_strain_share(fabric_strain[1]),
        "kinetic_energy": part.kinetic_energy(model, v),
    }
    if inside_deep is not None:
        out["inside_share"] = part.deep_share(inside_deep[0])
        out["deep_share"] = part.deep_share(inside_deep[1])
    else:
        out["inside_share"] = out["deep_share"] = 0.0
    return out


@dataclass
class ColliderTrack:
    """What the simulator needs of a moving collider: its frames, faces and which faces collide.
    A BodySequence provides one (`track_of`); tests and studies build them for spheres and
    cylinders."""

    vertices: np.ndarray  # (F, V, 3)
    faces: np.ndarray  # (T, 3)
    face_mask: np.ndarray  # (T,) bool
    fps: float = 30.0
    lead_in_frames: int = 0
    # (T,) each face's body part, or None for a collider that is one surface (BodyCollider)
    face_parts: np.ndarray | None = None
    # The distance fields of the parts folding across a joint in the body stage's flexion
    # frames (the hip, knee and elbow), for the part guard (search_kernels.fold_near); a batch's
    # scenes' joined (datagen.sim.batch); None where none fold.
    fold_fields: FoldFields | JoinedFoldFields | None = None
    # A body's neck joint at each frame (F, 3) and at rest (3,), for the note a rejection as
    # unstable gives where a neckline had slid off the shoulders (slid_necklines_note); None
    # for other colliders and a batch's joined track.
    neck: np.ndarray | None = None
    rest_neck: np.ndarray | None = None
    # (V,) each vertex's body part, for the place a breach's reason names (where_strained);
    # None for other colliders and a batch's joined track.
    vertex_parts: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.vertices.shape[0])


def track_of(body: BodySequence) -> ColliderTrack:
    from datagen.body.parts import FLEXION_JOINTS, FLEXION_SIDES, PART_INDEX
    from datagen.qa import NECK_JOINT

    faces = body.rest.faces
    face_parts = body.rest.part_labels[faces[:, 0]]
    report = getattr(body, "self_collision", None)
    by_joint = getattr(report, "flexion_overlap_by_joint", None) or {}
    folds = [(side_a, side_b, frozenset(by_joint[name]))
             for name, (side_a, side_b) in zip(FLEXION_JOINTS, FLEXION_SIDES, strict=True)
             if by_joint.get(name)]
    fields = FoldFields(body.vertices, faces, face_parts, folds, PART_INDEX) if folds else None
    return ColliderTrack(body.vertices, faces, body.collider_face_mask, body.fps,
                         body.lead_in_frames, face_parts, fields,
                         neck=body.joints[:, NECK_JOINT], rest_neck=body.rest.joints[NECK_JOINT],
                         vertex_parts=body.rest.part_labels)


def body_start_transform(body: BodySequence) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation taking the rest body (pelvis above the origin, facing -y) to the
    sequence's first frame (the rest pose, turned to the motion's heading and placed where the
    lead-in starts): garments fitted to the rest body are moved with it."""
    from datagen.rotations import axis_angle_to_matrix

    rot = axis_angle_to_matrix(body.poses[0, :3])
    return rot, body.trans[0] - rot @ body.rest.joints[0]


def _per_frame(known: dict[int, np.ndarray], frame: int,
               compute: Callable[[], np.ndarray]) -> np.ndarray:
    """compute() for `frame`, kept in `known` for the last two frames asked for: a frame's end
    is the next frame's start, and a retried frame asks again."""
    value = known.get(frame)
    if value is None:
        value = compute()
        for old in [f for f in known if f < frame - 1]:
            del known[old]
        known[frame] = value
    return value


class _Simulation:
    def __init__(self, garments: list[Garment], body: ColliderTrack | None, options: SimOptions,
                 start: tuple[np.ndarray, np.ndarray] | None = None,
                 parts: list[tuple[int, int, int, int]] | None = None):
        """`parts`: the scenes of a batch (datagen.sim.batch), each measured and guarded on its
        own: its garments g0:g1 and its collider's vertices b0:b1; None: the garments are one
        scene."""
        # The set-up (model, collider, pins, solver) is timed apart from the frames: a peer's
        # timed frames leave out its own set-up (docs/simulator.md, "Timing against a peer").
        self._t_created = time.perf_counter()
        self.garments = garments
        self.body = body
        self.options = options
        self.fabrics = [get_fabric(g.fabric, options.fabrics) for g in garments]
        self.model = build_cloth_model(list(zip(garments, self.fabrics, strict=True)))
        ranges = self.model.garment_ranges
        self.parts = [_Part.whole(self.model)] if parts is None else [
            _Part.of(self.model, ranges[g0][0], ranges[g1 - 1][1], slice(b0, b1), f"scene {k}: ")
            for k, (g0, g1, b0, b1) in enumerate(parts)
        ]
        if start is not None:
            rot, shift = start
            self.model.x0 = self.model.x0 @ rot.T + shift
        content = scene_content(garments, body is not None, options.wind, self.fabrics)
        self.effects: Effects = resolve_effects(options.effects, content)
        self.fps = output_fps(body)
        self.substeps, self.iterations = options.resolve_steps(self.fps)
        self.search_every = interval_at(self.fps, options.search_every)
        self.refine_rest_frames = interval_at(self.fps, REFINE_REST)
        self.sor = options.resolve_sor()
        self.plain_reverse = options.plain_reverse_sweeps()
        if body is not None:
            self.faces = np.asarray(body.faces)
            self.mask = np.asarray(body.face_mask, dtype=bool)
            self.collider = BodyCollider(self.faces, self.mask, body.vertices.shape[1],
                                         face_parts=body.face_parts)
            # The depth QA asks only which side of the body each vertex is on and whether it
            # is deeper than its thickness, so its search reaches just past the thickest
            # fabric (collider.signed_distance's `within`).
            self._depth_reach = depth_qa_reach(self.model.thickness, self.collider.cell,
                                               self.collider.closed)
        else:
            self.collider = None
        self.pins = None
        self._pins_at: dict[int, np.ndarray] = {}  # _pin_targets
        self._tangents_at: dict[int, np.ndarray] = {}  # _tangents
        self.fixed_pins = None
        if self.effects.pins and len(self.model.pinned):
            if body is not None:
                self.pins = attach_pins(self.model.x0[self.model.pinned],
                                        body.vertices[0].astype(np.float64), self.faces,
                                        self.mask)
            else:  # no body to hold them: pinned vertices stay where they start
                self.fixed_pins = self.model.x0[self.model.pinned].copy()
        self.retries = 0
        # Where the next frame starts (_advance): the doublings of the substeps that the last
        # retry needed, the frames left before one fewer is tried, and how many such tries
        # in a row have failed (each doubles the hold).
        self.start_level = 0
        self.hold_left = 0
        self.failed_step_downs = 0
        self.stepping_down = False
        self.retry_hold_frames = interval_at(self.fps, RETRY_HOLD)
        self.strain_refinements = 0
        self.refine_rest = 0  # frames left before strain refinement is tried again
        self.last_share = 0.0  # the previous frame's over-strained share (while resting)
        self.frame_substeps: list[int] = []
        # Positions and each part's kinetic energy where the frame being run starts
        # (_advance): the energy guard's reference for the frame and its retries.
        self._frame_start: tuple[np.ndarray, list[float]] | None = None
        # The state last read from a solver, until that solver's state changes: a frame reads
        # it once (its guards) instead of again for the strain check, the output and the
        # next frame's start (each read is a device copy and a float64 conversion).
        self._known: tuple[object, np.ndarray, np.ndarray] | None = None
        # The fabric strain of the last positions it was computed for: the strain refinement's
        # check and the frame's QA read the same positions (2 ms a walking t-shirt frame each).
        self._strain_of: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None

    def _state(self, solver) -> tuple[np.ndarray, np.ndarray]:
        known = self._known
        if known is None or known[0] is not solver:
            x, v = solver.get_state()
            x.flags.writeable = v.flags.writeable = False  # shared by the readers above
            known = self._known = (solver, x, v)
        return known[1], known[2]

    def _set_state(self, solver, x: np.ndarray, v: np.ndarray) -> None:
        solver.set_state(x, v)
        self._known = None  # stored in the solver's precision: read it back when needed

    def _solver(self, substeps: int):
        settings = SolverSettings(
            substeps=substeps,
            iterations=self.iterations,
            sor=self.sor,
            plain_reverse=self.plain_reverse,
            tolerance=self.options.tolerance,
            cg_tolerance=self.options.cg_tolerance,
            cg_max_iterations=self.options.cg_max_iterations,
            cg_forcing=self.options.cg_forcing,
            wind=tuple(self.options.wind) if self.options.wind else (0.0, 0.0, 0.0),
        )
        return make_solver(self.options.solver, self.model, self.effects, settings)

    def _set_body(self, solver, f0: int, f1: int) -> None:
        if self.fixed_pins is not None:
            solver.set_pin_targets(self.fixed_pins, self.fixed_pins)
        if self.collider is None:
            return
        b = self.body.vertices
        # Along the frames' Hermite path; the settle (f0 = f1) holds the body still.
        tangents = np.stack([self._tangents(f0), self._tangents(f1)]) if f1 == f0 + 1 else None
        self.collider.set_frames(b[f0], b[f1], tangents)
        fields = self.body.fold_fields
        self.collider.set_fold(fields.blob(f0, f1) if fields is not None else None)
        if self.pins is not None:
            solver.set_pin_targets(self._pin_targets(f0), self._pin_targets(f1))

    def _tangents(self, frame: int) -> np.ndarray:
        """The body's path tangents at `frame` (collider.frame_tangents)."""
        return _per_frame(self._tangents_at, frame,
                          lambda: frame_tangents(self.body.vertices, frame))

    def _pin_targets(self, frame: int) -> np.ndarray:
        """The pins' targets on the body at `frame`."""
        return _per_frame(self._pins_at, frame,
                          lambda: self.pins.targets(self.body.vertices[frame], self.faces))

    def _body_speed(self, vertices: slice) -> float:
        """The speed of the body's fastest vertex over the current frame (m/s; 0 without a
        body), among `vertices` (a scene's body in a batch), as the collider bounded it along
        the body's path when _set_body gave it the frame (collider.path_bounds)."""
        if self.body is None:
            return 0.0
        return self.collider.fastest_travel_among(vertices) * self.fps

    def _speed_limit(self, body_speed: float) -> float:
        if self.body is None:
            return self.options.speed_limit
        return max(self.options.speed_limit, 3.0 * body_speed)

    def _frame(self, solver, f0: int, f1: int, profile: bool, search: bool = True) -> str | None:
        """Advance one frame; returns a failure reason or None."""
        self._set_body(solver, f0, f1)
        if search:
            # A full closest-triangle search lets vertices move to another body part; between
            # searches they follow their triangles and untracked ones are searched every substep.
            solver.search(self.collider, 1.0)
        h = 1.0 / self.fps / solver.settings.substeps
        self._known = None
        # Outer garments are searched against the inner one at the same frames as the body.
        solver.advance_frame(self.collider, solver.settings.substeps, h, profile, search)
        x, v = self._state(solver)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            return "non-finite positions"
        speeds = _row_norms(v)
        for k, part in enumerate(self.parts):
            fastest = part.lo + int(np.argmax(speeds[part.lo:part.hi]))
            speed = float(speeds[fastest])
            body_speed = self._body_speed(part.body)
            limit = self._speed_limit(body_speed)
            if speed > limit:
                return (f"{part.label}runaway velocity {speed:.1f} m/s (limit {limit:.1f}) "
                        f"in {self._garment_label(fastest)}")
            ke = part.kinetic_energy(self.model, v)
            if ke > 0.5 * part.mass * limit**2 * 0.25:
                return f"{part.label}kinetic energy blow-up ({ke:.3g} J)"
            reason = self._energy_gain(solver.settings, part, k, ke, x, body_speed)
            if reason is not None:
                return reason
        return None

    def _garment_label(self, vertex: int) -> str:
        """Which garment cloth vertex `vertex` belongs to, as a rejection names it: an outfit's
        runaway is often one garment gone (a strap top slid down onto the thighs), not all."""
        g = self.garments[int(self.model.garment_of_vertex[vertex])]
        return f"the {g.category} '{g.name}'"

    def _energy_gain(self, settings: SolverSettings, part: _Part, k: int, ke: float,
                     x: np.ndarray, body_speed: float) -> str | None:
        """Why the frame just run gave the cloth of part k more kinetic energy than anything
        in the scene can (ENERGY_SLACK), or None."""
        if self._frame_start is None:
            return None
        x0, ke0 = self._frame_start[0], self._frame_start[1][k]
        mass = part.mass
        gravity = float(np.linalg.norm(settings.gravity)) if self.effects.gravity else 0.0
        drive = settings.recover_speed + body_speed
        if self.effects.wind and self.options.wind:
            drive += float(np.linalg.norm(self.options.wind))
        floor = 0.5 * mass * ENERGY_FLOOR_SPEED**2
        bound = ENERGY_SLACK * kinetic_energy_bound(ke0, mass, 1.0 / self.fps, gravity, drive)
        if ke <= bound + floor:
            return None
        # Only now the stored energy: a stretched garment snapping back may take its speed
        # from it (two passes over the springs and stencils, rarely needed).
        released = max(elastic_energy(self.model, x0, part.springs, part.bends)
                       - elastic_energy(self.model, x, part.springs, part.bends), 0.0)
        bound += ENERGY_SLACK * released
        if ke <= bound + floor:
            return None
        return (f"{part.label}energy gain: kinetic energy {ke0:.3g} -> {ke:.3g} J in one frame, "
                f"over the {bound + floor:.3g} J that gravity, the collider, wind and "
                f"{released:.3g} J of released elastic energy can give")

    def run(self) -> SimResult:
        self.solvers = {self.substeps: self._solver(self.substeps)}
        self.solver = self.solvers[self.substeps]
        t_frames = time.perf_counter()
        body = self.body
        n_body = body.n_frames if body is not None else self.options.frames + 1
        lead_in = body.lead_in_frames if body is not None else 0
        settle = int(round(self.options.settle_seconds * self.fps))
        outputs: dict[str, list] = {g.name: [] for g in self.garments}
        qa_rows: list[dict] = []
        step = 0
        total = settle + n_body - 1
        settings = f"{self.options.solver} {self.options.steps_label(self.fps)}"
        for _ in range(settle):
            # The outfit settles on the rest pose quasi-statically: each frame starts at rest,
            # so a garment fitted with ease lands on the shoulders without the impact that
            # would carry its straps down the slope of the trapezius.
            self._advance(0, 0, step, lead_in, refine=False)
            step += 1
            x, v = self._state(self.solver)
            self._set_state(self.solver, x, np.zeros_like(v))
            report_frame(step, total, settings)
        if lead_in == 0:
            self._record(0, outputs, qa_rows)
        for f0 in range(n_body - 1):
            self._advance(f0, f0 + 1, step, lead_in)
            step += 1
            if f0 + 1 >= lead_in:
                self._record(f0 + 1, outputs, qa_rows)
            report_frame(step, total, settings)
        t_end = time.perf_counter()
        return self._result(outputs, qa_rows, t_frames - self._t_created, t_end - t_frames,
                            settle)

    def _advance(self, f0: int, f1: int, step: int, lead_in: int, refine: bool = True) -> None:
        """One frame, redone from its start with twice the substeps when a stability guard
        trips (up to MAX_RETRIES times, then the sequence is rejected) or, when `refine`, when
        more edges than STRAIN_SHARE_MAX end beyond their fabric's strain bound (up to
        `strain_refinements` times, then the frame is kept: strain is a quality figure, not a
        failure). When even the last refinement removes less than a fifth of the
        over-strained edges, substeps do not resolve this strain (a garment made smaller than
        its body): refinement then rests for REFINE_REST frames (at PRESET_FPS: as long in
        time at any rate), unless a frame ends with
        REST_BREAK times the previous frame's over-strained share (a kick that starts while a
        tight crotch rests: resting through it left 4.8 % of a trouser's edges over the bound).
        (The first doubling alone can
        help little where the fourfold one helps a lot: a leather trouser leg swung in a dance
        went from 2.5 % of its edges over the bound to 0.06 % at 4x.)"""
        solver = self.solver
        x0, v0 = self._state(solver)
        self._frame_start = (x0, [p.kinetic_energy(self.model, v0) for p in self.parts])
        tracking0 = solver.get_tracking()
        every = self.options.profile_every
        search = step % self.search_every == 0
        start = level = self.start_level
        current = solver if start == 0 else self._refined(start, x0, v0, tracking0)
        reason = self._frame(current, f0, f1, every > 0 and step % every == 0, search)
        limit = self.options.strain_refinements if refine else 0
        resting = self.refine_rest > 0
        self.refine_rest = max(self.refine_rest - 1, 0)
        stable: tuple[int, object] | None = None  # the last stable run: (level, solver)
        held = None  # the level at which the frame first ran stable
        first = None  # the share over the bound before any refinement
        while True:
            if reason is None:
                stable = (level, current)
                held = level if held is None else held
                if limit == 0:
                    break
                share = self._over_strain(current)
                first = share if first is None else first
                if share <= STRAIN_SHARE_MAX:
                    break
                if resting and level == start:
                    if share <= REST_BREAK * self.last_share:
                        break
                    self.refine_rest = 0  # the strain jumped: a new event, refine it
                if level - start >= limit:
                    if share > 0.8 * first:
                        self.refine_rest = self.refine_rest_frames
                    break
                self.strain_refinements += 1
            elif stable is not None:  # a refinement went unstable: keep the stable run
                level, current = stable
                break
            elif level >= MAX_RETRIES:
                frame = max(f1 - lead_in, 0)
                raise RejectedSequence(
                    "simulate",
                    f"unstable at frame {frame}: {reason}, "
                    + self._retries_phrase(start, level)
                    + slid_necklines_note(self.garments, self.model.garment_ranges,
                                          x0, self.body, f0),
                    (max(f0 - lead_in, 0), frame),
                )
            else:
                self.retries += 1
            level += 1
            current = self._refined(level, x0, v0, tracking0)
            reason = self._frame(current, f0, f1, False)
        if first is not None:
            self.last_share = share
        if current is not solver:
            x, v = self._state(current)
            self._set_state(solver, x, v)
            solver.set_tracking(current.get_tracking())
        self.frame_substeps.append(self.substeps * 2**level)
        self._hold_retry_level(start, held)

    def _retries_phrase(self, start: int, level: int) -> str:
        """What a rejection says of the frame's runs: its own retries, and the level it started
        at when an earlier frame's retry was still held (the doublings alone would count the
        earlier frame's retries as this one's)."""
        top = f"{self.substeps * 2**level} substeps"
        if start == 0:
            return f"still after {level} retries with up to {top}"
        held = f"{self.substeps * 2**start} substeps, held since an earlier frame's retry"
        tried = level - start
        if tried == 0:
            return f"at {held}"
        return (f"still after {tried} {'retry' if tried == 1 else 'retries'} from {held}, "
                f"with up to {top}")

    def _refined(self, level: int, x0: np.ndarray, v0: np.ndarray, tracking0):
        """The solver at `level` doublings of the substeps (made on first use), set to the
        frame's start."""
        sub = self.substeps * 2**level
        if sub not in self.solvers:
            self.solvers[sub] = self._solver(sub)
        current = self.solvers[sub]
        self._set_state(current, x0, v0)
        current.set_tracking(tracking0)
        return current

    def _hold_retry_level(self, start: int, held: int) -> None:
        """Where the next frame starts, after a frame that started at `start` doublings and
        first ran stable at `held` (RETRY_HOLD): a retried frame holds its level; a held
        level steps down by one when its hold runs out; a step down that fails doubles the
        next hold. Strain refinements do not hold (they have their own rest)."""
        if held > start:
            if self.stepping_down:
                self.failed_step_downs += 1
            self.start_level = held
            self.hold_left = self.retry_hold_frames * 2**self.failed_step_downs
        elif self.stepping_down:  # the step down held: stay here for a hold of its own
            self.failed_step_downs = 0
            self.hold_left = self.retry_hold_frames
        if held == start and start > 0:
            self.hold_left -= 1
            if self.hold_left <= 0:
                self.start_level = start - 1
                self.stepping_down = True
                return
        self.stepping_down = False

    def _strain(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """_fabric_strain of positions read by _state, computed once for them (they are
        read-only: the same object is the same positions)."""
        if self._strain_of is None or self._strain_of[0] is not x:
            self._strain_of = (x, _fabric_strain(self.model, x))
        return self._strain_of[1]

    def _over_strain(self, solver) -> float:
        """The share of fabric edges beyond their bound, in the garment that has the most."""
        x, _ = self._state(solver)
        over = self._strain(x)[1]
        return max(p.over_strain_share(over) for p in self.parts)

    def _record(self, body_frame: int, outputs, qa_rows) -> None:
        x, v = self._state(self.solver)
        if self.options.neckline_guard:
            slid = slid_necklines(self.garments, self.model.garment_ranges, x, self.body,
                                  body_frame)
            if slid:
                frame = slid[0][1].frame
                raise SlidOffShoulders("; ".join(b.reason for _, b in slid)
                                       + "; the run stopped there", (frame, frame))
        for g, (lo, hi) in zip(self.garments, self.model.garment_ranges, strict=True):
            outputs[g.name].append(x[lo:hi].astype(np.float32))
        flags = None
        if self.collider is not None and self.effects.body_collision:
            # The collider holds this frame's body as its end position. Each vertex measured
            # against its closest triangle, found anew: the triangle a vertex tracks can be
            # another part's than the one it is inside (a top caught between the swinging arm
            # and the torso tracked the arm 12-24 mm inside the torso), and the QA read 5-30x
            # too few vertices too deep on make dataset's sequences (docs/simulator.md).
            if self.collider.grid_tag == 0:  # the first frame, before any step: no grid yet
                b = self.body.vertices[body_frame]
                self.collider.set_frames(b, b)
            # The solver's tracked triangles only bound the search (it finds the nearest).
            # Read in place: the solver holds this frame's end (_advance copied a retry's in).
            if self.collider.closed:
                # Inside by the body's volume, and how deep: only the vertices inside are
                # searched for (docs/simulator.md, "The depth QA by the body's volume").
                depth = self.collider.inside_depth(self.solver.x, hint=self.solver.tri,
                                                   within=self._depth_reach)
                flags = (depth >= 0.0, depth > self.model.thickness)
            else:
                sd = self.collider.signed_distance(self.solver.x, hint=self.solver.tri,
                                                   within=self._depth_reach)
                flags = (sd < 0.0, sd < -self.model.thickness)
        strain = self._strain(x)
        qa_rows.append([_qa(self.model, p, v, flags, strain) for p in self.parts])
        if self.options.bound_guard and len(self.parts) == 1:
            frame = len(qa_rows) - 1
            found = [replace(b, frame=frame, where=self._where_broken(b.series, x, strain, flags,
                                                                     body_frame))
                     for b in breaches({k: np.array([value])
                                        for k, value in qa_rows[-1][0].items()})]
            if found:
                raise BoundBroken("; ".join(b.reason for b in found) + "; the run stopped there",
                                  (frame, frame))

    def _where_broken(self, series: str, x: np.ndarray, strain: tuple[np.ndarray, np.ndarray],
                      flags: tuple[np.ndarray, np.ndarray] | None, body_frame: int) -> str:
        """Where a bound the guard found broken lies (where_strained, where_deep), against
        this frame's body where the track carries its vertices' parts."""
        parts = getattr(self.body, "vertex_parts", None)
        body_x = None if parts is None else self.body.vertices[body_frame]
        if series == "over_strain_share":
            return where_strained(self.model, self.garments, x, body_x, parts, strain[1])
        if series == "deep_share" and flags is not None:
            return where_deep(self.model, self.garments, x, flags[1], body_x, parts)
        return ""

    def _result(self, outputs, qa_rows, setup: float, frames: float, settle) -> SimResult:
        costs: dict[str, float] = {}
        launches: dict[str, int] = {}
        for s in self.solvers.values():
            for k, v in s.costs.items():
                costs[k] = costs.get(k, 0.0) + v
            for k, v in s.launches.items():
                launches[k] = launches.get(k, 0) + v
        # Each part's series (one part unless a batch: datagen.sim.batch reads them all).
        self.part_qa = [
            {k: np.array([row[p][k] for row in qa_rows], dtype=np.float32) for k in qa_rows[0][p]}
            for p in range(len(self.parts))
        ]
        qa = self.part_qa[0]
        n_frames = len(qa_rows)
        report = {
            "solver": self.options.solver,
            "quality": self.options.quality,
            "substeps": self.substeps,
            "iterations": self.iterations,
            "sor": self.sor,
            "sor_plain_reverse": self.plain_reverse,
            "effects": self.effects.enabled(),
            "effect_costs_s": _effect_costs(costs),
            "kernel_launches": launches,
            # The whole run, and its two parts: the set-up before the first frame (model,
            # collider, pins, solver) and the frames (settling, lead-in and sequence).
            "wall_time_s": setup + frames,
            "setup_time_s": setup,
            "frames_time_s": frames,
            "retries": self.retries,
            "strain_refinements": self.strain_refinements,
            "settle_frames": settle,
            "frames": n_frames,
            "vertices": self.model.n_vertices,
            "simulated_seconds_per_wall_second": (len(self.frame_substeps) / self.fps)
            / (setup + frames),
            "frame_substeps_max": max(self.frame_substeps, default=self.substeps),
            # Frames whose kept run had more substeps than the run's own: retried, held after
            # a retry (RETRY_HOLD) or refined for strain. A run with many is not a run at its
            # stated steps (the accuracy study notes it).
            "frames_at_finer_steps": sum(s > self.substeps for s in self.frame_substeps),
            # Elements the model floored (a user's template with degenerate triangles).
            "degenerate_elements": {k: v for k, v in self.model.degenerate.items() if v},
            # Each fabric's values as simulated: a shard names its fabrics, and a user's fabric
            # (or a built-in of another datagen version) is known only by these.
            "fabrics": {f.name: asdict(f) for f in self.fabrics},
        }
        return SimResult(
            garment_names=[g.name for g in self.garments],
            vertices={name: np.stack(frames) for name, frames in outputs.items()},
            qa=qa,
            report=report,
        )


# The per-effect kernels whose work a parallel backend's fused sweeps do (solvers.XPBDSolver.
# _coloured_substep: pressure drag's vectors, prediction, pins, bending and every spring set).
SWEEP_COSTS = ("pressure_drag", "gravity", "air_drag", "pins", "bending", "stretch", "shear",
               "elastic", "seams", "stretch_loops")


def _effect_costs(costs: dict[str, float]) -> dict[str, float]:
    """Seconds per effect. Frames run by the fused kernel are attributed in proportion to the
    per-effect kernels of the profiled frames, and a parallel backend's fused sweeps likewise
    among the effects they run ("sweeps" where no frame was profiled)."""
    costs = dict(costs)
    sweeps = costs.pop("fused_sweeps", 0.0)
    if sweeps > 0:
        swept = {k: v for k, v in costs.items() if k in SWEEP_COSTS}
        total = sum(swept.values())
        # Every profiled frame predicts (gravity or air drag); tethers alone ("pins") run in
        # every frame and say nothing of the split.
        if total > 0 and ("gravity" in swept or "air_drag" in swept):
            for k, v in swept.items():
                costs[k] = v + sweeps * v / total
        else:
            costs["sweeps"] = sweeps
    fused = costs.pop("fused_frame", 0.0)
    total = sum(costs.values())
    if fused > 0 and total > 0:
        return {k: v + fused * v / total for k, v in costs.items()}
    if fused > 0:
        return {"all": fused}
    return dict(costs)


def necklines_off(garments: list[Garment], neckline_frames, neck: np.ndarray,
                  rest_neck: np.ndarray) -> list[tuple[Garment, Breach]]:
    """Each garment whose neckline (qa.neckline_slip) is past qa.NECKLINE_SLIP_MAX in some
    frame, with its breach (qa.neckline_breach: its worst frame, counted from the first of
    `neck`). `neckline_frames(k, g, loop)`: garment k's neckline vertices `loop` at the frames
    whose neck joint `neck` (F, 3) gives, (F, L, 3); `rest_neck` (3,) the fit's."""
    from datagen import qa

    found = []
    for k, g in enumerate(garments):
        loop = g.loops.get("neck")
        if loop is None or len(loop) == 0:
            continue
        loop = np.asarray(loop, dtype=np.int64)
        breach = qa.neckline_breach(neckline_frames(k, g, loop), g.vertices[loop], neck,
                                    rest_neck, g.category)
        if breach is not None:
            found.append((g, breach))
    return found


def slid_necklines(garments: list[Garment], ranges, x: np.ndarray,
                   track: ColliderTrack | None, body_frame: int) -> list[tuple[Garment, Breach]]:
    """necklines_off in the outfit's positions `x` (garment k at rows ranges[k]) at
    `body_frame` of `track`, each breach's frame the output frame (body_frame less the track's
    lead-in). Empty for a collider without a neck joint (a sphere, a batch's joined track)."""
    if track is None or track.neck is None or track.rest_neck is None:
        return []
    frame = max(body_frame - track.lead_in_frames, 0)
    return [(g, replace(b, frame=frame)) for g, b in necklines_off(
        garments, lambda k, g, loop: x[ranges[k][0] + loop][None],
        track.neck[body_frame][None], track.rest_neck)]


def slid_necklines_note(garments: list[Garment], ranges, x: np.ndarray,
                        track: ColliderTrack | None, body_frame: int) -> str:
    """'; the top's neckline had slid 0.34 m off the shoulders by then' for each garment of
    slid_necklines (same arguments), else empty. A strap top that slid down the arms and is
    caught at the elbow runs away there, and a rejection as unstable should say what came
    first (docs/simulator.md, "Old overlaps separate at the recovery speed")."""
    return "".join(f"; the {g.category}'s neckline had slid {b.value:.2f} m off the shoulders "
                   "by then" for g, b in slid_necklines(garments, ranges, x, track, body_frame))


def simulate(garments: list[Garment], body: BodySequence | ColliderTrack | None,
             options: SimOptions | None = None) -> SimResult:
    """Simulate the garments on a body sequence (garments fitted to its rest body move with it
    to where the sequence starts), on a collider track, or in free space (body None)."""
    if not garments:
        raise InputError(None, "outfit", "at least one garment", "none")
    if isinstance(body, BodySequence):
        require_lead_in(body.lead_in_frames, None, "motion.lead_in")
        return _Simulation(garments, track_of(body), options or SimOptions(),
                           body_start_transform(body)).run()
    return _Simulation(garments, body, options or SimOptions()).run()


def simulate_parts(garments: list[Garment], track: ColliderTrack, options: SimOptions,
                   parts: list[tuple[int, int, int, int]]) -> tuple[SimResult, list[dict]]:
    """Simulate garments that form several independent scenes on one collider track (a batch:
    datagen.sim.batch); `parts` as in _Simulation. Returns the joint result and each part's QA
    series (the joint result's own `qa` is the first part's)."""
    simulation = _Simulation(garments, track, options, parts=parts)
    result = simulation.run()
    return result, simulation.part_qa
