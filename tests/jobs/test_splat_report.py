"""The mapping report's stream replay: lag and keeping up, on hand-computed schedules."""

from __future__ import annotations

import pytest

from gsfix_online.jobs.splat_report import stream_timing


def test_stream_that_is_kept_up_with() -> None:
    t = stream_timing([10.0, 10.5, 11.0], [0.4, 0.4, 0.4])
    assert t["stream_hz"] == pytest.approx(2.0) and t["stream_s"] == pytest.approx(1.5)
    assert t["keeps_up"] and t["realtime_factor"] == pytest.approx(1.5 / 1.2)
    assert t["lag_s"]["max"] == pytest.approx(0.4) and t["lag_s"]["p50"] == pytest.approx(0.4)


def test_slow_mapper_queues_frames_and_falls_behind() -> None:
    t = stream_timing([0.0, 0.5, 1.0], [1.0, 1.0, 1.0])  # finishes at 1, 2, 3
    assert not t["keeps_up"] and t["realtime_factor"] == pytest.approx(0.5)
    assert t["lag_s"]["max"] == pytest.approx(2.0) and t["lag_s"]["p50"] == pytest.approx(1.5)


def test_one_slow_frame_is_absorbed_by_idle_time() -> None:
    t = stream_timing([0.0, 0.5, 1.0, 1.5], [0.8, 0.1, 0.1, 0.1])  # 2nd waits 0.3 s
    assert t["keeps_up"] and t["lag_s"]["max"] == pytest.approx(0.8)
    assert t["lag_s"]["mean"] == pytest.approx((0.8 + 0.4 + 0.1 + 0.1) / 4)
