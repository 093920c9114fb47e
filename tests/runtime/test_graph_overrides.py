"""``load_graph(path, overrides)``: overrides of the graph's own keys and of one node's entry."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from gsfix_online.core.config import ConfigError
from gsfix_online.runtime.graph import load_graph, node_params


def _graph(tmp_path: Path) -> Path:
    raw = {
        "name": "g",
        "nodes": {
            "server": {
                "kind": "map_server",
                "restart": "always",
                "inputs": ["src/out"],
                "params": {"port": 5590, "server": {"max_pixels": 100}},
            },
            "src": {"kind": "monitor", "outputs": {"out": "reliable"}},
        },
    }
    p = tmp_path / "g.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


def test_override_nodes_x_params_keeps_the_node_kind_wiring_and_other_params(tmp_path: Path):
    g = load_graph(
        _graph(tmp_path),
        ["nodes.server.params.port=5601", "port_base=47000", "nodes.src.restart=never"],
    )
    e = g.nodes["server"]
    assert (e.kind, e.restart, e.inputs) == ("map_server", "always", ["src/out"])
    p = node_params(e)
    assert (p.port, p.server.max_pixels, p.host) == (5601, 100, "127.0.0.1")
    assert g.port_base == 47000 and g.nodes["src"].restart == "never"
    assert g.nodes["src"].kind == "monitor"


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("nodes.nope.params.port=1", r"unknown key 'nodes.nope'.*known keys: server, src"),
        ("nodes.server=1", "nodes.NODE.KEY=VALUE"),
        ("nodes.server.params.port=0", "port: value 0 is out of range"),
        ("nodes.server.kind=nothing", "kind must be one of"),
    ],
)
def test_a_bad_node_override_is_one_line_naming_it(tmp_path: Path, override: str, match: str):
    with pytest.raises(ConfigError, match=match) as err:
        load_graph(_graph(tmp_path), [override])
    assert "\n" not in str(err.value)


def test_a_shared_section_reaches_every_node_that_has_it_and_a_nodes_own_key_wins():
    from gsfix_online.core.config import configs_dir

    graph = configs_dir() / "graphs" / "repair.yaml"
    over = ["repair.fixer.inference.steps=3", "fixer.inference.steps=2", "replay.mode=realtime",
            "replay.source.stride=2", "port_base=47000"]  # fmt: skip
    g = load_graph(graph, over)
    steps = {n: node_params(g.nodes[n]).fixer.inference.steps for n in ("trainer", "repair")}
    assert steps == {"trainer": 2, "repair": 3}
    replay = node_params(g.nodes["replay"])  # replay.KEY: the shared section, else the node's
    assert (replay.replay.mode, replay.source.stride, g.port_base) == ("realtime", 2, 47000)
    with pytest.raises(ConfigError, match="unknown key 'fixer.inference.stepz'; did you mean"):
        load_graph(graph, ["fixer.inference.stepz=2"])
