"""Shared fixtures: small posed RGB-D sequences generated in the test, never downloaded.

One thread per test process: the tests' tensors are tiny, and on a 2-core machine a second
intra-op thread only spins against the other process (pytest-xdist's second worker, or the node
processes a graph test starts): measured up to 15-20x slower steps (see
tests/mapping/splat/test_render_stress.py). ``OMP_NUM_THREADS`` is set before torch is imported,
so the node processes the tests start inherit it; a value already set is kept.
"""

from __future__ import annotations

import json
import os
from collections import OrderedDict
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame

T0_NS = 1_700_000_000_000_000_000


def make_frames(
    n: int = 8,
    width: int = 40,
    height: int = 30,
    gray: bool = False,
    seed: int = 0,
    fps: float = 10.0,
) -> list[RGBDFrame]:
    """Random-texture frames on a smooth camera path; depth 0.4..6 m with ~5% invalid pixels."""
    rng = np.random.default_rng(seed)
    K = Intrinsics(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    frames = []
    for i in range(n):
        shape = (height, width) if gray else (height, width, 3)
        color = rng.integers(0, 256, shape, dtype=np.uint8)
        depth = rng.uniform(0.4, 6.0, (height, width)).astype(np.float32)
        depth[rng.random((height, width)) < 0.05] = 0.0
        a = 0.3 * i
        T = look_at([np.cos(a), np.sin(a), 0.2 * i], [0.0, 0.0, 1.0])
        frames.append(make_frame(color, depth, K, T, T0_NS + int(i * 1e9 / fps), seq=i))
    return frames


@pytest.fixture
def frames() -> list[RGBDFrame]:
    return make_frames()


@pytest.fixture
def gray_frames() -> list[RGBDFrame]:
    return make_frames(gray=True, seed=1)


# How ``make test`` shares the suite between its two pytest-xdist workers (``-n 2 --dist
# loadfile``): a module's tests go to one worker (its module fixtures are built once), except
# that the modules that time what happens on sockets and in small graphs of node processes are
# one unit (they run one after another, never beside each other, as loaded as in a serial run),
# and the repair-graph modules are split test by test (each test is a whole graph run of half a
# minute, independent of the others: a module of them would keep one worker busy for minutes).
TIMING_MODULES = frozenset(
    {
        "tests/apps/test_client.py",
        "tests/faults/test_kill_restart.py",
        "tests/faults/test_slow_consumer_memory.py",
        "tests/nodes/test_graph_processes.py",
        "tests/nodes/test_slow_consumer.py",
        "tests/runtime/test_liveness.py",
        "tests/runtime/test_zmq_transport.py",
    }
)
GRAPH_MODULES = frozenset(
    {
        "tests/faults/test_repair_kill.py",
        "tests/jobs/bench/test_bench.py",
        "tests/jobs/test_repair_run.py",
        "tests/services/test_live_map_graph.py",
    }
)


def work_unit(nodeid: str) -> str:
    """The unit of work a test belongs to under ``make test`` (see above)."""
    module = nodeid.split("::", 1)[0]
    if module in TIMING_MODULES:
        return "timing"
    return nodeid if module in GRAPH_MODULES else module


# Measured wall seconds of the suite's slower tests under ``make test``, to hand the longest
# units out first: in collection order (xdist's default puts units of many tests first) the
# last graph tests ran alone at the end while the other worker idled, 73 s of a 589 s run.
# Refresh after adding slow tests: ``python benchmarks/pytest_times.py --record
# tests/test_times.json times.jsonl`` (the command on benchmarks/results/test_speed_cpu.md).
TEST_TIMES = Path(__file__).with_name("test_times.json")


def read_test_times(path: Path = TEST_TIMES) -> dict[str, float]:
    """{test id: seconds}; empty without the file (the order is then xdist's)."""
    return json.loads(path.read_text()) if path.is_file() else {}


class LongestFirst(OrderedDict):
    """xdist's queue of work units ({unit: {test id: done}}) that hands out the unit of the
    most recorded seconds first (longest-processing-time scheduling), in queue order among
    units of equal time (tests without a record count 0)."""

    def __init__(self, seconds: dict[str, float]) -> None:
        super().__init__()
        self.seconds = seconds

    def cost(self, unit: str) -> float:
        return sum(self.seconds.get(test, 0.0) for test in self[unit])

    def popitem(self, last: bool = True) -> tuple[str, dict[str, bool]]:
        if last or not self:
            return super().popitem(last)
        unit = max(self, key=self.cost)  # the first of the longest: max keeps the first
        return unit, self.pop(unit)


class _Units:
    """xdist's scheduler hook, registered only where xdist is installed (pytest refuses a
    conftest hook it does not know)."""

    @staticmethod
    def pytest_xdist_make_scheduler(config: pytest.Config, log):
        """``--dist loadfile`` with the units of :func:`work_unit`. (Not ``xdist_group`` marks:
        xdist 3.8 renames the marked tests through an attribute pytest 9 no longer reads.)"""
        if config.getvalue("dist") != "loadfile":
            return None
        from xdist.scheduler import LoadFileScheduling

        class Units(LoadFileScheduling):
            def __init__(self, config: pytest.Config, log=None) -> None:
                super().__init__(config, log)
                self.workqueue = LongestFirst(read_test_times())

            def _split_scope(self, nodeid: str) -> str:
                return work_unit(nodeid)

        return Units(config, log)


def pytest_configure(config: pytest.Config) -> None:
    if config.pluginmanager.hasplugin("xdist"):
        config.pluginmanager.register(_Units(), "gsfix-test-units")
