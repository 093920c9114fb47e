"""A slow reliable receiver for the liveness tests: ``sink_proc.py BIND_ADDRESS READY_FILE DELAY_S``.

Binds one reliable input (``tcp://127.0.0.1:*`` picks a free port), writes its actual address
to READY_FILE, then runs the node loop with a handler that sleeps DELAY_S per ``heartbeat``
message (what the tests send): its main thread is busy, its libzmq I/O thread is not. Ends on
SIGINT/SIGTERM, or is killed by the test.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from gsfix_online.runtime.config import EndpointConfig, TransportConfig
from gsfix_online.runtime.node import Node
from gsfix_online.runtime.zmq_transport import ZmqTransport


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")
    address, ready, delay_s = argv[0], Path(argv[1]), float(argv[2])
    config = TransportConfig(inputs=(EndpointConfig(address, bind=True, mode="reliable"),))
    transport = ZmqTransport(config, name="sink")
    node = Node("sink", transport, {"heartbeat": lambda msg: time.sleep(delay_s)})
    tmp = ready.with_suffix(".tmp")
    tmp.write_text(transport.input_addresses[0])
    tmp.rename(ready)  # atomic: the test never reads half an address
    return node.run()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
