"""The TSDF node's component: fuses posed frames, keeps a mesh that holds every integrated frame
for renders, writes and announces meshes. Handlers take and return messages; no sockets.

- ``on_rgbd``: integrate a posed frame (unposed ones are counted and skipped). When the remesh
  policy (:func:`gsfix_online.mapping.tsdf.should_remesh`) says the volume changed enough, the
  mesh is extracted again and, with ``write_periodic``, written and announced. With
  ``input_frames`` set (the repair command sets it), the frame that completes the input also
  writes and announces a mesh holding every frame, so the trainer renders its keyframes from it.
- ``on_render_request``: the mesh is extracted again first whenever a frame was integrated since
  the last extraction, except while a known input (``input_frames``) is still arriving, when the
  policy's mesh serves (the planner's progress probes). The remesh policy counts new blocks, and
  later frames that lift voxels over ``mesh_weight_threshold`` add surface without adding
  blocks, so renders from the policy's mesh missed up to ``remesh_max_frames`` frames (on a
  40-frame room run, 69 % of a held-out frame's pixels: see ``benchmarks/bench_mesh_fresh.py``).
  Asked for ``guessed_depth``, it also gives the depth of the mesh's planes extended where the
  mesh has no surface (:mod:`gsfix_online.mapping.mesh_planes`; 0 where it has one, or where no
  plane bounds the ray), fitted once per mesh.
- ``on_snapshot`` (a ``command`` of kind ``snapshot``): remesh if anything changed, write the mesh (to ``meta.path`` when it names a
  .ply/.glb file inside ``write_root``, else to ``mesh_dir``) and announce it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.mesh_planes import PlaneGuessConfig, Planes, fit_planes, guessed_depth
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume
from gsfix_online.runtime import Message, message_to_frame
from gsfix_online.runtime.ratelog import warn_repeated
from gsfix_online.runtime.requests import MAX_RENDER_PIXELS, path_inside, render_size, reply_topic

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params:
    tsdf: TsdfConfig = field(default_factory=TsdfConfig)
    # the surface guessed where the mesh has none, for seeding repaired views' unseen parts
    guess: PlaneGuessConfig = field(default_factory=PlaneGuessConfig)
    mesh_dir: str = "outputs/tsdf"  # periodic and requested snapshots: mesh.ply, mesh.glb
    formats: list[str] = field(default_factory=lambda: ["ply", "glb"])
    write_periodic: bool = True  # write and announce the mesh at every periodic remesh
    snapshot_topic: str = "tsdf/snapshot"  # snapshot commands here ask for a mesh
    # the folder a snapshot path named in a message must lie in; "" = mesh_dir's parent
    write_root: str = ""
    max_render_pixels: int = field(
        default=MAX_RENDER_PIXELS, metadata=rng(1, None, "largest render a request may ask for")
    )
    stop_after: int = field(
        default=0, metadata=rng(0, None, "exit after this many integrated frames; 0 = never")
    )
    # The input's frame count (the repair command sets it): the frame that completes it writes
    # and announces a mesh holding every frame, whatever the remesh policy says
    input_frames: int = field(
        default=0, metadata=rng(0, None, "frames in the input; 0 = unknown (a live input)")
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
        self.planes: Planes | None = None  # the mesh's, fitted at the first guess asked for
        self.unposed = 0
        self.renders = 0
        self.snapshots = 0
        # newest stamp integrated per camera: a restarted replay sends its frames again, and
        # integrating one twice would double its weight (counted as repeated, not integrated)
        self.last_stamp_ns: dict[str, int] = {}
        self.repeated = 0
        self.input_ended = False  # the input's last frame came and its mesh was announced

    # -- handlers --------------------------------------------------------------------------

    def on_rgbd(self, msg: Message) -> list[Message]:
        if not msg.meta.get("posed", False):
            self.unposed += 1
            return self._input_end(msg.stamp_ns)
        frame = message_to_frame(msg)
        last = self.last_stamp_ns.get(frame.frame_id, -1)
        if frame.stamp_ns <= last:
            self.repeated += 1
            warn_repeated(logger, self.name, self.repeated, frame.stamp_ns, last, "tsdf/repeated")
            return []
        self.volume.integrate(frame)
        self.last_stamp_ns[frame.frame_id] = frame.stamp_ns
        ended = self._input_end(msg.stamp_ns)
        if ended:
            return ended
        if self.params.write_periodic and self.volume.needs_remesh():
            self._remesh()
            return [self._write(Path(self.params.mesh_dir), msg.stamp_ns)]
        return []

    def on_render_request(self, msg: Message) -> Message:
        meta = msg.meta
        w, h = render_size(msg, self.params.max_render_pixels)
        K = Intrinsics.from_K(msg.arrays["K"], w, h)
        # Every integrated frame, not only what the remesh policy waits for; while a known input
        # is still arriving the policy's mesh serves (the planner's progress probes meanwhile)
        if self.params.input_frames and not self._input_complete():
            if self.mesh is None or self.volume.needs_remesh():
                self._remesh()
        else:
            self._fresh_mesh()
        assert self.renderer is not None
        r = self.renderer.render(msg.arrays["T_world_cam"], K)
        self.renders += 1
        images = {"color": r.rgb(), "depth": r.depth_m, "alpha": r.valid.astype(np.float32)}
        if "synthesised" in meta["what"]:  # a mesh of measured depth: all of it observed
            images["synthesised"] = np.zeros(r.depth_m.shape, np.float32)
        if "guessed_depth" in meta["what"]:
            if self.planes is None:
                self.planes = fit_planes(self.renderer.mesh, self.params.guess)
                logger.info("%s: %d planes guess the unseen surface", self.name, len(self.planes))
            images["guessed_depth"] = guessed_depth(self.planes, msg.arrays["T_world_cam"], K,
                                                    r.valid)  # fmt: skip
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
        if msg.type != "command" or msg.meta["kind"] != "snapshot":
            kind = msg.meta.get("kind", "")
            raise ValueError(f"{msg.topic}: a snapshot request is a command of kind snapshot, "
                             f"got {msg.type} {kind}".rstrip())  # fmt: skip
        self._fresh_mesh()
        path = str(msg.meta.get("path", "") or "")
        if path.endswith((".ply", ".glb")):
            root = self.params.write_root or Path(self.params.mesh_dir).resolve().parent
            return self._write(path_inside(path, root, "snapshot path"), msg.stamp_ns)
        return self._write(Path(self.params.mesh_dir), msg.stamp_ns)

    # -- helpers ---------------------------------------------------------------------------

    def _input_complete(self) -> bool:
        n = self.params.input_frames
        return bool(n) and self.volume.frames + self.unposed >= n

    def _input_end(self, stamp_ns: int) -> list[Message]:
        """Once, when the input's last frame came: write and announce a mesh of every frame."""
        if self.input_ended or not self._input_complete():
            return []
        self.input_ended = True
        self._fresh_mesh()
        logger.info("%s: all %d frames of the input came (%d integrated); announcing their mesh",
                    self.name, self.params.input_frames, self.volume.frames)  # fmt: skip
        return [self._write(Path(self.params.mesh_dir), stamp_ns)]

    def _remesh(self) -> None:
        self.mesh = self.volume.extract_mesh()
        self.renderer = MeshRenderer(self.mesh)
        self.planes = None

    def _fresh_mesh(self) -> None:
        """A mesh of every integrated frame: extracted again if a frame came since."""
        if self.mesh is None or self.volume.remesh.frames > 0:
            self._remesh()

    def _write(self, target: Path, stamp_ns: int) -> Message:
        assert self.mesh is not None
        if target.suffix in (".ply", ".glb"):
            files = [write_mesh(self.mesh, target)]
        else:
            files = [write_mesh(self.mesh, target / f"mesh.{ext}") for ext in self.params.formats]
        self.snapshots += 1
        return Message(
            topic=f"mesh/{self.name}",
            type="map_event",
            seq=self.snapshots - 1,
            stamp_ns=stamp_ns,
            frame_id="world",
            meta={
                "kind": "mesh_written",
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
