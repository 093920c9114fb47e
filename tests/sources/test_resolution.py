"""The processing resolution (sources/resolution.py): sizes, intrinsics that keep a point where
the resized image has it, colour area-averaged, depth never mixed across an edge, and every
reader and the live cameras' path yielding frames at ``max_width``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gsfix_online.core.types import Intrinsics
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.camera import CameraFrame
from gsfix_online.sources.resolution import (
    at_processing_resolution,
    frames_at,
    nearest_index,
    processing_size,
    resize_color,
    resize_depth,
)
from tests.conftest import make_frames
from tests.sources.test_formats import _write

REPLICA = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
TOL = {"px": 1e-9, "ramp": 0.5 + 1e-6}  # ramp: colour is uint8, rounded once by cv2


@pytest.mark.parametrize(
    ("size", "max_width", "want"),
    [
        ((1200, 680), 640, (640, 360)),  # 680 * 640 / 1200 = 362.67: 360, a multiple of 8
        ((1200, 680), 320, (320, 184)),  # 181.33: 184
        ((1200, 680), 330, (328, 184)),  # the width rounds down to a multiple of 8 too
        ((320, 240), 640, (320, 240)),  # never upsampled: the demo stays 320x240
        ((640, 480), 640, (640, 480)),
        ((640, 480), 0, (640, 480)),  # 0 = no limit
        ((641, 3), 640, (640, 8)),  # never under 8 pixels
        ((100, 50), 4, (8, 8)),
    ],
)
def test_processing_size(size: tuple[int, int], max_width: int, want: tuple[int, int]) -> None:
    assert processing_size(*size, max_width) == want


def test_a_negative_max_width_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="max_width must be 0 .* got -1"):
        processing_size(640, 480, -1)
    src = _write("tum", tmp_path, make_frames(n=1))
    with pytest.raises(ValueError, match="max_width must be 0 .* got -5"):
        open_source(SourceConfig(max_width=-5), src)


@pytest.mark.parametrize("size", [(640, 360), (320, 184), (97, 55)])
def test_a_point_lands_at_the_scaled_pixel(size: tuple[int, int]) -> None:
    """Project points with the camera's K and with the processing K: the processing pixel is the
    camera pixel scaled by the half-pixel rule, u' = (u + 0.5) * sx - 0.5."""
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-2, 2, (50, 2)), rng.uniform(0.5, 6, 50)])  # [50, 3] m
    small = REPLICA.scaled(*size)
    uv = (p @ REPLICA.K.T)[:, :2] / p[:, 2:]
    uv_small = (p @ small.K.T)[:, :2] / p[:, 2:]
    s = np.array([size[0] / REPLICA.width, size[1] / REPLICA.height])
    np.testing.assert_allclose(uv_small, (uv + 0.5) * s - 0.5, atol=TOL["px"])
    # and back: the image corners and centre are where they were, in image fractions
    for u, v in ((-0.5, -0.5), (1199.5, 679.5), (599.5, 339.5)):
        q = np.linalg.solve(REPLICA.K, [u, v, 1.0])
        got = small.K @ q
        np.testing.assert_allclose(got[:2] / got[2], ((u + 0.5) * s[0] - 0.5,
                                                       (v + 0.5) * s[1] - 0.5), atol=TOL["px"])  # fmt: skip


@pytest.mark.parametrize(("w_in", "w_out"), [(200, 100), (250, 100), (240, 37)])
def test_area_averaged_colour_sits_where_the_intrinsics_say(w_in: int, w_out: int) -> None:
    """A ramp whose value is each pixel's x: area averaging gives every output pixel the input
    x of its centre, (x' + 0.5) * W / W' - 0.5, the place the scaled principal point assumes."""
    ramp = np.tile(np.arange(w_in, dtype=np.uint8), (6, 1))
    out = resize_color(np.dstack([ramp] * 3), w_out, 3)
    want = (np.arange(w_out) + 0.5) * (w_in / w_out) - 0.5
    assert out.shape == (3, w_out, 3)
    np.testing.assert_allclose(out[1, :, 0], want, atol=TOL["ramp"])


@pytest.mark.parametrize(("h", "w"), [(360, 640), (184, 320), (7, 9), (100, 101)])
def test_a_depth_step_edge_stays_two_depths(h: int, w: int) -> None:
    """Near wall 1 m on the left, far wall 3 m on the right, a hole of invalid 0: resized, every
    pixel is one of the three, each row still steps once from near to far."""
    depth = np.full((680, 1200), 3.0, np.float32)
    depth[:, :517] = 1.0
    depth[300:340, 700:760] = 0.0  # a hole beside valid depth
    out = resize_depth(depth, w, h)
    assert out.shape == (h, w) and out.dtype == np.float32
    assert set(np.unique(out).tolist()) <= {0.0, 1.0, 3.0}
    valid = np.where(out > 0, out, 3.0)  # the hole lies on the far wall
    assert np.all(np.diff(valid, axis=1) >= 0)  # near then far, once
    assert np.all(np.count_nonzero(np.diff(valid, axis=1), axis=1) == 1)


def test_depth_takes_the_input_pixel_at_each_output_centre() -> None:
    assert nearest_index(4, 2).tolist() == [1, 3]  # centres 1.0 and 3.0: pixels 1 and 3
    assert nearest_index(5, 2).tolist() == [1, 3]  # centres 1.25 and 3.75
    assert nearest_index(3, 3).tolist() == [0, 1, 2]
    depth = np.arange(20, dtype=np.float32).reshape(4, 5)
    np.testing.assert_array_equal(resize_depth(depth, 2, 2), [[6.0, 8.0], [16.0, 18.0]])


def test_upsampled_colour_has_the_camera_size() -> None:
    small = np.zeros((181, 320, 3), np.uint8)
    small[:, 160:] = 200
    big = resize_color(small, 1200, 680, "cubic")
    assert big.shape == (680, 1200, 3) and big.dtype == np.uint8
    assert big[:, :580].max() == 0 and big[:, 620:].min() == 200  # the edge stays where it was


@pytest.mark.parametrize("fmt", ["tum", "replica", "mcap"])
def test_a_reader_with_max_width_yields_the_scaled_size_and_K(fmt: str, tmp_path: Path) -> None:
    frames = make_frames(n=3, width=40, height=30)
    src = _write(fmt, tmp_path, frames)
    full = list(open_source(SourceConfig(), src))
    reader = open_source(SourceConfig(max_width=24), src)
    small = list(reader)
    cam = full[0].intrinsics
    assert reader.camera is not None and reader.camera.K.tolist() == cam.K.tolist()
    want = cam.scaled(24, 16)  # 30 * 24 / 40 = 18: 16, a multiple of 8
    for a, b in zip(full, small, strict=True):
        assert (b.width, b.height) == (24, 16) and b.depth.shape == (16, 24)
        np.testing.assert_allclose(b.intrinsics.K, want.K, atol=1e-12)
        np.testing.assert_array_equal(
            b.color, cv2.resize(a.color, (24, 16), interpolation=cv2.INTER_AREA)
        )
        assert set(np.unique(b.depth).tolist()) <= set(np.unique(a.depth).tolist())
        np.testing.assert_array_equal(b.T_world_cam, a.T_world_cam)
        assert b.stamp_ns == a.stamp_ns
    # narrower than max_width: the frames as read, the same arrays
    same = list(open_source(SourceConfig(max_width=40), src))
    assert all(np.array_equal(a.color, b.color) for a, b in zip(full, same, strict=True))


def test_the_live_cameras_path_resizes_unposed_frames() -> None:
    f = make_frames(n=2, width=40, height=30, gray=True)
    cams = [CameraFrame(x.color, x.depth, x.intrinsics, x.stamp_ns, "cam", x.seq) for x in f]
    out = list(frames_at(cams, 32))
    assert [(c.width, c.height, c.color.shape) for c in out] == [(32, 24, (24, 32))] * 2
    assert out[0].intrinsics == f[0].intrinsics.scaled(32, 24)
    assert at_processing_resolution(cams[0], 0) is cams[0]
    with pytest.raises(ValueError, match="got -1"):
        next(frames_at(cams, -1))
