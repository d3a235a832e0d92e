"""Params of the `policy_eval` stage (`policy_eval:` in params.yaml)."""

from __future__ import annotations

from dataclasses import dataclass

from wc.devices import check_device_name
from wc.seeds import SeedStream, stream_range

POLICY_SEEDS = stream_range(SeedStream.POLICY_EVAL)  # trial episode seeds live here, apart from simulate's and expand's


@dataclass(frozen=True)
class PolicyEvalConfig:
    task: str  # task program whose initial states are sampled (the policy's task), e.g. lift_handle
    trials: int  # seeded episodes per policy (paper: 20); the same trial seeds for every policy
    seed: int  # first trial seed; trial i has seed `seed + i` (lerobot-eval's --seed convention)
    seed_offset: int  # episode seed = seed_offset + trial seed, inside the policy seed stream (wc.seeds)
    lift_height_m: float  # success: the bag's lowest vertex at least this far above the table top ...
    hold_s: float  # ... at every frame for this long
    max_steps: int | None  # steps per episode; null: the task program's own length plus the hold
    device: str  # simulator, renderer and policy: cpu | cuda | cuda:k | auto
    videos: int  # episodes recorded as mp4 per policy (the first trials)
    workers: int = 1  # processes running trials side by side (each its own env; on a GPU they share it)
    batch: int = 0  # trials of a policy run at once as the worlds of one Newton model, one policy call per step for
    # all (wc.policy_eval.batched_env); 0: each trial alone in a one-world env (what lerobot-eval's plugin env runs)

    def validate(self) -> None:
        if self.trials < 1:
            raise ValueError(f"trials must be >= 1, got {self.trials}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        first, last = self.seed_offset + self.seed, self.seed_offset + self.seed + self.trials - 1
        if first not in POLICY_SEEDS or last not in POLICY_SEEDS:
            raise ValueError(f"seed_offset + seed .. + trials - 1 ({first} .. {last}) must lie in the policy seed stream "
                             f"[{POLICY_SEEDS.start}, {POLICY_SEEDS.stop}) so trial episodes never repeat a simulate "
                             f"or expand episode; seed_offset {POLICY_SEEDS.start} (2 * 2**32) does")
        if not self.lift_height_m > 0:
            raise ValueError(f"lift_height_m must be positive, got {self.lift_height_m}")
        if self.hold_s < 0:
            raise ValueError(f"hold_s must be >= 0, got {self.hold_s}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or null, got {self.max_steps}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.batch < 0:
            raise ValueError(f"batch must be >= 0 (0: one trial per env, N: N trials per batch), got {self.batch}")
        if self.videos < 0:
            raise ValueError(f"videos must be >= 0, got {self.videos}")
        check_device_name(self.device)
