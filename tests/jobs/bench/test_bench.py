"""``gsfix-online bench``: the Pareto front on hand-made points, the knob and skip tables, and the
sweep machinery on a tiny tank with real repair-graph runs (rows, CSV, JSON, resume, plot)."""

from __future__ import annotations

import copy
import csv
import io
import json
import math
from pathlib import Path

import cv2
import pytest

from gsfix_online.apps.cli import main
from gsfix_online.jobs.bench.knobs import KNOBS, QUICK, one_at_a_time, overrides_for
from gsfix_online.jobs.bench.pareto import front_gap, pareto_front, plot_fronts
from gsfix_online.jobs.bench.runner import _StampedLog
from gsfix_online.jobs.bench.skips import SKIPS, skip_table, to_markdown, verdict
from gsfix_online.jobs.bench.sweep import (
    BenchInput,
    Results,
    RunSpec,
    knob_runs,
    run_key,
    run_sweep,
    ship_tank_input,
)
from gsfix_online.runtime.graph import load_graph
from tests.jobs.test_repair_run import EAGER, FAST

# -- Pareto fronts ------------------------------------------------------------------------------


def test_pareto_front_of_hand_made_points():
    #          0     1     2    3     4     5     6
    t = [10.0, 20.0, 15.0, 5.0, 30.0, None, 15.0]
    e = [3.0, 1.0, 2.0, 4.0, 1.0, 0.0, 2.5]
    # 3 (fastest), 0, 2, 1 improve in turn; 4 is as good as 1 but slower; 5 has no time; 6 is
    # as fast as 2 and worse
    assert pareto_front(t, e) == [3, 0, 2, 1]
    assert pareto_front([1.0, 1.0], [2.0, 2.0]) == [0]  # equal points: the first
    assert pareto_front([], []) == []
    assert pareto_front([1.0, math.nan], [1.0, 0.0]) == [0]
    with pytest.raises(ValueError, match="differ in length: 2 != 1"):
        pareto_front([1.0, 2.0], [1.0])


def test_front_gap_is_zero_on_the_front_and_the_error_lost_behind_it():
    t = [10.0, 20.0, 15.0, 12.0]
    e = [3.0, 1.0, 2.0, 3.5]
    assert front_gap(t, e, 0) == 0.0 and front_gap(t, e, 1) == 0.0
    assert front_gap(t, e, 3) == pytest.approx(0.5)  # run 0 is faster and 0.5 better
    assert math.isnan(front_gap([None, 1.0], [1.0, 1.0], 0))


def test_plot_fronts_writes_a_png_with_one_panel_per_error_column(tmp_path: Path):
    rows = [
        {"knob": "default", "value": "", "total_s": 10.0, "psnr_final": 20.0, "depth_mae_cm": 4},
        {"knob": "kf_iters", "value": 4, "total_s": 14.0, "psnr_final": 21.0, "depth_mae_cm": 3},
        {"knob": "kf_iters", "value": 1, "total_s": 8.0, "psnr_final": 19.0},
    ]
    drawn = plot_fronts(rows, tmp_path / "p.png", "test")
    assert drawn == ["psnr_final", "depth_mae_cm"]  # the columns with two runs
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img.shape[1] > img.shape[0] > 200
    with pytest.raises(ValueError, match="no error column"):
        plot_fronts(rows[:1], tmp_path / "q.png", "test")


# -- the knob and skip tables -------------------------------------------------------------------


def test_every_knob_and_skip_override_is_a_valid_param_of_the_repair_graph():
    from gsfix_online.core.config import ConfigError, read_yaml
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH, apply_overrides
    from gsfix_online.runtime.graph import NodeEntry, node_params

    graph = load_graph(DEFAULT_GRAPH)
    for k in KNOBS.values():  # the default is the graph's value, as its node runs with it
        node, *path = k.keys[0].split(".")
        value = node_params(graph.nodes[node])
        for p in path:
            value = getattr(value, p)
        assert k.default == value and k.default not in k.values, k.name
    # every value of every knob, and every skip turned off, builds its node's params
    over = [o for k in KNOBS.values() for v in k.values for o in k.overrides(v)]
    over += [o for s in SKIPS if s.off for o in s.off]
    raw = read_yaml(DEFAULT_GRAPH)
    for o in over:
        g = copy.deepcopy(raw)
        apply_overrides(g, [o])
        name = o.split(".", 1)[0]
        e = g["nodes"][name]
        node_params(NodeEntry(kind=e["kind"], params=e["params"]), where=o)
    with pytest.raises(ConfigError, match="voxel_sise'; did you mean 'tsdf.tsdf.voxel_size'"):
        apply_overrides(copy.deepcopy(raw), ["tsdf.tsdf.voxel_sise=0.01"])  # checked at once


def test_one_at_a_time_runs_each_knob_value_beside_the_defaults():
    runs = one_at_a_time({"kf_iters": (1, 2, 4), "voxel_m": (0.04,)})
    assert runs == [{}, {"kf_iters": 1}, {"kf_iters": 4}, {"voxel_m": 0.04}]  # 2 is the default
    assert one_at_a_time({"finetune_steps": (40, 10)}, {"finetune_steps": 40}) == [
        {}, {"finetune_steps": 10},
    ]  # fmt: skip
    specs = knob_runs({"threads": (2,)})
    assert [s.label for s in specs] == [{"knob": "default", "value": ""},
                                        {"knob": "threads", "value": 2}]  # fmt: skip
    assert specs[1].overrides == ["splat.threads=2", "repair.threads=2"]
    assert overrides_for({"voxel_m": 0.04, "kf_iters": 1}) == [
        "tsdf.tsdf.voxel_size=0.04", "splat.mapper.kf_iters=1",
    ]  # fmt: skip
    with pytest.raises(ValueError, match="unknown knob.s. nope; known: voxel_m"):
        one_at_a_time({"nope": (1,)})
    assert set(QUICK) <= set(KNOBS) and all(len(v) == 2 for v in QUICK.values())


def test_skip_verdicts_follow_the_stated_judgement():
    assert verdict(0.3, -0.02) == "keep: no error cost"  # within the noise
    assert verdict(0.3, -0.25) == "keep: saves more time than it costs"  # 0.25 dB for 30 %
    assert verdict(0.1, -0.25) == "off: costs more error than it saves time"  # 0.25 dB for 10 %
    assert verdict(-0.1, -0.2) == "off: costs more error than it saves time"
    assert verdict(math.nan, 0.0) == "not measured"
    assert verdict(-0.1, 0.0) == "keep: no error cost, no time saved"
    base = {"cpu_s": 60.0, "total_s": 50.0, "psnr_final": 20.0, "psnr_output": 19.0}
    off = {"planner": {"cpu_s": 100.0, "total_s": 40.0, "psnr_final": 20.3, "psnr_output": 19.0}}
    table = skip_table(base, off)
    assert [e["skip"] for e in table] == [s.name for s in SKIPS]
    p = next(e for e in table if e["skip"] == "planner")
    assert (p["saved_s"], p["saved_frac"]) == (40.0, 0.4)
    assert p["psnr_final_change_db"] == pytest.approx(-0.3)  # 0.3 dB for 40 %
    assert p["verdict"] == "keep: saves more time than it costs"
    missing = next(e for e in table if e["skip"] == "distill_plateau")
    assert missing["verdict"] == "not in the library"
    md = to_markdown(table)
    assert md.count("\n") == len(SKIPS) + 1
    assert "| 60 / 100 | 40 s (40 %) | 50 / 40 | -0.30 | +0.00 |" in md and "CPU s with" in md
    wall = skip_table(base, off, "total_s")
    assert next(e for e in wall if e["skip"] == "planner")["saved_s"] == -10.0


def test_stage_lines_are_stamped_a_start_at_its_first_line_an_end_at_its_last():
    out = io.StringIO()
    log = _StampedLog(out)
    log.write("[trainer] INFO x: trainer: end of the input (10 frames): run 1 starts\n[trai")
    start = log.marks["finetune_start"]
    log.write("ner] INFO x: trainer: run 1 stopped (max_steps) at step 4\n")
    end = log.marks["finetune_end"]
    log.write("[trainer] INFO x: trainer: idle after the end of the input (1 run)\n")
    log.write("[trainer] INFO x: trainer: end of the input (10 frames): again\n")
    log.write("[splat] INFO x: run 2 stopped (max_steps)\n")  # another node's line
    assert log.marks == {"finetune_start": start, "finetune_end": end} and end >= start
    assert out.getvalue().count("\n") == 5  # every line forwarded


def test_a_finished_row_of_another_sweep_is_borrowed_and_no_run_runs_nothing(tmp_path: Path):
    inp = BenchInput(tmp_path / "log.mcap", tmp_path / "views.txt", name="x")
    specs = [RunSpec({"skip": "none (defaults)"}), RunSpec({"skip": "planner"}, ["a.b=1"])]
    other = Results(tmp_path / "quick.json", {})
    other.put({"key": run_key(inp, ["t.s=20"], RunSpec({"knob": "default"})), "rc": 0,
               "knob": "default", "total_s": 5.0})  # fmt: skip
    results = Results(tmp_path / "skips.json", {})
    said: list[str] = []
    rows = run_sweep(inp, specs, ["t.s=20"], tmp_path, results, None, said.append,
                     borrow=(other,), run=False)  # fmt: skip
    assert said == [] and len(rows) == 1  # the planner run is not done, and was not run
    assert rows[0]["skip"] == "none (defaults)" and rows[0]["total_s"] == 5.0
    assert json.loads(results.path.read_text())["rows"] == rows


# -- the sweep on a tiny tank, as real processes ------------------------------------------------


def test_sweep_runs_writes_rows_and_resumes_without_running_again(tmp_path: Path):
    inp = ship_tank_input(tmp_path / "work", 80, 60, 10, views=2)
    assert inp.depth_gt is not None and inp.gt_mesh is not None and inp.gt_mesh.is_file()
    specs = knob_runs({"distill_passes": (1, 0)}, {"distill_passes": 1})
    base = [*FAST, *EAGER, "splat.refine_at_input_end=10"]
    results = Results(tmp_path / "res" / "b.json", {"command": "test"})
    said: list[str] = []
    rows = run_sweep(inp, specs, base, tmp_path / "work", results, 300, said.append)

    # 1. A finished row per run: its knob, times, memory, scores
    assert [(r["knob"], r["value"], r["rc"]) for r in rows] == [
        ("default", "", 0), ("distill_passes", 0, 0),
    ], [r.get("error") for r in rows]  # fmt: skip
    for r in rows:
        assert r["frames"] == 10 and (r["width"], r["height"], r["n_views"]) == (80, 60, 2)
        assert 0 < r["map_s"] < r["total_s"] and r["finetune_s"] > 0 and r["fix_s"] > 0
        assert r["cpu_s"] > 5  # 7 node processes importing torch
        assert r["peak_rss_mb"] > r["peak_node_rss_mb"] > 50  # several torch processes
        for col in ("psnr_gs", "psnr_fixed", "psnr_output", "psnr_final"):
            assert 5 < r[col] < 60, (col, r[col])
        assert 0 <= r["ssim_final"] <= 1 and r["repaired"] == 2
        assert 0 < r["depth_mae_cm"] < 100
        assert 0 < r["mesh_accuracy_cm"] < 20 and 0 < r["mesh_completeness_cm"] < 200
    assert rows[1]["overrides"] == ["splat.distill_passes=0"]
    # no passes after the repairs (their wall time, not distill_s: with the compiled
    # rasterizer a pass over this 80x60 map takes about as long as the noise between runs)
    assert rows[0]["passes_s"] > 0 and rows[1]["passes_s"] == 0

    # 2. The JSON and CSV hold the same rows
    doc = json.loads(results.path.read_text())
    assert doc["command"] == "test" and [r["key"] for r in doc["rows"]] == [r["key"] for r in rows]
    table = list(csv.DictReader(io.StringIO(results.path.with_suffix(".csv").read_text())))
    assert [(t["knob"], t["value"]) for t in table] == [("default", ""), ("distill_passes", "0")]
    assert float(table[1]["total_s"]) == pytest.approx(rows[1]["total_s"], rel=1e-3)
    assert list(table[0])[:4] == ["knob", "value", "rc", "total_s"]

    # 3. Resume: a new call with the same runs runs nothing and returns the same rows
    said.clear()
    again = run_sweep(inp, specs, base, tmp_path / "work", Results(results.path, {}), 300,
                      said.append)  # fmt: skip
    assert said == [] and again == rows
    # ... a run it lacks is run alone
    more = knob_runs({"distill_passes": (1, 0, 2)}, {"distill_passes": 1})
    results2 = Results(results.path, {})
    assert [results2.done(k) for k in (r["key"] for r in rows)] == [True, True]
    assert len(more) == 3


def test_bench_command_errors_name_the_bad_argument(tmp_path: Path, capsys):
    assert main(["bench", "--views", str(tmp_path), "--results", str(tmp_path)]) == 2
    assert (
        "--views, --views-gt, --views-depth and --gt-mesh need --input" in capsys.readouterr().err
    )
    args = ["bench", "--knobs", "nope", "--work", str(tmp_path), "--results", str(tmp_path),
            "--frames", "4", "--width", "40", "--height", "30", "--n-views", "1"]  # fmt: skip
    assert main(args) == 2
    assert "unknown knob(s) nope" in capsys.readouterr().err
    bad = tmp_path / "b.json"
    bad.write_text("[1]")
    args = ["bench", "--quick", "--name", "b", "--work", str(tmp_path), "--results",
            str(tmp_path), "--frames", "4", "--width", "40", "--height", "30", "--n-views", "1"]  # fmt: skip
    assert main(args) == 2
    assert "is not a bench results file" in capsys.readouterr().err
