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

import copy
import dataclasses
import os
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from gsfix_online.core.config import (
    ConfigError,
    build,
    build_from,
    deep_merge,
    full_key,
    gather,
    origin_of,
    read_yaml,
    to_dict,
    under,
    unknown_key,
)
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


# Sections of node params that a graph command's settings give to every node that has them
# (sections of the root config, gsfix_online.jobs.config): ``fixer.inference.steps=2`` reaches the
# trainer and the repair node. Every other key names a node or the graph itself.
SHARED_SECTIONS = ("source", "replay", "fixer")


def _params_class(entry: dict[str, Any]) -> Any:
    kind = entry.get("kind")
    return node_module(kind).Params if kind in node_kinds() else None


def _section_type(entry: dict[str, Any], section: str) -> Any:
    """The dataclass of ``section`` in the node's params, or None when it has none."""
    cls = _params_class(entry)
    if cls is None:
        return None
    tp = typing.get_type_hints(cls).get(section)
    return tp if dataclasses.is_dataclass(tp) else None


def apply_settings(
    raw: dict[str, Any],
    settings: dict[str, Any],
    origins: dict[str, str],
    where: str = "graph",
    also: tuple[str, ...] = (),
    shared: tuple[str, ...] = SHARED_SECTIONS,
) -> list[str]:
    """Apply ``settings`` (nested, from :func:`gsfix_online.core.config.gather`: ``-c`` files
    and ``KEY=VALUE`` overrides) to the raw graph ``raw`` in place; returns the nodes changed.

    A top-level key is one of the ``shared`` sections (every node whose params have it; where a
    node has that name too, its params' other keys go to it: ``replay.source.path``), a node's
    name (its params, key by key: ``splat.mapper.kf_iters``; it wins over a shared section),
    ``nodes`` (node entries: ``nodes.splat.restart=never``) or a key of the graph
    (``port_base``). Anything else is an error naming the key and the nearest valid ones
    (``also``: keys the caller reads itself, for that list). Each changed node's params are
    checked here, with the key as the user wrote it.
    """
    nodes = raw.get("nodes") or {}
    if not isinstance(nodes, dict):
        raise ConfigError(f"{where}: nodes must be a mapping of node name -> entry")
    graph_keys = [f.name for f in dataclasses.fields(GraphConfig)]
    shared = tuple(s for s in shared if any(_section_type(e, s) for e in nodes.values()))
    changed: dict[str, dict[str, str]] = {}  # node -> origins of its params' new keys
    # shared sections first: a node's own key wins over the section it shares
    order = sorted(settings, key=lambda k: k not in shared)
    for key in order:
        value = settings[key]
        origin = origin_of(origins, key)
        if key in shared and key in nodes and isinstance(value, dict):
            # a node named like a shared section (the replay node): keys of its params that
            # the section does not have go to the node (``replay.source.path``)
            section = next((_section_type(e, key) for e in nodes.values()
                            if _section_type(e, key)), None)  # fmt: skip
            node_cls = _params_class(nodes[key])
            fields = {f.name for f in dataclasses.fields(section)} if section else set()
            own = {k: v for k, v in value.items()
                   if k not in fields and node_cls and k in node_cls.__dataclass_fields__}  # fmt: skip
            if own:
                deep_merge(nodes[key].setdefault("params", {}), own)
                node_origins = changed.setdefault(key, {})
                node_origins.update({k: o for k, o in under(origins, key).items()
                                     if k.split(".")[0] in own})  # fmt: skip
                value = {k: v for k, v in value.items() if k not in own}
                if not value:
                    continue
        if key in shared and not isinstance(value, dict):
            raise ConfigError(f"{origin}: {key}: expected a mapping of keys, got {value!r}")
        if key in shared:
            targets = [n for n, e in nodes.items() if _section_type(e, key)]
            # the keys as the user wrote them, checked against the first node's section
            first = nodes[targets[0]].get("params") or {}
            merged = deep_merge(copy.deepcopy(first.get(key) or {}), value)
            build_from(_section_type(nodes[targets[0]], key), merged, origins, prefix=key)
            for name in targets:
                params = nodes[name].setdefault("params", {})
                params[key] = deep_merge(params.get(key) or {}, value)
                changed.setdefault(name, {}).update(under(origins, key, key))
        elif key in nodes:
            if not isinstance(value, dict):
                raise ConfigError(f"{origin}: '{key}' is a node: set its params as {key}.KEY=VALUE")
            deep_merge(nodes[key].setdefault("params", {}), value)
            changed.setdefault(key, {}).update(under(origins, key))
        elif key == "nodes" and isinstance(value, dict):
            for name, entry in value.items():
                if name not in nodes:
                    raise unknown_key(origin_of(origins, f"nodes.{name}"), f"nodes.{name}",
                                      list(nodes), [f"nodes.{n}" for n in nodes])  # fmt: skip
                if not isinstance(entry, dict):
                    raise ConfigError(f"{origin_of(origins, f'nodes.{name}')}: nodes.{name}: "
                                      "set its entry as nodes.NODE.KEY=VALUE")  # fmt: skip
                deep_merge(nodes[name], entry)
                changed.setdefault(name, {})
        elif key in graph_keys:
            mapping = isinstance(raw.get(key), dict) and isinstance(value, dict)
            raw[key] = deep_merge(raw[key], value) if mapping else value
        else:
            known = sorted({*shared, *nodes, *also})
            raise unknown_key(origin, full_key(origins, key), known, [*known, *graph_keys], key)
    for name, node_origins in changed.items():  # origins relative to the node's params
        cls = _params_class(nodes[name])
        if cls is None:
            continue  # no such kind: load_graph names it
        params = nodes[name].get("params") or {}
        rel = {k: f"{where}: nodes.{name}.params" for k in _dotted(params)}
        rel.update(node_origins)
        build_from(cls, params, {f"{name}.{k}": o for k, o in rel.items()}, name)
    return list(changed)


def _dotted(d: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        out.append(prefix + k)
        if isinstance(v, dict):
            out += _dotted(v, prefix + k + ".")
    return out


def load_graph(
    path: str | Path,
    overrides: list[str] | None = None,
    files: list[str | Path] | None = None,
) -> GraphConfig:
    """Parse and check a graph YAML: node kinds, wiring and every node's own params.

    ``files`` (``-c``) and ``overrides`` set any key (:func:`apply_settings`): a key of the
    graph (``port_base=47000``), a node's entry (``nodes.NODE.restart=never``), a node's params
    (``NODE.KEY=VALUE``, also ``nodes.NODE.params.KEY=VALUE``), or a shared section
    (``fixer.inference.steps=2``)."""
    data = read_yaml(path)
    if overrides or files:
        settings, origins = gather(files, overrides)
        apply_settings(data, settings, origins, where=str(path))
    return parse_graph(data, path)


def parse_graph(data: dict[str, Any], path: str | Path = "graph") -> GraphConfig:
    """A graph from its raw dict (a graph file as :func:`read_yaml` reads it), checked as
    :func:`load_graph` checks it; ``path`` names it in errors."""
    data = copy.deepcopy(data)
    nodes_raw = data.get("nodes") or {}
    if not isinstance(nodes_raw, dict):
        raise ConfigError(f"{path}: nodes must be a mapping of node name -> entry")
    top = {k: v for k, v in data.items() if k != "nodes"}
    graph = build(GraphConfig, base=top)
    nodes = {}
    for name, raw in nodes_raw.items():
        if not isinstance(raw, dict):
            raise ConfigError(f"{path}: nodes.{name}: expected a mapping")
        try:
            nodes[name] = build(NodeEntry, base=raw)
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


def resolved(graph: GraphConfig) -> GraphConfig:
    """``graph`` with every node's params in full (defaults filled in): what each node runs
    with, to write beside a run."""
    nodes = {
        name: dataclasses.replace(entry, params=to_dict(node_params(entry)))
        for name, entry in graph.nodes.items()
    }
    return dataclasses.replace(graph, nodes=nodes)


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


def read_node_file(path: str | Path, name: str | None = None) -> tuple[NodeFile, Any]:
    """A node file as its process reads it: (the file, the node's params built and checked)."""
    raw = read_yaml(path)
    nf = build(NodeFile, base=raw)
    if name is not None and name != nf.name:
        raise ConfigError(f"{path}: holds node {nf.name!r}, not {name!r}")
    entry = NodeEntry(kind=nf.kind, params=nf.params)
    return nf, node_params(entry, where=f"{path}: params")


def run_node_file(path: str | Path, name: str | None = None) -> int:
    """Entry point of a node process: parse its file, build the transport, run the node kind."""
    nf, params = read_node_file(path, name)
    module = node_module(nf.kind)
    from gsfix_online.runtime.zmq_transport import ZmqTransport

    transport = ZmqTransport(nf.transport, name=nf.name)
    profile_dir = os.environ.get(PROFILE_ENV, "")
    if not profile_dir:
        return int(module.run(nf.name, params, transport, nf.runtime))
    return profiled(
        Path(profile_dir), nf.name, lambda: module.run(nf.name, params, transport, nf.runtime)
    )


PROFILE_ENV = "GSFIX_PROFILE_DIR"  # set by the launcher: each node profiles itself into it


def profiled(folder: Path, name: str, run: Callable[[], Any]) -> int:
    """Run a node under pyinstrument's sampling profiler; write ``<name>.html`` (the call tree
    to browse) and ``<name>.txt`` (the tree as text, calls under 1 % of the time left out) into
    ``folder`` when it ends, also on SIGTERM (the node's loop returns)."""
    try:
        from pyinstrument import Profiler
    except ImportError as exc:
        raise ConfigError(
            "profiling a node needs pyinstrument: pip install 'gsfix-online[dev]'"
        ) from exc
    from gsfix_online.core.io import atomic_write_text

    folder.mkdir(parents=True, exist_ok=True)
    profiler = Profiler(interval=0.005)
    profiler.start()
    try:
        return int(run())
    finally:
        profiler.stop()
        atomic_write_text(folder / f"{name}.html", profiler.output_html())
        text = profiler.output_text(unicode=False, color=False, show_all=False, time="seconds",
                                    flat=False, processor_options={"filter_threshold": 0.01})  # fmt: skip
        atomic_write_text(folder / f"{name}.txt", text)
