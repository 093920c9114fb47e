"""Named, real-like variants of the synthetic scenes, and camera presets.

A variant is a set of config values for one kind of degradation; variants combine (comma
separated, later wins where they overlap) and combine with either scene family and any camera.
``real`` is every degradation at once (the colour rig; add ``gray`` for the grayscale one).

=============  ==============================================================================
variant        values (``ShipTankConfig`` fields)
=============  ==============================================================================
drift          VIO-like pose estimate: ``pose_drift=0.01`` (~1 % of the distance travelled and
               ~1 deg/m of yaw, random-walking), ``pose_noise=0.002`` m and
               ``pose_noise_deg=0.1`` deg per-frame jitter; written as ``tum/estimated.txt``,
               carried by ``log.mcap`` and ``replica/traj.txt``; ``tum/groundtruth.txt`` stays exact
noisy-depth    stereo-like depth: ``depth_noise=0.008`` (sigma = 0.008 z^2: 3 cm at 2 m),
               ``dropout=0.03`` in 4-px blobs (``dropout_blob_px=4``), lost beyond 75 deg
               incidence (``depth_grazing_deg=75``) and on surfaces darker than 10/255
               (``depth_dark_level=10``), stereo occlusion holes left of near objects for a
               D455-like 95 mm baseline (``stereo_baseline=0.095``)
exposure       auto-exposure: a gain per frame in [0.7, 1.4] (``exposure_gain_min/max``), a
               smooth wander over ~2 s (``exposure_smooth_s=2``) plus a sudden step in 3 % of
               the frames (``exposure_step_prob=0.03``), and auto white balance: 3 % per channel
               (``white_balance_sigma=0.03``), brightness-neutral; ``gt/`` and ``novel/`` stay
               at gain 1
blur           motion blur over a 20 ms shutter centred on each frame stamp (``shutter_s=0.02``,
               samples chosen from the image motion)
gray           the grayscale rig (``grayscale=true``: [H, W] uint8 images)
slow           a slow, hand-held-like trajectory: the tank's path enters one bay
               (``bays_visited=1``), the room's makes a quarter turn around the table
               (``room_loop=0.25``), with gentle sweeps (``yaw_sweep_deg=15``,
               ``pitch_sweep_deg=5``); the frames stay as many, so the camera moves 0.8 cm (tank)
               to 2.4 cm (room) a frame at 120 frames, against 3-7 cm in the default paths, and
               keeps seeing what it saw (a real 640x480 indoor log's regime)
real           drift + noisy-depth + exposure + blur
=============  ==============================================================================

Cameras: ``vga`` is 640x480 at the default 75 deg field of view; ``replica`` is Replica's layout,
1200x680 with fx = fy = 600, cx = 599.5, cy = 339.5.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

from gsfix_online.core.config import ConfigError
from gsfix_online.scene.config import ShipTankConfig

VARIANTS: dict[str, dict[str, Any]] = {
    "drift": {"pose_drift": 0.01, "pose_noise": 0.002, "pose_noise_deg": 0.1},
    "noisy-depth": {
        "depth_noise": 0.008,
        "dropout": 0.03,
        "dropout_blob_px": 4.0,
        "depth_grazing_deg": 75.0,
        "depth_dark_level": 10.0,
        "stereo_baseline": 0.095,
    },
    "exposure": {
        "exposure_gain_min": 0.7,
        "exposure_gain_max": 1.4,
        "exposure_smooth_s": 2.0,
        "exposure_step_prob": 0.03,
        "white_balance_sigma": 0.03,
    },
    "blur": {"shutter_s": 0.02},
    "gray": {"grayscale": True},
    "slow": {"bays_visited": 1, "room_loop": 0.25, "yaw_sweep_deg": 15.0, "pitch_sweep_deg": 5.0},
}
VARIANTS["real"] = {
    k: v for name in ("drift", "noisy-depth", "exposure", "blur") for k, v in VARIANTS[name].items()
}

CAMERAS: dict[str, dict[str, Any]] = {
    "vga": {"width": 640, "height": 480},
    "replica": {"width": 1200, "height": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5},
}


def split_names(names: str | Iterable[str]) -> list[str]:
    """``"drift,blur"`` or ``["drift", "blur"]`` -> ``["drift", "blur"]`` (empty parts dropped)."""
    parts = names.split(",") if isinstance(names, str) else list(names)
    return [p.strip() for p in parts if p.strip()]


def variant_settings(names: str | Iterable[str] = (), camera: str | None = None) -> dict[str, Any]:
    """Config values of the named variants and camera, merged in order; ConfigError for an unknown name."""
    out: dict[str, Any] = {}
    for name in split_names(names):
        if name not in VARIANTS:
            raise ConfigError(f"unknown scene variant '{name}' (known: {', '.join(VARIANTS)})")
        out.update(VARIANTS[name])
    if camera:
        if camera not in CAMERAS:
            raise ConfigError(f"unknown scene camera '{camera}' (known: {', '.join(CAMERAS)})")
        out.update(CAMERAS[camera])
    return out


def variant_overrides(
    names: str | Iterable[str] = (), camera: str | None = None, section: str = "scene"
) -> list[str]:
    """The same as command-line overrides (``scene.shutter_s=0.02``) for ``load_config``."""
    import json

    return [f"{section}.{k}={json.dumps(v)}" for k, v in variant_settings(names, camera).items()]


def apply_variant(
    cfg: ShipTankConfig, names: str | Iterable[str] = (), camera: str | None = None
) -> ShipTankConfig:
    """``cfg`` with the named variants and camera applied, re-validated."""
    from gsfix_online.scene.generate import checked

    return checked(dataclasses.replace(cfg, **variant_settings(names, camera)))
