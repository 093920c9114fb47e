"""Per-view exposure and white balance: an affine colour per training view.

Real cameras change exposure and white balance between frames. A map fitted to such frames bakes
each frame's exposure into the Gaussians grown from it and averages the rest into blotches. As
many 3DGS systems do for real cameras, each training view gets its own affine colour, applied to
every Gaussian's colour before compositing::

    image ~ gain * render + bias * alpha      (per channel; gain = exp(log_gain))

(``bias * alpha`` because compositing ``gain * c_i + bias`` over the Gaussians gives exactly
that; the background stays black.) The map itself keeps one canonical exposure, which renders of
new views use. A view's parameters are a ``[2, C]`` tensor: row 0 ``log_gain``, row 1 ``bias``
(colour in [0, 1]); zeros are the identity.

A new frame's parameters come in closed form (:func:`fit_affine`): a weighted ridge regression of
the frame on the map's render where the render is opaque, pulled towards the identity so that a
map that is not yet fitted is not mistaken for an exposure change. Keyframes keep theirs as
parameters optimised with the map, with an L2 prior towards the identity that ties the canonical
exposure to the average of the views. All functions here are pure torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from gsfix_online.core.config import rng


@dataclass(frozen=True)
class ExposureConfig:
    """Per-view affine colour compensation (off by default: the map's colour is the image's)."""

    enabled: bool = False
    # a bias as well as a gain per channel; off: a gain alone, which is exact for an exposure
    # change under a power-law (gamma) tone curve, and better conditioned (gain and bias trade
    # off on the narrow colour range of one view)
    bias: bool = False
    lr: float = field(default=2e-3, metadata=rng(0, None, "Adam rate of keyframes' log-gain, bias"))
    prior: float = field(
        default=0.1, metadata=rng(0, None, "loss weight of |log_gain|^2 + |bias|^2 per view")
    )
    ridge: float = field(
        default=0.05,
        metadata=rng(0, None, "closed-form fit: pull towards the identity, as a share of pixels"),
    )
    min_alpha: float = field(
        default=0.9, metadata=rng(0, 1, "closed-form fit: render alpha of the pixels it uses")
    )
    min_fraction: float = field(
        default=0.05, metadata=rng(0, 1, "closed-form fit: identity below this share of pixels")
    )
    max_log_gain: float = field(
        default=1.0, metadata=rng(0, None, "|log_gain| is clamped to this (e: x2.7 either way)")
    )


def identity(channels: int, device: torch.device | str = "cpu") -> Tensor:  # [2, C]
    return torch.zeros((2, channels), device=device)


def apply_affine(
    color: Tensor,  # [..., C] composited colour
    alpha: Tensor,  # [...] its alpha
    params: Tensor,  # [2, C] log_gain, bias
) -> Tensor:  # [..., C]
    """``exp(log_gain) * color + bias * alpha``: the affine colour of every Gaussian, composited."""
    return color * params[0].exp() + alpha[..., None] * params[1]


def invert_affine(
    color: Tensor,  # [..., C] a colour the view saw
    params: Tensor,  # [2, C]
) -> Tensor:  # [..., C] the canonical colour that renders as ``color`` in that view
    return (color - params[1]) * (-params[0]).exp()


def fit_affine(
    pred: Tensor,  # [P, C] canonical render colours
    target: Tensor,  # [P, C] the view's colours
    weight: Tensor,  # [P] >= 0
    ridge: float,
    max_log_gain: float = 1.0,
    bias: bool = True,
) -> Tensor:  # [2, C] log_gain, bias
    """Per channel ``argmin_{g, b} sum w (g x + b - y)^2 + ridge * sum(w) * ((g - 1)^2 + b^2)``
    (``b = 0`` without ``bias``).

    The ridge is relative to the total weight, so it means the same at any resolution. The gain
    is clamped to ``exp(+-max_log_gain)`` (and to > 0) before taking its log."""
    assert pred.shape == target.shape and pred.ndim == 2 and weight.shape == pred.shape[:1]
    w = weight.double()[:, None]
    x, y = pred.double(), target.double()
    W = w.sum().clamp_min(1e-12)
    lam = ridge * W
    sxx, sx, sxy, sy = (w * x * x).sum(0), (w * x).sum(0), (w * x * y).sum(0), (w * y).sum(0)
    # Normal equations [[sxx + lam, sx], [sx, W + lam]] [g, b] = [sxy + lam, sy]
    if bias:
        det = (sxx + lam) * (W + lam) - sx * sx
        g = ((sxy + lam) * (W + lam) - sx * sy) / det
        b = ((sxx + lam) * sy - sx * (sxy + lam)) / det
    else:
        g, b = (sxy + lam) / (sxx + lam), torch.zeros_like(sx)
    lim = float(torch.tensor(max_log_gain).exp())
    g = g.clamp(1.0 / lim, lim)
    return torch.stack([g.log(), b]).to(pred.dtype)


def prior_loss(params: Tensor) -> Tensor:  # [2, C] -> []
    """Mean squared distance of a view's parameters from the identity."""
    return (params * params).mean()
