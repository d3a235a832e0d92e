"""World-model data expansion (stage `expand`): new initial states by rigid planar transforms of settled source
frames, new action sequences from the task programs, batched WorldContact rollouts (optionally contact-projected
after every step), the source data's checks."""

from wc.expand.config import ExpandConfig
from wc.expand.contact import ContactProjectedPredictor, ContactProjection
from wc.expand.plan import (NoSourceEpisodesError, PlannedEpisode, SourceEpisode, check_clear_at_start, pick_parent,
                            plan_episode, presettle_state, source_episodes)
from wc.expand.batched_rollout import Rollout, rollout_batch
from wc.expand.stage import expand
from wc.expand.transform import check_on_table, planar_transform
from wc.expand.worker import verdict

__all__ = ["ContactProjectedPredictor", "ContactProjection", "ExpandConfig", "NoSourceEpisodesError",
           "PlannedEpisode", "Rollout", "SourceEpisode", "check_clear_at_start", "check_on_table", "expand",
           "pick_parent", "plan_episode", "planar_transform", "presettle_state", "rollout_batch",
           "source_episodes", "verdict"]
