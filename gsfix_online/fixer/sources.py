"""Model sources, each as a :class:`FixerBundle` (:func:`gsfix_online.fixer.loader.load_fixer`
picks one):

- ``default``: the embedded small model (:func:`build_default`, or a checkpoint of it).
- ``sd2``: Stable Diffusion 2 from a local diffusers folder or a single-file checkpoint, with
  its frozen VAE as codec. Nothing is ever downloaded: every load passes ``local_files_only``.

The empty-prompt embedding is computed once from the checkpoint's tokenizer and text encoder and
cached to a safetensors file; later loads read the file and never build a text model.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from gsfix_online.core.io import atomic_path
from gsfix_online.fixer.codec import Codec, PixelUnshuffleCodec, VaeCodec
from gsfix_online.fixer.config import (
    DEFAULT_PREDICTION_TYPE,
    MODE_CONDITIONS,
    DefaultModelConfig,
    ModelConfig,
)
from gsfix_online.fixer.model import GSFixer, widen_conv_in

logger = logging.getLogger(__name__)

EMBEDDING_FILE = "empty_prompt_embedding.safetensors"
# The pretrained base of the embedded default, shipped as package data (rebuilt by
# `gsfix-online fixer pretrain`; see weights/base/manifest.json for its figures).
BASE_CHECKPOINT = Path(__file__).parent / "weights" / "base"
# SD2's DDPM schedule; the default model uses it too so both sources share one noise process.
SD2_SCHEDULER: dict[str, Any] = {
    "num_train_timesteps": 1000,
    "beta_start": 0.00085,
    "beta_end": 0.012,
    "beta_schedule": "scaled_linear",
    "clip_sample": False,
    "set_alpha_to_one": False,
    "steps_offset": 1,
    "prediction_type": "epsilon",
    "rescale_betas_zero_snr": False,
}


def default_scheduler_config(prediction_type: str) -> dict[str, Any]:
    """SD2's betas with ``prediction_type`` ("auto" = DEFAULT_PREDICTION_TYPE); every type but
    epsilon gets the zero-terminal-SNR rescaling, so z_T is pure noise and the first DDIM step
    predicts x0 from the conditions (epsilon cannot: x0 = (z - sqrt(1 - a) eps) / sqrt(a))."""
    pt = DEFAULT_PREDICTION_TYPE if prediction_type == "auto" else prediction_type
    return {**SD2_SCHEDULER, "prediction_type": pt, "rescale_betas_zero_snr": pt != "epsilon"}


@dataclass
class FixerBundle:
    """Everything inference and fine-tuning need: the denoiser, its codec and noise schedule."""

    model: GSFixer
    codec: Codec
    scheduler_config: dict[str, Any]  # DDPM/DDIM config (betas, T, prediction_type)
    source: str  # "default" or "sd2"
    base: dict[str, Any] = field(default_factory=dict)  # what to record in a manifest

    def to(self, device: torch.device | str) -> FixerBundle:
        self.model.to(device)
        if isinstance(self.codec, VaeCodec):
            self.codec.to(device)
        return self


def _diffusers() -> Any:
    try:
        import diffusers
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise ImportError("GSFixer needs diffusers: pip install 'diffusers>=0.30'") from exc
    return diffusers


def import_library() -> None:
    """Import diffusers and its U-Net class now: 4-8 s of one core on the 2-core machine (it
    imports torch's compiler, transformers and every model file), which a node that loads its
    model later should spend while it waits, not when its first view arrives."""
    _ = _diffusers().UNet2DConditionModel


def default_unet_config(cfg: DefaultModelConfig, latent_channels: int) -> dict[str, Any]:
    """U-Net config of the embedded default (before widening).

    Same class as SD2 (UNet2DConditionModel), so the wrapper, widening, checkpoints and
    inference are shared, but with no attention blocks. Without text, cross-attention would
    attend to one constant embedding, a mixture of fixed vectors that convolutions learn more
    cheaply, and self-attention over 80x60 latents costs more on CPU than the rest of the net.
    """
    n = len(cfg.block_out_channels)
    return {
        "sample_size": 64,
        "in_channels": latent_channels,
        "out_channels": latent_channels,
        "down_block_types": ["DownBlock2D"] * n,
        "up_block_types": ["UpBlock2D"] * n,
        "mid_block_type": "UNetMidBlock2D",
        "block_out_channels": list(cfg.block_out_channels),
        "layers_per_block": cfg.layers_per_block,
        "norm_num_groups": cfg.norm_num_groups,
        "cross_attention_dim": cfg.cross_attention_dim,
        "attention_head_dim": 8,
    }


def build_default(cfg: ModelConfig) -> FixerBundle:
    """The embedded default with random weights from ``cfg.default.seed`` (the pretraining start)."""
    d = _diffusers()
    codec = PixelUnshuffleCodec(cfg.default.codec_factor)
    unet_cfg = default_unet_config(cfg.default, codec.latent_channels)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.default.seed)
        unet = d.UNet2DConditionModel(**unet_cfg)
        if cfg.default.residual:  # start from the identity: x0 = the condition latent
            torch.nn.init.zeros_(unet.conv_out.weight)
            torch.nn.init.zeros_(unet.conv_out.bias)
    widen_conv_in(unet, len(MODE_CONDITIONS[cfg.mode]))
    embedding = torch.zeros(1, 1, cfg.default.cross_attention_dim)
    model = GSFixer(unet, cfg.mode, codec.latent_channels, embedding, cfg.default.residual,
                    cfg.gs_condition)  # fmt: skip
    sched = default_scheduler_config(cfg.prediction_type)
    return FixerBundle(model, codec, sched, "default", {"codec": codec.spec()})


# ------------------------------------------------------------------------------------------
# Stable Diffusion 2
# ------------------------------------------------------------------------------------------


def embedding_cache_path(cfg: ModelConfig) -> Path:
    """Where the empty-prompt embedding of ``cfg.path`` is cached."""
    src = Path(cfg.path)
    if cfg.embedding_cache:
        return Path(cfg.embedding_cache) / f"{src.name}.{EMBEDDING_FILE}"
    return src / EMBEDDING_FILE if src.is_dir() else src.with_name(f"{src.name}.{EMBEDDING_FILE}")


def compute_empty_prompt_embedding(tokenizer: Any, text_encoder: Any) -> Tensor:  # [1, L, D]
    ids = tokenizer(
        "", padding="max_length", max_length=tokenizer.model_max_length, return_tensors="pt"
    ).input_ids
    with torch.no_grad():
        return text_encoder(ids.to(text_encoder.device))[0].float().cpu()


def _load_or_compute_embedding(cfg: ModelConfig, compute: Any) -> Tensor:
    from safetensors.torch import load_file, save_file

    path = embedding_cache_path(cfg)
    if path.is_file():
        return load_file(str(path))["embedding"]
    logger.info("computing the empty-prompt embedding once; caching it to %s", path)
    emb = compute()
    with atomic_path(path) as tmp:  # removed when saving fails
        save_file({"embedding": emb.contiguous()}, str(tmp), metadata={"source": str(cfg.path)})
    return emb


def _sd2_scheduler_config(folder: Path | None, prediction_type: str) -> dict[str, Any]:
    sched = dict(SD2_SCHEDULER)
    if folder is not None and (folder / "scheduler" / "scheduler_config.json").is_file():
        raw = json.loads((folder / "scheduler" / "scheduler_config.json").read_text())
        sched.update({k: v for k, v in raw.items() if k in SD2_SCHEDULER})
    # auto: what the checkpoint was trained for (SD2-base epsilon, SD2 768-v v_prediction).
    if prediction_type != "auto":
        sched["prediction_type"] = prediction_type
    return sched


def load_sd2(cfg: ModelConfig, torch_dtype: torch.dtype = torch.float32) -> FixerBundle:
    """Stable Diffusion 2 from ``cfg.path``: a diffusers folder or a single-file checkpoint."""
    d = _diffusers()
    src = Path(cfg.path)
    if src.is_dir():
        missing = [s for s in ("unet", "vae") if not (src / s).is_dir()]
        if missing:
            raise FileNotFoundError(
                f"{src} is not a diffusers SD2 folder: missing {', '.join(missing)}/"
            )
        kw: dict[str, Any] = {"local_files_only": True, "torch_dtype": torch_dtype}
        unet = d.UNet2DConditionModel.from_pretrained(src, subfolder="unet", **kw)
        vae = d.AutoencoderKL.from_pretrained(src, subfolder="vae", **kw)

        def compute() -> Tensor:
            from transformers import CLIPTextModel, CLIPTokenizer

            tok = CLIPTokenizer.from_pretrained(src, subfolder="tokenizer", local_files_only=True)
            te = CLIPTextModel.from_pretrained(src, subfolder="text_encoder", **kw)
            return compute_empty_prompt_embedding(tok, te)

        sched_folder: Path | None = src
    elif src.is_file():
        if not cfg.single_file_config:
            raise ValueError(
                "a single-file SD2 checkpoint needs fixer.model.single_file_config: a local "
                "diffusers config folder (model_index.json, unet/, vae/, ...) of the same model"
            )
        config = cfg.single_file_config
        kw = {"config": config, "local_files_only": True, "torch_dtype": torch_dtype}
        unet = d.UNet2DConditionModel.from_single_file(str(src), subfolder="unet", **kw)
        vae = d.AutoencoderKL.from_single_file(str(src), subfolder="vae", **kw)

        def compute() -> Tensor:
            pipe = d.StableDiffusionPipeline.from_single_file(str(src), **kw)
            return compute_empty_prompt_embedding(pipe.tokenizer, pipe.text_encoder)

        sched_folder = Path(config)
    else:
        raise FileNotFoundError(f"SD2 source {src} does not exist (a folder or a file expected)")

    embedding = _load_or_compute_embedding(cfg, compute)
    codec = VaeCodec(vae, source=str(src))
    widen_conv_in(unet, len(MODE_CONDITIONS[cfg.mode]))
    model = GSFixer(unet, cfg.mode, codec.latent_channels, embedding, gs_condition=cfg.gs_condition)
    sched = _sd2_scheduler_config(sched_folder, cfg.prediction_type)
    return FixerBundle(model, codec, sched, "sd2", {"path": str(src), "codec": codec.spec()})
