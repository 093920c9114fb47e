"""One entry point for every model source: :func:`load_fixer` returns a :class:`FixerBundle`
from SD2 weights, a random model of the embedded size, or a fine-tuning checkpoint (by default
the pretrained base inside the package)."""

from __future__ import annotations

import torch

from gsfix_online.core.config import to_dict
from gsfix_online.fixer.checkpoint import load_checkpoint
from gsfix_online.fixer.config import ModelConfig
from gsfix_online.fixer.model import GSFixer, add_condition_slot, merge_condition_slots
from gsfix_online.fixer.sources import BASE_CHECKPOINT, FixerBundle, build_default, load_sd2


def load_fixer(cfg: ModelConfig, torch_dtype: torch.dtype = torch.float32) -> FixerBundle:
    """The model ``cfg`` names: SD2 (base weights), or the default from the checkpoint at
    ``cfg.path`` ("" = the pretrained base inside the package, :data:`BASE_CHECKPOINT`).

    A ``mesh+gs`` checkpoint serves the modes ``gs`` and ``mesh`` too: its two condition slots
    are merged (:func:`~gsfix_online.fixer.model.merge_condition_slots`), and mode
    ``mesh+gs+ref`` too: a reference slot with zero weights is added
    (:func:`~gsfix_online.fixer.model.add_condition_slot`), so the model starts as the
    ``mesh+gs`` one. A random model for pretraining is :func:`build_default`."""
    if cfg.source == "sd2":
        return load_sd2(cfg, torch_dtype)
    if cfg.random_init and not cfg.path:
        return build_default(cfg)
    loaded = load_checkpoint(cfg.path or BASE_CHECKPOINT)
    bundle = loaded.bundle
    if not cfg.path and loaded.manifest["model_config"].get("default") != to_dict(cfg.default):
        raise ValueError(
            "the packaged base checkpoint has another model size than fixer.model.default; "
            "leave default as it is, or set fixer.model.random_init=true to train from scratch"
        )
    m = bundle.model
    if m.mode == "mesh+gs" and cfg.mode == "mesh+gs+ref":  # a new, zero slot: see add_...
        unet = add_condition_slot(m.unet, m.latent_channels)
        bundle.model = GSFixer(unet, cfg.mode, m.latent_channels, m.prompt_embedding, m.residual)
        bundle.base = {**bundle.base, "widened_from_mode": "mesh+gs"}
    elif m.mode == "mesh+gs" and cfg.mode != m.mode:  # a base for one condition: see merge_...
        unet = merge_condition_slots(m.unet, m.latent_channels)
        emb = m.prompt_embedding
        bundle.model = GSFixer(unet, cfg.mode, m.latent_channels, emb, m.residual)
        bundle.base = {**bundle.base, "merged_from_mode": "mesh+gs"}
    elif m.mode != cfg.mode:
        raise ValueError(
            f"checkpoint {cfg.path or BASE_CHECKPOINT} was trained for mode {m.mode!r}, "
            f"the config asks for {cfg.mode!r}"
        )
    if not cfg.path:  # the packaged base is where fine-tuning starts: fed as the config says
        bundle.model.gs_condition = cfg.gs_condition
    return bundle
