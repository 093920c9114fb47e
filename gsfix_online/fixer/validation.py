"""Deterministic held-out scores for early stopping and pretraining figures.

The training loss draws keyframes, crops, noise and timesteps at random, so two evaluations of
the same weights differ. Both scores below fix everything from a seed: the same weights on the
same cache give the same number.

- :func:`heldout_loss`: the training loss on a few seeded micro-batches, timesteps stratified
  over ``[0, T)`` so that the few samples cover the whole noise range.
- :func:`heldout_repair_loss`: the loss at the first timestep DDIM visits (``T - 1``), on every
  whole held-out view and variant. With x0 prediction on the zero-terminal-SNR schedule,
  ``z_t`` is pure noise there, so this is the mean squared error of a 1-step repair in latent
  space: the job the checkpoint is picked for.
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


@torch.no_grad()
def heldout_repair_loss(
    trainer: Trainer,
    cache: LatentCache,  # whole held-out views, with the condition variants to score
    batch_size: int = 4,
    seed: int = 1234,
) -> float:
    """Mean loss at ``t = T - 1`` over every (view, variant) of ``cache``, noise from ``seed``."""
    gen = torch.Generator().manual_seed(seed)
    T = trainer.cfg.num_train_timesteps
    trainer.model.eval()
    total, n = 0.0, 0
    for batch in cache.batches(batch_size):
        b = batch.z_gt.shape[0]
        noise = torch.randn(batch.z_gt.shape, generator=gen)
        t = torch.full((b,), T - 1, dtype=torch.int64)
        total += float(trainer.loss(batch, noise=noise, timesteps=t)) * b
        n += b
    if n == 0:
        raise ValueError("the held-out cache is empty")
    return total / n
