"""Random mask augmentation for GSFixer fine-tuning (GSFix3D Sec. 3.1.2).

The paper draws masks from a data set of real object masks, which cannot be downloaded here.
The masks below look like real holes instead, from three switchable sources:

- procedural object-like shapes: unions of ellipses and perturbed polygons with smooth outlines;
- disocclusions: the pixels of a keyframe that a nearby keyframe's depth, forward-warped into
  it, does not cover (what a moved camera sees that the other one did not);
- alpha holes: where a Gaussian-map render at a perturbed pose has low alpha (the render itself
  comes from a callback of the caller; here it is only an alpha image).

A draw (:func:`draw_masks`) applies the policy in :class:`MaskConfig`: with ``p_shared`` one mask
for both images (an occlusion), and independently with ``p_gs_only`` a mask for the 3DGS image
only (and, not in the paper, with ``p_mesh_only`` one for the mesh image only: mesh holes over
a good 3DGS render). :func:`apply_masks` blacks out the masked pixels; masks on the 3DGS image
are Gaussian blurred first (soft edges, as 3DGS holes have), mesh masks stay hard. All functions
are pure: randomness comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.fixer.config import MaskConfig

BoolImage = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class MaskDraw:
    """One augmentation decision: masks are True where content is removed."""

    shared: BoolImage | None  # [H, W] on mesh and 3DGS, or None
    gs_only: BoolImage | None  # [H, W] on 3DGS only, or None
    mesh_only: BoolImage | None = None  # [H, W] on the mesh only, or None


# ------------------------------------------------------------------------------------------
# Sources
# ------------------------------------------------------------------------------------------


def procedural_mask(
    rng: np.random.Generator, height: int, width: int, cfg: MaskConfig
) -> BoolImage:  # [H, W]
    """A union of 1..max_shapes ellipses and perturbed polygons, outlines smoothed."""
    canvas = np.zeros((height, width), np.uint8)
    area = rng.uniform(*cfg.shape_area) * height * width
    n = int(rng.integers(1, cfg.max_shapes + 1))
    for _ in range(n):
        r = math.sqrt(area / n / math.pi)  # radius of a disc of this piece's area
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        if rng.random() < 0.5:
            aspect = rng.uniform(0.4, 1.0)
            axes = (max(1, int(r / math.sqrt(aspect))), max(1, int(r * math.sqrt(aspect))))
            angle = rng.uniform(0, 180)
            cv2.ellipse(canvas, (int(cx), int(cy)), axes, angle, 0, 360, 255, -1)
        else:
            k = int(rng.integers(5, 12))
            theta = np.sort(rng.uniform(0, 2 * math.pi, k))
            radii = r * rng.uniform(0.5, 1.4, k)
            pts = np.stack([cx + radii * np.cos(theta), cy + radii * np.sin(theta)], 1)
            cv2.fillPoly(canvas, [pts.round().astype(np.int32)], 255)
    # Smooth the outline: blur, then threshold at half (rounds corners, keeps the area).
    sigma = max(1.0, 0.02 * min(height, width))
    smooth = cv2.GaussianBlur(canvas.astype(np.float32), (0, 0), sigma)
    return smooth > 127.5


def disocclusion_mask(
    depth_src_m: npt.NDArray[np.float32],  # [Hs, Ws] metres, 0 = invalid
    K_src: npt.NDArray[np.float64],  # [3, 3] pixels
    T_world_src: npt.NDArray[np.float64],  # [4, 4] camera-to-world
    K_tgt: npt.NDArray[np.float64],  # [3, 3] pixels
    T_world_tgt: npt.NDArray[np.float64],  # [4, 4] camera-to-world
    height: int,
    width: int,
    close_px: int = 1,
) -> BoolImage:  # [H, W] True = not covered
    """Pixels of the target view that no valid source pixel lands on when forward-warped.

    Each source pixel centre is unprojected with its depth, moved into the target camera and
    rounded to the nearest target pixel. A morphological closing of ``close_px`` fills the
    cracks that forward warping leaves where the target sees a surface larger than the source.
    """
    hs, ws = depth_src_m.shape
    v, u = np.mgrid[0:hs, 0:ws]
    z = depth_src_m.astype(np.float64)
    ok = z > 0
    x = (u[ok] - K_src[0, 2]) / K_src[0, 0] * z[ok]
    y = (v[ok] - K_src[1, 2]) / K_src[1, 1] * z[ok]
    p_src = np.stack([x, y, z[ok], np.ones_like(x)], 0)  # [4, N]
    T_tgt_src = np.linalg.inv(T_world_tgt) @ T_world_src
    p = (T_tgt_src @ p_src)[:3]
    front = p[2] > 1e-6
    p = p[:, front]
    with np.errstate(over="ignore", invalid="ignore"):  # depths of 1e30 m: inf, tested below
        uf = np.rint(K_tgt[0, 0] * p[0] / p[2] + K_tgt[0, 2])
        vf = np.rint(K_tgt[1, 1] * p[1] / p[2] + K_tgt[1, 2])
    # compared as floats: casting inf or 1e30 to int64 wraps around
    inside = (uf >= 0) & (uf < width) & (vf >= 0) & (vf < height)
    covered = np.zeros((height, width), np.uint8)
    covered[vf[inside].astype(np.int64), uf[inside].astype(np.int64)] = 1
    if close_px > 0:
        kernel = np.ones((2 * close_px + 1, 2 * close_px + 1), np.uint8)
        covered = cv2.morphologyEx(covered, cv2.MORPH_CLOSE, kernel)
    return covered == 0


def informative_hole(
    alpha: npt.NDArray[np.float32],  # [H, W] map alpha rendered at a perturbed pose
    threshold: float = 0.5,
    min_frac: float = 0.02,
    max_frac: float = 0.8,
) -> BoolImage | None:  # [H, W]
    """The alpha holes of a perturbed-pose render as a mask candidate, or None when they cover too
    little (nothing to learn) or too much (the pose looked away from the map) of the image."""
    hole = alpha_hole_mask(alpha, threshold)
    return hole if min_frac < hole.mean() < max_frac else None


def alpha_hole_mask(
    alpha: npt.NDArray[np.float32],  # [H, W] render opacity in [0, 1]
    threshold: float = 0.5,
    open_px: int = 1,
) -> BoolImage:  # [H, W]
    """Holes of a Gaussian-map render: alpha below ``threshold``, specks removed by an opening."""
    hole = (alpha < threshold).astype(np.uint8)
    if open_px > 0:
        kernel = np.ones((2 * open_px + 1, 2 * open_px + 1), np.uint8)
        hole = cv2.morphologyEx(hole, cv2.MORPH_OPEN, kernel)
    return hole.astype(bool)


def perturbed_pose(
    T_world_cam: npt.NDArray[np.float64],  # [4, 4] camera-to-world
    rng: np.random.Generator,
    max_deg: float = 25.0,  # rotation about a random axis through the camera centre
    max_m: float = 0.3,  # translation in a random direction
) -> npt.NDArray[np.float64]:  # [4, 4]
    """A pose near ``T_world_cam`` from which to render the map's alpha holes: the render then
    has the holes of a view off the trajectory, as the views a planner asks to repair do."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * math.radians(rng.uniform(0.3, 1.0) * max_deg))
    step = rng.normal(size=3)
    step *= rng.uniform(0.0, max_m) / np.linalg.norm(step)
    out = np.array(T_world_cam, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ R
    out[:3, 3] += step
    return out


# ------------------------------------------------------------------------------------------
# Policy
# ------------------------------------------------------------------------------------------


def _one_mask(
    rng: np.random.Generator,
    height: int,
    width: int,
    cfg: MaskConfig,
    disocclusions: list[BoolImage],
    alpha_holes: list[BoolImage],
) -> BoolImage:
    """Pick a source uniformly among those switched on that have masks; shapes need none."""
    choices: list[list[BoolImage] | None] = []
    if cfg.use_shapes:
        choices.append(None)
    if cfg.use_disocclusion and disocclusions:
        choices.append(disocclusions)
    if cfg.use_alpha_holes and alpha_holes:
        choices.append(alpha_holes)
    if not choices:  # every source off or empty: fall back to shapes rather than no mask
        return procedural_mask(rng, height, width, cfg)
    pick = choices[int(rng.integers(len(choices)))]
    if pick is None:
        return procedural_mask(rng, height, width, cfg)
    mask = pick[int(rng.integers(len(pick)))]
    return mask[:, ::-1] if rng.random() < 0.5 else mask  # a mirrored copy is as plausible


def draw_masks(
    cfg: MaskConfig,
    rng: np.random.Generator,
    height: int,
    width: int,
    disocclusions: list[BoolImage] | None = None,
    alpha_holes: list[BoolImage] | None = None,
) -> MaskDraw:
    """One draw of the policy: a shared mask with ``p_shared``, a 3DGS-only one with ``p_gs_only``,
    and a mesh-only one with ``p_mesh_only``."""
    if not cfg.enabled:
        return MaskDraw(None, None)
    dis, alp = disocclusions or [], alpha_holes or []
    for m in (*dis, *alp):
        if m.shape != (height, width) or m.dtype != np.bool_:
            raise ValueError(
                f"candidate masks must be bool [{height}, {width}], got {m.dtype} {m.shape}"
            )
    # Both coins are tossed on every draw so that the two events stay independent.
    shared_on = rng.random() < cfg.p_shared
    gs_on = rng.random() < cfg.p_gs_only
    shared = _one_mask(rng, height, width, cfg, dis, alp) if shared_on else None
    gs_only = _one_mask(rng, height, width, cfg, dis, alp) if gs_on else None
    mesh_only = None
    if cfg.p_mesh_only > 0 and rng.random() < cfg.p_mesh_only:  # 0: the paper's random stream
        mesh_only = _one_mask(rng, height, width, cfg, dis, alp)
    return MaskDraw(shared, gs_only, mesh_only)


def mesh_cut(draw: MaskDraw, height: int, width: int) -> BoolImage:  # [H, W]
    """Where a draw blacks out the mesh image (its shared and mesh-only masks): the reference
    warp, which follows the mesh's depth, loses its pixels there too."""
    cut = np.zeros((height, width), bool)
    for m in (draw.shared, draw.mesh_only):
        if m is not None:
            cut |= m
    return cut


def _blur(mask: Tensor, sigma: float) -> Tensor:  # [1, 1, H, W] -> same, soft
    import kornia

    if sigma <= 0:
        return mask
    k = 2 * math.ceil(2.5 * sigma) + 1  # GSFix3D: 51 x 51 at sigma 10
    return kornia.filters.gaussian_blur2d(mask, (k, k), (sigma, sigma), border_type="replicate")


def apply_masks(
    image_mesh: Tensor,  # [C, H, W] in [0, 1]
    image_gs: Tensor,  # [C, H, W] in [0, 1]
    draw: MaskDraw,
    cfg: MaskConfig,
) -> tuple[Tensor, Tensor]:  # (mesh, gs), masked pixels black
    """Black out the drawn masks: hard on the mesh image, Gaussian-blurred on the 3DGS image."""
    _, h, w = image_gs.shape
    sigma = cfg.blur_sigma_frac * min(h, w)
    keep_gs = torch.ones(1, 1, h, w, dtype=image_gs.dtype, device=image_gs.device)
    mesh = image_mesh
    targets = (
        (draw.shared, True, True),
        (draw.gs_only, False, True),
        (draw.mesh_only, True, False),
    )
    for mask, on_mesh, on_gs in targets:
        if mask is None:
            continue
        m = torch.from_numpy(np.ascontiguousarray(mask)).to(image_gs)[None, None]
        if on_mesh:
            mesh = mesh * (1 - m[0])
        if on_gs:
            keep_gs = keep_gs * (1 - _blur(m, sigma))
    return mesh, image_gs * keep_gs[0]
