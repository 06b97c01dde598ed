"""The accuracy measures of the study (datagen/study): known answers."""

from __future__ import annotations

from dataclasses import replace

import click
import numpy as np
import pytest

from datagen.study.metrics import (
    collider_penetration,
    final_distance,
    max_distance,
    rms_distance,
)
from datagen.study.sweep import CHAOS_MM, pareto, predictable_frames


@pytest.fixture
def trajectory():
    rng = np.random.default_rng(3)
    return rng.normal(size=(31, 500, 3))


def test_reference_against_itself_is_zero(trajectory):
    assert rms_distance(trajectory, trajectory) == 0.0
    assert max_distance(trajectory, trajectory) == 0.0
    assert final_distance(trajectory, trajectory) == 0.0


def test_rigid_shift_of_one_millimetre_reads_one_millimetre(trajectory):
    direction = np.array([2.0, -1.0, 2.0]) / 3.0  # unit length
    shifted = trajectory + 0.001 * direction
    assert rms_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)
    assert max_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)
    assert final_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)


def test_horizon_limits_the_frames_compared(trajectory):
    late = trajectory.copy()
    late[10:] += 0.5  # differs only from frame 10 on
    assert rms_distance(late, trajectory, 10) == 0.0
    assert rms_distance(late, trajectory) > 0.0


def test_predictable_frames_is_where_the_twin_leaves(trajectory):
    twin = trajectory.copy()
    twin[7:] += 2 * CHAOS_MM / 1000 / np.sqrt(3)  # 2 mm away from frame 7 on
    assert predictable_frames(trajectory, twin) == 7
    assert predictable_frames(trajectory, trajectory) == len(trajectory)


def test_pareto_front():
    points = [(1.0, 10.0), (2.0, 5.0), (3.0, 6.0), (4.0, 1.0), (0.5, 20.0)]
    assert sorted(pareto(points)) == [0, 1, 3, 4]


def test_a_stopped_study_keeps_its_finished_parts(tmp_path):
    """The full plan takes hours: a finished scene/fabric part is saved and a later run with the
    same plan reuses it instead of measuring it again; one from another plan is not reused."""
    import json
    from dataclasses import asdict

    from datagen.study.sweep import (
        Row,
        _part_path,
        _plan_signature,
        quick_plan,
        reusable,
        run_study,
    )

    plan = quick_plan()
    (scene, resolution), fabric = plan.scenes[0], plan.fabrics[0]
    row = Row(scene, fabric, resolution, "xpbd", 20, 4, 1089, 0.45, 1.31, 25.4, 4.46, 21.3,
              0.144, 0.0)
    signature = json.loads(json.dumps(_plan_signature(plan, scene)))
    part = {"key": f"{scene}/{fabric}", "signature": signature,
            "ladder": [{"substeps": 40, "seconds": 14.0}], "predictable_frames": 10,
            "blender_vs_ours_mm": None, "blender": "absent", "minutes": 3.0,
            "rows": [asdict(row)]}
    path = _part_path(tmp_path, scene, resolution, fabric)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(part))
    logged: list[str] = []
    summary, rows = run_study(tmp_path, quick=True, blender=False, log=logged.append)
    assert rows == [row]  # nothing was run again (a real run takes minutes)
    assert summary["minutes"] == 3.0 and summary["predictable_frames"] == {part["key"]: 10}
    assert any("reused" in line for line in logged)
    assert (tmp_path / "accuracy.csv").read_text().count("\n") == 2
    assert not reusable(part, {**signature, "reference_levels": 7}, have_blender=False)
    # a change to the simulator's sources makes the part stale
    assert not reusable(part, {**signature, "simulator": "0" * 16}, have_blender=False)
    assert not reusable(part, signature, have_blender=True)  # Blender's series is missing


def _one_finished_part(out):
    """The full plan's first part, saved under `out` as a run would (one row): (part, path, row)."""
    import json
    from dataclasses import asdict

    from datagen.study.sweep import Row, _part_path, _plan_signature, full_plan

    plan = full_plan()
    (scene, resolution), fabric = plan.scenes[0], plan.fabrics[0]
    row = Row(scene, fabric, resolution, "xpbd", 20, 4, 4225, 1.0, 1.0, 9.0, 3.0, 9.0, 0.1, 0.0)
    part = {"key": f"{scene}/{fabric}",
            "signature": json.loads(json.dumps(_plan_signature(plan, scene))),
            "ladder": [{"substeps": 40, "seconds": 50.0, "predictable_frames": 9}],
            "predictable_frames": 9, "blender_vs_ours_mm": None, "blender": "absent",
            "minutes": 30.0, "rows": [asdict(row)]}
    path = _part_path(out, scene, resolution, fabric)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(part))
    return part, path, row


def test_report_only_names_the_parts_not_measured_yet_or_measured_earlier(tmp_path):
    import json

    import click

    from datagen.study.sweep import full_plan, run_study

    plan = full_plan()
    with pytest.raises(click.UsageError, match="no finished part"):
        run_study(tmp_path, blender=False, measure=False, log=lambda _: None)
    part, path, row = _one_finished_part(tmp_path)
    summary, rows = run_study(tmp_path, blender=False, measure=False, log=lambda _: None)
    assert rows == [row]
    expected = [f"{s}/{f}" for s, _ in plan.scenes for f in plan.fabrics][1:]
    assert summary["missing_parts"] == expected
    # --part measures only the parts named: the finished one is reused, the rest not run
    summary, rows = run_study(tmp_path, blender=False, only={part["key"]}, log=lambda _: None)
    assert rows == [row] and summary["missing_parts"] == expected
    with pytest.raises(click.UsageError, match="tshirt_walk/silk: not a part of the full plan"):
        run_study(tmp_path, blender=False, only={"tshirt_walk/silk"}, log=lambda _: None)
    # A part the simulator has changed under is reported, marked, until it is measured again
    part["signature"]["simulator"] = "0" * 16
    path.write_text(json.dumps(part))
    summary, rows = run_study(tmp_path, blender=False, measure=False, log=lambda _: None)
    assert rows == [row] and summary["earlier_simulator_parts"] == [part["key"]]
    assert summary["missing_parts"] == expected
    part["signature"]["frames"] = 999  # ... but not one measured under another plan
    path.write_text(json.dumps(part))
    with pytest.raises(click.UsageError, match="no finished part"):
        run_study(tmp_path, blender=False, measure=False, log=lambda _: None)


def test_a_part_measured_on_another_machine_is_named_with_it_on_the_page(tmp_path, monkeypatch):
    """A part records the machine that measured it (study.machine). Reported on another, the
    page names that machine beside the part (its times and rounding are that machine's), and
    why a simulator change may only be a change of CPU; a part saved before parts recorded it
    is listed as not recorded; one measured here is not named."""
    import json

    from datagen.study import machine, sweep

    monkeypatch.setattr(machine, "this_machine", lambda: "x86_64, CPU HERE, 2 cores")
    part, path, row = _one_finished_part(tmp_path)
    doc = tmp_path / "page.md"

    def page(**saved) -> tuple[dict, str]:
        path.write_text(json.dumps({**part, **saved}))
        summary = sweep.main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc),
                                 command="test", measure=False)
        return summary, doc.read_text()

    summary, text = page()
    assert summary["other_machine_parts"] == {part["key"]: "not recorded"}
    assert f"**Machine not recorded: {part['key']}**" in text
    assert "per simulated second on this machine (x86_64, CPU HERE, 2 cores)" in text
    summary, text = page(machine="x86_64, CPU HERE, 2 cores")
    assert summary["other_machine_parts"] == {} and "another machine" not in text
    assert "not recorded" not in text
    summary, text = page(machine="x86_64, CPU THERE, 2 cores")
    assert summary["other_machine_parts"] == {part["key"]: "x86_64, CPU THERE, 2 cores"}
    assert (f"**Measured on another machine: {part['key']} (x86_64, CPU THERE, 2 cores).**"
            in text)
    # Reported under an earlier simulator, the log says the machine too
    logged = []
    part["signature"]["simulator"] = "0" * 16
    path.write_text(json.dumps({**part, "machine": "x86_64, CPU THERE, 2 cores"}))
    summary, _ = sweep.run_study(tmp_path, blender=False, measure=False, log=logged.append)
    assert summary["earlier_simulator_parts"] == [part["key"]]
    assert any("on another machine (x86_64, CPU THERE, 2 cores)" in line for line in logged)


def test_a_part_timed_with_our_set_up_is_reported_marked_and_measured_again_when_asked(
        tmp_path, monkeypatch):
    """Parts saved before the set-up was timed apart (no "timing" in their signature) timed
    ours with its set-up and Blender without its own: they are reported, named on the page,
    until `--part` (or a full run) measures them again."""
    import json

    from datagen.study import sweep

    part, path, row = _one_finished_part(tmp_path)
    del part["signature"]["timing"]
    path.write_text(json.dumps(part))
    doc = tmp_path / "page.md"
    summary = sweep.main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc),
                             command="test", measure=False)
    assert summary["timed_with_setup_parts"] == [part["key"]]
    assert summary["earlier_simulator_parts"] == []  # the same simulator: only the timing
    assert f"**Ours timed with its set-up: {part['key']}.**" in doc.read_text()
    measured = []

    def run_part(scene_name, resolution, fabric, plan, have_blender, log, contact=None):
        measured.append(f"{scene_name}/{fabric}")
        return {**part, "signature": sweep._plan_signature(plan, scene_name)}

    monkeypatch.setattr(sweep, "run_part", run_part)
    summary, rows = sweep.run_study(tmp_path, blender=False, only={part["key"]},
                                    log=lambda _: None)
    assert measured == [part["key"]] and summary["timed_with_setup_parts"] == []
    assert json.loads(path.read_text())["signature"]["timing"] == sweep.TIMING
    # measured again, the part is reused as it is
    summary, rows = sweep.run_study(tmp_path, blender=False, only={part["key"]},
                                    log=lambda _: None)
    assert measured == [part["key"]] and rows == [row]


def test_a_part_whose_scene_the_simulator_still_runs_the_same_is_carried_over(
        tmp_path, monkeypatch):
    """A part measured by other simulator sources stands for today's simulator when its
    behavioural fingerprint is today's (the page lists it as carried over); when the
    fingerprint differs it reads as measured earlier. The fingerprint is replaced here: this
    is about the bookkeeping (the next test runs the real one)."""
    import json
    from dataclasses import asdict

    from datagen.study import fingerprint
    from datagen.study.sweep import Row, _part_path, _plan_signature, full_plan, run_study

    plan = full_plan()
    (scene, resolution), fabric = plan.scenes[0], plan.fabrics[0]
    row = Row(scene, fabric, resolution, "xpbd", 20, 4, 4225, 1.0, 1.0, 9.0, 3.0, 9.0, 0.1, 0.0)
    signature = json.loads(json.dumps(_plan_signature(plan, scene)))
    part = {"key": f"{scene}/{fabric}", "signature": {**signature, "simulator": "0" * 16},
            "behaviour": "1" * 16, "ladder": [{"substeps": 40, "seconds": 50.0}],
            "predictable_frames": 9, "blender_vs_ours_mm": None, "blender": "absent",
            "minutes": 30.0, "rows": [asdict(row)]}
    path = _part_path(tmp_path, scene, resolution, fabric)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(part))
    asked = []

    def today(scene_name, res, fab, p):
        asked.append((scene_name, res, fab))
        return "1" * 16

    monkeypatch.setattr(fingerprint, "part_fingerprint", today)
    summary, rows = run_study(tmp_path, blender=False, measure=False, log=lambda _: None)
    assert rows == [row] and asked == [(scene, resolution, fabric)]
    assert summary["carried_over_parts"] == [part["key"]]
    assert summary["earlier_simulator_parts"] == []
    monkeypatch.setattr(fingerprint, "part_fingerprint", lambda *a: "2" * 16)
    summary, rows = run_study(tmp_path, blender=False, measure=False, log=lambda _: None)
    assert summary["carried_over_parts"] == [] and summary["earlier_simulator_parts"] == [
        part["key"]]
    # measured under another plan, a part is not carried over whatever its fingerprint
    part["signature"]["frames"] = 999
    path.write_text(json.dumps(part))
    monkeypatch.setattr(fingerprint, "part_fingerprint", today)
    with pytest.raises(click.UsageError, match="no finished part"):
        run_study(tmp_path, blender=False, measure=False, log=lambda _: None)


def test_the_fingerprint_repeats_and_sees_a_change_in_what_the_simulator_does():
    """The coarse sheet at the quick plan's cheapest settings of each solver: the same
    simulator gives the same digest twice; the same sheet in denim (standing in for a change
    to the simulator) gives another."""
    from dataclasses import replace

    from datagen.study.fingerprint import fingerprint_frames, scene_fingerprint
    from datagen.study.scenes import build_scene
    from datagen.study.sweep import quick_plan

    configs = quick_plan().configs
    frames = fingerprint_frames("sheet_sphere")
    scene = build_scene("sheet_sphere", "cotton", "coarse", frames=frames)
    first = scene_fingerprint(scene, configs)
    assert scene_fingerprint(build_scene("sheet_sphere", "cotton", "coarse", frames=frames),
                             configs) == first
    assert len(first) == 16
    scene.garments = [replace(g, fabric="denim") for g in scene.garments]
    assert scene_fingerprint(scene, configs) != first


def test_the_fingerprint_sees_a_change_that_only_later_sweeps_make(monkeypatch):
    """Sweeping stiff bending stencils again in a substep's later sweeps (29b9dd5) changes
    nothing at one iteration, and a fingerprint of each series' cheapest setting (5x1) carried
    every part over it: the denim skirt's `default` moved from 41.4 to 34.8 mm. The fingerprint
    also runs the series' setting with the most iterations, and sees it."""
    from datagen.sim import solvers
    from datagen.study.fingerprint import fingerprint_configs, fingerprint_frames, scene_fingerprint
    from datagen.study.scenes import build_scene

    assert fingerprint_configs([(5, 1), (20, 4), (40, 8), (80, 8)]) == [(5, 1), (40, 8)]
    assert fingerprint_configs([(200, 1), (400, 1)]) == [(200, 1)]
    scene = build_scene("sheet_sphere", "leather", "coarse",
                        frames=fingerprint_frames("sheet_sphere"))
    configs = {"xpbd": [(5, 1), (20, 4)]}
    cheapest = {"xpbd": [(5, 1)]}
    today = scene_fingerprint(scene, configs), scene_fingerprint(scene, cheapest)
    monkeypatch.setattr(solvers, "STIFF_BEND_RATIO", 0.0)  # the sweeps before 29b9dd5
    before = scene_fingerprint(scene, configs), scene_fingerprint(scene, cheapest)
    assert before[1] == today[1]  # what the cheapest setting alone saw
    assert before[0] != today[0]


def test_a_failing_finer_rung_ends_the_reference_ladder(monkeypatch):
    """The study's denim sheet was rejected at 160 substeps (a whipping corner tripped the
    runaway guard) and the exception ended the whole study. A finer rung that fails now ends
    the ladder at the last rung that ran, which becomes the reference, and the ladder records
    why; a failing first rung still raises (there is no reference at all). The worker is
    replaced: this is about the ladder's bookkeeping, not the solver."""
    from datagen.study import sweep

    rng = np.random.default_rng(0)
    base = rng.normal(size=(31, 50, 3))
    calls = []

    def fake_worker(scene, fabric, resolution, solver, substeps, iterations, fp64,
                    frames=None, perturb=0.0):
        calls.append((substeps, perturb, 31))
        if substeps >= 160:
            raise RuntimeError("study worker failed: ...\nRejectedSequence: runaway velocity")
        shift = 0.0 if perturb == 0.0 else 2e-4 * np.arange(31)[:, None, None]
        return {"positions": base + shift + 0.1 / substeps, "wall": np.float64(1.0)}

    monkeypatch.setattr(sweep, "run_worker", fake_worker)
    plan = sweep.full_plan()
    ref, ladder, predictable = sweep.reference_ladder("sheet_sphere", "denim", "4k", plan, 31,
                                                      lambda _: None)
    assert [e["substeps"] for e in ladder] == [40, 80, 160]
    assert ladder[-1]["failed"].endswith("runaway velocity")
    assert np.allclose(ref, base + 0.1 / 80)  # the last rung that ran
    assert predictable == 3  # the twin is 1.04 mm away (RMS) at frame 3
    assert ladder[1]["rms_to_previous_mm"] == pytest.approx(1000 * (0.1 / 40 - 0.1 / 80)
                                                            * np.sqrt(3))

    def failing_first(*args, **kwargs):
        raise RuntimeError("study worker failed: boom")

    # A finer rung's twin that leaves sooner shortens the horizon for every rung's change
    def chaotic_when_fine(scene, fabric, resolution, solver, substeps, iterations, fp64,
                          frames=None, perturb=0.0):
        n = 31 if frames is None else frames + 1
        calls.append((substeps, perturb, n))
        # the twin leaves 1 mm RMS at frame 3 at 40 substeps, at frame 2 from 80 on
        rate = 2e-4 if substeps == 40 else 3e-4
        shift = 0.0 if perturb == 0.0 else rate * np.arange(31)[:n, None, None]
        return {"positions": (base + 0.1 / substeps)[:n] + shift, "wall": np.float64(1.0)}

    calls.clear()
    monkeypatch.setattr(sweep, "run_worker", chaotic_when_fine)
    ref, ladder, predictable = sweep.reference_ladder("sheet_sphere", "denim", "4k", plan, 31,
                                                      lambda _: None)
    assert [e["predictable_frames"] for e in ladder] == [3, 2, 2, 2, 2]
    assert predictable == 2
    # the twins run only as long as the horizon still reaches
    assert [n for _, perturb, n in calls if perturb] == [31, 3, 2, 2, 2]
    for e, coarse in zip(ladder[1:], (40, 80, 160, 320), strict=True):
        assert e["rms_to_previous_mm"] == pytest.approx(
            1000 * (0.1 / coarse - 0.1 / (2 * coarse)) * np.sqrt(3))

    monkeypatch.setattr(sweep, "run_worker", failing_first)
    with pytest.raises(RuntimeError, match="boom"):
        sweep.reference_ladder("sheet_sphere", "denim", "4k", plan, 31, lambda _: None)


def _fake_study_worker(monkeypatch, sweep, seed: int) -> list[int]:
    """Replace the study's worker process by random trajectories that converge with the
    substeps; returns the list of substeps it is asked for."""
    base = np.random.default_rng(seed).normal(size=(31, 20, 3))
    runs: list[int] = []

    def worker(scene, fabric, resolution, solver, substeps, iterations, fp64, frames=None,
               perturb=0.0):
        runs.append(substeps)
        n = 31 if frames is None else frames + 1
        return {"positions": (base + 1e-4 / substeps)[:n], "wall": np.float64(2.0)}

    monkeypatch.setattr(sweep, "run_worker", worker)
    return runs


def test_a_reference_ladder_is_reused_while_the_reference_behaves_the_same(monkeypatch,
                                                                            tmp_path):
    """A part's float64 ladder is most of its time and depends only on the implicit solver: a
    change to xpbd alone must not cost it again. The ladder is stored under the reference's
    behavioural fingerprint: the same fingerprint with other sources reads it back (and says
    which sources measured it); another fingerprint measures it again. The worker and the
    fingerprint are replaced: this is about the bookkeeping."""
    from datagen.study import cache, fingerprint, sweep

    monkeypatch.setenv("DATAGEN_CACHE_DIR", str(tmp_path))
    runs = _fake_study_worker(monkeypatch, sweep, seed=1)
    behaviour = {"digest": "a" * 16}
    monkeypatch.setattr(fingerprint, "reference_fingerprint", lambda *a: behaviour["digest"])
    monkeypatch.setattr(cache, "source_digest", lambda: "sources-one")
    plan = replace(sweep.full_plan(), reference_levels=2)
    first = sweep.stored_reference_ladder("sheet_sphere", "cotton", "4k", plan, 31,
                                          lambda _: None)
    assert first[3] is None and runs == [40, 40, 80, 80]  # each rung and its twin
    monkeypatch.setattr(cache, "source_digest", lambda: "sources-two")
    runs.clear()
    again = sweep.stored_reference_ladder("sheet_sphere", "cotton", "4k", plan, 31,
                                          lambda _: None)
    assert runs == [] and again[3] == "sources-one"
    assert np.array_equal(again[0], first[0]) and again[1] == first[1] and again[2] == first[2]
    behaviour["digest"] = "b" * 16  # the implicit solver changed
    third = sweep.stored_reference_ladder("sheet_sphere", "cotton", "4k", plan, 31,
                                          lambda _: None)
    assert runs == [40, 40, 80, 80] and third[3] is None


def test_a_trajectory_cached_with_the_scenes_own_effects_is_not_read_for_the_peers(
        monkeypatch, tmp_path):
    """The study runs ours with the peer's effects (run.PEER_EFFECTS: the scene's own without
    self-collision). A skirt-like scene's own effects include self-collision, so its ladders
    cached before (with it) must not stand for runs without it; where the two are the same (a
    sheet), the keys stay as they were and so do the cached ladders. The worker is replaced:
    this is about the bookkeeping."""
    from datagen.study import cache, fingerprint, sweep

    tube = fingerprint.effects_key("tube_cylinder", "5k", "cotton")
    assert "self_collision" not in tube["effects"] and "body_collision" in tube["effects"]
    assert fingerprint.effects_key("sheet_sphere", "4k", "cotton") == {}
    monkeypatch.setenv("DATAGEN_CACHE_DIR", str(tmp_path))
    runs = _fake_study_worker(monkeypatch, sweep, seed=2)
    monkeypatch.setattr(fingerprint, "reference_fingerprint", lambda *a: "c" * 16)
    monkeypatch.setattr(cache, "source_digest", lambda: "sources-one")
    plan = replace(sweep.full_plan(), reference_levels=2)
    with monkeypatch.context() as m:  # the bookkeeping before: no effects in the key
        m.setattr(fingerprint, "effects_key", lambda *a: {})
        sweep.stored_reference_ladder("tube_cylinder", "cotton", "5k", plan, 31, lambda _: None)
    assert len(runs) == 4
    runs.clear()
    again = sweep.stored_reference_ladder("tube_cylinder", "cotton", "5k", plan, 31,
                                          lambda _: None)
    assert len(runs) == 4 and again[3] is None  # measured again, not read back


def test_reading_states_what_the_rows_show():
    """The report's reading is computed from the rows: an error falling as 1/substeps reads as
    order 1.00, a preset beaten in time and error by another run on the same mesh is off the
    front (named, with the speed-up), and a coarser mesh's rows do not push a preset off."""
    from datagen.study.report import convergence_order, reading
    from datagen.study.sweep import Row

    def row(sub, it, seconds, mm, resolution="4k", note="", vertices=4225):
        return Row("sheet_sphere", "cotton", resolution, "xpbd", sub, it, vertices, seconds,
                   mm, mm, mm, mm, 0.1, 0.0, "ok", note)

    rows = [row(s, 1, 0.03 * s, 40.0 / s) for s in (5, 10, 20, 40)]
    rows += [row(20, 4, 1.5, 2.5), row(10, 2, 0.35, 3.5)]
    rows.append(row(40, 1, 0.4, 0.5, "coarse", "measured at the reference mesh's vertices",
                    1089))
    assert convergence_order(rows) == pytest.approx(1.0)
    text = "\n".join(reading(rows, {"default": (20, 4), "draft": (10, 2)}))
    assert "substeps^-1.00" in text
    assert "**`default`** (20x4) is off the front: xpbd 40x1 is 1.25x faster" in text
    assert "**`draft`** (10x2) is on the front." in text
    assert "coarse 40x1: 0.50x the error in 0.33x the time" in text


def test_body_scenes_start_from_one_settled_state(tmp_path, monkeypatch):
    """Every run of a body scene starts from one cached settled state. A float64 study worker
    must find it cached (its own settle would start its runs elsewhere); the start keeps the
    template's rest metric, and the waist the skirt is pinned by is on the body. (The settle
    runs at one implicit substep per frame here: the start's 20 take minutes.)"""
    from dataclasses import replace

    import trimesh

    import datagen.sim.simulate as sim
    from datagen.study.scenes import build_scene

    real = sim.simulate
    monkeypatch.setattr(sim, "simulate", lambda g, b, o: real(g, b, replace(o, substeps=1,
                                                                             iterations=4)))
    monkeypatch.setenv("DATAGEN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("DATAGEN_SIM_FP64", "1")
    with pytest.raises(RuntimeError, match="settled start of study scene skirt_body"):
        build_scene("skirt_body", "cotton", frames=2)
    monkeypatch.delenv("DATAGEN_SIM_FP64")
    short = build_scene("skirt_body", "cotton", frames=2)
    longer = build_scene("skirt_body", "cotton", frames=4)  # the cached start
    a, b = short.garments[0], longer.garments[0]
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert np.abs(a.vertices - a.rest).max() > 0.05  # it is on the body, not at the rest
    body = trimesh.Trimesh(short.track.vertices[0], short.track.faces, process=False)
    _, gap, _ = trimesh.proximity.closest_point(body, a.vertices[a.pinned])
    assert gap.max() < 0.02, gap.max()


def test_a_rejected_warm_up_does_not_stand_for_the_measured_run(monkeypatch):
    """The study compiles each solver's kernels on a two-frame warm-up. The explicit solver's
    warm-up at 2 substeps blew up on the 1 cm body scenes, and its rejection was recorded as
    the 200- and 400-substep runs' own ("after 2 retries with up to 8 substeps"). The warm-up
    now runs at the run's steps, and only the measured run can reject."""
    from datagen.errors import RejectedSequence
    from datagen.sim.scenes import grid_sheet
    from datagen.sim.simulate import ColliderTrack
    from datagen.study import run as study_run
    from datagen.study.scenes import StudyScene
    from datagen.types import SimResult

    calls = []

    def fake_simulate(garments, track, options):
        calls.append((track.n_frames, options.substeps))
        if len(calls) == 1:
            raise RejectedSequence("simulate", "unstable at frame 1 (the warm-up)")
        n = track.n_frames
        return SimResult(["sheet"], {"sheet": np.zeros((n, 4, 3), np.float32)}, {},
                         {"frames_time_s": 2.0, "setup_time_s": 0.5})

    monkeypatch.setattr(study_run, "simulate", fake_simulate)
    monkeypatch.setattr(study_run, "_WARM", set())
    sheet = grid_sheet(1, 0.1, 1.0)
    track = ColliderTrack(np.zeros((11, 3, 3)), np.array([[0, 1, 2]]), np.ones(1, bool))
    scene = StudyScene("warm", "cotton", "", [sheet], track, 10, 10, 10)
    run = study_run.run_ours(scene, "explicit", 200, 1)
    assert calls == [(3, 200), (11, 200)]
    assert run.positions.shape == (11, 4, 3) and run.simulated == pytest.approx(10 / 30)
    assert (run.wall, run.setup) == (2.0, 0.5)  # the frames timed, the set-up apart


def test_equal_error_speed_pairs_each_blender_run_with_our_cheapest_as_close():
    """Each Blender run is matched with the cheapest of our xpbd runs (on the scene's mesh) whose
    error is no larger; the ratio is Blender's time over ours; an unmatched run says so."""
    from datagen.study.report import equal_error_speed
    from datagen.study.sweep import Row

    def row(series, sub, it, seconds, mm, resolution="4k", note=""):
        return Row("sheet_sphere", "cotton", resolution, series, sub, it, 4225, seconds,
                   mm, mm, mm, mm, 0.1, 0.0, "ok", note)

    rows = [row("xpbd", 10, 2, 0.5, 9.0), row("xpbd", 20, 4, 1.0, 4.0),
            row("xpbd", 40, 8, 3.0, 2.0), row("xpbd", 5, 1, 0.1, 1.0, "coarse",
                                              "measured at the reference mesh's vertices"),
            row("blender", 5, 1, 10.0, 5.0), row("blender", 20, 1, 40.0, 1.5),
            # Not a 5x1 run throughout: its frames ran at the guard's finer steps, so its time
            # is not credited to 5x1 (it would be the cheapest within q5's error).
            row("xpbd", 5, 1, 0.2, 3.0, "4k", "20 frames at finer steps, up to 10 substeps")]
    text = "\n".join(equal_error_speed(rows))
    assert "| sheet_sphere/cotton | q5 | 5.00 | 10.00 | xpbd 20x4 | 4.00 | 1.00 | 10.0x |" in text
    assert "| sheet_sphere/cotton | q20 | 1.50 | 40.00 | none of ours is this close |" in text
    # The presets' comparison names the same run as what the default's time buys: the default
    # (40x8, 2 mm) against Blender q5 (5 mm) is 3.3x; at q5's error, 20x4 is 10x faster.
    from datagen.study.report import comparison

    line = comparison(rows, {"default": (40, 8)})[0]
    assert "**3.3x** faster" in line and "xpbd 20x4 (4.00 mm at 1.00 s), 10.0x faster" in line


def test_a_regenerated_page_keeps_the_hand_written_state_of_the_study(tmp_path):
    """The reading that rows cannot give lives in OUT/state.md (first) and OUT/history.md
    (last) and survives --report-only."""
    from datagen.study.report import HISTORY_NOTE, STATE_NOTE
    from datagen.study.sweep import main_cli

    _one_finished_part(tmp_path)
    doc = tmp_path / "page.md"
    main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc), command="test",
             measure=False)
    assert "State of the study" not in doc.read_text()
    (tmp_path / STATE_NOTE).write_text("**State of the study.** Measured by hand.\n")
    main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc), command="test",
             measure=False)
    page = doc.read_text()
    assert page.index("not measured yet") < page.index("**State of the study.** Measured by hand.")
    assert page.index("Measured by hand.") < page.index("## The scenes")
    assert "How the study got here" not in page
    # The log of earlier measurements comes last, after every table, under its own heading.
    (tmp_path / HISTORY_NOTE).write_text("**Measured once (first session).** Long ago.\n")
    main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc), command="test",
             measure=False)
    page = doc.read_text()
    assert page.index("## The table") < page.index("## How the study got here")
    assert page.rstrip().endswith("**Measured once (first session).** Long ago.")
    assert page.index("Measured by hand.") < page.index("## The scenes")


def test_blenders_converged_quality_is_per_scene_so_other_parts_stay_reported():
    """Raising Blender's converged quality for some scenes (the sheets' quality 40 was not
    converged) changes only those scenes' part signatures, and a part measured at the old
    quality stays reportable, marked, not dropped; one from another plan is not."""
    from datagen.study.sweep import _plan_signature, earlier_simulator, full_plan, measured_earlier

    plan = full_plan()
    assert {plan.blender_converged_for(s) for s, _ in plan.scenes} == {320}
    old = replace(plan, blender_converged=40, blender_converged_by_scene={})
    new = replace(old, blender_converged_by_scene={"sheet_sphere": 320})
    assert new.blender_converged_for("tshirt_walk") == 40
    for scene, same_quality in (("tshirt_walk", True), ("sheet_sphere", False)):
        saved = {**_plan_signature(old, scene), "simulator": "0" * 16}
        now = _plan_signature(new, scene)
        # only a part at the same Blender quality can stand for today's (carried over)
        assert earlier_simulator({"signature": saved}, now) == same_quality
        assert measured_earlier({"signature": saved}, now)
        assert now["blender_converged"] == (40 if same_quality else 320)
    saved = _plan_signature(old, "sheet_sphere")
    assert not measured_earlier({"signature": saved}, saved)  # today's: reusable, not earlier
    assert not measured_earlier({"signature": {**saved, "reference_levels": 7}},
                                _plan_signature(plan, "sheet_sphere"))


def test_a_part_against_an_earlier_blender_quality_is_reported_and_named(tmp_path):
    import json

    from datagen.study.sweep import main_cli

    part, path, _ = _one_finished_part(tmp_path)
    path.write_text(json.dumps({**part, "signature": {**part["signature"], "simulator": "0" * 16,
                                                      "blender_converged": 40}}))
    doc = tmp_path / "page.md"
    summary = main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc), command="test",
                       measure=False)
    assert summary["earlier_simulator_parts"] == [part["key"]]
    assert summary["earlier_blender_converged"] == {part["key"]: 40}
    assert part["key"] not in summary["missing_parts"]
    assert (f"**Blender's rows against an earlier converged run: {part['key']} (quality 40).**"
            in doc.read_text())


def _fake_blender(monkeypatch, ref, deep_share=0.0):
    """Blender replaced by runs that land 0.32 m / quality off `ref` in x, and the penetration
    measure by `deep_share` (this is about the bookkeeping of Blender's series): the list of
    (quality, matched) calls."""
    from datagen.study import blender as peer
    from datagen.study import metrics
    from datagen.study.run import Run

    calls: list[tuple[int, bool]] = []

    def fake_blender(scene, quality, matched_contact=False):
        calls.append((quality, matched_contact))
        positions = ref.copy()
        positions[..., 0] += 0.32 / quality
        return Run(f"blender q{quality}", positions, 1.0, 0.1, {})

    monkeypatch.setattr(peer, "run_blender", fake_blender)
    monkeypatch.setattr(metrics, "scene_penetration", lambda positions, scene: (0.0, deep_share))
    return calls


def test_blenders_series_checks_its_converged_run_against_half_its_quality(monkeypatch):
    """Each part says how far Blender's "converged" run is from half its quality, reusing a
    timed quality's run when it is that half. A fake Blender that lands 0.32 m / quality off
    the reference puts quality 5 at 64 mm, 10 at 32 mm: 32 mm apart."""
    from types import SimpleNamespace

    from datagen.study.contact import STUDY_CUSHION_RULE
    from datagen.study.sweep import blender_series, quick_plan

    ref = np.zeros((4, 6, 3))
    calls = _fake_blender(monkeypatch, ref, deep_share=0.25)
    # converged at quality 10, timed quality 5, the study's cushion everywhere
    plan = replace(quick_plan(), blender_contact=STUDY_CUSHION_RULE)
    scene = SimpleNamespace(n_vertices=6)
    gap, halving, rows, cushion = blender_series(scene, "sheet_sphere", "cotton", "coarse", plan,
                                                 ref, horizon=4, pred=3, log=lambda _: None)
    assert sorted(calls) == [(5, False), (10, False)]  # quality 5 is the half and timed: once
    assert halving == {"quality": 5, "against": 10, "mm": pytest.approx(32.0)}
    assert gap == pytest.approx(32.0)  # the converged run against our reference
    assert [r.substeps for r in rows] == [5] and rows[0].rms_mm == pytest.approx(32.0)
    assert rows[0].deep_share == 0.25  # Blender's run measured as our QA measures ours
    assert cushion == {"blender_contact": "study", "blender_matched_deep_share": None}


@pytest.mark.parametrize("deep_share, matched", [(0.0, True), (0.01, True), (0.0101, False)])
def test_blenders_cushion_is_matched_only_where_its_quality_5_trial_keeps_the_cloth_out(
        monkeypatch, deep_share, matched):
    """The rule (datagen.study.contact): Blender's quality 5 with the cushion matched to our
    thickness; matched for the whole series when that trial keeps the share of the garment
    deeper than its thickness within the QA's 1 % (the bound included), else the study's
    cushion. Matched, the trial is the series' quality 5 run (not run twice)."""
    from types import SimpleNamespace

    from datagen.study.contact import choose_contact
    from datagen.study.sweep import blender_series, quick_plan

    ref = np.zeros((4, 6, 3))
    calls = _fake_blender(monkeypatch, ref, deep_share)
    scene = SimpleNamespace(n_vertices=6)
    choice = choose_contact(scene)
    assert (choice.matched, choice.matched_deep_share) == (matched, deep_share)
    assert choice.record() == {"blender_contact": "matched" if matched else "study",
                               "blender_matched_deep_share": deep_share}
    assert calls == [(5, True)]
    gap, halving, rows, cushion = blender_series(scene, "sheet_sphere", "cotton", "coarse",
                                                 quick_plan(), ref, horizon=4, pred=3,
                                                 log=lambda _: None, contact=choice)
    assert cushion == choice.record()
    assert calls[1:] == ([(10, True)] if matched else [(10, False), (5, False)])
    assert rows[0].note.endswith(f"{'matched' if matched else 'study'} cushion")
    assert rows[0].rms_mm == pytest.approx(32.0)  # whichever run it is, against quality 10
    other = SimpleNamespace(n_vertices=6)  # the trial stands only for its own scene
    choice.run(other, 5)
    assert calls[-1] == (5, matched)


def _saved_before_the_cushion_rule(tmp_path, monkeypatch):
    """_one_finished_part as saved before the plan chose Blender's cushion, with Blender's
    series, on a machine that has Blender: (part, path, row)."""
    import json

    from datagen.study import blender as peer

    part, path, row = _one_finished_part(tmp_path)
    del part["signature"]["blender_contact"]
    part.update(blender="Blender 3.4.1", blender_vs_ours_mm=20.0)
    path.write_text(json.dumps(part))
    monkeypatch.setattr(peer, "blender_executable", lambda: "/usr/bin/blender")
    monkeypatch.setattr(peer, "blender_version", lambda: "Blender 3.4.1")
    return part, path, row


def test_a_part_measured_with_the_studys_cushion_stands_where_the_rule_keeps_that_cushion(
        tmp_path, monkeypatch):
    """Measured again under the cushion rule, a part saved before it runs only the rule's
    trial: where the trial keeps the study's cushion, the part's Blender series is what the
    rule would measure, so it stands (saved with the rule and the trial's record); where the
    trial chooses the matched cushion, the part is measured again with that choice. Reported
    without measuring, it is named as measured with the study's cushion."""
    import json
    from types import SimpleNamespace

    from datagen.study import contact as contact_module
    from datagen.study import scenes, sweep
    from datagen.study.contact import CONTACT_RULE, STUDY_CUSHION_RULE, ContactChoice

    part, path, row = _saved_before_the_cushion_rule(tmp_path, monkeypatch)
    doc = tmp_path / "page.md"
    summary = sweep.main_cli(str(tmp_path), quick=False, blender=True, doc=str(doc),
                             command="test", measure=False)
    assert summary["earlier_blender_contact"] == {part["key"]: STUDY_CUSHION_RULE}
    assert summary["earlier_simulator_parts"] == []
    page = doc.read_text()
    assert f"**Blender with the study's cushion everywhere: {part['key']}.**" in page
    assert "Blender's cushion the study's, 13.3 mm (the part predates the cushion rule)" in page

    scene = SimpleNamespace(name="the part's scene")
    monkeypatch.setattr(scenes, "build_scene", lambda *args: scene)
    measured, tried = [], []
    deep = {"share": 0.18}

    def choose(s):
        tried.append(s)
        return ContactChoice(deep["share"] <= 0.01, deep["share"], None, s)

    def run_part(scene_name, resolution, fabric, plan, have_blender, log, contact=None):
        measured.append(contact)
        return {**part, "signature": sweep._plan_signature(plan, scene_name),
                **contact.record()}

    monkeypatch.setattr(contact_module, "choose_contact", choose)
    monkeypatch.setattr(sweep, "run_part", run_part)
    summary, rows = sweep.run_study(tmp_path, only={part["key"]}, log=lambda _: None)
    saved = json.loads(path.read_text())
    assert tried == [scene] and measured == [] and rows == [row]
    assert saved["signature"]["blender_contact"] == CONTACT_RULE
    assert (saved["blender_contact"], saved["blender_matched_deep_share"]) == ("study", 0.18)
    assert summary["blender_contact"] == {part["key"]: {"contact": "study",
                                                        "matched_deep_share": 0.18}}
    assert summary["earlier_blender_contact"] == {}
    # it now stands as it is: no trial; the page names its cushion and the trial's figure
    sweep.main_cli(str(tmp_path), quick=False, blender=True, doc=str(doc), command="test",
                   only={part["key"]})
    assert tried == [scene] and measured == []
    assert ("Blender's cushion the study's, 13.3 mm (matched to our thickness, its quality 5 "
            "let 18.00 % of the garment deeper than the thickness)") in doc.read_text()

    path.write_text(json.dumps(part))  # saved before the rule again; the trial holds now
    deep["share"] = 0.004
    summary, rows = sweep.run_study(tmp_path, only={part["key"]}, log=lambda _: None)
    assert len(tried) == 2 and [c.matched for c in measured] == [True]
    assert measured[0].scene is scene  # its trial is the series' quality 5 run
    assert json.loads(path.read_text())["blender_contact"] == "matched"


def test_the_page_gives_each_parts_blender_halving_or_says_it_was_not_measured(tmp_path):
    import json

    from datagen.study.sweep import main_cli

    part, path, _ = _one_finished_part(tmp_path)
    doc = tmp_path / "page.md"
    for halving, expected in (
            ({"quality": 160, "against": 320, "mm": 0.26},
             "Blender quality 160 against its quality 320 (is that run converged?) 0.26 mm"),
            (None, "Blender's halving not measured (the part predates it)")):
        path.write_text(json.dumps({**part, "blender_vs_ours_mm": 28.9,
                                    "blender_halving": halving}))
        main_cli(str(tmp_path), quick=False, blender=False, doc=str(doc), command="test",
                 measure=False)
        line = next(ln for ln in doc.read_text().splitlines()
                    if ln.startswith(f"- {part['key']}: Blender converged vs ours"))
        assert "28.9 mm RMS" in line and f"{expected}; Blender's cushion" in line


def test_the_machine_label_names_the_first_cpu_and_digests_its_flags_in_any_order():
    """A study part and a benchmark page name the CPU that measured them: the first processor
    of /proc/cpuinfo, its family, model and stepping, and a digest of its feature flags (what
    Taichi's LLVM compiles for), the same whatever order the kernel lists them in."""
    from datagen.study.machine import cpu_label

    def cpuinfo(flags: str, model: str = "2") -> str:
        block = (f"processor\t: {{}}\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\n"
                 f"model\t\t: {model}\nmodel name\t: AMD EPYC\nstepping\t: 1\nflags\t\t: {flags}\n")
        return block.format(0) + "\n" + block.format(1).replace("model name\t: AMD EPYC",
                                                               "model name\t: other")

    label = cpu_label(cpuinfo("fpu avx2 avx512f"))
    assert label.startswith("AMD EPYC (family 26, model 2, stepping 1, flags ")
    assert label == cpu_label(cpuinfo("avx512f fpu avx2"))
    assert label != cpu_label(cpuinfo("fpu avx2"))  # no AVX-512: other code, maybe other rounding
    assert label != cpu_label(cpuinfo("fpu avx2 avx512f", model="1"))


def test_collider_penetration_counts_vertices_inside_and_deeper_than_the_thickness():
    """A unit sphere (icosphere, 4 subdivisions) and 100 cloth vertices on a ray: 10 at 2 mm
    inside (inside, not deep at a 5 mm thickness), 5 at 20 mm inside (deep), the rest 5 mm
    outside. Frame 0 (the start) is not counted; the share is the worst frame's."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    # The mesh's surface along +z lies slightly inside the unit sphere: measure from it.
    top = float(sphere.vertices[:, 2].max())
    radii = np.full(100, top + 0.005)
    radii[:10] = top - 0.002
    radii[10:15] = top - 0.020
    frame = np.stack([np.zeros(100), np.zeros(100), radii], axis=1)
    outside = np.stack([np.zeros(100), np.zeros(100), np.full(100, top + 0.005)], axis=1)
    positions = np.stack([frame, outside, frame, outside])  # worst frames 0 and 2
    vertices = np.repeat(np.asarray(sphere.vertices)[None], 4, axis=0)
    inside, deep = collider_penetration(positions, vertices, np.asarray(sphere.faces), 0.005)
    assert (inside, deep) == (0.15, 0.05)
    # Over frame 1 alone nothing is inside.
    assert collider_penetration(positions, vertices, np.asarray(sphere.faces), 0.005,
                                frames=1) == (0.0, 0.0)


def test_blenders_matched_cushion_rests_the_cloth_at_our_thickness():
    """Blender holds cloth at 8/9 of (its collision distance + the collider's outer thickness);
    matched, that is each fabric's thickness, with the collider at Blender's smallest outer
    thickness; the study's cushion is 5 + 10 mm (13.3 mm at rest) whatever the fabric."""
    from datagen.sim.fabrics import FABRICS
    from datagen.study.blender import contact_settings

    for name, fabric in FABRICS.items():
        matched = contact_settings(name, matched=True)
        rest = 8 / 9 * (matched["collision_distance"] + matched["collider_thickness"])
        assert rest == pytest.approx(fabric.thickness, rel=1e-12)
        assert matched["collider_thickness"] == 0.001 and matched["collision_distance"] >= 0.001
    assert contact_settings("denim") == {"collision_distance": 0.005, "collider_thickness": 0.01}
