"""``gsfix-online demo``: the main job on the embedded synthetic ship tank.

Stages that exist today: generate the scene (TUM folder, MCAP log, ground truth, novel views), then
replay the log and the TUM folder through their readers and check that both give the same frames.
The mapping, keyframe, fixer and repair stages are appended here as they land.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsfix_online.config import Config, write_config

logger = logging.getLogger(__name__)


@dataclass
class StageTimes:
    rows: list[tuple[str, float, str]] = field(default_factory=list)  # (stage, seconds, note)

    def add(self, stage: str, seconds: float, note: str = "") -> None:
        self.rows.append((stage, seconds, note))

    def table(self) -> str:
        width = max(len(r[0]) for r in self.rows)
        lines = [
            f"{'stage':<{width}}  {'time':>8}  result",
            f"{'-' * width}  {'-' * 8}  {'-' * 40}",
        ]
        lines += [f"{s:<{width}}  {t:>7.2f}s  {n}" for s, t, n in self.rows]
        return "\n".join(lines)


def _replay(
    path: Path, cfg: Config, progress: bool, desc: str
) -> tuple[list[int], dict[str, int], float]:
    from tqdm import tqdm

    from gsfix_online.sources import open_source
    from gsfix_online.sources.replay import paced

    reader = open_source(cfg.source, path)
    t0 = time.perf_counter()
    stamps = []
    for frame in tqdm(
        paced(reader, cfg.replay, time.monotonic, time.sleep),
        total=len(reader),
        desc=desc,
        unit="frame",
        disable=not progress,
        leave=False,
    ):
        stamps.append(frame.stamp_ns)
    return stamps, reader.stats.as_dict(), time.perf_counter() - t0


def run_demo(cfg: Config, out: Path, progress: bool = True) -> int:
    """Run the demo into ``out``; prints a table of stages and writes ``summary.json``. Returns 0."""
    from gsfix_online.scene import generate_ship_tank
    from gsfix_online.sources.mcap_log import write_mcap

    out.mkdir(parents=True, exist_ok=True)
    write_config(cfg, out / "config.yaml")
    times = StageTimes()

    # 1. Generate the scene with its ground truth
    t0 = time.perf_counter()
    scene = generate_ship_tank(cfg.scene, out / "scene", write_mcap=write_mcap)
    cov = np.asarray(scene.novel_coverage, dtype=float)
    cov_note = f"coverage {cov.min():.2f}..{cov.max():.2f}" if len(cov) else "no novel views"
    times.add(
        "scene",
        time.perf_counter() - t0,
        f"{scene.n_frames} frames, {scene.n_novel} novel views ({cov_note})",
    )

    # 2. Replay the MCAP log and the TUM folder; both must give the same frames
    log_stamps, log_stats, dt_log = _replay(
        out / "scene" / "log.mcap", cfg, progress, "replay mcap"
    )
    times.add(
        "replay mcap",
        dt_log,
        f"{len(log_stamps)} frames, {len(log_stamps) / dt_log:.0f} frames/s, {log_stats['depth_pixels_invalidated']} bad depth px",
    )
    tum_stamps, tum_stats, dt_tum = _replay(out / "scene" / "tum", cfg, progress, "replay tum")
    times.add(
        "replay tum", dt_tum, f"{len(tum_stamps)} frames, {len(tum_stamps) / dt_tum:.0f} frames/s"
    )
    if log_stamps != tum_stamps:
        raise RuntimeError(
            f"MCAP log and TUM folder disagree: {len(log_stamps)} vs {len(tum_stamps)} frames"
        )

    print(times.table())
    summary = {
        "scene": str(out / "scene"),
        "frames": scene.n_frames,
        "novel_views": scene.n_novel,
        "novel_coverage": cov.tolist(),
        "stages": [{"stage": s, "seconds": round(t, 3), "result": n} for s, t, n in times.rows],
        "replay_stats": {"mcap": log_stats, "tum": tum_stats},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"outputs in {out} (summary.json, config.yaml, scene/)")
    return 0
