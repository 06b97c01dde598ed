"""The hand-offs between benchmarks: bench_gpu sets a GPU batch against Blender through the
peer rows bench_sim wrote, which hold only for the simulator sources both ran."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_gpu, bench_sim


def test_gpu_report_reads_the_peer_rows_of_the_same_sources_and_refuses_others(
        tmp_path, monkeypatch):
    rows = [{"scene": "tube_cylinder 5k", "fabric": "denim", "ours_s_per_sim_s": 1.39,
             "blender_s_per_sim_s": 5.42, "blender_err_mm": 35.56}]
    peer = tmp_path / "sim_peer.json"
    peer.write_text(json.dumps({"date": "2026-11-27", "source": "aaaa", "rows": rows}))
    monkeypatch.setattr(bench_sim, "PEER_JSON", peer)
    date, table = bench_gpu.blender_rows("aaaa")
    assert date == "2026-11-27"
    assert table == {("tube_cylinder 5k", "denim"): {"ours": 1.39, "blender": 5.42,
                                                     "blender_error_mm": 35.56}}
    with pytest.raises(SystemExit, match="sim_peer.json: field 'source'.*aaaa.*bbbb"):
        bench_gpu.blender_rows("bbbb")


def test_the_committed_peer_rows_cover_every_peer_scene():
    data = json.loads(bench_sim.PEER_JSON.read_text())
    keys = {(r["scene"], r["fabric"]) for r in data["rows"]}
    assert keys == {(f"{scene} {res}", fabric) for scene, res in bench_sim.PEER_SCENES
                    for fabric in bench_sim.FABRICS}
    assert all(r["blender_err_mm"] > 0 and r["ours_s_per_sim_s"] > 0 for r in data["rows"])
