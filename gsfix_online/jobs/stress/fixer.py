"""Stress properties of GSFixer: DDIM repair and one fine-tuning step, in float32 and bfloat16.

The model is the embedded default at a tiny size with random weights (as ``tests/fixer``
builds it); inputs are images at the edges of [0, 1] (all black, all white, 1 - 1e-7,
subnormal, checkerboards, random), sizes from 1 px (padding) up, gray or colour, every mode.

- ``fixer.inference``: the repaired images are finite, in [0, 1] and of the input's shape, with
  float32 and bfloat16 weights;
- ``fixer.train_step``: one step (latents cached in float16 as the trainer does, timesteps
  0 and T - 1 included, every prediction type, float32 or under bfloat16 autocast, as
  ``TrainConfig.mixed_precision`` does on CUDA) leaves a finite loss, finite weights and a
  finite EMA.
"""

from __future__ import annotations

import copy
import functools
from typing import Any

import numpy as np
from hypothesis import strategies as st

from gsfix_online.jobs.stress import Property

MODES = ("mesh+gs", "gs", "mesh")


@functools.lru_cache(maxsize=8)
def tiny_bundle(mode: str, dtype_name: str = "float32", prediction_type: str = "sample") -> Any:
    """A tiny embedded GSFixer with random weights (seed 0), cast to ``dtype_name``."""
    import torch

    from gsfix_online.fixer.config import DefaultModelConfig, ModelConfig
    from gsfix_online.fixer.sources import build_default

    default = DefaultModelConfig(
        codec_factor=2, block_out_channels=(8, 16), norm_num_groups=4, residual=False
    )
    cfg = ModelConfig(mode=mode, default=default, random_init=True, prediction_type=prediction_type)  # type: ignore[arg-type]
    bundle = build_default(cfg)
    bundle.model.to(getattr(torch, dtype_name))
    return bundle


def _image(kind: str, c: int, h: int, w: int, seed: int) -> Any:  # [1, c, h, w] in [0, 1]
    import torch

    g = torch.Generator().manual_seed(seed)
    if kind == "random":
        return torch.rand(1, c, h, w, generator=g)
    if kind == "checker":
        yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        return ((yy + xx) % 2).float().expand(1, c, h, w).clone()
    value = {"black": 0.0, "white": 1.0, "almost_white": 1 - 1e-7, "subnormal": 1e-40}[kind]
    return torch.full((1, c, h, w), value)


_KINDS = ["random", "checker", "black", "white", "almost_white", "subnormal"]


@st.composite
def _inference_case(draw: st.DrawFn) -> dict[str, Any]:
    return {
        "mode": draw(st.sampled_from(MODES)),
        "dtype": draw(st.sampled_from(["float32", "bfloat16"])),
        "c": draw(st.sampled_from([1, 3])),
        "h": draw(st.integers(1, 20)),
        "w": draw(st.integers(1, 20)),
        "mesh": draw(st.sampled_from(_KINDS)),
        "gs": draw(st.sampled_from(_KINDS)),
        "steps": draw(st.integers(1, 3)),
        "seed": draw(st.integers(0, 2**31 - 1)),
    }


def check_inference(ex: dict[str, Any]) -> None:
    """Repairs are finite, in [0, 1] and of the input's shape (float32 and bfloat16 weights)."""
    import torch

    from gsfix_online.fixer.config import InferenceConfig
    from gsfix_online.fixer.inference import repair

    bundle = tiny_bundle(ex["mode"], ex["dtype"])
    c, h, w = ex["c"], ex["h"], ex["w"]
    mesh = _image(ex["mesh"], c, h, w, ex["seed"]) if "mesh" in ex["mode"] else None
    gs = _image(ex["gs"], c, h, w, ex["seed"] + 1) if "gs" in ex["mode"] else None
    out = repair(bundle, mesh, gs, InferenceConfig(steps=ex["steps"], seed=ex["seed"])).images
    assert tuple(out.shape) == (1, c, h, w), f"repair shape {tuple(out.shape)}"
    assert torch.isfinite(out).all(), f"non-finite repair ({ex['dtype']} weights)"
    assert float(out.min()) >= 0 and float(out.max()) <= 1, "repair outside [0, 1]"


@st.composite
def _train_case(draw: st.DrawFn) -> dict[str, Any]:
    return {
        "mode": draw(st.sampled_from(MODES)),
        "prediction_type": draw(st.sampled_from(["sample", "epsilon", "v_prediction"])),
        "autocast": draw(st.booleans()),
        "kinds": draw(st.lists(st.sampled_from(_KINDS), min_size=3, max_size=3)),
        "timesteps": draw(
            st.lists(
                st.one_of(st.sampled_from([0, 999]), st.integers(0, 999)), min_size=2, max_size=2
            )
        ),
        "masks": draw(st.booleans()),
        "seed": draw(st.integers(0, 2**31 - 1)),
    }


def check_train_step(ex: dict[str, Any]) -> None:
    """One fine-tuning step on extreme triplets keeps the loss, weights and EMA finite."""
    import torch

    from gsfix_online.fixer.config import MaskConfig, TrainConfig
    from gsfix_online.fixer.train import LatentCache, Trainer

    base = tiny_bundle(ex["mode"], "float32", ex["prediction_type"])
    model = copy.deepcopy(base.model)  # the cached weights stay as built
    cfg = TrainConfig(batch_size=2, grad_accum=1, crop=0, ema_decay=0.9, seed=ex["seed"])
    trainer = Trainer(model, base.scheduler_config, cfg)
    cache = LatentCache(base.codec, MaskConfig(enabled=ex["masks"]), pool_size=2, seed=ex["seed"])
    mesh, gs, gt = (_image(k, 3, 8, 8, ex["seed"] + i)[0] for i, k in enumerate(ex["kinds"]))
    cache.add(0, mesh, gs, gt)
    batch = cache.sample(2, torch.Generator().manual_seed(ex["seed"]))
    t = torch.tensor(ex["timesteps"], dtype=torch.int64)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=ex["autocast"]):
        loss = trainer.loss(batch, timesteps=t)
    assert torch.isfinite(loss), f"non-finite loss {float(loss)}"
    res = trainer.train_step([batch])
    assert np.isfinite(res.loss), f"non-finite step loss {res.loss}"
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), f"non-finite weight {name} after one step"
    with trainer.averaged():
        for name, p in model.named_parameters():
            assert torch.isfinite(p).all(), f"non-finite EMA weight {name}"


PROPERTIES = [
    Property(
        "fixer.inference",
        "DDIM repairs of extreme images (1 px to 20 px, gray, bf16 weights): finite, in [0, 1]",
        _inference_case,
        check_inference,
        ci_examples=10,
    ),
    Property(
        "fixer.train_step",
        "one fine-tuning step on extreme triplets (t = 0, T-1, bf16 autocast): finite weights",
        _train_case,
        check_train_step,
        ci_examples=6,
    ),
]
