"""A node process for the shutdown test: ``node_proc.py IN_ADDRESS OUT_ADDRESS READY_FILE``.

Binds a latest-only input and output, writes READY_FILE once its sockets are up, then runs the
node loop until SIGINT/SIGTERM; the exit code is the run loop's (0 on a clean stop).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from gsfix_online.runtime.config import EndpointConfig, NodeRuntimeConfig, TransportConfig
from gsfix_online.runtime.node import Node
from gsfix_online.runtime.zmq_transport import ZmqTransport


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")
    in_addr, out_addr, ready = argv
    config = TransportConfig(
        inputs=(EndpointConfig(in_addr, bind=True),),
        outputs=(EndpointConfig(out_addr, bind=True),),
        linger_s=0.5,
    )
    node = Node(
        "proc",
        ZmqTransport(config, name="proc"),
        {"rgbd": lambda msg: None},
        NodeRuntimeConfig(heartbeat_period_s=0.05, poll_timeout_ms=50),
    )
    Path(ready).write_text("ready")
    return node.run()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
