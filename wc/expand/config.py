"""The `expand` params section: which task to expand, how many trajectories, how to draw new initial states."""

from __future__ import annotations

from dataclasses import dataclass

from wc.devices import check_device_name
from wc.distributed.config import check_executor

Range = tuple[float, float]


@dataclass(frozen=True)
class SlotConfig:
    """The slot engine (`engine: slots`, wc.expand.slot_expansion): the episodes of a batch run in slots that refill
    as episodes end or fail; the projection runs fixed pass counts (the reference loop stops once converged)."""

    sync_every: int = 8  # frames between the host's reads of the slots' first failures (one sync each)
    plans_ahead: int = 0  # episodes proposed and not yet filed at most (0: twice batch_size)
    expected_acceptance: float = 1.0  # acceptance assumed before the first verdict: the first wave proposes the wanted
    # episodes / this, so the replacements of its rejections need no wave of their own (1.0: exactly the wanted)
    planner_workers: int = 0  # planning processes beside the rollouts (0: in the stage's process)
    tail_min_slots: int = 16  # once nothing is left to load, the running episodes move to half as many slots while
    # they fill at most half, down to this many, when the frames left outweigh a capture (a frame's cost follows the
    # slot count, busy or not); 0: never; nor with compile_* on (a new slot count compiles again)
    bf16: bool = True  # the network in bf16 autocast (CUDA; the state stays fp32)
    cuda_graph: bool = True  # each part of a frame captured as a CUDA graph (CUDA)
    compile_network: bool = False  # the network's step through torch.compile (CUDA; compiles once per slot count)
    compile_projection: bool = False  # the joint projection's passes through torch.compile (CUDA; once per slot count)
    iterations: int = 10  # joint projection passes (edges, contacts, self-contact) per step
    final_edge_passes: int = 20  # edge-only passes after them
    bounded_rounds: int = 2  # bounded step: distance measurements and tries at the rest of the step
    bounded_passes: int = 10  # bounded step: Jacobi passes per round
    rollback_rounds: int = 12  # rollback rounds (a shorter step for a ring wider each round)
    vertex_pairs: int = 16  # candidate triangles kept per cloth vertex (self-contact, bounded step)
    edge_pairs: int = 16  # candidate edges kept per cloth edge (bounded step)
    pair_capacity: int = 512  # bounded step: near element pairs per episode its passes handle on CUDA (overflow counted)
    self_contact_capacity: int = 256  # self-contact: vertex-triangle pairs per episode handled on CUDA (overflow counted)

    def validate(self) -> None:
        for name in ("sync_every", "iterations", "bounded_passes", "vertex_pairs", "edge_pairs", "pair_capacity",
                     "self_contact_capacity"):
            if getattr(self, name) < 1:
                raise ValueError(f"slots.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("plans_ahead", "planner_workers", "tail_min_slots", "final_edge_passes", "bounded_rounds",
                     "rollback_rounds"):
            if getattr(self, name) < 0:
                raise ValueError(f"slots.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.expected_acceptance <= 1.0:
            raise ValueError(f"slots.expected_acceptance must be in (0, 1], got {self.expected_acceptance}")


@dataclass(frozen=True)
class ExpandConfig:
    """World-model data expansion of one task's source episodes (wc.expand.stage)."""

    task: str  # registered task program whose source episodes are expanded, e.g. lift_handle
    target_trajectories: int  # source episodes of the task + accepted generated ones wanted (paper: 150)
    max_attempts: int  # generated episodes tried at most, infeasible plans included
    batch_size: int  # generated episodes rolled out together (padded to the longest by holding the last action)
    yaw_range_deg: Range  # extra bag yaw about z through its centroid, on top of the cell's yaw bin offset
    shift_x_range_m: Range  # bag xy shift, uniform per axis
    shift_y_range_m: Range
    max_sources: int = 0  # the task's first accepted episodes in store order used as sources at most (0: all; paper: 25)
    task_check: bool = True  # also apply the task's own verdict (lift_handle: not_lifted), as the simulator agent does
    write_processes: int = 0  # processes writing the episodes' arrays (0: a thread of the stage's process)
    # after each predicted step: "joint" projects cloth edge limits and contacts together (wc.expand.constraints),
    # "contact" only pushes cloth out of bodies (wc.expand.contact), "none" keeps the model's step
    projection: str = "joint"
    projection_iterations: int = 50  # joint: loop passes at most (it stops once edges and contacts hold)
    projection_edge_ratio: Range = (0.9, 1.1)  # joint: edge length / rest length kept within these
    projection_final_edge_passes: int = 0  # joint: edge-only passes after a loop that left edges violated (0: none)
    pad_carry: bool = False  # joint: cloth held between closed finger pads moves with them (wc.expand.carry)
    pad_carry_radius_m: float = 0.004  # ... a cloth vertex this close to both pads of one arm is held
    self_contact: bool = False  # joint: cloth kept sim.self_contact_gap_m from its own triangles (wc.expand.self_contact)
    # joint: what keeps a projected step from making the cloth cross itself: "none"; "rollback", crossings the step
    # leaves rolled back (wc.expand.untangle); "bounded", relative motions bounded by element distances so that no
    # crossing can form (wc.expand.crossing_free)
    untangle: str = "none"
    untangle_rounds: int = 4  # rollback: shorter steps tried at most (1/2, 1/4, ..., the last one none);
    # bounded: distance measurements (and tries at the rest of the step) at most
    untangle_share: float = 0.8  # bounded: share of a pair's distance its ends may move relative to each other
    device: str = "cpu"  # cpu | cuda | cuda:k | auto
    seed: int = 0
    max_minutes: float = 0.0  # no batch started after this much wall time (0: no limit); the report says so
    executor: str = "local"  # local: in this process; ray / processes: each batch's rollouts and checks as a Ray
    # task / in one process per GPU (engine batches)
    batches_in_flight: int = 1  # batches planned before the earlier ones' verdicts are filed (1: each plan sees every
    # earlier verdict); the episodes depend on it, not on the executor
    # slots: batch_size slots refilled as episodes end or fail, fixed-pass projection, checks on the device
    # (wc.expand.slot_expansion; local executor); batches: batch by batch, the reference (wc.expand.worker)
    engine: str = "slots"
    slots: SlotConfig = SlotConfig()
    # independent expansions of fixed shares of the episodes and attempts, each with its own plan seeds, run in the
    # `processes` executor's device processes and concatenated in shard order (wc.expand.shards)
    shards: int = 1

    def validate(self) -> None:
        if not self.task:
            raise ValueError("task must name a task program")
        for name in ("target_trajectories", "max_attempts", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_sources < 0:
            raise ValueError(f"max_sources must be >= 0 (0: every accepted episode), got {self.max_sources}")
        if self.write_processes < 0:
            raise ValueError(f"write_processes must be >= 0 (0: in the stage's process), got {self.write_processes}")
        for name in ("yaw_range_deg", "shift_x_range_m", "shift_y_range_m"):
            low, high = getattr(self, name)
            if not low <= high:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(low, high)}")
        if self.projection not in ("joint", "contact", "none"):
            raise ValueError(f"projection must be joint, contact or none, got {self.projection!r}")
        if not self.pad_carry_radius_m > 0:
            raise ValueError(f"pad_carry_radius_m must be positive, got {self.pad_carry_radius_m}")
        if self.untangle not in ("none", "rollback", "bounded", "bounded+rollback"):
            raise ValueError(f"untangle must be none, rollback, bounded or bounded+rollback, got {self.untangle!r}")
        if not 0 < self.untangle_share < 1:
            raise ValueError(f"untangle_share must be in (0, 1), got {self.untangle_share}")
        for name in ("pad_carry", "untangle", "self_contact"):
            if getattr(self, name) not in (False, "none") and self.projection != "joint":
                raise ValueError(f"{name} needs projection 'joint', got {self.projection!r}")
        if self.untangle_rounds < 1:
            raise ValueError(f"untangle_rounds must be >= 1, got {self.untangle_rounds}")
        if not self.max_minutes >= 0:
            raise ValueError(f"max_minutes must be >= 0 (0: no limit), got {self.max_minutes}")
        if self.projection_iterations < 1:
            raise ValueError(f"projection_iterations must be >= 1, got {self.projection_iterations}")
        if self.projection_final_edge_passes < 0:
            raise ValueError(f"projection_final_edge_passes must be >= 0, got {self.projection_final_edge_passes}")
        lo, hi = self.projection_edge_ratio
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"projection_edge_ratio must satisfy 0 < min <= 1 <= max, got {self.projection_edge_ratio}")
        check_device_name(self.device)
        check_executor(self.executor)
        if self.batches_in_flight < 1:
            raise ValueError(f"batches_in_flight must be >= 1, got {self.batches_in_flight}")
        if self.shards < 1:
            raise ValueError(f"shards must be >= 1, got {self.shards}")
        if self.shards > 1:
            if self.executor != "local":
                raise ValueError(f"shards > 1 run on the processes section's devices: executor must be local, got "
                                 f"{self.executor!r}")
            if ":" in self.device:
                raise ValueError(f"device must be cpu, cuda or auto with shards > 1 (a shard's process sees only its "
                                 f"own GPU, as cuda), got {self.device!r}")
            if self.max_attempts < self.shards:
                raise ValueError(f"max_attempts must be >= shards (each shard tries a share of them), got "
                                 f"{self.max_attempts} < {self.shards}")
        if self.engine not in ("slots", "batches"):
            raise ValueError(f"engine must be slots or batches, got {self.engine!r}")
        if self.engine == "slots":
            if self.executor != "local":
                raise ValueError(f"engine slots runs in the stage's process: executor must be local, got "
                                 f"{self.executor!r} (engine batches runs on ray or processes; shards place slot "
                                 "expansions on devices)")
            if self.projection != "joint" or self.pad_carry:
                raise ValueError("engine slots projects jointly without pad carry (projection joint, pad_carry false); "
                                 "use engine batches for the others")
        self.slots.validate()
