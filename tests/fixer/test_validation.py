"""Tests for gsfix_online/fixer/validation.py: the held-out scores."""

from __future__ import annotations

import torch

from gsfix_online.fixer.config import MaskConfig, TrainConfig
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache, Trainer
from gsfix_online.fixer.validation import heldout_loss, heldout_repair_loss
from tests.fixer.conftest import tiny_model_cfg
from tests.fixer.test_train import _triplet


def _setup(residual: bool, masks: MaskConfig, pool: int) -> tuple[Trainer, LatentCache]:
    b = build_default(tiny_model_cfg(residual=residual, prediction_type="sample"))
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(batch_size=2, crop=0))
    cache = LatentCache(b.codec, masks, pool_size=pool, seed=0)
    for k in range(3):
        cache.add(k, *_triplet(k))
    return trainer, cache


def test_cache_batches_cover_every_view_and_variant_once():
    _, cache = _setup(False, MaskConfig(), pool=2)
    batches = list(cache.batches(4))
    assert [x.z_gt.shape[0] for x in batches] == [4, 2]
    z_gs = torch.cat([x.z_gs for x in batches])
    want = torch.cat([cache._entries[k].z_gs.float() for k in range(3)])
    assert torch.equal(z_gs, want)
    z_gt = torch.cat([x.z_gt for x in batches])
    assert torch.equal(z_gt[0], z_gt[1]) and torch.equal(z_gt[1], cache._entries[0].z_gt[0].float())


def test_repair_loss_of_a_fresh_residual_model_is_its_input_error():
    # a fresh residual model returns its 3DGS latent: the 1-step repair is the input itself
    trainer, cache = _setup(True, MaskConfig(enabled=False), pool=1)
    want = torch.stack(
        [((e.z_gs.float() - e.z_gt.float()) ** 2).mean() for e in cache._entries.values()]
    ).mean()
    got = heldout_repair_loss(trainer, cache, batch_size=2)
    assert abs(got - float(want)) < 1e-6 * max(1.0, float(want))


def test_heldout_scores_are_deterministic_and_follow_the_weights():
    trainer, cache = _setup(False, MaskConfig(), pool=2)
    a, b = heldout_repair_loss(trainer, cache), heldout_repair_loss(trainer, cache)
    assert a == b and a > 0
    assert heldout_loss(trainer, cache, batches=2, batch_size=2) == heldout_loss(
        trainer, cache, batches=2, batch_size=2
    )
    with torch.no_grad():
        for p in trainer.model.parameters():
            p.add_(0.05)
    assert heldout_repair_loss(trainer, cache) != a
