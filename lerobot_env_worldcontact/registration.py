"""The gymnasium id of the lift environment."""

from __future__ import annotations

import gymnasium as gym

from lerobot_env_worldcontact.config import GYM_ID

ENTRY_POINT = "wc.policy_eval.env:WorldContactLiftEnv"


def register() -> None:
    """Register GYM_ID once (importing the package twice, or reloading it, is harmless)."""
    if GYM_ID not in gym.registry:
        gym.register(id=GYM_ID, entry_point=ENTRY_POINT)
