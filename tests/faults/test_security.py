"""Security defaults: loopback binds unless a graph or flag names a host, nothing unpickled from
the wire or a run folder, and no name from a message becomes a path outside the node's folder."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from gsfix_online.core.se3 import look_at
from gsfix_online.runtime import Message, NodeRuntimeConfig
from gsfix_online.runtime.graph import GraphConfig, load_graph, transport_for
from gsfix_online.runtime.requests import path_inside, render_request
from gsfix_online.runtime.transport import InMemoryTransport

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted([*(ROOT / "gsfix_online").rglob("*.py"), *(ROOT / "nodes").rglob("*.py")])


class _TouchOnLoad:
    """A pickled object that creates ``path`` when unpickled: what a hostile file would carry."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):  # noqa: ANN204
        return (Path.touch, (self.path,))


# -- binds -------------------------------------------------------------------------------------


def test_every_tcp_address_of_a_graph_without_hosts_is_loopback(tmp_path: Path) -> None:
    graph = {
        "name": "sec",
        "transport": "tcp",
        "nodes": {
            "replay": {"kind": "replay", "outputs": {"frames": "reliable", "live": "latest"}},
            "monitor": {"kind": "monitor", "inputs": ["replay/frames", "replay/live"]},
            "tsdf": {"kind": "tsdf", "inputs": ["replay/frames"], "listen": {"req": "reliable"}},
        },
    }
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(graph))
    g = load_graph(tmp_path / "g.yaml")
    addresses = [
        ep.address
        for name in g.nodes
        for ep in (*transport_for(g, name).inputs, *transport_for(g, name).outputs)
    ]
    assert len(addresses) == 7
    assert all(re.fullmatch(r"tcp://127\.0\.0\.1:\d+", a) for a in addresses), addresses
    assert GraphConfig().hosts == {"local": "127.0.0.1"}


def test_shipped_graphs_bind_only_the_hosts_they_name() -> None:
    for path in sorted((ROOT / "configs" / "graphs").glob("*.yaml")):
        raw = yaml.safe_load(path.read_text())
        g = load_graph(path)
        named = set((raw.get("hosts") or {}).values())
        for name in g.nodes:
            t = transport_for(g, name)
            for ep in (*t.inputs, *t.outputs):
                if ep.address.startswith("tcp://"):
                    host = ep.address[len("tcp://") :].rsplit(":", 1)[0]
                    assert host == "127.0.0.1" or host in named, (path.name, ep.address)
                    assert host not in ("*", "0.0.0.0"), (path.name, ep.address)
        for entry in g.nodes.values():  # servers inside graphs
            host = entry.params.get("host")
            assert host in (None, "127.0.0.1") or host in named, (path.name, host)


def test_servers_and_commands_default_to_loopback() -> None:
    from gsfix_online.nodes.map_server import Params as MapServerParams

    from gsfix_online.apps.cli import build_parser

    assert MapServerParams().host == "127.0.0.1"
    parser = build_parser()
    serve = parser.parse_args(["serve", "run"])
    assert serve.host == "127.0.0.1"
    from gsfix_online.apps.viewer import ViewConfig
    from gsfix_online.core.config import build

    view = parser.parse_args(["view", "run"])
    assert view.host is None  # no flag: the setting's default decides
    assert build(ViewConfig).host == "127.0.0.1"


def test_a_default_map_server_listens_on_loopback_only() -> None:
    import psutil
    from gsfix_online.nodes.map_server import Params as MapServerParams
    from gsfix_online.nodes.map_server import RequestLoop, build_service

    from tests.nodes.test_graph_processes import free_port_base

    params = MapServerParams(port=free_port_base(1))
    loop = RequestLoop(build_service(params), params)
    try:
        listening = [
            c.laddr
            for c in psutil.Process().net_connections("tcp")
            if c.status == psutil.CONN_LISTEN and c.laddr.port == params.port
        ]
    finally:
        loop.close()
    assert listening and all(a.ip == "127.0.0.1" for a in listening), listening


def test_no_source_binds_a_wildcard_address_by_default() -> None:
    wildcard = re.compile(r"""(tcp://\*|=\s*["']0\.0\.0\.0["']|host:\s*0\.0\.0\.0)""")
    found = [
        f"{p.relative_to(ROOT)}:{i + 1}"
        for p in [*SOURCES, *(ROOT / "configs").rglob("*.yaml")]
        for i, line in enumerate(p.read_text().splitlines())
        if wildcard.search(line)
    ]
    assert found == []


# -- nothing unpickled -------------------------------------------------------------------------


def test_every_torch_load_is_weights_only_and_nothing_uses_pickle() -> None:
    loads, pickles = [], []
    for p in SOURCES:
        text = p.read_text()
        for m in re.finditer(r"torch\.load\(", text):
            call = text[m.start() : text.find("\n)", m.start()) + 2 if "\n)" in text else None]
            if "weights_only=True" not in text[m.start() : m.start() + 300]:
                loads.append(f"{p.relative_to(ROOT)}: {call[:80]!r}")
        for bad in ("pickle.load", "allow_pickle=True", "dill.", "joblib.load", "marshal.load"):
            if bad in text:
                pickles.append(f"{p.relative_to(ROOT)}: {bad}")
    assert loads == [] and pickles == []


def test_a_checkpoint_with_a_pickled_object_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    from gsfix_online.fixer import checkpoint as ck
    from gsfix_online.fixer.sources import build_default
    from tests.fixer.conftest import tiny_model_cfg

    cfg = tiny_model_cfg()
    path = ck.save_checkpoint(tmp_path / "ckpt", build_default(cfg), 1, cfg, trainer_state={})
    marker = tmp_path / "pwned"
    torch.save({"trainer": _TouchOnLoad(marker)}, path / "trainer.pt")
    manifest = path / "manifest.json"  # an attacker who also rewrites the checksums
    import json

    m = json.loads(manifest.read_text())
    m["files"]["trainer.pt"] = {
        "bytes": (path / "trainer.pt").stat().st_size,
        "sha256": ck._sha256(path / "trainer.pt"),
    }
    manifest.write_text(json.dumps(m))
    with pytest.raises(ck.CheckpointError, match="no usable checkpoint") as exc:
        ck.load_checkpoint(path)
    assert "\n" not in str(exc.value) and not marker.exists()


def test_a_snapshot_with_a_pickled_object_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.services.splat import SnapshotError, load_snapshot

    marker = tmp_path / "pwned"
    torch.save({"map": _TouchOnLoad(marker)}, tmp_path / "map.pt")
    with pytest.raises(SnapshotError, match="does not load") as exc:
        load_snapshot(MapperConfig(), tmp_path / "map.pt")
    assert "\n" not in str(exc.value) and not marker.exists()


# -- names from the wire -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "name", ["../outside.ply", "/etc/gsfix.ply", "sub/../../outside.ply", "link/x.ply", "", 7]
)
def test_path_inside_refuses_what_leaves_the_folder(tmp_path: Path, name: object) -> None:
    root = tmp_path / "run"
    (root / "sub").mkdir(parents=True)
    (root / "link").symlink_to(tmp_path)  # a link inside that points out
    with pytest.raises(ValueError) as exc:
        path_inside(name, root)
    assert "\n" not in str(exc.value)
    assert path_inside("sub/mesh.ply", root) == (root / "sub" / "mesh.ply").resolve()
    assert path_inside(str(root / "mesh.ply"), root) == (root / "mesh.ply").resolve()


def _tsdf_node(tmp_path: Path):  # noqa: ANN202
    from gsfix_online.nodes import tsdf

    params = tsdf.Params(mesh_dir=str(tmp_path / "run" / "mesh"), formats=["ply"])
    t = InMemoryTransport()
    node, _ = tsdf.build_node("tsdf", params, t, NodeRuntimeConfig())
    return node, t


def test_tsdf_node_writes_a_named_snapshot_only_inside_its_folder(tmp_path: Path) -> None:
    node, t = _tsdf_node(tmp_path)
    outside = tmp_path / "outside.ply"
    for path in (str(outside), str(tmp_path / "run" / ".." / "outside.ply")):
        t.feed(Message("tsdf/snapshot", "command", meta={"kind": "snapshot", "path": path}))
    inside = tmp_path / "run" / "mesh.ply"
    t.feed(Message("tsdf/snapshot", "command", meta={"kind": "snapshot", "path": str(inside)}))
    node.run_until_idle()
    assert not outside.exists() and inside.is_file()
    assert node.handler_errors == {"ValueError": 2}
    assert [m.meta["path"] for m in t.published if m.topic == "mesh/tsdf"] == [
        str(inside.resolve())
    ]


def test_splat_node_exports_only_inside_its_folder(tmp_path: Path) -> None:
    from gsfix_online.services.splat import Params, SplatService

    svc = SplatService("splat", Params(export_dir=str(tmp_path / "run" / "map")))
    msg = Message("splat/export", "command", meta={"kind": "export", "path": "/tmp/../etc"})
    with pytest.raises(ValueError, match="outside"):
        svc.on_export(msg)
    ok = Message(
        "splat/export", "command", meta={"kind": "export", "path": str(tmp_path / "run" / "m2")}
    )
    assert svc.on_export(ok).meta["path"] == ""  # nothing mapped yet: nothing exported


@pytest.mark.parametrize("kind", ["tsdf", "splat"])
def test_a_render_request_for_gigapixels_is_refused_before_allocating(
    tmp_path: Path, kind: str
) -> None:
    K = np.array([[30.0, 0, 20], [0, 30, 15], [0, 0, 1]])
    T = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    req = render_request("x", 1, T, K, 65535, 65535, ("color", "depth", "alpha"))
    if kind == "tsdf":
        node, t = _tsdf_node(tmp_path)
        t.feed(req)
        node.run_until_idle()
        assert node.handler_errors == {"ValueError": 1}
        assert not [m for m in t.published if m.type == "render_reply"]
    else:
        from gsfix_online.services.splat import Params, SplatService

        with pytest.raises(ValueError, match="above the limit") as exc:
            SplatService("splat", Params()).on_render_request(req)
        assert "\n" not in str(exc.value)
