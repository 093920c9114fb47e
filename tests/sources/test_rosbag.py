"""ROS bag reader/writer: round trips through every bag flavour, raw encodings, malformed bags.

Good bags come from ``write_rosbag``; malformed and unusual ones are written here straight with
rosbags (ROS2 HUMBLE types, SQLite storage), independently of the module's writer.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from gsfix_online.core.se3 import inv_T, look_at, pose_to_tq
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.sources import open_source, rosbag
from gsfix_online.sources.base import SourceError
from gsfix_online.sources.config import CameraConfig, SourceConfig
from gsfix_online.sources.rosbag import RosbagReader, looks_like, write_rosbag

W, H, N = 40, 30, 10
T0_NS = 1_700_000_000_123_456_789
DT_NS = 33_333_333  # 30 Hz
INTR = Intrinsics(50.0, 52.0, 19.5, 14.5, W, H)
CAMERA = CameraConfig(fx=50.0, fy=52.0, cx=19.5, cy=14.5)  # = INTR, for bags without CameraInfo

# Tolerances: colour and stamps are exact everywhere. 16UC1 at 1000/m rounds to half a millimetre,
# plus float32 division (< 3e-7 m at 4 m).
DEPTH_ATOL = {"32FC1": 0.0, "16UC1": 0.5e-3 + 1e-6}
POSE_ATOL = 1e-6

CFG = SourceConfig()
COLOR, DEPTH, POSE = CFG.color_topic, CFG.depth_topic, CFG.pose_topic
IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


def make_frames(gray: bool = False, n: int = N) -> list[RGBDFrame]:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        color = rng.integers(0, 256, (H, W) if gray else (H, W, 3), dtype=np.uint8)
        depth = rng.uniform(0.5, 4.0, (H, W)).astype(np.float32)
        depth[rng.random((H, W)) < 0.1] = 0.0
        a = 0.2 * i
        T = look_at([2.0 * np.cos(a), 2.0 * np.sin(a), 1.0 + 0.05 * i], [0.0, 0.0, 0.5])
        frames.append(
            make_frame(color, depth, INTR, T, T0_NS + i * DT_NS, frame_id="cam_optical", seq=i)
        )
    return frames


def read_all(path: Path, **cfg: object) -> tuple[list[RGBDFrame], RosbagReader]:
    reader = RosbagReader(path, SourceConfig(**cfg))  # type: ignore[arg-type]
    return list(reader), reader


def assert_same(out: list[RGBDFrame], ref: list[RGBDFrame], depth_atol: float) -> None:
    assert len(out) == len(ref)
    for a, b in zip(out, ref, strict=True):
        assert a.stamp_ns == b.stamp_ns
        assert a.frame_id == b.frame_id
        assert a.intrinsics == b.intrinsics
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_allclose(a.depth, b.depth, rtol=0, atol=depth_atol)
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, rtol=0, atol=POSE_ATOL)


# --------------------------------------------------------------------------------------------
# Round trips through write_rosbag
# --------------------------------------------------------------------------------------------

CASES = {
    "ros1-pose": dict(version="ros1"),
    "ros1-tf": dict(version="ros1", pose_source="tf"),
    "ros2-sqlite3-16UC1": dict(version="ros2", depth_encoding="16UC1"),
    "ros2-mcap": dict(version="ros2", storage="mcap"),
    "ros2-tf-mono8": dict(version="ros2", pose_source="tf", gray=True),
    "ros1-png": dict(version="ros1", compressed_color=True),
    "ros2-png-mono8": dict(version="ros2", compressed_color=True, gray=True),
}


@pytest.mark.parametrize("case", CASES)
def test_round_trip(tmp_path: Path, case: str) -> None:
    kw = dict(CASES[case])
    frames = make_frames(gray=bool(kw.pop("gray", False)))
    path = tmp_path / ("x.bag" if kw["version"] == "ros1" else "x")
    assert write_rosbag(path, frames, **kw) == N  # type: ignore[arg-type]
    assert looks_like(path)
    out, reader = read_all(path)
    assert len(reader) == N
    assert reader.pose_mode == kw.get("pose_source", "pose")
    assert reader.stats.as_dict() == {
        "frames": N,
        "depth_pixels_invalidated": 0,
        "unpaired": 0,
        "without_pose": 0,
        "out_of_order": 0,
        "duplicate_stamps": 0,
        "frames_lost": 0,
    }
    assert [f.seq for f in out] == list(range(N))
    assert_same(out, frames, DEPTH_ATOL[str(kw.get("depth_encoding", "32FC1"))])


@pytest.mark.parametrize("storage,suffix", [("sqlite3", ".db3"), ("mcap", ".mcap")])
def test_bare_storage_file(tmp_path: Path, storage: str, suffix: str) -> None:
    frames = make_frames()
    write_rosbag(tmp_path / "x", frames, version="ros2", storage=storage)  # type: ignore[arg-type]
    (bare,) = (tmp_path / "x").glob(f"*{suffix}")
    out, reader = read_all(bare)
    assert len(reader) == N
    assert_same(out, frames, 0.0)


def test_open_source_auto_detects_bags(tmp_path: Path) -> None:
    frames = make_frames(n=3)
    write_rosbag(tmp_path / "a.bag", frames, version="ros1")
    write_rosbag(tmp_path / "b", frames, version="ros2")
    for p in (tmp_path / "a.bag", tmp_path / "b"):
        reader = open_source(SourceConfig(), p)
        assert isinstance(reader, RosbagReader)
        assert len(list(reader)) == 3
    assert not looks_like(tmp_path)


def test_T_SC_and_topics_round_trip(tmp_path: Path) -> None:
    T_SC = look_at([0.1, 0.0, 0.2], [1.0, 0.3, 0.2])
    cfg = dict(
        T_SC=T_SC.reshape(-1).tolist(),
        color_topic="/c",
        depth_topic="/d",
        camera_info_topic="/i",
        tf_parent="odom",
        tf_child="base_link",
    )
    frames = make_frames(n=4)
    write_rosbag(
        tmp_path / "x.bag", frames, version="ros1", pose_source="tf", cfg=SourceConfig(**cfg)
    )
    out, _ = read_all(tmp_path / "x.bag", **cfg)
    assert_same(out, frames, 0.0)
    # Without T_SC the reader gives the tracked body pose T_world_S = T_world_cam @ inv(T_SC).
    body, _ = read_all(tmp_path / "x.bag", **{**cfg, "T_SC": []})
    for b, f in zip(body, frames, strict=True):
        np.testing.assert_allclose(b.T_world_cam, f.T_world_cam @ inv_T(T_SC), atol=POSE_ATOL)


def test_stride_and_max_frames(tmp_path: Path) -> None:
    frames = make_frames()
    write_rosbag(tmp_path / "x", frames, version="ros2")
    out, _ = read_all(tmp_path / "x", stride=3, max_frames=3)
    assert [f.stamp_ns for f in out] == [frames[i].stamp_ns for i in (0, 3, 6)]


# --------------------------------------------------------------------------------------------
# Bags written straight with rosbags
# --------------------------------------------------------------------------------------------

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def _header(stamp: int) -> object:
    t = T["builtin_interfaces/msg/Time"](sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
    return T["std_msgs/msg/Header"](stamp=t, frame_id="cam_optical")


def _image(stamp: int, encoding: str, arr: np.ndarray, pad: int = 0, big: bool = False) -> object:
    """Image with ``pad`` bytes of row padding, in big- or little-endian byte order."""
    h, w = arr.shape[:2]
    rows = (
        np.ascontiguousarray(arr.astype(arr.dtype.newbyteorder(">" if big else "<")))
        .view(np.uint8)
        .reshape(h, -1)
    )
    data = np.concatenate([rows, np.full((h, pad), 7, np.uint8)], axis=1).reshape(-1)
    return T[IMAGE](
        header=_header(stamp),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(big),
        step=rows.shape[1] + pad,
        data=data,
    )


def _pose(stamp: int, T_world: np.ndarray) -> object:
    t, q = pose_to_tq(T_world)
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    return T[POSE_STAMPED](header=_header(stamp), pose=pose)


ToMsg = Callable[[RGBDFrame], tuple[str, object]]


def write_raw(
    path: Path,
    frames: list[RGBDFrame],
    color: ToMsg | None = None,
    depth: ToMsg | None = None,
    depth_dt_ns: int = 0,
    depth_bag_delay_ns: int = 0,
    pose_from: int = 0,
    poses: bool = True,
) -> Path:
    """A bag without CameraInfo; ``color``/``depth`` make (msgtype, message), default rgb8 / 32FC1.

    ``depth_dt_ns`` shifts the depth header stamps, ``depth_bag_delay_ns`` only their bag time.
    """
    color = color or (lambda f: (IMAGE, _image(f.stamp_ns, "rgb8", f.color)))
    depth = depth or (lambda f: (IMAGE, _image(f.stamp_ns + depth_dt_ns, "32FC1", f.depth)))
    msgs = []
    for i, f in enumerate(frames):
        if poses and i >= pose_from:
            msgs.append((POSE, POSE_STAMPED, f.stamp_ns, _pose(f.stamp_ns, f.T_world_cam)))
        (ctype, cmsg), (dtype, dmsg) = color(f), depth(f)
        msgs.append((COLOR, ctype, f.stamp_ns, cmsg))
        msgs.append((DEPTH, dtype, f.stamp_ns + depth_dt_ns + depth_bag_delay_ns, dmsg))
    with Writer(path, version=8) as w:
        conns: dict[str, object] = {}
        for topic, msgtype, stamp, msg in sorted(msgs, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=TS)
            w.write(conns[topic], stamp, TS.serialize_cdr(msg, msgtype))
    return path


COLOR_WIRE = {  # encoding -> RGB [H, W, 3] to what goes on the wire
    "rgb8": lambda c: c,
    "bgr8": lambda c: c[:, :, ::-1],
    "rgba8": lambda c: np.dstack([c, np.full(c.shape[:2], 200, np.uint8)]),
    "bgra8": lambda c: np.dstack([c[:, :, ::-1], np.full(c.shape[:2], 200, np.uint8)]),
}


@pytest.mark.parametrize("encoding", [*COLOR_WIRE, "mono8"])
def test_raw_color_encodings_with_row_padding(tmp_path: Path, encoding: str) -> None:
    frames = make_frames(gray=encoding == "mono8", n=3)
    wire = COLOR_WIRE.get(encoding, lambda c: c)
    path = write_raw(
        tmp_path / "x",
        frames,
        color=lambda f: (IMAGE, _image(f.stamp_ns, encoding, wire(f.color), pad=5)),
    )
    out, _ = read_all(path, camera=CAMERA)
    assert_same(out, frames, 0.0)


def _depth_16(f: RGBDFrame, scale: float) -> np.ndarray:
    return np.rint(f.depth.astype(np.float64) * scale).astype(np.uint16)


def _compressed_depth(f: RGBDFrame) -> tuple[str, object]:
    ok, png = cv2.imencode(".png", _depth_16(f, 1000.0))
    assert ok
    data = np.frombuffer(struct.pack("<iff", 0, 0.0, 0.0) + png.tobytes(), np.uint8)
    return COMPRESSED, T[COMPRESSED](
        header=_header(f.stamp_ns), format="16UC1; compressedDepth png", data=data
    )


DEPTH_WIRE = {  # name -> (frame to (msgtype, msg), depth_scale config, atol)
    "16UC1-bigendian-padded": (
        lambda f: (IMAGE, _image(f.stamp_ns, "16UC1", _depth_16(f, 1000.0), pad=6, big=True)),
        0.0,
        DEPTH_ATOL["16UC1"],
    ),
    "16UC1-scale-5000": (
        lambda f: (IMAGE, _image(f.stamp_ns, "16UC1", _depth_16(f, 5000.0))),
        5000.0,
        0.1e-3 + 1e-6,
    ),
    "32FC1-bigendian-padded": (
        lambda f: (IMAGE, _image(f.stamp_ns, "32FC1", f.depth, pad=4, big=True)),
        0.0,
        0.0,
    ),
    "compressedDepth-png": (_compressed_depth, 0.0, DEPTH_ATOL["16UC1"]),
}


@pytest.mark.parametrize("name", DEPTH_WIRE)
def test_raw_depth_encodings(tmp_path: Path, name: str) -> None:
    to_msg, scale, atol = DEPTH_WIRE[name]
    frames = make_frames(n=3)
    out, _ = read_all(
        write_raw(tmp_path / "x", frames, depth=to_msg), camera=CAMERA, depth_scale=scale
    )
    assert_same(out, frames, atol)


def test_approximate_pairing_within_tolerance(tmp_path: Path) -> None:
    frames = make_frames()
    out, reader = read_all(write_raw(tmp_path / "x", frames, depth_dt_ns=-5_000_000), camera=CAMERA)
    assert [f.stamp_ns for f in out] == [f.stamp_ns for f in frames]  # colour stamps are kept
    assert reader.stats.unpaired == 0


def test_late_depth_waits_in_a_bounded_queue(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Depth reaches the bag 200 ms (6 frames) after its colour partner: the colour queue holds it.
    frames = make_frames()
    path = write_raw(tmp_path / "x", frames, depth_bag_delay_ns=200_000_000)
    out, reader = read_all(path, camera=CAMERA)
    assert_same(out, frames, 0.0)
    monkeypatch.setattr(rosbag, "MAX_QUEUE", 3)  # too short to wait 6 frames: colours are dropped
    out, reader = read_all(path, camera=CAMERA)
    assert reader.stats.unpaired > 0
    assert 2 * len(out) + reader.stats.unpaired == 2 * N  # every message is paired or counted


# --------------------------------------------------------------------------------------------
# Malformed input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["junk.bag", "junk.db3"])
def test_not_a_bag(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_bytes(b"not a bag" * 10)
    with pytest.raises(SourceError, match=f"cannot open .*{name}"):
        RosbagReader(tmp_path / name, SourceConfig())


def test_missing_color_topic_names_it_and_lists_topics(tmp_path: Path) -> None:
    write_rosbag(tmp_path / "x", make_frames(n=2), version="ros2")
    with pytest.raises(
        SourceError, match=r"color_topic /nope is not in the bag; topics: .*aligned_depth_to_color"
    ):
        RosbagReader(tmp_path / "x", SourceConfig(color_topic="/nope"))


def test_unsupported_encoding_is_one_line(tmp_path: Path) -> None:
    frames = make_frames(n=2)

    def yuv(f: RGBDFrame) -> tuple[str, object]:
        return IMAGE, _image(f.stamp_ns, "yuv422", f.color[:, :, :2].copy())

    reader = RosbagReader(write_raw(tmp_path / "x", frames, color=yuv), SourceConfig(camera=CAMERA))
    with pytest.raises(SourceError, match="unsupported image encoding 'yuv422'") as exc:
        list(reader)
    assert "\n" not in str(exc.value)


def test_data_shorter_than_height_times_step(tmp_path: Path) -> None:
    def short(f: RGBDFrame) -> tuple[str, object]:
        msg = _image(f.stamp_ns, "rgb8", f.color, pad=2)
        msg.data = msg.data[:-10]
        return IMAGE, msg

    reader = RosbagReader(
        write_raw(tmp_path / "x", make_frames(n=2), color=short), SourceConfig(camera=CAMERA)
    )
    with pytest.raises(SourceError, match=r"expected height\*step = 30\*122 = 3660"):
        list(reader)


def test_no_poses(tmp_path: Path) -> None:
    frames = make_frames(n=2)
    path = write_raw(tmp_path / "x", frames, poses=False)
    with pytest.raises(SourceError, match="no poses: neither pose_topic /pose nor /tf"):
        RosbagReader(path, SourceConfig(camera=CAMERA))
    with pytest.raises(SourceError, match="pose_topic /pose is not in the bag"):
        RosbagReader(path, SourceConfig(camera=CAMERA, pose_source="pose"))
    with pytest.raises(SourceError, match="poses are required"):
        RosbagReader(path, SourceConfig(camera=CAMERA, pose_source="none"))
    write_rosbag(tmp_path / "tf.bag", frames, version="ros1", pose_source="tf")
    with pytest.raises(
        SourceError, match=r"no transform world -> camera_link .* seen: map -> camera_link"
    ):
        RosbagReader(tmp_path / "tf.bag", SourceConfig(tf_parent="world"))


def test_camera_config_overrides_camera_info(tmp_path: Path) -> None:
    write_rosbag(tmp_path / "x", make_frames(n=2), version="ros2")
    cam = CameraConfig(fx=60.0, fy=61.0, cx=20.0, cy=15.0)
    out, _ = read_all(tmp_path / "x", camera=cam)
    assert out[0].intrinsics == Intrinsics(60.0, 61.0, 20.0, 15.0, W, H)


def test_missing_camera_info_needs_config(tmp_path: Path) -> None:
    path = write_raw(tmp_path / "x", make_frames(n=2))
    with pytest.raises(SourceError, match="no usable camera info on /camera/color/camera_info"):
        RosbagReader(path, SourceConfig())


def test_stamps_too_far_apart_are_unpaired(tmp_path: Path) -> None:
    frames = make_frames()
    out, reader = read_all(
        write_raw(tmp_path / "x", frames, depth_dt_ns=500_000_000), camera=CAMERA
    )
    assert out == []
    assert reader.stats.unpaired == 2 * N
    assert reader.stats.without_pose == 0


def test_frames_before_first_pose_are_counted(tmp_path: Path) -> None:
    frames = make_frames()
    out, reader = read_all(write_raw(tmp_path / "x", frames, pose_from=3), camera=CAMERA)
    assert reader.stats.without_pose == 3
    assert reader.stats.unpaired == 0
    assert_same(out, frames[3:], 0.0)
