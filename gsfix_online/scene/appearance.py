"""Procedural surface appearance of the tank: epoxy paint, rust, grime, run-off streaks, speckle.

Everything is a function of the world point, its normal and its material, so every view of a
surface sees the same albedo. Noise comes from a few tileable band-limited textures (made once by
filtering white noise in the Fourier domain) sampled triplanarly with bilinear look-ups. Detail
finer than about two pixels fades out with the pixel footprint, a cheap stand-in for mip-mapping
that keeps one-ray-per-pixel renders from aliasing into view-dependent noise.

Albedo is linear (not gamma encoded) in 0..1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gsfix_online.scene.geometry import Material, TankLayout

F32 = npt.NDArray[np.float32]


def srgb_to_linear(c: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return np.asarray(c, np.float64) ** 2.2


def linear_to_srgb(c: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return np.clip(np.asarray(c, np.float64), 0.0, 1.0) ** (1.0 / 2.2)


def _f32(c: tuple[float, float, float]) -> npt.NDArray[np.float32]:
    return srgb_to_linear(c).astype(np.float32)


# Paint per material (sRGB) and how readily it rusts (1 = bare shell plating).
_PAINT = {
    Material.SHELL: ((0.74, 0.73, 0.68), 1.0),  # light grey epoxy
    Material.WEB: ((0.79, 0.75, 0.63), 1.0),  # buff
    Material.STIFFENER: ((0.72, 0.71, 0.66), 1.25),
    Material.BRACKET: ((0.79, 0.75, 0.63), 1.3),
    Material.LADDER: ((0.88, 0.66, 0.09), 0.55),  # safety yellow
    Material.PIPE: ((0.50, 0.53, 0.56), 0.8),
    Material.PIPE_RED: ((0.64, 0.13, 0.10), 0.5),
    Material.FLANGE: ((0.40, 0.41, 0.43), 1.4),
    Material.COAMING: ((0.74, 0.73, 0.68), 1.2),
}
N_MATERIALS = max(_PAINT) + 1
PAINT_LINEAR = np.zeros((N_MATERIALS, 3))
RUST_PRONE = np.zeros(N_MATERIALS)
for _m, (_c, _r) in _PAINT.items():
    PAINT_LINEAR[_m] = srgb_to_linear(_c)
    RUST_PRONE[_m] = _r
RUST_LIGHT = _f32((0.58, 0.31, 0.12))
RUST_DARK = _f32((0.30, 0.16, 0.08))
STAIN = _f32((0.62, 0.50, 0.36))
STREAK = _f32((0.42, 0.26, 0.14))
MUD = _f32((0.36, 0.31, 0.24))
WELD = _f32((0.40, 0.36, 0.32))

LOW_PERIOD = 9.7  # m covered by one tile of the coarse texture (3.8 cm texels at 256)
HIGH_PERIOD = 2.3  # m covered by one tile of the fine texture (4.5 mm texels at 512)
DEFAULT_HEIGHT = 3.0  # m, for streak fading when there is no tank layout (test meshes)
STREAK_PERIOD = (1.5, 30.0)  # m per tile across / down a run-off streak (stretched 20x along z)
# Coarse channels: rust, grime, rust tone / mud, paint patches. Band (lo, hi) in cycles per tile, beta.
LOW_BANDS = ((4, 48, 1.6), (2, 32, 2.0), (6, 96, 1.0), (2, 24, 2.0))
# Fine channels: detail (3-12 cm), speckle (1-2.5 cm), pitting; streaks (sampled stretched along z).
HIGH_BANDS = ((19, 77, 1.0), (92, 230, 0.0), (40, 200, 0.5), (30, 150, 0.5))
_PLANE_AXES = ((1, 2), (0, 2), (0, 1))  # texture coordinates for a normal along x, y, z
_REMAP_COLS = 256  # remap wants both image sides < 32767: look-ups go through [n / 256, 256] maps


def band_noise(
    rng: np.random.Generator, size: int, bands: tuple[tuple[float, float, float], ...]
) -> F32:
    """Tileable Gaussian noise [size, size, C], one channel per (f_lo, f_hi, beta) band, unit std.

    The power spectrum falls as f^-beta between soft cut-offs at f_lo and f_hi (cycles per tile).
    """
    f = np.hypot(
        *np.meshgrid(np.fft.fftfreq(size) * size, np.fft.fftfreq(size) * size, indexing="ij")
    )
    f[0, 0] = 1e-6
    out = np.empty((size, size, len(bands)), np.float32)
    for c, (lo, hi, beta) in enumerate(bands):
        amp = f ** (-beta / 2.0) * np.exp(-((f / hi) ** 2)) * (1.0 - np.exp(-((f / lo) ** 2)))
        amp[0, 0] = 0.0
        field = np.fft.ifft2(np.fft.fft2(rng.standard_normal((size, size))) * amp).real
        out[..., c] = (field - field.mean()) / field.std()
    return out


def bilinear(tex: F32, u: npt.NDArray[np.floating], v: npt.NDArray[np.floating]) -> F32:
    """Wrap-around bilinear look-up of ``tex`` [S, S, C<=4] at texel coordinates u (columns), v (rows) [n] -> [n, C].

    Texel centres sit at integer coordinates. OpenCV's remap does the work (~4x numpy gathers).
    """
    import cv2

    S, C = tex.shape[0], tex.shape[2]
    assert tex.shape[1] == S and C <= 4, "texture must be [S, S, C<=4]"
    n = len(u)
    rows = -(-n // _REMAP_COLS)
    maps = np.zeros((2, rows * _REMAP_COLS), np.float32)
    maps[0, :n] = np.mod(u, S)
    maps[1, :n] = np.mod(v, S)
    shape = (rows, _REMAP_COLS)
    out = cv2.remap(
        tex,
        maps[0].reshape(shape),
        maps[1].reshape(shape),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    )
    return out.reshape(-1, C)[:n]


@dataclass
class TriplanarPlan:
    """Which points use which axis-aligned projection, and how much; shared by all textures."""

    idx: list[npt.NDArray[np.int64]]  # per axis: points with weight > 0
    weight: list[F32]  # per axis: [n_a, 1] weights (rows sum to 1 over the axes)
    uv: list[tuple[F32, F32]]  # per axis: the point's two in-plane coordinates, m
    n: int


def triplanar_plan(
    points: npt.NDArray[np.floating], normals: npt.NDArray[np.floating]
) -> TriplanarPlan:
    """Blend weights ~ |n|^4, dropping any below 2 %; axis-aligned plates use one projection."""
    n2 = np.square(normals, dtype=np.float32)
    w = n2 * n2
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    w[w < 0.02] = 0.0
    w /= w.sum(axis=1, keepdims=True)
    plan = TriplanarPlan([], [], [], len(points))
    for a, (i, j) in enumerate(_PLANE_AXES):
        idx = np.flatnonzero(w[:, a] > 0)
        plan.idx.append(idx)
        plan.weight.append(w[idx, a, None])
        plan.uv.append((points[idx, i], points[idx, j]))
    return plan


def triplanar(tex: F32, period: float, plan: TriplanarPlan) -> F32:
    """Blend of the three axis-aligned projections of ``tex`` (one tile per ``period`` m): [N, C]."""
    S = tex.shape[0]
    out = np.zeros((plan.n, tex.shape[2]), np.float32)
    for a in range(3):
        idx = plan.idx[a]
        if len(idx) == 0:
            continue
        # A different offset per projection so that walls, floor and ends do not repeat each other.
        u = plan.uv[a][0] * (S / period) + 0.318 * a * S
        v = plan.uv[a][1] * (S / period) + 0.577 * a * S
        out[idx] += plan.weight[a] * bilinear(tex, u, v)
    return out


def smoothstep(e0: float, e1: float, x: npt.NDArray[np.floating]) -> npt.NDArray[np.floating]:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def fade(feature_m: float, footprint_m: npt.NDArray[np.floating]) -> npt.NDArray[np.floating]:
    """1 where a feature spans >= 2 pixels, 0 where it spans <= 1 pixel."""
    return np.clip(feature_m / np.maximum(footprint_m, 1e-6) - 1.0, 0.0, 1.0)


def edge_distance(points: npt.NDArray[np.floating], layout: TankLayout) -> npt.NDArray[np.float32]:
    """Distance to the nearest plate junction (shell corner, web/shell line) or lightening-hole rim [N].

    Main plates are the shell walls (x, y, z = 0 or the tank size) and the webs (x = web mid-plane).
    A point on a plate normal to axis a is at the distance to the nearest plate normal to another
    axis from a junction line. Points off the main plates (stiffeners, pipes) get inf.
    """
    p = np.asarray(points, np.float32)
    on_tol = layout.web_thickness / 2.0 + 2e-3
    m = np.empty((len(p), 3), np.float32)  # distance to the nearest plate normal to x, y, z
    m[:, 0] = np.abs(p[:, 0])
    for x in (*layout.web_x, layout.length):
        np.minimum(m[:, 0], np.abs(p[:, 0] - x), out=m[:, 0])
    m[:, 1] = np.minimum(np.abs(p[:, 1]), np.abs(p[:, 1] - layout.width))
    m[:, 2] = np.minimum(np.abs(p[:, 2]), np.abs(p[:, 2] - layout.height))
    out = np.full(len(p), np.inf, np.float32)
    for axis in range(3):
        on = m[:, axis] < on_tol
        others = np.delete(m[on], axis, axis=1)
        out[on] = np.minimum(out[on], others.min(axis=1))
    a, b = layout.hole_axes
    for x, (hy, hz) in zip(layout.web_x, layout.hole_yz, strict=True):
        near = np.flatnonzero(np.abs(p[:, 0] - x) < on_tol)
        if len(near):
            r = np.hypot((p[near, 1] - hy) / a, (p[near, 2] - hz) / b)
            out[near] = np.minimum(out[near], np.abs(r - 1.0) * min(a, b))
    return out


class Appearance:
    """Albedo of the tank surfaces at world points; deterministic by ``seed``."""

    def __init__(self, seed: int, layout: TankLayout | None = None) -> None:
        rng = np.random.default_rng([int(seed), 0xA1BE])
        self.layout = layout
        self._low = band_noise(rng, 256, LOW_BANDS)
        high = band_noise(rng, 512, HIGH_BANDS)
        self._high = np.ascontiguousarray(high[..., :3])
        self._streak = np.ascontiguousarray(high[..., 3:])
        self._paint = PAINT_LINEAR.astype(np.float32)
        self._rust_threshold = (1.65 * (2.0 - RUST_PRONE)).astype(np.float32)

    def albedo(
        self,
        points: npt.NDArray[np.floating],  # [N, 3] world, m
        normals: npt.NDArray[np.floating],  # [N, 3] unit, world
        material: npt.NDArray[np.integer],  # [N] Material
        footprint_m: npt.ArrayLike,  # [N] or scalar: size of a pixel on the surface, m
    ) -> F32:  # [N, 3] linear albedo in 0..1
        n_pts = len(points)
        p = np.asarray(points, np.float32)
        n = np.asarray(normals, np.float32)
        mat = np.asarray(material, np.int64)
        fp = np.broadcast_to(np.asarray(footprint_m, np.float32), (n_pts,))
        z = p[:, 2]
        # 1. Noise look-ups: coarse [N, 4] and fine [N, 4] channels.
        plan = triplanar_plan(p, n)
        lo = triplanar(self._low, LOW_PERIOD, plan)
        hi = triplanar(self._high, HIGH_PERIOD, plan)
        # 2. Paint with touch-up patches.
        col = self._paint[mat] * (1.0 + 0.06 * lo[:, 3:4])
        is_plate = np.isin(mat, (Material.SHELL, Material.WEB, Material.COAMING))
        vertical = np.abs(n[:, 2]) < 0.3
        # 3. Distances to plate junctions and to the shell's weld seams (butts mid-bay, one seam
        #    along each wall, floor and deck plate).
        d_edge = np.full(n_pts, np.inf, np.float32)
        d_seam = np.full(n_pts, np.inf, np.float32)
        height = DEFAULT_HEIGHT
        if self.layout is not None:
            lay = self.layout
            height = lay.height
            d_edge = edge_distance(p, lay)
            shell = np.flatnonzero(mat == Material.SHELL)
            if len(shell):
                ps, ns = p[shell], n[shell]
                edges = np.asarray((0.0, *lay.web_x, lay.length), np.float32)
                butts = (edges[:-1] + edges[1:]) / 2.0
                d_butt = np.full(len(shell), np.inf, np.float32)
                for b in butts:
                    d_butt = np.minimum(d_butt, np.abs(ps[:, 0] - b))
                d_long = np.where(
                    np.abs(ns[:, 2]) < 0.3,
                    np.abs(ps[:, 2] - lay.height / 2),
                    np.abs(ps[:, 1] - lay.width / 2),
                )
                d_seam[shell] = np.minimum(np.where(np.abs(ns[:, 0]) < 0.5, d_butt, np.inf), d_long)
        weld = np.exp(-((d_seam / 0.008) ** 2)) * fade(0.012, fp)
        col += (WELD - col) * (0.6 * weld)[:, None]
        # 4. Rust: thresholded coarse noise, more on edges, welds, near the floor, on thin parts.
        field = (
            lo[:, 0]
            + 1.5 * np.exp(-d_edge / 0.06)
            + 0.9 * np.exp(-d_seam / 0.03)
            + 1.0 * np.exp(-z / 0.3)
            + 0.3 * hi[:, 0]
            - self._rust_threshold[mat]
        )
        rust_a = smoothstep(0.0, 0.3, field)
        stain_a = 0.35 * smoothstep(-0.5, 0.0, field) * (1.0 - rust_a)
        tone = np.clip(0.5 + 0.4 * lo[:, 2] + 0.2 * hi[:, 2], 0.0, 1.0)[:, None]
        rust = RUST_DARK + (RUST_LIGHT - RUST_DARK) * tone
        rust *= (1.0 - 0.55 * smoothstep(1.2, 1.9, hi[:, 2]) * fade(0.015, fp))[:, None]  # pitting
        col += (STAIN * (1.0 + 0.06 * lo[:, 3:4]) - col) * stain_a[:, None]
        col += (rust - col) * rust_a[:, None]
        # 5. Run-off streaks down the vertical plating, strongest low down and under grime.
        sv = np.flatnonzero(vertical & is_plate)
        if len(sv):
            h = np.where(np.abs(n[sv, 1]) > np.abs(n[sv, 0]), p[sv, 0], p[sv, 1])
            S = self._streak.shape[0]
            u, v = h * (S / STREAK_PERIOD[0]), z[sv] * (S / STREAK_PERIOD[1])
            s = bilinear(self._streak, u, v)[:, 0]
            a = (
                smoothstep(0.5, 1.8, s)
                * smoothstep(-0.6, 0.6, lo[sv, 1])
                * (1.1 - z[sv] / height)
                * fade(0.02, fp[sv])
            )
            col[sv] += (STREAK - col[sv]) * np.clip(0.6 * a, 0.0, 1.0)[:, None]
        # 6. Grime (broad darkening) and mud on the floor.
        grime = 0.22 * smoothstep(-0.4, 1.6, lo[:, 1]) * (1.0 + 0.8 * np.exp(-z / 0.5))
        col *= (1.0 - np.clip(grime, 0.0, 0.6))[:, None]
        floor = np.flatnonzero((n[:, 2] > 0.8) & (z < 0.03))
        if len(floor):
            mud_a = 0.65 * smoothstep(-1.2, 1.0, -lo[floor, 2])
            col[floor] += (MUD * (1.0 + 0.25 * lo[floor, 1:2]) - col[floor]) * mud_a[:, None]
        # 7. Fine texture: detail and speckle, faded below two pixels.
        detail = 0.08 * hi[:, 0] * fade(0.06, fp) + 0.06 * hi[:, 1] * fade(0.02, fp)
        col *= (1.0 + detail)[:, None]
        return np.clip(col, 0.0, 1.0).astype(np.float32)
