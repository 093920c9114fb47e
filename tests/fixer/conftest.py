"""Shared fixtures for GSFixer: tiny models with fixed seeds, a tiny SD2-layout folder."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from gsfix_online.fixer.config import DefaultModelConfig, ModelConfig

# Tolerances per dtype (house style: one table). float32: U-Net outputs differ between batched
# and single-view runs by at most ~2e-6 in the tiny models (measured), from summation order.
TOL = {torch.float32: {"atol": 1e-5, "rtol": 1e-5}}

# Not residual: a fresh residual model returns its input whatever the noise, which would hide
# what the generic tests look at (seeds, batching, pinned slices); residual has its own tests.
TINY_DEFAULT = DefaultModelConfig(
    codec_factor=2, block_out_channels=(8, 16), norm_num_groups=4, residual=False
)


def tiny_model_cfg(mode: str = "mesh+gs", residual: bool = False, **kw) -> ModelConfig:
    """A random tiny default model (random_init: the packaged base is full size)."""
    default = dataclasses.replace(TINY_DEFAULT, residual=residual)
    kw.setdefault("random_init", True)
    return ModelConfig(mode=mode, default=default, **kw)  # type: ignore[arg-type]


def tiny_sd2_unet(seed: int = 0):
    """A 2-level UNet2DConditionModel with cross-attention, 4 latent channels (SD2's classes)."""
    from diffusers import UNet2DConditionModel

    torch.manual_seed(seed)
    return UNet2DConditionModel(
        sample_size=8,
        in_channels=4,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=(8, 16),
        layers_per_block=1,
        norm_num_groups=4,
        cross_attention_dim=16,
        attention_head_dim=(2, 4),
        use_linear_projection=True,
    )


def write_tiny_sd2(root: Path, seed: int = 0) -> Path:
    """Write a Stable Diffusion 2 folder in diffusers layout with random tiny weights."""
    from diffusers import AutoencoderKL, DDIMScheduler
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    root.mkdir(parents=True, exist_ok=True)
    tiny_sd2_unet(seed).save_pretrained(root / "unet")
    torch.manual_seed(seed + 1)
    AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
        up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
        block_out_channels=(8, 16),
        latent_channels=4,
        norm_num_groups=4,
        sample_size=32,
        scaling_factor=0.18215,
    ).save_pretrained(root / "vae")
    torch.manual_seed(seed + 2)
    text_cfg = CLIPTextConfig(
        vocab_size=5,
        hidden_size=16,
        intermediate_size=32,
        num_hidden_layers=1,
        num_attention_heads=2,
        max_position_embeddings=8,
        bos_token_id=0,
        eos_token_id=1,
        pad_token_id=1,
    )
    CLIPTextModel(text_cfg).save_pretrained(root / "text_encoder")
    # A tokenizer built from a local five-token vocabulary (no download).
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1, "!": 2, "a": 3, "a</w>": 4}
    (root / "tok_src").mkdir(exist_ok=True)
    (root / "tok_src" / "vocab.json").write_text(json.dumps(vocab))
    (root / "tok_src" / "merges.txt").write_text("#version: 0.2\n")
    tok = CLIPTokenizer(
        str(root / "tok_src" / "vocab.json"),
        str(root / "tok_src" / "merges.txt"),
        model_max_length=8,
    )
    tok.save_pretrained(root / "tokenizer")
    # SD2 (768-v) schedule; prediction_type v_prediction, which our config overrides.
    DDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
        prediction_type="v_prediction",
    ).save_pretrained(root / "scheduler")
    (root / "model_index.json").write_text(
        json.dumps({"_class_name": "StableDiffusionPipeline", "_diffusers_version": "0.42.1"})
    )
    return root


@pytest.fixture(scope="session")
def tiny_sd2_dir(tmp_path_factory) -> Path:
    return write_tiny_sd2(tmp_path_factory.mktemp("sd2"))


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny models gain nothing from threads, and on a shared 2-core machine two intra-op
    threads contend with other processes (measured: 20x slower backward passes under load)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
