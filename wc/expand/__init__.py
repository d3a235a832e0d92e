"""World-model data expansion (stage `expand`): new initial states by rigid planar transforms of settled source
frames, new action sequences from the task programs, batched WorldContact rollouts, the source data's checks."""

from wc.expand.config import ExpandConfig
from wc.expand.plan import NoSourceEpisodesError, PlannedEpisode, SourceEpisode, plan_episode, source_episodes
from wc.expand.rollout import Rollout, finite_rollout, rollout_batch
from wc.expand.stage import expand, verdict
from wc.expand.transform import check_on_table, planar_transform

__all__ = ["ExpandConfig", "NoSourceEpisodesError", "PlannedEpisode", "Rollout", "SourceEpisode", "check_on_table",
           "expand", "finite_rollout", "plan_episode", "planar_transform", "rollout_batch", "source_episodes",
           "verdict"]
