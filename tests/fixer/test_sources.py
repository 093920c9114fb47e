"""Tests for gsfix_online/fixer/sources.py: the default model and the SD2 source."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from gsfix_online.fixer.codec import PixelUnshuffleCodec, VaeCodec
from gsfix_online.fixer.config import ModelConfig
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.sources import (
    build_default,
    compute_empty_prompt_embedding,
    embedding_cache_path,
)
from tests.fixer.conftest import tiny_model_cfg


@pytest.mark.parametrize(("mode", "copies"), [("mesh+gs", 3), ("gs", 2), ("mesh", 2)])
def test_default_channels_per_mode(mode, copies):
    b = build_default(tiny_model_cfg(mode))
    assert isinstance(b.codec, PixelUnshuffleCodec)
    assert b.model.unet.config.in_channels == copies * b.codec.latent_channels
    assert b.source == "default"


def test_default_is_seeded():
    a, b = build_default(tiny_model_cfg()), build_default(tiny_model_cfg())
    for pa, pb in zip(a.model.parameters(), b.model.parameters(), strict=True):
        assert torch.equal(pa, pb)


def test_default_size_fits_budget():
    """The full-size default: base checkpoint <= 20 MB in float32."""
    b = build_default(ModelConfig())
    n_bytes = sum(p.numel() * 4 for p in b.model.unet.parameters())
    assert n_bytes <= 20e6
    assert b.codec.latent_channels == 48 and b.model.unet.config.in_channels == 144


def _sd2_cfg(path, **kw) -> ModelConfig:
    return ModelConfig(source="sd2", path=str(path), **kw)


def test_load_tiny_sd2_folder(tiny_sd2_dir, tmp_path):
    folder = shutil.copytree(tiny_sd2_dir, tmp_path / "sd2")
    b = load_fixer(_sd2_cfg(folder))
    assert isinstance(b.codec, VaeCodec) and b.codec.scaling_factor == pytest.approx(0.18215)
    assert b.model.unet.config.in_channels == 12
    assert b.model.prompt_embedding.shape == (1, 8, 16)
    assert b.scheduler_config["prediction_type"] == "v_prediction"  # auto: the checkpoint's
    assert b.scheduler_config["beta_schedule"] == "scaled_linear"
    assert (folder / "empty_prompt_embedding.safetensors").is_file()


def test_empty_prompt_embedding_cached_and_text_model_not_loaded_again(
    tiny_sd2_dir, tmp_path, monkeypatch
):
    from transformers import CLIPTextModel, CLIPTokenizer

    folder = shutil.copytree(tiny_sd2_dir, tmp_path / "sd2")
    cfg = _sd2_cfg(folder, embedding_cache=str(tmp_path / "cache"))
    first = load_fixer(cfg).model.prompt_embedding
    assert embedding_cache_path(cfg).is_file()
    tok = CLIPTokenizer.from_pretrained(folder / "tokenizer", local_files_only=True)
    te = CLIPTextModel.from_pretrained(folder / "text_encoder", local_files_only=True)
    torch.testing.assert_close(first, compute_empty_prompt_embedding(tok, te))

    def boom(*a, **k):
        raise AssertionError("text model loaded although the embedding is cached")

    monkeypatch.setattr(CLIPTextModel, "from_pretrained", boom)
    monkeypatch.setattr(CLIPTokenizer, "from_pretrained", boom)
    torch.testing.assert_close(load_fixer(cfg).model.prompt_embedding, first)


def test_sd2_gs_mode_has_8_channels(tiny_sd2_dir):
    b = load_fixer(_sd2_cfg(tiny_sd2_dir, mode="gs"))
    assert b.model.unet.config.in_channels == 8


def test_sd2_missing_folder_parts(tmp_path):
    (tmp_path / "unet").mkdir()
    with pytest.raises(FileNotFoundError, match="missing vae/"):
        load_fixer(_sd2_cfg(tmp_path))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_fixer(_sd2_cfg(tmp_path / "nope"))


def test_sd2_single_file_needs_local_config(tmp_path):
    f = tmp_path / "sd2.safetensors"
    f.write_bytes(b"")
    with pytest.raises(ValueError, match="single_file_config"):
        load_fixer(_sd2_cfg(f))


@pytest.mark.parametrize(("mode", "copies"), [("mesh+gs", 3), ("gs", 2), ("mesh", 2)])
def test_empty_path_loads_the_packaged_base(mode, copies):
    from gsfix_online.fixer.sources import BASE_CHECKPOINT

    assert (BASE_CHECKPOINT / "manifest.json").is_file()
    assert sum(f.stat().st_size for f in BASE_CHECKPOINT.iterdir()) <= 20e6
    b = load_fixer(ModelConfig(mode=mode))
    assert b.model.mode == mode and b.model.residual
    assert b.model.unet.config.in_channels == copies * 48
    assert b.scheduler_config["prediction_type"] == "sample"
    assert b.scheduler_config["rescale_betas_zero_snr"] is True
    assert all(p.dtype == torch.float32 for p in b.model.parameters())  # stored float16


def test_packaged_base_refuses_another_model_size():
    from gsfix_online.fixer.config import DefaultModelConfig

    with pytest.raises(ValueError, match="random_init"):
        load_fixer(ModelConfig(default=DefaultModelConfig(block_out_channels=(16, 32))))
    assert load_fixer(tiny_model_cfg()).model.unet.config.block_out_channels == [8, 16]


def test_a_failed_embedding_cache_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    import errno

    import safetensors.torch

    from gsfix_online.fixer.sources import _load_or_compute_embedding

    def full(tensors, filename, metadata=None):  # noqa: ANN001, ANN202
        Path(filename).write_bytes(b"half a file")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(safetensors.torch, "save_file", full)
    cfg = _sd2_cfg(tmp_path / "sd2", embedding_cache=str(tmp_path / "cache"))
    with pytest.raises(OSError, match="cannot write .*: No space left on device"):
        _load_or_compute_embedding(cfg, lambda: torch.zeros(1, 4, 8))
    assert list((tmp_path / "cache").iterdir()) == []
