"""The guessed surface: a box's partly observed walls, extended, give the true depth of what the
mesh never saw (the analytic ray-plane depth is the oracle); a camera outside a plane ignores it;
a mesh without large planes guesses nothing."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import TriMesh
from gsfix_online.mapping.mesh_planes import PlaneGuessConfig, fit_planes, guessed_depth
from gsfix_online.mapping.mesh_render import MeshRenderer

K = Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)
BOX = np.array([4.0, 3.0, 2.5])  # x, y, z extent, m; the space is [0, BOX]


def quad_grid(origin, u, v, n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A flat patch origin + s u + t v, s and t in [0, 1], as an n x n grid of triangle pairs."""
    s, t = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    verts = np.asarray(origin) + s[..., None] * np.asarray(u) + t[..., None] * np.asarray(v)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
    tris = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)]).reshape(-1, 3)
    return verts.reshape(-1, 3), tris


def lower_half_box() -> TriMesh:
    """The floor and the lower half of the four walls: what a robot on the floor maps."""
    x, y, z = BOX
    h = z / 2
    patches = [
        quad_grid([0, 0, 0], [x, 0, 0], [0, y, 0]),  # floor, z = 0
        quad_grid([0, 0, 0], [0, y, 0], [0, 0, h]),  # wall x = 0
        quad_grid([x, 0, 0], [0, y, 0], [0, 0, h]),  # wall x = 4
        quad_grid([0, 0, 0], [x, 0, 0], [0, 0, h]),  # wall y = 0
        quad_grid([0, y, 0], [x, 0, 0], [0, 0, h]),  # wall y = 3
    ]
    verts, tris, base = [], [], 0
    for v, t in patches:
        verts.append(v)
        tris.append(t + base)
        base += len(v)
    v = np.concatenate(verts).astype(np.float32)
    return TriMesh(v, np.concatenate(tris).astype(np.int32), np.full((len(v), 3), 128, np.uint8))


def looking_along_x(at: tuple[float, float, float], up_tilt_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world of a camera at ``at`` looking along +x (OpenCV axes: z forward, y down),
    tilted up by ``up_tilt_deg``."""
    a = np.deg2rad(up_tilt_deg)
    fwd = np.array([np.cos(a), 0.0, np.sin(a)])
    down = np.array([np.sin(a), 0.0, -np.cos(a)])
    right = np.cross(down, fwd)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = at
    return T


def true_box_exit(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Oracle: per pixel, the z-depth at which the ray leaves the box [0, BOX], and whether it
    leaves through the ceiling (z = BOX[2])."""
    u = (np.arange(K.width) - K.cx) / K.fx
    v = (np.arange(K.height) - K.cy) / K.fy
    d_cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), -1)
    d = d_cam @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide="ignore"):
        t_hi = np.where(d > 0, (BOX - o) / d, np.where(d < 0, -o / d, np.inf))
    return t_hi.min(axis=-1), (t_hi.argmin(axis=-1) == 2) & (d[..., 2] > 0)


def true_box_depth(T: np.ndarray) -> np.ndarray:
    return true_box_exit(T)[0]


def test_the_walls_extended_give_the_true_depth_where_the_mesh_saw_nothing():
    mesh = lower_half_box()
    planes = fit_planes(mesh, PlaneGuessConfig(distance_m=0.02, voxel_m=0.05))
    # the floor and four walls, each oriented towards the inside of the box
    assert len(planes) == 5
    centre = BOX / 2
    assert (planes.normals @ centre + planes.offsets > 0).all()
    T = looking_along_x((1.0, 1.5, 1.0), up_tilt_deg=10.0)  # upwards, over the mapped half
    r = MeshRenderer(mesh).render(T, K)
    unseen = ~r.valid
    assert 0.2 < unseen.mean() < 0.8, "the view must hold seen and unseen parts"
    guess = guessed_depth(planes, T, K)
    truth = true_box_depth(T)
    # where the true surface is one of the fitted planes (a wall, not the unmapped ceiling)
    # the guess is exact; where the mesh has a surface, the guess agrees with it
    walls = unseen & (np.abs(truth - guess) < 1e-3)
    assert walls.sum() > 0.5 * unseen.sum()
    np.testing.assert_allclose(guess[r.valid], r.depth_m[r.valid], rtol=0, atol=0.03)
    # given the mesh render's surface, the guess is only for what the mesh never saw
    off_mesh = guessed_depth(planes, T, K, r.valid)
    assert (off_mesh[r.valid] == 0).all()
    np.testing.assert_array_equal(off_mesh[unseen], guess[unseen])
    # the ceiling was never mapped: rays through it leave by no fitted plane before the far
    # wall, so the guess there is a wall behind it (farther than the truth), never nearer
    assert (guess[unseen] >= truth[unseen] - 1e-3).all()


def test_a_camera_outside_a_planes_inner_side_ignores_it():
    mesh = lower_half_box()
    planes = fit_planes(mesh, PlaneGuessConfig(distance_m=0.02, voxel_m=0.05))
    inside = looking_along_x((1.0, 1.5, 0.6))
    outside = looking_along_x((-1.0, 1.5, 0.6))  # behind the wall x = 0, looking in
    g_in, g_out = guessed_depth(planes, inside, K), guessed_depth(planes, outside, K)
    centre = (K.height // 2, K.width // 2)
    assert g_in[centre] == pytest.approx(3.0, abs=0.03)  # the wall x = 4, 3 m ahead
    # from outside, the wall x = 0 it stands behind does not count: the ray is bounded by
    # the far wall, 5 m ahead
    assert g_out[centre] == pytest.approx(5.0, abs=0.03)


def test_a_mesh_without_large_planes_guesses_nothing():
    rng = np.random.default_rng(0)
    blob = rng.normal(size=(3000, 3)).astype(np.float32)  # a cloud with no plane of 4 %
    mesh = TriMesh(blob, np.zeros((0, 3), np.int32), np.zeros((3000, 3), np.uint8))
    planes = fit_planes(mesh, PlaneGuessConfig(min_support=0.2, voxel_m=0.0))
    assert len(planes) == 0
    assert (guessed_depth(planes, looking_along_x((0, 0, 0)), K) == 0).all()
    assert len(fit_planes(lower_half_box(), PlaneGuessConfig(enabled=False))) == 0


def test_the_fit_is_the_same_every_time_and_for_any_vertex_order():
    mesh = lower_half_box()
    cfg = PlaneGuessConfig(distance_m=0.02, voxel_m=0.05)
    order = np.random.default_rng(1).permutation(mesh.n_vertices)
    back = np.argsort(order)  # new index of each old vertex
    shuffled = TriMesh(
        mesh.vertices[order], back[mesh.triangles].astype(np.int32), mesh.colors[order]
    )
    a, b, c = fit_planes(mesh, cfg), fit_planes(mesh, cfg), fit_planes(shuffled, cfg)
    for other in (b, c):  # the same planes, far below the points' micrometre rounding
        np.testing.assert_allclose(other.normals, a.normals, rtol=0, atol=1e-9)
        np.testing.assert_allclose(other.offsets, a.offsets, rtol=0, atol=1e-9)


def test_the_planes_come_in_one_order_whichever_is_found_first():
    # RANSAC seeds 0-7 find the box's walls in 6 different orders (the opposite walls hold the
    # same number of points, so a CPU's rounding alone can swap them); the planes come out the same
    mesh = lower_half_box()
    fits = [fit_planes(mesh, PlaneGuessConfig(distance_m=0.02, seed=s)) for s in range(8)]
    for other in fits[1:]:
        np.testing.assert_allclose(other.normals, fits[0].normals, rtol=0, atol=1e-9)
        np.testing.assert_allclose(other.offsets, fits[0].offsets, rtol=0, atol=1e-9)
    assert (np.diff(fits[0].normals[:, 0]) >= 0).all()  # ordered by normal, then offset
