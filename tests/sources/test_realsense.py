"""RealSense source without a camera.

A ``rs.software_device`` with a "Stereo Module" (Z16 depth, Y8 left infrared) and an "RGB Camera"
(RGB8 colour) is fed frames of known content and stamps, recorded to a ``.db3`` with
``rs.recorder``, and played back through ``RealSenseSource(playback_file=...)``, the code path
users run. ``frames_from_rs`` is also tested on frames taken straight from a software sensor.
"""

from __future__ import annotations

import gc
import time
from pathlib import Path

import numpy as np
import pyrealsense2 as rs
import pytest

from gsfix_online.core.config import ConfigError, build, to_dict
from gsfix_online.core.types import FrameError, Intrinsics, RGBDFrame
from gsfix_online.sources.base import SourceError
from gsfix_online.sources.camera import CameraFrame
from gsfix_online.sources.realsense import (
    RealSenseConfig,
    RealSenseSource,
    frames_from_rs,
    ms_to_ns,
)

W, H, N = 64, 48, 6
T0_MS = 1_700_000_000_000.5  # epoch-like global_time stamp; 0.25 ms steps are exact in a double
DT_MS = 33.25
T0_NS, DT_NS = 1_700_000_000_000_500_000, 33_250_000
DEPTH_UNITS = 0.001  # metres per Z16 step
HOLE = (slice(5, 9), slice(10, 14))  # invalid (0) depth pixels
# Colour and depth intrinsics differ slightly (ppx by 2e-3 px) so that a test can tell which one a
# frame carries; the reprojection between them moves pixels by 2e-3 px and so changes nothing.
COLOR_K = (50.0, 51.0, 31.5, 23.5)  # fx, fy, ppx, ppy
DEPTH_K = (50.0, 51.0, 31.502, 23.5)  # also the left IR imager's, as on a D4xx

# Tolerances. Metres from Z16 with float32 units: < 1e-7 m at 1.3 m. The SDK's rs.align
# reprojects every depth pixel to a 2x2 pixel footprint and keeps the nearest depth, so an aligned
# pixel may hold its left/top neighbour's value: 1 mm on the x ramp; holes shrink at their edges.
DEPTH_ATOL_M = 1e-6
ALIGNED_DEPTH_ATOL_M = 1e-3 + 1e-6
MIN_ALIGNED_VALID = 0.9  # fraction of valid input pixels still valid after alignment (0.92 seen)

XX, YY = np.meshgrid(np.arange(W), np.arange(H))


def depth_mm(k: int) -> np.ndarray:  # [H, W] uint16, a 1 mm/pixel ramp in x plus a hole
    d = (1000 + 25 * k + XX).astype(np.uint16)
    d[HOLE] = 0
    return d


def color_rgb(k: int) -> np.ndarray:  # [H, W, 3] uint8
    return np.stack([4 * XX, 5 * YY, np.full_like(XX, 40 * k)], axis=-1).astype(np.uint8)


def ir_y8(k: int) -> np.ndarray:  # [H, W] uint8
    return ((3 * XX + 2 * YY + 7 * k) % 256).astype(np.uint8)


def _intrinsics(k: tuple[float, float, float, float], coeffs=(0.0,) * 5, model=None):
    intr = rs.intrinsics()
    intr.width, intr.height = W, H
    intr.fx, intr.fy, intr.ppx, intr.ppy = k
    intr.model = rs.distortion.brown_conrady if model is None else model
    intr.coeffs = list(coeffs)
    return intr


def _stream(kind, index, uid, fmt, bpp, k, **kw) -> rs.video_stream:
    s = rs.video_stream()
    s.type, s.index, s.uid, s.fmt, s.bpp = kind, index, uid, fmt, bpp
    s.width, s.height, s.fps = W, H, 30
    s.intrinsics = _intrinsics(k, **kw)
    return s


def _inject(sensor, profile, pixels: np.ndarray, bpp: int, stamp_ms: float, number: int) -> None:
    f = rs.software_video_frame()
    f.pixels = pixels  # copied by the SDK
    f.stride, f.bpp = W * bpp, bpp
    f.timestamp, f.domain, f.frame_number = stamp_ms, rs.timestamp_domain.global_time, number
    f.profile = profile.as_video_stream_profile()
    if pixels.dtype == np.uint16:
        f.depth_units = DEPTH_UNITS
    sensor.on_video_frame(f)


def record_db3(path: Path, n: int = N, **color_intrinsics) -> Path:
    """Record n frames of depth, left IR and colour from a software device to ``path`` (.db3).

    ``color_intrinsics``: ``coeffs`` and ``model`` of the colour stream (default: no distortion).
    """
    dev = rs.software_device()
    stereo = dev.add_sensor("Stereo Module")
    rgb = dev.add_sensor("RGB Camera")
    depth_p = stereo.add_video_stream(_stream(rs.stream.depth, 0, 0, rs.format.z16, 2, DEPTH_K))
    ir_p = stereo.add_video_stream(_stream(rs.stream.infrared, 1, 1, rs.format.y8, 1, DEPTH_K))
    color_p = rgb.add_video_stream(
        _stream(rs.stream.color, 0, 2, rs.format.rgb8, 3, COLOR_K, **color_intrinsics)
    )
    stereo.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)
    same_place = rs.extrinsics()
    same_place.rotation, same_place.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0]
    depth_p.register_extrinsics_to(color_p, same_place)
    depth_p.register_extrinsics_to(ir_p, same_place)

    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(4 * n)
    stereo.open([depth_p, ir_p])
    rgb.open(color_p)
    stereo.start(queue)
    rgb.start(queue)
    for k in range(n):
        stamp = T0_MS + DT_MS * k
        _inject(stereo, depth_p, depth_mm(k), 2, stamp, k)
        _inject(stereo, ir_p, ir_y8(k), 1, stamp, k)
        _inject(rgb, color_p, color_rgb(k), 3, stamp, k)
        time.sleep(0.01)
    stereo.stop()
    rgb.stop()
    stereo.close()
    rgb.close()
    del recorder  # closes the db3
    gc.collect()
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_db3(tmp_path_factory.mktemp("realsense") / "synthetic.db3")


def play(path: Path, **kw) -> tuple[list[CameraFrame], RealSenseSource]:
    with RealSenseSource(RealSenseConfig(playback_file=str(path), **kw)) as src:
        frames = list(src)
    return frames, src


def check_stream(frames: list[CameraFrame], src: RealSenseSource) -> list[int]:
    """Common checks; returns the recorded index k of each frame."""
    # The SDK may lose the first or last frame of a playback; with the source's pause-until-
    # started, 2.59.1 lost none in 450 plays of this recording.
    assert N - 1 <= len(frames) <= N, f"{len(frames)} of {N} frames played back"
    stamps = [f.stamp_ns for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    ks = [(s - T0_NS) // DT_NS for s in stamps]
    assert stamps == [T0_NS + k * DT_NS for k in ks]  # exact injected stamps, in ns
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert src.stats.frames == len(frames) and src.stats.timeouts == 0
    assert src.timestamp_domain == "global_time"
    return ks


def test_playback_depth_aligned_to_color(recording: Path) -> None:
    frames, src = play(recording)
    for frame, k in zip(frames, check_stream(frames, src), strict=True):
        assert frame.frame_id == "realsense_color_optical"
        assert frame.intrinsics == Intrinsics(*np.float32(COLOR_K).tolist(), W, H)
        np.testing.assert_array_equal(frame.color, color_rgb(k))  # the colour is not resampled
        expected = depth_mm(k) / 1000.0
        both = (expected > 0) & (frame.depth > 0)
        assert both.sum() >= MIN_ALIGNED_VALID * (expected > 0).sum()
        np.testing.assert_allclose(
            frame.depth[both], expected[both], rtol=0, atol=ALIGNED_DEPTH_ATOL_M
        )
        assert frame.depth.dtype == np.float32


def test_playback_color_aligned_to_depth(recording: Path) -> None:
    frames, src = play(recording, align_to_color=False)
    for frame, k in zip(frames, check_stream(frames, src), strict=True):
        assert frame.frame_id == "realsense_depth_optical"
        assert frame.intrinsics == Intrinsics(*np.float32(DEPTH_K).tolist(), W, H)
        # Depth is not resampled: every pixel, holes included, is the recorded mm / 1000.
        np.testing.assert_allclose(frame.depth, depth_mm(k) / 1000.0, rtol=0, atol=DEPTH_ATOL_M)
        # Colour is reprojected; with the 2x2 footprint a pixel may take its left/top neighbour.
        valid = frame.depth > 0
        diff = frame.color.astype(int) - color_rgb(k).astype(int)
        assert (
            np.isin(diff[valid][:, 0], (0, -4)).all() and np.isin(diff[valid][:, 1], (0, -5)).all()
        )
        assert (diff[valid][:, 2] == 0).all()
        assert (frame.color[~valid] == 0).all()  # no depth, no colour


def test_playback_ir_only(recording: Path) -> None:
    frames, src = play(recording, ir_only=True)
    for frame, k in zip(frames, check_stream(frames, src), strict=True):
        assert frame.frame_id == "realsense_infra1_optical"
        assert frame.is_gray
        assert frame.intrinsics == Intrinsics(*np.float32(DEPTH_K).tolist(), W, H)
        np.testing.assert_array_equal(frame.color, ir_y8(k))
        np.testing.assert_allclose(frame.depth, depth_mm(k) / 1000.0, rtol=0, atol=DEPTH_ATOL_M)


def test_distorted_colour_recording(tmp_path: Path) -> None:
    # Model and coefficients survive the db3; frames in the distorted camera are refused at start.
    coeffs = (0.1, -0.02, 0.0, 0.0, 0.0)
    path = record_db3(
        tmp_path / "distorted.db3", n=3, coeffs=coeffs, model=rs.distortion.inverse_brown_conrady
    )
    with pytest.raises(SourceError, match="Color stream has inverse_brown_conrady distortion"):
        RealSenseSource(RealSenseConfig(playback_file=str(path)))
    frames, _ = play(path, distortion="ignore")
    assert len(frames) >= 2 and frames[0].intrinsics.cx == np.float32(COLOR_K[2])
    frames, _ = play(path, align_to_color=False)  # frames in the (pinhole) depth camera
    assert len(frames) >= 2 and frames[0].frame_id == "realsense_depth_optical"


def test_played_frames_pose_into_rgbd_frames(recording: Path) -> None:
    frames, _ = play(recording)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    posed = frames[0].posed(T)
    assert isinstance(posed, RGBDFrame)
    assert posed.stamp_ns == frames[0].stamp_ns and posed.frame_id == "realsense_color_optical"
    np.testing.assert_array_equal(posed.T_world_cam, T)
    np.testing.assert_array_equal(posed.depth, frames[0].depth)
    with pytest.raises(FrameError, match="rotation"):
        frames[0].posed(np.diag([1.0, 1.0, -1.0, 1.0]))


# --------------------------------------------------------------------------------------------
# frames_from_rs on frames straight from a software sensor (no recording)
# --------------------------------------------------------------------------------------------


def sensor_frames(color_fmt, color: np.ndarray, depth: np.ndarray, units: float, **intr_kw):
    """One (image, depth) pair of SDK frames from a software sensor."""
    dev = rs.software_device()
    sensor = dev.add_sensor("Camera")
    bpp = color.shape[2] if color.ndim == 3 else 1
    kind = rs.stream.infrared if color_fmt == rs.format.y8 else rs.stream.color
    img_p = sensor.add_video_stream(_stream(kind, 1, 0, color_fmt, bpp, COLOR_K, **intr_kw))
    dep_p = sensor.add_video_stream(_stream(rs.stream.depth, 0, 1, rs.format.z16, 2, COLOR_K))
    queue = rs.frame_queue(4, keep_frames=True)
    sensor.open([img_p, dep_p])
    sensor.start(queue)
    for profile, pixels, b in ((img_p, color, bpp), (dep_p, depth, 2)):
        f = rs.software_video_frame()
        f.pixels, f.stride, f.bpp = pixels, W * b, b
        f.timestamp, f.domain, f.frame_number = 12.5, rs.timestamp_domain.hardware_clock, 3
        f.profile = profile.as_video_stream_profile()
        f.depth_units = units
        sensor.on_video_frame(f)
    image, dframe = queue.wait_for_frame(1000), queue.wait_for_frame(1000)
    sensor.stop()
    sensor.close()
    return image, dframe.as_depth_frame()


@pytest.mark.parametrize(
    ("fmt", "channels", "to_rgb"),
    [
        (rs.format.rgb8, 3, lambda a: a),
        (rs.format.bgr8, 3, lambda a: a[:, :, ::-1]),
        (rs.format.rgba8, 4, lambda a: a[:, :, :3]),
        (rs.format.bgra8, 4, lambda a: a[:, :, 2::-1]),
        (rs.format.y8, 0, lambda a: a),
    ],
)
def test_frames_from_rs_formats(fmt, channels: int, to_rgb) -> None:
    rng = np.random.default_rng(0)
    shape = (H, W, channels) if channels else (H, W)
    pixels = rng.integers(0, 256, shape, dtype=np.uint8)
    depth = rng.integers(0, 65536, (H, W), dtype=np.uint16)
    image, dframe = sensor_frames(fmt, pixels, depth, units=1e-4)
    frame = frames_from_rs(image, dframe, dframe.get_units(), frame_id="cam", seq=7)
    np.testing.assert_array_equal(frame.color, to_rgb(pixels))
    assert frame.color.flags.c_contiguous
    # 1e-4 m units (D405-like): 0.1 mm steps up to 6.5535 m; float32 rel. error < 1e-7.
    np.testing.assert_allclose(frame.depth, depth * 1e-4, rtol=2e-7, atol=0)
    assert frame.stamp_ns == 12_500_000 and frame.seq == 7 and frame.frame_id == "cam"
    assert frame.intrinsics == Intrinsics(*np.float32(COLOR_K).tolist(), W, H)


def test_frames_from_rs_distortion() -> None:
    pixels = np.zeros((H, W, 3), np.uint8)
    depth = np.full((H, W), 1500, np.uint16)
    kw = dict(coeffs=(0.1, -0.02, 0.0, 0.0, 0.0), model=rs.distortion.inverse_brown_conrady)
    image, dframe = sensor_frames(rs.format.rgb8, pixels, depth, units=1e-3, **kw)
    with pytest.raises(SourceError, match="inverse_brown_conrady distortion"):
        frames_from_rs(image, dframe, 1e-3)
    frame = frames_from_rs(image, dframe, 1e-3, distortion="ignore")
    assert frame.intrinsics.fx == 50.0
    np.testing.assert_allclose(frame.depth, 1.5, rtol=1e-7)


def test_frames_from_rs_unregistered() -> None:
    dev = rs.software_device()
    sensor = dev.add_sensor("Camera")
    img_p = sensor.add_video_stream(_stream(rs.stream.color, 0, 0, rs.format.rgb8, 3, COLOR_K))
    small = _stream(rs.stream.depth, 0, 1, rs.format.z16, 2, COLOR_K)
    small.width, small.height = W // 2, H // 2
    small.intrinsics = _intrinsics(COLOR_K)
    small.intrinsics.width, small.intrinsics.height = W // 2, H // 2
    dep_p = sensor.add_video_stream(small)
    queue = rs.frame_queue(4, keep_frames=True)
    sensor.open([img_p, dep_p])
    sensor.start(queue)
    for profile, pixels, b, w in (
        (img_p, np.zeros((H, W, 3), np.uint8), 3, W),
        (dep_p, np.zeros((H // 2, W // 2), np.uint16), 2, W // 2),
    ):
        f = rs.software_video_frame()
        f.pixels, f.stride, f.bpp, f.timestamp, f.frame_number = pixels, w * b, b, 1.0, 0
        f.profile = profile.as_video_stream_profile()
        sensor.on_video_frame(f)
    image, dframe = queue.wait_for_frame(1000), queue.wait_for_frame(1000)
    sensor.stop()
    sensor.close()
    with pytest.raises(SourceError, match="64x48 and depth 32x24 are not registered"):
        frames_from_rs(image, dframe, 1e-3)


@pytest.mark.parametrize(
    ("ms", "ns"),
    [
        (0.0, 0),
        (12.5, 12_500_000),
        (T0_MS, T0_NS),
        (1_700_000_000_123.456, 1_700_000_000_123_456_055),  # the double nearest to ...123.456
    ],
)
def test_ms_to_ns(ms: float, ns: int) -> None:
    assert ms_to_ns(ms) == ns


# --------------------------------------------------------------------------------------------
# Errors and configuration
# --------------------------------------------------------------------------------------------


def test_no_device_error() -> None:
    # CI has no RealSense: this is the message a user without a camera sees. (With one plugged
    # in, an unknown serial gives the same kind of message.)
    has_device = rs.context().query_devices().size() > 0
    cfg = RealSenseConfig(serial="000000000000") if has_device else RealSenseConfig()
    with pytest.raises(
        SourceError, match="no RealSense camera (with serial .* )?is connected"
    ) as info:
        RealSenseSource(cfg)
    assert "playback_file" in str(info.value) and "\n" not in str(info.value)


def test_unknown_serial_error() -> None:
    with pytest.raises(SourceError, match="no RealSense camera"):
        RealSenseSource(RealSenseConfig(serial="000000000000"))


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        (dict(playback_file="missing.db3"), "missing.db3 does not exist"),
        (dict(playback_file="run.mp4"), "must be a .db3 or .bag"),
        (dict(ir_only=True, align_to_color=True), "align_to_color does not apply"),
    ],
)
def test_bad_config(kw: dict, message: str) -> None:
    with pytest.raises(SourceError, match=message):
        RealSenseSource(RealSenseConfig(**kw))


def test_recording_without_requested_stream(tmp_path: Path) -> None:
    # A depth-only recording cannot give colour frames: the error says which streams were asked.
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    depth_p = sensor.add_video_stream(_stream(rs.stream.depth, 0, 0, rs.format.z16, 2, DEPTH_K))
    path = tmp_path / "depth_only.db3"
    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(4)
    sensor.open(depth_p)
    sensor.start(queue)
    for k in range(2):
        _inject(sensor, depth_p, depth_mm(k), 2, T0_MS + DT_MS * k, k)
    sensor.stop()
    sensor.close()
    del recorder
    gc.collect()
    with pytest.raises(SourceError, match="cannot open the depth \\+ colour streams"):
        RealSenseSource(RealSenseConfig(playback_file=str(path)))


def test_config_round_trip() -> None:
    cfg = build(RealSenseConfig, overrides=["ir_only=true", "emitter=off", "depth_width=848"])
    assert cfg.ir_only and cfg.emitter is False and cfg.depth_width == 848
    assert cfg.image_kind == "ir" and not cfg.aligns_to_color
    assert build(RealSenseConfig, base=to_dict(cfg)) == cfg
    assert RealSenseConfig().image_kind == "color"
    assert RealSenseConfig(align_to_color=False).image_kind == "depth"
    with pytest.raises(ConfigError, match="align_to_color does not apply"):
        build(RealSenseConfig, overrides=["ir_only=true", "align_to_color=true"])
    with pytest.raises(ConfigError, match="out of range"):
        build(RealSenseConfig, overrides=["color_fps=0"])


def test_camera_frame_validation() -> None:
    intr = Intrinsics(50.0, 50.0, 31.5, 23.5, W, H)
    color, depth = np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32)
    with pytest.raises(FrameError, match="depth must be float32"):
        CameraFrame(color, depth.astype(np.float64), intr, 0, "cam", 0)
    with pytest.raises(FrameError, match="sizes differ"):
        CameraFrame(color[:, :10], depth, intr, 0, "cam", 0)
    with pytest.raises(FrameError, match="stamp_ns must be an integer"):
        CameraFrame(color, depth, intr, 1.5, "cam", 0)
    assert CameraFrame(color[:, :, 0], depth, intr, np.int64(5), "cam", 0).stamp_ns == 5
