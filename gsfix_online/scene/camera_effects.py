"""Camera effects on the colour image: auto-exposure gain changes and motion blur.

Both act on linear radiance (the renderer's light before its tone curve), as a sensor does: the
exposure gain scales the light, motion blur averages it over the shutter time. The caller then
applies the tone curve, the sensor noise and the 8-bit rounding. Ground-truth images skip them.

Auto-exposure: a gain per frame in [g_min, g_max], the mix of a smooth wander (Gaussian-filtered
white noise over ``smooth_s`` seconds) and occasional steps (a new level with probability
``step_prob`` per frame, as when an auto-exposure loop reacts to a lamp or a dark opening).
Auto white balance: per-channel gains that wander the same way but keep the brightness.

Motion blur: a gather approximation. Each pixel's surface point (from the sharp render) is
projected into the camera poses where the shutter opens and closes; the blurred pixel averages the
sharp image at the pixel minus the displacement at times spread over the shutter (linear in time
between the stamp and either end). Exact for a locally uniform motion field, approximate at
occlusion boundaries; deterministic (no random numbers), and exactly the sharp image when the
camera does not move.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import interpolate_pose
from gsfix_online.core.types import Intrinsics

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

BLUR_STEP_PX = 1.5  # auto sample count: one shutter sample per this much image motion
BLUR_MAX_AUTO_SAMPLES = 32
STEP_WEIGHT = 0.5  # share of the (normalised log) gain given to steps when steps are on
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # linear RGB -> luminance (as the renderer's gray)


def exposure_gains(
    n: int,
    fps: float,
    gain_min: float,
    gain_max: float,
    smooth_s: float,
    step_prob: float,
    rng: np.random.Generator,
) -> F64:  # [n] gains in [gain_min, gain_max]
    """Per-frame auto-exposure gains; all 1 when ``gain_min == gain_max == 1``.

    In log gain, ``mid + half * x`` with x in [-1, 1]: x mixes tanh of unit-variance smoothed noise
    and, when ``step_prob`` > 0, a piecewise-constant level redrawn uniformly at random frames.
    """
    from scipy.ndimage import gaussian_filter1d

    if gain_min == gain_max == 1.0:
        return np.ones(n)
    lo, hi = np.log(gain_min), np.log(gain_max)
    mid, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    white = rng.standard_normal(n)
    smooth = gaussian_filter1d(white, max(smooth_s * fps, 1e-3), mode="reflect")
    smooth = smooth - smooth.mean()
    smooth = np.tanh(1.2 * smooth / max(float(smooth.std()), 1e-12))
    steps = rng.random(n) < step_prob
    levels = rng.uniform(-1.0, 1.0, n)
    level = levels[np.maximum.accumulate(np.where(steps, np.arange(n), 0))]  # [n] last step's level
    w = STEP_WEIGHT if step_prob > 0 else 0.0
    x = np.clip((1.0 - w) * smooth + w * level, -1.0, 1.0)
    return np.exp(mid + half * x)


def white_balance_gains(
    n: int,
    fps: float,
    sigma: float,
    smooth_s: float,
    rng: np.random.Generator,
) -> F64:  # [n, 3] per-channel gains, luminance-neutral
    """Auto white balance wandering: per channel, a log gain of std ``sigma`` smoothed over
    ``smooth_s`` seconds, rescaled so that each frame's luminance gain is 1 (the colour shifts,
    the brightness does not)."""
    from scipy.ndimage import gaussian_filter1d

    white = rng.standard_normal((n, 3))
    smooth = gaussian_filter1d(white, max(smooth_s * fps, 1e-3), axis=0, mode="reflect")
    smooth = (smooth - smooth.mean(0)) / np.maximum(smooth.std(0), 1e-12)
    g = np.exp(sigma * smooth)
    return g / (g @ LUMINANCE)[:, None]


def pose_at(
    poses: F64,  # [N, 4, 4] T_world_cam of the whole sequence
    i: int,
    offset: float,  # in frames, within [-1, 1]
) -> F64:  # [4, 4]
    """The pose ``offset`` frames from frame ``i``: SE(3)-interpolated toward the previous or next
    frame, held at the first and last frame (the camera starts and ends at rest). A neighbour
    with an identical pose gives that pose exactly."""
    j = i + (1 if offset > 0 else -1)
    if offset == 0 or not 0 <= j < len(poses) or np.array_equal(poses[j], poses[i]):
        return poses[i]
    return interpolate_pose(poses[i], poses[j], abs(float(offset)))


def project(
    points: F64,  # [H, W, 3] world
    intr: Intrinsics,
    T_world_cam: F64,  # [4, 4]
) -> tuple[F64, npt.NDArray[np.bool_]]:  # pixel coordinates [H, W, 2] (u, v) and z > 0 [H, W]
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    pc = (points - t) @ R  # [H, W, 3] camera frame (R^T (p - t))
    z = pc[..., 2]
    ok = z > 1e-6
    zs = np.where(ok, z, 1.0)
    uv = np.stack([intr.fx * pc[..., 0] / zs + intr.cx, intr.fy * pc[..., 1] / zs + intr.cy], -1)
    return uv, ok


def image_motion(
    points: F64,  # [H, W, 3] world points of the sharp render
    mask: npt.NDArray[np.bool_],  # [H, W] pixels that hit something
    intr: Intrinsics,
    T_ref: F64,  # [4, 4] the sharp render's pose
    T_samples: F64,  # [S, 4, 4] other poses
) -> F32:  # [S, H, W, 2] displacement of each pixel's point at each pose, px
    """Where each pixel's surface point moves in the image at each sample pose (0 off the mesh)."""
    uv0, ok0 = project(points, intr, T_ref)
    flows = np.zeros((len(T_samples), *mask.shape, 2), np.float32)
    for k, T in enumerate(T_samples):
        if np.array_equal(T, T_ref):
            continue  # exactly no motion
        uv, ok = project(points, intr, T)
        valid = (mask & ok0 & ok)[..., None]
        flows[k] = np.where(valid, uv - uv0, 0.0)
    return flows


def shutter_ends(
    poses: F64,  # [N, 4, 4] T_world_cam of the whole sequence
    i: int,
    shutter_frames: float,  # shutter time x fps, in (0, 1]
) -> F64:  # [2, 4, 4] poses when the shutter of frame i opens and closes
    """The shutter is centred on the frame stamp: it opens half a shutter before it."""
    assert 0.0 < shutter_frames <= 1.0
    return np.stack([pose_at(poses, i, -shutter_frames / 2), pose_at(poses, i, shutter_frames / 2)])


def blur_sample_count(
    flows: F32,  # [2, H, W, 2] image motion at the shutter's opening and closing
    mask: npt.NDArray[np.bool_],  # [H, W]
) -> int:
    """One sample per ~1.5 px of the 99th-percentile image motion over the shutter, at least 2,
    at most 32."""
    d = np.linalg.norm(flows[1] - flows[0], axis=-1)[mask]
    extent = float(np.percentile(d, 99)) if d.size else 0.0
    return int(np.clip(np.ceil(extent / BLUR_STEP_PX) + 1, 2, BLUR_MAX_AUTO_SAMPLES))


def motion_blur(
    image: F32,  # [H, W, C] or [H, W] linear radiance of the sharp render
    flow_open: F32,  # [H, W, 2] image motion from the frame stamp back to the shutter's opening
    flow_close: F32,  # [H, W, 2] ... and forward to its closing
    samples: int,
) -> F32:  # same shape as image: the average over the shutter
    """Average of the sharp image sampled at each pixel minus its displacement at ``samples``
    times spread evenly over the shutter (interval midpoints).

    The displacement grows linearly from 0 at the stamp to ``flow_open`` / ``flow_close`` at the
    shutter's ends (a few degrees of turn at most: the exact motion is that close to linear).
    Written as ``image + mean(sample - image)``, so pixels that do not move keep their value bit
    for bit.
    """
    import cv2

    img = np.ascontiguousarray(image, np.float32)
    h, w = img.shape[:2]
    gu, gv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    acc = np.zeros_like(img)
    for a in (np.arange(samples) + 0.5) / samples * 2.0 - 1.0:  # shutter time in [-1, 1]
        f = flow_close if a > 0 else flow_open
        if a == 0 or not f.any():
            continue
        k = np.float32(abs(a))
        s = cv2.remap(
            img, gu - k * f[..., 0], gv - k * f[..., 1], cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip
        acc += s.reshape(img.shape) - img
    return img + acc / np.float32(samples)
