"""Render requests between nodes, as messages: who asked, and where the reply goes.

A request names its sender (``reply_to``); servers reply on ``render_reply/<requester>/<server>``,
so each requester subscribes to its own namespace. Pure functions on messages, no sockets.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from gsfix_online.runtime.wire import Message


def reply_topic(server: str, request: Message) -> str:
    """``render_reply/<requester>/<server>`` when the request names ``reply_to``, else
    ``render_reply/<server>``: requesters subscribe to their own namespace."""
    reply_to = request.meta.get("reply_to")
    return f"render_reply/{reply_to}/{server}" if reply_to else f"render_reply/{server}"


def render_request(
    requester: str,
    request_id: int,
    T_world_cam: np.ndarray,  # [4, 4]
    K: np.ndarray,  # [3, 3] px
    width: int,
    height: int,
    what: Iterable[str],
    topic: str | None = None,
    meta: dict[str, Any] | None = None,  # extra meta keys
) -> Message:
    """A ``render_request`` whose replies come back on ``render_reply/<requester>/<server>``."""
    return Message(
        topic=topic or f"render_request/{requester}",
        type="render_request",
        seq=max(request_id, 0),
        meta={
            "width": int(width),
            "height": int(height),
            "request_id": int(request_id),
            "what": list(what),
            "reply_to": requester,
            **(meta or {}),
        },
        arrays={
            "K": np.ascontiguousarray(K, np.float64),
            "T_world_cam": np.ascontiguousarray(T_world_cam, np.float64),
        },
    )


def reply_server(requester: str, msg: Message) -> str | None:
    """The server a render reply addressed to ``requester`` came from; None if not for us."""
    prefix = f"render_reply/{requester}/"
    return msg.topic[len(prefix) :] if msg.topic.startswith(prefix) else None
