"""Pretraining the embedded default GSFixer on procedurally generated scenes.

GSFix3D pretrains on synthetic indoor and street data with added noise and blur; we pretrain on
our own generator instead. Each scene is a ship tank with a randomised layout (length, width,
height, number of web frames; zero webs make a plain room), texture seed, lighting (lamps or
headlamp, ambient and power), field of view and camera sweep, rendered at a small size for a few
frames and cached on disk. Ground truth is degraded into the two conditions (``triplets.py``):

- ``I_gs``: ground truth blurred, with Gaussian noise and soft holes showing black background;
- ``I_mesh``: the ground-truth mesh ray-cast with its vertex colours (exact geometry, colours
  no finer than the mesh edge), relit with the frame's blurred light as a fused TSDF mesh is.

The last ``val_scenes`` scenes are held out: their loss is evaluated every ``eval_every`` steps,
and at the end their views are repaired with DDIM and scored against the degraded input.

Layout of ``OUT``::

    scenes/             cached renders, one .npz per scene (reused by later runs)
    checkpoints/        resumable checkpoints (with optimizer state), ``latest``
    base/               the exported base checkpoint (weights only): fixer.model.path
    pretrain.json       figures: losses, PSNR of repairs vs inputs, times
    config.yaml         the resolved configuration
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch

from gsfix_online.core.config import rng, to_dict
from gsfix_online.core.io import atomic_path, atomic_write_text
from gsfix_online.fixer.config import FixerConfig, TrainConfig
from gsfix_online.fixer.masks import alpha_hole_mask
from gsfix_online.fixer.triplets import DegradeConfig, degrade_gs, degrade_mesh, relit_mesh_render
from gsfix_online.jobs.map_corpus import MapCorpusConfig, load_or_build_corpus, map_views
from gsfix_online.scene.draws import is_room_seed, random_scene_layout

logger = logging.getLogger(__name__)

SCENE_CACHE_VERSION = 1


def _pretrain_train_defaults() -> TrainConfig:
    # What built the packaged base (benchmarks/results/fixer_pretrain.json): Adam lr 3e-4 on
    # batches of 32 crops of 32 latent pixels, an EMA of the weights (decay 0.999): 5100 steps in
    # 200 s on an H200 (on 2 CPU cores about 80 min, extrapolated, not timed; resumable). The base before
    # it (lr 3e-5, batch 2 x 4, 2000 steps on the CPU) repaired novel views 0.04 (tank) and
    # 0.46 dB (room) worse after fine-tuning, one run each
    # (benchmarks/results/variants_gpu_base_cpu.json).
    return TrainConfig(lr=3e-4, batch_size=32, grad_accum=1, crop=32, ema_decay=0.999, seed=0)


DEFAULT_GRAYSCALE_PROB = 0.2


@dataclass(frozen=True)
class PretrainConfig:
    """The pretraining job (the model itself is ``fixer.model``; masks are ``fixer.masks``)."""

    # The defaults rebuild the packaged base's first stage (benchmarks/results/fixer_pretrain.json);
    # `make pretrain-stage2` its second stage on our own maps (benchmarks/results/stage2_cpu.json).
    scenes: int = field(default=96, metadata=rng(2, 100_000, "procedural scenes, val included"))
    val_scenes: int = field(default=2, metadata=rng(1, 1000, "last scenes held out"))
    frames: int = field(default=6, metadata=rng(1, 1000, "frames rendered per scene"))
    width: int = field(default=160, metadata=rng(16, 4096, "render width, px"))
    height: int = field(default=128, metadata=rng(16, 4096, "render height, px"))
    # 0 = no synthetic degradations: train on the map triplets (``maps``) alone
    variants: int = field(default=4, metadata=rng(0, 64, "degraded versions of each frame"))
    grayscale_prob: float = field(
        default=DEFAULT_GRAYSCALE_PROB,
        metadata=rng(0, 1, "share of grayscale scenes (the ship rig's cameras)"),
    )
    # Indoor rooms (the scene generator's room family: furniture, books, pictures, painted walls)
    # beside the tanks, drawn per seed; 0 keeps the tank-only corpus the shipped base saw.
    room_prob: float = field(default=0.0, metadata=rng(0, 1, "share of room scenes"))
    steps: int = field(default=5100, metadata=rng(1, None, "optimizer steps in total"))
    eval_every: int = field(default=1000, metadata=rng(1, None, "steps between held-out losses"))
    save_every: int = field(default=500, metadata=rng(1, None, "steps between checkpoints"))
    val_views: int = field(default=8, metadata=rng(0, 1000, "held-out views repaired at the end"))
    seed: int = field(default=0, metadata=rng(0, 2**31 - 1, "first scene seed; degradations"))
    # The exported base in float16: half the size; its repairs are scored from that file.
    base_fp16: bool = True
    # Also write the base flat into the package (gsfix_online/fixer/weights/base), where
    # load_fixer finds it when fixer.model.path is empty.
    install: bool = False
    # Where the U-Net trains: auto = CUDA when torch sees a GPU (bf16 autocast there), else CPU.
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # Stop training after this many seconds of this sitting (a checkpoint is saved, the base is
    # exported and scored as at the end); a later --resume goes on towards ``steps``. 0 = none.
    time_limit_s: float = field(
        default=0.0, metadata=rng(0, None, "seconds of training per sitting, 0 = no limit")
    )
    # A fresh job starts from these weights (a checkpoint folder, e.g. the packaged base) instead
    # of random ones: a second stage on another corpus. Ignored when resuming. "" = random.
    init: str = ""
    train: TrainConfig = field(default_factory=_pretrain_train_defaults)
    degrade: DegradeConfig = field(default_factory=DegradeConfig)
    # Triplets rendered from each scene's own TSDF mesh and Gaussian map at its novel views (the
    # degradations a repair meets); maps.views = 0 leaves them out.
    maps: MapCorpusConfig = field(default_factory=MapCorpusConfig)

    def validate(self) -> None:
        if self.val_scenes >= self.scenes:
            raise ValueError(f"val_scenes {self.val_scenes} must be < scenes {self.scenes}")
        if self.variants == 0 and self.maps.views == 0:
            raise ValueError("pretrain.variants and pretrain.maps.views are both 0: no triplets")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise ValueError("pretrain.device is cuda, but torch sees no CUDA device")


@dataclass(frozen=True)
class PretrainJob:
    """Root config of ``gsfix-online fixer pretrain``."""

    fixer: FixerConfig = field(default_factory=FixerConfig)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)


@dataclass
class SceneViews:
    """A scene's cached renders."""

    seed: int
    gt: npt.NDArray[np.uint8]  # [F, H, W, 3] noise-free colour (gray scenes: equal channels)
    mesh: npt.NDArray[np.uint8]  # [F, H, W, 3] relit vertex-colour mesh render
    valid: npt.NDArray[np.bool_]  # [F, H, W] the mesh was hit


@dataclass
class PretrainResult:
    step: int
    checkpoint: Path  # resumable root
    base: Path  # exported weights-only checkpoint
    figures: dict[str, Any]


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------


def random_scene_config(seed: int, cfg: PretrainConfig, attempt: int = 0) -> Any:
    """A ShipTankConfig with layout, texture, lighting and camera drawn from ``seed``."""
    return random_scene_layout(
        seed, cfg.width, cfg.height, cfg.grayscale_prob, max(cfg.frames, 2), attempt,
        room_prob=cfg.room_prob,
    )  # fmt: skip


def render_scene(seed: int, cfg: PretrainConfig, attempts: int = 8) -> SceneViews:
    """Ground truth and relit mesh renders of ``cfg.frames`` frames of scene ``seed``."""
    from gsfix_online.mapping.mesh import TriMesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.scene.generate import build_scene, mesh_albedo_srgb, render_sample
    from gsfix_online.scene.trajectory import SceneLayoutError

    for attempt in range(attempts):
        try:
            scene = build_scene(random_scene_config(seed, cfg, attempt))
            break
        except SceneLayoutError as exc:  # e.g. no trajectory with enough clearance
            logger.debug("scene %d attempt %d: %s", seed, attempt, exc)
    else:
        raise RuntimeError(f"no valid layout for scene seed {seed} in {attempts} attempts")
    m = scene.mesh
    albedo = np.clip(np.rint(mesh_albedo_srgb(scene) * 255), 0, 255).astype(np.uint8)
    renderer = MeshRenderer(
        TriMesh(m.vertices.astype(np.float32), m.triangles.astype(np.int32), albedo)
    )
    gts, meshes, valids = [], [], []
    for i in range(cfg.frames):
        s = render_sample(scene, i)
        gt = s.color_gt if s.color_gt.ndim == 3 else np.repeat(s.color_gt[..., None], 3, 2)
        r = renderer.render(s.T_world_cam, scene.intrinsics)
        gt_f = gt.astype(np.float32) / 255
        mesh = relit_mesh_render(r.rgb().astype(np.float32) / 255, gt_f, r.valid)
        if scene.cfg.grayscale:
            mesh = np.repeat(mesh.mean(axis=2, keepdims=True), 3, 2)
        gts.append(gt)
        meshes.append(np.clip(np.rint(mesh * 255), 0, 255).astype(np.uint8))
        valids.append(r.valid)
    return SceneViews(seed, np.stack(gts), np.stack(meshes), np.stack(valids))


def load_or_render_scene(seed: int, cfg: PretrainConfig, cache_dir: Path) -> SceneViews:
    """The scene's renders from ``cache_dir``, rendered and written (atomically) when missing."""
    room = "_room" if is_room_seed(seed, cfg.room_prob) else ""  # tanks keep their names
    # the grayscale share draws which scenes are gray: another share is another file (the
    # default's files keep their names)
    gray = "" if cfg.grayscale_prob == DEFAULT_GRAYSCALE_PROB else f"_g{cfg.grayscale_prob:g}"
    size = f"{cfg.width}x{cfg.height}_f{cfg.frames}"
    name = f"scene_v{SCENE_CACHE_VERSION}_{seed:06d}_{size}{gray}{room}.npz"
    path = cache_dir / name
    if path.is_file():
        with np.load(path) as z:
            return SceneViews(seed, z["gt"], z["mesh"], z["valid"])
    views = render_scene(seed, cfg)
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, gt=views.gt, mesh=views.mesh, valid=views.valid)
    return views


def degraded_views(
    views: SceneViews, rng_: np.random.Generator, cfg: DegradeConfig, variants: int
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """``variants`` degraded (mesh, gs, gt, alpha) of each frame; images [3, H, W], alpha [H, W]."""
    out = []
    for f in range(views.gt.shape[0]):
        gt = views.gt[f].astype(np.float32) / 255
        mesh_c = views.mesh[f].astype(np.float32) / 255
        for _ in range(variants):
            gs, alpha = degrade_gs(gt, rng_, cfg)
            mesh = degrade_mesh(gt, rng_, cfg, mesh_c, views.valid[f])
            out.append(
                (
                    torch.from_numpy(mesh).permute(2, 0, 1),
                    torch.from_numpy(gs).permute(2, 0, 1),
                    torch.from_numpy(gt).permute(2, 0, 1),
                    torch.from_numpy(alpha),
                )
            )
    return out


# ------------------------------------------------------------------------------------------
# Job
# ------------------------------------------------------------------------------------------


def install_base(checkpoint: str | os.PathLike[str]) -> Path:
    """Copy a checkpoint flat into the package's base folder (what an empty model path loads)."""
    import shutil

    from gsfix_online.fixer.checkpoint import resolve_checkpoint
    from gsfix_online.fixer.sources import BASE_CHECKPOINT

    src = resolve_checkpoint(checkpoint)
    tmp = BASE_CHECKPOINT.with_name(f".{BASE_CHECKPOINT.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(src, tmp)
    except BaseException:  # a full disk: no half copy left beside the base
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = BASE_CHECKPOINT.with_name(f".{BASE_CHECKPOINT.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if BASE_CHECKPOINT.exists():
        BASE_CHECKPOINT.rename(old)
    tmp.rename(BASE_CHECKPOINT)
    shutil.rmtree(old, ignore_errors=True)
    return BASE_CHECKPOINT


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:  # [3, H, W] each, in [0, 1]
    mse = float(((a.clamp(0, 1) - b) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


def _score_repairs(
    bundle: Any, views: list[tuple[torch.Tensor, ...]], fx: FixerConfig, batch: int = 8
) -> dict[str, float]:
    """Mean PSNR over ``views`` (mesh, gs, gt, alpha) of the DDIM repair and the mesh fill."""
    from gsfix_online.fixer.inference import repair

    rep, fill, gs = [], [], []
    for i in range(0, len(views), batch):
        sel = views[i : i + batch]
        mesh = torch.stack([v[0] for v in sel])
        g = torch.stack([v[1] for v in sel])
        alpha = torch.stack([v[3] for v in sel])[:, None]
        out = repair(bundle, mesh, g, fx.inference).images
        filled = alpha * g + (1 - alpha) * mesh
        for k, v in enumerate(sel):
            rep.append(_psnr(out[k], v[2]))
            fill.append(_psnr(filled[k], v[2]))
            gs.append(_psnr(g[k], v[2]))
    return {
        "views": len(views),
        "psnr_repair_db": float(np.mean(rep)),
        "psnr_mesh_fill_db": float(np.mean(fill)),
        "psnr_gs_db": float(np.mean(gs)),
    }


def run_pretrain(
    job: PretrainJob,
    out: str | os.PathLike[str],
    resume: bool = False,
    progress: Callable[[int, int, str], None] | None = None,  # (step, total, text)
) -> PretrainResult:
    """Pretrain (or resume) the default model; see the module docstring for what is written."""
    from gsfix_online.fixer.checkpoint import load_checkpoint, save_checkpoint
    from gsfix_online.fixer.inference import repair
    from gsfix_online.fixer.sources import build_default
    from gsfix_online.fixer.train import LatentCache, Trainer
    from gsfix_online.fixer.validation import heldout_loss

    cfg, fx = job.pretrain, job.fixer
    out = Path(out)
    ckpt_root = out / "checkpoints"
    times: dict[str, float] = {}
    t0 = time.perf_counter()

    # 1. Check inputs
    if fx.model.source != "default":
        raise ValueError(
            "pretraining builds the embedded default: fixer.model.source must be default"
        )
    device = torch.device(
        "cuda"
        if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available())
        else "cpu"
    )
    has_ckpt = (ckpt_root / "latest").is_file()
    if has_ckpt and not resume:
        raise FileExistsError(f"{ckpt_root} holds checkpoints: pass --resume or another --out")

    # 2. Scenes (cached on disk), degraded into triplets; the maps of each scene
    seeds = [cfg.seed + i for i in range(cfg.scenes)]
    n_train = cfg.scenes - cfg.val_scenes
    scenes = [load_or_render_scene(s, cfg, out / "scenes") for s in seeds] if cfg.variants else []
    times["scenes_s"] = time.perf_counter() - t0
    t = time.perf_counter()
    maps = (
        load_or_build_corpus(seeds, cfg.width, cfg.height, cfg.grayscale_prob, cfg.maps,
                             out / "maps", room_prob=cfg.room_prob, progress=progress)
        if cfg.maps.views else []
    )  # fmt: skip
    times["maps_s"] = time.perf_counter() - t

    # 3. Model and trainer: fresh, or the last checkpoint with its optimizer state
    if resume and has_ckpt:
        loaded = load_checkpoint(ckpt_root)
        bundle = loaded.bundle
        saved = dict(loaded.manifest.get("extra", {}).get("pretrain", {}))
        # more steps is what resume is for; where and how long a sitting trains may differ
        sitting = {"steps": cfg.steps, "device": cfg.device, "time_limit_s": cfg.time_limit_s}
        if "maps" in saved:  # how many processes build the corpus changes nothing it holds
            saved["maps"] = {**saved["maps"], "workers": cfg.maps.workers}
        if {**saved, **sitting} != to_dict(cfg):
            logger.warning("resuming with a pretraining config that differs from the checkpoint's")
    else:
        loaded = None
        if cfg.init:  # a second stage: these weights, a fresh optimizer
            bundle = load_checkpoint(cfg.init).bundle
            bundle.model.float()
            bundle.model.gs_condition = fx.model.gs_condition  # as this stage feeds it
        else:
            bundle = build_default(dataclasses.replace(fx.model, path=""))
    bundle.to(device)
    trainer = Trainer(bundle.model, bundle.scheduler_config, cfg.train, device)
    if loaded is not None and loaded.trainer_state is not None:
        trainer.load_state_dict(loaded.trainer_state)
    start_step = trainer.step

    # 4. Latent caches (deterministic from the seed, so a resumed job rebuilds the same ones)
    t = time.perf_counter()
    deg_rng = np.random.default_rng([cfg.seed, 0xDE6])
    fed = bundle.model.gs_condition
    cache = LatentCache(bundle.codec, fx.masks, cfg.train.pool_size, seed=cfg.seed, device=device,
                        gs_condition=fed)  # fmt: skip
    clean = dataclasses.replace(fx.masks, enabled=False)
    val_cache = LatentCache(bundle.codec, clean, 1, device=device, gs_condition=fed)
    val_views: list[tuple[torch.Tensor, ...]] = []
    for k, views in enumerate(scenes):
        held = k >= n_train
        for j, (m, g, gt, a) in enumerate(
            degraded_views(views, deg_rng, cfg.degrade, 1 if held else cfg.variants)
        ):
            (val_cache if held else cache).add((views.seed, j), m, g, gt)
            if held:
                val_views.append((m, g, gt, a))
    map_val: list[tuple[torch.Tensor, ...]] = []
    for k, tri in enumerate(maps):
        held = k >= n_train
        for j, (m, g, gt, a) in enumerate(map_views(tri)):
            if held:
                val_cache.add(("map", tri.seed, j), m, g, gt)
                map_val.append((m, g, gt, a))
                continue
            holes = alpha_hole_mask(a.numpy())  # the map's own holes, as mask candidates
            for c in range(cfg.maps.weight):
                cache.add(
                    ("map", tri.seed, j, c), m, g, gt, alpha_holes=[holes] if holes.any() else []
                )
    times["cache_s"] = time.perf_counter() - t

    def evaluate() -> float:  # with the weights checkpoints export (EMA, when on)
        with trainer.averaged():
            return heldout_loss(trainer, val_cache, batches=4, batch_size=4, crop=cfg.train.crop)

    def save(step: int, val: float) -> Path:
        extra = {"pretrain": to_dict(cfg), "val_loss": val}
        return save_checkpoint(
            ckpt_root, bundle, step, fx.model, trainer_state=trainer.state_dict(), extra=extra
        )

    # 5. Train
    history: list[dict[str, float]] = []
    if start_step == 0:
        history.append({"step": 0, "val_loss": evaluate()})
    t = time.perf_counter()
    losses: list[float] = []
    val = history[-1]["val_loss"] if history else float("nan")
    stopped_early = False
    while trainer.step < cfg.steps:
        if cfg.time_limit_s and time.perf_counter() - t >= cfg.time_limit_s:
            stopped_early = trainer.step > start_step
            if stopped_early:  # the resumable state of this sitting
                val = evaluate()
                history.append(
                    {
                        "step": trainer.step,
                        "train_loss": float(np.mean(losses or [np.nan])),
                        "val_loss": val,
                    }
                )
                save(trainer.step, val)
            logger.info(
                "time limit %.0f s reached at step %d of %d",
                cfg.time_limit_s,
                trainer.step,
                cfg.steps,
            )
            break
        res = trainer.fit_step(cache)
        losses.append(res.loss)
        if res.step % cfg.eval_every == 0 or res.step == cfg.steps:
            val = evaluate()
            history.append(
                {"step": res.step, "train_loss": float(np.mean(losses)), "val_loss": val}
            )
            logger.info("step %d: train %.4f, held-out %.4f", res.step, np.mean(losses), val)
            losses = []
        if res.step % cfg.save_every == 0 or res.step == cfg.steps:
            save(res.step, val)
        if progress is not None:
            progress(res.step, cfg.steps, f"loss {res.loss:.4f}")
    times["train_s"] = time.perf_counter() - t
    if device.type == "cuda":
        torch.cuda.synchronize()
    steps_run = trainer.step - start_step
    if not has_ckpt and steps_run == 0:  # nothing trained and nothing saved yet
        save(trainer.step, val)

    # 6. Export the weights-only base checkpoint (and score the exported weights below)
    dtype = torch.float16 if cfg.base_fp16 else None
    extra = {"val_loss": val, "pretrain": to_dict(cfg)}
    with trainer.averaged():
        base = save_checkpoint(
            out / "base", bundle, trainer.step, fx.model, extra=extra, keep=1, weights_dtype=dtype
        )
    trained = bundle
    bundle = load_checkpoint(base).bundle.to(device)

    # 7. Repair held-out views with DDIM; score against the degraded inputs
    t = time.perf_counter()
    figures: dict[str, Any] = {"val_loss": val, "history": history}
    if map_val:  # every held-out scene's novel views, as our own maps rendered them
        figures["map_views"] = _score_repairs(bundle, map_val, fx)
    if cfg.val_views and val_views:
        sel = val_views[: cfg.val_views]
        mesh = torch.stack([v[0] for v in sel])
        gs = torch.stack([v[1] for v in sel])
        gt = torch.stack([v[2] for v in sel])
        alpha = torch.stack([v[3] for v in sel])[:, None]
        rep = repair(bundle, mesh, gs, fx.inference).images
        with trainer.averaged():
            rep32 = repair(trained, mesh, gs, fx.inference).images
        rep1 = repair(bundle, mesh, gs, dataclasses.replace(fx.inference, steps=1)).images
        fill = alpha * gs + (1 - alpha) * mesh
        n = len(sel)
        figures["val_views"] = n
        figures["psnr_repair_db"] = float(np.mean([_psnr(rep[i], gt[i]) for i in range(n)]))
        figures["psnr_repair_fp32_db"] = float(np.mean([_psnr(rep32[i], gt[i]) for i in range(n)]))
        figures["psnr_repair_1_step_db"] = float(np.mean([_psnr(rep1[i], gt[i]) for i in range(n)]))
        figures["psnr_gs_input_db"] = float(np.mean([_psnr(gs[i], gt[i]) for i in range(n)]))
        figures["psnr_mesh_input_db"] = float(np.mean([_psnr(mesh[i], gt[i]) for i in range(n)]))
        figures["psnr_mesh_fill_db"] = float(np.mean([_psnr(fill[i], gt[i]) for i in range(n)]))
        figures["inference_steps"] = fx.inference.steps
    times["repair_s"] = time.perf_counter() - t
    times["total_s"] = time.perf_counter() - t0

    # 8. Record
    size_mb = sum(f.stat().st_size for f in base.iterdir()) / 1e6
    figures.update(
        {
            "step": trainer.step,
            "steps_this_run": steps_run,
            "resumed_from": start_step,
            "train_scenes": n_train,
            "val_scenes": cfg.val_scenes,
            "train_entries": len(cache),
            "map_scenes": len(maps),
            "base_checkpoint": str(base),
            "base_checkpoint_mb": size_mb,
            "times": times,
            "threads": torch.get_num_threads(),
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "stopped_by_time_limit": stopped_early,
        }
    )
    atomic_write_text(out / "pretrain.json", json.dumps(figures, indent=2))
    if cfg.install:
        install_base(base)
    return PretrainResult(trainer.step, ckpt_root, base, figures)
