"""Closed-loop evaluation of trained lerobot policies in the Newton simulator (the `policy_eval` stage).

`env.WorldContactLiftEnv` is the gymnasium environment (also registered as a lerobot env plugin by the
top-level package `lerobot_env_worldcontact`); `stage.run` evaluates every trained policy on the same
trial seeds and writes reports/policy.json, episode videos and a success-rate plot.
"""
