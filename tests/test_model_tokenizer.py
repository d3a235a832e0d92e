"""Neighbour search, continuous convolution and the contact-centric vertex tokenizer (small CPU cases)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from wc.model.conv import ContinuousConv, ball_to_cube_volume_preserving
from wc.model.neighbors import nearest_index, radius_pairs
from wc.model.tokenizer import ContactTokenizer, LinearTokenizer, topology_pairs


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------- neighbours


def _brute_pairs(q, p, radius, qb, pb, exclude_self=False):
    d2 = (p[None, :, :] - q[:, None, :]).square().sum(-1)  # same expression as radius_pairs' final test
    mask = (d2 < radius**2) & (qb[:, None] == pb[None, :])
    if exclude_self:
        mask &= torch.arange(q.shape[0])[:, None] != torch.arange(p.shape[0])[None, :]
    return mask.nonzero(as_tuple=True)  # row-major: sorted by qi then pj


@pytest.mark.parametrize("batches", [1, 3])
def test_radius_pairs_matches_brute_force(batches):
    g = _gen(1)
    q = torch.rand(300, 3, generator=g) * 0.4 - 0.2
    p = torch.rand(200, 3, generator=g) * 0.4 - 0.2
    qb = torch.randint(0, batches, (300,), generator=g)
    pb = torch.randint(0, batches, (200,), generator=g)
    qi, pj = radius_pairs(q, p, 0.05, query_batch=qb, point_batch=pb)
    bi, bj = _brute_pairs(q, p, 0.05, qb, pb)
    assert qi.dtype == pj.dtype == torch.int64
    assert qi.numel() > 100
    assert torch.equal(qi, bi) and torch.equal(pj, bj)
    # the brief's brute force with cdist agrees as well (no distance sits on the radius here)
    d = torch.cdist(q.double(), p.double())
    ci, cj = ((d < 0.05) & (qb[:, None] == pb[None, :])).nonzero(as_tuple=True)
    assert torch.equal(qi, ci) and torch.equal(pj, cj)


def test_radius_pairs_exclude_self_and_empty():
    g = _gen(2)
    x = torch.rand(150, 3, generator=g) * 0.2
    b = torch.randint(0, 3, (150,), generator=g)
    qi, pj = radius_pairs(x, x, 0.04, query_batch=b, point_batch=b, exclude_self=True)
    bi, bj = _brute_pairs(x, x, 0.04, b, b, exclude_self=True)
    assert torch.equal(qi, bi) and torch.equal(pj, bj)
    assert not torch.any(qi == pj)
    with_self, _ = radius_pairs(x, x, 0.04, query_batch=b, point_batch=b)
    assert with_self.numel() == qi.numel() + 150
    for q, p in ((torch.zeros(0, 3), x), (x, torch.zeros(0, 3))):
        ei, ej = radius_pairs(q, p, 0.04)
        assert ei.shape == ej.shape == (0,) and ei.dtype == torch.int64
    far_i, _ = radius_pairs(x, x + 10.0, 0.04)  # no pair at all
    assert far_i.numel() == 0


def test_nearest_index():
    g = _gen(3)
    q = torch.rand(50, 3, generator=g)
    p = torch.rand(40, 3, generator=g)
    qb = torch.randint(0, 2, (50,), generator=g)
    pb = torch.arange(40) % 2
    j = nearest_index(q, p, qb, pb)
    d = (q[:, None] - p[None]).square().sum(-1).masked_fill(qb[:, None] != pb[None], math.inf)
    assert torch.equal(j, d.argmin(1))
    with pytest.raises(ValueError, match="no points"):
        nearest_index(q, p, qb, torch.zeros(40, dtype=torch.long))


def test_topology_pairs_stay_in_object_and_radius():
    g = _gen(4)
    uv = torch.rand(60, 2, generator=g) * 0.1
    obj = torch.randint(0, 2, (60,), generator=g)
    ti, tj = topology_pairs(uv, obj, 0.03)
    assert ti.numel() > 0
    assert torch.all(obj[ti] == obj[tj]) and not torch.any(ti == tj)
    assert torch.all((uv[ti] - uv[tj]).square().sum(-1) < 0.03**2)


# ---------------------------------------------------------------- continuous convolution


def _ball_to_cube_reference(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Open3D's MapSphereToCylinder + MapCylinderToCube, scalar, written from the formula."""
    n2 = x * x + y * y + z * z
    if n2 < 1e-8:
        return 0.0, 0.0, 0.0
    n = math.sqrt(n2)
    if 1.25 * z * z > x * x + y * y:
        s = math.sqrt(3 * n / (n + abs(z)))
        x, y, z = x * s, y * s, math.copysign(n, z)
    else:
        s = n / math.sqrt(x * x + y * y)
        x, y, z = x * s, y * s, 1.5 * z
    nxy2 = x * x + y * y
    if nxy2 < 1e-8:
        return 0.0, 0.0, z
    nxy = math.sqrt(nxy2)
    if abs(y) <= abs(x):
        t = math.copysign(nxy, x)
        return t, t * 4 / math.pi * math.atan(y / x), z
    t = math.copysign(nxy, y)
    return t * 4 / math.pi * math.atan(x / y), t, z


def _conv_reference(conv, qpos, npos, feats, qi, pj, transform=None):
    """out[i] = b + sum_pairs window * sum_corners w_c * kernel[z, y, x]^T u_j, with Python loops."""
    k, radius = conv.kernel_size, conv.radius
    out = conv.bias.detach().double().repeat(qpos.shape[0], 1)
    kern = conv.kernel.detach().double()
    for i, j in zip(qi.tolist(), pj.tolist()):
        r = (npos[j] - qpos[i]).double()
        window = min(max((1 - float(r @ r) / radius**2) ** 3, 0.0), 1.0)
        if transform is not None:
            r = transform.double() @ r
        cube = _ball_to_cube_reference(*(r / radius).tolist())
        coord = [(c + 1) / 2 * (k - 1) for c in cube]
        lo = [min(max(int(math.floor(c)), 0), k - 1) for c in coord]
        frac = [min(max(c - l, 0.0), 1.0) for c, l in zip(coord, lo)]
        for corner in itertools.product((0, 1), repeat=3):  # (x, y, z) offsets
            w, idx = 1.0, []
            for axis in range(3):
                w *= frac[axis] if corner[axis] else 1 - frac[axis]
                idx.append(min(lo[axis] + corner[axis], k - 1))
            out[i] += window * w * (feats[j].double() @ kern[idx[2], idx[1], idx[0]])
    return out


def test_ball_to_cube_matches_open3d_formula_and_preserves_volume():
    g = _gen(5)
    d = torch.randn(200, 3, generator=g, dtype=torch.float64)
    p = d / d.norm(dim=1, keepdim=True) * torch.rand(200, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    ref = torch.tensor([_ball_to_cube_reference(*row) for row in p.tolist()], dtype=torch.float64)
    assert torch.allclose(ball_to_cube_volume_preserving(p), ref, atol=1e-12)
    for point in p[:10]:  # Jacobian determinant = cube volume / ball volume everywhere
        jac = torch.autograd.functional.jacobian(ball_to_cube_volume_preserving, point)
        assert torch.linalg.det(jac).item() == pytest.approx(6 / math.pi, rel=1e-9)
    surface = ball_to_cube_volume_preserving(d / d.norm(dim=1, keepdim=True))
    assert torch.allclose(surface.abs().amax(1), torch.ones(200, dtype=torch.float64))


def _conv_case(seed: int, dtype=torch.float32):
    g = _gen(seed)
    conv = ContinuousConv(5, 3, radius=0.1, kernel_size=4).to(dtype)
    with torch.no_grad():
        conv.bias.uniform_(-1, 1, generator=g)
    qpos = (torch.rand(6, 3, generator=g) * 0.15).to(dtype)
    npos = (torch.rand(9, 3, generator=g) * 0.15).to(dtype)
    feats = torch.randn(9, 5, generator=g).to(dtype)
    qi, pj = radius_pairs(qpos.float(), npos.float(), 0.1)
    return conv, qpos, npos, feats, qi, pj


def test_continuous_conv_matches_reference():
    conv, qpos, npos, feats, qi, pj = _conv_case(6)
    assert qi.numel() >= 10
    out = conv(qpos, npos, feats, qi, pj)
    assert out.shape == (6, 3) and out.dtype == torch.float32
    assert torch.allclose(out.double(), _conv_reference(conv, qpos, npos, feats, qi, pj), atol=1e-5)
    transform = torch.eye(3) + 0.2 * torch.randn(3, 3, generator=_gen(7))
    out_t = conv(qpos, npos, feats, qi, pj, transform)
    assert torch.allclose(out_t.double(), _conv_reference(conv, qpos, npos, feats, qi, pj, transform), atol=1e-5)
    assert not torch.allclose(out_t, out)


def test_continuous_conv_window_and_pair_order():
    conv, qpos, npos, feats, qi, pj = _conv_case(8)
    out = conv(qpos, npos, feats, qi, pj)
    perm = torch.randperm(qi.numel(), generator=_gen(9))
    assert torch.allclose(conv(qpos, npos, feats, qi[perm], pj[perm]), out, atol=1e-6)
    # a pair beyond the radius contributes nothing (window 0), one inside does
    far = torch.tensor([[0.0, 0.0, 0.0], [0.101, 0.0, 0.0], [0.0, 0.05, 0.0]])
    one = torch.zeros(1, dtype=torch.long)
    f1 = torch.ones(3, 5)
    beyond = conv(far[:1], far, f1, one, torch.tensor([1]))
    inside = conv(far[:1], far, f1, one, torch.tensor([2]))
    assert torch.equal(beyond, conv.bias.detach()[None])
    assert not torch.allclose(inside, beyond)
    empty = conv(qpos, npos, feats, qi[:0], pj[:0])  # no pairs: bias only
    assert torch.equal(empty, conv.bias.detach().expand(6, 3))


def test_continuous_conv_gradcheck_float64():
    conv, qpos, npos, feats, qi, pj = _conv_case(10, torch.float64)
    qi, pj = qi[:6], pj[:6]
    transform = (torch.eye(3, dtype=torch.float64) + 0.1).requires_grad_()
    qpos.requires_grad_()
    npos.requires_grad_()
    feats.requires_grad_()
    assert conv(qpos, npos, feats, qi, pj, transform).dtype == torch.float64
    assert torch.autograd.gradcheck(
        lambda a, b, c, t: conv(a, b, c, qi, pj, t), (qpos, npos, feats, transform), eps=1e-7, atol=1e-6
    )
    out = conv(qpos, npos, feats, qi, pj).sum()
    out.backward()
    assert conv.kernel.grad is not None and conv.kernel.grad.abs().sum() > 0


# ---------------------------------------------------------------- tokenizer

RADII = dict(spatial_radius=0.03, topology_radius=0.03, controllable_radius=0.04, environment_radius=0.04)


def _scene(b: int = 1, n: int = 40, mc: int = 12, me: int = 10, seed: int = 11):
    g = _gen(seed)
    uv = torch.rand(n, 2, generator=g) * 0.1
    obj = (torch.arange(n) >= n // 2).long()
    attributes = torch.cat((obj[:, None].float() * 0.5, uv), dim=1)
    ti, tj = topology_pairs(uv, obj, RADII["topology_radius"])

    def normals(m):
        nn_ = torch.randn(b, m, 3, generator=g)
        return nn_ / nn_.norm(dim=-1, keepdim=True)

    state = dict(
        x=torch.rand(b, n, 3, generator=g) * 0.1,
        v=torch.randn(b, n, 3, generator=g) * 0.2,
        attributes=attributes,
        object_index=obj,
        ti=ti,
        tj=tj,
        ctrl_x=torch.rand(b, mc, 3, generator=g) * 0.1,
        ctrl_v=torch.randn(b, mc, 3, generator=g) * 0.2,
        ctrl_attr=torch.cat((torch.full((b, mc, 1), 1.0), normals(mc)), dim=-1),
        env_x=torch.rand(b, me, 3, generator=g) * 0.1,
        env_v=torch.zeros(b, me, 3),
        env_attr=torch.cat((torch.full((b, me, 1), -1.0), normals(me)), dim=-1),
    )
    return state


def _tokenizer(seed: int = 0) -> ContactTokenizer:
    torch.manual_seed(seed)
    tok = ContactTokenizer(**RADII, velocity_scale=0.5)
    with torch.no_grad():  # nonzero biases and a non-trivial frame, so the tests see every part
        for p in tok.parameters():
            if p.ndim == 1:
                p.uniform_(-0.1, 0.1)
        tok.offset_transform.add_(0.1 * torch.randn(3, 3))
    return tok


def test_parameter_count_and_shape():
    tok = ContactTokenizer(**RADII, velocity_scale=0.5)
    assert sum(p.numel() for p in tok.parameters()) == 57_993
    assert torch.equal(tok.offset_transform.detach(), torch.eye(3))
    s = _scene()
    h = tok(**s)
    assert h.shape == (1, 40, 192) and torch.isfinite(h).all()


def test_translation_invariance():
    tok = _tokenizer()
    s = _scene()
    shift = torch.tensor([0.7, -0.3, 0.2])
    moved = dict(s, x=s["x"] + shift, ctrl_x=s["ctrl_x"] + shift, env_x=s["env_x"] + shift)
    h, h_moved = tok(**s), tok(**moved)
    assert h[..., :128].abs().max() > 1e-3  # the convolutions see neighbours
    assert torch.allclose(h, h_moved, atol=1e-5)


def test_controllable_sample_inside_radius_only():
    tok = _tokenizer()
    s = _scene(mc=0)
    h0 = tok(**s)
    x0 = s["x"][0, 0]
    ctrl_attr = torch.tensor([[[1.0, 0.0, 0.0, 1.0]]])
    far = dict(s, ctrl_x=(x0 + torch.tensor([0.5, 0.0, 0.0])).reshape(1, 1, 3), ctrl_v=torch.ones(1, 1, 3),
               ctrl_attr=ctrl_attr)
    near = dict(far, ctrl_x=(x0 + torch.tensor([0.01, 0.0, 0.0])).reshape(1, 1, 3))
    assert torch.equal(tok(**far), h0)
    h_near = tok(**near)
    g_c = slice(96, 128)  # order: S 32, T 32, E 32, C 32, direct 64
    assert not torch.allclose(h_near[0, 0, g_c], h0[0, 0, g_c])
    assert torch.equal(h_near[..., :96], h0[..., :96]) and torch.equal(h_near[..., 128:], h0[..., 128:])


def test_batch_equals_single_runs():
    tok = _tokenizer()
    s = _scene(b=2)
    h = tok(**s)
    for i in range(2):
        single = {k: (t[i : i + 1] if k not in ("attributes", "object_index", "ti", "tj") else t) for k, t in s.items()}
        assert torch.allclose(h[i : i + 1], tok(**single), atol=1e-6)


def test_linear_tokenizer_shapes():
    tok = LinearTokenizer(velocity_scale=0.5)
    s = _scene(b=2)
    h = tok(**s)
    assert h.shape == (2, 40, 192) and torch.isfinite(h).all()
    no_ctrl = _scene(b=2, mc=0)
    assert tok(**no_ctrl).shape == (2, 40, 192)
    assert ContactTokenizer(**RADII, velocity_scale=0.5)(**no_ctrl).shape == (2, 40, 192)


@pytest.mark.parametrize("cls", ["contact", "linear"])
def test_clear_errors(cls):
    tok = ContactTokenizer(**RADII, velocity_scale=0.5) if cls == "contact" else LinearTokenizer(velocity_scale=0.5)
    s = _scene()
    with pytest.raises(ValueError, match=r"x must be \(B, N, 3\)"):
        tok(**dict(s, x=s["x"][0]))
    with pytest.raises(ValueError, match="attributes has 39 rows"):
        tok(**dict(s, attributes=s["attributes"][:-1]))
    with pytest.raises(ValueError, match="ctrl_attr must be"):
        tok(**dict(s, ctrl_attr=s["ctrl_attr"][..., :3]))
    with pytest.raises(ValueError, match="env_v must be"):
        tok(**dict(s, env_v=s["env_v"][:, :-1]))
    bad = s["x"].clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite x in the object state"):
        tok(**dict(s, x=bad))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    dev = torch.device("cuda")
    g = _gen(12)
    x = torch.rand(500, 3, generator=g) * 0.3
    b = torch.randint(0, 3, (500,), generator=g)
    cpu_pairs = radius_pairs(x, x, 0.04, query_batch=b, point_batch=b, exclude_self=True)
    cuda_pairs = radius_pairs(x.to(dev), x.to(dev), 0.04, query_batch=b.to(dev), point_batch=b.to(dev), exclude_self=True)
    assert all(c.device.type == "cuda" for c in cuda_pairs)
    assert all(torch.equal(a, c.cpu()) for a, c in zip(cpu_pairs, cuda_pairs))
    assert torch.equal(nearest_index(x[:50].to(dev), x[50:].to(dev)).cpu(), nearest_index(x[:50], x[50:]))

    tok = _tokenizer()
    s = _scene(b=2)
    h = tok(**s)
    tok_cuda = tok.to(dev)
    s_cuda = {k: t.to(dev) for k, t in s.items()}
    h_cuda = tok_cuda(**s_cuda)
    assert torch.allclose(h_cuda.cpu(), h, atol=1e-5)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        h_bf16 = tok_cuda(**s_cuda)
    assert torch.isfinite(h_bf16).all()
    assert torch.allclose(h_bf16.float().cpu(), h, atol=0.05, rtol=0.05)
    h_bf16.float().square().sum().backward()
    assert tok_cuda.spatial.kernel.grad is not None and torch.isfinite(tok_cuda.spatial.kernel.grad).all()
    lin = LinearTokenizer(velocity_scale=0.5)
    assert torch.allclose(lin.to(dev)(**s_cuda).cpu(), lin.cpu()(**s), atol=1e-5)
