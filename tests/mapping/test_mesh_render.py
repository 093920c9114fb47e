"""Mesh renderer (analytic triangle and quad: z-depth, barycentric colour, mask) and mesh export."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.types import FrameError, Intrinsics
from gsfix_online.mapping.mesh import MeshFormatError, TriMesh, read_mesh, write_mesh
from gsfix_online.mapping.mesh_render import MeshRenderer

K = Intrinsics(50.0, 50.0, 39.5, 29.5, 80, 60)


def quad(z: float, half: float = 5.0, gray: bool = False) -> TriMesh:
    v = np.array(
        [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float32
    )
    c = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]], np.uint8)
    if gray:
        c = np.repeat(c.mean(1, keepdims=True).astype(np.uint8), 3, 1)
    return TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), c, gray)


def test_quad_renders_z_depth_not_ray_distance():
    r = MeshRenderer(quad(2.0)).render(np.eye(4), K)
    assert r.valid.all()
    np.testing.assert_allclose(r.depth_m, 2.0, atol=1e-5)  # corners are 2.0, not 2 / cos(angle)
    T = np.eye(4)
    T[:3, 3] = (0.3, -0.2, 0.5)
    np.testing.assert_allclose(MeshRenderer(quad(2.0)).render(T, K).depth_m, 1.5, atol=1e-5)


def test_single_triangle_colour_is_barycentric_and_mask_is_exact():
    v = np.array([[-1, -1, 2], [1, -1, 2], [0, 1, 2]], np.float32)
    c = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    mesh = TriMesh(v, np.array([[0, 1, 2]], np.int32), c)
    r = MeshRenderer(mesh).render(np.eye(4), K)
    # Pixel through the centroid (0, -1/3, 2): u = cx, v = cy + fy * (-1/3) / 2.
    u, vv = 39.5, 29.5 - 50.0 / 6.0
    assert abs(vv - round(vv)) > 0.1  # not exactly on a pixel: check nearby pixel analytically
    p = np.array([0.0, (round(vv) - 29.5) / 50.0 * 2.0])  # world x, y of that pixel's hit
    # barycentric weights of p in triangle (a, b, c) in the plane
    a, b, cc = v[:, :2]
    m = np.column_stack([b - a, cc - a])
    l1, l2 = np.linalg.solve(m, p - a)
    expect = (1 - l1 - l2) * c[0] + l1 * c[1] + l2 * c[2]
    assert r.valid[round(vv), int(u + 0.5)]
    got = r.color[round(vv), 40].astype(float)
    p40 = np.array([(40 - 39.5) / 50.0 * 2.0, p[1]])
    l1, l2 = np.linalg.solve(m, p40 - a)
    expect = (1 - l1 - l2) * c[0] + l1 * c[1] + l2 * c[2]
    assert np.abs(got - expect).max() <= 1.0
    # Outside the triangle: invalid, zero depth and colour.
    assert not r.valid[0, 0] and r.depth_m[0, 0] == 0 and r.color[0, 0].sum() == 0
    # The mask covers the triangle's projected area (area 2 m^2 at z = 2 -> 2 * (50 / 2)^2 px).
    assert abs(r.valid.sum() - 2 * 25.0**2) < 0.05 * 2 * 25.0**2


def test_gray_mesh_renders_gray_and_empty_mesh_renders_nothing():
    r = MeshRenderer(quad(1.0, gray=True)).render(np.eye(4), K)
    assert r.color.shape == (60, 80) and r.rgb().shape == (60, 80, 3)
    e = MeshRenderer(TriMesh.empty()).render(np.eye(4), K)
    assert not e.valid.any() and e.color.shape == (60, 80, 3) and e.depth_m.max() == 0
    with pytest.raises(FrameError, match="T_world_cam"):
        MeshRenderer(quad(1.0)).render(np.full((4, 4), np.nan), K)


@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_mesh_write_read_round_trip(tmp_path, suffix):
    if suffix == ".glb":
        pytest.importorskip("trimesh")
    mesh = quad(1.5)
    path = write_mesh(mesh, tmp_path / f"mesh{suffix}")
    back = read_mesh(path)
    assert back.n_triangles == 2
    order = np.lexsort(back.vertices.T)
    np.testing.assert_allclose(
        back.vertices[order], mesh.vertices[np.lexsort(mesh.vertices.T)], atol=1e-6
    )
    np.testing.assert_array_equal(back.colors[order], mesh.colors[np.lexsort(mesh.vertices.T)])
    assert [p.name for p in tmp_path.iterdir()] == [f"mesh{suffix}"]  # no temporary left
    with pytest.raises(ValueError, match="must end in .ply or .glb"):
        write_mesh(mesh, tmp_path / "mesh.obj")


def test_empty_mesh_writes_valid_files(tmp_path):
    e = write_mesh(TriMesh.empty(), tmp_path / "e.ply")
    assert read_mesh(e, allow_empty=True).n_vertices == 0
    with pytest.raises(MeshFormatError, match=f"^{e}: the mesh has no triangles"):
        read_mesh(e)  # where a mesh is required (a run's), an empty one is refused
    pytest.importorskip("trimesh")
    assert (
        read_mesh(write_mesh(TriMesh.empty(), tmp_path / "e.glb"), allow_empty=True).n_vertices == 0
    )


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflow to inf is a defect, not a view
def test_pose_or_focal_length_beyond_the_float32_ray_caster_is_one_clear_error():
    r = MeshRenderer(quad(2.0))
    far = np.eye(4)
    far[:3, 3] = (0.0, 0.0, 1e39)  # finite in float64, inf in float32
    with pytest.raises(FrameError, match="translation 1e\\+39 m is beyond the float32"):
        r.render(far, K)
    with pytest.raises(FrameError, match="fx=1e-38 fy=50.0 give ray slopes of 3.95e\\+39"):
        r.render(np.eye(4), Intrinsics(1e-38, 50.0, 39.5, 29.5, 80, 60))
    # Far but representable poses still render (nothing is hit out there).
    far[:3, 3] = (0.0, 0.0, 1e6)
    assert not r.render(far, K).valid.any()
