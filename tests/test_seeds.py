"""Simulate, expand and policy evaluation draw episode seeds from disjoint streams (wc/seeds.py)."""

import numpy as np
import pytest

from tests.conftest import load_params
from wc.config import ParamsError, load_section
from wc.policy_eval.config import PolicyEvalConfig
from wc.seeds import STREAM_SPAN, SeedStream, episode_seed, stream_of, stream_range



def test_each_stage_stream_holds_only_its_own_seeds():
    drawn = {stream: {episode_seed(0, task, i, stream) for task in range(4) for i in range(200)} for stream in SeedStream}
    for stream, seeds in drawn.items():
        assert len(seeds) == 800  # independent draws, no repeats inside a stream
        assert all(seed in stream_range(stream) and stream_of(seed) is stream for seed in seeds)
    assert not drawn[SeedStream.SIMULATE] & drawn[SeedStream.EXPAND]
    assert not drawn[SeedStream.SIMULATE] & drawn[SeedStream.POLICY_EVAL]
    assert not drawn[SeedStream.EXPAND] & drawn[SeedStream.POLICY_EVAL]


def test_the_same_indices_give_different_episodes_in_different_streams():
    """Expand once asked for (seed 0, task 0, i), simulate's first task's stream: the draw is shared, the seed not."""
    sim, exp = episode_seed(0, 0, 3), episode_seed(0, 0, 3, SeedStream.EXPAND)
    assert exp - sim == STREAM_SPAN
    assert np.random.default_rng(sim).random() != np.random.default_rng(exp).random()


def test_simulate_seeds_are_the_plain_uint32_draws():
    """Stream 0 keeps the seeds simulate has always drawn, so existing source data stay reproducible."""
    draw = int(np.random.SeedSequence([7, 2, 5]).generate_state(1)[0])
    assert episode_seed(7, 2, 5) == draw < 2**32


def test_a_seed_outside_every_stream_is_an_error():
    with pytest.raises(ValueError, match="outside every seed stream"):
        stream_of(len(SeedStream) * STREAM_SPAN)
    with pytest.raises(ValueError, match="outside every seed stream"):
        stream_of(-1)


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_shipped_policy_trials_live_in_the_policy_stream(file):
    cfg = load_section(load_params(file=file), "policy_eval", PolicyEvalConfig)
    for trial in range(cfg.trials):
        assert stream_of(cfg.seed_offset + cfg.seed + trial) is SeedStream.POLICY_EVAL


@pytest.mark.parametrize("offset", [0, 2**32, 3 * 2**32 - 1])  # simulate's, expand's, the last trial past the end
def test_policy_trial_seeds_outside_their_stream_are_refused(offset):
    params = load_params(f"policy_eval.seed_offset={offset}", "policy_eval.trials=2")
    with pytest.raises(ParamsError, match="policy seed stream"):
        load_section(params, "policy_eval", PolicyEvalConfig)
