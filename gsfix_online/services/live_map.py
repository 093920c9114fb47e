"""A live graph's map in the map server: its exports and meshes, and repairs through the graph.

In a graph, the ``map_server`` node serves the splat node's exports and the TSDF node's meshes as
one map (``live``: :class:`~gsfix_online.services.map_server.MapServer` holds it). A repair of
that map is not run by the server: :class:`LiveMap` hands it to the graph and follows the view
through it, so a client's view is scored, repaired and distilled exactly as the run's own views.
Messages in, messages out; no sockets, and the clock is passed in (``nodes/map_server.py`` wires
it). One view at a time; stages, each reported to the client as it happens:

1. ``forwarded``: the view goes to the planner as a ``render_request`` on ``view_request/<node>``
   (its own K, width, height; the planner numbers it and scores it like a view of its list).
2. ``decided``: the planner's decision (``decision/<planner>/gs``, meta ``origin: request``),
   matched to the request by its pose, intrinsics and size (the planner echoes them bit for
   bit); from here on the view is followed by the id the planner gave it. A skipped view ends
   here: the answer is the planner's 3DGS render of the view with the planner's reason.
3. ``repaired``: the repair node's ``repaired_view/<repair>`` of that id (GSFixer, the run's
   fallback choice applied): the image of the answer.
4. ``distilled``: the splat node's ``distill/<splat>`` announcement of that id (meta ``version``:
   views distilled into the splat node's map so far).
5. ``exported``: the server asks the splat node for an export (a ``command`` of kind ``export``
   on ``export_topic``, meta ``path``: a new folder ``export_dir/export-NNNN``; the splat node
   takes a relative path from its ``write_root``, the repair command's output folder), loads
   it when the ``export/<splat>`` announcement names the PLY it wrote there, and answers with the live map's new
   version, which ``maps()``, ``splats()`` and renders show from then on.

Other ``export/`` announcements (the graph's own exports, e.g. the repair writer's at the end)
are loaded as new versions too, and ``mesh/`` announcements replace the live map's mesh. A view
that has not reached its end after ``timeout_s`` fails with the stage it waited for.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.runtime.requests import render_request
from gsfix_online.runtime.wire import Message
from gsfix_online.services.map_server import MapServer, RequestError

logger = logging.getLogger(__name__)

Stage = Literal["forwarded", "decided", "repaired", "distilled", "exported"]
# the fraction of the work done when a stage is reached (what the client's progress shows)
FRACTION: dict[str, float] = {
    "forwarded": 0.05,
    "decided": 0.3,
    "repaired": 0.6,
    "distilled": 0.8,
    "exported": 1.0,
}
WAITING_FOR = {  # what a view waits for after each stage
    "forwarded": "the planner's decision",
    "decided": "the repair node's GSFixer",
    "repaired": "the splat node's distillation",
    "distilled": "the splat node's export",
}


@dataclass(frozen=True)
class LiveConfig:
    map: str = "live"  # the live map's name
    planner: str = "planner"  # the node that scores views (decisions on decision/<planner>/)
    repair: str = "repair"  # the node that repairs them (repaired_view/<repair>)
    splat: str = "splat"  # the node that distils and exports (distill/, export/<splat>)
    export_topic: str = "splat/export"  # the splat node's export requests
    # the exports asked for: relative = inside the splat node's write_root (which an export
    # path must lie in); with `gsfix-online repair`, DIR/work/live_map
    export_dir: str = "work/live_map"
    mesh_topic: str = "mesh/"  # the TSDF node's mesh announcements
    timeout_s: float = field(
        default=900.0, metadata=rng(1, None, "a live repair fails after this long, s")
    )


@dataclass(frozen=True)
class Update:
    """What the client of the running view hears: progress, or the end (done or failed)."""

    kind: Literal["progress", "done", "failed"]
    fraction: float = 0.0
    text: str = ""  # progress: "<stage>: what happened; waiting for ..."; failed: the reason
    result: dict[str, Any] = field(default_factory=dict)  # done: the client's result
    image: npt.NDArray[np.uint8] | None = None  # done: [H, W, 3]


@dataclass
class LiveJob:
    """One view on its way through the graph."""

    T_world_cam: list[float]  # [16] row-major, camera-to-world, as sent to the planner
    K: list[float]  # [9] row-major, pixels
    width: int
    height: int
    started: float
    stage: Stage = "forwarded"
    view_id: int | None = None  # the planner's id, from its decision on
    reason: str = ""
    image: npt.NDArray[np.uint8] | None = None  # [H, W, 3] the repair
    distilled: int | None = None  # the splat node's count of views distilled
    export_path: Path | None = None  # as asked for: relative to the splat node's write_root
    times: dict[str, float] = field(default_factory=dict)  # stage -> seconds after the start


def model_folder(path: str | Path) -> Path:
    """The 3DGS model folder of an ``export/`` announcement's path: the splat node names the
    PLY it wrote (``DIR/point_cloud/iteration_N/point_cloud.ply``), a folder stays itself."""
    p = Path(path).resolve()
    if p.suffix.lower() == ".ply" and p.parent.parent.name == "point_cloud":
        return p.parents[2]
    return p


def names(folder: Path, asked: Path) -> bool:
    """Whether the exported ``folder`` (absolute) is the one asked for as ``asked`` (a relative
    path is taken from the splat node's write_root, which this node does not know)."""
    if asked.is_absolute():
        return folder == asked.resolve()
    return folder.parts[-len(asked.parts) :] == asked.parts


class LiveMap:
    """Follows live repairs through the graph and keeps the live map current (module doc)."""

    def __init__(self, name: str, cfg: LiveConfig, service: MapServer) -> None:
        self.name = name
        self.cfg = cfg
        self.service = service
        self.job: LiveJob | None = None
        self.updates: list[Update] = []
        self.exports = 0  # exports asked for
        self.counts = {"forwarded": 0, "repaired": 0, "skipped": 0, "failed": 0}

    # -- requests ----------------------------------------------------------------------------

    def wants(self, args: dict[str, Any]) -> bool:
        """Whether a repair request is for the live map: it names it, or names no map while
        the server holds no finished run."""
        name = args.get("map")
        if name is None:
            return all(m.run is None for m in self.service.maps.values())
        return name == self.cfg.map

    @property
    def busy(self) -> bool:
        return self.job is not None

    def check_idle(self, now: float) -> None:
        """RequestError ``busy`` while a live repair runs (one repair at a time)."""
        if self.job is not None:
            raise RequestError("busy", f"busy: a repair of map {self.cfg.map!r} is in the graph "
                               f"({now - self.job.started:.1f} s so far, waiting for "
                               f"{WAITING_FOR[self.job.stage]}); ask again when it ends")  # fmt: skip

    def begin(self, args: dict[str, Any], now: float) -> list[Message]:
        """Check a repair request of the live map; returns the view request for the planner."""
        self.check_idle(now)
        if self.service.busy:
            raise RequestError("busy", "busy: a repair of a finished run is running; ask again "
                               "when it ends")  # fmt: skip
        v = self.service._view(args)  # the server's own check: bad pose, intrinsics, size
        k = v.intrinsics
        T = [float(x) for x in np.asarray(v.T_world_cam, np.float64).ravel()]
        K = [float(x) for x in np.asarray(k.K, np.float64).ravel()]
        self.job = LiveJob(T, K, k.width, k.height, now)
        self.counts["forwarded"] += 1
        self._progress("forwarded", now, f"sent to {self.cfg.planner} as a view request")
        msg = render_request(
            self.name, -1, np.reshape(T, (4, 4)), np.reshape(K, (3, 3)), k.width, k.height,
            ("color", "alpha"), topic=f"view_request/{self.name}",
        )  # fmt: skip
        return [msg]

    def poll(self, now: float) -> None:
        """Fail the running view once it has taken ``timeout_s``."""
        job = self.job
        if job is not None and now - job.started > self.cfg.timeout_s:
            self._fail(f"live repair gave up after {self.cfg.timeout_s:g} s: no answer from "
                       f"{WAITING_FOR[job.stage]} (stage {job.stage})")  # fmt: skip

    def take_updates(self) -> list[Update]:
        out, self.updates = self.updates, []
        return out

    # -- the graph's messages ----------------------------------------------------------------

    def on_decision(self, msg: Message, now: float) -> None:
        """``decision/<planner>/gs``: the planner scored a view (ours if the camera matches)."""
        job, m = self.job, msg.meta
        if (
            job is None
            or job.stage != "forwarded"
            or msg.topic != f"decision/{self.cfg.planner}/gs"
        ):
            return
        # the planner echoes the request's camera bit for bit (float64 through msgpack)
        camera = (m.get("T_world_cam"), m.get("K"), m.get("width"), m.get("height"))
        if m.get("origin") != "request" or camera != (
            job.T_world_cam,
            job.K,
            job.width,
            job.height,
        ):
            return
        job.view_id = int(m["view_id"])
        reason = str(m.get("reason", ""))
        if not m.get("repair", False):
            self.counts["skipped"] += 1
            image = np.array(msg.arrays["color"], np.uint8)
            self._progress("decided", now, f"{self.cfg.planner} skips view {job.view_id}: {reason}")
            self._done(now, image, f"skipped by {self.cfg.planner}: {reason}; the 3DGS render")
            return
        job.reason = f"repaired: {reason}"
        self._progress("decided", now, f"{self.cfg.planner} repairs view {job.view_id}: {reason}")

    def on_repaired(self, msg: Message, now: float) -> None:
        """``repaired_view/<repair>``: the repair of our view."""
        job, m = self.job, msg.meta
        ours = f"repaired_view/{self.cfg.repair}"
        if job is None or job.stage != "decided" or not self._ours(msg, ours):
            return
        job.image = np.array(msg.arrays["color"], np.uint8)
        step = int(m.get("model_step", 0))
        model = "the packaged base" if int(m.get("model_version", 0)) == 0 else f"step {step}"
        job.reason += f"; GSFixer ({model})"
        self._progress("repaired", now, f"GSFixer ({model}) in {float(m.get('fix_s', 0)):.2f} s")

    def on_map_event(self, msg: Message, now: float) -> list[Message]:
        """``distill/``, ``export/`` and mesh announcements; returns the export request."""
        m, job = msg.meta, self.job
        path = str(m.get("path", "") or "")
        if m["kind"] == "distilled" and msg.topic.startswith(f"distill/{self.cfg.splat}"):
            if job is None or job.stage != "repaired" or not self._ours(msg, "distill/"):
                return []
            if float(m["distill_s"]) <= 0:  # the end of passes, not the view itself
                return []
            job.distilled = int(m["version"])
            self.exports += 1
            job.export_path = Path(self.cfg.export_dir) / f"export-{self.exports:04d}"
            self._progress("distilled", now, f"{self.cfg.splat} distilled view {job.view_id} "
                           f"in {float(m['distill_s']):.2f} s ({job.distilled} views so far)")  # fmt: skip
            meta = {"kind": "export", "path": str(job.export_path)}
            return [Message(self.cfg.export_topic, "command", self.exports, msg.stamp_ns,
                            "world", meta)]  # fmt: skip
        if m["kind"] == "exported" and msg.topic.startswith("export/") and path:
            folder = model_folder(path)
            ours = (
                job is not None and job.export_path is not None and names(folder, job.export_path)
            )
            try:
                served = self.service.update_splats(self.cfg.map, folder)
            except Exception as exc:  # a broken folder: say so, keep serving the old version
                logger.exception("%s: cannot load the export %s", self.name, path)
                if ours:
                    self._fail(f"loading the export {folder} failed: {type(exc).__name__}: {exc}")
                return []
            logger.info("%s: live map version %d from %s", self.name, served.version, folder)
            if ours:
                assert job is not None
                job.reason += f"; distilled into map version {served.version}"
                self._progress("exported", now, f"map {self.cfg.map!r} version {served.version}")
                assert job.image is not None
                self._done(now, job.image, job.reason, served.version)
        elif (
            m["kind"] == "mesh_written"
            and msg.topic.startswith(self.cfg.mesh_topic)
            and path
            and self.cfg.map in self.service.maps
        ):
            self.service.update_mesh(self.cfg.map, path)
        return []

    # -- inside ------------------------------------------------------------------------------

    def _ours(self, msg: Message, prefix: str) -> bool:
        job = self.job
        assert job is not None
        return msg.topic.startswith(prefix) and int(msg.meta.get("view_id", -1)) == job.view_id

    def _progress(self, stage: Stage, now: float, what: str) -> None:
        job = self.job
        assert job is not None
        job.stage = stage
        job.times[stage] = now - job.started
        wait = f"; waiting for {WAITING_FOR[stage]}" if stage in WAITING_FOR else ""
        self.updates.append(Update("progress", FRACTION[stage], f"{stage}: {what}{wait}"))

    def _done(
        self, now: float, image: npt.NDArray[np.uint8], reason: str, version: int | None = None
    ) -> None:
        job = self.job
        assert job is not None
        self.job = None
        if version is not None:
            self.counts["repaired"] += 1
        result = {
            "reason": reason,
            "map_version": version,
            "view_id": job.view_id,
            "repair": version is not None,
            "distilled": job.distilled,
            "stages_s": dict(job.times),
            "seconds": now - job.started,
        }
        self.updates.append(Update("done", 1.0, "done", result, image))

    def _fail(self, reason: str) -> None:
        self.job = None
        self.counts["failed"] += 1
        self.updates.append(Update("failed", text=reason))

    def stats(self) -> dict[str, Any]:
        job = self.job
        return {
            **{f"live/{k}": v for k, v in self.counts.items()},
            "live/stage": job.stage if job is not None else "",
        }
