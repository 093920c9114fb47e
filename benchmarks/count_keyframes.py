"""Keyframes the CPU mapper profile selects on recorded inputs, counted offline.

With ``min_new_gaussians: 0`` (``configs/profiles/mapper_cpu.yaml``) keyframe selection depends
only on the frames (poses, depth, stamps), so :func:`~gsfix_online.mapping.splat.keyframes.
select_keyframe` over an input's frames gives the keyframes the splat node would pick, without
mapping. Frames are read as the repair graph's replay reads them: ``source.max_width`` 320 and
every ``--holdout``-th frame held out (``sources.replay.is_held_out``); ``--pose-file`` where the
input folder has that file, else the format's own (TUM: ``groundtruth.txt``; the table names the
file used). Arms: the profile as it is, and the profile with each ``--arm NAME KEY=VALUE ...``
(keys of ``KeyframeConfig``). Per input it also gives what the share rule's gate
(``share_below_step_m``) measures: the mean pose distance between consecutive frames over the path
so far (translation + ``rotation_weight_m`` x angle), at the end and at its highest::

    .venv/bin/python benchmarks/count_keyframes.py DIR/tum [DIR/tum ...] \
        [--pose-file estimated.txt] [--holdout 10] [--arm ungated share_below_step_m=0]

Prints a Markdown table: keyframes / mapped frames per arm, and the reasons of each.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "configs" / "profiles" / "mapper_cpu.yaml"


def read_frames(path: str, pose_file: str, max_width: int, holdout: int) -> tuple[list, str]:
    """The frames the splat node maps, and the pose file they were read with."""
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.replay import is_held_out

    used = pose_file if pose_file and (Path(path) / pose_file).is_file() else ""
    cfg = SourceConfig(path=path, pose_file=used, max_width=max_width)
    frames = [f for i, f in enumerate(open_source(cfg)) if not is_held_out(i, holdout)]
    return frames, used or "format default"


def count(frames: list, cfg) -> Counter:  # noqa: ANN001 - KeyframeConfig
    from gsfix_online.mapping.splat.keyframes import initialize_state, select_keyframe

    state = initialize_state()
    return Counter(select_keyframe(f, 0, state, cfg).reason for f in frames)


def main() -> None:
    from gsfix_online.core.config import build
    from gsfix_online.core.se3 import pose_distances
    from gsfix_online.mapping.splat.mapper import MapperConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", help="recorded inputs (e.g. a scene's tum/ folder)")
    ap.add_argument(
        "--pose-file",
        default="estimated.txt",
        help="pose list to read where the input has it (else the format's own)",
    )
    ap.add_argument("--max-width", type=int, default=320, help="source.max_width (the graph's)")
    ap.add_argument("--holdout", type=int, default=0, help="hold out every K-th frame (0: none)")
    ap.add_argument(
        "--arm",
        nargs="+",
        action="append",
        default=[],
        metavar=("NAME", "KEY=VALUE"),
        help="another arm: the profile with these keyframes.KEY=VALUE",
    )
    args = ap.parse_args()

    arms = {"profile": build(MapperConfig, files=[PROFILE]).keyframes}
    for name, *kv in args.arm:
        over = [f"keyframes.{s}" for s in kv]
        arms[name] = build(MapperConfig, files=[PROFILE], overrides=over).keyframes
    weight = arms["profile"].rotation_weight_m

    head = ["input", "poses", "frames", "mean step so far, m: end / max"] + list(arms)
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for path in args.inputs:
        frames, used = read_frames(path, args.pose_file, args.max_width, args.holdout)
        T = np.stack([f.T_world_cam for f in frames])
        steps = [pose_distances(a, b, weight)[0, 0] for a, b in zip(T[:-1], T[1:], strict=True)]
        mean = np.cumsum(steps) / np.arange(1, len(steps) + 1)
        cells = [path, used, str(len(frames)), f"{mean[-1]:.3f} / {mean.max():.3f}"]
        for cfg in arms.values():
            c = count(frames, cfg)
            why = ", ".join(f"{r} {n}" for r, n in sorted(c.items()) if r not in ("none", "first"))
            cells.append(f"**{len(frames) - c['none']}** ({why})")
        print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
