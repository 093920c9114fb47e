"""The root configuration: one section per component, loaded by :func:`load_config`.

Priority: dataclass defaults < YAML files (in order) < command-line overrides ``section.key=value``.
Each component receives only its own section. :func:`write_config` saves the resolved config next
to every output.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from gsfix_online.core.config import ConfigError, build, rng, to_dict, write_config
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.sources.config import ReplayConfig, SourceConfig


@dataclass(frozen=True)
class DemoConfig:
    """The demo's changes to the repair graph (configs/graphs/repair.yaml), as ``NODE.KEY=VALUE``
    overrides: by default the planner proposes views of its own beside the scene's novel views."""

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
    fixer: FixerConfig = field(default_factory=FixerConfig)  # fixer.model.path: the base
    demo: DemoConfig = field(default_factory=DemoConfig)  # the demo's repair-graph overrides


def load_config(
    files: list[str | os.PathLike[str]] | None = None, overrides: list[str] | None = None
) -> Config:
    """Resolve the root config from YAML ``files`` and ``overrides``; raises ConfigError (one line)."""
    return build(Config, files=files, overrides=overrides)


__all__ = ["Config", "ConfigError", "load_config", "to_dict", "write_config"]
