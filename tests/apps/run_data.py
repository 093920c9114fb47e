"""A tiny run folder of ``gsfix-online repair``, written by the run's own writers.

Views go through :class:`~gsfix_online.repair.outputs.RepairOutputs` (metrics.json, view images,
report.html), the map through ``save_model`` and the mesh through ``write_mesh``: the same code
the writer node uses, at 32x24 pixels.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap, rgb_to_sh0
from gsfix_online.mapping.splat.ply import CameraEntry, save_model
from gsfix_online.repair.outputs import RepairOutputs

H, W = 24, 32
K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
N_GAUSSIANS = 40
N_REPAIRED = 10
SH_DEGREE = 1


def image(value: int, seed: int) -> np.ndarray:  # [H, W, 3] uint8
    rng = np.random.default_rng(seed)
    return np.clip(value + rng.integers(-20, 21, (H, W, 3)), 0, 255).astype(np.uint8)


def pose(x: float) -> np.ndarray:  # [4, 4] camera-to-world, looking down +z
    T = np.eye(4)
    T[0, 3] = x
    return T


def gaussian_map(seed: int = 0) -> GaussianMap:
    rng = np.random.default_rng(seed)
    n = N_GAUSSIANS
    means = rng.uniform([-0.5, -0.4, 1.5], [0.5, 0.4, 2.5], (n, 3))
    quats = rng.normal(size=(n, 4))
    rgb = rng.uniform(0.1, 0.9, (n, 1, 3))
    sh0 = rgb_to_sh0(torch.tensor(rgb, dtype=torch.float32))
    shN = rng.normal(0, 0.05, (n, 3, 3)).astype(np.float32)
    gmap = GaussianMap.from_tensors(
        means.astype(np.float32), np.full((n, 3), np.log(0.08), np.float32),
        quats.astype(np.float32), rng.normal(0, 1, n).astype(np.float32), sh0, shN,
        sh_degree=SH_DEGREE,
    )  # fmt: skip
    # the last N_REPAIRED grown from repaired views, never seen; the others seen 1-4 times
    gmap.origin[-N_REPAIRED:] = ORIGIN_REPAIRED
    gmap.observations[:-N_REPAIRED] = torch.from_numpy(rng.integers(1, 5, n - N_REPAIRED))
    return gmap


def box_mesh() -> TriMesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(1.0, 0.8, 0.2)
    m.translate((-0.5, -0.4, 2.0))
    v = np.asarray(m.vertices, np.float32)
    colors = np.clip(v * 100 + 128, 0, 255).astype(np.uint8)
    return TriMesh(v, np.asarray(m.triangles, np.int32), colors)


def make_run(root: Path, n_views: int = 3, maps: bool = True, gt: bool = True) -> Path:
    """A finished run in ``root/run``: view 1 skipped, the others repaired; with ``gt``, ground
    truth in ``root/gt`` and every stage scored (SSIM is the slow part on a busy machine)."""
    gt_dir = root / "gt"
    gt_dir.mkdir(parents=True, exist_ok=True)
    out = RepairOutputs(root / "run", gt_dir if gt else None)
    alpha = np.ones((H, W), np.float32)
    alpha[:, :8] = 0.0
    valid = np.ones((H, W), bool)
    valid[:4] = False
    for i in range(n_views):
        gt = image(100 + 10 * i, seed=i)
        cv2.imwrite(str(gt_dir / f"{i:03d}.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR))
        repair = i != 1
        cam = {"K": K.ravel().tolist(), "T_world_cam": pose(0.1 * i).ravel().tolist(),
               "width": W, "height": H}  # fmt: skip
        score = {"surface_fraction": 1.0, "hole_fraction": 0.25, "disagree_fraction": 0.0,
                 "underobserved_fraction": math.nan}  # fmt: skip
        reason = "holes 25%" if repair else "few holes (2%)"
        out.on_decision(i, repair, reason, score, cam, seconds=0.5 + i)
        out.on_renders(i, gs=image(90 + 10 * i, 10 + i), alpha=alpha, mesh=image(80, 20 + i),
                       valid=valid)  # fmt: skip
        if repair:
            timings = {"render_s": 0.2, "fix_s": 3.0 + i}
            out.on_fixed(i, image(100 + 10 * i, 30 + i), timings, {"version": 1, "step": 10})
            out.on_distilled(i, 1.5)
        out.on_final(i, image(98 + 10 * i, 40 + i))
    extra = {"timings_s": {"collect_s": 40.0, "final_s": 2.0}, "map": "map", "mesh": "mesh.ply"}
    out.write(extra)
    if maps:
        intr = Intrinsics.from_K(K, W, H)
        cams = [CameraEntry.from_pose(k, f"kf_{k:06d}", intr, pose(-0.1 * k)) for k in range(2)]
        save_model(out.out / "map", gaussian_map(), 7, cams)
        write_mesh(box_mesh(), out.out / "mesh.ply")
    return out.out
