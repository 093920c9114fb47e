"""Round trips through every folder format and our MCAP log: write -> detect -> read -> compare."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gsfix_online.core.se3 import look_at
from gsfix_online.sources import SourceConfig, detect_format, open_source
from gsfix_online.sources.mcap_log import write_mcap
from gsfix_online.sources.okvis import write_okvis
from gsfix_online.sources.redwood import write_redwood
from gsfix_online.sources.replica import write_replica
from gsfix_online.sources.scannetpp import write_scannetpp
from gsfix_online.sources.tum import write_tum

T_SC = look_at([0.05, -0.02, 0.01], [0.3, 1.0, 0.2])  # a camera mounted at an angle on the IMU


def _write(fmt: str, root: Path, frames) -> Path:  # noqa: ANN001
    if fmt == "tum":
        write_tum(root / "seq", frames)
        return root / "seq"
    if fmt == "replica":
        write_replica(root / "room0", frames, color_ext=".png")
        return root / "room0"
    if fmt == "redwood":
        write_redwood(root / "scene", frames)
        return root / "scene"
    if fmt == "scannetpp":
        write_scannetpp(root / "scene", frames)
        return root / "scene"
    if fmt == "okvis":
        write_okvis(root / "okvis", frames, T_SC)
        return root / "okvis"
    if fmt == "mcap":
        write_mcap(root / "log.mcap", frames)
        return root / "log.mcap"
    raise AssertionError(fmt)


# depth tolerance: half a quantisation step of each format's PNG scale (float32 for MCAP)
DEPTH_TOL = {
    "tum": 0.5 / 5000,
    "replica": 0.5 / 6553.5,
    "redwood": 0.5e-3,
    "scannetpp": 0.5e-3,
    "okvis": 0.5e-3,
    "mcap": 0.0,
}
KEEPS_STAMPS = {
    "tum",
    "okvis",
    "mcap",
}  # Replica and Redwood have no stamps; ScanNet++ stores float seconds
FORMATS = sorted(DEPTH_TOL)


def _cfg(fmt: str) -> SourceConfig:
    return SourceConfig(T_SC=T_SC.ravel().tolist()) if fmt == "okvis" else SourceConfig()


def assert_same_frames(fmt: str, got, want) -> None:  # noqa: ANN001
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.color.shape == w.color.shape and np.array_equal(g.color, w.color)
        # float32 ulp at 6 m is 4.8e-7; scaling to and from integers costs up to two of them
        assert np.max(np.abs(g.depth - w.depth)) <= DEPTH_TOL[fmt] + 1e-6
        assert np.array_equal(g.depth == 0, w.depth == 0)
        assert np.max(np.abs(g.T_world_cam - w.T_world_cam)) < 1e-6
        assert pytest.approx(w.intrinsics.K, abs=1e-9) == g.intrinsics.K
        if fmt in KEEPS_STAMPS:
            assert g.stamp_ns == w.stamp_ns
        elif fmt == "scannetpp":
            assert abs(g.stamp_ns - w.stamp_ns) < 1000


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_rgb(fmt, tmp_path, frames):
    src = _write(fmt, tmp_path, frames)
    assert detect_format(src) == fmt
    reader = open_source(_cfg(fmt), src)
    got = list(reader)
    assert reader.format == fmt and len(reader) == len(frames)
    assert (
        reader.stats.frames == len(frames)
        and reader.stats.unpaired == 0
        and reader.stats.without_pose == 0
    )
    assert_same_frames(fmt, got, frames)


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_grayscale(fmt, tmp_path, gray_frames):
    got = list(open_source(_cfg(fmt), _write(fmt, tmp_path, gray_frames)))
    assert got[0].color.ndim == 2
    assert_same_frames(fmt, got, gray_frames)


def test_replica_jpeg_within_compression_error(tmp_path, frames):
    from gsfix_online.sources.base import read_color

    # smooth images: JPEG error on random noise says nothing about real data
    smooth = [
        f.__class__(
            **{
                **f.__dict__,
                "color": np.repeat(
                    np.linspace(0, 255, f.width, dtype=np.uint8)[None, :, None], f.height, 0
                ).repeat(3, 2),
            }
        )
        for f in frames
    ]
    write_replica(tmp_path, smooth, color_ext=".jpg")
    got = list(open_source(SourceConfig(), tmp_path))
    assert len(got) == len(frames)
    err = np.abs(got[0].color.astype(int) - smooth[0].color.astype(int))
    assert err.mean() < 2.0 and read_color(tmp_path / "results" / "frame000000.jpg").shape == (
        30,
        40,
        3,
    )


@pytest.mark.parametrize("fmt", FORMATS)
def test_stride_and_max_frames(fmt, tmp_path, frames):
    src = _write(fmt, tmp_path, frames)
    cfg = SourceConfig(stride=2, max_frames=3, T_SC=_cfg(fmt).T_SC)
    got = list(open_source(cfg, src))
    assert [g.seq for g in got] == [0, 2, 4]
