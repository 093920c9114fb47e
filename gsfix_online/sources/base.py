"""Shared parts of frame sources: the reader interface, statistics, image I/O and association."""

from __future__ import annotations

import heapq
import itertools
import logging
from abc import ABC, abstractmethod
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import FrameError, Intrinsics, RGBDFrame
from gsfix_online.sources.config import SourceConfig
from gsfix_online.sources.plausibility import (
    PLAUSIBLE_MEDIAN_M,
    DepthSummary,
    frame_median,
    likely_scale,
    plausible,
    scale_from_motion,
)
from gsfix_online.sources.resolution import at_processing_resolution, processing_size

logger = logging.getLogger(__name__)


class SourceError(ValueError):
    """A dataset, bag or log is missing files or holds data that cannot be read."""


# What a damaged file raises inside the parsers the readers use (text decoding, PNG and zlib,
# struct unpacking, protobuf, YAML, JSON, missing keys of a cut index): at the readers' boundary
# each becomes one SourceError line naming the recording (a flipped byte in a TUM pose list
# escaped as UnicodeDecodeError; benchmarks/results/fault_findings.md).
_DAMAGE_NAMES = {"DecodeError", "YAMLError", "ScannerError", "ParserError", "error", "ZstdError"}


def damaged(path: Path, exc: BaseException) -> SourceError | None:
    """The SourceError for ``exc`` raised while reading ``path``, or None when ``exc`` is not
    what a damaged file raises (a SourceError or FrameError already: one line naming the
    file, or a bug)."""
    if isinstance(exc, (SourceError, FrameError)) or not isinstance(exc, Exception):
        return None
    parsing = (UnicodeError, ValueError, KeyError, IndexError, EOFError, OSError, TypeError)
    if not isinstance(exc, parsing) and type(exc).__name__ not in _DAMAGE_NAMES:
        return None
    text = " ".join(str(exc).split())[:300]
    return SourceError(f"{path} is damaged or unreadable: {type(exc).__name__}: {text}")


@dataclass
class SourceStats:
    """What a reader did with its input, for logs and reports."""

    frames: int = 0  # frames yielded
    depth_pixels_invalidated: int = 0  # NaN/inf/negative depth pixels set to 0
    unpaired: int = 0  # colour or depth images without a partner within max_assoc_s
    without_pose: int = 0  # frames dropped because no pose was within max_pose_gap_s
    out_of_order: int = 0  # frames listed or received after a newer one (yielded in time order)
    duplicate_stamps: int = 0  # frames at the stamp of the frame before them: dropped
    frames_lost: int = 0  # frames in damaged parts of a log that were skipped

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))


class FrameSource(ABC):
    """A reader: iterating it streams validated :class:`RGBDFrame` objects, one at a time, in
    time order.

    Subclasses implement :meth:`_frames`; time order, stride, frame limits, statistics, the
    depth checks and the processing resolution (``cfg.max_width``: frames are yielded resized,
    :mod:`~gsfix_online.sources.resolution`; ``camera`` keeps the intrinsics as read) are
    handled here. Indexes (file lists, trajectories) are loaded up front;
    images are read only when yielded. A reader whose input can arrive out of time order
    (bags, logs) sorts within a look-ahead of ``lookahead`` frames and fails with one line on a
    frame later than that; file indexes are sorted whole (``lookahead`` 0).
    """

    format: str = "?"
    lookahead: int = 16  # frames held to sort a stream into time order

    def __init__(self, path: str | Path, cfg: SourceConfig) -> None:
        self.path = Path(path)
        self.cfg = cfg
        self.stats = SourceStats()
        self.depth = DepthSummary()
        self.warnings: list[str] = []  # what the last iteration warned about, for reports
        # the intrinsics of the first frame as read, before the processing resolution
        self.camera: Intrinsics | None = None
        processing_size(1, 1, cfg.max_width)  # a negative max_width fails here, in one line
        if not self.path.exists():
            raise SourceError(f"{self.format}: {self.path} does not exist")

    @abstractmethod
    def _frames(self) -> Iterator[RGBDFrame]: ...

    def depth_units(self) -> tuple[str, float] | None:
        """(raw depth dtype, units per metre) as read, when the reader knows them."""
        return None

    def __iter__(self) -> Iterator[RGBDFrame]:
        self.stats = SourceStats()
        self.depth = DepthSummary()
        self.warnings = []
        checks = DepthChecks(self)
        n_out = 0
        for i, frame in enumerate(checks.first(self._ordered(self._checked_frames()))):
            if i % self.cfg.stride:
                continue
            if self.camera is None:
                self.camera = frame.intrinsics
            frame = at_processing_resolution(frame, self.cfg.max_width)
            self.stats.frames += 1
            self.stats.depth_pixels_invalidated += frame.n_depth_invalidated
            checks.add(frame)
            yield frame
            n_out += 1
            if self.cfg.max_frames and n_out >= self.cfg.max_frames:
                break
        s = self.stats
        if s.depth_pixels_invalidated:
            self._warn(
                f"{s.depth_pixels_invalidated} invalid depth pixels (NaN/inf/negative) set to 0"
            )
        if s.unpaired or s.without_pose:
            self._warn(f"{s.unpaired} images unpaired, {s.without_pose} frames without pose")
        if s.out_of_order:
            self._warn(f"{s.out_of_order} frames out of time order (yielded sorted by stamp)")
        if s.duplicate_stamps:
            self._warn(f"{s.duplicate_stamps} frames at an already used stamp dropped")
        checks.finish()

    def _warn(self, text: str) -> None:
        self.warnings.append(text)
        logger.warning("%s: %s: %s", self.format, self.path, text)

    def _ordered(self, frames: Iterator[RGBDFrame]) -> Iterator[RGBDFrame]:
        """``frames`` in time order: sorted within ``lookahead`` frames, out-of-order arrivals
        counted, a second frame at one stamp dropped (counted); a frame older than one already
        yielded is a SourceError."""
        heap: list[tuple[int, int, RGBDFrame]] = []
        newest_in: int | None = None
        last_out: int | None = None
        for k, frame in enumerate(frames):
            stamp = frame.stamp_ns
            if newest_in is not None and stamp < newest_in:
                self.stats.out_of_order += 1
            newest_in = stamp if newest_in is None else max(newest_in, stamp)
            if last_out is not None and stamp < last_out:
                raise SourceError(
                    f"{self.format}: {self.path}: frame at {ns_to_seconds(stamp)} s comes more "
                    f"than {self.lookahead} frames after the newer frame at "
                    f"{ns_to_seconds(last_out)} s; the input is out of time order beyond the "
                    "reader's look-ahead"
                )
            heapq.heappush(heap, (stamp, k, frame))
            while len(heap) > self.lookahead:
                last_out = yield from self._pop(heap, last_out)
        while heap:
            last_out = yield from self._pop(heap, last_out)

    def _pop(
        self, heap: list[tuple[int, int, RGBDFrame]], last_out: int | None
    ) -> Generator[RGBDFrame, None, int]:
        stamp, _, frame = heapq.heappop(heap)
        if stamp == last_out:
            self.stats.duplicate_stamps += 1
        else:
            yield frame
        return stamp

    def _checked_frames(self) -> Iterator[RGBDFrame]:
        frames = self._frames()
        while True:
            try:
                frame = next(frames)
            except StopIteration:
                return
            except Exception as exc:
                err = damaged(self.path, exc)
                if err is None:
                    raise
                raise err from exc
            yield frame

    def depth_scale(self, default: float) -> float:
        return self.cfg.depth_scale or default

    def intrinsics_from_config(self, width: int, height: int) -> Intrinsics:
        cam = self.cfg.camera
        if not cam.is_set:
            raise SourceError(
                f"{self.format}: {self.path} has no camera file; set source.camera.fx/fy/cx/cy"
            )
        return Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, width, height)

    def T_SC(self) -> npt.NDArray[np.float64]:
        return (
            np.asarray(self.cfg.T_SC, dtype=np.float64).reshape(4, 4)
            if self.cfg.T_SC
            else np.eye(4)
        )


class DepthChecks:
    """The depth checks of one iteration of ``reader``: its :class:`DepthSummary`, a user-set
    scale that makes the first frames implausible (an error unless ``force_depth_scale``), and
    at the end warnings for an implausible median, frames without depth and a scale the poses
    disagree with (:func:`scale_from_motion`)."""

    FIRST = 5  # frames a user-set scale must make implausible, all of them, to be refused
    BASELINE_M = 0.1  # camera motion between the two frames of the scale check
    TRIES = 3

    def __init__(self, reader: FrameSource) -> None:
        self.reader = reader
        self.units = reader.depth_units()
        self.ref: RGBDFrame | None = None
        self.tries = 0
        self.motion_scale: float | None = None

    def first(self, frames: Iterator[RGBDFrame]) -> Iterator[RGBDFrame]:
        cfg = self.reader.cfg
        if not cfg.depth_scale or cfg.force_depth_scale:
            yield from frames
            return
        head = list(itertools.islice(frames, self.FIRST))
        medians = [frame_median(f.depth) for f in head]
        if head and not any(m is not None and plausible(m) for m in medians):
            known = [m for m in medians if m is not None]
            got = f"medians {min(known):.3g} to {max(known):.3g} m" if known else "no valid depth"
            hint = ""
            if known and self.units is not None:
                scale = likely_scale(float(np.median(known)), self.units[1], self.units[0])
                hint = f"; the likely scale is {scale:g} units/m" if scale else ""
            lo, hi = PLAUSIBLE_MEDIAN_M
            raise SourceError(
                f"{self.reader.format}: {self.reader.path}: source.depth_scale={cfg.depth_scale:g} "
                f"makes every frame's depth implausible (first {len(head)}: {got}, expected a "
                f"median of {lo:g} to {hi:g} m){hint}; set source.force_depth_scale=true to read "
                "at this scale anyway"
            )
        yield from head
        yield from frames

    def add(self, frame: RGBDFrame) -> None:
        if self.reader.depth.add(frame.depth) is None or self.units is None:
            return
        if self.ref is None:
            self.ref = frame
            return
        baseline = np.linalg.norm(frame.T_world_cam[:3, 3] - self.ref.T_world_cam[:3, 3])
        if self.motion_scale is None and self.tries < self.TRIES and baseline >= self.BASELINE_M:
            self.tries += 1
            dtype, scale = self.units
            self.motion_scale = scale_from_motion(self.ref, frame, scale, dtype)

    def finish(self) -> None:
        depth, warn = self.reader.depth, self.reader._warn
        if depth.all_zero_frames:
            warn(f"{depth.all_zero_frames} of {depth.frames} frames have no valid depth (all zero)")
        p = depth.percentiles()
        if p is None:
            return
        dtype, scale = self.units or ("", 0.0)
        read_at = f" ({dtype} depth read at {scale:g} units/m)" if self.units else ""
        lo, hi = PLAUSIBLE_MEDIAN_M
        if not plausible(p[1]):
            likely = likely_scale(p[1], scale, dtype) if self.units else None
            hint = f"; the likely scale is {likely:g} units/m (source.depth_scale={likely:g})"
            warn(f"median depth {p[1]:.3g} m is implausible (expected {lo:g} to {hi:g} m)"
                 f"{read_at}{hint if likely else ''}")  # fmt: skip
        elif self.motion_scale is not None:
            m = self.motion_scale
            warn(f"the depth disagrees with the poses{read_at}: they agree at {m:g} units/m "
                 f"(median {p[1] * scale / m:.3g} m, not {p[1]:.3g} m); the likely scale is "
                 f"{m:g} units/m (source.depth_scale={m:g})")  # fmt: skip


# --------------------------------------------------------------------------------------------
# Image files
# --------------------------------------------------------------------------------------------


def read_color(path: Path) -> npt.NDArray[np.uint8]:
    """8-bit colour (RGB [H, W, 3]) or grayscale ([H, W]) image; alpha is dropped."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SourceError(f"cannot read image {path}")
    if img.dtype != np.uint8:
        raise SourceError(f"colour image {path} must be 8-bit, got {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            return img[:, :, 0]
        code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
        return cv2.cvtColor(img, code)
    return img


def write_color(path: Path, color: npt.NDArray[np.uint8], jpeg_quality: int = 95) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = color if color.ndim == 2 else cv2.cvtColor(color, cv2.COLOR_RGB2BGR)
    params = (
        [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if path.suffix.lower() in (".jpg", ".jpeg") else []
    )
    if not cv2.imwrite(str(path), img, params):
        raise SourceError(f"cannot write image {path}")


def read_depth_png(path: Path, scale: float) -> npt.NDArray[np.float32]:
    """16-bit depth PNG in ``scale`` units per metre -> float32 metres (0 stays invalid)."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SourceError(f"cannot read depth image {path}")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise SourceError(
            f"depth image {path} must be 16-bit single channel, got {raw.dtype} {list(raw.shape)}"
        )
    return (raw.astype(np.float32) / np.float32(scale)).astype(np.float32)


def write_depth_png(path: Path, depth_m: npt.NDArray[np.float32], scale: float) -> None:
    """float32 metres -> 16-bit PNG in ``scale`` units per metre. Depths that do not fit are an error."""
    import cv2

    raw = np.rint(
        np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float64) * scale
    )
    if raw.max(initial=0) > 65535:
        raise SourceError(
            f"depth {raw.max() / scale:.2f} m does not fit a 16-bit PNG at scale {scale} (max {65535 / scale:.2f} m)"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.clip(raw, 0, 65535).astype(np.uint16)):
        raise SourceError(f"cannot write depth image {path}")


def check_frame_images(color: np.ndarray, depth: np.ndarray, where: str) -> None:
    if color.shape[:2] != depth.shape:
        raise SourceError(
            f"{where}: colour {list(color.shape[:2])} and depth {list(depth.shape)} sizes differ"
        )


# --------------------------------------------------------------------------------------------
# Timestamp association
# --------------------------------------------------------------------------------------------


def associate(a_ns: Sequence[int], b_ns: Sequence[int], max_diff_ns: int) -> list[tuple[int, int]]:
    """One-to-one matching of two stamp lists, closest pairs first, within ``max_diff_ns``.

    Returns index pairs (i, j) sorted by i. Same rule as the TUM benchmark's associate.py.
    """
    a = np.asarray(a_ns, dtype=np.int64)
    b = np.asarray(b_ns, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return []
    bs = np.argsort(b, kind="stable")
    b_sorted = b[bs]
    cands: list[tuple[int, int, int]] = []
    for i, t in enumerate(a):
        lo = int(np.searchsorted(b_sorted, t - max_diff_ns, side="left"))
        hi = int(np.searchsorted(b_sorted, t + max_diff_ns, side="right"))
        for k in range(lo, hi):
            cands.append((abs(int(b_sorted[k]) - int(t)), i, int(bs[k])))
    cands.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in cands:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j))
    pairs.sort()
    return pairs


def seconds_to_ns(text: str) -> int:
    """Decimal seconds string (e.g. '1305031102.175304') -> int ns, without float rounding."""
    import re

    text = text.strip()
    m = re.fullmatch(r"([+-]?)(\d*)(?:\.(\d*))?", text)
    if m and (m.group(2) or m.group(3)):
        ns = int(m.group(2) or 0) * 1_000_000_000 + int(((m.group(3) or "") + "000000000")[:9])
        return -ns if m.group(1) == "-" else ns
    try:
        value = float(text)  # scientific notation
    except ValueError:
        raise SourceError(f"bad timestamp {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise SourceError(f"bad timestamp {text!r}")
    return int(round(value * 1e9))


def ns_to_seconds(ns: int) -> str:
    """int ns -> decimal seconds string with 9 digits, the exact inverse of :func:`seconds_to_ns`."""
    sign = "-" if ns < 0 else ""
    ns = abs(int(ns))
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def to_frame(*args: object, where: str, **kwargs: object) -> RGBDFrame:
    """make_frame with the source location prefixed to any validation error."""
    from gsfix_online.core.types import make_frame

    try:
        return make_frame(*args, **kwargs)  # type: ignore[arg-type]
    except FrameError as exc:
        raise FrameError(f"{where}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Readers of image folders with an index
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FileItem:
    """One indexed frame: image paths, its camera pose (None = no pose found) and stamp."""

    color: Path
    depth: Path
    T_world_cam: npt.NDArray[np.float64] | None  # [4, 4]
    stamp_ns: int
    K: npt.NDArray[np.float64] | None = (
        None  # [3, 3] pixels, for the colour image, when the index has one
    )


class FileSequenceReader(FrameSource):
    """A dataset of colour/depth files listed in an index built by the subclass's constructor.

    Subclasses set ``self.items``, ``self.scale`` (depth units per metre) and implement
    :meth:`intrinsics`; images are loaded one frame at a time while iterating.
    """

    items: list[FileItem]
    scale: float
    resize_color_to_depth: bool = False

    lookahead = 0  # the index is sorted by stamp before reading (see _frames)

    def __len__(self) -> int:
        return len(self.items)

    def depth_units(self) -> tuple[str, float] | None:
        return ("uint16", self.scale)

    def intrinsics(self, item: FileItem, width: int, height: int) -> Intrinsics:
        """Intrinsics of ``item``'s colour image of ``width`` x ``height``."""
        if item.K is not None and not self.cfg.camera.is_set:
            return Intrinsics.from_K(item.K, width, height)
        return self.intrinsics_from_config(width, height)

    def _frames(self) -> Iterator[RGBDFrame]:
        # time order: an index listed out of order (a reversed rgb.txt) is read sorted, counted
        stamps = [item.stamp_ns for item in self.items]
        self.stats.out_of_order += sum(b < a for a, b in itertools.pairwise(stamps))
        order = sorted(range(len(stamps)), key=stamps.__getitem__)
        for seq, item in enumerate(self.items[i] for i in order):
            if item.T_world_cam is None:
                self.stats.without_pose += 1
                continue
            where = f"{self.format}: {item.color.relative_to(self.path) if item.color.is_relative_to(self.path) else item.color}"
            color = read_color(item.color)
            depth = read_depth_png(item.depth, self.scale)
            intr = self.intrinsics(item, color.shape[1], color.shape[0])
            if self.resize_color_to_depth and color.shape[:2] != depth.shape:
                import cv2

                h, w = depth.shape
                color = cv2.resize(color, (w, h), interpolation=cv2.INTER_AREA)
                intr = intr.scaled(w, h)
            check_frame_images(color, depth, where)
            yield to_frame(
                color,
                depth,
                intr,
                item.T_world_cam,
                item.stamp_ns,
                frame_id="camera",
                seq=seq,
                where=where,
            )
