"""Padded pair lists (the CUDA path's static capacities, wc.expand.cloth_elements.compact): their unused entries
scatter into distinct rows (spread_unused) and change nothing, in the bounded step's passes and in the self-contact
pass, bit for bit against the same pairs without padding."""

import numpy as np
import torch

from tests.conftest import load_params
from wc.config import load_section
from wc.expand.cloth_elements import ClothElements, compact, spread_unused
from wc.expand.fixed_untangle import BoundedStep
from wc.expand.self_contact import separate_pairs
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene


def test_unused_entries_go_to_distinct_rows_and_used_ones_stay():
    index = torch.tensor([5, 0, 0, 0, 0, 7])
    valid = torch.tensor([True, False, False, False, False, True])
    np.testing.assert_array_equal(spread_unused(index, valid, 4).numpy(), [5, 1, 2, 3, 0, 7])
    idx, used, lost = compact(torch.tensor([False, True, False, True]), capacity=6)
    assert used.tolist() == [True, True, False, False, False, False] and int(lost) == 0
    assert idx[2:].tolist() == [0, 0, 0, 0]  # what spread_unused is for: the padding all points at entry 0


def _bag_batch(episodes: int = 2) -> tuple[ClothElements, torch.Tensor, torch.Tensor]:
    scene = build_scene(load_section(load_params(), "scene", SceneConfig), ("bag",))
    el = ClothElements.of_scene(scene)
    rest = torch.as_tensor(scene.objects["bag"].vertices, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    x_prev = rest.expand(episodes, -1, -1).clone()
    x = x_prev + 0.004 * torch.randn(x_prev.shape, generator=gen, dtype=torch.float64)
    return el, x_prev, x


def _padded(*columns: torch.Tensor, extra: int) -> tuple[list[torch.Tensor], torch.Tensor]:
    """The columns with `extra` unused entries appended, each a copy of entry 0 (as compact's padding reads), and the
    valid mask."""
    valid = torch.cat([torch.ones(len(columns[0]), dtype=torch.bool), torch.zeros(extra, dtype=torch.bool)])
    return [torch.cat([c, c[:1].expand(extra, *c.shape[1:])]) for c in columns], valid


def test_the_bounded_steps_passes_ignore_padding():
    el, x_prev, x = _bag_batch()
    step = BoundedStep(el, share=0.45, rounds=1, passes=5, vertex_pairs=8, edge_pairs=8, pair_capacity=64)
    gen = torch.Generator().manual_seed(1)
    m = 400
    episode = torch.randint(0, 2, (m,), generator=gen)
    i, j = (torch.randint(0, len(el.vertices), (m,), generator=gen) for _ in range(2))
    bound = 0.002 * torch.rand(m, generator=gen, dtype=torch.float64)
    motion = (x - x_prev).contiguous()
    plain, limited = step._project(motion.clone(), episode, i, j, bound, torch.ones(m, dtype=torch.bool))
    (episode_p, i_p, j_p, bound_p), valid = _padded(episode, i, j, bound, extra=3000)
    padded, limited_p = step._project(motion.clone(), episode_p, i_p, j_p, bound_p, valid)
    assert int(limited) > 0 and int(limited_p) == int(limited)
    torch.testing.assert_close(padded, plain, rtol=0.0, atol=0.0)


def test_the_self_contact_pass_ignores_padding():
    el, x_prev, x = _bag_batch()
    faces = el.faces
    gen = torch.Generator().manual_seed(2)
    m = 60  # distinct vertices, each put 5 mm over a triangle it is not part of (10 mm the frame before)
    b = torch.randint(0, 2, (m,), generator=gen)
    row = el.vertices[torch.randperm(len(el.vertices), generator=gen)[:m]]
    tri = torch.stack([next(f for f in faces[torch.randperm(len(faces), generator=gen)] if r not in f) for r in row])
    for k in range(m):
        for state, height in ((x_prev, 0.01), (x, 0.005)):
            p = state[b[k], tri[k]]
            normal = torch.linalg.cross(p[1] - p[0], p[2] - p[0])
            state[b[k], row[k]] = p.mean(0) + height * normal / normal.norm()
    inv_mass = torch.ones(x.shape[:2], dtype=x.dtype)
    plain = x.clone()
    short = separate_pairs(x_prev, plain, b, row, tri, torch.ones(m, dtype=torch.bool), inv_mass, gap_m=0.008)
    (b_p, row_p, tri_p), valid = _padded(b, row, tri, extra=2000)
    padded = x.clone()
    short_p = separate_pairs(x_prev, padded, b_p, row_p, tri_p, valid, inv_mass, gap_m=0.008)
    assert float(short.max()) > 0.0 and not torch.equal(plain, x)  # the pass moved something
    torch.testing.assert_close(padded, plain, rtol=0.0, atol=0.0)
    torch.testing.assert_close(short_p, short, rtol=0.0, atol=0.0)
