"""model.rest_features: the rest-space pair features tell a mesh neighbour from another layer, keep a stretched
topology pair, and give the same tokens on the padded (static-shape) path as on the pair list."""

from __future__ import annotations

import torch

from tests.test_model_tokenizer import RADII, _scene, _tokenizer
from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.tokenizer import REST_FAR, ContactTokenizer, rest_pair_features, topology_pairs


def _rest_tokenizer(seed: int = 0) -> ContactTokenizer:
    torch.manual_seed(seed)
    tok = ContactTokenizer(**RADII, velocity_scale=0.5, rest_features=True)
    with torch.no_grad():
        for p in tok.parameters():
            if p.ndim == 1:
                p.uniform_(-0.1, 0.1)
    return tok


def test_rest_pair_features_tell_a_mesh_neighbour_from_another_layer():
    uv = torch.tensor([[0.0, 0.0], [0.01, 0.0], [0.5, 0.0], [0.0, 0.0]])
    obj = torch.tensor([0, 0, 0, 1])
    qi, pj = torch.tensor([0, 0, 0]), torch.tensor([1, 2, 3])
    feats, dist = rest_pair_features(uv, obj, qi, pj, radius=0.02)
    assert torch.allclose(feats[0], torch.tensor([0.5, 0.0, 0.5]))  # near in rest space
    assert torch.allclose(feats[1], torch.tensor([REST_FAR, 0.0, REST_FAR]))  # another layer: far, capped
    assert torch.equal(feats[2], torch.tensor([0.0, 0.0, REST_FAR]))  # another object
    assert torch.isclose(dist[0], torch.tensor(0.01)) and torch.isinf(dist[2])


def test_rest_features_keep_a_stretched_topology_pair():
    """Two same-object vertices 1 cm apart in rest uv, pulled 10 cm apart: the paper's window drops the pair
    (the topology channels see no neighbour), the rest-space window keeps it."""
    s = _scene(n=2, mc=0, me=0)
    uv = torch.tensor([[0.0, 0.0], [0.01, 0.0]])
    obj = torch.zeros(2, dtype=torch.long)
    ti, tj = topology_pairs(uv, obj, RADII["topology_radius"])
    stretched = dict(s, x=torch.tensor([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]]),
                     attributes=torch.cat((torch.zeros(2, 1), uv), dim=1), object_index=obj, ti=ti, tj=tj)
    g_t = slice(32, 64)
    for tok, keeps in ((_tokenizer(), False), (_rest_tokenizer(), True)):
        lone = tok(**dict(stretched, ti=ti[:0], tj=tj[:0]))  # no topology pairs at all
        h = tok(**stretched)
        assert torch.allclose(h[..., g_t], lone[..., g_t]) != keeps


def test_rest_features_padded_path_equals_the_pair_list():
    """The static-shape (padded, compiled) path gives the same tokens as the searched pair list."""
    tok = _rest_tokenizer()
    s = _scene(b=2)
    caps = {name: NeighborCapacity(64, 64) for name in ("spatial", "environment", "controllable")}
    fixed = FixedNeighbors.for_topology(caps, s["ti"], s["tj"], s["x"].shape[1])
    h = tok(**s)
    assert torch.allclose(tok(**s, neighbors=fixed), h, atol=1e-5)
    assert int(fixed.overflow.sum()) == 0
    assert sum(p.numel() for p in tok.parameters()) == 57_993 + 2 * 3 * 4**3 * 32  # 3 pair channels, 2 kernels
