"""A tiny finished run for the map server: a 3DGS model of a few hundred Gaussians on a box's
front face, the box as a TSDF-like mesh, metrics.json with two views (one with a fallback
choice in the summary) and their images, and a tiny GSFixer checkpoint in work/checkpoints.
cameras.json holds three input keyframes and a repaired view 1 m to the right.

Scene: the camera at the origin looks down +z (OpenCV axes); the box's front face is the plane
z = 2 m, spanning x in [-0.6, 0.6], y in [-0.45, 0.45]; the Gaussians lie on that plane.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gsfix_online.core.io import atomic_write_text
from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap, rgb_to_sh0
from gsfix_online.mapping.splat.ply import CameraEntry, camera_name, save_model
from gsfix_online.repair.outputs import write_png

W, H = 48, 32
K = np.array([[40.0, 0.0, (W - 1) / 2], [0.0, 40.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
FACE_Z_M = 2.0
N_GAUSSIANS = 300
REPAIRED_X_M = 0.25  # the face's Gaussians right of this grew from a repaired view
REPAIRED_CAMERA_X_M = 1.0  # where cameras.json's repaired view sits
REFERENCE_RGB = (30, 60, 220)  # the face's colour in the input keyframes' images (references)
FALLBACK = {
    "per_region": {"both": "fixed", "gs_only": "fixed", "mesh_only": "mesh_inpaint",
                   "neither": "mesh_inpaint"},
    "mse": {r: {"fixed": 1.0, "inpaint": 2.0, "mesh_inpaint": 3.0}
            for r in ("both", "gs_only", "mesh_only", "neither")},
    "pixels": {"both": 900, "gs_only": 100, "mesh_only": 20, "neither": 10},
    "samples": 1,
    "why": "test choice",
}  # fmt: skip


def pose(x_m: float = 0.0, y_m: float = 0.0) -> np.ndarray:  # [4, 4] camera-to-world
    T = np.eye(4)
    T[:2, 3] = (x_m, y_m)
    return T


def face_gaussians(n: int = N_GAUSSIANS, seed: int = 0) -> GaussianMap:
    """Gaussians on the box's front face (z = FACE_Z_M), a colour gradient left to right; those
    right of x = REPAIRED_X_M were grown from a repaired view."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-0.5, -0.35], [0.5, 0.35], (n, 2))
    means = np.column_stack([xy, np.full(n, FACE_Z_M)]).astype(np.float32)
    rgb = np.column_stack([0.2 + 0.6 * (xy[:, 0] + 0.5), np.full(n, 0.5), np.full(n, 0.3)])
    sh0 = rgb_to_sh0(torch.tensor(rgb[:, None, :], dtype=torch.float32))
    gmap = GaussianMap.from_tensors(
        means, np.full((n, 3), np.log(0.04), np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full(n, 2.0, np.float32), sh0,
        np.zeros((n, 0, 3), np.float32), sh_degree=0,
    )  # fmt: skip
    gmap.origin[torch.from_numpy(xy[:, 0] > REPAIRED_X_M)] = ORIGIN_REPAIRED
    return gmap


def box_mesh() -> TriMesh:
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.2, 0.9, 0.3)
    box.translate((-0.6, -0.45, FACE_Z_M))
    v = np.asarray(box.vertices, np.float32)
    colors = np.tile(np.uint8([200, 120, 40]), (len(v), 1))
    return TriMesh(v, np.asarray(box.triangles, np.int32), colors)


def tiny_checkpoint(root: Path) -> Path:
    from gsfix_online.fixer.checkpoint import save_checkpoint
    from gsfix_online.fixer.config import DefaultModelConfig, ModelConfig
    from gsfix_online.fixer.loader import load_fixer

    default = DefaultModelConfig(codec_factor=2, block_out_channels=(8, 16), norm_num_groups=4)
    model = ModelConfig(default=default, random_init=True)
    return save_checkpoint(root, load_fixer(model), 3, model)


def reference_frame(x_m: float) -> dict[str, np.ndarray]:
    """An input keyframe as the trainer keeps it (work/keyframes): at ``pose(x_m)``, the box's
    face in REFERENCE_RGB at its depth, no depth elsewhere."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    x = x_m + (u - K[0, 2]) / K[0, 0] * FACE_Z_M
    y = (v - K[1, 2]) / K[1, 1] * FACE_Z_M
    face = (np.abs(x) <= 0.6) & (np.abs(y) <= 0.45)
    color = np.zeros((H, W, 3), np.uint8)
    color[face] = REFERENCE_RGB
    return {"color": color, "depth": np.where(face, FACE_Z_M, 0.0).astype(np.float32),
            "K": K.copy(), "T_world_cam": pose(x_m)}  # fmt: skip


def make_served_run(
    root: Path,
    checkpoint: bool = True,
    summary: dict[str, Any] | None = None,
    references: bool = False,
) -> Path:
    """Write the run folder ``root/run`` (see the module docstring); returns its path.
    ``summary`` adds to metrics.json's summary (e.g. the held-out reach a newer run records);
    ``references`` writes the three input keyframes' images and depths (reference_frame)."""
    run = root / "run"
    intr = Intrinsics.from_K(K, W, H)
    cams = [CameraEntry.from_pose(k, camera_name(k, False), intr, pose(0.05 * k)) for k in range(3)]
    cams.append(CameraEntry.from_pose(3, camera_name(3, True), intr, pose(REPAIRED_CAMERA_X_M)))
    save_model(run / "map", face_gaussians(), 12, cams)
    write_mesh(box_mesh(), run / "mesh.ply")
    views = []
    for i in range(2):
        files = {}
        for j, name in enumerate(("gs", "output")):
            img = np.full((H, W, 3), 40 * (i + 1) + 20 * j, np.uint8)
            write_png(run / "views" / f"{i:03d}" / f"{name}.png", img)
            files[name] = f"views/{i:03d}/{name}.png"
        cam = {"K": K.ravel().tolist(), "T_world_cam": pose(0.1 * i, 0.02).ravel().tolist(),
               "width": W, "height": H}  # fmt: skip
        views.append({"view": f"{i:03d}", "view_id": i, "repair": i == 0,
                      "reason": "holes 20%" if i == 0 else "few holes", "camera": cam,
                      "files": files, "metrics": {}})  # fmt: skip
    metrics = {"summary": {"views": 2, "fallback": FALLBACK, **(summary or {})}, "views": views,
               "map": "map", "mesh": "mesh.ply"}  # fmt: skip
    atomic_write_text(run / "metrics.json", json.dumps(metrics))
    if checkpoint:
        tiny_checkpoint(run / "work" / "checkpoints")
    if references:
        (run / "work" / "keyframes").mkdir(parents=True, exist_ok=True)
        for k in range(3):
            np.savez(run / "work" / "keyframes" / f"kf_{k:08d}.npz", **reference_frame(0.05 * k))
    return run
