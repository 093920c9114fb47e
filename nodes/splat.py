"""Splat node: builds the 3D Gaussian map from posed ``rgbd`` frames and serves it.

- ``rgbd`` (posed): :meth:`Mapper.process`; each keyframe is published reliably as a
  ``keyframe`` message (colour, depth, pose, intrinsics, the map's render and alpha at the pose).
- ``render_request``: replies ``render_reply`` on ``render_reply/<name>`` with what was asked
  (colour as rgb8, depth in m, alpha), latest-only unless ``reliable_replies``.
- ``repaired_view``: :meth:`Mapper.distill` (the view is kept as an extra observation).
- Every ``snapshot_every`` frames and on exit the mapper's state is written atomically to
  ``snapshot``; a node started with an existing snapshot resumes from it. On exit (and on
  SIGUSR1) the map is exported in the standard 3DGS layout to ``export_dir``.
- Every ``stats_every`` frames it publishes ``stats/<name>/map`` (Gaussians, keyframes, steps,
  skipped non-finite steps, mapping time per frame).
"""

from __future__ import annotations

import logging
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.config_schema import rng
from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, message_to_frame

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    mapper: MapperConfig = field(default_factory=MapperConfig)
    snapshot: str = ""  # mapper state file (torch); resumed from when it exists; "" = none
    snapshot_every: int = field(
        default=50, metadata=rng(0, None, "frames between snapshots; 0 = on exit only")
    )
    export_dir: str = ""  # standard 3DGS model folder written on exit and on SIGUSR1
    refine_on_exit: int = field(
        default=0, metadata=rng(0, None, "global refinement steps before the final export")
    )
    reliable_replies: bool = False  # render replies over the reliable output(s)
    stats_every: int = field(default=10, metadata=rng(1, None, "frames between map stats"))
    stop_after: int = field(default=0, metadata=rng(0, None, "exit after n frames; 0 = never"))
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))


def save_snapshot(mapper: Mapper, path: Path) -> None:
    """Write the mapper's state atomically (temporary file, then rename): never half a file."""
    import io

    import torch

    from gsfix_online.config_schema import atomic_write_bytes

    buf = io.BytesIO()
    torch.save(mapper.state_dict(), buf)
    atomic_write_bytes(path, buf.getvalue())


def load_snapshot(cfg: MapperConfig, path: Path) -> Mapper:
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    mapper = Mapper(cfg, channels=int(state["map"]["channels"]))
    mapper.load_state_dict(state)
    return mapper


def _rgb8(color: np.ndarray) -> np.ndarray:  # [H, W, C] in [0, 1] -> [H, W, 3] uint8
    c = np.rint(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.ascontiguousarray(np.repeat(c, 3, axis=2) if c.shape[2] == 1 else c)


class SplatService:
    """The node's component glue: messages in, messages out; no sockets, no clock."""

    def __init__(self, name: str, params: Params) -> None:
        self.name = name
        self.params = params
        self.mapper: Mapper | None = None
        self.frames = 0
        self.distilled = 0
        self.kf_seq = 0
        snap = Path(params.snapshot) if params.snapshot else None
        if snap is not None and snap.is_file():
            self.mapper = load_snapshot(params.mapper, snap)
            self.frames = self.mapper.n_frames
            logger.info(
                "%s: resumed from %s (%d Gaussians, %d keyframes, %d frames)",
                name, snap, len(self.mapper.gmap), len(self.mapper.store), self.frames,
            )  # fmt: skip

    def _mapper(self, channels: int) -> Mapper:
        if self.mapper is None:
            self.mapper = Mapper(self.params.mapper, channels=channels)
        return self.mapper

    def on_rgbd(self, msg: Message) -> Message | None:
        frame = message_to_frame(msg)
        mapper = self._mapper(1 if frame.is_gray else 3)
        res = mapper.process(frame)
        self.frames += 1
        if res.keyframe is None:
            return None
        kf = res.keyframe
        assert kf.render is not None and kf.alpha is not None
        self.kf_seq += 1
        return Message(
            topic=f"keyframe/{self.name}",
            type="keyframe",
            seq=self.kf_seq - 1,
            stamp_ns=frame.stamp_ns,
            frame_id=frame.frame_id,
            meta={"keyframe_id": kf.kf_id},
            arrays={
                "color": frame.color,
                "depth": frame.depth,
                "K": frame.intrinsics.K,
                "T_world_cam": frame.T_world_cam,
                "gs_render": _rgb8(kf.render),
                "gs_alpha": np.ascontiguousarray(kf.alpha, dtype=np.float32),
            },
        )

    def on_render_request(self, msg: Message) -> Message:
        w, h, what = int(msg.meta["width"]), int(msg.meta["height"]), list(msg.meta["what"])
        if self.mapper is None:  # nothing mapped yet: an empty map renders black, alpha 0
            color = np.zeros((h, w, 3), np.float32)
            depth = alpha = np.zeros((h, w), np.float32)
        else:
            color, depth, alpha = self.mapper.render_numpy(
                msg.arrays["T_world_cam"], msg.arrays["K"], w, h
            )
        images = {"color": _rgb8(color), "depth": depth.astype(np.float32), "alpha": alpha}
        return Message(
            topic=f"render_reply/{self.name}",
            type="render_reply",
            seq=msg.seq,
            stamp_ns=msg.stamp_ns,
            frame_id=msg.frame_id,
            meta={"request_id": int(msg.meta["request_id"])},
            arrays={k: np.ascontiguousarray(images[k], dtype=images[k].dtype) for k in what},
        )

    def on_repaired_view(self, msg: Message) -> None:
        mapper = self._mapper(3)
        res = mapper.distill(
            msg.arrays["color"],
            msg.arrays["T_world_cam"],
            msg.arrays["K"],
            mask=msg.arrays.get("mask"),
            stamp_ns=msg.stamp_ns,
        )
        self.distilled += 1
        logger.info(
            "%s: distilled repaired view for keyframe %s (loss %.4f -> %.4f)",
            self.name, msg.meta["keyframe_id"], res.loss_first, res.loss_last,
        )  # fmt: skip

    def stats_message(self, stamp_ns: int, period_s: float, extra: dict[str, Any]) -> Message:
        meta: dict[str, Any] = {"node": self.name, "period_s": float(period_s)}
        if self.mapper is not None:
            meta.update({f"map/{k}": v for k, v in self.mapper.stats().items()})
        meta["map/distilled"] = self.distilled
        meta.update(extra)
        return Message(topic=f"stats/{self.name}/map", type="stats", stamp_ns=stamp_ns, meta=meta)

    def snapshot(self) -> None:
        if self.params.snapshot and self.mapper is not None:
            save_snapshot(self.mapper, Path(self.params.snapshot))

    def export(self) -> Path | None:
        if not self.params.export_dir or self.mapper is None:
            return None
        from gsfix_online.mapping.splat.ply import CameraEntry, save_model

        cams = [
            CameraEntry.from_frame(kf.kf_id, f"kf_{kf.kf_id:06d}", kf.frame)
            for kf in self.mapper.store
        ]
        return save_model(
            self.params.export_dir, self.mapper.gmap, self.mapper.n_steps, cameras=cams
        )


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    import time

    import torch

    if params.threads:
        torch.set_num_threads(params.threads)
    service = SplatService(name, params)
    node: Node
    export_requested = threading.Event()
    map_times: list[float] = []

    def on_rgbd(msg: Message) -> None:
        t0 = time.perf_counter()
        kf = service.on_rgbd(msg)
        map_times.append(time.perf_counter() - t0)
        if kf is not None:
            node.publish(kf, reliable=True)
        n = service.frames
        if params.snapshot_every and n % params.snapshot_every == 0:
            service.snapshot()
        if n % params.stats_every == 0:
            lat = np.asarray(map_times[-params.stats_every :]) * 1e3
            extra = {"map/process_p50_ms": float(np.percentile(lat, 50)),
                     "map/process_max_ms": float(lat.max())}  # fmt: skip
            node.publish(service.stats_message(time.time_ns(), float(lat.sum() / 1e3), extra))
        if export_requested.is_set():
            export_requested.clear()
            logger.info("%s: exported %s", name, service.export())
        if params.stop_after and n >= params.stop_after:
            node.request_stop()

    def on_request(msg: Message) -> None:
        node.publish(service.on_render_request(msg), reliable=params.reliable_replies)

    handlers = {"rgbd": on_rgbd, "render_request": on_request,
                "repaired_view": service.on_repaired_view}  # fmt: skip
    node = Node(name, transport, handlers=handlers, config=runtime)
    previous = None
    if threading.current_thread() is threading.main_thread() and hasattr(signal, "SIGUSR1"):
        previous = signal.signal(signal.SIGUSR1, lambda *_: export_requested.set())
    try:
        node.run()
    finally:
        if previous is not None:
            signal.signal(signal.SIGUSR1, previous)
        if service.mapper is not None and params.refine_on_exit:
            service.mapper.refine(params.refine_on_exit)
        service.snapshot()
        path = service.export()
        logger.info("%s: %d frames mapped; snapshot %s; export %s", name, service.frames,
                    params.snapshot or "-", path or "-")  # fmt: skip
    return 0
