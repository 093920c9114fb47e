"""Procedural surface appearance of the room: plaster, wallpaper, oak planks, a patterned rug,
wood grain, fabric, a venetian blind, books and abstract pictures.

Like the tank's :class:`~gsfix_online.scene.appearance.Appearance`, albedo is a function of the
world point, its normal and its material (so every view agrees), built from the same band-limited
tileable noise, and detail finer than about two pixels fades out with the pixel footprint. Base
colours vary a little with the seed, so rooms of different seeds differ. Albedo is linear, 0..1.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from gsfix_online.scene.appearance import (
    HIGH_BANDS,
    HIGH_PERIOD,
    LOW_BANDS,
    band_noise,
    bilinear,
    fade,
    smoothstep,
    srgb_to_linear,
    triplanar,
    triplanar_plan,
)
from gsfix_online.scene.room import N_BOOK_COLOURS, N_PICTURES, RoomLayout, RoomMaterial

F32 = npt.NDArray[np.float32]
M = RoomMaterial

LOW_PERIOD = 4.1  # m per tile of the coarse texture (finer than the tank's: a room is smaller)
PLANK_WIDTH, PLANK_LENGTH = 0.14, 1.1  # m, floor boards along x
PICTURE_PERIOD = 1.3  # m per tile of the pictures' colour fields

# Base colours (sRGB).
_BASE = {
    M.WALL: (0.86, 0.84, 0.78),
    M.WALLPAPER: (0.52, 0.60, 0.56),
    M.CEILING: (0.93, 0.93, 0.91),
    M.FLOOR: (0.62, 0.45, 0.28),
    M.RUG: (0.58, 0.19, 0.17),
    M.WOOD: (0.70, 0.55, 0.36),
    M.WOOD_DARK: (0.36, 0.24, 0.16),
    M.FABRIC: (0.30, 0.38, 0.50),
    M.METAL: (0.86, 0.86, 0.84),
    M.DOOR: (0.90, 0.89, 0.85),
    M.TRIM: (0.94, 0.94, 0.92),
    M.BLIND: (0.88, 0.85, 0.76),
    M.SHADE: (0.90, 0.86, 0.72),
    M.CERAMIC: (0.75, 0.40, 0.30),
}
_BOOKS = (
    (0.55, 0.12, 0.10), (0.12, 0.22, 0.45), (0.15, 0.38, 0.22), (0.85, 0.75, 0.45),
    (0.20, 0.20, 0.22), (0.80, 0.80, 0.76), (0.62, 0.35, 0.12), (0.42, 0.18, 0.40),
    (0.10, 0.45, 0.50), (0.75, 0.55, 0.15), (0.35, 0.30, 0.25), (0.65, 0.20, 0.30),
    (0.25, 0.30, 0.60), (0.45, 0.50, 0.20), (0.90, 0.45, 0.25), (0.55, 0.58, 0.62),
)  # fmt: skip
_PICTURE_PALETTES = (  # three colours per picture (sRGB)
    ((0.85, 0.65, 0.25), (0.15, 0.30, 0.55), (0.90, 0.88, 0.80)),
    ((0.20, 0.45, 0.30), (0.85, 0.80, 0.60), (0.45, 0.20, 0.15)),
    ((0.75, 0.25, 0.20), (0.95, 0.90, 0.75), (0.10, 0.10, 0.15)),
    ((0.35, 0.55, 0.75), (0.90, 0.85, 0.70), (0.30, 0.35, 0.20)),
    ((0.60, 0.40, 0.60), (0.95, 0.75, 0.40), (0.20, 0.25, 0.40)),
    ((0.15, 0.15, 0.18), (0.85, 0.85, 0.85), (0.80, 0.30, 0.10)),
    ((0.55, 0.70, 0.45), (0.25, 0.40, 0.55), (0.95, 0.95, 0.85)),
    ((0.90, 0.60, 0.55), (0.40, 0.25, 0.35), (0.70, 0.75, 0.80)),
)
RUG_COLOURS = ((0.85, 0.75, 0.55), (0.16, 0.20, 0.33))  # motif, border (sRGB)
WALLPAPER_MOTIF = (0.82, 0.80, 0.68)
N_MATERIALS = int(M.PICTURE) + N_PICTURES


def _hash01(a: npt.NDArray[np.int64], b: npt.NDArray[np.int64], salt: int) -> F32:
    """Deterministic pseudo-random value in [0, 1) per integer pair."""
    x = (a.astype(np.uint64) * np.uint64(73856093)) ^ (b.astype(np.uint64) * np.uint64(19349663))
    x ^= np.uint64(salt * 83492791 & 0xFFFFFFFF)
    x = (x ^ (x >> np.uint64(13))) * np.uint64(1274126177)
    x ^= x >> np.uint64(16)
    return ((x & np.uint64(0xFFFF)).astype(np.float32)) / np.float32(65536.0)


def _in_plane(p: F32, n: F32) -> tuple[F32, F32]:
    """Two in-plane coordinates per point: (x, y) on horizontal faces, (along the wall, z) else."""
    nx, ny, nz = np.abs(n[:, 0]), np.abs(n[:, 1]), np.abs(n[:, 2])
    horiz = nz >= np.maximum(nx, ny)
    u = np.where(horiz, p[:, 0], np.where(ny >= nx, p[:, 0], p[:, 1]))
    v = np.where(horiz, p[:, 1], p[:, 2])
    return u, v


class RoomAppearance:
    """Albedo of the room's surfaces at world points; deterministic by ``seed``."""

    def __init__(self, seed: int, layout: RoomLayout | None = None) -> None:
        rng = np.random.default_rng([int(seed), 0x2004])
        self.layout = layout
        self._low = band_noise(rng, 256, LOW_BANDS)
        self._high = band_noise(rng, 512, HIGH_BANDS)
        base = np.full((N_MATERIALS, 3), 0.5)
        for m, c in _BASE.items():
            base[m] = c
        for k in range(N_BOOK_COLOURS):
            base[M.BOOK + k] = _BOOKS[k]
        # Seed-dependent tint of the big surfaces and the furniture (a different room per seed).
        level = 1.0 + rng.normal(0.0, 0.06, (N_MATERIALS, 1))
        tint = np.clip(level * (1.0 + rng.normal(0.0, 0.015, (N_MATERIALS, 3))), 0.8, 1.2)
        self._base = srgb_to_linear(np.clip(base * tint, 0.0, 1.0)).astype(np.float32)
        self._palettes = srgb_to_linear(np.asarray(_PICTURE_PALETTES)).astype(np.float32)
        self._rug = srgb_to_linear(RUG_COLOURS).astype(np.float32)
        self._motif = srgb_to_linear(WALLPAPER_MOTIF).astype(np.float32)
        self._salt = int(rng.integers(1 << 30))

    def albedo(
        self,
        points: npt.NDArray[np.floating],  # [N, 3] world, m
        normals: npt.NDArray[np.floating],  # [N, 3] unit, world
        material: npt.NDArray[np.integer],  # [N] RoomMaterial
        footprint_m: npt.ArrayLike,  # [N] or scalar: size of a pixel on the surface, m
    ) -> F32:  # [N, 3] linear albedo in 0..1
        n_pts = len(points)
        p = np.asarray(points, np.float32)
        n = np.asarray(normals, np.float32)
        mat = np.asarray(material, np.int64)
        fp = np.broadcast_to(np.asarray(footprint_m, np.float32), (n_pts,))
        # 1. Noise look-ups and the base colour with a broad mottle.
        plan = triplanar_plan(p, n)
        lo = triplanar(self._low, LOW_PERIOD, plan)
        hi = triplanar(self._high, HIGH_PERIOD, plan)
        col = self._base[mat] * (1.0 + 0.05 * lo[:, 3:4])
        u, v = _in_plane(p, n)
        # 2. Plaster (walls, ceiling, door): faint blotches and speckle.
        sel = np.isin(mat, (M.WALL, M.CEILING, M.DOOR, M.WALLPAPER, M.TRIM))
        col[sel] *= 1.0 + 0.04 * lo[sel, 1:2] + 0.03 * hi[sel, 1:2] * fade(0.01, fp[sel])[:, None]
        # 3. Wallpaper: a dot lattice between thin stripes.
        i = np.flatnonzero(mat == M.WALLPAPER)
        if len(i):
            dots = np.sin(2 * np.pi * u[i] / 0.16) * np.sin(2 * np.pi * v[i] / 0.16)
            stripe = np.exp(-((((u[i] + 0.08) % 0.32) - 0.16) ** 2) / 0.006**2)
            a = (smoothstep(0.45, 0.7, dots) * fade(0.04, fp[i])
                 + 0.8 * stripe * fade(0.012, fp[i]))  # fmt: skip
            col[i] += (self._motif - col[i]) * np.clip(0.75 * a, 0.0, 1.0)[:, None]
        # 4. Floor: staggered planks, each with its own tone, grain along x and dark seams.
        i = np.flatnonzero((mat == M.FLOOR) & (n[:, 2] > 0.5))
        if len(i):
            x, y = p[i, 0], p[i, 1]
            row = np.floor(y / PLANK_WIDTH).astype(np.int64)
            off = _hash01(row, row * 0 + 7, self._salt) * PLANK_LENGTH
            col_i = np.floor((x + off) / PLANK_LENGTH).astype(np.int64)
            tone = _hash01(row, col_i, self._salt) * 2.0 - 1.0
            S = self._high.shape[0]
            grain = bilinear(
                self._high[..., 2:3], x * (S / (8 * HIGH_PERIOD)), y * (S / HIGH_PERIOD)
            )[:, 0]
            dy = (
                np.abs(((y / PLANK_WIDTH) % 1.0) - 0.5) * PLANK_WIDTH
            )  # 0.07 mid-board, 0 at a seam
            dx = np.abs((((x + off) / PLANK_LENGTH) % 1.0) - 0.5) * PLANK_LENGTH
            seam = np.maximum(
                np.exp(-(((PLANK_WIDTH / 2 - dy) / 0.003) ** 2)),
                np.exp(-(((PLANK_LENGTH / 2 - dx) / 0.003) ** 2)),
            ) * fade(0.008, fp[i])
            shade = (1.0 + 0.16 * tone + 0.12 * grain * fade(0.01, fp[i])) * (1.0 - 0.6 * seam)
            col[i] *= shade[:, None]
        # 5. Wood: grain along the face's first in-plane axis.
        i = np.flatnonzero(np.isin(mat, (M.WOOD, M.WOOD_DARK)))
        if len(i):
            S = self._high.shape[0]
            g = bilinear(
                self._high[..., 2:3], u[i] * (S / (6 * HIGH_PERIOD)), v[i] * (S / HIGH_PERIOD)
            )
            col[i] *= 1.0 + 0.15 * g * fade(0.008, fp[i])[:, None]
        # 6. Fabric: a fine weave and soft folds.
        i = np.flatnonzero(mat == M.FABRIC)
        if len(i):
            col[i] *= 1.0 + 0.1 * lo[i, 1:2] + 0.08 * hi[i, 1:2] * fade(0.008, fp[i])[:, None]
        # 7. Rug: a border band and a diamond lattice, with pile noise.
        i = np.flatnonzero((mat == M.RUG) & (n[:, 2] > 0.5))
        if len(i) and self.layout is not None:
            x0, x1, y0, y1 = self.layout.rug
            rx, ry = p[i, 0] - x0, p[i, 1] - y0
            edge = np.minimum(np.minimum(rx, x1 - x0 - rx), np.minimum(ry, y1 - y0 - ry))
            q = np.abs(((rx + ry) / 0.25) % 1.0 - 0.5) + np.abs(((rx - ry) / 0.25) % 1.0 - 0.5)
            motif = smoothstep(0.55, 0.65, q) * fade(0.03, fp[i])
            col[i] += (self._rug[0] - col[i]) * (0.8 * motif)[:, None]
            border = smoothstep(0.13, 0.11, edge) * (1.0 - smoothstep(0.05, 0.03, edge))
            col[i] += (self._rug[1] - col[i]) * border[:, None]
            col[i] *= 1.0 + 0.12 * hi[i, 1:2] * fade(0.006, fp[i])[:, None]
        # 8. Blind: horizontal slats, each shaded from top to bottom.
        i = np.flatnonzero(mat == M.BLIND)
        if len(i):
            t = (p[i, 2] / 0.05) % 1.0
            col[i] *= (1.0 - (0.35 * (1.0 - t)) * fade(0.025, fp[i]))[:, None]
        # 9. Books: a faded band near the top of the spine; pictures: three-colour fields.
        i = np.flatnonzero((mat >= M.BOOK) & (mat < M.BOOK + N_BOOK_COLOURS))
        if len(i):
            col[i] *= 1.0 + 0.08 * hi[i, 0:1] * fade(0.01, fp[i])[:, None]
        i = np.flatnonzero(mat >= M.PICTURE)
        if len(i):
            k = mat[i] - M.PICTURE
            S = self._low.shape[0]
            f = bilinear(
                self._low,
                u[i] * (S / PICTURE_PERIOD) + 37.0 * k,
                v[i] * (S / PICTURE_PERIOD) + 91.0 * k,
            )
            w = np.stack([smoothstep(-0.3, 0.6, f[:, 0]), smoothstep(-0.2, 0.8, f[:, 1])], -1)
            pal = self._palettes[k]  # [n, 3, 3]
            c = pal[:, 2] + (pal[:, 0] - pal[:, 2]) * w[:, :1]
            col[i] = c + (pal[:, 1] - c) * w[:, 1:2] * (1.0 - w[:, :1])
        return np.clip(col, 0.0, 1.0).astype(np.float32)
