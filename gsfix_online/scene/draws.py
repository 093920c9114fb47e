"""Random scene layouts for pretraining corpora: a ship tank or a room drawn from a seed."""

from __future__ import annotations

import dataclasses

import numpy as np

from gsfix_online.scene.config import ShipTankConfig


def is_room_seed(seed: int, room_prob: float) -> bool:
    """Whether scene ``seed`` is a room: one draw per seed (not per layout attempt), from its own
    stream, so the tanks' layouts do not change with ``room_prob``."""
    return room_prob > 0 and bool(np.random.default_rng([seed, 0x2004]).random() < room_prob)


def random_scene_layout(
    seed: int, width: int, height: int, grayscale_prob: float, n_frames: int, attempt: int = 0,
    room_prob: float = 0.0,
) -> ShipTankConfig:  # fmt: skip
    """A ShipTankConfig (no novel views) with layout, texture, lighting and camera from ``seed``:
    a tank, or with probability ``room_prob`` a room."""
    r = np.random.default_rng([seed, attempt, 0x5CE4E])
    length = float(r.uniform(3.0, 9.0))
    width_m = float(r.uniform(2.2, 4.5))
    height_m = float(r.uniform(2.0, 3.4))
    max_webs = max(0, int(length // 1.6) - 1)
    webs = int(r.integers(0, max_webs + 1))
    tank = ShipTankConfig(
        seed=seed,
        width=width,
        height=height,
        fov_x_deg=float(r.uniform(60.0, 90.0)),
        n_frames=n_frames,
        tank_length=length,
        tank_width=width_m,
        tank_height=height_m,
        n_web_frames=webs,
        web_hole_width=float(r.uniform(0.6, width_m - 1.0)),
        web_hole_height=float(r.uniform(0.6, height_m - 0.8)),
        lighting="headlamp" if r.random() < 0.35 else "lamps",
        ambient=float(r.uniform(0.03, 0.25)),
        light_power=float(r.uniform(0.6, 1.8)),
        grayscale=bool(r.random() < grayscale_prob),
        yaw_sweep_deg=float(r.uniform(15.0, 60.0)),
        pitch_sweep_deg=float(r.uniform(5.0, 30.0)),
        n_novel=0,
    )
    if not is_room_seed(seed, room_prob):
        return tank
    q = np.random.default_rng([seed, attempt, 0x2004])
    return dataclasses.replace(
        tank,
        family="room",
        room_length=float(q.uniform(4.5, 8.0)),
        room_width=float(q.uniform(3.6, 6.0)),
        room_height=float(q.uniform(2.4, 3.2)),
        room_loop=float(q.uniform(0.5, 1.1)),
    )
