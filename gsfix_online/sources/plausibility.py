"""Depth plausibility at the readers' boundary: the depth range of a recording and its scale.

A wrong depth scale does not fail anywhere downstream: millimetre PNGs read at 5000 units per
metre map a tank at a fifth of its size, ``"depth_scale": 1`` in kilometres. The readers keep a
:class:`DepthSummary` of what they yielded (median, 1st and 99th percentile in metres, the
fraction of invalid pixels, frames whose depth is all zero) and name the likely scale when the
median is implausible; :func:`scale_from_motion` finds a scale error the median alone cannot (a
fifth of 2 m is still a plausible depth) from two posed frames of the same surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import RGBDFrame

PLAUSIBLE_MEDIAN_M = (0.1, 30.0)  # median depth of a frame of an RGB-D camera, metres
TYPICAL_DEPTH_M = 2.0  # what the likely scale aims at when the median is implausible
# raw depth units per metre in use: millimetres, TUM, Replica, 0.1 mm; metres for float images
COMMON_SCALES = {"uint16": (1000.0, 5000.0, 6553.5, 10000.0), "float32": (1.0, 1000.0)}
MOTION_AGREE = 0.05  # median relative depth difference of two views that agree
_SAMPLES_PER_FRAME = 256
_MAX_SAMPLES = 1 << 17  # depths kept for the percentiles: thinned over frames beyond this


def plausible(median_m: float) -> bool:
    lo, hi = PLAUSIBLE_MEDIAN_M
    return lo <= median_m <= hi


def frame_median(depth_m: npt.NDArray[np.float32]) -> float | None:  # depth_m: [H, W]
    """Median of the valid (> 0) depths of a frame; None when every pixel is invalid."""
    valid = depth_m[depth_m > 0]
    return float(np.median(valid)) if valid.size else None


@dataclass
class DepthSummary:
    """Depth statistics of the frames a reader yielded (a strided sample of each frame)."""

    frames: int = 0
    pixels: int = 0
    invalid_pixels: int = 0  # depth 0 (no measurement) after validation
    all_zero_frames: int = 0  # frames without a single valid depth
    implausible_frames: int = 0  # frames whose median is outside PLAUSIBLE_MEDIAN_M
    _samples: list[npt.NDArray[np.float32]] = field(default_factory=list, repr=False)
    _every: int = field(default=1, repr=False)  # sample every n-th frame (doubles when full)

    def add(self, depth_m: npt.NDArray[np.float32]) -> float | None:  # depth_m: [H, W]
        """Count one frame; returns its median depth (None when all zero)."""
        valid = depth_m[depth_m > 0]
        self.frames += 1
        self.pixels += depth_m.size
        self.invalid_pixels += depth_m.size - valid.size
        if not valid.size:
            self.all_zero_frames += 1
            return None
        if self.frames % self._every == 0:
            step = max(1, valid.size // _SAMPLES_PER_FRAME)
            self._samples.append(valid[::step][:_SAMPLES_PER_FRAME].copy())
            if len(self._samples) * _SAMPLES_PER_FRAME > _MAX_SAMPLES:
                self._samples = self._samples[::2]
                self._every *= 2
        median = float(np.median(valid))
        self.implausible_frames += not plausible(median)
        return median

    @property
    def invalid_fraction(self) -> float:
        return self.invalid_pixels / self.pixels if self.pixels else 0.0

    def percentiles(self) -> tuple[float, float, float] | None:
        """(1st percentile, median, 99th percentile) of the valid depths in metres, or None."""
        if not self._samples:
            return None
        p1, p50, p99 = np.percentile(np.concatenate(self._samples), [1, 50, 99])
        return float(p1), float(p50), float(p99)

    def describe(self) -> str:
        """``median 2.06 m (1%: 0.71 m, 99%: 4.10 m), 3.1% invalid`` or ``no valid depth``."""
        p = self.percentiles()
        invalid = f"{100 * self.invalid_fraction:.1f}% invalid"
        if p is None:
            return f"no valid depth, {invalid}"
        return f"median {p[1]:.3g} m (1%: {p[0]:.3g} m, 99%: {p[2]:.3g} m), {invalid}"


def likely_scale(median_m: float, scale: float, dtype: str) -> float | None:
    """The common scale for ``dtype`` that puts ``median_m`` (read at ``scale`` units per metre)
    nearest a typical depth, when that is another scale and makes it plausible; else None."""
    raw = median_m * scale
    best = min(COMMON_SCALES.get(dtype, ()), key=lambda s: abs(math.log(raw / s / TYPICAL_DEPTH_M)),
               default=None)  # fmt: skip
    if best is None or best == scale or not plausible(raw / best):
        return None
    return best


def scale_from_motion(
    a: RGBDFrame, b: RGBDFrame, scale: float, dtype: str, min_points: int = 200
) -> float | None:
    """The common scale for ``dtype`` under which ``a``'s depth, moved by the poses into ``b``,
    best agrees with ``b``'s depth; None when the frames share too little or ``scale`` fits.

    A depth scale error s scales every point but not the (metric) poses, so the surfaces seen
    by two frames a baseline apart only agree at the right scale. Each candidate is scored by
    the median relative depth difference at the pixels both frames see.
    """
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(a.depth > 0)
    if len(xs) < min_points:
        return None
    pick = rng.choice(len(xs), size=min(len(xs), 4000), replace=False)
    ys, xs = ys[pick], xs[pick]
    T_b_a = np.linalg.inv(b.T_world_cam) @ a.T_world_cam
    Ka, Kb = a.intrinsics, b.intrinsics
    rays = np.stack([(xs - Ka.cx) / Ka.fx, (ys - Ka.cy) / Ka.fy, np.ones(len(xs))])  # [3, N]
    errors: dict[float, float] = {}
    for cand in sorted({scale, *COMMON_SCALES.get(dtype, ())}):
        k = scale / cand  # metres at `cand` per metre read at `scale`
        p = T_b_a[:3, :3] @ (rays * a.depth[ys, xs] * k) + T_b_a[:3, 3:]
        z = p[2]
        front = z > 1e-6
        u = np.round(Kb.fx * p[0, front] / z[front] + Kb.cx).astype(np.int64)
        v = np.round(Kb.fy * p[1, front] / z[front] + Kb.cy).astype(np.int64)
        inside = (u >= 0) & (u < b.width) & (v >= 0) & (v < b.height)
        zb = b.depth[v[inside], u[inside]] * k
        seen = zb > 0
        if seen.sum() < min_points:
            continue
        errors[cand] = float(np.median(np.abs(z[front][inside][seen] - zb[seen]) / zb[seen]))
    if scale not in errors:
        return None
    best = min(errors, key=errors.__getitem__)
    # a clear winner only: surfaces that agree (within sensor noise and occlusions) at a scale
    # that has at most half the error of the one in use; random depth agrees at none
    if best == scale or errors[best] > MOTION_AGREE or errors[best] > 0.5 * errors[scale]:
        return None
    return best
