"""The planner's state machine: which render to ask for next, and when a view is scored.

No sockets and no clock: the node passes ``now`` (monotonic seconds) in and sends the
:class:`Ask` objects that come out. The flow per view:

1. **Gate.** Views wait until both maps (3DGS and mesh) have integrated ``min_frames`` frames.
   Progress comes from tiny probe renders (8x6 alpha) whose replies carry the server's frame
   count, sent every ``probe_every_s``. With ``min_frames`` = 0 the gate is open from the start.
2. **Pacing.** At most ``max_in_flight`` views are being rendered at once, a new one at least
   ``min_interval_s`` after the previous, so render requests never crowd out mapping.
3. **Renders.** One render request per view goes to both servers; a view whose two replies have
   not come within ``reply_timeout_s`` is asked again (replies from latest-only servers may be
   superseded; duplicates are ignored).
4. **Score.** With both renders in, :func:`~gsfix_online.repair.planner.score_view` decides
   (observation counts from the keyframe poses seen so far) and a :class:`Decision` comes out.

Optional proposals: every ``propose_every`` keyframes, views beside the keyframe (see
:func:`~gsfix_online.repair.views.propose_around`) join the queue, up to ``max_proposals``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.repair.planner import (
    SkipPolicy,
    ViewScore,
    keyframe_distance,
    observation_counts,
    score_view,
)
from gsfix_online.repair.views import View, propose_around

Server = Literal["gs", "mesh"]
PROBE_SIZE = (8, 6)  # width, height of a progress probe


@dataclass(frozen=True)
class PacingPolicy:
    min_frames: int = field(
        default=0, metadata=rng(0, None, "views wait until both maps integrated this many frames")
    )
    probe_every_s: float = field(
        default=2.0, metadata=rng(0.01, 3600, "progress probes while the gate is closed, s")
    )
    max_in_flight: int = field(default=1, metadata=rng(1, 64, "views being rendered at once"))
    min_interval_s: float = field(
        default=0.0, metadata=rng(0, 3600, "least time between two views' requests, s")
    )
    reply_timeout_s: float = field(
        default=30.0, metadata=rng(0.1, 3600, "ask again when a view's renders take longer, s")
    )


@dataclass(frozen=True)
class ProposalPolicy:
    every_keyframes: int = field(
        default=0, metadata=rng(0, None, "propose views every n-th keyframe; 0 = never")
    )
    yaw_deg: float = field(default=35.0, metadata=rng(0, 180, "turn left/right of the keyframe"))
    back_m: float = field(default=0.3, metadata=rng(0, 100, "step back along the optical axis"))
    max_proposals: int = field(default=8, metadata=rng(0, None, "proposed views in total"))


@dataclass(frozen=True)
class Ask:
    """A render request to send to both servers."""

    request_id: int  # the view id, or a negative id for a probe
    T_world_cam: npt.NDArray[np.float64]  # [4, 4]
    K: npt.NDArray[np.float64]  # [3, 3] px
    width: int
    height: int
    what: tuple[str, ...]


@dataclass(frozen=True)
class Decision:
    view: View
    score: ViewScore
    gs_color: npt.NDArray[np.uint8]  # [H, W, 3]
    gs_alpha: npt.NDArray[np.float32]  # [H, W]
    mesh_color: npt.NDArray[np.uint8]  # [H, W, 3]
    mesh_depth: npt.NDArray[np.float32]  # [H, W] m, 0 = no surface
    mesh_valid: npt.NDArray[np.bool_]  # [H, W]
    seconds: float  # from the first request to the decision
    # from the nearest keyframe seen so far (planner.keyframe_distance, at the median depth of
    # the mesh render; 1 m where the mesh sees nothing); NaN before the first keyframe
    keyframe_distance_m: float = math.nan
    # [H, W] the share of the 3DGS render's colour that Gaussians grown from repaired views
    # make (what the map shows there was synthesised); None: the server did not say
    gs_synthesised: npt.NDArray[np.float32] | None = None


@dataclass
class _InFlight:
    view: View
    first_sent: float
    last_sent: float
    replies: dict[str, dict[str, Any]] = field(default_factory=dict)  # server -> arrays


class ViewPlanner:
    """Queue, gate, pacing and scoring of requested views (see the module doc)."""

    def __init__(
        self,
        skip: SkipPolicy,
        pacing: PacingPolicy,
        proposals: ProposalPolicy | None = None,
        camera: tuple[npt.NDArray[np.float64], int, int] | None = None,  # K [3, 3], W, H
    ) -> None:
        self.skip = skip
        self.pacing = pacing
        self.proposals = proposals or ProposalPolicy()
        self.camera = camera
        self.queue: deque[View] = deque()
        self.in_flight: dict[int, _InFlight] = {}
        self.progress: dict[str, int] = {"gs": 0, "mesh": 0}
        self.kf_poses: list[npt.NDArray[np.float64]] = []
        self.kf_camera: tuple[npt.NDArray[np.float64], int, int] | None = None
        self.next_id = 0
        self.n_proposed = 0
        self.n_probes = 0
        self.n_resent = 0
        self._next_probe = 0.0
        self._probe_answered: set[str] = {"gs", "mesh"}  # servers that answered the last probe
        self._probe_sent = -math.inf
        self._last_view_sent = -np.inf
        self.decided: set[int] = set()

    # -- inputs ------------------------------------------------------------------------------

    def add_view(self, view: View) -> View:
        """Queue a view; ``view_id`` < 0 gets the next free id. Returns the queued view."""
        if view.view_id < 0:
            view = View(
                self.next_id, view.T_world_cam, view.K, view.width, view.height, view.origin
            )
        self.next_id = max(self.next_id, view.view_id + 1)
        self.queue.append(view)
        return view

    def on_keyframe(
        self,
        T_world_cam: npt.NDArray[np.float64],  # [4, 4]
        K: npt.NDArray[np.float64],  # [3, 3] px
        width: int,
        height: int,
    ) -> list[View]:
        """Remember a keyframe (observation counts, the input camera); returns proposed views."""
        self.kf_poses.append(np.asarray(T_world_cam, np.float64))
        if self.kf_camera is None:
            self.kf_camera = (np.asarray(K, np.float64), int(width), int(height))
        p = self.proposals
        out: list[View] = []
        if p.every_keyframes and len(self.kf_poses) % p.every_keyframes == 0:
            for T in propose_around(T_world_cam, p.yaw_deg, p.back_m):
                if self.n_proposed >= p.max_proposals:
                    break
                self.n_proposed += 1
                out.append(self.add_view(View(-1, T, origin="proposal")))
        return out

    @property
    def gate_open(self) -> bool:
        return min(self.progress.values()) >= self.pacing.min_frames

    def _input_camera(self) -> tuple[npt.NDArray[np.float64], int, int] | None:
        return self.camera or self.kf_camera

    # -- outputs -----------------------------------------------------------------------------

    def poll(self, now: float) -> list[Ask]:
        """The requests due at ``now``: a probe, re-sent and new views."""
        asks: list[Ask] = []
        cam = self._input_camera()
        if not self.gate_open:  # (then min_frames > 0)
            # One probe at a time: a busy map answers late, and probes sent meanwhile would
            # only queue up behind it (a new one goes after reply_timeout_s all the same)
            answered = len(self._probe_answered) == 2
            late = now - self._probe_sent >= self.pacing.reply_timeout_s
            if now >= self._next_probe and (answered or late):
                asks.append(self._probe(now))
            return asks
        for f in self.in_flight.values():
            if now - f.last_sent >= self.pacing.reply_timeout_s:
                f.last_sent = now
                self.n_resent += 1
                asks.append(self._ask(f.view))
        while (
            self.queue
            and len(self.in_flight) < self.pacing.max_in_flight
            and now - self._last_view_sent >= self.pacing.min_interval_s
        ):
            view = self.queue[0]
            if not view.has_camera:
                if cam is None:
                    break  # no keyframe yet: the input camera is not known
                view = view.with_camera(*cam)
            self.queue.popleft()
            self.in_flight[view.view_id] = _InFlight(view, now, now)
            self._last_view_sent = now
            asks.append(self._ask(view))
        return asks

    def _probe(self, now: float) -> Ask:
        self._next_probe = now + self.pacing.probe_every_s
        self._probe_answered, self._probe_sent = set(), now
        self.n_probes += 1
        w, h = PROBE_SIZE
        K = np.array([[w, 0, (w - 1) / 2], [0, w, (h - 1) / 2], [0, 0, 1]], np.float64)
        return Ask(-self.n_probes, np.eye(4), K, w, h, ("alpha",))

    @staticmethod
    def _ask(view: View) -> Ask:
        assert view.K is not None
        what = ("color", "depth", "alpha", "synthesised")
        return Ask(view.view_id, view.T_world_cam, view.K, view.width, view.height, what)

    def on_reply(
        self,
        server: Server,
        request_id: int,
        frames: int | None,  # frames the server has integrated (progress)
        arrays: dict[str, np.ndarray],
        now: float,
    ) -> Decision | None:
        """A render reply; returns the decision once both renders of a view are in."""
        if frames is not None:
            self.progress[server] = max(self.progress[server], int(frames))
        if request_id == -self.n_probes:
            self._probe_answered.add(server)
        f = self.in_flight.get(request_id)
        if request_id < 0 or f is None:
            return None  # a probe, or a duplicate after a re-send
        f.replies[server] = arrays
        if len(f.replies) < 2:
            return None
        del self.in_flight[request_id]
        self.decided.add(request_id)
        return self._decide(f, now)

    def _decide(self, f: _InFlight, now: float) -> Decision:
        gs, mesh = f.replies["gs"], f.replies["mesh"]
        view = f.view
        assert view.K is not None
        valid = np.asarray(mesh["alpha"]) > 0.5
        depth = np.where(valid, np.asarray(mesh["depth"], np.float32), 0.0).astype(np.float32)
        obs, reach = None, math.nan
        if self.kf_poses:
            z = float(np.median(depth[valid])) if valid.any() else 1.0
            reach = keyframe_distance(view.T_world_cam, np.stack(self.kf_poses), z)
        if self.kf_poses and self.kf_camera is not None:
            K_kf, w_kf, h_kf = self.kf_camera
            obs = observation_counts(
                depth, view.K, view.T_world_cam, np.stack(self.kf_poses), K_kf, (w_kf, h_kf)
            )
        score = score_view(gs["color"], gs["alpha"], mesh["color"], valid, self.skip, obs)
        return Decision(
            view, score, gs["color"], gs["alpha"], mesh["color"], depth, valid,
            now - f.first_sent, reach, gs.get("synthesised"),
        )  # fmt: skip

    def stats(self) -> dict[str, Any]:
        return {
            "planner/queued": len(self.queue),
            "planner/in_flight": len(self.in_flight),
            "planner/decided": len(self.decided),
            "planner/proposed": self.n_proposed,
            "planner/probes": self.n_probes,
            "planner/resent": self.n_resent,
            "planner/frames_gs": self.progress["gs"],
            "planner/frames_mesh": self.progress["mesh"],
        }
