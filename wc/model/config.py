"""The `model` params section: WorldContact's sizes, neighbour radii and the two ablation switches."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal


@dataclass(frozen=True)
class ModelConfig:
    """WorldContact hyper-parameters (paper Appendix: widths 32/32/64/64, 3 encoder levels, 3 decoder layers).

    The radii are the neighbour sets' compact supports; they scale with the mesh resolution,
    so they are params (paper scale: params/gpu.yaml). Widths and depths default to the paper's.
    """

    spatial_radius_m: float  # N^S: other predicted vertices within this 3D distance
    topology_radius_m: float  # N^T: same-object vertices within this rest-(u, v) distance
    controllable_radius_m: float  # N^C: robot link / finger / held-object samples
    environment_radius_m: float  # N^E: table samples
    tag_scale: float = 0.02  # object/body tags enter features as tag * tag_scale (tags run to ~50)
    kernel_size: int = 4  # continuous-convolution grid K (K^3 cells)
    encoder_levels: int = 3  # L_e
    decoder_layers: int = 3  # L_d
    heads: int = 8
    decoder_ffn_hidden: int = 128
    dropout: float = 0.1  # decoder attention and FFN
    rope_min_wavelength_m: float = 0.01
    rope_max_wavelength_m: float = 1.0
    tokenizer: Literal["contact", "linear"] = "contact"  # "linear": the no-contact-tokenizer ablation
    compress: bool = True  # False: the no-hierarchical-compression ablation (full-resolution attention)
    # A departure from the paper: the spatial and topology kernels also see each pair's rest-space relation
    # ([Δu, Δv, rest distance] / radius; far across objects), and the topology window follows the rest distance,
    # so stretched mesh neighbours keep their weight and a folded strap's other layer is told from a neighbour.
    rest_features: bool = False
    # How the head's Δx becomes X̂ (the paper is silent on the output parametrisation):
    # "integrate": X̂ = X + Δt·V̂ + ΔX, ΔX a residual on the semi-implicit Euler step (positions follow the
    # predicted velocities, as they do in the stored frames, where V is the frame displacement / Δt);
    # "direct": X̂ = X + ΔX, the paper's equation taken literally.
    position_update: Literal["integrate", "direct"] = "integrate"
    # Rollouts without gradients reuse neighbour pairs searched with radius + skin while no point has moved
    # more than ~skin/2 (wc/model/neighbor_cache.py): the same pairs, fewer searches. 0 = search every step.
    neighbor_skin_m: float = 0.0

    def validate(self) -> None:
        for name in ("spatial_radius_m", "topology_radius_m", "controllable_radius_m", "environment_radius_m",
                     "tag_scale", "rope_min_wavelength_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.rope_max_wavelength_m <= self.rope_min_wavelength_m:
            raise ValueError("rope_max_wavelength_m must exceed rope_min_wavelength_m")
        for name in ("kernel_size", "encoder_levels", "decoder_layers", "heads", "decoder_ffn_hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.position_update not in ("integrate", "direct"):
            raise ValueError(f"position_update must be 'integrate' or 'direct', got {self.position_update!r}")
        if not self.neighbor_skin_m >= 0.0:
            raise ValueError(f"neighbor_skin_m must be >= 0 (0 = no reuse), got {self.neighbor_skin_m}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
