"""MapClient: ask a map server (``gsfix-online serve RUN_DIR``) for its maps, renders and repairs.

Example::

    from gsfix_online import MapClient

    c = MapClient("tcp://127.0.0.1:5590", timeout_s=10.0)
    for m in c.maps():                       # MapInfo(name, version, gaussians, has_mesh, views)
        print(m)
    v = c.views()[0]                         # a keyframe or a repaired view of the run
    r = c.render(v["T_world_cam"], v["K"], v["width"], v["height"], source="both")
    r.color, r.mesh, r.alpha, r.depth_m      # uint8 [H, W, 3], uint8 [H, W, 3], float32 [H, W] x2
    out = c.repair(v["T_world_cam"], v["K"], 320, 240, progress=lambda f, t: print(f, t))
    out.image, out.map_version, out.reason   # the repair; the map's version after distilling it
    open("map.ply", "wb").write(c.splats())  # the standard 3DGS PLY (the new version after repair)

Every call takes ``timeout_s`` (default: the client's). A call raises :class:`MapServerError`
when the server answered with a reason (a bad pose, an unknown map, a size above the server's
limit, a repair already running: ``busy``), and :class:`MapTimeoutError` when no answer came in
time or the server went away during the call; both are :class:`MapClientError`. For
:meth:`MapClient.repair`, ``timeout_s`` bounds the silence between the server's messages: it
reports progress at least every second while it works, so a long repair finishes and a dead
server is noticed. After a timeout the client stays usable; a late answer is dropped.

Protocol (ZeroMQ; the client is a DEALER, the server a ROUTER): every message is the frames
``[PROTOCOL, header, *buffers]``. The header is a msgpack map; requests carry ``id`` (int),
``op`` (str), ``args`` (map of scalars and flat lists) and ``timeout_s``; answers carry the
request's ``id``, ``status`` (``ok`` | ``progress`` | ``error``), ``result`` (map),
``error`` (one line) and ``kind`` (``bad_request``, ``unknown_map``, ``too_large``,
``not_found``, ``busy``, ``unknown_op``, ``failed``). Both list their buffers in ``arrays``:
``{"name", "dtype", "shape"}``, where dtype ``bytes`` is a file's raw bytes and any other is a
little-endian NumPy dtype of :data:`gsfix_online.runtime.schema.WIRE_DTYPES`. Nothing is
pickled. One client per thread: a MapClient is not thread-safe.
"""

from __future__ import annotations

import ipaddress
import itertools
import logging
import math
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import numpy.typing as npt

from gsfix_online.runtime.schema import DTYPE_NAMES, WIRE_DTYPES

logger = logging.getLogger(__name__)

PROTOCOL = b"gsfix-map/1"
DEFAULT_ADDRESS = "tcp://127.0.0.1:5590"
MAX_HEADER_BYTES = 1 << 20
BYTES = "bytes"  # the dtype of a raw file buffer

Progress = Callable[[float, str], None]  # (fraction in [0, 1], what the server is doing)


class MapClientError(RuntimeError):
    """A map-server call failed."""


class MapServerError(MapClientError):
    """The server answered with a one-line reason; ``kind`` names the class of error."""

    def __init__(self, message: str, kind: str = "failed") -> None:
        super().__init__(message)
        self.kind = kind


class MapTimeoutError(MapClientError):
    """No answer within the deadline, or the server went away during the call."""


class MapAddressError(MapClientError, ValueError):
    """An address or a timeout the client cannot use (a one-line reason with the expected form)."""


def check_address(address: Any) -> tuple[str, int]:
    """(host, port) of a map server address ``tcp://HOST:PORT``; MapAddressError otherwise."""
    form = "expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:5590"
    if not isinstance(address, str):
        raise MapAddressError(f"address must be a string ({form}), got {type(address).__name__}")
    scheme, sep, rest = address.partition("://")
    host, colon, port = rest.rpartition(":")
    host = host.strip("[]")  # tcp://[::1]:5590
    if not sep or scheme != "tcp" or not colon or not host or not port.isdigit():
        raise MapAddressError(f"address must look like tcp://HOST:PORT ({form}), got {address!r}")
    if not 0 < int(port) < 65536:
        raise MapAddressError(f"address port must be in 1..65535, got {address!r}")
    return host, int(port)


def check_timeout(timeout_s: Any) -> float:
    """A positive, finite number of seconds; MapAddressError in one line otherwise."""
    try:
        t = float(timeout_s)
    except (TypeError, ValueError):
        t = math.nan
    if not (t > 0 and math.isfinite(t)):
        raise MapAddressError(
            f"timeout_s must be positive and finite (seconds; a repair reports progress, so a "
            f"long one needs no long timeout), got {timeout_s!r}"
        )
    return t


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _refused(host: str, port: int) -> bool:
    """Whether a TCP connection to ``host:port`` is refused right now (nothing listens)."""
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return False
    except ConnectionRefusedError:
        return True
    except OSError:  # unreachable, timed out: not known to be refused, wait as usual
        return False


class ProtocolError(ValueError):
    """Frames that do not follow the map-server protocol."""


# ----------------------------------------------------------------------------------------------
# Frames (shared with the server: nodes/map_server.py)
# ----------------------------------------------------------------------------------------------


def pack(header: dict[str, Any], buffers: dict[str, Any] | None = None) -> list[Any]:
    """``[PROTOCOL, msgpack(header + arrays), *buffers]``; a buffer is bytes or an ndarray."""
    frames: list[Any] = []
    descs = []
    for name, buf in (buffers or {}).items():
        if isinstance(buf, bytes | bytearray | memoryview):
            descs.append({"name": name, "dtype": BYTES, "shape": [len(buf)]})
            frames.append(buf)
        else:
            a = np.ascontiguousarray(buf)
            name_of = DTYPE_NAMES[a.dtype.newbyteorder("<")]  # a KeyError: not a wire dtype
            a = a.astype(WIRE_DTYPES[name_of], copy=False)
            descs.append({"name": name, "dtype": name_of, "shape": list(a.shape)})
            frames.append(a.data)
    head = msgpack.packb({**header, "arrays": descs}, use_bin_type=True)
    return [PROTOCOL, head, *frames]


def unpack(frames: Sequence[Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(header, buffers by name) of ``[PROTOCOL, header, *buffers]``, or a ProtocolError."""
    if len(frames) < 2 or bytes(frames[0]) != PROTOCOL:
        raise ProtocolError(f"not a {PROTOCOL.decode()} message")
    raw = bytes(frames[1])
    if len(raw) > MAX_HEADER_BYTES:
        raise ProtocolError(f"header of {len(raw)} bytes exceeds {MAX_HEADER_BYTES}")
    try:
        header = msgpack.unpackb(raw, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types for malformed input
        raise ProtocolError(f"header is not msgpack ({type(exc).__name__})") from None
    if not isinstance(header, dict) or not isinstance(header.get("arrays", []), list):
        raise ProtocolError("header must be a map with an 'arrays' list")
    descs = header.pop("arrays", [])
    if len(descs) != len(frames) - 2:
        raise ProtocolError(f"header lists {len(descs)} buffers, {len(frames) - 2} came")
    out: dict[str, Any] = {}
    for d, frame in zip(descs, frames[2:], strict=True):
        if not isinstance(d, dict) or not isinstance(d.get("name"), str):
            raise ProtocolError("every array needs a name, dtype and shape")
        buf = frame.buffer if hasattr(frame, "buffer") else memoryview(frame)
        shape = d.get("shape")
        if not isinstance(shape, list) or not all(isinstance(s, int) and s >= 0 for s in shape):
            raise ProtocolError(f"array {d['name']}: shape must be non-negative ints")
        if d.get("dtype") == BYTES:
            out[d["name"]] = bytes(buf)
            continue
        if d.get("dtype") not in WIRE_DTYPES:
            raise ProtocolError(f"array {d['name']}: dtype {d.get('dtype')!r} is not allowed")
        dtype = WIRE_DTYPES[d["dtype"]]
        if int(np.prod(shape)) * dtype.itemsize != buf.nbytes:
            raise ProtocolError(f"array {d['name']}: {buf.nbytes} bytes do not fit {shape}")
        out[d["name"]] = np.frombuffer(buf, dtype).reshape(shape)
    return header, out


# ----------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MapInfo:
    name: str
    version: int  # 0 as loaded; +1 for every repair distilled into it
    gaussians: int
    has_mesh: bool
    views: int  # keyframes and repaired views of the run (see MapClient.views)


@dataclass(frozen=True, eq=False)
class Render:
    color: npt.NDArray[np.uint8] | None  # [H, W, 3] 3DGS render (source gs or both)
    mesh: npt.NDArray[np.uint8] | None  # [H, W, 3] mesh render, black where no surface
    alpha: npt.NDArray[np.float32] | None  # [H, W] 3DGS opacity (gs or both)
    depth_m: npt.NDArray[np.float32] | None  # [H, W] z-depth, m: the mesh's when rendered, 0 =
    #                                          no surface; else the 3DGS map's expected depth
    # [H, W] beside the 3DGS colour: 255 x the share of each pixel's colour that Gaussians grown
    # from repaired views make (0 observed, 255 synthesised); None without a 3DGS render
    provenance: npt.NDArray[np.uint8] | None = None


@dataclass(frozen=True, eq=False)
class Repaired:
    image: npt.NDArray[np.uint8]  # [H, W, 3] the repair (GSFixer, the run's fallback applied)
    map_version: int | None  # the map's version with the repair distilled in; None if not
    reason: str  # which model and fallback made it, and what was distilled


def _numbers(x: Any, name: str) -> list[float]:
    try:
        return [float(v) for v in np.asarray(x, dtype=np.float64).ravel()]
    except (TypeError, ValueError):
        raise MapClientError(f"{name} must be numbers, got {type(x).__name__}") from None


# ----------------------------------------------------------------------------------------------
# Client
# ----------------------------------------------------------------------------------------------


class MapClient:
    """A connection to one map server; see the module docstring for the calls and errors."""

    def __init__(
        self,
        address: str = DEFAULT_ADDRESS,
        timeout_s: float = 10.0,
        connect_timeout_s: float | None = 1.0,
    ) -> None:
        """``connect_timeout_s``: how long nothing may listen on a loopback address (a refused
        connection) before a call fails, instead of waiting out ``timeout_s``; a client that
        starts its server itself gives it the server's start-up time, or None to wait."""
        self._host, self._port = check_address(address)
        self.address = address
        self.timeout_s = check_timeout(timeout_s)
        self.connect_timeout_s = (
            None if connect_timeout_s is None else check_timeout(connect_timeout_s)
        )
        self._ids = itertools.count(1)
        self._sock: Any = None
        self._monitor: Any = None

    def __repr__(self) -> str:
        return f"MapClient({self.address!r}, timeout_s={self.timeout_s})"

    def __enter__(self) -> MapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.disable_monitor()
            self._monitor.close(linger=0)
            self._sock.close(linger=0)
            self._sock = self._monitor = None

    def _socket(self) -> Any:
        if self._sock is None:
            import zmq

            s = zmq.Context.instance().socket(zmq.DEALER)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.IMMEDIATE, 1)  # no queueing towards a server that is not there
            s.setsockopt(zmq.RECONNECT_IVL, 100)
            s.setsockopt(zmq.RECONNECT_IVL_MAX, 1000)
            s.setsockopt(zmq.HEARTBEAT_IVL, 1000)  # a silent peer counts as gone after 3 s
            s.setsockopt(zmq.HEARTBEAT_TIMEOUT, 3000)
            self._monitor = s.get_monitor_socket(zmq.EVENT_DISCONNECTED)
            s.connect(self.address)
            self._sock = s
        return self._sock

    def _call(
        self,
        op: str,
        args: dict[str, Any],
        timeout_s: float | None,
        progress: Progress | None = None,
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        import zmq

        timeout = self.timeout_s if timeout_s is None else check_timeout(timeout_s)
        sock = self._socket()
        t0 = time.monotonic()
        deadline = t0 + timeout

        def timed_out() -> MapTimeoutError:
            return MapTimeoutError(
                f"map server {self.address} did not answer {op} within {timeout:g} s "
                "(is it running?)"
            )

        # 1. Forget disconnects from before this call, then send once the server is connected.
        while self._monitor.poll(0):
            self._monitor.recv_multipart()
        rid = next(self._ids)
        frames = pack({"id": rid, "op": op, "args": args, "timeout_s": timeout})
        if not sock.poll(0, zmq.POLLOUT):
            self._wait_for_listener(deadline, op)
        if not sock.poll(max(0, int((deadline - time.monotonic()) * 1000)), zmq.POLLOUT):
            raise timed_out()
        sock.send_multipart(frames, copy=False)
        # 2. Wait for our answer; progress moves the deadline (the server is alive and working).
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._monitor, zmq.POLLIN)
        while True:
            left_ms = int((deadline - time.monotonic()) * 1000)
            events = dict(poller.poll(max(0, left_ms))) if left_ms > 0 else {}
            if sock in events:
                try:
                    header, buffers = unpack(sock.recv_multipart(copy=False))
                except ProtocolError as exc:
                    raise MapClientError(f"map server {self.address}: {exc}") from None
                if header.get("id") != rid:
                    logger.debug("dropping a late answer to request %s", header.get("id"))
                    continue
                status = header.get("status")
                if status == "progress":
                    if progress is not None:
                        r = header.get("result", {})
                        progress(float(r.get("fraction", 0.0)), str(r.get("text", "")))
                    deadline = time.monotonic() + timeout
                    continue
                if status == "error":
                    raise MapServerError(str(header.get("error")), str(header.get("kind")))
                return dict(header.get("result", {})), buffers
            if self._monitor in events:
                self._monitor.recv_multipart()
                raise MapTimeoutError(
                    f"map server {self.address} went away during {op} after "
                    f"{time.monotonic() - t0:.1f} s (did it stop?)"
                )
            if time.monotonic() >= deadline:
                raise timed_out()

    def _wait_for_listener(self, deadline: float, op: str) -> None:
        """Fail fast when nothing listens on a loopback address (a refused connection): ZeroMQ
        would retry quietly until the deadline. A server still starting gets
        ``connect_timeout_s``; other hosts are not probed (a refusal there may be a firewall's)."""
        if self.connect_timeout_s is None or not _is_loopback(self._host):
            return
        give_up = min(time.monotonic() + self.connect_timeout_s, deadline)
        while _refused(self._host, self._port):
            if time.monotonic() >= give_up:
                if give_up >= deadline:
                    return  # the caller's deadline came first: its timeout says so
                raise MapTimeoutError(
                    f"map server {self.address}: nothing listens there (connection refused for "
                    f"{self.connect_timeout_s:g} s; start one with gsfix-online serve RUN_DIR)"
                )
            time.sleep(0.05)

    # -- calls -------------------------------------------------------------------------------

    def maps(self, timeout_s: float | None = None) -> list[MapInfo]:
        """The maps the server holds, with their versions."""
        result, _ = self._call("maps", {}, timeout_s)
        return [MapInfo(**m) for m in result["maps"]]

    def stats(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Server counters: uptime_s, requests, errors, expired, by_op, maps (versions), busy."""
        result, _ = self._call("stats", {}, timeout_s)
        return result

    def mesh(
        self, map: str | None = None, fmt: str = "ply", timeout_s: float | None = None
    ) -> bytes:
        """The TSDF mesh as a PLY (the run's file) or GLB file."""
        _, buffers = self._call("mesh", {"map": map, "fmt": fmt}, timeout_s)
        return buffers["data"]

    def splats(self, map: str | None = None, timeout_s: float | None = None) -> bytes:
        """The Gaussian map as a standard 3DGS PLY: the run's file until a repair is distilled."""
        _, buffers = self._call("splats", {"map": map}, timeout_s)
        return buffers["data"]

    def views(self, map: str | None = None, timeout_s: float | None = None) -> list[dict]:
        """Cameras of the run's keyframes and views: ``{kind: keyframe | view, id, K [9],
        T_world_cam [16] (row-major, camera-to-world), width, height, images: {name: path}}``."""
        result, _ = self._call("views", {"map": map}, timeout_s)
        return list(result["views"])

    def image(self, path: str, map: str | None = None, timeout_s: float | None = None) -> bytes:
        """A PNG of the run folder by its path relative to the folder (see views())."""
        _, buffers = self._call("image", {"map": map, "path": path}, timeout_s)
        return buffers["data"]

    def _view_args(self, T_world_cam: Any, K: Any, width: int, height: int, map: str | None):
        return {
            "map": map,
            "T_world_cam": _numbers(T_world_cam, "T_world_cam"),
            "K": _numbers(K, "K"),
            "width": width,
            "height": height,
        }

    def render(
        self,
        T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes (or 16 numbers)
        K: npt.ArrayLike,  # [3, 3] pixels (or 9 numbers)
        width: int,
        height: int,
        source: str = "gs",  # gs | mesh | both
        map: str | None = None,
        timeout_s: float | None = None,
    ) -> Render:
        """Render the 3DGS map, the mesh or both at a pose and intrinsics."""
        args = {**self._view_args(T_world_cam, K, width, height, map), "source": source}
        _, b = self._call("render", args, timeout_s)
        return Render(b.get("color"), b.get("mesh"), b.get("alpha"), b.get("depth_m"),
                      b.get("provenance"))  # fmt: skip

    def repair(
        self,
        T_world_cam: npt.ArrayLike,  # [4, 4] camera-to-world, OpenCV axes (or 16 numbers)
        K: npt.ArrayLike,  # [3, 3] pixels (or 9 numbers)
        width: int,
        height: int,
        map: str | None = None,
        progress: Progress | None = None,
        timeout_s: float | None = None,
    ) -> Repaired:
        """Repair a view with GSFixer and distil it into the server's map (one at a time: a
        second repair while one runs is answered ``busy``)."""
        args = self._view_args(T_world_cam, K, width, height, map)
        result, b = self._call("repair", args, timeout_s, progress)
        version = result.get("map_version")
        return Repaired(b["image"], None if version is None else int(version), result["reason"])
