"""Luxonis OAK (depthai v3) stereo camera -> unposed :class:`CameraFrame` objects.

Pipeline (built on the device by :func:`build_pipeline`):

- stereo: left (``CAM_B``) and right (``CAM_C``) mono cameras at ``mono_width`` x ``mono_height``
  feed a ``StereoDepth`` node (``preset``, left-right check, ``subpixel``,
  ``extended_disparity``). Its depth is RAW16 in millimetres, reprojected on the device into the
  image camera with ``setDepthAlign(socket)`` and scaled to the image size with ``setOutputSize``.
- image, by mode: colour (default) is ``CAM_A`` at ``width`` x ``height``, NV12, undistorted on the
  device (``undistort``); ``ir_only`` (grayscale) is the left mono camera ``CAM_B``, undistorted,
  GRAY8 at the mono size (``width``/``height`` are then unused).
- a ``Sync`` node groups image and depth whose stamps lie within half a frame period; the group
  comes to the host on a non-blocking queue of ``queue_size`` (older groups are dropped when the
  consumer is slow, counted in ``stats.dropped`` from gaps in the image sequence numbers).

Frames: colour RGB uint8 [H, W, 3] (``frame_id`` ``oak_rgb_optical``) or grayscale [H, W]
(``oak_left_optical``); depth float32 metres (mm / 1000), 0 = invalid, same pixels as the image.

Intrinsics: the device calibration of the image camera at the image size,
``readCalibration().getCameraIntrinsics(socket, width, height)`` (which models the Camera node's
default scale-and-centre-crop). On the first frame they are compared with the intrinsics the frame
itself carries (``ImgFrame.getTransformation()``) and a disagreement is logged.

Stamps (``clock``): ``host`` (default) is ``ImgFrame.getTimestamp()``, the device clock synced by
depthai to the host's steady clock (``std::chrono::steady_clock``: ``time.monotonic_ns()`` on
Linux, not epoch time); ``device`` is ``getTimestampDevice()``, the device's own monotonic clock.
Both are converted to integer ns (depthai stamps have microsecond resolution). Poses must come
in the same clock.

What a user sets: ``device_id`` (empty = the first available device), sizes, ``fps``, the mode,
the stereo options and, on OAK-D Pro models, the IR dot projector and flood light intensities.
There is no recording playback here: depthai's holistic record/replay still needs a device.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import timedelta
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

Clock = Literal["host", "device"]
StereoPreset = Literal[
    "default", "robotics", "high_detail", "accuracy", "density", "fast_accuracy", "fast_density"
]

DEPTH_UNITS_M = 1e-3  # StereoDepth's RAW16 depth is in millimetres (its default depth unit)
INTRINSICS_WARN_PX = 1.0  # calibration vs frame intrinsics: larger differences are logged
FRAME_IDS = {False: "oak_rgb_optical", True: "oak_left_optical"}  # keyed by ir_only
NO_DEVICE_HINT = "plug one in (USB 3 or PoE) and check the udev rules; a device used by another process is not available"


@dataclass(frozen=True)
class OakConfig:
    """OAK stereo camera: image and aligned depth sizes, rate and stereo options."""

    device_id: str = ""  # "" = first available; else the device id (MXID), name or IP address
    width: int = field(default=640, metadata=rng(16, 4096, "colour image (and depth) width, px"))
    height: int = field(default=400, metadata=rng(16, 4096, "colour image (and depth) height, px"))
    fps: float = field(default=15.0, metadata=rng(1, 120, "frame rate of all cameras, Hz"))
    # Grayscale mode: the left mono camera is the image, depth aligned to it; no colour camera.
    ir_only: bool = False
    mono_width: int = field(default=640, metadata=rng(16, 4096, "stereo input width, px"))
    mono_height: int = field(default=400, metadata=rng(16, 4096, "stereo input height, px"))
    preset: StereoPreset = "robotics"  # StereoDepth.PresetMode, lower case
    left_right_check: bool = True  # drop pixels where left and right disparities disagree
    subpixel: bool = True  # finer depth steps at range (the SDK notes: not with extended_disparity)
    extended_disparity: bool = False  # closer minimum depth (about half), for tight spaces
    undistort: bool = True  # colour mode: undistort the colour image on the device
    clock: Clock = "host"  # stamps: host-synced ("host") or device monotonic ("device")
    ir_dot_intensity: float = field(
        default=0.0, metadata=rng(0, 1, "OAK-D Pro IR dot projector, 0 = off")
    )
    ir_flood_intensity: float = field(
        default=0.0, metadata=rng(0, 1, "OAK-D Pro IR flood light, 0 = off")
    )
    queue_size: int = field(default=8, metadata=rng(1, 64, "frame groups buffered on the host"))
    timeout_ms: int = field(default=2000, metadata=rng(1, 60_000, "wait for one frame group, ms"))
    max_timeouts: int = field(
        default=5, metadata=rng(1, None, "consecutive timeouts before giving up")
    )

    def validate(self) -> None:
        for name in ("width", "height", "mono_width", "mono_height"):
            if getattr(self, name) % 2:
                raise ValueError(f"{name} must be even (NV12 images), got {getattr(self, name)}")

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of the yielded images."""
        if self.ir_only:
            return self.mono_width, self.mono_height
        return self.width, self.height


# --------------------------------------------------------------------------------------------
# Conversion (pure: depthai messages in, CameraFrame out)
# --------------------------------------------------------------------------------------------


def import_depthai() -> ModuleType:
    try:
        import depthai as dai
    except ImportError:
        raise ImportError(f"the OAK source needs depthai (v3): {SENSORS_INSTALL}") from None
    return dai


def timedelta_to_ns(td: timedelta) -> int:
    """Exact: depthai stamps are timedeltas with microsecond resolution."""
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


def _plane(
    data: npt.NDArray[np.uint8],  # [N] the frame's bytes
    offset: int,
    rows: int,
    stride: int,
    row_bytes: int,
) -> npt.NDArray[np.uint8]:  # [rows, row_bytes]
    end = offset + rows * stride
    if data.size < end - stride + row_bytes:
        raise SourceError(
            f"OAK frame holds {data.size} bytes, too few for {rows} rows of {row_bytes} (stride {stride})"
        )
    if data.size < end:  # the last row need not be padded
        data = np.concatenate([data, np.zeros(end - data.size, np.uint8)])
    return data[offset:end].reshape(rows, stride)[:, :row_bytes]


def dai_image(
    frame: Any,  # dai.ImgFrame: NV12, BGR888i/RGB888i, BGR888p/RGB888p, GRAY8 or RAW8
    gray: bool = False,  # True: grayscale [H, W] (NV12: the Y plane) whatever the type
) -> npt.NDArray[np.uint8]:  # [H, W, 3] RGB or [H, W] gray, a new array
    import cv2

    dai = import_depthai()
    T = dai.ImgFrame.Type
    kind = frame.getType()
    w, h, stride = frame.getWidth(), frame.getHeight(), frame.getStride()
    data = np.asarray(frame.getData(), dtype=np.uint8).reshape(-1)
    if kind == T.NV12:
        if w % 2 or h % 2:
            raise SourceError(f"OAK NV12 frame must have even width and height, got {w}x{h}")
        y = _plane(data, 0, h, stride, w)
        if gray:
            return y.copy()
        uv = _plane(data, frame.getPlaneStride(0), h // 2, stride, w)
        return cv2.cvtColor(np.concatenate([y, uv]), cv2.COLOR_YUV2RGB_NV12)
    if kind in (T.GRAY8, T.RAW8):
        return _plane(data, 0, h, stride, w).copy()
    if kind in (T.BGR888i, T.RGB888i):
        rgb = _plane(data, 0, h, stride, 3 * w).reshape(h, w, 3)
        rgb = rgb[:, :, ::-1] if kind == T.BGR888i else rgb
    elif kind in (T.BGR888p, T.RGB888p):
        step = frame.getPlaneStride(0)
        planes = [_plane(data, i * step, h, stride, w) for i in range(3)]
        rgb = np.stack(planes[::-1] if kind == T.BGR888p else planes, axis=-1)
    else:
        raise SourceError(
            f"OAK image type {kind.name} is not supported (expected NV12, BGR888i, RGB888i, BGR888p, RGB888p, GRAY8 or RAW8)"
        )
    rgb = np.ascontiguousarray(rgb)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if gray else rgb


def dai_depth_m(
    frame: Any,  # dai.ImgFrame RAW16 depth
    depth_units_m: float = DEPTH_UNITS_M,
) -> npt.NDArray[np.float32]:  # [H, W] metres, 0 = invalid
    dai = import_depthai()
    if frame.getType() != dai.ImgFrame.Type.RAW16:
        raise SourceError(
            f"OAK depth must be RAW16 (StereoDepth.depth), got {frame.getType().name}"
        )
    w, h = frame.getWidth(), frame.getHeight()
    data = np.asarray(frame.getData(), dtype=np.uint8).reshape(-1)
    rows = np.ascontiguousarray(_plane(data, 0, h, frame.getStride(), 2 * w))
    return depth_units_to_m(rows.view("<u2").astype(np.uint16, copy=False), depth_units_m)


def frames_from_dai(
    color_imgframe: Any,  # dai.ImgFrame: the image (colour or mono)
    depth_imgframe: Any,  # dai.ImgFrame RAW16 depth, aligned to the image (same pixels)
    K: npt.ArrayLike,  # [3, 3] pixels, for the image at its size
    *,
    frame_id: str = FRAME_IDS[False],
    clock: Clock = "host",
    gray: bool = False,  # yield the image as grayscale (mono cameras, ir_only)
    seq: int | None = None,  # None = the image's sequence number
    depth_units_m: float = DEPTH_UNITS_M,
) -> CameraFrame:
    """One aligned image + depth pair from depthai -> CameraFrame (copies the pixels)."""
    # 1. Check that depth is aligned to the image
    iw, ih = color_imgframe.getWidth(), color_imgframe.getHeight()
    dw, dh = depth_imgframe.getWidth(), depth_imgframe.getHeight()
    if (iw, ih) != (dw, dh):
        raise SourceError(
            f"OAK depth {dw}x{dh} is not aligned to the {iw}x{ih} image; use StereoDepth setDepthAlign and setOutputSize"
        )
    # 2. Convert pixels, intrinsics and stamp
    stamp = (
        color_imgframe.getTimestamp() if clock == "host" else color_imgframe.getTimestampDevice()
    )
    return CameraFrame(
        color=dai_image(color_imgframe, gray=gray),
        depth=dai_depth_m(depth_imgframe, depth_units_m),
        intrinsics=Intrinsics.from_K(K, iw, ih),
        stamp_ns=timedelta_to_ns(stamp),
        frame_id=frame_id,
        seq=color_imgframe.getSequenceNum() if seq is None else seq,
    )


# --------------------------------------------------------------------------------------------
# Device pipeline
# --------------------------------------------------------------------------------------------


def build_pipeline(pipeline: Any, cfg: OakConfig) -> Any:
    """Add cameras, StereoDepth aligned to the image camera and a Sync node to ``pipeline``.

    ``pipeline`` must have a device (depthai refuses camera nodes in a host-only pipeline).
    Returns the host queue of ``dai.MessageGroup`` with messages "image" and "depth".
    """
    dai = import_depthai()
    S = dai.CameraBoardSocket
    mono = (cfg.mono_width, cfg.mono_height)
    size = cfg.image_size

    # 1. Stereo pair -> depth, reprojected into the image camera
    left = pipeline.create(dai.node.Camera).build(S.CAM_B, sensorFps=cfg.fps)
    right = pipeline.create(dai.node.Camera).build(S.CAM_C, sensorFps=cfg.fps)
    stereo = pipeline.create(dai.node.StereoDepth)
    stereo.setDefaultProfilePreset(getattr(dai.node.StereoDepth.PresetMode, cfg.preset.upper()))
    stereo.setLeftRightCheck(cfg.left_right_check)
    stereo.setSubpixel(cfg.subpixel)
    stereo.setExtendedDisparity(cfg.extended_disparity)
    left.requestOutput(mono, dai.ImgFrame.Type.GRAY8, fps=cfg.fps).link(stereo.left)
    right.requestOutput(mono, dai.ImgFrame.Type.GRAY8, fps=cfg.fps).link(stereo.right)

    # 2. The image camera
    if cfg.ir_only:
        stereo.setDepthAlign(S.CAM_B)
        image = left.requestOutput(
            size, dai.ImgFrame.Type.GRAY8, fps=cfg.fps, enableUndistortion=True
        )
    else:
        stereo.setDepthAlign(S.CAM_A)
        stereo.setOutputSize(*size)
        color = pipeline.create(dai.node.Camera).build(S.CAM_A, sensorFps=cfg.fps)
        image = color.requestOutput(
            size, dai.ImgFrame.Type.NV12, fps=cfg.fps, enableUndistortion=cfg.undistort
        )

    # 3. Group image and depth by stamp
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(timedelta(seconds=0.5 / cfg.fps))
    image.link(sync.inputs["image"])
    stereo.depth.link(sync.inputs["depth"])
    return sync.out.createOutputQueue(maxSize=cfg.queue_size, blocking=False)


class OakSource:
    """Streams :class:`CameraFrame` objects from an OAK device; a context manager.

    The device is opened and the pipeline started in the constructor, stopped in :meth:`close`.
    """

    def __init__(self, cfg: OakConfig) -> None:
        try:
            cfg.validate()
        except ValueError as exc:
            raise SourceError(f"OAK: {exc}") from None
        dai = import_depthai()
        self.cfg = cfg
        self.stats = CameraStats()
        self._dai = dai
        self._device: Any = None
        self._pipeline: Any = None
        self._last_seq: int | None = None
        self._checked_intrinsics = False

        # 1. Open the device
        info = self._find_device(cfg.device_id)
        try:
            self._device = dai.Device(info)
        except RuntimeError as exc:
            raise SourceError(f"OAK {info.getDeviceId()}: cannot open the device: {exc}") from None
        self._where = f"OAK {info.getDeviceId()}"
        try:
            # 2. Pipeline, intrinsics, IR illumination
            self._pipeline = dai.Pipeline(self._device)
            self._queue = build_pipeline(self._pipeline, cfg)
            socket = dai.CameraBoardSocket.CAM_B if cfg.ir_only else dai.CameraBoardSocket.CAM_A
            w, h = cfg.image_size
            K = self._device.readCalibration().getCameraIntrinsics(socket, w, h)
            self.K = np.asarray(K, dtype=np.float64)  # [3, 3] pixels, for the image size
            self._set_ir(cfg)
            # 3. Start
            self._pipeline.start()
        except RuntimeError as exc:
            self.close()
            raise SourceError(f"{self._where}: cannot start the pipeline: {exc}") from None
        except BaseException:
            self.close()
            raise
        logger.info(
            "%s: streaming %s %dx%d @ %g Hz",
            self._where,
            "mono" if cfg.ir_only else "colour",
            w,
            h,
            cfg.fps,
        )

    def _find_device(self, device_id: str) -> Any:
        infos = self._dai.Device.getAllAvailableDevices()
        if not infos:
            raise SourceError(f"no OAK device is connected; {NO_DEVICE_HINT}")
        if not device_id:
            return infos[0]
        for info in infos:
            if device_id in (info.getDeviceId(), info.name):
                return info
        found = ", ".join(f"{i.getDeviceId()} ({i.name})" for i in infos)
        raise SourceError(f"no OAK device {device_id} is connected (available: {found})")

    def _set_ir(self, cfg: OakConfig) -> None:
        for name, value in (
            ("setIrLaserDotProjectorIntensity", cfg.ir_dot_intensity),
            ("setIrFloodLightIntensity", cfg.ir_flood_intensity),
        ):
            if value > 0 and not getattr(self._device, name)(value):
                logger.warning("%s: %s(%g) failed (not an OAK-D Pro?)", self._where, name, value)

    # ---- streaming --------------------------------------------------------------------------

    def __iter__(self) -> Iterator[CameraFrame]:
        return self._frames()

    def _frames(self) -> Iterator[CameraFrame]:
        dai = self._dai
        consecutive = 0
        while self._pipeline is not None:
            try:
                group = self._queue.get(timedelta(milliseconds=self.cfg.timeout_ms))
            except dai.MessageQueue.QueueException as exc:
                if self._pipeline is None:  # closed by us
                    return
                raise SourceError(f"{self._where}: the pipeline stopped: {exc}") from None
            if group is None:
                self.stats.timeouts += 1
                consecutive += 1
                if consecutive >= self.cfg.max_timeouts:
                    raise SourceError(
                        f"{self._where}: no frames for {consecutive} x {self.cfg.timeout_ms} ms; check the cable and the device"
                    )
                continue
            consecutive = 0
            frame = self._convert(group)
            if frame is not None:
                self.stats.frames += 1
                yield frame

    def _convert(self, group: Any) -> CameraFrame | None:
        names = set(group.getMessageNames())
        if not {"image", "depth"} <= names:
            self.stats.incomplete += 1
            return None
        image, depth = group["image"], group["depth"]
        seq = image.getSequenceNum()
        if self._last_seq is not None and seq > self._last_seq + 1:
            self.stats.dropped += seq - self._last_seq - 1
        self._last_seq = seq
        if not self._checked_intrinsics:
            self._check_intrinsics(image)
        return frames_from_dai(
            image,
            depth,
            self.K,
            frame_id=FRAME_IDS[self.cfg.ir_only],
            clock=self.cfg.clock,
            gray=self.cfg.ir_only,
            seq=self.stats.frames,
        )

    def _check_intrinsics(self, image: Any) -> None:
        self._checked_intrinsics = True
        t = image.getTransformation()
        if not t.isValid():
            return
        K_frame = np.asarray(t.getIntrinsicMatrix(), dtype=np.float64)
        if np.max(np.abs(K_frame - self.K)) > INTRINSICS_WARN_PX:
            logger.warning(
                "%s: calibration intrinsics %s differ from the frame's own %s; using the calibration",
                self._where,
                np.round(self.K, 2).tolist(),
                np.round(K_frame, 2).tolist(),
            )

    # ---- lifetime ---------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the pipeline and release the device; safe to call more than once."""
        pipeline, self._pipeline = self._pipeline, None
        device, self._device = self._device, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError as exc:
                logger.debug("OAK: stop: %s", exc)
        if device is not None:
            device.close()
        if any(self.stats.as_dict()[k] for k in ("dropped", "timeouts")):
            logger.warning("OAK: %s", self.stats.as_dict())

    def __enter__(self) -> OakSource:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
