"""WorldContact: (ΔX_t, ΔV_t) = F_θ(S_t, B_{t+Δt}) (paper Eq. student_corrector), assembled from its four parts."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from wc.model.config import ModelConfig
from wc.model.decoder import GlobalTokenDecoder
from wc.model.encoder import HierarchicalEncoder
from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.head import StateHead
from wc.model.layout import Samples, SceneLayout
from wc.model.neighbor_cache import NeighborCache
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.attention import RoPE3D
from wc.model.projection import TopologyProjection
from wc.model.tokenizer import ContactTokenizer, LinearTokenizer, axis_scale, topology_pairs

WIDTH = 192  # spatial 32 + topology 32 + boundary 64 + direct 64 (Appendix)
HEAD_DIM = WIDTH // 8


class WorldContact(nn.Module):
    """Tokenizer → hierarchical encoder → global-token decoder → head.

    `scales` (velocity_m_s, delta_x_m, delta_v_m_s) come from the training data, each one value or one per axis
    (x, y, z): velocity features are divided by the first, and the head predicts Δx, Δv in units of the other
    two, so an untrained network starts near zero change whatever the scene's units of motion.
    """

    def __init__(self, config: ModelConfig, velocity_m_s: float | Sequence[float], delta_x_m: float | Sequence[float],
                 delta_v_m_s: float | Sequence[float]) -> None:
        super().__init__()
        self.config = config
        if config.tokenizer == "contact":
            self.tokenizer: nn.Module = ContactTokenizer(
                spatial_radius=config.spatial_radius_m, topology_radius=config.topology_radius_m,
                controllable_radius=config.controllable_radius_m, environment_radius=config.environment_radius_m,
                velocity_scale=velocity_m_s, kernel_size=config.kernel_size, rest_features=config.rest_features)
        else:
            self.tokenizer = LinearTokenizer(velocity_scale=velocity_m_s)
        rope = RoPE3D(WIDTH // config.heads, config.rope_min_wavelength_m, config.rope_max_wavelength_m)
        self.encoder = HierarchicalEncoder(WIDTH, config.heads, config.encoder_levels, rope, compress=config.compress)
        self.decoder = GlobalTokenDecoder(WIDTH, config.heads, config.decoder_layers, config.decoder_ffn_hidden,
                                          config.dropout, rope)
        self.head = StateHead(WIDTH)
        self.register_buffer("scales", torch.stack([axis_scale(velocity_m_s, "velocity_m_s"),  # (3 scales, 3 axes)
                                                    axis_scale(delta_x_m, "delta_x_m"),
                                                    axis_scale(delta_v_m_s, "delta_v_m_s")]))

    def parameter_counts(self) -> dict[str, int]:
        """Trainable parameters per module (the Appendix: 57,993 / 782,784 / 1,116,480 / 42,502)."""
        counts = {name: sum(p.numel() for p in getattr(self, name).parameters() if p.requires_grad)
                  for name in ("tokenizer", "encoder", "decoder", "head")}
        return {**counts, "total": sum(counts.values())}

    def _topology(self, layout: SceneLayout) -> tuple[torch.Tensor, torch.Tensor]:
        key = f"topology_pairs@{self.config.topology_radius_m}"
        if key not in layout.cache:  # static per layout: computed once in rest (u, v)
            layout.cache[key] = topology_pairs(layout.rest_uv, layout.object_index, self.config.topology_radius_m)
        return layout.cache[key]

    def forward(self, x: torch.Tensor, v: torch.Tensor, layout: SceneLayout, controllable: Samples,
                environment: Samples, neighbors: NeighborCache | FixedNeighbors | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """(Δx, Δv), each (B, N, 3), from x, v (B, N, 3) at t and the prescribed samples at t+Δt.

        neighbors: a Verlet-skin neighbour cache (same result, fewer searches), e.g. `neighbor_cache(layout)`,
        or the static-shape search `fixed_neighbors(layout, capacities)` (same result within capacity, no sync)."""
        if x.ndim != 3 or x.shape[1] != layout.num_vertices or x.shape[-1] != 3:
            raise ValueError(f"x must be (B, {layout.num_vertices}, 3) for objects {layout.objects}, got {tuple(x.shape)}")
        ti, tj = self._topology(layout)
        h = self.tokenizer(x, v, layout.attributes, layout.object_index, ti, tj,  # Eq. tokenizer
                           controllable.x, controllable.v, controllable.attributes,
                           environment.x, environment.v, environment.attributes, neighbors=neighbors)
        global_h, global_x, _ = self.encoder(h, x)  # Eqs. encoder_attention, merge
        h_d = self.decoder(h, x, global_h, global_x)  # Eqs. decoder_self, decoder_cross
        out = self.head(h_d).float()  # Eq. state_head
        return out[..., :3] * self.scales[1], out[..., 3:] * self.scales[2]

    def projection(self, layout: SceneLayout, smoothing_iterations: int = 4, smoothing_weight: float = 0.35,
                   constraint_iterations: int = 32, edge_ratio: tuple[float, float] = (0.9, 1.1)) -> TopologyProjection:
        """The differentiable topology projection P for a layout (cached on it)."""
        key = f"projection@{smoothing_iterations},{smoothing_weight},{constraint_iterations},{edge_ratio}"
        if key not in layout.cache:
            layout.cache[key] = TopologyProjection(
                layout.edges, layout.rest_lengths, layout.num_vertices, smoothing_iterations=smoothing_iterations,
                smoothing_weight=smoothing_weight, constraint_iterations=constraint_iterations,
                min_ratio=edge_ratio[0], max_ratio=edge_ratio[1]).to(layout.edges.device)
        return layout.cache[key]

    def fixed_neighbors(self, layout: SceneLayout, capacities: dict[str, NeighborCapacity]) -> FixedNeighbors:
        """The layout's static-shape neighbour search with these capacities (cached on the layout per capacities)."""
        key = f"fixed_neighbors@{sorted(capacities.items())}"
        if key not in layout.cache:
            ti, tj = self._topology(layout)
            layout.cache[key] = FixedNeighbors.for_topology(capacities, ti, tj, layout.num_vertices)
        return layout.cache[key]

    def neighbor_cache(self, layout: SceneLayout, skin_m: float | None = None) -> NeighborCache | None:
        """The layout's Verlet-skin neighbour cache (skin default: config.neighbor_skin_m); None when the skin
        is 0 or the tokenizer searches no neighbours. Cached on the layout: its reuse test makes it valid for
        any state, and an entry is replaced when the batch shape changes."""
        skin = self.config.neighbor_skin_m if skin_m is None else float(skin_m)
        if skin < 0:
            raise ValueError(f"neighbour skin must be >= 0 m, got {skin}")
        if skin == 0 or self.config.tokenizer != "contact":
            return None
        key = f"neighbor_cache@{skin}"
        if key not in layout.cache:
            layout.cache[key] = NeighborCache(skin)
        return layout.cache[key]


def advance(model: WorldContact, x: torch.Tensor, v: torch.Tensor, layout: SceneLayout, controllable: Samples,
            environment: Samples, dt: float, projection: TopologyProjection | None = None,
            neighbors: NeighborCache | FixedNeighbors | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One predicted frame: V̂ = V + ΔV and X̂ = X + ΔX ("direct") or X + Δt·V̂ + ΔX ("integrate");
    with P, X̂ = P(X̃) and V̂ = (X̂_{t+Δt} − X̂_t)/Δt (Eq. projection_finetune)."""
    dx, dv = model(x, v, layout, controllable, environment, neighbors=neighbors)
    v_next = v + dv
    x_next = x + dx + dt * v_next if model.config.position_update == "integrate" else x + dx
    if projection is None:
        return x_next, v_next
    x_next = projection(x, x_next)
    return x_next, (x_next - x) / dt
