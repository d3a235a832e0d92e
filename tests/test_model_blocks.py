"""Attention, encoder (merging), decoder, head and topology projection of the WorldContact network."""

from __future__ import annotations

import math

import pytest
import torch

from wc.model import encoder as encoder_module
from wc.model.attention import Attention, RoPE3D, SwiGLU
from wc.model.decoder import GlobalTokenDecoder
from wc.model.encoder import HierarchicalEncoder, bipartite_merge
from wc.model.head import StateHead
from wc.model.projection import TopologyProjection, edges_from_faces

C = 192


def n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def grid_mesh(n: int, spacing_m: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat n x n vertex grid (n^2, 3) [m] and its triangles (2 (n-1)^2, 3)."""
    ii, jj = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    x = torch.stack([ii * spacing_m, jj * spacing_m, torch.zeros(n, n)], dim=-1).reshape(-1, 3).float()
    v = (ii[:-1, :-1] * n + jj[:-1, :-1]).reshape(-1)
    faces = torch.cat([torch.stack([v, v + n, v + 1], -1), torch.stack([v + 1, v + n, v + n + 1], -1)])
    return x, faces


def test_parameter_counts_match_appendix() -> None:
    assert n_params(HierarchicalEncoder()) == 782_784
    assert n_params(HierarchicalEncoder().levels[0]) == 260_928
    assert n_params(GlobalTokenDecoder()) == 1_116_480
    assert n_params(GlobalTokenDecoder().layers[0]) == 372_160
    assert n_params(StateHead()) == 42_502
    assert n_params(RoPE3D()) == 0


@pytest.mark.parametrize("n", [1, 2, 3, 8, 9])
def test_merge_keeps_multiplicity_and_weighted_means(n: int) -> None:
    torch.manual_seed(n)
    h, x = torch.randn(2, n, 16), torch.randn(2, n, 3)
    m = torch.randint(1, 5, (2, n)).float()
    h2, x2, m2 = bipartite_merge(h, x, m, torch.randn(2, n, 24))
    assert h2.shape == (2, math.ceil(n / 2), 16) and x2.shape == (2, math.ceil(n / 2), 3) and m2.shape == (2, math.ceil(n / 2))
    torch.testing.assert_close(m2.sum(1), m.sum(1))
    torch.testing.assert_close((m2[..., None] * x2).sum(1), (m[..., None] * x).sum(1))
    torch.testing.assert_close((m2[..., None] * h2).sum(1), (m[..., None] * h).sum(1))


def test_merge_joins_each_odd_token_to_most_similar_even_token() -> None:
    torch.manual_seed(0)
    keys_b = torch.randn(1, 4, 24)
    keys = torch.stack([keys_b, 3.0 * keys_b.roll(1, dims=1)], dim=2).flatten(1, 2)  # odd 2i+1 ~ even 2(i-1)
    h = torch.arange(8.0).reshape(1, 8, 1)
    h2, _, m2 = bipartite_merge(h, torch.zeros(1, 8, 3), torch.ones(1, 8), keys)
    # even 2k is joined by odd 2k+3 (cyclically)
    torch.testing.assert_close(m2, torch.full((1, 4), 2.0))
    torch.testing.assert_close(h2[0, :, 0], torch.tensor([(0 + 3) / 2, (2 + 5) / 2, (4 + 7) / 2, (6 + 1) / 2]))


def test_merge_chunked_similarity_matches_one_chunk(monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(1)
    h, x, keys = torch.randn(2, 33, 8), torch.randn(2, 33, 3), torch.randn(2, 33, 24)
    full = bipartite_merge(h, x, torch.ones(2, 33), keys)
    monkeypatch.setattr(encoder_module, "_SIM_CHUNK_ELEMENTS", 40)  # 1 A row per chunk
    for a, b in zip(full, bipartite_merge(h, x, torch.ones(2, 33), keys)):
        torch.testing.assert_close(a, b)


def test_merge_is_differentiable_in_features_and_anchors() -> None:
    h, x = torch.randn(1, 5, 4, requires_grad=True), torch.randn(1, 5, 3, requires_grad=True)
    h2, x2, _ = bipartite_merge(h, x, torch.ones(1, 5), torch.randn(1, 5, 24))
    (h2.sum() + x2.sum()).backward()
    assert (h.grad != 0).all() and (x.grad != 0).all()


def test_rope_is_a_rotation_with_relative_positions() -> None:
    torch.manual_seed(0)
    rope = RoPE3D(24, 0.02, 2.0)
    q, k = torch.randn(2, 8, 10, 24), torch.randn(2, 8, 12, 24)
    pq, pk = torch.rand(2, 10, 3), torch.rand(2, 12, 3)
    rq = rope(q, pq)
    torch.testing.assert_close(rq.norm(dim=-1), q.norm(dim=-1))
    shift = torch.tensor([0.37, -1.2, 0.05])
    scores = rq @ rope(k, pk).transpose(-1, -2)
    shifted = rope(q, pq + shift) @ rope(k, pk + shift).transpose(-1, -2)
    torch.testing.assert_close(shifted, scores, atol=2e-3, rtol=0)  # float32 angles of up to ~400 rad
    q64, k64, pq64, pk64 = q.double(), k.double(), pq.double(), pk.double()
    scores64 = rope(q64, pq64) @ rope(k64, pk64).transpose(-1, -2)
    shifted64 = rope(q64, pq64 + shift.double()) @ rope(k64, pk64 + shift.double()).transpose(-1, -2)
    torch.testing.assert_close(shifted64, scores64, atol=1e-9, rtol=0)
    assert not torch.allclose(scores, q @ k.transpose(-1, -2), atol=1e-2)  # positions matter


@pytest.mark.parametrize("cross", [False, True])
def test_attention_batch_equals_single_scene_runs(cross: bool) -> None:
    torch.manual_seed(0)
    attn = Attention(C, 8, qk_norm=True, dropout=0.1).eval()
    h, x = torch.randn(2, 7, C), torch.rand(2, 7, 3)
    ctx, cx = (torch.randn(2, 5, C), torch.rand(2, 5, 3)) if cross else (None, None)
    out, keys = attn(h, x, ctx, cx, return_keys=True)
    assert out.shape == (2, 7, C) and keys.shape == (2, 5 if cross else 7, 24)
    for b in range(2):
        one = attn(h[b:b + 1], x[b:b + 1], None if ctx is None else ctx[b:b + 1], None if cx is None else cx[b:b + 1])
        torch.testing.assert_close(out[b:b + 1], one, atol=1e-5, rtol=1e-5)


def test_swiglu_shape() -> None:
    assert SwiGLU(C, 128)(torch.randn(3, 4, C)).shape == (3, 4, C)


@pytest.mark.parametrize("n", [1, 2, 7, 64])
@pytest.mark.parametrize("compress", [True, False])
def test_encoder_output_shapes(n: int, compress: bool) -> None:
    enc = HierarchicalEncoder(compress=compress)
    g, ga, m = enc(torch.randn(2, n, C), torch.rand(2, n, 3))
    ng = math.ceil(n / 8) if compress else n
    assert g.shape == (2, ng, C) and ga.shape == (2, ng, 3) and m.shape == (2, ng)
    torch.testing.assert_close(m.sum(1), torch.full((2,), float(n)))


def test_decoder_and_head_shapes_and_near_zero_initial_prediction() -> None:
    dec, head = GlobalTokenDecoder(), StateHead()
    out = dec(torch.randn(2, 20, C), torch.rand(2, 20, 3), torch.randn(2, 3, C), torch.rand(2, 3, 3))
    assert out.shape == (2, 20, C)
    pred = head(out)
    assert pred.shape == (2, 20, 6) and pred.abs().max() < 0.1


def test_blocks_run_under_cpu_bf16_autocast_and_backprop() -> None:
    torch.manual_seed(0)
    enc, dec, head = HierarchicalEncoder(), GlobalTokenDecoder(), StateHead()
    h = torch.randn(2, 30, C, requires_grad=True)
    x = torch.rand(2, 30, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        g, ga, _ = enc(h, x)
        out = head(dec(h, x, g, ga))
    assert out.shape == (2, 30, 6) and torch.isfinite(out.float()).all()
    out.float().sum().backward()
    assert torch.isfinite(h.grad).all() and h.grad.abs().sum() > 0


def test_edges_from_faces_two_triangles() -> None:
    edges = edges_from_faces(torch.tensor([[0, 1, 2], [2, 1, 3]]))
    assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_projection_keeps_grid_edges_within_bounds() -> None:
    torch.manual_seed(0)
    spacing_m = 0.01
    x, faces = grid_mesh(16, spacing_m)
    edges = edges_from_faces(faces)
    rest = (x[edges[:, 1]] - x[edges[:, 0]]).norm(dim=-1)
    proj = TopologyProjection(edges, rest, x.shape[0])
    assert n_params(proj) == 0
    x_prev = x[None].expand(3, -1, -1)
    x_pred = x_prev + torch.tensor([0.002, 0.0, -0.001]) + 0.2 * spacing_m * torch.randn(3, *x.shape)
    ratio = lambda y: (y[:, edges[:, 1]] - y[:, edges[:, 0]]).norm(dim=-1) / rest  # noqa: E731
    assert ratio(x_pred).min() < 0.5 and ratio(x_pred).max() > 1.5  # the noise does violate the bounds
    r = ratio(proj(x_prev, x_pred))
    tol = 1e-3  # measured worst violation over seeds on 8..32 grids at this noise: 2.3e-4
    assert r.min() >= 0.9 - tol and r.max() <= 1.1 + tol
    # untouched when already in bounds: a rigid translation passes through unchanged
    torch.testing.assert_close(proj(x_prev, x_prev + 0.05), x_prev + 0.05)


@pytest.mark.parametrize(("smoothing_iterations", "constraint_iterations", "noise_m", "seed"), [(1, 8, 0.3, 0), (4, 32, 0.8, 2)])
def test_projection_gradcheck_two_triangles(smoothing_iterations: int, constraint_iterations: int, noise_m: float,
                                            seed: int) -> None:
    """Both stages active (the smoothed prediction still violates edges; 4 smoothing iterations bring small
    noise into bounds on this tiny mesh, hence fewer of them or larger noise). The averaged Jacobi step is
    only piecewise smooth (the set of violating edges changes where an edge sits at a bound); these
    cases keep finite differences off the kinks."""
    torch.manual_seed(seed)
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]], dtype=torch.float64)
    edges = edges_from_faces(torch.tensor([[0, 1, 2], [2, 1, 3]]))
    rest = (x[edges[:, 1]] - x[edges[:, 0]]).norm(dim=-1)
    x_prev = x[None].clone().requires_grad_(True)
    x_pred = (x[None] + noise_m * torch.randn(1, 4, 3, dtype=torch.float64)).requires_grad_(True)
    smoothed = TopologyProjection(edges, rest, 4, smoothing_iterations, constraint_iterations=0)(x_prev, x_pred)
    ratio = (smoothed[0, edges[:, 1]] - smoothed[0, edges[:, 0]]).norm(dim=-1) / rest
    assert ((ratio < 0.9) | (ratio > 1.1)).sum() >= 2
    proj = TopologyProjection(edges, rest, 4, smoothing_iterations, constraint_iterations=constraint_iterations)
    assert torch.autograd.gradcheck(proj, (x_prev, x_pred))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device (run on the GPU machine)")
def test_projection_cuda_graph_matches_eager_and_follows_new_inputs() -> None:
    """The no-grad CUDA path replays a captured graph: same result as eager, for new inputs of the same shape,
    and a second shape captures its own graph; with gradients the eager path runs."""
    torch.manual_seed(0)
    x, faces = grid_mesh(12)
    edges = edges_from_faces(faces).cuda()
    rest = (x[edges[:, 1].cpu()] - x[edges[:, 0].cpu()]).norm(dim=-1).cuda()
    proj = TopologyProjection(edges, rest, x.shape[0])
    for batch in (2, 2, 3):
        x_prev = x.cuda()[None].expand(batch, -1, -1).contiguous()
        x_pred = x_prev + 0.003 * torch.randn(batch, *x.shape, device="cuda")
        with torch.no_grad():
            graphed = proj(x_prev, x_pred)
        torch.testing.assert_close(graphed, proj.project(x_prev, x_pred), atol=1e-6, rtol=0)
    assert len(proj._graphs) == 2
    x_pred.requires_grad_(True)
    proj(x_prev, x_pred).sum().backward()
    assert x_pred.grad is not None


def test_projection_without_cuda_graph_is_the_eager_projection() -> None:
    """On CPU (and with cuda_graph off) forward is exactly project(), with and without gradients."""
    torch.manual_seed(1)
    x, faces = grid_mesh(8)
    edges = edges_from_faces(faces)
    rest = (x[edges[:, 1]] - x[edges[:, 0]]).norm(dim=-1)
    x_pred = x[None] + 0.003 * torch.randn(1, *x.shape)
    for proj in (TopologyProjection(edges, rest, x.shape[0]), TopologyProjection(edges, rest, x.shape[0], cuda_graph=False)):
        with torch.no_grad():
            assert torch.equal(proj(x[None], x_pred), proj.project(x[None], x_pred))
        assert not proj._graphs
