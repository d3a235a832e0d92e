"""Continuous convolution over neighbour pairs (Ummenhofer et al. 2020, Open3D-ML ContinuousConv).

The learned kernel W(r) is a K x K x K grid of (Cin x Cout) matrices on the ball of radius R: an
offset r is scaled into the unit ball, mapped to the cube [-1, 1]^3 with the volume-preserving
ball-to-cube mapping, and the grid is trilinearly interpolated there (align_corners=True). Each
pair is weighted by the poly6 window, so the kernel goes smoothly to zero at the radius; there is
no normalisation by neighbour count (WorldParticle and DeepLagrangianFluids use normalize=False).
Differentiable w.r.t. positions, features and the kernel; pure torch, any device, float32/float64.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

_EPS_SQ = 1.0e-8  # squared norms below this map to the centre (Open3D's threshold)


def ball_to_cube_volume_preserving(p: Tensor) -> Tensor:
    """Map points (..., 3) of the unit ball onto the cube [-1, 1]^3, preserving volume.

    Ball -> cylinder (axis z) -> cube, as Open3D-ML's BALL_TO_CUBE_VOLUME_PRESERVING mapping
    (open3d/ml/impl/continuous_conv/CoordinateTransformation: MapSphereToCylinder followed by
    MapCylinderToCube; Griepentrog et al.). Branches use torch.where with guarded denominators so
    the unselected branch never puts inf/nan into the gradient.
    """
    x, y, z = p.unbind(-1)
    one = torch.ones_like(x)

    # Sphere -> cylinder of radius 1, height [-1, 1].
    sq_norm = x * x + y * y + z * z
    centre = sq_norm < _EPS_SQ
    norm = sq_norm.clamp_min(_EPS_SQ).sqrt()
    sq_xy = x * x + y * y
    cap = 1.25 * z * z > sq_xy  # polar caps map to the cylinder's lids
    s_cap = (3.0 * norm / (norm + z.abs())).sqrt()
    # Off the caps sq_xy >= (5/9) sq_norm >= (5/9) eps, so this clamp only guards the unused branch.
    s_side = norm / sq_xy.clamp_min(0.5 * _EPS_SQ).sqrt()
    s = torch.where(cap, s_cap, s_side)
    x1, y1 = x * s, y * s
    z1 = torch.where(cap, torch.copysign(norm, z), 1.5 * z)

    # Cylinder -> cube: the disc's polar angle becomes the square's edge coordinate.
    sq_xy1 = x1 * x1 + y1 * y1
    axis = sq_xy1 < _EPS_SQ
    norm_xy = sq_xy1.clamp_min(_EPS_SQ).sqrt()
    x_major = y1.abs() <= x1.abs()
    den_x = torch.where(x_major & ~axis, x1, one)
    den_y = torch.where(~x_major & ~axis, y1, one)
    k = 4.0 / math.pi
    x_sx = torch.copysign(norm_xy, x1)
    y_sy = torch.copysign(norm_xy, y1)
    x2 = torch.where(x_major, x_sx, y_sy * k * torch.atan(x1 / den_y))
    y2 = torch.where(x_major, x_sx * k * torch.atan(y1 / den_x), y_sy)
    x2 = torch.where(axis, torch.zeros_like(x2), x2)
    y2 = torch.where(axis, torch.zeros_like(y2), y2)

    out = torch.stack((x2, y2, z1), dim=-1)
    return torch.where(centre[..., None], torch.zeros_like(out), out)


def poly6_window(r_sq_normalised: Tensor) -> Tensor:
    """Pair importance clamp((1 - |r|^2/R^2)^3, 0, 1) from |r|^2/R^2: 1 at the centre, 0 at R."""
    return (1.0 - r_sq_normalised).pow(3).clamp(0.0, 1.0)


def trilinear_corners(grid_coord: Tensor, kernel_size: int) -> tuple[Tensor, Tensor]:
    """Flat cell indices (P, 8) and weights (P, 8) of grid coordinates (P, 3) in [0, K-1].

    Open3D's LINEAR interpolation: indices clamped to the grid, fractions clamped to [0, 1]. The
    flat index is (iz * K + iy) * K + ix, i.e. the kernel is stored [z, y, x] like Open3D's filter.
    """
    k = kernel_size
    i0 = grid_coord.detach().floor().clamp(0, k - 1)
    frac = (grid_coord - i0).clamp(0.0, 1.0)  # (P, 3), differentiable
    i0 = i0.long()
    i1 = (i0 + 1).clamp(max=k - 1)
    idx = torch.stack((i0, i1), dim=-1)  # (P, 3, 2): axis, lower/upper
    w = torch.stack((1.0 - frac, frac), dim=-1)  # (P, 3, 2)
    ix, iy, iz = idx.unbind(1)
    wx, wy, wz = w.unbind(1)
    flat = (iz[:, :, None, None] * k + iy[:, None, :, None]) * k + ix[:, None, None, :]  # (P, 2, 2, 2)
    weight = wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]
    return flat.reshape(-1, 8), weight.reshape(-1, 8)


class ContinuousConv(nn.Module):
    """g_i = sum_j window(|r_ij|) W(r_ij)^T u_j + b over given pairs (i = query, j = neighbour).

    Kernel parameter (K, K, K, Cin, Cout) stored [z, y, x] (Open3D layout), bias (Cout,).
    radius [m] is the kernel's support: extent 2 * radius in Open3D's terms.
    """

    def __init__(self, in_channels: int, out_channels: int, radius: float, kernel_size: int = 4, bias: bool = True) -> None:
        super().__init__()
        if not radius > 0.0:
            raise ValueError(f"radius must be positive, got {radius}")
        if kernel_size < 2:
            raise ValueError(f"kernel_size must be >= 2 (align_corners grid), got {kernel_size}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.radius = float(radius)
        self.kernel_size = kernel_size
        self.kernel = nn.Parameter(torch.empty(kernel_size, kernel_size, kernel_size, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Xavier-uniform over the kernel as a (K^3 * Cin) -> (K^3 * Cout) map; zero bias."""
        cells = self.kernel_size**3
        bound = math.sqrt(6.0 / (cells * (self.in_channels + self.out_channels)))
        nn.init.uniform_(self.kernel, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, radius={self.radius}, kernel_size={self.kernel_size}"

    def forward(
        self,
        query_pos: Tensor,
        neighbor_pos: Tensor,
        neighbor_feats: Tensor,
        qi: Tensor,
        pj: Tensor,
        offset_transform: Tensor | None = None,
        pair_feats: Tensor | None = None,
        window_dist: Tensor | None = None,
    ) -> Tensor:
        """Aggregate neighbour features onto queries.

        query_pos (N, 3), neighbor_pos (M, 3) [m]; neighbor_feats (M, Cin - Cp); pairs qi, pj (P,) int64
        indexing query and neighbour; offset_transform (3, 3) applied to offsets before the kernel
        lookup (the window uses the untransformed offset). pair_feats (P, Cp): features of the pair itself,
        appended to the neighbour's; window_dist (P,) [m]: the distance the window fades with instead of
        |r| (e.g. the rest distance, so a stretched pair keeps its weight). Returns (N, Cout). Geometry and
        the sum over pairs run in float32 (float64 if positions are float64) even under autocast.
        """
        n, k = query_pos.shape[0], self.kernel_size
        if query_pos.ndim != 2 or query_pos.shape[1] != 3:
            raise ValueError(f"query_pos must be (N, 3), got {tuple(query_pos.shape)}")
        if neighbor_pos.ndim != 2 or neighbor_pos.shape[1] != 3:
            raise ValueError(f"neighbor_pos must be (M, 3), got {tuple(neighbor_pos.shape)}")
        if qi.ndim != 1 or qi.shape != pj.shape:
            raise ValueError(f"qi and pj must be equal-length 1-D index tensors, got {tuple(qi.shape)}, {tuple(pj.shape)}")
        self._check_features(neighbor_pos, neighbor_feats, pair_feats, window_dist, qi.shape, offset_transform)

        dtype = _geometry_dtype(query_pos)
        with torch.autocast(device_type=query_pos.device.type, enabled=False):
            r = neighbor_pos.to(dtype)[pj] - query_pos.to(dtype)[qi]  # (P, 3) [m]
            importance, grid_coord = self._kernel_coordinates(r, offset_transform, window_dist)
            cell, weight = trilinear_corners(grid_coord, k)  # (P, 8)
            feats = _with_pair_feats(neighbor_feats.to(dtype)[pj], pair_feats)  # (P, Cin)
            values = (weight * importance[:, None])[:, :, None] * feats[:, None, :]  # (P, 8, Cin)
            acc = torch.zeros(n * k**3, self.in_channels, dtype=dtype, device=query_pos.device)
            acc.index_add_(0, (qi[:, None] * k**3 + cell).reshape(-1), values.reshape(-1, self.in_channels))
        return self._apply_kernel(acc.reshape(n, k**3 * self.in_channels))

    def forward_padded(self, query_pos: Tensor, neighbor_pos: Tensor, neighbor_feats: Tensor, index: Tensor,
                       valid: Tensor, offset_transform: Tensor | None = None, pair_feats: Tensor | None = None,
                       window_dist: Tensor | None = None) -> Tensor:
        """`forward` over fixed-K padded neighbour slots: index (N, K) into the neighbours, valid (N, K) bool;
        pair_feats (N, K, Cp) and window_dist (N, K) as in `forward`, per slot.

        Static shapes and no scatter: each slot's K^3 trilinear weights are the product of per-axis hat functions
        max(0, 1 - |g - node|) (equal to the corner weights of `trilinear_corners` inside the grid), and the sum
        over slots is one batched matmul. Padding slots contribute exactly zero. Returns (N, Cout).
        """
        n, k = query_pos.shape[0], self.kernel_size
        if index.ndim != 2 or index.shape[0] != n or valid.shape != index.shape:
            raise ValueError(f"index and valid must both be (N={n}, K), got {tuple(index.shape)}, {tuple(valid.shape)}")
        self._check_features(neighbor_pos, neighbor_feats, pair_feats, window_dist, index.shape, offset_transform)
        dtype = _geometry_dtype(query_pos)
        with torch.autocast(device_type=query_pos.device.type, enabled=False):
            r = _gather_rows(neighbor_pos.to(dtype), index) - query_pos.to(dtype)[:, None]  # (N, K, 3) [m]
            importance, grid_coord = self._kernel_coordinates(r, offset_transform, window_dist)
            importance = importance * valid.to(dtype)
            nodes = torch.arange(k, device=r.device, dtype=dtype)
            # clamped to the grid like `trilinear_corners` (a transformed offset may leave the unit ball)
            g = grid_coord.clamp(0.0, k - 1.0)
            hat = (1.0 - (g[..., None] - nodes).abs()).clamp_min(0.0)  # (N, K, 3, k): x, y, z axes
            wx, wy, wz = hat.unbind(-2)
            cells = (wz[..., :, None, None] * wy[..., None, :, None] * wx[..., None, None, :]).flatten(-3)  # [z, y, x]
            cells = cells * importance[..., None]  # (N, K, k^3)
            feats = _with_pair_feats(_gather_rows(neighbor_feats.to(dtype), index), pair_feats)  # (N, K, Cin)
            acc = torch.bmm(cells.transpose(1, 2), feats)  # (N, k^3, Cin): sum over slots
        return self._apply_kernel(acc.reshape(n, k**3 * self.in_channels))

    def _check_features(self, neighbor_pos: Tensor, neighbor_feats: Tensor, pair_feats: Tensor | None,
                        window_dist: Tensor | None, pairs: torch.Size, offset_transform: Tensor | None) -> None:
        """ValueError naming the argument whose shape does not fit `pairs` (P,) or (N, K) and the channels."""
        own = self.in_channels - (0 if pair_feats is None else pair_feats.shape[-1])
        if neighbor_feats.shape != (neighbor_pos.shape[0], own):
            raise ValueError(f"neighbor_feats must be ({neighbor_pos.shape[0]}, {own}), got {tuple(neighbor_feats.shape)}")
        if pair_feats is not None and pair_feats.shape[:-1] != pairs:
            raise ValueError(f"pair_feats must be ({', '.join(map(str, pairs))}, Cp), got {tuple(pair_feats.shape)}")
        if window_dist is not None and window_dist.shape != pairs:
            raise ValueError(f"window_dist must be {tuple(pairs)}, got {tuple(window_dist.shape)}")
        if offset_transform is not None and offset_transform.shape != (3, 3):
            raise ValueError(f"offset_transform must be (3, 3), got {tuple(offset_transform.shape)}")

    def _kernel_coordinates(self, r: Tensor, offset_transform: Tensor | None,
                            window_dist: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Window importance (...,) and kernel grid coordinates (..., 3) in [0, K-1] of offsets r (..., 3) [m];
        the window fades with window_dist (...,) [m] when given, else with |r|."""
        dist_sq = r.square().sum(-1) if window_dist is None else window_dist.to(r.dtype).square()
        importance = poly6_window(dist_sq / self.radius**2)
        if offset_transform is not None:
            r = r @ offset_transform.to(r.dtype).T
        cube = ball_to_cube_volume_preserving(r / self.radius)  # in [-1, 1]^3
        return importance, (cube + 1.0) * (0.5 * (self.kernel_size - 1))  # align_corners: [-1, 1] -> [0, K-1]

    def _apply_kernel(self, acc: Tensor) -> Tensor:
        """One matmul for all queries (N, K^3 Cin) -> (N, Cout); autocast may run it in bf16, the sums stay fp32."""
        out = acc @ self.kernel.reshape(-1, self.out_channels).to(acc.dtype)
        if self.bias is not None:
            out = out + self.bias
        return out


def _with_pair_feats(feats: Tensor, pair_feats: Tensor | None) -> Tensor:
    """Each pair's neighbour features (..., C) followed by its own pair features (..., Cp), if any."""
    return feats if pair_feats is None else torch.cat((feats, pair_feats.to(feats.dtype)), dim=-1)


def _gather_rows(t: Tensor, index: Tensor) -> Tensor:
    """t[index] for t (M, C) and index (N, K) -> (N, K, C) through index_select, whose backward is an atomic
    index_add (advanced indexing's backward sorts the indices: 80 % of an eager training step on an H100)."""
    return t.index_select(0, index.reshape(-1)).reshape(*index.shape, t.shape[-1])


def _geometry_dtype(t: Tensor) -> torch.dtype:
    """float64 for float64 positions, else float32 (geometry never runs in reduced precision)."""
    return torch.float64 if t.dtype == torch.float64 else torch.float32
