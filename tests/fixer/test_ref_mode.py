"""Tests for mode ``mesh+gs+ref``: the reference warp as a third GSFixer condition
(fixer/model.py, loader.py, inference.py, train.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.fixer import checkpoint as ck
from gsfix_online.fixer.config import MODE_CONDITIONS, InferenceConfig, MaskConfig, TrainConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.model import add_condition_slot, ref_condition, select_conditions
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache, Trainer
from tests.fixer.conftest import TOL, tiny_model_cfg

H, W = 16, 24


def _images(seed: int = 0, b: int = 1):  # mesh, gs, ref [b, 3, H, W]; valid [b, 1, H, W]
    g = torch.Generator().manual_seed(seed)
    mesh, gs, ref = (torch.rand(b, 3, H, W, generator=g) for _ in range(3))
    valid = torch.rand(b, 1, H, W, generator=g) > 0.5
    return mesh, gs, ref, valid


def _perturbed_mesh_gs(tmp_path, residual: bool):
    """A trained-looking mesh+gs checkpoint (random weights moved off their init)."""
    cfg = tiny_model_cfg(residual=residual)
    b = build_default(cfg)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for p in b.model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    ck.save_checkpoint(tmp_path / "ckpt", b, 3, cfg)
    return b, cfg


def test_the_3dgs_latent_stays_last_so_the_residual_adds_it():
    assert MODE_CONDITIONS["mesh+gs+ref"][-1] == "gs"
    z = [torch.full((1, 2, 1, 1), float(v)) for v in (1, 2, 3)]
    cond = select_conditions("mesh+gs+ref", z[0], z[1], z[2])  # mesh 1, gs 2, ref 3
    assert cond.flatten().tolist() == [1, 1, 3, 3, 2, 2]


@pytest.mark.parametrize("residual", [False, True])
def test_widened_from_mesh_gs_the_model_repairs_as_the_mesh_gs_one_whatever_the_ref(
    tmp_path, residual
):
    base, cfg = _perturbed_mesh_gs(tmp_path, residual)
    wide = load_fixer(dataclasses.replace(cfg, random_init=False, path=str(tmp_path / "ckpt"),
                                          mode="mesh+gs+ref"))  # fmt: skip
    assert wide.model.mode == "mesh+gs+ref" and wide.base["widened_from_mode"] == "mesh+gs"
    c = wide.codec.latent_channels
    assert wide.model.unet.conv_in.in_channels == 4 * c
    assert torch.count_nonzero(wide.model.unet.conv_in.weight[:, c : 2 * c]) == 0
    mesh, gs, ref, valid = _images(b=2)
    inf = InferenceConfig(steps=2)
    expected = repair(base, mesh, gs, inf).images
    for r, v in ((ref, valid), (torch.zeros_like(ref), torch.zeros_like(valid))):
        got = repair(wide, mesh, gs, inf, image_ref=r, ref_valid=v).images
        torch.testing.assert_close(got, expected, **TOL[torch.float32])


def test_from_an_unconditioned_unet_the_four_slots_share_the_weights_as_the_paper_widens():
    cfg = tiny_model_cfg("mesh+gs+ref")
    w = build_default(cfg).model.unet.conv_in.weight.detach()
    c = w.shape[1] // 4
    for k in range(1, 4):
        torch.testing.assert_close(w[:, k * c : (k + 1) * c], w[:, :c])


def test_add_condition_slot_needs_a_mesh_gs_unet():
    unet = build_default(tiny_model_cfg("gs")).model.unet
    with pytest.raises(ValueError, match="a mesh\\+gs U-Net has"):
        add_condition_slot(unet, 12)


def test_ref_condition_is_the_warp_where_it_has_pixels_and_the_mesh_elsewhere():
    mesh, _, ref, valid = _images()
    out = ref_condition(mesh, ref, valid)
    torch.testing.assert_close(out, torch.where(valid, ref, mesh), atol=0, rtol=0)
    with pytest.raises(ValueError, match="ref_valid must be bool"):
        ref_condition(mesh, ref, valid.float())


def test_missing_conditions_are_one_line_errors():
    b = build_default(tiny_model_cfg("mesh+gs+ref"))
    mesh, gs, ref, valid = _images()
    inf = InferenceConfig(steps=1)
    for kw, msg in (
        ({}, r"mode 'mesh\+gs\+ref' needs image_ref, got None"),
        ({"image_ref": ref}, r"needs ref_valid bool \[1, 1, 16, 24\], got None"),
        ({"image_ref": ref, "ref_valid": valid[:, :, :8]}, "needs ref_valid bool"),
        ({"image_ref": ref[..., :8], "ref_valid": valid}, "image_ref differs"),
    ):
        with pytest.raises(ValueError, match=msg) as e:
            repair(b, mesh, gs, inf, **kw)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="needs the ref image"):
        select_conditions("mesh+gs+ref", torch.zeros(1, 2, 1, 1), torch.zeros(1, 2, 1, 1))


def test_train_step_and_ddim_repair_shapes():
    cfg = tiny_model_cfg("mesh+gs+ref")
    b = build_default(cfg)
    cache = LatentCache(b.codec, MaskConfig(), pool_size=2, seed=0)
    for key in range(3):
        mesh, gs, ref, valid = _images(key)
        cache.add(key, mesh[0], gs[0], torch.rand(3, H, W), image_ref=ref[0],
                  ref_valid=valid[0, 0].numpy())  # fmt: skip
    batch = cache.sample(2, torch.Generator().manual_seed(0), crop=4)
    assert batch.z_ref is not None and batch.z_ref.shape == batch.z_gs.shape == (2, 12, 4, 4)
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(batch_size=2, grad_accum=2, crop=4))
    before = b.model.unet.conv_in.weight.detach().clone()
    res = trainer.fit_step(cache)
    assert res.step == 1 and np.isfinite(res.loss)
    assert not torch.equal(b.model.unet.conv_in.weight, before)
    mesh, gs, ref, valid = _images(b=2)
    out = repair(b, mesh, gs, InferenceConfig(steps=2), image_ref=ref, ref_valid=valid).images
    assert out.shape == (2, 3, H, W)


def test_a_mesh_gs_cache_feeds_no_ref_and_the_ref_model_says_so():
    b = build_default(tiny_model_cfg("mesh+gs+ref"))
    cache = LatentCache(b.codec, MaskConfig(enabled=False), pool_size=1)
    mesh, gs, _, _ = _images()
    cache.add(0, mesh[0], gs[0], gs[0])
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(batch_size=1, grad_accum=1))
    with pytest.raises(ValueError, match="needs the ref image"):
        trainer.fit_step(cache)
    with pytest.raises(ValueError, match="image_ref needs ref_valid bool"):
        cache.add(1, mesh[0], gs[0], gs[0], image_ref=mesh[0])


def test_a_mask_cut_into_the_mesh_cuts_the_warp_there_and_spares_it_elsewhere():
    """Pixel-unshuffle latents decode exactly: the reference slot of each pool variant is the
    warp where it has pixels and the mesh image was not cut, else the (masked) mesh image."""
    b = build_default(tiny_model_cfg("mesh+gs+ref"))
    masks = MaskConfig(p_shared=1.0, p_gs_only=1.0, p_mesh_only=1.0, use_disocclusion=False,
                       use_alpha_holes=False, shape_area=(0.2, 0.3))  # fmt: skip
    cache = LatentCache(b.codec, masks, pool_size=3, seed=1, dtype=torch.float32)
    mesh = torch.full((3, H, W), 0.5)
    ref = torch.full((3, H, W), 0.9)
    valid = np.zeros((H, W), bool)
    valid[:, W // 3 :] = True
    cache.add(0, mesh, torch.full((3, H, W), 0.3), mesh, image_ref=ref, ref_valid=valid)
    e = cache._entries[0]
    dec = lambda z: (b.codec.decode(z).clamp(-1, 1) + 1) / 2  # noqa: E731
    for v in range(3):
        m, r = dec(e.z_mesh[v : v + 1])[0, 0], dec(e.z_ref[v : v + 1])[0, 0]
        cut = m < 0.25  # the mesh image is 0.5 or cut to 0
        assert cut.any() and (~cut).any()
        warp = torch.from_numpy(valid) & ~cut
        torch.testing.assert_close(r[warp], torch.full_like(r[warp], 0.9), atol=1e-5, rtol=0)
        torch.testing.assert_close(r[~warp], m[~warp], atol=1e-5, rtol=0)
