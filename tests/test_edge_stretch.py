"""wc.validate.edge_stretch: per-frame edge strains of a two-triangle sheet with a known stretch, an edge subset, the
pooled summary, the blow-up check's own strain, and errors that name the problem; benchmarks.fabric_stretch on one
lift_handle plan (slow)."""

import json

import numpy as np
import pytest

from benchmarks import fabric_stretch
from tests.conftest import ROOT
from wc.report_kinds import report_headline
from wc.validate.edge_stretch import RestEdges, group_edges, stretch_summary

# unit square, two triangles: edges (0,1) (0,2) (0,3) (1,2) (2,3), the diagonal (0,2) of length sqrt(2)
SQUARE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
FACES = np.array([[0, 1, 2], [0, 2, 3]])


def test_strains_of_a_sheet_stretched_along_x():
    rest = RestEdges.of_mesh(SQUARE, FACES)
    assert rest.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    assert rest.length == pytest.approx([1.0, np.sqrt(2), 1.0, 1.0, 1.0])
    x = np.stack([SQUARE, SQUARE * [1.1, 1.0, 1.0]])  # frame 1: 10 % longer along x
    strain = rest.strains(x)
    assert strain.shape == (2, 5)
    assert strain[0] == pytest.approx(0.0)
    assert strain[1] == pytest.approx([0.1, np.sqrt(1.21 + 1) / np.sqrt(2) - 1, 0.0, 0.0, 0.1])


def test_group_edges_keeps_edges_with_both_ends_in_the_group():
    rest = RestEdges.of_mesh(SQUARE, FACES)
    assert group_edges(rest.edges, [1, 2, 3]).tolist() == [False, False, False, True, True]
    assert not group_edges(rest.edges, []).any()


def test_summary_pools_the_samples():
    strain = np.array([[0.0, 0.1], [0.02, 0.2]])
    s = stretch_summary(strain, limit=0.05)
    assert s["max"] == pytest.approx(0.2) and s["p50"] == pytest.approx(np.median(strain))
    assert s["p99"] == pytest.approx(np.percentile(strain, 99)) and s["p90"] <= s["p99"] <= s["max"]
    assert s["share_above_limit"] == pytest.approx(0.5) and s["samples"] == 4 and s["limit"] == 0.05
    assert stretch_summary(np.zeros((0, 3))) is None


def test_max_strain_is_the_blow_up_checks():
    """The per-edge strains' frame max equals the strain validate.blow_up bounds."""
    from wc.validate.predicates import Episode, speed_and_strain

    class Mesh:
        vertices, faces = SQUARE, FACES

    class Scene:
        objects = {"sheet": Mesh}

        @staticmethod
        def vertex_slices():
            return {"sheet": slice(0, 4)}

    rng = np.random.default_rng(0)
    x = SQUARE + rng.normal(0.0, 0.05, (3, 4, 3))
    _, strain = speed_and_strain(Scene, Episode(x, np.zeros_like(x), np.zeros((3, 14)), np.zeros((3, 0, 7)), 0.04))
    assert RestEdges.of_mesh(SQUARE, FACES).strains(x).max(axis=1) == pytest.approx(strain)


@pytest.mark.parametrize("call, message", [
    (lambda: RestEdges.of_mesh(SQUARE[:, :2], FACES), "rest vertices must be finite"),
    (lambda: RestEdges.of_mesh(SQUARE, FACES + 2), "face indices must lie in"),
    (lambda: RestEdges.of_mesh(np.zeros((4, 3)), FACES), "zero length"),
    (lambda: RestEdges.of_mesh(SQUARE, FACES).strains(SQUARE), r"must be \(T, N, 3\)"),
    (lambda: RestEdges.of_mesh(SQUARE, FACES).strains(SQUARE[None, :3]), "the edges need 4"),
    (lambda: RestEdges.of_mesh(SQUARE, FACES).strains(np.stack([SQUARE, SQUARE * np.nan])), r"first 1\)"),
    (lambda: group_edges(np.zeros((3, 3)), [0]), r"edges must be \(E, 2\)"),
    (lambda: stretch_summary(np.array([0.1, np.inf])), "1 strains are not finite"),
])
def test_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_a_setting_splits_at_the_commas_that_start_a_key():
    assert fabric_stretch.parse_setting("sim.bag.tri_ke=1e4, sim.bag.tri_ka=1e4") == ["sim.bag.tri_ke=1e4",
                                                                                     "sim.bag.tri_ka=1e4"]
    assert fabric_stretch.parse_setting("a.b=[1, 2],c=3") == ["a.b=[1, 2]", "c=3"]
    with pytest.raises(Exception, match="key=value"):
        fabric_stretch.parse_setting("1e4")


def test_a_setting_labels_its_chart_column_one_override_per_line():
    setting = "sim.bag.tri_ke=1e4,scene.robot.left_base_xyz_yaw_deg=[-0.75, 0.0] (plans of seed 1)"
    label = fabric_stretch.tick_label(setting)
    assert label.splitlines() == ["bag.tri_ke=1e4", "robot.left_base_xyz_yaw_deg", "=[-0.75, 0.0]", "(plans of seed 1)"]
    assert fabric_stretch.tick_label("params as given") == "params as given"


@pytest.mark.slow
def test_one_lift_handle_plan_is_measured(tmp_path):
    out = tmp_path / "fs.json"
    fabric_stretch.main(["--params", str(ROOT / "params.yaml"), "--set", "tasks.lift_handle.hold_s=0.2",
                         "--task", "lift_handle", "--plans", "1", "--settings", "sim.bag.tri_ke=1000.0",
                         "--out", str(out)])
    row, = json.loads(out.read_text())["settings"]
    assert row["plans"] == 1 and sum(row["verdicts"].values()) == 1 and row["tri_ke"] == 1000.0
    every = row["stretch"]["all_frames"]
    for summary in (every["all"], every["handles"]):
        figures = [summary[k] for k in ("p50", "p90", "p99", "max", "share_above_limit")]
        assert np.isfinite(figures).all() and min(figures) >= -1, summary
        assert summary["p50"] <= summary["p90"] <= summary["p99"] <= summary["max"]
    assert every["handles"]["samples"] < every["all"]["samples"]
    episode, = row["episodes"]
    print(f"lift_handle: {episode['frames']} frames, {row['rollout_s_per_episode']:.1f} s rollout, verdict "
          f"{episode['verdict']}, lifted frames {episode['lifted_frames']}")
    assert "| sim.bag.tri_ke=1000.0 |" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 0


def test_the_results_page_headline_reads_each_setting(tmp_path):
    lifted = {"p50": 0.01, "p90": 0.03, "p99": 0.151, "max": 0.362, "limit": 0.05, "share_above_limit": 0.04,
              "samples": 10}
    rows = [{"setting": "sim.bag.tri_ke=1000.0", "iterations": 20, "accepted": 1.0,
             "stretch": {"lifted": {"all": lifted}}},
            {"setting": "sim.bag.tri_ke=30000.0", "iterations": 20, "plans": 0, "accepted": None}]
    path = tmp_path / "fabric_stretch_test.json"
    path.write_text(json.dumps({"settings": rows}))
    kind, line = report_headline(path)
    assert kind == "fabric stretch"
    assert "sim.bag.tri_ke=1000.0 (20 iterations): 1.00 accepted, lifted strain p99 15.1 %, worst 36.2 %" in line
    assert "sim.bag.tri_ke=30000.0 (20 iterations): - accepted, lifted strain no lifted frame" in line
