"""TSDF node: fuses posed ``rgbd`` frames into a TSDF volume, keeps a mesh, renders it on request.

Inputs (dispatched by exact topic first, then by type):

- ``rgbd`` (posed) -> integrate. Unposed frames are counted and skipped. When the remesh policy
  says the volume changed enough, the mesh is extracted again and, with ``write_periodic``,
  written to ``mesh_dir`` (``mesh.ply`` / ``mesh.glb``, atomically) and announced.
- ``render_request`` -> ``render_reply`` on ``render_reply/<node>`` (``render_reply/<requester>/<node>``
  when the request names ``reply_to``; meta ``frames`` = frames integrated) with the asked-for subset of
  ``color`` (RGB; gray meshes replicated), ``depth`` (z-depth, m, 0 = no surface) and ``alpha``
  (1 where the mesh was hit). The mesh is refreshed first when it is stale.
- a ``checkpoint`` message on ``snapshot_topic`` -> remesh if anything changed, write the mesh
  (to ``meta.path`` when it names a .ply/.glb file, else to ``mesh_dir``) and announce it. A
  path from a message must lie inside ``write_root`` (default: the folder holding ``mesh_dir``);
  any other is refused with an error, and render requests above ``max_render_pixels`` too.

Announcements are ``checkpoint`` messages on ``mesh/<node>``: ``path`` (the first file), ``version``
(mesh version), ``step`` (frames integrated), plus ``files``, ``vertices`` and ``triangles``.
``stats/<node>`` carries the volume's counters as ``tsdf/<key>`` (frames, blocks, capacity,
growths, invalid depth by reason, mesh version).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.config_schema import rng
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume
from gsfix_online.runtime import Message, Node, NodeRuntimeConfig, Transport, message_to_frame
from gsfix_online.runtime.requests import MAX_RENDER_PIXELS, path_inside, render_size
from gsfix_online.types import Intrinsics
from nodes._common import reply_topic

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    tsdf: TsdfConfig = field(default_factory=TsdfConfig)
    mesh_dir: str = "outputs/tsdf"  # periodic and requested snapshots: mesh.ply, mesh.glb
    formats: list[str] = field(default_factory=lambda: ["ply", "glb"])
    write_periodic: bool = True  # write and announce the mesh at every periodic remesh
    snapshot_topic: str = "tsdf/snapshot"  # checkpoint messages here ask for a snapshot
    # the folder a snapshot path named in a message must lie in; "" = mesh_dir's parent
    write_root: str = ""
    max_render_pixels: int = field(
        default=MAX_RENDER_PIXELS, metadata=rng(1, None, "largest render a request may ask for")
    )
    stop_after: int = field(
        default=0, metadata=rng(0, None, "exit after this many integrated frames; 0 = never")
    )

    def validate(self) -> None:
        bad = [f for f in self.formats if f not in ("ply", "glb")]
        if bad or not self.formats:
            raise ValueError(f"formats must be a non-empty subset of ply, glb, got {self.formats}")


class TsdfService:
    """The node's state: the volume, its latest mesh and renderer; handlers return messages."""

    def __init__(self, name: str, params: Params, volume: TsdfVolume | None = None) -> None:
        self.name = name
        self.params = params
        self.volume = volume or TsdfVolume(params.tsdf)
        self.mesh: TriMesh | None = None
        self.renderer: MeshRenderer | None = None
        self.unposed = 0
        self.renders = 0
        self.snapshots = 0
        # newest stamp integrated per camera: a restarted replay sends its frames again, and
        # integrating one twice would double its weight (counted as repeated, not integrated)
        self.last_stamp_ns: dict[str, int] = {}
        self.repeated = 0

    # -- handlers --------------------------------------------------------------------------

    def on_rgbd(self, msg: Message) -> list[Message]:
        if not msg.meta.get("posed", False):
            self.unposed += 1
            return []
        frame = message_to_frame(msg)
        if frame.stamp_ns <= self.last_stamp_ns.get(frame.frame_id, -1):
            self.repeated += 1
            return []
        self.volume.integrate(frame)
        self.last_stamp_ns[frame.frame_id] = frame.stamp_ns
        if self.params.write_periodic and self.volume.needs_remesh():
            self._remesh()
            return [self._write(Path(self.params.mesh_dir), msg.stamp_ns)]
        return []

    def on_render_request(self, msg: Message) -> Message:
        meta = msg.meta
        w, h = render_size(msg, self.params.max_render_pixels)
        K = Intrinsics.from_K(msg.arrays["K"], w, h)
        if self.mesh is None or self.volume.needs_remesh():
            self._remesh()
        assert self.renderer is not None
        r = self.renderer.render(msg.arrays["T_world_cam"], K)
        self.renders += 1
        images = {"color": r.rgb(), "depth": r.depth_m, "alpha": r.valid.astype(np.float32)}
        return Message(
            topic=reply_topic(self.name, msg),
            type="render_reply",
            seq=self.renders - 1,
            stamp_ns=msg.stamp_ns,
            frame_id=msg.frame_id,
            meta={
                "request_id": meta["request_id"],
                "mesh_version": self.volume.mesh_version,
                "frames": self.volume.frames,
            },  # fmt: skip
            arrays={k: images[k] for k in meta["what"]},
        )

    def on_snapshot(self, msg: Message) -> Message:
        if msg.type != "checkpoint":  # any message on the topic wrote the mesh before
            raise ValueError(f"a snapshot request must be a checkpoint message, got {msg.type}")
        if self.mesh is None or self.volume.remesh.frames > 0:
            self._remesh()
        path = str(msg.meta.get("path", "") or "")
        if path.endswith((".ply", ".glb")):
            root = self.params.write_root or Path(self.params.mesh_dir).resolve().parent
            return self._write(path_inside(path, root, "snapshot path"), msg.stamp_ns)
        return self._write(Path(self.params.mesh_dir), msg.stamp_ns)

    # -- helpers ---------------------------------------------------------------------------

    def _remesh(self) -> None:
        self.mesh = self.volume.extract_mesh()
        self.renderer = MeshRenderer(self.mesh)

    def _write(self, target: Path, stamp_ns: int) -> Message:
        assert self.mesh is not None
        if target.suffix in (".ply", ".glb"):
            files = [write_mesh(self.mesh, target)]
        else:
            files = [write_mesh(self.mesh, target / f"mesh.{ext}") for ext in self.params.formats]
        self.snapshots += 1
        return Message(
            topic=f"mesh/{self.name}",
            type="checkpoint",
            seq=self.snapshots - 1,
            stamp_ns=stamp_ns,
            frame_id="world",
            meta={
                "path": str(files[0]),
                "version": self.volume.mesh_version,
                "step": self.volume.frames,
                "files": [str(f) for f in files],
                "vertices": self.mesh.n_vertices,
                "triangles": self.mesh.n_triangles,
            },
        )

    def stats(self) -> dict[str, Any]:
        out = {f"tsdf/{k}": v for k, v in self.volume.stats().items()}
        out.update({"tsdf/unposed": self.unposed, "tsdf/renders": self.renders})
        out["tsdf/repeated"] = self.repeated
        return out


def build_node(
    name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig
) -> tuple[Node, TsdfService]:
    service = TsdfService(name, params)
    node: Node

    def on_rgbd(msg: Message) -> list[Message]:
        out = service.on_rgbd(msg)
        if params.stop_after and service.volume.frames >= params.stop_after:
            node.request_stop()
        return out

    handlers = {
        params.snapshot_topic: service.on_snapshot,
        "rgbd": on_rgbd,
        "render_request": service.on_render_request,
    }
    node = Node(name, transport, handlers, config=runtime, extra_stats=service.stats)
    return node, service


def run(name: str, params: Params, transport: Transport, runtime: NodeRuntimeConfig) -> int:
    node, service = build_node(name, params, transport, runtime)
    try:
        return node.run()
    finally:
        logger.info("%s: %s", name, service.stats())
