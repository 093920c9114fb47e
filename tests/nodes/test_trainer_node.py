"""Tests for nodes/trainer.py on the in-memory transport: keyframes in, checkpoints out, restart."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from gsfix_online.nodes import trainer as trainer_node

from gsfix_online.core.config import build
from gsfix_online.fixer.checkpoint import load_checkpoint
from gsfix_online.fixer.config import FixerConfig, TrainConfig
from gsfix_online.fixer.trainer_policy import FinetunePolicy
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig
from tests.fixer.conftest import tiny_model_cfg

H, W = 32, 48
K = np.array([[40.0, 0, (W - 1) / 2], [0, 40.0, (H - 1) / 2], [0, 0, 1]])


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny models: threads only contend (see tests/fixer/conftest.py)
    yield
    torch.set_num_threads(n)


def _params(tmp_path, **kw) -> trainer_node.Params:
    fixer = FixerConfig(
        model=tiny_model_cfg(),
        train=TrainConfig(lr=3e-3, batch_size=2, grad_accum=1, crop=0, pool_size=2),
    )
    policy = FinetunePolicy(
        min_keyframes=5, holdout_frac=0.2, eval_every=2, patience=2, max_steps_per_run=6
    )
    base = dict(
        fixer=fixer,
        policy=policy,
        checkpoint_dir=str(tmp_path / "ckpt"),
        keyframe_dir=str(tmp_path / "kf"),
        val_batches=1,
        steps_per_slice=2,
    )
    return trainer_node.Params(**{**base, **kw})


def _keyframe(i: int) -> Message:
    rng = np.random.default_rng(i)
    yy, xx = np.mgrid[0:H, 0:W]
    base = 0.5 + 0.4 * np.sin(xx / (3 + i) + yy / 5)[..., None] * rng.uniform(0.5, 1, 3)
    color = np.clip(base * 255, 0, 255).astype(np.uint8)
    alpha = np.ones((H, W), np.float32)
    alpha[5:15, 10 + i : 25 + i] = 0.0
    gs = np.clip(base + rng.normal(0, 0.05, base.shape), 0, 1) * alpha[..., None]
    T = np.eye(4)
    T[0, 3] = 0.05 * i
    return Message(
        topic="keyframe/splat",
        type="keyframe",
        seq=i,
        stamp_ns=i,
        frame_id="camera",
        meta={"keyframe_id": i},
        arrays={
            "color": color,
            "depth": np.full((H, W), 2.0, np.float32),
            "K": K,
            "T_world_cam": T,
            "gs_render": (gs * 255).astype(np.uint8),
            "gs_alpha": alpha,
        },
    )


def _drive(node, service, params, max_slices: int = 100) -> None:
    for _ in range(max_slices):
        if not trainer_node.step(node, service, params) and not node.transport.inbox:
            return
    raise AssertionError("the trainer never went idle")


def _checkpoints(transport: InMemoryTransport) -> list[Message]:
    return [m for m in transport.published if m.type == "model_checkpoint"]


def test_keyframes_in_checkpoints_out_and_restart_resumes(tmp_path):
    params = _params(tmp_path)
    t = InMemoryTransport(script=[_keyframe(i) for i in range(4)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert svc.trainer.step == 0 and not _checkpoints(t)  # 4 < min_keyframes: waits

    t.feed(_keyframe(4))
    _drive(node, svc, params)
    st = svc.policy_state
    assert st.runs == 1 and not st.running and st.last_stop in ("patience", "max_steps")
    assert len(st.holdout_ids) == 1 and len(svc.val_cache) == 1 and len(svc.cache) == 4
    ckpts = _checkpoints(t)
    assert ckpts, "no held-out improvement in a run of tiny steps"
    versions = [m.meta["version"] for m in ckpts]
    assert sorted(set(versions)) == list(range(1, max(versions) + 1)) and versions == sorted(
        versions
    )
    # The run's end is announced once, last, with its best (the last saved) checkpoint
    assert [m.meta["run_done"] for m in ckpts] == [False] * (len(ckpts) - 1) + [True]
    assert all(m.topic == "checkpoint/trainer" for m in ckpts)
    last = load_checkpoint(tmp_path / "ckpt")
    assert last.step == ckpts[-1].meta["step"] and str(last.path) == ckpts[-1].meta["path"]
    steps_done = svc.trainer.step

    # Nothing new: the policy skips, nothing is published (but the node's heartbeat, due once
    # a second: on a loaded machine the run above can take that long)
    def published() -> list:
        return [p for p in t.outbox if p.message.type != "heartbeat"]

    n_out = len(published())
    _drive(node, svc, params)
    assert svc.trainer.step == steps_done and len(published()) == n_out

    # Restart (as after a crash): weights, step, policy and keyframes come back from disk
    t2 = InMemoryTransport()
    node2, svc2 = trainer_node.build_node("trainer", params, t2, NodeRuntimeConfig())
    assert svc2.trainer.step == last.step and svc2.version == ckpts[-1].meta["version"]
    assert svc2.policy_state.runs == 1 and len(svc2.keyframes) == 5
    assert len(svc2.cache) == 4 and len(svc2.val_cache) == 1
    _drive(node2, svc2, params)
    assert svc2.trainer.step == last.step  # no new keyframes since: still skipped
    t2.feed(_keyframe(5))
    _drive(node2, svc2, params)
    assert svc2.policy_state.runs == 2 and svc2.trainer.step > last.step  # resumed
    for m in _checkpoints(t2):
        assert m.meta["version"] > ckpts[-1].meta["version"]


def test_mesh_announcement_renders_mesh_conditions(tmp_path):
    params = _params(tmp_path, keyframe_dir="")
    # A plane at z = 2 m in front of every keyframe camera, mid-gray
    v = np.array([[-5, -5, 2], [5, -5, 2], [5, 5, 2], [-5, 5, 2]], np.float32)
    mesh = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.full((4, 3), 128, np.uint8))
    path = write_mesh(mesh, tmp_path / "mesh.ply")
    meta = {"kind": "mesh_written", "path": str(path), "version": 1, "step": 3,
            "files": [str(path)], "vertices": 4, "triangles": 2}  # fmt: skip
    announce = Message(topic="mesh/tsdf", type="map_event", meta=meta)
    t = InMemoryTransport(script=[_keyframe(0), announce, _keyframe(1)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert svc.counts["mesh_updates"] == 1 and svc.mesh_version == 1
    for key in (0, 1):  # keyframe 0 re-rendered at the announcement, 1 rendered on arrival
        z_mesh = svc.cache._entries[key].z_mesh.float()
        # mesh image 128/255 -> model range ~0.004; masked pixels 0 -> -1
        assert (z_mesh.abs() < 0.01).float().mean() > 0.3
    stats = svc.stats()
    assert stats["trainer/keyframes"] == 2 and stats["trainer/mesh_version"] == 1


def test_while_the_input_lasts_new_meshes_wait_for_their_share_of_the_time(tmp_path):
    from gsfix_online.services.trainer import TrainerService

    params = dataclasses.replace(_params(tmp_path, keyframe_dir=""), mesh_share=0.5)
    now = [0.0]
    svc = TrainerService("trainer", params, clock=lambda: now[0])
    for i in range(2):
        svc.on_keyframe(_keyframe(i))
    encode = svc._encode

    def slow_encode(kid, kf):  # each keyframe's new mesh image takes 1 s
        now[0] += 1.0
        encode(kid, kf)

    svc._encode = slow_encode
    v = np.array([[-5, -5, 2], [5, -5, 2], [5, 5, 2], [-5, 5, 2]], np.float32)
    mesh = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.full((4, 3), 128, np.uint8))

    def announce(version: int) -> Message:
        path = write_mesh(mesh, tmp_path / f"mesh{version}.ply")
        meta = {"kind": "mesh_written", "path": str(path), "version": version}
        return Message(topic="mesh/tsdf", type="map_event", meta=meta)

    svc.on_map_event(announce(1))  # taken: 2 s of re-encoding, so the next waits until 4 s
    assert (svc.mesh_version, svc.counts["mesh_updates"], now[0]) == (1, 1, 2.0)
    now[0] = 3.0
    svc.on_map_event(announce(2))
    svc.on_map_event(announce(3))  # the latest replaces the one waiting
    assert svc.mesh_version == 1 and svc.mesh_waiting is not None
    assert not svc.take_waiting_mesh()
    now[0] = 4.0
    assert svc.take_waiting_mesh()  # its share allows it now; version 2 was never rendered
    assert (svc.mesh_version, svc.counts["mesh_updates"]) == (3, 2)
    svc.on_map_event(announce(4))  # due at 4 + 2 / 0.5 = 8 s
    assert svc.mesh_version == 3
    svc.policy_state.input_ended = True  # once the input has ended, the last mesh counts now
    assert svc.take_waiting_mesh() and svc.mesh_version == 4


def test_params_from_yaml():
    p = build(trainer_node.Params, files=["configs/profiles/trainer_cpu.yaml"])
    assert p.policy.min_keyframes >= 1 and p.fixer.model.source == "default"
    assert p.fixer.inference.steps == 1  # extends repair_cpu.yaml: the repair node's inference


def test_with_ema_checkpoints_hold_the_averaged_weights(tmp_path):
    import dataclasses

    base = _params(tmp_path)
    fixer = dataclasses.replace(
        base.fixer, train=dataclasses.replace(base.fixer.train, ema_decay=0.5)
    )
    params = dataclasses.replace(base, fixer=fixer)
    t = InMemoryTransport(script=[_keyframe(i) for i in range(5)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert _checkpoints(t) and svc.trainer.step > 1
    saved = load_checkpoint(tmp_path / "ckpt")
    name, live = next((n, p) for n, p in svc.bundle.model.named_parameters() if p.requires_grad)
    stored = dict(saved.bundle.model.named_parameters())[name]
    with svc.trainer.averaged():
        averaged = live.detach().clone()
    # The run's last step was an improvement here (checked), so the newest checkpoint holds the
    # average as it is now (float16 on disk), not the trained weights
    assert saved.step == svc.trainer.step
    torch.testing.assert_close(stored.detach().float(), averaged.float(), atol=1e-3, rtol=0)
    assert not torch.allclose(stored.detach().float(), live.detach().float(), atol=1e-3, rtol=0)


def test_quiet_s_starts_the_run_after_the_last_keyframe(tmp_path):
    import dataclasses

    base = _params(tmp_path)
    params = dataclasses.replace(base, policy=dataclasses.replace(base.policy, quiet_s=30.0))
    now = [100.0]
    t = InMemoryTransport(script=[_keyframe(i) for i in range(6)])
    node, svc = trainer_node.build_node(
        "trainer", params, t, NodeRuntimeConfig(), clock=lambda: now[0]
    )
    _drive(node, svc, params)
    assert svc.trainer.step == 0 and svc.policy_state.runs == 0  # keyframes just arrived
    now[0] += 29.0
    assert not svc.busy
    now[0] += 1.0  # 30 s without a keyframe: the run starts, on all six
    assert svc.busy
    _drive(node, svc, params)
    assert svc.policy_state.runs == 1 and svc.trainer.step > 0 and len(svc.keyframes) == 6


@pytest.mark.parametrize("select_by", ["loss", "holes"])
def test_a_run_shorter_than_one_evaluation_still_ends_with_a_checkpoint(tmp_path, select_by):
    # 3 steps with an evaluation every 20: the run stops before it ever evaluates
    policy = FinetunePolicy(
        min_keyframes=5, holdout_frac=0.2, eval_every=20, patience=2, max_steps_per_run=3
    )
    params = _params(tmp_path, policy=policy, select_by=select_by)
    t = InMemoryTransport(script=[_keyframe(i) for i in range(5)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert svc.policy_state.runs == 1 and svc.trainer.step == 3
    ckpts = _checkpoints(t)
    if select_by == "loss":  # the weights it ended with: nothing measured them
        assert [m.meta["run_done"] for m in ckpts] == [True]  # the end is announced, once
        assert load_checkpoint(tmp_path / "ckpt").step == 3 == ckpts[0].meta["step"]
    else:  # the run's starting weights, measured by its baseline evaluation, saved then
        assert [(m.meta["step"], m.meta["run_done"]) for m in ckpts] == [(0, False), (0, True)]
        assert load_checkpoint(tmp_path / "ckpt").step == 0
    # its progress line once the input has ended counts the one run in the singular
    svc.policy_state.input_ended = True
    svc.next_log_s = -float("inf")
    assert svc.progress_line() == "idle after the end of the input (1 run, last stop max_steps)"


def test_the_end_of_the_input_waits_for_its_keyframes_then_announces_the_plan(tmp_path):
    params = _params(tmp_path, keyframe_dir="")
    end = Message("input_end/splat", "input_end", meta={"frames": 9, "keyframes": 4, "samples": 0})
    t = InMemoryTransport(script=[_keyframe(0), _keyframe(1), _keyframe(2), end])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert not [m for m in t.published if m.type == "trainer_plan"]  # keyframe 3 is missing
    svc.next_log_s = -float("inf")
    assert svc.progress_line() == "the input ended: waiting for its last samples (3/4)"
    t.feed(_keyframe(3))
    _drive(node, svc, params)
    (plan,) = [m for m in t.published if m.type == "trainer_plan"]
    assert plan.topic == "trainer_plan/trainer" and plan.meta["run"] == 0
    assert not plan.meta["will_train"] and plan.meta["reason"]
    assert (plan.meta["train"] + plan.meta["holdout"], plan.meta["max_steps"]) == (4, 6)


def test_in_mode_mesh_gs_ref_a_samples_warp_comes_from_the_other_training_samples(tmp_path):
    """Plain colours per sample show where each warp's pixels come from: never the sample
    itself, never a held-out sample; a sample without others has a warp without pixels."""
    fixer = dataclasses.replace(_params(tmp_path).fixer, model=tiny_model_cfg("mesh+gs+ref"))
    policy = FinetunePolicy(min_keyframes=100, holdout_frac=0.5)  # ids 0, 2 train; 1 held out
    params = _params(tmp_path, fixer=fixer, policy=policy, keyframe_dir="")
    v = np.array([[-5, -5, 2], [5, -5, 2], [5, 5, 2], [-5, 5, 2]], np.float32)
    mesh = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.full((4, 3), 128, np.uint8))
    path = write_mesh(mesh, tmp_path / "mesh.ply")

    def announce(version: int) -> Message:
        meta = {"kind": "mesh_written", "path": str(path), "version": version, "step": 3,
                "files": [str(path)], "vertices": 4, "triangles": 2}  # fmt: skip
        return Message(topic="mesh/tsdf", type="map_event", meta=meta)

    def keyframe(i: int, value: int) -> Message:
        m = _keyframe(i)
        m.arrays["color"] = np.full((H, W, 3), value, np.uint8)
        return m

    t = InMemoryTransport(script=[announce(1), keyframe(0, 30)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert not svc.keyframes[0].ref[1].any()  # alone: no other sample to warp from
    for msg in (keyframe(1, 120), keyframe(2, 220), announce(2)):  # the mesh re-encodes all
        t.feed(msg)
    _drive(node, svc, params)
    assert [svc.keyframes[k].split for k in (0, 1, 2)] == ["train", "holdout", "train"]
    for kid, other in ((0, 220), (2, 30)):
        color, valid = svc.keyframes[kid].ref
        assert valid.mean() > 0.5 and (color[valid] == other).all()
    color, valid = svc.keyframes[1].ref  # the held-out sample: from both training samples
    assert valid.mean() > 0.5 and (color[valid] != 120).any()
    assert svc.cache._entries[0].z_ref is not None and svc.val_cache._entries[1].z_ref is not None
    cover = np.mean([svc.keyframes[k].ref[1].mean() for k in (0, 1, 2)])
    assert svc.stats()["trainer/ref_coverage"] == pytest.approx(cover)


@pytest.mark.parametrize("select_by", ["holes", "loss"])
def test_the_checkpoint_a_run_keeps_is_its_best_by_the_chosen_measure(tmp_path, select_by):
    """Each evaluation measures the held-out diffusion loss and, with select_by "holes",
    GSFixer's error inside holes cut into both renders of the held-out samples; the run keeps
    (saves and announces last) the checkpoint whose chosen measure was best."""
    policy = FinetunePolicy(min_keyframes=5, holdout_frac=0.2, eval_every=2, patience=10,
                            max_steps_per_run=10, min_rel_improvement=0.0)  # fmt: skip
    params = _params(tmp_path, policy=policy, select_by=select_by)
    t = InMemoryTransport(script=[_keyframe(i) for i in range(5)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    seen: list[tuple[int, float]] = []  # (step, holes error) per evaluation
    real = svc.holes_error

    def spy() -> float:
        value = real()
        seen.append((svc.trainer.step, value))
        return value

    svc.holes_error = spy  # type: ignore[method-assign]
    counted = svc.counts["evaluations"]
    _drive(node, svc, params)
    n_evals = svc.counts["evaluations"] - counted
    assert n_evals == 6  # a baseline at step 0, then every 2 steps to 10
    if select_by == "loss":
        assert seen == []  # the holes error is not measured
        return
    assert len(seen) == n_evals and all(0 < h < 255**2 for _, h in seen), seen
    values = [h for _, h in seen]
    assert len(set(values)) > 1  # the weights change what it invents
    best_step = seen[int(np.argmin(values[1:])) + 1][0]  # the baseline is no checkpoint
    assert svc.policy_state.best_loss == min(values)
    assert min(values[1:]) < values[0]  # fine-tuning improved on the baseline
    ckpts = _checkpoints(t)
    assert ckpts[-1].meta["run_done"] and ckpts[-1].meta["step"] == best_step
    manifest = json.loads((Path(ckpts[-1].meta["path"]) / "manifest.json").read_text())
    assert manifest["extra"]["heldout_holes_mse"] == min(values)


def test_the_holes_error_is_inf_without_held_out_samples(tmp_path):
    params = _params(tmp_path)
    t = InMemoryTransport(script=[_keyframe(i) for i in range(3)])
    node, svc = trainer_node.build_node("trainer", params, t, NodeRuntimeConfig())
    _drive(node, svc, params)
    assert not any(kf.split == "holdout" for kf in svc.keyframes.values())
    assert svc.holes_error() == float("inf")
