"""Intel RealSense (D4xx) camera or recording -> unposed :class:`CameraFrame` objects.

Streams, by mode (``RealSenseConfig``):

- colour (default): RGB8 colour and Z16 depth. With ``align_to_color`` (the default) depth is
  reprojected into the colour camera by the SDK (``rs.align(rs.stream.color)``): frames carry the
  colour image, the colour intrinsics and ``frame_id`` ``realsense_color_optical``. With
  ``align_to_color: false`` colour is reprojected into the depth camera instead
  (``rs.align(rs.stream.depth)``): depth is untouched, colour pixels without depth are black,
  intrinsics are the depth stream's and ``frame_id`` is ``realsense_depth_optical``.
- ``ir_only`` (the grayscale ship rig, D455): the left infrared imager (``infrared`` index 1, Y8)
  is the grayscale image. D4xx depth is computed in the left imager's frame, so no reprojection
  is needed; frames carry the IR intrinsics and ``frame_id`` ``realsense_infra1_optical``. Turn
  the emitter off (``emitter: false``) or its dot pattern is part of the image.

Units: depth is converted with the SDK's depth units (metres per Z16 step, from the depth frame,
else ``depth_sensor.get_depth_scale()``; 1 mm on most D4xx) to float32 metres, 0 = invalid.

Intrinsics are the SDK's stream intrinsics (``fx, fy, ppx, ppy, width, height``) of the image the
frame carries. Mapping assumes pinhole images: D4xx depth and infrared report no distortion, but
some colour modules report non-zero (inverse) Brown-Conrady coefficients. With
``distortion: error`` (default) frames in such a camera are refused at start; ``distortion:
ignore`` uses them as if they were pinhole (the coefficients are dropped, not applied). Only the camera the frames are in is checked: with ``align_to_color: false`` that is the
(pinhole) depth camera.

Stamps: the SDK frame timestamp (ms, double) of the image, converted exactly to integer ns. Its
clock is the frame's timestamp domain, logged once and kept in ``source.timestamp_domain``:
``global_time`` (D4xx default: device clock mapped to host epoch time), ``hardware_clock`` (device
clock since power-up) or ``system_time`` (host arrival time). Poses must come in the same clock.

Frame sets: the SDK pipeline repeats the last frame of a stream in a set where that stream has
none. A frame is yielded only when both its image and its depth frame are new since the last
one yielded (else ``stats.repeated``) and their stamps lie within ``max_pair_dt_ms`` (else
``stats.unpaired``). Gaps in the image frame numbers are counted in ``stats.dropped``.

Recordings: ``playback_file`` names a ``.db3`` (rosbag2/SQLite, what librealsense 2.59 records)
or a legacy ``.bag``. It is played once (no repeat) and iteration ends at its end; with
``realtime: false`` (default) frames come as fast as they are consumed and none are dropped;
``realtime: true`` follows the recorded timing and drops frames the consumer is too slow for.
Stream sizes and rates come from the recording; the live-only keys (serial, sizes, fps, emitter)
are ignored.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.core.types import Intrinsics
from gsfix_online.sources.base import SourceError
from gsfix_online.sources.camera import (
    SENSORS_INSTALL,
    CameraFrame,
    CameraStats,
    depth_units_to_m,
)

logger = logging.getLogger(__name__)

DistortionPolicy = Literal["error", "ignore"]

DISTORTION_ATOL = 1e-6  # larger |coefficient| means the stream is really distorted
PLAYBACK_POLL_MS = 100  # recordings: how often to check for the end of the file while waiting
RECORDING_SUFFIXES = (".db3", ".bag")
FRAME_IDS = {
    "color": "realsense_color_optical",
    "depth": "realsense_depth_optical",
    "ir": "realsense_infra1_optical",
}
NO_DEVICE_HINT = (
    "plug one in (USB 3) or set playback_file to a .db3/.bag recording "
    "(record one with realsense-viewer or rs-record)"
)


@dataclass(frozen=True)
class RealSenseConfig:
    """RealSense camera or recording. Sizes, rates, serial and emitter apply to live cameras only."""

    serial: str = ""  # "" = the first connected camera
    color_width: int = field(default=640, metadata=rng(1, 8192, "colour width, pixels"))
    color_height: int = field(default=480, metadata=rng(1, 8192, "colour height, pixels"))
    color_fps: int = field(default=30, metadata=rng(1, 300, "colour frame rate, Hz"))
    depth_width: int = field(default=640, metadata=rng(1, 8192, "depth (and IR) width, pixels"))
    depth_height: int = field(default=480, metadata=rng(1, 8192, "depth (and IR) height, pixels"))
    depth_fps: int = field(default=30, metadata=rng(1, 300, "depth (and IR) frame rate, Hz"))
    # Grayscale mode: left IR (Y8) image with depth, no colour stream (D455 ship rig).
    ir_only: bool = False
    # Colour mode: True = depth into colour pixels, False = colour into depth pixels.
    # None = True; must be None or False with ir_only.
    align_to_color: bool | None = None
    playback_file: str = ""  # "" = live camera; else a .db3 (or legacy .bag) recording
    realtime: bool = False  # recordings: follow the recorded timing (may drop frames)
    # IR dot projector, live only: None = leave as the camera has it. (A bool, not "on"/"off":
    # YAML reads a bare on/off as true/false, so `emitter: off` works as expected.)
    emitter: bool | None = None
    distortion: DistortionPolicy = "error"  # a distorted stream: refuse it, or use it as pinhole
    timeout_ms: int = field(default=2000, metadata=rng(1, 60_000, "wait for one frame set, ms"))
    max_timeouts: int = field(
        default=5, metadata=rng(1, None, "consecutive timeouts before giving up")
    )
    max_pair_dt_ms: float = field(
        default=0.0,
        metadata=rng(0, 1000, "max image/depth stamp difference, ms; 0 = half a frame period"),
    )

    def validate(self) -> None:
        if self.ir_only and self.align_to_color:
            raise ValueError(
                "align_to_color does not apply with ir_only (depth is already in the left IR frame); leave it unset"
            )
        if self.playback_file and Path(self.playback_file).suffix not in RECORDING_SUFFIXES:
            raise ValueError(
                f"playback_file must be a .db3 or .bag recording, got '{self.playback_file}'"
            )

    @property
    def aligns_to_color(self) -> bool:
        return not self.ir_only and self.align_to_color is not False

    @property
    def image_kind(self) -> Literal["color", "depth", "ir"]:
        """Which camera the yielded frames are in."""
        if self.ir_only:
            return "ir"
        return "color" if self.aligns_to_color else "depth"


# --------------------------------------------------------------------------------------------
# Conversion (pure: SDK frames in, CameraFrame out)
# --------------------------------------------------------------------------------------------


def import_pyrealsense2() -> ModuleType:
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise ImportError(f"the RealSense source needs pyrealsense2: {SENSORS_INSTALL}") from None
    return rs


def ms_to_ns(ms: float) -> int:
    """SDK timestamp (ms, double) -> int ns, exact to the double's resolution even at epoch times."""
    whole = math.floor(ms)
    return int(whole) * 1_000_000 + round((ms - whole) * 1e6)


def rs_intrinsics(
    profile: Any,  # rs.video_stream_profile (or any stream profile of a video stream)
    distortion: DistortionPolicy = "error",
) -> Intrinsics:
    """Pinhole intrinsics of a video stream; a distorted stream raises SourceError under "error"."""
    vsp = profile.as_video_stream_profile()
    intr = vsp.get_intrinsics()
    coeffs = [float(c) for c in intr.coeffs]
    if distortion == "error" and any(abs(c) > DISTORTION_ATOL for c in coeffs):
        raise SourceError(
            f"RealSense {vsp.stream_name()} stream has {intr.model.name} distortion {coeffs}; "
            "mapping needs pinhole images: set distortion: ignore to drop the coefficients"
        )
    return Intrinsics(
        float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy), intr.width, intr.height
    )


def _rows(frame: Any) -> tuple[npt.NDArray[np.uint8], int, int]:
    """A video frame's pixels as uint8 [H, W * bytes_per_pixel] (row padding removed), W, H."""
    vf = frame.as_video_frame()
    w, h = vf.get_width(), vf.get_height()
    stride, bpp = vf.get_stride_in_bytes(), vf.get_bytes_per_pixel()
    flat = np.frombuffer(vf.get_data(), dtype=np.uint8)
    assert flat.size >= stride * h and stride >= w * bpp, (flat.size, stride, w, h, bpp)
    return flat[: stride * h].reshape(h, stride)[:, : w * bpp], w, h


def rs_image(frame: Any) -> npt.NDArray[np.uint8]:  # [H, W, 3] RGB or [H, W] gray
    """Colour or infrared video frame -> a new uint8 RGB or grayscale array."""
    import cv2

    rs = import_pyrealsense2()
    fmt = frame.get_profile().format()
    rows, w, h = _rows(frame)
    if fmt == rs.format.rgb8:
        return rows.reshape(h, w, 3).copy()
    if fmt == rs.format.bgr8:
        return np.ascontiguousarray(rows.reshape(h, w, 3)[:, :, ::-1])
    if fmt == rs.format.rgba8:
        return np.ascontiguousarray(rows.reshape(h, w, 4)[:, :, :3])
    if fmt == rs.format.bgra8:
        return np.ascontiguousarray(rows.reshape(h, w, 4)[:, :, 2::-1])
    if fmt == rs.format.y8:
        return rows.copy()
    if fmt in (rs.format.yuyv, rs.format.uyvy):
        code = cv2.COLOR_YUV2RGB_YUYV if fmt == rs.format.yuyv else cv2.COLOR_YUV2RGB_UYVY
        return cv2.cvtColor(np.ascontiguousarray(rows.reshape(h, w, 2)), code)
    raise SourceError(
        f"RealSense image format {fmt.name} is not supported (expected rgb8, bgr8, rgba8, bgra8, yuyv, uyvy or y8)"
    )


def rs_depth_m(
    frame: Any,  # rs.depth_frame, Z16
    depth_scale: float,  # metres per Z16 unit
) -> npt.NDArray[np.float32]:  # [H, W] metres, 0 = invalid
    rs = import_pyrealsense2()
    fmt = frame.get_profile().format()
    if fmt != rs.format.z16:
        raise SourceError(f"RealSense depth format must be z16, got {fmt.name}")
    rows, w, h = _rows(frame)
    raw = np.ascontiguousarray(rows).view("<u2").astype(np.uint16, copy=False)
    return depth_units_to_m(raw.reshape(h, w), depth_scale)


def frames_from_rs(
    color_frame: Any,  # rs.video_frame: colour (rgb8/bgr8/rgba8/bgra8/yuyv/uyvy) or infrared (y8)
    depth_frame: Any,  # rs.depth_frame: z16, registered to color_frame (same pixels)
    depth_scale: float,  # metres per depth unit (depth_frame.get_units(), sensor depth scale)
    *,
    frame_id: str = FRAME_IDS["color"],
    seq: int = 0,
    distortion: DistortionPolicy = "error",
) -> CameraFrame:
    """One registered image + depth pair from the SDK -> CameraFrame (copies the pixels).

    Intrinsics are those of ``color_frame``'s stream profile (after ``rs.align`` the aligned
    frames carry the target stream's profile); the stamp is ``color_frame``'s timestamp in ns.
    """
    # 1. Check that the two frames are registered
    cw, ch = color_frame.as_video_frame().get_width(), color_frame.as_video_frame().get_height()
    dw, dh = depth_frame.as_video_frame().get_width(), depth_frame.as_video_frame().get_height()
    if (cw, ch) != (dw, dh):
        raise SourceError(
            f"RealSense image {cw}x{ch} and depth {dw}x{dh} are not registered; align them first (rs.align)"
        )
    # 2. Convert pixels, intrinsics and stamp
    return CameraFrame(
        color=rs_image(color_frame),
        depth=rs_depth_m(depth_frame, depth_scale),
        intrinsics=rs_intrinsics(color_frame.get_profile(), distortion),
        stamp_ns=ms_to_ns(color_frame.get_timestamp()),
        frame_id=frame_id,
        seq=seq,
    )


# --------------------------------------------------------------------------------------------
# Source
# --------------------------------------------------------------------------------------------


class RealSenseSource:
    """Streams :class:`CameraFrame` objects from a RealSense camera or a recording.

    The pipeline starts in the constructor (errors such as a missing camera surface there) and
    stops in :meth:`close`; use it as a context manager::

        with RealSenseSource(RealSenseConfig(playback_file="run.db3")) as cam:
            for frame in cam:
                ...
    """

    def __init__(self, cfg: RealSenseConfig) -> None:
        try:
            cfg.validate()
        except ValueError as exc:
            raise SourceError(f"RealSense: {exc}") from None
        rs = import_pyrealsense2()
        self.cfg = cfg
        self.stats = CameraStats()
        self.timestamp_domain = ""  # set from the first frame: global_time, hardware_clock, ...
        self._rs = rs
        self._pipe: Any = None
        self._playback: Any = None
        self._where = cfg.playback_file or "RealSense"

        # 1. Pick the device: a recording or a live camera
        rs_cfg = rs.config()
        if cfg.playback_file:
            path = Path(cfg.playback_file)
            if not path.is_file():
                raise SourceError(f"RealSense recording {path} does not exist")
            rs_cfg.enable_device_from_file(str(path), repeat_playback=False)
        else:
            rs_cfg.enable_device(self._find_serial(cfg.serial))

        # 2. Ask for the streams of the mode
        self._enable_streams(rs_cfg)

        # 3. Resolve: the device and its stream profiles, without starting
        pipe = rs.pipeline()
        try:
            profile = rs_cfg.resolve(rs.pipeline_wrapper(pipe))
        except RuntimeError as exc:
            raise SourceError(
                f"{self._where}: cannot open the {self._streams_text()}: {exc}"
            ) from None
        # 4. Check the camera the frames will be in (before starting: nothing to clean up)
        image_profile = self._image_profile(profile)
        intr = image_profile.as_video_stream_profile().get_intrinsics()
        if cfg.distortion == "error":
            rs_intrinsics(image_profile, "error")
        elif any(abs(c) > DISTORTION_ATOL for c in intr.coeffs):
            logger.warning(
                "%s: ignoring %s distortion %s of the %s stream",
                self._where,
                intr.model.name,
                list(intr.coeffs),
                image_profile.stream_name(),
            )
        self._max_pair_dt_ms = cfg.max_pair_dt_ms or 500.0 / (image_profile.fps() or 30)
        target = {"color": rs.stream.color, "depth": rs.stream.depth, "ir": None}[cfg.image_kind]
        self._align = rs.align(target) if target is not None else None
        self._last: tuple[int, int] | None = None  # (image, depth) frame numbers last yielded

        # 5. Configure the device and start
        device = profile.get_device()
        if cfg.playback_file:
            # Measured with pyrealsense2 2.59.1, colour + depth recordings (two sensors):
            # - real time switched off only after start lost 0-3 of the first frames;
            # - without the pause, about 1 play in 100 lost the first 1-5 of 6 frames: the
            #   sensors start one after the other and the pipeline drops the frames of the one
            #   that started first. Paused, the file waits until every sensor runs: 0 in 300.
            self._playback = device.as_playback()
            self._playback.set_real_time(cfg.realtime)
            self._playback.pause()
        else:
            self._set_emitter(device)
        try:
            profile = pipe.start(rs_cfg)
        except RuntimeError as exc:
            raise SourceError(
                f"{self._where}: cannot start the {self._streams_text()}: {exc}"
            ) from None
        self._pipe = pipe
        if self._playback is not None:
            self._playback.resume()
        self._depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        logger.info("%s: streaming %s", self._where, self._streams_text())

    # ---- setup helpers ----------------------------------------------------------------------

    def _find_serial(self, serial: str) -> str:
        rs = self._rs
        found = [
            d.get_info(rs.camera_info.serial_number)
            for d in rs.context().query_devices()
            if d.supports(rs.camera_info.serial_number)
        ]
        if not found:
            raise SourceError(f"no RealSense camera is connected; {NO_DEVICE_HINT}")
        if serial and serial not in found:
            raise SourceError(
                f"no RealSense camera with serial {serial} is connected (connected: {', '.join(found)}); {NO_DEVICE_HINT}"
            )
        return serial or found[0]

    def _enable_streams(self, rs_cfg: Any) -> None:
        rs, cfg = self._rs, self.cfg
        if cfg.playback_file:  # sizes and formats as recorded
            rs_cfg.enable_stream(rs.stream.depth)
            if cfg.ir_only:
                rs_cfg.enable_stream(rs.stream.infrared, 1)
            else:
                rs_cfg.enable_stream(rs.stream.color)
            return
        w, h, fps = cfg.depth_width, cfg.depth_height, cfg.depth_fps
        rs_cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
        if cfg.ir_only:
            rs_cfg.enable_stream(rs.stream.infrared, 1, w, h, rs.format.y8, fps)
        else:
            rs_cfg.enable_stream(
                rs.stream.color, cfg.color_width, cfg.color_height, rs.format.rgb8, cfg.color_fps
            )

    def _streams_text(self) -> str:
        cfg = self.cfg
        if cfg.playback_file:
            return "depth + " + ("infrared 1" if cfg.ir_only else "colour") + " streams"
        depth = f"depth {cfg.depth_width}x{cfg.depth_height}@{cfg.depth_fps}"
        if cfg.ir_only:
            return f"{depth} + infrared 1 Y8 at the same size and rate"
        return f"{depth} + colour {cfg.color_width}x{cfg.color_height}@{cfg.color_fps} RGB8"

    def _set_emitter(self, device: Any) -> None:
        if self.cfg.emitter is None:
            return
        rs = self._rs
        sensor = device.first_depth_sensor()
        if not sensor.supports(rs.option.emitter_enabled):
            logger.warning("%s: this camera has no emitter option; ignoring emitter", self._where)
            return
        sensor.set_option(rs.option.emitter_enabled, 1.0 if self.cfg.emitter else 0.0)

    def _image_profile(self, profile: Any) -> Any:
        rs = self._rs
        kind = self.cfg.image_kind
        if kind == "ir":
            return profile.get_stream(rs.stream.infrared, 1)
        return profile.get_stream(rs.stream.color if kind == "color" else rs.stream.depth)

    # ---- streaming --------------------------------------------------------------------------

    def __iter__(self) -> Iterator[CameraFrame]:
        return self._frames()

    def _frames(self) -> Iterator[CameraFrame]:
        rs = self._rs
        poll_ms = (
            min(PLAYBACK_POLL_MS, self.cfg.timeout_ms)
            if self._playback is not None
            else self.cfg.timeout_ms
        )
        waited_ms = 0
        consecutive = 0
        while self._pipe is not None:
            ok, frameset = self._pipe.try_wait_for_frames(poll_ms)
            if not ok:
                if self._playback is not None:
                    if self._playback.current_status() == rs.playback_status.stopped:
                        return  # end of the recording
                    waited_ms += poll_ms
                    if waited_ms < self.cfg.timeout_ms:
                        continue
                waited_ms = 0
                self.stats.timeouts += 1
                consecutive += 1
                if consecutive >= self.cfg.max_timeouts:
                    raise SourceError(
                        f"{self._where}: no frames for {consecutive} x {self.cfg.timeout_ms} ms; check the cable and the camera"
                    )
                continue
            waited_ms = consecutive = 0
            frame = self._convert(frameset)
            if frame is not None:
                self.stats.frames += 1
                yield frame

    def _convert(self, frameset: Any) -> CameraFrame | None:
        # 1. Pick the frames; skip sets that repeat a frame already used or pair distant ones
        image = frameset.get_infrared_frame(1) if self.cfg.ir_only else frameset.get_color_frame()
        depth = frameset.get_depth_frame()
        if not image or not depth:
            self.stats.incomplete += 1
            return None
        numbers = (image.get_frame_number(), depth.get_frame_number())
        if self._last is not None and (numbers[0] == self._last[0] or numbers[1] == self._last[1]):
            self.stats.repeated += 1
            return None
        if abs(image.get_timestamp() - depth.get_timestamp()) > self._max_pair_dt_ms:
            self.stats.unpaired += 1
            return None
        if self._last is not None and numbers[0] > self._last[0] + 1:
            self.stats.dropped += numbers[0] - self._last[0] - 1
        self._last = numbers
        if not self.timestamp_domain:
            self.timestamp_domain = image.get_frame_timestamp_domain().name
            logger.info("%s: frame stamps are %s", self._where, self.timestamp_domain)

        # 2. Register depth and image
        if self._align is not None:
            frameset = self._align.process(frameset)
            image = frameset.get_color_frame()
            depth = frameset.get_depth_frame()

        # 3. Convert
        units = depth.as_depth_frame().get_units() or self._depth_scale
        return frames_from_rs(
            image,
            depth,
            units,
            frame_id=FRAME_IDS[self.cfg.image_kind],
            seq=self.stats.frames,
            distortion=self.cfg.distortion,
        )

    # ---- lifetime ---------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the pipeline; safe to call more than once."""
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError as exc:  # already stopped by the SDK (device lost)
                logger.debug("%s: stop: %s", self._where, exc)
            if any(self.stats.as_dict()[k] for k in ("dropped", "timeouts", "unpaired")):
                logger.warning("%s: %s", self._where, self.stats.as_dict())

    def __enter__(self) -> RealSenseSource:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
