"""Frame sources: dataset readers, ROS bags, our MCAP logs, and replay with rate control.

``open_source(cfg)`` picks the reader from ``cfg.format`` or, for ``auto``, from the files at
``cfg.path``. Every reader streams validated frames and keeps counts in ``reader.stats``.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from gsfix_online.sources.base import FrameSource, SourceError, SourceStats, damaged
from gsfix_online.sources.config import ReplayConfig, SourceConfig

# format name -> (module, reader class); modules are imported only when used.
READERS: dict[str, tuple[str, str]] = {
    "tum": ("gsfix_online.sources.tum", "TumReader"),
    "replica": ("gsfix_online.sources.replica", "ReplicaReader"),
    "redwood": ("gsfix_online.sources.redwood", "RedwoodReader"),
    "scannetpp": ("gsfix_online.sources.scannetpp", "ScannetppReader"),
    "okvis": ("gsfix_online.sources.okvis", "OkvisReader"),
    "rosbag": ("gsfix_online.sources.rosbag", "RosbagReader"),
    "mcap": ("gsfix_online.sources.mcap_log", "McapReader"),
}


def detect_format(path: str | Path) -> str:
    """Name the reader for ``path`` from its files; raises SourceError when nothing matches."""
    p = Path(path)
    if not p.exists():
        raise SourceError(f"source path {p} does not exist")
    if p.is_file():
        if p.suffix == ".bag":
            return "rosbag"
        if p.suffix == ".db3":
            return "rosbag"
        if p.suffix == ".mcap":
            from gsfix_online.sources.mcap_log import mcap_profile

            return "rosbag" if mcap_profile(p) in ("ros1", "ros2") else "mcap"
        raise SourceError(f"cannot tell the format of file {p}; set source.format")
    if (p / "metadata.yaml").is_file():
        return "rosbag"
    for name in ("tum", "replica", "redwood", "scannetpp", "okvis"):
        module = importlib.import_module(READERS[name][0])
        if module.looks_like(p):
            return name
    raise SourceError(
        f"cannot tell the dataset layout of {p} (expected TUM, Replica, Redwood, ScanNet++, OKVIS, a bag or .mcap); set source.format"
    )


def open_source(cfg: SourceConfig, path: str | Path | None = None) -> FrameSource:
    """Build the reader named by ``cfg.format`` (or detected) for ``path`` (default ``cfg.path``)."""
    p = Path(path if path is not None else cfg.path)
    if not str(p):
        raise SourceError("no source path given (set source.path)")
    fmt = detect_format(p) if cfg.format == "auto" else cfg.format
    module_name, cls_name = READERS[fmt]
    cls = getattr(importlib.import_module(module_name), cls_name)
    try:
        return cls(p, cfg)
    except Exception as exc:  # a damaged index file (bag metadata, pose list) read at open
        err = damaged(p, exc)
        if err is None:
            raise
        raise err from exc


__all__ = [
    "READERS",
    "FrameSource",
    "ReplayConfig",
    "SourceConfig",
    "SourceError",
    "SourceStats",
    "detect_format",
    "open_source",
]
