"""Sensor models: stereo-like depth noise and dropouts, image noise, VIO-like pose drift and jitter.

Depth is lost in blobs at random (``dropout``) and, optionally, where stereo matching fails on
real sensors: at grazing incidence and on dark surfaces (``surface_dropout``), and left of near
objects, where the second imager cannot see the background (``stereo_occlusion``).

All functions take a ``numpy.random.Generator`` so that the caller controls determinism
(``generate`` seeds one per frame from the scene seed and the frame index).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

# pose_drift 0.01 -> ~1 deg of yaw per metre travelled
DRIFT_YAW_RAD_PER_UNIT = np.radians(1.0) / 0.01
DRIFT_BIAS_WALK = 0.5  # the drift rates themselves random-walk by this fraction per sqrt(metre)


def dropout_mask(
    shape: tuple[int, int], fraction: float, blob_px: float, rng: np.random.Generator
) -> npt.NDArray[np.bool_]:
    """Blob-shaped invalid regions covering ``fraction`` of the image: smooth noise above its quantile."""
    import cv2

    if fraction <= 0.0:
        return np.zeros(shape, bool)
    field = cv2.GaussianBlur(
        rng.standard_normal(shape).astype(np.float32),
        (0, 0),
        blob_px,
        borderType=cv2.BORDER_REFLECT,
    )
    k = int(round(fraction * field.size))
    if k == 0:
        return np.zeros(shape, bool)
    thresh = np.partition(field.ravel(), field.size - k)[field.size - k]
    return field >= thresh


def noisy_depth(
    depth_m: F32,  # [H, W] noise-free depth along z, 0 = invalid
    k: float,  # sigma = k z^2 (1/m)
    dropout: float,
    blob_px: float,
    depth_min: float,
    depth_max: float,
    rng: np.random.Generator,
) -> F32:  # [H, W]
    """Stereo-like depth: Gaussian noise with sigma = k z^2, blob dropouts, invalid outside [min, max]."""
    z = depth_m.astype(np.float64)
    out = z + k * z * z * rng.standard_normal(z.shape)
    out[dropout_mask(z.shape, dropout, blob_px, rng)] = 0.0
    # Range limits apply to the measured value: the sensor only knows what it measured.
    out[(z <= 0) | (out < depth_min) | (out > depth_max)] = 0.0
    return out.astype(np.float32)


def surface_dropout(
    cos_incidence: F32,  # [H, W] |cos| of the angle between the view ray and the surface normal
    brightness: F32,  # [H, W] surface brightness, 8-bit display levels (0..255)
    grazing_deg: float,  # depth is lost beyond this incidence angle (90 = never)
    dark_level: float,  # and on surfaces darker than this (0 = never)
    blob_px: float,
    rng: np.random.Generator,
) -> npt.NDArray[np.bool_]:  # [H, W] True where depth is lost
    """Stereo failures on hard surfaces, in blobs: a loss probability per pixel (0 below the
    grazing angle, 1 from 10 deg beyond it; 1 at black, 0 from ``dark_level`` up, smoothly)
    compared with a spatially smooth uniform field (blurred noise through the normal CDF)."""
    import cv2
    from scipy.special import ndtr

    theta = np.degrees(np.arccos(np.clip(cos_incidence, 0.0, 1.0)))
    p = np.zeros(theta.shape, np.float64)
    if grazing_deg < 90.0:
        t = np.clip((theta - grazing_deg) / 10.0, 0.0, 1.0)
        p = np.maximum(p, t * t * (3 - 2 * t))
    if dark_level > 0.0:
        t = np.clip(1.0 - brightness / dark_level, 0.0, 1.0)
        p = np.maximum(p, t * t * (3 - 2 * t))
    field = cv2.GaussianBlur(
        rng.standard_normal(theta.shape).astype(np.float32),
        (0, 0),
        blob_px,
        borderType=cv2.BORDER_REFLECT,
    )
    u = ndtr(field / max(float(field.std()), 1e-12))  # ~uniform in (0, 1), spatially smooth
    return u < p


def stereo_occlusion(
    depth_m: F32,  # [H, W] true depth along z, 0 = no surface
    fx: float,  # px
    baseline_m: float,  # the second imager sits this far along +x (right)
    max_shift_px: int = 256,
) -> npt.NDArray[np.bool_]:  # [H, W] True where the second imager cannot see the surface
    """Stereo occlusion holes: a pixel has no depth when a nearer surface to its right hides it
    from the right imager, i.e. some pixel k columns to the right has a disparity larger by more
    than k. That is the band left of every near object, as wide as the disparity step there."""
    valid = depth_m > 0
    d = np.where(valid, fx * baseline_m / np.where(valid, depth_m, 1.0), 0.0)  # disparity, px
    out = np.zeros(depth_m.shape, bool)
    if not valid.any():
        return out
    span = min(int(np.ceil(d.max() - d[valid].min())), max_shift_px, depth_m.shape[1] - 1)
    for k in range(1, span + 1):
        out[:, :-k] |= d[:, k:] - d[:, :-k] > k
    return out & valid


def noisy_image(color_f: F32, sigma: float, rng: np.random.Generator) -> npt.NDArray[np.uint8]:
    """Display values 0..255 (float, [H, W] or [H, W, 3]) plus Gaussian noise, rounded to uint8."""
    noisy = (
        color_f + sigma * rng.standard_normal(color_f.shape).astype(np.float32)
        if sigma > 0
        else color_f
    )
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def drift_poses(
    poses: F64,  # [N, 4, 4] exact T_world_cam
    drift: float,
    noise_m: float,
    noise_deg: float,
    rng: np.random.Generator,
) -> F64:  # [N, 4, 4] estimated T_world_cam; frame 0 is exact
    """VIO-like estimate: drift growing with distance travelled plus per-frame jitter.

    Drift is a world-frame correction ``D_i`` (estimate = D_i @ truth) built incrementally: per
    step of length ds the position drifts by ``b * ds`` and the heading by ``w * ds`` about the
    vertical through the current estimated position (roll and pitch stay observable from gravity,
    as in VIO). The rates b (m/m, ~``drift``) and w (rad/m) start random and random-walk. Jitter is
    independent per frame and does not accumulate.
    """
    poses = np.asarray(poses, np.float64)
    out = poses.copy()
    if drift > 0:
        b = rng.normal(0.0, drift, 3) * [1.0, 1.0, 0.5]
        w = rng.normal(0.0, drift * DRIFT_YAW_RAD_PER_UNIT)
        D = np.eye(4)
        for i in range(1, len(poses)):
            ds = float(np.linalg.norm(poses[i, :3, 3] - poses[i - 1, :3, 3]))
            b += rng.normal(0.0, drift * DRIFT_BIAS_WALK * np.sqrt(ds), 3) * [1.0, 1.0, 0.5]
            w += rng.normal(0.0, drift * DRIFT_YAW_RAD_PER_UNIT * DRIFT_BIAS_WALK * np.sqrt(ds))
            pivot = (D @ poses[i])[:3, 3]
            step = np.eye(4)
            step[:3, :3] = Rotation.from_rotvec([0.0, 0.0, w * ds]).as_matrix()
            step[:3, 3] = pivot - step[:3, :3] @ pivot + b * ds
            D = step @ D
            out[i] = D @ poses[i]
    if noise_m > 0 or noise_deg > 0:
        n = len(poses)
        jitter = np.tile(np.eye(4), (n, 1, 1))
        jitter[:, :3, :3] = Rotation.from_rotvec(
            rng.normal(0.0, np.radians(noise_deg), (n, 3))
        ).as_matrix()
        jitter[:, :3, 3] = rng.normal(0.0, noise_m, (n, 3))
        jitter[0] = np.eye(4)
        out = out @ jitter  # body-frame jitter
    return out
