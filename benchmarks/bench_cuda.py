"""The CUDA paths on a GPU machine: gsplat against the CPU rasterizer, GSFixer repair and
fine-tuning speed with the packaged base and with a Stable Diffusion 2-size model.

Sections (``--sections``), each timed with CUDA events or synchronised clocks, medians over
``--repeats`` after a warm-up, the CPU baseline measured in the same run:

- ``render``: one forward + backward render of N random Gaussians at 640x480 through gsplat
  (CUDA) and through our CPU rasterizer (``--cpu-threads``), for several N.
- ``fixer``: the packaged base: 4-step and 1-step DDIM repair per view (``shifts`` 1 and 4) at
  320x240, 640x480 and 1200x680 on CUDA, and at 320x240 on the CPU; one fine-tuning step of the
  repair graph's protocol (batch 2 x 4) and of the paper's (2 x 16).
- ``sd2``: a Stable Diffusion 2-base-size GSFixer (U-Net 866 M parameters, SD's VAE) with random
  weights, written as a diffusers folder and loaded through ``load_fixer`` (the product path);
  4-step DDIM per view at 512x512, 640x480 and 1200x680 in float16 and float32, and one
  fine-tuning step (batch 2, bf16 autocast) with its peak memory. Random weights cost the same
  time as trained ones; no weights can be downloaded here.

    python benchmarks/bench_cuda.py [--sections render fixer sd2] [--out results.json]

Figures on a lent GPU machine: ``benchmarks/results/cuda_<device>.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from gsfix_online.fixer.config import InferenceConfig, MaskConfig, ModelConfig, TrainConfig
from gsfix_online.fixer.inference import repair
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.fixer.sources import EMBEDDING_FILE
from gsfix_online.fixer.train import LatentCache, Trainer

SIZES = {"320x240": (240, 320), "640x480": (480, 640), "1200x680": (680, 1200)}
DEV = "cuda"  # --smoke: "cpu", tiny sizes (checks this script on a machine without a GPU)
SMOKE = False


def sync() -> None:
    if DEV == "cuda":
        torch.cuda.synchronize()


def peak_gib() -> float:
    return torch.cuda.max_memory_allocated() / 2**30 if DEV == "cuda" else float("nan")


def reset_peak() -> None:
    if DEV == "cuda":
        torch.cuda.reset_peak_memory_stats()


def timed(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> float:
    """Median seconds of ``fn`` (synchronised before and after each call)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def images(h: int, w: int, n: int = 1, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth textured view and a degraded copy with a black hole ([n, 3, h, w] in [0, 1])."""
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    f = torch.rand(n, 3, 2, generator=g) * 12 + 1
    img = 0.5 + 0.4 * torch.sin(f[..., 0, None, None] * x + f[..., 1, None, None] * y)
    gs = img.clone()
    gs[..., h // 4 : h // 2, w // 4 : w // 2] = 0
    return img.clamp(0, 1), gs


# ------------------------------------------------------------------------------------------


def bench_render(repeats: int, cpu_threads: int) -> list[dict[str, Any]]:
    from gsfix_online.mapping.splat.render import render

    rows = []
    w, h = 640, 480
    K = torch.tensor([[500.0, 0, w / 2], [0, 500.0, h / 2], [0, 0, 1]])
    for n in (200,) if SMOKE else (10_000, 100_000, 1_000_000):
        g = torch.Generator().manual_seed(n)
        means = torch.randn(n, 3, generator=g) * torch.tensor([1.5, 1.0, 0.5])
        means[:, 2] += 4.0
        quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
        scales = torch.rand(n, 3, generator=g) * 0.03 + 0.005
        opac = torch.rand(n, generator=g) * 0.9 + 0.05
        colors = torch.rand(n, 3, generator=g)
        row: dict[str, Any] = {"gaussians": n, "size": f"{w}x{h}"}
        for backend in ("cuda", "cpu"):
            if backend == "cpu" and (n > 100_000 or not cpu_threads):
                continue
            if backend == "cuda" and DEV != "cuda":
                continue
            dev = "cuda" if backend == "cuda" else "cpu"
            params = [t.to(dev).requires_grad_(True) for t in (means, quats, scales, opac, colors)]
            view, Kd = torch.eye(4, device=dev), K.to(dev)

            def step(params=params, view=view, Kd=Kd, backend=backend) -> None:
                out = render(*params, view, Kd, w, h, backend=backend)
                (out.color.mean() + out.depth.mean()).backward()

            if backend == "cpu":
                old = torch.get_num_threads()
                torch.set_num_threads(cpu_threads)
            try:
                row[f"{backend}_fwd_bwd_s"] = timed(step, repeats if backend == "cuda" else 1)
            finally:
                if backend == "cpu":
                    torch.set_num_threads(old)
        if "cpu_fwd_bwd_s" in row and "cuda_fwd_bwd_s" in row:
            row["speedup"] = row["cpu_fwd_bwd_s"] / row["cuda_fwd_bwd_s"]
        print(f"render {row}", flush=True)
        rows.append(row)
    return rows


def bench_fixer(repeats: int, cpu_threads: int, base: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {"repair": [], "train": [], "base": base or "packaged"}
    bundle = load_fixer(ModelConfig(path=base))  # "" = the packaged base
    params = sum(p.numel() for p in bundle.model.unet.parameters())
    out["params_m"] = params / 1e6
    for dev in dict.fromkeys((DEV, "cpu") if cpu_threads else (DEV,)):
        bundle.to(dev)
        sizes = SIZES if dev == "cuda" else {"320x240": SIZES["320x240"]}
        if SMOKE:
            sizes = {"40x32": (32, 40)}
        if dev == "cpu":
            torch.set_num_threads(cpu_threads)
        for name, (h, w) in sizes.items():
            mesh, gs = images(h, w)
            for steps, shifts in ((4, 1), (1, 4), (4, 4)):
                cfg = InferenceConfig(steps=steps, shifts=shifts)
                t = timed(lambda b=bundle, c=cfg, m=mesh, g=gs: repair(b, m, g, c), repeats)
                row = {
                    "device": dev,
                    "size": name,
                    "steps": steps,
                    "shifts": shifts,
                    "s_per_view": t,
                }
                out["repair"].append(row)
                print(f"fixer repair {row}", flush=True)
        if dev == "cuda":  # throughput of a batch of 8 views
            mesh, gs = images(*(32, 40) if SMOKE else (240, 320), n=8)
            cfg = InferenceConfig(steps=4, shifts=1, batch_size=8)
            t = timed(lambda b=bundle, m=mesh, g=gs, c=cfg: repair(b, m, g, c), repeats)
            out["repair_batch8_320x240_s_per_view"] = t / 8
    bundle.to(DEV)
    mesh, gs = images(*(32, 40) if SMOKE else (240, 320), n=4)
    for name, tc in (
        ("repair graph (batch 2 x 4, crop 32)", TrainConfig(batch_size=2, grad_accum=4)),
        ("paper (batch 2 x 16, crop 32)", TrainConfig(batch_size=2, grad_accum=16)),
        ("paper, whole views (batch 2 x 16)", TrainConfig(batch_size=2, grad_accum=16, crop=0)),
    ):
        cache = LatentCache(bundle.codec, MaskConfig(), tc.pool_size, device=DEV)
        t_cache = timed(lambda c=cache: c.add("k", mesh[0], gs[0], mesh[0]), repeats)
        for i in range(4):
            cache.add(i, mesh[i], gs[i], mesh[i])
        trainer = Trainer(bundle.model, bundle.scheduler_config, tc, DEV)
        t_step = timed(lambda tr=trainer, c=cache: tr.fit_step(c), repeats, warmup=2)
        row = {"protocol": name, "step_s": t_step, "cache_add_s": t_cache,
               "steps_per_10_min": int(600 / t_step)}  # fmt: skip
        out["train"].append(row)
        print(f"fixer train {row}", flush=True)
    return out


SD2_UNET = dict(  # Stable Diffusion 2(-base) U-Net
    sample_size=64,
    in_channels=4,
    out_channels=4,
    down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
    up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
    block_out_channels=(320, 640, 1280, 1280),
    layers_per_block=2,
    cross_attention_dim=1024,
    attention_head_dim=(5, 10, 20, 20),
    use_linear_projection=True,
)
SD_VAE = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 4,
    up_block_types=("UpDecoderBlock2D",) * 4,
    block_out_channels=(128, 256, 512, 512),
    layers_per_block=2,
    latent_channels=4,
    sample_size=768,
    scaling_factor=0.18215,
)


def write_sd2(root: Path) -> Path:
    """An SD2-size diffusers folder with random weights and a cached empty-prompt embedding."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from safetensors.torch import save_file

    torch.manual_seed(0)
    unet_cfg, vae_cfg = SD2_UNET, SD_VAE
    if SMOKE:
        unet_cfg = {**SD2_UNET, "block_out_channels": (32, 64, 64, 64), "attention_head_dim": 8}
        vae_cfg = {**SD_VAE, "block_out_channels": (32, 32, 32, 32)}
    UNet2DConditionModel(**unet_cfg).save_pretrained(root / "unet")
    AutoencoderKL(**vae_cfg).save_pretrained(root / "vae")
    DDIMScheduler(
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
        set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon",
    ).save_pretrained(root / "scheduler")  # fmt: skip
    save_file({"embedding": torch.randn(1, 77, 1024) * 0.1}, str(root / EMBEDDING_FILE))
    return root


def bench_sd2(repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {"repair": []}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        root = write_sd2(Path(tmp) / "sd2")
        out["write_s"] = time.perf_counter() - t0
        for dtype in (torch.float16, torch.float32):
            t0 = time.perf_counter()
            bundle = load_fixer(ModelConfig(source="sd2", path=str(root)), torch_dtype=dtype)
            bundle.to(DEV)
            sync()
            load_s = time.perf_counter() - t0
            out["unet_params_m"] = sum(p.numel() for p in bundle.model.unet.parameters()) / 1e6
            sizes = {"512x512": (512, 512), **SIZES}
            for name, (h, w) in ({"64x48": (48, 64)} if SMOKE else sizes).items():
                if name == "320x240":
                    continue
                mesh, gs = images(h, w)
                cfg = InferenceConfig(steps=4, shifts=1)
                reset_peak()
                t = timed(lambda b=bundle, c=cfg, m=mesh, g=gs: repair(b, m, g, c), repeats)
                row = {"dtype": str(dtype).replace("torch.", ""), "size": name, "steps": 4,
                       "s_per_view": t, "load_s": load_s,
                       "peak_gib": peak_gib()}  # fmt: skip
                out["repair"].append(row)
                print(f"sd2 repair {row}", flush=True)
            if dtype == torch.float32:  # fine-tuning keeps fp32 master weights (bf16 autocast)
                mesh, gs = images(*(48, 64) if SMOKE else (480, 640), n=2)
                tc = TrainConfig(batch_size=2, grad_accum=1, crop=0, pool_size=1)
                cache = LatentCache(bundle.codec, MaskConfig(), 1, device=DEV)
                for i in range(2):
                    cache.add(i, mesh[i], gs[i], mesh[i])
                bundle.model.unet.enable_gradient_checkpointing()
                trainer = Trainer(bundle.model, bundle.scheduler_config, tc, DEV)
                reset_peak()
                t = timed(lambda tr=trainer, c=cache: tr.fit_step(c), repeats, warmup=2)
                out["train_step_640x480_batch2_s"] = t
                out["train_step_peak_gib"] = peak_gib()
                out["train_steps_x16_accum_per_10_min"] = int(600 / (16 * t))
                print(f"sd2 train step {t:.3f} s, peak {out['train_step_peak_gib']:.1f} GiB")
            del bundle
            if DEV == "cuda":
                torch.cuda.empty_cache()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", nargs="+", default=["render", "fixer", "sd2"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--cpu-threads", type=int, default=2, help="the CPU baseline's threads (0: no CPU rows)"
    )
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--smoke", action="store_true", help="CPU, tiny sizes: checks the script")
    ap.add_argument("--base", default="", help="fixer: a base checkpoint folder (packaged base)")
    args = ap.parse_args()
    global DEV, SMOKE
    if args.smoke:
        DEV, SMOKE, args.repeats = "cpu", True, 1
    elif not torch.cuda.is_available():
        raise SystemExit("bench_cuda needs a CUDA device (torch sees none); --smoke runs on CPU")
    result: dict[str, Any] = {
        "device": torch.cuda.get_device_name(0) if DEV == "cuda" else "cpu (smoke)",
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "platform": platform.platform(),
        "cpu_threads_baseline": args.cpu_threads,
        "repeats": args.repeats,
        "errors": {},
    }
    benches = {
        "render": lambda: bench_render(args.repeats, args.cpu_threads),
        "fixer": lambda: bench_fixer(args.repeats, args.cpu_threads, args.base),
        "sd2": lambda: bench_sd2(args.repeats),
    }
    for name in args.sections:
        t0 = time.perf_counter()
        try:
            result[name] = benches[name]()
        except Exception as exc:  # one section's failure is a finding, not the end of the run
            result["errors"][name] = "".join(traceback.format_exception_only(exc)).strip()
            traceback.print_exc()
        result[f"{name}_wall_s"] = time.perf_counter() - t0
        if args.out:  # after each section: a killed run keeps what it measured
            args.out.write_text(json.dumps(result, indent=2, default=str))
    print(json.dumps({k: v for k, v in result.items() if k.endswith("wall_s") or k == "errors"}))
    return 1 if result["errors"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
