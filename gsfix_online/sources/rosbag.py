"""ROS bags without ROS: ROS1 ``.bag``, rosbag2 folders (SQLite ``.db3`` or MCAP), bare ``.db3``/``.mcap``.

Read and written through the pure-Python ``rosbags`` package.

Topics and messages (config keys of ``source``):

- ``color_topic``: ``sensor_msgs/Image`` with encoding rgb8, bgr8, rgba8, bgra8 or mono8, or
  ``sensor_msgs/CompressedImage`` (jpeg or png).
- ``depth_topic``: ``sensor_msgs/Image`` 16UC1 (``depth_scale`` units per metre, default 1000 = mm)
  or 32FC1 (metres), or ``sensor_msgs/CompressedImage`` 16UC1 ``compressedDepth`` (a 12-byte header,
  then a 16-bit PNG) or a plain 16-bit PNG. Raw images honour ``step`` (row padding) and ``is_bigendian``.
- ``camera_info_topic``: ``sensor_msgs/CameraInfo``; K, width and height of the first message.
  ``source.camera``, when set, overrides it (as for the file datasets) and is required when the bag
  has no camera info or an all-zero (uncalibrated) K. Distortion is ignored: images must be rectified.
- Poses, by ``pose_source``:
  ``pose``: ``geometry_msgs/PoseStamped`` on ``pose_topic``;
  ``tf``: ``tf2_msgs/TFMessage`` on ``/tf`` and ``/tf_static``, the transforms whose
  ``header.frame_id`` is ``tf_parent`` and ``child_frame_id`` is ``tf_child`` (a leading ``/`` is
  ignored; only that direct edge is used, chains are not composed; a ``/tf_static`` edge holds at
  all times and is used only when ``/tf`` has none);
  ``auto``: ``pose`` when ``pose_topic`` is in the bag, else ``tf``. ``none`` is refused: mapping needs poses.
  The tracked pose is T_world_S; the camera pose is T_world_S @ ``T_SC``.

Pairing: colour and depth messages are streamed in bag order and matched on header stamps (sensor
time) by a bounded greedy rule: while both queues hold a message, pair the two heads when their
stamps are within ``max_assoc_s``, else drop the older head (``stats.unpaired``). A queue longer than
``MAX_QUEUE`` drops its oldest message (also unpaired). Each pair takes the pose interpolated at the
colour stamp, within ``max_pose_gap_s``; pairs without one are counted in ``stats.without_pose``.
Memory stays bounded: only poses and camera info are read up front.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Reader1Error
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import ReaderError as Reader2Error
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from gsfix_online.core.se3 import inv_T, pose_from_tq, pose_to_tq
from gsfix_online.core.trajectory import Trajectory
from gsfix_online.core.types import FrameError, Intrinsics, RGBDFrame
from gsfix_online.sources.base import (
    FrameSource,
    SourceError,
    check_frame_images,
    ns_to_seconds,
    to_frame,
)
from gsfix_online.sources.config import SourceConfig
from gsfix_online.sources.pose_list import QUAT_NORM_TOL

logger = logging.getLogger(__name__)

DEPTH_SCALE = 1000.0  # 16UC1 depth: millimetres, the ROS (REP 118) convention
MAX_QUEUE = 32  # messages one stream may hold while waiting for its partner (bounds memory)
TF_TOPICS = ("/tf", "/tf_static")

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMAGE_TYPES = (IMAGE, COMPRESSED)

# encoding -> (dtype, channels)
COLOR_ENCODINGS = {
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1),
}
DEPTH_ENCODINGS = {"16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
COMPRESSED_DEPTH_HEADER = 12  # ROS compressedDepth: int32 format, float32 depthQuantA, depthQuantB

# Reading errors of rosbags that mean "this file cannot be read", not a bug of ours.
_BAG_ERRORS = (AnyReaderError, Reader1Error, Reader2Error, OSError)


# --------------------------------------------------------------------------------------------
# Messages -> arrays
# --------------------------------------------------------------------------------------------


def stamp_to_ns(header: Any) -> int:  # noqa: ANN401 - a rosbags std_msgs/Header
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_to_array(msg: Any, encodings: dict, where: str) -> np.ndarray:  # noqa: ANN401
    """Raw ``sensor_msgs/Image`` -> owned native-endian array [H, W] or [H, W, C]."""
    enc = str(msg.encoding)
    if enc not in encodings:
        raise SourceError(
            f"{where}: unsupported image encoding {enc!r} (expected one of {', '.join(encodings)})"
        )
    dtype, channels = encodings[enc]
    dtype = np.dtype(dtype)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    if h <= 0 or w <= 0:
        raise SourceError(f"{where}: image size must be positive, got {w}x{h}")
    if step < row_bytes:
        raise SourceError(
            f"{where}: step {step} is less than width*channels*bytes = {row_bytes} for {enc}"
        )
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if data.size < h * step:
        raise SourceError(
            f"{where}: image data has {data.size} bytes, expected height*step = {h}*{step} = {h * step}"
        )
    rows = data[: h * step].reshape(h, step)[:, :row_bytes].copy()  # drops row padding
    wire = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    arr = rows.view(wire).reshape((h, w, channels) if channels > 1 else (h, w))
    return arr.astype(dtype, copy=False)


def _decode_png_or_jpeg(data: npt.NDArray[np.uint8], where: str) -> np.ndarray:
    import cv2

    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SourceError(f"{where}: cannot decode the compressed image ({data.size} bytes)")
    return img


def decode_color(msg: Any, msgtype: str, where: str) -> npt.NDArray[np.uint8]:  # noqa: ANN401
    """Colour message -> RGB [H, W, 3] or grayscale [H, W] uint8."""
    if msgtype == IMAGE:
        arr = image_to_array(msg, COLOR_ENCODINGS, where)
        enc = str(msg.encoding)
        if enc.startswith("bgr"):
            arr = arr[:, :, 2::-1]
        elif arr.ndim == 3:
            arr = arr[:, :, :3]
        return np.ascontiguousarray(arr)
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt or not any(c in fmt for c in ("jpeg", "jpg", "png")):
        raise SourceError(
            f"{where}: unsupported colour CompressedImage format {msg.format!r} (expected jpeg or png)"
        )
    img = _decode_png_or_jpeg(np.asarray(msg.data, dtype=np.uint8), where)
    if img.dtype != np.uint8:
        raise SourceError(f"{where}: compressed colour must be 8-bit, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        import cv2

        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


def decode_depth(msg: Any, msgtype: str, scale: float, where: str) -> npt.NDArray[np.float32]:  # noqa: ANN401
    """Depth message -> float32 metres [H, W]; 16-bit values are divided by ``scale``."""
    if msgtype == IMAGE:
        raw = image_to_array(msg, DEPTH_ENCODINGS, where)
    else:
        fmt = str(msg.format)
        data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
        if "compresseddepth" in fmt.lower():
            if not fmt.startswith("16UC1") or "rvl" in fmt.lower():
                raise SourceError(
                    f"{where}: unsupported compressedDepth format {fmt!r} (expected '16UC1; compressedDepth png')"
                )
            if (
                data[COMPRESSED_DEPTH_HEADER : COMPRESSED_DEPTH_HEADER + 8].tobytes()
                == PNG_SIGNATURE
            ):
                data = data[COMPRESSED_DEPTH_HEADER:]
        raw = _decode_png_or_jpeg(data, where)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise SourceError(
                f"{where}: compressed depth must be a 16-bit single-channel PNG, got {raw.dtype} {list(raw.shape)}"
            )
    if raw.dtype == np.uint16:
        return (raw.astype(np.float32) / np.float32(scale)).astype(np.float32)
    return raw.astype(np.float32, copy=False)


def _field(msg: Any, name: str) -> Any:  # noqa: ANN401
    """CameraInfo matrices are upper case in ROS1 (K, D) and lower case in ROS2 (k, d)."""
    return getattr(msg, name.lower()) if hasattr(msg, name.lower()) else getattr(msg, name.upper())


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------


def _topic_list(topics: dict) -> str:
    return ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"


class RosbagReader(FrameSource):
    """Posed RGB-D frames from a ROS1 or ROS2 bag; see the module docstring for topics and pairing."""

    format = "rosbag"

    def __init__(self, path: str | Path, cfg: SourceConfig) -> None:
        super().__init__(path, cfg)
        # 1. Check the configuration
        if cfg.pose_source == "none":
            raise SourceError(
                f"rosbag: {self.path}: pose_source 'none' is not valid for mapping, poses are required "
                "(set source.pose_source to pose, tf or auto)"
            )
        if cfg.color_topic == cfg.depth_topic:
            raise SourceError(f"rosbag: color_topic and depth_topic are both {cfg.color_topic}")
        self._scale = self.depth_scale(DEPTH_SCALE)
        self._static_T: npt.NDArray[np.float64] | None = None  # [4, 4] T_world_cam from /tf_static
        self._K: npt.NDArray[np.float64] | None = None  # [3, 3] pixels, from CameraInfo
        self._info_size: tuple[int, int] = (0, 0)  # (width, height) of CameraInfo, 0 = unknown
        with self._open() as bag:
            # 2. Check the topics and their message types
            topics = bag.topics
            self._color_type = self._require(topics, cfg.color_topic, IMAGE_TYPES, "color_topic")
            self._depth_type = self._require(topics, cfg.depth_topic, IMAGE_TYPES, "depth_topic")
            self._n_color = int(topics[cfg.color_topic].msgcount)
            self.pose_mode = self._pose_mode(topics)
            # 3. Camera info (first message) and poses: small, read up front
            if cfg.camera_info_topic in topics:
                self._require(topics, cfg.camera_info_topic, (CAMERA_INFO,), "camera_info_topic")
                self._read_camera_info(bag)
            T_world_S = self._read_poses(bag, topics)
        if self._K is None and not cfg.camera.is_set:
            raise SourceError(
                f"rosbag: {self.path}: no usable camera info on {cfg.camera_info_topic}; "
                "set source.camera_info_topic or source.camera.fx/fy/cx/cy"
            )
        self.trajectory = T_world_S.transformed(self.T_SC())  # T_world_cam
        if self._static_T is not None:
            self._static_T = self._static_T @ self.T_SC()

    @contextmanager
    def _open(self) -> Iterator[AnyReader]:
        # Used only for bags that embed no type definitions (old or bare .db3); ROS1 bags always do.
        store = get_typestore(
            Stores.ROS1_NOETIC if self.path.suffix == ".bag" else Stores.ROS2_HUMBLE
        )
        try:
            bag = AnyReader([self.path], default_typestore=store)
            bag.open()
        except _BAG_ERRORS as exc:
            raise SourceError(f"rosbag: cannot open {self.path}: {exc}") from None
        try:
            yield bag
        finally:
            bag.close()

    def _require(self, topics: dict, topic: str, msgtypes: tuple[str, ...], key: str) -> str:
        if topic not in topics:
            raise SourceError(
                f"rosbag: {self.path}: {key} {topic} is not in the bag; topics: {_topic_list(topics)}"
            )
        msgtype = topics[topic].msgtype
        if msgtype not in msgtypes:
            raise SourceError(
                f"rosbag: {self.path}: {key} {topic} has type {msgtype}, expected {' or '.join(msgtypes)}"
            )
        return msgtype

    def _pose_mode(self, topics: dict) -> Literal["pose", "tf"]:
        cfg = self.cfg
        has_tf = any(t in topics for t in TF_TOPICS)
        if cfg.pose_source == "pose" or (cfg.pose_source == "auto" and cfg.pose_topic in topics):
            self._require(topics, cfg.pose_topic, (POSE_STAMPED,), "pose_topic")
            return "pose"
        if cfg.pose_source == "tf" or has_tf:
            for t in TF_TOPICS:
                if t in topics:
                    self._require(topics, t, (TF_MESSAGE,), "tf topic")
            if not has_tf:
                raise SourceError(
                    f"rosbag: {self.path}: pose_source tf needs /tf or /tf_static; topics: {_topic_list(topics)}"
                )
            return "tf"
        raise SourceError(
            f"rosbag: {self.path}: no poses: neither pose_topic {cfg.pose_topic} nor /tf, /tf_static is in "
            f"the bag; topics: {_topic_list(topics)}"
        )

    def _messages(self, bag: AnyReader, topics: Iterable[str]) -> Iterator[tuple[Any, int, bytes]]:
        """Messages of ``topics`` in bag order (rosbags reads *every* topic when given no connections)."""
        wanted = set(topics)
        conns = [c for c in bag.connections if c.topic in wanted]
        if not conns:
            return
        try:
            yield from bag.messages(connections=conns)
        except _BAG_ERRORS as exc:  # a truncated or corrupt file
            raise SourceError(f"rosbag: cannot read {self.path}: {exc}") from None

    def _deserialize(self, bag: AnyReader, raw: bytes, con: Any, where: str) -> Any:  # noqa: ANN401
        try:
            return bag.deserialize(raw, con.msgtype)
        except _BAG_ERRORS as exc:
            raise SourceError(f"{where}: cannot decode {con.msgtype}: {exc}") from None

    def _read_camera_info(self, bag: AnyReader) -> None:
        topic = self.cfg.camera_info_topic
        for con, _, raw in self._messages(bag, [topic]):
            msg = self._deserialize(bag, raw, con, f"rosbag: {self.path} {topic}")
            K = np.asarray(_field(msg, "K"), dtype=np.float64).reshape(3, 3)
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                logger.warning(
                    "%s: %s has no calibration (K = 0); using source.camera", self.path, topic
                )
                return
            self._K = K
            self._info_size = (int(msg.width), int(msg.height))
            if all(self._info_size):  # validate once, here
                self._intrinsics(*self._info_size)
            return

    def _read_poses(self, bag: AnyReader, topics: dict) -> Trajectory:
        """Pose messages -> Trajectory of T_world_S (a /tf_static edge goes to ``self._static_T``)."""
        cfg = self.cfg
        parent, child = cfg.tf_parent.lstrip("/"), cfg.tf_child.lstrip("/")
        wanted = (cfg.pose_topic,) if self.pose_mode == "pose" else TF_TOPICS
        stamps: list[int] = []
        tq: list[tuple[float, ...]] = []
        static: tuple[float, ...] | None = None
        seen: set[str] = set()
        for con, _, raw in self._messages(bag, wanted):
            msg = self._deserialize(bag, raw, con, f"rosbag: {self.path} {con.topic}")
            if self.pose_mode == "pose":
                p, q = msg.pose.position, msg.pose.orientation
                stamps.append(stamp_to_ns(msg.header))
                tq.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
                continue
            for tf in msg.transforms:
                edge = (tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))
                if edge != (parent, child):
                    seen.add(f"{edge[0]} -> {edge[1]}")
                    continue
                t, q = tf.transform.translation, tf.transform.rotation
                values = (t.x, t.y, t.z, q.x, q.y, q.z, q.w)
                if con.topic == "/tf_static":
                    static = values
                else:
                    stamps.append(stamp_to_ns(tf.header))
                    tq.append(values)
        if not tq and static is None:
            if self.pose_mode == "pose":
                raise SourceError(
                    f"rosbag: {self.path}: no poses: pose_topic {cfg.pose_topic} has no messages"
                )
            shown = ", ".join(sorted(seen)[:20]) or "none"
            raise SourceError(
                f"rosbag: {self.path}: no poses: no transform {parent} -> {child} on /tf or /tf_static "
                f"(set source.tf_parent/tf_child); transforms seen: {shown}"
            )
        if tq:
            return Trajectory(np.asarray(stamps, np.int64), self._to_poses(np.asarray(tq)))
        self._static_T = self._to_poses(np.asarray([static]))[0]
        return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))

    def _to_poses(self, tq: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """[N, 7] (tx, ty, tz, qx, qy, qz, qw) -> [N, 4, 4], rejecting NaN and non-unit quaternions."""
        if not np.all(np.isfinite(tq)):
            raise SourceError(f"rosbag: {self.path}: a pose contains NaN or inf")
        norm = np.linalg.norm(tq[:, 3:], axis=1)
        if np.any(np.abs(norm - 1.0) > QUAT_NORM_TOL):
            i = int(np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)[0])
            raise SourceError(
                f"rosbag: {self.path}: pose {i} (in bag order) has a quaternion of norm "
                f"{norm[i]:.6g}; expected 1 within {QUAT_NORM_TOL:g}"
            )
        return pose_from_tq(tq[:, :3], tq[:, 3:])

    def _pose_at(self, stamp_ns: int) -> npt.NDArray[np.float64] | None:
        if self._static_T is not None:
            return self._static_T.copy()
        return self.trajectory.query(stamp_ns, int(round(self.cfg.max_pose_gap_s * 1e9)))

    def _intrinsics(self, width: int, height: int) -> Intrinsics:
        # source.camera, when set, overrides the bag's CameraInfo (as for the file datasets).
        if self._K is None or self.cfg.camera.is_set:
            return self.intrinsics_from_config(width, height)
        w, h = self._info_size if all(self._info_size) else (width, height)
        try:
            return Intrinsics.from_K(self._K, w, h)
        except FrameError as exc:
            raise SourceError(f"rosbag: {self.path} {self.cfg.camera_info_topic}: {exc}") from None

    def __len__(self) -> int:
        return self._n_color

    def _frames(self) -> Iterator[RGBDFrame]:
        cfg = self.cfg
        max_dt = int(round(cfg.max_assoc_s * 1e9))
        color_q: deque[tuple[int, Any]] = deque()  # (header stamp ns, message)
        depth_q: deque[tuple[int, Any]] = deque()
        seq = 0
        with self._open() as bag:
            for con, _, raw in self._messages(bag, (cfg.color_topic, cfg.depth_topic)):
                msg = self._deserialize(bag, raw, con, f"rosbag: {self.path} {con.topic}")
                q = color_q if con.topic == cfg.color_topic else depth_q
                q.append((stamp_to_ns(msg.header), msg))
                while color_q and depth_q:
                    tc, td = color_q[0][0], depth_q[0][0]
                    if abs(tc - td) <= max_dt:
                        frame = self._pair(color_q.popleft(), depth_q.popleft(), seq)
                        seq += 1
                        if frame is not None:
                            yield frame
                    else:
                        (color_q if tc < td else depth_q).popleft()
                        self.stats.unpaired += 1
                if len(q) > MAX_QUEUE:
                    q.popleft()
                    self.stats.unpaired += 1
        self.stats.unpaired += len(color_q) + len(depth_q)

    def _pair(
        self, color_item: tuple[int, Any], depth_item: tuple[int, Any], seq: int
    ) -> RGBDFrame | None:
        stamp, cmsg = color_item
        _, dmsg = depth_item
        T = self._pose_at(stamp)
        if T is None:
            self.stats.without_pose += 1
            return None
        where = f"rosbag: {self.path.name} {self.cfg.color_topic} @ {ns_to_seconds(stamp)}"
        color = decode_color(cmsg, self._color_type, where)
        depth = decode_depth(dmsg, self._depth_type, self._scale, where)
        check_frame_images(color, depth, where)
        intr = self._intrinsics(depth.shape[1], depth.shape[0])
        frame_id = str(cmsg.header.frame_id) or "camera"
        return to_frame(color, depth, intr, T, stamp, frame_id=frame_id, seq=seq, where=where)


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def _writer_typestore(ros1: bool):  # noqa: ANN202 - rosbags Typestore
    """NOETIC for ROS1 (it lacks tf2_msgs/TFMessage, registered here), HUMBLE for ROS2."""
    if not ros1:
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    return ts


class _Messages:
    """Builds ROS1 or ROS2 messages from a typestore (header and CameraInfo field names differ)."""

    def __init__(self, ts: Any, ros1: bool) -> None:  # noqa: ANN401
        self.t = ts.types
        self.ros1 = ros1

    def header(self, stamp_ns: int, frame_id: str, seq: int) -> Any:  # noqa: ANN401
        stamp = self.t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
        )
        extra = {"seq": seq} if self.ros1 else {}
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **extra)

    def image(self, header: Any, array: np.ndarray, encoding: str) -> Any:  # noqa: ANN401
        h, w = array.shape[:2]
        data = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
        return self.t[IMAGE](
            header=header,
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )

    def compressed_png(self, header: Any, color: npt.NDArray[np.uint8]) -> Any:  # noqa: ANN401
        import cv2

        gray = color.ndim == 2
        ok, buf = cv2.imencode(".png", color if gray else cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        if not ok:
            raise SourceError("cannot PNG-encode a colour image")
        fmt = "mono8; png compressed mono8" if gray else "rgb8; png compressed bgr8"
        return self.t[COMPRESSED](header=header, format=fmt, data=buf.reshape(-1))

    def camera_info(self, header: Any, intr: Intrinsics) -> Any:  # noqa: ANN401
        P = np.zeros((3, 4))
        P[:, :3] = intr.K
        name = str.upper if self.ros1 else str.lower
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        mats = {
            "D": np.zeros(5),
            "K": intr.K.reshape(-1),
            "R": np.eye(3).reshape(-1),
            "P": P.reshape(-1),
        }
        return self.t[CAMERA_INFO](
            header=header,
            height=intr.height,
            width=intr.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **{name(k): v for k, v in mats.items()},
        )

    def _tq(self, T: npt.NDArray[np.float64]) -> tuple[Any, Any]:  # noqa: ANN401
        t, q = pose_to_tq(T)
        quat = self.t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        return (float(t[0]), float(t[1]), float(t[2])), quat

    def pose_stamped(self, header: Any, T: npt.NDArray[np.float64]) -> Any:  # noqa: ANN401
        (x, y, z), quat = self._tq(T)
        pose = self.t["geometry_msgs/msg/Pose"](
            position=self.t["geometry_msgs/msg/Point"](x=x, y=y, z=z), orientation=quat
        )
        return self.t[POSE_STAMPED](header=header, pose=pose)

    def tf(self, header: Any, child: str, T: npt.NDArray[np.float64]) -> Any:  # noqa: ANN401
        (x, y, z), quat = self._tq(T)
        transform = self.t["geometry_msgs/msg/Transform"](
            translation=self.t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=quat
        )
        stamped = self.t["geometry_msgs/msg/TransformStamped"](
            header=header, child_frame_id=child, transform=transform
        )
        return self.t[TF_MESSAGE](transforms=[stamped])


def write_rosbag(
    path: str | Path,
    frames: Iterable[RGBDFrame],
    version: Literal["ros1", "ros2"],
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
    depth_encoding: Literal["16UC1", "32FC1"] = "32FC1",
    compressed_color: bool = False,
    pose_source: Literal["pose", "tf"] = "pose",
    cfg: SourceConfig | None = None,
) -> int:
    """Write frames as a ROS1 ``.bag`` file or a ROS2 bag folder; returns the number written.

    Per frame: colour (rgb8/mono8 Image, or a png CompressedImage), depth Image, CameraInfo and the
    pose (PoseStamped on ``pose_topic``, or a TFMessage ``tf_parent`` -> ``tf_child`` on /tf), each
    with the frame stamp as header stamp and bag time. Topics, ``depth_scale`` (16UC1, default mm)
    and ``T_SC`` come from ``cfg`` (defaults when None); the pose written is T_world_cam @ inv(T_SC),
    so reading with the same config gives the frames back.
    """
    # 1. Check arguments
    cfg = cfg or SourceConfig()
    path = Path(path)
    if version not in ("ros1", "ros2"):
        raise SourceError(f"version must be 'ros1' or 'ros2', got {version!r}")
    if storage not in ("sqlite3", "mcap"):
        raise SourceError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}")
    if depth_encoding not in DEPTH_ENCODINGS:
        raise SourceError(f"depth_encoding must be 16UC1 or 32FC1, got {depth_encoding!r}")
    if pose_source not in ("pose", "tf"):
        raise SourceError(f"pose_source must be 'pose' or 'tf', got {pose_source!r}")
    pose_topic = cfg.pose_topic if pose_source == "pose" else "/tf"
    topics = (cfg.color_topic, cfg.depth_topic, cfg.camera_info_topic, pose_topic)
    if len(set(topics)) != len(topics):
        raise SourceError(
            f"colour, depth, camera info and pose topics must differ, got {', '.join(topics)}"
        )
    if path.exists():
        raise SourceError(f"{path} exists; write_rosbag does not overwrite")
    ros1 = version == "ros1"
    if ros1 and path.suffix != ".bag":
        raise SourceError(f"a ROS1 bag path must end in .bag, got {path}")
    scale = cfg.depth_scale or DEPTH_SCALE
    T_CS = inv_T(np.asarray(cfg.T_SC, dtype=np.float64).reshape(4, 4)) if cfg.T_SC else np.eye(4)

    # 2. Open the bag with the four connections
    ts = _writer_typestore(ros1)
    build = _Messages(ts, ros1)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer: Any = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=8, storage_plugin=plugin)
    color_type = COMPRESSED if compressed_color else IMAGE
    pose_type = POSE_STAMPED if pose_source == "pose" else TF_MESSAGE
    n = 0
    with writer:
        conns = {
            "color": (writer.add_connection(cfg.color_topic, color_type, typestore=ts), color_type),
            "depth": (writer.add_connection(cfg.depth_topic, IMAGE, typestore=ts), IMAGE),
            "info": (
                writer.add_connection(cfg.camera_info_topic, CAMERA_INFO, typestore=ts),
                CAMERA_INFO,
            ),
            "pose": (writer.add_connection(pose_topic, pose_type, typestore=ts), pose_type),
        }

        def put(kind: str, msg: Any, stamp: int) -> None:  # noqa: ANN401
            con, msgtype = conns[kind]
            writer.write(con, stamp, serialize(msg, msgtype))

        # 3. One message per topic per frame, pose first
        for f in frames:
            stamp = int(f.stamp_ns)
            if stamp < 0:
                raise SourceError(
                    f"frame {f.seq}: ROS time cannot be negative, got stamp_ns={stamp}"
                )
            hdr = build.header(stamp, f.frame_id, n)
            T_world_S = f.T_world_cam @ T_CS
            if pose_source == "pose":
                put(
                    "pose",
                    build.pose_stamped(build.header(stamp, cfg.tf_parent, n), T_world_S),
                    stamp,
                )
            else:
                put(
                    "pose",
                    build.tf(build.header(stamp, cfg.tf_parent, n), cfg.tf_child, T_world_S),
                    stamp,
                )
            put("info", build.camera_info(hdr, f.intrinsics), stamp)
            if compressed_color:
                put("color", build.compressed_png(hdr, f.color), stamp)
            else:
                put("color", build.image(hdr, f.color, "mono8" if f.is_gray else "rgb8"), stamp)
            if depth_encoding == "32FC1":
                depth = f.depth.astype("<f4")
            else:
                raw = np.rint(f.depth.astype(np.float64) * scale)
                if raw.max(initial=0) > 65535:
                    raise SourceError(
                        f"frame {f.seq}: depth {raw.max() / scale:.2f} m does not fit 16UC1 at "
                        f"{scale:g} units per metre (max {65535 / scale:.2f} m)"
                    )
                depth = raw.astype("<u2")
            put("depth", build.image(hdr, depth, depth_encoding), stamp)
            n += 1
    return n


def looks_like(path: Path) -> bool:
    """A ROS1 bag, a bare rosbag2 SQLite file, or a rosbag2 folder (bare .mcap is told apart by profile)."""
    if path.is_file():
        return path.suffix in (".bag", ".db3")
    return path.is_dir() and (path / "metadata.yaml").is_file()
