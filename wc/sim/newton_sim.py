"""The source simulator: Newton `SolverVBD` cloth + rigid bodies, robot links driven kinematically.

One Newton world per episode; `worlds > 1` simulates several episodes at once (GPU throughput).
Robot links are kinematic root bodies whose poses come from our batched FK of the commanded
action, interpolated per substep so contact sees the right link velocities. `NewtonSimulator` is a
`wc.dynamics.Dynamics` (rollout, rollout_batch, start / step); its per-frame API (set_state,
advance_frame, read_state) is what those are made of.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import warp as wp

import newton
from wc.devices import resolve_warp_device
from wc.dynamics import ObjectState, SteppedEpisode, as_command, finite_state, stepped
from wc.scene.scene import Scene
from wc.sim.config import SimConfig
from wc.rotations import quat_rotate
from wc.sim.kinematic import interpolate_actions, pose_twists
from wc.sim.rigid_fit import rigid_pose_from_vertices

GRAVITY = (0.0, 0.0, -9.81)


@wp.kernel
def _set_kinematic_bodies(
    poses: wp.array2d[wp.transform],
    twists: wp.array2d[wp.spatial_vector],
    substep: int,
    body_index: wp.array[int],
    body_q: wp.array[wp.transform],
    body_qd: wp.array[wp.spatial_vector],
):
    i = wp.tid()
    b = body_index[i]
    body_q[b] = poses[substep, i]
    body_qd[b] = twists[substep, i]


class NewtonSimulator:
    """Advances the object state of `worlds` episodes of one scene under prescribed robot motion."""

    def __init__(self, scene: Scene, cfg: SimConfig, worlds: int | None = None):
        self.scene, self.cfg = scene, cfg
        self.worlds = worlds or cfg.worlds
        self.device = resolve_warp_device(cfg.device, "sim.device")
        self.num_links = len(scene.link_names)
        world = self._world_builder()
        self.particles_per_world = world.particle_count
        self.bodies_per_world = world.body_count
        builder = newton.ModelBuilder(gravity=GRAVITY)
        builder.replicate(world, self.worlds)
        builder.color()
        self.model = builder.finalize(device=self.device)
        self.model.soft_contact_ke = cfg.soft_contact_ke
        self.model.soft_contact_kd = cfg.soft_contact_kd
        self.model.soft_contact_mu = cfg.bag.friction
        self.solver = newton.solvers.SolverVBD(
            self.model,
            iterations=cfg.iterations,
            friction_epsilon=cfg.friction_epsilon,
            particle_enable_self_contact=cfg.self_contact and self.particles_per_world > 0,
            particle_self_contact_margin=cfg.self_contact_margin_m,
            particle_self_contact_gap=cfg.self_contact_gap_m,
            particle_topological_contact_filter_threshold=cfg.self_contact_filter_rings,
            rigid_body_particle_contact_buffer_size=cfg.body_particle_contact_buffer,
            rigid_body_contact_buffer_size=cfg.body_contact_buffer,
        )
        self.pipeline = newton.CollisionPipeline(
            self.model, soft_contact_gap=cfg.soft_contact_gap_m, enable_rigid_soft_full_surface_contact=True
        )
        self.contacts = self.pipeline.contacts()
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        link_rows = np.arange(self.num_links)[None, :] + self.bodies_per_world * np.arange(self.worlds)[:, None]
        self._link_body_index = wp.array(link_rows.reshape(-1).astype(np.int32), dtype=int, device=self.device)
        shape = (cfg.substeps, self.worlds * self.num_links)
        self._kin_poses = wp.zeros(shape, dtype=wp.transform, device=self.device)
        self._kin_twists = wp.zeros(shape, dtype=wp.spatial_vector, device=self.device)
        self._graph = None
        self.solver_steps = 0
        self._episode: SteppedEpisode | None = None  # of start / step
        self._x: np.ndarray | None = None  # (N, 3) world 0's positions at the episode's last frame, as simulated

    @staticmethod
    def device_name(cfg: SimConfig) -> str:
        return resolve_warp_device(cfg.device, "sim.device")

    # -- building ---------------------------------------------------------------------------

    def _world_builder(self) -> newton.ModelBuilder:
        scene, cfg = self.scene, self.cfg
        b = newton.ModelBuilder(gravity=GRAVITY)
        table = scene.table
        b.add_shape_box(-1, xform=wp.transform(table.center_m, wp.quat_identity()), hx=table.half_extents_m[0],
                        hy=table.half_extents_m[1], hz=table.half_extents_m[2],
                        cfg=newton.ModelBuilder.ShapeConfig(mu=cfg.table_friction), label="table")
        shapes_by_link: dict[str, list] = {}
        for shape in scene.link_shapes:
            shapes_by_link.setdefault(shape.link, []).append(shape)
        robot_cfg = newton.ModelBuilder.ShapeConfig(mu=cfg.robot_friction, density=0.0)
        for name in scene.link_names:
            body = b.add_body(xform=wp.transform_identity(), mass=0.0, is_kinematic=True, label=name)
            if name in scene.held:  # a held object: kinematic too, its own surface as collision geometry
                mesh = scene.held[name].mesh
                b.add_shape_mesh(body, mesh=newton.Mesh(mesh.vertices, mesh.faces.reshape(-1)), cfg=robot_cfg)
                continue
            for shape in shapes_by_link.get(name.split("_", 1)[1], []):
                xform = wp.transform(shape.local_pos, shape.local_quat_xyzw)
                if shape.kind == "box":
                    b.add_shape_box(body, xform=xform, hx=shape.size[0], hy=shape.size[1], hz=shape.size[2],
                                    cfg=robot_cfg)
                else:
                    b.add_shape_capsule(body, xform=xform, radius=shape.size[0], half_height=shape.size[1],
                                        cfg=robot_cfg)
        self._rigid_bodies: dict[str, int] = {}
        for name, mesh in scene.objects.items():
            if scene.object_kinds[name] == "cloth":
                m = cfg.bag
                b.add_cloth_mesh(pos=(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=(0.0, 0.0, 0.0),
                                 vertices=[wp.vec3(*p) for p in mesh.vertices], indices=mesh.faces.reshape(-1).tolist(),
                                 density=m.density_kg_m2, tri_ke=m.tri_ke, tri_ka=m.tri_ka, tri_kd=m.tri_kd,
                                 edge_ke=m.edge_ke, edge_kd=m.edge_kd, particle_radius=m.particle_radius_m,
                                 label=name)
            else:
                material = getattr(cfg, name)
                body = b.add_body(xform=wp.transform_identity(), label=name)
                b.add_shape_mesh(body, mesh=newton.Mesh(mesh.vertices, mesh.faces.reshape(-1)),
                                 cfg=newton.ModelBuilder.ShapeConfig(density=material.density_kg_m3,
                                                                     mu=material.friction))
                self._rigid_bodies[name] = body
        return b

    # -- state in and out, one frame at a time (public: what rollout_batch is made of, for closed loops) ------

    def set_state(self, states: list[ObjectState], action: np.ndarray) -> None:
        """Set particles, rigid bodies and robot links of every world (frame-0 inputs: one state and action (14,)
        per world, the last repeated for the rest) and forget the solver's history (and any stepped episode)."""
        self._episode = None
        q = np.zeros((self.worlds, self.particles_per_world, 3), np.float32)
        qd = np.zeros_like(q)
        body_q = self.state_0.body_q.numpy().reshape(self.worlds, self.bodies_per_world, 7)
        body_qd = np.zeros((self.worlds, self.bodies_per_world, 6), np.float32)
        slices = self.scene.vertex_slices()
        for w in range(self.worlds):
            state = states[min(w, len(states) - 1)]
            cloth_rows = 0
            for name, rows in slices.items():
                if self.scene.object_kinds[name] == "cloth":
                    n = rows.stop - rows.start
                    q[w, cloth_rows:cloth_rows + n] = state.x[rows]
                    qd[w, cloth_rows:cloth_rows + n] = state.v[rows]
                    cloth_rows += n
                else:
                    body = self._rigid_bodies[name]
                    pose, twist = rigid_pose_from_vertices(self.scene.objects[name].vertices, state.x[rows],
                                                           state.v[rows])
                    body_q[w, body], body_qd[w, body] = pose, twist
            body_q[w, : self.num_links] = self.scene.link_poses(action[min(w, len(action) - 1)])
        for s in (self.state_0, self.state_1):
            if self.particles_per_world:
                s.particle_q.assign(q.reshape(-1, 3))
                s.particle_qd.assign(qd.reshape(-1, 3))
            s.body_q.assign(body_q.reshape(-1, 7))
            s.body_qd.assign(body_qd.reshape(-1, 6))
        # a new episode is a discontinuity: forget the solver's pose / contact history (a rigid body
        # moved since the last step would otherwise get the jump as velocity)
        self.solver.reset(self.state_0, flags=0)
        self.pipeline.reset_contact_matching()

    def read_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Concatenated object vertices of every world: x, v each (W, N, 3), not checked finite."""
        q = qd = np.zeros((self.worlds, 0, 3), np.float32)
        if self.particles_per_world:
            q = self.state_0.particle_q.numpy().reshape(self.worlds, -1, 3)
            qd = self.state_0.particle_qd.numpy().reshape(self.worlds, -1, 3)
        body_q = self.state_0.body_q.numpy().reshape(self.worlds, self.bodies_per_world, 7)
        body_qd = self.state_0.body_qd.numpy().reshape(self.worlds, self.bodies_per_world, 6)
        out = []
        for w in range(self.worlds):
            xs, vs, cloth_rows = [], [], 0
            for name, mesh in self.scene.objects.items():
                n = len(mesh.vertices)
                if self.scene.object_kinds[name] == "cloth":
                    xs.append(q[w, cloth_rows:cloth_rows + n])
                    vs.append(qd[w, cloth_rows:cloth_rows + n])
                    cloth_rows += n
                else:
                    pose, twist = body_q[w, self._rigid_bodies[name]], body_qd[w, self._rigid_bodies[name]]
                    r = quat_rotate(pose[None, 3:], mesh.vertices)
                    xs.append(pose[:3] + r)
                    vs.append(twist[:3] + np.cross(twist[3:], r))  # body origin = centre of mass
            out.append((np.concatenate(xs), np.concatenate(vs)))
        return (np.stack([o[0] for o in out]).astype(np.float32), np.stack([o[1] for o in out]).astype(np.float32))

    # -- stepping ----------------------------------------------------------------------------

    def _substeps(self) -> None:
        for s in range(self.cfg.substeps):
            wp.launch(_set_kinematic_bodies, dim=self.worlds * self.num_links,
                      inputs=[self._kin_poses, self._kin_twists, s, self._link_body_index],
                      outputs=[self.state_0.body_q, self.state_0.body_qd], device=self.device)
            self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.cfg.dt_s)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def advance_frame(self, action_now: np.ndarray, action_next: np.ndarray) -> None:
        """One recorded frame (substeps solver steps) under actions (W, 14) -> (W, 14)."""
        sub = np.stack([interpolate_actions(a0, a1, self.cfg.substeps) for a0, a1 in zip(action_now, action_next)])
        poses = self.scene.link_poses(sub)  # (W, S, L, 7)
        prev = np.concatenate([self.scene.link_poses(action_now)[:, None], poses[:, :-1]], axis=1)
        twists = pose_twists(prev, poses, self.cfg.dt_s)
        self._kin_poses.assign(np.ascontiguousarray(poses.transpose(1, 0, 2, 3).reshape(self.cfg.substeps, -1, 7)))
        self._kin_twists.assign(np.ascontiguousarray(twists.transpose(1, 0, 2, 3).reshape(self.cfg.substeps, -1, 6)))
        if self.cfg.self_contact and self.particles_per_world:
            self.solver.rebuild_bvh(self.state_0)
        # A CUDA graph of one frame replays the substeps without launch gaps. The first frame runs
        # eagerly, since solver buffers may grow on first use; an even substep count returns the
        # swapped states to the arrays the graph captured.
        use_graph = wp.get_device(self.device).is_cuda and self.cfg.substeps % 2 == 0 and self.solver_steps > 0
        if use_graph and self._graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                self._substeps()
            self._graph = capture.graph
        if use_graph:
            wp.capture_launch(self._graph)
        else:
            self._substeps()
        self.solver_steps += self.cfg.substeps

    def _batch(self, items: list) -> list:
        if not 1 <= len(items) <= self.worlds:
            raise ValueError(f"got {len(items)} episodes for a simulator of {self.worlds} worlds")
        return items + [items[-1]] * (self.worlds - len(items))

    def settle(self, states: list[ObjectState], actions: list[np.ndarray], seconds: float) -> list[ObjectState]:
        """Let objects come to rest under gravity with the robot held at `actions` (14,) each."""
        n = len(states)
        held = np.stack(self._batch(list(actions)))
        self.set_state(self._batch(list(states)), held)
        frames = int(round(seconds / self.cfg.frame_dt_s))
        x, v = self.read_state()
        for _ in range(frames):
            previous = x
            self.advance_frame(held, held)
            x = self.read_state()[0]
            v = (x - previous) / self.cfg.frame_dt_s  # the frame-mean velocity, as rollout_batch records it
        return [ObjectState(x[w], v[w]) for w in range(n)]

    def rollout_batch(self, initial: list[ObjectState], actions: list[np.ndarray],
                      on_frame: Callable[[], None] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Roll out episodes from their frame-0 states under actions (T, 14): [(x, v) of (T, N, 3)].

        Values are returned as simulated, not checked finite: a blow-up is the caller's to judge.
        """
        n, steps = len(initial), {len(a) for a in actions}
        if len(steps) != 1:
            raise ValueError(f"episodes in one batch must have the same length, got {sorted(steps)}")
        acts = np.stack(self._batch([np.asarray(a, np.float32) for a in actions]))  # (W, T, 14)
        if acts.shape[-1] != 14:
            raise ValueError(f"actions must be (T, 14), got {acts.shape[1:]}")
        self.set_state(self._batch(list(initial)), acts[:, 0])
        frames = [self.read_state()]
        for k in range(acts.shape[1] - 1):
            self.advance_frame(acts[:, k], acts[:, k + 1])
            frames.append(self.read_state())
            if on_frame is not None:
                on_frame()
        x = np.stack([f[0] for f in frames], axis=1)  # (W, T, N, 3)
        v = np.stack([f[1] for f in frames], axis=1)
        # Recorded velocity = the frame's mean velocity (x_k - x_{k-1}) / Δt. The solver's last-substep
        # velocity carries VBD contact jitter as large as the motion itself (a bag resting on the table
        # "moves" at cm/s); the frame mean is smooth and is the velocity WorldContact's projection
        # produces (V = (X_{t+Δt} - X_t) / Δt). Frame 0 keeps the state it started from.
        v[:, 1:] = (x[:, 1:] - x[:, :-1]) / self.cfg.frame_dt_s
        return [(x[w], v[w]) for w in range(n)]

    def rollout(self, initial: ObjectState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One episode: (x, v) each (T, N, 3), frame 0 = `initial`."""
        return self.rollout_batch([initial], [actions])[0]

    def start(self, initial: ObjectState, action: np.ndarray) -> None:
        """Frame 0 of a stepped episode (every world runs it, world 0 is read): the object state and the robot's
        command (14,); forgets the solver's history."""
        self._restart(SteppedEpisode(initial, [as_command(action)]))

    def _restart(self, episode: SteppedEpisode) -> None:
        self.set_state([episode.origin], episode.action[None])
        self._episode, self._x = episode, self.read_state()[0][0]

    def step(self, state: ObjectState, action: np.ndarray) -> ObjectState:
        """The object state one frame (substeps solver steps) after `state` as the robot moves from the current
        command to `action` (14,); v is the frame-mean velocity, as `rollout_batch` records it. The solver's history
        goes on when `state` is the one the last start / step gave, else `state` is written in first (as `start`)."""
        nxt = as_command(action)
        episode = stepped(self._episode, state)
        if episode is not self._episode:
            self._restart(episode)
        now = episode.action
        self.advance_frame(np.repeat(now[None], self.worlds, 0), np.repeat(nxt[None], self.worlds, 0))
        x = self.read_state()[0][0]
        self._episode = None  # until the step is known finite: after a FloatingPointError, start again
        out = finite_state(x, (x - self._x) / self.cfg.frame_dt_s, episode.frame + 1)
        episode.actions.append(nxt)
        self._episode, episode.last, self._x = episode, out, x
        return out
