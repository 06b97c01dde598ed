"""Batches: several scenes in one solver (datagen.sim.batch) give each scene what it gets alone."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from datagen.errors import InputError, RejectedSequence
from datagen.sim.batch import BatchScene, lay_out, simulate_batch
from datagen.sim.simulate import SimOptions, simulate
from datagen.study.scenes import mirrored_track, sheet_sphere, tube_cylinder

sys.path.insert(0, str(Path(__file__).parent))  # fold_scenes

FRAMES = 6
OPTIONS = SimOptions(solver="xpbd", frames=FRAMES, profile_every=0, settle_seconds=0.0,
                     effects="auto,-self_collision")


def batch_scenes() -> list[BatchScene]:
    """Three different scenes: a cotton tube, a denim tube swung the other way, a falling sheet
    (no pins, a static collider). Also run on two threads by tests/parallel_sweeps.py."""
    cotton = tube_cylinder("cotton", "coarse", frames=FRAMES)
    denim = tube_cylinder("denim", "coarse", frames=FRAMES)
    sheet = sheet_sphere("cotton", "coarse", frames=FRAMES)
    return [BatchScene(cotton.garments, cotton.track),
            BatchScene(denim.garments, mirrored_track(denim.track)),
            BatchScene(sheet.garments, sheet.track)]


@pytest.fixture(scope="module")
def scenes() -> list[BatchScene]:
    return batch_scenes()


def batched_against_alone(scenes: list[BatchScene]) -> list[tuple]:
    """Per scene: its result in the batch, its run alone moved where the batch puts it, and the
    largest distance between the two (moved back) in any frame. Also run on two threads by
    tests/parallel_sweeps.py."""
    layout = lay_out(scenes)
    rows = []
    for scene, result, shift in zip(scenes, simulate_batch(scenes, OPTIONS), layout.offsets,
                                    strict=True):
        garments = [replace(g, vertices=g.vertices + shift) for g in scene.garments]
        alone = simulate(garments, replace(scene.track, vertices=scene.track.vertices + shift),
                         OPTIONS)
        name = scene.garments[0].name
        moved_back = (alone.vertices[name] - shift).astype(np.float32)
        rows.append((result, alone, float(np.abs(result.vertices[name] - moved_back).max())))
    return rows


def test_each_scene_of_a_batch_is_the_scene_simulated_alone(scenes):
    """The batch's cells keep the scenes apart, so nothing of one reaches another: each tube is
    bit for bit the tube simulated alone at the same place, its QA series its own. The sheet,
    which alone has a collider at rest and no pins, shares the batch's moving collider (once it
    reaches its sphere, its contact searches run at other substeps): within microns."""
    layout = lay_out(scenes)
    for a in range(3):  # cells side by side, none overlapping another
        for b in range(a):
            apart = (layout.cells[a, 0] >= layout.cells[b, 1] - 1e-9) | (
                layout.cells[b, 0] >= layout.cells[a, 1] - 1e-9)
            assert apart.any()
    rows = batched_against_alone(scenes)
    for k, (scene, (result, alone, gap)) in enumerate(zip(scenes, rows, strict=True)):
        assert result.report["batch"] == {"scenes": 3, "index": k, "alone": False,
                                          "batch_vertices": sum(
                                              len(g.vertices) for s in scenes
                                              for g in s.garments)}
        name = scene.garments[0].name
        assert result.garment_names == [name]
        if k < 2:
            assert gap == 0.0
            for series, values in alone.qa.items():
                np.testing.assert_array_equal(result.qa[series], values, err_msg=series)
        else:
            assert gap < 2e-5
        # Where the scene was given, not where the batch put it: the cloth starts there.
        np.testing.assert_allclose(result.vertices[name][0], scene.garments[0].vertices,
                                   atol=1e-6)


def test_a_scene_that_leaves_its_cell_has_the_batch_simulated_again_scene_by_scene(scenes):
    """With cells barely wider than the scenes, the swinging tubes' hems reach past their cells'
    edges: the batch is not trusted, and every scene is simulated alone, which its report says."""
    pair = scenes[:2]
    results = simulate_batch(pair, OPTIONS, margin=0.21)
    for k, result in enumerate(results):
        batch = result.report["batch"]
        assert batch["alone"] and batch["index"] == k
        assert "left their lattice cells" in batch["why"]
        alone = simulate(pair[k].garments, pair[k].track, OPTIONS)
        np.testing.assert_array_equal(result.vertices["tube"], alone.vertices["tube"])


def test_scenes_that_cannot_share_a_solver_are_refused_naming_the_scene(scenes):
    slow = replace(scenes[1].track, fps=25.0)
    with pytest.raises(InputError, match=r"scenes\[1\]\.track\.fps.*30\.0.*25\.0"):
        simulate_batch([scenes[0], BatchScene(scenes[1].garments, slow)], OPTIONS)
    # The tubes (skirt-like) call for self-collision, the sheet does not: one solver cannot run
    # both, and the effects that act on every vertex must agree.
    with pytest.raises(InputError, match=r"scenes\[2\] effects.*self_collision"):
        simulate_batch(scenes, replace(OPTIONS, effects="auto"))
    with pytest.raises(InputError, match=r"scenes\[0\]\.garments.*unique garment names"):
        twice = scenes[0].garments * 2
        simulate_batch([BatchScene(twice, scenes[0].track)], OPTIONS)


def test_each_scene_is_guarded_against_its_own_collider_and_a_bad_one_costs_the_others_time(
        scenes):
    """The runaway guards allow a scene's cloth 3x its own collider's fastest speed (or the
    limit given), and kinetic energy to match (an RMS speed of half that): the sheet over its
    static sphere is held to 2 m/s, whose kinetic-energy bound its free fall breaks at frame 4
    (1.3 m/s), while the tube beside it swings with its cylinder (3.3 m/s allowed: against that,
    as the batch's fastest collider, the sheet would pass these 4 frames). The batch is rejected
    naming the sheet's scene; simulated alone, the tube passes and the sheet is rejected."""
    def first_frames(scene: BatchScene) -> BatchScene:
        track = scene.track
        return BatchScene(scene.garments, replace(track, vertices=track.vertices[:5]))

    pair = [first_frames(scenes[0]), first_frames(scenes[2])]
    options = replace(OPTIONS, speed_limit=2.0, frames=4)
    tube, sheet = simulate_batch(pair, options)
    assert isinstance(sheet, RejectedSequence) and "kinetic energy blow-up" in sheet.reason
    assert tube.report["batch"]["alone"]
    assert "scene 1: kinetic energy blow-up" in tube.report["batch"]["why"]
    alone = simulate(pair[0].garments, pair[0].track, options)
    np.testing.assert_array_equal(tube.vertices["tube"], alone.vertices["tube"])


@pytest.mark.parametrize("n_cells", [1, 1023, 1024, 1025, 5000])
def test_the_collider_grids_blocked_prefix_sum_is_the_running_total(n_cells):
    """The body grid's cell offsets come from a prefix sum in blocks (summed in parallel, the
    blocks' sums prefixed, the blocks filled in parallel), which a batch's lattice of millions
    of cells needs on a GPU: the offsets are the running total of the counts at every size
    around a block's edge, the total last, and the counts are cleared for the next frame."""
    import taichi as ti

    from datagen.sim import grid_kernels as GK
    from datagen.sim.backend import init_taichi

    init_taichi()
    counts_np = np.random.default_rng(n_cells).integers(0, 4, n_cells).astype(np.int32)
    counts_np[: min(n_cells, 1100) // 2] = 0  # a run of empty cells across a block's edge
    counts, starts = ti.ndarray(ti.i32, n_cells + 3), ti.ndarray(ti.i32, n_cells + 4)
    counts.from_numpy(np.concatenate([counts_np, [7, 7, 7]]).astype(np.int32))
    blocks = ti.ndarray(ti.i32, n_cells // GK.PREFIX_BLOCK + 2)
    GK.grid_prefix(counts, starts, n_cells, blocks)
    expected = np.concatenate([[0], np.cumsum(counts_np)])
    np.testing.assert_array_equal(starts.to_numpy()[: n_cells + 1], expected)
    np.testing.assert_array_equal(counts.to_numpy(), [0] * n_cells + [7, 7, 7])



def test_a_hashed_body_grid_gives_the_batch_the_dense_grids_contacts(scenes, monkeypatch):
    """A grid over more cells than DENSE_GRID_CELLS is hashed (a batch of long walks would need
    billions of dense cells): forced here, with one bucket per triangle so that many cells
    share a bucket, the batch runs on a table of 16,384 buckets and each scene is the
    dense grid's run (the tubes bit for bit; the sheet, whose vertices can be equally near two
    triangles of the sphere, which the hashed grid breaks by index, within microns)."""
    from datagen.sim import collider as collider_module

    dense = simulate_batch(scenes, OPTIONS)
    grids = []
    build = collider_module.BodyCollider._build_grid

    def spy(self):
        build(self)
        grids.append((self.hashed, int(self.dims_np[1]) + 1))

    monkeypatch.setattr(collider_module, "DENSE_GRID_CELLS", 0)
    monkeypatch.setattr(collider_module, "HASH_BUCKETS_PER_TRIANGLE", 1)
    monkeypatch.setattr(collider_module.BodyCollider, "_build_grid", spy)
    hashed = simulate_batch(scenes, OPTIONS)
    assert grids and all(h for h, _ in grids)
    assert max(n for _, n in grids) <= 16384
    for k, (scene, a, b) in enumerate(zip(scenes, dense, hashed, strict=True)):
        name = scene.garments[0].name
        gap = np.abs(a.vertices[name] - b.vertices[name]).max()
        assert gap == 0.0 if k < 2 else gap < 2e-5, (k, gap)


def test_a_batch_looks_up_each_scenes_folding_parts_in_its_own_fields():
    """A part folding onto cloth from beyond a grid cell is caught by its distance field
    (datagen.sim.fold_fields; alone: tests/test_sim_physics.py). In a batch every scene's
    fields ride in one table, each scene's parts numbered apart and its fields' frames moved
    with it (where the batch puts it): two plates folding onto two trouser legs side by side
    swallow none of either leg, as each does alone; joined without the fields, both legs are
    swallowed."""
    from fold_scenes import plate_folding_onto_trouser_leg

    options = SimOptions(settle_seconds=0.0, strain_refinements=0)
    pair = [plate_folding_onto_trouser_leg(fold=True) for _ in range(2)]
    scenes = [BatchScene([p.leg], p.track) for p in pair]
    for p, result in zip(pair, simulate_batch(scenes, options), strict=True):
        assert not result.report["batch"]["alone"]
        assert max(p.swallowed(result.vertices[p.leg.name])) == 0
    blind = [BatchScene(s.garments, replace(s.track, fold_fields=None)) for s in scenes]
    for p, result in zip(pair, simulate_batch(blind, options), strict=True):
        assert max(p.swallowed(result.vertices[p.leg.name])) > 100
