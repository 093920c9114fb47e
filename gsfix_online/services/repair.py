"""The repair node's component: runs GSFixer on the views the planner accepted and sends the repairs on, reliably.

Inputs (exact topic first, then type):

- ``render_request`` on ``view/...`` (the planner's accepted views, reliable): queued in order.
- ``render_reply`` on ``render_reply/<this node>/<server>``: the view's 3DGS render (colour,
  alpha) from ``gs_server`` and its mesh render (colour, alpha = hit) from ``mesh_server``.
- ``model_checkpoint`` on ``checkpoint_topic`` (the trainer's announcements): with
  ``checkpoint: latest`` or ``wait`` the newer model is loaded before the next view.
- ``trainer_plan`` on ``plan_topic``: the trainer's plan when the input ends (see below).
- ``render_reply`` on ``decision_topic`` (the planner's decisions): the renders of held-out
  frames, and of every view its reference warp (``decision/<planner>/ref``, the fallback
  ``ref_inpaint``: the real frames nearest the view warped by its mesh depth).
- ``map_event`` on ``distill/<gs_server>``: with ``wait_distilled``, the next view's renders
  are asked for once the splat node announces the last repaired view distilled (at most
  ``distilled_wait_s`` later), so that the map they show holds what the views before it
  invented, and the view is composed consistently with them.

One view at a time: request both renders (asked again after ``reply_timeout_s``), repair, then
publish reliably:

- ``repaired_view/<node>`` (colour, K, T_world_cam; meta ``view_id``, ``keyframe_id`` = -1,
  ``model_step``, ``model_version``, ``render_s``, ``fix_s``) to the splat node (distillation)
  and to the output writer;
- ``repair_input/<node>/gs`` and ``/mesh``: the renders GSFixer got (``render_reply`` messages,
  meta ``view_id``), for the outputs.

Which model: ``base`` = ``fixer.model`` only; ``latest`` = the base until the trainer announces
a checkpoint, then the newest; ``wait`` = no repair before the first checkpoint; ``run`` = no
repair before ``checkpoint_runs`` fine-tuning runs have ended (the trainer's announcement says
``run_done``), then the newest. With ``run``, the trainer's plan (``trainer_plan/<trainer>``,
sent when the input ends) overrides ``checkpoint_runs``: the node waits for the run it names,
or repairs with the base at once when it says no run will come, logging the trainer's reason.
``wait`` and ``run`` give up after ``checkpoint_wait_s`` (0 = never: the trainer is a live peer,
and waiting is what a slow one needs) and use the newest checkpoint announced by then, else the
base. While views wait for a model, a line every ``log_every_s`` says for what.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.fixer.sources import import_library
from gsfix_online.repair.compose import ComposeRules, compose_view
from gsfix_online.repair.fallback import (
    BLEND_DETAIL_PX,
    Choice,
    HeldOutChoices,
    baseline_candidates,
    fixer_only,
    regions,
)
from gsfix_online.repair.references import warp_arrays
from gsfix_online.repair.repairer import ViewRepairer, seed_depth
from gsfix_online.runtime.requests import render_request, reply_server
from gsfix_online.runtime.wire import Message

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Params(ComposeRules):  # how a view is composed and distilled: ComposeRules' settings
    fixer: FixerConfig = field(default_factory=FixerConfig)
    checkpoint: Literal["base", "latest", "wait", "run"] = "latest"
    checkpoint_wait_s: float = field(
        default=600.0, metadata=rng(0, None, "wait/run: longest wait for the model, s; 0 = none")
    )
    checkpoint_runs: int = field(
        default=1, metadata=rng(1, None, "run: fine-tuning runs to wait for before repairing")
    )
    checkpoint_topic: str = "checkpoint/"  # the trainer's announcements
    plan_topic: str = "trainer_plan/"  # the trainer's plan when the input ends
    log_every_s: float = field(
        default=30.0, metadata=rng(1, None, "seconds between lines while views wait for a model")
    )
    view_topic: str = "view/"  # the planner's accepted views
    gs_server: str = "splat"
    mesh_server: str = "tsdf"
    reply_timeout_s: float = field(
        default=30.0, metadata=rng(0.1, 3600, "ask for a view's renders again after, s")
    )
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    # Send a seed depth for the whole view: the mesh's, and in parts no map holds, depth inpainted
    # from it (gsfix_online.repair.repairer.seed_depth); False: the mesh's surface only.
    seed_empty: bool = True
    # The held-out input frames (``repair --holdout``, views [first, stop) of the planner) and
    # the folder of their camera images (NNN.png; only these ids are read): with both set, the
    # choice per region is measured on them, rendered from the finished maps, instead of on the
    # trainer's samples (rendered while mapping, when the 3DGS map was still rough). Repairs
    # wait for the planner's decisions on every one of them. [] or "": the trainer's choice.
    # That choice holds for views as near the keyframes as the held-out frames are; a view
    # farther off takes the mesh first (fallback.for_view), as every view does without them.
    holdout_views: list[int] = field(default_factory=list)
    gt_dir: str = ""
    decision_topic: str = "decision/"  # the planner's decisions (renders of every view)
    # One repaired view at a time through the map: the next view's renders wait until the splat
    # node has distilled the last one (its distill/ announcement), or ``distilled_wait_s``. Off:
    # with far_gs_only_holes "none" (a view delivers what the views before it invented) no view's
    # final map fell more than 0.16 dB under its output on the demo, tank seed 1 and rooms 1 and
    # 2 (tank view 003: -0.60..-0.93 dB shipped), but those inventions, seen from another view,
    # are floating slabs and clouds, and the output's SSIM fell under mesh + Telea's on the tank
    # and room 1, its PSNR too on room 2 (benchmarks/results/wait_distilled_cpu.md)
    wait_distilled: bool = False
    distilled_wait_s: float = field(
        default=60.0, metadata=rng(0, 3600, "longest wait for a view's distillation, s")
    )


@dataclass
class _Current:
    msg: Message  # the accepted view
    sent: float
    started: float
    replies: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


class RepairService:
    """Queue of accepted views, the render exchange and GSFixer; no sockets, clock passed in."""

    def __init__(self, name: str, params: Params, started: float) -> None:
        self.name = name
        self.params = params
        self.repairer = ViewRepairer(params.fixer)
        self.started = started
        if params.checkpoint not in ("wait", "run"):
            self.repairer.load_base()
        else:  # the model's library while the maps are built, not on the first repair's path
            import_library()
        self.runs_done = 0  # the highest run whose end a checkpoint announced
        self.plan: dict[str, Any] | None = None  # the trainer's plan (meta of trainer_plan/)
        self.next_log = started + params.log_every_s
        self.queue: deque[Message] = deque()
        self.current: _Current | None = None
        self.pending_checkpoint: tuple[str, int] | None = None
        # Where GSFixer's output is used and where the fallbacks (gsfix_online.repair.fallback):
        # the choice the trainer measured for a checkpoint; GSFixer everywhere without one.
        self.choices: dict[int, str] = {}  # checkpoint version -> Choice as JSON
        self.choice = fixer_only()  # the held-out frames' once measured, else the trainer's
        self.trainer_choice = self.choice  # the trainer's, for the checkpoint in use
        self.near_measured = False  # self.choice came from the held-out frames
        # held-out frame id -> its keyframe distance (planner.keyframe_distance; None: unknown)
        self.holdout_distance: dict[int, float | None] = {}
        # held-out frames: view id -> {"gs"|"mesh": the decision's render arrays}
        self.holdout: dict[int, dict[str, dict[str, np.ndarray]]] = {}
        self.holdout_version = -1  # model version the held-out choice was measured with
        # held-out frame id -> the choice measured on the other held-out frames (None: it was
        # the only one): a scored frame follows it, never a choice that read its own truth
        self.own_choice: dict[int, Choice | None] = {}
        # views to repair: view id -> the part neither map holds ([H, W] bool), cut into the
        # held-out frames to measure the regions they barely have (measure_on_frames)
        self.hole_shapes: dict[int, np.ndarray] = {}
        self._alphas: dict[int, dict[str, np.ndarray]] = {}  # until both renders came
        self.view_refs: dict[int, dict[str, np.ndarray]] = {}  # view id -> its reference warp
        # wait_distilled: (the last repaired view's id, when it was sent) until it is distilled
        self.undistilled: tuple[int, float] | None = None
        self.counts = {"views": 0, "repaired": 0, "resent": 0, "checkpoints": 0,
                       "with_references": 0, "flat_holes": 0, "distill_waits_timed_out": 0}  # fmt: skip

    def on_view(self, msg: Message) -> None:
        if msg.topic.startswith(self.params.view_topic):
            self.queue.append(msg)
            self.counts["views"] += 1

    def on_plan(self, msg: Message) -> None:
        if self.params.checkpoint == "base" or not msg.topic.startswith(self.params.plan_topic):
            return
        self.plan = dict(msg.meta)
        log = logger.info if self.plan["will_train"] else logger.warning
        log("%s: the trainer's plan: %s", self.name, self.plan["reason"])

    def on_checkpoint(self, msg: Message) -> None:
        if self.params.checkpoint == "base":
            return
        if not msg.topic.startswith(self.params.checkpoint_topic):
            return
        version = int(msg.meta["version"])
        if "fallback" in msg.meta:
            self.choices[version] = str(msg.meta["fallback"])
        if msg.meta["run_done"]:
            self.runs_done = max(self.runs_done, int(msg.meta["run"]))
        pending = self.pending_checkpoint[1] if self.pending_checkpoint else -1
        if version > max(self.repairer.version, pending):
            self.pending_checkpoint = (str(msg.meta["path"]), version)

    def on_reply(self, msg: Message) -> None:
        if msg.topic.startswith(self.params.decision_topic):
            self.on_decision(msg)
            return
        server = reply_server(self.name, msg)
        kind = {self.params.gs_server: "gs", self.params.mesh_server: "mesh"}.get(server or "")
        cur = self.current
        if kind is None or cur is None or int(msg.meta["request_id"]) != cur.msg.meta["view_id"]:
            return  # not ours, or a duplicate of an earlier view
        cur.replies[kind] = dict(msg.arrays)

    def on_map_event(self, msg: Message) -> None:
        """The splat node's ``distilled`` announcement of the last repaired view ends the wait
        of the next one (``wait_distilled``)."""
        if (
            self.undistilled is not None
            and msg.topic.startswith(f"distill/{self.params.gs_server}")
            and msg.meta.get("kind") == "distilled"
            and int(msg.meta.get("view_id", -1)) == self.undistilled[0]
        ):
            self.undistilled = None

    def _say_waiting(self, now: float, what: str, waited_s: float) -> None:
        """Once every ``log_every_s``: how many views wait, for what, and for how long."""
        if now >= self.next_log:
            self.next_log = now + self.params.log_every_s
            logger.info("%s: %d views wait for %s; %.0f s so far", self.name, len(self.queue),
                        what, waited_s)  # fmt: skip

    def _distilled(self, now: float) -> bool:
        """False while the last repaired view waits for its distillation (``wait_distilled``);
        a wait past ``distilled_wait_s`` is given up, with a warning."""
        if self.undistilled is None:
            return True
        vid, sent = self.undistilled
        if now - sent < self.params.distilled_wait_s:
            self._say_waiting(now, f"the splat node to distil view {vid:03d}", now - sent)
            return False
        logger.warning("%s: view %03d was not announced distilled within %.0f s; repairing the "
                       "next view without it", self.name, vid, self.params.distilled_wait_s)  # fmt: skip
        self.counts["distill_waits_timed_out"] += 1
        self.undistilled = None
        return True

    def on_decision(self, msg: Message) -> None:
        """The planner's renders of a view (``decision/<planner>/gs|mesh``): kept for the
        held-out frames, whose camera images measure the choice per region."""
        hv = self.params.holdout_views
        vid = int(msg.meta.get("view_id", -1))
        kind = msg.topic.rsplit("/", 1)[-1]
        if kind == "ref":  # a held-out frame may be repaired too: kept for both
            self.view_refs[vid] = dict(msg.arrays)
        if len(hv) != 2 or kind not in ("gs", "mesh", "ref"):
            return
        if hv[0] <= vid < hv[1]:
            self.holdout.setdefault(vid, {})[kind] = dict(msg.arrays)
            d = msg.meta.get("keyframe_distance_m")
            self.holdout_distance[vid] = None if d is None else float(d)
        elif msg.meta.get("repair", False) and kind != "ref":  # keep the shape of its holes
            parts = self._alphas.setdefault(vid, {})
            parts[kind] = np.asarray(msg.arrays["alpha"], np.float32)
            if len(parts) == 2:
                del self._alphas[vid]
                empty = regions(parts["gs"], parts["mesh"] > 0.5,
                                self.params.fixer.masks.alpha_threshold) == 3  # fmt: skip
                if empty.any():
                    self.hole_shapes[vid] = empty

    def _holdout_choice(self, now: float) -> bool:
        """With held-out frames configured: measure the choice per region on them for the model
        in use (once per model); False while their decisions have not all come."""
        hv, gt_dir = self.params.holdout_views, self.params.gt_dir
        if len(hv) != 2 or not gt_dir or self.holdout_version == self.repairer.version:
            return True
        complete = [
            v for v in range(hv[0], hv[1]) if {"gs", "mesh"} <= set(self.holdout.get(v, {}))
        ]
        if len(complete) < hv[1] - hv[0]:
            self._say_waiting(now, f"the planner's decisions on the held-out frames "
                                   f"({len(complete)} of {hv[1] - hv[0]})", now - self.started)  # fmt: skip
            return False
        self.holdout_version = self.repairer.version
        measured = measure_on_frames(self.repairer, self.holdout, gt_dir, self.params.fixer,
                                     list(self.hole_shapes.values()), blend=self.params.blend)  # fmt: skip
        if measured is not None:
            self.choice, self.own_choice, self.near_measured = measured.all, measured.without, True
            logger.info("%s: choice per region from the held-out frames %s (%s); it holds for "
                        "views up to %s m from a keyframe", self.name, self.choice.describe(),
                        self.choice.why, self.holdout_reach)  # fmt: skip
        return True

    @property
    def holdout_reach(self) -> float | None:
        """The farthest held-out frame's keyframe distance, m (None: one is not known)."""
        d = list(self.holdout_distance.values())
        return None if not d or None in d else max(d)  # type: ignore[type-var]

    def waiting_for(self, target: int) -> str:
        """What views wait for, for the progress log: the plan, or the end of run ``target``
        with the runs ended so far (the plan's reason is as it stood when the input ended)."""
        if self.plan is None:
            return "the trainer's plan (sent when the input ends)"
        return (f"fine-tuning run {target} to end ({self.runs_done} ended so far; when the "
                f"input ended: {self.plan['reason']})")  # fmt: skip

    def _model(self, now: float) -> bool:
        """Swap in an announced checkpoint; False while waiting for the first one (``wait``) or
        for the end of ``checkpoint_runs`` fine-tuning runs (``run``)."""
        limit = self.params.checkpoint_wait_s
        waited_out = limit > 0 and now - self.started >= limit
        target = int(self.plan["run"]) if self.plan is not None else self.params.checkpoint_runs
        runs_ended = self.runs_done >= target
        no_run = self.plan is not None and not self.plan["will_train"]
        if self.params.checkpoint == "run" and not (runs_ended or waited_out or no_run):
            self._say_waiting(now, self.waiting_for(target), now - self.started)
            return False  # take no intermediate checkpoint: the run's end brings the best one
        if self.pending_checkpoint is not None:
            path, version = self.pending_checkpoint
            self.pending_checkpoint = None
            self.repairer.load_checkpoint(path, version)
            self.counts["checkpoints"] += 1
            self.choice = (Choice.from_json(self.choices[version]) if version in self.choices
                           else fixer_only("the trainer measured no choice"))  # fmt: skip
            self.trainer_choice, self.near_measured = self.choice, False
            self.own_choice = {}  # measured for the model before: measured again for this one
            logger.info("%s: using checkpoint %s (version %d); per region %s", self.name, path,
                        version, self.choice.describe())  # fmt: skip
        if not self.repairer.ready and (waited_out or no_run):
            if no_run and target == 0:
                logger.warning("%s: no fine-tuning run; using the base model", self.name)
            elif not no_run:
                logger.warning("%s: no checkpoint after %.0f s; using the base model", self.name,
                               limit)  # fmt: skip
            self.repairer.load_base()
        return self.repairer.ready

    def work(self, now: float) -> tuple[list[Message], bool]:
        """(messages to publish reliably, whether to come back without waiting)."""
        cur = self.current
        if cur is None:
            if (not self.queue or not self._model(now) or not self._holdout_choice(now)
                    or not self._distilled(now)):  # fmt: skip
                return [], False
            view = self.queue.popleft()
            self.current = _Current(view, now, now)
            return [self._ask(view)], False
        if len(cur.replies) < 2:
            if now - cur.sent >= self.params.reply_timeout_s:
                cur.sent = now
                self.counts["resent"] += 1
                return [self._ask(cur.msg)], False
            return [], False
        self.current = None
        return self._repair(cur, now), bool(self.queue)

    def _ask(self, view: Message) -> Message:
        m = view.meta
        return render_request(
            self.name, int(m["view_id"]), view.arrays["T_world_cam"], view.arrays["K"],
            int(m["width"]), int(m["height"]), ("color", "alpha", "depth", "synthesised", "guessed_depth"),
        )  # fmt: skip

    def _repair(self, cur: _Current, now: float) -> list[Message]:
        gs, mesh = cur.replies["gs"], cur.replies["mesh"]
        view = cur.msg
        vid = int(view.meta["view_id"])
        ref = self.view_refs.pop(vid, None)  # the planner's, from its decision
        self.counts["with_references"] += ref is not None
        ref_color, ref_valid = warp_arrays(ref)
        t0 = time.perf_counter()  # the model's own time, not the wait for renders
        out = self.repairer.repair(np.asarray(gs["color"]), np.asarray(mesh["color"]), ref_color,
                                   ref_valid)  # fmt: skip
        fix_s = time.perf_counter() - t0
        self.counts["repaired"] += 1
        meta = {
            "view_id": vid,
            "keyframe_id": -1,
            "model_step": out.model_step,
            "model_version": out.model_version,
            "render_s": now - cur.started,
            "fix_s": fix_s,
        }
        valid = (np.asarray(mesh["alpha"]) > 0.5).astype(np.float32)
        # The floor: GSFixer where it measured better than the mesh and OpenCV alone
        gs_alpha = np.asarray(gs["alpha"], np.float32)
        cands = baseline_candidates(np.asarray(gs["color"]), gs_alpha, np.asarray(mesh["color"]),
                                    valid > 0, self.params.fixer.masks.alpha_threshold,
                                    ref_color, ref_valid)  # fmt: skip
        cands["fixed"] = out.image
        dist = view.meta.get("keyframe_distance_m")
        near = self.choice if self.near_measured else None
        if near is not None and vid in self.own_choice:  # a held-out frame: the others' choice
            near = self.own_choice[vid]
        synth = gs.get("synthesised")  # what other views' repairs grew (synthesised)
        done = compose_view(cands, gs_alpha, valid > 0, self.params.fixer.masks.alpha_threshold,
                            None if dist is None else float(dist), near, self.holdout_reach,
                            self.trainer_choice, self.params.rules(),
                            None if synth is None else np.asarray(synth))  # fmt: skip
        image, region, choice, source = done.image, done.region, done.choice, done.source
        if source == "held-out frames" and vid in self.own_choice:
            source = "the other held-out frames"
        self.counts["flat_holes"] += done.flat_holes
        meta["choice"] = choice.to_json()  # per region, the errors and why
        meta["choice_from"] = source
        meta["feather_px"] = self.params.feather_px  # the seams' blend (the output's provenance)
        meta["detail_px"] = BLEND_DETAIL_PX  # how a blend blurs its fallback (likewise)
        meta["keyframe_distance_m"] = dist
        meta["measured_choice"] = self.choice.to_json()  # the run's measurement, for the writer
        meta["trainer_choice"] = self.trainer_choice.to_json()  # beyond its reach (for_view)
        # how far that measurement holds (the writer gives skipped views within it the choice)
        meta["holdout_reach_m"] = self.holdout_reach if self.near_measured else None
        # and, per held-out frame, the choice without it (for the ones the writer composes)
        meta["measured_choice_without"] = json.dumps(
            {str(v): None if c is None else json.loads(c.to_json())
             for v, c in (self.own_choice.items() if self.near_measured else ())}
        )  # fmt: skip
        logger.info("%s: repaired view %03d in %.2f s (model version %d; %s from the %s)",
                    self.name, vid, fix_s, out.model_version, json.dumps(choice.describe()),
                    source.removeprefix("the "))  # fmt: skip
        repaired = {"color": image, "K": view.arrays["K"],
                    "T_world_cam": view.arrays["T_world_cam"]}  # fmt: skip
        # distillation fits what the map does not explain (compose_view's mask)
        if done.mask is not None:
            repaired["mask"] = done.mask
        repaired["region"] = region  # what the output was composed by: its provenance
        if self.params.wait_distilled:
            self.undistilled = (vid, now)
        if "depth" in mesh:  # lets distillation grow the map into its holes
            repaired["depth"] = seed_depth(mesh["depth"], valid > 0, self.params.seed_empty,
                                           mesh.get("guessed_depth"))  # fmt: skip
        return [
            Message(
                f"repaired_view/{self.name}", "repaired_view", vid, view.stamp_ns, "world", meta,
                repaired,
            ),
            Message(
                f"repair_input/{self.name}/gs", "render_reply", vid, view.stamp_ns, "world",
                {"request_id": vid, "view_id": vid},
                {"color": gs["color"], "alpha": gs["alpha"],
                 **({} if synth is None else {"synthesised": synth})},
            ),
            Message(
                f"repair_input/{self.name}/mesh", "render_reply", vid, view.stamp_ns, "world",
                {"request_id": vid, "view_id": vid}, {"color": mesh["color"], "alpha": valid},
            ),
            Message(  # GSFixer's own output, before the choice per region
                f"repair_input/{self.name}/fixer", "render_reply", vid, view.stamp_ns, "world",
                {"request_id": vid, "view_id": vid}, {"color": out.image},
            ),
        ]  # fmt: skip

    def stats(self) -> dict[str, Any]:
        out = {f"repair/{k}": v for k, v in self.counts.items()}
        out.update(
            {"repair/queued": len(self.queue), "repair/model_version": self.repairer.version}
        )
        return out


def measure_on_frames(
    repairer: ViewRepairer,
    frames: dict[int, dict[str, dict[str, np.ndarray]]],  # view id -> gs/mesh render arrays
    gt_dir: str,
    fixer: FixerConfig,
    hole_shapes: list[np.ndarray] | None = None,  # [H, W] bool: what no map holds in a view
    min_fraction: float = 0.01,
    blend: bool = False,  # fallback.choose's
) -> HeldOutChoices | None:
    """The choice per region measured on held-out input frames: each frame's camera image
    (``gt_dir/NNN.png``) against GSFixer (the repairer's model) and the two fallbacks.

    First on the frames as they are, in the regions they really have. A region holding less
    than ``min_fraction`` of their pixels (held-out frames lie on the mapped trajectory, so
    little of them is unobserved) is measured instead with ``hole_shapes`` cut in: the parts
    of the views to repair that neither map holds, cut into both renders, the 3DGS render
    and the mesh render in turn (:func:`~gsfix_online.repair.fallback.measure`). Returns the
    choice from all frames (for the views to repair) and, per measured frame, the choice from
    the others (:func:`~gsfix_online.repair.fallback.held_out_choices`: a held-out frame is
    scored, so it must not pick its own candidates; None for a lone frame). None: no frame
    has an image."""
    from pathlib import Path

    from gsfix_online.repair.fallback import HeldOutSample, held_out_choices, measure_each
    from gsfix_online.repair.outputs import read_png_rgb

    samples, vids = [], []
    for vid, r in sorted(frames.items()):
        path = Path(gt_dir) / f"{vid:03d}.png"
        if not path.is_file():
            logger.warning("held-out frame %d has no image %s: not measured", vid, path)
            continue
        gs, mesh = r["gs"], r["mesh"]
        h, w = np.asarray(gs["alpha"]).shape
        samples.append(HeldOutSample(
            read_png_rgb(path, w, h), np.asarray(gs["color"]), np.asarray(gs["alpha"], np.float32),
            np.asarray(mesh["color"]), np.asarray(mesh["alpha"]) > 0.5, *warp_arrays(r.get("ref")),
        ))  # fmt: skip
        vids.append(vid)
    if not samples:
        return None

    def repair_fn(
        gs: np.ndarray, mesh: np.ndarray, ref: np.ndarray | None = None, ref_valid: Any = None
    ) -> np.ndarray:
        return repairer.repair(gs, mesh, ref, ref_valid).image

    with_ref = repairer.ready and "ref" in repairer.bundle.model.conditions

    # The frames as they are: small cut holes inside observed surfaces, where Telea excels,
    # are unlike what neither map holds in the views to repair. On the room (40 frames, seed
    # 0) the uncut frames chose GSFixer there and the repaired novel views gained 0.54 dB over
    # the choice with procedural holes; on the tank both chose the same
    # (benchmarks/results/choice_cpu.json).
    seed, alpha_min = fixer.train.seed, fixer.masks.alpha_threshold
    each = measure_each(samples, repair_fn, None, seed, alpha_min, cuts=("none",),
                        with_ref=with_ref)  # fmt: skip
    h, w = samples[0].gt.shape[:2]
    shapes = [m for m in (hole_shapes or []) if m.shape == (h, w) and m.any()]
    backup, where = None, ""
    pixels = {r: sum(e.pixels[r] for e in each) for r in each[0].pixels}
    total = sum(pixels.values())
    if shapes and any(n < min_fraction * total for n in pixels.values()):
        # Regions the frames barely have, measured with the views' own holes cut in: on the
        # room with every degradation (40 frames, seed 0) held-out frames had 0.3 % of their
        # pixels in no map, which chose mesh + Telea there; the views' holes chose GSFixer, and
        # the 7 repaired novel views went from 16.31 to 16.62 dB (mesh fill + Telea: 16.52)
        # (benchmarks/results/choice_views_cpu.json).
        def cut(rng: np.random.Generator, hh: int, ww: int) -> np.ndarray:
            return shapes[int(rng.integers(len(shapes)))]

        backup = measure_each(samples, repair_fn, cut, seed, alpha_min,
                              cuts=("both", "gs", "mesh"), with_ref=with_ref)  # fmt: skip
        where = f"; {len(shapes)} views' holes cut in for thin regions"
    h = held_out_choices(each, vids, backup, min_fraction=min_fraction, blend=blend)
    why = f"{len(samples)} held-out input frames, rendered from the finished maps{where}"
    own = {
        vid: None if o is None else replace(o, why=f"{why}, without frame {vid}; {o.why}")
        for vid, o in h.without.items()
    }
    return HeldOutChoices(replace(h.all, why=f"{why}; {h.all.why}"), own)
