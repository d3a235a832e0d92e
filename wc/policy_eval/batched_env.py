"""`BatchedLiftEnv`: B trials of the lift task closed-loop at once, as B worlds of one Newton model.

The per-trial `WorldContactLiftEnv` gives each trial its own one-world simulator; a GPU spends about as long on a
step of one world as of many, so here one `NewtonSimulator` of B worlds advances B trials per frame, one renderer
call draws every running world's views, and the policy is called once per step on the stacked observations (batch B).

What stays the per-trial env's: each trial is planned by it (`planned_reset`: the same spec, settled frame-0 state
and program per trial seed, settled in its one-world simulator, so arms and both paths stay paired by trial seed),
observations are its `observation` (the dataset's video round trip), heights its `lowest_heights`, and each trial is
judged by its own `TrialJudge`. A trial that has ended (success, a non-finite action or state, or max_steps) keeps
its verdict; its world keeps stepping with its last command held, and its observation is no longer rendered.

The physics is the per-trial env's up to the solver's order of work: NewtonSimulator colours the B-world model's
particle graph as a whole, so a world's VBD colour groups differ from the one-world model's, and VBD's few iterations
do not converge, so the order shows (on the CPU, from the same state and commands: 0.3 mm after one frame; the 0.6 s
settle of trial seed 2 ends 1.8 cm apart, which is why settling stays in the planner's one-world simulator). A
trial whose lift is near `lift_height_m` can therefore get another verdict batched than alone (the oracle's seed-2
lift: success at the same step 69, max lift 62.7 mm alone, 65.3 mm batched). Every policy's trials are cut into the
same batches, so arms stay paired. Bitwise-equal batches would need NewtonSimulator to replicate a one-world colouring
(wc/sim is frozen). A world whose state turns non-finite is judged non_finite and steps on with NaN particles; Newton
groups self-contact and shape contact by world, but that no NaN reaches another world is untested.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from wc.config import load_section
from wc.policy.dataset import RIGHT_ARM
from wc.policy_eval.env import WorldContactLiftEnv, build_renderer, trial_info
from wc.policy_eval.success import TrialJudge
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import EpisodeSpec


class BatchedLiftEnv:
    """Up to `worlds` trials at once; `planner` is the per-trial env whose plans, observations and heights it uses.

    reset(seeds) -> (observations, infos), one per trial; step(actions (B, 7)) -> (observations, infos), where an
    ended trial's observation and info stay those of its last step. `done` says whether every trial has ended."""

    def __init__(self, planner: WorldContactLiftEnv, worlds: int) -> None:
        if worlds < 1:
            raise ValueError(f"worlds must be >= 1, got {worlds}")
        self.planner, self.worlds = planner, worlds
        sim_cfg = dataclasses.replace(load_section(planner.params, "sim", SimConfig), worlds=worlds,
                                      device=planner.device)
        self.sim = NewtonSimulator(planner.world.sim_scene, sim_cfg)
        self.renderer = build_renderer(planner.params, planner.scene, planner.device, worlds)
        self.seconds = {"reset": 0.0, "physics": 0.0, "render": 0.0}
        self.seeds: list[int] = []
        self.specs: list[EpisodeSpec] = []
        self.planned_actions: list[np.ndarray] = []  # per trial (T, 14): the task's own program
        self.judges: list[TrialJudge] = []
        self.commands = np.zeros((0, 14), np.float32)  # per trial: the robot's current command

    @property
    def done(self) -> bool:
        return all(j.done for j in self.judges)

    def reset(self, seeds: list[int]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        if not 1 <= len(seeds) <= self.worlds:
            raise ValueError(f"got {len(seeds)} trials for a batch of {self.worlds} worlds")
        tic = time.perf_counter()
        plans = [self.planner.planned_reset(int(s)) for s in seeds]
        self.seeds = [int(s) for s in seeds]
        self.specs = [p[0] for p in plans]
        self.planned_actions = [p[2] for p in plans]
        self.commands = np.stack([p[0] for p in self.planned_actions]).astype(np.float32)
        self.sim.set_state([p[1] for p in plans], self.commands)  # idle worlds repeat the last trial
        self.judges = [self.planner.new_judge(p) for p in self.planned_actions]
        self.seconds["reset"] += time.perf_counter() - tic
        x = np.stack([p[1].x for p in plans])
        heights = self.planner.lowest_heights(x)
        starts = [j.start(h) for j, h in zip(self.judges, heights)]  # frame 0 counts, as in the per-trial env
        self.observations = self._observe(x, self.commands)
        self.infos = [self._info(i, s, h) for i, (s, h) in enumerate(zip(starts, heights))]
        return list(self.observations), list(self.infos)

    def step(self, actions: np.ndarray) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """Right-arm actions (B, 7) (rows of ended trials are ignored: their worlds hold their last command)."""
        if not self.judges or self.done:
            raise RuntimeError("step() after every trial ended: call reset() first")
        actions = np.asarray(actions, np.float32)
        if actions.shape != (len(self.seeds), 7):
            raise ValueError(f"actions must be ({len(self.seeds)}, 7): per trial the right arm q_R (6, rad) + "
                             f"gripper opening (m), got {actions.shape}")
        running = [i for i, j in enumerate(self.judges) if not j.done]
        failures: dict[int, str] = {}
        now, nxt = self.commands.copy(), self.commands.copy()
        for i in running:
            command = np.concatenate([self.planned_actions[i][0, :RIGHT_ARM.start], actions[i]])
            if np.isfinite(command).all():
                nxt[i] = command
            else:
                failures[i] = "non_finite_action"  # its world holds the last command
        tic = time.perf_counter()
        self.sim.advance_frame(self._padded(now), self._padded(nxt))
        x = self.sim.read_state()[0][:len(self.seeds)]  # (B, N, 3)
        self.seconds["physics"] += time.perf_counter() - tic
        self.commands = nxt
        for i in running:
            if i not in failures and not np.isfinite(x[i]).all():
                failures[i] = "non_finite"
        observed = [i for i in running if i not in failures]
        heights = dict(zip(observed, self.planner.lowest_heights(x[observed])))
        if observed:
            for i, observation in zip(observed, self._observe(x[observed], nxt[observed])):
                self.observations[i] = observation
        for i in running:
            height = heights.get(i, float("nan"))
            success, _, _ = self.judges[i].step(height, failures.get(i))
            self.infos[i] = self._info(i, success, height)
        return list(self.observations), list(self.infos)

    def _padded(self, commands: np.ndarray) -> np.ndarray:
        """(worlds, 14): the trials' commands, idle worlds repeating the last."""
        return np.concatenate([commands, np.repeat(commands[-1:], self.worlds - len(commands), axis=0)])

    def _observe(self, x: np.ndarray, commands: np.ndarray) -> list[dict[str, Any]]:
        """Observations of states x (n, N, 3) under robot commands (n, 14), rendered in one call."""
        tic = time.perf_counter()
        frames = self.renderer.render(x, self.planner.scene.link_poses(commands), "policy_eval")
        out = [self.planner.observation({n: f[k] for n, f in frames.items()}, c) for k, c in enumerate(commands)]
        self.seconds["render"] += time.perf_counter() - tic
        return out

    def _info(self, i: int, success: bool, height: float) -> dict[str, Any]:
        return trial_info(self.judges[i], success, height, self.seeds[i], self.specs[i].seed) | {
            "done": self.judges[i].done}
