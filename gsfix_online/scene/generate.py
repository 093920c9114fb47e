"""Build the ship-tank scene, stream its frames, and write the dataset folder.

In memory: ``build_scene(cfg)`` -> :class:`ShipTankScene`; ``iter_samples(scene)`` renders each
frame once and yields the noise-free and the noisy version together; ``iter_frames(cfg)`` yields
plain :class:`RGBDFrame` objects. On disk: ``generate_ship_tank(cfg, out_dir)`` writes::

    scene.json            parameters, intrinsics, counts, novel-view coverage, timings
    tum/                  noisy input sequence (groundtruth.txt exact; estimated.txt when drift/noise is on)
    gt/mesh.ply           ground-truth mesh, vertex colours = albedo (sRGB)
    gt/color|depth/NNNNNN.png   noise-free training images (depth 16-bit, 5000 / m)
    novel/views.txt       novel camera poses (TUM pose list), novel/color|depth/NNN.png, novel/intrinsics.json
    log.mcap              only with ``write_mcap``: the TUM frames with the estimated poses
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.config_schema import ConfigError, build, to_dict
from gsfix_online.scene.appearance import Appearance, linear_to_srgb
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.scene.geometry import TankLayout, TankMesh, build_tank
from gsfix_online.scene.render import LightRig, Renderer, RenderResult
from gsfix_online.scene.sensor import drift_poses, noisy_depth, noisy_image
from gsfix_online.scene.trajectory import (
    NovelView,
    ObservedSurface,
    camera_poses,
    check_clearance,
    observed_points,
    select_novel_views,
)
from gsfix_online.types import Intrinsics, RGBDFrame, make_frame

logger = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # depth PNG units per metre (TUM)
_FRAME_STREAM, _DRIFT_STREAM = 0xF4A3E, 0xD41F7  # rng stream tags mixed with the seed


@dataclass
class ShipTankScene:
    """Everything needed to render the sequence; built once, cheap to keep."""

    cfg: ShipTankConfig
    layout: TankLayout
    mesh: TankMesh
    renderer: Renderer
    intrinsics: Intrinsics
    poses: npt.NDArray[np.float64]  # [N, 4, 4] exact T_world_cam
    # [N, 4, 4] VIO-like estimate (equal to poses when drift and noise are off)
    poses_est: npt.NDArray[np.float64]
    stamps_ns: npt.NDArray[np.int64]  # [N]

    @property
    def has_estimate(self) -> bool:
        c = self.cfg
        return c.pose_drift > 0 or c.pose_noise > 0 or c.pose_noise_deg > 0


@dataclass
class SceneSample:
    """One trajectory frame, rendered once: noise-free ground truth and the noisy sensor view."""

    index: int
    stamp_ns: int
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] exact
    T_world_cam_est: npt.NDArray[np.float64]  # [4, 4] estimate
    color_gt: npt.NDArray[np.uint8]  # [H, W, 3] or [H, W]
    depth_gt: npt.NDArray[np.float32]  # [H, W] m, every hit (no range limit)
    color: npt.NDArray[np.uint8]  # noisy
    depth: npt.NDArray[np.float32]  # noisy, dropouts and range limits applied
    points: npt.NDArray[np.float64]  # [H, W, 3] world hit points
    mask: npt.NDArray[np.bool_]  # [H, W] ray hit the mesh

    def frame(
        self, intr: Intrinsics, noisy: bool = True, pose: Literal["gt", "estimated"] = "gt"
    ) -> RGBDFrame:
        color, depth = (self.color, self.depth) if noisy else (self.color_gt, self.depth_gt)
        T = self.T_world_cam if pose == "gt" else self.T_world_cam_est
        return make_frame(color, depth, intr, T, self.stamp_ns, frame_id="camera", seq=self.index)


@dataclass
class SceneInfo:
    """What ``generate_ship_tank`` wrote."""

    out_dir: Path
    scene_json: Path
    tum_dir: Path
    gt_mesh: Path
    gt_dir: Path
    novel_dir: Path
    mcap: Path | None
    n_frames: int
    n_triangles: int
    n_novel: int
    novel_coverage: list[float]
    timings_s: dict[str, float] = field(default_factory=dict)


def checked(cfg: ShipTankConfig) -> ShipTankConfig:
    """``cfg`` re-validated through the config machinery (ranges, literals, cross-field rules)."""
    if not isinstance(cfg, ShipTankConfig):
        raise ConfigError(f"expected a ShipTankConfig, got {type(cfg).__name__}")
    return build(ShipTankConfig, base=to_dict(cfg))


def build_scene(cfg: ShipTankConfig) -> ShipTankScene:
    """Mesh, renderer, camera and poses for ``cfg``; raises ConfigError / SceneLayoutError on bad input."""
    cfg = checked(cfg)
    mesh = build_tank(cfg)
    lay = mesh.layout
    assert lay is not None
    lights = LightRig(
        mode=cfg.lighting, ambient=cfg.ambient, lamps=lay.lamps, power=cfg.light_power
    )
    renderer = Renderer(mesh, Appearance(cfg.seed, lay), lights)
    poses = camera_poses(cfg, lay)
    check_clearance(renderer, lay, poses[:, :3, 3], cfg.clearance, "trajectory")
    rng = np.random.default_rng([cfg.seed, _DRIFT_STREAM])
    est = drift_poses(poses, cfg.pose_drift, cfg.pose_noise, cfg.pose_noise_deg, rng)
    stamps = np.array([cfg.stamp_ns(i) for i in range(cfg.n_frames)], np.int64)
    return ShipTankScene(cfg, lay, mesh, renderer, cfg.intrinsics, poses, est, stamps)


def render_sample(scene: ShipTankScene, i: int) -> SceneSample:
    """Frame ``i``: one render, then the sensor noise drawn from the frame's own rng."""
    cfg = scene.cfg
    r = scene.renderer.render(scene.intrinsics, scene.poses[i], grayscale=cfg.grayscale)
    rng = np.random.default_rng([cfg.seed, _FRAME_STREAM, i])
    color = noisy_image(r.color_f, cfg.image_noise, rng)
    limits = (cfg.depth_min, cfg.depth_max)
    depth = noisy_depth(r.depth, cfg.depth_noise, cfg.dropout, cfg.dropout_blob_px, *limits, rng)
    return SceneSample(
        index=i,
        stamp_ns=int(scene.stamps_ns[i]),
        T_world_cam=scene.poses[i],
        T_world_cam_est=scene.poses_est[i],
        color_gt=r.color,
        depth_gt=r.depth,
        color=color,
        depth=depth,
        points=r.points,
        mask=r.mask,
    )


def iter_samples(scene: ShipTankScene, workers: int = 2) -> Iterator[SceneSample]:
    """All frames in order. ``workers`` > 1 renders a few frames ahead in threads (Embree and most
    numpy work release the GIL); the output does not depend on it."""
    n = len(scene.poses)
    if workers <= 1:
        for i in range(n):
            yield render_sample(scene, i)
        return
    ahead = 2 * workers  # bounded: at most this many rendered frames wait in memory
    with ThreadPoolExecutor(workers, thread_name_prefix="ship-tank") as pool:
        pending = deque(pool.submit(render_sample, scene, i) for i in range(min(ahead, n)))
        for i in range(n):
            sample = pending.popleft().result()
            if i + ahead < n:
                pending.append(pool.submit(render_sample, scene, i + ahead))
            yield sample


def iter_frames(
    cfg: ShipTankConfig | ShipTankScene, noisy: bool = True, pose: Literal["gt", "estimated"] = "gt"
) -> Iterator[RGBDFrame]:
    """The sequence as RGBDFrames (noisy sensor images by default), streamed."""
    scene = cfg if isinstance(cfg, ShipTankScene) else build_scene(cfg)
    for s in iter_samples(scene):
        yield s.frame(scene.intrinsics, noisy=noisy, pose=pose)


def observe(scene: ShipTankScene, samples: Iterable[SceneSample] | None = None) -> ObservedSurface:
    """Voxels the trajectory's range-limited depth saw (a depth-only pass unless samples are given)."""
    cfg = scene.cfg
    obs = ObservedSurface(cfg.coverage_voxel)
    if samples is None:
        for T in scene.poses:
            depth, points, _ = scene.renderer.depth(scene.intrinsics, T)
            obs.add(observed_points(depth, points, cfg.depth_min, cfg.depth_max))
    else:
        for s in samples:
            obs.add(observed_points(s.depth_gt, s.points, cfg.depth_min, cfg.depth_max))
    return obs


def novel_views(scene: ShipTankScene, observed: ObservedSurface | None = None) -> list[NovelView]:
    obs = observed if observed is not None else observe(scene)
    return select_novel_views(
        scene.cfg, scene.layout, scene.renderer, scene.intrinsics, obs, scene.poses[:, :3, 3]
    )


def render_view(scene: ShipTankScene, T_world_cam: npt.ArrayLike) -> RenderResult:
    return scene.renderer.render(scene.intrinsics, T_world_cam, grayscale=scene.cfg.grayscale)


def mesh_albedo_srgb(scene: ShipTankScene) -> npt.NDArray[np.float64]:
    """Per-vertex albedo [V, 3] in sRGB 0..1 (detail finer than the mesh edge faded out)."""
    m = scene.mesh
    mat = np.zeros(len(m.vertices), np.uint8)
    mat[m.triangles.ravel()] = np.repeat(m.material, 3)
    albedo = scene.renderer.appearance.albedo(
        m.vertices, m.vertex_normals, mat, scene.cfg.mesh_edge / 2
    )
    return linear_to_srgb(albedo)


def _clear_previous_scene(out: Path) -> None:
    """Remove what an earlier generation wrote here (it has a scene.json), so no stale view remains.

    A folder holding anything else is left alone and refused: generation never deletes user files.
    """
    import shutil

    if not out.exists() or not any(out.iterdir()):
        return
    if not (out / "scene.json").is_file():
        raise FileExistsError(
            f"{out} is not empty and holds no earlier scene (scene.json); choose an empty folder"
        )
    for name in ("tum", "gt", "novel"):
        shutil.rmtree(out / name, ignore_errors=True)
    for name in ("log.mcap", "scene.json"):
        (out / name).unlink(missing_ok=True)


def generate_ship_tank(
    cfg: ShipTankConfig,
    out_dir: str | Path,
    write_mcap: Callable[[Path, Iterable[RGBDFrame]], object] | None = None,
) -> SceneInfo:
    """Write the whole dataset folder (layout in the module docstring); returns what was written."""
    import open3d as o3d

    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.base import write_color, write_depth_png
    from gsfix_online.sources.tum import write_intrinsics_json, write_pose_list, write_tum

    out = Path(out_dir)
    _clear_previous_scene(out)
    timings: dict[str, float] = {}
    t_start = t = time.perf_counter()

    # 1. Scene
    scene = build_scene(cfg)
    cfg = scene.cfg
    intr = scene.intrinsics
    timings["build"] = time.perf_counter() - t
    logger.info(
        "ship tank: %d triangles, %d frames at %dx%d",
        scene.mesh.n_triangles,
        cfg.n_frames,
        cfg.width,
        cfg.height,
    )

    # 2. Trajectory frames: each rendered once; GT images written and observed voxels collected on the way
    t = time.perf_counter()
    obs = ObservedSurface(cfg.coverage_voxel)

    def frames() -> Iterator[RGBDFrame]:
        for s in iter_samples(scene):
            write_color(out / "gt" / "color" / f"{s.index:06d}.png", s.color_gt)
            write_depth_png(
                out / "gt" / "depth" / f"{s.index:06d}.png", _fit_png(s.depth_gt), DEPTH_SCALE
            )
            obs.add(observed_points(s.depth_gt, s.points, cfg.depth_min, cfg.depth_max))
            yield s.frame(intr, noisy=True, pose="gt")

    n_frames = write_tum(
        out / "tum", frames(), depth_scale=DEPTH_SCALE, pose_file="groundtruth.txt"
    )
    if scene.has_estimate:
        write_pose_list(
            out / "tum" / "estimated.txt",
            scene.stamps_ns.tolist(),
            scene.poses_est,
            "estimated (VIO-like drift): timestamp tx ty tz qx qy qz qw",
        )
    timings["frames"] = time.perf_counter() - t

    # 3. Novel views
    t = time.perf_counter()
    views = novel_views(scene, obs)
    novel = out / "novel"
    write_pose_list(
        novel / "views.txt",
        [cfg.stamp_ns(i) for i in range(len(views))],
        [v.T_world_cam for v in views],
        "novel views: timestamp tx ty tz qx qy qz qw",
    )
    for k, v in enumerate(views):
        r = render_view(scene, v.T_world_cam)
        write_color(novel / "color" / f"{k:03d}.png", r.color)
        write_depth_png(novel / "depth" / f"{k:03d}.png", _fit_png(r.depth), DEPTH_SCALE)
    write_intrinsics_json(novel / "intrinsics.json", intr, DEPTH_SCALE)
    timings["novel"] = time.perf_counter() - t

    # 4. Ground-truth mesh
    t = time.perf_counter()
    mesh_path = out / "gt" / "mesh.ply"
    mesh_path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(
        str(mesh_path), scene.mesh.to_open3d(mesh_albedo_srgb(scene)), write_ascii=False
    ):
        raise OSError(f"cannot write {mesh_path}")
    timings["mesh"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start

    # 5. Optional MCAP log: the written TUM frames read back with the estimated poses (no re-render)
    mcap_path = None
    if write_mcap is not None:
        t = time.perf_counter()
        mcap_path = out / "log.mcap"
        pose_file = "estimated.txt" if scene.has_estimate else "groundtruth.txt"
        write_mcap(
            mcap_path,
            iter(open_source(SourceConfig(format="tum", pose_file=pose_file), out / "tum")),
        )
        timings["mcap"] = time.perf_counter() - t

    # 6. Description
    info = SceneInfo(
        out_dir=out,
        scene_json=out / "scene.json",
        tum_dir=out / "tum",
        gt_mesh=mesh_path,
        gt_dir=out / "gt",
        novel_dir=novel,
        mcap=mcap_path,
        n_frames=n_frames,
        n_triangles=scene.mesh.n_triangles,
        n_novel=len(views),
        novel_coverage=[v.coverage for v in views],
        timings_s=timings,
    )
    _write_scene_json(info, scene, views, len(obs))
    logger.info("ship tank written to %s in %.1f s", out, timings["total"])
    return info


def _fit_png(depth: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Depths beyond what a 16-bit PNG at 5000 / m holds (13.1 m) become 0 (invalid)."""
    return np.where(depth * DEPTH_SCALE > 65535, 0.0, depth).astype(np.float32)


def _write_scene_json(
    info: SceneInfo, scene: ShipTankScene, views: list[NovelView], n_voxels: int
) -> None:
    cfg, intr = scene.cfg, scene.intrinsics
    data = {
        "generator": "gsfix_online.scene.generate_ship_tank",
        "seed": cfg.seed,
        "config": to_dict(cfg),
        "conventions": {
            "world": "x along the tank, y across, z up; metres; origin at a floor corner",
            "poses": "T_world_cam camera-to-world, OpenCV camera axes (x right, y down, z forward)",
            "depth": "metres along the optical axis; PNG 16-bit at 5000 per metre, 0 = invalid",
            "stamps": "stamp_ns = 1_700_000_000 s + i / fps",
        },
        "intrinsics": dataclasses.asdict(intr),
        "depth_scale": DEPTH_SCALE,
        "counts": {
            "frames": info.n_frames,
            "triangles": scene.mesh.n_triangles,
            "vertices": len(scene.mesh.vertices),
            "novel_views": len(views),
            "observed_voxels": n_voxels,
        },
        "layout": asdict(scene.layout),
        "novel_views": [
            {"index": k, "kind": v.kind, "coverage": v.coverage} for k, v in enumerate(views)
        ],
        "has_estimated_poses": scene.has_estimate,
        "timings_s": info.timings_s,
    }
    info.scene_json.parent.mkdir(parents=True, exist_ok=True)
    info.scene_json.write_text(json.dumps(data, indent=2))
