"""The node run loop on the in-memory transport, with a fake clock."""

from __future__ import annotations

import logging
import signal

import numpy as np
import pytest

from gsfix_online.runtime.config import NodeRuntimeConfig
from gsfix_online.runtime.node import Node
from gsfix_online.runtime.transport import InMemoryTransport
from gsfix_online.runtime.wire import Message
from tests.runtime.samples import rgbd_message, sample_messages


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def health(t: InMemoryTransport, kind: str) -> list[Message]:
    return [m for m in t.published if m.type == kind]


def test_dispatch_topic_before_type_and_unhandled() -> None:
    calls: list[str] = []
    t = InMemoryTransport(
        script=[
            rgbd_message(0, topic="rgbd/cam0"),
            rgbd_message(1, topic="rgbd/cam1"),
            sample_messages()["pose"],
        ]
    )
    node = Node(
        "n",
        t,
        {
            "rgbd/cam1": lambda m: calls.append(f"topic:{m.seq}"),
            "rgbd": lambda m: calls.append(f"type:{m.seq}"),
        },
        clock=FakeClock(),
    )
    assert node.run_until_idle() == 3
    assert calls == ["type:0", "topic:1"]
    assert node.unhandled == {"pose": 1}
    assert node.handled == {"rgbd/cam0": 1, "rgbd/cam1": 1}


def test_handler_outputs_are_published() -> None:
    pose = sample_messages()["pose"]
    t = InMemoryTransport(script=[rgbd_message(0), rgbd_message(1)])

    def handler(m: Message) -> Message | list[Message]:
        return pose if m.seq == 0 else [pose, pose]

    Node("n", t, {"rgbd": handler}, clock=FakeClock()).run_until_idle()
    assert [m.type for m in t.published if m.type == "pose"] == ["pose"] * 3


def test_handler_errors_counted_logged_once_and_loop_continues(
    caplog: pytest.LogCaptureFixture,
) -> None:
    done: list[int] = []

    def handler(m: Message) -> None:
        if m.seq < 5:
            raise ValueError(f"bad frame {m.seq}\nsecond line")
        done.append(m.seq)

    t = InMemoryTransport(script=[rgbd_message(i) for i in range(7)])
    node = Node("n", t, {"rgbd": handler}, clock=FakeClock())
    with caplog.at_level(logging.WARNING, logger="gsfix_online.runtime.node"):
        node.run_until_idle()
    assert done == [5, 6]
    assert node.handler_errors == {"ValueError": 5}
    errors = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert len(errors) == 1 and "\n" not in errors[0] and "ValueError: bad frame 0" in errors[0]


def test_raise_policy_stops_the_loop() -> None:
    t = InMemoryTransport(script=[rgbd_message(0), rgbd_message(1)])
    node = Node(
        "n",
        t,
        {"rgbd": lambda m: 1 / 0},
        config=NodeRuntimeConfig(on_handler_error="raise"),
        clock=FakeClock(),
    )
    with pytest.raises(ZeroDivisionError):
        node.run_until_idle()
    assert t.queue_depth() == 1


def test_heartbeat_and_stats_periods() -> None:
    clock = FakeClock()
    t = InMemoryTransport()
    node = Node(
        "mapper",
        t,
        {"rgbd": lambda m: None},
        config=NodeRuntimeConfig(heartbeat_period_s=1.0, stats_period_s=5.0),
        clock=clock,
        time_ns=lambda: 42,
    )
    for step in range(21):  # 0 .. 10 s in 0.5 s steps, two frames per step
        clock.t = 100.0 + 0.5 * step
        t.feed(rgbd_message(2 * step))
        t.feed(rgbd_message(2 * step + 1))
        node.run_until_idle()
    beats = health(t, "heartbeat")
    assert len(beats) == 11  # t = 0, 1, ..., 10
    assert beats[0].topic == "heartbeat/mapper" and beats[0].stamp_ns == 42
    assert beats[-1].meta["uptime_s"] == pytest.approx(10.0)
    assert [b.seq for b in beats] == list(range(11))
    stats = health(t, "stats")
    assert len(stats) == 2  # t = 5, 10
    s = stats[-1].meta
    assert s["node"] == "mapper" and s["period_s"] == pytest.approx(5.0)
    assert s["rate_hz/rgbd/cam0"] == pytest.approx(4.0)  # 20 frames in 5 s
    assert s["received/rgbd/cam0"] == 40  # stats go out before the frames of t = 10 are read
    assert s["rejected_total"] == 0 and s["handler_errors"] == 0


def test_stats_latency_percentiles_and_rejections() -> None:
    clock = FakeClock()
    durations = [0.001 * (i + 1) for i in range(100)]  # 1 .. 100 ms

    def slow(m: Message) -> None:
        clock.t += durations[m.seq]

    t = InMemoryTransport(script=[[b"junk"], *[rgbd_message(i) for i in range(100)]])
    node = Node("n", t, {"rgbd": slow}, NodeRuntimeConfig(stats_period_s=3600), clock=clock)
    node.run_until_idle()
    s = node.stats_meta(clock.t)
    assert s["latency_n"] == 100
    assert s["latency_p50_ms"] == pytest.approx(np.percentile(np.array(durations) * 1e3, 50))
    assert s["latency_p99_ms"] == pytest.approx(np.percentile(np.array(durations) * 1e3, 99))
    assert s["rejected/frame_count"] == 1 and s["rejected_total"] == 1
    assert node.stats_meta(clock.t)["latency_n"] == 0  # window resets per report


def test_health_publish_failure_does_not_stop_the_node() -> None:
    class NoOutput(InMemoryTransport):
        def publish(self, msg: Message, reliable: bool = False) -> None:
            raise RuntimeError("no output")

    t = NoOutput(script=[rgbd_message(0)])
    seen: list[int] = []
    Node("n", t, {"rgbd": lambda m: seen.append(m.seq)}, clock=FakeClock()).run_until_idle()
    assert seen == [0]


def test_run_stops_on_sigterm_and_closes_transport() -> None:
    t = InMemoryTransport(script=[rgbd_message(i) for i in range(3)])
    seen: list[int] = []

    def handler(m: Message) -> None:
        seen.append(m.seq)
        if m.seq == 1:
            signal.raise_signal(signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    node = Node("n", t, {"rgbd": handler}, clock=FakeClock())
    assert node.run() == 0
    assert seen == [0, 1] and t.closed
    assert signal.getsignal(signal.SIGTERM) is before


def test_consumer_without_outputs_publishes_no_health_and_logs_nothing(caplog):
    from gsfix_online.runtime import InMemoryTransport, Node

    class Sink(InMemoryTransport):
        publishes_latest = False

    t = Sink()
    node = Node("sink", t, handlers={})
    with caplog.at_level("WARNING"):
        node.run_until_idle()
    assert t.published == [] and not caplog.records
