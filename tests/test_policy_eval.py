"""policy_eval on real Newton and real lerobot at tiny size: the env's spaces and frames, the success
predicate, the task's own program replayed closed-loop succeeds, the stage end to end with two tiny random
ACT policies, lerobot's make_env builds the env from the plugin config, and clear errors."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from tests.conftest import load_params
from wc.config import ParamsError, load_section
from wc.model_ref import file_sha256
from wc.policy.comparison import FLAG, flagged_title
from wc.policy.dataset import RIGHT_ARM, create_dataset
from wc.policy.dataset_config import DatasetConfig
from wc.policy.finetune import SUMMARY_FILE
from wc.policy_eval.config import PolicyEvalConfig
from wc.policy_eval.env import WorldContactLiftEnv
from wc.policy_eval.closed_loop import OracleActor, run_episode
from wc.policy_eval.plots import CSV_HEADER, write_success_metrics, write_success_table
from wc.policy_eval.stage import policy_dirs, run
from wc.policy_eval.success import LiftHoldMonitor, TrialJudge, first_success, hold_frames, wilson_interval
from wc.policy_eval.trials import run_trials, trial_jobs

SIZE = 32  # px: both cameras
ORACLE_SEED = 2  # a trial whose planned program lifts the bag (lowest vertex > 5 cm from frame 64) at the default physics
ORACLE = dict(lift_height_m=0.04, hold_s=0.2)  # margin below the 5.1-5.4 cm it reaches; a short hold keeps it ~70 steps


def _params(**policy_eval: Any) -> dict[str, Any]:
    params = load_params()
    params["render"].update(width=SIZE, height=SIZE)
    params["policy_eval"].update(task="lift_handle", device="cpu", **policy_eval)  # the oracle seed is lift_handle's
    return params


@pytest.fixture(scope="module")
def env() -> WorldContactLiftEnv:
    return WorldContactLiftEnv(_params(max_steps=None, **ORACLE))


# --- the success predicate -------------------------------------------------------------------------------------

def test_success_needs_an_unbroken_hold() -> None:
    assert hold_frames(2.0, 0.04) == 50 and hold_frames(0.0, 0.04) == 0 and hold_frames(0.05, 0.04) == 2
    lift, hold = 0.05, 3
    assert first_success([0.0, 0.05, 0.06, 0.07, 0.08, 0.09], lift, hold) == 4  # 3 intervals after frame 1
    assert first_success([0.0, 0.06, 0.06, 0.049, 0.06, 0.06, 0.06], lift, hold) is None  # broken once
    assert first_success([0.06, 0.06, 0.06, 0.06], lift, 0) == 0
    monitor = LiftHoldMonitor(lift, hold)
    for h in (0.01, 0.02):
        monitor.update(h)
    assert monitor.failure() == "not_lifted"
    monitor.update(0.07)
    assert monitor.failure() == "not_held" and monitor.max_height_m == pytest.approx(0.07)
    monitor.update(0.0)
    assert monitor.failure() == "dropped"
    with pytest.raises(ValueError, match="not finite"):
        monitor.update(float("nan"))


def _judged(heights: list[float], hold: int = 3, max_steps: int = 10) -> tuple[TrialJudge, list[tuple]]:
    judge, verdicts = TrialJudge(0.05, hold, max_steps), []
    judge.start(0.0)
    for h in heights:
        verdicts.append(judge.step(h))
        if judge.done:
            break
    return judge, verdicts


def test_a_trial_ends_once_its_hold_can_no_longer_complete() -> None:
    """max_steps 10, hold 3 intervals (a streak of 4 frames): a bag never lifted has lost at step 7 (3 steps left
    make a streak of 3); one lifted from step 7 on could still succeed there, and does at step 10."""
    judge, verdicts = _judged([0.0] * 10)
    assert (judge.steps, judge.failure, verdicts[-1]) == (7, "not_lifted", (False, False, True))
    judge, verdicts = _judged([0.0] * 6 + [0.06] * 4)
    assert (judge.steps, judge.success, verdicts[-1]) == (10, True, (True, True, False))
    judge, _ = _judged([0.06, 0.06] + [0.0] * 8)  # lifted, dropped: lost too once 3 steps are left
    assert (judge.steps, judge.failure) == (7, "dropped")
    judge, _ = _judged([0.06] * 3, hold=20)  # a hold longer than the trial: lost at the first step
    assert (judge.steps, judge.failure) == (1, "not_held")
    with pytest.raises(RuntimeError, match="verdict is final"):
        judge.step(0.06)


# --- the environment on real Newton ----------------------------------------------------------------------------

@pytest.mark.slow
def test_reset_and_step_shapes_and_frames(env: WorldContactLiftEnv) -> None:
    obs, info = env.reset(seed=ORACLE_SEED)
    assert set(obs) == {"pixels", "agent_pos"} and set(obs["pixels"]) == {"top", "wrist"}
    for image in obs["pixels"].values():
        assert image.shape == (SIZE, SIZE, 3) and image.dtype == np.uint8 and image.std() > 5  # a scene, not a fill
    assert obs["agent_pos"].dtype == np.float32 and obs["agent_pos"].shape == (7,)
    np.testing.assert_array_equal(obs["agent_pos"], env.planned_actions[0, RIGHT_ARM])
    assert info["is_success"] is False and info["episode_seed"] == 2 * 2**32 + ORACLE_SEED
    assert env.observation_space.contains(obs)
    start = env._resets[ORACLE_SEED][1]  # the settled frame-0 state (x, v)
    np.testing.assert_array_equal(env.x, start.x)
    planned = env.planned_actions[:4]
    for k in range(1, 4):
        obs, reward, terminated, truncated, info = env.step(planned[k, RIGHT_ARM])
        assert (reward, terminated, truncated, info["steps"]) == (0.0, False, False, k)
    np.testing.assert_array_equal(obs["agent_pos"], planned[3, RIGHT_ARM])
    assert env.render().shape == (SIZE, 2 * SIZE, 3)
    # the closed loop steps the simulator exactly as the simulate stage's open-loop rollout does
    x_loop = env.x.copy()
    x_open, _ = env.world.sim.rollout(start, planned)
    np.testing.assert_allclose(x_loop, x_open[3], rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match=r"action must be \(7,\)"):
        env.step(np.zeros(14, np.float32))


@pytest.mark.slow
def test_the_policy_sees_frames_as_the_dataset_stored_them(env: WorldContactLiftEnv, tmp_path: Path) -> None:
    """One rendered frame through both paths: written into a LeRobot dataset by the dataset stage's writer and
    decoded by stock LeRobot (training), and through the env's observation (evaluation). Same size, RGB order,
    and the codec's artefacts: the observation is far closer to the decoded training frame than the raw render is."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    obs, _ = env.reset(seed=ORACLE_SEED)
    raw = env.raw_frames(env.x, env.planned_actions[0])
    cfg = load_section(_params(), "dataset", DatasetConfig)
    ds = create_dataset(tmp_path / "ds", "test/roundtrip", env.metadata["render_fps"], SIZE, SIZE, cfg)
    for _ in range(3):
        ds.add_frame({"observation.state": obs["agent_pos"], "action": obs["agent_pos"], "task": "t",
                      **{f"observation.images.{cam}": raw[cam] for cam in ("top", "wrist")}})
    ds.save_episode(parallel_encoding=False)
    ds.finalize()
    trained = LeRobotDataset("test/roundtrip", root=tmp_path / "ds", video_backend="pyav")[0]
    for cam in ("top", "wrist"):
        seen = np.round(trained[f"observation.images.{cam}"].numpy().transpose(1, 2, 0) * 255)
        assert obs["pixels"][cam].shape == seen.shape == raw[cam].shape
        to_obs, to_raw = np.abs(seen - obs["pixels"][cam]).mean(), np.abs(seen - raw[cam]).mean()
        assert to_raw > 0.3 and to_obs < 0.2 * to_raw, (cam, to_obs, to_raw)  # here: 0 vs ~3 grey levels
        channels = [np.corrcoef(seen[..., c].ravel(), obs["pixels"][cam][..., c].ravel())[0, 1] for c in range(3)]
        assert min(channels) > 0.99, channels  # same colour order (a BGR swap would decorrelate R and B)
        np.testing.assert_array_equal(obs["pixels"][cam], env.video(raw[cam]))


@pytest.mark.slow
def test_task_program_replayed_closed_loop_succeeds(env: WorldContactLiftEnv) -> None:
    outcome, frames, s_per_step = run_episode(env, OracleActor(env), ORACLE_SEED, record=True)
    assert outcome.success and outcome.failure is None, outcome
    assert outcome.max_lift_m >= env.cfg.lift_height_m
    assert outcome.steps < env._max_episode_steps and len(frames) == outcome.steps + 1
    # a policy that leaves the bag on the table fails with not_lifted, ended at once: a 2 s hold cannot fit in 3 steps
    env.cfg = dataclasses.replace(env.cfg, max_steps=3)
    hold = lambda observation: observation["agent_pos"].copy()  # noqa: E731
    hold.reset = lambda: None
    outcome, _, _ = run_episode(env, hold, ORACLE_SEED)
    assert (outcome.success, outcome.failure, outcome.steps) == (False, "not_lifted", 1)


# --- the stage with two tiny random ACT policies ---------------------------------------------------------------

def _tiny_act(path: Path, seed: int) -> None:
    """A randomly initialised ACT policy + processors, saved the lerobot way (what finetune writes)."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies import make_pre_post_processors
    from lerobot.policies.act import ACTConfig, ACTPolicy

    torch.manual_seed(seed)
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, SIZE, SIZE))
    vector = PolicyFeature(type=FeatureType.STATE, shape=(7,))
    config = ACTConfig(input_features={"observation.images.top": image, "observation.images.wrist": image,
                                       "observation.state": vector},
                       output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))},
                       device="cpu", chunk_size=4, n_action_steps=4, dim_model=32, n_heads=2, dim_feedforward=64,
                       n_encoder_layers=1, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=8,
                       pretrained_backbone_weights=None, push_to_hub=False)
    policy = ACTPolicy(config)
    stats = {k: {"mean": torch.zeros(7), "std": torch.full((7,), 1e-3)} for k in ("observation.state", "action")}
    stats |= {f"observation.images.{c}": {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)}
              for c in ("top", "wrist")}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(path)


@pytest.mark.slow
def test_stage_end_to_end_in_worker_processes(tmp_path: Path) -> None:
    """Two policies x two trials in two worker processes: the report, videos, table and plot, and the same
    outcomes as the trials run in this process."""
    for i, name in enumerate(("source", "expanded")):
        _tiny_act(tmp_path / "models" / name, seed=i)
        (tmp_path / "models" / name / SUMMARY_FILE).write_text(json.dumps({"episodes": 3}))  # as finetune records
    params = _params(trials=2, seed=ORACLE_SEED, max_steps=2, videos=1, workers=2)
    paths = dict(report=tmp_path / "policy.json", videos_dir=tmp_path / "videos", table=tmp_path / "rates.csv",
                 metrics=tmp_path / "rates.json", plot=tmp_path / "rates.png")
    report = run(params, tmp_path / "models", progress=False, **paths)
    saved = json.loads(paths["report"].read_text())
    assert saved["seeds"] == [ORACLE_SEED, ORACLE_SEED + 1] and set(saved["success_rate"]) == {"source", "expanded"}
    assert saved[FLAG] is True  # both trained on 3 episodes: no generated one
    for name in ("source", "expanded"):
        policy = saved["policies"][name]
        assert [t["seed"] for t in policy["outcomes"]] == saved["seeds"] and policy["episodes"] == 3
        first = policy["outcomes"][0]
        assert first["steps"] <= 2 and first["success"] is False and Path(first["video"]).is_file()
        assert first["failure"] in ("not_lifted", "non_finite") and "video" not in policy["outcomes"][1]
        assert saved["successes"][name] == 0 and policy["ci95"] == pytest.approx(list(wilson_interval(0, 2)))
        weights = tmp_path / "models" / name / "model.safetensors"  # each policy's weights named by their hash
        assert policy["model"] == str(tmp_path / "models" / name) and policy["model_sha256"] == file_sha256(weights)
    videos = sorted(p.name for p in paths["videos_dir"].iterdir())
    assert videos == [f"expanded_trial00_seed{ORACLE_SEED}.mp4", f"source_trial00_seed{ORACLE_SEED}.mp4"]
    assert paths["table"].read_text().splitlines()[0] == "policy,successes,trials,success_rate,ci95_low,ci95_high"
    assert json.loads(paths["metrics"].read_text())["expanded"]["trials"] == 2
    assert paths["plot"].stat().st_size > 0 and report["params_hash"] == saved["params_hash"]
    assert report["timing"]["s_per_step"]["source"] > 0 and report["timing"]["workers"] == 2
    assert report["timing"]["env_seconds"]["physics"] > 0 and report["timing"]["policy_load_s"]["expanded"] > 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind
    here = run_trials(params, trial_jobs({"source": tmp_path / "models" / "source"}, saved["seeds"], 0),
                      tmp_path / "unused", workers=1)
    assert [r.outcome for r in here] == [{k: v for k, v in o.items() if k != "video"}
                                         for o in saved["policies"]["source"]["outcomes"]]


def test_per_arm_metrics_match_the_table(tmp_path: Path) -> None:
    """reports/policy_success.json (DVC metrics): per arm its own counts, rate and Wilson interval, low before high,
    the same figures as the CSV row; nothing else (no timings)."""
    policies = {arm: {"successes": k, "trials": 50, "success_rate": k / 50, "ci95": list(wilson_interval(k, 50)),
                      "outcomes": [], "failures": {"dropped": 50 - k}} for arm, k in (("source", 37), ("expanded", 45))}
    write_success_metrics(tmp_path / "m.json", policies)
    write_success_table(tmp_path / "t.csv", policies)
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert set(metrics) == {"source", "expanded"}
    assert metrics["expanded"] == {"successes": 45, "trials": 50, "success_rate": 0.9,
                                   "ci95_low": pytest.approx(0.786, abs=1e-3), "ci95_high": pytest.approx(0.957, abs=1e-3)}
    assert metrics["source"]["successes"] == 37 and metrics["source"]["ci95_low"] < 0.74 < metrics["source"]["ci95_high"]
    rows = (tmp_path / "t.csv").read_text().splitlines()[1:]
    assert [float(v) for v in rows[1].split(",")[1:]] == pytest.approx([metrics["expanded"][k] for k in CSV_HEADER[1:]])


def test_wilson_interval() -> None:
    low, high = wilson_interval(13, 20)  # the paper's source-only 13/20
    assert (round(low, 3), round(high, 3)) == (0.433, 0.819)
    assert wilson_interval(0, 50)[0] == 0.0 and 0 < wilson_interval(0, 50)[1] < 0.1
    assert wilson_interval(50, 50)[1] == 1.0 and 0.9 < wilson_interval(50, 50)[0] < 1.0
    for k in range(0, 21, 5):  # contains the rate, narrows with more trials
        low, high = wilson_interval(k, 20)
        assert low <= k / 20 <= high
        assert wilson_interval(5 * k, 100)[1] - wilson_interval(5 * k, 100)[0] < high - low
    with pytest.raises(ValueError, match="successes <= trials"):
        wilson_interval(3, 2)


def test_the_plot_title_says_when_the_arms_are_the_same() -> None:
    assert "NO GENERATED EPISODES" in flagged_title("rates", True)
    assert flagged_title("rates", False) == flagged_title("rates", None) == "rates"


def test_missing_policy_and_bad_params_fail_clearly(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no trained policy 'source'.*finetune"):
        run(_params(), tmp_path / "nowhere", report=tmp_path / "r.json", progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        policy_dirs(tmp_path, ["empty"])
    bad = {"policy_eval": {**_params()["policy_eval"], "seed_offset": 7}, "_source": "test"}
    with pytest.raises(ParamsError, match="seed_offset"):
        load_section(bad, "policy_eval", PolicyEvalConfig)


# --- lerobot's own code path -----------------------------------------------------------------------------------

@pytest.mark.slow
def test_lerobot_make_env_builds_the_plugin_env(tmp_path: Path) -> None:
    import lerobot_env_worldcontact  # noqa: F401  registers the env type and the gym id
    from lerobot.envs.factory import make_env, make_env_config
    from lerobot.envs.utils import env_to_policy_features, preprocess_observation

    params = _params(max_steps=1)
    params.pop("_source")
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(copy.deepcopy(params)))
    cfg = make_env_config("worldcontact", params=str(tmp_path / "params.yaml"))
    assert cfg.gym_id == "gym_worldcontact/LiftBag-v0"
    features = env_to_policy_features(cfg)
    assert features["observation.images.top"].shape == (3, SIZE, SIZE) and features["observation.state"].shape == (7,)
    vec = make_env(cfg, n_envs=1)["worldcontact"][0]
    try:
        obs, _ = vec.reset(seed=[ORACLE_SEED])
        batch = preprocess_observation(obs)
        assert {k: tuple(v.shape) for k, v in batch.items()} == {
            "observation.images.top": (1, 3, SIZE, SIZE), "observation.images.wrist": (1, 3, SIZE, SIZE),
            "observation.state": (1, 7)}
        assert vec.call("task_description") == ("right grasp and lift",) and vec.call("_max_episode_steps") == (1,)
        _, _, terminated, truncated, info = vec.step(obs["agent_pos"])
        assert truncated.tolist() == [True] and not terminated.any() and "is_success" in info["final_info"]
    finally:
        vec.close()
