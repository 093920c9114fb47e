"""Repairing views with GSFixer: deterministic DDIM from the condition renders (Sec. 3.2).

:func:`repair` encodes the mesh and 3DGS renders of a batch of views (and in mode
``mesh+gs+ref`` their reference warps, over the mesh render: ``model.ref_condition``), starts ``z_T`` from seeded
Gaussian noise, runs ``steps`` DDIM steps (eta = 0, "trailing" spacing, so the first step starts
at t = T - 1 even with 1 step) and decodes the last step's x0 estimate. Images of any size are padded to the codec's and the
U-Net's multiple and cropped back; grayscale views come back grayscale.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from gsfix_online.fixer.codec import to_model_range
from gsfix_online.fixer.config import MODE_CONDITIONS, InferenceConfig
from gsfix_online.fixer.model import condition_images, ref_condition, select_conditions
from gsfix_online.fixer.sources import FixerBundle


@dataclass
class RepairResult:
    images: Tensor  # [B, C, H, W] in [0, 1], C and size as the inputs
    timesteps: list[int]  # DDIM timesteps visited


def _check_images(
    image_mesh: Tensor | None,
    image_gs: Tensor | None,
    mode: str,
    image_ref: Tensor | None = None,
    ref_valid: Tensor | None = None,
) -> tuple[int, int, int, int]:
    given = {"mesh": image_mesh, "gs": image_gs, "ref": image_ref}
    shape = None
    for name in MODE_CONDITIONS[mode]:
        img = given[name]
        if img is None:
            raise ValueError(f"mode {mode!r} needs image_{name}, got None")
        if img.ndim != 4 or img.shape[1] not in (1, 3) or not img.is_floating_point():
            raise ValueError(
                f"image_{name} must be float [B, 1|3, H, W] in [0, 1], "
                f"got {img.dtype} {list(img.shape)}"
            )
        if shape is not None and tuple(img.shape) != shape:
            raise ValueError(f"image_{name} differs from the other images: {list(img.shape)} vs "
                             f"{list(shape)}")  # fmt: skip
        shape = tuple(img.shape)
    assert shape is not None
    if "ref" in MODE_CONDITIONS[mode]:
        want = [shape[0], 1, shape[2], shape[3]]
        if ref_valid is None or ref_valid.dtype != torch.bool or list(ref_valid.shape) != want:
            got = "None" if ref_valid is None else f"{ref_valid.dtype} {list(ref_valid.shape)}"
            raise ValueError(f"mode {mode!r} needs ref_valid bool {want}, got {got}")
    return shape  # type: ignore[return-value]


@torch.no_grad()
def repair(
    bundle: FixerBundle,
    image_mesh: Tensor | None,  # [B, C, H, W] in [0, 1], C = 1 or 3; None in mode gs
    image_gs: Tensor | None,  # [B, C, H, W]; None in mode mesh
    cfg: InferenceConfig,
    generator: torch.Generator | None = None,  # default: a CPU generator seeded with cfg.seed
    image_ref: Tensor | None = None,  # [B, C, H, W] reference warp; mode mesh+gs+ref only
    ref_valid: Tensor | None = None,  # [B, 1, H, W] bool: the warp has a pixel there
) -> RepairResult:
    from diffusers import DDIMScheduler

    model, codec = bundle.model, bundle.codec
    model.eval()
    device = next(model.parameters()).device
    # 1. Check inputs
    b, c, h, w = _check_images(image_mesh, image_gs, model.mode, image_ref, ref_valid)
    image_gs = condition_images(image_mesh, image_gs, model.gs_condition)
    if "ref" in model.conditions:
        assert image_mesh is not None and image_ref is not None and ref_valid is not None
        image_ref = ref_condition(image_mesh, image_ref, ref_valid)
    else:
        image_ref = None

    # 2. Block offsets: with ``shifts`` > 1 the views are repaired on that many codec grids,
    # each shifted diagonally by a fraction of the codec's block, and the repairs averaged
    # (cycle spinning), so no pixel grid is preferred (GSFixer's errors follow its latent blocks).
    f = codec.downsample
    offsets = sorted({round(i * f / cfg.shifts) for i in range(cfg.shifts)})
    if generator is None:
        generator = torch.Generator().manual_seed(cfg.seed)
    scheduler = DDIMScheduler.from_config(bundle.scheduler_config, timestep_spacing="trailing")
    scheduler.set_timesteps(cfg.steps, device=device)
    total: Tensor | None = None
    for o in offsets:
        img = _repair_grid(model, codec, scheduler, image_mesh, image_gs, image_ref, o,
                           (b, c, h, w), cfg, generator, device)  # fmt: skip
        total = img if total is None else total + img
    assert total is not None
    return RepairResult((total / len(offsets)).cpu(), [int(t) for t in scheduler.timesteps])


def _repair_grid(
    model: Any,
    codec: Any,
    scheduler: Any,
    image_mesh: Tensor | None,  # [B, C, H, W] in [0, 1]
    image_gs: Tensor | None,  # [B, C, H, W]
    image_ref: Tensor | None,  # [B, C, H, W] the reference slot's image (ref_condition)
    offset: int,  # pixels the codec grid starts before the image, along both axes
    shape: tuple[int, int, int, int],  # (B, C, H, W)
    cfg: InferenceConfig,
    generator: torch.Generator,
    device: torch.device,
) -> Tensor:  # [B, C, H, W] in [0, 1]
    b, c, h, w = shape
    # 1. Pad to the codec's and U-Net's multiple (replicate: no artificial black border), with
    # ``offset`` pixels before the image
    mult = codec.downsample * model.multiple
    ph, pw = -(h + offset) % mult, -(w + offset) % mult

    def prep(img: Tensor | None) -> Tensor | None:
        if img is None:
            return None
        img = to_model_range(img.to(device, torch.float32))
        pad = (offset, pw, offset, ph)
        return F.pad(img, pad, mode="replicate") if any(pad) else img

    mesh, gs, ref = prep(image_mesh), prep(image_gs), prep(image_ref)

    # 2. Initial noise for all views at once, so results do not depend on the batch size
    lat_shape = (
        b,
        codec.latent_channels,
        (h + offset + ph) // codec.downsample,
        (w + offset + pw) // codec.downsample,
    )
    noise = torch.randn(lat_shape, generator=generator).to(device)
    out = []
    for i in range(0, b, cfg.batch_size):
        sl = slice(i, i + cfg.batch_size)
        # 3. Encode the conditions
        z_mesh = codec.encode(mesh[sl]) if mesh is not None else None
        z_gs = codec.encode(gs[sl]) if gs is not None else None
        z_ref = codec.encode(ref[sl]) if ref is not None else None
        cond = select_conditions(model.mode, z_mesh, z_gs, z_ref)
        cond = cond.to(next(model.parameters()).dtype)
        # 4. Denoise with DDIM (eta = 0: deterministic given the initial noise)
        z = noise[sl].to(cond.dtype)
        for k, t in enumerate(scheduler.timesteps):
            pred = model(cond, z, t.expand(z.shape[0]))
            res = scheduler.step(pred, t, z, eta=0.0)
            # The last step returns its x0 estimate: its prev_sample would keep
            # sqrt(1 - alpha_bar_0) = 0.029 of the noise (set_alpha_to_one is off in SD2's
            # schedule), a floor of ~37 dB on repairs.
            last = k == len(scheduler.timesteps) - 1
            z = res.pred_original_sample if last else res.prev_sample
        # 5. Decode, crop back, restore the channel count
        img = (codec.decode(z).float().clamp(-1, 1) + 1) / 2
        img = img[..., offset : offset + h, offset : offset + w]
        out.append(img.mean(dim=1, keepdim=True) if c == 1 else img)
    return torch.cat(out)
