"""Corrupted files for every reader (TUM, Replica, Redwood, ScanNet++, OKVIS, ROS 1 and ROS 2
bags, MCAP): each file of a small recording cut in half or with a flipped byte. A reader either
reads frames (a flipped pixel is still a picture) or stops with one SourceError line; nothing
else escapes, and nothing hangs."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.sources import SourceConfig, SourceError, open_source
from tests.conftest import make_frames
from tests.sources.test_formats import FORMATS, T_SC, _write

ALL = [*FORMATS, "ros1", "ros2"]


def _record(fmt: str, root: Path) -> Path:
    from gsfix_online.sources.rosbag import write_rosbag

    frames = make_frames(n=3, width=16, height=12)
    if fmt in ("ros1", "ros2"):
        root.mkdir(parents=True)
        path = root / ("seq.bag" if fmt == "ros1" else "seq_ros2")
        write_rosbag(path, frames, fmt, cfg=SourceConfig())  # type: ignore[arg-type]
        return path
    return _write(fmt, root, frames)


def _damage(path: Path, how: str, rng: np.random.Generator) -> None:
    data = bytearray(path.read_bytes())
    if how == "truncated":
        path.write_bytes(bytes(data[: len(data) // 2]))
    elif data:
        i = int(rng.integers(0, len(data)))
        data[i] ^= 0xFF
        path.write_bytes(bytes(data))


@pytest.mark.parametrize("fmt", ALL)
def test_every_damaged_file_of_a_recording_reads_or_fails_in_one_line(fmt: str, tmp_path: Path):
    clean = _record(fmt, tmp_path / "clean")
    files = [clean] if clean.is_file() else sorted(p for p in clean.rglob("*") if p.is_file())
    assert files
    cfg = {"okvis": {"T_SC": T_SC.ravel().tolist()}}.get(fmt, {})
    rng = np.random.default_rng(0)
    outcomes = {"read": 0, "refused": 0}
    for i, f in enumerate(files):
        for how in ("truncated", "flipped"):
            root = tmp_path / f"case{i}{how}"
            if clean.is_file():
                damaged = root / clean.name
                root.mkdir()
                shutil.copy(clean, damaged)
                target = damaged
            else:
                damaged = root / clean.name
                shutil.copytree(clean, damaged)
                target = damaged / f.relative_to(clean)
            _damage(target, how, rng)
            t0 = time.monotonic()
            try:
                reader_fmt = "rosbag" if fmt.startswith("ros") else fmt
                frames = list(open_source(SourceConfig(format=reader_fmt, **cfg), damaged))
                assert len(frames) <= 3
                outcomes["read"] += 1
            except SourceError as exc:
                assert "\n" not in str(exc), f"{target} ({how}): {exc}"
                outcomes["refused"] += 1
            except Exception as exc:  # anything else is a defect at the reader's boundary
                raise AssertionError(f"{target} ({how}): {type(exc).__name__}: {exc}") from exc
            assert time.monotonic() - t0 < 10, f"{target} ({how}) took too long"
    assert outcomes["refused"] >= 1, outcomes  # a cut recording is noticed somewhere
