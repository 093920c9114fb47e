"""gsfix-online stress: the timed long run, its table and JSON, and failure reporting."""

from __future__ import annotations

import json

from hypothesis import strategies as st

from gsfix_online.apps.cli import main
from gsfix_online.jobs.stress import Property
from gsfix_online.jobs.stress.runner import StressSummary, run_property


def test_stress_command_runs_geometry_for_its_budget_and_writes_the_table(tmp_path, capsys):
    out = tmp_path / "stress.json"
    rc = main(["stress", "--minutes", "0.01", "--area", "geometry", "--no-progress",
               "--out", str(out), "--seed", "3"])  # fmt: skip
    assert rc == 0
    text = capsys.readouterr().out
    assert "geometry.look_at" in text and "0 failed" in text and "(seed 3)" in text
    data = json.loads(out.read_text())
    names = [p["name"] for p in data["properties"]]
    assert names[0] == "geometry.quat_to_rotation" and len(names) == 6
    assert all(p["examples"] > 0 and p["failures"] == 0 for p in data["properties"])


def test_a_failing_property_is_shrunk_to_its_smallest_input_and_reported():
    def check(x: int) -> None:
        assert x < 7, f"x = {x} is too big"

    prop = Property("demo.small", "x < 7", lambda: st.integers(0, 1000), check, ci_examples=50)
    run = run_property(prop)
    assert run.failures == 1 and run.example == "7"
    assert run.failure == "AssertionError: x = 7 is too big"
    table = StressSummary(1.0, 0, [run]).table()
    assert "demo.small" in table and "1 failed" in table and "x = 7 is too big" in table


def test_bad_minutes_is_a_one_line_error(capsys):
    assert main(["stress", "--minutes", "0", "--no-progress"]) == 2
    assert (
        capsys.readouterr().out.strip()
        == "gsfix-online stress: error: minutes must be positive, got 0.0"
    )
