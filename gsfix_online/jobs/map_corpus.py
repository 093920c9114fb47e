"""Pretraining triplets with the real degradations: our own maps of a scene at its novel views.

The synthetic degradations of ``triplets.py`` stand in for the two conditions when only ground
truth exists. What GSFixer meets at repair time is different: a TSDF mesh fused from noisy depth
(holes where depth dropped out, colours averaged over a voxel, surfaces shifted by pose error) and
a Gaussian map fitted online for a few steps per keyframe (floaters, under-fitted borders, soft
holes where nothing was seen) rendered at a view off the trajectory. This module builds those for
a procedural scene, as the repair graph does on a robot:

1. the scene's sensor frames (noisy colour and depth; with a share of scenes mapped at drifting
   pose estimates) are fused into a TSDF (Open3D) and mapped by the Gaussian mapper;
2. at the scene's novel views (30-85 % of each seen by the trajectory, the planner's kind) the
   mesh is ray-cast and the map rendered, and ground truth is rendered noise-free; with
   ``holdout`` also at frames of the trajectory kept out of mapping, where the maps render the
   surface well and a repair has to keep what they show.

A scene's triplets are cached on disk (atomic ``.npz``), so a pretraining job that resumes or
runs again builds each scene once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from gsfix_online.core.config import profile, rng, to_dict
from gsfix_online.core.io import atomic_path
from gsfix_online.mapping.splat.mapper import MapperConfig

logger = logging.getLogger(__name__)

MAP_CACHE_VERSION = 1


def _corpus_mapper_defaults() -> MapperConfig:
    # The repair graph's 2-core mapper (configs/profiles/mapper_cpu.yaml): the maps of the
    # corpus are the maps a repair meets
    return profile(MapperConfig, "mapper_cpu.yaml")


@dataclass(frozen=True)
class MapCorpusConfig:
    """Triplets rendered from each pretraining scene's own TSDF mesh and Gaussian map."""

    # 0 = off: pretraining uses the synthetic degradations only
    views: int = field(default=0, metadata=rng(0, 64, "novel views rendered per scene, 0 = off"))
    frames: int = field(default=30, metadata=rng(2, 1000, "sensor frames mapped per scene"))
    refine: int = field(
        default=30, metadata=rng(0, 100_000, "map refinement steps after the frames")
    )
    voxel_size: float = field(default=0.03, metadata=rng(0.005, 1.0, "TSDF voxel, m"))
    drift_prob: float = field(
        default=0.3, metadata=rng(0, 1, "share of scenes mapped at drifting pose estimates")
    )
    # Every K-th sensor frame (i % K == K // 2) is kept out of mapping and rendered too: views
    # on the trajectory, where the maps render the surface well and a repair must keep it
    holdout: int = field(default=0, metadata=rng(0, 1000, "held-out frame spacing, 0 = none"))
    # sampled entries per map view in the training cache, against 1 per synthetic variant
    weight: int = field(default=2, metadata=rng(1, 64, "cache entries per map view"))
    # Scenes mapped at once, each in its own process on one thread (how, not what: the cached
    # files and their names do not depend on it)
    workers: int = field(default=1, metadata=rng(1, 256, "processes building scenes at once"))
    mapper: MapperConfig = field(default_factory=_corpus_mapper_defaults)


@dataclass
class MapTriplets:
    """One scene's renders at its novel views; uint8 images [V, H, W, 3]."""

    seed: int
    gt: npt.NDArray[np.uint8]  # noise-free camera image at the exact view
    mesh: npt.NDArray[np.uint8]  # TSDF mesh ray cast (black where nothing was hit)
    gs: npt.NDArray[np.uint8]  # Gaussian-map render over black
    alpha: npt.NDArray[np.uint8]  # [V, H, W] the map's alpha, 0..255
    valid: npt.NDArray[np.bool_]  # [V, H, W] the mesh was hit
    drift: bool = False
    heldout: npt.NDArray[np.bool_] | None = None  # [V] a held-out trajectory frame (else novel)

    def __len__(self) -> int:
        return int(self.gt.shape[0])


def _rgb_u8(x: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    if x.dtype != np.uint8:
        x = np.clip(np.rint(np.asarray(x, np.float32) * 255.0), 0, 255).astype(np.uint8)
    if x.ndim == 2:
        x = x[:, :, None]
    return np.ascontiguousarray(np.broadcast_to(x, (*x.shape[:2], 3)))


def scene_config(seed: int, width: int, height: int, grayscale_prob: float, cfg: MapCorpusConfig,
                 attempt: int = 0, room_prob: float = 0.0) -> Any:  # fmt: skip
    """The pretraining layout of ``seed`` (``pretrain.random_scene_config``) with a mapping
    trajectory, novel views, sensor noise and, for a share of scenes, pose drift."""
    from gsfix_online.scene.draws import random_scene_layout

    base = random_scene_layout(seed, width, height, grayscale_prob, max(cfg.frames, 2), attempt,
                               room_prob=room_prob)  # fmt: skip
    r = np.random.default_rng([seed, attempt, 0x3A9])
    drift: dict[str, float] = {}
    if r.random() < cfg.drift_prob:
        drift = {
            "pose_drift": float(r.uniform(0.005, 0.025)),
            "pose_noise": float(r.uniform(0.0, 0.006)),
            "pose_noise_deg": float(r.uniform(0.0, 0.4)),
        }
    return dataclasses.replace(base, n_novel=cfg.views, **drift)


def build_map_triplets(
    seed: int, width: int, height: int, grayscale_prob: float, cfg: MapCorpusConfig,
    attempts: int = 8, room_prob: float = 0.0,
) -> MapTriplets:  # fmt: skip
    """Map scene ``seed`` (TSDF and Gaussians) and render both at its novel views (and at its
    held-out frames, with ``cfg.holdout``)."""
    from gsfix_online.fixer.sample_builder import render_pair
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.mapping.splat.mapper import Mapper
    from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume
    from gsfix_online.scene.generate import (
        build_scene,
        in_estimated_frame,
        iter_samples,
        novel_views,
        observe,
        render_view,
    )
    from gsfix_online.scene.trajectory import SceneLayoutError

    if cfg.views < 1:
        raise ValueError("map corpus views must be >= 1 to build triplets")
    # 1. A scene with novel views (a layout may leave no clear trajectory: try the next draw)
    for attempt in range(attempts):
        try:
            scene = build_scene(
                scene_config(seed, width, height, grayscale_prob, cfg, attempt, room_prob)
            )
            samples = list(iter_samples(scene, workers=1))
            views = novel_views(scene, observe(scene, samples))
            if views:
                break
        except SceneLayoutError as exc:
            logger.debug("map scene %d attempt %d: %s", seed, attempt, exc)
    else:
        raise RuntimeError(f"no layout with novel views for scene seed {seed} in {attempts} tries")
    drift = scene.has_estimate
    pose = "estimated" if drift else "gt"

    # 2. Map the sensor frames as the repair graph does
    t0 = time.perf_counter()
    gray = scene.cfg.grayscale
    torch.manual_seed(seed)
    mapper = Mapper(dataclasses.replace(cfg.mapper, seed=seed), channels=1 if gray else 3,
                    device="cpu")  # fmt: skip
    tsdf = TsdfVolume(TsdfConfig(voxel_size=cfg.voxel_size, depth_max=scene.cfg.depth_max))
    K = cfg.holdout
    held = [s for s in samples if K and s.index % K == K // 2]
    for s in samples:
        if K and s.index % K == K // 2:
            continue
        f = s.frame(scene.intrinsics, noisy=True, pose=pose)
        mapper.process(f)
        tsdf.integrate(f)
    if cfg.refine:
        mapper.refine(cfg.refine)
    renderer = MeshRenderer(tsdf.extract_mesh())
    map_s = time.perf_counter() - t0

    # 3. Render both maps at the novel views (in the map's frame) and ground truth at the exact one
    exact = np.stack([v.T_world_cam for v in views])
    asked = in_estimated_frame(exact, scene.poses, scene.poses_est) if drift else exact
    if held:  # held-out frames: where the front end put them (the map's frame)
        exact = np.concatenate([exact, np.stack([s.T_world_cam for s in held])])
        asked = np.concatenate([asked, np.stack([s.T_world_cam_est if drift else s.T_world_cam
                                                 for s in held])])  # fmt: skip
    intr = scene.intrinsics
    gts, meshes, gss, alphas, valids = [], [], [], [], []
    for T, T_map in zip(exact, asked, strict=True):
        gts.append(_rgb_u8(render_view(scene, T).color))
        pair = render_pair(mapper, renderer, T_map, intr)  # as the trainer's samples are made
        meshes.append(pair.mesh)
        valids.append(pair.mesh_valid)
        gss.append(pair.gs)
        alphas.append(np.clip(np.rint(pair.gs_alpha * 255), 0, 255).astype(np.uint8))
    logger.debug("map scene %d: %d frames mapped in %.1f s, %d views", seed, len(samples),
                 map_s, len(views))  # fmt: skip
    heldout = np.arange(len(exact)) >= len(views)
    return MapTriplets(
        seed, np.stack(gts), np.stack(meshes), np.stack(gss), np.stack(alphas),
        np.stack(valids), drift, heldout,
    )  # fmt: skip


def map_cache_path(
    seed: int, width: int, height: int, grayscale_prob: float, cfg: MapCorpusConfig,
    cache_dir: Path, room_prob: float = 0.0,
) -> Path:  # fmt: skip
    """Where the scene's map triplets are cached: the name holds every setting they depend on."""
    from gsfix_online.scene.draws import is_room_seed

    mapper = hashlib.sha1(json.dumps(to_dict(cfg.mapper), sort_keys=True).encode()).hexdigest()
    key = (
        f"f{cfg.frames}_v{cfg.views}_r{cfg.refine}_vox{cfg.voxel_size:g}_d{cfg.drift_prob:g}"
        f"_g{grayscale_prob:g}"
        + ("_room" if is_room_seed(seed, room_prob) else "")  # a tank's file whatever the share
        + (f"_h{cfg.holdout}" if cfg.holdout else "")
        + f"_m{mapper[:8]}"
    )
    return Path(cache_dir) / f"maps_v{MAP_CACHE_VERSION}_{seed:06d}_{width}x{height}_{key}.npz"


def load_or_build_map_triplets(
    seed: int, width: int, height: int, grayscale_prob: float, cfg: MapCorpusConfig,
    cache_dir: Path, room_prob: float = 0.0,
) -> MapTriplets:  # fmt: skip
    """The scene's map triplets from ``cache_dir``, built and written (atomically) when missing."""
    path = map_cache_path(seed, width, height, grayscale_prob, cfg, cache_dir, room_prob)
    if path.is_file():
        with np.load(path) as z:
            held = z["heldout"] if "heldout" in z else np.zeros(len(z["gt"]), bool)
            return MapTriplets(seed, z["gt"], z["mesh"], z["gs"], z["alpha"], z["valid"],
                               bool(z["drift"]), held)  # fmt: skip
    t = build_map_triplets(seed, width, height, grayscale_prob, cfg, room_prob=room_prob)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        held = t.heldout if t.heldout is not None else np.zeros(len(t), bool)
        np.savez_compressed(tmp, gt=t.gt, mesh=t.mesh, gs=t.gs, alpha=t.alpha, valid=t.valid,
                            drift=np.array(t.drift), heldout=held)  # fmt: skip
    return t


def _build_in_worker(args: tuple[Any, ...]) -> int:  # a worker process: build and cache a scene
    torch.set_num_threads(1)
    seed, *rest = args
    load_or_build_map_triplets(seed, *rest[:-1], room_prob=rest[-1])
    return int(seed)


def load_or_build_corpus(
    seeds: list[int], width: int, height: int, grayscale_prob: float, cfg: MapCorpusConfig,
    cache_dir: Path, room_prob: float = 0.0,
    progress: Callable[[int, int, str], None] | None = None,  # (done, total, text)
) -> list[MapTriplets]:  # fmt: skip
    """The map triplets of every seed, in order; scenes not cached yet are built first, in
    ``cfg.workers`` processes (spawned: the parent's threads do not follow them into a fork)."""
    import concurrent.futures as cf
    import multiprocessing as mp

    missing = [
        s for s in seeds
        if not map_cache_path(s, width, height, grayscale_prob, cfg, cache_dir, room_prob).is_file()
    ]  # fmt: skip
    workers = min(cfg.workers, len(missing))
    what = f"map triplets: {len(missing)} of {len(seeds)} scenes to build (TSDF and Gaussians)"
    if workers > 1:
        if progress is not None:
            progress(0, len(missing), f"{what}, {workers} processes")
        args = [(s, width, height, grayscale_prob, cfg, cache_dir, room_prob) for s in missing]
        with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
            pending = [ex.submit(_build_in_worker, a) for a in args]
            for k, fut in enumerate(cf.as_completed(pending)):
                seed = fut.result()  # a failed scene fails the corpus, naming its error
                if progress is not None:
                    progress(k + 1, len(missing), f"map triplets: scene {seed} built")
    elif missing and progress is not None:
        progress(0, len(missing), f"{what}, one at a time")
    out = []
    for s in seeds:
        if progress is not None and s in missing and workers <= 1:
            progress(
                missing.index(s), len(missing), f"map triplets: scene {s} (TSDF and Gaussians)"
            )
        out.append(load_or_build_map_triplets(s, width, height, grayscale_prob, cfg, cache_dir,
                                              room_prob=room_prob))  # fmt: skip
    return out


def map_views(
    t: MapTriplets,
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """(mesh, gs, gt, alpha) of each view; images float [3, H, W] in [0, 1], alpha [H, W]."""
    from gsfix_online.fixer.triplets import to_chw

    return [
        (to_chw(t.mesh[v]), to_chw(t.gs[v]), to_chw(t.gt[v]),
         torch.from_numpy(t.alpha[v].astype(np.float32) / 255.0))
        for v in range(len(t))
    ]  # fmt: skip
