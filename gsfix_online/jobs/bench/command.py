"""``gsfix-online bench``: the knob sweep (``--quick`` or full), or the skip table (``--skips``).

Process code: it picks the input (the synthetic ship tank, or ``--input SRC --views VIEWS.txt
--views-gt DIR``), the runs, and the result files, runs the sweep (:mod:`.sweep`) and writes the
CSV, the JSON, the Pareto plot or the skip table. Outputs (under ``--results``):

- ``--quick``: ``bench_quick_cpu.{csv,json}``, ``bench_quick_pareto.png``;
- full sweep: ``bench_full_cpu.{csv,json}``, ``bench_full_pareto.png``;
- ``--skips``: ``bench_skips_cpu.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from pathlib import Path
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true",
                      help="the most important knobs, 2 values each, on a small tank (~11 min)")  # fmt: skip
    mode.add_argument("--skips", action="store_true",
                      help="each skip against the same run without it, in one table")  # fmt: skip
    p.add_argument("--knobs", nargs="+", default=None, metavar="NAME",
                   help="full sweep: only these knobs (see gsfix_online/jobs/bench/knobs.py)")  # fmt: skip
    p.add_argument("--input", default=None, help="any input a reader accepts (default: the tank)")
    p.add_argument("--views", type=Path, default=None, help="--input: TUM pose list of views")
    p.add_argument("--views-gt", type=Path, default=None, help="--input: NNN.png ground truth")
    p.add_argument("--views-depth", type=Path, default=None,
                   help="--input: NNN.png ground-truth depth (metres x --depth-scale)")  # fmt: skip
    p.add_argument("--depth-scale", type=float, default=5000.0)
    p.add_argument("--gt-mesh", type=Path, default=None, help="--input: ground-truth mesh PLY")
    p.add_argument("--holdout", type=int, default=0, metavar="K",
                   help="also score every K-th input frame, held out of mapping")  # fmt: skip
    p.add_argument("--width", type=int, default=None, help="tank width px")
    p.add_argument("--height", type=int, default=None, help="tank height px")
    p.add_argument("--frames", type=int, default=None, help="tank frames")
    p.add_argument("--n-views", type=int, default=None, help="tank novel views to repair")
    p.add_argument("--out", type=Path, default=Path("outputs") / "bench",
                   help="output folder (default: outputs/bench in the current folder)")  # fmt: skip
    p.add_argument("--work", type=Path, default=None,
                   help="run folders and generated scenes (default: OUT/work)")  # fmt: skip
    p.add_argument("--results", type=Path, default=None,
                   help="folder of the CSV, JSON, plot and table (default: OUT)")  # fmt: skip
    p.add_argument("--name", default=None, help="result file stem (default bench_{quick,full,"
                   "skips}_cpu)")  # fmt: skip
    p.add_argument("--timeout", type=float, default=None,
                   help="give up a run after s (default: 900 with --quick, else 3600)")  # fmt: skip
    p.add_argument("--no-run", action="store_true",
                   help="run nothing: write the table and plots from the runs done so far")  # fmt: skip
    p.add_argument("-c", "--config", action="append", default=[], metavar="YAML",
                   help="repair-graph settings for every run (repeatable; later wins), e.g. "
                   "-c paper")  # fmt: skip
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="repair-graph settings for every run: NODE.KEY=VALUE, fixer.KEY=VALUE "
                   "(as gsfix-online repair)")  # fmt: skip
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--no-progress", action="store_true", help=argparse.SUPPRESS)


def _input(args: argparse.Namespace, scene: dict[str, int]) -> Any:
    from gsfix_online.core.config import ConfigError
    from gsfix_online.jobs.bench.runner import BenchInput
    from gsfix_online.jobs.bench.sweep import ship_tank_input

    if args.input is None:
        if any(x is not None for x in (args.views, args.views_gt, args.views_depth, args.gt_mesh)):
            raise ConfigError("--views, --views-gt, --views-depth and --gt-mesh need --input")
        s = {k: getattr(args, a) or scene[k] for k, a in
             (("width", "width"), ("height", "height"), ("n_frames", "frames"),
              ("views", "n_views"))}  # fmt: skip
        inp = ship_tank_input(args.work, s["width"], s["height"], s["n_frames"], s["views"])
        return dataclasses.replace(inp, holdout=args.holdout)
    for flag, path in (("--views-gt", args.views_gt), ("--views-depth", args.views_depth)):
        if path is not None and not path.is_dir():
            raise ConfigError(f"{flag} {path} is not a folder of NNN.png images")
    if args.gt_mesh is not None and not args.gt_mesh.is_file():
        raise ConfigError(f"--gt-mesh {args.gt_mesh} is not a file")
    return BenchInput(Path(args.input), args.views, args.views_gt, args.views_depth,
                      args.gt_mesh, args.holdout, str(args.input), args.depth_scale)  # fmt: skip


def _settings(args: argparse.Namespace) -> list[str]:
    """``-c`` files then overrides as one list of overrides (the runs' keys name them), checked
    against the repair graph before any run starts."""
    import copy

    from gsfix_online.core.config import gather, read_yaml, to_overrides
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH
    from gsfix_online.runtime.graph import apply_settings

    settings, origins = gather(args.config, args.overrides)
    apply_settings(copy.deepcopy(read_yaml(DEFAULT_GRAPH)), settings, origins, str(DEFAULT_GRAPH))
    files, _ = gather(args.config)
    return [*to_overrides(files), *args.overrides]


def main(args: argparse.Namespace) -> int:
    from gsfix_online.jobs.bench import knobs as K
    from gsfix_online.jobs.bench.sweep import Results, RunSpec, knob_runs, machine, run_sweep

    # 1. The runs and where their results go (never into the installed package or a checkout)
    args.work = args.work or args.out / "work"
    args.results = args.results or args.out
    mode = "quick" if args.quick else "skips" if args.skips else "full"
    stem = args.name or f"bench_{mode}_cpu"
    if mode == "full" and args.knobs:
        K.check_values(dict.fromkeys(args.knobs))
    results = Results(args.results / f"{stem}.json", {})
    full_scene = {"width": 160, "height": 120, "n_frames": 60, "views": 8}
    scenes = {"quick": K.QUICK_SCENE, "skips": K.SKIPS_SCENE, "full": full_scene}
    base = _settings(args)
    inp = _input(args, scenes[mode])
    borrow: tuple[Any, ...] = ()
    if mode == "quick":
        base = [*K.QUICK_BASE, *base]
        specs = knob_runs(K.QUICK, K.QUICK_DEFAULTS)
    elif mode == "skips":
        from gsfix_online.jobs.bench.skips import SKIPS

        # the quick sweep's base; its default run is borrowed when the scenes match
        base = [*K.QUICK_BASE, *base]
        quick = args.results / "bench_quick_cpu.json"
        borrow = (Results(quick, {}),) if quick.is_file() else ()
        specs = [RunSpec({"skip": "none (defaults)"})]
        specs += [RunSpec({"skip": s.name}, list(s.off)) for s in SKIPS if s.off]
    else:
        names = args.knobs or list(K.KNOBS)
        specs = knob_runs({n: K.KNOBS[n].values for n in names})
    cmd = "gsfix-online bench" + {"quick": " --quick", "skips": " --skips", "full": ""}[mode]
    results.meta.update({"command": cmd, "input": inp.describe(), "base": base, **machine()})
    # 2. The runs (those done already are kept)
    t0 = time.monotonic()
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    print(f"bench {mode}: {len(specs)} runs on {inp.describe()['name']}; results "
          f"{results.path}", flush=True)  # fmt: skip
    timeout = args.timeout or (900.0 if mode == "quick" else 3600.0)
    rows = run_sweep(inp, specs, base, args.work / stem, results, timeout,
                     say=lambda s: print(s, flush=True), borrow=borrow,
                     run=not args.no_run)  # fmt: skip
    wall = time.monotonic() - t0
    done = {"started": started, "wall_s_this_call": round(wall, 1),
            "load_avg_end": [round(x, 2) for x in os.getloadavg()]}  # fmt: skip
    # 3. The plot, or the skip table
    if mode == "skips":
        return _write_skips(args.results / stem, rows, results, done, len(specs))
    return _write_sweep(args.results / stem, rows, results, done, cmd, inp, len(specs))


def _write_sweep(
    stem: Path, rows: list[dict], results: Any, done: dict, cmd: str, inp: Any, n_runs: int
) -> int:
    from gsfix_online.jobs.bench.pareto import PANELS, front_gap, pareto_front, plot_fronts

    ok = [r for r in rows if r.get("rc") == 0]
    # CPU seconds of the nodes where every run has them (other jobs' load barely moves them)
    time_key = "cpu_s" if ok and all(r.get("cpu_s") for r in ok) else "total_s"
    fronts: dict[str, Any] = {"time": time_key}
    t = [r.get(time_key) for r in ok]
    for col, _, higher in PANELS:
        err = [(-r[col] if higher else r[col]) if r.get(col) is not None else None for r in ok]
        idx = [i for i, r in enumerate(ok) if r.get("knob") == "default"]
        fronts[col] = {
            "front": [f"{ok[i]['knob']}={ok[i]['value']}" for i in pareto_front(t, err)],
            "default_behind": front_gap(t, err, idx[0]) if idx else math.nan,
        }
    results.write({**done, "fronts": fronts})
    png = stem.with_name(stem.name.replace("_cpu", "") + "_pareto.png")
    if len(ok) >= 2:
        plot_fronts(ok, png, f"{cmd} on {inp.describe()['name']}: time against error", time_key)
        print(f"-> {png}")
    for col, f in fronts.items():
        if col == "time":
            continue
        print(f"{col}: front {', '.join(f['front']) or '–'}; defaults behind by "
              f"{f['default_behind']:.3g}")  # fmt: skip
    print(f"-> {results.path} and {results.path.with_suffix('.csv')} "
          f"({done['wall_s_this_call']:.0f} s)")  # fmt: skip
    return 0 if len(ok) == n_runs else 1


def _write_skips(stem: Path, rows: list[dict], results: Any, done: dict, n_runs: int) -> int:
    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.jobs.bench.skips import skip_table, to_markdown

    on = [r for r in rows if r.get("skip") == "none (defaults)" and r.get("rc") == 0]
    offs = {r["skip"]: r for r in rows if r.get("rc") == 0 and r not in on}
    table = skip_table(on[0] if on else {}, offs)
    results.write({**done, "table": table})
    md = to_markdown(table)
    atomic_write_text(stem.with_suffix(".md"), md + "\n")
    print(md)
    print(f"-> {stem.with_suffix('.md')} and {results.path}")
    return 0 if len(offs) + len(on) == n_runs and all(r.get("rc") == 0 for r in rows) else 1


def cli_main(args: argparse.Namespace) -> int:
    try:
        return main(args)
    except ValueError as exc:
        print(f"gsfix-online bench: error: {exc}", file=sys.stderr)
        return 2
