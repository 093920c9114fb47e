"""The room family: layout, mesh, path clearance, valid frames, novel views and the written
folder (the same layout as the tank's), and Replica's 1200x680 camera."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.core.config import ConfigError
from gsfix_online.scene import CAMERAS, ShipTankConfig, build_scene, generate_ship_tank
from gsfix_online.scene.generate import render_sample, render_view
from gsfix_online.scene.room import RoomLayout, RoomMaterial, build_room
from gsfix_online.scene.trajectory import observed_points
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.base import read_color, read_depth_png
from gsfix_online.sources.tum import read_pose_list

ROOM = ShipTankConfig(family="room", width=80, height=60, n_frames=16, n_novel=3, seed=1)
TOL = {"png_depth": 0.5 / 5000 + 1e-6, "pose": 1e-6}


@pytest.fixture(scope="module")
def room_scene():
    return build_scene(ROOM)


@pytest.fixture(scope="module")
def room_dir(tmp_path_factory: pytest.TempPathFactory):
    return generate_ship_tank(ROOM, tmp_path_factory.mktemp("room") / "r")


def test_room_mesh_has_every_part_and_unit_normals() -> None:
    mesh = build_room(ShipTankConfig(family="room"))
    assert isinstance(mesh.layout, RoomLayout)
    assert 10_000 < mesh.n_triangles < 150_000
    mats = set(np.unique(mesh.material).tolist())
    plain = {int(m) for m in RoomMaterial if m not in (RoomMaterial.BOOK, RoomMaterial.PICTURE)}
    assert plain <= mats
    assert len([m for m in mats if RoomMaterial.BOOK <= m < RoomMaterial.PICTURE]) >= 8
    assert len([m for m in mats if m >= RoomMaterial.PICTURE]) == 4
    np.testing.assert_allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-5)


def test_room_path_keeps_clearance_and_loops_around_the_table(room_scene) -> None:
    lay, pos = room_scene.layout, room_scene.poses[:, :3, 3]
    assert np.all(room_scene.renderer.distance(pos) >= ROOM.clearance)
    assert np.all((pos > 0) & (pos < [lay.length, lay.width, lay.height]))
    cx, cy = lay.table_centre
    angle = np.unwrap(np.arctan2(pos[:, 1] - cy, pos[:, 0] - cx))
    assert abs(angle[-1] - angle[0]) > 0.7 * 2 * np.pi * ROOM.room_loop  # most of the loop
    assert np.all((pos[:, 2] > 1.1) & (pos[:, 2] < 1.6))  # hand height


def test_room_frames_are_valid_textured_and_hole_free(room_scene) -> None:
    for i in (0, 5, 10, 15):
        s = render_sample(room_scene, i)
        assert s.mask.mean() > 0.999  # a closed room: every ray hits something
        assert s.color.shape == (60, 80, 3) and s.color.dtype == np.uint8
        assert s.depth_gt.min() > 0.3 and s.depth_gt.max() < 8.0
        assert (s.depth > 0).mean() > 0.9
        assert 40 < s.color_gt.mean() < 220 and s.color_gt.std() > 15  # lit and textured


def test_room_novel_views_are_partly_observed_and_outside_furniture(room_dir, room_scene) -> None:
    cov = room_dir.novel_coverage
    assert len(cov) == ROOM.n_novel
    assert all(ROOM.novel_coverage_min <= c <= ROOM.novel_coverage_max for c in cov)
    views = read_pose_list(room_dir.novel_dir / "views.txt").poses
    for k, T in enumerate(views):
        eye = T[:3, 3]
        for lo, hi in room_scene.layout.keep_out:
            assert not (np.all(eye > lo) and np.all(eye < hi))
        r = render_view(room_scene, T)
        np.testing.assert_array_equal(
            r.color, read_color(room_dir.novel_dir / "color" / f"{k:03d}.png")
        )


def test_room_folder_has_the_tank_layout_and_reads_back(room_dir, room_scene) -> None:
    out = room_dir.out_dir
    for rel in ("tum/rgb.txt", "tum/groundtruth.txt", "gt/mesh.ply", "novel/intrinsics.json"):
        assert (out / rel).is_file(), rel
    data = json.loads(room_dir.scene_json.read_text())
    assert data["family"] == "room" and data["config"]["family"] == "room"
    assert data["inputs"] == {"tum": "tum", "tum_pose_file": "groundtruth.txt"}
    frames = list(open_source(SourceConfig(), room_dir.tum_dir))
    assert len(frames) == ROOM.n_frames
    for f, T in zip(frames, room_scene.poses, strict=True):
        np.testing.assert_allclose(f.T_world_cam, T, atol=TOL["pose"])
    gt = read_depth_png(room_dir.gt_dir / "depth" / "000003.png", 5000.0)
    np.testing.assert_allclose(gt, render_sample(room_scene, 3).depth_gt, atol=TOL["png_depth"])


def test_room_gt_mesh_covers_what_the_camera_sees(room_dir, room_scene) -> None:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(room_dir.gt_mesh))
    assert len(mesh.triangles) == room_dir.n_triangles
    assert np.asarray(mesh.vertex_colors).std() > 0.05  # coloured, not flat
    s = render_sample(room_scene, 7)
    pts = observed_points(s.depth_gt, s.points, 0.2, 8.0)
    dist = room_scene.renderer.distance(pts)
    assert np.percentile(dist, 99) < 1e-3


def test_replica_camera_validates_and_renders_one_frame() -> None:
    cfg = replace(ROOM, n_frames=2, n_novel=0, **CAMERAS["replica"])
    scene = build_scene(cfg)
    k = scene.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (1200, 680, 600.0, 600.0, 599.5, 339.5)
    s = render_sample(scene, 0)
    assert s.color.shape == (680, 1200, 3) and s.depth.shape == (680, 1200)
    assert s.mask.mean() > 0.999


def test_room_ignores_tank_geometry_checks_and_checks_its_own() -> None:
    build_scene(replace(ROOM, n_frames=2, n_novel=0, n_web_frames=8))  # tank-only field: ignored
    with pytest.raises(ConfigError):
        build_scene(replace(ROOM, room_width=2.0))
    with pytest.raises(ConfigError):
        build_scene(replace(ROOM, family="cave"))  # type: ignore[arg-type]


def test_room_same_seed_same_frames_other_seed_other_room(tmp_path: Path) -> None:
    a = render_sample(build_scene(replace(ROOM, n_frames=4)), 2)
    b = render_sample(build_scene(replace(ROOM, n_frames=4)), 2)
    c = render_sample(build_scene(replace(ROOM, n_frames=4, seed=2)), 2)
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(a.depth, b.depth)
    assert not np.array_equal(a.color, c.color)
