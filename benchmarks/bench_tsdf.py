"""TSDF benchmark: our TsdfVolume against a bare Open3D loop, in the same run, interleaved.

For 640x480 and 320x240 ship-tank frames and voxel sizes of 1, 2 and 4 cm it measures:
integration ms/frame (ours and the bare ``compute_unique_block_coordinates`` + ``integrate`` loop,
alternating which goes first on each frame; medians), meshing time, ray casting ms/frame with
the mesh renderer (RaycastingScene) and with ``VoxelBlockGrid.ray_cast`` on the same views, their
depth error against the noise-free depth, and peak memory (RSS above the start of the case,
sampled every 5 ms, both volumes together; memory freed by an earlier case is reused, so the
exact figure for ours is ``volume_mb_ours``: capacity x bytes per block).

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_tsdf.py

Scenes are generated into outputs/bench_tsdf/ on the first run (about a minute).
Writes benchmarks/results/tsdf_cpu.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c
import psutil

from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume, inverse_pose
from gsfix_online.runtime.wire import frame_to_message
from gsfix_online.sources import SourceConfig, open_source

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # nodes/ (a top-level package)
from gsfix_online.services.tsdf import Params, TsdfService  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZES = {"640x480": (640, 480), "320x240": (320, 240)}
VOXELS = (0.01, 0.02, 0.04)
DEPTH_MAX = 5.0
TRUNC_VOXELS = 4.0


class PeakRss:
    """Samples this process's RSS in a thread; ``peak_mb`` above the value at start."""

    def __init__(self, period_s: float = 0.005) -> None:
        self.proc = psutil.Process()
        self.period_s = period_s
        self.base = self.peak = self.proc.memory_info().rss
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def __enter__(self) -> PeakRss:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)

    @property
    def peak_mb(self) -> float:
        return (self.peak - self.base) / 2**20


def ensure_scene(out: Path, width: int, height: int, n_frames: int) -> Path:
    if (out / "scene.json").is_file():
        return out
    cmd = [
        str(ROOT / ".venv/bin/gsfix-online"),
        "scene",
        "ship-tank",
        f"scene.width={width}",
        f"scene.height={height}",
        f"scene.n_frames={n_frames}",
        "--out",
        str(out),
        "--no-mcap",
        "--no-progress",
    ]
    subprocess.run(cmd, check=True)
    return out


class BareLoop:
    """What a user writes with Open3D alone (float depth in metres needs float colour)."""

    def __init__(self, voxel: float) -> None:
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            ("tsdf", "weight", "color"), (o3c.float32,) * 3, ((1), (1), (3)), voxel, 16, 1000
        )

    def integrate(self, f) -> None:  # noqa: ANN001
        depth = o3d.t.geometry.Image(o3c.Tensor(f.depth))
        color = o3d.t.geometry.Image(o3c.Tensor(f.color.astype(np.float32)))
        K = o3c.Tensor(f.intrinsics.K)
        E = o3c.Tensor(np.linalg.inv(f.T_world_cam))
        blocks = self.vbg.compute_unique_block_coordinates(
            depth, K, E, 1.0, DEPTH_MAX, TRUNC_VOXELS
        )
        self.vbg.integrate(blocks, depth, color, K, E, 1.0, DEPTH_MAX, TRUNC_VOXELS)


def vbg_ray_cast(vbg, f, depth_hint):  # noqa: ANN001, ANN201
    """VoxelBlockGrid.ray_cast over the blocks of the view's frustum (from a depth image)."""
    K = o3c.Tensor(f.intrinsics.K)
    E = o3c.Tensor(inverse_pose(f.T_world_cam))
    blocks = vbg.compute_unique_block_coordinates(
        o3d.t.geometry.Image(o3c.Tensor(depth_hint)), K, E, 1.0, DEPTH_MAX, TRUNC_VOXELS
    )
    k = f.intrinsics
    out = vbg.ray_cast(
        blocks, K, E, k.width, k.height, ["depth", "color"], 1.0, 0.1, DEPTH_MAX, 3.0, TRUNC_VOXELS
    )
    return out["depth"].numpy()[..., 0]


def bench_case(frames, gt_depths, voxel: float, n_views: int) -> dict[str, object]:
    cfg = TsdfConfig(
        voxel_size=voxel, depth_max=DEPTH_MAX, trunc_voxels=TRUNC_VOXELS, device="CPU:0"
    )
    ours, bare = TsdfVolume(cfg), BareLoop(voxel)
    # The node's handler as it runs on a received message (message -> frame validation ->
    # integrate; wire decoding is the transport benchmark's), with periodic meshing off (timed
    # separately as mesh_s).
    node = TsdfService("bench", Params(tsdf=cfg, write_periodic=False))
    msgs = [frame_to_message(f, "rgbd/bench") for f in frames]
    t_ours, t_bare, t_node = [], [], []
    with PeakRss() as mem:
        for i, f in enumerate(frames):
            calls = [
                (t_ours, lambda f=f: ours.integrate(f)),
                (t_bare, lambda f=f: bare.integrate(f)),
                (t_node, lambda i=i: node.on_rgbd(msgs[i])),
            ]
            for times, fn in calls[i % 3 :] + calls[: i % 3]:  # rotate the order
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
        mesh_s = []
        for _ in range(3):
            t0 = time.perf_counter()
            mesh = ours.extract_mesh()
            mesh_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        renderer = MeshRenderer(mesh)
        bvh_s = time.perf_counter() - t0
        views = np.linspace(0, len(frames) - 1, n_views).round().astype(int)
        rc_mesh, rc_vbg, err_mesh, err_vbg = [], [], [], []
        for v in views:
            f, gt = frames[v], gt_depths[v]
            t0 = time.perf_counter()
            r = renderer.render(f.T_world_cam, f.intrinsics)
            rc_mesh.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            d_vbg = vbg_ray_cast(bare.vbg, f, r.depth_m)
            rc_vbg.append(time.perf_counter() - t0)
            both = (r.depth_m > 0) & (d_vbg > 0) & (gt > 0) & (gt <= DEPTH_MAX)
            err_mesh.append(np.abs(r.depth_m[both] - gt[both]).mean())
            err_vbg.append(np.abs(d_vbg[both] - gt[both]).mean())
    warm = slice(min(5, len(frames) // 4), None)  # first frames allocate most blocks
    o, b = np.median(t_ours[warm]), np.median(t_bare[warm])
    ratios = np.array(t_ours[warm]) / np.array(t_bare[warm])
    return {
        "voxel_m": voxel,
        "frames": len(frames),
        "integrate_ms_ours": 1e3 * float(o),
        "integrate_ms_bare": 1e3 * float(b),
        "overhead": float(o / b) - 1.0,
        "overhead_per_frame_median": float(np.median(ratios)) - 1.0,
        "integrate_ms_node": 1e3 * float(np.median(t_node[warm])),
        "overhead_node": float(np.median(t_node[warm]) / b) - 1.0,
        # Means include periodic work (the weight cap every few frames) that medians hide.
        "integrate_ms_ours_mean": 1e3 * float(np.mean(t_ours[warm])),
        "integrate_ms_bare_mean": 1e3 * float(np.mean(t_bare[warm])),
        "overhead_mean": float(np.mean(t_ours[warm]) / np.mean(t_bare[warm])) - 1.0,
        "integrate_ms_ours_all_frames": 1e3 * float(np.median(t_ours)),
        "blocks": ours.n_blocks,
        "volume_mb_ours": ours.capacity * cfg.block_bytes / 2**20,
        "peak_rss_mb_both": mem.peak_mb,  # growth in this case; freed memory is reused
        "peak_rss_mb_process": mem.peak / 2**20,
        "mesh_s": float(np.median(mesh_s)),
        "triangles": mesh.n_triangles,
        "bvh_build_s": bvh_s,
        "raycast_ms_mesh": 1e3 * float(np.median(rc_mesh)),
        "raycast_ms_vbg": 1e3 * float(np.median(rc_vbg)),
        "raycast_depth_mae_cm_mesh": 100 * float(np.mean(err_mesh)),
        "raycast_depth_mae_cm_vbg": 100 * float(np.mean(err_vbg)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="frames per case")
    ap.add_argument("--views", type=int, default=10, help="ray-cast views per case")
    ap.add_argument("--scenes", type=Path, default=ROOT / "outputs/bench_tsdf")
    ap.add_argument("--sizes", nargs="*", default=list(SIZES))
    ap.add_argument("--voxels", nargs="*", type=float, default=list(VOXELS))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/tsdf_cpu.json")
    args = ap.parse_args()
    t_start = time.perf_counter()
    results = []
    for size in args.sizes:
        w, h = SIZES[size]
        scene = ensure_scene(args.scenes / f"tank{w}", w, h, max(args.frames, 60))
        frames = list(open_source(SourceConfig(path=str(scene / "tum"))))[: args.frames]
        gt = [
            cv2.imread(str(scene / "gt/depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED).astype(
                np.float32
            )
            / 5000.0
            for i in range(len(frames))
        ]
        for voxel in args.voxels:
            row = {"size": size, **bench_case(frames, gt, voxel, args.views)}
            results.append(row)
            print(
                f"{size} {100 * voxel:g} cm: integrate ours {row['integrate_ms_ours']:.1f} ms, "
                f"bare {row['integrate_ms_bare']:.1f} ms (overhead {100 * row['overhead']:+.1f} %, "
                f"of means {100 * row['overhead_mean']:+.1f} %), node {row['integrate_ms_node']:.1f} ms "
                f"({100 * row['overhead_node']:+.1f} %), "
                f"mesh {row['mesh_s']:.2f} s, ray cast mesh {row['raycast_ms_mesh']:.1f} ms "
                f"vs vbg {row['raycast_ms_vbg']:.1f} ms, peak {row['peak_rss_mb_both']:.0f} MB",
                flush=True,
            )
    goal = next((r for r in results if r["size"] == "320x240" and r["voxel_m"] == 0.02), None)
    doc = {
        "benchmark": "bench_tsdf",
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": sys.version.split()[0],
            "open3d": o3d.__version__,
            "load_avg_at_end": os.getloadavg(),
        },
        "depth_max_m": DEPTH_MAX,
        "trunc_voxels": TRUNC_VOXELS,
        "results": results,
        "goals": {
            "overhead_le_10pct": all(r["overhead"] <= 0.10 for r in results),
            "node_overhead_le_10pct": all(r["overhead_node"] <= 0.10 for r in results),
            "overhead_of_means_le_10pct": all(r["overhead_mean"] <= 0.10 for r in results),
            "realtime_30hz_2cm_320x240": goal is not None
            and goal["integrate_ms_ours"] <= 1000 / 30,
        },
        "wall_s": time.perf_counter() - t_start,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2))
    print(f"goals: {doc['goals']} -> {args.out} ({doc['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
