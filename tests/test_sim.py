"""The Newton source simulator on CPU at small size: grasp -> lift -> release, rigid objects, determinism.

Slow (Newton kernels compile on first use, ~1-2 min; then ~1-2 min of simulation).
"""

import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT, load_params
from wc.config import load_section
from wc.dynamics import ObjectState
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import EpisodeSpec, get_task

pytestmark = pytest.mark.slow
# A short lift: hold 0.4 s instead of 2 s; everything else is the default scene and task.
OVERRIDES = ["tasks.lift_handle.hold_s=0.4", "sim.settle_s=0.4"]


@pytest.fixture(scope="module")
def setup():
    params = load_params(*OVERRIDES)
    scene = build_scene(load_section(params, "scene", SceneConfig))
    return params, scene, load_section(params, "sim", SimConfig), get_task("lift_handle", params)


def _lift_actions(scene, sim, task, seed=0):
    spec = EpisodeSpec("lift_handle", seed, 0, 0.08, 0.17)
    initial = task.initial_state(scene, spec, np.random.default_rng(seed))
    held = task.settle_action(scene, spec, initial)
    settled = sim.settle([initial], [held], sim.cfg.settle_s)[0]
    return settled, task.actions(scene, settled, spec, held, sim.cfg.frame_dt_s)


def test_grasp_lift_release(setup):
    """The closed gripper lifts the bag off the table by its handle; opening the gripper drops it."""
    params, scene, cfg, task = setup
    sim = NewtonSimulator(scene, cfg)
    settled, actions = _lift_actions(scene, sim, task)
    release_frames = int(round(0.8 / cfg.frame_dt_s))
    opened = np.repeat(actions[-1:], release_frames, axis=0)
    opened[:, 13] = np.linspace(actions[-1, 13], task.common.open_m, release_frames)
    x, v = sim.rollout(settled, np.concatenate([actions, opened]))
    table = scene.table.top_z
    lowest = x[..., 2].min(axis=1) - table
    held_end = len(actions) - 1
    assert np.isfinite(x).all() and np.isfinite(v).all()
    assert lowest[0] < 0.01, "the bag starts on the table"
    assert lowest[held_end] >= 0.03, f"held bag's lowest vertex only {lowest[held_end]:.3f} m above the table"
    verdict = task.check(scene, EpisodeSpec("lift_handle", 0, 0, 0.08, 0.17), x[: held_end + 1], actions)
    assert (verdict is None) == (lowest[held_end] >= task.cfg.success_lift_m)
    assert lowest[-1] < 0.01, f"released bag did not fall back (lowest vertex {lowest[-1]:.3f} m)"
    assert x[-1, :, 2].max() < x[held_end, :, 2].max() - 0.05


def test_same_seed_same_arrays(setup):
    params, scene, cfg, task = setup
    results = []
    for _ in range(2):
        sim = NewtonSimulator(scene, cfg)
        settled, actions = _lift_actions(scene, sim, task, seed=3)
        results.append(sim.rollout(settled, actions[:15]))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])


def test_rigid_sphere_falls_and_rests_rigidly(setup):
    """A free sphere (a predicted rigid object) falls onto the table; its vertices move rigidly."""
    params, _, cfg, _ = setup
    scene = build_scene(load_section(params, "scene", SceneConfig), ["sphere"])
    sim = NewtonSimulator(scene, cfg)
    rest = scene.objects["sphere"].vertices
    x0 = rest + np.array([0.0, 0.0, scene.table.top_z + 0.15], np.float32)
    x, v = sim.rollout(ObjectState(x0, np.zeros_like(x0)), np.repeat(scene.home_action()[None], 16, axis=0))
    radius = np.linalg.norm(rest, axis=1).max()
    pair = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)  # noqa: E731
    np.testing.assert_allclose(pair(x[-1]), pair(x0), atol=1e-4)
    assert x[-1, :, 2].min() == pytest.approx(scene.table.top_z, abs=0.01)
    assert x[-1, :, 2].mean() == pytest.approx(scene.table.top_z + radius, abs=0.01)


def test_held_object_is_a_kinematic_body_posed_by_its_link(setup):
    params, _, cfg, _ = setup
    scene = build_scene(load_section(params, "scene", SceneConfig), ["sphere"],
                        held={"cube": ("right_link6", [0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0])})
    sim = NewtonSimulator(scene, cfg)
    x0 = scene.objects["sphere"].vertices + np.array([-0.2, 0.0, 0.1], np.float32)
    actions = np.repeat(scene.home_action()[None], 3, axis=0)
    actions[:, 7] = [0.0, 0.05, 0.1]
    sim.rollout(ObjectState(x0, np.zeros_like(x0)), actions)
    body = scene.link_names.index("held_cube")
    newton_pose = sim.state_0.body_q.numpy()[body]
    expected = scene.link_poses(actions[-1])[body]
    np.testing.assert_allclose(newton_pose[:3], expected[:3], atol=1e-5)
    assert abs(float(np.dot(newton_pose[3:], expected[3:]))) == pytest.approx(1.0, abs=1e-5)


def test_batched_worlds_match_single_world_runs(setup):
    """Episodes batched as separate Newton worlds give what each gives alone (indexing per world)."""
    params, _, cfg, _ = setup
    scene = build_scene(load_section(params, "scene", SceneConfig), ["sphere"])
    rest = scene.objects["sphere"].vertices
    starts = [rest + np.array([-0.15, 0.0, 0.10], np.float32), rest + np.array([0.0, 0.12, 0.20], np.float32)]
    actions = [np.repeat(scene.home_action()[None], 8, axis=0) for _ in starts]
    actions[1][:, 7] = np.linspace(0.0, 0.4, 8)  # the second world's right arm turns; the first's stays
    initial = [ObjectState(x, np.zeros_like(x)) for x in starts]
    batched = NewtonSimulator(scene, cfg, worlds=2).rollout_batch(initial, actions)
    for w in range(2):
        alone = NewtonSimulator(scene, cfg, worlds=1).rollout(initial[w], actions[w])
        np.testing.assert_allclose(batched[w][0], alone[0], atol=5e-4)  # m; contact order differs per batch
        np.testing.assert_allclose(batched[w][1], alone[1], atol=0.03)  # m/s at the landing; solver order differs
    assert not np.allclose(batched[0][0][-1], batched[1][0][-1])


def test_newton_and_the_renderer_define_their_kernels_without_backward_passes():
    """Importing wc's Newton users first (a fresh process, as a stage starts) gives Newton's and wc's kernel modules
    enable_backward False: half the cold CPU compile, and nothing here differentiates through warp."""
    code = ("import wc.render.renderer, wc.sim.newton_sim, wc.validate.cloth_bvh, warp as wp\n"
            "import newton._src.solvers.vbd.solver_vbd as vbd, newton._src.sensors.sensor_camera as cam\n"
            "modules = {k.module.name: k.module.options['enable_backward'] for m in (vbd, cam, wc.validate.cloth_bvh)\n"
            "           for k in vars(m).values() if isinstance(k, wp.Kernel)}\n"
            "print(len(modules), sorted(name for name, backward in modules.items() if backward))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    count, with_backward = out.strip().split(" ", 1)
    assert int(count) >= 3 and with_backward == "[]"
