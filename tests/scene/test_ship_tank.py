"""Synthetic ship tank: renderer against analytic planes, ground truth round trips, sensor noise
statistics, trajectory clearance, novel-view coverage, determinism, and the written dataset."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.core.config import ConfigError
from gsfix_online.core.se3 import look_at, make_T
from gsfix_online.core.types import Intrinsics
from gsfix_online.scene import ShipTankConfig, build_scene, generate_ship_tank, iter_frames, observe
from gsfix_online.scene.generate import render_sample, render_view
from gsfix_online.scene.geometry import Material, build_tank, plane_mesh
from gsfix_online.scene.render import Renderer, pixel_rays
from gsfix_online.scene.trajectory import (
    ObservedSurface,
    SceneLayoutError,
    check_clearance,
    observed_points,
)
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.base import read_color, read_depth_png
from gsfix_online.sources.tum import read_pose_list

# Tolerances, one table. Depth from Embree is float32 metres.
TOL = {
    "plane_depth": 1e-5,  # float32 ray parameter at 1 m
    "png_depth": 0.5 / 5000 + 1e-6,  # half a step of the 5000 / m PNG, plus float32 rounding
    "pose": 1e-6,  # TUM pose files are written with 17 significant digits
    "noise_sigma_rel": 0.2,  # measured sigma / (k z^2), 20 %: ~10^4 samples per bin
    "dropout_abs": 0.01,  # blobs cut at the exact quantile; the range limits take a few more
    "image_sigma_rel": 0.15,
}

SMALL = ShipTankConfig(width=80, height=60, n_frames=20, n_novel=3, seed=3)


@pytest.fixture(scope="module")
def small_scene():
    return build_scene(SMALL)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("tank") / "a"
    return generate_ship_tank(SMALL, out)


# --------------------------------------------------------------------------------------------
# Renderer: analytic planes
# --------------------------------------------------------------------------------------------

POSES = [
    np.eye(4),
    look_at([0.3, -0.2, 0.5], [1.0, 0.4, 2.0]),
    make_T(np.diag([1.0, -1.0, -1.0]), [5.0, 2.0, -3.0]),  # looking down world -z
]


@pytest.mark.parametrize("T", POSES, ids=["identity", "oblique", "flipped"])
def test_plane_at_unit_depth_renders_depth_one(T: np.ndarray) -> None:
    intr = Intrinsics(60.0, 55.0, 39.5, 29.5, 80, 60)
    # A 200 m square perpendicular to the optical axis, 1 m in front of the camera.
    corners_cam = np.array([[-100, -100, 1], [100, -100, 1], [100, 100, 1], [-100, 100, 1]], float)
    corners = corners_cam @ T[:3, :3].T + T[:3, 3]
    hits = Renderer(plane_mesh(corners)).cast(intr, T)
    assert hits.mask.all()
    np.testing.assert_allclose(hits.depth, 1.0, atol=TOL["plane_depth"])
    # Unprojecting the depth gives points on the plane (camera z = 1) and equals the hit points.
    origin, dirs = pixel_rays(intr, T)
    pts = origin + dirs * hits.depth[..., None]
    z_cam = (pts - T[:3, 3]) @ T[:3, :3][:, 2]
    np.testing.assert_allclose(z_cam, 1.0, atol=TOL["plane_depth"])
    np.testing.assert_allclose(hits.points, pts, atol=1e-9)
    # Normals face the camera.
    np.testing.assert_allclose(hits.normals @ T[:3, :3][:, 2], -1.0, atol=1e-5)


def test_depth_is_along_optical_axis_not_ray_length() -> None:
    intr = Intrinsics(40.0, 40.0, 39.5, 29.5, 80, 60)
    hits = Renderer(plane_mesh([[-50, -50, 2], [50, -50, 2], [50, 50, 2], [-50, 50, 2]])).cast(
        intr, np.eye(4)
    )
    u, v = np.meshgrid(np.arange(80), np.arange(60))
    stretch = np.sqrt(((u - intr.cx) / intr.fx) ** 2 + ((v - intr.cy) / intr.fy) ** 2 + 1.0)
    np.testing.assert_allclose(hits.depth, 2.0, atol=2 * TOL["plane_depth"])
    np.testing.assert_allclose(hits.ray_length, 2.0 * stretch, rtol=1e-5)
    assert hits.ray_length[0, 0] > 2.0 * 1.5  # corners: ray much longer than the depth


def test_render_shapes_and_gray() -> None:
    intr = Intrinsics(40.0, 40.0, 19.5, 14.5, 40, 30)
    r = Renderer(plane_mesh([[-5, -5, 1], [5, -5, 1], [5, 5, 1], [-5, 5, 1]]))
    rgb = r.render(intr, np.eye(4))
    gray = r.render(intr, np.eye(4), grayscale=True)
    assert rgb.color.dtype == np.uint8 and rgb.color.shape == (30, 40, 3)
    assert gray.color.dtype == np.uint8 and gray.color.shape == (30, 40)
    assert rgb.color.std() > 0  # textured, not flat


def test_grayscale_frames_are_hw_uint8() -> None:
    f = next(iter_frames(replace(SMALL, grayscale=True, n_frames=2)))
    assert f.color.dtype == np.uint8 and f.color.shape == (60, 80) and f.is_gray


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def test_tank_mesh_is_moderate_and_has_every_part() -> None:
    mesh = build_tank(ShipTankConfig())
    assert 20_000 < mesh.n_triangles < 150_000
    assert set(np.unique(mesh.material)) == {int(m) for m in Material}
    np.testing.assert_allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-5)


def test_web_ring_covers_plate_minus_hole() -> None:
    """Both faces of every web: plate area minus the (polygonal) ellipse, corners included."""
    cfg = ShipTankConfig()
    mesh = build_tank(cfg)
    lay = mesh.layout
    V, T = mesh.vertices, mesh.triangles[mesh.material == Material.WEB]
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    face = np.abs(n[:, 0]) > 0.999 * np.linalg.norm(n, axis=1)  # plate faces, not the hole rim
    area = 0.5 * np.linalg.norm(n[face], axis=1).sum()
    a, b = lay.hole_axes
    expected = 2 * cfg.n_web_frames * (lay.width * lay.height - np.pi * a * b)
    assert abs(area - expected) / expected < 2e-3


def test_trajectory_frames_see_no_holes_in_the_mesh(small_scene) -> None:
    for i in (0, 7, 13, 19):
        _, _, mask = small_scene.renderer.depth(small_scene.intrinsics, small_scene.poses[i])
        assert mask.mean() > 0.999


# --------------------------------------------------------------------------------------------
# Trajectory and novel views
# --------------------------------------------------------------------------------------------


def test_trajectory_keeps_clearance(small_scene) -> None:
    cfg, lay = small_scene.cfg, small_scene.layout
    pos = small_scene.poses[:, :3, 3]
    assert np.all(small_scene.renderer.distance(pos) >= cfg.clearance)
    assert np.all((pos > 0) & (pos < [lay.length, lay.width, lay.height]))
    # It moves through at least two bays and never into the last one.
    assert pos[:, 0].max() - pos[:, 0].min() > 2.0 and pos[:, 0].max() < lay.web_x[-1]
    with pytest.raises(SceneLayoutError, match="from the structure"):
        check_clearance(small_scene.renderer, lay, np.array([[0.05, 1.0, 1.0]]), 0.3, "test")


def test_novel_views_are_partly_observed_and_less_than_training(dataset, small_scene) -> None:
    cfg = small_scene.cfg
    cov = dataset.novel_coverage
    assert len(cov) == cfg.n_novel
    assert all(cfg.novel_coverage_min <= c <= cfg.novel_coverage_max for c in cov)
    # Training frames are fully observed by construction; held-out ones (odd frames against the
    # surface seen by the even ones) still beat the novel views on average. At 80x60 and 20 frames
    # single held-out frames can drop to ~0.5: pixels are wider than the voxels and steps are long.
    full = observe(small_scene)
    _, p0, m0 = small_scene.renderer.depth(small_scene.intrinsics, small_scene.poses[4])
    assert full.coverage(p0[m0]) > 0.999 > max(cov)
    obs = ObservedSurface(cfg.coverage_voxel)
    for i in range(0, cfg.n_frames, 2):
        d, p, _ = small_scene.renderer.depth(small_scene.intrinsics, small_scene.poses[i])
        obs.add(observed_points(d, p, cfg.depth_min, cfg.depth_max))
    train = []
    for i in range(1, cfg.n_frames - 1, 2):
        _, p, m = small_scene.renderer.depth(small_scene.intrinsics, small_scene.poses[i])
        train.append(obs.coverage(p[m]))
    assert np.mean(train) > np.mean(cov) + 0.1
    # The written novel views have that coverage against the whole trajectory.
    T = read_pose_list(dataset.novel_dir / "views.txt").poses
    assert len(T) == cfg.n_novel
    for k, Tk in enumerate(T):
        _, p, m = small_scene.renderer.depth(small_scene.intrinsics, Tk)
        assert abs(full.coverage(p[m]) - cov[k]) < 1e-3
        assert small_scene.renderer.distance(Tk[None, :3, 3])[0] >= cfg.clearance
        assert (dataset.novel_dir / "color" / f"{k:03d}.png").is_file()


# --------------------------------------------------------------------------------------------
# Sensor noise
# --------------------------------------------------------------------------------------------


def test_depth_noise_dropout_and_image_noise_statistics(small_scene) -> None:
    cfg = small_scene.cfg
    z_all, r_all, lost, valid_gt, dimg = [], [], [], [], []
    for i in range(cfg.n_frames):
        s = render_sample(small_scene, i)
        inside = (s.depth_gt > cfg.depth_min + 0.1) & (s.depth_gt < cfg.depth_max - 0.5)
        both = inside & (s.depth > 0)
        z_all.append(s.depth_gt[both])
        r_all.append(s.depth[both] - s.depth_gt[both])
        lost.append(np.count_nonzero(inside & (s.depth == 0)))
        valid_gt.append(np.count_nonzero(inside))
        mid = (s.color_gt > 20) & (s.color_gt < 235)  # away from clipping
        dimg.append(s.color.astype(float)[mid] - s.color_gt.astype(float)[mid])
    z, r = np.concatenate(z_all), np.concatenate(r_all)
    for lo, hi in ((0.8, 1.6), (1.6, 3.0)):
        sel = (z >= lo) & (z < hi)
        assert sel.sum() > 2000
        ratio = np.std(r[sel] / z[sel] ** 2) / cfg.depth_noise
        assert abs(ratio - 1.0) < TOL["noise_sigma_rel"], (lo, hi, ratio)
    assert abs(sum(lost) / sum(valid_gt) - cfg.dropout) < TOL["dropout_abs"]
    # The colour noise is sigma on top of the rounding of the noise-free image (1/12 variance).
    measured = np.std(np.concatenate(dimg))
    assert abs(measured / np.hypot(cfg.image_noise, np.sqrt(1 / 12)) - 1.0) < TOL["image_sigma_rel"]


def test_dropouts_are_blobs(small_scene) -> None:
    s = render_sample(small_scene, 5)
    drop = (s.depth == 0) & (s.depth_gt > 0.5) & (s.depth_gt < 7.0)
    neighbour = drop[1:, :] & drop[:-1, :]
    # For independent pixels P(neighbour dropped | dropped) = 0.02; blobs make it large.
    assert neighbour.sum() / max(drop[1:, :].sum(), 1) > 0.5


def test_drift_off_by_default_and_grows_with_distance(tmp_path: Path) -> None:
    cfg = replace(SMALL, n_frames=12, n_novel=0, pose_drift=0.02, width=40, height=30)
    got: list[np.ndarray] = []

    def fake_mcap(path: Path, frames) -> None:  # noqa: ANN001
        got.extend(f.T_world_cam for f in frames)

    info = generate_ship_tank(cfg, tmp_path / "d", write_mcap=fake_mcap)
    gt = read_pose_list(info.tum_dir / "groundtruth.txt").poses
    est = read_pose_list(info.tum_dir / "estimated.txt").poses
    err = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert err[0] < 1e-9 and err[-1] > err[len(err) // 2] > 0
    np.testing.assert_allclose(np.stack(got), est, atol=TOL["pose"])  # the MCAP gets the estimate
    np.testing.assert_allclose(gt, build_scene(cfg).poses, atol=TOL["pose"])
    assert build_scene(SMALL).has_estimate is False


# --------------------------------------------------------------------------------------------
# The written dataset
# --------------------------------------------------------------------------------------------


def test_tum_folder_reads_back_with_exact_poses(dataset, small_scene) -> None:
    reader = open_source(SourceConfig(), dataset.tum_dir)
    frames = list(reader)
    assert len(frames) == SMALL.n_frames == dataset.n_frames
    for f, T in zip(frames, small_scene.poses, strict=True):
        np.testing.assert_allclose(f.T_world_cam, T, atol=TOL["pose"])
    mem = next(iter_frames(small_scene))
    np.testing.assert_array_equal(frames[0].color, mem.color)
    np.testing.assert_allclose(frames[0].depth, mem.depth, atol=TOL["png_depth"])
    assert frames[1].stamp_ns - frames[0].stamp_ns == 100_000_000
    assert not (dataset.tum_dir / "estimated.txt").exists()


def test_gt_mesh_depth_matches_gt_depth_images(dataset, small_scene) -> None:
    import open3d as o3d

    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(dataset.gt_mesh)))
    assert mesh.triangle.indices.shape[0] == dataset.n_triangles
    assert mesh.vertex.colors.shape[0] == mesh.vertex.positions.shape[0]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    intr = small_scene.intrinsics
    poses = read_pose_list(dataset.tum_dir / "groundtruth.txt").poses
    for i in (0, 9, 19):
        origin, dirs = pixel_rays(intr, poses[i])
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], -1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        gt = read_depth_png(dataset.gt_dir / "depth" / f"{i:06d}.png", 5000.0)
        ok = np.isfinite(t) & (gt > 0)
        assert ok.mean() > 0.999
        np.testing.assert_allclose(gt[ok], t[ok], atol=TOL["png_depth"])
        assert read_color(dataset.gt_dir / "color" / f"{i:06d}.png").shape == (60, 80, 3)


def test_scene_json_and_novel_files(dataset) -> None:
    data = json.loads(dataset.scene_json.read_text())
    assert data["seed"] == SMALL.seed and data["counts"]["frames"] == SMALL.n_frames
    assert data["counts"]["triangles"] == dataset.n_triangles
    assert [v["coverage"] for v in data["novel_views"]] == dataset.novel_coverage
    assert {"build", "frames", "novel", "total"} <= set(data["timings_s"])
    assert json.loads((dataset.novel_dir / "intrinsics.json").read_text())["width"] == 80
    d = read_depth_png(dataset.novel_dir / "depth" / "000.png", 5000.0)
    assert d.shape == (60, 80) and (d > 0).mean() > 0.99


# --------------------------------------------------------------------------------------------
# Determinism and validation
# --------------------------------------------------------------------------------------------


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "scene.json"
    }


def test_same_seed_same_bytes_other_seed_differs(dataset, tmp_path: Path) -> None:
    again = generate_ship_tank(SMALL, tmp_path / "b")
    a, b = _files(dataset.out_dir), _files(again.out_dir)
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []
    other = list(iter_frames(replace(SMALL, seed=4, n_frames=2)))
    same = list(iter_frames(replace(SMALL, n_frames=2)))
    assert not np.array_equal(other[1].color, same[1].color)
    assert not np.array_equal(other[1].depth, same[1].depth)
    # Frame 0 sits at the start of the path whatever n_frames is.
    first_written = sorted((dataset.tum_dir / "rgb").iterdir())[0]
    np.testing.assert_array_equal(same[0].color, read_color(first_written))


def test_novel_render_is_noise_free(small_scene, dataset) -> None:
    T = read_pose_list(dataset.novel_dir / "views.txt").poses[0]
    r = render_view(small_scene, T)
    np.testing.assert_array_equal(r.color, read_color(dataset.novel_dir / "color" / "000.png"))


@pytest.mark.parametrize(
    "kw",
    [
        {"novel_coverage_min": 0.9, "novel_coverage_max": 0.5},
        {"width": 2},
        {"depth_max": 20.0},
        {"n_web_frames": 8},  # bays shorter than 1 m
        {"lighting": "sun"},
    ],
)
def test_bad_config_is_rejected(kw: dict) -> None:
    with pytest.raises(ConfigError):
        build_scene(replace(SMALL, **kw))


def test_mcap_log_carries_the_estimated_poses(tmp_path: Path) -> None:
    from gsfix_online.sources import mcap_log

    cfg = replace(SMALL, n_frames=6, n_novel=0, pose_drift=0.02, width=40, height=30)
    info = generate_ship_tank(cfg, tmp_path / "m", write_mcap=mcap_log.write_mcap)
    assert info.mcap is not None and info.mcap.is_file()
    frames = list(open_source(SourceConfig(), info.mcap))
    est = read_pose_list(info.tum_dir / "estimated.txt").poses
    assert len(frames) == cfg.n_frames
    np.testing.assert_allclose(np.stack([f.T_world_cam for f in frames]), est, atol=TOL["pose"])


def test_regeneration_replaces_an_earlier_scene_and_refuses_other_folders(tmp_path: Path) -> None:
    big = replace(SMALL, n_frames=6, n_novel=2, width=40, height=30)
    generate_ship_tank(big, tmp_path / "s")
    assert (tmp_path / "s" / "novel" / "color" / "001.png").is_file()
    generate_ship_tank(replace(big, n_novel=1), tmp_path / "s")
    assert not (tmp_path / "s" / "novel" / "color" / "001.png").exists()  # no stale view left
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="holds no earlier scene"):
        generate_ship_tank(big, tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
