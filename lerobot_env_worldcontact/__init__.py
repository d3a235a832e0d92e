"""lerobot env plugin: the WorldContact lift task in the Newton simulator.

Importing this package registers the gymnasium id `gym_worldcontact/LiftBag-v0`
(wc.policy_eval.env.WorldContactLiftEnv) and the lerobot `EnvConfig` choice `worldcontact`, so
`lerobot.envs.make_env` and stock `lerobot-eval` build it:

    lerobot-eval --env.discover_packages_path=lerobot_env_worldcontact --env.type=worldcontact \
        --env.params=params.yaml --policy.path=models/policy/source --eval.n_episodes=20 --eval.batch_size=1 \
        --seed=0 --policy.device=cpu --output_dir=outputs/eval_source

(lerobot's `register_third_party_plugins` also imports it by itself once it is installed as a
distribution named `lerobot_env_worldcontact`.)
"""

from __future__ import annotations

from lerobot_env_worldcontact.config import GYM_ID, WorldContactEnvConfig
from lerobot_env_worldcontact.registration import register

register()

__all__ = ["GYM_ID", "WorldContactEnvConfig", "register"]
