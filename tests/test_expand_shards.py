"""`expand.shards` (wc.expand.shards): the expansion split into fixed shares with their own plan seeds, run in the
processes executor's device processes and concatenated in shard order: the same stores whether the shards run on one
process or on two; the report sums the shards' counts and says where each ran; bad values name the key."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import load_params
from tests.expand_inputs import expand_params, write_source_store, write_tiny_model
from tests.test_ray_stages import _same_stores
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.expand import ExpandConfig, expand
from wc.expand.plan import plan_seed
from wc.expand.shards import combined_report, share
from wc.expand.stage import _params_hash


@pytest.mark.parametrize("total, shards, shares", [(5, 2, [3, 2]), (2, 3, [1, 1, 0]), (8, 1, [8])])
def test_shares_are_fixed_and_add_up(total, shards, shares):
    assert [share(total, shards, i) for i in range(shards)] == shares


def test_shard_0_draws_the_unsharded_seeds_and_shards_differ():
    assert plan_seed(3, 0, 0) == plan_seed(3, 0, 0) != plan_seed(3, 1, 0)


@pytest.mark.parametrize("overrides, message", [
    (["expand.shards=0"], "expand: shards must be >= 1, got 0"),
    (["expand.shards=2", "expand.engine=batches", "expand.executor=processes"],
     "expand: shards > 1 run on the processes section's devices: executor must be local, got 'processes'"),
    (["expand.shards=2", "expand.device=cuda:1"], "expand: device must be cpu, cuda or auto with shards > 1"),
    (["expand.shards=9", "expand.max_attempts=8"], r"expand: max_attempts must be >= shards .*, got 8 < 9"),
])
def test_bad_shard_params_are_named(overrides, message):
    with pytest.raises(ParamsError, match=message):
        load_section(load_params(*overrides), "expand", ExpandConfig)


def test_shards_change_the_params_hash_and_their_placement_does_not():
    base = load_params()
    assert _params_hash(load_params("expand.shards=2")) != _params_hash(base)
    assert _params_hash(load_params("processes.devices=3")) == _params_hash(base)


def test_the_report_sums_the_shards():
    def shard(accepted: int, generated: int) -> dict[str, Any]:
        return {"attempts": generated + 1, "infeasible_plans": 1, "generated": generated, "accepted": accepted,
                "rejected": generated - accepted, "frames_generated": 10 * generated, "rollout_s": 1.0,
                "rejections": {"blow_up": generated - accepted}, "rejected_episodes": [{"seed": generated}],
                "infeasible": [], "projection_stats": {"steps": 5, "max_depth_after_m": 0.1 * accepted},
                "untangle_stats": None, "wanted_generated": 2, "source_episodes": 2, "target_trajectories": 6,
                "stopped_early": False, "device": "cpu", "wall_s": 3.0}

    placed = [{"gpu": "0", "pid": 1}, {"gpu": "1", "pid": 2}]
    r = combined_report([shard(2, 3), shard(1, 4)], placed, wall_s=6.0)
    assert (r["accepted"], r["generated"], r["attempts"], r["wanted_generated"]) == (3, 7, 9, 4)
    assert r["rejections"] == {"blow_up": 4} and r["rejected_episodes"] == [{"seed": 3}, {"seed": 4}]
    assert r["projection_stats"] == {"steps": 10, "max_depth_after_m": 0.2}
    assert (r["expanded_total"], r["target_reached"], r["accepted_per_min"]) == (5, False, 30.0)
    assert [(s["shard"], s["gpu"], s["accepted"]) for s in r["shards"]] == [(0, "0", 2), (1, "1", 1)]


@pytest.fixture(scope="module")
def sharded(tmp_path_factory) -> tuple[Path, dict[str, Any]]:
    """The same two-shard expansion with both shards on one process and on two."""
    folder = tmp_path_factory.mktemp("shards")
    params = expand_params()
    params["expand"].update(shards=2)
    store, model = write_source_store(folder, params), write_tiny_model(folder, params)
    runs = {}
    for devices in (1, 2):
        p = copy.deepcopy(params)
        p["processes"]["devices"] = devices
        d = folder / f"devices{devices}"
        runs[devices] = expand(p, model, store, d / "e.zarr", d / "e.json", d / "rejected.zarr")
    return folder, runs


@pytest.mark.slow
def test_two_shards_write_the_same_stores_on_one_process_or_two(sharded):
    folder, runs = sharded
    one, two = runs[1], runs[2]
    accepted = _same_stores(folder / "devices1/e.zarr", folder / "devices2/e.zarr")
    _same_stores(folder / "devices1/rejected.zarr", folder / "devices2/rejected.zarr")
    assert len(accepted) == one["accepted"] == sum(s["accepted"] for s in one["shards"]) >= 1
    assert one["params_hash"] == two["params_hash"] == TrajectoryStore(folder / "devices1/e.zarr").attrs["params_hash"]
    timing = ("wall_s", "trajectories_per_min", "accepted_per_min", "model_frames_per_s", "rollout_s", "executor",
              "out", "rejected_out", "shards", "environment")
    assert {k: v for k, v in one.items() if k not in timing} == {k: v for k, v in two.items() if k not in timing}
    assert (one["executor"]["devices"], two["executor"]["devices"]) == (["cpu"], ["cpu", "cpu"])
    assert len({s["process"] for s in one["shards"]}) == 1 and len({s["process"] for s in two["shards"]}) == 2
    assert [s["wanted_generated"] for s in one["shards"]] == [1, 1]  # 4 target - 2 sources, shared out


@pytest.mark.slow
def test_each_shard_draws_its_own_plan_seeds(sharded):
    folder, runs = sharded
    seeds = [TrajectoryStore(folder / "devices1/e.zarr").episode_attrs(e)["seed"]
             for e in TrajectoryStore(folder / "devices1/e.zarr").episode_ids]
    rejected = [r["seed"] for r in runs[1]["rejected_episodes"]] + [i["seed"] for i in runs[1]["infeasible"]]
    drawn = {plan_seed(3, shard, i) for shard in (0, 1) for i in range(3)}  # expand.seed 3, 3 attempts a shard
    assert set(seeds + rejected) <= drawn and seeds
    assert not list(folder.glob("devices*/.e.zarr.tmp-*"))  # the shards' temporary stores are gone
