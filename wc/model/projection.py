"""Differentiable topology projection P used during fine-tuning (paper Eq. projection_finetune + Appendix).

P smooths the predicted displacement field with a few Laplacian iterations, then keeps every rest
edge within [min_ratio, max_ratio] of its rest length by Jacobi edge-constraint iterations. All
plain torch ops, so gradients flow through every iteration into the rollout. Without gradients on CUDA
(rollouts, expansion) the fixed-shape loop is captured once per input shape as a CUDA graph and
replayed: the same kernels, without ~500 launches per call.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


def edges_from_faces(faces: Tensor) -> Tensor:
    """Unique undirected edges (E, 2) long, each row sorted (i < j), from triangles faces (F, 3)."""
    faces = torch.as_tensor(faces, dtype=torch.long)
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], dim=0)
    return torch.unique(torch.sort(e, dim=1).values, dim=0)


class TopologyProjection(nn.Module):
    """X_hat = P(X_tilde, E): smoothing of the displacement, then edge-length limits (no parameters).

    The velocity rule V_hat = (X_hat_{t+dt} - X_hat_t) / dt of Eq. projection_finetune is applied by
    the caller on the returned positions.
    """

    def __init__(self, edges: Tensor, rest_lengths: Tensor, num_vertices: int, smoothing_iterations: int = 4,
                 smoothing_weight: float = 0.35, constraint_iterations: int = 32, min_ratio: float = 0.9,
                 max_ratio: float = 1.1, cuda_graph: bool = True) -> None:
        super().__init__()
        edges = torch.as_tensor(edges, dtype=torch.long)
        rest_lengths = torch.as_tensor(rest_lengths, dtype=torch.float32, device=edges.device)
        if edges.ndim != 2 or edges.shape[1] != 2 or rest_lengths.shape != edges.shape[:1]:
            raise ValueError(f"edges must be (E, 2) and rest_lengths (E,), got {tuple(edges.shape)} and {tuple(rest_lengths.shape)}")
        if not 0.0 < min_ratio <= 1.0 <= max_ratio:
            raise ValueError(f"need 0 < min_ratio <= 1 <= max_ratio, got {min_ratio}, {max_ratio}")
        self.num_vertices = num_vertices
        self.smoothing_iterations, self.smoothing_weight = smoothing_iterations, smoothing_weight
        self.constraint_iterations = constraint_iterations
        self.register_buffer("edges", edges, persistent=False)
        self.register_buffer("min_length", min_ratio * rest_lengths, persistent=False)  # (E,) [m]
        self.register_buffer("max_length", max_ratio * rest_lengths, persistent=False)  # (E,) [m]
        ones = torch.ones(edges.numel(), device=edges.device)
        degree = torch.zeros(num_vertices, device=edges.device).index_add_(0, edges.flatten(), ones)
        self.register_buffer("degree", degree, persistent=False)  # (N,) rest-edge neighbours
        self.cuda_graph = cuda_graph
        self._graphs: dict[tuple, tuple[torch.cuda.CUDAGraph, Tensor, Tensor, Tensor]] = {}

    def _neighbour_sum(self, d: Tensor) -> Tensor:
        """Sum over rest-edge neighbours of a per-vertex field d (B, N, K)."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        return torch.zeros_like(d).index_add(1, i, d.index_select(1, j)).index_add(1, j, d.index_select(1, i))

    def smooth(self, d: Tensor) -> Tensor:
        """Uniform-umbrella Laplacian smoothing d <- d + w (mean_nbr(d) - d); isolated vertices unchanged."""
        deg = self.degree.to(d.dtype)[:, None]
        has_nbr = (deg > 0).to(d.dtype)
        for _ in range(self.smoothing_iterations):
            d = d + self.smoothing_weight * has_nbr * (self._neighbour_sum(d) / deg.clamp(min=1) - d)
        return d

    def constrain(self, x: Tensor) -> Tensor:
        """Jacobi edge-length projection: every violating edge moves both ends equally to its nearest bound;
        per-vertex corrections are averaged over the violating edges at that vertex."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        lo, hi = self.min_length.to(x.dtype), self.max_length.to(x.dtype)
        eps = torch.finfo(x.dtype).tiny
        for _ in range(self.constraint_iterations):
            e = x.index_select(1, j) - x.index_select(1, i)  # (B, E, 3); index_select: an atomic backward
            length = (e.square().sum(-1) + eps).sqrt()  # eps keeps the gradient finite at zero length
            excess = length - torch.minimum(torch.maximum(length, lo), hi)  # 0 inside [lo, hi]
            violating = (excess != 0).to(x.dtype)
            step = (0.5 * excess / length)[..., None] * e  # move i by +step, j by -step
            correction = torch.zeros_like(x).index_add(1, i, step).index_add(1, j, -step)
            count = torch.zeros_like(x[..., 0]).index_add(1, i, violating).index_add(1, j, violating)
            x = x + correction / count.clamp(min=1)[..., None]
        return x

    def project(self, x_prev: Tensor, x_pred: Tensor) -> Tensor:
        """The eager (reference, differentiable) projection; see forward."""
        dtype = torch.promote_types(x_pred.dtype, torch.float32)
        x_prev, x_pred = x_prev.to(dtype), x_pred.to(dtype)
        x = x_prev + self.smooth(x_pred - x_prev)
        return self.constrain(x)

    def _graphed(self, x_prev: Tensor, x_pred: Tensor) -> Tensor:
        """project() through a CUDA graph captured on the first call with this shape and dtype."""
        dtype = torch.promote_types(x_pred.dtype, torch.float32)
        key = (tuple(x_pred.shape), dtype, x_pred.device)
        if key not in self._graphs:
            static_prev = x_prev.detach().to(dtype).clone()
            static_pred = x_pred.detach().to(dtype).clone()
            side = torch.cuda.Stream(x_pred.device)
            side.wait_stream(torch.cuda.current_stream(x_pred.device))
            with torch.cuda.stream(side), torch.autocast("cuda", enabled=False):
                self.project(static_prev, static_pred)  # warm-up outside the capture (allocator, kernels)
            torch.cuda.current_stream(x_pred.device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph), torch.autocast("cuda", enabled=False):
                static_out = self.project(static_prev, static_pred)
            self._graphs[key] = (graph, static_prev, static_pred, static_out)
        graph, static_prev, static_pred, static_out = self._graphs[key]
        static_prev.copy_(x_prev)
        static_pred.copy_(x_pred)
        graph.replay()
        return static_out.clone()

    def forward(self, x_prev: Tensor, x_pred: Tensor) -> Tensor:
        """Eq. projection_finetune: X_hat_{t+dt} (B, N, 3) [m] from X_hat_t = x_prev and the network's X_tilde = x_pred.

        Computed (and returned) in at least float32, also under autocast. Without gradients on CUDA (and
        cuda_graph set) it replays a captured CUDA graph of the same computation, except while a caller captures
        its own graph (a whole static rollout step): a graph cannot be replayed during a capture, so the projection's
        kernels are captured into the caller's.
        """
        if torch.compiler.is_compiling():  # inside a caller's compiled step: its kernels are the caller's
            return self.project(x_prev, x_pred)
        capturing = x_pred.is_cuda and torch.cuda.is_current_stream_capturing()  # inside a caller's graph: no replay
        if self.cuda_graph and x_pred.is_cuda and not torch.is_grad_enabled() and not capturing:
            return self._graphed(x_prev, x_pred)
        return self.project(x_prev, x_pred)
