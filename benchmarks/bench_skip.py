"""What skipping saves: the repair command on the synthetic ship tank with the planner's default
skip policy, against the same run with skipping disabled (every view repaired and distilled). The
views are the scene's novel views plus poses of the trajectory, which the map already explains.

Reports per run: wall time, time in GSFixer and in distillation (per-view sums), views repaired,
and PSNR/SSIM of the final renders (after distillation) and of the 2D outputs on the scene's
novel views. Run it under the bench lock on a shared machine::

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_skip.py

Results: ``benchmarks/results/skip_cpu.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def view_set(scene: Path, work: Path, n_path: int) -> tuple[Path, Path]:
    """The scene's novel views (000..) plus ``n_path`` poses of the trajectory itself, which the
    map explains (the views a skip policy should save), with ground truth images for all."""
    import shutil

    novel = [ln for ln in (scene / "novel" / "views.txt").read_text().splitlines()
             if ln and not ln.startswith("#")]  # fmt: skip
    path = [ln for ln in (scene / "tum" / "groundtruth.txt").read_text().splitlines()
            if ln and not ln.startswith("#")]  # fmt: skip
    rgb = [ln.split()[1] for ln in (scene / "tum" / "rgb.txt").read_text().splitlines()
           if ln and not ln.startswith("#")]  # fmt: skip
    picks = [round(i * (len(path) - 1) / max(n_path - 1, 1)) for i in range(n_path)]
    gt = work / "views_gt"
    gt.mkdir(parents=True, exist_ok=True)
    for i in range(len(novel)):
        shutil.copy(scene / "novel" / "color" / f"{i:03d}.png", gt / f"{i:03d}.png")
    for j, k in enumerate(picks):
        shutil.copy(scene / "tum" / rgb[k], gt / f"{len(novel) + j:03d}.png")
    views = work / "views.txt"
    views.write_text("\n".join(novel + [path[k] for k in picks]) + "\n")
    return views, gt


def run(scene: Path, out: Path, overrides: list[str], views: Path, gt: Path) -> dict:
    from gsfix_online.jobs.repair_run import prepare, run_graph

    graph, info, n = prepare(scene / "log.mcap", views, out, gt, overrides=overrides)
    with (out / "work" / "stdout.log").open("w") as log:
        res = run_graph(graph, log=log, timeout_s=3000)
    if res.returncode != 0 or res.metrics is None:
        raise SystemExit(f"repair run failed: {res.message}")
    s = res.metrics["summary"]
    t = s["stage_time_totals_s"]
    return {
        "wall_s": res.seconds,
        "views": s["views"],
        "repaired": s["repaired"],
        "skipped": s["skipped"],
        "skip_reasons": s["skip_reasons"],
        "fix_s": t.get("fix_s", 0.0),
        "distill_s": t.get("distill_s", 0.0),
        "distill_passes_s": res.metrics["timings_s"].get("distill_passes_s", 0.0),
        "repair_phase_s": res.metrics["timings_s"].get("collect_s", 0.0),
        "stages": s["stages"],
        "decisions": [(v["view"], v["repair"], v["reason"]) for v in res.metrics["views"]],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--path-views", type=int, default=8, help="trajectory poses among the views")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "skip_cpu.json")
    ap.add_argument("overrides", nargs="*", help="NODE.KEY=VALUE for both runs")
    args = ap.parse_args()

    from gsfix_online.core.config import build
    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.scene import generate_ship_tank
    from gsfix_online.scene.config import ShipTankConfig
    from gsfix_online.sources.mcap_log import write_mcap

    work = Path(tempfile.mkdtemp(prefix="bench_skip_"))
    over = [f"width={args.width}", f"height={args.height}", f"n_frames={args.frames}"]
    generate_ship_tank(build(ShipTankConfig, overrides=over), work / "scene", write_mcap=write_mcap)
    t0 = time.time()
    views, gt = view_set(work / "scene", work, args.path_views)
    default = run(work / "scene", work / "default", list(args.overrides), views, gt)
    every = run(work / "scene", work / "every", [*args.overrides, "planner.skip.enabled=false"],
                views, gt)  # fmt: skip

    def psnr(r: dict, stage: str) -> float | None:
        s = r["stages"].get(stage)
        return s["psnr_db"] if s else None

    result = {
        "what": "repair command on the ship tank: default skip policy vs skipping disabled",
        "scene": {"width": args.width, "height": args.height, "frames": args.frames},
        "overrides": args.overrides,
        "default_skip": default,
        "no_skip": every,
        "saved": {
            "wall_s": every["wall_s"] - default["wall_s"],
            "repair_phase_s": every["repair_phase_s"] - default["repair_phase_s"],
            "fix_s": every["fix_s"] - default["fix_s"],
            "distill_s": every["distill_s"] - default["distill_s"],
        },
        "psnr_change_db": {
            "final": (psnr(default, "final") or 0) - (psnr(every, "final") or 0),
            "fixed_or_gs": (psnr(default, "fixed_or_gs") or 0) - (psnr(every, "fixed_or_gs") or 0),
        },
        "machine": f"{platform.machine()} {platform.processor()}".strip(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t0)),
        "command": "flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_skip.py",
    }
    atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("saved", "psnr_change_db")}, indent=2))
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
