"""Cloth solvers with a common substep interface.

- `xpbd`: extended position-based dynamics with small substeps (Macklin et al. 2019) on the
  same springs and bending model as the others: stiffness enters as compliance 1/k, the
  Rayleigh damping of the springs as XPBD's damping term, so it converges to the same
  physics. Gauss-Seidel sweeps (alternating direction) on the CPU, coloured Gauss-Seidel on a GPU.
- `explicit`: semi-implicit (symplectic) Euler with many substeps; a baseline.
- `implicit`: backward Euler solved by Newton with preconditioned conjugate gradients
  (datagen.sim.implicit); the reference the others are measured against.

All three share the external forces, the strain limit (xpbd within its sweeps, the others by
a projection after each substep), pins and collision handling, so their differences are the
time integration only.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import taichi as ti

from datagen.sim import backend
from datagen.sim import contact_kernels as CK
from datagen.sim import kernel_common as KC
from datagen.sim import kernels as K
from datagen.sim import parallel_kernels as PK
from datagen.sim import search_kernels as SK
from datagen.sim import self_collision_kernels as SCK
from datagen.sim.backend import init_taichi
from datagen.sim.effects import Effects
from datagen.sim.model import (
    NO_LIMIT,
    PRESSURE_BOTH_FACES,
    PRESSURE_OFF,
    PRESSURE_OUTER_FACE,
    SEAM,
    SHEAR,
    STRUCTURAL,
    ClothModel,
)
from datagen.sim.precision import NP_REAL, REAL, VEC3, VEC4

# A bend is stiff at step h when its compliance over h^2 is below its generalised inverse mass
# (sum of weight^2 / mass over its four vertices): a Gauss-Seidel sweep then leaves about
# 1 / (1 + ratio) of its error or more, too much for one sweep per substep. Soft bends (cotton,
# silk at the default step: median ratios 1.5-95) converge in one sweep; denim on the 5k tube
# (median 0.25) did not: 45 mm from the reference after 16 frames at 20x4 with one bending
# sweep, 32 mm with its stiff bends swept in all four (Blender's quality 5: 36 mm from its own
# converged run). docs/simulator.md, "Sweep order".
STIFF_BEND_RATIO = 1.0
STRAIN_LIMIT_SWEEPS = 20  # force-based solvers: most projection sweeps per substep
STRAIN_LIMIT_TOLERANCE = 1e-4  # ... and the excess (relative to the limit) that ends them


@dataclass(frozen=True)
class SolverSettings:
    substeps: int = 10  # per frame
    iterations: int = 1  # constraint sweeps (xpbd) or Newton iterations cap (implicit)
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    recover_speed: float = 0.3  # m/s: how fast a penetrating vertex is moved out
    sor: float = 1.0  # over-relaxation of Gauss-Seidel sweeps
    # xpbd: sweeps in reverse order are plain. With one sweep per substep the direction
    # alternates every substep, so over-relaxed and plain sweeps alternate: a plain sweep
    # settles the local modes that over-relaxation flips (docs/simulator.md).
    plain_reverse: bool = False
    tolerance: float = 1e-5  # implicit: Newton stops when the update is below this (m)
    cg_tolerance: float = 1e-4  # implicit: relative residual of each CG solve
    cg_max_iterations: int = 200
    # implicit: loosen each CG solve while Newton is far from converged (the references, which
    # run Newton to its tolerance; with a Newton cap it would leave steps less converged)
    cg_forcing: bool = False


def fresh_guards(n: int) -> np.ndarray:
    """Per-vertex search guards (search_kernels.nearest_one) that make the first search happen: an
    odometer reading from long ago, and no grid (grids are numbered from 1)."""
    g = np.zeros((n, KC.GUARD.n), NP_REAL)
    g[:, KC.G_ODO] = -1e30
    return g


def wavefront_order(elements: np.ndarray, n_vertices: int) -> np.ndarray:
    """A serial Gauss-Seidel order that gives the same result as visiting the elements (rows of
    vertex indices: springs, bending stencils) in index order, with neighbours in the order
    rarely sharing a vertex.

    Two elements that share no vertex commute exactly (each reads and writes only its own
    vertices and multiplier), so any order that keeps every pair that shares one in index order
    gives the same floats. This one sorts by wavefront: an element's level is one more than the
    highest level among the earlier elements it shares a vertex with, and the elements of a
    level share none. In mesh order nearly every element shares a vertex with the one before,
    and a serial sweep waits for each update (a square root and divisions) before the next; in
    wavefront order the CPU overlaps them (a 10k sheet's stretch springs 16.5 -> 13.3 ns
    each, its shear springs 31.7 -> 16.3). Visited backwards it matches a reverse sweep in
    index order the same way."""
    m, width = elements.shape
    if m == 0:
        return np.zeros(0, np.int64)
    init_taichi()
    level = _nd(ti.i32, np.zeros(m, np.int32))
    K.wavefront_levels(_nd(ti.i32, elements.astype(np.int32).ravel()), width,
                       _nd(ti.i32, np.zeros(n_vertices, np.int32)), level)
    return np.lexsort((np.arange(m), level.to_numpy())).astype(np.int64)


def _nd(dtype, data: np.ndarray):
    arr = ti.ndarray(dtype, max(len(data), 1))
    if len(data):
        arr.from_numpy(np.ascontiguousarray(data))
    return arr


def colour_order(elements: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy colouring of constraint elements (rows of vertex indices) so that no two of a
    colour share a vertex: in element order, each takes the lowest colour that none of its
    vertices has yet. Returns the element indices sorted by colour (stable: a colour keeps the
    elements' order) and the colours' offsets into them (colours + 1)."""
    used = [0] * n_vertices  # per vertex, a bit per colour it has
    colours = np.zeros(len(elements), np.int64)
    for k, row in enumerate(np.asarray(elements).tolist()):
        taken = 0
        for v in row:
            taken |= used[v]
        free = ~taken & (taken + 1)  # the lowest colour not taken, as a bit
        for v in row:
            used[v] |= free
        colours[k] = free.bit_length() - 1
    order = np.argsort(colours, kind="stable").astype(np.int32)
    n_colours = int(colours.max()) + 1 if len(colours) else 0
    ptr = np.zeros(n_colours + 1, np.int32)
    np.add.at(ptr, colours + 1, 1)
    return order, np.cumsum(ptr).astype(np.int32)


class _Colouring:
    """A sweep's elements sorted by colour, on the device (kernels.springs_coloured)."""

    def __init__(self, elements: np.ndarray, n_vertices: int, ids: np.ndarray | None = None):
        order, ptr = colour_order(elements, n_vertices)
        self.n_colours = len(ptr) - 1
        # Host copies too: the fused sweeps join the spring sets' colourings (XPBDSolver).
        self.order_np = order if ids is None else ids[order].astype(np.int32)
        self.ptr_np = ptr
        self.order = _nd(ti.i32, self.order_np)
        self.ptr = _nd(ti.i32, ptr)


def _vertex_lists(owner: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Entries grouped by the vertex that owns them (CSR): per vertex its range in the order
    (n + 1 offsets), and the order (entry indices, stable within a vertex)."""
    ptr = np.zeros(n + 1, np.int64)
    np.add.at(ptr, owner + 1, 1)
    return np.cumsum(ptr).astype(np.int32), np.argsort(owner, kind="stable")


def _vertex_lists_nd(owner: np.ndarray, n: int):
    """_vertex_lists on the device: (starts, entries) for the gathering kernels, each entry an
    index into `owner` (which the kernel decodes: element and role)."""
    starts, entries = _vertex_lists(owner, n)
    return _nd(ti.i32, starts), _nd(ti.i32, entries.astype(np.int32))


class _SpringSet:
    """The springs of one kind in the order a sweep visits them: the model's, or its wavefront
    order (`wavefront`, serial Gauss-Seidel sweeps: the same result, faster)."""

    def __init__(self, model: ClothModel, select: np.ndarray, wavefront: bool = False) -> None:
        index = np.flatnonzero(select)
        # order[k]: the position in the model's order of the set's k-th spring
        self.order = (wavefront_order(model.springs[index], model.n_vertices) if wavefront
                      else np.arange(len(index)))
        index = index[self.order]
        self.index = index
        self.count = len(index)
        # The model's values of the set's springs, in float64, for their per-step terms.
        self.model_arrays = {
            "springs": model.springs[index],
            "rest": model.rest_length[index].astype(np.float64),
            "limit": model.limit_length[index].astype(np.float64),
            "k_t": model.k_tension[index].astype(np.float64),
            "k_c": model.k_compression[index].astype(np.float64),
            "beta": model.spring_beta[index].astype(np.float64),
        }
        self.springs = _nd(ti.math.ivec2, model.springs[index].astype(np.int32))
        self.rest = _nd(REAL, model.rest_length[index].astype(NP_REAL))
        self.limit = _nd(REAL, model.limit_length[index].astype(NP_REAL))
        self.k_t = _nd(REAL, model.k_tension[index].astype(NP_REAL))
        self.k_c = _nd(REAL, model.k_compression[index].astype(NP_REAL))
        self.beta = _nd(REAL, model.spring_beta[index].astype(NP_REAL))
        self.lam = _nd(REAL, np.zeros(self.count, NP_REAL))
        # The xpbd sweeps' per-step terms (kernels.ST_*; spring_step_terms), set by
        # XPBDSolver._use_step.
        self.terms = ti.ndarray(KC.GUARD, max(self.count, 1))

    def step_terms(self, w: np.ndarray, h: float) -> np.ndarray:
        """spring_step_terms of this set's springs at step h, with inverse masses w."""
        m = self.model_arrays
        ends = m["springs"]
        return spring_step_terms(m["rest"], m["limit"], m["k_t"], m["k_c"], m["beta"],
                                 w[ends[:, 0]] + w[ends[:, 1]], h)


def spring_step_terms(rest: np.ndarray, limit: np.ndarray, k_t: np.ndarray, k_c: np.ndarray,
                      beta: np.ndarray, wsum: np.ndarray, h: float) -> np.ndarray:
    """The springs' per-step terms for kernels.spring_delta at step h (kernels.ST_*), in
    float64: rest and limit lengths, compliance over h^2 in tension and compression, damping
    over h, the inverse of the XPBD update's denominator (1 + gamma) (w_i + w_j) + alpha for
    either compliance, and the inverse of w_i + w_j (all three zero where both ends are
    pinned)."""
    alpha_t = 1.0 / (k_t * h * h)
    alpha_c = 1.0 / (k_c * h * h)
    gamma = beta / h
    free = wsum > 0.0

    def inverse(a: np.ndarray) -> np.ndarray:
        return np.divide(1.0, a, out=np.zeros_like(a), where=free)

    return np.stack([rest, limit, alpha_t, alpha_c, gamma,
                     inverse((1.0 + gamma) * wsum + alpha_t),
                     inverse((1.0 + gamma) * wsum + alpha_c), inverse(wsum)], axis=1)


class ClothSolver:
    """State and the parts every solver shares: external forces, pins, collision, timing."""

    name = "base"
    # Long-range attachments to the pins (ClothModel.tethers): the xpbd solver's sweeps need them
    # to hold a hanging garment's strain limit; the others project the limit to a tolerance.
    uses_tethers = False
    # Serial Gauss-Seidel sweeps visit springs and bends in wavefront order (wavefront_order);
    # solvers that sum forces keep the model's order.
    wavefront = False

    def __init__(self, model: ClothModel, effects: Effects, settings: SolverSettings) -> None:
        init_taichi()
        # A GPU or several CPU threads: kernels whose serial form is one task or sums in thread
        # order have parallel forms there (parallel_kernels.py).
        self.parallel = not backend.serial()
        self.model = model
        self.effects = effects
        self.settings = settings
        n = model.n_vertices
        self.n = n
        self.x = _nd(VEC3, model.x0.astype(NP_REAL))
        self.xp = _nd(VEC3, model.x0.astype(NP_REAL))
        self.v = _nd(VEC3, np.zeros((n, 3), NP_REAL))
        w = model.inv_mass.astype(NP_REAL)
        if not effects.pins:
            w = (1.0 / model.mass).astype(NP_REAL)
        self.w_np = w
        self.w = _nd(REAL, w)
        # Each vertex's air terms (kernels.air_velocity): the linear drag, and the pressure
        # drag's vector, set every substep from the faces where that effect is on.
        air = np.zeros((n, 4), NP_REAL)
        air[:, 0] = model.air_drag
        self.air = _nd(VEC4, air)
        self._init_pressure_drag()
        self.thickness = _nd(REAL, model.thickness.astype(NP_REAL))
        self.friction = _nd(REAL, model.friction.astype(NP_REAL))
        self.tri = _nd(ti.i32, -np.ones(n, np.int32))
        self.guard = _nd(KC.GUARD, fresh_guards(n))
        self._tracking: dict | None = None  # get_tracking's snapshot
        self.odo = 0.0  # metres the body's fastest vertex has travelled (see nearest_one)
        self.contact_n = _nd(VEC3, np.zeros((n, 3), NP_REAL))
        self.contact_v = _nd(VEC3, np.zeros((n, 3), NP_REAL))
        self.gravity = VEC3(*settings.gravity)
        self.wind = VEC3(*(settings.wind if effects.wind else (0.0, 0.0, 0.0)))
        # Parallel backends sweep by colour: there the order does not matter.
        wavefront = self.wavefront and not self.parallel
        self.sets: dict[str, _SpringSet] = {}
        kinds = [
            ("stretch", effects.stretch, (model.spring_kind == STRUCTURAL) & ~model.spring_elastic),
            ("shear", effects.shear, (model.spring_kind == SHEAR) & ~model.spring_elastic),
            ("elastic", effects.elastic, model.spring_elastic),
            ("seams", True, model.spring_kind == SEAM),
        ]
        for name, on, select in kinds:
            if on and select.any():
                self.sets[name] = _SpringSet(model, select, wavefront)
        if not effects.elastic and model.spring_elastic.any() and effects.stretch:
            # Without the elastic effect, elastic loops are plain fabric.
            plain = model.spring_elastic
            self.sets["stretch_loops"] = _SpringSet(_unelastic(model), plain, wavefront)
        self.n_bends = len(model.bends) if effects.bending else 0
        # The bending stencils in sweep order: the model index of each.
        self.bend_order = (wavefront_order(model.bends, n) if wavefront and self.n_bends
                           else np.arange(self.n_bends))
        if self.n_bends:
            b = self.bend_order
            self.bends_np = model.bends[b]
            self.bends = _nd(ti.math.ivec4, self.bends_np)
            self.kw = _nd(VEC4, model.bend_weights[b].astype(NP_REAL))
            self.bstiff = _nd(REAL, model.bend_stiffness[b].astype(NP_REAL))
            self.bbeta = _nd(REAL, model.bend_beta[b].astype(NP_REAL))
            self.lam_b = ti.ndarray(VEC3, self.n_bends)
        self.n_pins = len(model.pinned) if effects.pins else 0
        if self.n_pins:
            self.pin_idx = _nd(ti.i32, model.pinned.astype(np.int32))
            # Host arrays (set_pin_targets): a CPU reads them in place, where an upload to a
            # device array cost 0.1 ms each in Taichi's Python (a GPU copies them per launch).
            self.pin_t0 = np.zeros((self.n_pins, 3), NP_REAL)
            self.pin_t1 = np.zeros((self.n_pins, 3), NP_REAL)
        pairs, lengths = model.tethers if self.n_pins and self.uses_tethers else (None, ())
        self.n_tethers = len(lengths)
        if self.n_tethers:
            self.tethers = _nd(ti.math.ivec2, pairs)
            self.tether_len = _nd(REAL, lengths.astype(NP_REAL))
        self.costs: dict[str, float] = defaultdict(float)
        self.launches: dict[str, int] = defaultdict(int)
        self._sweep = 0
        self._init_strain_limit()
        self._init_self_collision()
        self._init_layers()

    # -- pressure drag -------------------------------------------------------------------------
    def _init_pressure_drag(self) -> None:
        # model.PRESSURE_*: cloth on a body meets the free stream on its outer face only.
        self.use_pressure = (PRESSURE_OFF if not self.effects.pressure_drag
                             else PRESSURE_OUTER_FACE if self.effects.body_collision
                             else PRESSURE_BOTH_FACES)
        self.cloth_faces = _nd(ti.math.ivec3, np.zeros((1, 3), np.int32))  # placeholders
        self.cloth_vertex_faces = (_nd(ti.i32, np.zeros(2, np.int32)),) * 2
        if not self.use_pressure:
            return
        self.cloth_faces = _nd(ti.math.ivec3, self.model.faces.astype(np.int32))
        if self.parallel:
            self.cloth_vertex_faces = _vertex_lists_nd(self.model.faces.ravel(), self.n)

    def _pressure_vectors(self) -> None:
        """Each vertex's pressure-drag vector at the substep's start (kernels.air_velocity):
        every substep, as the panels turn within a frame and so that the motion does not
        depend on the output rate (set once an output frame, 30 and 60 fps parted by 1.6 mm
        on a sheet dropped onto a sphere)."""
        if not self.use_pressure:
            return
        if self.parallel:
            self._run("pressure_drag", PK.set_pressure_vectors_gathered, self.x,
                      self.cloth_faces, *self.cloth_vertex_faces, self.air)
        else:
            self._run("pressure_drag", K.set_pressure_vectors, self.x, self.cloth_faces,
                      self.air)

    # -- strain limiting (force-based solvers) -----------------------------------------------
    def _init_strain_limit(self) -> None:
        """The springs that have a limit length (fabric stretch and shear), as one set: the
        force-based solvers project them after each substep so that every solver simulates the
        same model as xpbd, which limits inside its constraint sweeps."""
        active = [s.index for s in self.sets.values()]
        index = np.concatenate(active) if active else np.zeros(0, np.int64)
        index = index[self.model.fabric_springs[index]]  # seams and elastics have no limit
        self.n_limited = len(index)
        self.limited = _nd(ti.math.ivec2, self.model.springs[index].astype(np.int32))
        self.limited_length = _nd(REAL, self.model.limit_length[index].astype(NP_REAL))

    def _limit_strain(self, h: float) -> None:
        """Gauss-Seidel sweeps (alternating direction) until no spring is more than
        STRAIN_LIMIT_TOLERANCE past its limit, at most STRAIN_LIMIT_SWEEPS."""
        if not self.n_limited:
            return
        t = time.perf_counter()
        for sweep in range(STRAIN_LIMIT_SWEEPS):
            worst = K.limit_strain(self.x, self.v, self.w, self.limited, self.limited_length, h,
                                   sweep % 2)
            self.launches["strain_limit"] += 1
            if worst < STRAIN_LIMIT_TOLERANCE:
                break
        self.costs["strain_limit"] += time.perf_counter() - t

    def _limit_after_contact(self, collider, h: float) -> None:
        """The strain limit's sweeps after contact, along the body (see
        kernels.limit_after_contact_one), then contact again, without friction, for the
        vertices they moved into the body: every solver ends its substep with them."""
        body = collider is not None and self.effects.body_collision
        if not (self.n_limited and (body or self.use_layers)):
            return
        t = time.perf_counter()
        moved = False
        for sweep in range(K.AFTER_CONTACT_SWEEPS):
            worst = K.limit_after_contact(self.x, self.w, self.limited, self.limited_length,
                                          self.contact_n, sweep % 2)
            self.launches["strain_limit"] += 1
            moved = moved or worst > 0.0
            if worst < K.AFTER_CONTACT_TOLERANCE:
                break
        self.costs["strain_limit"] += time.perf_counter() - t
        if body and moved:
            # The body where _collide put it this substep (_search_and_collide).
            self._collide_interpolated(collider, h, False)

    # -- cloth-cloth collision ---------------------------------------------------------------
    def _init_self_collision(self) -> None:
        """Vertex-vertex repulsion within each garment: vertices closer than `radius` that are
        not near each other in the rest shape (a fold, not fabric neighbours) are pushed apart."""
        self.use_self = bool(self.effects.self_collision)
        model = self.model
        edge = float(np.median(model.rest_length[model.spring_kind == STRUCTURAL])) if len(
            model.rest_length) else 0.01
        self.self_radius = max(float(model.thickness.max()), 0.4 * edge)
        self.self_min_rest = 2.0 * edge + self.self_radius
        self.self_inv_cell = 0.5 / self.self_radius  # cells twice the radius (self_collide_one)
        size = 1 << int(np.ceil(np.log2(max(2 * self.n, 16))))
        self.s_mask = size - 1
        self.s_counts = _nd(ti.i32, np.zeros(size if self.use_self else 1, np.int32))
        self.s_starts = _nd(ti.i32, np.zeros(size + 1 if self.use_self else 2, np.int32))
        self.s_items = _nd(ti.i32, np.zeros(self.n if self.use_self else 1, np.int32))
        self.s_owner = _nd(ti.i32, model.garment_of_vertex.astype(np.int32))
        self.s_rest = _nd(VEC3, model.rest_x.astype(NP_REAL))
        # Parallel backends push all vertices at once (parallel_kernels.self_collide_parallel).
        parallel = self.use_self and self.parallel
        self.s_push = ti.ndarray(VEC3, self.n if parallel else 1)
        self.s_scan = ti.ndarray(ti.i32, size // PK.SCAN_BLOCK + 2 if parallel else 1)

    def _init_layers(self) -> None:
        """Outer garments collide with the innermost one's surface (layered outfits)."""
        from datagen.sim.collider import BodyCollider

        model = self.model
        layers = model.layers or [0] * len(model.garment_names)
        inner_layer = min(layers)
        inner = [g for g, layer in enumerate(layers) if layer == inner_layer]
        outer = [g for g, layer in enumerate(layers) if layer > inner_layer]
        self.use_layers = bool(self.effects.garment_collision and outer)
        layer_w = np.zeros(self.n, NP_REAL)
        if self.use_layers:
            self.inner_vertices = np.concatenate(
                [np.arange(*model.garment_ranges[g]) for g in inner])
            # The collider indexes the cloth's own vertices: contact reads the inner garment's
            # current positions straight from the solver's arrays.
            faces = np.concatenate([model.faces[slice(*model.face_ranges[g])] for g in inner])
            self.layer_collider = BodyCollider(faces.astype(np.int32),
                                               np.ones(len(faces), bool), self.n, normals=False)
            for g in outer:
                lo, hi = model.garment_ranges[g]
                layer_w[lo:hi] = 1.0
            layer_w[model.pinned if self.effects.pins else []] = 0.0
        self.layer_w = _nd(REAL, layer_w)
        # The inner garment's vertex normals at its current positions, and the outer
        # garments' push back on it (contact_kernels.collide_layer_one).
        n_layer = self.n if self.use_layers else 1
        self.layer_nrm = ti.ndarray(VEC3, n_layer)
        # Parallel backends sum the pushes in fixed point and gather the normals per vertex.
        self.layer_react = ti.ndarray(CK.REACT_EXACT if self.parallel else VEC4, n_layer)
        self.layer_react.fill(0)
        if self.parallel and self.use_layers:
            self.layer_vertex_faces = _vertex_lists_nd(faces.ravel(), self.n)
        self.layer_count = ti.ndarray(REAL, n_layer)  # pushes each took in the last substep
        self.layer_count.fill(0.0)
        self.layer_tri = _nd(ti.i32, -np.ones(self.n, np.int32))
        self.layer_guard = _nd(KC.GUARD, fresh_guards(self.n))
        self.layer_odo = 0.0  # metres the inner garment's fastest vertex has travelled
        self.layer_travel = 0.0  # ... and travels in the current frame

    def begin_frame(self, collider, frame_time: float, search: bool = True) -> None:
        """Per-frame set-up: the inner garment's surface for the layer collisions, at the frame's
        start and predicted at its end. Inner vertices near the body move with the body triangle
        they track, the others with their velocity: the inner garment moves as fast as the body
        (17 cm a frame in a run), and a surface held still for the frame would drag the outer
        garment behind it and then jump through it. With `search`, outer vertices are searched
        against it afresh (the frames the body is searched, as between those they follow the
        inner triangles they track)."""
        if not self.use_layers:
            return
        x, v = self.get_state()
        inner0 = x[self.inner_vertices]
        inner1 = inner0 + v[self.inner_vertices] * frame_time
        if collider is not None and self.effects.body_collision:
            tri = self.tri.to_numpy()[self.inner_vertices]
            tracked = tri >= 0
            corners = collider.faces_np[tri[tracked]]
            moved = (collider.v1_np[corners] - collider.v0_np[corners]).mean(axis=1)
            inner1[tracked] = inner0[tracked] + moved
        self.layer_travel = float(np.linalg.norm(inner1 - inner0, axis=1).max())
        c = self.layer_collider
        path0, path1 = x.copy(), x.copy()  # only the inner garment's entries are read
        path0[self.inner_vertices] = inner0
        path1[self.inner_vertices] = inner1
        c.set_frames(path0, path1)
        if search:
            self._run("garment_collision", c.nearest, self.x, self.layer_w, self.layer_tri, 0.0,
                      SK.SEARCH_TRACKED, self.layer_guard, self.layer_odo)

    def end_frame(self, collider) -> None:
        if collider is not None and self.effects.body_collision:
            self.odo += collider.max_speed
        if self.use_layers:
            self.layer_odo += self.layer_travel

    def _cloth_collisions(self, h: float, s0: float, s1: float) -> None:
        if self.use_layers:
            c = self.layer_collider
            self._run("garment_collision", c.nearest, self.x, self.layer_w, self.layer_tri, s1,
                      SK.SEARCH_UNTRACKED, self.layer_guard,
                      self.layer_odo + s1 * self.layer_travel)
            if self.parallel:
                self._run("garment_collision", PK.vertex_normals_gathered, self.x, c.faces,
                          *self.layer_vertex_faces, self.layer_nrm)
            else:
                self._run("garment_collision", CK.vertex_normals, self.x, c.faces,
                          self.layer_nrm)
            self._run("garment_collision", CK.collide_layers, self.x, self.xp, self.w,
                      self.layer_w, self.layer_tri, c.faces, c.fadj, self.layer_nrm,
                      self.thickness, self.friction, self.settings.recover_speed * h,
                      2.0 * c.cell, self.contact_n, self.contact_v, h, self.layer_react,
                      self.layer_count, self.effects.friction, self.parallel)
        if self.use_self:
            if self.parallel:
                self._run("self_collision", PK.self_collide_parallel, self.x, self.xp, self.w,
                          self.s_owner, self.s_rest, self.s_counts, self.s_starts, self.s_items,
                          self.s_scan, self.s_push, self.self_inv_cell, self.s_mask,
                          self.self_radius, self.self_min_rest,
                          self.settings.recover_speed * h)
                return
            self._run("self_collision", SCK.self_collide, self.x, self.xp, self.w, self.s_owner,
                      self.s_rest, self.s_counts, self.s_starts, self.s_items,
                      self.self_inv_cell, self.s_mask, self.self_radius, self.self_min_rest,
                      self.settings.recover_speed * h)

    # -- state -------------------------------------------------------------------------------
    def get_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities (float64 copies)."""
        out = np.empty((2, self.n, 3))
        K.read_state(self.x, self.v, out, backend.serial())
        return out[0], out[1]

    def set_state(self, x: np.ndarray, v: np.ndarray) -> None:
        self.x.from_numpy(np.asarray(x, NP_REAL))
        self.v.from_numpy(np.asarray(v, NP_REAL))

    def get_tracking(self) -> dict:
        """What the collision search knows: tracked triangles, search guards and odometers. A
        solver that takes over a frame (a retry with more substeps) needs it with the state: a
        guard is only a proof together with the odometer it was measured on. The arrays are
        copied on the device into this solver's snapshot, which the next call overwrites (a
        frame takes one before it runs; reading them back cost 0.5 ms a frame)."""
        if self._tracking is None:
            kinds = {"tri": ti.i32, "guard": KC.GUARD}
            if self.use_layers:
                kinds.update(layer_tri=ti.i32, layer_guard=KC.GUARD)
            self._tracking = {name: ti.ndarray(kind, self.n) for name, kind in kinds.items()}
        t = self._tracking
        K.copy_tracking(self.tri, self.guard, t["tri"], t["guard"], backend.serial())
        t["odo"] = self.odo
        if self.use_layers:
            K.copy_tracking(self.layer_tri, self.layer_guard, t["layer_tri"], t["layer_guard"],
                            backend.serial())
            t["layer_odo"] = self.layer_odo
        return t

    def set_tracking(self, tracking: dict) -> None:
        K.copy_tracking(tracking["tri"], tracking["guard"], self.tri, self.guard, backend.serial())
        self.odo = tracking["odo"]
        if self.use_layers:
            K.copy_tracking(tracking["layer_tri"], tracking["layer_guard"], self.layer_tri,
                            self.layer_guard, backend.serial())
            self.layer_odo = tracking["layer_odo"]

    def set_pin_targets(self, t0: np.ndarray, t1: np.ndarray) -> None:
        if self.n_pins:
            self.pin_t0 = np.ascontiguousarray(t0, NP_REAL)
            self.pin_t1 = np.ascontiguousarray(t1, NP_REAL)

    # -- timing ------------------------------------------------------------------------------
    def _run(self, effect: str, fn, *args) -> None:
        t = time.perf_counter()
        fn(*args)
        self.costs[effect] += time.perf_counter() - t
        self.launches[effect] += 1

    def _interpolate_body(self, c, s0: float, s1: float) -> None:
        """The body at fractions s0 and s1 of the frame, on its path (kernels.interpolate_body),
        into c.bs0, c.bs1 and its normals at s1 into c.ns1: what every contact call reads."""
        self._run("body_collision", K.interpolate_body, c.b0, c.b1, c.n0, c.n1, c.used, s0, s1,
                  c.bs0, c.bs1, c.ns1, not self.parallel)

    # -- shared parts of a substep -----------------------------------------------------------
    def _pins(self, s1: float) -> None:
        if self.n_pins:
            self._run("pins", K.apply_pins, self.x, self.pin_idx, self.pin_t0, self.pin_t1, s1)

    def _contact_and_finish(self, collider, s0: float, s1: float, h: float, finish) -> None:
        """A substep's end on the per-effect paths of the XPBD and explicit solvers: body
        contact, garment layers, the strain limit's sweeps after contact, then `finish`
        (kernels.finish, or finish_contacts for the force-based explicit solver) takes the
        velocities from the positions."""
        self._collide(collider, s0, s1, h)
        self._cloth_collisions(h, s0, s1)
        self._limit_after_contact(collider, h)
        self._run("integration", finish, self.x, self.xp, self.v, self.w, self.contact_n,
                  self.contact_v, h)

    def _collide(self, collider, s0: float, s1: float, h: float) -> None:
        self._run("body_collision", CK.clear_contacts, self.contact_n, self.contact_v)
        if collider is None or not self.effects.body_collision:
            return
        self._search_and_collide(collider, s0, s1, h)

    def _search_and_collide(self, collider, s0: float, s1: float, h: float) -> None:
        """A substep's body contact. Vertices that track no triangle look for one at every
        substep (cheap: they are far from the body, in empty cells), so fast limbs and falling
        cloth are caught in time, among the triangles where the body's path puts them at the
        substep's end, as contact then takes them; computed as the fused xpbd frame kernel
        computes it (the body interpolated once per substep, the odometer summed in the
        kernel), so that a profiled frame computes an unprofiled one operation for operation
        (to the last bit without fast math: backend.py)."""
        c = collider
        self._interpolate_body(c, s0, s1)
        self._run("body_collision", SK.nearest_untracked, self.x, self.w, c.bs1, c.faces,
                  c.origin, c.inv_cell, c.dims, c.starts, c.items, c.cell, self.tri,
                  self.guard, self.odo, c.max_speed, c.grid_tag, s1, c.shift, c.tbox,
                  c.fold_nd, 0)
        self._collide_interpolated(c, h, self.effects.friction)

    def _collide_interpolated(self, c, h: float, friction: bool) -> None:
        """Contact with the body as _interpolate_body last put it in c.bs0, c.bs1, c.ns1."""
        self._run("body_collision", CK.collide_body, self.x, self.xp, self.w, self.tri, c.faces,
                  c.fadj, c.bs0, c.bs1, c.ns1, self.thickness, self.friction,
                  self.settings.recover_speed * h, 2.0 * c.cell, self.contact_n, self.contact_v,
                  h, friction)

    def search(self, collider, s: float) -> None:
        """Global closest-triangle search against the body for the vertices that track a
        triangle (every SimOptions.search_every frames; between searches they follow the
        triangles they track, and the others are searched at every substep)."""
        if collider is not None and self.effects.body_collision:
            self._run("body_collision", collider.nearest, self.x, self.w, self.tri, s,
                      SK.SEARCH_TRACKED, self.guard, self.odo + s * collider.max_speed)

    def substep(self, h: float, collider, s0: float, s1: float) -> None:
        raise NotImplementedError

    def advance_frame(self, collider, n_sub: int, h: float, profile: bool = False,
                      search: bool = True) -> None:
        """All substeps of one frame. `profile` runs the per-effect kernels so that each
        effect's cost is measured (solvers with a fused frame kernel skip them otherwise);
        `search` searches outer garments against the inner one afresh (begin_frame)."""
        self.begin_frame(collider, n_sub * h, search)
        for k in range(n_sub):
            self.substep(h, collider, k / n_sub, (k + 1) / n_sub)
        self.end_frame(collider)


def _unelastic(model: ClothModel) -> ClothModel:
    """The model with elastic loops reverted to plain fabric (elastic effect off)."""
    from dataclasses import replace

    from datagen.sim.model import ELASTIC_LENGTH, ELASTIC_STIFFNESS

    el = model.spring_elastic
    return replace(
        model,
        rest_length=np.where(el, model.rest_length / ELASTIC_LENGTH, model.rest_length),
        k_tension=np.where(el, model.k_tension / ELASTIC_STIFFNESS, model.k_tension),
        k_compression=np.where(el, model.k_compression / ELASTIC_STIFFNESS, model.k_compression),
    )


class XPBDSolver(ClothSolver):
    name = "xpbd"
    uses_tethers = True
    wavefront = True

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        self.gauss_seidel = not self.parallel
        self._step_h: float | None = None  # the step the per-step terms were set for
        self.n_stiff_bends = 0
        if self.n_bends:
            kw = model.bend_weights[self.bend_order].astype(np.float64)
            wk = self.w_np.astype(np.float64)[self.bends_np] * kw
            # Each bend's generalised inverse mass (see STIFF_BEND_RATIO).
            self.bend_inv_mass = (wk * kw).sum(axis=1)
            # The sweeps' weights and each vertex's inverse mass times its weight
            # (kernels.bend_delta).
            self.bend_kk = _nd(KC.GUARD, np.concatenate([kw, wk], axis=1).astype(NP_REAL))
            self.bend_step = ti.ndarray(VEC4, self.n_bends)  # _use_step
        self.stiff_bends = _nd(ti.i32, np.zeros(1, np.int32))
        if not self.gauss_seidel:  # a parallel backend: coloured sweeps
            self.spring_colours = {
                name: _Colouring(model.springs[s.index], self.n) for name, s in self.sets.items()
            }
            if self.n_bends:
                self.bend_colours = _Colouring(self.bends_np, self.n)
        self._build_fused()
        self._init_active_limit()
        # Profiled frames run the per-effect kernels (advance_frame); the others, on a parallel
        # backend, the substep's few launches (_coloured_substep).
        self._profiling = False
        if not self.gauss_seidel:
            self._init_coloured_limit()
            self._init_fused_colours()

    def _init_active_limit(self) -> None:
        """The arrays of kernels.limit_after_contact_active, over the fused springs (seams and
        elastics have no limit, so it never moves them): `limit_adj` holds each vertex's springs
        (CSR offsets, then fused spring indices) and the order of its first sweep; the vertex
        lists (queued flags, moved flags, the queue's two halves, the moved vertices: 5 n
        entries, and two counters). It visits the springs in the model's order: its sweeps
        enqueue the vertices they move, so the order matters beyond pairs that share a vertex
        (wavefront_order does not apply), and the sweeps stay as they were."""
        pairs = self.f_springs.to_numpy()[: self.f_count]
        # The fused springs (each set's after the ones before) in the model's order.
        offsets = np.cumsum([0] + [s.count for s in self.sets.values()])
        visit = np.argsort(np.concatenate(
            [lo + s.order for lo, s in zip(offsets[:-1], self.sets.values(), strict=True)]
            + [np.zeros(0, np.int64)]))
        ptr, order = _vertex_lists(pairs[visit].T.ravel(), self.n)  # both ends
        spring = np.tile(visit, 2)
        adj = [ptr, spring[order], visit]
        # The fused frame kernel reads the cloth's faces here (pressure drag): it has no
        # argument left for an array of their own.
        self.adj_faces = sum(len(a) for a in adj)
        self.n_adj_faces = len(self.model.faces) if self.use_pressure else 0
        if self.use_pressure:
            adj.append(self.model.faces.ravel())
        self.limit_adj = _nd(ti.i32, np.concatenate(adj).astype(np.int32))
        self.limit_lists = _nd(ti.i32, np.zeros(5 * self.n + 2, np.int32))

    def _init_coloured_limit(self) -> None:
        """The arrays of the coloured strain limit after contact (parallel_kernels): the
        limited fused springs by colour, a sweep's largest excess, the moved vertices' flags."""
        limited = np.flatnonzero(self.f_limit.to_numpy()[: self.f_count] < NO_LIMIT)
        pairs = self.f_springs.to_numpy()[limited] if len(limited) else np.zeros((0, 2), int)
        self.limit_colours = _Colouring(pairs, self.n, limited.astype(np.int32))
        self.limit_worst = _nd(REAL, np.zeros(1, NP_REAL))
        self.limit_moved = _nd(ti.i32, np.zeros(self.n, np.int32))

    def _init_fused_colours(self) -> None:
        """The fused springs (_build_fused) by colour for parallel_kernels.xpbd_iteration_coloured:
        each set's colouring (spring_colours), its indices shifted to the fused arrays, and each
        colour's slice of that order, forward and then reversed within each set (the sets keep
        their order: the per-effect sweeps' order either way)."""
        orders, forward, reverse, lo = [], [], [], 0
        for name, s in self.sets.items():
            ptr = self.spring_colours[name].ptr_np
            orders.append(self.spring_colours[name].order_np + lo)
            spans = [(lo + ptr[c], lo + ptr[c + 1]) for c in range(len(ptr) - 1)]
            forward += spans
            reverse += spans[::-1]
            lo += s.count
        self.n_spring_colours = len(forward)
        order = np.concatenate(orders) if orders else np.zeros(0, np.int64)
        self.fused_spring_order = _nd(ti.i32, order.astype(np.int32))
        self.fused_spring_ranges = _nd(ti.math.ivec2, np.asarray(
            forward + reverse if forward else [(0, 0)], np.int32).reshape(-1, 2))
        self._no_bend_colours = _Colouring(np.zeros((0, 4), np.int32), self.n)

    def _limit_after_contact(self, collider, h: float) -> None:
        """As ClothSolver's, with the sweeps after the first on the springs around what moved
        (kernels.limit_after_contact_active), and contact again on the vertices they moved. On
        a parallel backend, coloured sweeps instead (_limit_after_contact_coloured)."""
        body = collider is not None and self.effects.body_collision
        if not (self.f_nsets and (body or self.use_layers)):
            return
        if not self.gauss_seidel:
            return self._limit_after_contact_coloured(collider if body else None, h)
        self._limit_after_contact_listed(collider, h, body)

    def _limit_after_contact_listed(self, collider, h: float, body: bool) -> None:
        """The serial form: one task that sweeps the springs around what the last sweep
        moved (kernels.limit_after_contact_listed), then contact for the moved vertices."""
        t = time.perf_counter()
        n_moved = K.limit_after_contact_listed(self.x, self.w, self.f_springs, self.f_limit,
                                               self.contact_n, self.limit_adj, self.limit_lists)
        self.launches["strain_limit"] += 1
        self.costs["strain_limit"] += time.perf_counter() - t
        # The body where _collide put it this substep (_search_and_collide), as the fused
        # kernel takes it.
        c = collider if body else self._placeholder_collider()
        self._run("body_collision", K.collide_listed, self.x, self.xp, self.w, self.tri,
                  c.faces, c.fadj, c.bs0, c.bs1, c.ns1, self.thickness, self.friction,
                  self.settings.recover_speed * h, 2.0 * c.cell, self.contact_n, self.contact_v,
                  h, self.limit_lists, n_moved, body)

    def _limit_after_contact_coloured(self, collider, h: float) -> None:
        """The strain limit after contact on a parallel backend: coloured sweeps, then contact
        again for what they moved (parallel_kernels)."""
        lc = self.limit_colours
        if not lc.n_colours:
            return
        t = time.perf_counter()
        for sweep in range(K.AFTER_CONTACT_SWEEPS):
            worst = PK.limit_sweep_coloured(self.x, self.w, self.f_springs, self.f_limit,
                                            self.contact_n, lc.order, lc.ptr, self.limit_worst,
                                            self.limit_moved, sweep % 2, lc.n_colours)
            self.launches["strain_limit"] += 1
            if worst < K.AFTER_CONTACT_TOLERANCE:
                break
        self.costs["strain_limit"] += time.perf_counter() - t
        # The body where _collide put it this substep (_search_and_collide): fractions 0 and
        # 1 of bs0, bs1.
        c = collider if collider is not None else self._placeholder_collider()
        self._run("body_collision", PK.collide_moved, self.x, self.xp, self.w, self.tri,
                  c.faces, c.fadj, c.bs0, c.bs1, c.ns1, c.ns1, 0.0, 1.0, self.thickness,
                  self.friction, self.settings.recover_speed * h, 2.0 * c.cell, self.contact_n,
                  self.contact_v, h, self.limit_moved, collider is not None)

    def _build_fused(self) -> None:
        """All spring sets in one array, in the order the per-effect kernels visit them."""
        sets = list(self.sets.values())
        if sets:

            def cat(attr, dtype):
                return np.concatenate(
                    [getattr(s, attr).to_numpy()[: s.count] for s in sets]
                ).astype(dtype)

            springs = cat("springs", np.int32)
            ranges, lo = [], 0
            for s in sets:
                ranges.append((lo, lo + s.count))
                lo += s.count
            self.f_springs = _nd(ti.math.ivec2, springs)
            self.f_limit = _nd(REAL, cat("limit", NP_REAL))
            self.f_terms = ti.ndarray(KC.GUARD, len(springs))  # _use_step
            self.f_lam = _nd(REAL, np.zeros(len(springs), NP_REAL))
            self.f_ranges = _nd(ti.math.ivec2, np.asarray(ranges, np.int32))
            self.f_nsets = len(ranges)
            self.f_count = len(springs)
        else:
            self.f_springs = _nd(ti.math.ivec2, np.zeros((1, 2), np.int32))
            self.f_limit = _nd(REAL, np.zeros(1, NP_REAL))
            self.f_terms = ti.ndarray(KC.GUARD, 1)
            self.f_lam = _nd(REAL, np.zeros(1, NP_REAL))
            self.f_ranges = _nd(ti.math.ivec2, np.zeros((1, 2), np.int32))
            self.f_nsets = 0
            self.f_count = 0
        if not self.n_bends:
            self.bends = _nd(ti.math.ivec4, np.zeros((1, 4), np.int32))
            self.kw = _nd(VEC4, np.zeros((1, 4), NP_REAL))
            self.bbeta = _nd(REAL, np.zeros(1, NP_REAL))
            self.bend_kk = _nd(KC.GUARD, np.zeros((1, 8), NP_REAL))
            self.bend_step = _nd(VEC4, np.zeros((1, 4), NP_REAL))
            self.lam_b = ti.ndarray(VEC3, 1)
        if not self.n_pins:
            self.pin_idx = _nd(ti.i32, np.zeros(1, np.int32))
            self.pin_t0 = self.pin_t1 = np.zeros((1, 3), NP_REAL)
        if not self.n_tethers:
            self.tethers = _nd(ti.math.ivec2, np.zeros((1, 2), np.int32))
            self.tether_len = _nd(REAL, np.zeros(1, NP_REAL))
        self._dummy_collider = None
        self.wind_np = np.asarray(self.settings.wind if self.effects.wind else (0.0, 0.0, 0.0))

    def stiff_bend_ids(self, h: float) -> np.ndarray:
        """The bends too stiff at step h to converge in one sweep (see STIFF_BEND_RATIO), in
        sweep order."""
        if not self.n_bends:
            return np.zeros(0, np.int32)
        compliance = 1.0 / (self.model.bend_stiffness[self.bend_order] * h * h)
        # All four vertices pinned: nothing to move, never stiff.
        stiff = compliance < STIFF_BEND_RATIO * self.bend_inv_mass
        return np.flatnonzero(stiff).astype(np.int32)

    def _use_step(self, h: float) -> None:
        """Upload the stiff bends and the springs' and bends' per-step terms for step h (once
        per step size: retries change it)."""
        # The step as the kernels read it (P_H is a REAL), as the sweeps took it when they
        # divided by it themselves.
        h = float(NP_REAL(h))
        if h == self._step_h:
            return
        if self.sets:
            w = self.w_np.astype(np.float64)
            terms = [s.step_terms(w, h) for s in self.sets.values()]
            for s, t in zip(self.sets.values(), terms, strict=True):
                s.terms.from_numpy(t.astype(NP_REAL))
            self.f_terms.from_numpy(np.concatenate(terms).astype(NP_REAL))
        if self.n_bends:
            # kernels.bend_delta: compliance over h^2, damping over h, and the inverse of the
            # update's denominator (zero where all four vertices are pinned: nothing moves).
            alpha = 1.0 / (self.model.bend_stiffness[self.bend_order] * h * h)
            gamma = self.model.bend_beta[self.bend_order] / h
            den = (1.0 + gamma) * self.bend_inv_mass + alpha
            inv = np.divide(1.0, den, out=np.zeros_like(den), where=self.bend_inv_mass > 0.0)
            terms = np.stack([alpha, gamma, inv, np.zeros_like(inv)], axis=1)
            self.bend_step.from_numpy(terms.astype(NP_REAL))
        ids = self.stiff_bend_ids(h)
        self.n_stiff_bends = len(ids)
        self.stiff_bends = _nd(ti.i32, ids if len(ids) else np.zeros(1, np.int32))
        if not self.gauss_seidel and len(ids):
            self.stiff_bend_colours = _Colouring(self.bends_np[ids], self.n, ids)
        self._step_h = h

    def advance_frame(self, collider, n_sub: int, h: float, profile: bool = False,
                      search: bool = True) -> None:
        if profile or not self.gauss_seidel:
            self._profiling = profile
            return super().advance_frame(collider, n_sub, h, profile, search)
        self.begin_frame(collider, n_sub * h, search)
        self._use_step(h)
        import time

        e = self.effects
        use_collision = collider is not None and e.body_collision
        c = collider if use_collision else self._placeholder_collider()
        lc = self.layer_collider if self.use_layers else self._placeholder_collider()
        t = time.perf_counter()
        P = np.zeros(K.P_SIZE, NP_REAL)
        P[K.P_H] = h
        P[K.P_OMEGA] = self._sweep_sor(0)
        P[K.P_OMEGA_REVERSE] = self._sweep_sor(1)
        P[K.P_RECOVER] = self.settings.recover_speed * h
        travel = c.max_speed if use_collision else 0.0
        P[K.P_ODO] = self.odo
        P[K.P_TRAVEL] = travel
        P[K.P_CELL] = c.cell
        P[K.P_INV_CELL] = c.inv_cell
        P[K.P_GRAVITY : K.P_GRAVITY + 3] = self.settings.gravity
        P[K.P_WIND : K.P_WIND + 3] = self.wind_np
        P[K.P_ORIGIN : K.P_ORIGIN + 3] = c.origin_np
        P[K.P_L_ORIGIN : K.P_L_ORIGIN + 3] = lc.origin_np
        P[K.P_S_INV_CELL] = self.self_inv_cell
        P[K.P_S_RADIUS] = self.self_radius
        P[K.P_S_MIN_REST] = self.self_min_rest
        P[K.P_L_INV_CELL] = lc.inv_cell
        P[K.P_L_CELL] = lc.cell
        P[K.P_L_ODO] = self.layer_odo
        P[K.P_L_TRAVEL] = self.layer_travel
        P[K.P_TAG] = c.grid_tag
        P[K.P_L_TAG] = lc.grid_tag
        P[K.P_SHIFT : K.P_SHIFT + 3] = c.shift_np
        P[K.P_L_SHIFT : K.P_L_SHIFT + 3] = lc.shift_np
        # The fold fields ride after the scalars (search_kernels.fold_near reads them at P_SIZE).
        P = np.concatenate([P, np.asarray(c.fold_np, NP_REAL)])
        Q = np.zeros(K.Q_SIZE, np.int32)
        Q[K.Q_N_SUB] = n_sub
        Q[K.Q_N_ITER] = self.settings.iterations
        Q[K.Q_SWEEP0] = self._sweep
        Q[K.Q_N_SETS] = self.f_nsets
        Q[K.Q_N_BENDS] = self.n_bends
        Q[K.Q_N_STIFF_BENDS] = self.n_stiff_bends
        Q[K.Q_N_PINS] = self.n_pins
        Q[K.Q_N_TETHERS] = self.n_tethers
        Q[K.Q_FACES] = self.adj_faces
        Q[K.Q_N_FACES] = self.n_adj_faces
        Q[K.Q_S_MASK] = self.s_mask
        Q[K.Q_DIMS : K.Q_DIMS + 3] = c.dims_np
        Q[K.Q_L_DIMS : K.Q_L_DIMS + 3] = lc.dims_np
        # P and Q go to the kernel as numpy arrays: on a CPU it reads them in place, where an
        # upload to a device array cost 0.09 ms each in Taichi's Python.
        K.xpbd_frame(
            self.x, self.xp, self.v, self.w, self.air,
            self.f_springs, self.f_terms, self.f_limit, self.f_lam,
            self.f_ranges,
            self.bends, self.bend_kk, self.bend_step, self.lam_b, self.stiff_bends,
            self.pin_idx, self.pin_t0, self.pin_t1, self.tethers, self.tether_len,
            self.tri, c.faces, c.fadj, c.b0, c.b1, c.n0, c.n1, c.bs0, c.bs1, c.ns1, c.used,
            self.thickness, self.friction, self.contact_n, self.contact_v,
            c.starts, c.items, self.guard, c.tbox,
            self.s_owner, self.s_rest, self.s_counts, self.s_starts, self.s_items,
            self.layer_w, self.layer_tri, self.layer_guard, lc.tbox,
            lc.faces, lc.fadj, lc.b0, lc.b1, self.layer_nrm, self.layer_react, self.layer_count,
            lc.starts, lc.items,
            self.limit_adj, self.limit_lists,
            P, Q,
            e.gravity, e.air_drag, self.use_pressure, use_collision, e.friction,
            self.use_layers,
            self.use_self,
        )  # fmt: skip
        self._sweep += n_sub * self.settings.iterations
        self.end_frame(collider if use_collision else None)
        self.costs["fused_frame"] += time.perf_counter() - t
        self.launches["fused_frame"] += 1

    def _placeholder_collider(self):
        """Empty collider arrays for scenes without a body (the kernel never reads them)."""
        if self._dummy_collider is None:
            from types import SimpleNamespace

            v3 = ti.ndarray(VEC3, 1)
            i3 = _nd(ti.math.ivec3, np.zeros((1, 3), np.int32))
            i1 = _nd(ti.i32, np.zeros(2, np.int32))
            self._dummy_collider = SimpleNamespace(
                faces=i3,
                fadj=i3,
                b0=v3,
                b1=v3,
                n0=v3,
                n1=v3,
                bs0=v3,
                bs1=v3,
                ns1=v3,
                used=i1,
                origin=VEC3(0.0),
                origin_np=np.zeros(3),
                fold_np=np.zeros(1, NP_REAL),
                dims_np=np.ones(3, np.int32),
                inv_cell=1.0,
                dims=ti.math.ivec3(1, 1, 1),
                starts=i1,
                items=i1,
                cell=1.0,
                grid_tag=0,
                shift_np=np.zeros(3),
                tbox=ti.ndarray(KC.GUARD, 1),
            )
        return self._dummy_collider

    def substep(self, h: float, collider, s0: float, s1: float) -> None:
        self._use_step(h)
        if self.parallel and not self._profiling:
            self._coloured_substep(h, s1)
        else:
            self._per_effect_sweeps(h, s1)
        if self.n_tethers:  # after the sweeps, as in the fused kernel
            self._run("pins", K.apply_tethers, self.x, self.tethers, self.tether_len)
        self._contact_and_finish(collider, s0, s1, h, K.finish)

    def _coloured_substep(self, h: float, s1: float) -> None:
        """_per_effect_sweeps on a parallel backend in 1 + iterations launches
        (parallel_kernels.xpbd_substep_begin and xpbd_iteration_coloured): the same elements in
        the same order, so the same result to the last bit without fast math."""
        e = self.effects
        self._run("fused_sweeps", PK.xpbd_substep_begin, self.x, self.xp, self.v, self.w,
                  self.air, self.cloth_faces, *self.cloth_vertex_faces, self.gravity,
                  self.wind, h, self.pin_idx, self.pin_t0, self.pin_t1, self.n_pins, s1,
                  self.f_lam, self.lam_b, e.gravity, e.air_drag, self.use_pressure)
        for it in range(self.settings.iterations):
            reverse = self._sweep % 2
            self._sweep += 1
            sor = self._sweep_sor(reverse)
            bends, omega_b = self._iteration_bends(it, sor)
            bends = bends or self._no_bend_colours
            self._run("fused_sweeps", PK.xpbd_iteration_coloured, self.x, self.xp, self.w,
                      self.f_springs, self.f_terms, self.f_lam, self.fused_spring_order,
                      self.fused_spring_ranges, *self._bend_args()[2:], bends.order, bends.ptr,
                      reverse, sor, omega_b,
                      bends.n_colours, self.n_spring_colours)

    def _per_effect_sweeps(self, h: float, s1: float) -> None:
        """The substep's prediction, pins and iterations, a kernel per effect (each effect's
        cost timed)."""
        e = self.effects
        self._pressure_vectors()
        self._run(
            "gravity" if e.gravity else "air_drag",
            K.predict,
            self.x,
            self.xp,
            self.v,
            self.w,
            self.air,
            self.gravity,
            self.wind,
            h,
            e.gravity,
            e.air_drag,
            self.use_pressure,
        )
        self._pins(s1)
        for s in self.sets.values():
            s.lam.fill(0.0)
        if self.n_bends:
            K.clear_vec3(self.lam_b)
        for it in range(self.settings.iterations):
            reverse = self._sweep % 2
            self._sweep += 1
            sor = self._sweep_sor(reverse)
            # Most bending is soft: one sweep per substep converges it, and the further
            # iterations go to the stiff stretch and shear springs (as in the fused kernel);
            # bends stiff at this step (STIFF_BEND_RATIO: denim, leather) are swept every time.
            # Bending runs before the springs: its damping reads the sweep's displacement as
            # velocity, and run last (with one iteration) it undid the springs' corrections on
            # a 1 cm cotton sheet at first contact, which grew 30x a frame into a runaway.
            if self.gauss_seidel:
                self._bending_sweep(h, it, reverse, sor)
                for name, s in self.sets.items():
                    self._run(
                        name,
                        K.springs_gauss_seidel,
                        self.x,
                        self.xp,
                        self.w,
                        s.springs,
                        s.terms,
                        s.lam,
                        reverse,
                        sor,
                    )
            else:
                self._coloured_iteration(h, it, reverse, sor)

    def _bending_sweep(self, h: float, it: int, reverse: int, sor: float) -> None:
        """Iteration it's bending on the serial per-effect path: every stencil in the first
        sweep, over-relaxed by `sor`, and the stiff ones in the later sweeps, plain (see the
        fused kernel). benchmarks/study_bend_block.py replaces it with an exact solve."""
        if self.n_bends and it == 0:
            self._run("bending", K.bends_gauss_seidel, *self._bend_args(),
                      self.stiff_bends, self.n_stiff_bends, reverse, sor, False)
        elif self.n_stiff_bends:
            self._run("bending", K.bends_gauss_seidel, *self._bend_args(),
                      self.stiff_bends, self.n_stiff_bends, reverse, 1.0, True)

    def _bend_args(self) -> tuple:
        """The bending kernels' leading arguments (positions, stencils, weights, the step's
        terms, multipliers), shared by the serial and the coloured sweeps."""
        return (self.x, self.xp, self.bends, self.bend_kk, self.bend_step, self.lam_b)

    def _sweep_sor(self, reverse: int) -> float:
        """The over-relaxation of a sweep in this direction (SolverSettings.plain_reverse)."""
        return 1.0 if self.settings.plain_reverse and reverse else self.settings.sor

    def _iteration_bends(self, it: int, sor: float) -> tuple[_Colouring | None, float]:
        """The bends iteration `it` sweeps on a parallel backend and their over-relaxation:
        every bend at `sor` first, then the stiff ones plain (see the fused kernel), or none."""
        if self.n_bends and it == 0:
            return self.bend_colours, sor
        if self.n_stiff_bends:
            return self.stiff_bend_colours, 1.0
        return None, 1.0

    def _coloured_iteration(self, h: float, it: int, reverse: int, sor: float) -> None:
        """The Gauss-Seidel branch's sweeps of one iteration on a parallel backend: the same
        order of effects and the same over-relaxation (`sor`, this sweep's), each colour one
        parallel loop."""
        bends, omega = self._iteration_bends(it, sor)
        if bends is not None:
            self._run("bending", K.bends_coloured, *self._bend_args(), bends.order, bends.ptr,
                      reverse, omega, bends.n_colours)
        for name, s in self.sets.items():
            c = self.spring_colours[name]
            self._run(name, K.springs_coloured, self.x, self.xp, self.w, s.springs, s.terms,
                      s.lam, c.order, c.ptr, reverse, sor, c.n_colours)


class ExplicitSolver(ClothSolver):
    name = "explicit"

    def __init__(self, model, effects, settings) -> None:
        super().__init__(model, effects, settings)
        self.f = _nd(VEC3, np.zeros((self.n, 3), NP_REAL))
        # Parallel backends gather each vertex's forces (parallel_kernels): the scatter's
        # float adds come out in thread order, and runs of one input would differ.
        if self.parallel:
            self.set_lists = {}
            for name, s in self.sets.items():
                ends = s.springs.to_numpy()  # (the kernel reads its length as the count)
                self.set_lists[name] = _vertex_lists_nd(ends.T.ravel(), self.n)
            if self.n_bends:
                self.bend_lists = _vertex_lists_nd(self.bends_np.ravel(), self.n)

    def substep(self, h: float, collider, s0: float, s1: float) -> None:
        e = self.effects
        self._pressure_vectors()
        for name, s in self.sets.items():
            args = (self.x, self.v, self.f, s.springs, s.rest, s.k_t, s.k_c, s.beta)
            if self.parallel:
                self._run(name, PK.spring_forces_gathered, *args, *self.set_lists[name])
            else:
                self._run(name, K.spring_forces, *args)
        if self.n_bends:
            args = (self.x, self.v, self.f, self.bends, self.kw, self.bstiff, self.bbeta)
            if self.parallel:
                self._run("bending", PK.bend_forces_gathered, *args, *self.bend_lists)
            else:
                self._run("bending", K.bend_forces, *args)
        self._run(
            "integration",
            K.explicit_update,
            self.x,
            self.xp,
            self.v,
            self.f,
            self.w,
            self.air,
            self.gravity,
            self.wind,
            h,
            e.gravity,
            e.air_drag,
            self.use_pressure,
        )
        self._limit_strain(h)
        self._pins(s1)
        self._contact_and_finish(collider, s0, s1, h, K.finish_contacts)


def make_solver(name: str, model: ClothModel, effects: Effects, settings: SolverSettings):
    from datagen.errors import InputError

    if name == "xpbd":
        return XPBDSolver(model, effects, settings)
    if name == "explicit":
        return ExplicitSolver(model, effects, settings)
    if name == "implicit":
        from datagen.sim.implicit import ImplicitSolver

        return ImplicitSolver(model, effects, settings)
    raise InputError(None, "solver", "one of xpbd, explicit, implicit", name)
