"""How ``make test`` hands its work units to the two workers: the longest recorded first."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import GRAPH_MODULES, LongestFirst, read_test_times, work_unit


def test_the_unit_of_the_most_recorded_seconds_goes_first_and_ties_keep_queue_order():
    q = LongestFirst({"a.py::t1": 1.0, "a.py::t2": 2.0, "g.py::t": 30.0, "b.py::t": 3.0})
    for unit, tests in (("a.py", ["a.py::t1", "a.py::t2"]), ("c.py", ["c.py::t"]),
                        ("g.py", ["g.py::t"]), ("b.py", ["b.py::t"]), ("d.py", ["d.py::t"])):  # fmt: skip
        q[unit] = dict.fromkeys(tests, False)
    order = [q.popitem(last=False)[0] for _ in range(len(q))]
    assert order == ["g.py", "a.py", "b.py", "c.py", "d.py"]  # 30, 3 (1 + 2), 3, 0, 0
    q["x.py"], q["y.py"] = {}, {}
    assert q.popitem()[0] == "y.py"  # the other end is a plain ordered dict's


def test_the_recorded_times_name_test_files_that_exist_and_cover_the_graph_tests():
    times = read_test_times()
    root = Path(__file__).parent.parent
    assert times and all((root / t.split("::")[0]).is_file() for t in times), "stale record"
    assert all(v > 0 for v in times.values())
    # the repair-graph modules make test runs have their tests recorded: they are the units
    # worth ordering (test_repair_kill is marked slow, and skipped there)
    recorded = {t.split("::")[0] for t in times}
    assert recorded >= GRAPH_MODULES - {"tests/faults/test_repair_kill.py"}
    assert work_unit(next(t for t in times if t.startswith("tests/jobs/test_repair_run.py")))
    assert read_test_times(root / "nonexistent.json") == {}
