"""The GSFixer denoiser: a diffusers U-Net on ``concat(z_mesh, z_gs, z_t)`` without text.

The U-Net's first convolution is widened for the condition latents by repeating its pretrained
weights along the input channels and dividing by the number of copies (GSFix3D Sec. 3.1.1), so
that identical latents in every slot reproduce the pretrained response. Text conditioning is
replaced by a fixed empty-prompt embedding held as a buffer (see ``sources.py`` for its cache).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from gsfix_online.fixer.config import MODE_CONDITIONS, REF_SLOT


def _replace_conv_in(unet: Any, weight: Tensor) -> Any:  # weight [O, I', k, k]
    """Swap ``unet.conv_in`` for one with ``weight`` (and the old bias), in place; returns unet.

    ``unet.config.in_channels`` is updated so that ``save_pretrained`` / ``from_pretrained``
    round-trip the changed model."""
    old: nn.Conv2d = unet.conv_in
    new = nn.Conv2d(
        weight.shape[1],
        old.out_channels,
        kernel_size=old.kernel_size,
        stride=old.stride,
        padding=old.padding,
        bias=old.bias is not None,
    ).to(device=old.weight.device, dtype=old.weight.dtype)
    with torch.no_grad():
        new.weight.copy_(weight)
        if old.bias is not None:
            new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=new.in_channels)
    return unet


def widen_conv_in(unet: Any, n_conditions: int) -> Any:
    """Give ``unet.conv_in`` ``(n_conditions + 1) x`` its input channels, in place; returns unet.

    The weights are repeated ``n_conditions + 1`` times along the input channels and divided by
    that count; the bias is kept.
    """
    copies = n_conditions + 1
    return _replace_conv_in(unet, unet.conv_in.weight.detach().repeat(1, copies, 1, 1) / copies)


def merge_condition_slots(unet: Any, latent_channels: int) -> Any:
    """Turn a ``mesh+gs`` U-Net into a one-condition one (mode ``gs`` or ``mesh``), in place.

    The first convolution's weights of the two condition slots are summed into one slot, so the
    narrowed U-Net given a latent ``z`` responds as the wide one given ``z`` in both slots (the
    3DGS render standing in for the mesh render, or the other way round). Fine-tuning starts
    there. Returns unet.
    """
    w = unet.conv_in.weight.detach()
    c = latent_channels
    if w.shape[1] != 3 * c:
        raise ValueError(f"conv_in takes {w.shape[1]} channels, a mesh+gs U-Net has {3 * c}")
    return _replace_conv_in(unet, torch.cat([w[:, :c] + w[:, c : 2 * c], w[:, 2 * c :]], dim=1))


def add_condition_slot(unet: Any, latent_channels: int, slot: int = REF_SLOT) -> Any:
    """Turn a ``mesh+gs`` U-Net into a ``mesh+gs+ref`` one, in place; returns unet.

    The first convolution gets a new condition slot at ``slot`` (in latents, counted from 0)
    whose weights are zero, so the widened U-Net responds to any reference latent exactly as the
    ``mesh+gs`` one does without it; fine-tuning then learns what the reference adds. (Repeating
    and dividing the weights, as :func:`widen_conv_in` does from an unconditioned U-Net, would
    halve the response to the 3DGS or mesh latent where the reference differs from it.)
    """
    w = unet.conv_in.weight.detach()
    c = latent_channels
    if w.shape[1] != 3 * c:
        raise ValueError(f"conv_in takes {w.shape[1]} channels, a mesh+gs U-Net has {3 * c}")
    zero = torch.zeros_like(w[:, :c])
    return _replace_conv_in(unet, torch.cat([w[:, : slot * c], zero, w[:, slot * c :]], dim=1))


class GSFixer(nn.Module):
    """Predicts the noise (or v, or x0) of ``z_t`` given the condition latents of one mode.

    ``residual`` (the embedded default only, with x0 prediction): the output is the U-Net's
    output plus the last condition latent (3DGS in modes mesh+gs, mesh+gs+ref and gs, the mesh
    in mode mesh: ``MODE_CONDITIONS`` keeps the residual's slot last),
    so the U-Net learns the repair as a correction and starts from the identity when its last
    convolution is zero. A small U-Net learns the identity map slowly: its 32 full-resolution
    channels cannot carry the 48 of a pixel-unshuffle latent (see config.py for the figures).
    """

    def __init__(
        self,
        unet: Any,  # diffusers UNet2DConditionModel, already widened
        mode: str,
        latent_channels: int,
        prompt_embedding: Tensor,  # [1, L, D] empty-prompt embedding
        residual: bool = False,  # add the last condition latent to the output (x0 prediction)
        gs_condition: str = "render",  # what the 3DGS slot is given: see ModelConfig
    ) -> None:
        super().__init__()
        n = len(MODE_CONDITIONS[mode])
        expected = latent_channels * (n + 1)
        if unet.config.in_channels != expected:
            raise ValueError(
                f"U-Net takes {unet.config.in_channels} input channels, mode {mode!r} with "
                f"{latent_channels}-channel latents needs {expected} (call widen_conv_in)"
            )
        self.unet = unet
        self.mode = mode
        self.conditions = MODE_CONDITIONS[mode]
        self.latent_channels = latent_channels
        self.residual = residual
        assert mode == "mesh" or self.conditions[-1] == "gs", "the residual's slot must be last"
        if gs_condition != "render" and mode != "mesh+gs":
            raise ValueError(f"gs_condition {gs_condition} needs mode mesh+gs, got mode {mode}")
        self.gs_condition = gs_condition
        self.register_buffer("prompt_embedding", prompt_embedding.detach().clone())

    @property
    def multiple(self) -> int:
        """Latent sizes must be multiples of this (the U-Net's total downsampling)."""
        return 2 ** (len(self.unet.config.block_out_channels) - 1)

    def forward(
        self,
        z_cond: Tensor,  # [B, n*C, h, w] condition latents, concatenated in mode order
        z_t: Tensor,  # [B, C, h, w] noisy target latent
        t: Tensor,  # [B] integer timesteps
    ) -> Tensor:  # [B, C, h, w]
        x = torch.cat([z_cond, z_t], dim=1)
        emb = self.prompt_embedding.to(x.dtype).expand(x.shape[0], -1, -1)
        out = self.unet(x, t, encoder_hidden_states=emb).sample
        if self.residual:  # the U-Net predicts the correction of the 3DGS (or mesh) latent
            out = out + z_cond[:, -self.latent_channels :]
        return out


def condition_images(
    image_mesh: Tensor | None,  # [B, C, H, W] mesh render, black where the mesh has no surface
    image_gs: Tensor | None,  # [B, C, H, W] 3DGS render
    gs_condition: str,  # "render" or "mesh_first" (ModelConfig.gs_condition)
) -> Tensor | None:  # the image for the 3DGS slot
    """The 3DGS slot's image: the render itself, or with ``mesh_first`` the mesh render wherever
    it has a surface (any channel above zero) and the 3DGS render elsewhere."""
    if gs_condition == "render" or image_mesh is None or image_gs is None:
        return image_gs
    if gs_condition != "mesh_first":
        raise ValueError(f"gs_condition must be render or mesh_first, got {gs_condition!r}")
    covered = (image_mesh > 0).any(dim=-3, keepdim=True)
    return torch.where(covered, image_mesh, image_gs)


def ref_condition(
    image_mesh: Tensor,  # [B, C, H, W] mesh render (masked as the 3DGS render is, in training)
    image_ref: Tensor,  # [B, C, H, W] reference warp, black where it has no pixels
    ref_valid: Tensor,  # [B, 1, H, W] bool: the warp has a pixel there
) -> Tensor:  # [B, C, H, W] the image for the reference slot
    """The reference slot's image: the warp where it has pixels, the mesh render elsewhere.

    Not black: the tank is dark, and a black hole would read as a dark wall. The mesh render is
    the view's nearest guess there (``repair.ref_warp.ref_warp_inpaint`` fills the warp from it
    too), and where the two slots agree the U-Net can see that the warp had nothing there. A view without any warp gets the mesh render
    in both slots, as a training sample without references does."""
    if ref_valid.dtype != torch.bool or ref_valid.ndim != 4 or ref_valid.shape[1] != 1:
        raise ValueError(
            f"ref_valid must be bool [B, 1, H, W], got {ref_valid.dtype} {list(ref_valid.shape)}"
        )
    return torch.where(ref_valid, image_ref, image_mesh)


def select_conditions(
    mode: str,
    z_mesh: Tensor | None,  # [B, C, h, w]
    z_gs: Tensor | None,  # [B, C, h, w]
    z_ref: Tensor | None = None,  # [B, C, h, w] (mode mesh+gs+ref)
) -> Tensor:  # [B, n*C, h, w]
    """Concatenate the condition latents a mode uses, in its order (``MODE_CONDITIONS``)."""
    parts = {"mesh": z_mesh, "gs": z_gs, "ref": z_ref}
    chosen = [parts[name] for name in MODE_CONDITIONS[mode]]
    missing = [n for n, z in zip(MODE_CONDITIONS[mode], chosen, strict=True) if z is None]
    if missing:
        raise ValueError(f"mode {mode!r} needs the {', '.join(missing)} image(s), got None")
    return torch.cat(chosen, dim=1)  # type: ignore[arg-type]
