"""Tests for gsfix_online/fixer/train.py: the latent cache and the trainer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.fixer.checkpoint import load_checkpoint, save_checkpoint
from gsfix_online.fixer.codec import to_model_range
from gsfix_online.fixer.config import MaskConfig, TrainConfig
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache, Trainer
from tests.fixer.conftest import tiny_model_cfg

H, W = 16, 24


def _triplet(seed: int, channels: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(channels, H, W, generator=g)
    return (gt * 0.8).clamp(0, 1), (gt + 0.1 * torch.randn(gt.shape, generator=g)).clamp(0, 1), gt


def _cache(bundle, n=3, masks: MaskConfig | None = None, pool=3) -> LatentCache:
    cache = LatentCache(bundle.codec, masks or MaskConfig(), pool_size=pool, seed=0)
    for k in range(n):
        cache.add(k, *_triplet(k))
    return cache


def test_cache_pool_and_clean_latents():
    b = build_default(tiny_model_cfg())
    cache = _cache(b, masks=MaskConfig(enabled=False), pool=5)
    assert len(cache) == 3 and cache.pool_size == 1  # no masks: one clean variant
    mesh, _, gt = _triplet(0)
    e = cache._entries[0]
    ref = b.codec.encode(to_model_range(mesh[None]))
    torch.testing.assert_close(e.z_mesh.float(), ref, atol=2e-3, rtol=0)  # float16 storage
    torch.testing.assert_close(
        e.z_gt.float(), b.codec.encode(to_model_range(gt[None])), atol=2e-3, rtol=0
    )


def test_cache_masked_pool_differs_and_keeps_gt():
    b = build_default(tiny_model_cfg())
    masks = MaskConfig(p_shared=1.0, p_gs_only=1.0)
    cache = _cache(b, n=1, masks=masks, pool=4)
    e = cache._entries[0]
    assert e.z_mesh.shape[0] == 4 and e.z_gt.shape[0] == 1
    assert not torch.equal(e.z_gs[0], e.z_gs[1])


def test_cache_sample_shapes_crop_and_gray():
    b = build_default(tiny_model_cfg())
    cache = LatentCache(b.codec, MaskConfig(), pool_size=2)
    cache.add("gray", *_triplet(1, channels=1))
    g = torch.Generator().manual_seed(0)
    batch = cache.sample(3, g, crop=4)
    c = b.codec.latent_channels
    assert batch.z_mesh.shape == batch.z_gs.shape == batch.z_gt.shape == (3, c, 4, 4)
    assert batch.z_gt.dtype == torch.float32
    assert cache.sample(1, g).z_gt.shape == (1, c, H // 2, W // 2)


def test_cache_rejects_bad_inputs():
    b = build_default(tiny_model_cfg())
    cache = LatentCache(b.codec, MaskConfig())
    mesh, gs, gt = _triplet(0)
    with pytest.raises(ValueError, match="must match"):
        cache.add(0, mesh[:, :8], gs, gt)
    with pytest.raises(ValueError, match="multiple"):
        cache.add(0, mesh[:, :15], gs[:, :15], gt[:, :15])
    with pytest.raises(ValueError, match="empty"):
        cache.sample(1, torch.Generator())


def test_few_steps_lower_the_loss_on_a_fixed_batch():
    torch.manual_seed(0)
    b = build_default(tiny_model_cfg())
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(lr=1e-3, seed=0))
    batch = _cache(b).sample(4, torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(batch.z_gt.shape, generator=g)
    t = torch.tensor([50, 300, 600, 900])
    with torch.no_grad():
        before = float(trainer.loss(batch, noise, t))
    for _ in range(15):
        trainer.train_step([batch])
    with torch.no_grad():
        after = float(trainer.loss(batch, noise, t))
    assert trainer.step == 15
    assert after < 0.95 * before, (before, after)  # x0 loss 0.436 -> 0.289 measured


def test_v_prediction_target():
    b = build_default(tiny_model_cfg(prediction_type="v_prediction"))
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig())
    assert trainer.noise_scheduler.config.prediction_type == "v_prediction"
    loss = trainer.loss(_cache(b).sample(2, torch.Generator().manual_seed(0)))
    assert torch.isfinite(loss)


def test_resume_continues_step_count_and_trajectory(tmp_path):
    cfg = TrainConfig(lr=1e-3, batch_size=2, grad_accum=2, crop=4)
    model_cfg = tiny_model_cfg()

    def fresh():
        b = build_default(model_cfg)
        return b, Trainer(b.model, b.scheduler_config, cfg), _cache(b)

    # Uninterrupted: 5 steps.
    b, trainer, cache = fresh()
    straight = [trainer.fit_step(cache).loss for _ in range(5)]
    # Interrupted after 3, checkpointed, resumed in a new trainer.
    b, trainer, cache = fresh()
    for _ in range(3):
        trainer.fit_step(cache)
    save_checkpoint(tmp_path, b, trainer.step, model_cfg, trainer_state=trainer.state_dict())
    loaded = load_checkpoint(tmp_path)
    assert loaded.step == 3
    resumed = Trainer(loaded.bundle.model, loaded.bundle.scheduler_config, cfg)
    resumed.load_state_dict(loaded.trainer_state)
    assert resumed.step == 3
    rest = [resumed.fit_step(cache) for _ in range(2)]
    assert [r.step for r in rest] == [4, 5]
    assert [r.loss for r in rest] == pytest.approx(straight[3:], rel=1e-5)


def test_train_config_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        TrainConfig().lr = 1.0  # type: ignore[misc]


def test_sample_target_is_the_clean_latent():
    b = build_default(tiny_model_cfg(prediction_type="sample"))
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig())
    batch = _cache(b).sample(2, torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(batch.z_gt.shape, generator=g)
    t = torch.tensor([999, 10])
    z_t = trainer.noise_scheduler.add_noise(batch.z_gt, noise, t)
    # zero terminal SNR: z_T is pure noise, so the first DDIM step sees only the conditions
    torch.testing.assert_close(z_t[0], noise[0])
    with torch.no_grad():
        pred = b.model(torch.cat([batch.z_mesh, batch.z_gs], 1), z_t, t)
        expected = torch.nn.functional.mse_loss(pred, batch.z_gt)
        torch.testing.assert_close(trainer.loss(batch, noise, t), expected)


@pytest.mark.parametrize(("focus", "steps"), [(1.0, 4), (1.0, 1), (0.5, 4)])
def test_timestep_focus_draws_the_inference_timesteps(focus, steps):
    b = build_default(tiny_model_cfg())
    cfg = TrainConfig(timestep_focus=focus, focus_steps=steps)
    t = Trainer(b.model, b.scheduler_config, cfg).sample_timesteps(4000)
    visited = {999, 749, 499, 249} if steps == 4 else {999}
    share = float(np.isin(t.numpy(), list(visited)).mean())
    assert t.min() >= 0 and t.max() <= 999
    if focus == 1.0:
        assert share == 1.0
    else:  # half focused, half uniform (which hits the 4 values 0.4 % of the time)
        assert share == pytest.approx(0.5, abs=0.03)


def test_ema_tracks_the_weights_with_the_warm_up_decay_and_resumes(tmp_path):
    cfg = TrainConfig(lr=1e-2, batch_size=2, grad_accum=1, crop=4, ema_decay=0.9)
    b = build_default(tiny_model_cfg())
    trainer = Trainer(b.model, b.scheduler_config, cfg)
    cache = _cache(b)
    p = next(q for q in b.model.parameters() if q.requires_grad)
    expected = p.detach().clone()
    for n in range(1, 4):
        trainer.fit_step(cache)
        decay = min(0.9, n / (9 + n)) if n > 1 else 0.0  # diffusers EMAModel.get_decay
        expected = decay * expected + (1 - decay) * p.detach()
    live = p.detach().clone()
    with trainer.averaged():  # the average is swapped in ...
        torch.testing.assert_close(p.detach(), expected, rtol=1e-5, atol=1e-7)
        assert not torch.equal(p.detach(), live)
    assert torch.equal(p.detach(), live)  # ... and the trained weights come back
    # The average resumes from the trainer state
    resumed = Trainer(b.model, b.scheduler_config, cfg)
    resumed.load_state_dict(trainer.state_dict())
    with resumed.averaged():
        torch.testing.assert_close(p.detach(), expected, rtol=1e-5, atol=1e-7)


def test_without_ema_averaged_keeps_the_trained_weights():
    b = build_default(tiny_model_cfg())
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(lr=1e-2, grad_accum=1, crop=4))
    trainer.fit_step(_cache(b))
    p = next(q for q in b.model.parameters() if q.requires_grad)
    live = p.detach().clone()
    with trainer.averaged():
        assert torch.equal(p.detach(), live)
    assert "ema" not in trainer.state_dict()


@pytest.mark.parametrize("ema", [0.0, 0.9])
def test_wise_alpha_moves_checkpoints_back_towards_the_start_and_resumes(ema):
    """With wise_alpha the weights that evaluations and checkpoints use are
    start + alpha (w - start), w the EMA when there is one; the anchor survives a resume (a
    restarted trainer builds its model from a checkpoint, not from the start)."""
    cfg = TrainConfig(lr=1e-2, batch_size=2, grad_accum=1, crop=4, ema_decay=ema, wise_alpha=0.25)
    b = build_default(tiny_model_cfg())
    p = next(q for q in b.model.parameters() if q.requires_grad)
    start = p.detach().clone()
    trainer = Trainer(b.model, b.scheduler_config, cfg)
    plain = Trainer(
        build_default(tiny_model_cfg()).model, b.scheduler_config,
        dataclasses.replace(cfg, wise_alpha=1.0),
    )  # fmt: skip
    plain.model.load_state_dict(b.model.state_dict())
    cache = _cache(b)
    for _ in range(3):
        trainer.fit_step(cache)
    plain.load_state_dict({k: v for k, v in trainer.state_dict().items() if k != "wise_start"})
    plain.model.load_state_dict(b.model.state_dict())
    q = next(q for q in plain.model.parameters() if q.requires_grad)
    with plain.averaged():
        w = q.detach().clone()  # the trained (or EMA) weights without WiSE
    assert not torch.allclose(w, start)
    live = p.detach().clone()
    with trainer.averaged():
        torch.testing.assert_close(p.detach(), start + 0.25 * (w - start), rtol=1e-5, atol=1e-7)
    assert torch.equal(p.detach(), live)
    state = trainer.state_dict()
    with torch.no_grad():  # a restart loads the checkpoint's weights first
        p.add_(1.0)
    resumed = Trainer(b.model, b.scheduler_config, cfg)
    resumed.load_state_dict(state)
    torch.testing.assert_close(resumed.start[0], trainer.start[0])
    assert not torch.allclose(resumed.start[0], p.detach())
