"""Tests for gsfix_online/fixer/checkpoint.py: atomic writes, latest pointer, round trips."""

from __future__ import annotations

import pytest
import torch

from gsfix_online.fixer import checkpoint as ck
from gsfix_online.fixer.config import InferenceConfig, ModelConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.sources import build_default
from tests.fixer.conftest import tiny_model_cfg


def _perturb(bundle, seed=0):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in bundle.model.parameters():
            p.add_(0.01 * torch.randn(p.shape, generator=g))


def test_save_load_same_output(tmp_path):
    cfg = tiny_model_cfg()
    b = build_default(cfg)
    _perturb(b)
    path = ck.save_checkpoint(tmp_path / "ckpt", b, 7, cfg, extra={"keyframes": 12})
    assert path.name == "step_000007"
    assert (tmp_path / "ckpt" / "latest").read_text().strip() == "step_000007"
    loaded = ck.load_checkpoint(tmp_path / "ckpt")
    assert loaded.step == 7 and loaded.manifest["extra"] == {"keyframes": 12}
    assert loaded.trainer_state is None
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    a = repair(b, x, x, InferenceConfig(steps=2)).images
    c = repair(loaded.bundle, x, x, InferenceConfig(steps=2)).images
    torch.testing.assert_close(a, c, atol=0, rtol=0)
    # the model source interface loads the same checkpoint
    again = load_fixer(ModelConfig(path=str(tmp_path / "ckpt"), default=cfg.default))
    torch.testing.assert_close(repair(again, x, x, InferenceConfig(steps=2)).images, a)


def test_keep_prunes_old_checkpoints(tmp_path):
    cfg = tiny_model_cfg("gs")
    b = build_default(cfg)
    for step in (1, 2, 3, 4):
        ck.save_checkpoint(tmp_path, b, step, cfg, keep=2)
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_000003", "step_000004"]
    assert ck.load_checkpoint(tmp_path).step == 4
    assert ck.load_checkpoint(tmp_path / "step_000003").step == 3


def test_crash_during_write_leaves_previous_checkpoint(tmp_path, monkeypatch):
    cfg = tiny_model_cfg()
    b = build_default(cfg)
    ck.save_checkpoint(tmp_path, b, 1, cfg)

    def crash(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ck.torch, "save", crash)
    with pytest.raises(OSError, match="disk full"):
        ck.save_checkpoint(tmp_path, b, 2, cfg, trainer_state={"step": 2})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest", "step_000001"]
    assert ck.load_checkpoint(tmp_path).step == 1


def test_not_a_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="neither"):
        ck.load_checkpoint(tmp_path)


def test_sd2_checkpoint_round_trip(tiny_sd2_dir, tmp_path):
    cfg = ModelConfig(source="sd2", path=str(tiny_sd2_dir), embedding_cache=str(tmp_path / "c"))
    b = load_fixer(cfg)
    _perturb(b)
    ck.save_checkpoint(tmp_path / "ft", b, 5, cfg)
    loaded = ck.load_checkpoint(tmp_path / "ft")
    assert loaded.bundle.source == "sd2" and loaded.bundle.model.unet.config.in_channels == 12
    for pa, pb in zip(
        b.model.unet.parameters(), loaded.bundle.model.unet.parameters(), strict=True
    ):
        assert torch.equal(pa, pb)


def test_checkpoint_mode_must_match_config(tmp_path):
    cfg = tiny_model_cfg("gs")
    ck.save_checkpoint(tmp_path, build_default(cfg), 1, cfg)
    with pytest.raises(ValueError, match="trained for mode 'gs'"):
        load_fixer(ModelConfig(path=str(tmp_path), mode="mesh+gs", default=cfg.default))


def test_float16_weights_load_into_float32(tmp_path):
    cfg = tiny_model_cfg()
    b = build_default(cfg)
    _perturb(b)
    ck.save_checkpoint(tmp_path / "h", b, 1, cfg, weights_dtype=torch.float16)
    ck.save_checkpoint(tmp_path / "f", b, 1, cfg)
    size = {k: (tmp_path / k / "step_000001" / "unet.safetensors").stat().st_size for k in "hf"}
    assert size["h"] < 0.55 * size["f"]
    loaded = ck.load_checkpoint(tmp_path / "h").bundle
    assert all(p.dtype == torch.float32 for p in loaded.model.parameters())
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    a = repair(b, x, x, InferenceConfig(steps=2)).images
    c = repair(loaded, x, x, InferenceConfig(steps=2)).images
    torch.testing.assert_close(c, a, atol=2e-3, rtol=0)  # float16 rounding of the weights
