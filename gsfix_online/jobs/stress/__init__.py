"""The numerical stress suite: properties that must hold under extreme but legal inputs.

Each :class:`Property` pairs a hypothesis strategy (inputs at the edges of what the library
accepts: scales 1e-6 to 1e3 m, depths 1 mm to 1 km, Gaussians on the near plane and behind the
camera, anisotropy 1e6 and more, degenerate and unnormalised quaternions, nearly singular
intrinsics, poses 10 km from the origin, bfloat16 and float16 weights) with a check that raises
``AssertionError`` naming what broke. The same properties run in two places:

- ``tests/jobs/stress/`` (``make test``): a few examples each, derandomised (profile ``ci``);
- ``gsfix-online stress --minutes N [--seed S]`` (:mod:`.runner`): round robin over every
  property with fresh seeds until the time is up, then a table of examples and failures.

Properties live in :mod:`.geometry` (SE(3), quaternions, pose interpolation), :mod:`.splat`
(projection, rasterisation forward and backward, optimisation, distillation), :mod:`.tsdf`
(integration) and :mod:`.fixer` (GSFixer inference and a training step). hypothesis is a dev
dependency: it is imported by the modules that build strategies, never by ``import
gsfix_online``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

AREAS = ("geometry", "splat", "tsdf", "fixer")


@dataclass(frozen=True)
class Property:
    """One property: ``check(example)`` must not raise for any ``example`` of ``strategy()``."""

    name: str  # "area.what_holds"
    doc: str  # one line: what must hold, for which inputs
    strategy: Callable[[], Any]  # -> hypothesis SearchStrategy of one example
    check: Callable[[Any], None]  # raises AssertionError naming what broke
    ci_examples: int = 10  # examples in make test (profile ci); the long run takes many

    @property
    def area(self) -> str:
        return self.name.split(".", 1)[0]


def properties(area: str | None = None) -> list[Property]:
    """Every property, or those of one area (geometry, splat, tsdf, fixer)."""
    if area is not None and area not in AREAS:
        raise ValueError(f"stress area must be one of {', '.join(AREAS)}, got {area!r}")
    import importlib

    out: list[Property] = []
    for name in AREAS if area is None else (area,):
        out.extend(importlib.import_module(f"gsfix_online.jobs.stress.{name}").PROPERTIES)
    return out
