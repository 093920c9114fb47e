"""The in-memory transport and bus, and rate-limited rejection logging."""

from __future__ import annotations

import logging

import pytest

from gsfix_online.runtime.ratelog import RateLimitedLog
from gsfix_online.runtime.transport import InMemoryBus, InMemoryTransport, TransportError
from gsfix_online.runtime.wire import Message, WireError, encode
from tests.runtime.samples import rgbd_message, sample_messages


def test_scripted_input_and_rejections() -> None:
    good = rgbd_message(1)
    t = InMemoryTransport(script=[[b"junk"], good, [b"rgbd/cam0\x00", b"\xc1"], rgbd_message(2)])
    assert t.queue_depth() == 4
    first = t.recv()
    assert first is not None and first.seq == 1
    second = t.recv()
    assert second is not None and second.seq == 2
    assert t.recv() is None
    assert t.rejected == {"frame_count": 1, "header_msgpack": 1}
    assert t.received == {"rgbd/cam0": 2}


def test_publish_is_captured_decoded_and_validated() -> None:
    t = InMemoryTransport()
    for msg in sample_messages().values():
        t.publish(msg, reliable=msg.type == "keyframe")
    assert [p.message.type for p in t.outbox] == list(sample_messages())
    assert [p.reliable for p in t.outbox].count(True) == 1
    assert t.published[0].arrays["color"].shape == (6, 8, 3)
    bad = rgbd_message()
    bad.meta = {}
    with pytest.raises(WireError):
        t.publish(bad)
    t.close()
    with pytest.raises(TransportError):
        t.publish(rgbd_message())
    assert t.recv() is None


def test_bus_fans_out_by_subscription() -> None:
    bus = InMemoryBus()
    cam = bus.transport([])
    exact = bus.transport(["rgbd/cam0"])
    namespace = bus.transport(["rgbd/"])
    everything = bus.transport([""])
    cam.publish(rgbd_message(0, topic="rgbd/cam0"))
    cam.publish(rgbd_message(1, topic="rgbd/cam0_raw"))
    cam.publish(sample_messages()["pose"])

    def seqs(t: InMemoryTransport) -> list[tuple[str, int]]:
        out = []
        while (m := t.recv()) is not None:
            out.append((m.topic, m.seq))
        return out

    assert seqs(exact) == [("rgbd/cam0", 0)]
    assert seqs(namespace) == [("rgbd/cam0", 0), ("rgbd/cam0_raw", 1)]
    assert [t for t, _ in seqs(everything)] == ["rgbd/cam0", "rgbd/cam0_raw", "pose/body"]
    assert seqs(cam) == []  # not delivered back to the sender


def test_subscriptions_must_be_a_list() -> None:
    with pytest.raises(TypeError):
        InMemoryTransport("rgbd/")  # type: ignore[arg-type]


def test_rejections_logged_once_per_reason_per_period(caplog: pytest.LogCaptureFixture) -> None:
    bad_version = encode(rgbd_message())
    bad_version[1] = bad_version[1].replace(b"\xa1v\x01", b"\xa1v\x02")
    t = InMemoryTransport(script=[[b"x"]] * 50 + [bad_version] * 20)
    with caplog.at_level(logging.WARNING, logger="gsfix_online.runtime.transport"):
        assert t.recv() is None
    assert t.rejected == {"frame_count": 50, "version": 20}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines
    assert all("\n" not in line for line in lines)


def test_rate_limited_log_reports_suppressed_count(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    log = RateLimitedLog(logging.getLogger("test.ratelog"), period_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="test.ratelog"):
        assert log.warning("a", "first")
        assert not log.warning("a", "again")
        assert not log.warning("a", "again")
        assert log.warning("b", "other reason")
        now[0] = 10.5
        assert log.warning("a", "multi\nline")
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs[0] == "first" and msgs[1] == "other reason"
    assert msgs[2].startswith("multi line (+2 more")


def test_message_defaults() -> None:
    m = Message("stats/x", "stats", meta={"node": "x", "period_s": 1.0})
    assert (m.seq, m.stamp_ns, m.frame_id, m.arrays, m.sent_mono_ns) == (0, 0, "", {}, None)
