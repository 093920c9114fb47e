"""Accuracy report of the TSDF mesh on a synthetic ship tank (``gsfix-online scene ship-tank``).

``gsfix-online report tsdf --scene DIR --out OUT`` fuses the scene's TUM sequence, extracts the
mesh and compares it with the ground truth:

- geometry against ``gt/mesh.ply``: points sampled uniformly on both meshes; accuracy (mean
  distance of reconstructed points to the ground truth), completeness (mean distance of ground
  truth points to the reconstruction), precision/recall/F-score at 2 cm and 5 cm. Completeness and
  recall are given twice: over the whole tank, and over the part the training views saw within
  ``depth_max`` (the path covers part of the tank by design).
- mesh renders at the training views (against ``gt/color|depth``) and at the novel views (against
  ``novel/color|depth``): PSNR over pixels both have, depth error (mean and median |d|), and the
  fraction of ground-truth pixels the render covers.

Writes ``OUT/tsdf_report.json``, ``OUT/mesh.ply``, ``OUT/mesh.glb`` and ``OUT/config.yaml``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng, write_config
from gsfix_online.core.io import atomic_write_text
from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import write_mesh
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume

logger = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # ship-tank depth PNGs, units per metre


@dataclass(frozen=True)
class ReportParams:
    points: int = field(
        default=300_000, metadata=rng(1000, 10_000_000, "points sampled on each mesh")
    )
    thresholds_m: list[float] = field(default_factory=lambda: [0.02, 0.05])  # F-score taus
    observed_radius_m: float = field(
        default=0.05, metadata=rng(0.001, 1.0, "gt points this close to a seen point count as seen")
    )
    view_stride: int = field(
        default=1, metadata=rng(1, 10_000, "evaluate renders at every n-th training view")
    )
    seed: int = 0


@dataclass(frozen=True)
class TsdfReportConfig:
    tsdf: TsdfConfig = field(default_factory=TsdfConfig)
    report: ReportParams = field(default_factory=ReportParams)


# --------------------------------------------------------------------------------------------
# Metrics (pure)
# --------------------------------------------------------------------------------------------


def nn_distances(
    src: npt.NDArray[np.float64],  # [N, 3]
    dst: npt.NDArray[np.float64],  # [M, 3]
) -> npt.NDArray[np.float64]:  # [N] distance of each src point to its nearest dst point
    from scipy.spatial import cKDTree

    if len(dst) == 0:
        return np.full(len(src), np.inf)
    return cKDTree(dst).query(src, k=1, workers=-1)[0]


def surface_metrics(
    d_rec_to_gt: npt.NDArray[np.float64],  # [N]
    d_gt_to_rec: npt.NDArray[np.float64],  # [M]
    thresholds_m: list[float],
) -> dict[str, float]:
    out = {
        "accuracy_cm": 100 * float(np.mean(d_rec_to_gt)) if len(d_rec_to_gt) else float("inf"),
        "completeness_cm": 100 * float(np.mean(d_gt_to_rec)),
    }
    for tau in thresholds_m:
        p = float(np.mean(d_rec_to_gt < tau)) if len(d_rec_to_gt) else 0.0
        r = float(np.mean(d_gt_to_rec < tau))
        cm = f"{round(100 * tau):g}cm"
        out[f"precision_{cm}"] = p
        out[f"recall_{cm}"] = r
        out[f"fscore_{cm}"] = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return out


def image_metrics(
    color: npt.NDArray[np.uint8],  # [H, W, 3] or [H, W] render
    depth_m: npt.NDArray[np.float32],  # [H, W] render, 0 = none
    gt_color: npt.NDArray[np.uint8],
    gt_depth_m: npt.NDArray[np.float32],  # [H, W] 0 = none
) -> dict[str, float]:
    both = (depth_m > 0) & (gt_depth_m > 0)
    n = int(both.sum())
    out = {"coverage": float(n / max(int((gt_depth_m > 0).sum()), 1)), "pixels": n}
    if n == 0:
        return out | {"psnr_db": float("nan"), "depth_mae_cm": float("nan")}
    mse = float(np.mean((color[both].astype(np.float64) - gt_color[both].astype(np.float64)) ** 2))
    err = np.abs(depth_m[both] - gt_depth_m[both])
    return out | {
        "psnr_db": 10 * np.log10(255.0**2 / max(mse, 1e-12)),
        "depth_mae_cm": 100 * float(err.mean()),
        "depth_median_cm": 100 * float(np.median(err)),
    }


def summarize(rows: list[dict[str, float]]) -> dict[str, float]:
    """Means over views (PSNR averaged in dB), plus the worst view's PSNR."""
    keys = ("psnr_db", "depth_mae_cm", "depth_median_cm", "coverage")
    out: dict[str, float] = {"views": len(rows)}
    for k in keys:
        vals = [r[k] for r in rows if k in r and np.isfinite(r[k])]
        out[k] = float(np.mean(vals)) if vals else float("nan")
    psnr = [r["psnr_db"] for r in rows if np.isfinite(r.get("psnr_db", np.nan))]
    out["psnr_db_min"] = float(min(psnr)) if psnr else float("nan")
    return out


# --------------------------------------------------------------------------------------------
# The job (reads the scene folder, writes the report)
# --------------------------------------------------------------------------------------------


def _read_gt(color_path: Path, depth_path: Path, gray: bool) -> tuple[np.ndarray, np.ndarray]:
    color = cv2.imread(str(color_path), cv2.IMREAD_UNCHANGED)
    if color.ndim == 3:
        color = cv2.cvtColor(color, cv2.COLOR_BGR2RGB)
    if gray and color.ndim == 3:
        color = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
    depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float32) / DEPTH_SCALE
    return color, depth


def _sample(mesh: Any, n: int, seed: int) -> npt.NDArray[np.float64]:
    import open3d as o3d

    o3d.utility.random.seed(seed)
    return np.asarray(mesh.sample_points_uniformly(n).points)


def observed_points(
    depths: list[npt.NDArray[np.float32]],
    poses: list[npt.NDArray[np.float64]],
    K: Intrinsics,
    depth_max: float,
    stride: int = 4,
) -> npt.NDArray[np.float64]:
    """World points of ground-truth depth within ``depth_max`` (every ``stride``-th pixel)."""
    v, u = np.mgrid[0 : K.height : stride, 0 : K.width : stride]
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
    pts = []
    for d, T in zip(depths, poses, strict=True):
        z = d[::stride, ::stride]
        ok = (z > 0) & (z <= depth_max)
        p_cam = rays[ok] * z[ok, None]
        pts.append(p_cam @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def run_report(
    cfg: TsdfReportConfig, scene_dir: Path, out_dir: Path, progress: bool = False
) -> dict[str, Any]:
    import open3d as o3d

    from gsfix_online.core.progress import track
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.tum import read_intrinsics_json, read_pose_list

    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    rp = cfg.report
    # 1. Fuse the input sequence.
    reader = open_source(SourceConfig(path=str(scene_dir / "tum")))
    vol = TsdfVolume(cfg.tsdf)
    poses, n_frames, gray = [], 0, False
    t0 = time.perf_counter()
    for frame in track(reader, "integrate", len(reader), "frame", enabled=progress):
        vol.integrate(frame)
        poses.append(frame.T_world_cam)
        gray = frame.is_gray
        K_train = frame.intrinsics
        n_frames += 1
    t_integrate = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = vol.extract_mesh()
    t_mesh = time.perf_counter() - t0
    for ext in ("ply", "glb"):
        write_mesh(mesh, out_dir / f"mesh.{ext}")
    # 2. Geometry against the ground-truth mesh.
    gt = o3d.io.read_triangle_mesh(str(scene_dir / "gt" / "mesh.ply"))
    gt_pts = _sample(gt, rp.points, rp.seed)
    rec_pts = _sample(mesh.to_legacy(), rp.points, rp.seed) if not mesh.is_empty else gt_pts[:0]
    d_rec = nn_distances(rec_pts, gt_pts)
    d_gt = nn_distances(gt_pts, rec_pts)
    train_gt = [
        _read_gt(
            scene_dir / "gt/color" / f"{i:06d}.png", scene_dir / "gt/depth" / f"{i:06d}.png", gray
        )
        for i in range(0, n_frames, rp.view_stride)
    ]
    train_poses = poses[:: rp.view_stride]
    seen = observed_points([d for _, d in train_gt], train_poses, K_train, cfg.tsdf.depth_max)
    observed = nn_distances(gt_pts, seen) < rp.observed_radius_m
    geometry = surface_metrics(d_rec, d_gt, rp.thresholds_m)
    geo_obs = surface_metrics(d_rec, d_gt[observed], rp.thresholds_m)
    geometry.update(
        {
            f"observed_{k}": v
            for k, v in geo_obs.items()
            if not k.startswith(("accuracy", "precision"))
        }
    )
    geometry["observed_fraction"] = float(observed.mean())
    # 3. Renders at the training and the novel views.
    renderer = MeshRenderer(mesh)
    train_rows = []
    for (color, depth), T in zip(train_gt, train_poses, strict=True):
        r = renderer.render(T, K_train)
        train_rows.append(image_metrics(r.color, r.depth_m, color, depth))
    K_novel, _ = read_intrinsics_json(scene_dir / "novel" / "intrinsics.json")
    novel_rows = []
    for i, T in enumerate(read_pose_list(scene_dir / "novel" / "views.txt").poses):
        color, depth = _read_gt(
            scene_dir / "novel/color" / f"{i:03d}.png",
            scene_dir / "novel/depth" / f"{i:03d}.png",
            gray,
        )
        r = renderer.render(T, K_novel)
        novel_rows.append(image_metrics(r.color, r.depth_m, color, depth) | {"view": i})
    report = {
        "scene": str(scene_dir),
        "frames": n_frames,
        "tsdf": {
            "voxel_size_m": cfg.tsdf.voxel_size,
            "sdf_trunc_m": cfg.tsdf.sdf_trunc,
            "depth_range_m": [cfg.tsdf.depth_min, cfg.tsdf.depth_max],
            "blocks": vol.n_blocks,
            "integrate_ms_per_frame": 1e3 * t_integrate / max(n_frames, 1),
            "mesh_s": t_mesh,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "invalid_depth": vol.stats()["invalid_depth"],
        },
        "geometry": geometry,
        "train_views": summarize(train_rows),
        "novel_views": summarize(novel_rows),
        "novel_per_view": novel_rows,
    }
    atomic_write_text(out_dir / "tsdf_report.json", json.dumps(report, indent=2))
    write_config(cfg, out_dir / "config.yaml")
    return report


def format_report(rep: dict[str, Any]) -> str:
    g, tr, nv = rep["geometry"], rep["train_views"], rep["novel_views"]
    return "\n".join(
        [
            f"frames {rep['frames']}, voxel {100 * rep['tsdf']['voxel_size_m']:g} cm, "
            f"{rep['tsdf']['triangles']} triangles",
            f"accuracy {g['accuracy_cm']:.2f} cm, completeness {g['completeness_cm']:.2f} cm "
            f"(observed part: {g['observed_completeness_cm']:.2f} cm)",
            f"F-score 2 cm {g['fscore_2cm']:.3f} (observed {g['observed_fscore_2cm']:.3f}), "
            f"5 cm {g['fscore_5cm']:.3f} (observed {g['observed_fscore_5cm']:.3f})",
            f"training views: PSNR {tr['psnr_db']:.2f} dB, depth MAE {tr['depth_mae_cm']:.2f} cm, "
            f"coverage {tr['coverage']:.3f}",
            f"novel views:    PSNR {nv['psnr_db']:.2f} dB, depth MAE {nv['depth_mae_cm']:.2f} cm, "
            f"coverage {nv['coverage']:.3f}",
        ]
    )


__all__ = ["ReportParams", "TsdfReportConfig", "format_report", "run_report"]
