"""The root configuration: one section per component, loaded by :func:`load_config`.

Priority: dataclass defaults < YAML files (in order) < command-line overrides ``section.key=value``.
Each component receives only its own section. :func:`write_config` saves the resolved config next
to every output.

A command that runs a graph (``demo``, ``repair``, ``bench``, ``launch``) gives the sections
``source``, ``replay`` and ``fixer`` to every node of the graph whose params have a section of
that name (:func:`gsfix_online.runtime.graph.apply_settings`): ``fixer.inference.steps=2``
reaches the trainer and the repair node. Every other key of such a command starts with a node's
name (``splat.mapper.kf_iters=4``). docs/configuration.md has the whole story.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

from gsfix_online.core.config import (
    ConfigError,
    build_from,
    full_key,
    gather,
    origin_of,
    rng,
    to_dict,
    write_config,
)
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.sources.config import ReplayConfig, SourceConfig


@dataclass(frozen=True)
class DemoConfig:
    """The demo's changes to the repair graph (configs/graphs/repair.yaml), as ``NODE.KEY=VALUE``
    overrides: by default the planner proposes views of its own beside the scene's novel views.
    ``gsfix-online demo NODE.KEY=VALUE`` adds to ``extra_overrides``."""

    graph_overrides: list[str] = field(
        default_factory=lambda: [
            "planner.proposals.every_keyframes=8",
            "planner.proposals.max_proposals=4",
        ]
    )
    extra_overrides: list[str] = field(default_factory=list)  # appended, e.g. from the command line
    # 0 = no deadline, as `gsfix-online repair`: the run fails when a node dies, not when a busy
    # machine makes it slow (1800 s stopped a progressing demo beside two benchmark runs)
    timeout_s: float = field(
        default=0.0, metadata=rng(0, None, "stop the graph after, s; 0 = never")
    )


@dataclass(frozen=True)
class Config:
    source: SourceConfig = field(default_factory=SourceConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    scene: ShipTankConfig = field(default_factory=ShipTankConfig)
    # GSFixer keys set on every node of the graph that runs GSFixer (trainer, repair), over what
    # the graph's profiles give them: only the keys given here, so the file shows what changed
    # (each node's whole fixer section is in the run's work/graph.yaml)
    fixer: dict[str, Any] = field(default_factory=dict, metadata={"overlay": FixerConfig})
    demo: DemoConfig = field(default_factory=DemoConfig)  # the demo's repair-graph overrides


SECTIONS = tuple(Config.__dataclass_fields__)


def check_reads(
    command: str, settings: dict[str, Any], origins: dict[str, str], reads: tuple[str, ...]
) -> None:
    """One-line error for a root section that ``command`` does not read (never ignore a key)."""
    for key in settings:
        if key in SECTIONS and key not in reads:
            first = full_key(origins, key)
            what = ", ".join(f"{r}.*" for r in reads) or "no settings"
            raise ConfigError(
                f"{origin_of(origins, key)}: gsfix-online {command} does not read '{first}' "
                f"(it reads {what})"
            )


def read_sections(cfg: Config, reads: tuple[str, ...]) -> dict[str, Any]:
    """The sections of ``cfg`` a command reads, as written beside its outputs."""
    return {k: v for k, v in to_dict(cfg).items() if k in reads}


def load_config(
    files: list[str | os.PathLike[str]] | None = None,
    overrides: list[str] | None = None,
    command: str = "",
    reads: tuple[str, ...] = SECTIONS,
) -> Config:
    """Resolve the root config from YAML ``files`` and ``overrides``; raises ConfigError (one
    line) for a bad value, an unknown key, or a section the command does not read."""
    settings, origins = gather(files, overrides)
    check_reads(command or "config", settings, origins, reads)
    return build_from(Config, settings, origins)


__all__ = ["Config", "ConfigError", "load_config", "read_sections", "to_dict", "write_config"]
