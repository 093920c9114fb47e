"""Gaussian mapping throughput and quality on the synthetic ship tank (320x240).

Runs :mod:`gsfix_online.jobs.splat_report` (map the stream, then a full-resolution global
refinement, then PSNR/SSIM at training and novel views) with the CPU budget policy of
``configs/report_splat_fast.yaml`` (the tank's 10 Hz sequence thinned to a 2 Hz stream) for each
torch thread count given, and writes the figures: whether mapping keeps up with the stream
(real-time factor, lag), frames/s, seconds per keyframe, PSNR/SSIM before and after refinement,
refinement seconds, Gaussians and PLY megabytes. Run it under ``flock /tmp/gsfix-bench.lock``
on a shared machine.

    .venv/bin/python benchmarks/bench_mapping.py [--scene DIR] [--threads 1 2] [--max-frames N]
        [--refine-iters N] [--out benchmarks/results/mapping_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
from pathlib import Path

from gsfix_online.core.config import build
from gsfix_online.jobs.splat_report import ReportConfig, run, summary

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="", help="ship-tank folder (default: generate one)")
    p.add_argument("--threads", type=int, nargs="+", default=[1])
    p.add_argument("--max-frames", type=int, default=None, help="default: the config's")
    p.add_argument("--refine-iters", type=int, default=None, help="default: the config's")
    p.add_argument("--config", default=str(REPO / "configs" / "report_splat_fast.yaml"))
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "mapping_cpu.json"))
    args = p.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(args.scene) if args.scene else Path(tmp) / "scene"
        if not args.scene:
            from gsfix_online.scene import ShipTankConfig, generate_ship_tank

            generate_ship_tank(ShipTankConfig(), scene)
        runs = []
        for threads in args.threads:
            cfg = build(
                ReportConfig,
                files=[args.config],
                overrides=[
                    f"scene={scene}",
                    f"threads={threads}",
                    f"out={Path(tmp) / f'report_{threads}.json'}",
                    *([] if args.max_frames is None else [f"max_frames={args.max_frames}"]),
                    *([] if args.refine_iters is None else [f"refine_iters={args.refine_iters}"]),
                ],
            )
            report = run(cfg)
            print(f"threads {threads}:\n{summary(report)}", flush=True)
            report.pop("config")
            runs.append(report)
    result = {
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()},
        "config": args.config,
        "runs": runs,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
