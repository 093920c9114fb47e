"""Image quality metrics for repaired views: PSNR and SSIM (kornia) on uint8 or [0, 1] images.

Images are ``[H, W]`` (grayscale) or ``[H, W, C]`` numpy arrays or torch tensors, uint8 (0..255)
or floating point (0..1). Both images of a pair must have the same shape; a colour image is never
compared with a grayscale one silently (convert first). SSIM uses the 11x11 Gaussian window of
the original SSIM paper. :func:`masked_scores` scores parts of an image (e.g. the region classes
of :func:`gsfix_online.repair.fallback.regions`): PSNR of the part's mean squared error, and the
SSIM map (computed on the whole image, so each pixel's window sees its real neighbours) averaged
over the part's pixels; :func:`pooled` sums such parts over views, weighting each by its pixels.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

SSIM_WINDOW = 11


@dataclass(frozen=True)
class ImageScores:
    psnr_db: float
    ssim: float


def to_chw01(img: npt.NDArray | torch.Tensor, name: str = "image") -> torch.Tensor:
    """[H, W] or [H, W, C] uint8/float image -> float32 [C, H, W] tensor in [0, 1]."""
    if isinstance(img, np.ndarray):  # a copy where needed: decoded messages are read-only
        img = np.ascontiguousarray(img) if img.flags.writeable else np.array(img)
    t = torch.as_tensor(img)
    if t.ndim not in (2, 3) or (t.ndim == 3 and t.shape[2] not in (1, 3)):
        raise ValueError(f"{name} must be [H, W] or [H, W, 1|3], got shape {list(t.shape)}")
    if t.dtype == torch.uint8:
        t = t.float() / 255.0
    elif t.is_floating_point():
        t = t.float()
    else:
        raise ValueError(f"{name} must be uint8 or floating point, got {t.dtype}")
    return t[None] if t.ndim == 2 else t.permute(2, 0, 1)


def _pair(
    a: npt.NDArray | torch.Tensor, b: npt.NDArray | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    x, y = to_chw01(a, "prediction"), to_chw01(b, "target")
    if x.shape != y.shape:
        raise ValueError(
            f"prediction and target must have the same shape, got {list(x.shape)} and {list(y.shape)}"
        )
    return x, y


def psnr(
    pred: npt.NDArray | torch.Tensor,
    target: npt.NDArray | torch.Tensor,
    mask: npt.NDArray | None = None,
) -> float:
    """PSNR in dB over all pixels, or over ``mask`` (bool [H, W]) only. Identical images: inf."""
    x, y = _pair(pred, target)
    err = (x - y) ** 2
    if mask is not None:
        m = torch.as_tensor(np.asarray(mask, bool))
        if m.shape != x.shape[1:]:
            raise ValueError(f"mask must be [H, W] = {list(x.shape[1:])}, got {list(m.shape)}")
        if not bool(m.any()):
            return float("nan")
        err = err[:, m]
    return _psnr_db(float(err.mean()))


def _psnr_db(mse: float) -> float:  # mse of [0, 1] values
    return float("inf") if mse == 0.0 else float(-10.0 * np.log10(mse))


def ssim(pred: npt.NDArray | torch.Tensor, target: npt.NDArray | torch.Tensor) -> float:
    """Mean SSIM (kornia, 11x11 Gaussian window) over the image and its channels."""
    return float(ssim_map(pred, target).mean())


def ssim_map(
    pred: npt.NDArray | torch.Tensor, target: npt.NDArray | torch.Tensor
) -> torch.Tensor:  # [H, W]: SSIM of each pixel's window, mean over channels
    return _ssim_map(*_pair(pred, target))


def _ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:  # [C, H, W] x2 -> [H, W]
    from kornia.metrics import ssim as kssim

    # contiguous and without autograd: kornia's faster CPU path (2x measured on 80x60 images)
    with torch.inference_mode():
        x, y = x.contiguous()[None], y.contiguous()[None]
        return kssim(x, y, SSIM_WINDOW, max_val=1.0)[0].mean(dim=0)


def scores(pred: npt.NDArray | torch.Tensor, target: npt.NDArray | torch.Tensor) -> ImageScores:
    return ImageScores(psnr(pred, target), ssim(pred, target))


@dataclass(frozen=True)
class MaskedScores:
    """Scores over a set of pixels (one mask of one image, or pooled over images)."""

    psnr_db: float  # of ``mse``; inf where it is 0
    ssim: float  # the SSIM map averaged over the pixels
    mse: float  # mean squared error of [0, 1] values over the pixels and channels
    pixels: int


def masked_scores(
    pred: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    target: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    masks: Mapping[str, npt.NDArray[np.bool_]],  # name -> [H, W]
) -> dict[str, MaskedScores]:
    """PSNR and SSIM of each mask's pixels; a mask with no pixels is left out."""
    x, y = _pair(pred, target)
    h, w = x.shape[1:]
    for name, m in masks.items():
        if not isinstance(m, np.ndarray) or m.dtype != np.bool_ or m.shape != (h, w):
            got = f"{m.dtype} {list(m.shape)}" if isinstance(m, np.ndarray) else type(m).__name__
            raise ValueError(f"mask {name!r} must be bool [H, W] = {[h, w]}, got {got}")
    err = ((x - y) ** 2).mean(dim=0)  # [H, W]
    smap = _ssim_map(x, y)  # [H, W]
    out = {}
    for name, m in masks.items():
        n = int(m.sum())
        if n:
            sel = torch.from_numpy(m)
            mse = float(err[sel].double().mean())
            out[name] = MaskedScores(_psnr_db(mse), float(smap[sel].double().mean()), mse, n)
    return out


def pooled(parts: Iterable[MaskedScores]) -> MaskedScores | None:
    """The scores of the union of ``parts`` (each weighted by its pixels); None if empty."""
    parts = [p for p in parts if p.pixels]
    n = sum(p.pixels for p in parts)
    if not n:
        return None
    mse = sum(p.mse * p.pixels for p in parts) / n
    return MaskedScores(_psnr_db(mse), sum(p.ssim * p.pixels for p in parts) / n, mse, n)


def region_scores(
    pred: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    target: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    region: npt.NDArray[np.uint8] | None,  # [H, W] index into ``names``; None: no regions
    names: Sequence[str],
) -> tuple[MaskedScores, dict[str, MaskedScores]]:
    """The whole image's scores and each region's (regions without pixels left out), from one
    SSIM map."""
    h, w = np.shape(pred)[:2]
    masks = {"": np.ones((h, w), bool)}
    if region is not None:
        masks.update({name: region == i for i, name in enumerate(names)})
    by_mask = masked_scores(pred, target, masks)
    return by_mask.pop(""), by_mask


def _luma_gradient(img: npt.NDArray, dtype: type = np.float32) -> tuple[npt.NDArray, npt.NDArray]:
    """The y and x central differences of an image's luma in [0, 1] units; ``[H, W, 3]`` or
    ``[H, W]``, uint8 or floats in [0, 1]."""
    a = np.asarray(img)
    a = a.astype(dtype) / 255.0 if a.dtype == np.uint8 else a.astype(dtype)
    luma = a @ np.asarray([0.299, 0.587, 0.114], dtype) if a.ndim == 3 else a
    gy, gx = np.gradient(luma)
    return gy, gx


def sharpness(
    img: npt.NDArray, mask: npt.NDArray | None = None, footprint_px2: float = 0.0
) -> float:
    """Mean gradient magnitude of an image's luma (central differences), in [0, 1] units per
    pixel: a veil of large blurred Gaussians lowers it; ``[H, W, 3]`` or ``[H, W]``, uint8 or
    floats in [0, 1]. With ``mask`` ([H, W] bool), the mean over its pixels (NaN if none).
    With ``footprint_px2``, of the image convolved with a Gaussian of that variance (px²) first:
    a splat renderer's own low-pass (``render_output.EPS2D``) makes this the most a render of a
    map that holds the image exactly can have."""
    if footprint_px2 < 0:
        raise ValueError(f"footprint_px2 must be >= 0, got {footprint_px2}")
    if footprint_px2 > 0:
        import cv2

        a = np.asarray(img)
        a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
        img = cv2.GaussianBlur(a, (0, 0), math.sqrt(footprint_px2), borderType=cv2.BORDER_REFLECT)
    gy, gx = _luma_gradient(img)
    g = np.hypot(gx, gy)
    if mask is None:
        return float(g.mean())
    m = np.asarray(mask, bool)
    if m.shape != g.shape:
        raise ValueError(f"mask must be {list(g.shape)} like the image, got {list(m.shape)}")
    return float(g[m].mean()) if m.any() else math.nan


def edge_gain(img: npt.NDArray, truth: npt.NDArray, mask: npt.NDArray | None = None) -> float:
    """How much of the truth's edges an image reproduces, at their contrast: the least-squares
    coefficient of the image's luma gradient field on the truth's (the sum of their dot products
    over the truth's squared gradient magnitudes; central differences as :func:`sharpness`).
    1 for the truth itself; a blur or a veil lowers it; gradients the truth lacks (grain,
    seams, facets) leave it unchanged where they are uncorrelated with the truth's. Unlike
    :func:`sharpness` it tells lost detail from removed artefacts. Images ``[H, W, 3]`` or
    ``[H, W]`` of one height and width, uint8 or floats in [0, 1]; with ``mask`` ([H, W] bool)
    the sums run over its pixels. NaN if the truth is flat there."""
    if np.shape(img)[:2] != np.shape(truth)[:2]:
        raise ValueError(f"edge_gain needs images of one shape, got {list(np.shape(img))} "
                         f"and {list(np.shape(truth))}")  # fmt: skip
    (iy, ix), (ty, tx) = _luma_gradient(img, np.float64), _luma_gradient(truth, np.float64)
    dot, sq = ix * tx + iy * ty, tx * tx + ty * ty
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != sq.shape:
            raise ValueError(f"mask must be {list(sq.shape)} like the images, got {list(m.shape)}")
        dot, sq = dot[m], sq[m]
    energy = float(sq.sum())
    return float(dot.sum()) / energy if energy > 0 else math.nan


def block_gradient_ratio(
    img: npt.NDArray | torch.Tensor,  # [H, W] or [H, W, C], uint8 or [0, 1]
    block: int = 4,  # the codec's block, pixels (pixel-unshuffle factor, VAE downsampling)
    offset: int = 0,  # where the first block starts, pixels
) -> float:
    """Block artefact measure: the mean squared difference of neighbouring pixels across the
    boundaries of a ``block``-pixel grid, over that inside blocks (each a sum over the two axes).
    About 1 for an image with no preferred grid; above 1 where the grid shows (a codec's block
    pattern). Compare it with the ground truth's, not with 1: an image's content can favour a
    grid too. Inf where pixels differ only across boundaries; NaN for a flat image."""
    if block < 2:
        raise ValueError(f"block must be >= 2 pixels, got {block}")
    x = to_chw01(img).double()
    a = b = 0.0  # mean energy across boundaries and inside blocks, summed over the two axes
    for d, axis in ((x[:, :, 1:] - x[:, :, :-1], 2), (x[:, 1:, :] - x[:, :-1, :], 1)):
        # difference i is between pixels i and i + 1: a boundary where i + 1 starts a block
        starts = (torch.arange(d.shape[axis]) + 1 - offset) % block == 0
        e = (d**2).mean(dim=0)  # [H, W-1] or [H-1, W]
        e = e if axis == 2 else e.T
        a += e[:, starts].mean().item()
        b += e[:, ~starts].mean().item()
    if b > 0:
        return a / b
    return float("inf") if a > 0 else float("nan")


@dataclass(frozen=True)
class Headroom:
    """How much of a view's error one region holds, and what removing it would gain."""

    pixel_share: float  # of the view's pixels
    error_share: float  # of the view's squared error
    exact_gain_db: float  # whole-view PSNR gain if the region were exact
    mean_fill_gain_db: float  # ... if it held the target's mean colour there (a perfect flat fill)


def region_headroom(
    pred: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    target: npt.NDArray | torch.Tensor,  # [H, W(, C)]
    region: npt.NDArray[np.uint8],  # [H, W] index into ``names``
    names: Sequence[str],
) -> dict[str, Headroom]:
    """Per region (those with pixels): its share of the pixels and of the squared error, and the
    whole-view PSNR gained by an exact region or by the flat fill that is best in PSNR (the
    target's mean colour over the region). Where the flat fill gains as much as an exact region,
    no structure is left to recover there; a negative gain: the prediction beats any flat fill."""
    x, y = _pair(pred, target)
    region = np.asarray(region)
    if region.shape != tuple(x.shape[1:]):
        raise ValueError(f"region must be [H, W] = {list(x.shape[1:])}, got {list(region.shape)}")
    err = ((x - y) ** 2).double().mean(dim=0)  # [H, W]
    total = float(err.sum())
    n_all = err.numel()
    out = {}
    for i, name in enumerate(names):
        sel = torch.from_numpy(region == i)
        n = int(sel.sum())
        if not n:
            continue
        sse = float(err[sel].sum())
        flat = float(y[:, sel].double().var(dim=1, unbiased=False).mean()) * n  # SSE of the mean

        def gain(new_sse: float, sse: float = sse) -> float:
            rest = total - sse + new_sse
            if total == 0.0:
                return 0.0  # an exact view: nothing to gain
            return float("inf") if rest <= 0.0 else float(10.0 * np.log10(total / rest))

        out[name] = Headroom(n / n_all, sse / total if total > 0 else 0.0, gain(0.0), gain(flat))
    return out
