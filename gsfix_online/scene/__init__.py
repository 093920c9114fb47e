"""Synthetic ship ballast tank: a procedural compartment with exact ground truth, deterministic by seed.

``generate_ship_tank(cfg, out_dir)`` writes a TUM sequence, ground-truth images and mesh, and held-out
novel views; ``iter_frames(cfg)`` streams the frames in memory for tests. Open3D is imported only
when a scene is built.
"""

from gsfix_online.scene.config import ShipTankConfig
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

__all__ = [
    "SceneInfo",
    "SceneSample",
    "ShipTankConfig",
    "ShipTankScene",
    "build_scene",
    "generate_ship_tank",
    "iter_frames",
    "iter_samples",
    "novel_views",
    "observe",
]
