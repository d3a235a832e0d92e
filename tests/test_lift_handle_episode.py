"""The policy task end to end in Newton: a default-params lift_handle episode passes every validation
predicate and the task's own lift check.

Guards the handle pinch (7 cm below the apex, yaw -15 deg): pinched at 5-6 cm the strap slid through the
pads until the loop above them crossed itself, and a square-on pinch (yaw 0) over-stretched it on closing.
One full episode (~100 frames) takes about a minute on one CPU core.
"""

import numpy as np
import pytest

from tests.conftest import load_params
from wc.agent.runner import build_task_world, execute, judge, reset_batch
from wc.config import load_section
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.tasks.bag_geometry import lowest_height
from wc.validate import ValidateConfig

pytestmark = pytest.mark.slow
SPEC = dict(seed=5, cell=0, speed=0.08, amplitude=0.19)  # cell 0: grasp depth 0.07 m, yaw -15 deg


def test_default_lift_handle_episode_is_accepted_and_lifts_the_bag():
    params = load_params()
    task = get_task("lift_handle", params)
    assert task.cell_values(0) == {"grasp_depth_bins_m": 0.07, "grasp_across_bins": 0.5, "yaw_bins_deg": -15.0}
    sim_cfg = load_section(params, "sim", SimConfig)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, task)
    spec = EpisodeSpec(task.name, SPEC["seed"], SPEC["cell"], SPEC["speed"], SPEC["amplitude"])
    runnable, unreachable = reset_batch(world, [spec])
    assert not unreachable
    _, state, actions = runnable[0]
    (x, v), = execute(world, [state], [actions], None)[0]
    assert np.isfinite(x).all() and np.isfinite(v).all()
    verdict = judge(world, spec, x, v, actions, world.scene.link_poses(actions),
                    load_section(params, "validate", ValidateConfig), sim_cfg.frame_dt_s)
    assert verdict is None, f"lift_handle episode rejected: {verdict}"
    heights = lowest_height(world.scene, x)
    assert heights[0] < 0.01  # it starts on the table ...
    assert heights[-1] >= params["tasks"]["lift_handle"]["success_lift_m"]  # ... and hangs from the pinched handle
