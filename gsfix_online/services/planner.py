"""The planner as a component: view requests and renders in, decisions out (no sockets, no
clock). ``nodes/planner.py`` wires it to a transport; its docstring lists the messages.

Between messages the :class:`~gsfix_online.repair.scheduler.ViewPlanner` says what to request
(gate on mapping progress, pacing, re-sends); :func:`decision_messages` is what the planner
publishes for a decision: both renders with the score (``decision/<node>/gs|mesh``), the view's
reference warp (``decision/<node>/ref``: the real frames the planner keeps from the splat node's
keyframes and frame samples, warped into the view by its mesh depth, :mod:`~gsfix_online.repair.
ref_warp`; colour and ``alpha`` = where they see it), the view to repair (``view/<node>``) or,
for a skipped view with holes, their fill (``repaired_view/<node>``,
:func:`~gsfix_online.repair.repairer.fill_skipped`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.repair.planner import SkipPolicy
from gsfix_online.repair.ref_warp import RefWarp, RefWarpConfig
from gsfix_online.repair.references import ReferenceStore, reference_from_arrays
from gsfix_online.repair.repairer import fill_skipped
from gsfix_online.repair.scheduler import Decision, PacingPolicy, ProposalPolicy, ViewPlanner
from gsfix_online.repair.views import View, read_views
from gsfix_online.runtime import Message
from gsfix_online.runtime.requests import render_request, reply_server

logger = logging.getLogger(__name__)
LOG_EVERY_S = 30.0  # seconds between lines while views wait for the maps


@dataclass(frozen=True)
class ViewCamera:
    """Intrinsics of the views of the ``views`` file; fx = 0: the input camera's."""

    fx: float = field(default=0.0, metadata=rng(0, None, "px"))
    fy: float = field(default=0.0, metadata=rng(0, None, "px"))
    cx: float = field(default=0.0, metadata=rng(None, None, "px"))
    cy: float = field(default=0.0, metadata=rng(None, None, "px"))
    width: int = field(default=0, metadata=rng(0, 65535, "px"))
    height: int = field(default=0, metadata=rng(0, 65535, "px"))

    def validate(self) -> None:
        if self.fx > 0 and not (self.fy > 0 and self.width > 0 and self.height > 0):
            raise ValueError("camera: with fx set, fy, width and height must be set too")

    def K(self) -> np.ndarray | None:
        if self.fx <= 0:
            return None
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)


@dataclass(frozen=True)
class Params:
    views: str = ""  # TUM pose list of views to score (camera-to-world); "" = none
    camera: ViewCamera = field(default_factory=ViewCamera)
    skip: SkipPolicy = field(default_factory=SkipPolicy)
    pacing: PacingPolicy = field(default_factory=PacingPolicy)
    proposals: ProposalPolicy = field(default_factory=ProposalPolicy)
    gs_server: str = "splat"  # node that renders the Gaussian map
    mesh_server: str = "tsdf"  # node that renders the mesh
    # Views the map explains still get their holes closed: mesh fill + Telea, distilled where
    # the map has holes (no GSFixer). On the tank's skipped held-out frame 010 the final map
    # renders 22.83 dB where the 3DGS render had 19.72
    # (benchmarks/results/variants_passes_masked_cpu.json).
    fill_skipped: bool = True
    fill_dilate_px: int = field(default=3, metadata=rng(0, 64, "holes mask widening, px"))
    seed_empty: bool = True  # seed depth where no map holds anything (repairer.seed_depth)
    # Real frames warped into every view it decides (decision/<node>/ref; the fallback
    # ref_inpaint of the repair node and the writer): kept from the messages on these topics
    # (the splat node's keyframes and frame samples), at most ``reference_capacity``; [] = none
    reference_topics: list[str] = field(default_factory=lambda: ["keyframe/", "fixer_sample/"])
    reference_capacity: int = field(default=200, metadata=rng(1, None, "reference frames kept"))
    ref_warp: RefWarpConfig = field(default_factory=RefWarpConfig)


def _meta(d: Decision) -> dict[str, Any]:
    v, s = d.view, d.score
    assert v.K is not None
    return {
        "request_id": v.view_id,
        "view_id": v.view_id,
        "origin": v.origin,
        "repair": s.repair,
        "reason": s.reason,
        "surface_fraction": s.surface_fraction,
        "hole_fraction": s.hole_fraction,
        "disagree_fraction": s.disagree_fraction,
        "underobserved_fraction": s.underobserved_fraction,
        "empty_fraction": s.empty_fraction,
        "K": [float(x) for x in v.K.ravel()],
        "T_world_cam": [float(x) for x in v.T_world_cam.ravel()],
        "width": v.width,
        "height": v.height,
        "score_s": d.seconds,
        # None before the first keyframe (JSON has no NaN)
        "keyframe_distance_m": (
            None if math.isnan(d.keyframe_distance_m) else d.keyframe_distance_m
        ),  # fmt: skip
    }


def decision_messages(
    name: str, d: Decision, stamp_ns: int, views_total: int = 0,
    fill: dict[str, np.ndarray] | None = None, warp: RefWarp | None = None,
) -> list[Message]:  # fmt: skip
    """What the planner publishes for a decision (see the module doc); ``views_total``: the
    views it holds so far, its proposals included (the writer's end and progress count them);
    ``fill``: the arrays of a skipped view's fill (:func:`fill_skipped`), sent to distil;
    ``warp``: the view's reference warp (None: no reference frame yet)."""
    meta = _meta(d)
    meta["fill"] = fill is not None
    if views_total > 0:
        meta["views_total"] = int(views_total)
    seq = d.view.view_id
    out = [
        Message(
            f"decision/{name}/gs", "render_reply", seq, stamp_ns, "world", meta,
            {"color": d.gs_color, "alpha": np.ascontiguousarray(d.gs_alpha, np.float32),
             **({} if d.gs_synthesised is None
                else {"synthesised": np.ascontiguousarray(d.gs_synthesised, np.float32)})},
        ),
        Message(
            f"decision/{name}/mesh", "render_reply", seq, stamp_ns, "world", meta,
            {"color": d.mesh_color, "depth": d.mesh_depth,
             "alpha": d.mesh_valid.astype(np.float32)},
        ),
    ]  # fmt: skip
    if warp is not None:
        out.append(Message(
            f"decision/{name}/ref", "render_reply", seq, stamp_ns, "world",
            {**meta, "references": len(warp.used)},
            {"color": warp.image, "alpha": warp.valid.astype(np.float32)},
        ))  # fmt: skip
    if d.score.repair:
        v = d.view
        assert v.K is not None
        extra = {k: x for k, x in meta.items() if k not in ("request_id", "width", "height")}
        out.append(
            render_request(
                name,
                v.view_id,
                v.T_world_cam,
                v.K,
                v.width,
                v.height,
                ("color", "alpha"),
                topic=f"view/{name}",
                meta=extra,
            )  # fmt: skip
        )
    elif fill is not None:
        v = d.view
        fmeta = {"view_id": v.view_id, "keyframe_id": -1, "model_step": 0, "model_version": 0,
                 "fill_only": True}  # fmt: skip
        arrays = {**fill, "K": v.K, "T_world_cam": v.T_world_cam}
        out.append(Message(f"repaired_view/{name}", "repaired_view", seq, stamp_ns, "world",
                           fmeta, arrays))  # fmt: skip
    return out


class PlannerService:
    """Messages in, messages out, around a :class:`ViewPlanner`; no sockets, no clock."""

    def __init__(self, name: str, params: Params) -> None:
        self.name = name
        self.params = params
        c = params.camera
        K = c.K()
        camera = (K, c.width, c.height) if K is not None else None
        self.planner = ViewPlanner(params.skip, params.pacing, params.proposals, camera)
        if params.views:
            for v in read_views(params.views, K, c.width, c.height):
                self.planner.add_view(v)
        self.decisions = 0
        self.skipped = 0
        self.views_total = len(self.planner.queue)  # from the file, proposals, requests
        self.next_log = -math.inf
        self.references = ReferenceStore(params.reference_capacity)

    def waiting_line(self, now: float) -> str | None:
        """Every ``LOG_EVERY_S`` while views wait for the maps: what the gate waits for."""
        p = self.planner
        if p.gate_open or now < self.next_log:
            return None
        self.next_log = now + LOG_EVERY_S
        return (f"{len(p.queue)} views wait until both maps "
                f"hold {p.pacing.min_frames} frames (3DGS {p.progress['gs']}, mesh "
                f"{p.progress['mesh']})")  # fmt: skip

    def on_keyframe(self, msg: Message) -> None:
        """A keyframe (proposals beside it) or frame sample; both are kept as reference frames
        (by stamp: a frame that is both is kept once)."""
        if any(msg.topic.startswith(t) for t in self.params.reference_topics):
            self.references.add(int(msg.stamp_ns), reference_from_arrays(msg.arrays))
        if msg.topic.startswith("fixer_sample/"):
            return
        h, w = msg.arrays["depth"].shape
        for v in self.planner.on_keyframe(msg.arrays["T_world_cam"], msg.arrays["K"], w, h):
            self.views_total += 1
            logger.info("%s: proposed view %d beside keyframe", self.name, v.view_id)

    def on_view_request(self, msg: Message) -> None:
        m = msg.meta
        own = not m.get("input_camera", False)
        view = View(
            int(m.get("view_id", -1)),
            np.array(msg.arrays["T_world_cam"], np.float64),
            np.array(msg.arrays["K"], np.float64) if own else None,
            int(m["width"]) if own else 0,
            int(m["height"]) if own else 0,
            origin="request",
        )
        view = self.planner.add_view(view)
        self.views_total += 1
        logger.info("%s: view %d requested", self.name, view.view_id)

    def on_reply(self, msg: Message, now: float) -> list[Message]:
        server = reply_server(self.name, msg)
        kind = {self.params.gs_server: "gs", self.params.mesh_server: "mesh"}.get(server or "")
        if kind is None:
            return []
        frames = msg.meta.get("frames")
        d = self.planner.on_reply(
            kind,  # type: ignore[arg-type]
            int(msg.meta["request_id"]),
            int(frames) if isinstance(frames, int) else None,
            dict(msg.arrays),
            now,
        )
        if d is None:
            return []
        self.decisions += 1
        self.skipped += not d.score.repair
        logger.info(
            "%s: view %03d %s: %s", self.name, d.view.view_id,
            "repair" if d.score.repair else "skip", d.score.reason,
        )  # fmt: skip
        fill = None
        if self.params.fill_skipped and not d.score.repair:
            fill = fill_skipped(d.gs_color, d.gs_alpha, d.mesh_color, d.mesh_depth, d.mesh_valid,
                                self.params.skip.alpha_hole, self.params.fill_dilate_px,
                                self.params.seed_empty, d.gs_synthesised)  # fmt: skip
        v = d.view
        assert v.K is not None
        warp = self.references.warp(v.K, v.T_world_cam, d.mesh_depth, d.mesh_valid,
                                    self.params.ref_warp)  # fmt: skip
        return decision_messages(self.name, d, msg.stamp_ns, self.views_total, fill, warp)

    def poll(self, now: float) -> list[Message]:
        line = self.waiting_line(now)
        if line is not None:
            logger.info("%s: %s", self.name, line)
        return [
            render_request(self.name, a.request_id, a.T_world_cam, a.K, a.width, a.height, a.what)
            for a in self.planner.poll(now)
        ]

    def stats(self) -> dict[str, Any]:
        return {**self.planner.stats(), "planner/skipped": self.skipped}
