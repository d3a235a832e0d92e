"""Contact-centric vertex tokenizer (paper Eqs. contact_aggregation, contact_branches, tokenizer).

Every predicted vertex i gets a 192-wide token h_i from four neighbour sets aggregated by
continuous convolutions, g_i^k = sum_j W_k(r_ij) u_ij (k = S, T, C, E), plus a direct per-vertex
feature. Shapes: B scenes sharing one layout, N predicted vertices, Mc controllable and Me
environment samples per scene. Positions in metres, velocities in m/s (divided by velocity_scale
before they become features). `LinearTokenizer` is the paper's "no contact tokenizer" ablation.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from wc.model.conv import ContinuousConv
from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.neighbor_cache import NeighborCache, PairQuery, search_pairs
from wc.model.neighbors import nearest_index, radius_pairs

TOKEN_DIM = 192
VERTEX_FEATURES = 7  # [1, v / velocity_scale (3), c (3)] for vertices; [v / vs (3), tag, normal (3)] for samples
SAMPLE_ATTRIBUTES = 4  # [scaled tag, unit normal]
REST_PAIR_FEATURES = 3  # [Δu, Δv, rest distance] / radius of a same-object pair (rest_features switch)
REST_FAR = 2.0  # rest-feature cap: pairs of two objects, or this many radii apart in rest space, read as "far"


def rest_pair_features(uv: Tensor, obj: Tensor, qi: Tensor, pj: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Rest-space relation of pairs (qi, pj) (any equal shape) of vertices with rest uv (M, 2) [m] on objects
    obj (M,): features (..., 3) = [Δu, Δv, |Δuv|] / radius, clamped to ±REST_FAR, with [0, 0, REST_FAR] for
    pairs of different objects; and the rest distance (...,) [m] (+inf across objects). A mesh neighbour reads
    near in rest space however the cloth is folded; another layer of the same strap reads far."""
    d = uv[pj] - uv[qi]
    same = obj[pj] == obj[qi]
    dist = torch.where(same, d.norm(dim=-1), torch.full_like(d[..., 0], float("inf")))
    rel = torch.where(same[..., None], (d / radius).clamp(-REST_FAR, REST_FAR), torch.zeros_like(d))
    far = (dist / radius).clamp(max=REST_FAR)
    return torch.cat((rel, far[..., None]), dim=-1), dist


def topology_pairs(rest_uv: Tensor, object_index: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Topological neighbours N^T: pairs (ti, tj) within `radius` in rest uv space, same object, i != j.

    rest_uv (N, 2) in uv units, object_index (N,) int64. Computed once per layout; indices are
    into one scene's N vertices, sorted by ti then tj.
    """
    if rest_uv.ndim != 2 or rest_uv.shape[1] != 2:
        raise ValueError(f"rest_uv must be (N, 2), got {tuple(rest_uv.shape)}")
    if object_index.shape != (rest_uv.shape[0],):
        raise ValueError(f"object_index must be ({rest_uv.shape[0]},), got {tuple(object_index.shape)}")
    uv3 = torch.cat((rest_uv.float(), rest_uv.new_zeros(rest_uv.shape[0], 1, dtype=torch.float32)), dim=1)
    return radius_pairs(uv3, uv3, radius, query_batch=object_index, point_batch=object_index, exclude_self=True)


def _check_inputs(
    x: Tensor,
    v: Tensor,
    attributes: Tensor,
    object_index: Tensor,
    ti: Tensor,
    tj: Tensor,
    ctrl_x: Tensor,
    ctrl_v: Tensor,
    ctrl_attr: Tensor,
    env_x: Tensor,
    env_v: Tensor,
    env_attr: Tensor,
) -> None:
    """Raise ValueError naming the argument for wrong shapes (no host sync; values: `_state_flags`)."""
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"x must be (B, N, 3), got {tuple(x.shape)}")
    b, n, _ = x.shape
    if v.shape != x.shape:
        raise ValueError(f"v must be (B, N, 3) = {tuple(x.shape)} like x, got {tuple(v.shape)}")
    if attributes.ndim != 2 or attributes.shape[1] != 3:
        raise ValueError(f"attributes must be (N, 3) = [tag, u, v], got {tuple(attributes.shape)}")
    if attributes.shape[0] != n:
        raise ValueError(f"attributes has {attributes.shape[0]} rows but x has N = {n} vertices")
    if object_index.shape != (n,):
        raise ValueError(f"object_index must be (N,) = ({n},), got {tuple(object_index.shape)}")
    if ti.ndim != 1 or ti.shape != tj.shape:
        raise ValueError(f"ti and tj must be equal-length 1-D index tensors, got {tuple(ti.shape)}, {tuple(tj.shape)}")
    for name, sx, sv, sa in (("ctrl", ctrl_x, ctrl_v, ctrl_attr), ("env", env_x, env_v, env_attr)):
        if sx.ndim != 3 or sx.shape[0] != b or sx.shape[2] != 3:
            raise ValueError(f"{name}_x must be (B={b}, M, 3), got {tuple(sx.shape)}")
        if sv.shape != sx.shape:
            raise ValueError(f"{name}_v must be {tuple(sx.shape)} like {name}_x, got {tuple(sv.shape)}")
        if sa.ndim != 3 or sa.shape[:2] != sx.shape[:2] or sa.shape[2] != SAMPLE_ATTRIBUTES:
            raise ValueError(
                f"{name}_attr must be (B={b}, M={sx.shape[1]}, {SAMPLE_ATTRIBUTES}) = [tag, normal], got {tuple(sa.shape)}"
            )


def _state_flags(x: Tensor, v: Tensor, ti: Tensor, tj: Tensor, n: int) -> Tensor:
    """(3,) int64 on device: [x finite, v finite, topology indices in [0, n)]; read back by `_raise_on_flags`."""
    in_range = ((torch.stack((ti.min(), tj.min())) >= 0).all() & (torch.stack((ti.max(), tj.max())) < n).all()
                if ti.numel() > 0 else torch.ones((), dtype=torch.bool, device=ti.device))
    return torch.stack((torch.isfinite(x).all(), torch.isfinite(v).all(), in_range.to(x.device))).long()


def _raise_on_flags(flags: list[int], n: int) -> None:
    """ValueError for a non-finite object state or out-of-range topology pairs (flags from `_state_flags`)."""
    if not flags[0]:
        raise ValueError("non-finite x in the object state")
    if not flags[1]:
        raise ValueError("non-finite v in the object state")
    if not flags[2]:
        raise ValueError(f"topology pair indices ti, tj must lie in [0, N = {n})")


def _scene_ids(b: int, per_scene: int, device: torch.device) -> Tensor:
    """Batch id (B * per_scene,) of every row of a flattened (B, per_scene, ...) tensor."""
    return torch.arange(b, device=device).repeat_interleave(per_scene)


def axis_scale(value: float | Sequence[float], name: str) -> Tensor:
    """(3,) float32 per-axis scale from one value (every axis) or three; each must be positive."""
    scale = torch.as_tensor(value, dtype=torch.float32).reshape(-1)
    if scale.numel() == 1:
        scale = scale.expand(3).clone()
    if scale.numel() != 3 or not bool((scale > 0).all()) or not bool(torch.isfinite(scale).all()):
        raise ValueError(f"{name} must be one positive value or three (x, y, z), got {value}")
    return scale


class ContactTokenizer(nn.Module):
    """h_i = [g^S, g^T, g^E, g^C, direct] (B, N, 192) from the object state and the prescribed samples.

    Radii in metres (topology_radius in rest-uv metres: the caller's `topology_pairs` uses it, and it
    is the topology kernel's support), velocity_scale in m/s.
    """

    def __init__(
        self,
        spatial_radius: float,
        topology_radius: float,
        controllable_radius: float,
        environment_radius: float,
        velocity_scale: float | Sequence[float],
        kernel_size: int = 4,
        spatial_channels: int = 32,
        topology_channels: int = 32,
        boundary_channels: int = 64,
        direct_channels: int = 64,
        rest_features: bool = False,
    ) -> None:
        super().__init__()
        self.rest_features = rest_features
        self.register_buffer("velocity_scale", axis_scale(velocity_scale, "velocity_scale"), persistent=False)
        if boundary_channels % 2 != 0:
            raise ValueError(f"boundary_channels must be even (split C/E), got {boundary_channels}")
        self.spatial_radius = float(spatial_radius)
        self.topology_radius = float(topology_radius)
        self.controllable_radius = float(controllable_radius)
        self.environment_radius = float(environment_radius)
        self.out_dim = spatial_channels + topology_channels + boundary_channels + direct_channels
        f = VERTEX_FEATURES
        pair = REST_PAIR_FEATURES if rest_features else 0
        self.spatial = ContinuousConv(f + pair, spatial_channels, spatial_radius, kernel_size)
        # rest uv is isometric to the rest shape (metres), so uv-neighbours start within
        # topology_radius in 3D too; a pair stretched beyond it fades out through the window
        # (rest_features: the window follows the rest distance instead, so no pair drops out).
        self.topology = ContinuousConv(f + pair, topology_channels, topology_radius, kernel_size)
        self.environment = ContinuousConv(f, boundary_channels // 2, environment_radius, kernel_size)
        self.controllable = ContinuousConv(f, boundary_channels // 2, controllable_radius, kernel_size)
        # Translation invariance: absolute x is no token feature (only offsets r_ij and the vertex's
        # own velocity and attributes); positions enter later through RoPE on the anchors.
        self.direct = nn.Linear(f, direct_channels)
        # The appendix's tokenizer has 9 parameters more than its convolutions and direct layer;
        # we spend them on a learnable 3x3 map of the offsets shared by the four kernels (an
        # anisotropic kernel frame, e.g. to align with gravity). A choice of ours, not the paper's.
        self.offset_transform = nn.Parameter(torch.eye(3))

    def forward(
        self,
        x: Tensor,
        v: Tensor,
        attributes: Tensor,
        object_index: Tensor,
        ti: Tensor,
        tj: Tensor,
        ctrl_x: Tensor,
        ctrl_v: Tensor,
        ctrl_attr: Tensor,
        env_x: Tensor,
        env_v: Tensor,
        env_attr: Tensor,
        neighbors: NeighborCache | FixedNeighbors | None = None,
    ) -> Tensor:
        """Vertex tokens (B, N, 192).

        x, v (B, N, 3) object state at t; attributes (N, 3) = [tag, rest u, rest v]; object_index
        (N,) is only validated (the topology pairs already keep to one object, and spatial contact
        crosses objects by design); ti, tj (P,) from `topology_pairs` (one scene's indices);
        ctrl_* / env_* the controllable / environment samples at t + dt: x, v (B, M, 3),
        attr (B, M, 4) = [tag, unit normal]. neighbors: a Verlet-skin cache for the three searched sets
        (same pairs as fresh searches, so the same tokens); None searches afresh. One host sync per call
        when no set needs a new search. With `FixedNeighbors` (the static-shape path) the same sums run over
        padded neighbour slots with no host sync and no value checks (overflow goes to its counter).
        """
        _check_inputs(x, v, attributes, object_index, ti, tj, ctrl_x, ctrl_v, ctrl_attr, env_x, env_v, env_attr)
        b, n, _ = x.shape
        device = x.device
        vs = self.velocity_scale
        xf = x.reshape(b * n, 3)
        scene = _scene_ids(b, n, device)
        c = attributes.to(x.dtype).expand(b, n, 3).reshape(b * n, 3)
        ones = xf.new_ones(b * n, 1)
        u = torch.cat((ones, (v.reshape(b * n, 3) / vs).to(xf.dtype), c), dim=1)  # (B*N, 7) = [1, v_j, c_j]
        frame = self.offset_transform
        env_xf, env_u = self._samples(env_x, env_v, env_attr, xf.dtype)
        ctrl_xf, ctrl_u = self._samples(ctrl_x, ctrl_v, ctrl_attr, xf.dtype)
        queries = {  # spatial contact: Euclidean neighbours across all predicted objects of the scene
            "spatial": PairQuery(xf, xf, self.spatial_radius, scene, scene, b, exclude_self=True),
            "environment": PairQuery(xf, env_xf, self.environment_radius, scene, _scene_ids(b, env_x.shape[1], device), b),
            "controllable": PairQuery(xf, ctrl_xf, self.controllable_radius, scene,
                                      _scene_ids(b, ctrl_x.shape[1], device), b),
        }
        rest = self._rest_relation(attributes, object_index, b)
        if isinstance(neighbors, FixedNeighbors):
            found = neighbors.search(queries)
            s_index, s_valid = found["spatial"].index, found["spatial"].valid
            t_index, t_valid = neighbors.topology(b)
            rows = torch.arange(b * n, device=device)[:, None]
            g_s = self.spatial.forward_padded(xf, xf, u, s_index, s_valid, frame,
                                              *rest(rows, s_index, self.spatial_radius, window=False))
            g_t = self.topology.forward_padded(xf, xf, u, t_index, t_valid, frame,
                                               *rest(rows, t_index, self.topology_radius, window=True))
            g_e = self.environment.forward_padded(xf, env_xf, env_u, found["environment"].index,
                                                  found["environment"].valid, frame)
            g_c = self.controllable.forward_padded(xf, ctrl_xf, ctrl_u, found["controllable"].index,
                                                   found["controllable"].valid, frame)
        else:
            pairs = search_pairs(queries, neighbors, _state_flags(x, v, ti, tj, n), lambda f: _raise_on_flags(f, n))
            g_s = self.spatial(xf, xf, u, *pairs["spatial"], frame,
                               *rest(*pairs["spatial"], self.spatial_radius, window=False))
            # Topological contact: rest-uv neighbours, offset per scene, r from current positions.
            shift = (torch.arange(b, device=device) * n)[:, None]
            ti_b = (ti.to(device)[None, :] + shift).reshape(-1)
            tj_b = (tj.to(device)[None, :] + shift).reshape(-1)
            g_t = self.topology(xf, xf, u, ti_b, tj_b, frame, *rest(ti_b, tj_b, self.topology_radius, window=True))
            # Boundary contact with the prescribed samples at t + dt.
            g_e = self.environment(xf, env_xf, env_u, *pairs["environment"], frame)
            g_c = self.controllable(xf, ctrl_xf, ctrl_u, *pairs["controllable"], frame)

        direct = self.direct(u)  # [1, v_i, c_i]
        h = torch.cat((g_s, g_t, g_e, g_c, direct), dim=1)
        return h.reshape(b, n, self.out_dim)

    def _rest_relation(self, attributes: Tensor, object_index: Tensor, b: int):
        """pairs (qi, pj) over the B*N flattened vertices, radius, window -> (pair_feats, window_dist) for a
        branch: (None, None) unless rest_features; window: the window fades with the rest distance."""
        uv = attributes[:, 1:3].float().repeat(b, 1)
        obj = object_index.to(attributes.device).repeat(b)

        def relation(qi: Tensor, pj: Tensor, radius: float, window: bool) -> tuple[Tensor | None, Tensor | None]:
            if not self.rest_features:
                return None, None
            feats, dist = rest_pair_features(uv, obj, qi, pj, radius)
            return feats, (dist if window else None)
        return relation

    def _samples(self, sx: Tensor, sv: Tensor, sattr: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """Flattened sample positions (B*M, 3) and features u_j = [v_j / vs, attr_j] (B*M, 7) for g^C or g^E."""
        b, m, _ = sx.shape
        u = torch.cat(((sv.reshape(b * m, 3).to(dtype) / self.velocity_scale).to(dtype), sattr.reshape(b * m, 4).to(dtype)),
                      dim=1)
        return sx.reshape(b * m, 3).to(dtype), u


class LinearTokenizer(nn.Module):
    """Ablation "no contact tokenizer": h_i = Linear([x_i, v_i, c_i, nearest C sample, nearest E sample]).

    A sample's features are (x_j - x_i, v_j / vs, attr_j) (10); an empty sample set gives zeros.
    Same forward signature as ContactTokenizer; object_index and the topology pairs are ignored.
    """

    def __init__(self, velocity_scale: float | Sequence[float], out_dim: int = TOKEN_DIM) -> None:
        super().__init__()
        self.register_buffer("velocity_scale", axis_scale(velocity_scale, "velocity_scale"), persistent=False)
        self.out_dim = out_dim
        self.proj = nn.Linear(9 + 2 * (3 + 3 + SAMPLE_ATTRIBUTES), out_dim)

    def forward(
        self,
        x: Tensor,
        v: Tensor,
        attributes: Tensor,
        object_index: Tensor,
        ti: Tensor,
        tj: Tensor,
        ctrl_x: Tensor,
        ctrl_v: Tensor,
        ctrl_attr: Tensor,
        env_x: Tensor,
        env_v: Tensor,
        env_attr: Tensor,
        neighbors: NeighborCache | None = None,
    ) -> Tensor:
        """Vertex tokens (B, N, out_dim); arguments as ContactTokenizer.forward. neighbors: only whether it is
        `FixedNeighbors` matters (the static-shape path: nearest samples by a batched distance matrix, no sync)."""
        _check_inputs(x, v, attributes, object_index, ti, tj, ctrl_x, ctrl_v, ctrl_attr, env_x, env_v, env_attr)
        b, n, _ = x.shape
        static = isinstance(neighbors, FixedNeighbors)
        if not static:
            _raise_on_flags(_state_flags(x, v, ti, tj, n).tolist(), n)
        c = attributes.to(x.dtype).expand(b, n, 3)
        feats = [x, v / self.velocity_scale, c]
        for sx, sv, sa in ((ctrl_x, ctrl_v, ctrl_attr), (env_x, env_v, env_attr)):
            feats.append(self._nearest(x, sx, sv, sa, static))
        return self.proj(torch.cat(feats, dim=-1))

    def _nearest(self, x: Tensor, sx: Tensor, sv: Tensor, sa: Tensor, static: bool) -> Tensor:
        """(B, N, 10) = [x_j - x_i, v_j / vs, attr_j] of each vertex's nearest sample j (zeros if none)."""
        b, n, _ = x.shape
        m = sx.shape[1]
        if m == 0:
            return x.new_zeros(b, n, 3 + 3 + SAMPLE_ATTRIBUTES)
        xf = x.reshape(b * n, 3)
        if static:  # the distances of `nearest_index`, per scene at once; argmin keeps the lowest index on ties
            d = torch.cdist(x.detach().float(), sx.detach().float(), compute_mode="donot_use_mm_for_euclid_dist")
            j = (d.argmin(dim=-1) + (torch.arange(b, device=x.device) * m)[:, None]).reshape(b * n)
        else:
            j = nearest_index(xf, sx.reshape(b * m, 3), _scene_ids(b, n, x.device), _scene_ids(b, m, x.device))
        sxf = sx.reshape(b * m, 3).to(x.dtype)[j]
        svf = sv.reshape(b * m, 3).to(x.dtype)[j] / self.velocity_scale
        saf = sa.reshape(b * m, SAMPLE_ATTRIBUTES).to(x.dtype)[j]
        return torch.cat((sxf - xf, svf, saf), dim=-1).reshape(b, n, -1)
