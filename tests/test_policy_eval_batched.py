"""policy_eval's batched path (`policy_eval.batch`: a policy's trials as the worlds of one Newton model) on real Newton
and real lerobot at tiny size: each trial starts from the per-trial env's state, the task's own program replayed in a
batch gets the per-trial verdicts, the stage runs batched with tiny ACT policies, and the key is validated."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.test_policy_eval import ORACLE_SEED, SIZE, _params, _tiny_act
from wc.config import ParamsError, load_section
from wc.policy.finetune import SUMMARY_FILE
from wc.policy_eval.batched_env import BatchedLiftEnv
from wc.policy_eval.closed_loop import OracleActor, run_batch, run_episode
from wc.policy_eval.config import PolicyEvalConfig
from wc.policy_eval.env import WorldContactLiftEnv
from wc.policy_eval.stage import run
from wc.policy_eval.trials import TrialJob, trial_units

SEEDS = [ORACLE_SEED, ORACLE_SEED + 1]
STEPS = 8  # max_steps: the program's first frames, the bag still on the table (its lowest vertex ~4 mm up) ...
RESTING = dict(lift_height_m=0.05, hold_s=0.08)  # ... never lifted: with a 2-frame hold lost (not_lifted) at step 6
NAN_STEP = 4  # the second trial's actions turn non-finite here: it ends early, the first steps on


class NonFiniteFrom:
    """The oracle, with non-finite actions from step NAN_STEP on (per-trial: every action; batched: `rows`)."""

    def __init__(self, oracle: OracleActor, rows: list[int] | None = None) -> None:
        self.oracle, self.rows = oracle, rows

    def reset(self) -> None:
        self.oracle.reset()

    def __call__(self, observation: dict) -> np.ndarray:
        action = self.oracle(observation)
        return action * np.nan if self.oracle.k >= NAN_STEP else action

    def act(self, observations: list[dict]) -> np.ndarray:
        actions = self.oracle.act(observations)
        if self.oracle.k >= NAN_STEP:
            actions[self.rows] = np.nan
        return actions


@pytest.fixture(scope="module")
def env() -> WorldContactLiftEnv:
    return WorldContactLiftEnv(_params(max_steps=STEPS, **RESTING))


@pytest.fixture(scope="module")
def batched(env: WorldContactLiftEnv) -> BatchedLiftEnv:
    return BatchedLiftEnv(env, worlds=2)


@pytest.mark.slow
def test_each_trial_starts_from_the_per_trial_state(env: WorldContactLiftEnv, batched: BatchedLiftEnv) -> None:
    observations, infos = batched.reset(SEEDS)
    x = batched.sim.read_state()[0]
    links = batched.sim.state_0.body_q.numpy().reshape(2, batched.sim.bodies_per_world, 7)[:, :batched.sim.num_links]
    for i, seed in enumerate(SEEDS):
        single, info = env.reset(seed=seed)
        assert batched.specs[i] == env.episode_spec and info == {k: v for k, v in infos[i].items() if k != "done"}
        np.testing.assert_array_equal(batched.planned_actions[i], env.planned_actions)
        np.testing.assert_array_equal(x[i], env.world.sim.read_state()[0][0])  # the bag as the one-world sim holds it
        np.testing.assert_array_equal(links[i], env.world.sim.state_0.body_q.numpy()[:batched.sim.num_links])
        np.testing.assert_array_equal(observations[i]["agent_pos"], single["agent_pos"])
        for camera, image in single["pixels"].items():
            assert observations[i]["pixels"][camera].shape == (SIZE, SIZE, 3)
            assert np.abs(observations[i]["pixels"][camera].astype(int) - image).mean() < 1.0, camera


@pytest.mark.slow
def test_replayed_program_gets_the_per_trial_verdicts(env: WorldContactLiftEnv, batched: BatchedLiftEnv) -> None:
    """The task's program replayed in a batch of two gets each trial's verdict alone: the same success, failure and
    steps (not_lifted once the hold cannot complete; non_finite_action for the trial whose actions turn NaN, which keeps its verdict
    while the other steps on), and the same max lift up to the B-world solver's order of work (batched_env)."""
    alone = [run_episode(env, OracleActor(env), SEEDS[0])[0], run_episode(env, NonFiniteFrom(OracleActor(env)),
                                                                           SEEDS[1])[0]]
    assert [(o.success, o.failure, o.steps) for o in alone] == [(False, "not_lifted", STEPS - 2),
                                                                (False, "non_finite_action", NAN_STEP)]
    together, frames, s_per_step = run_batch(batched, NonFiniteFrom(OracleActor(batched), rows=[1]), SEEDS,
                                             record=[True, False])
    for a, b in zip(alone, together):
        assert (a.seed, a.episode_seed, a.success, a.failure, a.steps, a.cell) == \
               (b.seed, b.episode_seed, b.success, b.failure, b.steps, b.cell), (a, b)
        assert b.max_lift_m == pytest.approx(a.max_lift_m, abs=5e-4)
    assert len(frames[0]) == STEPS - 1 and frames[0][0].shape == (SIZE, 2 * SIZE, 3) and not frames[1]
    assert s_per_step > 0 and batched.done and batched.judges[1].steps == NAN_STEP
    with pytest.raises(RuntimeError, match="every trial ended"):
        batched.step(np.zeros((2, 7), np.float32))


@pytest.mark.slow
def test_stage_runs_batched(tmp_path: Path) -> None:
    """Two tiny ACT policies, three trials in batches of two: one policy call per step for a batch, the report's
    shape as the per-trial path writes it, the first trial's video, timing.batch."""
    for i, name in enumerate(("source", "expanded")):
        _tiny_act(tmp_path / "models" / name, seed=i)
        (tmp_path / "models" / name / SUMMARY_FILE).write_text(json.dumps({"episodes": 3}))
    params = _params(trials=3, seed=ORACLE_SEED, max_steps=2, videos=1, workers=1, batch=2)
    paths = dict(report=tmp_path / "policy.json", videos_dir=tmp_path / "videos", table=tmp_path / "rates.csv",
                 metrics=tmp_path / "rates.json", plot=tmp_path / "rates.png")
    report = run(params, tmp_path / "models", progress=False, **paths)
    saved = json.loads(paths["report"].read_text())
    assert saved["seeds"] == [ORACLE_SEED + i for i in range(3)] and report["timing"]["batch"] == 2
    for name in ("source", "expanded"):
        outcomes = saved["policies"][name]["outcomes"]
        assert [o["seed"] for o in outcomes] == saved["seeds"] and all(o["steps"] <= 2 for o in outcomes)
        assert set(outcomes[0]) == {"seed", "episode_seed", "success", "steps", "max_lift_m", "failure", "cell",
                                    "speed", "amplitude", "video"} and Path(outcomes[0]["video"]).is_file()
        assert "video" not in outcomes[1] and saved["policies"][name]["trials"] == 3
    assert sorted(p.name for p in paths["videos_dir"].iterdir()) == [
        f"expanded_trial00_seed{ORACLE_SEED}.mp4", f"source_trial00_seed{ORACLE_SEED}.mp4"]
    assert report["timing"]["env_seconds"]["physics"] > 0 and report["timing"]["s_per_step"]["source"] > 0


def test_trials_are_cut_into_the_same_batches_for_every_policy() -> None:
    jobs = [TrialJob(p, p, i, 10 + i, False) for i in range(5) for p in ("a", "b")]
    units = trial_units(jobs, 2)
    assert [[(j.policy, j.index) for j in u] for u in units] == [
        [("a", 0), ("a", 1)], [("b", 0), ("b", 1)], [("a", 2), ("a", 3)], [("b", 2), ("b", 3)], [("a", 4)], [("b", 4)]]
    assert trial_units(jobs, 0) == [[j] for j in jobs]


def test_batch_key_is_validated() -> None:
    section = _params()["policy_eval"]
    assert load_section({"policy_eval": section}, "policy_eval", PolicyEvalConfig).batch == section["batch"] == 0
    assert load_section({"policy_eval": {**section, "batch": 8}}, "policy_eval", PolicyEvalConfig).batch == 8
    not_integer = r"policy_eval.batch must be an integer"
    for bad, message in ((-1, r"policy_eval: batch must be >= 0"), (True, not_integer), ("4", not_integer),
                         (2.5, not_integer)):
        with pytest.raises(ParamsError, match=message):
            load_section({"policy_eval": {**section, "batch": bad}, "_source": "test"}, "policy_eval",
                         PolicyEvalConfig)
