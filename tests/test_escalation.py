"""A sequence whose run breaks a physical-validity bound, or is rejected as unstable, is
simulated once more one quality preset up (datagen.pipeline.stages.simulate_within_bounds)."""

from __future__ import annotations

import pickle
import re
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from datagen import qa
from datagen.errors import BoundBroken, RejectedSequence
from datagen.pipeline.stages import (
    SequenceRecord,
    mark_rejected,
    next_rung,
    reject_over_qa_bounds,
    simulate_within_bounds,
    simulation_runs,
)
from datagen.sim import simulate as sim_module
from datagen.sim.fabrics import FABRICS
from datagen.sim.scenes import grid_sheet, icosphere
from datagen.sim.simulate import ESCALATED_SOR, ColliderTrack, SimOptions, simulate
from datagen.spec import SceneSpec

sys.path.insert(0, str(Path(__file__).parent))
import shard_factory as sf  # noqa: E402


def test_escalation_goes_one_preset_up_with_plain_sweeps():
    up = SimOptions().escalated()
    assert (up.quality, up.sor) == ("reference", ESCALATED_SOR)
    assert up.resolve_steps() == (40, 8)  # the serial presets (one thread here)
    assert SimOptions(quality="draft").escalated().quality == "default"
    assert SimOptions(quality="draft", sor=1.3).escalated().sor == 1.3  # the caller's choice
    assert SimOptions(solver="implicit").escalated().quality == "reference"
    # Nothing above the top preset, and steps the caller gave are the caller's.
    assert SimOptions(quality="reference").escalated() is None
    assert SimOptions(substeps=30).escalated() is None
    assert SimOptions(iterations=6).escalated() is None
    # The ladder (stages.next_rung) goes one rung past the top preset, its steps doubled, and
    # no further: steps given, by the caller or by that rung, are not escalated.
    assert next_rung(SimOptions()) == up
    past = next_rung(up)
    assert (past.resolve_steps(), past.sor) == ((80, 16), ESCALATED_SOR)
    assert past.steps_label() == "reference 80x16, sor 1"
    assert next_rung(past) is None and next_rung(SimOptions(substeps=30)) is None
    assert next_rung(SimOptions(quality="reference")).sor == ESCALATED_SOR
    assert SimOptions().steps_label() == "default 20x4, sor 1.6"


def test_presets_keep_their_step_and_search_interval_in_time_at_any_output_rate():
    """The presets were tuned at 30 fps (20 substeps a frame at `default`: a 1/600 s step).
    Kept per frame, a 15 fps walk ran at twice that step and a 60 fps one paid twice the
    substeps per simulated second. Values worked out by hand from 20 x 30 / fps, rounded up
    unless within 1 % of a whole number."""
    from datagen.errors import InputError
    from datagen.sim.simulate import interval_at, substeps_at

    default = SimOptions()
    for fps, substeps in [(30.0, 20), (60.0, 10), (24.0, 25), (25.0, 24), (29.97, 20),
                          (90.0, 7), (15.0, 40), (10.0, 60), (120.0, 5), (1000.0, 1)]:
        assert default.resolve_steps(fps) == (substeps, 4), fps
    assert default.steps_label(60.0) == "default 10x4, sor 1.6"
    assert SimOptions(substeps=20).resolve_steps(60.0) == (20, 4)  # the caller's, as given
    assert SimOptions(solver="implicit").resolve_steps(60.0) == (5, 10)
    assert SimOptions(solver="implicit", quality="draft").resolve_steps(24.0) == (3, 4)  # 2.5 up
    explicit = SimOptions(solver="explicit")
    assert [explicit.resolve_steps(fps)[0] for fps in (30.0, 29.97, 30.3)] == [400, 400, 396]
    # The ladder at 60 fps: reference 40x8 is 20x8 there, and the rung past it twice that.
    past = next_rung(default.escalated(), 60.0)
    assert (past.resolve_steps(60.0), past.sor) == ((40, 16), ESCALATED_SOR)
    # The full search every 5 frames at 30 fps (1/6 s): never less often in time, but at
    # most once a frame.
    assert [interval_at(fps, 5) for fps in (30.0, 60.0, 29.97, 15.0, 10.0, 5.0)] == \
        [5, 10, 5, 2, 1, 1]
    assert substeps_at(30.0, 1) == 1
    with pytest.raises(InputError, match="fps"):
        default.resolve_steps(0.0)


def _sheet_on_sphere(monkeypatch, bound: float):
    """A cotton sheet falling on a sphere, with cotton's strain bound set to `bound`. Strain
    refinement is off, so a frame over the bound stays over it."""
    monkeypatch.setitem(FABRICS, "cotton", replace(FABRICS["cotton"], max_strain=bound))
    sv, sf = icosphere(0.25, 4)
    track = ColliderTrack(np.repeat(sv[None], 31, axis=0), sf, np.ones(len(sf), dtype=bool))
    return [grid_sheet(16, 0.8, 0.3)], track


def _counting_simulate(monkeypatch) -> list[SimOptions]:
    """The options of every simulate() call made through the stages (a spy on the real one)."""
    calls: list[SimOptions] = []

    def spy(garments, body, options):
        calls.append(options)
        return simulate(garments, body, options)

    monkeypatch.setattr(sim_module, "simulate", spy)
    return calls


def test_a_run_over_a_bound_is_simulated_again_one_preset_up(monkeypatch):
    """At a 2 % bound the default preset ends over it (measured: 0.0210 at frame 8 with plain
    sweeps), the reference steps within it (0.0187): the result is the second run, it says
    why, and it is the run that simulating at those options gives."""
    from datagen.sim.progress import frame_progress

    garments, track = _sheet_on_sphere(monkeypatch, 0.02)
    calls = _counting_simulate(monkeypatch)
    options = SimOptions(settle_seconds=0.0, strain_refinements=0)
    heard: list[tuple[int, int, str]] = []
    with frame_progress(lambda *frame: heard.append(frame)):
        result = simulate_within_bounds(garments, track, options)
    assert [c.quality for c in calls] == ["default", "reference"]
    # Each run tells the listener after each of its 30 frames, naming its settings.
    assert heard == [(k, 30, "xpbd default 20x4, sor 1.6") for k in range(1, 31)] + [
        (k, 30, "xpbd reference 40x8, sor 1") for k in range(1, 31)]
    assert (result.report["quality"], result.report["substeps"], result.report["iterations"],
            result.report["sor"]) == ("reference", 40, 8, 1.0)
    first = result.report["escalated_from"]
    assert first["settings"] == "xpbd default 20x4, sor 1.6"
    assert "qa/over_strain_share" in first["reason"] and "bound 0.001" in first["reason"]
    assert first["wall_time_s"] > 0
    assert not qa.breaches(result.qa)
    direct = simulate(garments, track, options.escalated())
    np.testing.assert_array_equal(result.vertices[garments[0].name],
                                  direct.vertices[garments[0].name])
    assert len(heard) == 60  # outside the block nobody listens


def test_datagen_simulate_shows_a_new_bar_for_each_run(capsys):
    from datagen.cli import FrameBar

    bar = FrameBar()
    for settings in ("xpbd default 20x4, sor 1.6", "xpbd reference 40x8, sor 1"):
        for k in range(1, 4):
            bar(k, 3, settings)
    bar.close()
    err = capsys.readouterr().err
    assert "simulating (xpbd default 20x4, sor 1.6): 100%" in err
    assert "simulating (xpbd reference 40x8, sor 1): 100%" in err and "3/3" in err


def test_datagen_simulate_bar_redraws_rarely_into_a_log(capsys, monkeypatch):
    """With stderr a file (pytest's capture is one) the frame bar redraws at most every
    cli.LOG_REDRAW_S seconds instead of every frame: 20 frames of 0.12 s give its first and
    last state only, where a terminal's bar (a redraw after 0.1 s) draws every frame."""
    import time

    from datagen import cli

    def twenty_frames() -> str:
        bar = cli.FrameBar()
        for k in range(1, 21):
            time.sleep(0.12)
            bar(k, 20, "xpbd default 20x4, sor 1.6")
        bar.close()
        return capsys.readouterr().err

    assert not sys.stderr.isatty()
    err = twenty_frames()
    assert "20/20" in err and err.count("simulating (") <= 3
    monkeypatch.setattr(cli, "LOG_REDRAW_S", 0.1)  # a terminal's interval
    assert twenty_frames().count("simulating (") >= 15


def test_a_run_within_its_bounds_is_not_simulated_again(monkeypatch):
    garments, track = _sheet_on_sphere(monkeypatch, 0.25)
    calls = _counting_simulate(monkeypatch)
    result = simulate_within_bounds(garments, track, SimOptions(settle_seconds=0.0))
    assert len(calls) == 1 and "escalated_from" not in result.report
    assert simulation_runs(result) == 1


def test_escalation_climbs_until_a_run_keeps_its_bounds(monkeypatch):
    """At a 1.2 % bound the draft preset (measured 0.0204) and the default steps with plain
    sweeps (0.0137) end over it, the reference steps within it (0.0115): the ladder stops
    there, and the result names both runs it did not keep."""
    garments, track = _sheet_on_sphere(monkeypatch, 0.012)
    calls = _counting_simulate(monkeypatch)
    options = SimOptions(quality="draft", settle_seconds=0.0, strain_refinements=0)
    result = simulate_within_bounds(garments, track, options)
    assert [c.quality for c in calls] == ["draft", "default", "reference"]
    assert (result.report["substeps"], result.report["iterations"]) == (40, 8)
    assert not qa.breaches(result.qa)
    dropped = result.report["escalations"]
    assert [d["settings"] for d in dropped] == ["xpbd draft 10x2, sor 1.6",
                                                "xpbd default 20x4, sor 1"]
    assert result.report["escalated_from"] == dropped[0]
    assert all("qa/over_strain_share" in d["reason"] and d["wall_time_s"] > 0 for d in dropped)


def _first_frame_over(garments, track, options) -> int:
    """The first output frame at which an unguarded run at `options` breaks a bound."""
    series = simulate(garments, track, options).qa["over_strain_share"]
    assert (series > qa.STRAIN_SHARE_MAX).any()
    return int(np.argmax(series > qa.STRAIN_SHARE_MAX))


def test_a_guarded_run_stops_at_its_first_frame_over_a_bound_and_climbs_the_same_ladder(
        monkeypatch):
    """Where the gate rejects a sequence over a bound (a dataset run), the simulator stops a
    run at its first output frame over one (SimOptions.bound_guard): the ladder would simulate
    it again whatever followed. At the 1.2 % bound the draft and default runs are over it and
    the reference run within: guarded, the same three rungs, each dropped run stopped at the
    first frame its unguarded twin went over, and the kept run the same bit for bit."""
    garments, track = _sheet_on_sphere(monkeypatch, 0.012)
    options = SimOptions(quality="draft", settle_seconds=0.0, strain_refinements=0)
    plain = simulate_within_bounds(garments, track, options)
    calls = _counting_simulate(monkeypatch)
    guarded = simulate_within_bounds(garments, track, replace(options, bound_guard=True))
    assert [c.quality for c in calls] == ["draft", "default", "reference"]
    firsts = [_first_frame_over(garments, track, replace(c, bound_guard=False))
              for c in calls[:2]]
    with pytest.raises(BoundBroken) as info:  # the simulator's own: its type crosses processes
        simulate(garments, track, calls[0])
    assert info.value.stage == "qa" and info.value.frames == (firsts[0], firsts[0])
    back = pickle.loads(pickle.dumps(info.value))
    assert isinstance(back, BoundBroken) and back.reason == info.value.reason
    np.testing.assert_array_equal(guarded.vertices[garments[0].name],
                                  plain.vertices[garments[0].name])
    dropped = guarded.report["escalations"]
    assert [d["settings"] for d in dropped] == ["xpbd draft 10x2, sor 1.6",
                                                "xpbd default 20x4, sor 1"]
    totals = set()
    for d, first in zip(dropped, firsts, strict=True):
        assert first < 29  # stopped before the end
        # The reason says where: the garment and how many of its springs (a sphere has no
        # body parts to name).
        found = re.search(rf"qa/over_strain_share ([0-9.]+) at frame {first}, bound 0\.001; "
                          r"the cotton sheet 'sheet', ([0-9]+) springs over\); "
                          r"the run stopped there$", d["reason"])
        assert found, d["reason"]
        totals.add(round(int(found[2]) / float(found[1])))  # the sheet's springs, both runs
    assert len(totals) == 1


def test_a_guarded_runs_reason_names_the_body_part_under_the_broken_bound(monkeypatch):
    """On a collider with body parts, the guard's reason also names the parts nearest the
    springs over their bound (qa.where_on_body, checked by hand in test_validate): the sphere
    of the tests above as one part, the left shin, is the only part to name, and the count of
    springs over is the breach's share of the sheet's springs, as in the test above."""
    garments, track = _sheet_on_sphere(monkeypatch, 0.012)
    track = replace(track, vertex_parts=np.full(track.vertices.shape[1], 4))  # 4: shin_l
    options = SimOptions(quality="draft", settle_seconds=0.0, strain_refinements=0,
                         bound_guard=True)
    with pytest.raises(BoundBroken) as info:
        simulate(garments, track, options)
    found = re.fullmatch(r"fabric springs strained beyond their fabric's max_strain "
                         r"\(qa/over_strain_share ([0-9.]+) at frame [0-9]+, bound 0\.001; "
                         r"the cotton sheet 'sheet', ([0-9]+) springs over, nearest shin_l "
                         r"100 %\); the run stopped there", info.value.reason)
    assert found, info.value.reason
    from datagen.sim.model import build_cloth_model

    springs = len(build_cloth_model([(garments[0], FABRICS["cotton"])]).fabric_strain_terms[0])
    assert int(found[2]) == round(float(found[1]) * springs) >= 1


def test_a_guarded_sequence_over_its_bound_on_every_rung_is_rejected_naming_every_run(
        monkeypatch):
    """Guarded, the sequence that every rung breaks (below, at the 0.6 % bound) is rejected at
    the stage "qa" after the same four runs, each stopped at its first frame over the bound."""
    garments, track = _sheet_on_sphere(monkeypatch, 0.006)
    calls = _counting_simulate(monkeypatch)
    options = SimOptions(quality="draft", settle_seconds=0.0, strain_refinements=0,
                         bound_guard=True)
    with pytest.raises(RejectedSequence) as caught:
        simulate_within_bounds(garments, track, options)
    assert [(c.quality, c.substeps) for c in calls] == [
        ("draft", None), ("default", None), ("reference", None), ("reference", 80)]
    exc = caught.value
    assert exc.stage == "qa" and exc.runs == 4
    assert exc.reason.startswith(
        "fabric springs strained beyond their fabric's max_strain (qa/over_strain_share ")
    assert exc.reason.count("the run stopped there") == 4
    assert "; simulated again at reference 80x16, sor 1, after the runs at xpbd draft 10x2" \
        in exc.reason
    last = _first_frame_over(garments, track, replace(calls[-1], bound_guard=False))
    assert exc.frames == (last, last)


def test_a_sequence_over_its_bound_on_every_rung_is_rejected_naming_every_run(monkeypatch):
    """At a 0.6 % bound every rung ends over it (measured: draft 0.0158, default with plain
    sweeps 0.0083, reference 0.0065, and the reference's steps doubled, the rung past the top
    preset, 0.0061): the last run is the result, and the gate rejects it naming every run."""
    garments, track = _sheet_on_sphere(monkeypatch, 0.006)
    calls = _counting_simulate(monkeypatch)
    options = SimOptions(quality="draft", settle_seconds=0.0, strain_refinements=0)
    result = simulate_within_bounds(garments, track, options)
    assert [(c.quality, c.substeps) for c in calls] == [
        ("draft", None), ("default", None), ("reference", None), ("reference", 80)]
    assert (result.report["substeps"], result.report["iterations"]) == (80, 16)
    assert qa.breaches(result.qa)
    record = SequenceRecord(spec=SceneSpec(0, 0, "seq"), status="ok", garments=garments,
                            sim=result, sim_runs=simulation_runs(result))
    assert record.sim_runs == 4
    rejected = reject_over_qa_bounds(record)
    assert rejected.status == "rejected" and rejected.stage == "qa"
    assert rejected.sim_runs == 4  # the gate's record still says what the sequence cost
    assert rejected.reason.startswith(
        "fabric springs strained beyond their fabric's max_strain (qa/over_strain_share ")
    # The gate says where, from the frame's stored positions, as a guarded run does.
    assert re.match(r"[^;]*; the cotton sheet 'sheet', [1-9][0-9]* springs over\); simulated",
                    rejected.reason), rejected.reason
    assert ("; simulated again at reference 80x16, sor 1, after the runs at xpbd draft 10x2, "
            "sor 1.6 (fabric springs strained beyond their fabric's max_strain "
            "(qa/over_strain_share 0.") in rejected.reason
    assert "), at xpbd default 20x4, sor 1 (fabric springs strained" in rejected.reason
    # Every run, the dropped ones too, says where: four times the sheet.
    assert len(re.findall(r"; the cotton sheet 'sheet', [1-9][0-9]* springs over\)",
                          rejected.reason)) == 4, rejected.reason
    assert ") and at xpbd reference 40x8, sor 1 (fabric springs strained" in rejected.reason
    # From steps the caller gave there is nothing to escalate to: one run, its breach as it is.
    calls.clear()
    given = simulate_within_bounds(garments, track, replace(options, substeps=20, iterations=4))
    assert len(calls) == 1 and "escalated_from" not in given.report


def _stiff_hanging_sheet(monkeypatch, stiffer: float):
    """A sheet `stiffer` times stiffer than cotton hanging from two corners, for the explicit
    solver, with retries off so that instability rejects. Measured: 100 times is unstable at
    the draft preset's 200 substeps (533 m/s in the first frame) and stable at the default's
    400; 200 times is unstable at both (620 and 899 m/s)."""
    cotton = FABRICS["cotton"]
    monkeypatch.setitem(FABRICS, "cotton", replace(cotton, stretch=stiffer * cotton.stretch,
                                                   shear=stiffer * cotton.shear))
    monkeypatch.setattr(sim_module, "MAX_RETRIES", 0)
    sheet = grid_sheet(8, 0.3, 1.0)
    sheet.pinned = np.array([0, 8])
    return [sheet], SimOptions(solver="explicit", quality="draft", frames=20,
                               settle_seconds=0.0, strain_refinements=0)


def test_a_run_rejected_as_unstable_is_simulated_again_one_preset_up(monkeypatch):
    garments, options = _stiff_hanging_sheet(monkeypatch, 100.0)
    result = simulate_within_bounds(garments, None, options)
    assert (result.report["quality"], result.report["substeps"]) == ("default", 400)
    first = result.report["escalated_from"]
    assert first["settings"] == "explicit draft 200x1, sor 1"
    assert first["reason"].startswith("unstable at frame 1: runaway velocity")
    assert first["wall_time_s"] is None  # a rejected run has no result to time
    assert np.isfinite(result.vertices[garments[0].name]).all()


def test_a_run_unstable_on_every_rung_is_rejected_naming_every_run(monkeypatch):
    """A sheet 100,000 times stiffer than cotton is unstable for the explicit solver on every
    rung, the top preset's 2000 substeps doubled included: the rejection names every run."""
    garments, options = _stiff_hanging_sheet(monkeypatch, 1e5)
    with pytest.raises(RejectedSequence) as info:
        simulate_within_bounds(garments, None, options)
    assert info.value.stage == "simulate"
    # Four runs (draft, default, reference, the reference's steps doubled), also after the
    # trip to the parent process a dataset's worker sends it on, and on the rejected record.
    assert info.value.runs == 4 and pickle.loads(pickle.dumps(info.value)).runs == 4
    record = SequenceRecord(spec=SceneSpec(0, 0, "seq"), status="ok", garments=garments)
    mark_rejected(record, info.value)
    assert record.sim_runs == 4 and record.garments is None
    message = info.value.reason
    assert message.startswith("unstable at frame 1: ")
    assert ("; simulated again at reference 4000x2, sor 1, after the runs at explicit draft "
            "200x1, sor 1 (unstable at frame 1: ") in message
    assert "), at explicit default 400x1, sor 1 (unstable at frame 1: " in message
    assert ") and at explicit reference 2000x1, sor 1 (unstable at frame 1: " in message


def test_the_manifest_says_which_sequences_were_simulated_again(tmp_path):
    from datagen.pipeline.dataset import manifest_rows

    plain, again = sf.make_record(0).record, sf.make_record(1).record
    why = ("fabric springs strained beyond their fabric's max_strain (qa/over_strain_share "
           "0.002 at frame 32, bound 0.001)")
    again.sim.report["escalated_from"] = {"settings": "xpbd default 20x4, sor 1.6",
                                          "reason": why, "wall_time_s": 25.0}
    sf.write_shard(tmp_path / "shard-00000.h5", [plain, again])
    rows = {row["index"]: row for row in manifest_rows(tmp_path)}
    assert rows[0]["escalated"] is None
    assert rows[1]["escalated"] == why


def test_a_batch_result_is_judged_as_a_run_of_its_own(monkeypatch):
    """A dataset run's batch (datagen.pipeline.batched) hands each scene's outcome to
    simulate_within_bounds, which judges it without simulating it again: within the bound it
    is the batch's result; over it, the scene is simulated again alone one preset up, exactly
    as an unbatched run would be; a scene the batch rejected is simulated again too."""
    from datagen.sim.batch import BatchScene, simulate_batch

    garments, track = _sheet_on_sphere(monkeypatch, 0.02)
    options = SimOptions(settle_seconds=0.0, strain_refinements=0)
    outcomes = simulate_batch([BatchScene(garments, track)] * 2, options)
    calls = _counting_simulate(monkeypatch)
    result = simulate_within_bounds(garments, track, options, first=outcomes[1])
    assert [c.quality for c in calls] == ["reference"]  # the first run was the batch's
    assert "batch" not in result.report
    assert "qa/over_strain_share" in result.report["escalated_from"]["reason"]
    direct = simulate(garments, track, options.escalated())
    np.testing.assert_array_equal(result.vertices[garments[0].name],
                                  direct.vertices[garments[0].name])

    # The bound is each spring's fabric's as simulated: at cotton's own 0.25 the batch's run
    # keeps it and is the result.
    monkeypatch.setitem(FABRICS, "cotton", replace(FABRICS["cotton"], max_strain=0.25))
    within = simulate_batch([BatchScene(garments, track)] * 2, options)
    calls.clear()
    kept = simulate_within_bounds(garments, track, options, first=within[1])
    assert calls == [] and kept is within[1] and kept.report["batch"]["index"] == 1

    unstable = RejectedSequence("simulate", "unstable at frame 3: runaway velocity", (3, 3))
    again = simulate_within_bounds(garments, track, options, first=unstable)
    assert [c.quality for c in calls] == ["reference"]
    assert again.report["escalated_from"] == {
        "settings": "xpbd default 20x4, sor 1.6",
        "reason": "unstable at frame 3: runaway velocity", "wall_time_s": None}


def test_simulate_writes_a_scene_over_a_bound_but_warns_that_a_dataset_would_reject_it(
        tmp_path, monkeypatch):
    """`datagen simulate` keeps the scene it was asked for, but where the kept run still breaks
    a QA bound it says so (on stderr, naming the bound, the value and the frame) instead of
    reporting it as if it were dataset-grade. Here the simulation is the shard factory's
    record, in a user's fabric, with the share of springs over that fabric's max_strain that a
    run would have measured (the test is about the command's report)."""
    from click.testing import CliRunner

    import datagen.body.anny_model as anny_model
    import datagen.pipeline.stages as stages
    from datagen.cli import main

    fabrics = tmp_path / "fabrics.yaml"
    fabrics.write_text("fabrics:\n  strict:\n    base: cotton\n    max_strain: 0.05\n")
    monkeypatch.setattr(anny_model, "default_body_model", lambda: None)

    def run(over_share: float, name: str):
        record = sf.make_record(0).record
        record.sim.qa["over_strain_share"][9] = over_share
        record.sim.report["simulated_seconds_per_wall_second"] = 1.0
        for g in record.garments:
            g.fabric = "strict"
        monkeypatch.setattr(stages, "run_sequence", lambda spec, model, fabrics=None: record)
        out = tmp_path / f"{name}.h5"
        result = CliRunner().invoke(main, ["simulate", "--fabrics-file", str(fabrics),
                                           "--fabric", "strict", "--out", str(out)])
        assert result.exit_code == 0, result.output
        assert out.exists()
        return result

    over = run(0.002, "over")
    assert ("breaks a QA bound, and a dataset run would reject this scene (stage qa): fabric "
            "springs strained beyond their fabric's max_strain (qa/over_strain_share 0.002 at "
            "frame 9, bound 0.001)") in over.stderr
    assert "0.200 % of springs over their fabric's max_strain" in over.output
    assert "warning" not in run(0.0009, "within").stderr


def test_the_gate_says_where_a_finished_run_breaks_the_strain_bound():
    """A finished run over the strain bound (a batch's, or `datagen simulate`'s) is judged from
    its stored frames: the shard factory's record with its upper garment blown up 50 % about
    its centre at frame 4 (its springs' strain there lies within -4.3 % and +2.6 %, so blown
    up each is at least 43 % long, past cotton's 0.25; at 30 %, 7 of 660 stayed within it) and
    its body's vertices all of the chest. The gate names that garment, every one of its
    fabric springs, and the chest; the lower garment, unstrained, is not named."""
    from datagen.pipeline.stages import over_qa_bounds
    from datagen.sim.model import build_cloth_model

    record = sf.make_record(0).record
    record.body.rest.part_labels[:] = 9  # PART_NAMES[9]: chest
    upper = next(g for g in record.garments if g.name == "upper")
    frames = record.sim.vertices["upper"]
    centre = frames[4].mean(axis=0)
    frames[4] = centre + 1.5 * (frames[4] - centre)
    record.sim.qa["over_strain_share"][4] = 1.0
    springs = len(build_cloth_model([(upper, FABRICS[upper.fabric])]).fabric_strain_terms[0])
    found, reason = over_qa_bounds(record)
    assert [b.series for b in found] == ["over_strain_share"]
    assert (f"(qa/over_strain_share 1 at frame 4, bound 0.001; the {upper.fabric} "
            f"{upper.category} 'upper', {springs} springs over, nearest chest 100 %)") in reason


def _falling_top(frames: int = 12):
    """A small cotton "top" falling freely from rest, its neckline its centre vertex, fitted
    0.1 m beside a neck joint that stays put, far above a small sphere it never reaches. After
    a fall of d that vertex lies sqrt(0.1^2 + d^2) from the joint against 0.1 m in the fit, so
    its slip passes the 0.2 m bound past d = 0.283 m. n substeps of h fall g h^2 n (n + 1) / 2
    (semi-implicit Euler from rest; air drag is off): at 20 substeps a frame (h = 1/600 s)
    0.269 m by output frame 7 and 0.351 m by frame 8, at 40 0.268 and 0.350, so at both presets
    output frame 8 is the first past the bound (a slip of 0.26)."""
    top = replace(grid_sheet(8, 0.2, 1.0, name="upper"), category="top",
                  loops={"neck": np.array([40])})  # the centre of the 9 x 9 grid
    sv, sfaces = icosphere(0.1, 1)
    neck = np.array([0.1, 0.0, 1.0])
    track = ColliderTrack(np.repeat((sv + [0.0, 0.0, -5.0])[None], frames + 1, axis=0), sfaces,
                          np.ones(len(sfaces), dtype=bool),
                          neck=np.repeat(neck[None], frames + 1, axis=0), rest_neck=neck)
    return [top], track, SimOptions(settle_seconds=0.0, effects=("auto", "-air_drag"))


SLID_REASON = (r"the top's neckline slid off the shoulders \(qa/neckline_slip 0\.2\d+ at frame 8, "
               r"bound 0\.2\); the run stopped there")


def test_the_neckline_guard_stops_a_run_at_the_frame_a_garment_slid_off():
    """With the guard (what a dataset whose recipe rejects asks for) the run stops at the
    first output frame past the neckline bound, naming it as the dataset's gate does; without
    it the run goes to its end and the gate's measure finds the garment off at its worst,
    last frame. The stop survives the trip from a dataset's worker process."""
    from datagen.errors import SlidOffShoulders
    from datagen.pipeline.stages import slid_off_in

    garments, track, options = _falling_top()
    with pytest.raises(SlidOffShoulders) as info:
        simulate(garments, track, replace(options, neckline_guard=True))
    assert info.value.stage == "qa" and info.value.frames == (8, 8)
    assert re.fullmatch(SLID_REASON, info.value.reason), info.value.reason
    back = pickle.loads(pickle.dumps(info.value))
    assert isinstance(back, SlidOffShoulders) and back.reason == info.value.reason
    whole = simulate(garments, track, options)
    assert whole.vertices["upper"].shape[0] == 13
    (breach,) = slid_off_in(garments, whole, track)
    assert breach.series == "neckline_slip" and breach.frame == 12
    # By frame 12 (n = 240) it has fallen 0.788 m: a slip of sqrt(0.1^2 + 0.788^2) - 0.1.
    assert breach.value == pytest.approx(0.6943, abs=2e-3)


def test_a_garment_off_the_shoulders_goes_up_the_presets_but_not_past_the_top(monkeypatch):
    """A garment that slid off is simulated again one preset up, as a run over a bound is
    (a coarse run can let a strap slide that finer steps keep on: docs/simulator.md), but not
    past the top preset, whose doubled steps are for the chaotic strain of a kick. This top
    falls at every step: with the guard the sequence is rejected after two runs, each stopped
    where the neckline slid off, naming both; without it the top preset's whole run is the
    result, for the gate to judge, and says why it was simulated again."""
    garments, track, options = _falling_top()
    calls = _counting_simulate(monkeypatch)
    with pytest.raises(RejectedSequence) as info:
        simulate_within_bounds(garments, track, replace(options, neckline_guard=True))
    assert [c.quality for c in calls] == ["default", "reference"]
    assert info.value.stage == "qa" and info.value.runs == 2
    first, again = info.value.reason.split("; simulated again at ")
    assert re.fullmatch(SLID_REASON, first), first
    assert again.startswith("reference 40x8, sor 1, after the run at xpbd default 20x4, sor "
                            "1.6: the top's neckline slid off the shoulders (qa/neckline_slip")
    record = SequenceRecord(spec=SceneSpec(0, 0, "seq"), status="ok", garments=garments)
    mark_rejected(record, info.value)
    assert (record.status, record.stage, record.sim_runs) == ("rejected", "qa", 2)
    calls.clear()
    result = simulate_within_bounds(garments, track, options)
    assert [c.quality for c in calls] == ["default", "reference"]
    assert result.report["quality"] == "reference" and simulation_runs(result) == 2
    assert result.report["escalated_from"]["reason"].startswith(
        "the top's neckline slid off the shoulders (qa/neckline_slip 0.")


def test_a_dataset_that_rejects_guards_necklines_and_one_that_keeps_does_not():
    from datagen.pipeline.dataset import _rejects
    from datagen.pipeline.stages import sim_options_from_spec
    from datagen.recipe import load_recipe

    spec = SceneSpec(0, 0, "seq")
    assert not sim_options_from_spec(spec).neckline_guard
    assert sim_options_from_spec(spec, guards=True).neckline_guard
    default = Path(__file__).parents[1] / "pipelines" / "default.yaml"
    loaded = load_recipe(default)
    assert loaded.recipe.simulation.qa == "reject" and _rejects(loaded)
    keep = replace(loaded.recipe, simulation=replace(loaded.recipe.simulation, qa="keep"))
    assert not _rejects(SimpleNamespace(recipe=keep))
