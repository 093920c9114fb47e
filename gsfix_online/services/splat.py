"""The splat node's component: builds the 3D Gaussian map from posed ``rgbd`` frames and serves
it. Messages in, messages out; no sockets and no clock (``nodes/splat.py`` wires it).

- ``rgbd`` (posed): :meth:`Mapper.process`; each keyframe is published reliably as a
  ``keyframe`` message (colour, depth, pose, intrinsics, the map's render and alpha at the pose).
  Frames drawn by :mod:`gsfix_online.fixer.samples` go out the same way on
  ``fixer_sample/<name>`` (GSFixer's training set does not hang on the keyframe policy), and
  after ``input_frames`` frames the end of the input on ``input_end/<name>``; once that is sent,
  :meth:`SplatService.after_input_end` refines the map (``refine_at_input_end``).
- ``render_request``: replies ``render_reply`` on ``render_reply/<requester>/<name>`` (or
  ``render_reply/<name>`` when the request names no ``reply_to``) with what was asked (colour as
  rgb8, depth in m, alpha) and meta ``frames`` (frames mapped so far: the planner's progress
  gate), latest-only unless ``reliable_replies``.
- ``repaired_view`` (GSFix3D distillation): :meth:`Mapper.distill` runs ``mapper.distill_iters``
  steps of (1 - l) L1 + l (1 - SSIM) on the view (paper: 20, l = 0.2; density control as the
  mapper's), which keeps it as an extra observation; then ``distill_passes`` passes over the
  keyframes plus repaired views are scheduled (the reference runs 50). They run in slices of
  ``pass_slice_steps`` refinement steps between messages, so live frames keep being mapped. A
  new repaired view restarts the count (one the map already explains, by ``pass_restart_loss``,
  asks for one pass). When the passes end, with ``mapper.polish_below_db``,
  the repaired views the map renders furthest from what they were fitted to are fitted again
  (:meth:`Mapper.polish`). Each distilled view, and the end of its passes, is
  announced as a ``map_event`` of kind ``distilled`` on ``distill/<name>`` (``version`` = views
  distilled, ``step`` = optimizer steps, ``view_id``, ``distill_s``, ``passes_pending`` steps,
  ``passes_s``).
- a ``command`` of kind ``export`` on ``export_topic`` (meta ``path``): export the standard 3DGS
  layout there and announce it on ``export/<name>`` (a ``map_event`` of kind ``exported``;
  meta ``keyframes_kept``, JSON: every input keyframe's render PSNR before the repaired views
  were distilled and now, and the repaired view it is near, see ``kept_keyframes``). The path must lie inside ``write_root`` (default:
  the folder holding ``export_dir``, else ``snapshot``'s, else the working directory): a name
  received over the wire never becomes a path outside it. Render requests above
  ``max_render_pixels`` are refused before anything is allocated.
- Every ``snapshot_every`` frames and on exit the mapper's state is written atomically to
  ``snapshot``; a node started with an existing snapshot resumes from it and announces the
  snapshot's keyframes again (:meth:`SplatService.keyframes_again`): those a killed node had
  sent but its reader had not acknowledged died with it (the trainer keeps one per id). On exit (and on
  SIGUSR1) the map is exported in the standard 3DGS layout to ``export_dir``.
- Every ``stats_every`` frames it publishes ``stats/<name>/map`` (Gaussians, keyframes, steps,
  skipped non-finite steps, mapping time per frame).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.fixer.sample_builder import Perturbation, map_arrays, rgb8
from gsfix_online.fixer.samples import FRAME_SAMPLE_ID0, SamplePolicy, SampleState
from gsfix_online.fixer.samples import step as sample_step
from gsfix_online.mapping.splat.keyframes import Keyframe, prior_images
from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig
from gsfix_online.repair.fallback import MESH_SAW
from gsfix_online.repair.outputs import keyframes_kept as summarise_kept
from gsfix_online.runtime.ratelog import warn_repeated
from gsfix_online.runtime.requests import MAX_RENDER_PIXELS, path_inside, render_size, reply_topic
from gsfix_online.runtime.threads import ThreadTuner
from gsfix_online.runtime.wire import Message, message_to_frame

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
    distill_passes: int = field(
        default=2,
        metadata=rng(0, None, "passes over keyframes + repaired views after a repair (ref.: 50)"),
    )
    # A view the map already renders close to what was delivered (its distillation loss starts
    # below this: the planner's fill of a skipped view's few holes, a held-out frame the map
    # explains) has nothing to blend in: it asks for one pass, not a new round of
    # ``distill_passes``. In the repair graph repaired novel views start at 0.06-0.15 and such
    # views at 0.001-0.008 (benchmarks/results/demo_5min_cpu.md). 0 = every view restarts them.
    pass_restart_loss: float = field(
        default=0.0, metadata=rng(0, None, "distillation loss below which passes do not restart")
    )
    pass_slice_steps: int = field(
        default=2, metadata=rng(1, None, "refinement steps between looks at the queue")
    )
    export_topic: str = "splat/export"  # export commands (meta path)
    # the folder an export path named in a message must lie in; "" = see the module doc
    write_root: str = ""
    max_render_pixels: int = field(
        default=MAX_RENDER_PIXELS, metadata=rng(1, None, "largest render a request may ask for")
    )
    announce: Literal["reliable", "latest"] = "reliable"  # distill/ and export/ announcements
    stats_every: int = field(default=10, metadata=rng(1, None, "frames between map stats"))
    stop_after: int = field(default=0, metadata=rng(0, None, "exit after n frames; 0 = never"))
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    # Torch threads the distillation passes may use once the end-of-input refinement is done
    # (0 = keep ``threads``). Mapping and that refinement share the cores with background
    # fine-tuning, which ends its run beside the refinement; after it, distillation and its
    # passes are the run's critical path. On 2 idle cores a pass step of the demo's map takes
    # 0.62 s on one thread and 0.35 s on two, but on busy cores two threads are many times
    # slower, so the passes time both counts and keep the faster (runtime/threads.py)
    threads_after_input: int = field(
        default=0, metadata=rng(0, 256, "torch threads the passes may use; 0 = threads")
    )
    # Map alpha at poses near each keyframe, sent with it as mask candidates for the trainer
    # (holes like those of views off the trajectory); rendered at 1/perturbed_downscale size.
    perturbed_renders: int = field(default=3, metadata=rng(0, 16, "renders per keyframe"))
    # The 3DGS render a keyframe carries for GSFixer's training: "after" the frame was mapped
    # (close to the frame itself), or "before" (what the map predicted at that pose: the
    # artefacts and holes of a novel view, whose repair is the job; made for the mapping's
    # own loss anyway). With the finely seeded map, "after" renders came so close to their
    # frames that GSFixer repaired the real-like room 0.6-1.2 dB worse; "before" won back
    # +0.39 to +0.60 dB of it and +0.03 to +0.26 dB of the output in 3 seeds, and left the
    # real-like tank and the demo within a run's spread (demo output 18.00 dB either way;
    # benchmarks/results/keyframe_render_before_cpu.md). On a clean procedural room (seed 1)
    # "after" was ahead: output +0.10 and +0.12 dB in 2 paired seeds
    # (benchmarks/results/issue43_three_seeds_cpu.md)
    keyframe_render: Literal["after", "before"] = "before"
    perturb_deg: float = field(default=25.0, metadata=rng(0, 180, "rotation of those poses"))
    perturb_m: float = field(default=0.3, metadata=rng(0, 10, "translation of those poses, m"))
    perturbed_downscale: int = field(default=2, metadata=rng(1, 16, "render size divisor"))
    # GSFixer's training set beside the keyframes: frames drawn from the input itself
    # (gsfix_online.fixer.samples), sent as ``keyframe`` messages on ``fixer_sample/<name>``
    # with ids from FRAME_SAMPLE_ID0 on. Off here (every 0): a graph turns it on where an
    # output routes ``fixer_sample/`` to a trainer (configs/graphs/repair.yaml).
    samples: SamplePolicy = field(default_factory=lambda: SamplePolicy(every=0))
    # The input's frame count, when known (an offline run): after that many frames the node
    # announces the end of the input on ``input_end/<name>`` (an ``input_end`` message, meta
    # ``frames``, ``keyframes``, ``samples``), so the trainer starts at once.
    input_frames: int = field(
        default=0, metadata=rng(0, None, "frames of the input; 0 = unknown (a live stream)")
    )
    # Global refinement over the keyframes once the input has ended, before anything renders
    # from the finished map (the planner scores views only then). The online steps leave the
    # map fitted to the latest frames; at the ship tank's held-out frames 100 steps lift raw
    # 3DGS from 21.9 to 26.0 dB, above the mesh + Telea's 25.4 (bench_heldout_map.py)
    refine_at_input_end: int = field(
        default=0, metadata=rng(0, None, "refinement steps when the input ends; 0 = none")
    )
    # What distillation costs what was observed: every input keyframe is rendered (PSNR against
    # its frame) before the first repaired view that follows it is distilled, and again when the
    # map is exported on request; the ``kept_keyframes`` nearest each repaired view (camera
    # centres) are marked as its neighbours. The export's announcement carries them
    # (``keyframes_kept``), and the writer puts them in metrics.json. 0 = not measured.
    kept_keyframes: int = field(
        default=2, metadata=rng(0, 64, "neighbouring input keyframes per repaired view")
    )
    # ... rendered at 1/this of the frame's size against the frame area-averaged. Full size: at
    # half size room seed 1's keyframes gained 3.47 dB (median) where they lost 1.19 at full
    # size, the fine detail moved (benchmarks/results/polish_keyframes_cpu.md); 52 keyframes of
    # 320x240 took 3.9 s at full size, 2.2 s at half, and every keyframe is rendered twice
    kept_downscale: int = field(default=1, metadata=rng(1, 16, "size divisor of those renders"))
    # A diagnosis: render every measured keyframe again after each stage of distillation (each
    # repaired view's own steps, the passes, polish) and log the median and worst change. It
    # found that polish, not the views' fits, moved what room seed 1's frames observed
    # (benchmarks/results/polish_keyframes_cpu.md). Off: each stage costs a render of every
    # keyframe (52 of 320x240: about 4 s).
    kept_stages: bool = False


class SnapshotError(ValueError):
    """A snapshot file fails its size or checksum check, or does not load (one line)."""


def save_snapshot(mapper: Mapper, path: Path) -> None:
    """Write the mapper's state atomically (temporary file, fsync, rename): never half a file.

    ``PATH.sha256`` beside it records the file's size and SHA-256, and the snapshot it replaces
    is kept as ``PATH.prev`` (with its record), so that :func:`load_snapshot` detects a damaged
    file and has a good one to fall back on. A crash between the renames leaves a snapshot whose
    record does not match: it is detected and the previous one is used.
    """
    import hashlib
    import io
    import os

    import torch

    from gsfix_online.core.io import atomic_path, atomic_write_text

    buf = io.BytesIO()
    torch.save(mapper.state_dict(), buf)
    payload = buf.getvalue()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        if path.is_file():
            for old in (_record(path), path):  # the record first: never a record without its file
                if old.is_file():
                    os.replace(old, _previous(old))
    atomic_write_text(_record(path), f"{hashlib.sha256(payload).hexdigest()} {len(payload)}\n")


def _previous(path: Path) -> Path:
    return path.with_name(path.name + ".prev")


def _record(path: Path) -> Path:  # PATH.sha256, or PATH.prev.sha256 for the previous one
    name = path.name.removesuffix(".prev")
    return path.with_name(name + ".sha256" + (".prev" if path.name.endswith(".prev") else ""))


def _read_snapshot(path: Path) -> dict[str, Any]:
    import hashlib
    import io

    import torch

    data = path.read_bytes()
    record = _record(path)
    if record.is_file():
        fields = record.read_text().split()
        if len(fields) != 2 or not fields[1].isdigit():
            raise SnapshotError(f"snapshot record {record} is malformed")
        if len(data) != int(fields[1]):
            raise SnapshotError(f"snapshot {path} has {len(data)} bytes, its record {fields[1]}")
        if hashlib.sha256(data).hexdigest() != fields[0]:
            raise SnapshotError(f"snapshot {path} is corrupt (SHA-256 differs from {record.name})")
    try:  # weights_only: tensors and plain containers, never arbitrary pickled objects
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several kinds for a damaged archive
        line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SnapshotError(f"snapshot {path} does not load: {line}") from None
    if not isinstance(state, dict) or "map" not in state:
        raise SnapshotError(f"snapshot {path} holds no mapper state")
    return state


def load_snapshot(cfg: MapperConfig, path: Path) -> Mapper:
    """The mapper saved at ``path``; when that file fails its checksum or does not load, the
    error is logged and ``PATH.prev`` (the snapshot before it) is used. Raises
    :class:`SnapshotError` when neither is usable."""
    problems = []
    for p in (path, _previous(path)):
        if not p.is_file():
            continue
        try:
            state = _read_snapshot(p)
            mapper = Mapper(cfg, channels=int(state["map"]["channels"]))
            mapper.load_state_dict(state)
        except (SnapshotError, KeyError, RuntimeError, ValueError, TypeError) as exc:
            problems.append(str(exc).splitlines()[0])
            logger.error("%s", problems[-1])
            continue
        if p != path:
            logger.warning("using the previous good snapshot %s", p)
        return mapper
    raise SnapshotError(f"no usable snapshot at {path} ({'; '.join(problems) or 'missing'})")


class SplatService:
    """The node's component glue: messages in, messages out; no sockets, no clock."""

    def __init__(self, name: str, params: Params) -> None:
        self.name = name
        self.params = params
        self.mapper: Mapper | None = None
        self.frames = 0
        self.distilled = 0
        self.kf_seq = 0
        self.pass_steps_left = 0  # refinement steps of the scheduled distillation passes
        self.passes_s = 0.0
        self.last_view_id = -1
        self.announced = 0
        self.rng = np.random.default_rng(0)  # perturbed poses: the same run maps the same way
        self.sample_state: SampleState = params.samples.initialize_state()
        self.input_ended = False
        self.refine_due = False  # the input has ended: after_input_end has work to do
        self.tuner: ThreadTuner | None = None  # threads of the passes (threads_after_input)
        self.repeated_frames = 0  # frames skipped as mapped already (see on_rgbd)
        # kept_keyframes: {input keyframe id: PSNR dB before the repaired views after it}, and
        # {input keyframe id: the first repaired view it is a neighbour of}
        self.kept_before: dict[int, float] = {}
        self.kept_near: dict[int, int] = {}
        snap = Path(params.snapshot) if params.snapshot else None
        if snap is not None and (snap.is_file() or _previous(snap).is_file()):
            self.mapper = load_snapshot(params.mapper, snap)
            self.frames = self.mapper.n_frames
            self.kf_seq = self.mapper.kf_state.n_keyframes  # keyframe messages sent before
            logger.info(
                "%s: resumed from %s (%d Gaussians, %d keyframes, %d frames)",
                name, snap, len(self.mapper.gmap), len(self.mapper.store), self.frames,
            )  # fmt: skip

    def keyframes_again(self) -> list[Message]:
        """The keyframes of the map (after a resume: its snapshot's) as ``keyframe`` messages,
        with the 3DGS render they were first announced with (``keyframe_render``)."""
        if self.mapper is None:
            return []
        out, after = [], 0
        for i, kf in enumerate(self.mapper.store):
            if kf.render is None or kf.alpha is None:
                continue
            arrays = self._keyframe_arrays(self.mapper, kf.frame, kf)
            after += self.params.keyframe_render == "before" and kf.prior is None
            out.append(self._keyframe_message("keyframe", i, kf.kf_id, kf.frame, arrays))
        if after:
            logger.warning("%s: %d of the snapshot's keyframes kept no render from before their "
                           "frame (an older snapshot): announced with the render after it",
                           self.name, after)  # fmt: skip
        return out

    def _mapper(self, channels: int) -> Mapper:
        if self.mapper is None:
            self.mapper = Mapper(self.params.mapper, channels=channels)
        return self.mapper

    def on_rgbd(self, msg: Message) -> list[Message]:
        """Map a frame; out: its keyframe and/or frame sample messages, and the end of the
        input after the last of ``input_frames`` frames."""
        frame = message_to_frame(msg)
        mapper = self._mapper(1 if frame.is_gray else 3)
        last = mapper.last_stamp_ns.get(frame.frame_id, -1)
        if frame.stamp_ns <= last:
            # mapped already: a restarted replay, or a link resending after this node restarted
            # from its snapshot, delivers it again (counted, not mapped twice)
            self.repeated_frames += 1
            warn_repeated(logger, self.name, self.repeated_frames, frame.stamp_ns, last,
                          "map/repeated_frames")  # fmt: skip
            return []
        res = mapper.process(frame)
        self.frames += 1
        out: list[Message] = []
        kf = res.keyframe
        if kf is not None:
            arrays = self._keyframe_arrays(mapper, frame, kf)
            out.append(self._keyframe_message("keyframe", self.kf_seq, kf.kf_id, frame, arrays))
            self.kf_seq += 1
        if sample_step(self.params.samples, self.sample_state, frame.T_world_cam, kf is not None):
            color, _, alpha = mapper.render_numpy(  # where the map moved the frame (poses)
                mapper.pose_for(frame.T_world_cam), frame.intrinsics.K, frame.width, frame.height
            )
            arrays = self._training_arrays(mapper, frame, color, alpha)
            sid = FRAME_SAMPLE_ID0 + self.frames - 1
            n = self.sample_state.samples - 1
            out.append(self._keyframe_message("fixer_sample", n, sid, frame, arrays))
        if self.params.input_frames and self.frames >= self.params.input_frames:
            end = self.input_end(frame.stamp_ns)
            if end is not None:
                self.refine_due = True
                out.append(end)
        return out

    def after_input_end(self) -> None:
        """What the end of the input starts, called once its announcement is out (the trainer
        ends its run beside it): the refinement, then ``threads_after_input`` torch threads."""
        if not self.refine_due:
            return
        self.refine_due = False
        self.refine_at_end()
        import torch

        base = self.params.threads or torch.get_num_threads()  # 0: torch's default count
        counts = sorted({base, self.params.threads_after_input})
        if self.params.threads_after_input and len(counts) > 1:
            self.tuner = ThreadTuner(counts)
            logger.info("%s: distillation passes on %s torch threads, by their measured speed",
                        self.name, " or ".join(map(str, counts)))  # fmt: skip

    def refine_at_end(self) -> None:
        """``refine_at_input_end`` refinement steps over the keyframes (see Params)."""
        n = self.params.refine_at_input_end
        if not n or self.mapper is None:
            return
        logger.info("%s: refining the map over its %d keyframes (%d steps) before serving it",
                    self.name, len(self.mapper.store), n)  # fmt: skip
        res = self.mapper.refine(n)
        logger.info("%s: refined, loss %.4f -> %.4f", self.name, res.loss_first, res.loss_last)

    def input_end(self, stamp_ns: int) -> Message | None:
        """The end-of-input announcement, once."""
        if self.input_ended:
            return None
        self.input_ended = True
        meta = {"frames": self.frames, "keyframes": self.kf_seq,
                "samples": self.sample_state.samples}  # fmt: skip
        logger.info("%s: end of the input after %d frames (%d keyframes, %d frame samples)",
                    self.name, self.frames, self.kf_seq, self.sample_state.samples)  # fmt: skip
        return Message(f"input_end/{self.name}", "input_end", 0, stamp_ns, "world", meta)

    def _training_arrays(
        self, mapper: Mapper, frame: Any, render: np.ndarray, alpha: np.ndarray
    ) -> dict[str, np.ndarray]:
        p = self.params
        perturb = Perturbation(p.perturbed_renders, p.perturb_deg, p.perturb_m,
                               p.perturbed_downscale)  # fmt: skip
        return map_arrays(mapper, frame, render, alpha, self.rng, perturb)

    def _keyframe_arrays(self, mapper: Mapper, frame: Any, kf: Keyframe) -> dict[str, np.ndarray]:
        """A keyframe's training arrays, its 3DGS render the one ``keyframe_render`` names (the
        render after the frame where a restored keyframe kept no prior)."""
        assert kf.render is not None and kf.alpha is not None
        arrays = self._training_arrays(mapper, frame, kf.render, kf.alpha)
        if self.params.keyframe_render == "before":
            prior = prior_images(kf, frame.height, frame.width)
            if prior is not None:
                arrays["gs_render"], arrays["gs_alpha"] = rgb8(prior[0]), prior[1]
        return arrays

    def _keyframe_message(
        self, kind: str, seq: int, kid: int, frame: Any, arrays: dict[str, np.ndarray]
    ) -> Message:
        return Message(
            topic=f"{kind}/{self.name}",
            type="keyframe",
            seq=seq,
            stamp_ns=frame.stamp_ns,
            frame_id=frame.frame_id,
            meta={"keyframe_id": int(kid)},
            arrays=arrays,
        )

    def on_render_request(self, msg: Message) -> Message:
        from gsfix_online.core.types import Intrinsics, check_pose

        (w, h), what = render_size(msg, self.params.max_render_pixels), list(msg.meta["what"])
        # the camera's checks (FrameError, one line), as the TSDF node's: a non-rigid pose or a
        # zero focal length rendered garbage, a singular pose failed inside torch
        T_world_cam = check_pose(msg.arrays["T_world_cam"])
        K = Intrinsics.from_K(msg.arrays["K"], w, h).K
        if self.mapper is None:  # nothing mapped yet: an empty map renders black, alpha 0
            color = np.zeros((h, w, 3), np.float32)
            depth = alpha = np.zeros((h, w), np.float32)
        else:
            # a pose in the front end's frame, moved as the map was (mapper.poses; else as is)
            T = self.mapper.pose_for(T_world_cam)
            color, depth, alpha = self.mapper.render_numpy(T, K, w, h)
        images = {"color": rgb8(color), "depth": depth.astype(np.float32), "alpha": alpha}
        if "synthesised" in what:  # what of it distillation grew from repaired views
            images["synthesised"] = (
                np.zeros((h, w), np.float32) if self.mapper is None
                else self.mapper.synthesised_share(T, K, w, h)
            )  # fmt: skip
        if "guessed_depth" in what:  # the map guesses no surface it has not got
            images["guessed_depth"] = np.zeros((h, w), np.float32)
        return Message(
            topic=reply_topic(self.name, msg),
            type="render_reply",
            seq=msg.seq,
            stamp_ns=msg.stamp_ns,
            frame_id=msg.frame_id,
            meta={"request_id": int(msg.meta["request_id"]), "frames": self.frames},
            arrays={k: np.ascontiguousarray(images[k], dtype=images[k].dtype) for k in what},
        )

    def on_repaired_view(self, msg: Message, seconds: Any = None) -> Message:
        """Distil a repaired view, schedule the passes; returns the announcement."""
        import time

        mapper = self._mapper(3)
        if self.tuner is not None:  # not a trial's count, which may be the slow one
            self.tuner.settle()
        view_id = int(msg.meta.get("view_id", -1))
        pose = mapper.pose_for(msg.arrays["T_world_cam"])  # where its 3DGS render was made
        if self.params.kept_keyframes > 0:
            new = [i for i in mapper.observed_ids() if i not in self.kept_before]
            self.kept_before.update(mapper.observed_psnr(new, self.params.kept_downscale))
            for kf_id in mapper.nearest_observed(pose, self.params.kept_keyframes):
                self.kept_near.setdefault(kf_id, view_id)
        region = msg.arrays.get("region")  # the output's provenance: where the mesh saw
        t0 = time.perf_counter()
        res = mapper.distill(
            msg.arrays["color"],
            pose,
            msg.arrays["K"],
            mask=msg.arrays.get("mask"),
            stamp_ns=msg.stamp_ns,
            depth=msg.arrays.get("depth"),
            observed=None if region is None else np.isin(region, MESH_SAW),
        )
        distill_s = time.perf_counter() - t0
        self._log_kept(f"repaired view {view_id}'s own steps")
        self.distilled += 1
        self.last_view_id = view_id
        per_pass = -(-len(mapper.store) // mapper.cfg.refine_views)  # ceil
        if res.loss_first >= self.params.pass_restart_loss:
            self.pass_steps_left = self.params.distill_passes * per_pass
        else:  # nothing to blend in: one pass at least, the round under way goes on
            self.pass_steps_left = max(
                self.pass_steps_left, min(1, self.params.distill_passes) * per_pass
            )
        self.passes_s = 0.0
        logger.info(
            "%s: distilled repaired view %d in %.2f s (loss %.4f -> %.4f); %d pass steps follow",
            self.name, self.last_view_id, distill_s, res.loss_first, res.loss_last,
            self.pass_steps_left,
        )  # fmt: skip
        return self.announcement(msg.stamp_ns, distill_s)

    def distill_passes(self, stamp_ns: int) -> Message | None:
        """One slice of the scheduled passes; the announcement when they are done."""
        import time

        if self.pass_steps_left <= 0 or self.mapper is None:
            return None
        n = min(self.params.pass_slice_steps, self.pass_steps_left)
        t0 = time.perf_counter()
        for _ in range(n):
            if self.tuner is not None:
                self.tuner.next()
            t_step = time.perf_counter()
            self.mapper.refine(1)
            if self.tuner is not None:
                self.tuner.record(time.perf_counter() - t_step)
        self.pass_steps_left -= n
        if self.pass_steps_left == 0:
            self._log_kept("the passes")
        if self.pass_steps_left == 0 and self.mapper.cfg.polish_below_db > 0:
            res = self.mapper.polish()
            if res.refilled:
                logger.info("%s: refilled holes in repaired views %s (%d seeds)", self.name,
                            sorted(res.refilled), sum(res.refilled.values()))  # fmt: skip
            if res.polished:
                logger.info("%s: polished repaired views %s (%d steps): fidelity %s -> %s dB",
                            self.name, res.polished, res.n_iters,
                            [round(res.before[k], 1) for k in res.polished],
                            [round(res.after[k], 1) for k in res.polished])  # fmt: skip
                self._log_kept("polish")
        self.passes_s += time.perf_counter() - t0
        if self.pass_steps_left == 0 and self.tuner is not None and self.tuner.medians:
            logger.info("%s: passes on %d torch threads (s a step by threads: %s)", self.name,
                        self.tuner.chosen, {k: round(v, 3) for k, v in self.tuner.medians.items()})  # fmt: skip
        return self.announcement(stamp_ns) if self.pass_steps_left == 0 else None

    def announcement(self, stamp_ns: int, distill_s: float = 0.0) -> Message:
        self.announced += 1
        return Message(
            topic=f"distill/{self.name}",
            type="map_event",
            seq=self.announced - 1,
            stamp_ns=stamp_ns,
            frame_id="world",
            meta={
                "kind": "distilled",
                "version": self.distilled,
                "step": self.mapper.n_steps if self.mapper is not None else 0,
                "view_id": self.last_view_id,
                "distill_s": distill_s,
                "passes_pending": self.pass_steps_left,
                "passes_s": self.passes_s,
                "gaussians": len(self.mapper.gmap) if self.mapper is not None else 0,
            },
        )

    def write_root(self) -> Path:
        p = self.params
        own = p.export_dir or p.snapshot
        return Path(p.write_root) if p.write_root else Path(own).resolve().parent if own else Path()

    def on_export(self, msg: Message) -> Message:
        if msg.type != "command" or msg.meta["kind"] != "export":
            kind = msg.meta.get("kind", "")
            raise ValueError(f"{msg.topic}: an export request is a command of kind export, "
                             f"got {msg.type} {kind}".rstrip())  # fmt: skip
        name = str(msg.meta.get("path", "") or "")
        target = path_inside(name, self.write_root(), "export path") if name else None
        path = self.export(str(target) if target else None)
        kept = self.keyframes_kept()
        return Message(
            topic=f"export/{self.name}",
            type="map_event",
            seq=msg.seq,
            stamp_ns=msg.stamp_ns,
            frame_id="world",
            meta={
                "kind": "exported",
                "path": str(path or ""),
                "version": self.distilled,
                "step": self.mapper.n_steps if self.mapper is not None else 0,
                **({"keyframes_kept": json.dumps(kept)} if kept else {}),
            },
        )

    def _kept_now(self) -> dict[int, float]:
        """The measured keyframes' render PSNR dB now (those the map still stores)."""
        assert self.mapper is not None
        return self.mapper.observed_psnr(list(self.kept_before), self.params.kept_downscale)

    def _kept_rows(self, now: dict[int, float]) -> list[dict[str, Any]]:
        """``keyframes_kept``'s rows for the measured keyframes' PSNR ``now`` (None: the map
        no longer stores the keyframe)."""
        return [
            {"keyframe_id": kf_id, "view_id": self.kept_near.get(kf_id, -1), "before_db": db,
             "after_db": now.get(kf_id)}
            for kf_id, db in sorted(self.kept_before.items())
        ]  # fmt: skip

    def _log_kept(self, stage: str) -> dict[int, float]:
        """With ``kept_stages``: every measured keyframe's change since it was first measured,
        logged as median and worst after ``stage``, and the same over the repaired views'
        neighbours so far with how many lost over ``KEYFRAME_LOSS_DB`` (the writer's summary,
        :func:`.repair.outputs.keyframes_kept`); returned by keyframe id (else empty)."""
        if not self.params.kept_stages or self.mapper is None or not self.kept_before:
            return {}
        now = self._kept_now()
        change = {k: now[k] - self.kept_before[k] for k in now}
        worst = min(change, key=change.__getitem__)
        kept = summarise_kept(self._kept_rows(now))
        n_near = sum(r["view_id"] >= 0 and r["change_db"] is not None for r in kept["keyframes"])
        logger.info("%s: after %s the %d input keyframes changed by %+.2f dB (median; worst %+.2f,"
                    " keyframe %d); the %d neighbours of repaired views by %+.2f (worst %+.2f; "
                    "%d lost over %.1f dB)", self.name, stage, len(change),
                    float(np.median(list(change.values()))), change[worst], worst, n_near,
                    math.nan if kept["median_change_db"] is None else kept["median_change_db"],
                    math.nan if kept["worst_change_db"] is None else kept["worst_change_db"],
                    len(kept["lost"]), kept["lost_above_db"])  # fmt: skip
        return change

    def keyframes_kept(self) -> list[dict[str, Any]]:
        """Every input keyframe measured before the repaired views (``kept_keyframes``): its
        render's PSNR dB against the frame then and now, and the first repaired view it is a
        neighbour of (-1: none). A keyframe the map no longer stores (a later input keyframe
        evicted it) keeps its row with ``after_db`` None: its change is unknown, not zero."""
        import time

        if self.mapper is None or not self.kept_before:
            return []
        t0 = time.perf_counter()
        rows = self._kept_rows(self._kept_now())
        kept = summarise_kept(rows)
        if kept["median_change_db"] is not None:
            logger.info("%s: the input keyframes nearest the repaired views changed by %+.2f "
                        "dB (median; worst %+.2f) since before the views were distilled; %d "
                        "keyframes measured in %.1f s", self.name, kept["median_change_db"],
                        kept["worst_change_db"], len(rows), time.perf_counter() - t0)  # fmt: skip
        return rows

    def stats_message(self, stamp_ns: int, period_s: float, extra: dict[str, Any]) -> Message:
        meta: dict[str, Any] = {"node": self.name, "period_s": float(period_s)}
        if self.mapper is not None:
            meta.update({f"map/{k}": v for k, v in self.mapper.stats().items()})
        meta["map/distilled"] = self.distilled
        meta["map/repeated_frames"] = self.repeated_frames
        meta.update(extra)
        return Message(topic=f"stats/{self.name}/map", type="stats", stamp_ns=stamp_ns, meta=meta)

    def snapshot(self) -> None:
        if self.params.snapshot and self.mapper is not None:
            save_snapshot(self.mapper, Path(self.params.snapshot))

    def export(self, target: str | None = None) -> Path | None:
        target = target or self.params.export_dir
        if not target or self.mapper is None:
            return None
        from gsfix_online.mapping.splat.ply import CameraEntry, camera_name, save_model
        from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID

        cams = [
            CameraEntry.from_frame(
                kf.kf_id, camera_name(kf.kf_id, kf.frame.frame_id == REPAIRED_FRAME_ID), kf.frame
            )
            for kf in self.mapper.store
        ]
        return save_model(target, self.mapper.gmap, self.mapper.n_steps, cameras=cams)
