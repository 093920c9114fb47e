"""The message layer every node uses: wire format, transports, the node run loop.

``wire`` defines the messages (the schema reference), ``transport`` the interface and its
in-memory double, ``zmq_transport`` the ZeroMQ implementation (imported lazily: pyzmq loads only
when a ZmqTransport is built), ``node`` the dispatch loop, ``config`` their settings.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gsfix_online.runtime.config import EndpointConfig, NodeRuntimeConfig, TransportConfig
from gsfix_online.runtime.node import Node
from gsfix_online.runtime.transport import (
    InMemoryBus,
    InMemoryTransport,
    Transport,
    TransportError,
    TransportInterrupted,
    TransportTimeout,
)
from gsfix_online.runtime.wire import (
    REGISTRY,
    SCHEMA_VERSION,
    Message,
    WireError,
    decode,
    encode,
    frame_to_message,
    message_to_frame,
)

if TYPE_CHECKING:
    from gsfix_online.runtime.zmq_transport import ZmqTransport


def __getattr__(name: str) -> Any:
    if name == "ZmqTransport":
        from gsfix_online.runtime.zmq_transport import ZmqTransport

        return ZmqTransport
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "REGISTRY",
    "SCHEMA_VERSION",
    "EndpointConfig",
    "InMemoryBus",
    "InMemoryTransport",
    "Message",
    "Node",
    "NodeRuntimeConfig",
    "Transport",
    "TransportConfig",
    "TransportError",
    "TransportInterrupted",
    "TransportTimeout",
    "WireError",
    "ZmqTransport",
    "decode",
    "encode",
    "frame_to_message",
    "message_to_frame",
]
