"""The repair writer as a component: collects a repair run into its output folder and says
when the run is complete (no sockets, no clock). ``nodes/repair_writer.py`` wires it to a
transport; its docstring lists the messages and the end of a run.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.core.io import atomic_write_text
from gsfix_online.repair.outputs import RepairOutputs, keyframes_kept
from gsfix_online.runtime import Message
from gsfix_online.runtime.requests import render_request, reply_server

logger = logging.getLogger(__name__)

FINAL_IN_FLIGHT = 4  # final render requests outstanding at once
LOG_EVERY_S = 30.0  # seconds between progress lines while collecting
SCORE_KEYS = ("surface_fraction", "hole_fraction", "disagree_fraction", "underobserved_fraction")


@dataclass(frozen=True)
class Params:
    out_dir: str = "outputs/repair"
    gt_dir: str = ""  # NNN.png ground-truth images of the views; "" = none
    # [first, stop): the views that are held-out input frames (`repair --holdout`), scored as
    # their own group in metrics.json; [] = none
    holdout_views: list[int] = field(default_factory=list)
    expected_views: int = field(
        default=0, metadata=rng(0, None, "end the run after this many views; 0 = never")
    )
    gs_server: str = "splat"
    export_topic: str = "splat/export"  # the splat node's export requests
    snapshot_topic: str = "tsdf/snapshot"  # the TSDF node's mesh snapshot requests
    reply_timeout_s: float = field(
        default=120.0, metadata=rng(0.1, 3600, "ask again when a reply takes longer, s")
    )
    # The views are repaired at the processing resolution (source.max_width); with this, each
    # view's output.png and final.png are also written upsampled (bicubic) to the camera's
    # resolution beside them, as output_camera.png and final_camera.png
    upsample_to_camera: bool = False
    camera_size: list[int] = field(default_factory=list)  # [W, H] set by the command
    processing_size: list[int] = field(default_factory=list)  # [W, H] set by the command

    def validate(self) -> None:
        for name in ("camera_size", "processing_size"):
            size = getattr(self, name)
            if size and (len(size) != 2 or min(size) < 1):
                raise ValueError(f"{name} must be [width, height] in pixels, got {size}")


KEPT_KEYS = ("keyframe_id", "view_id", "before_db", "after_db")


def _kept_rows(text: Any, topic: str) -> list[dict[str, Any]]:
    """The ``keyframes_kept`` rows of an export announcement, checked: JSON of a list of
    {keyframe_id, view_id, before_db, after_db} numbers, ``after_db`` null for a keyframe the
    map no longer stores; anything else is refused in one line (the run is written without
    them)."""
    try:
        rows = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        rows = None
    ok = isinstance(rows, list) and all(
        isinstance(r, dict)
        and all(isinstance(r.get(k), int | float) for k in KEPT_KEYS if k != "after_db")
        and (isinstance(r.get("after_db"), int | float) or r.get("after_db", 0) is None)
        for r in rows
    )
    if not ok:
        logger.warning("%s: keyframes_kept must be JSON of a list of {%s} numbers (after_db null "
                       "for a keyframe no longer stored); ignored", topic,
                       ", ".join(KEPT_KEYS))  # fmt: skip
        return []
    return [
        {k: (int(r[k]) if k.endswith("_id") else None if r[k] is None else float(r[k]))
         for k in KEPT_KEYS}
        for r in rows
    ]  # fmt: skip


@dataclass
class _Phase:
    name: str = "collect"  # collect -> final -> mesh -> export -> done
    sent: float = 0.0
    times: dict[str, float] = field(default_factory=dict)  # phase -> clock at its start


class WriterService:
    def __init__(self, name: str, params: Params, now: float) -> None:
        self.name = name
        self.params = params
        self.out = Path(params.out_dir)
        groups = {}
        if params.holdout_views:
            a, b = params.holdout_views
            groups = {"holdout": range(a, b)}
        self.outputs = RepairOutputs(self.out, params.gt_dir or None, groups)
        if params.upsample_to_camera and not (params.camera_size and params.processing_size):
            raise ValueError(  # the repair command sets both; a graph of one's own must too
                "writer: upsample_to_camera needs camera_size and processing_size [W, H], got "
                f"{params.camera_size} and {params.processing_size}"
            )
        self.phase = _Phase(times={"collect": now})
        self.distilled = 0  # views the splat node has distilled
        self.passes_pending = 0
        self.files: dict[str, Any] = {}
        self.final_sent: set[int] = set()
        self.next_log = now + LOG_EVERY_S
        self.views_total = 0  # the planner's count, its proposals included
        self._progress: dict[str, Any] = {}

    @property
    def target_views(self) -> int:
        """Views to wait for: ``expected_views`` or the planner's larger count; 0 = never end."""
        n = self.params.expected_views
        return max(n, self.views_total) if n else 0

    def progress(self) -> dict[str, Any]:
        """How far the run is (what ``OUT/work/progress.json`` holds)."""
        out, p = self.outputs, self.phase.name
        decided, target = len(out.decided()), self.target_views
        waiting = {
            "collect": "the planner's decisions" if not target or decided < target
            else "repairs and distillation",
            "final": "renders of the final map", "mesh": "the TSDF mesh",
            "export": "the 3DGS export", "done": "",
        }[p]  # fmt: skip
        return {
            "views": target, "decided": decided, "accepted": len(out.accepted()),
            "repaired": out.fixed_count(), "distilled": self.distilled,
            "final": sum(1 for r in out.decided() if "final" in r.images),
            "phase": p, "waiting": waiting,
        }  # fmt: skip

    def write_progress(self) -> None:
        """Rewrite ``OUT/work/progress.json`` when it changed (atomically)."""
        now = self.progress()
        if now != self._progress:
            self._progress = now
            atomic_write_text(self.out / "work" / "progress.json", json.dumps(now) + "\n")

    def waiting_line(self, now: float) -> str | None:
        """Every ``LOG_EVERY_S`` while collecting: how far the run is."""
        if self.phase.name != "collect" or now < self.next_log:
            return None
        self.next_log = now + LOG_EVERY_S
        out = self.outputs
        return (f"collecting: {len(out.decided())}/{self.target_views or '?'} views "
                f"decided, {out.fixed_count()}/{len(out.accepted())} repaired, "
                f"{self.distilled} distilled, {self.passes_pending} pass steps pending")  # fmt: skip

    @property
    def mesh_path(self) -> Path:
        return self.out / "mesh.ply"

    @property
    def map_dir(self) -> Path:
        return self.out / "map"

    # -- handlers ----------------------------------------------------------------------------

    def on_render_reply(self, msg: Message) -> None:
        topic, a, m = msg.topic, msg.arrays, msg.meta
        vid = int(m.get("view_id", m["request_id"]))
        if topic.startswith(("decision/", "repair_input/")):
            if topic.startswith("decision/"):
                self.views_total = max(self.views_total, int(m.get("views_total", 0)))
            if topic.startswith("decision/") and topic.endswith("/gs"):
                score = {k: float(m[k]) for k in SCORE_KEYS}
                camera = {k: m[k] for k in ("K", "T_world_cam", "width", "height")}
                self.outputs.on_decision(
                    vid, bool(m["repair"]), str(m["reason"]), score, camera,
                    str(m.get("origin", "file")), float(m.get("score_s", np.nan)),
                    bool(m.get("fill", False)),
                    None if m.get("keyframe_distance_m") is None
                    else float(m["keyframe_distance_m"]),
                )  # fmt: skip
            if topic.endswith("/fixer"):  # GSFixer's own output, before the choice per region
                self.outputs.on_fixer(vid, np.asarray(a["color"]))
            elif topic.endswith("/ref"):  # the planner's reference warp of the view
                self.outputs.on_ref(vid, np.asarray(a["color"]), np.asarray(a["alpha"]) > 0.5)
            elif topic.endswith("/gs"):
                self.outputs.on_renders(vid, gs=a["color"], alpha=a["alpha"],
                                        synthesised=a.get("synthesised"))  # fmt: skip
            else:
                self.outputs.on_renders(vid, mesh=a["color"], valid=np.asarray(a["alpha"]) > 0.5)
        elif reply_server(self.name, msg) == self.params.gs_server and "color" in a:
            self.outputs.on_final(vid, np.asarray(a["color"]))

    def on_repaired(self, msg: Message) -> None:
        m = msg.meta
        if m.get("fill_only", False):  # the planner's fill of a skipped view's holes
            self.outputs.on_filled(int(m["view_id"]), np.asarray(msg.arrays["color"]))
            return
        timings = {k: float(m[k]) for k in ("render_s", "fix_s") if k in m}
        model = {"version": int(m.get("model_version", 0)), "step": int(m["model_step"])}
        if "choice" in m:  # the fallback choice per region the repair followed
            choice = json.loads(str(m["choice"]))
            model["choice"] = choice["per_region"]
            model["choice_share"] = choice.get("share", {})  # GSFixer's share where it blends
            model["choice_hard"] = choice.get("hard", {})  # the choice without blends
            model["choice_from"] = str(m.get("choice_from", ""))
            if "feather_px" in m:  # how the output blends across seams (its provenance)
                model["feather_px"] = float(m["feather_px"])
            if "detail_px" in m:  # how a blend blurs its fallback (the output's provenance)
                model["detail_px"] = float(m["detail_px"])
            if m.get("keyframe_distance_m") is not None:
                model["keyframe_distance_m"] = float(m["keyframe_distance_m"])
            # the run's measured choice (held-out frames or trainer), not one view's
            self.outputs.fallback = json.loads(str(m.get("measured_choice", m["choice"])))
            if m.get("trainer_choice") is not None:  # what views beyond the reach followed
                self.outputs.trainer_choice = json.loads(str(m["trainer_choice"]))
            reach = m.get("holdout_reach_m")  # set when the held-out frames measured it
            self.outputs.holdout_reach_m = None if reach is None else float(reach)
            without = json.loads(str(m.get("measured_choice_without", "{}")))
            self.outputs.fallback_without = {int(v): c for v, c in without.items()}
        region = msg.arrays.get("region")  # what the output was composed by
        self.outputs.on_fixed(int(m["view_id"]), np.asarray(msg.arrays["color"]), timings, model,
                              None if region is None else np.asarray(region))  # fmt: skip

    def on_map_event(self, msg: Message) -> None:
        m = msg.meta
        if m["kind"] == "distilled" and msg.topic.startswith("distill/"):
            self.distilled = max(self.distilled, int(m["version"]))
            self.passes_pending = int(m["passes_pending"])
            if float(m["distill_s"]) > 0:
                self.outputs.on_distilled(int(m["view_id"]), float(m["distill_s"]))
            if self.passes_pending == 0:
                self.files["passes_s"] = m["passes_s"]
        elif (
            m["kind"] == "mesh_written"
            and msg.topic.startswith("mesh/")
            and Path(m["path"]) == self.mesh_path
            and self._whole("mesh")
        ):
            self.files["mesh"] = self.mesh_path.name
        elif (
            m["kind"] == "exported"
            and msg.topic.startswith("export/")
            and self.map_dir.resolve() in Path(m["path"] or "/").resolve().parents
            and self._whole("map")
        ):  # the export it asked for, not another node's
            self.files["map"] = self.map_dir.name
            if "keyframes_kept" in m:
                self.files["keyframes_kept"] = _kept_rows(m["keyframes_kept"], msg.topic)

    def _whole(self, what: str) -> bool:
        """Whether the run's mesh or 3DGS map, just written, is whole (the checks every reader
        of a run makes); a damaged file is refused in one line and asked for again after
        ``reply_timeout_s``. An empty mesh is kept with a warning: the run has no surface."""
        from gsfix_online.mapping.mesh import MeshFormatError, read_mesh
        from gsfix_online.mapping.splat.ply import PlyFormatError, check_ply, iterations, ply_path

        try:
            if what == "mesh":
                if read_mesh(self.mesh_path, allow_empty=True).is_empty:
                    logger.warning("%s: %s has no triangles: the run has no mesh to show or "
                                   "export", self.name, self.mesh_path)  # fmt: skip
            else:
                its = iterations(self.map_dir)
                if not its:
                    raise PlyFormatError(f"{self.map_dir}: no point_cloud/iteration_N")
                check_ply(ply_path(self.map_dir, its[-1]))
        except (MeshFormatError, PlyFormatError) as exc:
            logger.error("%s: refused the run's %s: %s", self.name, what, exc)
            return False
        return True

    # -- the end of a run --------------------------------------------------------------------

    def _collected(self) -> bool:
        n = self.target_views
        out = self.outputs
        if n == 0 or len(out.decided()) < n:
            return False
        k = len(out.to_distil())
        return all("output" in r.images for r in out.to_distil()) and (
            k == 0 or (self.distilled >= k and not self.passes_pending)
        )

    def _enter(self, phase: str, now: float) -> None:
        self.phase.name, self.phase.sent = phase, now
        self.phase.times[phase] = now
        logger.info("%s: %s", self.name, phase)

    def _requests(self, resend: bool = False) -> list[Message]:
        p = self.phase.name
        if p == "final":
            # A few at a time: the replies come back over reliable links too, and a sender
            # blocked on a full window cannot read the replies that would free it.
            waiting = [r for r in self.outputs.decided() if "final" not in r.images]
            if resend:
                self.final_sent.clear()
            in_flight = [r for r in waiting if r.view_id in self.final_sent]
            out = []
            for rec in [r for r in waiting if r.view_id not in self.final_sent]:
                if len(in_flight) + len(out) >= FINAL_IN_FLIGHT:
                    break
                self.final_sent.add(rec.view_id)
                c = rec.camera
                K, T = np.reshape(c["K"], (3, 3)), np.reshape(c["T_world_cam"], (4, 4))
                out.append(render_request(self.name, rec.view_id, T, K, c["width"], c["height"],
                                          ("color",)))  # fmt: skip
            return out
        if p == "mesh":
            meta = {"kind": "snapshot", "path": str(self.mesh_path)}
            return [Message(self.params.snapshot_topic, "command", meta=meta)]
        if p == "export":
            meta = {"kind": "export", "path": str(self.map_dir.resolve())}
            return [Message(self.params.export_topic, "command", meta=meta)]
        return []

    def work(self, now: float) -> tuple[list[Message], bool]:
        """(requests to publish reliably, finished)."""
        line = self.waiting_line(now)
        if line is not None:
            logger.info("%s: %s", self.name, line)
        self.write_progress()
        p = self.phase.name
        nxt = None
        if p == "collect" and self._collected():
            nxt = "final"
        elif p == "final" and all("final" in r.images for r in self.outputs.decided()):
            nxt = "mesh"
        elif p == "mesh" and "mesh" in self.files:
            nxt = "export"
        elif p == "export" and "map" in self.files:
            self._enter("done", now)
            self.write(now)
            self.write_progress()
            return [], True
        if nxt is not None:
            self._enter(nxt, now)
            return self._requests(), False
        if p != "collect" and now - self.phase.sent >= self.params.reply_timeout_s:
            logger.warning("%s: no reply in phase %s after %.0f s; asking again", self.name, p,
                           self.params.reply_timeout_s)  # fmt: skip
            self.phase.sent = now
            return self._requests(resend=True), False
        if p == "final":
            more = self._requests()
            if more:
                self.phase.sent = now
            return more, False
        return [], False

    def idle_work(self) -> bool:
        """While views are collected: one scoring baseline that is due (FSR, seconds a view),
        so that it is not made at the end of the run, after distillation. True while more are
        due."""
        if self.phase.name != "collect":
            return False
        return self.outputs.finish_baselines(limit=1) > 0

    def camera_size_of(self, width: int, height: int) -> tuple[int, int]:
        """The size a ``width`` x ``height`` view has at the camera's resolution: the input
        camera's own size for a view at the processing resolution, else scaled alike."""
        (cw, ch), (pw, ph) = self.params.camera_size, self.params.processing_size
        return round(width * cw / pw), round(height * ch / ph)

    def write_upsampled(self) -> None:
        """Each view's delivered repair and final render at the camera's resolution
        (``output_camera.png``, ``final_camera.png`` beside ``output.png``, ``final.png``)."""
        from gsfix_online.repair.outputs import write_png
        from gsfix_online.sources.resolution import resize_color

        for rec in self.outputs.decided():
            for key in ("output", "final"):
                img = rec.images.get(key)
                if img is None:
                    continue
                w, h = self.camera_size_of(img.shape[1], img.shape[0])
                path = self.out / "views" / rec.name / f"{key}_camera.png"
                write_png(path, resize_color(np.asarray(img), w, h, "cubic"))

    def write(self, now: float) -> dict[str, Any]:
        t = self.phase.times
        order = [k for k in ("collect", "final", "mesh", "export", "done") if k in t]
        phases = {f"{a}_s": t[b] - t[a] for a, b in zip(order, order[1:], strict=False)}
        extra = {
            "timings_s": {**phases, "distill_passes_s": self.files.get("passes_s", 0.0)},
            "map": self.files.get("map"),
            "mesh": self.files.get("mesh"),
            "report": "report.html",
        }
        if self.files.get("keyframes_kept"):
            extra["keyframes_kept"] = keyframes_kept(self.files["keyframes_kept"])
        if self.params.camera_size:
            extra["resolution"] = {"camera": list(self.params.camera_size),
                                   "processing": list(self.params.processing_size)}  # fmt: skip
        m = self.outputs.write(extra)  # skipped views get their output.png here
        if self.params.upsample_to_camera:
            self.write_upsampled()
        fid = m["summary"]["map_fidelity"]
        if fid["low"]:
            logger.warning("%s: the final map keeps the delivered repair poorly at views %s "
                           "(under %.0f dB from their outputs; median %.1f dB): see "
                           "metrics.json map_fidelity_db", self.name, ", ".join(fid["low"]),
                           fid["low_below_db"], fid["median_db"])  # fmt: skip
        if fid.get("blurred"):
            # mostly where the views invented a surface differently and the map averages their
            # texture, which has none of the scene's edges (sharpness_truth_edges_cpu.md)
            logger.warning("%s: the final map renders views %s blurrier than they were "
                           "delivered (sharpness under %.2f of what a map that holds their "
                           "outputs renders: a veil, or the views' invented texture averaged; "
                           "their provenance says which parts were synthesised): see "
                           "metrics.json map_sharpness",
                           self.name, ", ".join(fid["blurred"]), fid["blurred_below"])  # fmt: skip
        kept = m.get("keyframes_kept") or {}
        if kept.get("lost"):
            logger.warning("%s: distilling the repairs cost the input keyframes %s, next to "
                           "repaired views, more than %.1f dB (worst %.2f dB; median %+.2f): the "
                           "map renders what the robot saw there worse than before; see "
                           "metrics.json keyframes_kept",
                           self.name, ", ".join(map(str, kept["lost"])), kept["lost_above_db"],
                           kept["worst_change_db"], kept["median_change_db"])  # fmt: skip
        if kept.get("gone"):
            logger.warning("%s: the map no longer stores the input keyframes %s, measured before "
                           "the repaired views (later input keyframes evicted them): what "
                           "distilling cost them is not known; see metrics.json keyframes_kept",
                           self.name, ", ".join(map(str, kept["gone"])))  # fmt: skip
        return m
