"""Running the stress properties: hypothesis profiles, one property, a timed long run.

``gsfix-online stress --minutes N [--seed S] [--area A] [--out FILE]`` runs every property in
turn with a fresh seed per round: first the examples ``make test`` runs (whatever the budget),
then rounds of ``round_examples / 10`` times as many, until the time is up;
a property that fails is shrunk by hypothesis to its smallest failing input, reported, and not
run again. It prints a table (property, examples, failures, seconds, the failure) and exits 1
when any property failed. Progress is one live line on a terminal and a plain line every 30 s
otherwise (:mod:`gsfix_online.core.progress`).
"""

from __future__ import annotations

import itertools
import json
import logging
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from gsfix_online.core.config import rng
from gsfix_online.jobs.stress import Property, properties

logger = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'gsfix-online[dev]'"
PROFILE_CI = "ci"  # make test: few examples, derandomised, no deadline
PROFILE_LONG = "long"  # gsfix-online stress: many examples, random seeds


def _hypothesis() -> Any:
    try:
        import hypothesis
    except ImportError as exc:  # a dev dependency
        raise RuntimeError(f"the stress suite needs hypothesis: {INSTALL_HINT}") from exc
    return hypothesis


def register_profiles() -> None:
    """Register the ``ci`` and ``long`` settings profiles (idempotent)."""
    hyp = _hypothesis()
    HC = hyp.HealthCheck
    quiet = [HC.too_slow, HC.data_too_large, HC.filter_too_much, HC.large_base_example]
    common = {
        "deadline": None,
        "database": None,
        "suppress_health_check": quiet,
        "report_multiple_bugs": False,  # one smallest failure per property
    }
    # ci: derandomised, so make test checks the same examples on every machine; shrinking stays
    # on so that a failure shows its smallest input
    hyp.settings.register_profile(PROFILE_CI, max_examples=10, derandomize=True, **common)
    hyp.settings.register_profile(
        PROFILE_LONG, max_examples=10_000, phases=[hyp.Phase.generate, hyp.Phase.shrink], **common
    )


@dataclass
class PropertyRun:
    """What running one property did."""

    name: str
    examples: int = 0  # calls of the check, shrinking included
    failures: int = 0  # 0 or 1: a failing property is shrunk, reported and dropped
    seconds: float = 0.0
    failure: str = ""  # first line of the error after shrinking
    example: str = ""  # repr of the smallest failing example


def run_property(
    prop: Property,
    max_examples: int | None = None,  # default: prop.ci_examples
    profile: str = PROFILE_CI,
    seed: int | None = None,  # hypothesis seed (None: the profile's rule)
    on_example: Callable[[], None] | None = None,  # called after every example
    record: PropertyRun | None = None,  # accumulate into this run
) -> PropertyRun:
    """Run ``prop`` for ``max_examples`` examples; a failure is recorded, not raised."""
    hyp = _hypothesis()
    register_profiles()
    run = record if record is not None else PropertyRun(prop.name)
    last: list[Any] = [None]

    def body(example: Any) -> None:
        run.examples += 1
        try:
            prop.check(example)
        except BaseException:
            last[0] = example
            raise
        finally:
            if on_example is not None:
                on_example()

    settings = hyp.settings(
        hyp.settings.get_profile(profile),
        max_examples=prop.ci_examples if max_examples is None else max_examples,
    )
    test = hyp.given(prop.strategy())(settings(body))
    if seed is not None:
        test = hyp.seed(seed)(test)
    t0 = time.perf_counter()
    try:
        test()
    except Exception as exc:  # the check's AssertionError, or an error the library raised
        run.failures += 1
        lines = [s for s in f"{type(exc).__name__}: {exc}".splitlines() if s.strip()]
        run.failure = lines[0][:300]
        run.example = _short_repr(last[0])
    finally:
        run.seconds += time.perf_counter() - t0
    return run


def assert_property(prop: Property, max_examples: int | None = None) -> PropertyRun:
    """For tests: run ``prop`` under the ``ci`` profile and fail with the smallest example."""
    run = run_property(prop, max_examples)
    if run.failures:
        raise AssertionError(f"{prop.name}: {run.failure}\n  smallest failing input: {run.example}")
    return run


def _short_repr(example: Any, limit: int = 600) -> str:
    import numpy as np

    with np.printoptions(precision=17, threshold=40):
        text = repr(example)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# -- the long run ----------------------------------------------------------------------------


@dataclass
class StressSummary:
    seconds: float
    seed: int
    runs: list[PropertyRun]

    @property
    def failed(self) -> list[PropertyRun]:
        return [r for r in self.runs if r.failures]

    def table(self) -> str:
        """Plain-text table: property, examples, failures, seconds, failure."""
        rows = [("property", "examples", "failures", "seconds", "failure")]
        for r in self.runs:
            rows.append((r.name, str(r.examples), str(r.failures), f"{r.seconds:.1f}", r.failure))
        widths = [max(len(row[i]) for row in rows) for i in range(4)]
        lines = []
        for k, row in enumerate(rows):
            cells = [row[0].ljust(widths[0])] + [row[i].rjust(widths[i]) for i in (1, 2, 3)]
            lines.append("  ".join(cells) + ("  " + row[4] if row[4] else ""))
            if k == 0:
                lines.append("  ".join("-" * w for w in widths))
        total = sum(r.examples for r in self.runs)
        lines.append(
            f"{total} examples of {len(self.runs)} properties in {self.seconds:.0f} s "
            f"(seed {self.seed}): {len(self.failed)} failed"
        )
        return "\n".join(lines)


@dataclass(frozen=True)
class StressConfig:
    """``gsfix-online stress``'s settings (``-c``, ``minutes=5``; ``--minutes`` and the other
    flags set the same keys)."""

    minutes: float = field(default=10.0, metadata=rng(0, None, "time budget, minutes (> 0)"))
    seed: int = field(default=0, metadata=rng(0, None, "seed of the rounds' hypothesis seeds"))
    area: Literal["all", "geometry", "splat", "tsdf", "fixer"] = "all"  # only this area's


def run_stress(
    minutes: float,
    seed: int = 0,
    area: str | None = None,
    round_examples: int = 25,
    progress: bool = True,
    clock: Callable[[], float] = time.monotonic,
) -> StressSummary:
    """Round robin over the properties with fresh seeds until ``minutes`` have passed."""
    import torch

    from gsfix_online.core.progress import Progress

    if not minutes > 0:
        raise ValueError(f"minutes must be positive, got {minutes}")
    props = properties(area)
    runs = {p.name: PropertyRun(p.name) for p in props}
    rng = random.Random(seed)
    t0 = clock()
    deadline = t0 + 60.0 * minutes
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: threads only contend (see tests/fixer/conftest.py)
    try:
        with Progress("stress", None, "example", enabled=progress) as bar:
            # round robin; round 0 runs every property's make-test share whatever the budget
            # (about 30 s), later rounds round_examples / 10 times that, until the deadline
            for k in itertools.count():
                live = [p for p in props if not runs[p.name].failures]
                if not live or (k and clock() >= deadline):
                    break
                for prop in live:
                    if k and clock() >= deadline:
                        break
                    bar.set(text=prop.name)
                    n = prop.ci_examples if k == 0 else round_examples * prop.ci_examples // 10
                    run = run_property(
                        prop, max(1, n), PROFILE_LONG, seed=rng.getrandbits(64),
                        on_example=bar.update, record=runs[prop.name],
                    )  # fmt: skip
                    if run.failures:
                        bar.write(f"FAILED {prop.name}: {run.failure}\n  input: {run.example}")
    finally:
        torch.set_num_threads(threads)
    return StressSummary(clock() - t0, seed, list(runs.values()))


def write_summary(summary: StressSummary, path: Path) -> None:
    from gsfix_online.core.io import atomic_write_text

    data = {
        "seconds": summary.seconds,
        "seed": summary.seed,
        "properties": [asdict(r) for r in summary.runs],
    }
    atomic_write_text(path, json.dumps(data, indent=1) + "\n")


def cli_main(args: Any, cfg: StressConfig | None = None) -> int:
    """``gsfix-online stress``: run, print the table, exit 1 when a property failed."""
    cfg = cfg or StressConfig(args.minutes, args.seed, args.area or "all")
    area = None if cfg.area == "all" else cfg.area
    try:
        summary = run_stress(cfg.minutes, cfg.seed, area, progress=not args.no_progress)
    except (RuntimeError, ValueError) as exc:
        print(f"gsfix-online stress: error: {exc}")
        return 2
    print(summary.table())
    if args.out is not None:
        write_summary(summary, args.out)
        print(f"-> {args.out}")
    return 1 if summary.failed else 0
