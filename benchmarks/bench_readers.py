"""Reader throughput on the synthetic ship tank, against a bare cv2.imread loop in the same run.

Writes the default scene (320x240, 200 frames) in every format, reads each through its reader
(validation included) and through a bare loop that only decodes the same image files, and reports
median frames/s over repeats and the ratio. Also the peak RSS growth while streaming 10,000 frames.

    .venv/bin/python benchmarks/bench_readers.py [--repeats 5] [--out benchmarks/results/readers_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import psutil

from gsfix_online.scene import ShipTankConfig, generate_ship_tank
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.mcap_log import write_mcap
from gsfix_online.sources.okvis import write_okvis
from gsfix_online.sources.redwood import write_redwood
from gsfix_online.sources.replica import write_replica
from gsfix_online.sources.rosbag import write_rosbag
from gsfix_online.sources.scannetpp import write_scannetpp

EYE = [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


def bare_files(fmt: str, root: Path) -> list[Path]:
    pngs = {
        "tum": ("rgb", "depth"),
        "redwood": ("image", "depth"),
        "okvis": ("rgb", "depth"),
        "replica": ("results",),
        "scannetpp": ("iphone/rgb", "iphone/depth"),
    }.get(fmt)
    return [p for sub in pngs for p in sorted((root / sub).glob("*.png"))] if pngs else []


def timed(fn) -> float:  # noqa: ANN001
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/readers_cpu.json"))
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_readers_"))
    info = generate_ship_tank(ShipTankConfig(), work / "scene")
    frames = list(open_source(SourceConfig(), info.tum_dir))
    n = len(frames)
    roots = {
        "tum": info.tum_dir,
        "replica": work / "replica",
        "redwood": work / "redwood",
        "scannetpp": work / "scannetpp",
        "okvis": work / "okvis",
        "mcap": work / "log.mcap",
        "rosbag2": work / "bag2",
        "rosbag1": work / "log.bag",
    }
    write_replica(roots["replica"], frames, color_ext=".png")
    write_redwood(roots["redwood"], frames)
    write_scannetpp(roots["scannetpp"], frames)
    write_okvis(roots["okvis"], frames, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    write_mcap(roots["mcap"], frames)
    write_rosbag(roots["rosbag2"], frames, version="ros2")
    write_rosbag(roots["rosbag1"], frames, version="ros1")

    rows = []
    for fmt, root in roots.items():
        cfg = SourceConfig(T_SC=EYE) if fmt == "okvis" else SourceConfig()
        ours = [
            timed(lambda cfg=cfg, root=root: sum(1 for _ in open_source(cfg, root)))
            for _ in range(args.repeats)
        ]
        files = bare_files(fmt.rstrip("12"), root)
        bare = (
            [
                timed(lambda files=files: [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in files])
                for _ in range(args.repeats)
            ]
            if files
            else []
        )
        row = {"format": fmt, "frames": n, "ours_fps": n / statistics.median(ours)}
        if bare:
            row["bare_imread_fps"] = n / statistics.median(bare)
            row["ours_over_bare"] = row["ours_fps"] / row["bare_imread_fps"]
        rows.append(row)
        print(
            f"{fmt:<10} ours {row['ours_fps']:7.0f} frames/s"
            + (
                f"   bare imread {row['bare_imread_fps']:7.0f} frames/s   ratio {row['ours_over_bare']:.2f}"
                if bare
                else ""
            )
        )

    # Streaming memory: RSS while reading a 10,000-frame TUM sequence (hard-linked images).
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "sources"))
    from test_streaming import N_FRAMES, write_long_tum

    long_root = work / "long"
    write_long_tum(long_root)
    proc = psutil.Process()
    reader = open_source(SourceConfig(), long_root)
    rss = []
    for i, _ in enumerate(reader):
        if i % 500 == 0:
            rss.append(proc.memory_info().rss)
    growth_mb = (max(rss[1:]) - rss[1]) / 1e6
    print(
        f"streaming {N_FRAMES} TUM frames: RSS {rss[1] / 1e6:.0f} MB after 500 frames, max growth after that {growth_mb:.1f} MB"
    )
    result = {
        "machine": f"{platform.processor() or platform.machine()}, {psutil.cpu_count()} cores",
        "scene": "ship tank 320x240, 200 frames",
        "repeats": args.repeats,
        "readers": rows,
        "streaming_10k": {
            "frames": N_FRAMES,
            "rss_after_500_mb": rss[1] / 1e6,
            "max_rss_growth_mb": growth_mb,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
