"""Synthetic scenes with exact ground truth, deterministic by seed: a ship ballast tank and a
furnished room (``ShipTankConfig.family``), with real-like degradations (``variants``).

``generate_ship_tank(cfg, out_dir)`` writes a TUM sequence (plus an MCAP log and a Replica folder
on request), ground-truth images and mesh, and held-out novel views, for either family;
``iter_frames(cfg)`` streams the frames in memory for tests. Open3D is imported only when a scene
is built.
"""

from gsfix_online.scene.config import SceneConfig, ShipTankConfig
from gsfix_online.scene.generate import (
    SceneInfo,
    SceneSample,
    ShipTankScene,
    build_scene,
    generate_ship_tank,
    iter_frames,
    iter_samples,
    novel_views,
    observe,
)
from gsfix_online.scene.variants import CAMERAS, VARIANTS, apply_variant, variant_overrides

__all__ = [
    "CAMERAS",
    "VARIANTS",
    "SceneConfig",
    "SceneInfo",
    "SceneSample",
    "ShipTankConfig",
    "ShipTankScene",
    "apply_variant",
    "build_scene",
    "generate_ship_tank",
    "iter_frames",
    "iter_samples",
    "novel_views",
    "observe",
    "variant_overrides",
]
