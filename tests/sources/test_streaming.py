"""Readers stream: memory stays flat over a 10,000-frame sequence; replay paces by stamps."""

from __future__ import annotations

import os
import tracemalloc

import cv2
import numpy as np

from gsfix_online.core.types import Intrinsics
from gsfix_online.sources import ReplayConfig, SourceConfig, open_source
from gsfix_online.sources.replay import paced
from gsfix_online.sources.tum import write_intrinsics_json

N_FRAMES = 10_000
W, H = 64, 48


def write_long_tum(root) -> None:  # noqa: ANN001
    """A 10,000-frame TUM sequence; the images are hard links to one file, so it writes in a second."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(root / "c.png"), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
    cv2.imwrite(str(root / "d.png"), rng.integers(1000, 20000, (H, W), dtype=np.uint16))
    write_intrinsics_json(root / "camera.json", Intrinsics(50, 50, 31.5, 23.5, W, H))
    with (
        open(root / "rgb.txt", "w") as fr,
        open(root / "depth.txt", "w") as fd,
        open(root / "groundtruth.txt", "w") as fg,
    ):
        for i in range(N_FRAMES):
            s = f"{1000 + i // 30}.{(i % 30) * 33333:06d}"
            os.link(root / "c.png", root / "rgb" / f"{i}.png")
            os.link(root / "d.png", root / "depth" / f"{i}.png")
            fr.write(f"{s} rgb/{i}.png\n")
            fd.write(f"{s} depth/{i}.png\n")
            fg.write(f"{s} {i * 1e-3} 0 0 0 0 0 1\n")


def test_tum_streams_10k_frames_with_flat_memory(tmp_path):
    write_long_tum(tmp_path)
    reader = open_source(SourceConfig(), tmp_path)  # index (paths, stamps, poses) is loaded here
    frame_bytes = W * H * (3 + 4)
    tracemalloc.start()
    try:
        it = iter(reader)
        for _ in range(100):  # warm-up: caches, first allocations
            next(it)
        base, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        n = 100
        for frame in it:
            n += 1
            assert frame.depth.shape == (H, W)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n == N_FRAMES and reader.stats.frames == N_FRAMES
    # Holding all frames would take N_FRAMES * frame_bytes = 215 MB. What does grow is the index:
    # pathlib caches each path's string on first use (about 2 x 80 B per frame, measured).
    growth_per_frame = (peak - base) / N_FRAMES
    assert growth_per_frame < 400, (
        f"memory grew by {(peak - base) / 1e6:.1f} MB over {N_FRAMES} frames"
    )
    assert growth_per_frame < 0.02 * frame_bytes


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.t += dt


def test_replay_realtime_follows_stamps_at_speed(frames):
    clock = FakeClock()
    out = list(paced(frames, ReplayConfig(mode="realtime", speed=2.0), clock, clock.sleep))
    assert [f.seq for f in out] == [f.seq for f in frames]
    span = (frames[-1].stamp_ns - frames[0].stamp_ns) * 1e-9
    assert abs((clock.t - 100.0) - span / 2.0) < 1e-9
    assert len(clock.sleeps) == len(frames) - 1


def test_replay_slow_consumer_loses_nothing(frames):
    clock = FakeClock()
    out = []
    for f in paced(frames, ReplayConfig(mode="realtime", speed=1.0), clock, clock.sleep):
        out.append(f)
        clock.t += 0.5  # consumer takes 0.5 s per frame, stamps are 0.1 s apart
    assert len(out) == len(frames) and clock.sleeps == []


def test_replay_max_never_sleeps(frames):
    clock = FakeClock()
    assert len(list(paced(frames, ReplayConfig(mode="max"), clock, clock.sleep))) == len(frames)
    assert clock.sleeps == []
