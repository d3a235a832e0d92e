"""One closed-loop episode of an actor in the lift env (or a batch of them in the batched env), and the actor that
runs a lerobot policy.

The policy sees what it saw in training: lerobot's own `preprocess_observation` turns the env's
observations, stacked, into observation.images.<camera> (B, 3, H, W) float in [0, 1] and observation.state (B, 7),
the instruction goes in as `task`, then the policy's saved preprocessor, `select_action` (its action
queue: chunk_size predicted, n_action_steps executed, per batch row) and postprocessor (unnormalise).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.policies import PreTrainedPolicy
from lerobot.processor import PolicyProcessorPipeline
from lerobot.utils.constants import OBS_IMAGES

from wc.policy.dataset import RIGHT_ARM
from wc.policy_eval.batched_env import BatchedLiftEnv
from wc.policy_eval.env import WorldContactLiftEnv, side_by_side
from wc.tasks.base import EpisodeSpec


class Actor(Protocol):
    def reset(self) -> None: ...

    def __call__(self, observation: dict[str, Any]) -> np.ndarray:
        """(7,) right-arm action for the env observation."""
        ...


class BatchActor(Protocol):
    def reset(self) -> None: ...

    def act(self, observations: list[dict[str, Any]]) -> np.ndarray:
        """(B, 7) right-arm actions for B env observations (one batch: the trials started together)."""
        ...


@dataclass(frozen=True)
class TrialOutcome:
    seed: int  # trial seed
    episode_seed: int  # seed_offset + seed: the initial-state sampler's seed
    success: bool
    steps: int  # env steps taken (the success step included)
    max_lift_m: float  # highest lowest-bag-vertex height above the table top over the episode
    failure: str | None  # None on success; not_lifted | dropped | not_held | non_finite | non_finite_action
    cell: int  # the task's coverage cell, speed and amplitude drawn for the trial
    speed: float
    amplitude: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def trial_outcome(info: dict[str, Any], spec: EpisodeSpec) -> TrialOutcome:
    """The outcome of a trial from its last step's info and its spec."""
    return TrialOutcome(seed=int(info["trial_seed"]), episode_seed=int(info["episode_seed"]),
                        success=bool(info["is_success"]), steps=int(info["steps"]),
                        max_lift_m=float(info["max_lift_m"]), failure=info["failure"] or None, cell=spec.cell,
                        speed=spec.speed, amplitude=spec.amplitude)


def stack_observations(observations: list[dict[str, Any]]) -> dict[str, Any]:
    """B env observations as one vector-env observation: pixels.<camera> (B, H, W, 3), agent_pos (B, 7)."""
    first = observations[0]
    return {"pixels": {n: np.stack([o["pixels"][n] for o in observations]) for n in first["pixels"]},
            "agent_pos": np.stack([o["agent_pos"] for o in observations])}


class PolicyActor:
    """A lerobot policy with its pre-/post-processors (wc.policy.finetune.load_policy) as an Actor."""

    def __init__(self, policy: PreTrainedPolicy, preprocessor: PolicyProcessorPipeline,
                 postprocessor: PolicyProcessorPipeline, instruction: str) -> None:
        self.policy, self.preprocessor, self.postprocessor = policy, preprocessor, postprocessor
        self.instruction = instruction

    def reset(self) -> None:
        self.policy.reset()

    def __call__(self, observation: dict[str, Any]) -> np.ndarray:
        return self.act([observation])[0]

    def act(self, observations: list[dict[str, Any]]) -> np.ndarray:
        batch = preprocess_observation(stack_observations(observations))
        check_inputs(self.policy, batch)
        batch["task"] = [self.instruction] * len(observations)
        with torch.inference_mode():
            action = self.postprocessor(self.policy.select_action(self.preprocessor(batch)))
        return action.detach().to("cpu", torch.float32).numpy().reshape(len(observations), -1)


def check_inputs(policy: PreTrainedPolicy, batch: dict[str, Any]) -> None:
    """Raise a clear error if the env's observation lacks an input the policy was trained on, or an image
    differs in size (the dataset was rendered at other render.width / height)."""
    for key, feature in policy.config.input_features.items():
        if key not in batch:
            raise ValueError(f"the policy expects input {key!r}, the env provides {sorted(batch)}")
        if key.startswith(OBS_IMAGES) and tuple(batch[key].shape[1:]) != tuple(feature.shape):
            raise ValueError(f"policy input {key} is {tuple(feature.shape)} (C, H, W), the env renders "
                             f"{tuple(batch[key].shape[1:])}: set render.width / height to the training size")


def run_episode(env: WorldContactLiftEnv, actor: Actor, seed: int, record: bool = False,
                on_step: Callable[[], None] | None = None) -> tuple[TrialOutcome, list[np.ndarray], float]:
    """Reset the env to trial `seed` and the actor, act until the episode ends. Returns the outcome, the
    frames (top | wrist, (H, 2W, 3) uint8, one per frame incl. frame 0) when `record`, and the mean seconds
    per closed-loop step (policy + physics + rendering)."""
    actor.reset()
    torch.manual_seed(seed)  # policies that sample (pi0.5's denoising noise) repeat per trial seed
    observation, info = env.reset(seed=seed)
    frames = [env.render()] if record else []
    tic = time.perf_counter()
    done = False
    while not done:
        observation, _, terminated, truncated, info = env.step(actor(observation))
        done = terminated or truncated
        if record:
            frames.append(env.render())
        if on_step is not None:
            on_step()
    s_per_step = (time.perf_counter() - tic) / max(info["steps"], 1)
    return trial_outcome(info, env.episode_spec), frames, s_per_step


def run_batch(env: BatchedLiftEnv, actor: BatchActor, seeds: list[int], record: list[bool] | None = None,
              on_step: Callable[[], None] | None = None) -> tuple[list[TrialOutcome], list[list[np.ndarray]], float]:
    """Reset the batched env to trials `seeds` and the actor, act on every trial at once until all have ended. Returns
    per trial its outcome and its frames (as run_episode's, up to its own end) where `record` says, and the mean
    seconds per closed-loop step of the batch (one policy call + one physics frame + rendering for all trials)."""
    record = record or [False] * len(seeds)
    actor.reset()
    torch.manual_seed(seeds[0])  # a sampling policy repeats per batch (its first trial seed)
    observations, infos = env.reset(seeds)
    frames = [[side_by_side(o)] if r else [] for o, r in zip(observations, record)]
    tic, steps = time.perf_counter(), 0
    while not env.done:
        running = [not info.get("done", False) for info in infos]
        observations, infos = env.step(actor.act(observations))
        steps += 1
        for i, (was_running, r) in enumerate(zip(running, record)):
            if was_running and r:
                frames[i].append(side_by_side(observations[i]))
        if on_step is not None:
            on_step()
    s_per_step = (time.perf_counter() - tic) / max(steps, 1)
    return [trial_outcome(info, spec) for info, spec in zip(infos, env.specs)], frames, s_per_step


class OracleActor:
    """Replays the task's own planned program (the open-loop demonstration) through the env: frame k's
    action is planned[k + 1, right arm], the last one held. `act`: the same for every trial of a batched env."""

    def __init__(self, env: WorldContactLiftEnv | BatchedLiftEnv) -> None:
        self.env, self.k = env, 0

    def reset(self) -> None:
        self.k = 0

    def __call__(self, observation: dict[str, Any]) -> np.ndarray:
        self.k += 1
        return _planned_step(self.env.planned_actions, self.k)

    def act(self, observations: list[dict[str, Any]]) -> np.ndarray:
        self.k += 1
        return np.stack([_planned_step(planned, self.k) for planned in self.env.planned_actions])


def _planned_step(planned: np.ndarray, k: int) -> np.ndarray:
    """The right-arm action of frame k of a planned program (T, 14), its last held."""
    return planned[min(k, len(planned) - 1), RIGHT_ARM].copy()
