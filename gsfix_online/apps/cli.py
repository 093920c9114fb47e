"""The ``gsfix-online`` command: scene generation, conversion, inspection of inputs, replay, demo.

This is the outer layer: it parses arguments, configures logging and progress bars, times stages
and writes the resolved config next to every output. Components below it do no I/O of their own
beyond the files they are asked to read or write.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import NoReturn

logger = logging.getLogger("gsfix_online")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-c",
        "--config",
        action="append",
        default=[],
        metavar="YAML",
        help="config file (repeatable; later wins)",
    )
    p.add_argument(
        "overrides", nargs="*", metavar="KEY=VALUE", help="config overrides, e.g. scene.width=640"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def _graph_settings(p: argparse.ArgumentParser) -> None:
    """``-c`` and overrides of a command that runs a graph (see gsfix_online.jobs.config)."""
    p.add_argument(
        "-c", "--config", action="append", default=[], metavar="YAML",
        help="settings file (repeatable; later wins), e.g. -c paper (configs/profiles/paper.yaml)",
    )  # fmt: skip
    p.add_argument(
        "overrides", nargs="*", metavar="KEY=VALUE",
        help="NODE.KEY=VALUE sets a node's params (splat.threads=2); fixer.KEY, source.KEY and "
        "replay.KEY set every node that has that section (fixer.inference.steps=2)",
    )  # fmt: skip


def _source_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", help="dataset folder, bag (.bag, rosbag2 folder, .db3) or .mcap log")
    p.add_argument(
        "--format", default=None, help="source format (default: detect); same as source.format=..."
    )


NETWORK_NOTE = (
    "It binds 127.0.0.1 (this machine only) unless --host names another address: --host 0.0.0.0 "
    "opens it to every network the machine is on. There is no authentication and no "
    "encryption: anyone who reaches the port can read the maps and start repairs, so open it "
    "only on a network you trust (or reach it through an SSH tunnel: ssh -L PORT:127.0.0.1:PORT)."
)


PROFILE_HELP = (
    "profile every node of the repair graph (pyinstrument): a call tree per node in the run "
    "folder's work/profile/NODE.html and .txt"
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gsfix-online", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("scene", help="generate a synthetic scene with ground truth")
    p.add_argument("kind", choices=sorted(SCENE_FAMILIES), help="scene family")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument(
        "--variant",
        default="",
        help="comma-separated degradations: drift, noisy-depth, exposure, blur, gray, slow, "
        "real (= drift,noisy-depth,exposure,blur); see gsfix_online/scene/variants.py",
    )
    p.add_argument(
        "--camera",
        choices=["vga", "replica"],
        default=None,
        help="vga: 640x480; replica: 1200x680, fx=fy=600, cx=599.5, cy=339.5",
    )
    p.add_argument(
        "--formats",
        default="tum,mcap",
        help="comma-separated input formats to write: tum (always), mcap, replica",
    )
    p.add_argument("--no-mcap", action="store_true", help="skip writing log.mcap")
    _common(p)

    p = sub.add_parser("convert", help="convert any readable input to our MCAP log format")
    _source_args(p)
    p.add_argument("out", type=Path, help="output .mcap file")
    _common(p)

    p = sub.add_parser(
        "info", help="read an input through its reader and report frames, camera and problems"
    )
    _source_args(p)
    _common(p)

    p = sub.add_parser(
        "replay", help="replay an input with rate control and report the achieved rate"
    )
    _source_args(p)
    p.add_argument(
        "--mode", choices=["realtime", "max"], default=None, help="same as replay.mode=..."
    )
    p.add_argument(
        "--speed", type=float, default=None, help="multiple of real time; same as replay.speed=..."
    )
    _common(p)

    p = sub.add_parser("launch", help="start the nodes of a graph as processes and supervise them")
    p.add_argument("graph", type=Path, help="graph YAML (see configs/graphs/)")
    p.add_argument("--machine", default=None, help="start only the nodes placed on this machine")
    p.add_argument(
        "--emit", type=Path, default=None, help="write each node's config file here and exit"
    )
    _common(p)

    p = sub.add_parser(
        "node", help="run one node from its config file (for nodes on another machine)"
    )
    p.add_argument("name", help="node name (must match the file)")
    p.add_argument(
        "--config", "-c", dest="node_config", required=True, type=Path, help="node config file"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--no-progress", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(config=[], overrides=[])

    p = sub.add_parser("config", help="print the resolved configuration")
    _common(p)

    p = sub.add_parser("report", help="accuracy report of a component on a synthetic scene")
    p.add_argument("target", choices=sorted(REPORTS), help="what to evaluate")
    p.add_argument("--scene", required=True, type=Path, help="scene folder (gsfix-online scene)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    _common(p)

    p = sub.add_parser("fixer", help="GSFixer jobs: pretrain the embedded default model")
    fsub = p.add_subparsers(dest="fixer_command", required=True, metavar="JOB")
    q = fsub.add_parser("pretrain", help="pretrain the default model on procedural scenes")
    q.add_argument("--out", required=True, type=Path, help="output folder (scenes, checkpoints)")
    q.add_argument("--scenes", type=int, default=None, help="same as pretrain.scenes=N")
    q.add_argument("--steps", type=int, default=None, help="same as pretrain.steps=S")
    q.add_argument("--resume", action="store_true", help="continue from OUT/checkpoints")
    _common(q)

    p = sub.add_parser(
        "repair", help="run the repair graph offline over an input: score, repair, distil views"
    )
    p.add_argument("--input", required=True, help="dataset folder, bag or .mcap log")
    p.add_argument("--views", type=Path, default=None, help="TUM pose list of views to repair")
    p.add_argument(
        "--holdout", type=int, default=0, metavar="K",
        help="keep every K-th input frame out of mapping and fine-tuning and score every stage "
        "at those frames against the real images",
    )  # fmt: skip
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--views-gt", type=Path, default=None, help="folder of NNN.png ground truth")
    p.add_argument("--format", default=None, help="input format (default: detect)")
    p.add_argument("--graph", type=Path, default=None, help="graph YAML (default: repair.yaml)")
    p.add_argument(
        "--timeout", type=float, default=None, help="give up after this many s (default: never)"
    )
    _graph_settings(p)
    p.add_argument("--profile", action="store_true", help=PROFILE_HELP)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--no-progress", action="store_true", help=argparse.SUPPRESS)

    p = sub.add_parser(
        "export", help="export a finished run for other tools: 3DGS PLY, mesh PLY/GLB, rerun, MCAP"
    )
    p.add_argument("kind", choices=["ply", "mesh-ply", "glb", "rrd", "mcap"], help="what to write")
    p.add_argument("run", type=Path, help="run folder of gsfix-online repair")
    p.add_argument("--out", type=Path, default=None, help="output file (default: RUN/exports/)")
    p.add_argument("--input", default=None, help="rrd: add the input's frames (image, depth, pose)")
    p.add_argument("--input-every", type=int, default=1, metavar="N", help="rrd: every N-th frame")
    p.add_argument(
        "--no-keyframe-images", action="store_true", help="rrd: keyframe poses without renders"
    )
    _common(p)

    p = sub.add_parser(
        "serve", help="serve finished runs' maps to MapClient: renders, files, repairs",
        description="Serve finished runs' maps to MapClient (tcp://HOST:PORT). " + NETWORK_NOTE,
    )  # fmt: skip
    p.add_argument(
        "items", nargs="+", metavar="RUN_DIR | KEY=VALUE",
        help="run folder(s) of gsfix-online repair, then overrides of nodes/map_server.py's "
        "Params, e.g. server.mapper.distill_iters=40",
    )  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: 127.0.0.1, "
                   "this machine only; --host 0.0.0.0 opens it to the network, unauthenticated)")  # fmt: skip
    p.add_argument("--port", type=int, default=5590, help="TCP port (default: 5590)")
    p.add_argument("-c", "--config", action="append", default=[], metavar="YAML")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--no-progress", action="store_true", help=argparse.SUPPRESS)

    p = sub.add_parser(
        "view", help="web viewer of a run (or of a map server's live map): maps, cameras, distances",
        description="Web viewer of a run or of a map server's live map (http://HOST:PORT). "
        + NETWORK_NOTE,
    )  # fmt: skip
    p.add_argument(
        "items", nargs="*", metavar="RUN_DIR | KEY=VALUE",
        help="run folder of gsfix-online repair, then settings (host=..., port=...)",
    )  # fmt: skip
    p.add_argument("--live", default=None, metavar="ADDRESS|GRAPH", help="a map server's "
                   "address (tcp://127.0.0.1:5590) or a graph YAML with a map_server node, instead "
                   "of a run folder")  # fmt: skip
    p.add_argument("--map", default=None, help="--live: the map's name (default: the first)")
    p.add_argument("--server", default=None, metavar="ADDRESS",
                   help="a map server for the repair button (gsfix-online serve RUN)")  # fmt: skip
    p.add_argument("--host", default=None, help="address to bind (default: 127.0.0.1, this "
                   "machine only; --host 0.0.0.0 opens it to the network, unauthenticated); "
                   "host=...")  # fmt: skip
    p.add_argument("--port", type=int, default=None, help="HTTP port (default: 8080); port=...")
    p.add_argument("--labels", type=Path, default=None,
                   help="labels file (default: RUN/labels.json; --live: ./labels.json)")  # fmt: skip
    p.add_argument("-c", "--config", action="append", default=[], metavar="YAML",
                   help="settings file: host, port (repeatable; later wins)")  # fmt: skip
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")

    p = sub.add_parser("bench", help="run time against error: knob sweep, Pareto plots, skip table")
    from gsfix_online.jobs.bench.command import add_arguments as bench_arguments

    bench_arguments(p)

    p = sub.add_parser(
        "stress", help="numerical stress suite: every property under extreme inputs, timed"
    )
    p.add_argument("--minutes", type=float, default=None, help="same as minutes=N (default: 10)")
    p.add_argument("--seed", type=int, default=None, help="same as seed=S (default: 0)")
    p.add_argument("--area", default=None, choices=["geometry", "splat", "tsdf", "fixer"],
                   help="only this area's properties; same as area=A")  # fmt: skip
    p.add_argument("--out", type=Path, default=None, help="also write the summary as JSON")
    _common(p)

    p = sub.add_parser("demo", help="run the main job on the embedded synthetic ship tank")
    p.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder")
    p.add_argument("--profile", action="store_true", help=PROFILE_HELP)
    _common(p)
    _debug_flag(parser, sub)
    return parser


def _debug_flag(parser: argparse.ArgumentParser, sub: argparse._SubParsersAction) -> None:
    """``--debug`` before or after the command: an error shows its Python traceback instead of
    the one line that names what is wrong."""
    text = "on an error, show the Python traceback, not only the one-line message"
    parser.add_argument("--debug", action="store_true", help=text)
    todo = list(sub.choices.values())
    while todo:
        p = todo.pop()
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=text)
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo.extend(action.choices.values())


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )


def _load(args: argparse.Namespace, reads: tuple[str, ...], extra: list[str] | None = None):  # noqa: ANN202
    """The root config of a command that reads the sections ``reads`` (any other is an error)."""
    from gsfix_online.jobs.config import load_config

    overrides = list(args.overrides) + (extra or [])
    return load_config(args.config, overrides, args.command, reads)


def _no_settings(args: argparse.Namespace) -> None:
    """One-line error when a command that reads no settings is given some."""
    from gsfix_online.core.config import ConfigError, full_key, gather, origin_of

    settings, origins = gather(args.config, args.overrides)
    if settings:
        key = full_key(origins, next(iter(settings)))
        raise ConfigError(
            f"{origin_of(origins, key)}: gsfix-online {args.command} reads no settings ('{key}')"
        )


def _progress(it, total: int | None, desc: str, disable: bool):  # noqa: ANN001, ANN202
    from gsfix_online.core.progress import track

    return track(it, desc, total or None, "frame", enabled=not disable)


SCENE_FAMILIES = {"ship-tank": "tank", "room": "room"}  # scene KIND -> scene.family


def cmd_scene(args: argparse.Namespace) -> int:
    from gsfix_online.jobs.config import ConfigError, load_config, read_sections, write_config
    from gsfix_online.scene import generate_ship_tank, variant_overrides
    from gsfix_online.sources.mcap_log import write_mcap

    # defaults < YAML < KIND, --camera, --variant < KEY=VALUE
    family = SCENE_FAMILIES[args.kind]
    preset = [f"scene.family={family}", *variant_overrides(args.variant, args.camera)]
    cfg = load_config(args.config, preset + list(args.overrides), "scene", ("scene",))
    if cfg.scene.family != family:
        raise ConfigError(f"scene {args.kind} conflicts with scene.family={cfg.scene.family}")
    formats = {f.strip() for f in args.formats.split(",") if f.strip()}
    if not formats <= {"tum", "mcap", "replica"}:
        raise ConfigError(f"--formats: expected tum, mcap or replica, got {args.formats!r}")
    mcap = "mcap" in formats and not args.no_mcap
    t0 = time.perf_counter()
    info = generate_ship_tank(
        cfg.scene, args.out, write_mcap=write_mcap if mcap else None, replica="replica" in formats
    )
    write_config(read_sections(cfg, ("scene",)), args.out / "config.yaml")
    print(
        f"{args.kind}: {info.n_frames} frames, {info.n_novel} novel views in {time.perf_counter() - t0:.1f} s -> {args.out}"
    )
    return 0


def _source_cfg(args: argparse.Namespace) -> list[str]:
    extra = [f"source.path={args.src}"]
    if args.format:
        extra.append(f"source.format={args.format}")
    return extra


def cmd_convert(args: argparse.Namespace) -> int:
    from gsfix_online.jobs.config import read_sections, write_config
    from gsfix_online.sources import open_source
    from gsfix_online.sources.mcap_log import McapLogWriter

    cfg = _load(args, ("source",), _source_cfg(args))
    reader = open_source(cfg.source)
    t0 = time.perf_counter()
    with McapLogWriter(args.out) as w:  # atomic: a failed convert leaves no partial log
        for frame in _progress(reader, len(reader), "convert", args.no_progress):
            w.write(frame)
    write_config(
        read_sections(cfg, ("source",)), args.out.with_name(args.out.stem + ".config.yaml")
    )
    dt = time.perf_counter() - t0
    lost = f" ({reader.stats.frames_lost} frames lost)" if reader.stats.frames_lost else ""
    print(
        f"{reader.format} -> {args.out}: {w.frames} frames{lost} in {dt:.1f} s; "
        f"depth {reader.depth.describe()}; {json.dumps(reader.stats.as_dict())}"
    )
    return 0


def _describe(reader, frames: int, dt: float, first) -> str:  # noqa: ANN001
    rows = [
        ("format", reader.format),
        ("path", str(reader.path)),
        ("frames", f"{frames} ({frames / max(dt, 1e-9):.1f} frames/s read)"),
    ]
    if first is not None:
        kind = "grayscale" if first.is_gray else "RGB"
        k = first.intrinsics
        cam = reader.camera or k
        rows.append(("camera", f"{cam.width}x{cam.height} {kind}, fx={cam.fx:.2f} "
                               f"fy={cam.fy:.2f} cx={cam.cx:.2f} cy={cam.cy:.2f}"))  # fmt: skip
        limit = reader.cfg.max_width
        if (k.width, k.height) == (cam.width, cam.height):
            why = f"(source.max_width={limit})" if limit else "(source.max_width not set)"
            rows.append(("processing", f"{k.width}x{k.height}, the camera's {why}"))
        else:
            rows.append(("processing", f"{k.width}x{k.height}, fx={k.fx:.2f} fy={k.fy:.2f} "
                         f"cx={k.cx:.2f} cy={k.cy:.2f} (source.max_width={limit})"))  # fmt: skip
    rows.append(("depth", reader.depth.describe()))
    rows += [(key, str(value)) for key, value in reader.stats.as_dict().items() if key != "frames"]
    rows += [("warning", text) for text in reader.warnings]
    width = max(len(key) for key, _ in rows) + 2
    return "\n".join(f"{key:<{width}}{value}" for key, value in rows)


def cmd_info(args: argparse.Namespace, replay: bool = False) -> int:
    from gsfix_online.sources import open_source
    from gsfix_online.sources.replay import paced

    extra = _source_cfg(args)
    if replay and args.mode:
        extra.append(f"replay.mode={args.mode}")
    if replay and args.speed is not None:
        extra.append(f"replay.speed={args.speed}")
    cfg = _load(args, ("source", "replay") if replay else ("source",), extra)
    reader = open_source(cfg.source)
    frames = iter(reader)
    if replay:
        frames = paced(frames, cfg.replay, time.monotonic, time.sleep)
    t0 = time.perf_counter()
    first = None
    n = 0
    for frame in _progress(frames, len(reader), "replay" if replay else "read", args.no_progress):
        first = first or frame
        n += 1
    print(_describe(reader, n, time.perf_counter() - t0, first))
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    import yaml

    from gsfix_online.jobs.config import SECTIONS, to_dict

    print(yaml.safe_dump(to_dict(_load(args, SECTIONS)), sort_keys=False), end="")
    return 0


def cmd_launch(args: argparse.Namespace) -> int:
    from gsfix_online.runtime.graph import load_graph, write_node_file
    from gsfix_online.runtime.launcher import Launcher

    graph = load_graph(args.graph, args.overrides, files=args.config)
    if args.emit is not None:
        names = [
            n for n, e in graph.nodes.items() if args.machine is None or e.machine == args.machine
        ]
        for name in names:
            print(write_node_file(graph, name, args.emit / f"{name}.yaml"))
        return 0
    return Launcher(graph, machine=args.machine).run()


def cmd_node(args: argparse.Namespace) -> int:
    from gsfix_online.runtime.graph import run_node_file

    exit_without_teardown(run_node_file(args.node_config, args.name))


def exit_without_teardown(code: int) -> NoReturn:
    """End a node's process once its loop has returned, without the interpreter's teardown of
    every module: the node has closed its sockets and written its files, and the exit handlers
    (a timeline's last spans) and the log still run. Tearing down a process that imported
    torch and diffusers took 1.8 s of CPU, and a graph's nodes all end at once on 2 cores:
    3.9 s of the tiny tank's 34 s repair run went to waiting for them."""
    import atexit
    import os

    atexit._run_exitfuncs()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def cmd_repair(args: argparse.Namespace) -> int:
    from gsfix_online.core.progress import Progress
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH, prepare, run_graph

    graph_file, info, n_views = prepare(
        args.input, args.views, args.out, args.views_gt, args.graph or DEFAULT_GRAPH,
        args.overrides, args.format, args.holdout, files=args.config,
    )  # fmt: skip
    held = f" ({info.held_out} held out)" if info.held_out else ""
    cw, ch = info.camera_size
    camera = f" (camera {cw}x{ch})" if (cw, ch) != (info.width, info.height) else ""
    print(
        f"repair: {info.format} input, {info.frames} frames{held} at {info.width}x{info.height}"
        f"{camera}; {n_views} views; graph {graph_file}",
        flush=True,
    )
    # views decided of all views (the planner's proposals raise the total); node lines above it
    with Progress("repair", n_views, "view", enabled=not args.no_progress) as bar:
        res = run_graph(graph_file, timeout_s=args.timeout, progress=bar, profile=args.profile)
    if res.returncode != 0:
        print(f"gsfix-online repair: error: {res.message}", file=sys.stderr)
        return res.returncode
    s = res.metrics["summary"] if res.metrics else {}
    print(f"{s.get('views')} views: {s.get('repaired')} repaired, {s.get('skipped')} skipped "
          f"in {res.seconds:.1f} s")  # fmt: skip
    groups = s.get("groups") or {"all views": s.get("stages") or {}}
    for group, stages in groups.items():
        if stages:
            print(f" {group}:")
        for stage, v in stages.items():
            print(f"  {stage:<12} PSNR {v['psnr_db']:6.2f} dB  SSIM {v['ssim']:.3f}  "
                  f"({v['views']} views)")  # fmt: skip
    print(f"metrics {args.out / 'metrics.json'}, report {args.out / 'report.html'}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import copy
    import dataclasses

    from gsfix_online.core.config import build_from, gather, read_yaml, to_overrides
    from gsfix_online.jobs.config import SECTIONS, Config, check_reads
    from gsfix_online.jobs.demo import READS, run_demo
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH
    from gsfix_online.runtime.graph import apply_settings

    # Root sections the demo reads; every other key names a node of the repair graph, checked
    # here (with where it came from) and kept in demo.extra_overrides, so that the config.yaml
    # the demo writes runs the same demo again
    settings, origins = gather(args.config, args.overrides)
    root = {k: v for k, v in settings.items() if k in SECTIONS}
    nodes = {k: v for k, v in settings.items() if k not in SECTIONS}
    check_reads("demo", root, origins, READS)
    cfg = build_from(Config, root, origins)
    if nodes:
        graph = copy.deepcopy(read_yaml(DEFAULT_GRAPH))
        apply_settings(graph, nodes, origins, str(DEFAULT_GRAPH), READS, ("replay", "fixer"))
        extra = [*cfg.demo.extra_overrides, *to_overrides(nodes)]
        cfg = dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, extra_overrides=extra))
    return run_demo(cfg, args.out, progress=not args.no_progress, profile=args.profile)


def report_tsdf(args: argparse.Namespace) -> int:
    from gsfix_online.core.config import build
    from gsfix_online.jobs.tsdf_report import TsdfReportConfig, format_report, run_report

    cfg = build(TsdfReportConfig, files=args.config, overrides=args.overrides)
    rep = run_report(cfg, args.scene, args.out, progress=not args.no_progress)
    print(format_report(rep))
    print(f"-> {args.out / 'tsdf_report.json'}")
    return 0


def report_splat(args: argparse.Namespace) -> int:
    from gsfix_online.core.config import build, write_config
    from gsfix_online.jobs.splat_report import ReportConfig, run, summary

    out = args.out / "splat_report.json"
    over = [f"scene={args.scene}", f"out={out}", *args.overrides]
    cfg = build(ReportConfig, files=args.config, overrides=over)
    write_config(cfg, args.out / "splat_config.yaml")
    print(summary(run(cfg, progress=not args.no_progress)))
    print(f"-> {out}")
    return 0


def cmd_fixer_pretrain(args: argparse.Namespace) -> int:
    from gsfix_online.core.config import build, write_config
    from gsfix_online.jobs.pretrain import PretrainJob, run_pretrain

    extra = [f"pretrain.{k}={v}" for k in ("scenes", "steps") if (v := getattr(args, k))]
    job = build(PretrainJob, files=args.config, overrides=list(args.overrides) + extra)
    write_config(job, args.out / "config.yaml")
    from gsfix_online.core.progress import Progress

    with Progress("pretrain", job.pretrain.steps, "step", enabled=not args.no_progress) as bar:

        def progress(step: int, total: int, text: str) -> None:
            bar.set(step, total, text)

        res = run_pretrain(job, args.out, resume=args.resume, progress=progress)
    f = res.figures
    print(
        f"pretrained to step {res.step} in {f['times']['total_s']:.0f} s: held-out loss "
        f"{f['val_loss']:.4f}; PSNR on {f.get('val_views', 0)} held-out views: repair "
        f"{f.get('psnr_repair_db', float('nan')):.2f} dB, 3DGS input "
        f"{f.get('psnr_gs_input_db', float('nan')):.2f} dB, mesh fill "
        f"{f.get('psnr_mesh_fill_db', float('nan')):.2f} dB -> {res.base} "
        f"({f['base_checkpoint_mb']:.1f} MB; fixer.model.path={args.out / 'base'})"
    )
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import dataclasses

    from gsfix_online.core.config import build
    from gsfix_online.runtime.graph import node_module

    server = node_module("map_server")  # the graph's map server node, serving alone
    Params, serve = server.Params, server.serve

    overrides = [i for i in args.items if "=" in i]
    runs = [i for i in args.items if "=" not in i]
    if not runs:
        print("gsfix-online serve: error: name at least one run folder", file=sys.stderr)
        return 2
    over = [*overrides, f"host={args.host}", f"port={args.port}"]
    params = dataclasses.replace(build(Params, files=args.config, overrides=over), runs=runs)

    def ready(loop) -> None:  # noqa: ANN001
        for m in loop.service.maps.values():
            print(f"serving map {m.name!r} (version {m.version}, {len(m.gmap)} Gaussians, "
                  f"mesh {'yes' if m.has_mesh else 'no'}) on {loop.address}", flush=True)  # fmt: skip

    return serve(params, ready)  # a bad run folder or a busy port: main() says it in one line


def _flags(args: argparse.Namespace, names: tuple[str, ...]) -> list[str]:
    """The flags given among ``names`` as overrides of the same keys (a flag wins)."""
    return [f"{n}={getattr(args, n)}" for n in names if getattr(args, n) is not None]


def cmd_view(args: argparse.Namespace) -> int:
    from gsfix_online.apps.viewer import ViewConfig, cli_main
    from gsfix_online.core.config import ConfigError, build

    overrides = [i for i in args.items if "=" in i]
    runs = [Path(i) for i in args.items if "=" not in i]
    if len(runs) > 1:
        raise ConfigError(f"view one run folder at a time, got {len(runs)}")
    flags = _flags(args, ("host", "port"))
    cfg = build(ViewConfig, files=args.config, overrides=[*overrides, *flags])
    args.run, args.host, args.port = (runs[0] if runs else None), cfg.host, cfg.port
    return cli_main(args)


FIXER_JOBS = {"pretrain": cmd_fixer_pretrain}


def cmd_stress(args: argparse.Namespace) -> int:
    from gsfix_online.core.config import build
    from gsfix_online.jobs.stress.runner import StressConfig, cli_main

    flags = _flags(args, ("minutes", "seed", "area"))
    cfg = build(StressConfig, files=args.config, overrides=[*args.overrides, *flags])
    return cli_main(args, cfg)


def cmd_export(args: argparse.Namespace) -> int:
    from gsfix_online.apps.export import export

    _no_settings(args)
    res = export(
        args.kind, args.run, args.out, args.input, args.input_every,
        keyframe_images=not args.no_keyframe_images,
    )  # fmt: skip
    print(f"{args.kind} -> {res.summary()}")
    return 0


def report_fixer(args: argparse.Namespace) -> int:
    from gsfix_online.core.config import build
    from gsfix_online.jobs.fixer_report import FixerReportConfig, run, summary

    over = [f"scene={args.scene}", f"out={args.out}", *args.overrides]
    cfg = build(FixerReportConfig, files=args.config, overrides=over)
    print(summary(run(cfg, progress=not args.no_progress)))
    print(f"-> {args.out / 'fixer_report.json'}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from gsfix_online.jobs.bench.command import cli_main

    return cli_main(args)


# report target -> function(args) -> exit code; each owns its config (``-c``, overrides)
REPORTS = {"tsdf": report_tsdf, "splat": report_splat, "fixer": report_fixer}


COMMANDS = {
    "scene": cmd_scene,
    "convert": cmd_convert,
    "info": cmd_info,
    "replay": lambda a: cmd_info(a, replay=True),
    "launch": cmd_launch,
    "node": cmd_node,
    "config": cmd_config,
    "demo": cmd_demo,
    "repair": cmd_repair,
    "serve": cmd_serve,
    "view": cmd_view,
    "export": cmd_export,
    "stress": cmd_stress,
    "fixer": lambda a: FIXER_JOBS[a.fixer_command](a),
    "report": lambda a: REPORTS[a.target](a),
    "bench": cmd_bench,
}


def _user_errors() -> tuple[type[BaseException], ...]:
    """The errors that are the user's input or system, not a bug: each says what is wrong in
    one line (a file that cannot be read or written, a damaged map, a bad setting)."""
    from gsfix_online.apps.export import ExportError
    from gsfix_online.core.config import ConfigError
    from gsfix_online.core.types import FrameError
    from gsfix_online.mapping.mesh import MeshFormatError
    from gsfix_online.mapping.splat.ply import PlyFormatError
    from gsfix_online.runtime.transport import TransportError
    from gsfix_online.services.run_folder import RunFolderError
    from gsfix_online.sources.base import SourceError

    errors: tuple[type[BaseException], ...] = (
        ConfigError, SourceError, FrameError, TransportError, ExportError, RunFolderError,
        PlyFormatError, MeshFormatError, OSError,
    )  # fmt: skip
    zmq = sys.modules.get("zmq")  # a socket's error (an address in use) once zmq is in use
    return errors + ((zmq.ZMQError,) if zmq is not None else ())


def error_line(exc: BaseException) -> str:
    """One line for a user error; an OSError names its path (``PATH: Permission denied``)."""
    if isinstance(exc, OSError) and exc.strerror:
        names = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        text = f"{' -> '.join(names)}: {exc.strerror}" if names else exc.strerror
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split("\n"))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if getattr(args, "debug", False) or not isinstance(exc, _user_errors()):
            raise
        print(f"gsfix-online {args.command}: error: {error_line(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
