"""Tests for gsfix_online/fixer/inference.py: deterministic DDIM repair."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from gsfix_online.fixer.config import InferenceConfig, ModelConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.sources import build_default
from tests.fixer.conftest import TOL, tiny_model_cfg

STEPS_OVERFIT = 120


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


@pytest.mark.parametrize(
    ("prediction_type", "expected"),
    [
        ("sample", [0.3535, 0.5155, 0.4355, 0.3061, 0.3449, 0.4544]),
        ("v_prediction", [0.4078, 0.6655, 0.4908, 0.9816, 0.7871, 0.0]),
    ],
)
def test_pinned_output_slice_tiny_model(prediction_type, expected):
    # x0 and v prediction (zero terminal SNR) keep a random model's x0 estimate in range
    # (epsilon prediction divides by sqrt(alpha_bar) = 0.068 at t = 999 and saturates every
    # pixel), so the pin is informative.
    bundle = build_default(tiny_model_cfg(prediction_type=prediction_type))
    mesh, gs = _views(b=1, h=16, w=16)
    out = repair(bundle, mesh, gs, InferenceConfig(steps=4, seed=0)).images
    # Pinned on torch 2.13 CPU, diffusers 0.42.1 (random tiny model, seed 0).
    torch.testing.assert_close(out[0, 0, 8, 4:10], torch.tensor(expected), atol=1e-4, rtol=0)


def test_fresh_residual_model_returns_its_3dgs_input():
    """Analytic value: zero last convolution + x0 skip = the 3DGS latent, at 1 and 4 steps."""
    mesh, gs = _views(b=2, h=16, w=16)
    for mode, expected in (("mesh+gs", gs), ("gs", gs), ("mesh", mesh)):
        bundle = build_default(tiny_model_cfg(mode, residual=True))
        for steps in (1, 4):
            out = repair(
                bundle, mesh if mode != "gs" else None, gs if mode != "mesh" else None,
                InferenceConfig(steps=steps),
            ).images  # fmt: skip
            torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)


def test_overfit_one_triplet_repairs_it():
    """Sanity check of the whole pipeline (x0 target, zero-SNR schedule, DDIM, codec): a tiny
    residual model fitted to one triplet reproduces its ground truth at 1 and 4 DDIM steps,
    far above its degraded input (measured: input 20.1 dB; repairs 38.1 and 38.6 dB at 1 and 4
    steps)."""
    from gsfix_online.fixer.config import MaskConfig, TrainConfig
    from gsfix_online.fixer.train import LatentCache, Trainer

    g = torch.Generator().manual_seed(0)
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    gt = torch.stack([0.5 + 0.3 * torch.sin(xx / 3), 0.5 + 0.3 * torch.cos(yy / 4), xx / 40])
    gs = (gt + 0.1 * torch.randn(gt.shape, generator=g)).clamp(0, 1)
    mesh = gt.clone()
    mesh[:, 8:20, 8:20] = 0.2  # wrong colour in a patch
    cfg = tiny_model_cfg(residual=True)
    cfg = dataclasses.replace(
        cfg, default=dataclasses.replace(cfg.default, block_out_channels=(16, 32))
    )
    bundle = build_default(cfg)
    cache = LatentCache(bundle.codec, MaskConfig(enabled=False), 1)
    cache.add(0, mesh, gs, gt)
    trainer = Trainer(
        bundle.model,
        bundle.scheduler_config,
        TrainConfig(lr=3e-3, batch_size=1, grad_accum=1, crop=0),
    )
    for _ in range(STEPS_OVERFIT):
        trainer.fit_step(cache)

    def psnr(x):
        return float(-10 * torch.log10(((x - gt) ** 2).mean()))

    assert psnr(gs) < 21
    for steps in (1, 4):
        out = repair(bundle, mesh[None], gs[None], InferenceConfig(steps=steps)).images[0]
        assert psnr(out) > 30, (steps, psnr(out))


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


def _blocky_model(seed: int = 0):
    """A fresh residual model whose last convolution adds a fixed offset to every latent
    channel: the 3DGS image plus a pattern repeated in every codec block (a pure block artefact)."""
    cfg = tiny_model_cfg(residual=True)  # codec blocks of 4 px: a 2-px pattern has no "inside"
    bundle = build_default(
        dataclasses.replace(cfg, default=dataclasses.replace(cfg.default, codec_factor=4))
    )
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        conv = bundle.model.unet.conv_out
        conv.bias.copy_(0.1 * torch.randn(conv.bias.shape, generator=g))
    return bundle


def _smooth(h=48, w=64):
    yy, xx = torch.meshgrid(torch.arange(float(h)), torch.arange(float(w)), indexing="ij")
    return torch.stack([0.5 + 0.3 * torch.sin(xx / 5), 0.5 + 0.3 * torch.cos(yy / 6), xx / w])[None]


def test_grid_shifts_remove_a_block_pattern():
    from gsfix_online.core.metrics import block_gradient_ratio

    bundle, img = _blocky_model(), _smooth()
    f = bundle.codec.downsample

    def ratio(x):
        return block_gradient_ratio(x[0].permute(1, 2, 0).numpy(), f)

    gt = ratio(img)
    one = repair(bundle, img, img, InferenceConfig(steps=1, shifts=1)).images
    four = repair(bundle, img, img, InferenceConfig(steps=1, shifts=f)).images
    assert ratio(one) > 1.5 * gt  # the pattern shows on the codec's grid
    assert abs(ratio(four) / gt - 1) < 0.05  # averaged over every diagonal grid: gone
    # the averaged offsets are still there (cycle spinning moves them, it does not drop them)
    torch.testing.assert_close(four.mean(), one.mean(), atol=2e-3, rtol=0)


@pytest.mark.parametrize("shifts", [2, 3, 4])
def test_grid_shifts_keep_the_identity_and_shapes(shifts):
    """A fresh residual model returns its 3DGS input on every grid, so on their average too;
    odd sizes and grayscale come back as they came."""
    bundle = build_default(tiny_model_cfg(residual=True))
    for c, h, w in ((3, 21, 37), (1, 30, 45)):
        mesh, gs = _views(b=2, c=c, h=h, w=w)
        out = repair(bundle, mesh, gs, InferenceConfig(steps=1, shifts=shifts)).images
        assert out.shape == (2, c, h, w)
        torch.testing.assert_close(out, gs, atol=1e-5, rtol=0)


def test_one_grid_is_the_unshifted_repair():
    bundle = build_default(tiny_model_cfg(prediction_type="sample"))
    mesh, gs = _views(b=2, h=16, w=16)
    a = repair(bundle, mesh, gs, InferenceConfig(steps=2)).images
    b = repair(bundle, mesh, gs, InferenceConfig(steps=2, shifts=1)).images
    assert torch.equal(a, b)


def test_packaged_base_repairs_without_block_artefacts():
    """The shipped base on a procedural scene it was not pretrained on (seed 900; pretraining
    used 0-95): averaged over 4 codec grids its repair is within 5 % of the ground truth's ratio
    of gradient energy across block boundaries on every view, and no worse in PSNR than one grid.
    With one grid the shipped base is within 8 % (measured 6.2 %; the GPU-pretrained base
    before it 3.6 %, the CPU base before that showed the 4-px block pattern at 13 %; the
    measure's sensitivity: tests/core/test_metrics.py)."""
    import numpy as np

    from gsfix_online.core.metrics import block_gradient_ratio
    from gsfix_online.fixer.triplets import DegradeConfig
    from gsfix_online.jobs.pretrain import PretrainConfig, degraded_views, render_scene

    views = render_scene(900, PretrainConfig(frames=2, width=160, height=128))
    triplets = degraded_views(views, np.random.default_rng(0), DegradeConfig(), 1)
    bundle = load_fixer(ModelConfig())

    def ratio(x):  # [3, H, W]
        return block_gradient_ratio(x.permute(1, 2, 0).numpy(), bundle.codec.downsample)

    def psnr(x, gt):
        return float(-10 * torch.log10(((x - gt) ** 2).mean()))

    worst_one = 0.0
    for mesh, gs, gt, _ in triplets:
        out = {k: repair(bundle, mesh[None], gs[None], InferenceConfig(steps=1, shifts=k))
               .images[0] for k in (1, 4)}  # fmt: skip
        worst_one = max(worst_one, abs(ratio(out[1]) / ratio(gt) - 1))
        assert abs(ratio(out[4]) / ratio(gt) - 1) < 0.05
        assert psnr(out[4], gt) >= psnr(out[1], gt) - 0.05
    assert worst_one < 0.08, worst_one
