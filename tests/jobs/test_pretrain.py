"""Tests for gsfix_online/jobs/pretrain.py: a tiny pretraining run, its scene cache and resume."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from gsfix_online.core.config import build
from gsfix_online.fixer.checkpoint import load_checkpoint
from gsfix_online.fixer.config import FixerConfig, ModelConfig, TrainConfig
from gsfix_online.fixer.loader import load_fixer
from gsfix_online.jobs.pretrain import (
    PretrainConfig,
    PretrainJob,
    is_room_seed,
    load_or_render_scene,
    random_scene_config,
    run_pretrain,
)
from tests.fixer.conftest import tiny_model_cfg

TINY = PretrainConfig(
    scenes=2,
    val_scenes=1,
    frames=2,
    width=48,
    height=32,
    variants=1,
    steps=3,
    eval_every=2,
    save_every=2,
    val_views=2,
    train=TrainConfig(lr=1e-3, batch_size=2, grad_accum=1, crop=8, pool_size=1),
)


def test_random_scenes_differ_and_validate():
    cfgs = [random_scene_config(s, PretrainConfig()) for s in range(6)]
    assert len({(c.tank_length, c.n_web_frames, c.lighting) for c in cfgs}) == 6
    for c in cfgs:
        c.validate()


def test_room_prob_draws_rooms_for_a_share_of_seeds_and_leaves_the_tanks_as_they_were():
    seeds = range(200)
    tanks = [random_scene_config(s, PretrainConfig()) for s in seeds]
    mixed = [random_scene_config(s, PretrainConfig(room_prob=0.3)) for s in seeds]
    rooms = [s for s in seeds if mixed[s].family == "room"]
    assert all(t.family == "tank" for t in tanks)
    assert 40 <= len(rooms) <= 80  # 30 % of 200, binomial spread
    assert rooms == [s for s in seeds if is_room_seed(s, 0.3)]
    # a tank seed draws the same tank whatever the share of rooms; a room seed the same room
    # on every layout attempt's family draw
    assert all(mixed[s] == tanks[s] for s in seeds if s not in rooms)
    for s in rooms[:5]:
        c = mixed[s]
        assert random_scene_config(s, PretrainConfig(room_prob=0.3), attempt=1).family == "room"
        assert 4.5 <= c.room_length <= 8.0 and 3.6 <= c.room_width <= 6.0
        c.validate()
    assert not any(is_room_seed(s, 0.0) for s in seeds)
    assert all(is_room_seed(s, 1.0) for s in seeds)


def test_room_scenes_render_and_cache_under_their_own_name(tmp_path):
    cfg = dataclasses.replace(TINY, room_prob=1.0)
    views = load_or_render_scene(0, cfg, tmp_path)
    assert views.gt.shape == (2, 32, 48, 3) and views.valid.mean() > 0.5
    assert views.gt.std() > 5  # rendered, not blank
    (name,) = [p.name for p in tmp_path.glob("*.npz")]
    assert name.endswith("_room.npz")
    load_or_render_scene(0, TINY, tmp_path)  # the tank of the same seed: its own file
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_tiny_pretrain_then_resume_continues_the_step_count(tmp_path):
    job = PretrainJob(FixerConfig(model=tiny_model_cfg()), TINY)
    res = run_pretrain(job, tmp_path)
    f = res.figures
    assert res.step == 3 and f["steps_this_run"] == 3 and f["resumed_from"] == 0
    assert [h["step"] for h in f["history"]] == [0, 2, 3]
    assert np.isfinite(f["val_loss"]) and np.isfinite(f["psnr_repair_db"])
    assert f["base_checkpoint_mb"] < 20
    assert json.loads((tmp_path / "pretrain.json").read_text())["step"] == 3
    assert len(list((tmp_path / "scenes").glob("*.npz"))) == 2

    # The base is what fixer.model.path points to: weights only, same mode
    base = load_checkpoint(tmp_path / "base")
    assert base.trainer_state is None and base.step == 3
    bundle = load_fixer(dataclasses.replace(tiny_model_cfg(), path=str(tmp_path / "base")))
    assert bundle.model.mode == "mesh+gs"

    # Resume: cached scenes are reused, the step count goes on from the checkpoint
    more = dataclasses.replace(job, pretrain=dataclasses.replace(TINY, steps=5))
    res2 = run_pretrain(more, tmp_path, resume=True)
    assert res2.step == 5 and res2.figures["resumed_from"] == 3
    assert res2.figures["steps_this_run"] == 2
    assert res2.figures["times"]["scenes_s"] < 1.0  # read from the cache, not rendered
    assert load_checkpoint(tmp_path / "checkpoints").trainer_state["step"] == 5


def test_time_limit_ends_a_sitting_that_resume_continues(tmp_path):
    """A sitting stops at its time limit with a resumable checkpoint and a scored base."""
    cfg = dataclasses.replace(TINY, steps=100_000, eval_every=10_000, time_limit_s=1.5)
    res = run_pretrain(PretrainJob(FixerConfig(model=tiny_model_cfg()), cfg), tmp_path)
    f = res.figures
    assert 0 < res.step < 100_000 and f["stopped_by_time_limit"] and f["device"] == "cpu"
    assert 1.5 <= f["times"]["train_s"] < 10
    assert f["history"][-1]["step"] == res.step and np.isfinite(f["psnr_repair_db"])
    assert load_checkpoint(tmp_path / "checkpoints").trainer_state["step"] == res.step
    assert load_checkpoint(tmp_path / "base").step == res.step

    more = dataclasses.replace(cfg, steps=res.step + 2, time_limit_s=0.0)
    res2 = run_pretrain(PretrainJob(FixerConfig(model=tiny_model_cfg()), more), tmp_path, True)
    assert res2.step == res.step + 2 and res2.figures["resumed_from"] == res.step
    assert not res2.figures["stopped_by_time_limit"]


def test_refuses_to_overwrite_without_resume(tmp_path):
    job = PretrainJob(FixerConfig(model=tiny_model_cfg()), dataclasses.replace(TINY, steps=1))
    run_pretrain(job, tmp_path)
    try:
        run_pretrain(job, tmp_path)
    except FileExistsError as exc:
        assert "--resume" in str(exc)
    else:
        raise AssertionError("a second run over existing checkpoints must be refused")


def test_scene_cache_round_trip(tmp_path):
    a = load_or_render_scene(7, TINY, tmp_path)
    b = load_or_render_scene(7, TINY, tmp_path)  # from disk
    assert a.gt.shape == (2, 32, 48, 3) and a.gt.dtype == np.uint8
    np.testing.assert_array_equal(a.gt, b.gt)
    np.testing.assert_array_equal(a.mesh, b.mesh)
    assert a.valid.mean() > 0.9  # inside a closed tank nearly every ray hits
    # another grayscale share draws other gray scenes: its own file, not the cached one
    load_or_render_scene(7, dataclasses.replace(TINY, grayscale_prob=1.0), tmp_path)
    names = sorted(p.name for p in tmp_path.glob("*.npz"))
    assert len(names) == 2 and any("_g1" in n for n in names)


def test_job_config_from_overrides():
    job = build(PretrainJob, overrides=["pretrain.steps=7", "fixer.model.mode=gs"])
    assert job.pretrain.steps == 7 and job.fixer.model == ModelConfig(mode="gs")


def test_install_base_writes_a_flat_checkpoint(tmp_path, monkeypatch):
    from gsfix_online.fixer import sources
    from gsfix_online.jobs.pretrain import install_base

    monkeypatch.setattr(sources, "BASE_CHECKPOINT", tmp_path / "pkg" / "base")
    (tmp_path / "pkg" / "base").mkdir(parents=True)
    (tmp_path / "pkg" / "base" / "stale.txt").write_text("old")
    job = PretrainJob(FixerConfig(model=tiny_model_cfg()), dataclasses.replace(TINY, steps=1))
    res = run_pretrain(job, tmp_path / "run")
    dst = install_base(res.base)
    assert dst == tmp_path / "pkg" / "base"
    assert sorted(p.name for p in dst.iterdir()) == [
        "embedding.safetensors",
        "manifest.json",
        "unet.safetensors",
    ]
    assert load_checkpoint(dst).step == 1
