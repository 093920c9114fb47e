"""The repair job on inputs nobody tuned on: scene families, real-like degradations, resolutions.

For each case (scene family, variant, camera) and seed: generate the scene
(``gsfix-online scene``), run ``gsfix-online repair --holdout K`` on its log with its novel views
and their ground truth, and read ``metrics.json``. Every stage and baseline is scored at the
held-out input frames (real images, estimated poses) and at the novel views:

- ``gs``: raw 3DGS; ``gs_inpaint``: the 3DGS render, its holes (alpha < 0.5) filled by OpenCV
  Telea; ``mesh_inpaint``: the TSDF mesh render, holes filled by Telea (what a user gets from
  Open3D and OpenCV alone); ``inpaint``: mesh fill + Telea (the 3DGS render where
  its alpha is high, else the mesh, then Telea);
- ``fixed``: GSFixer's own output; ``output``: the repair delivered (GSFixer where it measured
  better than the fallbacks, theirs elsewhere; the 3DGS render where the planner skipped the
  view); ``final``: the map after distillation.

Writes ``benchmarks/results/variants_cpu.json`` (every run) and ``variants_cpu.md`` (medians over
seeds). Runs that finished are kept and skipped on the next call (``--work`` holds them), so a
long sweep resumes where it stopped.

    .venv/bin/python benchmarks/bench_variants.py --cases tank tank:real room:real \\
        --seeds 0 1 --frames 60
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "gsfix_online.apps.cli"]
STAGES = ("gs", "gs_inpaint", "mesh_inpaint", "inpaint", "fixed", "output", "output_or_gs", "final")


def parse_case(case: str) -> dict[str, str]:
    """``family[:variant[:camera]]``, e.g. ``tank``, ``tank:real``, ``room:gray:vga``."""
    parts = case.split(":")
    family = {"tank": "ship-tank", "room": "room"}[parts[0]]
    return {
        "case": case,
        "kind": family,
        "variant": parts[1] if len(parts) > 1 else "",
        "camera": parts[2] if len(parts) > 2 else "",
    }


def run_case(c: dict[str, str], seed: int, frames: int, holdout: int, work: Path,
             extra: list[str]) -> dict:  # fmt: skip
    tag = c["case"].replace(":", "_") + f"_s{seed}"
    scene, out = work / tag / "scene", work / tag / "run"
    if (out / "metrics.json").is_file() and (work / tag / "row.json").is_file():
        row = json.loads((work / tag / "row.json").read_text())
        if row["rc"] == 0:  # rows of older versions of this script lack the regions
            row["regions"] = json.loads((out / "metrics.json").read_text())["summary"].get(
                "region_groups", {})  # fmt: skip
        return row
    t0 = time.monotonic()
    if not (scene / "log.mcap").is_file():
        cmd = [*CLI, "scene", c["kind"], f"scene.seed={seed}", f"scene.n_frames={frames}"]
        if c["variant"]:
            cmd += ["--variant", c["variant"].replace("+", ",")]
        if c["camera"]:
            cmd += ["--camera", c["camera"]]
        subprocess.run([*cmd, "--out", str(scene)], check=True, cwd=ROOT)
    t_scene = time.monotonic() - t0
    if out.exists():
        import shutil

        shutil.rmtree(out)
    t1 = time.monotonic()
    cmd = [*CLI, "repair", *extra, "--input", str(scene / "log.mcap"),
           "--views", str(scene / "novel" / "views.txt"),
           "--views-gt", str(scene / "novel" / "color"), "--holdout", str(holdout),
           "--out", str(out)]  # fmt: skip
    with (work / tag / "repair.log").open("w") as log:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT).returncode
    row = {"case": c["case"], "seed": seed, "frames": frames, "holdout": holdout, "rc": rc,
           "scene_s": t_scene, "repair_s": time.monotonic() - t1}  # fmt: skip
    if rc == 0:
        m = json.loads((out / "metrics.json").read_text())
        row["groups"] = m["summary"]["groups"]
        row["regions"] = m["summary"].get("region_groups", {})  # group -> stage -> region
        # the run's measured fallback choice per region (repair.fallback; blends as
        # "0.45 fixed + mesh_inpaint"); views beyond the held-out frames' reach follow for_view
        from gsfix_online.repair.fallback import Choice

        fb = m["summary"].get("fallback")
        row["choice"] = Choice.from_json(json.dumps(fb)).describe() if fb else {}
        row["timings_s"] = m.get("timings_s", {})
    (work / tag / "row.json").write_text(json.dumps(row, indent=1))
    return row


def table(rows: list[dict]) -> str:
    """Medians over seeds, per case: PSNR dB / SSIM at held-out frames and novel views."""
    lines = [
        "| case | group | " + " | ".join(STAGES) + " | repair wall s | seeds |",
        "|---|---|" + "---|" * len(STAGES) + "---|---|",
    ]
    for case in dict.fromkeys(r["case"] for r in rows):
        ok = [r for r in rows if r["case"] == case and r["rc"] == 0]
        if not ok:
            lines.append(f"| {case} | failed | " + " | " * len(STAGES) + " | |")
            continue
        for group in ("holdout", "novel"):
            cells = []
            for st in STAGES:
                vals = [r["groups"][group][st] for r in ok if st in r["groups"].get(group, {})]
                if not vals:
                    cells.append("–")
                    continue
                p = statistics.median(v["psnr_db"] for v in vals)
                s = statistics.median(v["ssim"] for v in vals)
                cells.append(f"{p:.2f} / {s:.3f}")
            wall = statistics.median(r["repair_s"] for r in ok)
            lines.append(f"| {case} | {group} | " + " | ".join(cells) +
                         f" | {wall:.0f} | {len(ok)} |")  # fmt: skip
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["tank", "tank:real", "room", "room:real"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--holdout", type=int, default=10)
    ap.add_argument("--work", type=Path, default=ROOT / "outputs" / "bench_variants")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "variants_cpu")
    ap.add_argument("overrides", nargs="*", help="NODE.KEY=VALUE for every repair run")
    args = ap.parse_args()
    rows = []
    for case in args.cases:
        for seed in args.seeds:
            print(f"[bench_variants] {case} seed {seed} ...", flush=True)
            row = run_case(parse_case(case), seed, args.frames, args.holdout, args.work,
                           args.overrides)  # fmt: skip
            rows.append(row)
            print(f"[bench_variants] {case} seed {seed}: rc {row['rc']}, "
                  f"{row['repair_s']:.0f} s", flush=True)  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"argv": sys.argv[1:], "rows": rows},
                                                         indent=1))  # fmt: skip
    md = table(rows)
    args.out.with_suffix(".md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
