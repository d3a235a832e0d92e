"""The stress stage on a tiny run: two cases (nominal, fast motion) of one short lift_body episode each, simulated by
the real Newton source simulator at the default 306-vertex bag, rolled out by a tiny random WorldContact and the
two references; the video rendered by the real SensorCamera. Plus the hand-off rollout on a synthetic store."""

from __future__ import annotations

import copy
import csv
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from wc.eval.stress import stress
from tests.conftest import load_params
from tests.synthetic_store import write_synthetic_store
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.eval.cases import CaseReader
from wc.eval.methods import LearnedMethod
from wc.eval.predictors import ConstantVelocity
from wc.eval.stress import STRESS_HEADER, episode_rollout
from wc.eval.stress_config import StressConfig
from wc.eval.stress_truth import case_params, truth_hash
from wc.model.config import ModelConfig
from wc.model.worldcontact import WorldContact
from wc.scene.config import SceneConfig
from wc.train.checkpoint import save_weights

PANEL_PX = 48
VIDEO_FRAMES = 8
STEPS = 10


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return load_params()


def _stress_params(params: dict[str, Any], models: Path) -> dict[str, Any]:
    p = copy.deepcopy(params)
    p["stress"] = {
        "task": "lift_body", "episodes": 1, "max_attempts": 2, "rollout_frames": STEPS, "workers": 1, "seed": 0,
        "overrides": {"sim.settle_s": 0.12},  # the test's only shortcut: a brief settle
        "cases": {"nominal": {}, "fast_motion": {"overrides": {"tasks.lift_body.speed_range_m_s": [0.3, 0.3]}}},
        "video": {"case": "fast_motion", "method": "worldcontact", "baselines": ["zero_motion"],
                  "frames": VIDEO_FRAMES, "panel_px": PANEL_PX, "sheet_frames": 3},
    }
    p["evaluate"]["methods"] = {"worldcontact": {"kind": "worldcontact", "path": str(models / "worldcontact")},
                                "robocraft": {"kind": "baseline", "path": str(models / "absent")},
                                "zero_motion": {"kind": "zero_motion"},
                                "constant_velocity": {"kind": "constant_velocity"}}
    return p


def _outputs(root: Path) -> dict[str, Path]:
    names = {"store": "truth.zarr", "csv": "stress.csv", "png": "stress.png", "curves_csv": "curves.csv",
             "report": "stress.json", "video": "video.mp4", "sheet": "sheet.png", "metrics": "absent_metrics.json"}
    return {k: root / v for k, v in names.items()}


@pytest.fixture(scope="module")
def run(tmp_path_factory, params) -> tuple[dict[str, Any], dict[str, Path], dict[str, Any]]:
    root = tmp_path_factory.mktemp("stress")
    torch.manual_seed(0)
    model = WorldContact(load_section(params, "model", ModelConfig), velocity_m_s=0.3, delta_x_m=0.005,
                         delta_v_m_s=0.1).eval()
    (root / "models" / "worldcontact").mkdir(parents=True)
    save_weights(model, root / "models" / "worldcontact" / "model.safetensors", {"projection": False})
    p = _stress_params(params, root / "models")
    out = _outputs(root)
    return p, out, stress(p, **{k: str(v) for k, v in out.items()})


@pytest.mark.slow
def test_outputs_have_every_case_and_method(run):
    _, out, r = run
    rows = list(csv.DictReader(out["csv"].open()))
    assert list(rows[0]) == STRESS_HEADER
    methods = {"ground_truth", "worldcontact", "zero_motion", "constant_velocity"}
    assert {(row["case"], row["method"]) for row in rows} == {(c, m) for c in ("nominal", "fast_motion") for m in methods}
    assert "robocraft" in r["skipped"]
    reference = {row["case"]: float(row["position_mse_m2"]) for row in rows if row["method"] == "constant_velocity"}
    assert reference["nominal"] != pytest.approx(reference["fast_motion"])  # a ratio to the other case's would show
    for row in rows:
        assert int(row["steps"]) == STEPS
        if row["method"] == "ground_truth":
            assert float(row["position_mse_m2"]) == 0.0 and row["divergence_step"] == ""
        else:
            assert float(row["position_mse_m2"]) > 0
        # each method's error relative to constant velocity's in the same case
        assert float(row["position_mse_vs_constant_velocity"]) == pytest.approx(
            float(row["position_mse_m2"]) / reference[row["case"]], rel=1e-6), (row["case"], row["method"])
    curves = list(csv.DictReader(out["curves_csv"].open()))
    assert len(curves) == len(rows) * STEPS
    assert out["png"].stat().st_size > 10_000 and out["sheet"].stat().st_size > 5_000
    assert r["ground_truth"]["reused"] is False and set(r["ground_truth"]["cases"]) == {"nominal", "fast_motion"}


@pytest.mark.slow
def test_fast_motion_really_moves_the_gripper_faster(run):
    _, out, r = run
    store = TrajectoryStore(out["store"])
    by_case = {store.episode_attrs(e)["case"]: store.episode_attrs(e) for e in store.episode_ids}
    assert by_case["fast_motion"]["speed"] == pytest.approx(0.3)
    assert 0.06 <= by_case["nominal"]["speed"] <= 0.10
    # the recorded gripper motion, not just the planned speed, is faster
    assert by_case["fast_motion"]["peak_tcp_speed_m_s"] > 2.0 * by_case["nominal"]["peak_tcp_speed_m_s"]
    for attrs in by_case.values():
        assert attrs["first_failure"] not in ("non_finite", "blow_up") and attrs["split"] == "test"


@pytest.mark.slow
def test_video_has_three_panels_and_the_expected_frames(run):
    _, out, r = run
    cap = cv2.VideoCapture(str(out["video"]))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == VIDEO_FRAMES == r["video"]["frames"]
    assert frames[0].shape == (PANEL_PX, 3 * PANEL_PX, 3)
    assert r["video"]["baseline"] == "zero_motion" and len(r["video"]["panels"]) == 3
    for k in range(3):  # each panel holds a rendered scene and its own label (top-left corner)
        assert frames[0][:, k * PANEL_PX:(k + 1) * PANEL_PX].std() > 5.0
    labels = [frames[0][:12, k * PANEL_PX:(k + 1) * PANEL_PX].astype(int) for k in range(3)]
    assert all(np.abs(labels[i] - labels[j]).mean() > 1.0 for i, j in ((0, 1), (0, 2), (1, 2)))


@pytest.mark.slow
def test_rerun_reuses_the_ground_truth(run):
    p, out, r = run
    again = stress(p, **{k: str(v) for k, v in out.items()})
    assert again["ground_truth"]["reused"] is True
    assert [row["position_mse_m2"] for row in again["table"]] == [row["position_mse_m2"] for row in r["table"]]
    cfg = load_section(p, "stress", StressConfig)
    changed = copy.deepcopy(p)
    changed["stress"]["cases"]["fast_motion"]["overrides"]["tasks.lift_body.speed_range_m_s"] = [0.25, 0.25]
    assert truth_hash(changed, load_section(changed, "stress", StressConfig)) != truth_hash(p, cfg)
    video = copy.deepcopy(p)
    video["stress"]["video"]["frames"] = 5
    assert truth_hash(video, load_section(video, "stress", StressConfig)) == truth_hash(p, cfg)


def test_case_overrides_apply_and_bad_keys_are_named(params):
    p = _stress_params(params, Path("models"))
    cfg = load_section(p, "stress", StressConfig)
    fast = case_params(p, cfg, "fast_motion")
    assert fast["tasks"]["lift_body"]["speed_range_m_s"] == [0.3, 0.3] and fast["sim"]["settle_s"] == 0.12
    assert params["tasks"]["lift_body"]["speed_range_m_s"] == [0.06, 0.10]  # the caller's params are untouched
    p["stress"]["cases"]["fast_motion"]["overrides"] = {"tasks.lift_body.speed_m_s": 1.0}
    with pytest.raises(ParamsError, match=r"stress.cases.fast_motion.overrides.tasks.lift_body.speed_m_s"):
        case_params(p, load_section(p, "stress", StressConfig), "fast_motion")


@pytest.mark.parametrize("key, value, message", [
    ("rollout_frames", 0, r"stress: rollout_frames must be >= 1"),
    ("max_attempts", 0, r"stress: max_attempts \(0\) must be >= episodes"),
    ("overrides", {"scene.bag.width_m": 0.2}, r"overrides.scene.bag.width_m: an override key must be"),
    ("video", {"case": "nope"}, r"video.case 'nope' is not one of cases"),
])
def test_bad_config_is_named(params, key, value, message):
    p = _stress_params(params, Path("models"))
    if key == "video":
        p["stress"]["video"].update(value)
    else:
        p["stress"][key] = value
    with pytest.raises(ParamsError, match=message):
        load_section(p, "stress", StressConfig)
    p = _stress_params(params, Path("models"))
    p["stress"]["video"]["frames"] = 500
    with pytest.raises(ParamsError, match=r"stress.video: frames must be in \[2, 100\]"):
        load_section(p, "stress", StressConfig)


def test_handoff_rollout_carries_the_prediction_across_the_release(tmp_path, params):
    path = write_synthetic_store(tmp_path / "s.zarr", params, [("handoff", "test")], frames=10)
    store = TrajectoryStore(path)
    reader = CaseReader(store, load_section(params, "scene", SceneConfig), 0.02, torch.device("cpu"))
    eid = store.episode_ids[0]
    rollout = episode_rollout(reader, eid, 9, LearnedMethod(ConstantVelocity(), torch.device("cpu")), store.dt)
    (first, x0, v0), (second, x1, _) = rollout.phases
    release = first.phase.stop - 1
    assert len(x0) + len(x1) == 9 and len(x0) == release
    bag = slice(0, len(store.objects["bag"].rest_positions))
    # the bag starts the second phase where the first phase's prediction left it; the ball as recorded
    assert np.allclose(second.x[0, bag], x0[-1, bag], atol=1e-6)
    assert np.allclose(second.x[0, bag.stop:], store.read_window(eid, release, 1)["x"][0, bag.stop:])
    assert np.allclose(x1[0, bag], x0[-1, bag] + store.dt * v0[-1, bag], atol=1e-6)
    full = rollout.full_x(store)
    assert full.shape == (9, store.read_window(eid, 0, 1)["x"].shape[1], 3)
    assert np.allclose(full[:release, bag], x0[:, bag])
