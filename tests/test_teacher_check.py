"""Teacher check (wc/expand/teacher.py): a Newton episode stored as if generated replays in Newton to the same
trajectory and verdict; a missing or empty store is a clear error."""

from pathlib import Path

import numpy as np
import pytest

from wc.agent.runner import build_task_world, execute, judge, layout_attrs, reset_batch, simulator_store
from wc.config import load_section, read_params
from wc.expand.teacher import teacher_check
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate import ValidateConfig

ROOT = Path(__file__).resolve().parents[1]
TASK = "bag_drop"  # one second: the shortest Newton episode


@pytest.mark.slow
def test_a_newton_episode_replays_to_itself(tmp_path):
    params = read_params(ROOT / "params.yaml", [f"expand.task={TASK}"])
    task = get_task(TASK, params)
    scene_cfg, sim_cfg = load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig)
    world = build_task_world(scene_cfg, sim_cfg, task)
    (spec, state, actions), = reset_batch(world, [EpisodeSpec(TASK, 3, 0, 0.1, 0.06)])[0]
    (x, v), = execute(world, [state], [actions], None)[0]
    poses = world.scene.link_poses(actions)
    verdict = judge(world, spec, x, v, actions, poses, load_section(params, "validate", ValidateConfig),
                    sim_cfg.frame_dt_s)
    with simulator_store(tmp_path / "gen.zarr", scene_cfg, sim_cfg, [task], "test", "test") as (writer, scene):
        writer.add_episode(x, v, actions, poses, np.repeat(scene.env_poses()[None], len(x), axis=0), task=TASK,
                           seed=spec.seed, cell=spec.cell, speed=spec.speed, amplitude=spec.amplitude, split="train",
                           accepted=verdict is None, first_failure=verdict and verdict[0], source="worldcontact",
                           **layout_attrs(world, None))
    report = teacher_check(params, tmp_path / "gen.zarr")
    plan, = report["episodes"]
    assert report["plans"] == 1 and report["agreement"] == 1.0 and plan["worldcontact"] == plan["newton"]
    assert plan["rms_error_m"][0] == 0.0 and plan["mean_rms_error_m"] < 2e-3, plan["rms_error_m"]


def test_missing_store_is_named_and_an_empty_one_reported(tmp_path):
    params = read_params(ROOT / "params.yaml")
    with pytest.raises(FileNotFoundError, match="run the expand stage"):
        teacher_check(params, tmp_path / "none.zarr")
    scene_cfg, sim_cfg = load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig)
    with simulator_store(tmp_path / "empty.zarr", scene_cfg, sim_cfg, [get_task("lift_handle", params)], "t", "t"):
        pass
    report = teacher_check(params, tmp_path / "empty.zarr")
    assert report["plans"] == 0 and report["precision"] is None and "no generated" in report["note"]
