"""Quality report of the Gaussian map on a synthetic ship tank (``gsfix-online scene ship-tank``).

1. Map the scene's TUM sequence frame by frame with :class:`~.mapper.Mapper`, timing each frame.
   ``frame_stride`` thins the stream (5 turns the tank's 10 Hz into a 2 Hz stream). The frames
   are replayed against their own time stamps: a frame arriving while the mapper is busy waits,
   and ``keeps_up`` says whether the mapping took no longer than the stream lasted.
2. Refine globally (``refine_iters`` steps over the keyframes).
3. Render every ``eval_stride``-th training view and every novel view; PSNR and SSIM against the
   noise-free ground truth (``gt/color``, ``novel/color``). Novel views leave the trajectory, so
   holes are expected there.
4. Count Gaussians and the map size (the standard PLY's bytes), and write JSON.

``python -m gsfix_online.jobs.splat_report --scene DIR --out report.json [mapper.kf_iters=6]``
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.core.config import build, rng, to_dict
from gsfix_online.core.io import atomic_write_text
from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReportConfig:
    scene: str = ""  # a ship-tank folder (tum/, gt/, novel/)
    out: str = ""  # JSON path; empty = print only
    max_frames: int = field(default=0, metadata=rng(0, None, "map only the first n; 0 = all"))
    frame_stride: int = field(default=1, metadata=rng(1, None, "map every n-th frame"))
    refine_iters: int = field(default=300, metadata=rng(0, None, "final refinement steps"))
    eval_stride: int = field(default=5, metadata=rng(1, None, "evaluate every n-th frame"))
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    mapper: MapperConfig = field(default_factory=MapperConfig)


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path))


def _percentiles(x: list[float]) -> dict[str, float]:
    a = np.asarray(x, dtype=np.float64)
    if not a.size:
        return {"n": 0}
    return {
        "n": int(a.size),
        "mean": float(a.mean()),
        "p50": float(np.percentile(a, 50)),
        "p90": float(np.percentile(a, 90)),
        "max": float(a.max()),
    }


def stream_timing(
    stamps_s: list[float],  # arrival of each frame, s (any origin)
    busy_s: list[float],  # mapper time per frame, s
) -> dict[str, Any]:
    """Replay a stream against a single mapper: a frame starts when it arrived and the mapper is
    free. Lag = finish - arrival. The stream lasts n periods (median stamp gap)."""
    t = np.asarray(stamps_s, np.float64) - stamps_s[0]
    period = float(np.median(np.diff(t))) if len(t) > 1 else float("nan")
    free, lags = 0.0, []
    for arrival, busy in zip(t, busy_s, strict=True):
        free = max(free, arrival) + busy
        lags.append(free - arrival)
    stream_s = len(t) * period if len(t) > 1 else float("nan")
    return {
        "stream_hz": 1.0 / period,
        "stream_s": stream_s,
        "realtime_factor": stream_s / float(np.sum(busy_s)),
        "keeps_up": bool(np.sum(busy_s) <= stream_s),
        "lag_s": _percentiles(lags),
    }


def _evaluate(mapper: Mapper, views: list[tuple[np.ndarray, Any, Any]]) -> dict[str, Any]:
    """Mean PSNR/SSIM of the map's renders against (image uint8, T_world_cam, Intrinsics)."""
    from gsfix_online.core.metrics import psnr, ssim

    ps, ss, cover = [], [], []
    for img, T, intr in views:
        color, _, alpha = mapper.render_numpy(T, intr.K, intr.width, intr.height)
        target = img if img.ndim == 3 else img[..., None]
        if mapper.channels == 3 and target.shape[2] == 1:
            target = np.repeat(target, 3, axis=2)
        ps.append(psnr(color, target))
        ss.append(ssim(color, target))
        cover.append(float((alpha > 0.5).mean()))
    return {
        "n": len(views),
        "psnr_db": float(np.mean(ps)) if ps else float("nan"),
        "ssim": float(np.mean(ss)) if ss else float("nan"),
        "psnr_db_per_view": [round(p, 3) for p in ps],
        "alpha_coverage": float(np.mean(cover)) if cover else float("nan"),
    }


def run(cfg: ReportConfig, progress: bool = False) -> dict[str, Any]:
    """Map, refine and evaluate the scene in ``cfg.scene``; returns the report dict."""
    import torch

    from gsfix_online.mapping.splat.ply import write_ply
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.tum import read_intrinsics_json, read_pose_list

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    scene = Path(cfg.scene)
    if not (scene / "tum").is_dir():
        raise FileNotFoundError(f"{scene} is not a ship-tank folder (no tum/); make one with "
                                "`gsfix-online scene ship-tank --out DIR`")  # fmt: skip
    src = SourceConfig(path=str(scene / "tum"), max_frames=cfg.max_frames, stride=cfg.frame_stride)
    reader = open_source(src)

    # 1. Map frame by frame
    mapper: Mapper | None = None
    kf_s, non_kf_s, frames, busy, stamps = [], [], [], [], []
    t_start = time.perf_counter()
    from gsfix_online.core.progress import track

    for frame in track(reader, "mapping", len(reader), "frame", enabled=progress):
        if mapper is None:
            mapper = Mapper(cfg.mapper, channels=1 if frame.is_gray else 3)
        t0 = time.perf_counter()
        res = mapper.process(frame)
        busy.append(time.perf_counter() - t0)
        stamps.append(frame.stamp_ns * 1e-9)
        (kf_s if res.is_keyframe else non_kf_s).append(busy[-1])
        frames.append((frame.seq, frame.T_world_cam, frame.intrinsics))
    assert mapper is not None, f"{scene / 'tum'} has no frames"
    map_s = time.perf_counter() - t_start
    n_frames = len(frames)
    online = {
        "frames": n_frames,
        "keyframes": len(kf_s),
        "mapping_s": map_s,
        "frames_per_s": n_frames / map_s,
        "s_per_keyframe_amortised": map_s / max(len(kf_s), 1),
        "keyframe_s": _percentiles(kf_s),
        "non_keyframe_s": _percentiles(non_kf_s),
        "gaussians": len(mapper.gmap),
        **stream_timing(stamps, busy),
    }

    # 2. Evaluate the online map, refine, evaluate again
    gt_views = []
    for i, (_seq, T, intr) in enumerate(frames):
        if i % cfg.eval_stride == 0:
            j = i * cfg.frame_stride  # index in the full sequence
            gt_views.append((_read_png(scene / "gt" / "color" / f"{j:06d}.png"), T, intr))
    online["train"] = _evaluate(mapper, gt_views)
    t0 = time.perf_counter()
    refined = mapper.refine(cfg.refine_iters)
    refine_s = time.perf_counter() - t0

    novel = []
    intr_novel, _ = read_intrinsics_json(scene / "novel" / "intrinsics.json")
    poses = read_pose_list(scene / "novel" / "views.txt")
    for i, T in enumerate(poses.poses):
        novel.append((_read_png(scene / "novel" / "color" / f"{i:03d}.png"), T, intr_novel))

    # 3. Size of the standard PLY
    ply = Path(cfg.out).with_suffix(".ply") if cfg.out else Path("/tmp/gsfix-splat-report.ply")
    write_ply(ply, mapper.gmap)
    report = {
        "scene": str(scene),
        "resolution": [frames[0][2].width, frames[0][2].height],
        "threads": torch.get_num_threads(),
        "online": online,
        "refine": {
            "iters": refined.n_iters,
            "seconds": refine_s,
            "loss_first": refined.loss_first,
            "loss_last": refined.loss_last,
        },  # fmt: skip
        "train": _evaluate(mapper, gt_views),
        "novel": _evaluate(mapper, novel),
        "gaussians": len(mapper.gmap),
        "map_mb": ply.stat().st_size / 2**20,
        "mapper_stats": mapper.stats(),
        "config": to_dict(cfg),
    }
    if cfg.out:
        atomic_write_text(Path(cfg.out), json.dumps(report, indent=2))
    return report


def summary(report: dict[str, Any]) -> str:
    o = report["online"]
    return (
        f"frames {o['frames']} (keyframes {o['keyframes']}) mapped at {o['frames_per_s']:.2f} "
        f"frames/s; a {o['stream_hz']:.1f} Hz stream: {'keeps up' if o['keeps_up'] else 'falls behind'}"
        f" (real-time factor {o['realtime_factor']:.2f}, lag p50 {o['lag_s']['p50']:.2f} s, max "
        f"{o['lag_s']['max']:.2f} s); {o['s_per_keyframe_amortised']:.2f} s per keyframe amortised "
        f"(keyframe p50 {o['keyframe_s'].get('p50', float('nan')):.2f} s, non-keyframe p50 "
        f"{o['non_keyframe_s'].get('p50', float('nan')):.2f} s)\n"
        f"train PSNR {o['train']['psnr_db']:.2f} dB online -> {report['train']['psnr_db']:.2f} dB "
        f"after {report['refine']['iters']} refinement steps ({report['refine']['seconds']:.0f} s), "
        f"SSIM {report['train']['ssim']:.3f}\n"
        f"novel PSNR {report['novel']['psnr_db']:.2f} dB, SSIM {report['novel']['ssim']:.3f}, "
        f"alpha coverage {report['novel']['alpha_coverage']:.2f}\n"
        f"{report['gaussians']} Gaussians, {report['map_mb']:.2f} MB (PLY)"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", required=True, help="ship-tank folder")
    p.add_argument("--out", default="", help="report JSON path")
    p.add_argument("-c", "--config", action="append", default=[], help="YAML (repeatable)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("overrides", nargs="*", help="key=value, e.g. mapper.kf_iters=6")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = build(
        ReportConfig,
        files=args.config,
        overrides=[f"scene={args.scene}", f"out={args.out}", *args.overrides],
    )
    report = run(cfg, progress=not args.no_progress)
    print(summary(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
