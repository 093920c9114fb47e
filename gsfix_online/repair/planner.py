"""Which views need repair: scores computed from cheap renders before any diffusion runs.

A view is worth repairing when the 3DGS map leaves holes in it (low alpha where the mesh sees a
surface), when the 3DGS render disagrees with the mesh render (floaters, blur, wrong colour), or
when the surfaces it sees were observed by few keyframes. A view that sees almost no mapped
surface is skipped too: GSFixer would have no condition to repair from. The policy is a frozen
dataclass; :func:`score_view` is a pure function of the renders, so skip decisions are
reproducible and their reason is reported with numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.core.se3 import pose_distances


@dataclass(frozen=True)
class SkipPolicy:
    enabled: bool = True  # False: repair every view (for comparisons; the score is still reported)
    alpha_hole: float = field(
        default=0.5, metadata=rng(0.0, 1.0, "a pixel whose 3DGS alpha is below this is a hole")
    )
    hole_fraction: float = field(
        default=0.02, metadata=rng(0.0, 1.0, "repair when more of the surface than this is holes")
    )
    disagree_level: float = field(
        default=0.12,
        metadata=rng(0.0, 1.0, "3DGS vs mesh colour difference (0..1, 4x4 blocks) that disagrees"),
    )
    disagree_fraction: float = field(
        default=0.05, metadata=rng(0.0, 1.0, "repair when more of the surface than this disagrees")
    )
    min_observations: int = field(
        default=2, metadata=rng(0, None, "surface seen by fewer keyframes is under-observed")
    )
    underobserved_fraction: float = field(
        default=0.10, metadata=rng(0.0, 1.0, "repair when more of the surface is under-observed")
    )
    min_surface_fraction: float = field(
        default=0.05, metadata=rng(0.0, 1.0, "skip views where the mesh covers less than this")
    )
    # Parts of the view neither map holds (never observed): nothing to compare there, but what
    # GSFixer inpaints. On the ship tank's novel views, two views the surface criteria passed
    # had 3DGS renders 4-7 dB below their OpenCV-inpainted mesh fill for this reason.
    empty_fraction: float = field(
        default=0.05,
        metadata=rng(0.0, 1.0, "repair when more of the image than this is empty in both maps"),
    )


@dataclass(frozen=True)
class ViewScore:
    surface_fraction: float  # pixels where the mesh render hit a surface
    hole_fraction: float  # of the surface: 3DGS alpha below policy.alpha_hole
    disagree_fraction: float  # of the surface: 3DGS and mesh colours differ
    underobserved_fraction: float  # of the surface: seen by few keyframes (nan: not known)
    repair: bool
    reason: str
    empty_fraction: float = 0.0  # of the image: no mesh surface and 3DGS alpha below alpha_hole

    def to_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


def _gray01(img: np.ndarray) -> np.ndarray:
    g = img.astype(np.float32) / 255.0
    return g.mean(axis=2) if g.ndim == 3 else g


def _blocks(img: np.ndarray, f: int = 4) -> np.ndarray:
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    return cv2.resize(img[:h, :w], (w // f, h // f), interpolation=cv2.INTER_AREA)


def score_view(
    gs_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    gs_alpha: npt.NDArray[np.floating],  # [H, W] in [0, 1]
    mesh_color: npt.NDArray[np.uint8],  # [H, W(, 3)]
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    policy: SkipPolicy,
    observations: npt.NDArray[np.integer] | None = None,  # [H, W] keyframes that saw the pixel
) -> ViewScore:
    """Score a requested view from its 3DGS and mesh renders; decide whether to repair it."""
    # 1. Check inputs (one message per mistake, at this public boundary).
    hw = gs_alpha.shape
    for name, arr in (
        ("gs_color", gs_color),
        ("mesh_color", mesh_color),
        ("mesh_valid", mesh_valid),
    ):
        if arr.shape[:2] != hw:
            raise ValueError(f"{name} must be {list(hw)} like gs_alpha, got {list(arr.shape)}")
    if observations is not None and observations.shape != hw:
        raise ValueError(f"observations must be {list(hw)}, got {list(observations.shape)}")

    # 2. Fractions of the surface the mesh sees.
    surface = mesh_valid.astype(bool)
    n_surface = int(surface.sum())
    surface_fraction = n_surface / surface.size
    if surface_fraction < policy.min_surface_fraction and policy.enabled:
        return ViewScore(
            surface_fraction,
            0.0,
            0.0,
            float("nan"),
            False,
            f"sees little mapped surface ({surface_fraction:.1%} < {policy.min_surface_fraction:.1%})",
        )
    holes = surface & (gs_alpha < policy.alpha_hole)
    hole_fraction = float(holes.sum()) / max(n_surface, 1)
    # Colours are compared on 4x4 blocks: the mesh's vertex colours are smoother than the 3DGS
    # render, and pixel-level texture is not what marks a broken view.
    both = _blocks((surface & ~holes).astype(np.float32)) > 0.99
    diff = np.abs(_blocks(_gray01(gs_color)) - _blocks(_gray01(mesh_color)))
    disagree_fraction = float((diff[both] > policy.disagree_level).mean()) if both.any() else 0.0
    empty_fraction = float((~surface & (gs_alpha < policy.alpha_hole)).mean())
    under = float("nan")
    if observations is not None and n_surface:
        under = float((observations[surface] < policy.min_observations).mean())

    # 3. Decide, naming the first criterion that asks for repair.
    reasons = []
    if hole_fraction > policy.hole_fraction:
        reasons.append(f"holes {hole_fraction:.1%} > {policy.hole_fraction:.1%}")
    if disagree_fraction > policy.disagree_fraction:
        reasons.append(
            f"3DGS/mesh disagree on {disagree_fraction:.1%} > {policy.disagree_fraction:.1%}"
        )
    if under == under and under > policy.underobserved_fraction:
        reasons.append(f"under-observed {under:.1%} > {policy.underobserved_fraction:.1%}")
    if empty_fraction > policy.empty_fraction:
        reasons.append(f"empty {empty_fraction:.1%} > {policy.empty_fraction:.1%}")
    if not policy.enabled:
        reasons.append("skipping disabled")
    if reasons:
        return ViewScore(
            surface_fraction, hole_fraction, disagree_fraction, under, True, "; ".join(reasons),
            empty_fraction,
        )  # fmt: skip
    return ViewScore(
        surface_fraction,
        hole_fraction,
        disagree_fraction,
        under,
        False,
        f"map explains the view (holes {hole_fraction:.1%}, disagreement {disagree_fraction:.1%}, "
        f"empty {empty_fraction:.1%})",
        empty_fraction,
    )


def observation_counts(
    depth_m: npt.NDArray[np.float32],  # [H, W] z-depth of the view (0 = no surface)
    K: npt.NDArray[np.float64],  # [3, 3] pixels, of the view
    T_world_cam: npt.NDArray[np.float64],  # [4, 4] the view's camera-to-world
    keyframe_T_world_cam: npt.NDArray[np.float64],  # [M, 4, 4]
    keyframe_K: npt.NDArray[np.float64],  # [3, 3] (one camera for all keyframes)
    keyframe_size: tuple[int, int],  # (width, height)
    max_range_m: float = 10.0,
) -> npt.NDArray[np.int32]:
    """For each pixel of a view, how many keyframes had its surface point inside their image,
    in front of them and within ``max_range_m``. Pixels without depth get 0."""
    h, w = depth_m.shape
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    rays = np.linalg.solve(K, np.stack([u + 0.0, v + 0.0, np.ones_like(z)]))  # [3, P]
    pts_cam = rays * z
    pts_w = T_world_cam[:3, :3] @ pts_cam + T_world_cam[:3, 3:4]
    counts = np.zeros(len(z), np.int32)
    W, H = keyframe_size
    for T in keyframe_T_world_cam:
        R, t = T[:3, :3], T[:3, 3:4]
        p = R.T @ (pts_w - t)
        zk = p[2]
        ok = (zk > 1e-3) & (zk < max_range_m)
        uv = keyframe_K[:2] @ (p / np.where(ok, zk, 1.0))
        # Integer pixel coordinates are pixel centres: the image spans [-0.5, W - 0.5).
        ok &= (uv[0] >= -0.5) & (uv[0] < W - 0.5) & (uv[1] >= -0.5) & (uv[1] < H - 0.5)
        counts += ok
    out = np.zeros((h, w), np.int32)
    out[v, u] = counts
    return out


def keyframe_distance(
    T_world_cam: npt.NDArray[np.float64],  # [4, 4] the view's camera-to-world
    keyframe_T_world_cam: npt.NDArray[np.float64],  # [M, 4, 4], M >= 1
    depth_m: float,  # typical distance of the surfaces the view sees, m
) -> float:
    """How far a view is from the nearest keyframe, in metres at the surface: the camera's
    translation plus its rotation angle (radians) times ``depth_m``, which is how far the
    rotation moves the surface point at the image centre. 0 at a keyframe's own pose."""
    kf = np.asarray(keyframe_T_world_cam, np.float64).reshape(-1, 4, 4)
    if len(kf) == 0:
        raise ValueError("keyframe_distance needs at least one keyframe pose")
    return float(pose_distances(T_world_cam, kf, depth_m).min())
