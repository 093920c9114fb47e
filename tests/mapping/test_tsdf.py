"""TSDF component: analytic plane, colour round trip, bad depth, capacity growth, weight cap,
remesh policy, and the same integration done by a bare Open3D loop (slow reference)."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.config import ConfigError, build
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.tsdf import (
    DepthCounts,
    RemeshState,
    TsdfCapacityError,
    TsdfConfig,
    TsdfVolume,
    inverse_pose,
    sanitize_depth_range,
    should_remesh,
)

VOXEL = 0.02
K_SMALL = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)  # 77 x 62 deg field of view


def pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """Camera at (x, y, 0) looking along +z, turned by yaw about the camera y axis."""
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [x, y, 0.0]
    return T


def plane_depth(T: np.ndarray, z_plane: float, K: Intrinsics = K_SMALL) -> np.ndarray:
    """Analytic z-depth of the world plane z = z_plane seen from camera T (pixel centres)."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
    dz_world = d_cam @ T[2, :3]
    return ((z_plane - T[2, 3]) / dz_world).astype(np.float32)


def plane_frame(T: np.ndarray, z_plane: float = 1.0, color=None, seq: int = 0) -> RGBDFrame:
    color = np.full((K_SMALL.height, K_SMALL.width, 3), 128, np.uint8) if color is None else color
    return make_frame(color, plane_depth(T, z_plane), K_SMALL, T, 1_000 + seq, seq=seq)


def volume(**kw) -> TsdfVolume:
    return TsdfVolume(TsdfConfig(voxel_size=VOXEL, block_count=64, device="CPU:0", **kw))


def test_plane_sdf_is_the_analytic_distance_and_zero_at_the_surface():
    vol = volume()
    vol.integrate(plane_frame(pose()))
    vox = vol.voxels()
    assert len(vox.sdf_m) > 1000
    trunc = vol.cfg.sdf_trunc
    # Fronto-parallel plane: each voxel's sdf is (depth - z), truncated to [-trunc, trunc].
    np.testing.assert_allclose(
        vox.sdf_m, np.clip(1.0 - vox.points_m[:, 2], -trunc, trunc), atol=1e-5
    )
    at_surface = np.abs(vox.points_m[:, 2] - 1.0) < 1e-4
    assert at_surface.sum() > 100 and np.abs(vox.sdf_m[at_surface]).max() < 1e-4


@pytest.mark.parametrize("yaw_deg", [0.0, 20.0])
def test_integrate_extract_raycast_plane_depth_within_half_a_voxel(yaw_deg):
    z_plane = 1.013  # between voxel centres
    vol = volume()
    for i, (x, yaw) in enumerate(((-0.1, -25.0), (0.0, 0.0), (0.1, 25.0), (0.0, 0.0))):
        vol.integrate(plane_frame(pose(x, 0.0, yaw), z_plane, seq=i))
    mesh = vol.extract_mesh()
    assert mesh.n_triangles > 100
    T = pose(0.05, 0.02, yaw_deg)
    r = MeshRenderer(mesh).render(T, K_SMALL)
    inner = np.zeros_like(r.valid)
    inner[8:-8, 12:-12] = True  # away from the observed region's border
    assert r.valid[inner].mean() > 0.99
    err = np.abs(r.depth_m - plane_depth(T, z_plane))[inner & r.valid]
    assert err.max() < VOXEL / 2, err.max()
    assert np.all(r.depth_m[~r.valid] == 0)


def test_default_meshes_a_surface_one_frame_saw_and_a_threshold_waits_for_more():
    # A wall seen once (a novel view's side, a corner passed at speed) is in the default mesh:
    # bench_mesh_threshold.py measured meshing every fused voxel better at novel views and
    # held-out frames than waiting for 2 or 3 frames.
    inner = (slice(8, -8), slice(8, -8))
    vol = volume()
    vol.integrate(plane_frame(pose()))
    r = MeshRenderer(vol.extract_mesh()).render(pose(), K_SMALL)
    assert r.valid[inner].all()
    assert np.abs(r.depth_m[inner] - 1.0).max() < VOXEL / 2

    vol = volume(mesh_weight_threshold=2.0)
    vol.integrate(plane_frame(pose()))
    assert vol.extract_mesh().n_triangles == 0
    vol.integrate(plane_frame(pose(), seq=1))
    assert MeshRenderer(vol.extract_mesh()).render(pose(), K_SMALL).valid[inner].all()


def test_colour_round_trip_rgb_and_gray():
    h, w = K_SMALL.height, K_SMALL.width
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:, : w // 2] = (200, 30, 30)
    rgb[:, w // 2 :] = (20, 40, 220)
    vol = volume()
    for i in range(3):
        vol.integrate(plane_frame(pose(), 1.0, rgb, seq=i))
    r = MeshRenderer(vol.extract_mesh()).render(pose(), K_SMALL)
    left, right = r.color[8:-8, 4 : w // 2 - 4], r.color[8:-8, w // 2 + 4 : -4]
    assert np.abs(left.astype(int) - (200, 30, 30)).max() <= 1
    assert np.abs(right.astype(int) - (20, 40, 220)).max() <= 1

    gray = np.where(np.arange(w)[None, :] < w // 2, 60, 190).astype(np.uint8).repeat(h, 0)
    vol = volume()
    for i in range(3):
        vol.integrate(plane_frame(pose(), 1.0, gray, seq=i))
    mesh = vol.extract_mesh()
    assert mesh.gray
    r = MeshRenderer(mesh).render(pose(), K_SMALL)
    assert r.color.shape == (h, w) and r.rgb().shape == (h, w, 3)
    assert np.abs(r.color[8:-8, 4 : w // 2 - 4].astype(int) - 60).max() <= 1
    assert np.abs(r.color[8:-8, w // 2 + 4 : -4].astype(int) - 190).max() <= 1


def test_sanitize_depth_range_counts_each_reason():
    d = np.array([np.nan, np.inf, -np.inf, 0.0, -1.0, 0.1, 9.0, 1.0, 0.2, 5.0], np.float32)
    out, counts = sanitize_depth_range(d, 0.2, 5.0)
    assert counts == DepthCounts(nan=1, inf=2, zero=1, negative=1, near=1, far=1)
    assert counts.total == 7  # each invalid pixel once (-inf is inf, not negative)
    np.testing.assert_array_equal(out, np.float32([0, 0, 0, 0, 0, 0, 0, 1.0, 0.2, 5.0]))
    same, none = sanitize_depth_range(out[7:], 0.2, 5.0)
    assert same is out[7:] or np.shares_memory(same, out) and none.total == 0
    # Holes (0, also -0.0) only: counted, and the input comes back as it is (nothing to zero)
    holes = np.float32([0.0, 1.0, -0.0, 2.0])
    kept, c = sanitize_depth_range(holes, 0.2, 5.0)
    assert kept is holes and c == DepthCounts(zero=2)
    # Holes and far pixels: counted, the input comes back (Open3D skips depth > depth_max)
    far = np.float32([0.0, 1.0, 9.0, 5.0, 5.5])
    kept, c = sanitize_depth_range(far, 0.2, 5.0)
    assert kept is far and c == DepthCounts(zero=1, far=2)


@pytest.mark.parametrize("kinds", ["", "far", "nan", "inf", "negative", "near", "all"])
@pytest.mark.parametrize("depth_min", [0.0, 0.2])
def test_sanitize_depth_range_matches_a_reference(kinds, depth_min):
    """Counts per reason against one mask per reason; what may be fused is exactly the range."""
    rng = np.random.default_rng(len(kinds))
    d = rng.uniform(max(depth_min, 0.05), 5.0, (48, 64)).astype(np.float32)
    d[rng.random(d.shape) < 0.05] = 0.0  # holes, always there
    values = {"far": 7.5, "nan": np.nan, "inf": np.inf, "negative": -0.3, "near": 0.1}
    for k, v in values.items():
        if k in kinds or kinds == "all":
            d[rng.random(d.shape) < 0.02] = v
    if "inf" in kinds or kinds == "all":
        d[0, :3] = -np.inf
    finite = np.isfinite(d)
    ref = DepthCounts(
        nan=int(np.isnan(d).sum()),
        inf=int(np.isinf(d).sum()),
        zero=int((d == 0).sum()),
        negative=int((finite & (d < 0)).sum()),
        near=int((finite & (d > 0) & (d < depth_min)).sum()),
        far=int((finite & (d > 5.0)).sum()),
    )
    before = d.copy()
    out, counts = sanitize_depth_range(d, depth_min, 5.0)
    assert counts == ref
    valid = (d >= depth_min) & (d <= 5.0) & (d != 0)  # holes are never fused, even at depth_min 0
    assert counts.total == d.size - valid.sum()
    np.testing.assert_array_equal(out[valid], d[valid])  # valid pixels untouched
    assert np.all((out[~valid] == 0) | (out[~valid] > 5.0))  # the rest is 0 or skipped as far
    np.testing.assert_array_equal(d, before)  # the input is never modified


def test_bad_depth_is_counted_and_not_integrated():
    T = pose()
    good = plane_depth(T, 1.0)
    bad = good.copy()
    bad[:, :8] = np.nan
    bad[:, 8:16] = np.inf
    bad[:, 16:20] = 0.0
    bad[:, 20:24] = -1.0
    bad[:, 24:28] = 0.1  # nearer than depth_min
    bad[:, 56:] = 9.0  # farther than depth_max
    color = np.full((K_SMALL.height, K_SMALL.width, 3), 90, np.uint8)
    # Built directly (not through make_frame) so that NaN and inf reach the volume.
    frame = RGBDFrame(color, bad, K_SMALL, T, 0)
    clean = good.copy()
    clean[:, :28] = 0.0
    clean[:, 56:] = 0.0
    a, b = volume(), volume()
    res = a.integrate(frame)
    b.integrate(RGBDFrame(color, clean, K_SMALL, T, 0))
    h = K_SMALL.height
    assert res.invalid == DepthCounts(
        nan=8 * h, inf=8 * h, zero=4 * h, negative=4 * h, near=4 * h, far=8 * h
    )
    assert res.valid_pixels == 28 * h and a.stats()["invalid_depth/far"] == 8 * h
    va, vb = a.voxels(), b.voxels()
    order_a, order_b = np.lexsort(va.points_m.T), np.lexsort(vb.points_m.T)
    np.testing.assert_array_equal(va.points_m[order_a], vb.points_m[order_b])
    np.testing.assert_array_equal(va.sdf_m[order_a], vb.sdf_m[order_b])


def test_block_capacity_grows_and_loses_nothing():
    frames = [plane_frame(pose(x), 1.0, seq=i) for i, x in enumerate((-0.3, 0.0, 0.3))]
    small = TsdfVolume(TsdfConfig(voxel_size=VOXEL, block_count=4, device="CPU:0"))
    big = TsdfVolume(TsdfConfig(voxel_size=VOXEL, block_count=4096, device="CPU:0"))
    grown = [small.integrate(f).grew_to for f in frames]
    for f in frames:
        big.integrate(f)
    assert max(grown) >= small.n_blocks > 4 and small.growths >= 1
    assert small.n_blocks == big.n_blocks and small.capacity >= small.n_blocks
    assert small.extract_mesh().n_triangles == big.extract_mesh().n_triangles


def test_full_volume_raises_one_clear_line():
    vol = TsdfVolume(TsdfConfig(voxel_size=VOXEL, block_count=4, max_blocks=8, device="CPU:0"))
    with pytest.raises(
        TsdfCapacityError,
        match=r"TSDF volume full: 0 blocks in use, a frame may add \d+, max_blocks is 8",
    ) as exc:
        vol.integrate(plane_frame(pose()))
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(("every", "bound"), [(1, 3.0), (4, 6.0)])
def test_weight_cap(every, bound):
    vol = volume(weight_max=3.0, weight_cap_every=every)
    for i in range(10):
        vol.integrate(plane_frame(pose(), seq=i))
    w = vol.voxels().weight
    assert w.max() <= bound and w.min() >= 1.0


def test_remesh_policy():
    cfg = TsdfConfig(remesh_min_frames=5, remesh_new_blocks=64, remesh_max_frames=50)
    assert not should_remesh(cfg, RemeshState(0, 0, False))  # nothing integrated
    assert should_remesh(cfg, RemeshState(1, 0, False))  # first mesh
    assert not should_remesh(cfg, RemeshState(4, 500, True))  # too soon
    assert should_remesh(cfg, RemeshState(5, 64, True))  # enough new blocks
    assert not should_remesh(cfg, RemeshState(49, 10, True))  # only refinement
    assert should_remesh(cfg, RemeshState(50, 0, True))  # refinement, long enough
    vol = volume()
    vol.integrate(plane_frame(pose()))
    assert vol.needs_remesh()
    vol.extract_mesh()
    assert not vol.needs_remesh() and vol.mesh_version == 1


def test_config_is_validated():
    with pytest.raises(ConfigError, match="voxel_size"):
        build(TsdfConfig, base={"voxel_size": 0.0})
    with pytest.raises(ConfigError, match="depth_min must be < depth_max"):
        build(TsdfConfig, base={"depth_min": 3.0, "depth_max": 2.0})
    assert build(TsdfConfig, overrides=["voxel_size=0.01"]).sdf_trunc == pytest.approx(0.04)


def test_matches_a_bare_open3d_loop(frames):
    """Same frames through the bare Open3D calls give the same voxels (weight cap off)."""
    import open3d as o3d
    import open3d.core as o3c

    cfg = TsdfConfig(voxel_size=0.05, depth_min=0.0, depth_max=10.0, weight_max=1e6, device="CPU:0")
    ours = TsdfVolume(cfg)
    bare = o3d.t.geometry.VoxelBlockGrid(
        ("tsdf", "weight", "color"), (o3c.float32,) * 3, ((1), (1), (3)), 0.05, 16, 1000
    )
    for f in frames:
        ours.integrate(f)
        depth = o3d.t.geometry.Image(o3c.Tensor(f.depth))
        color = o3d.t.geometry.Image(o3c.Tensor(f.color.astype(np.float32)))
        K, E = o3c.Tensor(f.intrinsics.K), o3c.Tensor(inverse_pose(f.T_world_cam))
        blocks = bare.compute_unique_block_coordinates(depth, K, E, 1.0, 10.0, 4.0)
        bare.integrate(blocks, depth, color, K, E, 1.0, 10.0, 4.0)
    assert ours.n_blocks == bare.hashmap().size()
    a = ours.extract_mesh()
    b = bare.extract_triangle_mesh(cfg.mesh_weight_threshold - 1e-3)  # ours counts it in
    assert a.n_vertices == b.vertex.positions.shape[0] > 0
    np.testing.assert_allclose(
        np.sort(a.vertices, 0), np.sort(b.vertex.positions.numpy(), 0), atol=1e-6
    )


def voxel_attributes(vbg) -> tuple[np.ndarray, ...]:  # noqa: ANN001
    """Every allocated voxel's (coordinates, tsdf, weight, colour), in coordinate order."""
    coords, index = vbg.voxel_coordinates_and_flattened_indices()
    xyz, index = coords.numpy(), index.numpy().ravel()
    order = np.lexsort(xyz.T)
    attrs = [
        vbg.attribute(a).numpy().reshape(-1, c)
        for a, c in (("tsdf", 1), ("weight", 1), ("color", 3))
    ]
    return (xyz[order], *(a[index[order]] for a in attrs))


def test_equals_the_bare_loop_on_its_own_sanitised_input(frames, gray_frames):
    """Bit for bit the voxels (sdf, weight, colour) of a bare Open3D loop that zeroes all depth
    outside [depth_min, depth_max] and converts colour itself: far pixels left to Open3D, the
    reused colour buffer, gray frames and a change of image size included."""
    import open3d as o3d
    import open3d.core as o3c

    from tests.conftest import make_frames

    cfg = TsdfConfig(voxel_size=0.05, depth_min=0.5, depth_max=4.0, weight_max=1e6, device="CPU:0")
    ours = TsdfVolume(cfg)
    bare = o3d.t.geometry.VoxelBlockGrid(
        ("tsdf", "weight", "color"), (o3c.float32,) * 3, ((1), (1), (3)), 0.05, 16, 4000
    )
    sequence = frames[:4] + gray_frames[:4] + make_frames(4, width=64, height=48, seed=2)
    far = 0
    for f in sequence:
        res = ours.integrate(f)
        d = f.depth.copy()
        d[~((d >= cfg.depth_min) & (d <= cfg.depth_max))] = 0.0
        c = np.repeat(f.color[:, :, None], 3, 2) if f.is_gray else f.color
        depth = o3d.t.geometry.Image(o3c.Tensor(d))
        color = o3d.t.geometry.Image(o3c.Tensor(c.astype(np.float32)))
        K, E = o3c.Tensor(f.intrinsics.K), o3c.Tensor(inverse_pose(f.T_world_cam))
        blocks = bare.compute_unique_block_coordinates(depth, K, E, 1.0, cfg.depth_max, 4.0)
        bare.integrate(blocks, depth, color, K, E, 1.0, cfg.depth_max, 4.0)
        assert res.valid_pixels == np.count_nonzero(d) and res.invalid.far > 0
        far += res.invalid.far
    assert far == ours.stats()["invalid_depth/far"]
    assert ours.n_blocks == bare.hashmap().size()
    for a, b in zip(voxel_attributes(ours._vbg), voxel_attributes(bare), strict=True):
        np.testing.assert_array_equal(a, b)


def test_random_frames_fuse_and_count_every_pixel(frames):
    vol = volume()
    for f in frames:
        res = vol.integrate(f)
        assert res.valid_pixels + res.invalid.total == f.depth.size
    assert vol.frames == len(frames) and vol.stats()["blocks"] == vol.n_blocks > 0


def unaligned(a: np.ndarray) -> np.ndarray:
    """``a`` as a view one byte into a buffer, as a received message's array can be."""
    buf = bytearray(a.nbytes + 1)
    out = np.frombuffer(buf, dtype=a.dtype, offset=1, count=a.size).reshape(a.shape)
    out[...] = a
    assert out.flags.aligned == (a.dtype.itemsize == 1)  # bytes are aligned anywhere
    return out


def test_unaligned_arrays_integrate_as_their_aligned_copies():
    # Open3D refused an unaligned float32 depth ("unsupported python array format =f"): a
    # repair graph at 40x32 failed on one frame of eight, where the frame's offset was odd
    f = plane_frame(pose())
    g = make_frame(unaligned(f.color), unaligned(f.depth), K_SMALL, pose(), 1_000)
    a, b = volume(), volume()
    a.integrate(f)
    b.integrate(g)
    np.testing.assert_array_equal(a.voxels().sdf_m, b.voxels().sdf_m)
