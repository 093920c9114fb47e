"""Our log format: MCAP with Foxglove protobuf schemas, so Foxglove and Lichtblick open our logs.

One RGB-D frame is four messages with the same ``log_time`` (= the frame's ``stamp_ns``):

| topic                 | schema                      | content                                            |
|-----------------------|-----------------------------|----------------------------------------------------|
| ``/camera/color``     | ``foxglove.RawImage``       | ``rgb8`` or ``mono8``                               |
| ``/camera/depth``     | ``foxglove.RawImage``       | ``32FC1`` metres, 0 = invalid                       |
| ``/camera/calibration`` | ``foxglove.CameraCalibration`` | K (row-major 3x3), P, width, height, no distortion |
| ``/tf``               | ``foxglove.FrameTransform`` | parent ``world`` -> child = the image's frame_id (T_world_cam) |

The file's metadata record ``gsfix_online`` holds the log schema version. Files are chunked
(zstd). The reader goes chunk by chunk through the summary's chunk index: a chunk whose bytes
changed (CRC mismatch, zstd or record errors) is skipped, every other chunk is read, and the
frames lost with it are counted (``stats.frames_lost``) and reported in one line with their
range. A writer that crashed leaves a file without summary, which this reader still streams up
to the last complete chunk.
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from gsfix_online.core.io import atomic_path
from gsfix_online.core.se3 import R_to_quat_xyzw, make_T, quat_xyzw_to_R
from gsfix_online.core.types import Intrinsics, RGBDFrame
from gsfix_online.sources.base import FrameSource, SourceError, damaged, ns_to_seconds, to_frame
from gsfix_online.sources.pose_list import QUAT_NORM_TOL

logger = logging.getLogger(__name__)

LOG_SCHEMA_VERSION = "1"
TOPIC_COLOR = "/camera/color"
TOPIC_DEPTH = "/camera/depth"
TOPIC_CALIB = "/camera/calibration"
TOPIC_TF = "/tf"
WORLD_FRAME = "world"
_MAX_PENDING = 64  # partial frames kept while waiting for their other messages
_TOPICS = (TOPIC_COLOR, TOPIC_DEPTH, TOPIC_CALIB, TOPIC_TF)


def mcap_profile(path: Path) -> str:
    """The profile string in an MCAP file's header ('' for ours, 'ros1'/'ros2' for bags)."""
    from mcap.reader import make_reader

    try:
        with path.open("rb") as fh:
            return make_reader(fh).get_header().profile
    except Exception as exc:  # mcap raises several exception types for non-MCAP bytes
        raise SourceError(f"mcap: {path} is not a readable MCAP file ({_reason(exc)})") from None


class McapLogWriter:
    """Streams frames into an MCAP log. Use as a context manager; ``close()`` writes the summary.

    With ``atomic`` (the default) the log is written to a temporary file beside ``path`` that
    replaces it on ``close()`` (see :func:`~gsfix_online.core.io.atomic_path`): a writer that
    fails (an exception in the ``with`` block, a full disk) removes it and leaves no partial log.
    The recorder node writes in place instead (``atomic=False``), so that a crash keeps every
    finished chunk for the readers."""

    def __init__(
        self, path: str | Path, chunk_size: int = 4 * 1024 * 1024, atomic: bool = True
    ) -> None:
        self.path = Path(path)
        self._target = contextlib.ExitStack()  # atomic: the temporary file's atomic_path
        try:
            if atomic:
                out = self._target.enter_context(atomic_path(self.path))
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                out = self.path
            self._fh: BinaryIO = out.open("wb")
        except BaseException:
            self._target.__exit__(*sys.exc_info())
            raise
        self._closed = False
        try:
            self._start(chunk_size)
        except BaseException:
            self._abort(*sys.exc_info())
            raise

    def _start(self, chunk_size: int) -> None:
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from mcap.well_known import MessageEncoding
        from mcap.writer import Writer
        from mcap_protobuf.schema import register_schema

        self._w = Writer(self._fh, chunk_size=chunk_size)
        self._w.start(profile="", library="gsfix-online")
        self._w.add_metadata("gsfix_online", {"log_schema_version": LOG_SCHEMA_VERSION})
        self._msg = {"image": RawImage, "calib": CameraCalibration, "tf": FrameTransform}
        self._channels: dict[str, int] = {}
        for topic, cls in (
            (TOPIC_COLOR, RawImage),
            (TOPIC_DEPTH, RawImage),
            (TOPIC_CALIB, CameraCalibration),
            (TOPIC_TF, FrameTransform),
        ):
            schema_id = register_schema(self._w, cls)
            self._channels[topic] = self._w.register_channel(
                topic, MessageEncoding.Protobuf, schema_id
            )
        self.frames = 0

    def _add(self, topic: str, msg: Any, stamp_ns: int, seq: int) -> None:
        self._w.add_message(
            self._channels[topic],
            log_time=stamp_ns,
            data=msg.SerializeToString(),
            publish_time=stamp_ns,
            sequence=seq,
        )

    def write(self, frame: RGBDFrame) -> None:
        from google.protobuf.timestamp_pb2 import Timestamp

        # MCAP times are unsigned 64-bit, sequence numbers unsigned 32-bit: a frame outside
        # them (a negative stamp is legal on the wire) is refused before anything is written;
        # written, it failed only at close() and left the log without its footer
        if not 0 <= frame.stamp_ns < 2**64 or not 0 <= frame.seq < 2**32:
            raise ValueError(
                f"an MCAP frame needs stamp_ns in [0, 2^64) and seq in [0, 2^32), got "
                f"{frame.stamp_ns} and {frame.seq}"
            )

        ts = Timestamp(
            seconds=frame.stamp_ns // 1_000_000_000, nanos=frame.stamp_ns % 1_000_000_000
        )
        h, w = frame.depth.shape
        image_cls, calib_cls, tf_cls = self._msg["image"], self._msg["calib"], self._msg["tf"]
        gray = frame.is_gray
        color = image_cls(
            timestamp=ts,
            frame_id=frame.frame_id,
            width=w,
            height=h,
            encoding="mono8" if gray else "rgb8",
            step=w if gray else 3 * w,
            data=frame.color.tobytes(),
        )
        depth = image_cls(
            timestamp=ts,
            frame_id=frame.frame_id,
            width=w,
            height=h,
            encoding="32FC1",
            step=4 * w,
            data=frame.depth.astype("<f4").tobytes(),
        )
        K = frame.intrinsics.K
        P = np.hstack([K, np.zeros((3, 1))])
        calib = calib_cls(
            timestamp=ts,
            frame_id=frame.frame_id,
            width=w,
            height=h,
            distortion_model="",
            D=[],
            K=K.ravel().tolist(),
            R=np.eye(3).ravel().tolist(),
            P=P.ravel().tolist(),
        )
        tf = tf_cls(timestamp=ts, parent_frame_id=WORLD_FRAME, child_frame_id=frame.frame_id)
        t = frame.T_world_cam[:3, 3]
        q = R_to_quat_xyzw(frame.T_world_cam[:3, :3])
        tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in t)
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = (float(v) for v in q)
        for topic, msg in (
            (TOPIC_CALIB, calib),
            (TOPIC_TF, tf),
            (TOPIC_COLOR, color),
            (TOPIC_DEPTH, depth),
        ):
            self._add(topic, msg, frame.stamp_ns, frame.seq)
        self.frames += 1

    def close(self) -> None:
        """Write the summary and, when atomic, move the log to its path."""
        if self._closed:
            return
        try:
            self._w.finish()
            self._fh.flush()
        except BaseException:
            self._abort(*sys.exc_info())
            raise
        self._closed = True
        self._fh.close()
        self._target.close()  # atomic: sync, rename over the path

    def _abort(self, *exc: Any) -> None:
        """Close after a failure: an atomic writer's temporary file is removed (raising the
        one-line OSError of atomic_path for an OSError)."""
        self._closed = True
        self._fh.close()
        self._target.__exit__(*exc)

    def __enter__(self) -> McapLogWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        if exc[0] is None:
            self.close()
        elif not self._closed:
            self._abort(*exc)


def write_mcap(path: str | Path, frames: Iterable[RGBDFrame]) -> int:
    """Write frames to an MCAP log; returns the number written."""
    with McapLogWriter(path) as w:
        for f in frames:
            w.write(f)
        return w.frames


def _image_array(msg: Any, kind: str, where: str) -> np.ndarray:
    enc, h, w, step = msg.encoding, msg.height, msg.width, msg.step
    layouts = {
        "rgb8": (np.uint8, 3),
        "mono8": (np.uint8, 1),
        "bgr8": (np.uint8, 3),
        "32FC1": (np.dtype("<f4"), 1),
        "16UC1": (np.dtype("<u2"), 1),
    }
    if enc not in layouts:
        raise SourceError(
            f"{where}: {kind} encoding {enc!r} is not supported (use {', '.join(layouts)})"
        )
    dtype, ch = layouts[enc]
    row = w * ch * np.dtype(dtype).itemsize
    if step < row or len(msg.data) < step * h:
        raise SourceError(
            f"{where}: {kind} data has {len(msg.data)} bytes, expected {h} rows of step {step} >= {row}"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=step * h).reshape(h, step)[:, :row]
    arr = np.ascontiguousarray(buf).view(dtype).reshape((h, w, ch) if ch > 1 else (h, w))
    if enc == "bgr8":
        arr = arr[:, :, ::-1]
    return np.ascontiguousarray(arr)


class McapReader(FrameSource):
    """Reads our MCAP logs (see module docstring); other MCAP profiles go to the bag reader."""

    format = "mcap"

    def __init__(self, path: str | Path, cfg) -> None:  # noqa: ANN001 - SourceConfig
        super().__init__(path, cfg)
        profile = mcap_profile(self.path)
        if profile in ("ros1", "ros2"):
            raise SourceError(
                f"mcap: {self.path} is a {profile} bag; read it with source.format=rosbag"
            )
        self._n = None
        self._has_summary = False
        from mcap.reader import make_reader

        with self.path.open("rb") as fh:
            reader = make_reader(fh)
            try:
                summary = reader.get_summary()
            except Exception:  # truncated file: no summary section
                summary = None
            self._has_summary = summary is not None
            if summary is not None and summary.statistics is not None:
                ids = [c.id for c in summary.channels.values() if c.topic == TOPIC_COLOR]
                self._n = sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)
                topics = {c.topic for c in summary.channels.values()}
                missing = {TOPIC_COLOR, TOPIC_DEPTH, TOPIC_TF} - topics
                if missing:
                    raise SourceError(
                        f"mcap: {self.path} lacks topics {sorted(missing)} (has {sorted(topics)})"
                    )

    def __len__(self) -> int:
        return self._n or 0

    def _frames(self) -> Iterator[RGBDFrame]:
        from mcap.reader import make_reader

        self._lost = []
        self._yielded: list[int] = []
        with self.path.open("rb") as fh:
            summary = make_reader(fh).get_summary() if self._has_summary else None
            if summary is not None and summary.chunk_indexes:
                messages = self._indexed_messages(fh, summary)
            else:  # a crashed writer left no summary: stream the records from the start
                messages = self._streamed_messages(fh)
            yield from self._assemble(messages)
        self._report_lost()

    def _indexed_messages(self, fh: BinaryIO, summary: Any) -> Iterator[tuple[str, int, Any]]:  # noqa: ANN401
        """(topic, log_time, decoded message) in log-time order, chunk by chunk through the
        summary's chunk index; a chunk that fails its CRC or does not decompress or parse is
        skipped (:meth:`_skip_chunk`) and every other chunk is read."""
        from mcap.data_stream import ReadDataStream
        from mcap.records import Chunk, Message
        from mcap.stream_reader import breakup_chunk

        channels = {i: c for i, c in summary.channels.items() if c.topic in _TOPICS}
        decoders = self._decoders(summary, channels)
        chunks = sorted(
            summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)
        )
        heap: list[tuple[int, int, int, int, Any]] = []  # (log_time, chunk, index, channel, data)
        for k, ci in enumerate(chunks):
            while heap and heap[0][0] < ci.message_start_time:
                yield self._decoded(heapq.heappop(heap), channels, decoders)
            try:
                fh.seek(ci.chunk_start_offset + 1 + 8)
                records = breakup_chunk(Chunk.read(ReadDataStream(fh)), validate_crc=True)
            except Exception as exc:  # any damage in the chunk's bytes: CRC, zstd, lengths
                self._skip_chunk(fh, ci, k, len(chunks), exc, channels)
                continue
            for i, rec in enumerate(records):
                if isinstance(rec, Message) and rec.channel_id in channels:
                    heapq.heappush(heap, (rec.log_time, k, i, rec.channel_id, rec.data))
        while heap:
            yield self._decoded(heapq.heappop(heap), channels, decoders)

    def _decoders(self, summary: Any, channels: dict[int, Any]) -> dict[int, Any]:  # noqa: ANN401
        from mcap_protobuf.decoder import DecoderFactory

        factory, out = DecoderFactory(), {}
        for i, c in channels.items():
            schema = summary.schemas.get(c.schema_id)
            out[i] = factory.decoder_for(c.message_encoding, schema)
            if out[i] is None:
                raise SourceError(
                    f"mcap: {self.path}: {c.topic} is not a protobuf channel "
                    f"({c.message_encoding!r}, schema {schema.name if schema else None!r})"
                )
        return out

    @staticmethod
    def _decoded(
        item: tuple[int, int, int, int, Any], channels: dict, decoders: dict
    ) -> tuple[str, int, Any]:  # noqa: ANN401
        log_time, _, _, cid, data = item
        return channels[cid].topic, log_time, decoders[cid](data)

    def _skip_chunk(
        self, fh: BinaryIO, ci: Any, k: int, n: int, exc: Exception, channels: dict
    ) -> None:  # noqa: ANN401
        """Note a damaged chunk and the stamps of the frames in it, from its message indexes
        (which lie outside the chunk); None when those are damaged too."""
        from mcap.records import MessageIndex
        from mcap.stream_reader import StreamReader

        stamps: set[int] | None = set()
        try:
            for cid, offset in ci.message_index_offsets.items():
                if cid in channels and channels[cid].topic != TOPIC_CALIB:
                    fh.seek(offset)
                    index = next(StreamReader(fh, skip_magic=True).records)
                    assert isinstance(index, MessageIndex) and index.channel_id == cid
                    stamps.update(t for t, _ in index.records)  # type: ignore[union-attr]
        except Exception:  # noqa: BLE001 - the index is damaged too: the chunk's time range
            stamps = None
        self._lost.append(_LostChunk(k, n, _reason(exc), ci.message_start_time,
                                     ci.message_end_time, stamps))  # fmt: skip

    def _streamed_messages(self, fh: BinaryIO) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time, decoded message) in file order, up to the first damage."""
        from mcap.reader import NonSeekingReader
        from mcap_protobuf.decoder import DecoderFactory

        # validate_crcs: a damaged chunk ends the read (no index to skip it by), so frames up
        # to it are used and no corrupted image is mapped
        reader = NonSeekingReader(fh, validate_crcs=True, decoder_factories=[DecoderFactory()])
        it = reader.iter_decoded_messages(topics=list(_TOPICS), log_time_order=False)
        while True:
            try:
                _schema, channel, message, msg = next(it)
            except StopIteration:
                return
            except Exception as exc:  # a crash left a partial last chunk, or bytes changed
                if damaged(self.path, exc) is None and not _is_mcap_damage(exc):
                    raise
                last = f" at {ns_to_seconds(self._yielded[-1])} s" if self._yielded else ""
                self._warn(f"ends early ({_reason(exc)}); frames up to here{last} were read, "
                           "the rest is lost (no summary index to skip the damage by)")  # fmt: skip
                return
            yield channel.topic, message.log_time, msg

    def _assemble(self, messages: Iterator[tuple[str, int, Any]]) -> Iterator[RGBDFrame]:
        """Frames from the four messages at each stamp (see the module docstring)."""
        pending: dict[int, dict[str, Any]] = {}
        calib: Intrinsics | None = None
        seq = 0
        for topic, stamp, msg in messages:
            where = f"mcap: {self.path.name} @ {stamp}"
            if topic == TOPIC_CALIB:
                K = np.asarray(msg.K, dtype=np.float64).reshape(3, 3)
                calib = Intrinsics.from_K(K, msg.width, msg.height)
                continue
            if topic == TOPIC_TF and msg.parent_frame_id != WORLD_FRAME:
                continue  # other transforms in the tree are not camera poses
            slot = pending.setdefault(stamp, {})
            if topic == TOPIC_TF:
                q = (msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w)
                norm = float(np.linalg.norm(q))
                if not np.isfinite(norm) or abs(norm - 1.0) > QUAT_NORM_TOL:
                    raise SourceError(f"{where}: transform quaternion norm must be 1 within "
                                      f"{QUAT_NORM_TOL:g}, got {norm:.6g}")  # fmt: skip
                t = (msg.translation.x, msg.translation.y, msg.translation.z)
                slot["T"] = make_T(quat_xyzw_to_R(q), t)
            elif topic == TOPIC_COLOR:
                slot["color"] = _image_array(msg, "colour", where)
                slot["frame_id"] = msg.frame_id or "camera"
            else:
                depth = _image_array(msg, "depth", where)
                slot["depth"] = (
                    depth
                    if depth.dtype == np.float32
                    else (depth.astype(np.float32) / np.float32(self.depth_scale(1000.0)))
                )
            if {"T", "color", "depth"} <= slot.keys():
                del pending[stamp]
                if calib is None:
                    h, w = slot["depth"].shape
                    calib = self.intrinsics_from_config(w, h)
                self._yielded.append(stamp)
                yield to_frame(
                    slot["color"],
                    slot["depth"].astype(np.float32),
                    calib,
                    slot["T"],
                    stamp,
                    frame_id=slot["frame_id"],
                    seq=seq,
                    where=where,
                )
                seq += 1
            if len(pending) > _MAX_PENDING:  # messages that never completed a frame
                oldest = min(pending)
                pending.pop(oldest)
                self._incomplete(oldest)
        for stamp in pending:
            self._incomplete(stamp)

    def _incomplete(self, stamp: int) -> None:
        """A stamp whose frame never completed: lost with a damaged chunk, else unpaired."""
        if not any(c.holds(stamp) for c in self._lost):
            self.stats.unpaired += 1

    def _report_lost(self) -> None:
        """One line per skipped chunk: its frames lost, as indexes into the log and stamps."""
        if not self._lost:
            return
        if all(c.stamps is not None for c in self._lost):
            lost = sorted(set().union(*(c.stamps or () for c in self._lost)))
        else:  # an index was damaged too: the frames the statistics count that never came
            lost = []
            self.stats.frames_lost = max(
                0, (self._n or 0) - len(self._yielded) - self.stats.unpaired
            )
        every = sorted({*self._yielded, *lost})
        if lost:
            self.stats.frames_lost = len(lost)
        for c in self._lost:
            mine = [t for t in lost if c.holds(t)]
            if mine:
                i0, i1 = every.index(mine[0]), every.index(mine[-1])
                what = (f"{len(mine)} frames lost: frames {i0} to {i1} of {len(every)} "
                        f"({ns_to_seconds(mine[0])} s to {ns_to_seconds(mine[-1])} s)")  # fmt: skip
            else:
                what = (f"its frames lost ({ns_to_seconds(c.start)} s to "
                        f"{ns_to_seconds(c.end)} s; message index damaged too)")  # fmt: skip
            self._warn(f"chunk {c.index + 1} of {c.of} is damaged ({c.reason}): skipped, {what}; "
                       "every other chunk was read")  # fmt: skip


@dataclass(frozen=True)
class _LostChunk:
    index: int  # in log-time order, from 0
    of: int
    reason: str
    start: int  # log time of its first and last message, ns
    end: int
    stamps: set[int] | None  # frames with a message in it; None when its index is damaged too

    def holds(self, stamp: int) -> bool:
        return stamp in self.stamps if self.stamps is not None else self.start <= stamp <= self.end


def _reason(exc: BaseException) -> str:
    """``TypeName: text`` of an exception, never an empty pair of parentheses."""
    text = " ".join(str(exc).split())[:200]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _is_mcap_damage(exc: BaseException) -> bool:
    from mcap.exceptions import McapError

    return isinstance(exc, (McapError, EOFError)) or type(exc).__name__ == "ZstdError"


def looks_like(path: Path) -> bool:
    return path.is_file() and path.suffix == ".mcap"
