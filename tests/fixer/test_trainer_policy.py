"""Tests for gsfix_online/fixer/trainer_policy.py: start, hold-out, early stop, skip, resume."""

from __future__ import annotations

import math

import pytest

from gsfix_online.core.config import ConfigError, build, to_dict
from gsfix_online.fixer.trainer_policy import (
    FinetunePolicy,
    PolicyState,
    after_evaluate,
    after_train_step,
    next_action,
    on_keyframe,
)

POLICY = FinetunePolicy(
    min_keyframes=5, holdout_frac=0.2, eval_every=2, patience=2, max_steps_per_run=100
)


def _feed(state: PolicyState, ids, policy: FinetunePolicy = POLICY) -> list[str]:
    return [on_keyframe(policy, state, i) for i in ids]


def _run(state: PolicyState, losses, policy: FinetunePolicy = POLICY) -> list[tuple]:
    """Drive the policy, answering evaluations with ``losses`` in turn (until they run out)."""
    log, it = [], iter(losses)
    for _ in range(1000):
        action = next_action(policy, state)
        if action == "idle":
            break
        if action == "evaluate":
            loss = next(it, None)
            if loss is None:
                break
            o = after_evaluate(policy, state, loss)
            log.append(("eval", state.steps_in_run, o.save, o.stopped, o.reason))
        else:
            o = after_train_step(policy, state)
            if o.stopped:
                log.append(("stop", state.steps_in_run, o.save, o.reason))
    return log


def test_holdout_share_is_exact_and_stable():
    st = POLICY.initialize_state()
    splits = _feed(st, range(20))
    assert splits.count("holdout") == 4  # 20 * 0.2
    assert splits[4] == "holdout" and splits[0] == "train"
    assert _feed(st, [4]) == ["holdout"]  # a repeated id keeps its split
    assert st.arrivals == 20 and st.new_since_run == 21


def test_waits_for_min_keyframes_then_starts_with_baseline():
    st = POLICY.initialize_state()
    _feed(st, range(4))
    assert next_action(POLICY, st) == "idle" and st.runs == 0
    _feed(st, [4])
    assert next_action(POLICY, st) == "evaluate" and st.runs == 1 and st.new_since_run == 0
    o = after_evaluate(POLICY, st, 1.0)
    assert not o.save and not o.stopped and st.best_loss == 1.0  # the baseline saves nothing
    assert next_action(POLICY, st) == "train"


def test_early_stop_after_patience_and_saves_only_improvements():
    st = POLICY.initialize_state()
    _feed(st, range(5))
    # baseline 1.0, then 0.8 (better: save), 0.9, 0.85 (two without improvement: stop)
    log = _run(st, [1.0, 0.8, 0.9, 0.85])
    assert log == [
        ("eval", 0, False, False, ""),
        ("eval", 2, True, False, ""),
        ("eval", 4, False, False, ""),
        ("eval", 6, False, True, "patience"),
    ]
    assert not st.running and st.last_stop == "patience" and st.best_loss == 0.8


def test_min_rel_improvement():
    pol = FinetunePolicy(
        min_keyframes=5, holdout_frac=0.2, eval_every=1, patience=1, min_rel_improvement=0.1
    )
    st = pol.initialize_state()
    _feed(st, range(5), pol)
    log = _run(st, [1.0, 0.95], pol)  # 5 % better is not 10 % better
    assert log[-1] == ("eval", 1, False, True, "patience")


def test_skip_without_new_keyframes_and_resume_after_new_ones():
    st = POLICY.initialize_state()
    _feed(st, range(5))
    _run(st, [1.0, 1.0, 1.0])
    assert st.runs == 1 and not st.running
    assert next_action(POLICY, st) == "idle"  # nothing new: skip
    assert _run(st, []) == []
    _feed(st, [5])
    steps_before = st.steps_in_run
    log = _run(st, [0.9, 0.7, 0.7, 0.7])
    assert st.runs == 2 and log[0] == ("eval", 0, False, False, "")  # fresh baseline
    assert log[1][2] is True  # the resumed run improves and saves
    assert steps_before == 4


def test_max_steps_stops_and_without_holdout_saves_at_the_end():
    pol = FinetunePolicy(min_keyframes=2, holdout_frac=0.0, max_steps_per_run=3)
    st = pol.initialize_state()
    _feed(st, range(2), pol)
    assert st.holdout_ids == []
    assert _run(st, [], pol) == [("stop", 3, True, "max_steps")]
    pol2 = FinetunePolicy(
        min_keyframes=5, holdout_frac=0.2, eval_every=2, patience=9, max_steps_per_run=4
    )
    st2 = pol2.initialize_state()
    _feed(st2, range(5), pol2)
    log = _run(st2, [1.0, 0.9, 0.8], pol2)
    assert log[-1] == ("eval", 4, True, True, "max_steps")


def test_state_round_trip():
    st = POLICY.initialize_state()
    _feed(st, range(6))
    _run(st, [1.0, 0.5, 0.6])
    back = PolicyState.from_dict(to_dict(st.to_dict()))
    assert back == st
    fresh = POLICY.initialize_state()
    assert PolicyState.from_dict(fresh.to_dict()).best_loss == math.inf


@pytest.mark.parametrize(
    "kw",
    [
        {"holdout_frac": 0.0, "max_steps_per_run": 0},
        {"holdout_frac": 0.1, "min_keyframes": 5},
        {"patience": 0},
    ],
)
def test_invalid_policies(kw):
    with pytest.raises(ConfigError):
        build(FinetunePolicy, base=kw)


def test_quiet_s_holds_a_run_until_keyframes_stop_arriving():
    import dataclasses

    policy = dataclasses.replace(POLICY, quiet_s=10.0)
    st = policy.initialize_state()
    _feed(st, range(8), policy)
    assert next_action(policy, st, quiet_for_s=2.0) == "idle" and st.runs == 0
    assert next_action(policy, st, quiet_for_s=9.99) == "idle"
    assert next_action(policy, st, quiet_for_s=10.0) == "evaluate" and st.runs == 1
    # a run under way goes on whatever arrives
    after_evaluate(policy, st, 1.0)
    _feed(st, [8], policy)
    assert next_action(policy, st, quiet_for_s=0.0) == "train"
    assert next_action(POLICY, POLICY.initialize_state()) == "idle"  # default: no quiet needed


# -- the end of the input: a run on few samples, and the plan ---------------------------------


def test_the_end_of_the_input_starts_a_run_on_few_samples_at_once() -> None:
    from gsfix_online.fixer.trainer_policy import FinetunePolicy, next_action, on_input_end

    pol = FinetunePolicy(min_keyframes=8, holdout_frac=0.5, quiet_s=20.0)
    st = pol.initialize_state()
    for k in range(3):
        on_keyframe(pol, st, k)
    assert next_action(pol, st, quiet_for_s=0.0) == "idle"  # 3 < 8, and not quiet
    plan = on_input_end(pol, st)
    assert plan.will_train and plan.run == 1 and (plan.train, plan.holdout) == (2, 1)
    assert next_action(pol, st, quiet_for_s=0.0) == "evaluate"  # the run's baseline, at once


def test_the_plan_says_why_no_run_will_come() -> None:
    from gsfix_online.fixer.trainer_policy import FinetunePolicy, on_input_end

    pol = FinetunePolicy(min_keyframes=8, holdout_frac=0.2)
    st = pol.initialize_state()
    on_keyframe(pol, st, 0)
    plan = on_input_end(pol, st)
    assert not plan.will_train and plan.run == 0
    assert plan.reason == (
        "only 1 training and 0 held-out samples: a run needs at least 2, one of them held out"
    )


def test_the_plan_names_the_next_run_when_samples_came_during_one() -> None:
    from gsfix_online.fixer.trainer_policy import FinetunePolicy, next_action, on_input_end

    pol = FinetunePolicy(min_keyframes=2, holdout_frac=0.5)
    st = pol.initialize_state()
    for k in range(2):
        on_keyframe(pol, st, k)
    assert next_action(pol, st) == "evaluate" and st.running and st.runs == 1
    on_keyframe(pol, st, 2)  # arrives during run 1
    plan = on_input_end(pol, st)
    assert plan.will_train and plan.run == 2 and "run 2 follows" in plan.reason


# -- background fine-tuning: the run on at the end of the input is the planned one -------------


def test_the_run_on_at_the_end_of_the_input_ends_within_the_stated_steps() -> None:
    from gsfix_online.fixer.trainer_policy import on_input_end

    pol = FinetunePolicy(
        min_keyframes=2, holdout_frac=0.5, eval_every=10, patience=50, steps_after_input_end=25
    )
    st = pol.initialize_state()
    _feed(st, range(2), pol)
    assert next_action(pol, st) == "evaluate" and st.runs == 1
    after_evaluate(pol, st, 1.0)  # the baseline
    for _ in range(7):
        after_train_step(pol, st)
    _feed(st, [2, 3], pol)  # arrive during run 1: its cache holds them
    plan = on_input_end(pol, st)
    # 25 steps rounded up to 3 evaluation periods: the run ends at step 7 + 30
    assert plan.will_train and plan.run == 1 and st.step_cap == 37
    assert (
        plan.reason == "run 1 is on, on all 2 training and 2 held-out samples; it ends by step 37"
    )
    steps, stop = 7, None
    while stop is None:
        if next_action(pol, st) == "evaluate":
            o = after_evaluate(pol, st, 1.0 - steps / 100)  # improving: patience never stops it
        else:
            o = after_train_step(pol, st)
            steps += 1
        stop = o.reason if o.stopped else None
    assert (steps, stop, st.running, st.step_cap) == (37, "max_steps", False, 0)
    assert next_action(pol, st) == "idle"  # no run follows: the samples were the run's


def test_after_a_stop_before_the_end_a_last_short_run_takes_the_new_samples() -> None:
    from gsfix_online.fixer.trainer_policy import on_input_end

    pol = FinetunePolicy(
        min_keyframes=2, holdout_frac=0.5, eval_every=2, patience=1, steps_after_input_end=5
    )
    st = pol.initialize_state()
    _feed(st, range(2), pol)
    log = _run(st, [1.0, 1.0], pol)  # baseline, then no improvement: patience stops run 1
    assert log[-1] == ("eval", 2, False, True, "patience") and not st.running
    _feed(st, [2], pol)
    plan = on_input_end(pol, st)
    assert plan.run == 2 and plan.reason.endswith(
        "starts on 2 training and 1 held-out samples for 6 steps"
    )
    assert next_action(pol, st) == "evaluate" and st.step_cap == 6  # 5 rounded up to 3 evals


def test_without_the_option_a_full_run_follows_on_all_samples() -> None:
    from gsfix_online.fixer.trainer_policy import on_input_end

    pol = FinetunePolicy(min_keyframes=2, holdout_frac=0.5, max_steps_per_run=100)
    st = pol.initialize_state()
    _feed(st, range(2), pol)
    next_action(pol, st)
    _feed(st, [2], pol)
    plan = on_input_end(pol, st)
    assert plan.run == 2 and st.step_cap == 0


def test_a_held_out_keyframe_during_a_run_makes_the_next_evaluation_a_new_baseline() -> None:
    pol = FinetunePolicy(min_keyframes=2, holdout_frac=0.5, eval_every=2, patience=2)
    st = pol.initialize_state()
    _feed(st, range(2), pol)
    assert next_action(pol, st) == "evaluate"
    after_evaluate(pol, st, 0.01)  # the baseline on 1 held-out keyframe: easy
    after_train_step(pol, st)
    after_train_step(pol, st)
    assert after_evaluate(pol, st, 0.009).save  # better on the same set: saved
    assert _feed(st, [2, 3], pol) == ["train", "holdout"]  # the held-out set grows: harder
    after_train_step(pol, st)
    assert next_action(pol, st) == "evaluate" and st.needs_baseline
    o = after_evaluate(pol, st, 0.02)  # the new set's reference, not a loss to beat 0.009 with
    assert (o.save, o.stopped, st.best_loss, st.evals_since_best) == (False, False, 0.02, 0)
    after_train_step(pol, st)
    assert next_action(pol, st) == "evaluate"
    assert after_evaluate(pol, st, 0.018).save  # an improvement on the grown set
    _feed(st, [4], pol)  # a training keyframe: the set is the same, no new baseline
    assert not st.needs_baseline
