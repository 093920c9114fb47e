"""Tests for gsfix_online/jobs/map_corpus.py: triplets from a scene's own maps, and pretraining
on them (alone, and as a second stage from given weights)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.core.metrics import psnr
from gsfix_online.fixer.checkpoint import load_checkpoint, save_checkpoint
from gsfix_online.fixer.config import FixerConfig, TrainConfig
from gsfix_online.fixer.sources import build_default
from gsfix_online.jobs import map_corpus
from gsfix_online.jobs.map_corpus import (
    MapCorpusConfig,
    build_map_triplets,
    load_or_build_map_triplets,
    map_views,
    scene_config,
)
from gsfix_online.jobs.pretrain import PretrainConfig, PretrainJob, run_pretrain
from tests.fixer.conftest import tiny_model_cfg

W, H = 64, 48
SMALL = MapCorpusConfig(views=2, frames=12, refine=4, voxel_size=0.04, drift_prob=0.0, holdout=4)


@pytest.fixture(scope="module")
def triplets():  # 2 novel views, then held-out frames 1, 5 and 9
    return build_map_triplets(3, W, H, 0.0, SMALL)


def test_triplets_are_the_scene_maps_at_its_novel_views(triplets):
    t = triplets
    assert len(t) == 5 and not t.drift
    for a in (t.gt, t.mesh, t.gs):
        assert a.shape == (5, H, W, 3) and a.dtype == np.uint8
    assert t.alpha.shape == t.valid.shape == (5, H, W)
    for v in range(2):
        valid = t.valid[v]
        # novel views: the maps cover part of the view, not all of it (30-85 % was seen)
        assert 0.1 < valid.mean() < 0.99 and 0.1 < (t.alpha[v] > 127).mean() < 0.99
        assert (t.mesh[v][~valid] == 0).all()  # nothing hit: black, as a repair receives it
        # the mesh render shows the same scene: close to ground truth where it was hit, and far
        # closer than a shuffled image
        same = psnr(t.mesh[v], t.gt[v], valid)
        other = psnr(t.mesh[v], t.gt[1 - v], valid)
        assert same > 14.0 and same > other + 2.0
        # the 3DGS render: covered where its alpha is high, black over background elsewhere
        seen = t.alpha[v] > 200
        assert seen.mean() > 0.1 and psnr(t.gs[v], t.gt[v], seen) > 12.0
        assert t.gs[v][t.alpha[v] < 3].max(initial=0) <= 3


def test_drifting_scenes_map_at_estimated_poses():
    cfg = dataclasses.replace(SMALL, drift_prob=1.0)
    c = scene_config(3, W, H, 0.0, cfg)
    assert c.pose_drift > 0 and c.n_novel == 2 and c.n_frames == 12
    assert scene_config(3, W, H, 0.0, SMALL).pose_drift == 0  # drift_prob 0: exact poses


def test_room_seeds_map_a_room():
    from gsfix_online.jobs.pretrain import is_room_seed

    room = next(s for s in range(100) if is_room_seed(s, 0.3))
    tank = next(s for s in range(100) if not is_room_seed(s, 0.3))
    c = scene_config(room, W, H, 0.0, SMALL, room_prob=0.3)
    assert c.family == "room" and c.n_novel == 2 and c.n_frames == 12
    assert scene_config(tank, W, H, 0.0, SMALL, room_prob=0.3) == scene_config(
        tank, W, H, 0.0, SMALL
    )


def test_cache_round_trip_builds_each_scene_once(tmp_path, monkeypatch, triplets):
    calls = []

    def build(seed, *args, **kwargs):
        calls.append(seed)
        return triplets

    monkeypatch.setattr(map_corpus, "build_map_triplets", build)
    a = load_or_build_map_triplets(3, W, H, 0.0, SMALL, tmp_path)
    b = load_or_build_map_triplets(3, W, H, 0.0, SMALL, tmp_path)
    assert calls == [3] and len(list(tmp_path.glob("maps_v1_*.npz"))) == 1
    for k in ("gt", "mesh", "gs", "alpha", "valid", "heldout"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    # another corpus config is another file
    load_or_build_map_triplets(3, W, H, 0.0, dataclasses.replace(SMALL, refine=5), tmp_path)
    assert calls == [3, 3]
    other = dataclasses.replace(SMALL.mapper, kf_iters=SMALL.mapper.kf_iters + 1)
    load_or_build_map_triplets(3, W, H, 0.0, dataclasses.replace(SMALL, mapper=other), tmp_path)
    assert calls == [3, 3, 3]
    # a corpus with rooms: another file, the room share passed on to the builder
    seen = []
    monkeypatch.setattr(
        map_corpus, "build_map_triplets", lambda *a, **k: seen.append(k["room_prob"]) or triplets
    )
    load_or_build_map_triplets(3, W, H, 0.0, SMALL, tmp_path, room_prob=0.3)  # a tank seed
    assert seen == []  # the tank's file serves, whatever the share of rooms
    load_or_build_map_triplets(1, W, H, 0.0, SMALL, tmp_path, room_prob=0.3)  # a room seed
    assert seen == [0.3] and len(list(tmp_path.glob("maps_v1_000001_*_room_*.npz"))) == 1


def test_map_views_are_float_chw(triplets):
    views = map_views(triplets)
    assert len(views) == len(triplets)
    mesh, gs, gt, alpha = views[0]
    assert mesh.shape == gs.shape == gt.shape == (3, H, W) and alpha.shape == (H, W)
    assert float(gt.max()) <= 1.0 and float(alpha.min()) >= 0.0
    np.testing.assert_allclose(gt.permute(1, 2, 0).numpy() * 255, triplets.gt[0], atol=1e-3)


def test_pretrain_on_maps_alone_from_given_weights(tmp_path, monkeypatch, triplets):
    """variants=0 trains on the map triplets only; init starts from the weights given; the
    held-out scene's map views are repaired and scored."""
    monkeypatch.setattr(map_corpus, "build_map_triplets", lambda *a, **k: triplets)
    fx = FixerConfig(model=tiny_model_cfg())
    start = build_default(fx.model)
    with torch.no_grad():
        for p in start.model.parameters():
            p.add_(0.01)  # not the random init build_default gives
    init = save_checkpoint(tmp_path / "init", start, 0, fx.model, keep=1)
    cfg = PretrainConfig(
        scenes=2, val_scenes=1, width=W, height=H, variants=0, steps=1, eval_every=1,
        val_views=0, init=str(init), maps=dataclasses.replace(SMALL, weight=3),
        train=TrainConfig(lr=0.0, batch_size=2, grad_accum=1, crop=8, pool_size=1),
    )  # fmt: skip
    res = run_pretrain(PretrainJob(fx, cfg), tmp_path / "run")
    f = res.figures
    assert f["map_scenes"] == 2 and f["train_entries"] == 1 * 5 * 3  # 1 scene x 5 views x 3
    assert not (tmp_path / "run" / "scenes").exists()  # no synthetic scenes rendered
    mv = f["map_views"]
    assert mv["views"] == 5 and all(np.isfinite(mv[k]) for k in mv)
    # lr 0: the exported base holds the init weights
    base = load_checkpoint(res.base).bundle
    for (n, p), q in zip(base.model.named_parameters(), start.model.parameters(), strict=True):
        torch.testing.assert_close(p.float(), q, atol=2e-3, rtol=1e-3, msg=n)


def test_no_triplets_at_all_is_refused():
    with pytest.raises(ValueError, match="no triplets"):
        PretrainConfig(variants=0).validate()


def test_held_out_frames_are_views_on_the_trajectory_the_maps_render_well(triplets):
    t = triplets
    assert t.heldout is not None and t.heldout.tolist() == [False] * 2 + [True] * 3  # 1, 5, 9
    novel, held = ~t.heldout, t.heldout
    # on the trajectory the maps cover more and render closer to ground truth than off it
    assert t.valid[held].mean() > t.valid[novel].mean()
    gs_db = np.array([psnr(t.gs[v], t.gt[v]) for v in range(len(t))])
    assert np.median(gs_db[held]) > np.median(gs_db[novel]) + 3.0


def test_corpus_builds_missing_scenes_in_worker_processes(tmp_path, triplets):
    cfg = dataclasses.replace(SMALL, workers=2)
    calls = []
    corpus = map_corpus.load_or_build_corpus(
        [3, 5], W, H, 0.0, cfg, tmp_path, progress=lambda *a: calls.append(a)
    )
    assert [t.seed for t in corpus] == [3, 5]
    assert len(list(tmp_path.glob("maps_v1_*.npz"))) == 2
    assert calls[0][:2] == (0, 2) and "2 processes" in calls[0][2]
    assert sorted(c[0] for c in calls[1:]) == [1, 2] and {c[1] for c in calls} == {2}
    # a worker on one thread maps the scene as this process does
    for k in ("gt", "mesh", "valid", "heldout"):
        np.testing.assert_array_equal(getattr(corpus[0], k), getattr(triplets, k))
    for k in ("gs", "alpha"):
        diff = np.abs(getattr(corpus[0], k).astype(int) - getattr(triplets, k).astype(int))
        assert diff.mean() < 0.5, k
    # cached now: nothing to build, no processes
    calls.clear()
    again = map_corpus.load_or_build_corpus(
        [5, 3], W, H, 0.0, cfg, tmp_path, progress=lambda *a: calls.append(a)
    )
    assert calls == [] and [t.seed for t in again] == [5, 3]
    np.testing.assert_array_equal(again[1].gs, corpus[0].gs)
