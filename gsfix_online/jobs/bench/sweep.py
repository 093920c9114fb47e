"""A sweep: runs of the repair graph, one row each, resumable, written as CSV, JSON and plots.

Every run is a :class:`RunSpec` (a label and its overrides). Its key is the input, the sweep's
base overrides and its own overrides; :class:`Results` keeps the rows by key in the results JSON,
rewritten (atomically, with the CSV) after every run, so a sweep that stopped resumes where it
did: a run whose key holds a finished row is not run again. Runs go one after the other (each
uses the machine's cores); the synthetic ship tank is generated once per size into the work
folder (:func:`ship_tank_input`).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gsfix_online.core.io import atomic_write_text
from gsfix_online.jobs.bench.knobs import KNOBS, one_at_a_time, overrides_for
from gsfix_online.jobs.bench.runner import BenchInput, run_one

logger = logging.getLogger(__name__)

# CSV columns in this order first; the rest follow as they first occur
LEAD = ("knob", "value", "rc", "total_s", "cpu_s", "map_s", "refine_s", "finetune_s", "fix_s",
        "distill_s", "write_s", "peak_rss_mb", "peak_node_rss_mb", "psnr_gs", "ssim_gs",
        "psnr_fixed", "ssim_fixed", "psnr_output", "ssim_output", "psnr_final", "ssim_final",
        "depth_mae_cm", "mesh_accuracy_cm", "mesh_completeness_cm")  # fmt: skip


@dataclass(frozen=True)
class RunSpec:
    label: dict[str, Any]  # knob and value (or skip), the columns that name the run
    overrides: list[str] = field(default_factory=list)

    @property
    def tag(self) -> str:
        """A folder name for the run."""
        text = "_".join(f"{v}" for v in self.label.values()) or "default"
        return "".join(c if c.isalnum() or c in "._-" else "-" for c in text)


def knob_runs(
    sweep: dict[str, tuple[Any, ...]], defaults: dict[str, Any] | None = None
) -> list[RunSpec]:
    """The one-at-a-time runs of ``sweep`` (see :func:`~gsfix_online.jobs.bench.knobs.one_at_a_time`)."""
    specs = []
    for values in one_at_a_time(sweep, defaults):
        ((name, value),) = values.items() if values else (("default", ""),)
        specs.append(RunSpec({"knob": name, "value": value}, overrides_for(values)))
    return specs


def run_key(inp: BenchInput, base: list[str], spec: RunSpec) -> str:
    return json.dumps({"input": inp.describe(), "base": base, "overrides": spec.overrides},
                      sort_keys=True)  # fmt: skip


class Results:
    """The rows of a sweep by run key, in ``path`` (JSON) and ``path.with_suffix('.csv')``."""

    def __init__(self, path: Path, meta: dict[str, Any]) -> None:
        self.path = Path(path)
        self.meta = dict(meta)
        self.rows: dict[str, dict[str, Any]] = {}
        if self.path.is_file():
            try:
                old = json.loads(self.path.read_text())
                self.rows = {r["key"]: r for r in old["rows"]}
            except (json.JSONDecodeError, KeyError, TypeError) as exc:
                raise ValueError(f"{self.path} is not a bench results file ({exc})") from None

    def done(self, key: str) -> bool:
        return self.rows.get(key, {}).get("rc") == 0

    def put(self, row: dict[str, Any]) -> None:
        self.rows[row["key"]] = row
        self.write()

    def write(self, extra: dict[str, Any] | None = None) -> None:
        self.meta.update(extra or {})
        doc = {**self.meta, "rows": list(self.rows.values())}
        atomic_write_text(self.path, json.dumps(doc, indent=1, default=str) + "\n")
        atomic_write_text(self.path.with_suffix(".csv"), to_csv(list(self.rows.values())))


def to_csv(rows: list[dict[str, Any]]) -> str:
    cols = [c for c in LEAD if any(c in r for r in rows)]
    for r in rows:
        cols += [c for c in r if c not in cols and not isinstance(r[c], dict | list)]
    buf = io.StringIO()
    w = csv.DictWriter(buf, cols, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: _cell(r.get(c)) for c in cols})
    return buf.getvalue()


def _cell(v: Any) -> Any:
    return f"{v:.4g}" if isinstance(v, float) else ("" if v is None else v)


def machine() -> dict[str, Any]:
    return {"machine": f"{platform.machine()} {platform.processor()}".strip(),
            "cpus": os.cpu_count(), "load_avg": [round(x, 2) for x in os.getloadavg()]}  # fmt: skip


def run_sweep(
    inp: BenchInput,
    specs: list[RunSpec],
    base: list[str],
    work: Path,
    results: Results,
    timeout_s: float | None = None,
    say: Callable[[str], None] = print,
    borrow: tuple[Results, ...] = (),  # other sweeps' results: a finished row of the same key
    run: bool = True,  # False: run nothing, return the rows there are (a run not done: absent)
) -> list[dict[str, Any]]:
    """Run every spec whose key holds no finished row (here or in ``borrow``: then copied);
    the rows of all specs, in spec order."""
    work = Path(work)
    for n, spec in enumerate(specs, 1):
        key = run_key(inp, base, spec)
        if results.done(key):
            continue
        lent = next((b.rows[key] for b in borrow if b.done(key)), None)
        if lent is not None:
            results.put({**lent, **spec.label})
            continue
        if not run:
            continue
        name = ", ".join(f"{k}={v}" for k, v in spec.label.items())
        say(f"[bench] run {n}/{len(specs)}: {name} ...")
        load0 = os.getloadavg()[0]
        started = time.strftime("%Y-%m-%d %H:%M:%S")
        run_dir = work / "runs" / spec.tag
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        with (work / "runs" / f"{spec.tag}.log").open("w") as log:
            row = run_one(inp, [*base, *spec.overrides], run_dir, timeout_s, log=log)
        row = {"key": key, **spec.label, **row, "overrides": spec.overrides, "started": started,
               "load_avg_1m": [round(load0, 2), round(os.getloadavg()[0], 2)]}  # fmt: skip
        results.put(row)
        status = (f"{row['total_s']:.0f} s, final {row.get('psnr_final') or float('nan'):.2f} dB"
                  if row["rc"] == 0 else f"failed: {row.get('error')}")  # fmt: skip
        say(f"[bench] run {n}/{len(specs)}: {name}: {status}")
    keys = [run_key(inp, base, s) for s in specs]
    return [results.rows[k] for k in keys if k in results.rows]


def ship_tank_input(
    work: Path, width: int, height: int, frames: int, views: int, seed: int = 0
) -> BenchInput:
    """The synthetic ship tank (generated once into ``work``): its MCAP log, its first ``views``
    novel views with their colour and depth, and its ground-truth mesh."""
    from gsfix_online.core.config import build
    from gsfix_online.scene import generate_ship_tank
    from gsfix_online.scene.config import ShipTankConfig
    from gsfix_online.sources.mcap_log import write_mcap

    name = f"ship-tank {width}x{height} {frames} frames seed {seed}"
    scene = Path(work) / f"tank_{width}x{height}_{frames}f_s{seed}"
    if not (scene / "log.mcap").is_file():
        over = [f"width={width}", f"height={height}", f"n_frames={frames}", f"seed={seed}"]
        generate_ship_tank(build(ShipTankConfig, overrides=over), scene, write_mcap=write_mcap)
    lines = (scene / "novel" / "views.txt").read_text().splitlines()
    poses = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    if not 1 <= views <= len(poses):
        raise ValueError(f"views must be 1..{len(poses)} (the tank's novel views), got {views}")
    views_file = scene / f"views{views}.txt"
    atomic_write_text(views_file, "\n".join(poses[:views]) + "\n")
    return BenchInput(scene / "log.mcap", views_file, scene / "novel" / "color",
                      scene / "novel" / "depth", scene / "gt" / "mesh.ply", name=name)  # fmt: skip


__all__ = [
    "BenchInput",
    "Results",
    "RunSpec",
    "knob_runs",
    "run_key",
    "run_sweep",
    "ship_tank_input",
    "KNOBS",
]
