"""The typed announcements and requests (one message type per meaning) and docs/topics.md."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import msgpack
import pytest
import yaml

from gsfix_online.runtime import InMemoryTransport, Node
from gsfix_online.runtime.schema import REGISTRY, TOPICS, WireError, topics_markdown
from gsfix_online.runtime.wire import Message, decode, encode
from tests.runtime.samples import sample_messages

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "topics.md"
GRAPHS = ROOT / "configs" / "graphs"

# One valid meta per kind of each type with kinds
KIND_META: dict[tuple[str, str], dict[str, Any]] = {
    ("map_event", "distilled"): {
        "kind": "distilled", "version": 2, "step": 130, "view_id": 4, "distill_s": 0.8,
        "passes_pending": 12, "passes_s": 0.0, "gaussians": 5000,
    },
    ("map_event", "exported"): {"kind": "exported", "version": 2, "step": 130, "path": "/o/map"},
    ("map_event", "mesh_written"): {
        "kind": "mesh_written", "version": 3, "step": 40, "path": "/o/mesh.ply",
        "files": ["/o/mesh.ply", "/o/mesh.glb"], "vertices": 10, "triangles": 12,
    },
    ("command", "snapshot"): {"kind": "snapshot", "path": "/o/mesh.ply"},
    ("command", "export"): {"kind": "export", "path": ""},
}  # fmt: skip


def with_meta(msg: Message, change: Any) -> list[bytes]:
    """``msg``'s frames with its header meta changed by ``change`` (past encode's checks)."""
    frames = [bytes(f) for f in encode(msg)]
    header = msgpack.unpackb(frames[1])
    change(header["meta"])
    frames[1] = msgpack.packb(header)
    return frames


def test_the_overloaded_checkpoint_type_is_gone() -> None:
    assert "checkpoint" not in REGISTRY
    old = Message("checkpoint/trainer", "checkpoint", meta={"path": "", "version": 1, "step": 1})
    with pytest.raises(WireError, match="unknown message type 'checkpoint'") as exc:
        encode(old)
    assert exc.value.reason == "unknown_type"


def test_every_kind_is_declared_and_covered() -> None:
    declared = {(n, k) for n, spec in REGISTRY.items() for k in spec.kinds}
    assert declared == set(KIND_META)
    for name, spec in REGISTRY.items():
        if spec.kinds:
            assert spec.meta.get("kind") == "str", name


@pytest.mark.parametrize(("type_name", "kind"), sorted(KIND_META))
def test_every_kind_round_trips(type_name: str, kind: str) -> None:
    msg = Message("a/b", type_name, 7, 123, "world", dict(KIND_META[type_name, kind]))
    back = decode(encode(msg))
    assert (back.topic, back.type, back.seq, back.meta) == ("a/b", type_name, 7, msg.meta)


@pytest.mark.parametrize("type_name", ["model_checkpoint", "trainer_plan", "input_end"])
def test_a_missing_field_is_rejected_in_one_line(type_name: str) -> None:
    msg = sample_messages()[type_name]
    field = next(iter(REGISTRY[type_name].meta))
    with pytest.raises(WireError) as exc:
        decode(with_meta(msg, lambda m: m.pop(field)))
    text = str(exc.value)
    assert exc.value.reason == "meta" and "\n" not in text
    assert text == (
        f"meta: {type_name} on {msg.topic!r}: meta[{field!r}] must be "
        f"{REGISTRY[type_name].meta[field]}, got '<missing>'"
    )


def test_a_wrong_kind_or_a_kind_field_missing_is_rejected() -> None:
    msg = Message("mesh/tsdf", "map_event", meta=dict(KIND_META["map_event", "mesh_written"]))
    with pytest.raises(WireError) as exc:
        decode(with_meta(msg, lambda m: m.update(kind="written")))
    assert str(exc.value) == (
        "meta: map_event on 'mesh/tsdf': meta['kind'] must be one of distilled, exported, "
        "mesh_written, got 'written'"
    )
    with pytest.raises(WireError) as exc:
        decode(with_meta(msg, lambda m: m.pop("triangles")))
    assert str(exc.value) == (
        "meta: map_event on 'mesh/tsdf' (mesh_written): meta['triangles'] must be int, "
        "got '<missing>'"
    )
    with pytest.raises(WireError, match=r"command on 'tsdf/snapshot': meta\['kind'\] must be"):
        encode(Message("tsdf/snapshot", "command", meta={"kind": "snap", "path": ""}))
    with pytest.raises(WireError, match=r"model_checkpoint on 'c/t': meta\['heldout_loss'\]"):
        meta = {**sample_messages()["model_checkpoint"].meta, "heldout_loss": "low"}
        encode(Message("c/t", "model_checkpoint", meta=meta))


def test_a_node_never_sees_a_malformed_announcement(caplog: pytest.LogCaptureFixture) -> None:
    good = Message("mesh/tsdf", "map_event", meta=dict(KIND_META["map_event", "mesh_written"]))
    t = InMemoryTransport()
    t.feed(with_meta(good, lambda m: m.update(kind="mesh")))
    t.feed(with_meta(good, lambda m: m.pop("path")))
    t.feed(good)
    seen: list[Message] = []
    node = Node("trainer", t, {"map_event": seen.append})
    with caplog.at_level(logging.WARNING, logger="gsfix_online.runtime.transport"):
        node.run_until_idle()
    assert [m.meta["path"] for m in seen] == ["/o/mesh.ply"]
    assert t.rejected["meta"] == 2
    (line,) = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
    assert "map_event on 'mesh/tsdf'" in line and "meta['kind']" in line and "\n" not in line


def test_the_topic_table_names_registered_types_and_kinds() -> None:
    for t in TOPICS:
        spec = REGISTRY[t.type]
        assert (t.kind in spec.kinds) if spec.kinds else not t.kind, t.topic
    assert {t.type for t in TOPICS} == set(REGISTRY)
    assert {(t.type, t.kind) for t in TOPICS if t.kind} == set(KIND_META)
    assert sample_messages()  # every registered type has a sample (samples.py asserts it)


@pytest.mark.parametrize("graph", sorted(GRAPHS.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_routed_topic_names_its_node_among_the_producers(graph: Path) -> None:
    nodes = yaml.safe_load(graph.read_text()).get("nodes") or {}
    for name, node in nodes.items():
        for prefixes in (node.get("routes") or {}).values():
            for prefix in prefixes:
                rows = [
                    t
                    for t in TOPICS
                    if (t.topic.startswith(prefix) if prefix.endswith("/") else t.topic == prefix)
                ]
                assert any(node["kind"] in t.producers for t in rows), (name, prefix)


def test_docs_topics_md_is_generated_from_the_schema() -> None:
    text = topics_markdown()
    if os.environ.get("GSFIX_WRITE_DOCS"):
        DOC.write_text(text)
    assert DOC.read_text() == text, (
        "docs/topics.md is out of date: GSFIX_WRITE_DOCS=1 pytest tests/runtime/test_messages.py"
    )
