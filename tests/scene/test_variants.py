"""Named variants and camera presets, the drifted-pose inputs and how consumers select them, the
Replica output, the ``scene`` command, config round trips and determinism of degraded scenes."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsfix_online.core.config import ConfigError, build, write_config
from gsfix_online.core.se3 import inv_T
from gsfix_online.scene import (
    VARIANTS,
    ShipTankConfig,
    apply_variant,
    build_scene,
    generate_ship_tank,
    iter_frames,
    variant_overrides,
)
from gsfix_online.scene.generate import render_sample
from gsfix_online.scene.sensor import drift_poses
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.tum import read_pose_list

TOL = {"pose": 1e-6, "png_depth": 0.5 / 5000 + 1e-6, "replica_depth": 0.5 / 6553.5 + 1e-6}
TINY = ShipTankConfig(width=48, height=36, n_frames=8, n_novel=1, seed=6)


def test_every_variant_is_a_valid_config_and_real_is_the_four_degradations() -> None:
    for name in VARIANTS:
        for family in ("tank", "room"):
            apply_variant(replace(TINY, family=family), name)
    real = apply_variant(TINY, "real")
    for name in ("drift", "noisy-depth", "exposure", "blur"):
        for k, v in VARIANTS[name].items():
            assert getattr(real, k) == v, (name, k)
    assert not real.grayscale
    both = apply_variant(TINY, "real,gray", camera="vga")
    assert both.grayscale and (both.width, both.height) == (640, 480)
    slow = apply_variant(TINY, "real,slow")
    assert (slow.bays_visited, slow.room_loop, slow.pose_drift) == (1, 0.25, 0.01)
    with pytest.raises(ConfigError, match="unknown scene variant 'fog'"):
        apply_variant(TINY, "blur,fog")
    with pytest.raises(ConfigError, match="unknown scene camera"):
        apply_variant(TINY, camera="imax")


def test_variant_overrides_load_through_the_root_config() -> None:
    from gsfix_online.jobs.config import load_config

    cfg = load_config([], variant_overrides("real", camera="replica") + ["scene.shutter_s=0.01"])
    assert cfg.scene == replace(apply_variant(ShipTankConfig(), "real", "replica"), shutter_s=0.01)


def test_drift_rate_matches_the_configured_rate() -> None:
    """Relative pose error over 1-m segments (median of 8 seeds): translation ~1.9 % per metre
    and rotation ~1.0 deg per metre at pose_drift = 0.01 (measured on both paths)."""
    for family in ("tank", "room"):
        poses = build_scene(replace(TINY, family=family, n_frames=80, n_novel=0)).poses
        s = np.concatenate(
            [[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))]
        )
        trans, rot = [], []
        for seed in range(8):
            est = drift_poses(poses, 0.01, 0.0, 0.0, np.random.default_rng(seed))
            for i in range(0, len(poses), 4):
                j = int(np.searchsorted(s, s[i] + 1.0))
                if j >= len(poses):
                    break
                D = inv_T(inv_T(poses[i]) @ poses[j]) @ (inv_T(est[i]) @ est[j])
                trans.append(np.linalg.norm(D[:3, 3]) / (s[j] - s[i]))
                rot.append(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()) / (s[j] - s[i]))
        assert 0.01 < np.median(trans) < 0.03, family
        assert 0.6 < np.median(rot) < 1.6, family


def test_drift_variant_feeds_estimated_poses_and_keeps_ground_truth(tmp_path: Path) -> None:
    from gsfix_online.sources import mcap_log

    cfg = apply_variant(replace(TINY, n_frames=10), "drift")
    info = generate_ship_tank(cfg, tmp_path / "d", write_mcap=mcap_log.write_mcap, replica=True)
    gt = read_pose_list(info.tum_dir / "groundtruth.txt").poses
    est = read_pose_list(info.tum_dir / "estimated.txt").poses
    np.testing.assert_allclose(gt, build_scene(cfg).poses, atol=TOL["pose"])
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) > 1e-3
    data = json.loads(info.scene_json.read_text())
    assert data["inputs"]["tum_pose_file"] == "estimated.txt" and data["has_estimated_poses"]
    # How each consumer gets the poses the system should use:
    poses = lambda src: np.stack([f.T_world_cam for f in open_source(src)])  # noqa: E731
    tum_est = SourceConfig(path=str(info.tum_dir), pose_file=data["inputs"]["tum_pose_file"])
    np.testing.assert_allclose(poses(tum_est), est, atol=TOL["pose"])
    np.testing.assert_allclose(poses(SourceConfig(path=str(info.mcap))), est, atol=TOL["pose"])
    np.testing.assert_allclose(poses(SourceConfig(path=str(info.replica))), est, atol=TOL["pose"])
    # ... and the ground truth for scoring.
    np.testing.assert_allclose(poses(SourceConfig(path=str(info.tum_dir))), gt, atol=TOL["pose"])
    rows = np.loadtxt(info.replica / "traj_groundtruth.txt").reshape(-1, 4, 4)
    np.testing.assert_allclose(rows, gt, atol=TOL["pose"])
    # The novel views are asked for in the map's (estimated) frame: each keeps its exact pose
    # relative to the nearest input frame; their exact poses are kept beside them.
    views = read_pose_list(info.out_dir / "novel" / "views.txt").poses
    exact = read_pose_list(info.out_dir / "novel" / "views_groundtruth.txt").poses
    assert len(views) == len(exact) > 0
    for T, X in zip(views, exact, strict=True):
        i = int(np.argmin(np.linalg.norm(gt[:, :3, 3] - X[:3, 3], axis=1)))
        rel_map, rel_true = np.linalg.inv(est[i]) @ T, np.linalg.inv(gt[i]) @ X
        np.testing.assert_allclose(rel_map, rel_true, atol=1e-5)
    assert np.abs(views[:, :3, 3] - exact[:, :3, 3]).max() > 1e-4  # the drift moved them


@pytest.mark.parametrize("gray", [False, True])
def test_replica_folder_holds_the_tum_frames(tmp_path: Path, gray: bool) -> None:
    cfg = replace(TINY, n_frames=5, grayscale=gray)
    info = generate_ship_tank(cfg, tmp_path / "r", replica=True)
    assert info.replica is not None
    tum = list(open_source(SourceConfig(path=str(info.tum_dir))))
    rep = list(open_source(SourceConfig(path=str(info.replica))))
    assert [f.color.shape for f in rep] == [f.color.shape for f in tum]
    for a, b in zip(tum, rep, strict=True):
        np.testing.assert_array_equal(a.color, b.color)  # PNG: lossless
        fits = a.depth < 65535 / 6553.5
        np.testing.assert_allclose(b.depth[fits], a.depth[fits], atol=TOL["replica_depth"])
        assert a.intrinsics == b.intrinsics
    assert json.loads(info.scene_json.read_text())["inputs"]["replica"] == "replica"


def test_real_variant_is_deterministic_and_differs_by_seed(tmp_path: Path) -> None:
    cfg = apply_variant(replace(TINY, family="room", n_frames=6), "real")
    a = generate_ship_tank(cfg, tmp_path / "a")
    b = generate_ship_tank(cfg, tmp_path / "b")

    def files(root: Path) -> dict[str, bytes]:
        return {
            str(p.relative_to(root)): p.read_bytes()
            for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "scene.json"
        }

    fa, fb = files(a.out_dir), files(b.out_dir)
    assert fa.keys() == fb.keys() and "gt/exposure.txt" in fa
    assert [k for k in fa if fa[k] != fb[k]] == []
    other = next(iter_frames(replace(cfg, seed=7, n_frames=2)))
    same = next(iter_frames(replace(cfg, n_frames=2)))
    assert not np.array_equal(other.color, same.color)


def test_degradations_leave_ground_truth_and_novel_views_alone(tmp_path: Path) -> None:
    base = replace(TINY, n_novel=2)
    clean = generate_ship_tank(base, tmp_path / "clean")
    real = generate_ship_tank(apply_variant(base, "real"), tmp_path / "real")
    for sub in ("gt/color", "gt/depth", "novel/color", "novel/depth"):
        names = sorted(p.name for p in (clean.out_dir / sub).iterdir())
        assert names == sorted(p.name for p in (real.out_dir / sub).iterdir())
        for n in names:
            assert (clean.out_dir / sub / n).read_bytes() == (real.out_dir / sub / n).read_bytes()
    assert (clean.out_dir / "tum/rgb.txt").read_text() == (real.out_dir / "tum/rgb.txt").read_text()
    assert not (clean.out_dir / "novel/views_groundtruth.txt").exists()  # no estimate, one list
    a = next(iter(open_source(SourceConfig(path=str(clean.tum_dir)))))
    b = next(iter(open_source(SourceConfig(path=str(real.tum_dir)))))
    assert not np.array_equal(a.color, b.color) and not np.array_equal(a.depth, b.depth)


def test_config_round_trip_gives_the_same_frames(tmp_path: Path) -> None:
    cfg = apply_variant(replace(TINY, family="room", n_frames=3, fx=40.0, cx=23.0), "real,gray")
    path = write_config(cfg, tmp_path / "scene.yaml")
    back = build(ShipTankConfig, files=[path])
    assert back == cfg
    s1, s2 = render_sample(build_scene(cfg), 1), render_sample(build_scene(back), 1)
    np.testing.assert_array_equal(s1.color, s2.color)
    np.testing.assert_array_equal(s1.depth, s2.depth)
    k = build_scene(back).intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (40.0, 40.0, 23.0, (36 - 1) / 2)


@pytest.mark.parametrize(
    "kw",
    [
        {"shutter_s": 0.2},  # longer than the frame interval at 10 fps
        {"cx": 60.0},  # outside the 48-px-wide image
        {"exposure_gain_min": 1.2},
        {"depth_grazing_deg": 20.0},
    ],
)
def test_bad_degradation_config_is_rejected(kw: dict) -> None:
    with pytest.raises(ConfigError):
        build_scene(replace(TINY, **kw))


def test_scene_command_variants_formats_and_errors(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    from gsfix_online.apps.cli import main

    small = ["scene.width=40", "scene.height=30", "scene.n_frames=4", "scene.n_novel=1"]
    out = tmp_path / "room"
    args = ["scene", "room", *small, "--out", str(out), "--variant", "drift,exposure"]
    assert main([*args, "--formats", "tum,replica", "--no-progress"]) == 0
    assert "room: 4 frames" in capsys.readouterr().out
    assert (out / "replica/traj.txt").is_file() and not (out / "log.mcap").exists()
    data = json.loads((out / "scene.json").read_text())
    assert data["family"] == "room" and data["config"]["pose_drift"] == 0.01
    assert data["config"]["exposure_gain_max"] == 1.4
    from gsfix_online.jobs.config import load_config

    assert load_config([out / "config.yaml"]).scene == build(ShipTankConfig, base=data["config"])
    # Later KEY=VALUE overrides beat the variant; a contradicting family and bad names are errors.
    over = tmp_path / "over"
    assert main(["scene", "ship-tank", *small, "scene.pose_drift=0.05", "--out", str(over),
                 "--variant", "drift", "--no-mcap"]) == 0  # fmt: skip
    assert json.loads((over / "scene.json").read_text())["config"]["pose_drift"] == 0.05
    assert main(["scene", "room", "scene.family=tank", "--out", str(tmp_path / "x")]) == 2
    assert main(["scene", "room", "--out", str(tmp_path / "x"), "--variant", "fog"]) == 2
    assert main(["scene", "room", "--out", str(tmp_path / "x"), "--formats", "bag"]) == 2
    assert "expected tum, mcap or replica" in capsys.readouterr().err
