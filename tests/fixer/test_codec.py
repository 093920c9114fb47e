"""Tests for gsfix_online/fixer/codec.py."""

from __future__ import annotations

import pytest
import torch

from gsfix_online.fixer.codec import PixelUnshuffleCodec, VaeCodec, codec_from_spec, to_model_range


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_pixel_unshuffle_round_trip_is_exact(factor):
    x = torch.rand(2, 3, 8 * 3, 8 * 5) * 2 - 1
    codec = PixelUnshuffleCodec(factor, scale=0.7)
    z = codec.encode(x)
    assert z.shape == (2, 3 * factor * factor, 24 // factor, 40 // factor)
    assert codec.latent_channels == z.shape[1] and codec.downsample == factor
    torch.testing.assert_close(codec.decode(z), x, atol=1e-6, rtol=0)


def test_pixel_unshuffle_analytic_block():
    x = torch.arange(16.0).reshape(1, 1, 4, 4).expand(1, 3, 4, 4)
    z = PixelUnshuffleCodec(2).encode(x)
    # channel 0 of the first colour holds the top-left pixel of every 2x2 block
    assert z[0, 0].tolist() == [[0.0, 2.0], [8.0, 10.0]]


def test_codec_spec_round_trip():
    codec = PixelUnshuffleCodec(4, 2.0)
    again = codec_from_spec(codec.spec())
    assert (again.factor, again.scale) == (4, 2.0)
    with pytest.raises(ValueError, match="model source"):
        codec_from_spec({"kind": "vae"})


def test_to_model_range_gray_and_rgb():
    g = torch.full((1, 1, 2, 2), 0.75)
    out = to_model_range(g)
    assert out.shape == (1, 3, 2, 2) and torch.all(out == 0.5)
    assert torch.all(to_model_range(torch.zeros(1, 3, 2, 2)) == -1)


def test_vae_codec_scales_posterior_mean(tiny_sd2_dir):
    from diffusers import AutoencoderKL

    vae = AutoencoderKL.from_pretrained(tiny_sd2_dir / "vae", local_files_only=True)
    codec = VaeCodec(vae)
    assert codec.scaling_factor == pytest.approx(0.18215)
    assert (codec.latent_channels, codec.downsample) == (4, 2)
    x = torch.rand(1, 3, 16, 16) * 2 - 1
    z = codec.encode(x)
    with torch.no_grad():
        ref = vae.encode(x).latent_dist.mode() * 0.18215
    torch.testing.assert_close(z, ref)
    assert codec.decode(z).shape == x.shape
    assert not any(p.requires_grad for p in vae.parameters())
