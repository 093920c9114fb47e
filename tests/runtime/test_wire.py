"""Wire format: round trips, zero-copy receive, and one test per rejection reason."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import msgpack
import numpy as np
import pytest
import zmq

from gsfix_online.runtime import wire
from gsfix_online.runtime.transport import InMemoryTransport
from gsfix_online.runtime.wire import (
    REASONS,
    REGISTRY,
    Message,
    WireError,
    decode,
    encode,
    frame_to_message,
    message_to_frame,
    subscription_prefix,
    topic_matches,
)
from tests.conftest import make_frames
from tests.runtime.samples import rgbd_message, sample_messages


def as_bytes(frames: list) -> list[bytes]:
    """What arrives from a socket: one bytes object per frame."""
    return [
        bytes(memoryview(f).cast("B")) if isinstance(f, np.ndarray) else bytes(f) for f in frames
    ]


def assert_same(a: Message, b: Message) -> None:
    assert (a.topic, a.type, a.seq, a.stamp_ns, a.frame_id) == (
        b.topic,
        b.type,
        b.seq,
        b.stamp_ns,
        b.frame_id,
    )
    assert a.meta == b.meta
    assert list(a.arrays) == list(b.arrays)
    for name in a.arrays:
        x, y = a.arrays[name], b.arrays[name]
        assert (x.dtype, x.shape) == (y.dtype, y.shape), name
        assert x.tobytes() == y.tobytes(), name  # bit-exact, NaN-safe


@pytest.mark.parametrize("type_name", sorted(REGISTRY))
def test_round_trip_every_type(type_name: str) -> None:
    msg = sample_messages()[type_name]
    back = decode(as_bytes(encode(msg)))
    assert_same(msg, back)
    assert back.sent_mono_ns is None


def test_sent_stamp_round_trip_and_encode_does_not_copy() -> None:
    msg = rgbd_message()
    frames = encode(msg, sent_mono_ns=123)
    assert frames[2] is msg.arrays["color"] and frames[3] is msg.arrays["depth"]
    assert frames[0] == b"rgbd/cam0\x00"
    assert decode(as_bytes(frames)).sent_mono_ns == 123


def test_decode_is_zero_copy_over_zmq_frames() -> None:
    msg = rgbd_message(h=120, w=160)  # color 57,600 B, depth 76,800 B
    ctx = zmq.Context()
    a, b = ctx.socket(zmq.PAIR), ctx.socket(zmq.PAIR)
    try:
        a.bind("inproc://wire-zero-copy")
        b.connect("inproc://wire-zero-copy")
        a.send_multipart(encode(msg), copy=False)
        frames = b.recv_multipart(copy=False)
        back = decode(frames)
        for i, name in enumerate(back.arrays, start=2):
            arr = back.arrays[name]
            assert root_owner(arr) is frames[i], name  # a view over the frame, not a copy
            assert np.shares_memory(arr, np.frombuffer(frames[i].buffer, np.uint8))
            assert not arr.flags.writeable
        assert_same(msg, back)
    finally:
        a.close(0)
        b.close(0)
        ctx.term()


def test_decode_is_zero_copy_over_bytes() -> None:
    frames = as_bytes(encode(rgbd_message()))
    back = decode(frames)
    assert root_owner(back.arrays["depth"]) is frames[3]


# --------------------------------------------------------------------------------------------
# Malformed input: one case (or more) per reason
# --------------------------------------------------------------------------------------------


def rebuild(
    header_fn: Callable[[dict], object] | None = None,
    frames_fn: Callable[[list], list] | None = None,
    msg: Message | None = None,
) -> list:
    """Valid rgbd frames with the header and/or frame list mutated."""
    frames = as_bytes(encode(msg or rgbd_message()))
    if header_fn is not None:
        header = msgpack.unpackb(frames[1])
        out = header_fn(header)
        frames[1] = msgpack.packb(header if out is None else out)
    return frames_fn(frames) if frames_fn is not None else frames


def set_array(array: str, **changes: object) -> Callable[[dict], None]:
    def fn(h: dict) -> None:
        next(d for d in h["arrays"] if d["name"] == array).update(changes)

    return fn


def drop(key: str) -> Callable[[dict], None]:
    def fn(h: dict) -> None:
        h.pop(key)

    return fn


def poison(index: int, value: float) -> Callable[[list], list]:
    """Overwrite one float64 of frame ``index`` (K is frame 4, T_world_cam frame 5)."""

    def fn(frames: list) -> list:
        x = np.frombuffer(frames[index], np.float64).copy()
        x[0] = value
        frames[index] = x.tobytes()
        return frames

    return fn


def root_owner(arr: np.ndarray) -> object:
    while isinstance(arr.base, np.ndarray):
        arr = arr.base
    base = arr.base  # the buffer's exporter, or a memoryview over it
    return base.obj if isinstance(base, memoryview) else base


CASES: list[tuple[str, str, Callable[[], list]]] = [
    ("frame_count", "one frame", lambda: rebuild(frames_fn=lambda f: f[:1])),
    ("frame_count", "array frame missing", lambda: rebuild(frames_fn=lambda f: f[:-1])),
    ("frame_count", "extra frame", lambda: rebuild(frames_fn=lambda f: [*f, b"x"])),
    ("frame_type", "int frame", lambda: rebuild(frames_fn=lambda f: [f[0], f[1], 5, *f[3:]])),
    ("topic", "no delimiter", lambda: rebuild(frames_fn=lambda f: [b"rgbd/cam0", *f[1:]])),
    ("topic", "two delimiters", lambda: rebuild(frames_fn=lambda f: [b"rgbd\x00cam0\x00", *f[1:]])),
    ("topic", "not ascii", lambda: rebuild(frames_fn=lambda f: ["rgbd/çam\x00".encode(), *f[1:]])),
    ("topic", "space", lambda: rebuild(frames_fn=lambda f: [b"rgbd cam\x00", *f[1:]])),
    ("topic", "empty", lambda: rebuild(frames_fn=lambda f: [b"\x00", *f[1:]])),
    (
        "header_too_large",
        "70 KB header",
        lambda: rebuild(frames_fn=lambda f: [f[0], b"\x80" * 70_000, *f[2:]]),
    ),
    (
        "header_msgpack",
        "reserved byte",
        lambda: rebuild(frames_fn=lambda f: [f[0], b"\xc1", *f[2:]]),
    ),
    (
        "header_msgpack",
        "truncated header",
        lambda: rebuild(frames_fn=lambda f: [f[0], f[1][:-3], *f[2:]]),
    ),
    (
        "header_msgpack",
        "trailing bytes",
        lambda: rebuild(frames_fn=lambda f: [f[0], f[1] + b"\x01", *f[2:]]),
    ),
    ("header_not_map", "list header", lambda: rebuild(lambda h: [1, 2, 3])),
    ("header_not_map", "int header", lambda: rebuild(lambda h: 7)),
    ("header_keys", "seq missing", lambda: rebuild(drop("seq"))),
    ("header_keys", "seq str", lambda: rebuild(lambda h: h.update(seq="3"))),
    ("header_keys", "seq bool", lambda: rebuild(lambda h: h.update(seq=True))),
    ("header_keys", "seq negative", lambda: rebuild(lambda h: h.update(seq=-1))),
    ("header_keys", "stamp beyond int64", lambda: rebuild(lambda h: h.update(stamp_ns=2**64 - 1))),
    ("header_keys", "frame_id int", lambda: rebuild(lambda h: h.update(frame_id=3))),
    ("header_keys", "unknown key", lambda: rebuild(lambda h: h.update(extra=1))),
    ("header_keys", "v missing", lambda: rebuild(drop("v"))),
    ("version", "v=2", lambda: rebuild(lambda h: h.update(v=2))),
    ("version", "v=0", lambda: rebuild(lambda h: h.update(v=0))),
    ("unknown_type", "pointcloud", lambda: rebuild(lambda h: h.update(type="pointcloud"))),
    (
        "array_desc",
        "units missing",
        lambda: rebuild(lambda h: h["arrays"][0].pop("units") and None),
    ),
    (
        "array_desc",
        "descriptor not a map",
        lambda: rebuild(lambda h: h["arrays"].__setitem__(0, "color")),
    ),
    ("array_desc", "duplicate name", lambda: rebuild(set_array("depth", name="color"))),
    ("array_desc", "17 arrays", lambda: rebuild(lambda h: h.update(arrays=h["arrays"] * 5))),
    ("dtype", "object", lambda: rebuild(set_array("color", dtype="object"))),
    ("dtype", "O", lambda: rebuild(set_array("color", dtype="O"))),
    ("dtype", "|O8", lambda: rebuild(set_array("color", dtype="|O8"))),
    ("dtype", "unicode", lambda: rebuild(set_array("color", dtype="<U4"))),
    ("dtype", "complex", lambda: rebuild(set_array("K", dtype="complex128"))),
    ("dtype", "big-endian", lambda: rebuild(set_array("depth", dtype=">f4"))),
    ("dtype", "not a string", lambda: rebuild(set_array("depth", dtype=7))),
    ("shape", "negative dim", lambda: rebuild(set_array("depth", shape=[-6, -8]))),
    ("shape", "5 dims", lambda: rebuild(set_array("depth", shape=[1, 1, 6, 8, 1]))),
    ("shape", "string shape", lambda: rebuild(set_array("depth", shape="6x8"))),
    ("shape", "bool dims", lambda: rebuild(set_array("K", shape=[True, 3]))),
    ("shape", "scalar", lambda: rebuild(set_array("K", shape=[]))),
    (
        "too_large",
        "huge shape",
        lambda: rebuild(set_array("color", shape=[2**31 - 1, 2**31 - 1, 3])),
    ),
    ("size_mismatch", "shape vs bytes", lambda: rebuild(set_array("color", shape=[6, 8]))),
    (
        "size_mismatch",
        "truncated buffer",
        lambda: rebuild(frames_fn=lambda f: [*f[:3], f[3][:-1], *f[4:]]),
    ),
    ("schema", "depth float64", lambda: rebuild(set_array("depth", dtype="float64", shape=[3, 8]))),
    ("schema", "4-channel color", lambda: rebuild(set_array("color", shape=[6, 2, 12]))),
    (
        "schema",
        "K missing",
        lambda: rebuild(lambda h: h["arrays"].pop(2) and None, lambda f: f[:4] + f[5:]),
    ),
    ("schema", "unknown array", lambda: rebuild(set_array("T_world_cam", name="T_cam_world"))),
    ("schema", "wrong units", lambda: rebuild(set_array("depth", units="mm"))),
    ("schema", "sizes differ", lambda: rebuild(set_array("depth", shape=[8, 6]))),
    ("meta", "posed missing", lambda: rebuild(lambda h: h.update(meta={}))),
    ("meta", "posed str", lambda: rebuild(lambda h: h["meta"].update(posed="yes"))),
    ("meta", "posed without pose", lambda: rebuild(lambda h: h["meta"].update(posed=False))),
    ("meta", "nested map", lambda: rebuild(lambda h: h["meta"].update(extra={"a": 1}))),
    ("meta", "bytes value", lambda: rebuild(lambda h: h["meta"].update(extra=b"\x00"))),
    ("header_keys", "meta not a map", lambda: rebuild(lambda h: h.update(meta=[1]))),
    ("non_finite", "NaN pose", lambda: rebuild(frames_fn=poison(5, np.nan))),
    ("non_finite", "inf in K", lambda: rebuild(frames_fn=poison(4, np.inf))),
]


@pytest.mark.parametrize(("reason", "what", "make"), CASES, ids=[f"{r}-{w}" for r, w, _ in CASES])
def test_malformed_rejected_with_reason(reason: str, what: str, make: Callable[[], list]) -> None:
    frames = make()
    with pytest.raises(WireError) as exc:
        decode(frames)
    assert exc.value.reason == reason, str(exc.value)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(("reason", "what", "make"), CASES, ids=[f"{r}-{w}" for r, w, _ in CASES])
def test_malformed_rejected_with_reason_on_a_cold_cache(
    reason: str, what: str, make: Callable[[], list], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same reasons with no layout known yet (the test above runs with rgbd's known)."""
    monkeypatch.setattr(wire, "_DECODE_LAYOUTS", {})
    with pytest.raises(WireError) as exc:
        decode(make())
    assert exc.value.reason == reason, str(exc.value)


# Descriptors equal (==) to a known valid layout's, but not the same: a known layout must not
# let them through.
LOOKALIKES: list[tuple[str, str, Callable[[dict], object]]] = [
    ("shape", "float dims", set_array("depth", shape=[6.0, 8.0])),
    ("shape", "float dims in K", set_array("K", shape=[3.0, 3])),
    ("array_desc", "extra descriptor key", set_array("color", extra=1)),
    ("array_desc", "name as bytes", set_array("color", name=b"color")),
    ("array_desc", "units as bytes", set_array("depth", units=b"m")),
    ("dtype", "dtype as bytes", set_array("depth", dtype=b"float32")),
    ("array_desc", "unhashable name", set_array("depth", name=["depth"])),
]


@pytest.mark.parametrize(("reason", "what", "fn"), LOOKALIKES, ids=[w for _, w, _ in LOOKALIKES])
def test_known_layout_matches_exactly(reason: str, what: str, fn: Callable[[dict], object]) -> None:
    decode(rebuild())  # rgbd's layout is now known
    assert wire._DECODE_LAYOUTS
    with pytest.raises(WireError) as exc:
        decode(rebuild(fn))
    assert exc.value.reason == reason, str(exc.value)


def test_known_layout_still_checks_sizes_and_limits() -> None:
    frames = rebuild()
    decode(frames)  # known layout from here on
    declared = sum(len(f) for f in frames[2:])
    with pytest.raises(WireError) as exc:
        decode(frames, max_bytes=declared - 1)
    assert exc.value.reason == "too_large"
    with pytest.raises(WireError) as exc:
        decode([*frames[:3], frames[3][:-4], *frames[4:]])
    assert exc.value.reason == "size_mismatch"
    with pytest.raises(WireError) as exc:
        decode(frames[:-1])
    assert exc.value.reason == "frame_count"
    assert decode(frames).arrays["depth"].shape == (6, 8)


def test_every_reason_has_a_case() -> None:
    assert {r for r, _, _ in CASES} | {"too_large", "frame_count"} >= set(REASONS)


def test_total_size_limit() -> None:
    frames = as_bytes(encode(rgbd_message(h=60, w=80)))
    decode(frames, max_bytes=60 * 80 * 8)
    with pytest.raises(WireError, match="too_large"):
        decode(frames, max_bytes=60 * 80 * 7)


def test_unposed_rgbd_and_gray_color_are_valid() -> None:
    msg = rgbd_message()
    del msg.arrays["T_world_cam"]
    msg.meta = {"posed": False}
    msg.arrays["color"] = np.zeros((6, 8), np.uint8)
    assert_same(msg, decode(as_bytes(encode(msg))))


# --------------------------------------------------------------------------------------------
# Encode refuses what decode would refuse
# --------------------------------------------------------------------------------------------


def _with(**arrays: object) -> Message:
    msg = rgbd_message()
    msg.arrays.update(arrays)
    return msg


@pytest.mark.parametrize(
    ("reason", "msg"),
    [
        ("schema", _with(color=np.zeros((8, 6, 3), np.uint8).transpose(1, 0, 2))),
        ("dtype", _with(depth=np.zeros((6, 8), ">f4"))),
        ("dtype", _with(depth=np.zeros((6, 8), object))),
        ("schema", _with(depth=np.zeros((6, 8), np.float64))),
        ("schema", _with(K=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
        ("non_finite", _with(T_world_cam=np.full((4, 4), np.nan))),
        ("unknown_type", Message("x/y", "pointcloud")),
        (
            "topic",
            Message("rgbd/cam0/", "heartbeat", meta={"node": "a", "pid": 1, "uptime_s": 0.0}),
        ),
        ("topic", Message("rgbd\x00", "heartbeat", meta={"node": "a", "pid": 1, "uptime_s": 0.0})),
        (
            "meta",
            Message("hb", "heartbeat", meta={"node": "a", "pid": 1, "uptime_s": 0.0, "x": {1, 2}}),
        ),
        ("meta", Message("hb", "heartbeat", meta={"node": "a", "pid": "1", "uptime_s": 0.0})),
        (
            "header_keys",
            Message("hb", "heartbeat", seq=-1, meta={"node": "a", "pid": 1, "uptime_s": 0.0}),
        ),
    ],
)
def test_encode_rejects(reason: str, msg: Message) -> None:
    with pytest.raises(WireError) as exc:
        encode(msg)
    assert exc.value.reason == reason
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------------------------
# Topics, converters, documentation
# --------------------------------------------------------------------------------------------


def test_subscription_rules() -> None:
    assert subscription_prefix("rgbd/cam0") == b"rgbd/cam0\x00"
    assert subscription_prefix("rgbd/") == b"rgbd/"
    assert subscription_prefix("") == b""
    assert topic_matches("rgbd/cam0", "rgbd/cam0")
    assert not topic_matches("rgbd/cam0", "rgbd/cam0_raw")
    assert topic_matches("rgbd/", "rgbd/cam0_raw")
    assert not topic_matches("rgbd/", "pose/rgbd")
    assert topic_matches("", "anything")
    with pytest.raises(WireError):
        subscription_prefix("bad topic")


@pytest.mark.parametrize("gray", [False, True])
def test_frame_round_trip(gray: bool) -> None:
    frame = make_frames(n=2, width=16, height=12, gray=gray)[1]
    back = message_to_frame(decode(as_bytes(encode(frame_to_message(frame, "rgbd/cam0")))))
    assert np.array_equal(back.color, frame.color) and back.color.dtype == np.uint8
    assert back.depth.tobytes() == frame.depth.tobytes()
    assert back.intrinsics == frame.intrinsics
    assert np.array_equal(back.T_world_cam, frame.T_world_cam)
    assert (back.stamp_ns, back.seq, back.frame_id) == (frame.stamp_ns, frame.seq, frame.frame_id)


def test_unposed_frame_needs_a_pose() -> None:
    frame = make_frames(n=1, width=16, height=12)[0]
    msg = decode(as_bytes(encode(frame_to_message(frame, "rgbd/cam0", posed=False))))
    assert msg.meta["posed"] is False and "T_world_cam" not in msg.arrays
    with pytest.raises(WireError, match="unposed"):
        message_to_frame(msg)
    assert np.array_equal(message_to_frame(msg, frame.T_world_cam).T_world_cam, frame.T_world_cam)


def test_docstring_tables_match_the_registry() -> None:
    assert wire.describe_registry() in (wire.__doc__ or "")
    for name in REGISTRY:
        assert f"``{name}``" in (wire.__doc__ or "")


def test_a_transport_counts_every_case_under_its_reason() -> None:
    t = InMemoryTransport(script=[make() for _, _, make in CASES] + [encode(rgbd_message(9))])
    msg = t.recv()
    assert msg is not None and msg.seq == 9  # the valid message after all the bad ones
    assert t.rejected == Counter(reason for reason, _, _ in CASES)
