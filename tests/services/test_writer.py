"""The repair writer's component: what the splat node's export announcement adds to a run."""

from __future__ import annotations

import json
import logging

import pytest

from gsfix_online.runtime import Message
from gsfix_online.services.writer import Params, WriterService
from tests.apps.run_data import make_run


def exported(writer: WriterService, kept: object) -> Message:
    return Message("export/splat", "map_event", meta={
        "kind": "exported", "path": str(writer.map_dir / "point_cloud"), "keyframes_kept": kept,
    })  # fmt: skip


def test_the_keyframes_kept_reach_metrics_and_the_report_and_a_loss_is_warned_of(
    tmp_path, caplog
) -> None:
    run = make_run(tmp_path, n_views=1, gt=False)
    writer = WriterService("writer", Params(out_dir=str(run)), 0.0)
    rows = [
        {"keyframe_id": 1, "view_id": -1, "before_db": 31.0, "after_db": 29.0},  # no neighbour
        {"keyframe_id": 3, "view_id": 0, "before_db": 30.0, "after_db": 29.95},
        {"keyframe_id": 5, "view_id": 2, "before_db": 28.0, "after_db": 27.5},
        {"keyframe_id": 8, "view_id": 2, "before_db": 25.0, "after_db": 25.25},
    ]
    writer.on_map_event(exported(writer, json.dumps(rows)))
    assert writer.files["map"] == "map"
    with caplog.at_level(logging.WARNING):
        m = writer.write(1.0)

    kept = m["keyframes_kept"]
    assert [r["keyframe_id"] for r in kept["keyframes"]] == [1, 3, 5, 8]
    assert [r["change_db"] for r in kept["keyframes"]] == pytest.approx([-2.0, -0.05, -0.5, 0.25])
    # the bound is on the repaired views' neighbours; every keyframe is summed up beside it
    assert kept["median_change_db"] == pytest.approx(-0.05)
    assert kept["worst_change_db"] == pytest.approx(-0.5)
    assert kept["lost"] == [5] and kept["lost_above_db"] == 0.1  # 0.05 dB is within the bound
    assert kept["all_median_change_db"] == pytest.approx(-0.275)
    assert kept["all_worst_change_db"] == pytest.approx(-2.0)
    assert json.loads((run / "metrics.json").read_text())["keyframes_kept"] == kept
    report = (run / "report.html").read_text()
    assert "Input keyframes: their render before the repaired views were distilled" in report
    warned = [r.getMessage() for r in caplog.records if "keyframes_kept" in r.getMessage()]
    assert (
        len(warned) == 1
        and "input keyframes 5, next to repaired views, more than 0.1 dB" in warned[0]
    ), warned


def test_a_measured_keyframe_the_map_no_longer_stores_is_listed_gone_not_counted(
    tmp_path, caplog
) -> None:
    """A row whose after_db is null (a later input keyframe evicted it) has no change: it is
    listed in ``gone``, left out of the figures and warned of; the report says so."""
    run = make_run(tmp_path, n_views=1, gt=False)
    writer = WriterService("writer", Params(out_dir=str(run)), 0.0)
    rows = [
        {"keyframe_id": 3, "view_id": 0, "before_db": 30.0, "after_db": 30.5},
        {"keyframe_id": 4, "view_id": 0, "before_db": 30.0, "after_db": None},
        {"keyframe_id": 6, "view_id": -1, "before_db": 28.0, "after_db": 27.0},
    ]
    writer.on_map_event(exported(writer, json.dumps(rows)))
    with caplog.at_level(logging.WARNING):
        m = writer.write(1.0)
    kept = m["keyframes_kept"]
    assert kept["gone"] == [4] and kept["lost"] == []
    assert [r["change_db"] for r in kept["keyframes"]] == pytest.approx([0.5, None, -1.0])
    assert kept["median_change_db"] == pytest.approx(0.5) and kept["worst_change_db"] == 0.5
    assert kept["all_median_change_db"] == pytest.approx(-0.25)
    assert "no longer stored" in (run / "report.html").read_text()
    warned = [r.getMessage() for r in caplog.records if "no longer stores" in r.getMessage()]
    assert len(warned) == 1 and "input keyframes 4," in warned[0], warned


@pytest.mark.parametrize(
    "kept",
    ["not json", json.dumps({"keyframe_id": 1}), json.dumps([{"keyframe_id": 1, "view_id": 0}]),
     json.dumps([{"keyframe_id": 1, "view_id": 0, "before_db": "30", "after_db": 29.0}]),
     json.dumps([{"keyframe_id": 1, "view_id": 0, "before_db": None, "after_db": 29.0}]),
     json.dumps([{"keyframe_id": 1, "view_id": 0, "before_db": 30.0}])],
)  # fmt: skip
def test_malformed_keyframes_kept_are_refused_in_one_line_and_the_run_written_without(
    tmp_path, caplog, kept
) -> None:
    run = make_run(tmp_path, n_views=1, gt=False)
    writer = WriterService("writer", Params(out_dir=str(run)), 0.0)
    with caplog.at_level(logging.WARNING):
        writer.on_map_event(exported(writer, kept))
    refused = [r.getMessage() for r in caplog.records if "keyframes_kept must be" in r.getMessage()]
    assert len(refused) == 1 and "\n" not in refused[0] and "export/splat" in refused[0]
    assert writer.files["map"] == "map"  # the map itself is taken
    m = writer.write(1.0)
    assert "keyframes_kept" not in m
