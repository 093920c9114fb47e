"""Render a coloured mesh at any camera: colour, z-depth and a valid mask, by ray casting.

Open3D's ``RaycastingScene`` (Embree BVH) casts one ray per pixel centre. Rays leave the camera
centre through pixel (u, v) with camera-frame direction ``K^-1 [u, v, 1]`` (z = 1), so the hit
parameter ``t_hit`` is the z-depth in metres, not the distance along the ray. Colour is the
barycentric interpolation of the hit triangle's vertex colours. (``VoxelBlockGrid.ray_cast`` on
the TSDF was measured slower on CPU; see ``benchmarks/bench_tsdf.py``.)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import FrameError, Intrinsics, check_pose
from gsfix_online.mapping.mesh import TriMesh


@dataclass
class MeshRender:
    color: npt.NDArray[np.uint8]  # [H, W, 3] RGB, or [H, W] for a gray mesh; 0 where invalid
    depth_m: npt.NDArray[np.float32]  # [H, W] z-depth, metres; 0 where invalid
    valid: npt.NDArray[np.bool_]  # [H, W] a surface was hit

    def rgb(self) -> npt.NDArray[np.uint8]:  # [H, W, 3]
        """Colour as three channels (gray replicated), e.g. for a ``render_reply``."""
        if self.color.ndim == 3:
            return self.color
        return np.repeat(self.color[:, :, None], 3, axis=2)


# Ray origins and slopes are float32 in Open3D's ray caster: a pose or focal length that puts
# them beyond this is bad input (it would overflow to inf), not a view to render.
RAY_LIMIT = 1e30


@lru_cache(maxsize=8)
def camera_directions(intrinsics: Intrinsics) -> npt.NDArray[np.float32]:
    """[H, W, 3] ray directions in the camera frame with z = 1 (pixel-centre convention:
    pixel (u, v) is at integer coordinates, as for ``Intrinsics``)."""
    k = intrinsics
    u = (np.arange(k.width, dtype=np.float64) - k.cx) / k.fx
    v = (np.arange(k.height, dtype=np.float64) - k.cy) / k.fy
    slope = max(abs(u[0]), abs(u[-1]), abs(v[0]), abs(v[-1]))
    if not slope <= RAY_LIMIT:
        raise FrameError(
            f"intrinsics fx={k.fx} fy={k.fy} give ray slopes of {slope:.3g}, beyond the float32 ray caster's range"
        )
    d = np.empty((k.height, k.width, 3), np.float32)
    d[..., 0] = u[None, :]
    d[..., 1] = v[:, None]
    d[..., 2] = 1.0
    d.setflags(write=False)
    return d


def world_rays(
    T_world_cam: npt.NDArray[np.float64],  # [4, 4] camera-to-world, OpenCV axes
    intrinsics: Intrinsics,
) -> npt.NDArray[np.float32]:  # [H, W, 6] origin xyz, direction xyz (camera z component 1)
    reach = float(np.abs(T_world_cam[:3, 3]).max())
    if not reach <= RAY_LIMIT:
        raise FrameError(
            f"T_world_cam translation {reach:.3g} m is beyond the float32 ray caster's range"
        )
    d_cam = camera_directions(intrinsics)
    R = T_world_cam[:3, :3].astype(np.float32)
    rays = np.empty((intrinsics.height, intrinsics.width, 6), np.float32)
    rays[..., :3] = T_world_cam[:3, 3].astype(np.float32)
    rays[..., 3:] = d_cam @ R.T
    return rays


class MeshRenderer:
    """Ray caster over one :class:`TriMesh`; build once per mesh, render many views."""

    def __init__(self, mesh: TriMesh) -> None:
        import open3d as o3d
        import open3d.core as o3c

        self.mesh = mesh
        self._o3c = o3c
        self._scene = None
        if not mesh.is_empty:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(
                o3c.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
                o3c.Tensor(np.ascontiguousarray(mesh.triangles, np.uint32)),
            )

    def render(
        self,
        T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes
        intrinsics: Intrinsics,
    ) -> MeshRender:
        """Colour, z-depth and valid mask at ``T_world_cam``; raises FrameError on a bad pose."""
        T = check_pose(T_world_cam)
        if not isinstance(intrinsics, Intrinsics):
            raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
        h, w = intrinsics.height, intrinsics.width
        shape = (h, w) if self.mesh.gray else (h, w, 3)
        if self._scene is None:
            return MeshRender(
                np.zeros(shape, np.uint8), np.zeros((h, w), np.float32), np.zeros((h, w), bool)
            )
        # 1. Cast one ray per pixel.
        hits = self._scene.cast_rays(self._o3c.Tensor.from_numpy(world_rays(T, intrinsics)))
        t_hit = hits["t_hit"].numpy()
        valid = np.isfinite(t_hit)
        depth = np.where(valid, t_hit, 0.0).astype(np.float32)
        # 2. Interpolate vertex colours at the hits: p = (1-u-v) a + u b + v c.
        color = np.zeros((h, w, 3), np.uint8)
        if valid.any():
            prim = hits["primitive_ids"].numpy()[valid].astype(np.int64)
            uv = hits["primitive_uvs"].numpy()[valid]
            tri = self.mesh.triangles[prim]  # [n, 3]
            c = self.mesh.colors.astype(np.float32)
            wa = (1.0 - uv[:, 0] - uv[:, 1])[:, None]
            mixed = wa * c[tri[:, 0]] + uv[:, :1] * c[tri[:, 1]] + uv[:, 1:] * c[tri[:, 2]]
            color[valid] = np.clip(np.rint(mixed), 0, 255).astype(np.uint8)
        if self.mesh.gray:
            color = color[..., 0].copy()
        return MeshRender(color, depth, valid)
