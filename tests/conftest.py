"""Shared fixtures: small posed RGB-D sequences generated in the test, never downloaded."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame

T0_NS = 1_700_000_000_000_000_000


def make_frames(
    n: int = 8,
    width: int = 40,
    height: int = 30,
    gray: bool = False,
    seed: int = 0,
    fps: float = 10.0,
) -> list[RGBDFrame]:
    """Random-texture frames on a smooth camera path; depth 0.4..6 m with ~5% invalid pixels."""
    rng = np.random.default_rng(seed)
    K = Intrinsics(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    frames = []
    for i in range(n):
        shape = (height, width) if gray else (height, width, 3)
        color = rng.integers(0, 256, shape, dtype=np.uint8)
        depth = rng.uniform(0.4, 6.0, (height, width)).astype(np.float32)
        depth[rng.random((height, width)) < 0.05] = 0.0
        a = 0.3 * i
        T = look_at([np.cos(a), np.sin(a), 0.2 * i], [0.0, 0.0, 1.0])
        frames.append(make_frame(color, depth, K, T, T0_NS + int(i * 1e9 / fps), seq=i))
    return frames


@pytest.fixture
def frames() -> list[RGBDFrame]:
    return make_frames()


@pytest.fixture
def gray_frames() -> list[RGBDFrame]:
    return make_frames(gray=True, seed=1)
