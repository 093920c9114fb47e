"""GSFixer on CPU: the codec choice and the sizing of the embedded default model.

1. Codec: reconstruction PSNR and encode+decode time per 320x240 view of the exact
   pixel-unshuffle codec (f = 4, 8) against diffusers' AutoencoderTiny with random weights (the
   only small VAE we could have without downloading, since pretrained TAESD weights cannot be
   fetched).
2. Model candidates (codec factor, U-Net widths): parameters and base-checkpoint size, 4-step
   DDIM repair time per 320x240 view, and the time of one fine-tuning step (batch x accumulation
   micro-batches of latent crops) plus the latent-cache build per keyframe, extrapolated to a
   fine-tune of ``--keyframes`` keyframes and ``--steps`` steps.

Timings are medians over ``--repeats`` on 2 threads. Run it alone:

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_fixer.py [--out benchmarks/results/fixer_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gsfix_online.fixer.codec import PixelUnshuffleCodec, to_model_range
from gsfix_online.fixer.config import (
    DefaultModelConfig,
    InferenceConfig,
    MaskConfig,
    ModelConfig,
    TrainConfig,
)
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.sources import build_default
from gsfix_online.fixer.train import LatentCache, Trainer

H, W = 240, 320


def test_image(seed: int = 0) -> torch.Tensor:  # [1, 3, H, W] in [0, 1]
    """A textured image: smooth colour fields plus sharp edges and fine noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W] / max(H, W)
    img = np.zeros((H, W, 3))
    for c in range(3):
        for _ in range(6):
            fx, fy, ph = rng.uniform(1, 12, 2).tolist() + [rng.uniform(0, 6.3)]
            img[..., c] += np.sin(2 * math.pi * (fx * x + fy * y) + ph)
    img = (img - img.min()) / (img.max() - img.min())
    img[60:120, 80:200] = rng.uniform(0, 1, 3)  # a flat patch with sharp edges
    img += rng.normal(0, 0.03, img.shape)
    return torch.from_numpy(img.clip(0, 1)).permute(2, 0, 1)[None].float()


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def timed(fn: Any, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_codecs(img: torch.Tensor, repeats: int) -> list[dict[str, Any]]:
    from diffusers import AutoencoderTiny

    x = to_model_range(img)
    rows = []
    for f in (4, 8):
        codec = PixelUnshuffleCodec(f)
        rec = (codec.decode(codec.encode(x)) + 1) / 2
        t = timed(lambda c=codec: c.decode(c.encode(x)), repeats)
        rows.append(
            {
                "codec": f"pixel_unshuffle f={f}",
                "latent": list(codec.encode(x).shape[1:]),
                "psnr_db": psnr(rec, img),
                "max_abs_err": float((rec - img).abs().max()),
                "encode_decode_s": t,
                "weights_mb": 0.0,
            }
        )
    torch.manual_seed(0)
    tiny = AutoencoderTiny().eval()  # TAESD architecture, random weights
    with torch.no_grad():
        rec = ((tiny.decode(tiny.encode(x).latents).sample).clamp(-1, 1) + 1) / 2
        t = timed(lambda: tiny.decode(tiny.encode(x).latents), repeats)
        lat = list(tiny.encode(x).latents.shape[1:])
    rows.append(
        {
            "codec": "AutoencoderTiny (random weights)",
            "latent": lat,
            "psnr_db": psnr(rec, img),
            "max_abs_err": float((rec - img).abs().max()),
            "encode_decode_s": t,
            "weights_mb": sum(p.numel() for p in tiny.parameters()) * 4 / 1e6,
        }
    )
    return rows


def bench_model(
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    img: torch.Tensor,
    repeats: int,
    keyframes: int,
    steps: int,
) -> dict[str, Any]:
    bundle = build_default(model_cfg)
    n_params = sum(p.numel() for p in bundle.model.unet.parameters())
    gs = (img * 0.9).clamp(0, 1)
    # 1. Inference: 4-step DDIM on one 320x240 view (encode, 4 U-Net passes, decode)
    infer = InferenceConfig(steps=4)
    t_infer = timed(lambda: repair(bundle, img, gs, infer), repeats)
    # 2. Latent cache build per keyframe (mask draws + encoding of the pool)
    cache = LatentCache(bundle.codec, MaskConfig(), pool_size=train_cfg.pool_size)
    t_cache = timed(lambda: cache.add("k", img[0], gs[0], img[0]), repeats)
    # 3. One optimizer step
    trainer = Trainer(bundle.model, bundle.scheduler_config, train_cfg)
    t_step = timed(lambda: trainer.fit_step(cache), repeats)
    d = model_cfg.default
    return {
        "load_avg_1min": os.getloadavg()[0],  # other processes on the shared machine
        "codec_factor": d.codec_factor,
        "block_out_channels": list(d.block_out_channels),
        "layers_per_block": d.layers_per_block,
        "params_m": n_params / 1e6,
        "checkpoint_mb_fp32": n_params * 4 / 1e6,
        "infer_4step_s_per_view": t_infer,
        "cache_add_s_per_keyframe": t_cache,
        "train_step_s": t_step,
        "finetune_estimate_s": keyframes * t_cache + steps * t_step,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keyframes", type=int, default=60)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/fixer_cpu.json"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    img = test_image()
    codecs = bench_codecs(img, args.repeats)
    for row in codecs:
        print(
            f"{row['codec']:34s} latent {row['latent']}  PSNR {row['psnr_db']:.1f} dB  "
            f"{row['encode_decode_s'] * 1e3:.1f} ms"
        )
    train_cfg = TrainConfig()
    candidates = [
        DefaultModelConfig(),
        DefaultModelConfig(block_out_channels=(32, 64, 128, 128)),
        DefaultModelConfig(block_out_channels=(48, 96, 192)),
        DefaultModelConfig(block_out_channels=(32, 64, 128), layers_per_block=2),
        DefaultModelConfig(codec_factor=8, block_out_channels=(64, 128, 192)),
    ]
    models = []
    for d in candidates:
        row = bench_model(
            ModelConfig(default=d), train_cfg, img, args.repeats, args.keyframes, args.steps
        )
        models.append(row)
        print(
            f"f={row['codec_factor']} {row['block_out_channels']} x{row['layers_per_block']}: "
            f"{row['params_m']:.2f} M ({row['checkpoint_mb_fp32']:.1f} MB)  "
            f"infer {row['infer_4step_s_per_view']:.2f} s/view  step {row['train_step_s']:.2f} s  "
            f"cache {row['cache_add_s_per_keyframe'] * 1e3:.0f} ms/kf  "
            f"fine-tune {args.keyframes} kf x {args.steps} steps ~ {row['finetune_estimate_s']:.0f} s"
        )
    result = {
        "machine": {"platform": platform.platform(), "threads": args.threads},
        "torch": torch.__version__,
        "image": [H, W],
        "train": {
            "batch_size": train_cfg.batch_size,
            "grad_accum": train_cfg.grad_accum,
            "crop_latent": train_cfg.crop,
            "pool_size": train_cfg.pool_size,
            "keyframes": args.keyframes,
            "steps": args.steps,
        },
        "repeats": args.repeats,
        "codecs": codecs,
        "models": models,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
