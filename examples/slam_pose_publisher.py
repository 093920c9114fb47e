"""How a SLAM front end (OKVIS2, ORB-SLAM3, ...) sends poses to gsfix-online. Needs only pyzmq and numpy.

Each pose is one ZeroMQ multipart message on a PUB socket connected to the ``associate`` node's
``listen: {poses: ...}`` endpoint (``gsfix-online launch GRAPH --emit DIR`` prints the addresses):

    frame 0  b"pose/<name>\\x00"                    topic, NUL-terminated
    frame 1  msgpack map {"v": 1, "type": "pose", "seq": n, "stamp_ns": t, "frame_id": "imu",
             "meta": {"parent": "world", "child": "imu"},
             "arrays": [{"name": "T_world_body", "dtype": "float64", "shape": [4, 4], "units": "m"}]}
    frame 2  the 4x4 pose T_world_body as 16 little-endian float64, row-major

``T_world_body`` is the pose of the tracked frame (IMU or camera) in the world; the associate node
multiplies it by its configured ``T_SC``. ``stamp_ns`` is the sensor time of the pose, on the same
clock as the camera frames. The msgpack encoder below covers what the header needs, so the
example has no dependency beyond pyzmq and numpy.

    python examples/slam_pose_publisher.py tcp://127.0.0.1:46003 --rate 200 --seconds 10
"""

from __future__ import annotations

import argparse
import struct
import time

import numpy as np
import zmq


def packb(obj: object) -> bytes:
    """Minimal msgpack: None, bool, int, float, str, list, dict."""
    if obj is None:
        return b"\xc0"
    if obj is True or obj is False:
        return b"\xc3" if obj else b"\xc2"
    if isinstance(obj, int):
        if 0 <= obj < 128:
            return bytes([obj])
        if -32 <= obj < 0:
            return struct.pack("b", obj)
        return b"\xd3" + struct.pack(">q", obj) if obj < 0 else b"\xcf" + struct.pack(">Q", obj)
    if isinstance(obj, float):
        return b"\xcb" + struct.pack(">d", obj)
    if isinstance(obj, str):
        data = obj.encode()
        if len(data) < 32:
            return bytes([0xA0 | len(data)]) + data
        return b"\xda" + struct.pack(">H", len(data)) + data
    if isinstance(obj, (list, tuple)):
        head = bytes([0x90 | len(obj)]) if len(obj) < 16 else b"\xdc" + struct.pack(">H", len(obj))
        return head + b"".join(packb(v) for v in obj)
    if isinstance(obj, dict):
        head = bytes([0x80 | len(obj)]) if len(obj) < 16 else b"\xde" + struct.pack(">H", len(obj))
        return head + b"".join(packb(k) + packb(v) for k, v in obj.items())
    raise TypeError(f"cannot encode {type(obj).__name__}")


def pose_message(
    seq: int, stamp_ns: int, T_world_body: np.ndarray, name: str = "slam", child: str = "imu"
) -> list[bytes]:
    T = np.ascontiguousarray(T_world_body, dtype="<f8")
    assert T.shape == (4, 4)
    header = {
        "v": 1,
        "type": "pose",
        "seq": seq,
        "stamp_ns": stamp_ns,
        "frame_id": child,
        "meta": {"parent": "world", "child": child},
        "arrays": [{"name": "T_world_body", "dtype": "float64", "shape": [4, 4], "units": "m"}],
    }
    return [f"pose/{name}".encode() + b"\x00", packb(header), T.tobytes()]


def main() -> None:
    ap = argparse.ArgumentParser(description="publish a circular test trajectory as SLAM poses")
    ap.add_argument(
        "address", help="the associate node's listen endpoint, e.g. tcp://127.0.0.1:46003"
    )
    ap.add_argument("--rate", type=float, default=200.0, help="poses per second")
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    sock = zmq.Context.instance().socket(zmq.PUB)
    sock.connect(args.address)
    t0 = time.time_ns()
    for seq in range(int(args.rate * args.seconds)):
        stamp = t0 + int(seq * 1e9 / args.rate)
        a = 2 * np.pi * seq / (args.rate * 10)  # one circle per 10 s, camera looking outward
        T = np.eye(4)
        T[:3, :3] = [
            [np.cos(a), 0, np.sin(a)],
            [np.sin(a), 0, -np.cos(a)],
            [0, 1, 0],
        ]  # z out, y down
        T[:3, 3] = [np.cos(a), np.sin(a), 1.0]
        sock.send_multipart(pose_message(seq, stamp, T))
        time.sleep(max(0.0, (stamp - time.time_ns()) * 1e-9))
    sock.close(linger=1000)


if __name__ == "__main__":
    main()
