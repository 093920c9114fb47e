"""The root configuration: one section per component, loaded by :func:`load_config`.

Priority: dataclass defaults < YAML files (in order) < command-line overrides ``section.key=value``.
Each component receives only its own section. :func:`write_config` saves the resolved config next
to every output.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from gsfix_online.config_schema import ConfigError, build, to_dict, write_config
from gsfix_online.demo import DemoConfig
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.scene.config import ShipTankConfig
from gsfix_online.sources.config import ReplayConfig, SourceConfig


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
