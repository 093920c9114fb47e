"""Fine-tuning GSFixer: the latent cache and the trainer (GSFix3D Sec. 3.1).

- :class:`LatentCache` encodes each keyframe's triplet ``(I_mesh, I_gs, I_gt)`` once with the
  frozen codec, together with a pool of mask-augmented variants of the two conditions, and
  serves random (cropped) micro-batches from memory. The paper's code re-encodes all three images
  in every micro-batch.
- :class:`Trainer` holds the explicit training state (step count, Adam, the generator of noise,
  timesteps and crops) and runs one optimizer step over ``grad_accum`` micro-batches of the DDPM
  noise-prediction MSE. ``state_dict()`` / ``load_state_dict()`` checkpoint and resume it.
  With ``ema_decay`` > 0 it also keeps an exponential moving average of the weights, and with
  ``wise_alpha`` < 1 it moves them back towards the weights it started from (WiSE-FT);
  :meth:`Trainer.averaged` swaps the result in for evaluations and checkpoints.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from gsfix_online.fixer.codec import Codec, to_model_range
from gsfix_online.fixer.config import MaskConfig, TrainConfig
from gsfix_online.fixer.masks import BoolImage, MaskDraw, apply_masks, draw_masks, mesh_cut
from gsfix_online.fixer.model import GSFixer, condition_images, ref_condition, select_conditions


@dataclass
class Batch:
    z_mesh: Tensor  # [B, C, h, w]
    z_gs: Tensor  # [B, C, h, w]
    z_gt: Tensor  # [B, C, h, w]
    z_ref: Tensor | None = None  # [B, C, h, w] reference slot (mode mesh+gs+ref)


@dataclass
class StepResult:
    step: int  # optimizer steps done, this one included
    loss: float  # mean loss over the micro-batches of this step


@dataclass
class _Entry:
    z_mesh: Tensor  # [P, C, h, w] pool of (augmented) mesh latents
    z_gs: Tensor  # [P, C, h, w]
    z_gt: Tensor  # [1, C, h, w]
    z_ref: Tensor | None = None  # [P, C, h, w] reference slot, cut as the mesh variants are


class LatentCache:
    """Latents of keyframe triplets, each with ``pool_size`` mask-augmented condition variants."""

    def __init__(
        self,
        codec: Codec,
        mask_cfg: MaskConfig,
        pool_size: int = 4,
        seed: int = 0,
        dtype: torch.dtype = torch.float16,  # storage; batches come out float32
        device: torch.device | str = "cpu",
        gs_condition: str = "render",  # the model's ModelConfig.gs_condition
    ) -> None:
        self.codec = codec
        self.mask_cfg = mask_cfg
        self.gs_condition = gs_condition
        self.pool_size = pool_size if mask_cfg.enabled else 1
        self.rng = np.random.default_rng(seed)
        self.dtype = dtype
        self.device = torch.device(device)
        self._entries: dict[Any, _Entry] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def keys(self) -> list[Any]:
        return list(self._entries)

    @torch.no_grad()
    def add(
        self,
        key: Any,  # keyframe id; adding it again replaces its entry (e.g. after a re-render)
        image_mesh: Tensor,  # [C, H, W] float in [0, 1], C = 1 or 3
        image_gs: Tensor,  # [C, H, W]
        image_gt: Tensor,  # [C, H, W]
        disocclusions: list[BoolImage] | None = None,  # candidate masks for this keyframe
        alpha_holes: list[BoolImage] | None = None,
        image_ref: Tensor | None = None,  # [C, H, W] reference warp from *other* frames
        ref_valid: BoolImage | None = None,  # [H, W] the warp has a pixel there
    ) -> None:
        """Encode one keyframe: its ground truth once and ``pool_size`` augmented conditions
        (with ``image_ref``, the reference slot of each too: a mask cut into the mesh image
        cuts the warp there, and the slot shows the masked mesh where the warp has nothing)."""
        # 1. Check inputs
        shape = tuple(image_gt.shape)
        given = [("image_mesh", image_mesh), ("image_gs", image_gs)]
        for name, img in given + ([("image_ref", image_ref)] if image_ref is not None else []):
            if tuple(img.shape) != shape:
                raise ValueError(f"{name} must match image_gt {shape}, got {tuple(img.shape)}")
        if len(shape) != 3 or shape[0] not in (1, 3):
            raise ValueError(f"images must be [C, H, W] with C 1 or 3, got {shape}")
        _, h, w = shape
        d = self.codec.downsample
        if h % d or w % d:
            raise ValueError(f"image size {w}x{h} must be a multiple of the codec's {d}")
        if image_ref is not None and (
            not isinstance(ref_valid, np.ndarray)
            or ref_valid.dtype != np.bool_
            or ref_valid.shape != (h, w)
        ):
            got = f"{ref_valid.dtype} {ref_valid.shape}" if ref_valid is not None else "None"
            raise ValueError(f"image_ref needs ref_valid bool [{h}, {w}], got {got}")
        # 2. Draw the pool of masked variants
        meshes, gss, valids = [], [], []
        for i in range(self.pool_size):
            draw = MaskDraw(None, None)
            if i > 0 or self.mask_cfg.enabled:
                draw = draw_masks(self.mask_cfg, self.rng, h, w, disocclusions, alpha_holes)
            m, g = apply_masks(image_mesh, image_gs, draw, self.mask_cfg)
            meshes.append(m)
            gss.append(g)
            if image_ref is not None:
                assert ref_valid is not None
                valids.append(torch.from_numpy(ref_valid & ~mesh_cut(draw, h, w)))
        # 3. Encode (conditions of the whole pool in one batch); the 3DGS slot as the model is
        # fed at repair time, from the masked renders, and so is the reference slot
        mesh_pool = torch.stack(meshes)
        parts = [mesh_pool, condition_images(mesh_pool, torch.stack(gss), self.gs_condition)]
        if image_ref is not None:
            valid = torch.stack(valids)[:, None]
            parts.append(ref_condition(mesh_pool, image_ref.expand_as(mesh_pool), valid))
        conds = to_model_range(torch.cat(parts).to(self.device))
        z = self.codec.encode(conds).to(self.dtype).split(self.pool_size)
        z_gt = self.codec.encode(to_model_range(image_gt[None].to(self.device))).to(self.dtype)
        self._entries[key] = _Entry(z[0], z[1], z_gt, z[2] if image_ref is not None else None)

    def sample(
        self,
        batch_size: int,
        generator: torch.Generator,  # CPU generator: keyframe, variant and crop choices
        crop: int = 0,  # latent crop side (0 = whole latents)
    ) -> Batch:
        """A random micro-batch: keyframes with replacement, a random pool variant, a random crop."""
        if not self._entries:
            raise ValueError("the latent cache is empty: add keyframes first")
        keys = list(self._entries)
        zm, zg, zt, zr = [], [], [], []
        for _ in range(batch_size):
            e = self._entries[keys[int(torch.randint(len(keys), (1,), generator=generator))]]
            v = int(torch.randint(e.z_mesh.shape[0], (1,), generator=generator))
            _, _, h, w = e.z_gt.shape
            ch, cw = (min(crop, h), min(crop, w)) if crop else (h, w)
            y = int(torch.randint(h - ch + 1, (1,), generator=generator))
            x = int(torch.randint(w - cw + 1, (1,), generator=generator))
            window = (..., slice(y, y + ch), slice(x, x + cw))
            zm.append(e.z_mesh[v][window])
            zg.append(e.z_gs[v][window])
            zt.append(e.z_gt[0][window])
            if e.z_ref is not None:
                zr.append(e.z_ref[v][window])
        if zr and len(zr) != len(zt):
            raise ValueError("the latent cache mixes samples with and without a reference image")
        z_ref = torch.stack(zr).float() if zr else None
        return Batch(*(torch.stack(z).float() for z in (zm, zg, zt)), z_ref)


class Trainer:
    """DDPM fine-tuning of the whole U-Net with Adam; the state is step, optimizer, generator."""

    def __init__(
        self,
        model: GSFixer,
        scheduler_config: dict[str, Any],  # DDPM config of the model source
        cfg: TrainConfig,
        device: torch.device | str = "cpu",
    ) -> None:
        from diffusers import DDPMScheduler

        self.model = model.to(device)
        self.cfg = cfg
        self.device = torch.device(device)
        sched = {**scheduler_config, "num_train_timesteps": cfg.num_train_timesteps}
        self.noise_scheduler = DDPMScheduler.from_config(sched)
        self.optimizer = torch.optim.Adam(
            [p for p in model.parameters() if p.requires_grad], lr=cfg.lr
        )
        self.step = 0
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self._autocast = cfg.mixed_precision and self.device.type == "cuda"
        self.ema: Any = None
        if cfg.ema_decay > 0:
            from diffusers.training_utils import EMAModel

            self.ema = EMAModel(self._params(), decay=cfg.ema_decay)
        # the weights fine-tuning started from (the anchor of wise_alpha), kept through resumes
        self.start: list[Tensor] | None = None
        if cfg.wise_alpha < 1.0:
            self.start = [p.detach().clone() for p in self._params()]

    def _params(self) -> list[torch.nn.Parameter]:
        return [p for p in self.model.parameters() if p.requires_grad]

    @contextmanager
    def averaged(self) -> Iterator[None]:
        """The model holds the weights that evaluations and checkpoints use inside the block: the
        EMA (``ema_decay``), moved to ``start + wise_alpha (w - start)``; the trained weights
        again after it. Without either, the trained weights throughout."""
        if self.ema is None and self.start is None:
            yield
            return
        params = self._params()
        trained = [p.detach().clone() for p in params]
        with torch.no_grad():
            if self.ema is not None:
                self.ema.copy_to(params)
            if self.start is not None:
                for p, s0 in zip(params, self.start, strict=True):
                    p.lerp_(s0.to(p.device), 1.0 - self.cfg.wise_alpha)
        try:
            yield
        finally:
            with torch.no_grad():
                for p, t in zip(params, trained, strict=True):
                    p.copy_(t)

    def loss(
        self,
        batch: Batch,
        noise: Tensor | None = None,  # [B, C, h, w]; drawn from the generator when None
        timesteps: Tensor | None = None,  # [B] int64 in [0, T)
    ) -> Tensor:  # scalar
        """The noise-prediction MSE (or v-prediction MSE, as the scheduler's config says)."""
        z0 = batch.z_gt.to(self.device)
        b = z0.shape[0]
        if noise is None:
            noise = torch.randn(z0.shape, generator=self.generator)
        if timesteps is None:
            timesteps = self.sample_timesteps(b)
        noise, timesteps = noise.to(self.device), timesteps.to(self.device)
        z_t = self.noise_scheduler.add_noise(z0, noise, timesteps)
        z_ref = None if batch.z_ref is None else batch.z_ref.to(self.device)
        cond = select_conditions(
            self.model.mode, batch.z_mesh.to(self.device), batch.z_gs.to(self.device), z_ref
        )
        kind = self.noise_scheduler.config.prediction_type
        if kind == "v_prediction":
            target = self.noise_scheduler.get_velocity(z0, noise, timesteps)
        elif kind == "sample":
            target = z0
        else:
            target = noise
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=self._autocast):
            pred = self.model(cond, z_t, timesteps)
        return F.mse_loss(pred.float(), target.float())

    def sample_timesteps(self, n: int) -> Tensor:  # [n] int64 in [0, T)
        """Uniform timesteps, a ``timestep_focus`` share of them replaced by ones that DDIM
        visits with ``focus_steps`` trailing steps (T - 1, ..., T / focus_steps - 1)."""
        T = self.cfg.num_train_timesteps
        t = torch.randint(T, (n,), generator=self.generator, dtype=torch.int64)
        if self.cfg.timestep_focus > 0:
            k = self.cfg.focus_steps
            visited = (torch.arange(k, 0, -1) * T // k - 1).clamp_(0, T - 1)
            pick = visited[torch.randint(k, (n,), generator=self.generator)]
            focus = torch.rand(n, generator=self.generator) < self.cfg.timestep_focus
            t = torch.where(focus, pick, t)
        return t

    def train_step(self, micro_batches: list[Batch]) -> StepResult:
        """One optimizer step: gradients accumulated over ``micro_batches`` (their mean loss)."""
        self.model.train()
        self.optimizer.zero_grad(set_to_none=True)
        total = 0.0
        for batch in micro_batches:
            loss = self.loss(batch) / len(micro_batches)
            loss.backward()
            total += float(loss.detach())
        self.optimizer.step()
        if self.ema is not None:
            self.ema.step(self._params())
        self.step += 1
        return StepResult(self.step, total)

    def fit_step(self, cache: LatentCache) -> StepResult:
        """One optimizer step on ``grad_accum`` micro-batches sampled from ``cache``."""
        batches = [
            cache.sample(self.cfg.batch_size, self.generator, self.cfg.crop)
            for _ in range(self.cfg.grad_accum)
        ]
        return self.train_step(batches)

    def state_dict(self) -> dict[str, Any]:
        state = {
            "step": self.step,
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
        }
        if self.ema is not None:
            state["ema"] = self.ema.state_dict()
        if self.start is not None:
            state["wise_start"] = [t.clone() for t in self.start]
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        if self.ema is not None and "ema" in state:
            self.ema.load_state_dict(state["ema"])
        if self.start is not None and "wise_start" in state:
            start = state["wise_start"]
            if [t.shape for t in start] != [t.shape for t in self.start]:
                raise ValueError("wise_start does not match the model's trainable parameters")
            self.start = [t.clone() for t in start]
