"""The grouped cloth BVH (wc/validate/cloth_bvh.py): its crossing test and proximity lists against brute force over
every element pair, on perturbed states of the default bag, one BVH for several states."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from wc.config import load_section
from wc.expand.cloth_elements import ClothElements
from wc.expand.crossing_free import point_triangle_distance, segment_segment_distance
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.validate.cloth_bvh import ClothBVH, crossing_faces
from wc.validate.self_intersection import first_crossing_frame, unique_edges


@pytest.fixture(scope="module")
def bag():
    scene = build_scene(load_section(load_params(), "scene", SceneConfig))
    mesh = scene.objects["bag"]
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces), unique_edges(mesh.faces)


def states(rest: np.ndarray, count: int, noise_m: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rest + rng.normal(0.0, noise_m * (b % 4), rest.shape) for b in range(count)]).astype(np.float32)


def brute_force_crossings(x: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E,) bool: the edge crosses a triangle sharing no vertex with it (Moeller-Trumbore, strict)."""
    p, q = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]  # (E, 1, 3)
    a, b, c = (x[faces[:, k]][None] for k in range(3))  # (1, F, 3)
    e1, e2, d = b - a, c - a, q - p
    h = np.cross(d, e2)
    det = (e1 * h).sum(-1)
    inv = 1.0 / np.where(det == 0, 1.0, det)
    s = p - a
    u = inv * (s * h).sum(-1)
    r = np.cross(s, e1)
    w, t = inv * (d * r).sum(-1), inv * (e2 * r).sum(-1)
    hit = (det != 0) & (u > 0) & (w > 0) & (u + w < 1) & (t > 0) & (t < 1)
    adjacent = (faces[None, :, :, None] == edges[:, None, None, :]).any(axis=(2, 3))
    return (hit & ~adjacent).any(axis=1)


def test_crossings_of_many_states_match_brute_force(bag):
    rest, faces, edges = bag
    x = states(rest, 12, 0.003)
    hits = crossing_faces(x, faces, edges)
    for b in range(len(x)):
        assert np.array_equal(hits[b] >= 0, brute_force_crossings(x[b], faces, edges)), b
    assert (hits[0] == -1).all()  # the rest bag: its touching handle roots are not crossings
    assert (hits >= 0).any(axis=1).sum() >= 6  # the noisy states do cross


def test_a_crossing_in_one_state_is_found_in_that_state_only(bag):
    rest, faces, edges = bag
    x = np.stack([rest, rest, rest]).copy()
    body = np.argsort(np.abs(rest[:, 0]) + np.abs(rest[:, 2] - 0.06) + 10 * (rest[:, 1] - rest[:, 1].min()))[0]
    x[1, body, 1] = rest[:, 1].max() + 0.02  # a front-panel vertex pushed through the back panel
    crossing = (crossing_faces(x, faces, edges) >= 0).any(axis=1)
    assert crossing.tolist() == [False, True, False]
    assert first_crossing_frame(x, faces, edges) == 1
    x[1] = np.nan  # a diverged state takes part in nothing
    assert not (crossing_faces(x, faces, edges) >= 0).any()


def test_proximity_lists_hold_exactly_the_pairs_within_reach(bag):
    rest, faces, edges = bag
    scene = build_scene(load_section(load_params(), "scene", SceneConfig))
    el = ClothElements.of_scene(scene)
    x = torch.as_tensor(states(rest, 3, 0.002, seed=1))
    bvh = ClothBVH(x, el.faces, el.face_mesh, el.edges, el.edge_mesh, el.vertices, el.vertex_mesh, el.meshes)
    reach = torch.full((3, len(el.vertices)), 0.004)
    face_reach = torch.full((3, len(el.faces)), 0.001)
    skip = (torch.arange(len(el.vertices) + 1, dtype=torch.int32), el.vertices.to(torch.int32))  # incident faces
    vt = torch.empty(3, len(el.vertices), 64, dtype=torch.int32)
    dropped = torch.zeros(3, dtype=torch.int32)
    bvh.vertex_face_pairs(x, reach, face_reach, skip, vt, dropped)
    ee = torch.empty(3, len(el.edges), 64, dtype=torch.int32)
    edge_reach = torch.full((3, len(el.edges)), 0.0025)
    bvh.edge_edge_pairs(x, edge_reach, ee, dropped)
    assert not dropped.any()
    f, e = el.faces, el.edges
    for b in range(3):
        d = point_triangle_distance(x[b][el.vertices].repeat_interleave(len(f), 0),
                                    x[b][f].repeat(len(el.vertices), 1, 1)).view(len(el.vertices), len(f))
        incident = (f[None] == el.vertices[:, None, None]).any(-1)
        want = (d < 0.005) & ~incident
        got = torch.zeros_like(want)
        rows, slots = torch.nonzero(vt[b] >= 0, as_tuple=True)
        got[rows, vt[b][rows, slots].long()] = True
        assert torch.equal(got, want), b
        i, k = torch.triu_indices(len(e), len(e), 1)
        shared = (e[i][:, :, None] == e[k][:, None, :]).any(dim=(1, 2))
        dist = segment_segment_distance(x[b][e[i, 0]], x[b][e[i, 1]], x[b][e[k, 0]], x[b][e[k, 1]])
        want_ee = {(int(a), int(c)) for a, c in zip(i[(dist < 0.005) & ~shared], k[(dist < 0.005) & ~shared])}
        rows, slots = torch.nonzero(ee[b] >= 0, as_tuple=True)
        assert {(int(r), int(ee[b][r, s])) for r, s in zip(rows, slots)} == want_ee, b


def test_a_list_that_overflows_flags_its_state(bag):
    rest, faces, edges = bag
    scene = build_scene(load_section(load_params(), "scene", SceneConfig))
    el = ClothElements.of_scene(scene)
    x = torch.as_tensor(np.stack([rest, rest]))
    bvh = ClothBVH(x, el.faces, el.face_mesh, el.edges, el.edge_mesh, el.vertices, el.vertex_mesh, el.meshes)
    reach = torch.tensor([[0.0] * len(el.vertices), [0.05] * len(el.vertices)])  # state 1 reaches many triangles
    skip = (torch.arange(len(el.vertices) + 1, dtype=torch.int32), el.vertices.to(torch.int32))
    vt = torch.empty(2, len(el.vertices), 2, dtype=torch.int32)
    dropped = torch.zeros(2, dtype=torch.int32)
    bvh.vertex_face_pairs(x, reach, torch.zeros(2, len(el.faces)), skip, vt, dropped)
    assert dropped.tolist() == [0, 1]
    assert (vt[1] >= 0).all()  # full lists where they overflowed
