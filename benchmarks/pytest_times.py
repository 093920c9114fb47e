"""A pytest plugin that records each test's wall time and CPU time (its own process plus the
child processes it waited for), so the slowest tests can be found on a shared machine, where
wall time follows the load and CPU time does not.

Run: ``PYTHONPATH=$PWD .venv/bin/python -m pytest -p benchmarks.pytest_times tests/jobs``; the
times go to ``$GSFIX_TEST_TIMES`` (default ``test_times.jsonl``), one JSON line per test phase
(setup, call, teardown) with the worker's name under xdist, and the load average at the start.
``python benchmarks/pytest_times.py FILE [FILE ...]`` prints the slowest tests and the totals per
folder; ``--record OUT FILE [FILE ...]`` writes the slower tests' times as JSON for
``tests/test_times.json``.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _record(item: pytest.Item, phase: str, wall_s: float, cpu_s: float) -> None:
    row = {
        "test": item.nodeid,
        "phase": phase,
        "wall_s": round(wall_s, 3),
        "cpu_s": round(cpu_s, 3),
        "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
        "load1": round(os.getloadavg()[0], 2),
    }
    path = Path(os.environ.get("GSFIX_TEST_TIMES", "test_times.jsonl"))
    with path.open("a") as f:  # one short line per write: workers append without tearing
        f.write(json.dumps(row) + "\n")


def _timed(item: pytest.Item, phase: str):
    t0, c0 = time.perf_counter(), _cpu_s()
    yield
    _record(item, phase, time.perf_counter() - t0, _cpu_s() - c0)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item: pytest.Item):
    yield from _timed(item, "setup")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    yield from _timed(item, "call")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item):
    yield from _timed(item, "teardown")


def summarize(paths: list[Path], top: int = 15) -> str:
    """The slowest tests (setup + call + teardown) and the totals per test folder."""
    tests: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
    for path in paths:
        for line in path.read_text().splitlines():
            r = json.loads(line)
            t = tests[r["test"]]
            t[0] += r["wall_s"]
            t[1] += r["cpu_s"]
            t[2] = max(t[2], r["load1"])
    folders: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
    for name, (wall, cpu, _) in tests.items():
        parts = name.split("::")[0].split("/")
        folder = "/".join(parts[:2]) if len(parts) > 2 else parts[0]
        f = folders[folder]
        f[0] += wall
        f[1] += cpu
        f[2] += 1
    lines = [f"{'wall s':>8} {'cpu s':>8} {'load':>5}  slowest tests"]
    for name, (wall, cpu, load) in sorted(tests.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"{wall:8.1f} {cpu:8.1f} {load:5.1f}  {name}")
    lines.append(f"\n{'wall s':>8} {'cpu s':>8} {'tests':>5}  folder")
    for name, (wall, cpu, n) in sorted(folders.items(), key=lambda kv: -kv[1][0]):
        lines.append(f"{wall:8.1f} {cpu:8.1f} {int(n):5d}  {name}")
    return "\n".join(lines)


def record(paths: list[Path], least_s: float = 0.5) -> dict[str, float]:
    """{test id: wall seconds (setup + call + teardown)} of the tests of at least ``least_s``,
    for ``tests/test_times.json`` (the order ``make test`` hands its units out in)."""
    tests: dict[str, float] = defaultdict(float)
    for path in paths:
        for line in path.read_text().splitlines():
            r = json.loads(line)
            tests[r["test"]] += r["wall_s"]
    return {k: round(v, 1) for k, v in sorted(tests.items()) if v >= least_s}


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--record"] and len(args) > 2:
        out = Path(args[1])
        out.write_text(json.dumps(record([Path(p) for p in args[2:]]), indent=0) + "\n")
        print(f"wrote {out}")
    else:
        print(summarize([Path(p) for p in args]))
