"""Whether the receiver of a reliable link is there: the rule for how long a sender waits.

A reliable sender blocks while its receiver is behind, and how long it may wait depends only on
whether the receiver is alive, never on how slow it is (a splat node distils a view for minutes
between reads; an offline replay must wait for it, and drop nothing). So a blocked send or flush:

- waits without a deadline while the receiver is **connected**;
- waits up to ``reliable_connect_timeout_s`` (from the link's creation) for a receiver that has
  **not connected yet** (a node still importing torch);
- waits up to ``reliable_send_timeout_s`` (from the disconnect) for a receiver that **has gone**
  to come back (a launcher may restart it; the link resends what was lost), then raises
  :class:`TransportTimeout` naming the receiver and how many messages are unacknowledged.

"Connected" is libzmq's own view, read from the sender's socket monitor:
``EVENT_HANDSHAKE_SUCCEEDED`` (a receiver completed the ZMTP handshake) and
``EVENT_DISCONNECTED``. Not ``EVENT_CONNECTED``: the kernel of a frozen process still accepts
connections, so only a finished handshake proves a live peer. A process that dies closes its
sockets, which is seen at once; a frozen process or a lost network is seen through ZMTP
heartbeats (``HEARTBEAT_IVL``/``HEARTBEAT_TIMEOUT`` on the sender's socket). Heartbeats are
answered by the receiver's libzmq I/O thread, not by its application thread, so a node busy in a
handler stays connected, provided its inbound pipe never fills (libzmq stops reading a
connection whose pipe is full, heartbeats included): the sender holds at most
``reliable_window`` messages, below the receiver's ``reliable_hwm``, and does not resend while
the receiver has stayed connected (:meth:`PeerWatch.take_dropped`), since a live ZMTP connection
loses nothing.

Every wait that lasts longer than :data:`WAIT_LOG_FIRST_S` logs one plain line saying what it
waits for, and repeats it every :data:`WAIT_LOG_EVERY_S`.
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass, field
from typing import Literal

import zmq

from gsfix_online.runtime.transport import TransportTimeout

logger = logging.getLogger(__name__)

WAIT_LOG_FIRST_S = 10.0  # a blocked send or flush says what it waits for after this long
WAIT_LOG_EVERY_S = 30.0  # and again this often while it still waits

PeerState = Literal["never", "up", "down"]  # not connected yet, connected, gone

_UP = int(getattr(zmq, "EVENT_HANDSHAKE_SUCCEEDED", zmq.EVENT_CONNECTED))  # libzmq < 4.3
_DOWN = int(zmq.EVENT_DISCONNECTED)
_EVENT = struct.Struct("=H")  # native byte order, as libzmq writes it
MONITOR_EVENTS = _UP | _DOWN  # few: read only now and then (a send blocked, a resend due)


def _clock_time(mono: float) -> str:
    """Wall-clock HH:MM:SS of a ``time.monotonic()`` instant, for log lines."""
    return time.strftime("%H:%M:%S", time.localtime(time.time() - (time.monotonic() - mono)))


@dataclass
class Wait:
    """One blocked send or flush: when it began and when it logs next."""

    what: str  # "send" or "flush", for the log line
    started: float  # time.monotonic()
    next_log: float = field(init=False)

    def __post_init__(self) -> None:
        self.next_log = self.started + WAIT_LOG_FIRST_S


class PeerWatch:
    """The receiver of one reliable link as the sender's socket monitor reports it.

    ``monitor``: the PAIR socket of ``sock.get_monitor_socket(MONITOR_EVENTS)``, set up before
    the sender connects so that no event is missed. ``sender`` names this node, ``peer`` the
    receiving node and ``output`` the output, as the graph calls them ("" where unknown).
    """

    def __init__(
        self,
        monitor: zmq.Socket,
        sender: str,
        address: str,
        peer: str,
        output: str,
        connect_timeout_s: float,
        absent_timeout_s: float,
        now: float,
    ) -> None:
        self.monitor = monitor
        self.sender = sender
        self.address = address
        if peer:
            via = f"output {output!r}, " if output else ""
            self.label = f"node {peer!r} ({via}{address})"
        else:
            self.label = f"the receiver at {address}"
        self.connect_timeout_s = connect_timeout_s
        self.absent_timeout_s = absent_timeout_s
        self.state: PeerState = "never"
        self.since = now  # when ``state`` began (as first seen by this sender)
        self._dropped = False  # a disconnect seen since the last take_dropped()

    def poll(self, now: float) -> PeerState:
        """Read the monitor's events; the receiver's state now."""
        while True:
            try:
                frames = self.monitor.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return self.state
            (event,) = _EVENT.unpack_from(frames[0])  # uint16 event, then a uint32 value
            if event == _UP and self.state != "up":
                if self.state == "down":
                    logger.info(
                        "%s: %s is connected again after %.1f s",
                        self.sender, self.label, now - self.since,
                    )  # fmt: skip
                self.state, self.since = "up", now
            elif event == _DOWN:
                self._dropped = True
                if self.state != "down":
                    if self.state == "up":
                        logger.warning(
                            "%s: %s disconnected (a blocked send waits %.0f s for it to return)",
                            self.sender, self.label, self.absent_timeout_s,
                        )  # fmt: skip
                    self.state, self.since = "down", now

    def take_dropped(self) -> bool:
        """Whether the receiver disconnected since the last call (then what was in flight may
        be lost: resend it); False while it stayed connected (nothing was lost: don't)."""
        self.poll(time.monotonic())
        dropped, self._dropped = self._dropped, False
        return dropped

    def check(self, wait: Wait, unacked: int, now: float) -> None:
        """Called while ``wait`` is blocked: raise :class:`TransportTimeout` if the receiver has
        been absent too long, else log what it waits for when a log line is due."""
        state = self.poll(now)
        absent = now - self.since
        if state == "never" and absent > self.connect_timeout_s:
            why = (
                f"has not connected in {absent:.1f} s (reliable_connect_timeout_s "
                f"{self.connect_timeout_s:g}): is it running, at this address?"
            )
        elif state == "down" and absent > self.absent_timeout_s:
            why = (
                f"disconnected at {_clock_time(self.since)} and has not come back within "
                f"{self.absent_timeout_s:g} s (reliable_send_timeout_s): the process is gone, "
                "or its host stopped answering heartbeats"
            )
        else:
            why = ""
        if why:
            raise TransportTimeout(
                f"{self.sender}: reliable {wait.what} to {self.label} failed: it {why}; "
                f"{unacked} messages unacknowledged"
            )
        if now < wait.next_log:
            return
        wait.next_log = now + WAIT_LOG_EVERY_S
        waited = f"waiting since {_clock_time(wait.started)} ({now - wait.started:.0f} s)"
        if state == "up":
            logger.info(
                "%s: reliable %s: waiting for %s to acknowledge %d messages; it is connected "
                "(busy), %s",
                self.sender, wait.what, self.label, unacked, waited,
            )  # fmt: skip
        else:
            limit = self.connect_timeout_s if state == "never" else self.absent_timeout_s
            status = "has not connected yet" if state == "never" else "is disconnected"
            log = logger.info if state == "never" else logger.warning
            log(
                "%s: reliable %s: %s %s (%d messages unacknowledged), %s; giving up in %.0f s",
                self.sender, wait.what, self.label, status, unacked, waited, limit - absent,
            )  # fmt: skip
