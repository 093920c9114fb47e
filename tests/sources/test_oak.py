"""OAK source: conversion of real depthai ImgFrames built on the host, and the device pipeline.

Frames are ``dai.ImgFrame`` objects filled with ``setCvFrame``/``setData`` (no mocks). depthai's
own ``ImgFrame.getCvFrame()`` (BGR or gray) is the reference for the image conversions. The
pipeline test needs an OAK and is skipped when none is available (depthai refuses camera nodes
in a host-only pipeline).
"""

from __future__ import annotations

from datetime import timedelta

import depthai as dai
import numpy as np
import pytest

from gsfix_online.core.config import ConfigError, build, to_dict
from gsfix_online.core.types import Intrinsics
from gsfix_online.sources.base import SourceError
from gsfix_online.sources.oak import (
    OakConfig,
    OakSource,
    dai_image,
    frames_from_dai,
    timedelta_to_ns,
)

T = dai.ImgFrame.Type
W, H = 64, 48
K = [[50.0, 0.0, 31.5], [0.0, 51.0, 23.5], [0.0, 0.0, 1.0]]
STAMP = timedelta(seconds=1234, microseconds=567_891)
STAMP_NS = 1_234_567_891_000
DEVICE_STAMP = timedelta(seconds=3, microseconds=5)
DEVICE_STAMP_NS = 3_000_005_000

# Tolerances: every conversion is exact against depthai's own, except NV12 against the original
# image: 4:2:0 chroma of a smooth gradient, worst case measured 5 levels.
NV12_VS_SOURCE_ATOL = 6
DEPTH_ATOL_M = 1e-6  # mm * float32(1e-3): < 1e-7 m relative error

XX, YY = np.meshgrid(np.arange(W), np.arange(H))
BGR = np.stack([4 * XX, 5 * YY, np.full_like(XX, 100)], axis=-1).astype(np.uint8)  # smooth
MONO = ((3 * XX + 2 * YY) % 256).astype(np.uint8)
DEPTH_MM = (800 + 7 * XX + 3 * YY).astype(np.uint16)
DEPTH_MM[10:14, 20:30] = 0  # invalid


def img(array: np.ndarray, kind: dai.ImgFrame.Type, seq: int = 4) -> dai.ImgFrame:
    f = dai.ImgFrame()
    f.setCvFrame(array, kind)  # BGR or single channel in, converted to `kind` by depthai
    f.setTimestamp(STAMP)
    f.setTimestampDevice(DEVICE_STAMP)
    f.setSequenceNum(seq)
    return f


def raw(data: np.ndarray, kind: dai.ImgFrame.Type, width: int, height: int, stride: int):
    """An ImgFrame from bytes, as a device sends it (with row padding when stride > row bytes)."""
    f = dai.ImgFrame()
    f.setType(kind)
    f.setWidth(width)
    f.setHeight(height)
    f.setStride(stride)
    f.setData(np.ascontiguousarray(data).view(np.uint8).reshape(-1))
    f.setTimestamp(STAMP)
    return f


def depth_frame(depth_mm: np.ndarray = DEPTH_MM) -> dai.ImgFrame:
    h, w = depth_mm.shape
    return raw(depth_mm, T.RAW16, w, h, 2 * w)


def test_nv12_colour() -> None:
    color = img(BGR, T.NV12)
    frame = frames_from_dai(color, depth_frame(), K)
    assert frame.color.shape == (H, W, 3) and frame.color.dtype == np.uint8
    np.testing.assert_array_equal(frame.color, color.getCvFrame()[:, :, ::-1])  # depthai's own
    diff = np.abs(frame.color.astype(int) - BGR[:, :, ::-1].astype(int))
    assert diff.max() <= NV12_VS_SOURCE_ATOL
    assert frame.frame_id == "oak_rgb_optical" and frame.seq == 4
    assert frame.stamp_ns == STAMP_NS
    assert frame.intrinsics == Intrinsics(50.0, 51.0, 31.5, 23.5, W, H)


def test_nv12_with_row_padding() -> None:
    stride = W + 16
    ref = img(BGR, T.NV12)
    y_uv = ref.getData().reshape(H * 3 // 2, W)
    padded = np.zeros((H * 3 // 2, stride), np.uint8)
    padded[:, :W] = y_uv
    padded[:, W:] = 77  # padding must not leak into the image
    color = raw(padded, T.NV12, W, H, stride)
    assert color.getPlaneStride(0) == stride * H
    np.testing.assert_array_equal(dai_image(color), ref.getCvFrame()[:, :, ::-1])
    np.testing.assert_array_equal(dai_image(color, gray=True), y_uv[:H])  # the Y plane


@pytest.mark.parametrize("kind", [T.BGR888i, T.RGB888i, T.BGR888p, T.RGB888p])
def test_rgb_types(kind: dai.ImgFrame.Type) -> None:
    color = img(BGR, kind)
    frame = frames_from_dai(color, depth_frame(), K)
    np.testing.assert_array_equal(frame.color, BGR[:, :, ::-1])
    np.testing.assert_array_equal(frame.color, color.getCvFrame()[:, :, ::-1])
    assert frame.color.flags.c_contiguous


def test_interleaved_with_row_padding() -> None:
    stride = 3 * W + 8
    padded = np.full((H, stride), 200, np.uint8)
    padded[:, : 3 * W] = BGR.reshape(H, 3 * W)
    color = raw(padded, T.BGR888i, W, H, stride)
    np.testing.assert_array_equal(dai_image(color), BGR[:, :, ::-1])
    np.testing.assert_array_equal(dai_image(color), color.getCvFrame()[:, :, ::-1])


@pytest.mark.parametrize("kind", [T.GRAY8, T.RAW8])
@pytest.mark.parametrize("stride", [W, W + 16])
def test_mono(kind: dai.ImgFrame.Type, stride: int) -> None:
    padded = np.full((H, stride), 255, np.uint8)
    padded[:, :W] = MONO
    mono = raw(padded, kind, W, H, stride)
    frame = frames_from_dai(mono, depth_frame(), K, frame_id="oak_left_optical", gray=True)
    assert frame.is_gray
    np.testing.assert_array_equal(frame.color, MONO)
    np.testing.assert_array_equal(frame.color, mono.getCvFrame())
    assert frame.frame_id == "oak_left_optical"


def test_gray_from_colour() -> None:
    frame = frames_from_dai(img(BGR, T.BGR888i), depth_frame(), K, gray=True)
    assert frame.color.shape == (H, W)
    import cv2

    np.testing.assert_array_equal(frame.color, cv2.cvtColor(BGR, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize("stride", [2 * W, 2 * W + 32])
def test_raw16_depth_mm_to_m(stride: int) -> None:
    padded = np.full((H, stride // 2), 65535, np.uint16)
    padded[:, :W] = DEPTH_MM
    depth = raw(padded, T.RAW16, W, H, stride)
    frame = frames_from_dai(img(BGR, T.BGR888i), depth, K)
    assert frame.depth.dtype == np.float32
    np.testing.assert_allclose(frame.depth, DEPTH_MM / 1000.0, rtol=0, atol=DEPTH_ATOL_M)
    assert (frame.depth[10:14, 20:30] == 0).all()
    np.testing.assert_array_equal(depth.getFrame(), DEPTH_MM)  # depthai reads the same mm


def test_depth_from_setcvframe() -> None:
    depth = dai.ImgFrame()
    depth.setCvFrame(DEPTH_MM, T.RAW16)
    frame = frames_from_dai(img(BGR, T.BGR888i), depth, K)
    np.testing.assert_allclose(frame.depth, DEPTH_MM / 1000.0, rtol=0, atol=DEPTH_ATOL_M)


def test_stamps_and_sequence() -> None:
    color = img(BGR, T.NV12, seq=41)
    assert frames_from_dai(color, depth_frame(), K).stamp_ns == STAMP_NS
    frame = frames_from_dai(color, depth_frame(), K, clock="device", seq=2)
    assert frame.stamp_ns == DEVICE_STAMP_NS and frame.seq == 2
    assert frames_from_dai(color, depth_frame(), K).seq == 41
    assert timedelta_to_ns(timedelta(days=1, microseconds=1)) == 86_400_000_001_000
    assert timedelta_to_ns(timedelta(microseconds=-1)) == -1_000


def test_intrinsics_from_calibration() -> None:
    # A calibration built on the host: intrinsics at 1920x1080, asked for at 640x360 (same aspect).
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(
        dai.CameraBoardSocket.CAM_A, [[1500.0, 0, 960.0], [0, 1500.0, 540.0], [0, 0, 1]], 1920, 1080
    )
    K_small = calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, 640, 360)
    color = img(np.zeros((360, 640, 3), np.uint8), T.NV12)
    frame = frames_from_dai(color, depth_frame(np.zeros((360, 640), np.uint16)), K_small)
    assert frame.intrinsics == Intrinsics(500.0, 500.0, 320.0, 180.0, 640, 360)


def test_posed() -> None:
    frame = frames_from_dai(img(BGR, T.NV12), depth_frame(), K)
    posed = frame.posed(np.eye(4))
    assert posed.stamp_ns == STAMP_NS and posed.frame_id == frame.frame_id
    np.testing.assert_array_equal(posed.depth, frame.depth)


@pytest.mark.parametrize(
    ("color", "depth", "message"),
    [
        (lambda: img(BGR, T.NV12), lambda: depth_frame(DEPTH_MM[:24, :32]), "not aligned"),
        (lambda: img(BGR, T.YUV420p), depth_frame, "YUV420p is not supported"),
        (lambda: img(BGR, T.NV12), lambda: img(MONO, T.GRAY8), "depth must be RAW16"),
        (lambda: raw(MONO[:, :40], T.GRAY8, W, H, W), depth_frame, "too few"),
    ],
)
def test_bad_frames(color, depth, message: str) -> None:
    with pytest.raises(SourceError, match=message):
        frames_from_dai(color(), depth(), K)


def test_bad_K() -> None:
    with pytest.raises(ValueError, match="K must be"):
        frames_from_dai(
            img(BGR, T.NV12), depth_frame(), [[50.0, 1.0, 31.5], [0, 50, 23.5], [0, 0, 1]]
        )


# --------------------------------------------------------------------------------------------
# Configuration and the device
# --------------------------------------------------------------------------------------------


def test_config_round_trip() -> None:
    cfg = build(OakConfig, overrides=["ir_only=true", "preset=high_detail", "fps=30"])
    assert cfg.ir_only and cfg.preset == "high_detail" and cfg.fps == 30.0
    assert cfg.image_size == (cfg.mono_width, cfg.mono_height)
    assert build(OakConfig, base=to_dict(cfg)) == cfg
    assert OakConfig(width=320, height=200).image_size == (320, 200)
    with pytest.raises(ConfigError, match="width must be even"):
        build(OakConfig, overrides=["width=641"])
    with pytest.raises(ConfigError, match="expected one of"):
        build(OakConfig, overrides=["preset=fancy"])
    # Every preset name is a depthai PresetMode.
    from typing import get_args

    from gsfix_online.sources.oak import StereoPreset

    for name in get_args(StereoPreset):
        assert hasattr(dai.node.StereoDepth.PresetMode, name.upper())


def test_no_device_error() -> None:
    # Without a device (CI) the default config fails with this message; with one, an unknown id does.
    has_device = bool(dai.Device.getAllAvailableDevices())
    cfg = OakConfig(device_id="no-such-oak") if has_device else OakConfig()
    with pytest.raises(SourceError, match="no OAK device") as info:
        OakSource(cfg)
    assert "\n" not in str(info.value)


def _available() -> bool:
    return bool(dai.Device.getAllAvailableDevices())


@pytest.mark.device
@pytest.mark.skipif(not _available(), reason="needs an OAK device (none available)")
@pytest.mark.parametrize("ir_only", [False, True])
def test_device_pipeline(ir_only: bool) -> None:
    cfg = OakConfig(ir_only=ir_only, fps=15.0)
    frames = []
    with OakSource(cfg) as cam:
        for frame in cam:
            frames.append(frame)
            if len(frames) == 5:
                break
    w, h = cfg.image_size
    for f in frames:
        assert f.depth.shape == (h, w) and f.color.shape[:2] == (h, w)
        assert f.is_gray == ir_only
        assert f.intrinsics.width == w and 0.2 * w < f.intrinsics.fx < 5 * w
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:], strict=False))
    assert any((f.depth > 0).mean() > 0.05 for f in frames), "no valid depth at all"
    assert cam.stats.frames == 5
