"""When the background trainer fine-tunes GSFixer: frozen parameters plus explicit state.

The policy (gsplat ``DefaultStrategy`` style: config dataclass, ``initialize_state()``, pure
step functions that mutate only the state passed in):

- keyframes are split as they arrive: keyframe n (0-based, in arrival order) is held out when
  ``floor((n + 1) * holdout_frac) > floor(n * holdout_frac)``, so the held-out share is
  ``holdout_frac`` at every count and the split never changes for a keyframe already seen;
- a *run* starts once ``min_keyframes`` have arrived, at least one of them held out, and at least
  ``min_new_keyframes`` arrived since the last run started (no new keyframes: skip, nothing to
  learn that the last run did not);
- a run begins with a baseline evaluation of the held-out loss (the held-out set may have grown,
  so older figures are not comparable), then trains and evaluates every ``eval_every`` steps;
  an evaluation below ``best * (1 - min_rel_improvement)`` is an improvement (the caller saves a
  checkpoint); ``patience`` evaluations without one stop the run (early stop), as does
  ``max_steps_per_run``;
- keyframes arriving after a stop start the next run, which resumes from the current weights;
- once the input has ended (:func:`on_input_end`: an offline log is mapped), a run starts at
  once, on as few as ``min_keyframes_at_end`` samples, and :func:`plan` says which run ends
  with the model that repairs the views, or why there is none;
- background fine-tuning (``quiet_s`` 0, ``steps_after_input_end`` > 0): runs follow each other
  while the input is mapped, each on every sample that has arrived; the run on when the input
  ends is the planned one and ends within ``steps_after_input_end`` more steps.

Nothing here reads a clock, touches torch or does IO; the trainer node calls these functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng

Split = Literal["train", "holdout"]
Action = Literal["idle", "evaluate", "train"]
StopReason = Literal["", "patience", "max_steps"]


@dataclass(frozen=True)
class FinetunePolicy:
    """Parameters of the background fine-tuning schedule (all counts in keyframes or steps)."""

    min_keyframes: int = field(
        default=8, metadata=rng(1, None, "keyframes (train + held out) before the first run")
    )
    min_new_keyframes: int = field(
        default=1, metadata=rng(1, None, "new keyframes since the last run to start another")
    )
    holdout_frac: float = field(
        default=0.2, metadata=rng(0, 0.9, "share of keyframes held out for early stopping")
    )
    eval_every: int = field(default=20, metadata=rng(1, None, "optimizer steps between evals"))
    patience: int = field(
        default=3, metadata=rng(1, None, "evaluations without improvement before a stop")
    )
    min_rel_improvement: float = field(
        default=0.01, metadata=rng(0, 1, "relative held-out loss drop that counts as better")
    )
    max_steps_per_run: int = field(
        default=600, metadata=rng(0, None, "stop a run after this many steps; 0 = no limit")
    )
    # A run starts only once no keyframe has arrived for this long: while a robot pauses, or
    # when a replayed log has ended, so that the run trains on the whole keyframe set.
    quiet_s: float = field(
        default=0.0, metadata=rng(0, None, "seconds without a new keyframe before a run; 0 = any")
    )

    min_keyframes_at_end: int = field(
        default=2,
        metadata=rng(2, None, "samples (train + held out) for a run once the input ended"),
    )
    # Background fine-tuning (quiet_s 0): a run trains on every sample that has arrived, those
    # that came during it too, so at the end of the input it need not be followed by a new run
    # on all samples. With this > 0, the run that is on when the input ends (or, if none is, a
    # last run on the samples that came since the last one) ends within this many more steps,
    # rounded up to an evaluation; it is the run the plan names, and no run follows it.
    # 0: the run that follows on all samples is a full one (up to max_steps_per_run).
    steps_after_input_end: int = field(
        default=0, metadata=rng(0, None, "once the input ended: the planned run's last steps")
    )

    def validate(self) -> None:
        if self.holdout_frac == 0 and self.max_steps_per_run == 0:
            raise ValueError(
                "with holdout_frac 0 there is no early stop: max_steps_per_run must be > 0"
            )
        if self.holdout_frac > 0 and self.min_keyframes * self.holdout_frac < 1:
            need = math.ceil(1 / self.holdout_frac)
            raise ValueError(
                f"min_keyframes {self.min_keyframes} holds out no keyframe at holdout_frac "
                f"{self.holdout_frac}: use min_keyframes >= {need}"
            )

    def initialize_state(self) -> PolicyState:
        return PolicyState()


@dataclass
class PolicyState:
    """Everything the policy remembers; plain values, so it checkpoints as a dict."""

    split: dict[int, str] = field(default_factory=dict)  # keyframe id -> "train" | "holdout"
    arrivals: int = 0  # distinct keyframes seen
    new_since_run: int = 0  # keyframes (new or updated) since the last run started
    running: bool = False
    needs_baseline: bool = False  # the run's first action is an evaluation
    eval_due: bool = False  # an evaluation is owed at this step
    steps_in_run: int = 0
    best_loss: float = math.inf  # best held-out loss of the current run
    evals_since_best: int = 0
    runs: int = 0  # runs started
    last_stop: StopReason = ""
    input_ended: bool = False  # the input is over: no more samples will come
    step_cap: int = 0  # the current run stops at this step (steps_after_input_end); 0 = none

    @property
    def train_ids(self) -> list[int]:
        return [k for k, s in self.split.items() if s == "train"]

    @property
    def holdout_ids(self) -> list[int]:
        return [k for k, s in self.split.items() if s == "holdout"]

    def to_dict(self) -> dict[str, object]:
        d = dict(self.__dict__)
        d["split"] = {str(k): v for k, v in self.split.items()}
        d["best_loss"] = None if math.isinf(self.best_loss) else self.best_loss
        return d

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> PolicyState:
        d = dict(d)
        d["split"] = {int(k): str(v) for k, v in d["split"].items()}  # type: ignore[union-attr]
        d["best_loss"] = math.inf if d["best_loss"] is None else float(d["best_loss"])  # type: ignore[arg-type]
        return cls(**d)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Outcome:
    save: bool  # the weights are the run's best so far (or its end, without a held-out set)
    stopped: bool  # the run ended here
    reason: StopReason


def on_keyframe(policy: FinetunePolicy, state: PolicyState, keyframe_id: int) -> Split:
    """Record a keyframe (a repeated id keeps its split and counts as new data). A held-out
    keyframe that arrives during a run changes the set its evaluations average over, so the
    run's next evaluation is a new baseline: losses on different sets are not comparable (a
    run that kept the best loss of a 2-keyframe set stopped on patience against the harder
    10-keyframe set, with nothing saved)."""
    if keyframe_id not in state.split:
        n = state.arrivals
        f = policy.holdout_frac
        held = math.floor((n + 1) * f) > math.floor(n * f)
        state.split[keyframe_id] = "holdout" if held else "train"
        state.arrivals += 1
        if held and state.running:
            state.needs_baseline = True
    state.new_since_run += 1
    return state.split[keyframe_id]  # type: ignore[return-value]


def ready(policy: FinetunePolicy, state: PolicyState, quiet_for_s: float = math.inf) -> bool:
    """Whether a new run may start now, ``quiet_for_s`` after the last keyframe arrived (at
    once, and on fewer samples, after the end of the input)."""
    has_holdout = bool(state.holdout_ids) or policy.holdout_frac == 0
    need = policy.min_keyframes_at_end if state.input_ended else policy.min_keyframes
    return (
        (state.input_ended or quiet_for_s >= policy.quiet_s)
        and state.arrivals >= min(need, policy.min_keyframes)
        and has_holdout
        and bool(state.train_ids)
        and state.new_since_run >= policy.min_new_keyframes
    )


@dataclass(frozen=True)
class Plan:
    """What the trainer will do about the input it has: the run whose end brings the model
    that repairs the views (0: none), and why."""

    run: int
    will_train: bool  # that run has yet to end
    reason: str
    train: int
    holdout: int


def on_input_end(policy: FinetunePolicy, state: PolicyState) -> Plan:
    """Record that the input ended; returns the plan (see :class:`Plan`)."""
    state.input_ended = True
    k = policy.steps_after_input_end
    if k and state.running:  # the run on now has every sample: it ends within k steps
        state.step_cap = state.steps_in_run + _to_eval(policy, k)
        state.new_since_run = 0
    return plan(policy, state)


def _to_eval(policy: FinetunePolicy, steps: int) -> int:
    """``steps`` rounded up to a whole number of evaluation periods (with a held-out set)."""
    if policy.holdout_frac == 0:
        return steps
    return math.ceil(steps / policy.eval_every) * policy.eval_every


def plan(policy: FinetunePolicy, state: PolicyState) -> Plan:
    n_train, n_hold = len(state.train_ids), len(state.holdout_ids)
    counts = f"{n_train} training and {n_hold} held-out samples"
    new = state.new_since_run >= policy.min_new_keyframes
    if state.running:
        if state.step_cap:
            return Plan(state.runs, True, f"run {state.runs} is on, on all {counts}; it ends "
                        f"by step {state.step_cap}", n_train, n_hold)  # fmt: skip
        if new:
            return Plan(state.runs + 1, True, f"run {state.runs} is on; run {state.runs + 1} "
                        f"follows on all {counts}", n_train, n_hold)  # fmt: skip
        return Plan(state.runs, True, f"run {state.runs} is on, on {counts}", n_train, n_hold)
    if ready(policy, state):
        last = ""
        if state.input_ended and policy.steps_after_input_end:
            last = f" for {_to_eval(policy, policy.steps_after_input_end)} steps"
        return Plan(state.runs + 1, True, f"run {state.runs + 1} starts on {counts}{last}",
                    n_train, n_hold)  # fmt: skip
    if state.runs and not new:
        return Plan(state.runs, False, f"no new samples since run {state.runs}: its model "
                    "stands", n_train, n_hold)  # fmt: skip
    need = min(policy.min_keyframes_at_end, policy.min_keyframes)
    why = f"only {counts}: a run needs at least {need}"
    if policy.holdout_frac > 0:
        why += ", one of them held out"
    return Plan(state.runs, False, why, n_train, n_hold)


def next_action(
    policy: FinetunePolicy, state: PolicyState, quiet_for_s: float = math.inf
) -> Action:
    """What to do now; starts a run when one is due (see :func:`ready`). Call once per slice."""
    if not state.running:
        if not ready(policy, state, quiet_for_s):
            return "idle"
        state.running = True
        state.needs_baseline = policy.holdout_frac > 0
        state.steps_in_run = 0
        state.best_loss = math.inf
        state.evals_since_best = 0
        state.new_since_run = 0
        state.runs += 1
        state.last_stop = ""
        k = policy.steps_after_input_end if state.input_ended else 0
        state.step_cap = _to_eval(policy, k) if k else 0
    return "evaluate" if state.needs_baseline or state.eval_due else "train"


def after_train_step(policy: FinetunePolicy, state: PolicyState) -> Outcome:
    """Count one optimizer step; an evaluation falls due every ``eval_every`` steps."""
    assert state.running, "after_train_step outside a run"
    state.steps_in_run += 1
    if policy.holdout_frac > 0 and state.steps_in_run % policy.eval_every == 0:
        state.eval_due = True  # the evaluation decides about the step limit too
        return Outcome(False, False, "")
    if _at_limit(policy, state):
        _stop(state, "max_steps")
        # Without a held-out set the end of the run is the only point worth saving.
        return Outcome(policy.holdout_frac == 0, True, "max_steps")
    return Outcome(False, False, "")


def after_evaluate(policy: FinetunePolicy, state: PolicyState, heldout_loss: float) -> Outcome:
    """Record a held-out loss; says whether it improved (save) and whether the run stopped."""
    assert state.running, "after_evaluate outside a run"
    state.eval_due = False
    if state.needs_baseline:  # the weights now, on the held-out set now: a reference
        state.needs_baseline = False
        state.best_loss = heldout_loss
        state.evals_since_best = 0
        if _at_limit(policy, state):  # a baseline that fell on the last step
            _stop(state, "max_steps")
            return Outcome(False, True, "max_steps")
        return Outcome(False, False, "")
    improved = heldout_loss < state.best_loss * (1 - policy.min_rel_improvement)
    if improved:
        state.best_loss = heldout_loss
        state.evals_since_best = 0
    else:
        state.evals_since_best += 1
    if state.evals_since_best >= policy.patience:
        _stop(state, "patience")
        return Outcome(improved, True, "patience")
    if _at_limit(policy, state):
        _stop(state, "max_steps")
        return Outcome(improved, True, "max_steps")
    return Outcome(improved, False, "")


def _at_limit(policy: FinetunePolicy, state: PolicyState) -> bool:
    """The run has made its ``max_steps_per_run`` steps, or reached its step cap."""
    n = state.steps_in_run
    return bool(policy.max_steps_per_run and n >= policy.max_steps_per_run) or bool(
        state.step_cap and n >= state.step_cap
    )


def _stop(state: PolicyState, reason: StopReason) -> None:
    state.step_cap = 0
    state.running = False
    state.needs_baseline = False
    state.eval_due = False
    state.last_stop = reason
