"""Tests for fixer.model.gs_condition: what GSFixer's 3DGS slot is given, in training and repair."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from gsfix_online.core.config import build
from gsfix_online.fixer import checkpoint as ck
from gsfix_online.fixer.codec import to_model_range
from gsfix_online.fixer.config import InferenceConfig, MaskConfig, ModelConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.model import condition_images
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache
from tests.fixer.conftest import tiny_model_cfg

H, W = 16, 24


def _renders(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A mesh render with a hole (black) in its left third and a 3DGS render, [1, 3, H, W]."""
    g = torch.Generator().manual_seed(seed)
    mesh = 0.1 + 0.9 * torch.rand(1, 3, H, W, generator=g)
    mesh[..., : W // 3] = 0.0
    gs = torch.rand(1, 3, H, W, generator=g)
    return mesh, gs


def test_mesh_first_takes_the_mesh_where_it_has_a_surface_and_the_render_elsewhere():
    mesh, gs = _renders()
    mesh[0, :, 0, W - 1] = torch.tensor([0.0, 0.0, 0.2])  # one channel above zero: a surface
    out = condition_images(mesh, gs, "mesh_first")
    torch.testing.assert_close(out[..., : W // 3], gs[..., : W // 3], atol=0, rtol=0)
    torch.testing.assert_close(out[..., W // 3 :], mesh[..., W // 3 :], atol=0, rtol=0)
    assert condition_images(mesh, gs, "render") is gs
    assert condition_images(None, gs, "mesh_first") is gs  # mode gs: nothing to put first
    gray = condition_images(mesh[:, :1], gs[:, :1], "mesh_first")
    assert gray.shape == (1, 1, H, W)
    with pytest.raises(ValueError, match="render or mesh_first"):
        condition_images(mesh, gs, "mesh")


def test_a_mesh_first_model_repairs_as_a_render_model_given_the_composite():
    cfg = tiny_model_cfg(residual=True)
    render_model = build_default(cfg)
    with torch.no_grad():  # a trained-looking model: the zero last convolution would hide it
        for p in render_model.model.unet.conv_out.parameters():
            p.normal_(0, 0.05, generator=torch.Generator().manual_seed(1))
    first = build_default(dataclasses.replace(cfg, gs_condition="mesh_first"))
    first.model.unet.load_state_dict(render_model.model.unet.state_dict())
    mesh, gs = _renders()
    composite = torch.where((mesh > 0).any(1, keepdim=True), mesh, gs)
    inf = InferenceConfig(steps=1, shifts=2)
    a = repair(first, mesh, gs, inf).images
    torch.testing.assert_close(a, repair(render_model, mesh, composite, inf).images)
    assert not torch.allclose(a, repair(render_model, mesh, gs, inf).images, atol=1e-3)


def test_the_latent_cache_encodes_the_slot_the_model_is_fed():
    b = build_default(tiny_model_cfg())
    mesh, gs = _renders()
    gt = torch.rand(3, H, W, generator=torch.Generator().manual_seed(2))
    clean = MaskConfig(enabled=False)
    caches = {c: LatentCache(b.codec, clean, 1, gs_condition=c) for c in ("render", "mesh_first")}
    for cache in caches.values():
        cache.add(0, mesh[0], gs[0], gt)
    composite = torch.where((mesh > 0).any(1, keepdim=True), mesh, gs)
    for name, image in (("render", gs), ("mesh_first", composite)):
        ref = b.codec.encode(to_model_range(image))
        z = caches[name]._entries[0].z_gs.float()
        torch.testing.assert_close(z, ref, atol=2e-3, rtol=0)  # float16 storage
    # masked variants: a hole cut into the mesh shows the (masked) 3DGS render there
    holes = MaskConfig(p_shared=0.0, p_gs_only=0.0, p_mesh_only=1.0)
    cache = LatentCache(b.codec, holes, 2, seed=3, gs_condition="mesh_first")
    cache.add(0, mesh[0], gs[0], gt)
    e = cache._entries[0]
    assert not torch.allclose(e.z_gs.float(), b.codec.encode(to_model_range(composite)), atol=0.01)


def test_checkpoints_keep_how_they_were_fed_and_the_base_takes_the_config(tmp_path):
    cfg = tiny_model_cfg(gs_condition="mesh_first")
    b = build_default(cfg)
    assert b.model.gs_condition == "mesh_first"
    # saved from a config that says "render": the model's own feeding is what is recorded
    ck.save_checkpoint(tmp_path / "c", b, 3, dataclasses.replace(cfg, gs_condition="render"))
    loaded = ck.load_checkpoint(tmp_path / "c")
    assert loaded.manifest["model_config"]["gs_condition"] == "mesh_first"
    assert loaded.bundle.model.gs_condition == "mesh_first"
    # a checkpoint named by path is fed as it was trained, whatever the repairer's config says
    again = load_fixer(ModelConfig(path=str(tmp_path / "c"), default=cfg.default))
    assert again.model.gs_condition == "mesh_first"
    # the packaged base (path "") is fed as the config says: fine-tuning starts there
    assert load_fixer(ModelConfig()).model.gs_condition == "render"
    assert load_fixer(ModelConfig(gs_condition="mesh_first")).model.gs_condition == "mesh_first"


def test_gs_condition_is_validated_at_the_config():
    with pytest.raises(ValueError, match="needs mode mesh\\+gs"):
        build(ModelConfig, overrides=["mode=gs", "gs_condition=mesh_first"])
    with pytest.raises(ValueError, match="gs_condition"):
        build(ModelConfig, overrides=["gs_condition=gs_first"])
