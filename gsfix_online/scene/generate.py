"""Build a synthetic scene (ship tank or room), stream its frames, and write the dataset folder.

In memory: ``build_scene(cfg)`` -> :class:`ShipTankScene`; ``iter_samples(scene)`` renders each
frame once and yields the noise-free and the degraded version together; ``iter_frames(cfg)``
yields plain :class:`RGBDFrame` objects. On disk: ``generate_ship_tank(cfg, out_dir)`` writes::

    scene.json            parameters, intrinsics, counts, novel-view coverage, inputs, timings
    tum/                  degraded input sequence (groundtruth.txt exact; estimated.txt when drift/noise is on)
    gt/mesh.ply           ground-truth mesh, vertex colours = albedo (sRGB)
    gt/color|depth/NNNNNN.png   noise-free training images at nominal exposure (depth 16-bit, 5000 / m)
    gt/exposure.txt       only when the exposure or white balance varies: ``timestamp gain r g b``
    novel/views.txt       novel camera poses (TUM pose list) in the frame of the poses the system should
                          use (below; see in_estimated_frame), novel/color|depth/NNN.png, novel/intrinsics.json
    novel/views_groundtruth.txt   only with estimated poses: the novel views' exact poses
    log.mcap              only with ``write_mcap``: the TUM frames with the poses the system should use
    replica/              only with ``replica=True``: the same frames in the Replica (NICE-SLAM) layout,
                          traj.txt = the poses the system should use, traj_groundtruth.txt = exact

"The poses the system should use" are the estimated ones when drift or jitter is on, else the
exact ones; ``scene.json["inputs"]`` names them. Scoring always uses ``tum/groundtruth.txt``,
``gt/`` and ``novel/``.
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

from gsfix_online.core.config import ConfigError, build, to_dict
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.scene.appearance import Appearance, linear_to_srgb
from gsfix_online.scene.camera_effects import (
    blur_sample_count,
    exposure_gains,
    image_motion,
    motion_blur,
    shutter_ends,
    white_balance_gains,
)
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.scene.geometry import TankLayout, TankMesh, build_tank
from gsfix_online.scene.render import LightRig, Renderer, RenderResult, display
from gsfix_online.scene.room import RoomLayout
from gsfix_online.scene.sensor import (
    drift_poses,
    noisy_depth,
    noisy_image,
    stereo_occlusion,
    surface_dropout,
)
from gsfix_online.scene.trajectory import (
    NovelView,
    ObservedSurface,
    camera_poses,
    check_clearance,
    observed_points,
    select_novel_views,
)

logger = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # depth PNG units per metre (TUM)
_FRAME_STREAM, _DRIFT_STREAM = 0xF4A3E, 0xD41F7  # rng stream tags mixed with the seed
_EXPOSURE_STREAM, _SURFACE_STREAM, _WB_STREAM = 0xE7905, 0x5DF0C, 0xA3B17
LUMA = np.array([0.299, 0.587, 0.114], np.float32)  # display-value brightness for dark dropouts
REPLICA_MAX_DEPTH = 65535 / 6553.5  # m, what Replica's 16-bit depth holds
WORLD = {
    "tank": "x along the tank, y across, z up; metres; origin at a floor corner",
    "room": "x along the room, y across, z up; metres; origin at a floor corner",
}


@dataclass
class ShipTankScene:
    """Everything needed to render the sequence (any family); built once, cheap to keep."""

    cfg: ShipTankConfig
    layout: TankLayout | RoomLayout
    mesh: TankMesh
    renderer: Renderer
    intrinsics: Intrinsics
    poses: npt.NDArray[np.float64]  # [N, 4, 4] exact T_world_cam
    # [N, 4, 4] VIO-like estimate (equal to poses when drift and noise are off)
    poses_est: npt.NDArray[np.float64]
    stamps_ns: npt.NDArray[np.int64]  # [N]
    exposure_gains: npt.NDArray[np.float64] | None = None  # [N] auto-exposure gain; None = all 1
    white_balance: npt.NDArray[np.float64] | None = None  # [N, 3] per-channel gain; None = all 1

    @property
    def has_estimate(self) -> bool:
        c = self.cfg
        return c.pose_drift > 0 or c.pose_noise > 0 or c.pose_noise_deg > 0

    @property
    def input_pose_file(self) -> str:
        """The TUM pose list the system should be fed (the estimate when there is one)."""
        return "estimated.txt" if self.has_estimate else "groundtruth.txt"


@dataclass
class SceneSample:
    """One trajectory frame, rendered once: noise-free ground truth and the noisy sensor view."""

    index: int
    stamp_ns: int
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] exact
    T_world_cam_est: npt.NDArray[np.float64]  # [4, 4] estimate
    color_gt: npt.NDArray[np.uint8]  # [H, W, 3] or [H, W], nominal exposure, sharp, noise free
    depth_gt: npt.NDArray[np.float32]  # [H, W] m, every hit (no range limit)
    color: npt.NDArray[np.uint8]  # exposure gain, motion blur and noise applied
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
    replica: Path | None = None


def checked(cfg: ShipTankConfig) -> ShipTankConfig:
    """``cfg`` re-validated through the config machinery (ranges, literals, cross-field rules)."""
    if not isinstance(cfg, ShipTankConfig):
        raise ConfigError(f"expected a ShipTankConfig, got {type(cfg).__name__}")
    return build(ShipTankConfig, base=to_dict(cfg))


def build_scene(cfg: ShipTankConfig) -> ShipTankScene:
    """Mesh, renderer, camera and poses for ``cfg``; raises ConfigError / SceneLayoutError on bad input."""
    # 1. The family's mesh, appearance, lights and path
    cfg = checked(cfg)
    if cfg.family == "room":
        from gsfix_online.scene.room import ROOM_AMBIENT, ROOM_LAMP_POWER, build_room, room_poses
        from gsfix_online.scene.room_appearance import RoomAppearance

        mesh = build_room(cfg)
        lay = mesh.layout
        assert isinstance(lay, RoomLayout)
        power = cfg.light_power * (ROOM_LAMP_POWER if cfg.lighting == "lamps" else 1.0)
        lights = LightRig(cfg.lighting, cfg.ambient * ROOM_AMBIENT, lay.lamps, power)
        renderer = Renderer(mesh, RoomAppearance(cfg.seed, lay), lights)
        poses = room_poses(cfg, lay)
    else:
        mesh = build_tank(cfg)
        lay = mesh.layout
        assert lay is not None
        lights = LightRig(
            mode=cfg.lighting, ambient=cfg.ambient, lamps=lay.lamps, power=cfg.light_power
        )
        renderer = Renderer(mesh, Appearance(cfg.seed, lay), lights)
        poses = camera_poses(cfg, lay)
    check_clearance(renderer, lay, poses[:, :3, 3], cfg.clearance, "trajectory")
    # 2. Pose estimate and exposure gains, each from its own rng stream
    rng = np.random.default_rng([cfg.seed, _DRIFT_STREAM])
    est = drift_poses(poses, cfg.pose_drift, cfg.pose_noise, cfg.pose_noise_deg, rng)
    stamps = np.array([cfg.stamp_ns(i) for i in range(cfg.n_frames)], np.int64)
    gains = None
    if cfg.exposure_varies:
        gains = exposure_gains(
            cfg.n_frames,
            cfg.fps,
            cfg.exposure_gain_min,
            cfg.exposure_gain_max,
            cfg.exposure_smooth_s,
            cfg.exposure_step_prob,
            np.random.default_rng([cfg.seed, _EXPOSURE_STREAM]),
        )
    wb = None
    if cfg.white_balance_varies:
        rng = np.random.default_rng([cfg.seed, _WB_STREAM])
        wb = white_balance_gains(
            cfg.n_frames, cfg.fps, cfg.white_balance_sigma, cfg.exposure_smooth_s, rng
        )
    return ShipTankScene(cfg, lay, mesh, renderer, cfg.intrinsics, poses, est, stamps, gains, wb)


def sensor_light(scene: ShipTankScene, i: int, r: RenderResult) -> npt.NDArray[np.float32]:
    """Display values (0..255, before noise and rounding) of frame ``i`` as the colour sensor sees
    it: motion blur over the shutter, the exposure gain and the white balance, all on linear
    light; ``r.color_f`` itself when none applies."""
    cfg = scene.cfg
    gain = 1.0 if scene.exposure_gains is None else float(scene.exposure_gains[i])
    wb = None if scene.white_balance is None else scene.white_balance[i].astype(np.float32)
    rad = r.radiance
    moved = False
    if cfg.shutter_s > 0:
        ends = shutter_ends(scene.poses, i, cfg.shutter_s * cfg.fps)
        flows = image_motion(r.points, r.mask, scene.intrinsics, scene.poses[i], ends)
        moved = bool(flows.any())
        if moved:
            n = cfg.blur_samples or blur_sample_count(flows, r.mask)
            rad = motion_blur(rad, flows[0], flows[1], n)
    if gain == 1.0 and wb is None and not moved:
        return r.color_f
    if gain != 1.0:
        rad = rad * np.float32(gain)
    if wb is not None:
        rad = rad * wb
    return display(rad)


def _surface_loss(scene: ShipTankScene, i: int, r: RenderResult) -> npt.NDArray[np.bool_]:  # [H, W]
    """Depth lost at grazing incidence and on dark surfaces (its own rng stream per frame)."""
    cfg = scene.cfg
    rays = r.points - scene.poses[i][:3, 3]
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("hwc,hwc->hw", rays, r.normals.astype(np.float64))).astype(np.float32)
    bright = r.color_f if r.color_f.ndim == 2 else r.color_f @ LUMA
    rng = np.random.default_rng([cfg.seed, _SURFACE_STREAM, i])
    lost = surface_dropout(
        cos, bright, cfg.depth_grazing_deg, cfg.depth_dark_level, cfg.dropout_blob_px, rng
    )
    return lost & r.mask


def render_sample(scene: ShipTankScene, i: int) -> SceneSample:
    """Frame ``i``: one render, then the camera effects and the sensor noise (each frame draws
    from its own rng streams, so frames can render in any order)."""
    cfg = scene.cfg
    r = scene.renderer.render(scene.intrinsics, scene.poses[i], grayscale=cfg.grayscale)
    rng = np.random.default_rng([cfg.seed, _FRAME_STREAM, i])
    color = noisy_image(sensor_light(scene, i, r), cfg.image_noise, rng)
    limits = (cfg.depth_min, cfg.depth_max)
    depth = noisy_depth(r.depth, cfg.depth_noise, cfg.dropout, cfg.dropout_blob_px, *limits, rng)
    if cfg.depth_grazing_deg < 90.0 or cfg.depth_dark_level > 0.0:
        depth[_surface_loss(scene, i, r)] = 0.0
    if cfg.stereo_baseline > 0.0:
        depth[stereo_occlusion(r.depth, scene.intrinsics.fx, cfg.stereo_baseline)] = 0.0
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
    keep_out = scene.layout.keep_out if isinstance(scene.layout, RoomLayout) else ()
    return select_novel_views(
        scene.cfg,
        scene.layout,
        scene.renderer,
        scene.intrinsics,
        obs,
        scene.poses[:, :3, 3],
        keep_out,
    )


def in_estimated_frame(
    views: npt.NDArray[np.float64],  # [V, 4, 4] exact T_world_cam
    poses: npt.NDArray[np.float64],  # [N, 4, 4] exact input poses
    poses_est: npt.NDArray[np.float64],  # [N, 4, 4] their estimate (what the map is built in)
) -> npt.NDArray[np.float64]:  # [V, 4, 4]
    """Each novel view in the frame of the estimated poses, as a planner on the robot would ask
    for it: placed relative to the nearest input frame (camera centres), whose estimate carries
    the drift of the map around it: ``T_est_i @ inv(T_i) @ T_view``. Identity without drift."""
    centres = poses[:, :3, 3]
    out = np.empty_like(views)
    for k, T in enumerate(views):
        i = int(np.argmin(np.linalg.norm(centres - T[:3, 3], axis=1)))
        out[k] = poses_est[i] @ np.linalg.inv(poses[i]) @ T
    return out


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
    for name in ("tum", "gt", "novel", "replica"):
        shutil.rmtree(out / name, ignore_errors=True)
    for name in ("log.mcap", "scene.json"):
        (out / name).unlink(missing_ok=True)


def generate_ship_tank(
    cfg: ShipTankConfig,
    out_dir: str | Path,
    write_mcap: Callable[[Path, Iterable[RGBDFrame]], object] | None = None,
    replica: bool = False,
) -> SceneInfo:
    """Write the whole dataset folder (layout in the module docstring) for any scene family;
    returns what was written. ``replica``: also write ``replica/`` (Replica / NICE-SLAM layout)."""
    import open3d as o3d

    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.base import ns_to_seconds, write_color, write_depth_png
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
        "%s: %d triangles, %d frames at %dx%d",
        cfg.family,
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
    if scene.exposure_gains is not None or scene.white_balance is not None:
        n = cfg.n_frames
        g = scene.exposure_gains if scene.exposure_gains is not None else np.ones(n)
        wb = scene.white_balance if scene.white_balance is not None else np.ones((n, 3))
        lines = [
            f"{ns_to_seconds(ns)} {gi:.6f} {c[0]:.6f} {c[1]:.6f} {c[2]:.6f}"
            for ns, gi, c in zip(scene.stamps_ns.tolist(), g, wb, strict=True)
        ]
        (out / "gt" / "exposure.txt").write_text(
            "# light gains of each input frame on linear RGB (gt/ images have all 1): "
            "timestamp exposure white_balance_r g b\n" + "\n".join(lines) + "\n"
        )
    timings["frames"] = time.perf_counter() - t

    # 3. Novel views
    t = time.perf_counter()
    views = novel_views(scene, obs)
    novel = out / "novel"
    stamps = [cfg.stamp_ns(i) for i in range(len(views))]
    exact = [v.T_world_cam for v in views]
    if scene.has_estimate:
        write_pose_list(novel / "views_groundtruth.txt", stamps, exact,
                        "novel views, exact: timestamp tx ty tz qx qy qz qw")  # fmt: skip
    write_pose_list(
        novel / "views.txt",
        stamps,
        list(in_estimated_frame(np.asarray(exact), scene.poses, scene.poses_est)),
        "novel views in the frame of the input poses: timestamp tx ty tz qx qy qz qw",
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

    # 5. Optional MCAP log and Replica folder: the written TUM frames read back with the poses
    #    the system should use (no re-render)
    pose_file = scene.input_pose_file

    def inputs() -> Iterator[RGBDFrame]:
        return iter(open_source(SourceConfig(format="tum", pose_file=pose_file), out / "tum"))

    mcap_path = None
    if write_mcap is not None:
        t = time.perf_counter()
        mcap_path = out / "log.mcap"
        write_mcap(mcap_path, inputs())
        timings["mcap"] = time.perf_counter() - t
    replica_path = None
    if replica:
        t = time.perf_counter()
        replica_path = out / "replica"
        _write_replica(replica_path, inputs(), scene)
        timings["replica"] = time.perf_counter() - t

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
        replica=replica_path,
    )
    _write_scene_json(info, scene, views, len(obs))
    logger.info("%s written to %s in %.1f s", cfg.family, out, timings["total"])
    return info


def _write_replica(root: Path, frames: Iterator[RGBDFrame], scene: ShipTankScene) -> None:
    """The frames in the Replica layout (PNG colour: lossless, the same pixels as tum/), depth
    beyond what Replica's 16-bit PNG holds dropped; exact poses beside them when they differ."""
    import dataclasses as dc

    from gsfix_online.sources.replica import write_replica

    def fit(f: RGBDFrame) -> RGBDFrame:
        if f.depth.max(initial=0.0) < REPLICA_MAX_DEPTH:
            return f
        return dc.replace(
            f, depth=np.where(f.depth < REPLICA_MAX_DEPTH, f.depth, 0.0).astype(np.float32)
        )

    write_replica(root, (fit(f) for f in frames), color_ext=".png")
    if scene.has_estimate:
        with (root / "traj_groundtruth.txt").open("w") as fh:
            for T in scene.poses:
                fh.write(" ".join(f"{v:.17g}" for v in T.ravel()) + "\n")


def _fit_png(depth: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Depths beyond what a 16-bit PNG at 5000 / m holds (13.1 m) become 0 (invalid)."""
    return np.where(depth * DEPTH_SCALE > 65535, 0.0, depth).astype(np.float32)


def _write_scene_json(
    info: SceneInfo, scene: ShipTankScene, views: list[NovelView], n_voxels: int
) -> None:
    cfg, intr = scene.cfg, scene.intrinsics
    inputs: dict[str, str] = {"tum": "tum", "tum_pose_file": scene.input_pose_file}
    if info.mcap is not None:
        inputs["mcap"] = info.mcap.name
    if info.replica is not None:
        inputs["replica"] = info.replica.name
    data = {
        "generator": "gsfix_online.scene.generate_ship_tank",
        "family": cfg.family,
        "seed": cfg.seed,
        "config": to_dict(cfg),
        "conventions": {
            "world": WORLD[cfg.family],
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
        # What to feed the system (poses it should use); scoring uses tum/groundtruth.txt and gt/.
        "inputs": inputs,
        "exposure_gain_range": (
            None
            if scene.exposure_gains is None
            else [float(scene.exposure_gains.min()), float(scene.exposure_gains.max())]
        ),
        "timings_s": info.timings_s,
    }
    info.scene_json.parent.mkdir(parents=True, exist_ok=True)
    info.scene_json.write_text(json.dumps(data, indent=2))
