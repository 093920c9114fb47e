"""Render requests between nodes, as messages: who asked, and where the reply goes.

A request names its sender (``reply_to``); servers reply on ``render_reply/<requester>/<server>``,
so each requester subscribes to its own namespace. Pure functions on messages, no sockets.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
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


# A render request's size is checked before anything is allocated: the wire allows up to
# 65535 x 65535, which would ask a node for tens of GB of images.
MAX_RENDER_PIXELS = 4096 * 4096


def render_size(request: Message, max_pixels: int = MAX_RENDER_PIXELS) -> tuple[int, int]:
    """(width, height) of a ``render_request``; ValueError when it asks for more than
    ``max_pixels`` pixels."""
    w, h = int(request.meta["width"]), int(request.meta["height"])
    if w * h > max_pixels:
        raise ValueError(
            f"render_request {w}x{h} asks for {w * h} pixels, above the limit of {max_pixels}"
        )
    return w, h


# the longest file or folder name a message may use: file systems hold 255 bytes, and the atomic
# writer's temporary file adds a prefix and a suffix to it
MAX_NAME_BYTES = 200


def path_inside(name: object, root: str | Path, what: str = "path") -> Path:
    """The path a message names, which must lie inside ``root`` once ``..`` and symbolic links
    are resolved (a relative name is taken from ``root``). A name received over the wire never
    becomes a path outside the node's folder: ValueError naming both otherwise."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise ValueError(f"{what} must be a non-empty string without NUL, got {name!r}")
    longest = max(len(part.encode()) for part in Path(name).parts)
    if longest > MAX_NAME_BYTES:  # the atomic writer's temporary name adds a few bytes more
        raise ValueError(f"{what} has a name of {longest} bytes, more than {MAX_NAME_BYTES}")
    base = Path(root).resolve()
    target = (base / name).resolve()  # an absolute name replaces base
    if not target.is_relative_to(base):
        raise ValueError(f"{what} {name!r} from a message is outside {base}")
    return target
