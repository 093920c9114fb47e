"""Codecs between images and diffusion latents.

A codec maps RGB images in [-1, 1] to latents the U-Net denoises, and back. Two exist:

- :class:`PixelUnshuffleCodec`, the embedded default: space-to-depth by ``f``. Exact and
  invertible (reconstruction error 0 in float32), no weights, and encoding costs a reshape.
- :class:`VaeCodec`: a frozen ``AutoencoderKL`` (the SD2 VAE), latents scaled by the
  ``scaling_factor`` in its config.

Why not a small learned VAE for the default: with random weights (nothing can be downloaded) it
reconstructs at ~6 dB PSNR, and training one is a separate project; the measurement is in
``benchmarks/bench_fixer.py`` (``codec`` section). An orthogonal channel mix after the unshuffle
(a DCT of each f x f block) was considered and left out: it is a fixed 1x1 convolution that the
U-Net's first convolution absorbs, and white noise stays white under it, so it changes nothing
the model can learn.
"""

from __future__ import annotations

from typing import Any, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor


class Codec(Protocol):
    latent_channels: int  # C of a latent
    downsample: int  # image pixels per latent pixel, per axis

    def encode(self, images: Tensor) -> Tensor:  # [B, 3, H, W] in [-1, 1] -> [B, C, H/d, W/d]
        ...

    def decode(self, latents: Tensor) -> Tensor:  # [B, C, h, w] -> [B, 3, h*d, w*d] in ~[-1, 1]
        ...

    def spec(self) -> dict[str, Any]:  # what a checkpoint manifest records
        ...


class PixelUnshuffleCodec:
    """Exact space-to-depth codec: [B, 3, H, W] <-> [B, 3*f*f, H/f, W/f], times ``scale``."""

    def __init__(self, factor: int = 4, scale: float = 1.0) -> None:
        assert factor >= 1 and scale > 0
        self.factor = factor
        self.scale = scale
        self.latent_channels = 3 * factor * factor
        self.downsample = factor

    def encode(self, images: Tensor) -> Tensor:
        return F.pixel_unshuffle(images, self.factor) * self.scale

    def decode(self, latents: Tensor) -> Tensor:
        return F.pixel_shuffle(latents / self.scale, self.factor)

    def spec(self) -> dict[str, Any]:
        return {"kind": "pixel_unshuffle", "factor": self.factor, "scale": self.scale}


class VaeCodec:
    """A frozen AutoencoderKL; latents are the posterior mean times ``scaling_factor``."""

    def __init__(self, vae: Any, source: str = "") -> None:  # diffusers AutoencoderKL
        vae.requires_grad_(False)
        vae.eval()
        self.vae = vae
        self.source = source
        self.scaling_factor = float(vae.config.scaling_factor)
        self.latent_channels = int(vae.config.latent_channels)
        self.downsample = 2 ** (len(vae.config.block_out_channels) - 1)

    @torch.no_grad()
    def encode(self, images: Tensor) -> Tensor:
        images = images.to(self.vae.dtype)
        return self.vae.encode(images).latent_dist.mode() * self.scaling_factor

    @torch.no_grad()
    def decode(self, latents: Tensor) -> Tensor:
        latents = latents.to(self.vae.dtype)
        return self.vae.decode(latents / self.scaling_factor).sample

    def to(self, device: torch.device | str) -> VaeCodec:
        self.vae.to(device)
        return self

    def spec(self) -> dict[str, Any]:
        return {"kind": "vae", "source": self.source, "scaling_factor": self.scaling_factor}


def to_model_range(images: Tensor) -> Tensor:  # [B, 1|3, H, W] in [0, 1] -> [B, 3, H, W] in [-1, 1]
    """Grayscale is repeated to three channels; the codecs and U-Nets are RGB."""
    if images.shape[1] == 1:
        images = images.expand(-1, 3, -1, -1)
    return images * 2 - 1


def codec_from_spec(spec: dict[str, Any]) -> Codec:
    """Rebuild a weight-free codec from a manifest (VAE codecs come from their model source)."""
    if spec.get("kind") != "pixel_unshuffle":
        raise ValueError(f"codec spec {spec} cannot be rebuilt without its model source")
    return PixelUnshuffleCodec(int(spec["factor"]), float(spec["scale"]))
