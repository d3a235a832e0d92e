"""The expand stage's slot engine (wc/expand/slot_*.py, fixed_projection.py, frame_checks.py) on the CPU, at small
size: slots refill as episodes end or fail, the verdicts of the reference engine on the same plans, the projection's
invariants, and its static-shape helpers."""

from __future__ import annotations

import copy
from dataclasses import replace
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from tests.expand_inputs import expand_params, write_source_store, write_tiny_model
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.expand import expand
from wc.expand.body_contacts import DeviceBodies, horn_rotation, push_out
from wc.expand.cloth_elements import compact
from wc.expand.config import ExpandConfig
from wc.expand.fixed_projection import FixedProjectionConfig, FixedStepProjection
from wc.expand.slot_rollout import SlotPlan
from wc.expand.frame_checks import FRAME_CHECKS, FrameChecks
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.validate.config import ValidateConfig
from wc.validate.predicates import Episode, penetration, rigid_frames, self_intersection, table_and_robot_distance
from wc.validate.self_intersection import crossing_edges, unique_edges

CONFIG = FixedProjectionConfig((0.9, 1.1), 10, 20, 0.002, 1, 0.8, 2, 10, 6, 4, 16, 16, 4096)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> tuple[dict[str, Any], Path, Path]:
    params = expand_params()
    d = tmp_path_factory.mktemp("slots")
    return params, write_source_store(d, params), write_tiny_model(d, params)


@pytest.fixture(scope="module")
def scene():
    return build_scene(load_section(load_params(), "scene", SceneConfig))


def _run(inputs, tmp: Path, name: str, **expand_keys: Any) -> tuple[dict[str, Any], TrajectoryStore, TrajectoryStore]:
    params, store, model = inputs
    p = copy.deepcopy(params)
    validate = expand_keys.pop("validate", {})
    p["validate"].update(validate)
    p["expand"].update(expand_keys)
    r = expand(p, model, store, tmp / f"{name}.zarr", tmp / f"{name}.json", tmp / f"{name}_rejected.zarr")
    return r, TrajectoryStore(tmp / f"{name}.zarr"), TrajectoryStore(tmp / f"{name}_rejected.zarr")


@pytest.mark.slow
def test_two_slots_take_every_episode_in_turn_and_file_them_in_order(inputs, tmp_path):
    r, out, rejected = _run(inputs, tmp_path, "refill", engine="slots", batch_size=2, target_trajectories=7,
                            max_attempts=5, seed=5)
    assert r["engine"] == "slots" and r["slots"] == 2 and r["restarts"] == 0
    assert r["generated"] + r["infeasible_plans"] == 5 and r["generated"] >= 3  # more episodes than slots
    assert r["slot_loads"] == r["generated"]  # each generated episode took a slot once, in the one set of slots
    seeds = [out.episode_attrs(e)["seed"] for e in out.episode_ids]
    assert len(seeds) == r["accepted"]
    assert {"host_planning_s", "host_device_wait_s", "device_network_s", "device_projection_s",
            "device_untangle_s", "device_checks_s"} <= set(r["timing"])
    again, out2, rejected2 = _run(inputs, tmp_path, "again", engine="slots", batch_size=2, target_trajectories=7,
                                  max_attempts=5, seed=5, write_processes=1)  # written by a process this time
    assert [out2.episode_attrs(e)["seed"] for e in out2.episode_ids] == seeds  # same seed, same episodes
    assert rejected2.episode_ids == rejected.episode_ids
    for e in out.episode_ids:
        assert np.array_equal(out.read_episode(e, ("x",))["x"], out2.read_episode(e, ("x",))["x"])


@pytest.mark.slow
@pytest.mark.parametrize("check, failing", [("workspace", {"workspace_min_m": [-10.0, -10.0, 5.0]}),
                                            ("blow_up", {"max_speed_m_s": 1e-4})])
def test_both_engines_reject_the_same_plans_for_the_same_check(inputs, tmp_path, check, failing):
    verdicts = {}
    for engine in ("slots", "batches"):
        r, _, rejected = _run(inputs, tmp_path, engine, engine=engine, batch_size=2, target_trajectories=4,
                              max_attempts=2, seed=2, validate={**failing, "self_intersection_every": 1})
        verdicts[engine] = sorted((e["seed"], e["reason"]) for e in r["rejected_episodes"])
        assert r["accepted"] == 0 and r["rejections"][check] == r["generated"] > 0, (r["rejections"], r["rejected_episodes"])
        if engine == "slots":  # an episode stops at its first failing frame: its slot takes the next plan
            for eid, logged in zip(rejected.episode_ids, r["rejected_episodes"]):
                frames = len(rejected.read_episode(eid, ("x",))["x"])
                assert logged["frame"] < frames <= logged["frame"] + r["sync_every"] + 1
    assert verdicts["slots"] == verdicts["batches"]


def _perturbed(scene, batch: int, noise_m: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    rest = np.concatenate([m.vertices for m in scene.objects.values()]).astype(np.float32)
    rng = np.random.default_rng(seed)
    x_prev = np.repeat(rest[None] + [0.0, 0.0, 0.001], batch, axis=0).astype(np.float32)
    x = x_prev + rng.normal(0.0, noise_m, x_prev.shape).astype(np.float32)
    x[..., 2] -= 0.003  # partly into the table
    links = scene.link_poses(np.repeat(scene.home_action()[None], batch, axis=0))
    return torch.tensor(x_prev), torch.tensor(x), torch.tensor(links)


def test_the_joint_projection_keeps_edges_and_contacts_and_the_untangling_leaves_no_crossing(scene):
    x_prev, x, links = _perturbed(scene, 3, 0.004)
    v = (x - x_prev) / 0.04
    fixed = FixedStepProjection(scene, CONFIG, torch.device("cpu"))
    fixed.prepare(x_prev)
    joint_x, joint_v = fixed.joint(x_prev, x, v, links, 0.04)
    assert float(fixed.strain(joint_x).max()) <= 0.1 + 1e-3 < float(fixed.strain(x).max())
    assert float(fixed.bodies.depth(joint_x, fixed.bodies.pose(links, joint_x)).max()) < 1e-4
    assert float(fixed.bodies.depth(x, fixed.bodies.pose(links, x)).max()) > 1e-3
    out, out_v, crossing = fixed.untangle(x_prev, joint_x, joint_v, 0.04)
    faces, edges = scene.objects["bag"].faces, unique_edges(scene.objects["bag"].faces)
    assert not crossing.any()
    for b in range(3):
        assert (crossing_edges(out[b].numpy(), faces, edges) == -1).all()
    moved = (out - joint_x).norm(dim=-1) > 0  # the untangling only takes motion back
    assert (out_v.norm(dim=-1)[moved] <= joint_v.norm(dim=-1)[moved] + (out - joint_x).norm(dim=-1)[moved] / 0.04
            + 1e-4).all()
    untouched = (x - joint_x).norm(dim=-1) == 0
    assert torch.equal(joint_v[untouched], v[untouched])  # no velocity where nothing was corrected


def test_frame_checks_are_the_validate_predicates(scene):
    cfg = load_section(load_params(), "validate", ValidateConfig)
    x_prev, x, links = _perturbed(scene, 2, 0.0)
    x = x.clone()
    x[1, :, 2] -= 0.02  # episode 1: 2 cm into the table
    bag = scene.objects["bag"]
    p = bag.vertices
    body = int(np.argsort(np.abs(p[:, 0]) + np.abs(p[:, 2] - 0.06) + 10 * (p[:, 1] - p[:, 1].min()))[0])
    x[0, body] += torch.tensor([0.0031, float(p[:, 1].max() - p[:, 1].min()) + 0.02, 0.0017])  # episode 0: a vertex
    # through the back panel (off the grid lines: a crossing, not a touch)
    fixed = FixedStepProjection(scene, CONFIG, torch.device("cpu"))
    fixed.prepare(x)
    _, crossing = fixed.rollback.crossings(fixed.bvh, x)
    bad = FrameChecks(scene, cfg, DeviceBodies(scene, torch.device("cpu")), torch.device("cpu"))(
        x, torch.zeros_like(x), links, crossing)
    for b in range(2):
        ep = Episode(x[b:b + 1].numpy(), np.zeros_like(x[b:b + 1].numpy()), np.zeros((1, 14)), links[b:b + 1].numpy(),
                     0.04)
        assert bool(bad[b, FRAME_CHECKS.index("penetration")]) == (penetration(scene, ep, cfg) is not None)
        assert bool(bad[b, FRAME_CHECKS.index("self_intersection")]) == (self_intersection(scene, ep, cfg) is not None)
    assert bad[:, FRAME_CHECKS.index("self_intersection")].tolist() == [True, False]
    assert bad[:, FRAME_CHECKS.index("penetration")].tolist() == [False, True]


def test_push_out_puts_every_vertex_on_the_surface_of_the_union(scene):
    _, x, links = _perturbed(scene, 2, 0.003, seed=3)
    bodies = DeviceBodies(scene, torch.device("cpu"))
    posed = bodies.pose(links, x)
    moved, inside = push_out(x[:, bodies.cloth], posed)
    depth = table_and_robot_distance(scene, moved.double().numpy().reshape(-1, 3)[None],
                                     links[:1].numpy()).reshape(2, -1)
    assert inside.any() and depth.min() > -1e-6
    assert torch.equal(moved[~inside], x[:, bodies.cloth][~inside])


def test_horn_rotation_is_the_kabsch_fit():
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(40, 3))
    q = rng.normal(size=(6, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, xyz = q[:, 3:], q[:, :3]
    r = np.stack([np.eye(3) + 2 * w[k] * np.cross(np.eye(3), xyz[k]) + 2 * np.cross(xyz[k], np.cross(xyz[k], np.eye(3)))
                  for k in range(6)]).transpose(0, 2, 1)  # rotations (rows: images of the axes)
    x = np.einsum("bij,nj->bni", r, rest) + rng.normal(size=(6, 1, 3)) + rng.normal(0, 0.01, (6, 40, 3))
    pos, rot = rigid_frames(rest, x)
    p2, r2 = horn_rotation(torch.tensor(rest), torch.tensor(x))
    assert np.allclose(rot, r2.numpy(), atol=1e-9) and np.allclose(pos, p2.numpy(), atol=1e-9)


def test_compaction_without_a_sync_keeps_the_true_entries_in_order():
    valid = torch.tensor([[False, True, True], [False, False, True]])
    exact, mask, lost = compact(valid, None)
    assert exact.tolist() == [1, 2, 5] and mask.all() and int(lost) == 0
    static, mask, lost = compact(valid, 4)
    assert static[mask].tolist() == [1, 2, 5] and mask.tolist() == [True, True, True, False] and int(lost) == 0
    static, mask, lost = compact(valid, 2)
    assert static.tolist() == [1, 2] and mask.all() and int(lost) == 1


def test_proposals_cover_the_expected_rejections_and_episodes_past_the_target_are_surplus():
    """The slots fill with enough proposals to cover the rejections expected at the acceptance rate filed so far (not
    one wave per rejection at the end), and once the target is reached nothing more is counted or written."""
    from wc.expand.config import ExpandConfig
    from wc.expand.slot_expansion import SlotExpansion, _Outcome

    params = expand_params()
    params["expand"].update(batch_size=8, max_attempts=100)
    cfg = load_section(params, "expand", ExpandConfig)
    written = []
    e = SlotExpansion(None, None, [], cfg, None, 0.04, 4, None, None, time.perf_counter(),
                      lambda *a: written.append(a))

    def proposals_allowed() -> int:
        n = 0
        while e._may_propose():
            e.proposed += 1
            n += 1
        return n

    assert proposals_allowed() == 4  # no verdict yet: one proposal per wanted episode
    e.filed = e.generated = 4
    e.accepted = 2  # half accepted: the 2 still wanted need 4 in flight
    assert proposals_allowed() == 4 and e.proposed - e.filed == 4
    e.accepted = 4
    assert e.done and proposals_allowed() == 0
    e.outcomes[e.filed] = _Outcome(None, infeasible="would be filed before the target")
    e._file()
    assert e.surplus == 1 and e.filed == 5 and not written and not e.infeasible
    assert e.unused == 1 + e.proposed - e.filed
    params["expand"]["slots"]["expected_acceptance"] = 0.8  # a prior: the first wave covers its rejections too
    e = SlotExpansion(None, None, [], load_section(params, "expand", ExpandConfig), None, 0.04, 4, None, None,
                      time.perf_counter(), lambda *a: None)
    assert proposals_allowed() == 5  # 4 / 0.8
    params["expand"]["slots"]["expected_acceptance"] = 0.0
    with pytest.raises(ValueError, match="expected_acceptance must be in"):
        load_section(params, "expand", ExpandConfig)


@pytest.mark.slow
def test_planning_processes_start_with_the_pool_and_plan_as_the_stage_does(inputs):
    """PlanPool's worker processes start when it is made (their start-up overlaps the model's loading) and give the
    same plans as planning in the stage's own process."""
    from wc.expand.config import ExpandConfig
    from wc.expand.plan import source_episodes
    from wc.expand.plan_pool import PlanPool
    from wc.scene.episode_scenes import EpisodeScenes
    from wc.tasks.base import EpisodeSpec, get_task

    params, store, _ = inputs
    cfg = load_section(params, "expand", ExpandConfig)
    src = TrajectoryStore(store)
    task = get_task(cfg.task, params)
    sources, scene = source_episodes(src, task, EpisodeScenes(load_section(params, "scene", SceneConfig), src))
    validate_cfg = load_section(params, "validate", ValidateConfig)
    spec = EpisodeSpec(task.name, 11, sources[0].cell, 0.45, 0.025)
    with PlanPool(params, scene, sources, cfg, src.dt, validate_cfg, 0) as here:
        expected = here.submit(spec, 0).result()
    with PlanPool(params, scene, sources, cfg, src.dt, validate_cfg, 2) as pool:
        assert len(pool._pool._processes) == 2  # both started before any plan was asked for
        got = pool.submit(spec, 0).result(timeout=300)
    assert expected.planned is not None, expected.infeasible  # a plan to compare, not two refusals
    np.testing.assert_array_equal(got.planned.actions, expected.planned.actions)
    np.testing.assert_array_equal(got.poses, expected.poses)


def test_the_expansion_line_warns_when_near_pairs_did_not_fit_the_capacities():
    """Dropped near pairs are neither bounded nor kept apart (the bag slips out of the pads): the stage's line says so
    and names the params to raise; a run that dropped none, or the reference engine (no counters), says nothing."""
    from wc.expand.stage import expand_summary

    report = {"task": "lift_handle", "accepted": 3, "generated": 4, "infeasible_plans": 0, "expanded_total": 5,
              "target_trajectories": 5, "source_episodes": 2, "target_reached": True, "trajectories_per_min": 1.0,
              "device": "cuda", "wall_s": 1.0, "rejections": {"not_lifted": 1}}
    line = expand_summary({**report, "projection_stats": {"pairs_dropped": 4535049.0}})
    assert "WARNING: 4,535,049 near cloth pairs" in line and "expand.slots.pair_capacity" in line
    for stats in ({"pairs_dropped": 0.0}, None):
        assert "WARNING" not in expand_summary({**report, "projection_stats": stats})


@pytest.mark.slow
def test_the_static_pair_path_equals_the_exact_one_when_the_capacity_suffices_and_counts_what_overflows(scene,
                                                                                                       monkeypatch):
    """The bounded step's CUDA path (fixed passes, pairs compacted into a static pool of capacity x slots) run on the
    CPU: with room for every near pair it moves the cloth exactly as the CPU's exact path; with too little room the
    overflow is counted and the pairs left out stay over their bound (what made lifts slip on the GPU)."""

    import wc.expand.fixed_untangle as fixed_untangle

    x_prev, x, _ = _perturbed(scene, 2, 0.004)
    v = (x - x_prev) / 0.04

    def bounded(capacity: int | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        fixed = FixedStepProjection(scene, replace(CONFIG, pair_capacity=capacity or 1), torch.device("cpu"))
        fixed.prepare(x_prev)
        monkeypatch.setattr(fixed_untangle, "host_checks", lambda t: capacity is None)
        out, _ = fixed.bounded.apply(fixed.bvh, x_prev, x, v, 0.04, fixed.stats)
        return out, fixed.stats

    exact, exact_stats = bounded(None)
    assert int(exact_stats["limited_pairs"]) > 0  # the step moves near pairs past their bounds: there is work
    full_lists = int(exact_stats["pairs_dropped"])  # candidate lists (16 per vertex / edge) that overflowed
    roomy, roomy_stats = bounded(20_000)
    assert int(roomy_stats["pairs_dropped"]) == full_lists
    assert torch.allclose(roomy, exact, atol=1e-7)
    tight, tight_stats = bounded(8)
    assert int(tight_stats["pairs_dropped"]) > full_lists
    assert float((tight - exact).abs().max()) > 1e-4


@pytest.mark.slow
def test_the_tail_moves_to_fewer_slots_and_gives_the_same_episodes(inputs, tmp_path):
    """Once nothing is left to load, the running episodes move where they stand to half as many slots (the frame's
    cost follows the slot count): the same episodes and verdicts as staying in all of them, their frames before the
    move the same to the bit, and the device time of the replaced slots still counted. (The projection's candidate
    pairs are chosen again for the new batch, as whenever slots load, so later frames of this random network's
    episodes differ.)"""
    runs = {}
    for least in (0, 1):
        runs[least] = _run(inputs, tmp_path, f"tail{least}", engine="slots", batch_size=4, target_trajectories=20,
                           max_attempts=6, seed=5, slots={**inputs[0]["expand"]["slots"], "tail_min_slots": least,
                                                                      "sync_every": 2})
    (r0, out0, rej0), (r1, out1, rej1) = runs[0], runs[1]
    assert r0["tail_shrinks"] == 0 and r1["tail_shrinks"] >= 1
    assert r1["generated"] == r0["generated"] >= 5 and r1["slot_loads"] == r1["generated"]  # none ran twice
    assert sorted((e["seed"], e["reason"], e["frame"]) for e in r1["rejected_episodes"]) == \
        sorted((e["seed"], e["reason"], e["frame"]) for e in r0["rejected_episodes"])
    for a, b in ((out0, out1), (rej0, rej1)):
        assert [a.episode_attrs(e)["seed"] for e in a.episode_ids] == [b.episode_attrs(e)["seed"] for e in b.episode_ids]
        for e in a.episode_ids:
            xa, xb = a.read_episode(e, ("x",))["x"], b.read_episode(e, ("x",))["x"]
            assert xa.shape == xb.shape and np.isfinite(xb).all() and np.array_equal(xa[:3], xb[:3])
    assert r1["timing"]["device_network_s"] > 0 and r1["rollout_s"] > 0


@pytest.mark.slow
def test_a_plan_longer_than_the_slots_moves_the_running_episodes_to_longer_slots(inputs, tmp_path, monkeypatch):
    """Slots sized to the first plans exactly: a longer plan later makes longer slots, and the running episodes move
    over where they stand (none starts again): the same episodes and verdicts as slots long enough from the start."""
    import wc.expand.slot_expansion as slot_expansion

    keys = dict(engine="slots", batch_size=2, target_trajectories=20, max_attempts=8, seed=1,
                slots={**inputs[0]["expand"]["slots"], "tail_min_slots": 0, "sync_every": 2})
    r0, out0, _ = _run(inputs, tmp_path, "long", **keys)
    monkeypatch.setattr(slot_expansion, "FRAMES_MARGIN", 1.0)
    r1, out1, _ = _run(inputs, tmp_path, "exact", **keys)
    assert r0["restarts"] == 0 and r1["restarts"] >= 1
    assert r1["slot_loads"] == r1["generated"] == r0["generated"]
    assert sorted((e["seed"], e["reason"]) for e in r1["rejected_episodes"]) == \
        sorted((e["seed"], e["reason"]) for e in r0["rejected_episodes"])
    assert [out0.episode_attrs(e)["seed"] for e in out0.episode_ids] == \
        [out1.episode_attrs(e)["seed"] for e in out1.episode_ids]
    for e in out0.episode_ids:
        xa, xb = out0.read_episode(e, ("x",))["x"], out1.read_episode(e, ("x",))["x"]
        assert xa.shape == xb.shape and np.isfinite(xb).all() and np.array_equal(xa[:3], xb[:3])


@pytest.mark.slow
def test_the_compiled_joint_passes_trace_whole_and_give_the_eager_passes_result(scene, monkeypatch):
    """The CUDA path (fixed passes, capacity-compacted pairs) on the CPU: torch.compile(fullgraph) of the joint and edge
    passes traces without a graph break and changes no result."""
    from wc.expand import body_contacts, fixed_projection  # noqa: PLC0415

    for module in (body_contacts, fixed_projection):
        monkeypatch.setattr(module, "host_checks", lambda t: False)
    x_prev, x, links = _perturbed(scene, 2, 0.004)
    v = (x - x_prev) / 0.04
    results = []
    for compile_passes in (False, True):
        torch._dynamo.reset()
        fixed = FixedStepProjection(scene, replace(CONFIG, iterations=3, final_edge_passes=2), torch.device("cpu"))
        if compile_passes:
            fixed.compile_passes(backend="aot_eager")
        fixed.prepare(x_prev)
        results.append(fixed.joint(x_prev, x.clone(), v.clone(), links, 0.04))
        results.append(fixed.joint(x_prev, results[-1][0], results[-1][1], links, 0.04))  # a second call: no retrace
    for (eager_x, eager_v), (compiled_x, compiled_v) in zip(results[:2], results[2:]):
        assert float(fixed.strain(eager_x).max()) < float(fixed.strain(x).max())  # the passes did something
        torch.testing.assert_close(compiled_x, eager_x, atol=1e-6, rtol=0)
        torch.testing.assert_close(compiled_v, eager_v, atol=1e-5, rtol=0)


def test_rollouts_of_the_same_slots_and_capacities_share_one_network_step(inputs):
    """A longer plan's new slots reuse the network step (compiled once when compile_network is on); another slot
    count gets its own; a rollout on the shared step runs."""
    from wc.expand.plan import source_episodes  # noqa: PLC0415
    from wc.scene.episode_scenes import EpisodeScenes  # noqa: PLC0415
    from wc.expand.slot_stage import SlotModel  # noqa: PLC0415
    from wc.model.prescribed_inputs import KinematicInputs  # noqa: PLC0415
    from wc.tasks.base import get_task  # noqa: PLC0415

    params, store, model_dir = inputs
    cfg = load_section(params, "expand", ExpandConfig)
    src = TrajectoryStore(store)
    sources, scene = source_episodes(src, get_task(cfg.task, params),
                                     EpisodeScenes(load_section(params, "scene", SceneConfig), src), cfg.max_sources)
    model = SlotModel(params, Path(model_dir), scene, src, sources, replace(cfg, batch_size=2),
                      load_section(params, "validate", ValidateConfig))
    first, longer, fewer = model.rollout(6), model.rollout(12), model.rollout(6, batch=1)
    assert longer.net is first.net and fewer.net is not first.net and len(model.steps) == 2
    home = np.repeat(scene.home_action()[None, None], 12, axis=1)
    plan = SlotPlan(sources[0].x0, KinematicInputs(scene).poses(home)[0])
    longer.load([0, 1], [plan, plan])
    longer.advance(3)
    assert longer.read_failures()[0].tolist() == [3, 3]
