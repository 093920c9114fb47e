"""Compiled per-pixel compositing kernels of the CPU rasterizer (numba, no Python per pixel).

gsplat's CUDA kernel, one pixel at a time: each pixel walks its tile's depth-sorted Gaussians
front to back, ``sigma = ½a·dx² + b·dx·dy + ½c·dy²``, ``alpha = min(0.99, o·exp(-sigma))``,
skips ``alpha < 1/255`` and stops before the Gaussian that would take its transmittance to 1e-4
or below. The backward pass replays the same walk (nothing per pixel is stored) and takes the
"everything behind" term of d(out)/d(alpha) from the forward output:
``Σ_{j>i} wⱼgⱼ = Σ_all wⱼgⱼ − Σ_{j<=i} wⱼgⱼ``.

Gradients are written per intersection (one row per (tile, Gaussian) pair, owned by the one
thread that walks that tile), so threads never write the same memory; the caller sums rows per
Gaussian. Arithmetic is in float64 whatever the input dtype: the kernels are scalar code, where
float64 costs about what float32 does, and the thresholds then decide the same way for both.

Tiles are split between threads round-robin over a list sorted by work (the plan's ``order``),
and each thread runs a ``nogil`` kernel: no threading layer, safe to call from several Python
threads at once (the map server renders beside a repair).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

ALPHA_MIN = 1.0 / 255.0  # gsplat ALPHA_THRESHOLD
ALPHA_MAX = 0.99  # gsplat MAX_ALPHA
T_MIN = 1e-4  # gsplat TRANSMITTANCE_THRESHOLD

_POOL: ThreadPoolExecutor | None = None


@numba.njit(nogil=True, cache=True, fastmath=False, boundscheck=False)
def _gather(tile_gs, means2d, conics, opac, log_op255, feats, P, Fb):
    """One tile's Gaussians packed in depth order: the pixels then read them sequentially."""
    for j in range(tile_gs.shape[0]):
        g = tile_gs[j]
        P[j, 0] = means2d[g, 0]
        P[j, 1] = means2d[g, 1]
        P[j, 2] = conics[g, 0]
        P[j, 3] = conics[g, 1]
        P[j, 4] = conics[g, 2]
        P[j, 5] = opac[g]
        P[j, 6] = log_op255[g]
        for f in range(feats.shape[1]):
            Fb[j, f] = feats[g, f]


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _buffers(tiles, tile_count, F):
    """A thread's packed-tile buffers, sized for the largest of its tiles."""
    n_max = 0
    for i in range(tiles.shape[0]):
        n_max = max(n_max, tile_count[tiles[i]])
    return np.empty((n_max, 7)), np.empty((n_max, F))


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _raw_alpha(P, j, dx, dy):
    """o·exp(-sigma) of packed Gaussian j at offset (dx, dy); 0 where it is under 1/255
    (sigma beyond log(255·o)), without the exp."""
    sigma = 0.5 * (P[j, 2] * dx * dx + P[j, 4] * dy * dy) + P[j, 3] * dx * dy
    if sigma > P[j, 6]:
        return 0.0
    return P[j, 5] * math.exp(-sigma)


@numba.njit(nogil=True, cache=True, fastmath=False, boundscheck=False)
def _forward_tiles(
    tiles, means2d, conics, opac, log_op255, feats, isect_gauss, tile_start, tile_count,
    tiles_x, ts, width, height, out,
):  # fmt: skip
    """out[y, x, :] = Σ w·f over the pixels of ``tiles`` (out is zero on entry)."""
    F = feats.shape[1]
    P, Fb = _buffers(tiles, tile_count, F)
    for i in range(tiles.shape[0]):
        tile = tiles[i]
        s = tile_start[tile]
        n = tile_count[tile]
        if n == 0:
            continue
        _gather(isect_gauss[s : s + n], means2d, conics, opac, log_op255, feats, P, Fb)
        y0 = (tile // tiles_x) * ts
        x0 = (tile % tiles_x) * ts
        for py in range(y0, min(y0 + ts, height)):
            fy = py + 0.5
            for px in range(x0, min(x0 + ts, width)):
                fx = px + 0.5
                T = 1.0
                for j in range(n):
                    a = min(ALPHA_MAX, _raw_alpha(P, j, fx - P[j, 0], fy - P[j, 1]))
                    if a < ALPHA_MIN:
                        continue
                    nT = T * (1.0 - a)
                    if nT <= T_MIN:
                        break
                    w = a * T
                    for f in range(F):
                        out[py, px, f] += w * Fb[j, f]
                    T = nT


@numba.njit(nogil=True, cache=True, fastmath=False, boundscheck=False)
def _backward_tiles(
    tiles, means2d, conics, opac, log_op255, feats, isect_gauss, tile_start, tile_count,
    tiles_x, ts, width, height, out, d_out, grad,
):  # fmt: skip
    """grad[k] += d(loss)/d(mean x, mean y, a, b, c, opacity, features...) of intersection k."""
    F = feats.shape[1]
    P, Fb = _buffers(tiles, tile_count, F)
    for i in range(tiles.shape[0]):
        tile = tiles[i]
        s = tile_start[tile]
        n = tile_count[tile]
        if n == 0:
            continue
        _gather(isect_gauss[s : s + n], means2d, conics, opac, log_op255, feats, P, Fb)
        y0 = (tile // tiles_x) * ts
        x0 = (tile % tiles_x) * ts
        for py in range(y0, min(y0 + ts, height)):
            fy = py + 0.5
            for px in range(x0, min(x0 + ts, width)):
                fx = px + 0.5
                behind = 0.0  # Σ over every contribution of w·g, then minus those in front
                for f in range(F):
                    behind += d_out[py, px, f] * out[py, px, f]
                T = 1.0
                for j in range(n):
                    dx = fx - P[j, 0]
                    dy = fy - P[j, 1]
                    raw = _raw_alpha(P, j, dx, dy)
                    a = min(ALPHA_MAX, raw)
                    if a < ALPHA_MIN:
                        continue
                    om = 1.0 - a
                    nT = T * om
                    if nT <= T_MIN:
                        break
                    w = a * T
                    k = s + j
                    gdot = 0.0
                    for f in range(F):
                        gd = d_out[py, px, f]
                        gdot += Fb[j, f] * gd
                        grad[k, 6 + f] += w * gd
                    wg = w * gdot
                    behind -= wg  # now Σ over the Gaussians behind this one
                    if raw < ALPHA_MAX:  # clamped alpha has no gradient
                        # d(loss)/d(log alpha) = a·(T·g − behind / (1 − a))
                        dlogit = wg - a * behind / om
                        A, B, C = P[j, 2], P[j, 3], P[j, 4]
                        grad[k, 0] += dlogit * (A * dx + B * dy)  # d(log alpha)/d(mean x)
                        grad[k, 1] += dlogit * (B * dx + C * dy)
                        grad[k, 2] -= 0.5 * dx * dx * dlogit
                        grad[k, 3] -= dx * dy * dlogit
                        grad[k, 4] -= 0.5 * dy * dy * dlogit
                        grad[k, 5] += dlogit / P[j, 5]
                    T = nT


@numba.njit(cache=True, boundscheck=False)
def _bin(tx0, tx1, ty0, ty1, by_depth, tiles_x, n_tiles):
    """Counting sort of (tile, Gaussian) pairs: by tile, in depth order within a tile."""
    count = np.zeros(n_tiles, np.int64)
    for g in range(tx0.shape[0]):
        for ty in range(ty0[g], ty1[g] + 1):
            for tx in range(tx0[g], tx1[g] + 1):
                count[ty * tiles_x + tx] += 1
    start = np.zeros(n_tiles, np.int64)
    for t in range(1, n_tiles):
        start[t] = start[t - 1] + count[t - 1]
    total = start[n_tiles - 1] + count[n_tiles - 1] if n_tiles else 0
    gauss = np.empty(total, np.int64)
    tile_of = np.empty(total, np.int64)
    pos = start.copy()
    for i in range(by_depth.shape[0]):
        g = by_depth[i]
        for ty in range(ty0[g], ty1[g] + 1):
            for tx in range(tx0[g], tx1[g] + 1):
                t = ty * tiles_x + tx
                gauss[pos[t]] = g
                tile_of[pos[t]] = t
                pos[t] += 1
    return gauss, tile_of, start, count


def bin_pairs(
    tx0: np.ndarray,  # [V] int64 first tile column a Gaussian reaches (tx1 < tx0: none)
    tx1: np.ndarray,  # [V] int64 last tile column
    ty0: np.ndarray,  # [V] int64 first tile row
    ty1: np.ndarray,  # [V] int64 last tile row
    depths: np.ndarray,  # [V]
    tiles_x: int,
    n_tiles: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every (tile, Gaussian) pair sorted by tile, then depth (ties: lower index first).

    Returns the Gaussian [M] and tile [M] of each pair, each tile's first pair and its count
    [n_tiles]."""
    by_depth = np.argsort(depths, kind="stable")
    return _bin(*_i64(tx0, tx1, ty0, ty1, by_depth), tiles_x, n_tiles)


def _split(order: np.ndarray, n_threads: int) -> list[np.ndarray]:
    """Round-robin over tiles sorted by work: each thread gets a similar share of heavy tiles."""
    return [order[t::n_threads] for t in range(n_threads) if t < len(order)]


def _run(kernel, order: np.ndarray, n_threads: int, *args) -> None:
    global _POOL
    order = np.ascontiguousarray(order, dtype=np.int64)
    parts = [np.ascontiguousarray(p) for p in _split(order, max(1, n_threads))]
    if len(parts) <= 1:
        kernel(order, *args)
        return
    if _POOL is None or _POOL._max_workers < len(parts):  # noqa: SLF001 (size check only)
        _POOL = ThreadPoolExecutor(len(parts), thread_name_prefix="gsfix-raster")
    for fut in [_POOL.submit(kernel, p, *args) for p in parts]:
        fut.result()


def _f64(*arrays: np.ndarray) -> list[np.ndarray]:
    """C-contiguous float64 copies where needed: one compiled signature for every caller."""
    return [np.ascontiguousarray(a, dtype=np.float64) for a in arrays]


def _i64(*arrays: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray(a, dtype=np.int64) for a in arrays]


def _log_op255(opac: np.ndarray) -> np.ndarray:
    """Per Gaussian, the sigma above which alpha = o·exp(-sigma) < 1/255: log(255·o)."""
    with np.errstate(divide="ignore"):
        return np.log(np.maximum(opac.astype(np.float64), 0.0) * 255.0)


def composite_forward(
    means2d: np.ndarray,  # [V, 2]
    conics: np.ndarray,  # [V, 3]
    opac: np.ndarray,  # [V]
    feats: np.ndarray,  # [V, F]
    isect_gauss: np.ndarray,  # [M] int64, sorted by (tile, depth)
    tile_start: np.ndarray,  # [n_tiles] int64
    tile_count: np.ndarray,  # [n_tiles] int64
    order: np.ndarray,  # [n_tiles] int64, tiles by decreasing work
    tiles_x: int,
    tile_size: int,
    width: int,
    height: int,
    n_threads: int,
) -> np.ndarray:  # [H, W, F] Σ w·f, float64
    out = np.zeros((height, width, feats.shape[1]), dtype=np.float64)
    _run(
        _forward_tiles, order, n_threads, *_f64(means2d, conics, opac), _log_op255(opac),
        _f64(feats)[0], *_i64(isect_gauss, tile_start, tile_count), tiles_x, tile_size, width,
        height, out,
    )  # fmt: skip
    return out


def composite_backward(
    means2d: np.ndarray,
    conics: np.ndarray,
    opac: np.ndarray,
    feats: np.ndarray,
    isect_gauss: np.ndarray,
    tile_start: np.ndarray,
    tile_count: np.ndarray,
    order: np.ndarray,
    tiles_x: int,
    tile_size: int,
    width: int,
    height: int,
    n_threads: int,
    out: np.ndarray,  # [H, W, F] the forward output (float64, as composite_forward returns it)
    d_out: np.ndarray,  # [H, W, F] d(loss)/d(out)
) -> np.ndarray:  # [M, 6 + F] per intersection: d/d(mx, my, a, b, c, o, f...)
    grad = np.zeros((isect_gauss.shape[0], 6 + feats.shape[1]), dtype=np.float64)
    _run(
        _backward_tiles, order, n_threads, *_f64(means2d, conics, opac), _log_op255(opac),
        _f64(feats)[0], *_i64(isect_gauss, tile_start, tile_count), tiles_x, tile_size, width,
        height, *_f64(out, d_out), grad,
    )  # fmt: skip
    return grad
