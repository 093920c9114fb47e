"""The trainer node's component: fine-tunes GSFixer on keyframes in the background and announces checkpoints.

Inputs (exact topic first, then type):

- ``keyframe`` (reliable: every keyframe is training data) -> a triplet ``(I_mesh, I_gs, I_gt)``
  (camera image, splat render, and the latest TSDF mesh ray-cast at the keyframe's pose) goes
  into the latent cache, split into training or held-out per :mod:`gsfix_online.fixer.trainer_policy`.
  With ``keyframe_dir`` set, the keyframe is also written there, so a restarted node has it.
- a ``map_event`` of kind ``mesh_written`` on ``mesh_topic`` (the TSDF node's mesh
  announcements) -> the mesh is read and every keyframe's mesh image is rendered again from it
  (while the input lasts, only as often as ``mesh_share`` allows: the latest one waits).
- ``input_end`` on ``input_end_topic`` (the splat node's end of the input) -> once every keyframe
  and sample it counts has come, the plan is announced as ``trainer_plan`` on
  ``trainer_plan/<node>``.

Between messages the node works in slices of ``steps_per_slice`` optimizer steps (or one
held-out evaluation) as the policy says, then drains its queue again. Why slices and not a worker
thread: the node is its own process, so mapping never waits for it either way; in one thread the
model, the cache and the policy state need no locks, runs are reproducible, and the in-memory
tests drive it message by message. A slice is ~1-2 s with the default model on 2 CPU cores, and
reliable keyframes wait in the queue meanwhile, which is what reliable delivery is for.

Outputs: each checkpoint that improved the held-out loss (or ends a run without a held-out set)
is written atomically with :func:`save_checkpoint` (weights, optimizer, generator and policy
state) and announced as a ``model_checkpoint`` message on ``checkpoint/<node>`` (``path``,
``version`` = checkpoints written, ``step`` = optimizer steps, ``heldout_loss``, ``run``,
``run_done``).
On start the node resumes from ``checkpoint_dir/latest`` when there is one, else it loads
``fixer.model`` (the pretrained base, or random weights). ``stats/<node>`` carries
``trainer/<key>`` counters: keyframes, runs, steps, best held-out loss, last stop reason.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from gsfix_online.core.config import rng
from gsfix_online.core.io import atomic_path, atomic_write_text
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.fixer.trainer_policy import (
    FinetunePolicy,
    Outcome,
    PolicyState,
    after_evaluate,
    after_train_step,
    next_action,
    on_input_end,
    on_keyframe,
    ready,
)
from gsfix_online.repair.ref_warp import RefWarpConfig
from gsfix_online.runtime.wire import Message

logger = logging.getLogger(__name__)

POLICY_FILE = "policy.json"  # the policy state at the end of the last run
_KEYFRAME_ARRAYS = ("color", "depth", "K", "T_world_cam", "gs_render", "gs_alpha")


@dataclass(frozen=True)
class Params:
    fixer: FixerConfig = field(default_factory=FixerConfig)
    policy: FinetunePolicy = field(default_factory=FinetunePolicy)
    checkpoint_dir: str = "outputs/trainer/checkpoints"  # versioned, with `latest`
    keyframe_dir: str = "outputs/trainer/keyframes"  # "" = keep keyframes in memory only
    keep: int = field(default=3, metadata=rng(1, 1000, "checkpoints kept on disk"))
    steps_per_slice: int = field(
        default=1, metadata=rng(1, 1000, "optimizer steps between looks at the queue")
    )
    mesh_topic: str = "mesh/"  # map_event (mesh_written) messages here announce a mesh file
    # A new mesh renders every keyframe's mesh image again. While the input lasts the TSDF
    # node writes one every few seconds, and taking each one kept the demo's trainer encoding
    # until the input ended (27 s of its first 53, 6 meshes) instead of fine-tuning beside the
    # mapping: a mesh is taken only when re-encoding has had at most this share of the time
    # since the last one taken (the latest waiting mesh then; at the end of the input at once)
    mesh_share: float = field(
        default=1.0, metadata=rng(0.01, 1, "most time share for new meshes while input lasts")
    )
    announce: Literal["latest", "reliable"] = "latest"  # delivery of the announcements
    disocclusion_neighbours: int = field(
        default=2, metadata=rng(0, 16, "earlier keyframes whose depth gives disocclusion masks")
    )
    val_batches: int = field(default=2, metadata=rng(1, 100, "held-out micro-batches per eval"))
    stop_after_steps: int = field(
        default=0, metadata=rng(0, None, "exit after this many optimizer steps; 0 = never")
    )
    input_end_topic: str = "input_end/"  # the splat node's end-of-input announcement
    # At the end of a run, GSFixer and the fallbacks (mesh fill + Telea, mesh + Telea) are
    # scored per region on up to this many held-out samples (gsfix_online.repair.fallback);
    # the run's end announces the choice (meta ``fallback``), which the repair node follows.
    fallback_samples: int = field(
        default=8, metadata=rng(0, 1000, "held-out samples for the fallback choice; 0 = off")
    )
    # What picks a run's checkpoint at each evaluation: "loss", the diffusion loss on the
    # held-out latents; "holes", GSFixer's mean squared error (8-bit levels, one codec grid)
    # inside holes cut into both renders of up to ``select_samples`` held-out samples
    # (fallback.measure's neither region), the run's starting weights a candidate too. Not
    # adopted: it ranked a busy demo run's checkpoints right (steps 20, 40, 60: 2025, 2494, 2515;
    # their repairs at the novel views 17.33, 15.98, 15.23 dB, where the loss kept step 60), but
    # on the room (scene seed 1) it kept step 25, whose repairs scored 16.16 dB against 18.21
    # with the loss's, and the output fell under mesh + Telea (17.98 against 18.13 dB)
    # (benchmarks/results/select_holes_cpu.md).
    select_by: Literal["holes", "loss"] = "loss"
    select_samples: int = field(
        default=4, metadata=rng(1, 1000, "held-out samples the holes error is measured on")
    )
    log_every_s: float = field(
        default=30.0, metadata=rng(1, None, "seconds between progress or waiting lines")
    )
    # The CPU share of fine-tuning beside mapping: torch threads, and the process's nice level
    # (added to the one it started with), so that a trainer sharing the cores with the mapping
    # nodes gives way to them
    threads: int = field(default=0, metadata=rng(0, 256, "torch threads; 0 = torch default"))
    nice: int = field(default=0, metadata=rng(0, 19, "raise the node's nice level by this"))
    # Mode mesh+gs+ref: each sample's reference warp, from the *other* training samples warped
    # by the mesh depth at its pose, as the planner warps a view (keep the two configs alike)
    ref_warp: RefWarpConfig = field(default_factory=RefWarpConfig)


@dataclass
class _Keyframe:
    arrays: dict[str, np.ndarray]
    split: str
    # mode mesh+gs+ref: the sample's reference warp ([H, W, 3] uint8, [H, W] bool valid)
    ref: tuple[np.ndarray, np.ndarray] | None = None


class TrainerService:
    """The node's state: model, trainer, latent caches, policy state; handlers return messages."""

    def __init__(
        self, name: str, params: Params, clock: Callable[[], float] = time.monotonic
    ) -> None:
        import torch

        from gsfix_online.fixer.checkpoint import load_checkpoint
        from gsfix_online.fixer.loader import load_fixer
        from gsfix_online.fixer.train import LatentCache, Trainer

        self.name = name
        self.params = params
        self.clock = clock  # monotonic seconds: how long since the last keyframe (policy.quiet_s)
        self.last_keyframe_s = -math.inf
        fx = params.fixer
        self.root = Path(params.checkpoint_dir)
        # 1. Model: resume from our own latest checkpoint, else the configured base
        self.policy_state: PolicyState = params.policy.initialize_state()
        trainer_state = None
        self.version = 0
        if (self.root / "latest").is_file():
            loaded = load_checkpoint(self.root)
            self.bundle = loaded.bundle
            if loaded.trainer_state is not None:
                trainer_state = loaded.trainer_state.get("trainer")
                self.policy_state = PolicyState.from_dict(loaded.trainer_state["policy"])
                self.version = int(loaded.trainer_state.get("version", 0))
            # A run that stopped after this checkpoint recorded its end in policy.json.
            ended = self.root / POLICY_FILE
            if ended.is_file():
                rec = json.loads(ended.read_text())
                if rec.get("version") == self.version:
                    self.policy_state = PolicyState.from_dict(rec["policy"])
            logger.info("%s: resuming from %s (step %d)", name, loaded.path, loaded.step)
        else:
            self.bundle = load_fixer(fx.model)
        self.device = "cuda" if torch.cuda.is_available() else "cpu"
        self.bundle.to(self.device)
        self.trainer = Trainer(
            self.bundle.model, self.bundle.scheduler_config, fx.train, self.device
        )
        if trainer_state is not None:
            self.trainer.load_state_dict(trainer_state)
        # 2. Caches: training (mask-augmented pool) and held-out (clean, one variant)
        fed = self.bundle.model.gs_condition
        self.cache = LatentCache(self.bundle.codec, fx.masks, fx.train.pool_size, fx.train.seed,
                                 device=self.device, gs_condition=fed)  # fmt: skip
        clean = dataclasses.replace(fx.masks, enabled=False)
        self.val_cache = LatentCache(self.bundle.codec, clean, 1, device=self.device,
                                     gs_condition=fed)  # fmt: skip
        self.keyframes: dict[int, _Keyframe] = {}
        self.recent: deque[int] = deque(maxlen=max(params.disocclusion_neighbours, 1))
        self.mesh_renderer: Any = None
        self.mesh_version = -1
        self.mesh_waiting: Message | None = None  # the latest mesh not taken yet (mesh_share)
        self.mesh_next_s = -math.inf  # when the next mesh may be taken while the input lasts
        self.counts = {"keyframes": 0, "evaluations": 0, "checkpoints": 0, "mesh_updates": 0}
        self.outbox: list[Message] = []  # announcements made by handlers, sent by work()
        self.pending_end: Message | None = None  # the end of the input, before all samples came
        self.next_log_s = self.clock() + params.log_every_s
        self.last_loss = float("nan")
        self.last_heldout = float("nan")
        self.last_holes: float | None = None  # holes_error at the last evaluation (select_by)
        self.last_saved: tuple[str, int, float] | None = None  # (path, step, held-out loss)
        # 3. Keyframes written before a restart
        if params.keyframe_dir and Path(params.keyframe_dir).is_dir():
            for f in sorted(Path(params.keyframe_dir).glob("kf_*.npz")):
                with np.load(f) as z:
                    arrays = {k: z[k] for k in (*_KEYFRAME_ARRAYS, "perturbed_alpha") if k in z}
                self._add(int(f.stem[3:]), arrays, restored=True)
            if self.keyframes:
                logger.info("%s: restored %d keyframes from %s", name, len(self.keyframes),
                            params.keyframe_dir)  # fmt: skip

    # -- handlers --------------------------------------------------------------------------

    def on_keyframe(self, msg: Message) -> None:
        from gsfix_online.core.types import Intrinsics, make_frame

        kid = int(msg.meta["keyframe_id"])
        arrays = {
            k: msg.arrays[k] for k in (*_KEYFRAME_ARRAYS, "perturbed_alpha") if k in msg.arrays
        }
        # The frame's checks (rigid pose, intrinsics that fit the image; FrameError, one line)
        # before anything is kept: a keyframe with a singular pose was stored, and failed later
        # in the disocclusion masks of the next keyframe (benchmarks/results/fault_findings.md)
        h, w = arrays["depth"].shape
        frame = make_frame(arrays["color"], arrays["depth"], Intrinsics.from_K(arrays["K"], w, h),
                           arrays["T_world_cam"], msg.stamp_ns)  # fmt: skip
        arrays["depth"] = frame.depth  # NaN, inf and negative depth: 0 (no depth), as for frames
        if self.params.keyframe_dir:
            _write_npz(Path(self.params.keyframe_dir) / f"kf_{kid:08d}.npz", arrays)
        self._add(kid, arrays, restored=False)
        self.last_keyframe_s = self.clock()
        self._end_if_complete()

    def on_map_event(self, msg: Message) -> None:
        """Mesh announcements (kind ``mesh_written`` under ``mesh_topic``); other map events
        are ignored."""
        if msg.meta["kind"] == "mesh_written" and msg.topic.startswith(self.params.mesh_topic):
            self.on_mesh(msg)

    def on_input_end(self, msg: Message) -> None:
        """The input is over (``input_end`` under ``input_end_topic``). Once every keyframe and
        sample it counts has arrived (they come over other links, so possibly after it),
        announce the plan (``trainer_plan/<name>``: the run whose end brings the model for the
        repairs, 0 = none, and why); a run that is due starts at once."""
        if not msg.topic.startswith(self.params.input_end_topic):
            return
        self.pending_end = msg
        self._end_if_complete()

    def _end_if_complete(self) -> None:
        msg = self.pending_end
        if msg is None:
            return
        expected = int(msg.meta["keyframes"]) + int(msg.meta["samples"])
        if len(self.keyframes) < expected:
            return
        self.pending_end = None
        plan = on_input_end(self.params.policy, self.policy_state)
        log = logger.info if plan.will_train else logger.warning
        log("%s: end of the input (%s frames): %s", self.name, msg.meta["frames"],
            plan.reason)  # fmt: skip
        meta = {
            "version": self.version, "step": self.trainer.step, "run": plan.run,
            "will_train": plan.will_train, "reason": plan.reason, "train": plan.train,
            "holdout": plan.holdout, "max_steps": self.params.policy.max_steps_per_run,
        }  # fmt: skip
        self.outbox.append(
            Message(f"trainer_plan/{self.name}", "trainer_plan", 0, msg.stamp_ns, "world", meta)
        )

    def progress_line(self) -> str | None:
        """Every ``log_every_s``: what the trainer does or waits for (None in between)."""
        now = self.clock()
        if now < self.next_log_s:
            return None
        self.next_log_s = now + self.params.log_every_s
        st, pol = self.policy_state, self.params.policy
        if self.pending_end is not None:
            m = self.pending_end.meta
            want = int(m["keyframes"]) + int(m["samples"])
            return f"the input ended: waiting for its last samples ({len(self.keyframes)}/{want})"
        if st.running:
            return (f"run {st.runs}: step {st.steps_in_run}/{pol.max_steps_per_run or 'inf'}, "
                    f"loss {self.last_loss:.4f}, held-out {self.last_heldout:.4f}")  # fmt: skip
        if st.input_ended:
            runs = f"{st.runs} run{'s' if st.runs != 1 else ''}"
            return f"idle after the end of the input ({runs}, last stop {st.last_stop})"
        return (f"waiting for training samples or the end of the input: {st.arrivals} so far "
                f"({len(st.train_ids)} training, {len(st.holdout_ids)} held out; a run needs "
                f"{pol.min_keyframes} and {pol.quiet_s:g} s without a new one)")  # fmt: skip

    def on_mesh(self, msg: Message) -> None:
        """Take a new mesh now, or keep it until :attr:`Params.mesh_share` allows (the last
        one waiting is taken: :meth:`take_waiting_mesh`)."""
        version = int(msg.meta.get("version", self.mesh_version + 1))
        if version == self.mesh_version and self.mesh_renderer is not None:
            return
        self.mesh_waiting = msg
        self.take_waiting_mesh()

    def take_waiting_mesh(self) -> bool:
        """Take the waiting mesh if it is due (always once the input has ended); True if taken."""
        from gsfix_online.mapping.mesh import read_mesh
        from gsfix_online.mapping.mesh_render import MeshRenderer

        msg = self.mesh_waiting
        now = self.clock()
        if msg is None or (not self.policy_state.input_ended and now < self.mesh_next_s):
            return False
        self.mesh_waiting = None
        # a TSDF snapshot may be empty early on; a damaged one is an error
        self.mesh_renderer = MeshRenderer(read_mesh(msg.meta["path"], allow_empty=True))
        self.mesh_version = int(msg.meta.get("version", self.mesh_version + 1))
        self.counts["mesh_updates"] += 1
        for kid, kf in self.keyframes.items():  # same keyframes, better mesh images
            self._encode(kid, kf)
        spent = self.clock() - now
        self.mesh_next_s = now + spent / self.params.mesh_share
        return True

    # -- work between messages -------------------------------------------------------------

    def work(self, stamp_ns: int) -> list[Message]:
        """One slice: an evaluation, or up to ``steps_per_slice`` steps; announcements out."""
        from gsfix_online.fixer.validation import heldout_loss

        pol, st = self.params.policy, self.policy_state
        self.take_waiting_mesh()
        out, self.outbox = self.outbox, []
        for _ in range(self.params.steps_per_slice):
            action = next_action(pol, st, self._quiet_for())
            if action == "idle":
                break
            if action == "evaluate":
                with self.trainer.averaged():  # the weights a checkpoint would hold
                    loss = heldout_loss(
                        self.trainer,
                        self.val_cache,
                        batches=self.params.val_batches,
                        batch_size=self.params.fixer.train.batch_size,
                        crop=self.params.fixer.train.crop,
                    )
                    holes = self.holes_error() if self.params.select_by == "holes" else None
                self.last_heldout, self.last_holes = loss, holes
                self.counts["evaluations"] += 1
                baseline = st.needs_baseline
                outcome = after_evaluate(pol, st, loss if holes is None else holes)
                if baseline and holes is not None and math.isfinite(holes):
                    # the weights the run starts from are a candidate too: a run whose steps
                    # never invent better than them keeps them, not its last weights
                    outcome = dataclasses.replace(outcome, save=True)
            else:
                self.last_loss = self.trainer.fit_step(self.cache).loss
                outcome = after_train_step(pol, st)
            msg = self._after(outcome, stamp_ns)
            if msg is not None:
                out.append(msg)
            if action == "evaluate" or outcome.stopped:
                break  # an evaluation is a slice of its own
        return out

    @property
    def busy(self) -> bool:
        """A run is on, or one would start now."""
        return (
            bool(self.outbox)
            or self.policy_state.running
            or ready(self.params.policy, self.policy_state, self._quiet_for())
        )

    def _quiet_for(self) -> float:
        """Seconds since the last keyframe arrived (inf before any, and after a restart)."""
        return self.clock() - self.last_keyframe_s

    def _after(self, outcome: Outcome, stamp_ns: int) -> Message | None:
        msg = self._save(stamp_ns) if outcome.save else None
        if outcome.stopped and self.last_saved is None:
            # A run that ended before its first evaluation saved nothing; its weights become
            # the run's checkpoint, or a repair node waiting for the run's end waits forever
            msg = self._save(stamp_ns)
        if outcome.stopped and self.last_saved is not None:
            # The run's end, announced with its best (the last saved) checkpoint: a repair node
            # with `checkpoint: run` waits for this one.
            msg = self._announce(stamp_ns, *self.last_saved, run_done=True)
            if self.params.fallback_samples:
                msg.meta["fallback"] = self.measure_fallback().to_json()
        if outcome.stopped:
            # The weights stay those of the best checkpoint; record that the run ended, so a
            # restart does not train the stopped run again.
            rec = {"version": self.version, "policy": self.policy_state.to_dict()}
            self.root.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.root / POLICY_FILE, json.dumps(rec))
            logger.info(
                "%s: run %d stopped (%s) at step %d, best held-out %s %.4f",
                self.name,
                self.policy_state.runs,
                outcome.reason,
                self.trainer.step,
                "holes error" if self.params.select_by == "holes" else "loss",
                self.policy_state.best_loss,
            )
        return msg

    def _save(self, stamp_ns: int) -> Message:
        from gsfix_online.fixer.checkpoint import save_checkpoint

        self.version += 1
        state = {
            "trainer": self.trainer.state_dict(),
            "policy": self.policy_state.to_dict(),
            "version": self.version,
        }
        extra = {"heldout_loss": self.last_heldout, "run": self.policy_state.runs,
                 "heldout_holes_mse": self.last_holes}  # fmt: skip
        # With EMA the checkpoint holds the averaged weights (a resume continues training from
        # them; the average itself resumes from trainer_state).
        with self.trainer.averaged():
            path = save_checkpoint(
                self.root,
                self.bundle,
                self.trainer.step,
                self.params.fixer.model,
                trainer_state=state,
                extra=extra,
                keep=self.params.keep,
            )
        self.counts["checkpoints"] += 1
        self.last_saved = (str(path), self.trainer.step, self.last_heldout)
        return self._announce(stamp_ns, *self.last_saved, run_done=False)

    def _announce(
        self, stamp_ns: int, path: str, step: int, heldout: float, run_done: bool
    ) -> Message:
        return Message(
            topic=f"checkpoint/{self.name}",
            type="model_checkpoint",
            seq=self.version - 1,
            stamp_ns=stamp_ns,
            frame_id="world",
            meta={
                "path": path,
                "version": self.version,
                "step": step,
                "heldout_loss": heldout,
                "run": self.policy_state.runs,
                "mode": self.bundle.model.mode,
                "run_done": run_done,  # the fine-tuning run ended (early stop or step budget)
            },
        )

    def _heldout_samples(self, n: int) -> list[Any]:
        """Up to ``n`` held-out keyframes as HeldOutSamples: the camera image, the 3DGS render
        it came with and the mesh render at its pose now."""
        from gsfix_online.core.types import Intrinsics
        from gsfix_online.repair.fallback import HeldOutSample

        held = [k for k, kf in self.keyframes.items() if kf.split == "holdout"][:n]
        samples = []
        for kid in held:
            a = self.keyframes[kid].arrays
            h, w = a["depth"].shape
            mesh, valid = np.zeros((h, w, 3), np.uint8), np.zeros((h, w), bool)
            if self.mesh_renderer is not None:
                r = self.mesh_renderer.render(a["T_world_cam"], Intrinsics.from_K(a["K"], w, h))
                mesh, valid = _rgb3(r.rgb()), np.asarray(r.valid, bool)
            ref = self.keyframes[kid].ref or (None, None)
            samples.append(HeldOutSample(_rgb3(a["color"]), _rgb3(a["gs_render"]),
                                         a["gs_alpha"].astype(np.float32), mesh, valid,
                                         *ref))  # fmt: skip
        return samples

    def _measure(self, samples: list[Any], cuts: tuple[str, ...], shifts: int = 0) -> Any:
        """fallback.measure of the current weights on ``samples``, holes as the masks of
        training (one random stream from the training seed: the same holes every time); with
        ``shifts`` > 0 the repairs average that many codec grids, not the inference config's."""
        import torch

        from gsfix_online.fixer.config import MODE_CONDITIONS
        from gsfix_online.fixer.inference import repair
        from gsfix_online.fixer.masks import procedural_mask
        from gsfix_online.repair.fallback import measure

        fx = self.params.fixer
        conds = MODE_CONDITIONS[self.bundle.model.mode]
        inference = dataclasses.replace(fx.inference, shifts=shifts) if shifts else fx.inference

        def repair_fn(
            gs: np.ndarray, mesh: np.ndarray, ref: Any = None, ref_valid: Any = None
        ) -> np.ndarray:
            t = _chw01
            kw = {}
            if "ref" in conds:  # no warp: none of its pixels (the mesh render in that slot)
                h, w = gs.shape[:2]
                kw = {"image_ref": t(np.zeros_like(gs) if ref is None else ref),
                      "ref_valid": torch.from_numpy(np.zeros((h, w), bool) if ref_valid is None
                                                    else np.array(ref_valid))[None, None]}  # fmt: skip
            with torch.no_grad():
                res = repair(self.bundle, t(mesh) if "mesh" in conds else None,
                             t(gs) if "gs" in conds else None, inference, **kw)  # fmt: skip
            img = res.images[0].permute(1, 2, 0).numpy()
            return np.rint(np.clip(img, 0, 1) * 255).astype(np.uint8)

        def holes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
            return procedural_mask(rng, h, w, fx.masks)

        return measure(samples, repair_fn, holes, seed=fx.train.seed,
                       alpha_min=fx.masks.alpha_threshold, cuts=cuts,
                       with_ref="ref" in conds)  # fmt: skip

    def holes_error(self) -> float:
        """GSFixer's mean squared error (8-bit levels, over channels) inside holes cut into both
        renders of up to ``select_samples`` held-out samples, with the weights as they are (the
        caller averages them) and one codec grid; inf with no held-out sample or no hole pixel
        (never the best)."""
        samples = self._heldout_samples(self.params.select_samples)
        if not samples:
            return math.inf
        errors = self._measure(samples, ("both",), shifts=1)  # a quarter of the repair's cost
        n = errors.pixels["neither"]
        return errors.sse["neither"]["fixed"] / n if n else math.inf

    def measure_fallback(self) -> Any:
        """Where GSFixer (the weights a checkpoint holds) beats the mesh and OpenCV alone, on
        held-out samples with holes cut in (:func:`gsfix_online.repair.fallback.measure`)."""
        from gsfix_online.repair.fallback import choose, fixer_only

        samples = self._heldout_samples(self.params.fallback_samples)
        if not samples:
            return fixer_only("no held-out samples")
        with self.trainer.averaged():
            errors = self._measure(samples, ("none", "both", "gs", "mesh"))
        choice = choose(errors)
        logger.info("%s: fallback choice per region %s (%s)", self.name, choice.describe(),
                    choice.why)  # fmt: skip
        return choice

    # -- helpers ---------------------------------------------------------------------------

    def _add(self, kid: int, arrays: dict[str, np.ndarray], restored: bool) -> None:
        if restored and kid in self.policy_state.split:
            split = self.policy_state.split[kid]  # seen before the restart: same split
        else:
            split = on_keyframe(self.params.policy, self.policy_state, kid)
        kf = _Keyframe(arrays, split)
        self.keyframes[kid] = kf
        self.counts["keyframes"] = len(self.keyframes)
        self._encode(kid, kf)
        if kid not in self.recent:
            self.recent.append(kid)

    def _encode(self, kid: int, kf: _Keyframe) -> None:
        from gsfix_online.fixer.sample_builder import mesh_render, training_sample
        from gsfix_online.fixer.triplets import to_chw

        a = kf.arrays
        render = None if self.mesh_renderer is None else mesh_render(self.mesh_renderer, a)
        mesh = None if render is None else render.rgb()
        sample = training_sample(a, mesh, self.params.fixer.masks.alpha_threshold,
                                 self._neighbours(kid))  # fmt: skip
        t = sample.triplet
        ref: dict[str, Any] = {}
        if "ref" in self.bundle.model.conditions:
            kf.ref = self._ref_warp(kid, render)
            ref = {"image_ref": to_chw(kf.ref[0]), "ref_valid": kf.ref[1]}
        if kf.split == "holdout":
            self.val_cache.add(kid, t.image_mesh, t.image_gs, t.image_gt, **ref)
        else:
            self.cache.add(kid, t.image_mesh, t.image_gs, t.image_gt, sample.disocclusions,
                           t.alpha_holes, **ref)  # fmt: skip

    def _ref_warp(self, kid: int, render: Any) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``kid``'s reference warp ([H, W, 3] uint8, [H, W] valid): the other training
        samples (never itself, never a held-out one) warped by the mesh depth at its pose, as
        the planner warps a view from the keyframes and samples it keeps. Before a mesh or
        another sample: no pixels."""
        from gsfix_online.repair.ref_warp import ref_warp
        from gsfix_online.repair.references import reference_from_arrays

        a = self.keyframes[kid].arrays
        h, w = a["depth"].shape
        refs = [reference_from_arrays(kf.arrays) for o, kf in self.keyframes.items()
                if o != kid and kf.split != "holdout"]  # fmt: skip
        if render is None or not refs:
            return np.zeros((h, w, 3), np.uint8), np.zeros((h, w), bool)
        warp = ref_warp(a["K"], a["T_world_cam"], render.depth_m, np.asarray(render.valid, bool),
                        w, h, refs, self.params.ref_warp)  # fmt: skip
        return warp.image, warp.valid

    def _neighbours(self, kid: int) -> list[dict[str, np.ndarray]]:
        """The recent keyframes' arrays whose depth, warped into this one, gives disocclusion
        masks (none for a held-out keyframe, which has no masks)."""
        if self.params.disocclusion_neighbours == 0 or self.keyframes[kid].split == "holdout":
            return []
        return [self.keyframes[o].arrays for o in self.recent
                if o != kid and o in self.keyframes]  # fmt: skip

    def stats(self) -> dict[str, Any]:
        st = self.policy_state
        out = {f"trainer/{k}": v for k, v in self.counts.items()}
        out.update(
            {
                "trainer/train_keyframes": len(st.train_ids),
                "trainer/holdout_keyframes": len(st.holdout_ids),
                "trainer/runs": st.runs,
                "trainer/running": st.running,
                "trainer/step": self.trainer.step,
                "trainer/steps_in_run": st.steps_in_run,
                "trainer/loss": self.last_loss,
                "trainer/heldout_loss": self.last_heldout,
                "trainer/best_heldout_loss": st.best_loss if st.running else self.last_heldout,
                "trainer/last_stop": st.last_stop,
                "trainer/version": self.version,
                "trainer/mesh_version": self.mesh_version,
            }
        )
        refs = [kf.ref[1].mean() for kf in self.keyframes.values() if kf.ref is not None]
        if refs:  # mode mesh+gs+ref: the share of the samples' pixels their warps cover
            out["trainer/ref_coverage"] = float(np.mean(refs))
        return out


def _rgb3(im: np.ndarray) -> np.ndarray:  # [H, W] or [H, W, 3] uint8 -> [H, W, 3]
    return np.ascontiguousarray(np.repeat(im[..., None], 3, axis=2) if im.ndim == 2 else im)


def _chw01(im: np.ndarray) -> Any:  # [H, W, 3] uint8 -> [1, 3, H, W] float in [0, 1]
    import torch

    return torch.from_numpy(np.array(im)).permute(2, 0, 1)[None].float() / 255.0


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` atomically (temp file + rename)."""
    with atomic_path(path) as tmp:
        np.savez(tmp, **arrays)
