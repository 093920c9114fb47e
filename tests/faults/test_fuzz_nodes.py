"""10,000 malformed messages at each node kind's inputs, through its real handlers.

``tests/runtime/test_fuzz.py`` covers the wire decoder. Here the messages are mostly legal on the
wire and wrong in what they say (non-rigid poses, zero or negative focal lengths, NaN and
negative depth, 1-pixel images, gigapixel or zero-sized requests, missing or mistyped meta, ids
out of range, paths out of the folder, topics of another handler), with a share of wire garbage.
Each kind runs its own ``run()`` (its event loop, handlers and exit path) on the in-memory
transport; the script ends with SIGTERM, the way the launcher stops a node. Every message is
accounted for (handled, not wanted, or rejected by the wire), every handler error is a one-line
validation error of an expected kind, nothing hangs, and a valid message afterwards still works.

Sources (replay, camera, realsense, oak) have no inputs: their input is files and devices,
fuzzed as corrupted files in ``test_corrupt_readers.py``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gsfix_online.runtime import InMemoryTransport, Message, Node, NodeRuntimeConfig
from gsfix_online.runtime.wire import WireError, encode
from tests.runtime.samples import T0_NS, rgbd_message, sample_messages

N_FUZZ = 10_000
H, W = 6, 8
# Handler errors a fuzzed message may raise: validation at the boundary. Anything else (an
# IndexError deep in a renderer, a ZeroDivisionError, a torch RuntimeError) means the boundary
# let the input through, and fails the test.
# A mesh announcement names a file: a fuzzed path that holds no whole mesh is refused by the
# mesh check (MeshFormatError, a ValueError) or, when nothing is there, by the file system.
VALIDATION = {"ValueError", "TypeError", "KeyError", "FrameError", "WireError", "MeshFormatError",
              "OSError", "FileNotFoundError", "IsADirectoryError"}  # fmt: skip
RUNTIME = {"log_period_s": 0.0, "stats_period_s": 0.5, "poll_timeout_ms": 0}


class _Scripted(InMemoryTransport):
    """The script, then SIGTERM to this process once it is used up."""

    signalled = False

    def recv(self, timeout_ms: int = 0) -> Message | None:
        msg = super().recv(timeout_ms)
        if msg is None and not self.signalled:
            self.signalled = True
            os.kill(os.getpid(), signal.SIGTERM)
        return msg


# ------------------------------------------------------------------------------------------------
# Malformed messages
# ------------------------------------------------------------------------------------------------

BAD_VALUES: list[Any] = [None, "", "x", -1, 0, 2**62, 1.5, float("nan"), True, [1, 2], "a" * 3000]
BAD_PATHS = ["/etc/x.ply", "../x.ply", "../../x", "/", "", "x" * 300 + ".ply", "a/../../b.glb"]
WHAT = [[], ["x"], ["color", "color"], ["depth"], ["alpha", "color", "depth", "x"], [1]]
SIZES = [0, 1, 2, 65535, 9000, -3]


def _images(msg: Message, h: int, w: int) -> dict[str, np.ndarray]:
    out = {}
    for k, a in msg.arrays.items():
        if a.ndim >= 2 and a.shape[-2:] == (H, W) or (a.ndim == 3 and a.shape[:2] == (H, W)):
            shape = (h, w, *a.shape[2:]) if a.shape[:2] == (H, W) else (*a.shape[:-2], h, w)
            out[k] = np.resize(a, shape).astype(a.dtype)
        else:
            out[k] = a
    return out


def _mutate(msg: Message, rng: np.random.Generator) -> Message:
    meta = dict(msg.meta)
    arrays = {k: np.array(v) for k, v in msg.arrays.items()}
    topic, type_, stamp = msg.topic, msg.type, msg.stamp_ns
    # nine in ten get one change every handler must refuse first: a bad pose, K or size, a path
    # out of the folder (legal ones cost a full mapping step, distillation or export each)
    first = [int(rng.choice([0, 1, 3, 5, 9]))] if rng.random() < 0.9 else []
    for op in first + [int(rng.integers(0, 16)) for _ in range(int(rng.integers(0, 3)))]:
        pose = next((k for k in ("T_world_cam", "T_world_body") if k in arrays), None)
        if op == 0 and pose:
            arrays[pose][:3, :3] *= rng.choice([0.0, 2.0, -1.0, 1e6])  # not a rotation
        elif op == 1 and pose:
            arrays[pose][3] = [0.0, 0.0, 1.0, 1.0]  # not rigid
        elif op == 2 and pose:
            arrays[pose][:3, 3] = rng.choice([1e9, -1e12])  # far away
        elif op == 3 and "K" in arrays:
            i, j = [(0, 0), (1, 1), (0, 2), (2, 2), (1, 2)][int(rng.integers(0, 5))]
            arrays["K"][i, j] = rng.choice([0.0, -500.0, 1e9, 1e-300])
        elif op == 4 and "depth" in arrays:
            arrays["depth"][...] = rng.choice([np.nan, np.inf, -1.0, 0.0, 1e30])
        elif op == 5:
            h, w = (int(x) for x in rng.choice([1, 2, 3], 2))
            arrays = _images(dataclasses.replace(msg, arrays=arrays), h, w)
        elif op == 6 and "color" in arrays and arrays["color"].ndim == 3:
            arrays["color"] = np.ascontiguousarray(arrays["color"][..., 0])  # gray
        elif op == 7 and meta:
            meta.pop(list(meta)[int(rng.integers(0, len(meta)))])
        elif op == 8 and meta:
            meta[list(meta)[int(rng.integers(0, len(meta)))]] = BAD_VALUES[
                int(rng.integers(0, len(BAD_VALUES)))
            ]
        elif op == 9:
            meta["path"] = BAD_PATHS[int(rng.integers(0, len(BAD_PATHS)))]
        elif op == 10:
            meta["width"], meta["height"] = (SIZES[int(i)] for i in rng.integers(0, len(SIZES), 2))
        elif op == 11:
            meta["what"] = WHAT[int(rng.integers(0, len(WHAT)))]
        elif op == 12:
            key = ["request_id", "keyframe_id", "view_id", "model_step", "version", "reply_to"]
            meta[key[int(rng.integers(0, len(key)))]] = BAD_VALUES[
                int(rng.integers(0, len(BAD_VALUES)))
            ]
        elif op == 13:
            stamp = int(rng.choice([0, -1, 2**63 - 1]))
        elif op == 14 and arrays:
            arrays.pop(list(arrays)[int(rng.integers(0, len(arrays)))])
        elif op == 15 and "depth" in arrays:
            h, w = arrays["depth"].shape
            n = int(rng.integers(0, 4))
            arrays["perturbed_alpha"] = rng.random((n, h, w), dtype=np.float32)
    return Message(topic, type_, msg.seq, stamp, msg.frame_id, meta, arrays)


def fuzzed(keys: list[str], n: int, seed: int) -> Iterator[list[object]]:
    """``n`` malformed messages (as wire frames) aimed at the handlers ``keys`` (topics or
    types) and at others; a twentieth is wire garbage. Stamps are old (before the valid frame
    fed first), so the few frames that pass every check are counted as repeats rather than
    mapped, but for one in fifty."""
    rng = np.random.default_rng(seed)
    samples = sample_messages(H, W)
    types = sorted(samples)
    later = T0_NS + 10**12
    for i in range(n):
        if i % 20 == 0:
            yield [
                b"rgbd/cam0\x00",
                bytes(rng.integers(0, 256, int(rng.integers(0, 40)), np.uint8)),
            ]
            continue
        key = keys[int(rng.integers(0, len(keys)))] if rng.random() < 0.8 else None
        if key in samples:
            base = samples[key]
        else:
            base = samples[types[int(rng.integers(0, len(types)))]]
            if key is not None:  # a topic: any type on it
                base = dataclasses.replace(base, topic=key)
        msg = _mutate(base, rng)
        if rng.random() < 0.02:
            later += 10**8
            msg = dataclasses.replace(msg, stamp_ns=later)
        try:
            yield encode(msg)
        except (WireError, ValueError, TypeError):  # the sender's own check: garble the header
            frames = encode(base)
            yield [frames[0], b"\x82\xa1v\x01\xa4type\xa3bad", *frames[2:]]


# ------------------------------------------------------------------------------------------------
# Each kind
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Kind:
    module: str
    params: Callable[[Path], Any]
    valid: Callable[[], list[Message]]  # valid input afterwards: the node still answers
    answers: Callable[[list[Message]], bool]  # what the valid input must produce
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)


def _frame(i: int) -> Message:
    return rgbd_message(i, H, W)


def _request(rid: int = 7, topic: str = "render_request/fuzz") -> Message:
    from gsfix_online.nodes._common import render_request

    f = _frame(0)
    return render_request("fuzz", rid, f.arrays["T_world_cam"], f.arrays["K"], W, H,
                          ("color", "depth", "alpha"), topic=topic)  # fmt: skip


def _replied(out: list[Message]) -> bool:
    return any(
        m.type == "render_reply"
        and m.meta.get("request_id") == 7
        and all(np.isfinite(a).all() for a in m.arrays.values())
        for m in out
    )


def _tiny_fixer() -> dict[str, Any]:
    tiny = {"codec_factor": 2, "block_out_channels": [8, 16], "norm_num_groups": 4, "seed": 0}
    return {"model": {"default": tiny, "random_init": True}, "inference": {"steps": 1}}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _views(tmp: Path) -> str:
    (tmp / "views.txt").write_text("0 0 0 0 0 0 0 1\n")
    return str(tmp / "views.txt")


KINDS: dict[str, Kind] = {
    "tsdf": Kind(
        "gsfix_online.nodes.tsdf",
        lambda d: {
            "mesh_dir": str(d / "mesh"),
            "formats": ["ply"],
            "tsdf": {"voxel_size": 0.1, "depth_max": 6.0},
        },
        lambda: [_frame(10**4), _request()],
        _replied,
    ),  # fmt: skip
    "splat": Kind(
        "gsfix_online.nodes.splat",
        lambda d: {
            "threads": 1,
            "snapshot_every": 0,
            "perturbed_renders": 0,
            "distill_passes": 0,
            "export_dir": str(d / "map"),
            "mapper": {
                "kf_iters": 1,
                "non_kf_iters": 1,
                "train_downscale": 1,
                "distill_iters": 1,
                "densify": {"enabled": False},
            },
        },
        lambda: [_frame(10**4), _request()],
        _replied,
    ),  # fmt: skip
    "trainer": Kind(
        "gsfix_online.nodes.trainer",
        lambda d: {
            "checkpoint_dir": str(d / "ck"),
            "keyframe_dir": "",
            "fixer": _tiny_fixer(),
            "policy": {"min_keyframes": 100_000},
        },
        lambda: [],
        lambda out: True,
    ),  # fmt: skip
    "planner": Kind(
        "gsfix_online.nodes.planner",
        lambda d: {"views": _views(d)},
        lambda: [],
        lambda out: True,
    ),
    "repair": Kind(
        "gsfix_online.nodes.repair", lambda d: {"fixer": _tiny_fixer()}, lambda: [], lambda out: True
    ),
    "repair_writer": Kind(
        "gsfix_online.nodes.repair_writer", lambda d: {"out_dir": str(d / "run")}, lambda: [], lambda out: True
    ),
    "monitor": Kind("gsfix_online.nodes.monitor", lambda d: {}, lambda: [_frame(10**4)], lambda out: True),
    "recorder": Kind(
        "gsfix_online.nodes.recorder",
        lambda d: {"path": str(d / "rec.mcap"), "topics": [""]},
        lambda: [_frame(10**4)],
        lambda out: True,
    ),
    "associate": Kind("gsfix_online.nodes.associate", lambda d: {}, lambda: [], lambda out: True),
    # its request server binds 127.0.0.1 on a free port; the graph side gets the fuzz
    "map_server": Kind("gsfix_online.nodes.map_server", lambda d: {"port": _free_port()}, lambda: [],
                       lambda out: True),
}  # fmt: skip


class _Recorded(Node):
    """The real node; the test keeps a reference to read its counters afterwards."""

    made: list[Node] = []

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _Recorded.made.append(self)


def _run(kind: Kind, tmp: Path, script: list[list[object]], monkeypatch) -> tuple[Node, _Scripted]:  # noqa: ANN001
    import importlib

    from gsfix_online.core.config import build

    module = importlib.import_module(kind.module)
    monkeypatch.setattr(module, "Node", _Recorded)
    _Recorded.made = []
    tmp.mkdir(parents=True, exist_ok=True)
    params = build(module.Params, base=kind.params(tmp))
    transport = _Scripted()
    for frames in script:
        transport.feed(frames)
    runtime = NodeRuntimeConfig(**RUNTIME)
    previous = signal.getsignal(signal.SIGTERM)
    try:
        assert module.run("fuzz", params, transport, runtime) == 0
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert len(_Recorded.made) == 1
    return _Recorded.made[0], transport


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflow or NaN cast is a defect too
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_ten_thousand_malformed_messages_at_each_node_kind(kind, tmp_path, monkeypatch, caplog):  # noqa: ANN001
    spec = KINDS[kind]
    # 1. Which handlers the node has (an empty run), then messages aimed at them
    probe, _ = _run(spec, tmp_path / "probe", [], monkeypatch)
    keys = sorted(probe.handlers)
    script = [encode(m) for m in spec.valid()[:1]]  # the valid frame first: later stamps
    script += list(fuzzed(keys, N_FUZZ, seed=sum(map(ord, kind))))
    script += [encode(m) for m in spec.valid()[1:]]

    # 2. Run it
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="gsfix_online.runtime.node"):
        node, transport = _run(spec, tmp_path, script, monkeypatch)
    elapsed = time.monotonic() - t0

    # 3. Every message accounted for; rejections counted in the node's stats
    handled = sum(node.handled.values())
    unhandled = sum(node.unhandled.values())
    rejected = sum(transport.rejected.values())
    assert handled + unhandled + rejected == len(script), (handled, unhandled, rejected)
    stats = node.stats_meta(node.clock())
    assert stats["rejected_total"] == rejected >= N_FUZZ // 20
    assert stats["handler_errors"] == sum(node.handler_errors.values())
    assert stats["unhandled"] == unhandled

    # 4. Handler errors are validation errors, each one line naming what is wrong
    assert set(node.handler_errors) <= VALIDATION, node.handler_errors
    lines = [r.getMessage() for r in caplog.records if "handler for" in r.getMessage()]
    assert len(lines) == sum(node.handler_errors.values())
    assert all("\n" not in line for line in lines), next(x for x in lines if "\n" in x)

    # 5. No hang, and valid input afterwards still answered
    assert elapsed < 60, elapsed
    assert spec.answers([p.message for p in transport.outbox]), [
        p.message.topic for p in transport.outbox
    ]
