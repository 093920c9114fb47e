"""Fuzz: >= 10,000 malformed messages at a node; it never crashes and counts every one."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gsfix_online.runtime.config import NodeRuntimeConfig
from gsfix_online.runtime.node import Node
from gsfix_online.runtime.transport import InMemoryTransport
from gsfix_online.runtime.wire import REGISTRY, WIRE_DTYPES, Message, encode
from tests.runtime.samples import rgbd_message, sample_messages

BAD_PER_EXAMPLE = 100
EXAMPLES = 100  # BAD_PER_EXAMPLE * EXAMPLES >= 10,000 malformed messages


def as_bytes(frames: list) -> list[bytes]:
    return [
        bytes(memoryview(f).cast("B")) if isinstance(f, np.ndarray) else bytes(f) for f in frames
    ]


VALID = {t: as_bytes(encode(m)) for t, m in sample_messages().items()}
TYPES = sorted(VALID)
WITH_ARRAYS = [t for t in TYPES if len(VALID[t]) > 2]
WITH_POSE = [t for t in TYPES if {"T_world_cam", "T_world_body"} & set(REGISTRY[t].arrays)]

bad_dtypes = st.sampled_from(
    [
        "object",
        "O",
        "|O",
        "<U4",
        "S8",
        "V8",
        "complex64",
        "complex128",
        "float128",
        "<M8[ns]",
        ">f4",
        "int",
        "",
    ]
) | st.text(max_size=10).filter(lambda s: s not in WIRE_DTYPES)
msgpack_int = st.integers(-(2**63), 2**64 - 1)  # what msgpack can carry
not_int = st.one_of(
    st.none(), st.text(max_size=5), st.floats(), st.booleans(), st.lists(msgpack_int, max_size=2)
)
not_str = st.one_of(st.none(), msgpack_int, st.floats(), st.booleans(), st.binary(max_size=4))
WRONG_VALUE = {
    "v": not_int,
    "type": not_str,
    "seq": not_int | st.integers(-(2**63), -1) | st.integers(min_value=2**63, max_value=2**64 - 1),
    "stamp_ns": not_int,
    "frame_id": not_str,
    "meta": st.one_of(not_str, st.lists(msgpack_int, max_size=2)),
    "arrays": st.one_of(not_str, st.dictionaries(st.text(max_size=3), msgpack_int, max_size=2)),
}


def header_of(frames: list[bytes]) -> dict[str, Any]:
    return msgpack.unpackb(frames[1])


def with_header(frames: list[bytes], header: object) -> list[bytes]:
    return [frames[0], msgpack.packb(header), *frames[2:]]


@st.composite
def malformed(draw: st.DrawFn) -> list[bytes]:
    kind = draw(
        st.sampled_from(
            [
                "random_frames",
                "random_header",
                "truncated",
                "frame_count",
                "version",
                "dtype",
                "shape_mismatch",
                "huge_shape",
                "non_map_header",
                "missing_key",
                "wrong_key_type",
                "unknown_type",
                "extra_key",
                "missing_meta",
                "nan_pose",
                "bad_topic",
            ]
        )
    )
    type_name = draw(
        st.sampled_from(WITH_ARRAYS if kind in ("dtype", "shape_mismatch", "huge_shape") else TYPES)
    )
    frames = list(VALID[type_name])
    header = header_of(frames)
    if kind == "random_frames":
        return draw(st.lists(st.binary(max_size=48), max_size=6))
    if kind == "random_header":
        return [frames[0], draw(st.binary(max_size=64)), *frames[2:]]
    if kind == "truncated":
        i = draw(st.integers(0, len(frames) - 1))
        cut = draw(st.integers(1, len(frames[i])))
        frames[i] = frames[i][:-cut]
        return frames
    if kind == "frame_count":
        if draw(st.booleans()) or len(frames) == 2:
            return frames + draw(st.lists(st.binary(max_size=16), min_size=1, max_size=3))
        return frames[: draw(st.integers(0, len(frames) - 1))]
    if kind == "version":
        header["v"] = draw(st.integers(-(2**63), 2**64 - 1).filter(lambda v: v != 1))
    elif kind == "dtype":
        draw(st.sampled_from(header["arrays"]))["dtype"] = draw(bad_dtypes)
    elif kind == "shape_mismatch":
        i = draw(st.integers(0, len(header["arrays"]) - 1))
        desc = header["arrays"][i]
        itemsize = WIRE_DTYPES[desc["dtype"]].itemsize
        shape = draw(
            st.lists(st.integers(0, 40), min_size=1, max_size=4).filter(
                lambda s: math.prod(s) * itemsize != len(frames[2 + i])
            )
        )
        desc["shape"] = shape
    elif kind == "huge_shape":
        desc = draw(st.sampled_from(header["arrays"]))
        desc["shape"] = draw(st.lists(st.integers(2**20, 2**64 - 1), min_size=2, max_size=4))
    elif kind == "non_map_header":
        header = draw(
            st.one_of(
                msgpack_int, st.text(max_size=8), st.lists(msgpack_int, max_size=3), st.none()
            )
        )
    elif kind == "missing_key":
        del header[draw(st.sampled_from(sorted(header)))]
    elif kind == "wrong_key_type":
        key = draw(st.sampled_from(sorted(WRONG_VALUE)))
        header[key] = draw(WRONG_VALUE[key])
    elif kind == "unknown_type":
        header["type"] = draw(st.text(max_size=12).filter(lambda s: s not in REGISTRY))
    elif kind == "extra_key":
        header[draw(st.text(max_size=8).filter(lambda s: s not in header))] = 1
    elif kind == "missing_meta":
        del header["meta"][draw(st.sampled_from(sorted(REGISTRY[type_name].meta)))]
    elif kind == "nan_pose":
        type_name = draw(st.sampled_from(WITH_POSE))
        frames = list(VALID[type_name])
        i = next(
            2 + k
            for k, d in enumerate(header_of(frames)["arrays"])
            if d["name"].startswith("T_world")
        )
        T = np.frombuffer(frames[i], np.float64).copy()
        T[draw(st.integers(0, 15))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        frames[i] = T.tobytes()
        return frames
    elif kind == "bad_topic":
        topic = draw(
            st.binary(max_size=12).filter(lambda b: not (b.endswith(b"\x00") and b.count(0) == 1))
        )
        return [topic, *frames[1:]]
    return with_header(frames, header)


def test_fuzz_node_survives_and_counts_every_rejection() -> None:
    total_bad = 0

    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        database=None,
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.large_base_example,
        ],
    )
    @given(bad=st.lists(malformed(), min_size=BAD_PER_EXAMPLE, max_size=BAD_PER_EXAMPLE + 10))
    def run(bad: list[list[bytes]]) -> None:
        nonlocal total_bad
        handled: list[Message] = []
        t = InMemoryTransport()
        handlers = {name: handled.append for name in REGISTRY}
        node = Node(
            "fuzz", t, handlers, NodeRuntimeConfig(on_handler_error="raise"), clock=lambda: 0.0
        )
        for i, frames in enumerate(bad):
            t.feed(frames)
            if i % 25 == 0:
                t.feed(rgbd_message(i))  # valid messages mixed in
        node.run_until_idle()
        n_valid_mixed = len(handled)
        assert sum(t.rejected.values()) == len(bad), t.rejected
        assert n_valid_mixed == len(range(0, len(bad), 25))
        # Valid messages sent after the flood are still processed.
        for i in range(3):
            t.feed(rgbd_message(1000 + i))
        node.run_until_idle()
        assert [m.seq for m in handled[n_valid_mixed:]] == [1000, 1001, 1002]
        assert not node.handler_errors
        total_bad += len(bad)

    run()
    assert total_bad >= 10_000, total_bad
