"""Per repaired view, does the final map keep what the view delivered? (issue 43's veil check)

For each repair run folder given, every view that was repaired and scored against ground truth:
the output's and the final map's PSNR (``metrics.json``), final - output in dB, and the
sharpness ratio of the final render over the output (``core.metrics.sharpness``, mean gradient
magnitude; under 0.9 is a veil). With several runs of the same scene (seeds), the per-view
medians over the runs follow, and the views that fail either bound (final more than 0.3 dB
below the output, or sharpness under 0.9). Beside each view, the sharpness ratio on the pixels
of each source of the output (``provenance.npz``): where the map loses the detail; and the
same ratio at half resolution (2x2 area means, "at 1/2"), which a veil lowers and the loss of
pixel-scale grain does not (a diagnostic: the bound is judged at full resolution). Where the
run's ground truth is found (a demo run: ``RUN/../scene/novel/color``), also how much of the
truth's edges the output and the final render reproduce at their contrast ("truth's edges":
``core.metrics.edge_gain``, the least-squares gain of their luma gradients on the truth's) and
the final's over the output's: a blur or a veil lowers it, dropping the output's grain, seams
and facets does not (the JSON also keeps "detail", the correlation of their 1-px high-pass luma
with the truth's). And the ratio the output itself would have through the
rasterizer's low-pass ("low-pass": the output blurred by the ``eps2d`` Gaussian every splat's
footprint is widened by, 0.3 px², over the output): what a map that rendered the output exactly
through that filter would score (a diagnostic: compositing can be a little sharper than it). And,
with no truth needed, how much of the output's edges the final render keeps at their contrast
where the output shows what was observed ("observed edges kept": ``edge_gain`` of the final on
the output over the pixels ``provenance.npz`` marks observed). And the floor: the output's and
the final map's PSNR over the run's best classical baseline (``summary.best_classical``), per
view, with the views under it.

    .venv/bin/python benchmarks/veil_table.py RUN1/repair RUN2/repair RUN3/repair \\
        [--json benchmarks/results/veil_demo_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

DB_BELOW_MAX = 0.3  # the final map at most this far under the output
SHARPNESS_MIN = 0.9  # and at least this sharp relative to it
MIN_SOURCE_SHARE = 0.02  # a source of the output's pixels gets its own sharpness above this share


def by_source(out, fin, prov: Path, truth=None) -> dict[str, float]:  # noqa: ANN001
    """Per source of the output (provenance.npz's ``source``: 3DGS render, mesh render,
    GSFixer, classical fill, ...) that covers at least MIN_SOURCE_SHARE of its pixels, on those
    pixels: ``sharpness_NAME``, the sharpness ratio (where the final map loses the output's
    detail), ``share_NAME`` and ``kept_NAME`` (``edge_gain`` of the final on the output); with
    the truth, ``truth_output_NAME`` and ``truth_final_NAME`` (their gains on the truth's)."""
    import numpy as np

    from gsfix_online.core.metrics import edge_gain, sharpness
    from gsfix_online.repair.provenance import SOURCES

    if not prov.is_file():
        return {}
    src = np.load(prov)["source"]
    rows = {}
    for i, name in enumerate(SOURCES):
        m = src == i
        base = sharpness(out, m) if m.mean() >= MIN_SOURCE_SHARE else 0.0
        if base <= 0:
            continue
        rows[f"sharpness_{name}"] = sharpness(fin, m) / base
        rows[f"share_{name}"] = float(m.mean())
        rows[f"kept_{name}"] = edge_gain(fin, out, m)
        if truth is not None:
            rows[f"truth_output_{name}"] = edge_gain(out, truth, m)
            rows[f"truth_final_{name}"] = edge_gain(fin, truth, m)
    return rows


def half(img):  # noqa: ANN001, ANN201 -- [H, W, 3] uint8 -> 2x2 area means, [H/2, W/2, 3]
    """The image at half resolution: its grain under 2 px averaged out, its veils kept (a
    diagnostic beside the bound, which is judged at full resolution)."""
    import cv2

    return cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)


def lowpass_ratio(img) -> float:  # noqa: ANN001 -- [H, W, 3] uint8
    """The sharpness an image keeps through the rasterizer's low-pass, over its own: the
    Gaussian blur of variance ``render_output.EPS2D`` that every splat's footprint carries."""
    from gsfix_online.core.metrics import sharpness
    from gsfix_online.mapping.splat.render_output import EPS2D

    return sharpness(img, footprint_px2=EPS2D) / sharpness(img)


def fine_detail(img):  # noqa: ANN001, ANN201 -- [H, W, 3] uint8 -> [H, W] float32, levels
    """An image's fine detail: its luma minus a 1-px Gaussian blur of it."""
    import cv2
    import numpy as np

    y = np.asarray(img, np.float32) @ np.float32([0.299, 0.587, 0.114])
    return y - cv2.GaussianBlur(y, (0, 0), 1.0)


def correlation(a, b) -> float:  # noqa: ANN001 -- arrays of one shape
    import numpy as np

    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def detail_vs_truth(img, gt) -> float:  # noqa: ANN001 -- [H, W, 3] uint8 each
    """The correlation of an image's fine detail with the truth's over the view (1: the same
    detail, 0: unrelated grain)."""
    return correlation(fine_detail(img), fine_detail(gt))


def view_rows(run: Path) -> dict[str, dict[str, float]]:
    """view name -> output_db, final_db, final_minus_output_db, sharpness, and the sharpness
    per source of the output's pixels (``by_source``, printed beside the table)."""
    import numpy as np

    from gsfix_online.core.metrics import edge_gain, sharpness
    from gsfix_online.repair.outputs import read_png_rgb

    rows = {}
    metrics = json.loads((run / "metrics.json").read_text())
    # the floor: the best of what the mesh and OpenCV alone give (the run's summary names it)
    classical = (metrics["summary"].get("best_classical") or {}).get("stage")
    for v in metrics["views"]:
        m = v.get("metrics") or {}
        if not v.get("repair") or "output" not in m or "final" not in m:
            continue
        out = read_png_rgb(run / "views" / v["view"] / "output.png")
        fin = read_png_rgb(run / "views" / v["view"] / "final.png")
        o, f = m["output"]["psnr_db"], m["final"]["psnr_db"]
        rows[v["view"]] = {"output_db": o, "final_db": f, "final_minus_output_db": f - o,
                           "sharpness": sharpness(fin) / sharpness(out),
                           "half_sharpness": sharpness(half(fin)) / sharpness(half(out)),
                           "lowpass": lowpass_ratio(out)}  # fmt: skip
        # the writer's measure (metrics.json map_sharpness): against the output through the
        # low-pass, what a map that holds it exactly renders
        rows[v["view"]]["map_sharpness"] = rows[v["view"]]["sharpness"] / rows[v["view"]]["lowpass"]
        if classical in m:
            c = m[classical]["psnr_db"]
            rows[v["view"]].update(output_minus_classical_db=o - c, final_minus_classical_db=f - c)
        gt = run.parent / "scene" / "novel" / "color" / f"{v['view']}.png"
        truth = read_png_rgb(gt, out.shape[1], out.shape[0]) if gt.is_file() else None
        if truth is not None:
            rows[v["view"]]["detail_output"] = detail_vs_truth(out, truth)
            rows[v["view"]]["detail_final"] = detail_vs_truth(fin, truth)
            eo, ef = edge_gain(out, truth), edge_gain(fin, truth)
            rows[v["view"]].update(edges_output=eo, edges_final=ef,
                                   edges_ratio=ef / eo if eo else float("nan"))  # fmt: skip
        prov = run / "views" / v["view"] / "provenance.npz"
        if prov.is_file():  # no truth needed: the output's edges where it shows what was observed
            observed = np.load(prov)["synthesised"] < 0.5
            rows[v["view"]]["observed_edges"] = edge_gain(fin, out, observed)
        rows[v["view"]].update(by_source(out, fin, prov, truth))
    return rows


def source_summary(per_run: dict[str, dict[str, dict[str, float]]]) -> dict[str, dict]:
    """Per source of the output, medians over every view of every run where it covers enough
    pixels: its share, the sharpness ratio, the output's edges kept, and with the truth the
    output's and the final's gains on the truth's edges."""
    from gsfix_online.repair.provenance import SOURCES

    rows = [r for run in per_run.values() for r in run.values()]
    out = {}
    for name in SOURCES:
        have = [r for r in rows if f"sharpness_{name}" in r]
        if not have:
            continue
        keys = ("share", "sharpness", "kept", "truth_output", "truth_final")
        out[name] = {"views": len(have)} | {
            k: statistics.median(r[f"{k}_{name}"] for r in have)
            for k in keys
            if all(f"{k}_{name}" in r for r in have)
        }
    return out


def source_cell(row: dict[str, float]) -> str:
    return ", ".join(f"{k.removeprefix('sharpness_')} {x:.2f}" for k, x in row.items()
                     if k.startswith("sharpness_"))  # fmt: skip


def marks(row: dict[str, float]) -> tuple[str, str]:
    """ " **x**" beside the final - output and the sharpness cells whose bound fails."""
    x = " **x**"
    return (x if row["final_minus_output_db"] < -DB_BELOW_MAX else "",
            x if row["sharpness"] < SHARPNESS_MIN else "")  # fmt: skip


def observed_cell(row: dict[str, float]) -> str:
    x = row.get("observed_edges")
    return "" if x is None else f"{x:.2f}{' **x**' if x < SHARPNESS_MIN else ''}"


def edges_cell(row: dict[str, float]) -> str:
    if "edges_output" not in row:
        return ""
    x = " **x**" if row["edges_ratio"] < SHARPNESS_MIN else ""
    return f"{row['edges_output']:.2f}, {row['edges_final']:.2f} ({row['edges_ratio']:.2f}{x})"


def lowpass_cell(row: dict[str, float]) -> str:
    x = row["map_sharpness"]
    return f"{row['lowpass']:.2f} ({x:.2f}{' **x**' if x < SHARPNESS_MIN else ''})"


def failing(row: dict[str, float]) -> bool:
    return row["final_minus_output_db"] < -DB_BELOW_MAX or row["sharpness"] < SHARPNESS_MIN


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="repair run folders (metrics.json)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    per_run = {str(r): view_rows(r) for r in a.runs}
    for run, rows in per_run.items():
        print(f"\n{run}\n| view | output dB | final dB | final - output | sharpness | "
              "at 1/2 | low-pass (sharpness over it) | observed edges kept | truth's edges: output, "
              "final (ratio) | sharpness by source |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")  # fmt: skip
        for name, r in sorted(rows.items()):
            db_x, sharp_x = marks(r)
            detail = edges_cell(r)
            print(f"| {name} | {r['output_db']:.2f} | {r['final_db']:.2f} | "
                  f"{r['final_minus_output_db']:+.2f}{db_x} | {r['sharpness']:.2f}{sharp_x} | "
                  f"{r['half_sharpness']:.2f} | {lowpass_cell(r)} | {observed_cell(r)} | {detail} | "
                  f"{source_cell(r)} |")  # fmt: skip
    names = sorted(set.intersection(*(set(r) for r in per_run.values())))
    median: dict[str, dict[str, float]] = {}
    for name in names:
        rows = [per_run[run][name] for run in per_run]
        keys = set.intersection(*(set(r) for r in rows))
        median[name] = {k: statistics.median(r[k] for r in rows) for k in rows[0] if k in keys}
    if len(per_run) > 1:
        print(f"\nmedian over {len(per_run)} runs\n| view | output dB | final dB | "
              "final - output | sharpness | at 1/2 | low-pass (sharpness over it) | observed edges kept | "
              "truth's edges: output, final (ratio) |\n"
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|")  # fmt: skip
        for name, r in median.items():
            db_x, sharp_x = marks(r)
            detail = edges_cell(r)
            print(f"| {name} | {r['output_db']:.2f} | {r['final_db']:.2f} | "
                  f"{r['final_minus_output_db']:+.2f}{db_x} | {r['sharpness']:.2f}{sharp_x} | "
                  f"{r['half_sharpness']:.2f} | {lowpass_cell(r)} | {observed_cell(r)} | {detail} |")  # fmt: skip
    bad = [n for n, r in median.items() if failing(r)]
    print(f"\nviews failing a bound (median): {bad or 'none'}")
    soft = [n for n, r in median.items() if r["map_sharpness"] < SHARPNESS_MIN]
    print(f"views under {SHARPNESS_MIN} of the output's sharpness through the low-pass (the "
          f"writer's map_sharpness; median): {soft or 'none'}")  # fmt: skip
    if median and all("output_minus_classical_db" in r for r in median.values()):
        floor = {n: (round(r["output_minus_classical_db"], 2), round(r["final_minus_classical_db"], 2))
                 for n, r in median.items()}  # fmt: skip
        under = {n: x for n, x in floor.items() if min(x) < 0}
        print(f"views under the best classical baseline, (output, final map) - baseline dB "
              f"(median): {under or 'none'}")  # fmt: skip
    if median and all("edges_ratio" in r for r in median.values()):
        lost = [n for n, r in median.items() if r["edges_ratio"] < SHARPNESS_MIN]
        print(
            f"views whose final map keeps under {SHARPNESS_MIN} of the output's gain on the "
            f"truth's edges (median): {lost or 'none'}"
        )
    sources = source_summary(per_run)
    print("\nper source of the output, medians over every view\n| source | views | share | "
          "sharpness | output's edges kept | truth's edges: output -> final |\n"
          "|---|---:|---:|---:|---:|---|")  # fmt: skip
    for name, r in sources.items():
        truth = (f"{r['truth_output']:.2f} -> {r['truth_final']:.2f}"
                 if "truth_output" in r else "")  # fmt: skip
        print(
            f"| {name} | {r['views']} | {r['share']:.2f} | {r['sharpness']:.2f} | "
            f"{r['kept']:.2f} | {truth} |"
        )
    if a.json:
        out: dict[str, Any] = {"runs": per_run, "median": median, "failing": bad,
                               "under_lowpass_bound": soft, "sources": sources,
                               "bounds": {"db_below_max": DB_BELOW_MAX,
                                          "sharpness_min": SHARPNESS_MIN}}  # fmt: skip
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
