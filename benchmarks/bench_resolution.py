"""The processing resolution (``source.max_width``): what a lower one saves in time and costs in
quality, on a recorded input with held-out frames.

For each width, ``gsfix-online repair --input SRC --holdout K source.max_width=W
writer.upsample_to_camera=true`` runs in a child process (wall time and the CPU seconds of every
process it started), then the held-out frames are scored two ways:

- at the processing resolution, as the run scores them (``metrics.json`` group ``holdout``): the
  delivered ``output``, the ``final`` map's render, and the fallback floor, ``inpaint`` (mesh fill
  + Telea) and ``mesh_inpaint`` (mesh + Telea);
- at the camera's resolution: ``output_camera.png`` and ``final_camera.png`` (bicubic upsampled
  by the writer), and the floor's images upsampled the same way, against the input's own frames
  as the reader yields them without ``max_width``. This is what a user with the camera's images
  sees, and what makes two widths comparable (a lower resolution scores higher by itself at its
  own resolution: its ground truth is smoother).

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_resolution.py \\
        --input ROOM/tum --holdout 10 --widths 320 640 --out-dir RUNS \\
        [--json benchmarks/results/processing_resolution_cpu.json] [-- OVERRIDE ...]

Results: ``benchmarks/results/processing_resolution_cpu.md`` (and its JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FLOOR = ("inpaint", "mesh_inpaint")  # the fallback floor: mesh fill + Telea, mesh + Telea


def run_repair(src: str, holdout: int, width: int, out: Path, extra: list[str]) -> dict[str, float]:
    """One repair run in a child process: wall seconds and CPU seconds of all its processes."""
    cmd = [sys.executable, "-m", "gsfix_online.apps.cli", "repair", "--input", src,
           "--holdout", str(holdout), "--out", str(out), f"source.max_width={width}",
           "writer.upsample_to_camera=true", *extra]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu}


def camera_scores(run: Path, src: str, holdout: int) -> dict[str, dict[str, float]]:
    """Mean PSNR/SSIM at the camera's resolution over the held-out frames, per stage."""
    from gsfix_online.core.metrics import psnr, ssim
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.replay import is_held_out
    from gsfix_online.sources.resolution import resize_color

    truth = [f.color for i, f in enumerate(open_source(SourceConfig(path=src)))
             if is_held_out(i, holdout)]  # fmt: skip
    scores: dict[str, list[tuple[float, float]]] = {}
    for k, gt in enumerate(truth):
        d = run / "views" / f"{k:03d}"
        h, w = gt.shape[:2]
        images = {s: read_png_rgb(d / f"{s}_camera.png") for s in ("output", "final")}
        for s in FLOOR:  # the floor upsampled as the writer upsamples the delivered repair
            small = read_png_rgb(d / f"{s}.png")
            images[s] = resize_color(small, w, h, "cubic")
        for s, img in images.items():
            assert img.shape == gt.shape, (s, img.shape, gt.shape)
            scores.setdefault(s, []).append((psnr(img, gt), ssim(img, gt)))
    return {s: {"psnr_db": float(np.mean([p for p, _ in v])),
                "ssim": float(np.mean([q for _, q in v])), "views": len(v)}
            for s, v in scores.items()}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input", required=True, help="a recorded input (dataset folder, log)")
    ap.add_argument("--holdout", type=int, default=10)
    ap.add_argument("--widths", type=int, nargs="+", default=[320, 640])
    ap.add_argument("--out-dir", type=Path, required=True, help="one run folder per width")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("overrides", nargs="*", help="graph overrides for every run (after --)")
    args = ap.parse_args(argv)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    rows: list[dict[str, Any]] = []
    for width in args.widths:
        out = args.out_dir / f"w{width}"
        timing = run_repair(args.input, args.holdout, width, out, args.overrides)
        m = json.loads((out / "metrics.json").read_text())
        held = m["summary"]["groups"]["holdout"]
        processing = {s: held[s] for s in ("output", "final", *FLOOR) if s in held}
        row = {
            "max_width": width,
            "size": m["resolution"]["processing"],
            **timing,
            "processing": processing,
            "camera": camera_scores(out, args.input, args.holdout),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = {"input": args.input, "holdout": args.holdout, "overrides": args.overrides,
              "commit": commit, "cores": os.cpu_count(), "machine": platform.machine(),
              "rows": rows}  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
