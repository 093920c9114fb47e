"""Tests for gsfix_online/fixer/inference.py: deterministic DDIM repair."""

from __future__ import annotations

import pytest
import torch

from gsfix_online.fixer.config import InferenceConfig, ModelConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.sources import build_default, load_fixer
from tests.fixer.conftest import TOL, tiny_model_cfg


def _views(b=3, c=3, h=20, w=28, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, c, h, w, generator=g), torch.rand(b, c, h, w, generator=g)


def test_fixed_seed_is_reproducible_and_seed_matters():
    bundle = build_default(tiny_model_cfg())
    mesh, gs = _views()
    a = repair(bundle, mesh, gs, InferenceConfig(seed=3)).images
    b = repair(bundle, mesh, gs, InferenceConfig(seed=3)).images
    c = repair(bundle, mesh, gs, InferenceConfig(seed=4)).images
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_batching_does_not_change_results():
    bundle = build_default(tiny_model_cfg())
    mesh, gs = _views(b=3)
    one = repair(bundle, mesh, gs, InferenceConfig(batch_size=1)).images
    all3 = repair(bundle, mesh, gs, InferenceConfig(batch_size=3)).images
    torch.testing.assert_close(one, all3, **TOL[torch.float32])


@pytest.mark.parametrize(("c", "h", "w"), [(3, 16, 16), (3, 21, 37), (1, 30, 45)])
@pytest.mark.parametrize("steps", [1, 4])
def test_shape_range_padding_and_gray(c, h, w, steps):
    bundle = build_default(tiny_model_cfg())
    mesh, gs = _views(b=2, c=c, h=h, w=w)
    res = repair(bundle, mesh, gs, InferenceConfig(steps=steps))
    assert res.images.shape == (2, c, h, w)
    assert res.images.min() >= 0 and res.images.max() <= 1
    assert len(res.timesteps) == steps and res.timesteps[0] == 999  # trailing spacing


def test_pinned_output_slice_tiny_model():
    # v-prediction keeps a random model's x0 estimate in range (epsilon prediction divides
    # by sqrt(alpha_bar) = 0.068 at t = 999 and saturates every pixel), so the pin is informative.
    bundle = build_default(tiny_model_cfg(prediction_type="v_prediction"))
    mesh, gs = _views(b=1, h=16, w=16)
    out = repair(bundle, mesh, gs, InferenceConfig(steps=4, seed=0)).images
    # Pinned on torch 2.13 CPU, diffusers 0.42.1 (random tiny model, seed 0).
    expected = torch.tensor([0.4008, 0.6720, 0.5032, 0.9810, 0.7886, 0.0])
    torch.testing.assert_close(out[0, 0, 8, 4:10], expected, atol=1e-4, rtol=0)


def test_single_condition_modes():
    mesh, gs = _views(b=1)
    assert (
        repair(build_default(tiny_model_cfg("gs")), None, gs, InferenceConfig()).images.shape
        == gs.shape
    )
    assert (
        repair(build_default(tiny_model_cfg("mesh")), mesh, None, InferenceConfig()).images.shape
        == mesh.shape
    )


def test_input_validation():
    bundle = build_default(tiny_model_cfg())
    mesh, gs = _views()
    with pytest.raises(ValueError, match="needs image_mesh"):
        repair(bundle, None, gs, InferenceConfig())
    with pytest.raises(ValueError, match=r"float \[B, 1\|3, H, W\]"):
        repair(bundle, (mesh * 255).to(torch.uint8), gs, InferenceConfig())
    with pytest.raises(ValueError, match="differ"):
        repair(bundle, mesh[:, :, :10], gs, InferenceConfig())


def test_sd2_source_repairs(tiny_sd2_dir, tmp_path):
    cfg = ModelConfig(source="sd2", path=str(tiny_sd2_dir), embedding_cache=str(tmp_path))
    bundle = load_fixer(cfg)
    mesh, gs = _views(b=2, h=15, w=17)
    res = repair(bundle, mesh, gs, InferenceConfig(steps=2))
    assert res.images.shape == (2, 3, 15, 17)
    assert torch.equal(res.images, repair(bundle, mesh, gs, InferenceConfig(steps=2)).images)
