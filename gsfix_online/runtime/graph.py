"""Node graphs: a YAML file names the nodes, their wiring and restart policies.

```yaml
name: replay-local
transport: ipc              # ipc (one machine) or tcp (across machines)
hosts: {robot: 127.0.0.1}   # tcp: address of each machine; nodes pick one with `machine:`
port_base: 46000            # tcp: the i-th output of the graph gets port_base + i
nodes:
  replay:
    kind: replay            # what runs: a registered node kind (see node_kinds)
    machine: robot
    restart: on-failure     # never | on-failure | always
    max_restarts: 3
    outputs: {frames: reliable}       # output name -> delivery mode (reliable | latest)
    routes: {frames: [rgbd/]}         # optional: only these topics go out on that output
    params: {source: {path: log.mcap}, replay: {mode: max}}
  monitor:
    kind: monitor
    inputs: [replay/frames]           # node/output of other nodes
```

Addresses are derived from the graph alone, so every machine computes the same wiring:
``ipc://<run_dir>/<graph>-<node>-<output>.sock`` or ``tcp://<host>:<port>``. Latest-only outputs
bind at the publisher. A reliable output is one link per receiver, and each link binds at its
receiver (many senders may connect to one receiver): with several readers, the sender opens one
DEALER per reader and every message routed to the output goes to each of them, acknowledged per
link (``...-<output>-<reader>.sock``; tcp ports of the extra links follow all other ports, so
adding a reader never moves an existing port). ``routes`` sends each message only to the outputs
whose topics it matches, so a node with several reliable outputs (keyframes to the trainer,
render replies to the requesters) does not send everything everywhere.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from gsfix_online.core.config import ConfigError, build, parse_override, read_yaml, to_dict
from gsfix_online.runtime.config import EndpointConfig, NodeRuntimeConfig, TransportConfig

RestartPolicy = Literal["never", "on-failure", "always"]

# The registry of node kinds: the entry points of group "gsfix_online.nodes" (pyproject.toml names
# each kind and the module in nodes/ that runs it). Each is a module with `Params` (a config
# dataclass) and `run(name, params, transport, runtime_cfg) -> int`. A package of the user's may
# add kinds by declaring entry points in the same group; the library never imports nodes/.
NODE_GROUP = "gsfix_online.nodes"


def node_kinds() -> dict[str, Any]:
    """Kind name -> its entry point (not loaded), from the installed packages' metadata."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=NODE_GROUP)}


@dataclass(frozen=True)
class NodeEntry:
    kind: str = ""
    machine: str = "local"
    restart: RestartPolicy = "on-failure"
    max_restarts: int = field(default=3, metadata={"range": (0, 1000)})
    outputs: dict[str, str] = field(default_factory=dict)  # name -> "reliable" | "latest"
    # output name -> topics it carries (subscription syntax, "ns/" = a namespace); absent = all
    routes: dict[str, list[str]] = field(default_factory=dict)
    inputs: list[str] = field(default_factory=list)  # "node/output"
    # Inputs this node binds for programs outside the graph (e.g. the SLAM front end's poses):
    # name -> delivery mode. Their addresses follow the graph's outputs (see `address`).
    listen: dict[str, str] = field(default_factory=dict)
    subscriptions: list[str] = field(default_factory=lambda: [""])
    params: dict[str, Any] = field(default_factory=dict)
    runtime: NodeRuntimeConfig = field(default_factory=NodeRuntimeConfig)

    def validate(self) -> None:
        kinds = node_kinds()
        if self.kind not in kinds:
            raise ValueError(f"kind must be one of {', '.join(sorted(kinds))}, got {self.kind!r}")
        for name, mode in self.outputs.items():
            if mode not in ("reliable", "latest"):
                raise ValueError(f"output {name!r} mode must be reliable or latest, got {mode!r}")
        for name, mode in self.listen.items():
            if name in self.outputs:
                raise ValueError(f"listen {name!r} has the name of an output; rename one")
            if mode not in ("reliable", "latest"):
                raise ValueError(f"listen {name!r} mode must be reliable or latest, got {mode!r}")
        for ref in self.inputs:
            if ref.count("/") != 1:
                raise ValueError(f"input {ref!r} must look like node/output")
        for name, topics in self.routes.items():
            if name not in self.outputs:
                raise ValueError(f"routes names {name!r}, which is not an output")
            if not topics:
                raise ValueError(f"routes.{name} must list at least one topic")


@dataclass(frozen=True)
class GraphConfig:
    name: str = "graph"
    transport: Literal["ipc", "tcp"] = "ipc"
    hosts: dict[str, str] = field(default_factory=lambda: {"local": "127.0.0.1"})
    port_base: int = field(default=46000, metadata={"range": (1024, 65000)})
    run_dir: str = ""  # ipc socket folder; the launcher fills a fresh one when empty
    # A reliable send or flush waits for a connected receiver however slow it is (a splat node
    # distilling for minutes). It gives up on a receiver that disconnected and has not come back
    # within reliable_send_timeout_s (time for a launcher restart), or that has not connected
    # within reliable_connect_timeout_s of the sender's start (runtime/liveness.py).
    reliable_send_timeout_s: float = field(default=30.0, metadata={"range": (0.001, 3600)})
    reliable_connect_timeout_s: float = field(default=120.0, metadata={"range": (0.001, 86400)})
    nodes: dict[str, NodeEntry] = field(default_factory=dict)


def load_graph(path: str | Path, overrides: list[str] | None = None) -> GraphConfig:
    """Parse and check a graph YAML: node kinds, wiring and every node's own params.

    ``overrides`` set any key: ``port_base=47000``, or a node's entry key by key,
    ``nodes.NODE.params.KEY=VALUE`` (the rest of the node's entry stays as the file has it)."""
    data = read_yaml(path)
    nodes_raw = data.get("nodes") or {}
    if not isinstance(nodes_raw, dict):
        raise ConfigError(f"{path}: nodes must be a mapping of node name -> entry")
    top = {k: v for k, v in data.items() if k != "nodes"}
    graph_over: list[str] = []
    node_over: dict[str, list[str]] = {}
    for text in overrides or []:
        keys, _ = parse_override(text)
        if keys[0] != "nodes":
            graph_over.append(text)
        elif len(keys) < 3 or keys[1] not in nodes_raw:
            raise ConfigError(
                f"override '{text}' must look like nodes.NODE.KEY=VALUE with NODE one of "
                f"{', '.join(nodes_raw) or 'none'}"
            )
        else:  # applied to that node's entry below, so its kind and wiring stay
            node_over.setdefault(keys[1], []).append(text.split(".", 2)[2])
    graph = build(GraphConfig, overrides=graph_over, base=top)
    nodes = {}
    for name, raw in nodes_raw.items():
        if not isinstance(raw, dict):
            raise ConfigError(f"{path}: nodes.{name}: expected a mapping")
        try:
            nodes[name] = build(NodeEntry, base=raw, overrides=node_over.get(name))
        except ConfigError as exc:
            raise ConfigError(
                f"{path}: nodes.{name}: {str(exc).removeprefix('defaults: ')}"
            ) from None
    graph = dataclasses.replace(graph, nodes=nodes)
    for name, entry in nodes.items():
        if entry.machine not in graph.hosts:
            raise ConfigError(
                f"{path}: nodes.{name}.machine {entry.machine!r} is not in hosts ({', '.join(graph.hosts)})"
            )
        for ref in entry.inputs:
            src, out = ref.split("/")
            if src not in nodes or out not in nodes[src].outputs:
                raise ConfigError(
                    f"{path}: nodes.{name}.inputs: {ref!r} names no output of the graph"
                )
        node_params(entry, where=f"{path}: nodes.{name}.params")  # fail at launch, not in the child
    return graph


def node_module(kind: str) -> Any:
    """The module that runs node ``kind``, loaded through the registry."""
    kinds = node_kinds()
    if kind not in kinds:
        raise ConfigError(f"node kind must be one of {', '.join(sorted(kinds))}, got {kind!r}")
    return kinds[kind].load()


def node_params(entry: NodeEntry, where: str = "params") -> Any:
    module = node_module(entry.kind)
    try:
        return build(module.Params, base=entry.params)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {str(exc).removeprefix('defaults: ')}") from None


def _outputs(graph: GraphConfig) -> list[tuple[str, str, str]]:
    """(node, output, mode) in graph order, then the listen inputs: the order fixes tcp ports."""
    outs = [(n, o, m) for n, e in graph.nodes.items() for o, m in e.outputs.items()]
    return outs + [(n, o, m) for n, e in graph.nodes.items() for o, m in e.listen.items()]


def _readers(graph: GraphConfig, node: str, out: str) -> list[str]:
    return [n for n, e in graph.nodes.items() if f"{node}/{out}" in e.inputs]


def _fanout_links(graph: GraphConfig) -> list[tuple[str, str, str]]:
    """(node, output, reader) of every reliable link after an output's first reader."""
    return [
        (n, o, r)
        for n, o, m in _outputs(graph)
        if m == "reliable" and o in graph.nodes[n].outputs
        for r in _readers(graph, n, o)[1:]
    ]


def address(graph: GraphConfig, node: str, out: str, reader: str | None = None) -> str:
    """The address of output ``node/out`` (of its link to ``reader``: reliable outputs have one
    link per reader, default the first); for tcp, on the machine of the side that binds."""
    outs = _outputs(graph)
    index = next(i for i, (n, o, _) in enumerate(outs) if (n, o) == (node, out))
    mode = outs[index][2]
    readers = _readers(graph, node, out) if mode == "reliable" else []
    if out in graph.nodes[node].listen:
        readers = []  # the listening node binds
    if reader is not None and reader not in readers:
        raise ConfigError(f"graph {graph.name}: {reader} reads no reliable link of {node}/{out}")
    k = readers.index(reader) if reader is not None else 0
    if graph.transport == "ipc":
        suffix = f"-{readers[k]}" if k > 0 else ""
        return f"ipc://{Path(graph.run_dir) / f'{graph.name}-{node}-{out}{suffix}.sock'}"
    if k > 0:
        index = len(outs) + _fanout_links(graph).index((node, out, readers[k]))
    binder = readers[k] if readers else node
    return f"tcp://{graph.hosts[graph.nodes[binder].machine]}:{graph.port_base + index}"


def transport_for(graph: GraphConfig, name: str) -> TransportConfig:
    """The sockets node ``name`` opens: its outputs (one link per reader of a reliable output)
    and the outputs it reads."""
    entry = graph.nodes[name]
    outputs = []
    for out, mode in entry.outputs.items():
        topics = tuple(entry.routes.get(out, ()))
        readers = _readers(graph, name, out) if mode == "reliable" else []
        if not readers:  # latest-only, or a reliable output nobody in the graph reads
            addr = address(graph, name, out)
            outputs.append(EndpointConfig(addr, True, mode, topics, name=out))  # type: ignore[arg-type]
        for reader in readers:
            addr = address(graph, name, out, reader)
            outputs.append(EndpointConfig(addr, False, "reliable", topics, out, peer=reader))
    inputs = []
    for ref in entry.inputs:
        src, out = ref.split("/")
        mode = graph.nodes[src].outputs[out]
        addr = address(graph, src, out, name if mode == "reliable" else None)
        inputs.append(EndpointConfig(addr, mode == "reliable", mode, name=ref))  # type: ignore[arg-type]
    for name_in, mode in entry.listen.items():
        addr = address(graph, name, name_in)
        inputs.append(EndpointConfig(addr, True, mode, name=name_in))  # type: ignore[arg-type]
    return TransportConfig(
        inputs=tuple(inputs),
        outputs=tuple(outputs),
        subscriptions=tuple(entry.subscriptions),
        reliable_send_timeout_s=graph.reliable_send_timeout_s,
        reliable_connect_timeout_s=graph.reliable_connect_timeout_s,
    )


@dataclass(frozen=True)
class NodeFile:
    """What ``gsfix-online node NAME --config FILE`` reads: one node, fully wired."""

    name: str = ""
    kind: str = ""
    transport: TransportConfig = field(default_factory=TransportConfig)
    runtime: NodeRuntimeConfig = field(default_factory=NodeRuntimeConfig)
    params: dict[str, Any] = field(default_factory=dict)


def node_file(graph: GraphConfig, name: str) -> dict[str, Any]:
    entry = graph.nodes[name]
    return to_dict(
        NodeFile(name, entry.kind, transport_for(graph, name), entry.runtime, entry.params)
    )


def write_node_file(graph: GraphConfig, name: str, path: Path) -> Path:
    from gsfix_online.core.io import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(node_file(graph, name), sort_keys=False))
    return path


def run_node_file(path: str | Path, name: str | None = None) -> int:
    """Entry point of a node process: parse its file, build the transport, run the node kind."""
    raw = read_yaml(path)
    nf = build(NodeFile, base=raw)
    if name is not None and name != nf.name:
        raise ConfigError(f"{path}: holds node {nf.name!r}, not {name!r}")
    entry = NodeEntry(kind=nf.kind, params=nf.params)
    params = node_params(entry, where=f"{path}: params")
    module = node_module(nf.kind)
    from gsfix_online.runtime.zmq_transport import ZmqTransport

    transport = ZmqTransport(nf.transport, name=nf.name)
    return int(module.run(nf.name, params, transport, nf.runtime))
