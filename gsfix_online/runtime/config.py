"""Configuration of the message layer: endpoints, transport limits and the node run loop.

A node's YAML section names its inputs and outputs; everything else has defaults that suit
640x480 RGB-D at 30 Hz on one host. Addresses are ZeroMQ endpoints: ``ipc:///run/gsfix/rgbd``
(same host, fastest) or ``tcp://host:port`` (``tcp://127.0.0.1:*`` binds a free port; read the
real one back from ``ZmqTransport.bound_addresses``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng

DeliveryMode = Literal["latest", "reliable"]
ErrorPolicy = Literal["log", "raise"]

MiB = 1 << 20


@dataclass(frozen=True)
class EndpointConfig:
    """One socket: where it is, which side binds, and how messages are delivered.

    ``latest``: PUB/SUB, newest message per topic wins, older unread ones are dropped and counted.
    ``reliable``: DEALER -> ROUTER with acks and resend, no loss; the sender blocks when the
    receiver falls behind, for as long as the receiver is connected, and raises
    ``TransportTimeout`` once it has been absent too long (``liveness.py``).
    A reliable link has exactly one receiver (many senders may share it).
    ``topics`` routes an output: only messages on these topics (subscription syntax: ``"keyframe/"``
    = that namespace) go out on it; empty = every message of its delivery mode.
    ``name`` and ``peer`` only label log lines and errors (the graph fills them in).
    """

    address: str = ""  # "ipc:///path" or "tcp://host:port"
    bind: bool = False  # True: this side binds (the long-lived side), False: it connects
    mode: DeliveryMode = "latest"
    topics: tuple[str, ...] = ()  # outputs only: route these topics here; () = all
    name: str = ""  # the graph's name of this output or input
    peer: str = ""  # reliable outputs: the node that reads this link

    def validate(self) -> None:
        if not self.address.startswith(("ipc://", "tcp://", "inproc://")):
            raise ValueError(
                f"endpoint address must start with ipc://, tcp:// or inproc://, got {self.address!r}"
            )
        if self.address.startswith("tcp://") and ":" not in self.address[len("tcp://") :]:
            raise ValueError(f"tcp endpoint needs host:port, got {self.address!r}")


@dataclass(frozen=True)
class TransportConfig:
    """Sockets and limits of one node's transport."""

    inputs: tuple[EndpointConfig, ...] = ()  # sockets this node receives on
    outputs: tuple[EndpointConfig, ...] = ()  # sockets this node publishes on
    # Topic subscriptions: "rgbd/cam0" = that topic only, "rgbd/" = every topic under rgbd/,
    # "" = everything.
    subscriptions: tuple[str, ...] = ("",)
    max_message_bytes: int = field(
        default=256 * MiB, metadata=rng(1024, 2**31, "largest accepted message, bytes")
    )
    # 32: acks come every half window, and each one wakes the sender and costs both ends
    # Python and a round trip through the I/O threads; at 16, 640x480 RGB-D at full speed on 2
    # cores took about 1.5x the main-thread CPU per frame that it takes at 32 (sender and
    # receiver together; benchmarks/bench_transport.py --window).
    # The sender holds at most this many messages (32 such frames: 69 MB), below reliable_hwm.
    reliable_window: int = field(
        default=32, metadata=rng(1, 4096, "reliable: messages in flight before send blocks")
    )
    reliable_hwm: int = field(
        default=64, metadata=rng(1, 1_000_000, "reliable: socket high-water mark, messages")
    )
    # How long a blocked reliable send or flush waits for a receiver that is not there. One
    # that is connected is waited for without a deadline, however slow (liveness.py).
    reliable_send_timeout_s: float = field(
        default=30.0,
        metadata=rng(0.001, 3600, "reliable: give up on a receiver disconnected this long, s"),
    )
    reliable_connect_timeout_s: float = field(
        default=120.0,
        metadata=rng(0.001, 86400, "reliable: give up on a receiver not connected after, s"),
    )
    # ZMTP heartbeats on reliable outputs: the receiver's libzmq I/O thread answers them, so a
    # frozen process or a lost network counts as disconnected after heartbeat_timeout_s, a busy
    # one never. 0 = off (then only a closed connection counts).
    heartbeat_s: float = field(
        default=1.0, metadata=rng(0, 3600, "reliable: heartbeat interval (0 = off), s")
    )
    heartbeat_timeout_s: float = field(
        default=10.0, metadata=rng(0.001, 3600, "reliable: disconnect after no reply for, s")
    )
    reliable_resend_s: float = field(
        default=0.5, metadata=rng(0.001, 600, "reliable: resend unacked messages after, s")
    )
    linger_s: float = field(
        default=1.0, metadata=rng(0, 60, "on close: wait this long to flush unsent messages, s")
    )
    log_period_s: float = field(
        default=10.0, metadata=rng(0, 3600, "at most one log line per rejection reason per period")
    )


@dataclass(frozen=True)
class NodeRuntimeConfig:
    """The node run loop: health topics and error policy."""

    heartbeat_period_s: float = field(
        default=1.0, metadata=rng(0.01, 3600, "publish heartbeat/<node> this often, s")
    )
    stats_period_s: float = field(
        default=5.0, metadata=rng(0.01, 3600, "publish stats/<node> this often, s")
    )
    poll_timeout_ms: int = field(
        default=50, metadata=rng(0, 10_000, "longest wait for a message before housekeeping")
    )
    on_handler_error: ErrorPolicy = "log"  # "raise" stops the loop at the first handler error
    log_period_s: float = field(
        default=10.0,
        metadata=rng(0, 3600, "at most one log line per handler error kind per period"),
    )
    latency_window: int = field(
        default=4096, metadata=rng(16, 1_000_000, "handler latencies kept for p50/p99")
    )
