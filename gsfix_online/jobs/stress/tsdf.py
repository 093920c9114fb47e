"""Stress properties of TSDF integration (Open3D VoxelBlockGrid, :mod:`gsfix_online.mapping.tsdf`).

``tsdf.plane``: a tilted plane seen at 1 mm to 1 km (depth range and voxel size chosen to
include it, or not), with holes, NaN and inf pixels, extreme intrinsics and a pose up to 10 km
from the origin, integrated twice. Counts add up to the pixels; every observed voxel is finite
with |sdf| <= the truncation and weight in (0, 2]; the mesh is finite and lies on the plane
within a voxel plus the float32 rounding of coordinates 10 km out.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import strategies as st

from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.jobs.stress import Property
from gsfix_online.jobs.stress.strategies import log_uniform, poses

F32_EPS = float(np.finfo(np.float32).eps)


@st.composite
def _plane_case(draw: st.DrawFn) -> dict[str, Any]:
    w, h = draw(st.integers(4, 16)), draw(st.integers(4, 12))
    fx = draw(log_uniform(0.5, 1e4))
    fy = draw(st.one_of(st.just(fx), log_uniform(0.5, 1e4)))
    K = Intrinsics(fx, fy, w / 2, h / 2, w, h)
    d0 = draw(log_uniform(1e-3, 1e3))
    tilt = draw(st.floats(-0.5, 0.5))  # depth changes by d0 * tilt across the image
    u = np.arange(w)[None, :]  # depth images have pixel centres at integers (scene/render.py)
    # the plane z - tilt x = d0: depth d0 / (1 - tilt x_n) at x_n = (u - cx) / fx; rays that
    # meet it behind the camera or at a grazing angle see nothing (depth 0)
    denom = np.broadcast_to(1.0 - tilt * (u - K.cx) / K.fx, (h, w))
    depth = np.where(denom > 0.05, d0 / np.maximum(denom, 0.05), 0.0)
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    bad = rng.random((h, w))
    depth = np.where(bad < 0.05, 0.0, depth)
    depth = np.where((bad >= 0.05) & (bad < 0.08), np.nan, depth)
    depth = np.where((bad >= 0.08) & (bad < 0.1), np.inf, depth).astype(np.float32)
    voxel = draw(log_uniform(0.002, 1.0))
    depth_max = draw(log_uniform(0.05, 100.0))
    depth_min = draw(st.one_of(st.just(0.0), st.floats(0.0, depth_max * 0.99)))
    return {
        "K": K, "depth": depth, "T": draw(poses()), "d0": d0, "tilt": tilt,
        "voxel": voxel, "depth_min": depth_min, "depth_max": depth_max,
    }  # fmt: skip


def check_tsdf_plane(ex: dict[str, Any]) -> None:
    """Integrating a plane twice: counts, finite voxels, bounded sdf and weights, mesh on it."""
    from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume

    K: Intrinsics = ex["K"]
    cfg = TsdfConfig(
        voxel_size=ex["voxel"], depth_min=ex["depth_min"], depth_max=ex["depth_max"],
        block_resolution=8, block_count=64, max_blocks=200_000, device="CPU:0",
        mesh_weight_threshold=1.0, weight_max=64.0,
    )  # fmt: skip
    vol = TsdfVolume(cfg)
    color = np.full((K.height, K.width, 3), 200, np.uint8)
    frame = make_frame(color, ex["depth"], K, ex["T"], 1)
    for _ in range(2):
        res = vol.integrate(frame)
        assert res.valid_pixels + res.invalid.total == K.width * K.height, f"counts {res}"
    vox = vol.voxels()
    for name, arr in (("points", vox.points_m), ("sdf", vox.sdf_m), ("weight", vox.weight)):
        assert np.isfinite(arr).all(), f"non-finite voxel {name}"
    trunc = cfg.sdf_trunc
    assert (np.abs(vox.sdf_m) <= trunc * (1 + 1e-5)).all(), "|sdf| above the truncation"
    assert ((vox.weight > 0) & (vox.weight <= 2 + 1e-6)).all(), "weights outside (0, 2]"
    mesh = vol.extract_mesh()
    if not len(mesh.vertices):
        return
    assert np.isfinite(mesh.vertices).all(), "non-finite mesh vertices"
    T = ex["T"]
    p = (mesh.vertices.astype(np.float64) - T[:3, 3]) @ T[:3, :3]  # world -> camera
    n = np.array([-ex["tilt"], 0.0, 1.0])  # the plane z - tilt x = d0, camera frame
    dist = np.abs(p @ n - ex["d0"]) / np.linalg.norm(n)
    rounding = 8 * F32_EPS * float(np.abs(T[:3, 3]).max() + ex["d0"])  # Open3D works in float32
    # a voxel takes the depth of the pixel it projects into (nearest): on a tilted plane that
    # is off by up to half the depth step between neighbouring pixels
    d = np.where(np.isfinite(ex["depth"]), ex["depth"], 0.0).astype(np.float64)
    step = np.abs(np.diff(d, axis=1))[(d[:, 1:] > 0) & (d[:, :-1] > 0)]
    limit = 1.5 * ex["voxel"] + rounding + 0.5 * float(step.max() if step.size else 0.0)
    assert float(dist.max()) <= limit, (
        f"mesh vertex {float(dist.max()):.4g} m off the plane (voxel {ex['voxel']:.4g} m, "
        f"allowed {limit:.4g} m)"
    )


PROPERTIES = [
    Property(
        "tsdf.plane",
        "a plane 1 mm to 1 km away, 10 km out: finite voxels, bounded sdf, mesh on the plane",
        _plane_case,
        check_tsdf_plane,
        ci_examples=12,
    ),
]
