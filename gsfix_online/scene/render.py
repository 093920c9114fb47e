"""Ray-casting renderer for the scene meshes (Open3D ``RaycastingScene``, Embree on the CPU).

Cameras are pinhole ``Intrinsics`` with a camera-to-world ``T_world_cam`` in OpenCV axes (x right,
y down, z forward). Pixel (u, v) looks along ``R @ ((u - cx) / fx, (v - cy) / fy, 1)``; because that
direction has unit z in the camera, the hit parameter *is* the depth along the optical axis.

Shading is Lambertian: ``albedo * (ambient + sum of lights)``, then a highlight shoulder (no hard
clipping next to a lamp) and an sRGB-like gamma.
``lamps``: fixed point lamps with 1 / r^2 falloff and shadows from occlusion rays; the image of a
surface does not depend on the viewpoint. ``headlamp``: one light at the camera centre with a beam
falloff; it casts no visible shadows. Renders are noise free; ``sensor`` adds the noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import Intrinsics, check_pose
from gsfix_online.scene.appearance import Appearance
from gsfix_online.scene.geometry import TankLayout, TankMesh

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

LAMP_INTENSITY = 1.4  # irradiance 1 at ~1.2 m facing the lamp
HEADLAMP_INTENSITY = 1.6
LIGHT_R0_SQ = 0.04  # m^2 added to r^2 so that nothing right next to a light blows up
SHADOW_OFFSET = 2e-3  # m along the normal before casting a shadow ray
GRAY_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])  # linear luminance
KNEE = 0.6  # linear level above which highlights roll off instead of clipping


def tone_map(x: F32) -> F32:
    """Linear radiance -> 0..1: identity up to KNEE, then an exponential shoulder toward 1 (C1 smooth)."""
    x = np.maximum(x, 0.0)
    head = np.float32(1.0 - KNEE)
    shoulder = KNEE + head * (1.0 - np.exp(-(x - KNEE) / head))
    return np.where(x < KNEE, x, shoulder).astype(np.float32)


def display(radiance: F32) -> F32:
    """Linear radiance (any shape) -> display values 0..255 before rounding: tone curve, gamma."""
    return 255.0 * tone_map(radiance) ** np.float32(1.0 / 2.2)


class AlbedoModel(Protocol):
    """Surface colour at world points (tank: ``Appearance``, room: ``RoomAppearance``)."""

    def albedo(
        self,
        points: npt.NDArray[np.floating],  # [N, 3] world, m
        normals: npt.NDArray[np.floating],  # [N, 3] unit, world
        material: npt.NDArray[np.integer],  # [N] material ids of the mesh
        footprint_m: npt.ArrayLike,  # [N] or scalar: size of a pixel on the surface, m
    ) -> F32: ...  # [N, 3] linear albedo in 0..1


@dataclass(frozen=True)
class LightRig:
    mode: Literal["lamps", "headlamp"] = "lamps"
    ambient: float = 0.1
    lamps: tuple[tuple[float, float, float], ...] = ()  # world positions, m (lamps mode)
    power: float = 1.0  # multiplier on lamp / headlamp intensity


@dataclass
class RayHits:
    """Geometry under each pixel; fields are meaningless where ``mask`` is False."""

    depth: F32  # [H, W] m along the optical axis, 0 = no hit
    ray_length: F32  # [H, W] m from the camera centre
    points: F64  # [H, W, 3] world
    normals: F32  # [H, W, 3] world, unit, facing the camera
    material: npt.NDArray[np.uint8]  # [H, W]
    mask: npt.NDArray[np.bool_]  # [H, W] True where a ray hit the mesh


@dataclass
class RenderResult:
    color: npt.NDArray[np.uint8]  # [H, W, 3] RGB or [H, W] gray
    color_f: F32  # same shape, display values 0..255 before rounding (for adding sensor noise)
    radiance: F32  # same shape, linear light before the tone curve: color_f = display(radiance)
    depth: F32  # [H, W] m along the optical axis, 0 = no hit
    normals: F32  # [H, W, 3] world, facing the camera
    points: F64  # [H, W, 3] world hit points (meaningless where mask is False)
    mask: npt.NDArray[np.bool_]  # [H, W]


def pixel_rays(intr: Intrinsics, T_world_cam: npt.ArrayLike) -> tuple[F64, F64]:
    """Ray origin [3] and directions [H, W, 3] (world, camera-z component 1) of every pixel centre."""
    T = np.asarray(T_world_cam, np.float64)
    u = (np.arange(intr.width) - intr.cx) / intr.fx
    v = (np.arange(intr.height) - intr.cy) / intr.fy
    d_cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1)  # [H, W, 3]
    return T[:3, 3].copy(), d_cam @ T[:3, :3].T


class Renderer:
    """Casts rays against a :class:`TankMesh` and shades the hits with an :class:`AlbedoModel`
    (the tank's :class:`Appearance` unless given)."""

    def __init__(
        self,
        mesh: TankMesh,
        appearance: AlbedoModel | None = None,
        lights: LightRig | None = None,
    ) -> None:
        import open3d as o3d

        self.mesh = mesh
        if appearance is None:
            tank = mesh.layout if isinstance(mesh.layout, TankLayout) else None
            appearance = Appearance(0, tank)
        self.appearance = appearance
        if lights is None:
            lights = LightRig(lamps=mesh.layout.lamps if mesh.layout is not None else ())
        self.lights = lights
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, np.uint32)),
        )
        # Build (commit) the BVH now with one query, not lazily inside a worker thread.
        self._scene.compute_distance(o3d.core.Tensor(np.zeros((1, 3), np.float32)))
        # Flat triangles use their face normal; the rest (pipes, rims) interpolate vertex normals.
        V, Tr = mesh.vertices, mesh.triangles
        fn = np.cross(V[Tr[:, 1]] - V[Tr[:, 0]], V[Tr[:, 2]] - V[Tr[:, 0]])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
        self._face_normals = fn.astype(np.float32)  # [T, 3]
        dev = np.einsum("tkc,tc->tk", mesh.vertex_normals[Tr].astype(np.float64), fn)  # [T, 3]
        self._smooth = np.any(np.abs(dev) < 1.0 - 1e-6, axis=1)  # [T]

    # ---- geometry queries ------------------------------------------------------------------

    def _cast(
        self, intr: Intrinsics, T_world_cam: npt.ArrayLike
    ) -> tuple[F64, F64, dict, F32, npt.NDArray[np.bool_]]:
        T = check_pose(T_world_cam)
        origin, dirs = pixel_rays(intr, T)
        rays = np.empty((intr.height, intr.width, 6), np.float32)
        rays[..., :3] = origin
        rays[..., 3:] = dirs
        ans = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()  # [H, W] in units of |dir|, i.e. depth along z
        mask = np.isfinite(t)
        depth = np.where(mask, t, 0.0).astype(np.float32)
        return origin, dirs, ans, depth, mask

    def depth(
        self, intr: Intrinsics, T_world_cam: npt.ArrayLike
    ) -> tuple[F32, F64, npt.NDArray[np.bool_]]:
        """Depth [H, W], world points [H, W, 3] and hit mask [H, W], without normals or shading."""
        origin, dirs, _, depth, mask = self._cast(intr, T_world_cam)
        return depth, origin + dirs * depth[..., None].astype(np.float64), mask

    def cast(self, intr: Intrinsics, T_world_cam: npt.ArrayLike) -> RayHits:
        """Depth, world points, normals and materials seen by the camera."""
        origin, dirs, ans, depth, mask = self._cast(intr, T_world_cam)
        tri = np.where(mask, ans["primitive_ids"].numpy(), 0).astype(np.int64)
        points = origin + dirs * depth[..., None].astype(np.float64)
        # Face normals, or vertex normals interpolated on curved parts; turned toward the camera.
        n = self._face_normals[tri]  # [H, W, 3]
        sm = np.flatnonzero((mask & self._smooth[tri]).ravel())
        if len(sm):
            # Barycentric weights of vertices 1 and 2 of the hit triangle.
            uv = ans["primitive_uvs"].numpy().reshape(-1, 2)[sm]  # [S, 2]
            vidx = self.mesh.triangles[tri.ravel()[sm]]  # [S, 3]
            vn = self.mesh.vertex_normals
            ns = (
                (1.0 - uv.sum(1, keepdims=True)) * vn[vidx[:, 0]]
                + uv[:, :1] * vn[vidx[:, 1]]
                + uv[:, 1:] * vn[vidx[:, 2]]
            )
            n.reshape(-1, 3)[sm] = ns / np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-12)
        facing_away = np.einsum("hwc,hwc->hw", n, dirs.astype(np.float32)) > 0
        n[facing_away] *= -1.0
        ray_len = (depth * np.linalg.norm(dirs, axis=-1)).astype(np.float32)
        return RayHits(depth, ray_len, points, n, self.mesh.material[tri], mask)

    def distance(self, points: npt.ArrayLike) -> F64:
        """Unsigned distance of each point [N, 3] to the nearest triangle [N]."""
        q = self._o3d.core.Tensor(
            np.ascontiguousarray(np.asarray(points).reshape(-1, 3), np.float32)
        )
        return self._scene.compute_distance(q).numpy().astype(np.float64)

    def occluded(self, origins: npt.ArrayLike, targets: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """True where the segment origin -> target [N, 3] hits geometry before the target."""
        o = np.asarray(origins).reshape(-1, 3)
        rays = np.empty((len(o), 6), np.float32)
        rays[:, :3] = o
        rays[:, 3:] = np.asarray(targets).reshape(-1, 3) - o
        return (
            self._scene.test_occlusions(self._o3d.core.Tensor(rays), tnear=0.0, tfar=0.999)
            .numpy()
            .astype(bool)
        )

    # ---- shading ----------------------------------------------------------------------------

    def _behind_web(self, points: F32, lamp: tuple[float, float, float]) -> npt.NDArray[np.bool_]:
        """True where the segment point -> lamp [N] crosses a web plate outside its lightening hole.

        Web plates span the whole cross-section, so such a segment is certainly shadowed; the rest
        still needs an occlusion ray. Points on the hole rim count as inside the hole.
        """
        lay = self.mesh.layout
        assert lay is not None
        out = np.zeros(len(points), bool)
        a, b = lay.hole_axes
        for xk, (hy, hz) in zip(lay.web_x, lay.hole_yz, strict=True):
            dp = points[:, 0] - xk
            dl = lamp[0] - xk
            idx = np.flatnonzero(dp * dl < 0)
            if len(idx) == 0:
                continue
            s = dp[idx] / (dp[idx] - dl)
            qy = points[idx, 1] + s * (lamp[1] - points[idx, 1])
            qz = points[idx, 2] + s * (lamp[2] - points[idx, 2])
            out[idx[((qy - hy) / a) ** 2 + ((qz - hz) / b) ** 2 > 1.0 + 1e-3]] = True
        return out

    def irradiance(
        self,
        points: F32,  # [M, 3] world
        normals: F32,  # [M, 3] unit, facing the camera
        to_cam: F32,  # [M, 3] unit, from the point toward the camera
        ray_length: F32,  # [M] m
        cos_axis: F32,  # [M] cosine between the ray and the optical axis
    ) -> F32:  # [M] light arriving at each point, ambient included
        rig = self.lights
        E = np.full(len(points), rig.ambient, np.float32)
        if rig.mode == "headlamp":
            cos = np.clip(np.einsum("ij,ij->i", normals, to_cam), 0.0, 1.0)
            E += rig.power * HEADLAMP_INTENSITY * cos * cos_axis**3 / (ray_length**2 + LIGHT_R0_SQ)
            return E
        for lamp in rig.lamps:
            to_l = np.asarray(lamp, np.float32) - points
            r2 = np.einsum("ij,ij->i", to_l, to_l)
            cos = np.einsum("ij,ij->i", normals, to_l) / np.sqrt(r2)
            lit = np.flatnonzero(cos > 0)
            if isinstance(self.mesh.layout, TankLayout):  # exact and cheap: webs outside holes
                lit = lit[~self._behind_web(points[lit], lamp)]
            if len(lit) == 0:
                continue
            shadow = self.occluded(
                points[lit] + SHADOW_OFFSET * normals[lit], np.asarray(lamp, np.float32)[None]
            )
            E[lit] += (rig.power * LAMP_INTENSITY) * cos[lit] * ~shadow / (r2[lit] + LIGHT_R0_SQ)
        return E

    def render(
        self, intr: Intrinsics, T_world_cam: npt.ArrayLike, grayscale: bool = False
    ) -> RenderResult:
        """Noise-free colour (or gray), depth and normals of one view."""
        # 1. Geometry, flattened to the M pixels that hit something
        T = check_pose(T_world_cam)
        hits = self.cast(intr, T)
        m = hits.mask.ravel()
        sel = slice(None) if m.all() else np.flatnonzero(m)
        p = hits.points.reshape(-1, 3)[sel].astype(np.float32)
        n = hits.normals.reshape(-1, 3)[sel]
        ray_len = hits.ray_length.ravel()[sel]
        to_cam = (T[:3, 3].astype(np.float32) - p) / np.maximum(ray_len, 1e-9)[:, None]
        # 2. Albedo, with the pixel footprint (grazing angles widen it) for texture fading
        cos_view = np.abs(np.einsum("ij,ij->i", n, to_cam))
        footprint = ray_len / np.float32(intr.fx) / np.maximum(cos_view, 0.25)
        albedo = self.appearance.albedo(p, n, hits.material.ravel()[sel], footprint)  # [M, 3]
        # 3. Light, gamma, quantisation
        cos_axis = hits.depth.ravel()[sel] / np.maximum(ray_len, 1e-9)
        radiance = albedo * self.irradiance(p, n, to_cam, ray_len, cos_axis)[:, None]
        if grayscale:
            radiance = radiance @ GRAY_WEIGHTS.astype(np.float32)[:, None]
        vals = display(radiance)  # [M, 3] or [M, 1]
        shape = (intr.height, intr.width) + (() if grayscale else (3,))
        color_f = np.zeros((m.size, vals.shape[1]), np.float32)
        color_f[sel] = vals
        color_f = color_f.reshape(shape)
        rad = np.zeros((m.size, vals.shape[1]), np.float32)
        rad[sel] = radiance
        color = np.clip(np.rint(color_f), 0, 255).astype(np.uint8)
        return RenderResult(
            color, color_f, rad.reshape(shape), hits.depth, hits.normals, hits.points, hits.mask
        )
