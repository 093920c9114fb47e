"""Image quality metrics for repaired views: PSNR and SSIM (kornia) on uint8 or [0, 1] images.

Images are ``[H, W]`` (grayscale) or ``[H, W, C]`` numpy arrays or torch tensors, uint8 (0..255)
or floating point (0..1). Both images of a pair must have the same shape; a colour image is never
compared with a grayscale one silently (convert first). SSIM uses the 11x11 Gaussian window of
the original SSIM paper.
"""

from __future__ import annotations

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
    mse = float(err.mean())
    return float("inf") if mse == 0.0 else float(-10.0 * np.log10(mse))


def ssim(pred: npt.NDArray | torch.Tensor, target: npt.NDArray | torch.Tensor) -> float:
    """Mean SSIM (kornia, 11x11 Gaussian window) over the image and its channels."""
    from kornia.metrics import ssim as kssim

    x, y = _pair(pred, target)
    return float(kssim(x[None], y[None], SSIM_WINDOW, max_val=1.0).mean())


def scores(pred: npt.NDArray | torch.Tensor, target: npt.NDArray | torch.Tensor) -> ImageScores:
    return ImageScores(psnr(pred, target), ssim(pred, target))
