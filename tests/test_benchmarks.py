"""The hand-offs between benchmarks: bench_gpu sets a GPU batch against Blender through the
peer rows bench_sim wrote, which hold only for the simulator both ran."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_gpu, bench_sim
from datagen.qa import DEEP_SHARE_MAX


def test_gpu_report_reads_the_peer_rows_of_the_same_simulator_and_refuses_others(
        tmp_path, monkeypatch):
    """The same sources, or other sources whose default peer runs are bit for bit bench_sim's
    (its recorded behaviour digest, computed again at the GPU run's sources); else refused."""
    from datagen.study import cache

    rows = [{"scene": "tube_cylinder 5k", "fabric": "denim", "ours_s_per_sim_s": 1.39,
             "blender_s_per_sim_s": 5.42, "blender_err_mm": 35.56}]
    peer = tmp_path / "sim_peer.json"
    peer.write_text(json.dumps({"date": "2026-11-27", "source": "aaaa", "behaviour": "b1",
                                "rows": rows}))
    monkeypatch.setattr(bench_sim, "PEER_JSON", peer)
    behaviour = {"now": "b1"}
    monkeypatch.setattr(bench_sim, "peer_behaviour", lambda: behaviour["now"])
    monkeypatch.setattr(cache, "source_digest", lambda: "bbbb")  # this checkout's sources
    date, table, how = bench_gpu.blender_rows("aaaa")
    assert date == "2026-11-27" and how == "the same simulator sources (aaaa)"
    assert table == {("tube_cylinder 5k", "denim"): {"ours": 1.39, "blender": 5.42,
                                                     "blender_error_mm": 35.56}}
    # Other sources, the same behaviour: the chain holds and says why.
    _, same, how = bench_gpu.blender_rows("bbbb")
    assert same == table and "aaaa for bench_sim and bbbb for the GPU run" in how
    assert "bit for bit" in how and "b1" in how
    # Other sources that behave otherwise.
    behaviour["now"] = "b2"
    with pytest.raises(SystemExit, match="field 'source'.*aaaa.*bbbb.*behaviour b2, then b1"):
        bench_gpu.blender_rows("bbbb")
    # A GPU run of sources other than this checkout's: its behaviour cannot be computed here.
    behaviour["now"] = "b1"
    with pytest.raises(SystemExit, match="aaaa, the GPU run with cccc \\(this checkout: bbbb\\)"):
        bench_gpu.blender_rows("cccc")


def test_the_committed_peer_rows_cover_every_peer_scene():
    data = json.loads(bench_sim.PEER_JSON.read_text())
    keys = {(r["scene"], r["fabric"]) for r in data["rows"]}
    assert keys == {(f"{scene} {res}", fabric) for scene, res in bench_sim.PEER_SCENES
                    for fabric in bench_sim.FABRICS}
    assert all(r["blender_err_mm"] > 0 and r["ours_s_per_sim_s"] > 0 for r in data["rows"])
    # Blender's timed run kept the cloth out of the collider by the QA's bound (a run through
    # it is no peer to time), with the cushion matched to ours wherever that held.
    for r in data["rows"]:
        assert r["blender_deep_share_max"] <= DEEP_SHARE_MAX
        matched_held = r["blender_matched_deep_share"] <= DEEP_SHARE_MAX
        assert r["blender_contact"] == ("matched" if matched_held else "study")
    # Blender's error is against a run that is itself checked: quality 320 against 160
    assert all(r["blender_ref_halving_mm"] >= 0 for r in data["rows"])
    # At Blender's error both simulators' errors are means over the same starts, the bound
    # Blender's mean, and the chosen setting's mean within it.
    for r in data["rows"]:
        starts = r["blender_err_starts_mm"]
        assert len(starts) == len(bench_sim.ERROR_STARTS) and starts[0] == r["blender_err_mm"]
        assert r["blender_err_mean_mm"] == pytest.approx(sum(starts) / len(starts))
        chosen = r["at_error"]
        if chosen["steps"] is not None:
            lo, hi = chosen["err_range_mm"]
            assert lo <= chosen["err_mm"] <= hi and chosen["err_mm"] <= r["blender_err_mean_mm"]


def _study_tube():
    """The studies' coarse denim tube model (1,200 vertices, 48 pinned along its top)."""
    from datagen.sim.fabrics import FABRICS
    from datagen.sim.model import build_cloth_model
    from datagen.study.scenes import build_scene

    scene = build_scene("tube_cylinder", "denim", "coarse", frames=1)
    return build_cloth_model([(g, FABRICS[g.fabric]) for g in scene.garments])


class _ShakenTubeStep:
    """One step (5 a frame) of the studies' coarse denim tube hanging from its pins, from a
    shaken state, no collider: `step(solver)` gives the positions after it, `newton` the
    implicit solver's converged backward Euler step and `moved` how far that moved a vertex."""

    def __init__(self) -> None:
        import numpy as np

        from datagen.sim.effects import Effects
        from datagen.sim.implicit import ImplicitSolver
        from datagen.sim.solvers import SolverSettings

        self.model = model = _study_tube()
        rng = np.random.default_rng(5)
        x0 = model.x0 + rng.normal(scale=0.002, size=model.x0.shape)
        v0 = rng.normal(scale=0.05, size=model.x0.shape)
        x0[model.pinned], v0[model.pinned] = model.x0[model.pinned], 0.0
        self.x0, self.v0 = x0, v0
        self.effects = Effects(pins=True)
        self.newton = self.step(ImplicitSolver(model, self.effects, SolverSettings(
            iterations=50, tolerance=1e-7, cg_tolerance=1e-7, cg_max_iterations=5000)))
        self.moved = float(np.abs(self.newton - x0).max())

    def step(self, solver):
        import numpy as np

        pinned = self.model.x0[self.model.pinned]
        solver.set_state(self.x0, self.v0)
        solver.set_pin_targets(pinned, pinned)
        solver.substep(1.0 / 30.0 / 5, None, 0.0, 1.0)
        return solver.get_state()[0].astype(np.float64)

    def error(self, solver) -> float:
        """How far `solver`'s step ends from Newton's (max over vertices, metres)."""
        import numpy as np

        return float(np.abs(self.step(solver) - self.newton).max())


def test_the_bending_study_solves_its_block_exactly_and_consistently():
    """benchmarks/study_bend_block.py sets an exact bending block against the sweeps: after
    its solve every stencil's XPBD equation holds, (1 + gamma) B x + alpha~ lambda - gamma B xp
    = 0, and the move is the one the multipliers give (dx = W B^T dl, pinned vertices still),
    as Gauss-Seidel keeps it."""
    import numpy as np

    from benchmarks.study_bend_block import ExactBendBlock
    from datagen.sim.effects import Effects
    from datagen.sim.precision import NP_REAL
    from datagen.sim.solvers import SolverSettings, XPBDSolver

    model = _study_tube()
    solver = XPBDSolver(model, Effects(pins=True), SolverSettings(substeps=20, iterations=2))
    h = 1.0 / 30.0 / 20
    rng = np.random.default_rng(3)
    xp = model.x0.astype(NP_REAL)
    x = (model.x0 + rng.normal(scale=0.003, size=model.x0.shape)).astype(NP_REAL)
    lam0 = rng.normal(scale=1e-6, size=(len(solver.bends_np), 3)).astype(np.float32)
    solver.x.from_numpy(x)
    solver.xp.from_numpy(xp)
    solver.lam_b.from_numpy(lam0)
    block = ExactBendBlock(solver, h)

    def residual(x, lam):
        b_x = block.B @ x.astype(np.float64)
        return ((1.0 + block.gamma)[:, None] * b_x + block.alpha[:, None] * lam
                - block.gamma[:, None] * (block.B @ xp.astype(np.float64)))

    before = np.abs(residual(x, lam0)).max()
    block.solve(solver)
    x1, lam1 = solver.x.to_numpy(), solver.lam_b.to_numpy().astype(np.float64)
    assert np.abs(residual(x1, lam1)).max() < 1e-3 * before
    w = solver.w_np.astype(np.float64)
    moved = x1.astype(np.float64) - x
    assert len(model.pinned) and np.all(moved[model.pinned] == 0.0)
    expected = w[:, None] * (block.B.T @ (lam1 - lam0))
    assert np.abs(moved - expected).max() < 1e-3 * np.abs(moved).max()
    assert np.abs(moved).max() > 1e-4  # the solve did move the cloth


def test_the_prefactored_study_iterates_to_the_implicit_solvers_backward_euler_step():
    """benchmarks/study_prefactored_implicit.py solves each step with a constant matrix: its
    fixed point must be the backward Euler step that the implicit solver's Newton iterations
    reach, or its errors would measure another model. One step of a coarse denim tube hanging
    from its pins, from a shaken state, no collider."""
    from benchmarks.study_prefactored_implicit import PrefactoredImplicit
    from datagen.sim.solvers import SolverSettings

    case = _ShakenTubeStep()

    def prefactored(iterations):
        return PrefactoredImplicit(case.model, case.effects, SolverSettings(iterations=iterations))

    assert case.moved > 1e-3  # the step did move the cloth
    assert case.error(prefactored(400)) < 1e-3 * case.moved
    assert case.error(prefactored(1)) > 1e-2 * case.moved  # one iteration is inexact


def test_the_prefactored_studys_bdf2_falls_as_a_body_falls():
    """BDF2, the study's second-order integrator, follows a free fall to a small fraction of
    backward Euler's lag (g h t / 2, 6.5 mm after 0.2 s at 150 steps a second): the sheets'
    error at a few steps a frame is mostly that lag."""
    import numpy as np

    from benchmarks.study_prefactored_implicit import PrefactoredImplicit
    from datagen.sim.effects import Effects
    from datagen.sim.solvers import SolverSettings

    model = _study_tube()
    h, steps = 1.0 / 150.0, 30
    t = h * steps
    exact = -0.5 * 9.81 * t * t
    drop = {}
    for bdf2 in (False, True):
        solver = PrefactoredImplicit(model, Effects(air_drag=False), SolverSettings(iterations=2))
        solver.bdf2 = bdf2
        for _ in range(steps):
            solver.substep(h, None, 0.0, 1.0)
        x = solver.get_state()[0].astype(np.float64)
        drop[bdf2] = (x - model.x0)[:, 2].mean()
    lag = 0.5 * 9.81 * h * t
    assert abs(drop[False] - exact) == pytest.approx(lag, rel=0.05)  # backward Euler's lag
    # BDF2 keeps only its backward Euler first step's offset (order h^2 g), which does not grow
    assert abs(drop[True] - exact) < 2.0 * h * h * 9.81 < 0.15 * lag


def test_the_vbd_study_iterates_to_the_implicit_solvers_backward_euler_step():
    """benchmarks/study_vbd.py's vertex blocks minimise the implicit solver's incremental
    potential one vertex at a time: many sweeps must reach the step that Newton reaches (else
    its errors would measure another model), a few must not, and Chebyshev acceleration must
    come closer than plain sweeps of the same count. One step of a coarse denim tube hanging
    from its pins, from a shaken state, no collider."""
    from benchmarks.study_vbd import VBDSolver
    from datagen.sim.solvers import SolverSettings

    case = _ShakenTubeStep()

    def vbd(iterations, rho=0.0):
        solver = VBDSolver(case.model, case.effects, SolverSettings(iterations=iterations))
        solver.rho = rho
        return solver

    assert case.moved > 1e-3  # the step did move the cloth
    assert case.error(vbd(1000)) < 1e-3 * case.moved
    few = case.error(vbd(8))
    assert few > 1e-2 * case.moved  # eight sweeps are inexact (about 30 % of the move)
    assert case.error(vbd(8, rho=0.9)) < 0.5 * few  # Chebyshev: about 10 %


def test_blender_at_one_thread_is_given_one_openmp_thread_too(monkeypatch):
    """bench_sim's machine ratio runs two Blenders side by side at `-t 1`. `-t` does not cap
    Blender's OpenMP threads, and two Blenders each spinning a thread per core ran 7x slower
    each (4k sheet, 60 frames: 98 s instead of 14), which flattered our machine ratio by
    1.4-1.8x. With a thread count, run_blender sets OMP_NUM_THREADS to it; without one,
    Blender keeps its defaults."""
    from datagen.study import blender as peer
    from datagen.study.scenes import build_scene

    calls = []

    class Launched(Exception):
        pass

    def fake_run(cmd, **kwargs):
        calls.append((cmd, kwargs.get("env")))
        raise Launched

    monkeypatch.setattr(peer, "blender_executable", lambda: "/usr/bin/blender")
    monkeypatch.setattr(peer.subprocess, "run", fake_run)
    scene = build_scene("sheet_sphere", "cotton", "coarse", frames=1)
    for threads in (1, None):
        with pytest.raises(Launched):
            peer.run_blender(scene, 5, threads=threads)
    (one_cmd, one_env), (default_cmd, default_env) = calls
    assert one_cmd[one_cmd.index("-t") + 1] == "1" and one_env["OMP_NUM_THREADS"] == "1"
    assert "-t" not in default_cmd and default_env is None


def test_the_warm_start_study_starts_from_the_product_and_carries_the_hanging_load():
    """benchmarks/study_warm_start.py carries each substep's multipliers into the next: its
    cold variant must be the product's xpbd step to the bit (its errors are set against the
    product's), and a carried load must leave a hanging tube less sagged, nearer to what
    converged sweeps give, than cold sweeps at the same cost: the effect the study weighs
    against its instability. A coarse denim tube hanging from its pins, from rest, no collider,
    30 substeps at 2 sweeps each."""
    import numpy as np

    from benchmarks.study_warm_start import WarmStartXPBD
    from datagen.sim.effects import Effects
    from datagen.sim.solvers import SolverSettings, XPBDSolver

    model = _study_tube()
    h, substeps = 1.0 / 30.0 / 20, 30

    def hang(solver, variant: str | None = None):
        if variant is not None:
            solver.variant = variant
        solver.set_state(model.x0, np.zeros_like(model.x0))
        solver.set_pin_targets(model.x0[model.pinned], model.x0[model.pinned])
        for _ in range(substeps):
            solver.substep(h, None, 0.0, 1.0)
        return solver.get_state()[0].astype(np.float64)

    effects = Effects(pins=True)
    product = hang(XPBDSolver(model, effects, SolverSettings(iterations=2)))
    cold = hang(WarmStartXPBD(model, effects, SolverSettings(iterations=2)), "cold")
    assert np.array_equal(cold, product)
    warm = hang(WarmStartXPBD(model, effects, SolverSettings(iterations=2)), "smooth x2")
    converged = hang(XPBDSolver(model, effects, SolverSettings(iterations=64)))
    free = np.ones(len(model.x0), bool)
    free[model.pinned] = False
    sag = {k: float((converged[free, 2] - x[free, 2]).mean())
           for k, x in (("cold", cold), ("warm", warm))}
    assert sag["cold"] > 0.0  # cold sweeps leave the tube lower than converged ones
    assert abs(sag["warm"]) < 0.5 * sag["cold"], sag


def test_the_coarse_study_solves_a_chain_exactly_and_lifts_the_hanging_load():
    """benchmarks/study_coarse_correction.py adds sweeps over chains of springs along fibres:
    one chain's update must be the exact Galerkin solve of the substep's linearised spring
    system on that chain's direction (one multiplier increment for all its springs, the
    vertices moving by W J^T P dmu), and chain sweeps must leave a hanging tube less sagged
    than the product's sweeps at the same steps (the long-range load they exist to carry)."""
    import numpy as np
    import taichi as ti

    from benchmarks import chain_kernels as CK
    from benchmarks.study_coarse_correction import ChainLevel, CoarseXPBD
    from datagen.sim.effects import Effects
    from datagen.sim.kernels import vec3
    from datagen.sim.precision import NP_REAL
    from datagen.sim.solvers import SolverSettings, XPBDSolver

    model = _study_tube()
    effects = Effects(pins=True)
    h = 1.0 / 30.0 / 20
    solver = XPBDSolver(model, effects, SolverSettings(iterations=2))
    rng = np.random.default_rng(5)
    xp = model.x0.astype(NP_REAL)
    x = (model.x0 + rng.normal(scale=0.002, size=model.x0.shape)).astype(NP_REAL)
    solver.x.from_numpy(x)
    solver.xp.from_numpy(xp)
    s = solver.sets["stretch"]
    springs = s.springs.to_numpy()
    level = ChainLevel(springs, model.x0, 8)
    ptr, all_members = level.ptr.to_numpy(), level.members.to_numpy()
    w = solver.w_np.astype(np.float64)
    q = next(q for q in range(level.n_runs) if ptr[q + 1] - ptr[q] == 8
             and (w[springs[all_members[ptr[q]:ptr[q + 1]]]] > 0).all())  # eight free springs
    members = all_members[ptr[q]:ptr[q + 1]]
    one = ti.ndarray(ti.i32, 2)  # a level of that one chain
    one.from_numpy(ptr[q:q + 2].copy())
    compliances = CK.set_compliances(s)
    lam0 = rng.normal(scale=1e-7, size=s.count).astype(NP_REAL)
    s.lam.from_numpy(lam0)
    CK.chains_gauss_seidel(solver.x, solver.xp, solver.w, s.springs, s.rest, *compliances,
                           s.beta, s.lam, one, level.members, level.flip,
                           ti.ndarray(vec3, s.count), h, 0, 1.0)
    # The same update from the linearised system, in float64.
    x64 = x.astype(np.float64)
    i, j = springs[members].T
    d = x64[j] - x64[i]
    length = np.linalg.norm(d, axis=1)
    n = d / length[:, None]
    c = length - s.rest.to_numpy()[members]
    comp_t, comp_c = CK.compliances_np(s)
    alpha = np.where(c < 0, comp_c[members], comp_t[members]) / h**2
    gamma = s.beta.to_numpy()[members] / h
    rate = (n * ((x64[j] - xp[j]) - (x64[i] - xp[i]))).sum(axis=1)
    rhs = ((-c - alpha * lam0[members] - gamma * rate) / (1 + gamma)).sum()
    g = np.zeros_like(x64)  # J^T P: each spring's direction, outward at its two ends
    np.add.at(g, i, -n)
    np.add.at(g, j, n)
    dmu = rhs / ((w[:, None] * g * g).sum() + (alpha / (1 + gamma)).sum())
    lam1 = s.lam.to_numpy().astype(np.float64)
    assert np.allclose(lam1[members] - lam0[members], dmu, rtol=1e-4)
    others = np.setdiff1d(np.arange(s.count), members)
    assert np.array_equal(lam1[others], lam0[others])
    moved = solver.x.to_numpy().astype(np.float64) - x64
    assert np.allclose(moved, w[:, None] * g * dmu, atol=1e-4 * np.abs(moved).max())
    assert np.abs(moved).max() > 1e-5
    # On a straight chain (the rest shape's) the interior vertices' moves cancel: the chain
    # acts as one long spring between its ends.
    solver.x.from_numpy(xp)
    s.lam.from_numpy(lam0)
    CK.chains_gauss_seidel(solver.x, solver.xp, solver.w, s.springs, s.rest, *compliances,
                           s.beta, s.lam, one, level.members, level.flip,
                           ti.ndarray(vec3, s.count), h, 0, 1.0)
    moves = np.sort(np.linalg.norm(solver.x.to_numpy().astype(np.float64) - xp, axis=1))
    assert moves[-2] > 0.0 and moves[-3] < 1e-3 * moves[-2]

    # A coarse denim tube hanging from its pins, from rest, no collider: 30 substeps at 2
    # sweeps each, against converged sweeps (64 a substep).
    def hang(solver):
        solver.set_state(model.x0, np.zeros_like(model.x0))
        solver.set_pin_targets(model.x0[model.pinned], model.x0[model.pinned])
        for _ in range(30):
            solver.substep(h, None, 0.0, 1.0)
        return solver.get_state()[0].astype(np.float64)

    cold = hang(XPBDSolver(model, effects, SolverSettings(iterations=2)))
    chains = CoarseXPBD(model, effects, SolverSettings(iterations=2))
    chains.kind, chains.lengths = "sweep", (64, 16, 4)
    coarse = hang(chains)
    converged = hang(XPBDSolver(model, effects, SolverSettings(iterations=64)))
    free = np.ones(len(model.x0), bool)
    free[model.pinned] = False
    sag = {k: float((converged[free, 2] - p[free, 2]).mean())
           for k, p in (("cold", cold), ("chains", coarse))}
    assert sag["cold"] > 0.0
    assert abs(sag["chains"]) < 0.1 * sag["cold"], sag  # 3.4 mm cold, 0.02 mm with chains


def test_the_body_frame_study_splits_what_it_times_and_leaves_the_simulator_as_it_was():
    """benchmarks/study_body_frame.py times a frame's parts by wrapping the simulator's
    methods: the body collision's search and contact add up to the body collision the
    simulator itself counts, the fused frame's parts fit in its time, and the wrappers are gone
    afterwards (the rest of a test session runs the simulator unwrapped)."""
    from benchmarks.study_body_frame import measure_setting
    from datagen.sim import simulate as simulate_module
    from datagen.sim import solvers
    from datagen.study.scenes import build_scene

    def methods():
        sim = simulate_module._Simulation
        return (solvers.ClothSolver._run, solvers.XPBDSolver.advance_frame,
                solvers.XPBDSolver.search, sim._set_body, sim._record, sim._advance)

    before = methods()
    scene = build_scene("tube_cylinder", "cotton", "coarse", frames=6)
    row = measure_setting(scene, 4, 1, per_effect=True)
    assert methods() == before
    body = row["effects_ms"]["body_collision"]
    split = row["effect_search_ms"] + row["effect_contact_ms"]
    assert row["effect_search_ms"] > 0 and row["effect_contact_ms"] > 0
    # each launch is timed by both, the split from just outside the simulator's own timer
    assert body <= split <= 1.2 * body + 0.05
    # the solver, the full search and the collider run inside the frame loop's advances, and
    # those and the QA inside the run (the rest is the set-up)
    inside = sum(row[f"{k}_ms"] for k in ("solver", "search", "collider"))
    assert row["solver_ms"] > 0 and row["collider_ms"] > 0 and inside <= row["loop_ms"]
    assert row["loop_ms"] + row["qa_ms"] < row["ms_frame"]
    assert row["bound"] == 0.25 and 0.0 < row["strain_p999"] < 10.0


def test_the_dataset_projection_gives_the_mean_with_its_t_interval_and_the_escalations():
    """bench_dataset projects the CLOTH3D recipe's cost from a sample of its sequences: the mean
    core-seconds times the sequence count, with the mean's 95 % interval (Student's t), and how
    many the QA gate would let through, with the written share's interval (Wilson's). Three
    runs of 10, 20 and 30 s: mean 20, standard deviation 10, t(0.975, 2) = 4.303, so the half
    width is 4.303 * 10 / sqrt(3) = 24.8 s; over 3600 sequences, 20 core-hours (-5 to 45). The
    escalated one's 30 s are half the sample's 60."""
    from benchmarks.bench_dataset import projection_lines

    def run(index, seconds, escalated=False, status="ok"):
        return {"index": index, "seconds": seconds, "frames": 300, "status": status,
                "escalated": escalated, "retries": int(escalated), "garments": 1 + index % 2,
                "vertices": 5000 * (1 + index % 2),
                "note": "ok" if not escalated else "ok; simulated again at reference"}

    text = "\n".join(projection_lines({"sequences": 3600, "runs": [
        run(0, 10.0), run(1, 20.0), run(2, 30.0, escalated=True)]}))
    assert "mean 20 (95 % interval -5-45)" in text
    assert "**20 core-hours** (1 core-days; 95 % interval -5-45)" in text
    assert "| 1 of 3 (50 % of the sample's core-seconds) |" in text
    assert "| 1 in 1 sequences |" in text
    assert ("2 with 1 garment, 1 with 2 garments (5,000-10,000 garment vertices); 300 frames |"
            in text)
    assert "- sequence 2: ok, 30 s (ok; simulated again at reference)" in text
    # A sequence the QA gate rejected keeps no garments: its vertices are unknown (None) and
    # the vertex range comes from the finished ones.
    rejected = dict(run(3, 20.0, status="rejected"), vertices=None)
    text = "\n".join(projection_lines({"sequences": 3600, "runs": [
        run(0, 10.0), run(1, 20.0), rejected]}))
    assert "3: 2 finished, 1 rejected; " in text
    assert "(5,000-10,000 garment vertices)" in text
    # Written 2 of 3: Wilson's 95 % interval, by hand with z = 1.96, is centred on
    # (2/3 + z^2/6) / (1 + z^2/3) = 0.57308 with half width
    # z / (1 + z^2/3) * sqrt((2/9)/3 + z^2/36) = 0.36543: 20.77-93.85 %, of 3600 748-3,379.
    assert ("| 2 of 3, 67 % (95 % interval 21-94 %, Wilson's): the recipe's 3,600 would write "
            "about **2,400** (748-3,379) |") in text
    # Writing 3600 at that share runs 3600 / (2/3) = 5400; the mean of 10, 20 and 20 s over
    # 3600 sequences is 16.7 core-hours, over 2/3 written 25.
    assert "| to write 3,600 at the sample's share | about 5,400 sequences run, 25 core-hours |" \
        in text


def test_the_choice_at_blenders_error_skips_costlier_settings_and_takes_each_ones_least_time():
    # 25x2, 30x2, 40x2 and 20x4 do at least 20x2's substeps and iterations.
    assert bench_sim.undominated([(30, 1), (20, 2), (25, 2), (30, 2), (40, 2), (20, 4)]) == [
        (30, 1), (20, 2)]
    # 20x4 has fewer substeps than 30x1 and more iterations: neither undercuts the other.
    assert bench_sim.undominated([(30, 1), (30, 2), (40, 2), (20, 4)]) == [(30, 1), (20, 4)]
    assert bench_sim.undominated([(20, 4)]) == [(20, 4)]
    # One slow run does not decide: 20x2's least time wins although its first run was the slowest.
    times = {(30, 1): [1.20, 1.18], (20, 2): [1.60, 0.95], (20, 4): [1.10, 1.40]}
    assert bench_sim.choose_fastest(times) == (20, 2)
    assert bench_sim.choose_fastest({(30, 1): [1.0], (20, 2): [1.0]}) == (30, 1)


def test_the_gpu_run_keeps_its_order_skips_what_the_deadline_cannot_hold_and_packs_each_mode(
        tmp_path, monkeypatch):
    """bench_gpu --run on a short lease: the report's modes first, none started past the
    deadline (the hard cases need HARD_MODE_SECONDS of it), the folder packed after each mode
    so that what finished comes back; an unknown mode is refused by name. The backends'
    processes are replaced here: what is tested is the run's schedule, not the GPU."""
    import subprocess
    import tarfile
    import time as time_module

    ran = []
    clock = {"t": 0.0}

    def both(mode, out_dir, scenes, env):
        ran.append(mode)
        (out_dir / f"{mode}_cuda.json").write_text("[]")
        clock["t"] += 100.0  # each mode takes 100 s

    def gpu_alone(cmd, **kwargs):
        if "--mode" in cmd:
            ran.append(cmd[cmd.index("--mode") + 1])
            clock["t"] += 10.0
        return subprocess.CompletedProcess(cmd, 0, stdout="Some GPU\n")

    monkeypatch.setattr(bench_gpu, "_both_backends", both)
    monkeypatch.setattr(bench_gpu.subprocess, "run", gpu_alone)
    monkeypatch.setattr(time_module, "monotonic", lambda: clock["t"])
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    pack = tmp_path / "run.tgz"
    bench_gpu.run_all(tmp_path / "run", scenes, ("hard", "cases", "profile", "batch"),
                      deadline=400.0, pack=pack)
    # hard asked for first, run last; at 210 s only 190 of the deadline are left for it
    assert ran == ["cases", "batch", "profile"]
    with tarfile.open(pack) as tar:
        names = set(tar.getnames())
    assert {"run/machine.json", "run/cases_cuda.json", "run/batch_cuda.json"} <= names
    machine = json.loads((tmp_path / "run" / "machine.json").read_text())
    assert machine["gpu"] == "Some GPU"
    with pytest.raises(SystemExit, match="--modes: unknown batches"):
        bench_gpu.run_all(tmp_path / "run2", None, ("cases", "batches"))


def test_the_sweep_floor_times_the_products_sweep_its_loads_alone_and_a_disc_in_l1():
    """benchmarks/bench_sweep_floor.py: its `product` kernel is the product's forward sweep
    (kernels.springs_gauss_seidel's update from the same state, within float32 rounding:
    compiled apart under fast math, two kernels may associate a sum otherwise), its memory floor
    moves nothing (every load kept, every store of zero), and its arithmetic floor's patch is
    a disc of the cloth's springs, all ends within the disc, in an order where no two
    consecutive springs share a vertex more often than the product's wavefront order lets
    them."""
    import numpy as np
    import taichi as ti

    from benchmarks import bench_sweep_floor as floor
    from datagen.sim import kernels as K
    from datagen.sim.effects import Effects
    from datagen.sim.precision import NP_REAL
    from datagen.sim.simulate import OVER_RELAXATION
    from datagen.sim.solvers import SolverSettings, XPBDSolver

    model = _study_tube()
    solver = XPBDSolver(model, Effects(pins=True), SolverSettings(substeps=20, iterations=4))
    h, omega = 1.0 / 30.0 / 20, OVER_RELAXATION["xpbd"]
    rng = np.random.default_rng(5)
    x0 = (model.x0 + rng.normal(scale=0.002, size=model.x0.shape)).astype(NP_REAL)
    solver._use_step(h)
    stretch = solver.sets["stretch"]
    args = (stretch.springs, stretch.terms, stretch.lam)

    def state_after(sweep) -> tuple[np.ndarray, np.ndarray]:
        solver.x.from_numpy(x0)
        solver.xp.from_numpy(model.x0.astype(NP_REAL))
        stretch.lam.from_numpy(np.zeros(stretch.count, NP_REAL))
        sweep()
        ti.sync()
        return solver.x.to_numpy(), stretch.lam.to_numpy()

    ours = state_after(lambda: floor.sweeps(2, solver.x, solver.xp, solver.w, *args, omega))
    product = state_after(lambda: [K.springs_gauss_seidel(solver.x, solver.xp, solver.w, *args,
                                                          0, omega) for _ in range(2)])
    assert np.abs(ours[0] - x0).max() > 1e-5  # the sweeps did move the cloth
    assert np.abs(ours[0] - product[0]).max() < 1e-6
    assert np.abs(ours[1] - product[1]).max() < 1e-5 * np.abs(product[1]).max()
    touched = state_after(lambda: floor.touches(3, 0.0, solver.x, solver.xp, solver.w, *args))
    assert np.array_equal(touched[0], x0) and not touched[1].any()

    springs = stretch.springs.to_numpy()
    disc = floor.patch_vertices(model.x0)
    assert len(disc) == floor.PATCH_VERTICES
    centre = model.x0[model.n_vertices // 2]
    radius = np.linalg.norm(model.x0[disc] - centre, axis=1).max()
    outside = np.setdiff1d(np.arange(model.n_vertices), disc)
    assert (np.linalg.norm(model.x0[outside] - centre, axis=1) >= radius).all()
    index = floor.patch_elements(springs, disc, model.n_vertices)
    inside = np.isin(springs, disc).all(axis=1)
    assert sorted(index) == sorted(np.flatnonzero(inside)) and len(index) > 100
    patch = springs[index]
    shared = [len(set(a) & set(b)) > 0 for a, b in zip(patch[:-1], patch[1:], strict=True)]
    assert np.mean(shared) < 0.1


def test_the_sweep_floors_lane_sweep_is_the_spring_update_eight_independent_springs_at_a_time():
    """bench_sweep_floor.lane_sweeps: its groups hold each spring once, no two springs of a
    group share a vertex, and its sweeps give the scalar update's positions and multipliers
    in the same (colour) order within float32 rounding."""
    import numpy as np
    import taichi as ti

    from benchmarks import bench_sweep_floor as floor
    from datagen.sim.effects import Effects
    from datagen.sim.precision import NP_REAL
    from datagen.sim.simulate import OVER_RELAXATION
    from datagen.sim.solvers import SolverSettings, XPBDSolver

    model = _study_tube()
    solver = XPBDSolver(model, Effects(pins=True), SolverSettings(substeps=20, iterations=4))
    h, omega = 1.0 / 30.0 / 20, OVER_RELAXATION["xpbd"]
    solver._use_step(h)
    stretch = solver.sets["stretch"]
    springs = stretch.springs.to_numpy()
    order, groups = floor.lane_groups(springs, model.n_vertices)
    assert len(groups) % floor.LANES == 0
    assert sorted(groups[groups >= 0]) == list(range(len(springs)))
    for group in groups.reshape(-1, floor.LANES):
        ends = springs[order[group[group >= 0]]].ravel()
        assert len(set(ends)) == len(ends)
    arrays = floor._spring_subset((stretch.springs, stretch.terms, stretch.lam), order)
    rng = np.random.default_rng(5)
    x0 = (model.x0 + rng.normal(scale=0.002, size=model.x0.shape)).astype(NP_REAL)

    def state_after(sweep) -> tuple[np.ndarray, np.ndarray]:
        solver.x.from_numpy(x0)
        solver.xp.from_numpy(model.x0.astype(NP_REAL))
        arrays[-1].from_numpy(np.zeros(len(springs), NP_REAL))
        sweep()
        ti.sync()
        return solver.x.to_numpy(), arrays[-1].to_numpy()

    scalar = state_after(lambda: floor.sweeps(3, solver.x, solver.xp, solver.w, *arrays,
                                              omega))
    lanes = state_after(lambda: floor.lane_sweeps(3, solver.x, solver.xp, solver.w, *arrays,
                                                  floor._nd(ti.i32, groups), omega))
    assert np.abs(scalar[0] - x0).max() > 1e-3  # the sweeps did move the cloth
    assert np.abs(lanes[0] - scalar[0]).max() < 1e-6
    assert np.abs(lanes[1] - scalar[1]).max() < 1e-4 * np.abs(scalar[1]).max()
