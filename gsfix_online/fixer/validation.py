"""A deterministic held-out loss for early stopping and pretraining figures.

The training loss draws keyframes, crops, noise and timesteps at random, so two evaluations of
the same weights differ. :func:`heldout_loss` fixes all of them from a seed: the same weights on
the same cache give the same number, and timesteps are stratified over ``[0, T)`` so that the
few samples cover the whole noise range.
"""

from __future__ import annotations

import torch

from gsfix_online.fixer.train import LatentCache, Trainer


@torch.no_grad()
def heldout_loss(
    trainer: Trainer,
    cache: LatentCache,
    batches: int = 4,
    batch_size: int = 4,
    crop: int = 0,  # latent crop side, 0 = whole views
    seed: int = 1234,
) -> float:
    """Mean noise-prediction MSE on ``batches`` seeded micro-batches of ``cache``."""
    gen = torch.Generator().manual_seed(seed)
    n = batches * batch_size
    T = trainer.cfg.num_train_timesteps
    steps = ((torch.arange(n) + 0.5) * T / n).long().clamp_(0, T - 1)
    trainer.model.eval()
    total = 0.0
    for i in range(batches):
        batch = cache.sample(batch_size, gen, crop)
        noise = torch.randn(batch.z_gt.shape, generator=gen)
        t = steps[i * batch_size : (i + 1) * batch_size]
        total += float(trainer.loss(batch, noise=noise, timesteps=t))
    return total / batches
