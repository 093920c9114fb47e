"""Replay with rate control: real time, N times real time, or as fast as the consumer takes frames.

The clock and sleep functions are passed in, so the pacing is testable and never reads a clock it
was not given. In ``max`` mode nothing sleeps: a blocking consumer sets the pace.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

from gsfix_online.core.types import RGBDFrame
from gsfix_online.sources.config import ReplayConfig


def is_held_out(index: int, every: int) -> bool:
    """Frame ``index`` (0-based, in input order) is held out of mapping and fine-tuning: every
    ``every``-th frame, from the middle of the first block (``index % every == every // 2``), so
    each held-out frame has mapped frames on both sides; ``every`` 0 holds out none."""
    return every > 0 and index % every == every // 2


def paced(
    frames: Iterable[RGBDFrame],
    cfg: ReplayConfig,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
) -> Iterator[RGBDFrame]:
    """Yield ``frames``; in ``realtime`` mode frame i is released at t0 + (stamp_i - stamp_0) / speed.

    A consumer slower than real time is not caught up by dropping frames: replay never loses data,
    it falls behind (later frames are then released without waiting). Frames held out by
    ``cfg.holdout_every`` (:func:`is_held_out`) are not yielded.
    """
    t0_wall: float | None = None
    t0_stamp = 0
    for i, frame in enumerate(frames):
        if is_held_out(i, cfg.holdout_every):
            continue
        if cfg.mode == "realtime":
            if t0_wall is None:
                t0_wall, t0_stamp = clock(), frame.stamp_ns
            due = t0_wall + (frame.stamp_ns - t0_stamp) * 1e-9 / cfg.speed
            wait = due - clock()
            if wait > 0:
                sleep(wait)
        yield frame
