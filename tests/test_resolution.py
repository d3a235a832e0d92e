"""The bag-resolution study (benchmarks/resolution.py): its parsing, the comparison against the finest stable
resolution, the common surface points, and one small run in Newton on the CPU (slow)."""

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from benchmarks import resolution
from tests.conftest import load_params
from wc.config import load_section
from wc.report_kinds import kind_of
from wc.scene.config import SceneConfig
from wc.scene.resample import surface_map
from wc.scene.scene import build_scene

ROOT = Path(__file__).resolve().parents[1]


def test_a_resolution_is_a_vertex_count_with_its_own_overrides():
    assert resolution.parse_resolution("1200") == (1200, [])
    assert resolution.parse_resolution("5000:sim.bag.particle_radius_m=0.002,sim.iterations=40") == (
        5000, ["sim.bag.particle_radius_m=0.002", "sim.iterations=40"])
    for bad in ("", "many", "2", "300:radius"):
        with pytest.raises(argparse.ArgumentTypeError):
            resolution.parse_resolution(bad)


def test_common_points_lie_on_the_bag_and_repeat_with_their_seed():
    params = load_params()
    a, b = (resolution.common_points(params, 50, seed=3) for _ in range(2))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, resolution.common_points(params, 50, seed=4))
    bag = build_scene(load_section(params, "scene", SceneConfig)).objects["bag"]
    on_surface = surface_map(bag.vertices, bag.faces, a).apply(bag.vertices)  # a point's closest surface point
    np.testing.assert_allclose(on_surface, a, atol=1e-9)


def test_frames_and_distances():
    assert list(resolution.frame_indices(10, 3)) == [0, 4, 9]
    a = {1: np.zeros((4, 2, 3), np.float32), 2: np.zeros((3, 2, 3), np.float32)}
    b = {1: np.full((5, 2, 3), 0.001, np.float32), 3: np.zeros((3, 2, 3), np.float32)}
    assert resolution.mean_distance_mm(a, b) == pytest.approx(np.sqrt(3.0), rel=1e-5)  # seed 1 alone, 4 frames
    assert resolution.mean_distance_mm(a, {3: b[3]}) is None


def _measured(verdicts: dict[int, str], offset_m: float) -> resolution.Measured:
    m = resolution.Measured()
    m.verdicts = dict(verdicts)
    m.points = {s: np.full((3, 2, 3), offset_m, np.float32) for s in verdicts}
    return m


def _row(vertices: int, stable: bool, floor_mm: float | None) -> dict:
    return {"vertices": vertices, "stable": stable, "noise_floor_mm": floor_mm}


def test_the_reference_is_the_finest_stable_and_the_needed_the_coarsest_that_matches_it():
    ok = {1: "accepted", 2: "accepted", 3: "not_lifted"}
    rows = [_row(300, True, 0.5), _row(1200, True, 0.5), _row(5000, True, 2.0), _row(20000, False, None)]
    measured = [_measured(ok | {3: "accepted"}, 0.0),  # a verdict off: agreement 2/3
                _measured(ok, 0.001),  # same verdicts, sqrt(3) mm from the reference: within its 2 mm floor
                _measured(ok, 0.0), _measured({1: "blow_up", 2: "blow_up", 3: "blow_up"}, 0.5)]
    assert resolution.compare(rows, measured, agreement=0.95) == 1200
    assert [r["reference"] for r in rows] == [False, False, True, False]
    assert rows[0]["verdict_agreement"] == pytest.approx(2 / 3)
    assert rows[1]["rms_mm"] == pytest.approx(np.sqrt(3.0), rel=1e-5) and rows[1]["within_noise"]
    rows[2]["noise_floor_mm"] = 1.0  # a quieter reference: 1,200 is no longer within it, so it needs itself
    assert resolution.compare(rows, measured, agreement=0.95) == 5000
    unstable = [_row(300, False, None)]
    assert resolution.compare(unstable, measured[:1], agreement=0.95) is None
    assert unstable[0]["verdict_agreement"] is None


@pytest.mark.slow
def test_two_resolutions_of_a_bag_drop_are_compared(tmp_path):
    out = tmp_path / "resolution.json"
    resolution.main(["--params", str(ROOT / "params.yaml"), "--set", "sim.worlds=2", "--task", "bag_drop",
                     "--plans", "2", "--resolution", "160", "--resolution", "100", "--points", "32",
                     "--image-plans", "1", "--image-frames", "2", "--image-px", "16", "--out", str(out)])
    report = json.loads(out.read_text())
    rows = report["rows"]
    assert [r["vertices"] for r in rows] == sorted(r["vertices"] for r in rows) and len(rows) == 2
    assert all(r["plans"] == 2 and sum(r["verdicts"].values()) == 2 for r in rows)
    assert all(r["newton_s_per_episode"] > 0 and r["noise_floor_mm"] > 0 for r in rows)
    reference = [r for r in rows if r["reference"]]
    if reference:  # the finest stable: its distance to itself is nil, its verdicts agree with themselves
        assert reference[0]["rms_mm"] == 0.0 and reference[0]["verdict_agreement"] == 1.0
        assert reference[0]["image_diff"] == {"top": 0.0, "wrist": 0.0}
        assert report["needed_vertices"] in [r["vertices"] for r in rows]
    assert out.with_suffix(".md").exists() and out.with_suffix(".png").exists()
    line = kind_of("resolution_cpu.json").headline(report, "resolution_cpu.json")
    assert f"(needed: {report['needed_vertices']})" in line and f"{rows[0]['vertices']} vertices: " in line
