"""Configuration of GSFixer: model source, mask augmentation policy, fine-tuning, inference.

One frozen dataclass per component, composed into :class:`FixerConfig` (the ``fixer`` section of
the root config). Defaults follow the GSFix3D paper where it gives a value and the CPU budget of
the embedded default model where it does not (each such field says so).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng

FixerMode = Literal["mesh+gs", "gs", "mesh", "mesh+gs+ref"]
ModelSource = Literal["default", "sd2"]
PredictionType = Literal["auto", "epsilon", "v_prediction", "sample"]
GsCondition = Literal["render", "mesh_first"]
# What "auto" means for the embedded default (the SD2 source takes its checkpoint's scheduler).
# x0 ("sample") prediction on the zero-terminal-SNR schedule, with the residual skip of
# DefaultModelConfig, chosen by measurement (benchmarks/results/fixer_pretrain.json): fitting
# the default model to one degraded triplet (3DGS input 28.5 dB) for 400 steps, 1- / 4-step
# DDIM repairs reach 6.0 / 6.0 dB with epsilon (its x0 estimate at t ~ T divides the error by
# sqrt(alpha_bar_T) = 0.07), 20.1 / 11.8 dB with v-prediction, 28.6 / 28.7 dB with x0 and
# 34.2 / 34.1 dB with x0 + residual. Pretrained for 2000 steps, the base repairs held-out
# views at 26.6 dB against 21.4 dB for their 3DGS input (4 steps; 26.3 dB at 1 step).
DEFAULT_PREDICTION_TYPE = "sample"

# Conditions per mode, in the order they are concatenated before z_t (the paper's order). The
# residual skip (DefaultModelConfig.residual) adds the *last* one: 3DGS wherever a mode has it,
# so the reference warp ("ref": real frames near the view warped into it by the mesh depth,
# the mesh render where the warp has no pixels; see model.ref_condition) goes between the two.
MODE_CONDITIONS: dict[str, tuple[str, ...]] = {
    "mesh+gs": ("mesh", "gs"),
    "gs": ("gs",),
    "mesh": ("mesh",),
    "mesh+gs+ref": ("mesh", "ref", "gs"),
}
# Where the new slot of mode mesh+gs+ref goes when a mesh+gs model is widened for it.
REF_SLOT = MODE_CONDITIONS["mesh+gs+ref"].index("ref")


@dataclass(frozen=True)
class DefaultModelConfig:
    """The embedded default: a small U-Net on an exact pixel-unshuffle codec (CPU-sized)."""

    codec_factor: int = field(
        default=4, metadata=rng(2, 8, "pixel-unshuffle factor f: latents are 3*f*f x H/f x W/f")
    )
    # (32, 64, 128) at f = 4: 4 U-Net passes on a 320x240 view in ~1 s on 2 CPU cores, 2.1 M
    # parameters (8.5 MB fp32); see benchmarks/results/fixer_cpu.json.
    block_out_channels: tuple[int, ...] = (32, 64, 128)
    layers_per_block: int = field(default=1, metadata=rng(1, 4, "resnets per U-Net level"))
    norm_num_groups: int = field(default=8, metadata=rng(1, 64, "GroupNorm groups"))
    cross_attention_dim: int = field(
        default=8, metadata=rng(1, 4096, "width of the (unused, all-zero) prompt embedding")
    )
    seed: int = field(default=0, metadata=rng(0, None, "seed of the random initialisation"))
    # x0 = U-Net output + the 3DGS latent (the mesh latent in mode mesh); needs prediction_type
    # sample; the U-Net's last convolution starts at zero, so a fresh model returns its input.
    residual: bool = True

    def validate(self) -> None:
        if not self.block_out_channels:
            raise ValueError("block_out_channels must not be empty")
        for c in self.block_out_channels:
            if c <= 0 or c % self.norm_num_groups:
                raise ValueError(
                    f"block_out_channels {self.block_out_channels} must be positive multiples "
                    f"of norm_num_groups {self.norm_num_groups}"
                )


@dataclass(frozen=True)
class ModelConfig:
    """Which model to load and how its U-Net is conditioned."""

    source: ModelSource = "default"  # default = embedded small model; sd2 = Stable Diffusion 2
    # default: a checkpoint folder written by save_checkpoint ("" = the pretrained base that
    # ships inside the package, gsfix_online/fixer/weights/base).
    # sd2: a diffusers folder (unet/ vae/ text_encoder/ tokenizer/ scheduler/) or a single
    # .safetensors/.ckpt file (then single_file_config names the local diffusers config folder).
    path: str = ""
    single_file_config: str = ""
    # Where the empty-prompt embedding is cached; "" = next to the checkpoint.
    embedding_cache: str = ""
    # default only, with path "": random weights of the size in `default` instead of the
    # packaged base (pretraining starts there; tests use tiny models).
    random_init: bool = False
    # the scene decides: no mesh -> gs. mesh+gs+ref: the reference warp as a third condition
    # (a mesh+gs checkpoint or the base starts it with the new slot's weights at zero)
    mode: FixerMode = "mesh+gs"
    # What the 3DGS slot (mode mesh+gs) is given: "render" = the 3DGS render (the paper);
    # "mesh_first" = the mesh render where the mesh covers a pixel, the 3DGS render elsewhere,
    # so that the repair starts (residual skip) from the better-placed surface. The mesh slot
    # keeps the mesh render, so the U-Net still sees where the mesh has holes. A checkpoint is
    # fed as it was trained (its manifest records this); the value here applies to the model
    # that fine-tuning or pretraining starts from.
    gs_condition: GsCondition = "render"
    # What the U-Net predicts. auto: the SD2 source takes its checkpoint's scheduler config
    # (SD2-base: epsilon, as the paper); the embedded default takes DEFAULT_PREDICTION_TYPE.
    # Non-epsilon types use the zero-terminal-SNR schedule, so that the first DDIM step at
    # t = T - 1 predicts x0 from the conditions alone; see DEFAULT_PREDICTION_TYPE's figures.
    prediction_type: PredictionType = "auto"
    default: DefaultModelConfig = field(default_factory=DefaultModelConfig)

    def validate(self) -> None:
        if self.gs_condition != "render" and self.mode != "mesh+gs":
            raise ValueError(
                f"gs_condition {self.gs_condition} needs mode mesh+gs, got mode {self.mode}"
            )
        if self.source == "sd2" and not self.path:
            raise ValueError("source sd2 needs path (a local SD2 folder or single file)")
        resolved = (
            DEFAULT_PREDICTION_TYPE if self.prediction_type == "auto" else self.prediction_type
        )
        if self.source == "default" and self.default.residual and resolved != "sample":
            raise ValueError(
                f"default.residual needs prediction_type sample, got {self.prediction_type} "
                "(set default.residual=false)"
            )


@dataclass(frozen=True)
class MaskConfig:
    """Random mask augmentation policy (GSFix3D Sec. 3.1.2); pure parameters, no state."""

    enabled: bool = True
    # 0.5 each (was 0.3): views asked for repair are off the trajectory and have large holes
    # in both renders; the base was pretrained with 0.5, and with 0.5 plus perturbed-pose alpha
    # holes a 300-step tank fine-tune repairs novel views at 16.2 dB (0.3 without those holes:
    # 14.5 dB); benchmarks/results/fixer_report_cpu.json.
    p_shared: float = field(
        default=0.5, metadata=rng(0, 1, "probability of one mask on both mesh and 3DGS (occlusion)")
    )
    p_gs_only: float = field(
        default=0.5, metadata=rng(0, 1, "probability of an extra mask on the 3DGS image only")
    )
    # Not in the paper: a hard mask on the mesh image only, as where the TSDF mesh has a hole
    # (beyond depth_max, too few observations) but the 3DGS map renders well. 0 = off.
    p_mesh_only: float = field(
        default=0.0, metadata=rng(0, 1, "probability of an extra mask on the mesh image only")
    )
    # GSFix3D blurs with sigma 10 px at 480x640; as a fraction of the shorter image side.
    blur_sigma_frac: float = field(
        default=0.021, metadata=rng(0, 1, "Gaussian blur of 3DGS masks, sigma / min(H, W)")
    )
    use_shapes: bool = True  # procedural object-like shapes
    use_disocclusion: bool = True  # keyframe depth reprojected into a nearby keyframe
    use_alpha_holes: bool = True  # holes of Gaussian-map renders at perturbed poses
    shape_area: tuple[float, float] = field(
        default=(0.02, 0.2), metadata=rng(0, 1, "area fraction range of a procedural shape")
    )
    max_shapes: int = field(default=3, metadata=rng(1, 16, "pieces in one procedural mask"))
    alpha_threshold: float = field(
        default=0.5, metadata=rng(0, 1, "render alpha below this is a hole")
    )

    def validate(self) -> None:
        lo, hi = self.shape_area
        if not 0 < lo <= hi:
            raise ValueError(f"shape_area must satisfy 0 < min <= max, got {self.shape_area}")


@dataclass(frozen=True)
class TrainConfig:
    """Fine-tuning protocol: DDPM, noise-prediction MSE, Adam (paper: lr 3e-5, batch 2 x 16)."""

    lr: float = field(default=3e-5, metadata=rng(0, 1, "Adam learning rate"))
    batch_size: int = field(default=2, metadata=rng(1, None, "samples per micro-batch"))
    # Paper 16; the CPU default uses 4 so that a few hundred steps fit in 10 minutes.
    grad_accum: int = field(default=4, metadata=rng(1, None, "micro-batches per optimizer step"))
    num_train_timesteps: int = field(default=1000, metadata=rng(1, None, "DDPM steps T"))
    # Random crop of the cached latents, in latent pixels (0 = whole view). The U-Net is
    # convolutional, so crops train it at a fraction of the cost of whole views.
    crop: int = field(default=32, metadata=rng(0, None, "latent crop side, 0 = none"))
    pool_size: int = field(
        default=4, metadata=rng(1, None, "mask-augmented variants cached per keyframe")
    )
    mixed_precision: bool = True  # bf16 autocast, on CUDA only
    seed: int = field(default=0, metadata=rng(0, None, "seed of noise, timesteps and crops"))
    # Off by default: not shown to help (a 300-step pretraining with 0.5 repaired held-out
    # views at 28.0 dB against 29.3 dB without, but that run also had other training settings).
    # Share of samples whose timestep is one that DDIM visits with focus_steps trailing steps
    # (e.g. 999, 749, 499, 249); the rest are uniform over [0, T) as in DDPM.
    timestep_focus: float = field(
        default=0.0, metadata=rng(0, 1, "share of timesteps drawn from the inference schedule")
    )
    focus_steps: int = field(default=4, metadata=rng(1, 1000, "DDIM steps whose timesteps focus"))
    # Exponential moving average of the U-Net weights (diffusers EMAModel: decay
    # min(ema_decay, n / (9 + n)) at step n > 1): held-out evaluations and checkpoints use the
    # averaged weights. 0 = off (the paper's protocol). A few hundred small-batch CPU steps leave
    # checkpoints 0.7 dB apart on novel views; averaging them removes most of that spread.
    ema_decay: float = field(
        default=0.0, metadata=rng(0, 0.99999, "EMA decay of the weights; 0 = no EMA")
    )
    # Weight-space ensembling with the weights fine-tuning started from (WiSE-FT): evaluations
    # and checkpoints hold start + wise_alpha x (trained - start), after the EMA. 1 = the
    # trained weights (the paper's protocol). Fine-tuning teaches the scene's colours where no
    # map holds anything (+5 dB there at novel views) but over-corrects surfaces the maps
    # render (-0.3..-1.3 dB at held-out frames); 0.75 kept most of the first and undid most of
    # the second (benchmarks/results/finetune_wise_cpu.json).
    wise_alpha: float = field(
        default=1.0, metadata=rng(0, 1, "share of the fine-tuning kept in checkpoints")
    )


@dataclass(frozen=True)
class InferenceConfig:
    """Deterministic DDIM repair of views."""

    steps: int = field(default=4, metadata=rng(1, 1000, "DDIM steps (paper: 4)"))
    batch_size: int = field(default=4, metadata=rng(1, None, "views per U-Net batch"))
    seed: int = field(default=0, metadata=rng(0, None, "seed of the initial noise"))
    # Codec grids per view (cycle spinning): 1 repairs on one grid; k > 1 averages the repairs
    # on k grids shifted diagonally by 1/k of the codec's block, which removes the block
    # pattern of the pixel-unshuffle codec (figures: benchmarks/results/fixer_shifts_cpu.md).
    shifts: int = field(default=1, metadata=rng(1, 64, "codec grid offsets averaged per view"))


@dataclass(frozen=True)
class FixerConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    inference: InferenceConfig = field(default_factory=InferenceConfig)
