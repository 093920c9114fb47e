"""Tests for gsfix_online/fixer/validation.py: the held-out loss."""

from __future__ import annotations

import torch

from gsfix_online.fixer.config import MaskConfig, TrainConfig
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache, Trainer
from gsfix_online.fixer.validation import heldout_loss
from tests.fixer.conftest import tiny_model_cfg
from tests.fixer.test_train import _triplet


def test_heldout_loss_is_deterministic_and_follows_the_weights():
    b = build_default(tiny_model_cfg(prediction_type="sample"))
    trainer = Trainer(b.model, b.scheduler_config, TrainConfig(batch_size=2, crop=0))
    cache = LatentCache(b.codec, MaskConfig(enabled=False), pool_size=1, seed=0)
    for k in range(3):
        cache.add(k, *_triplet(k))
    a = heldout_loss(trainer, cache, batches=2, batch_size=2)
    assert a == heldout_loss(trainer, cache, batches=2, batch_size=2) and a > 0
    with torch.no_grad():
        for p in trainer.model.parameters():
            p.add_(0.05)
    assert heldout_loss(trainer, cache, batches=2, batch_size=2) != a
