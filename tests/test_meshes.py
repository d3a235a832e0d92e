"""Object meshes (bag, sphere, cube) and the table's environment samples; fast, no Newton."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from wc.scene.bag import make_bag
from wc.scene.mesh import ObjectMesh, check_mesh, lumped_vertex_areas
from wc.scene.rigid import make_cube, make_sphere
from wc.scene.table import TableSpec, table_env_samples

DIMS = dict(width_m=0.24, depth_m=0.12, height_m=0.18, handle_width_m=0.04, handle_rise_m=0.10)
H, RISE, D2 = DIMS["height_m"], DIMS["handle_rise_m"], DIMS["depth_m"] / 2


@pytest.fixture(scope="module", params=[400, 20274])
def bag(request: pytest.FixtureRequest) -> ObjectMesh:
    return make_bag(request.param, tag=1, **DIMS)


def _boundary_edges(faces: np.ndarray) -> np.ndarray:
    edges = np.sort(trimesh.Trimesh(faces=faces, process=False).edges, axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    return unique[count == 1]


def _face_normals(mesh: ObjectMesh) -> tuple[np.ndarray, np.ndarray]:
    tri = mesh.vertices.astype(np.float64)[mesh.faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(axis=1)


@pytest.mark.parametrize("target", [150, 300, 400, 600, 1000, 5000, 20274, 25000])
def test_bag_vertex_count_near_target(target: int) -> None:
    mesh = make_bag(target, tag=1, **DIMS)
    assert abs(mesh.num_vertices - target) <= 0.15 * target
    check_mesh(mesh)


def test_bag_valid_mesh(bag: ObjectMesh) -> None:
    check_mesh(bag)  # winding, degenerate/duplicate faces, one component, every vertex referenced
    tm = bag.to_trimesh()
    assert tm.is_winding_consistent and not tm.is_watertight
    assert bag.vertices[:, 2].min() == 0.0
    np.testing.assert_allclose(bag.vertices[:, 2].max(), H + RISE, rtol=1e-5)
    np.testing.assert_allclose(bag.vertices[:, :2].mean(axis=0), 0.0, atol=1e-6)


def test_bag_normals_point_outward(bag: ObjectMesh) -> None:
    normal, centre = _face_normals(bag)
    on = lambda name: np.isin(bag.faces, bag.groups[name]).all(axis=1)  # noqa: E731
    bottom = centre[:, 2] < 1e-9
    assert (normal[bottom, 2] < 0).all()
    tube = on("body") & ~bottom
    assert (np.einsum("ij,ij->i", normal[tube, :2], centre[tube, :2]) > 0).all()
    for h in (0, 1):  # arch normals point away from the arch's centre (0, height)
        strap = on(f"handle_{h}") & ~tube
        away = centre[strap] - np.array([0.0, 0.0, H])
        assert strap.any() and (np.einsum("ij,ij->i", normal[strap, 1:], away[:, 1:]) > 0).all()


def test_bag_open_top_closed_bottom(bag: ObjectMesh) -> None:
    boundary = _boundary_edges(bag.faces)
    z = bag.vertices[boundary, 2]
    assert (z >= H - 1e-6).all()  # no hole at the bottom or in the walls
    loops = trimesh.graph.connected_components(boundary, min_len=1)
    assert len(loops) == 3  # the mouth, and the opening over each side gusset under a handle
    mouth = np.unique(boundary[(np.abs(bag.vertices[boundary, 0]) < DIMS["width_m"] / 2 - DIMS["handle_width_m"])
                               .all(axis=1)])
    assert np.isin(mouth, bag.groups["rim"]).all()  # between the straps the rim is open, front and back
    assert (bag.vertices[mouth, 1] < 0).any() and (bag.vertices[mouth, 1] > 0).any()


def test_bag_handles_join_rim(bag: ObjectMesh) -> None:
    rim, body = set(bag.groups["rim"].tolist()), set(bag.groups["body"].tolist())
    for h, sign in ((0, 1.0), (1, -1.0)):
        strap = bag.groups[f"handle_{h}"]
        shared = np.array(sorted(set(strap.tolist()) & body))
        assert len(shared) >= 6 and set(shared.tolist()) <= rim
        y = bag.vertices[shared, 1]
        assert np.isclose(y, -D2).sum() == np.isclose(y, D2).sum() == len(shared) // 2
        x = bag.vertices[strap, 0] * sign
        assert x.min() >= DIMS["width_m"] / 2 - DIMS["handle_width_m"] - 1e-6
        # the strap shares faces' edges with the tube, not just vertices (check_mesh: one piece)
        assert np.isin(bag.faces, strap).all(axis=1).sum() > 0


def test_bag_groups_and_attributes(bag: ObjectMesh) -> None:
    n = bag.num_vertices
    part, s, u = bag.attributes["part"], bag.attributes["handle_s"], bag.attributes["handle_u"]
    handles = np.concatenate([bag.groups["handle_0"], bag.groups["handle_1"]])
    assert len(np.unique(handles)) == len(handles)  # the two straps are disjoint
    on_handle = np.zeros(n, bool)
    on_handle[handles] = True
    assert (part[bag.groups["handle_0"]] == 1).all() and (part[bag.groups["handle_1"]] == 2).all()
    assert (part[~on_handle] == 0).all()
    assert ((s[on_handle] >= 0) & (s[on_handle] <= 1)).all() and (s[~on_handle] == -1).all()
    assert ((u[on_handle] >= 0) & (u[on_handle] <= 1)).all() and (u[~on_handle] == -1).all()
    y = bag.vertices[:, 1]
    rim_handle = np.intersect1d(handles, bag.groups["rim"])
    np.testing.assert_array_equal(s[rim_handle], np.where(y[rim_handle] < 0, 0.0, 1.0))
    top = on_handle & np.isclose(s, 0.5)  # a row of vertices at the top of each arch
    assert top.sum() == 2 * len(np.unique(u[bag.groups["handle_0"]]))
    np.testing.assert_allclose(bag.vertices[top, 2], H + RISE, rtol=1e-5)
    np.testing.assert_allclose(bag.vertices[top, 1], 0.0, atol=1e-6)
    outer = on_handle & np.isclose(u, 1.0)
    np.testing.assert_allclose(np.abs(bag.vertices[outer, 0]), DIMS["width_m"] / 2, rtol=1e-6)
    assert np.allclose(bag.vertices[bag.groups["rim"], 2], H)
    assert np.allclose(bag.vertices[bag.groups["bottom"], 2], 0.0)
    assert len(np.union1d(np.union1d(bag.groups["body"], bag.groups["bottom"]), handles)) == n


def test_bag_vertex_areas_sum_to_surface_area(bag: ObjectMesh) -> None:
    assert (bag.vertex_area > 0).all()
    np.testing.assert_allclose(bag.vertex_area.sum(), bag.to_trimesh().area, rtol=1e-5)
    np.testing.assert_allclose(lumped_vertex_areas(bag.vertices, bag.faces).sum(), bag.to_trimesh().area, rtol=1e-6)


def test_bag_uv_locally_isometric(bag: ObjectMesh) -> None:
    assert np.isfinite(bag.rest_uv).all()
    edges = np.unique(np.sort(bag.to_trimesh().edges, axis=1), axis=0)
    inside = ~np.isin(edges, bag.groups["uv_seam"]).any(axis=1)
    ratio = (np.linalg.norm(np.diff(bag.rest_uv[edges[inside]], axis=1)[:, 0], axis=1)
             / np.linalg.norm(np.diff(bag.vertices[edges[inside]], axis=1)[:, 0], axis=1))
    assert inside.mean() > 0.8
    assert abs(ratio.mean() - 1.0) < 0.02 and ratio.min() > 0.95 and ratio.max() < 1.1
    # the seams are where uv jumps: the tube's seam column is far from its neighbours in uv
    all_ratio = (np.linalg.norm(np.diff(bag.rest_uv[edges], axis=1)[:, 0], axis=1)
                 / np.linalg.norm(np.diff(bag.vertices[edges], axis=1)[:, 0], axis=1))
    assert all_ratio.max() > 5


@pytest.mark.parametrize("change", [
    dict(target_vertices=20), dict(target_vertices=400.5), dict(width_m=0.0), dict(depth_m=-0.1),
    dict(height_m=float("nan")), dict(handle_rise_m=0.0), dict(handle_width_m=0.12), dict(handle_width_m=0.2),
])
def test_bag_rejects_bad_arguments(change: dict) -> None:
    args = dict(target_vertices=400, tag=1, **DIMS) | change
    with pytest.raises(ValueError):
        make_bag(**args)


def test_check_mesh_rejects_broken_meshes() -> None:
    good = make_cube(0.02, 30, tag=3)
    check_mesh(good, closed=True)
    flipped = good.faces.copy()
    flipped[0] = flipped[0, ::-1]
    duplicated = np.concatenate([good.faces, good.faces[:1, [1, 2, 0]]])
    for faces in (flipped, duplicated, good.faces[1:]):  # winding, duplicate face, a hole
        broken = ObjectMesh("broken", good.vertices, faces, good.rest_uv, good.vertex_area, 3)
        with pytest.raises(ValueError):
            check_mesh(broken, closed=True)
    extra = ObjectMesh("extra", np.concatenate([good.vertices, good.vertices[:1]]), good.faces,
                       np.concatenate([good.rest_uv, good.rest_uv[:1]]),
                       np.concatenate([good.vertex_area, good.vertex_area[:1]]), 3)
    with pytest.raises(ValueError, match="unreferenced"):
        check_mesh(extra)


def _check_closed_outward(mesh: ObjectMesh) -> None:
    tm = mesh.to_trimesh()
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    normal, centre = _face_normals(mesh)
    assert (np.einsum("ij,ij->i", normal, centre) > 0).all()
    np.testing.assert_allclose(mesh.vertex_area.sum(), tm.area, rtol=1e-5)
    assert np.isfinite(mesh.rest_uv).all()


@pytest.mark.parametrize("target", [100, 951, 3000])
def test_sphere(target: int) -> None:
    mesh = make_sphere(0.03, target, tag=2)
    assert mesh.num_vertices == target and mesh.tag == 2
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices, axis=1), 0.03, rtol=1e-6)
    _check_closed_outward(mesh)
    assert 0.9 < mesh.to_trimesh().volume / (4 / 3 * np.pi * 0.03**3) < 1.0  # inscribed polyhedron


@pytest.mark.parametrize("target", [100, 465, 3000])
def test_cube(target: int) -> None:
    mesh = make_cube(0.025, target, tag=3)
    assert abs(mesh.num_vertices - target) <= 0.15 * target
    np.testing.assert_allclose(np.abs(mesh.vertices).max(axis=1), 0.025, rtol=1e-6)
    _check_closed_outward(mesh)
    np.testing.assert_allclose(mesh.to_trimesh().volume, 0.05**3, rtol=1e-5)


@pytest.mark.parametrize("make, arg", [(make_sphere, "radius_m"), (make_cube, "half_extent_m")])
def test_rigid_rejects_bad_arguments(make, arg: str) -> None:
    with pytest.raises(ValueError):
        make(**{arg: 0.0, "target_vertices": 500, "tag": 0})
    with pytest.raises(ValueError):
        make(**{arg: 0.03, "target_vertices": 3, "tag": 0})


def test_table_samples_on_top_within_region() -> None:
    spec = TableSpec(center=[0.3, 0.0, 0.35], half_extents=[0.4, 0.6, 0.35])
    assert spec.top_z == pytest.approx(0.7)
    centre, half = np.array([0.5, 0.1]), np.array([0.3, 0.2])
    points, normals = table_env_samples(spec, centre, half, 0.01)
    assert points.shape == normals.shape and points.dtype == np.float32
    np.testing.assert_allclose(points[:, 2], spec.half_extents[2])  # local frame: top at +half_z
    world_xy = points[:, :2] + spec.center[:2]
    lo = np.maximum(centre - half, spec.center[:2] - spec.half_extents[:2])  # clipped to the table in x
    hi = np.minimum(centre + half, spec.center[:2] + spec.half_extents[:2])
    assert (world_xy >= lo - 1e-6).all() and (world_xy <= hi + 1e-6).all()
    np.testing.assert_array_equal(normals, np.tile([0, 0, 1], (len(points), 1)))
    finer, _ = table_env_samples(spec, centre, half, 0.005)
    assert 3.5 < len(finer) / len(points) < 4.5


def test_table_rejects_empty_region() -> None:
    spec = TableSpec(center=[0.0, 0.0, 0.35], half_extents=[0.4, 0.6, 0.35])
    with pytest.raises(ValueError):
        table_env_samples(spec, [2.0, 0.0], [0.1, 0.1], 0.01)
    with pytest.raises(ValueError):
        table_env_samples(spec, [0.0, 0.0], [0.1, 0.1], 0.0)
