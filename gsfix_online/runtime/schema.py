"""The message registry: which arrays (dtype, shape, units) and meta each message type carries.

Pure data and checks, shared by ``wire.encode`` and ``wire.decode``; the tables in the ``wire``
module docstring are :func:`describe_registry` of this registry.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

INT64_MAX = 2**63 - 1
_SCALARS = (type(None), bool, int, float, str)

REASONS = (
    "frame_count",  # fewer than 2 frames, or frames != 2 + len(arrays)
    "frame_type",  # a frame is not a bytes-like buffer
    "too_large",  # message or declared arrays exceed max_bytes
    "topic",  # topic frame malformed
    "header_too_large",
    "header_msgpack",  # header is not valid msgpack
    "header_not_map",
    "header_keys",  # missing/unknown header keys or wrong value types
    "version",
    "unknown_type",
    "array_desc",  # array descriptor malformed
    "dtype",  # dtype not in the allow-list
    "shape",  # shape not a list of ints in range
    "size_mismatch",  # shape * itemsize != frame length
    "schema",  # arrays do not match the message type
    "meta",  # required meta missing or of the wrong type
    "non_finite",  # NaN/inf in a pose or intrinsics
)

WIRE_DTYPES: dict[str, np.dtype[Any]] = {
    name: np.dtype(code)
    for name, code in {
        "bool": "|b1",
        "uint8": "|u1",
        "int8": "|i1",
        "uint16": "<u2",
        "int16": "<i2",
        "uint32": "<u4",
        "int32": "<i4",
        "uint64": "<u8",
        "int64": "<i8",
        "float16": "<f2",
        "float32": "<f4",
        "float64": "<f8",
    }.items()
}
DTYPE_NAMES = {dt: name for name, dt in WIRE_DTYPES.items()}


class WireError(ValueError):
    """A message failed to encode or decode; ``reason`` is a short key from :data:`REASONS`."""

    def __init__(self, reason: str, detail: str) -> None:
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


# --------------------------------------------------------------------------------------------
# Registry: message type -> arrays and meta it must carry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ArraySpec:
    dtypes: tuple[str, ...]
    shapes: tuple[tuple[int | None, ...], ...]  # allowed patterns, None = any size
    units: str
    required: bool = True
    finite: bool = False  # reject NaN/inf


@dataclass(frozen=True)
class MessageSpec:
    doc: str  # one line for the schema tables
    arrays: Mapping[str, ArraySpec]
    # required meta: key -> "int" | "float" (finite) | "number" (any float, NaN too) | "str" |
    # "bool" | "str_list"
    meta: Mapping[str, str]
    same_hw: tuple[str, ...] = ()  # images whose [H, W] must agree
    check: Callable[[dict[str, Any], Collection[str]], str | None] | None = None  # -> error or None
    optional: Mapping[str, str] = field(default_factory=dict)  # meta checked when present
    # meta "kind" (required, str) -> the further meta that kind requires; {} = no kind field
    kinds: Mapping[str, Mapping[str, str]] = field(default_factory=dict)


_COLOR = ArraySpec(("uint8",), ((None, None, 3), (None, None)), "rgb8/mono8")
_RGB = ArraySpec(("uint8",), ((None, None, 3),), "rgb8")
_DEPTH = ArraySpec(("float32",), ((None, None),), "m")
_ALPHA = ArraySpec(("float32",), ((None, None),), "0..1")
_K = ArraySpec(("float64",), ((3, 3),), "px", finite=True)
_POSE = ArraySpec(("float64",), ((4, 4),), "m", finite=True)
_IMAGES = ("color", "depth", "gs_render", "gs_alpha", "alpha", "mask", "synthesised", "region",
           "guessed_depth")  # fmt: skip
# What a render request may ask for: ``synthesised`` is, per pixel, the share of the render's
# colour made by Gaussians grown from repaired views (0 for a mesh: all observed);
# ``guessed_depth``, the z-depth of the surface the map guesses where it has none (the mesh's
# planes extended; 0 where it has a surface or no guess, and from a Gaussian map)
RENDER_IMAGES = ("color", "depth", "alpha", "synthesised", "guessed_depth")


def _opt(spec: ArraySpec) -> ArraySpec:
    return ArraySpec(spec.dtypes, spec.shapes, spec.units, False, spec.finite)


def _check_rgbd(meta: dict[str, Any], names: Collection[str]) -> str | None:
    if meta["posed"] != ("T_world_cam" in names):
        return f"posed={meta['posed']} but T_world_cam is {'present' if 'T_world_cam' in names else 'absent'}"
    return None


def _check_size(meta: dict[str, Any], names: Collection[str]) -> str | None:
    if not (0 < meta["width"] <= 65535 and 0 < meta["height"] <= 65535):
        return f"width and height must be in [1, 65535], got {meta['width']}x{meta['height']}"
    return None


def _check_request(meta: dict[str, Any], names: Collection[str]) -> str | None:
    what = meta["what"]
    if not what or not set(what) <= set(RENDER_IMAGES):
        return f"what must be a non-empty subset of {'/'.join(RENDER_IMAGES)}, got {what}"
    return _check_size(meta, names)


def _check_reply(meta: dict[str, Any], names: Collection[str]) -> str | None:
    return (
        None
        if names
        else "render_reply carries no color, depth, alpha, synthesised or guessed_depth"
    )


REGISTRY: dict[str, MessageSpec] = {
    "rgbd": MessageSpec(
        "a camera frame (depth 0 = invalid); T_world_cam iff meta posed (false: awaiting a pose)",
        {"color": _COLOR, "depth": _DEPTH, "K": _K, "T_world_cam": _opt(_POSE)},
        {"posed": "bool"},
        same_hw=_IMAGES,
        check=_check_rgbd,
    ),
    "pose": MessageSpec(
        "a body pose in the parent frame (SLAM output)",
        {"T_world_body": _POSE},
        {"parent": "str", "child": "str"},
    ),
    "camera_info": MessageSpec(
        "intrinsics of a camera; width, height in [1, 65535]",
        {"K": _K, "D": ArraySpec(("float64",), ((None,),), "1", required=False, finite=True)},
        {"width": "int", "height": "int", "distortion_model": "str"},
        check=_check_size,
    ),
    "keyframe": MessageSpec(
        "a selected frame with the splat render at its pose",
        {
            "color": _COLOR,
            "depth": _DEPTH,
            "K": _K,
            "T_world_cam": _POSE,
            "gs_render": _RGB,
            "gs_alpha": _ALPHA,
            # Map alpha rendered at poses near the keyframe's (mask candidates with the holes
            # of views off the trajectory, for GSFixer's mask augmentation)
            "perturbed_alpha": ArraySpec(("float32",), ((None, None, None),), "0..1", False),
        },
        {"keyframe_id": "int"},
        same_hw=_IMAGES,
    ),
    "render_request": MessageSpec(
        "render the map at a pose; what: non-empty subset of color, depth, alpha, synthesised, "
        "guessed_depth",
        {"K": _K, "T_world_cam": _POSE},
        {"width": "int", "height": "int", "request_id": "int", "what": "str_list"},
        check=_check_request,
    ),
    "render_reply": MessageSpec(
        "the images asked for by render_request request_id (at least one)",
        {
            "color": _opt(_RGB),
            "depth": _opt(_DEPTH),
            "alpha": _opt(_ALPHA),
            "synthesised": _opt(_ALPHA),
            "guessed_depth": _opt(_DEPTH),
        },
        {"request_id": "int"},
        same_hw=_IMAGES,
        check=_check_reply,
    ),
    "repaired_view": MessageSpec(
        "a view repaired by the diffusion model at model_step",
        {
            "color": _RGB,
            "K": _K,
            "T_world_cam": _POSE,
            "mask": ArraySpec(("uint8",), ((None, None),), "255=repaired", required=False),
            # The regions the colour was composed by (fallback.far_regions): the writer's
            # provenance of the view
            "region": ArraySpec(
                ("uint8",), ((None, None),), "fallback.REGIONS index, 4=flat", required=False
            ),  # fmt: skip
            # The mesh render's depth (0 = no surface): where the map has holes, distillation
            # seeds Gaussians at this depth with the repaired colour.
            "depth": _opt(_DEPTH),
        },
        {"keyframe_id": "int", "model_step": "int"},
        same_hw=_IMAGES,
    ),
    "model_checkpoint": MessageSpec(
        "the trainer wrote a GSFixer checkpoint to path (version: checkpoints written, step: "
        "optimizer steps; run_done: fine-tuning run `run` ended with it)",
        {},
        {
            "path": "str",
            "version": "int",
            "step": "int",
            "run": "int",
            "run_done": "bool",
            "mode": "str",
        },  # fmt: skip
        optional={"heldout_loss": "number", "fallback": "str"},  # fallback: Choice as JSON
    ),
    "trainer_plan": MessageSpec(
        "what the trainer will do once the input ended: the run whose end brings the repair "
        "model (0 = none) and why",
        {},
        {
            "run": "int",
            "will_train": "bool",
            "reason": "str",
            "train": "int",
            "holdout": "int",
            "max_steps": "int",
            "version": "int",
            "step": "int",
        },  # fmt: skip
    ),
    "input_end": MessageSpec(
        "the input is over: how many frames it had, and the keyframes and training samples "
        "sent for them",
        {},
        {"frames": "int", "keyframes": "int", "samples": "int"},
    ),
    "map_event": MessageSpec(
        "a map changed: a repaired view was distilled (version: views distilled), the 3DGS map "
        "was exported, or a mesh was written (version: mesh version, step: frames)",
        {},
        {"kind": "str", "version": "int", "step": "int"},
        # exported: the input keyframes near the repaired views, before and after, as JSON
        optional={"keyframes_kept": "str"},
        kinds={
            "distilled": {
                "view_id": "int",
                "distill_s": "float",
                "passes_pending": "int",
                "passes_s": "float",
                "gaussians": "int",
            },  # fmt: skip
            "exported": {"path": "str"},
            "mesh_written": {
                "path": "str",
                "files": "str_list",
                "vertices": "int",
                "triangles": "int",
            },  # fmt: skip
        },
    ),
    "command": MessageSpec(
        "a request to a map node: snapshot (TSDF: write the mesh, to path if a .ply/.glb) or "
        "export (3DGS: the standard layout, to path; empty: its own folder)",
        {},
        {"kind": "str", "path": "str"},
        kinds={"snapshot": {}, "export": {}},
    ),
    "heartbeat": MessageSpec(
        "a node is alive (every heartbeat_period_s)",
        {},
        {"node": "str", "pid": "int", "uptime_s": "float"},
    ),
    "stats": MessageSpec(
        "node counters; extra flat keys rate_hz/<topic>, dropped/<topic>, rejected/<reason>, ...",
        {},
        {"node": "str", "period_s": "float"},
    ),
    "ack": MessageSpec(
        "reliable links only: every link sequence number <= ack_seq was delivered",
        {},
        {"ack_seq": "int"},
    ),
}


def _fields_text(fields: Mapping[str, str]) -> str:
    return ", ".join(f"{k} ({v})" for k, v in fields.items())


def _shape_text(pattern: tuple[int | None, ...]) -> str:
    names = {1: ("N",), 2: ("H", "W"), 3: ("H", "W", "C")}[len(pattern)]
    if len(pattern) == 3 and pattern[2] is None:  # a stack of images: [N, H, W]
        names = ("N", "H", "W")
    dims = [str(d) if d is not None else names[i] for i, d in enumerate(pattern)]
    return "[" + ", ".join(dims) + "]"


def describe_registry() -> str:
    """The registry as text tables (the module docstring embeds this; a test keeps them equal)."""
    out = []
    for name, spec in REGISTRY.items():
        out += [f"``{name}``: {spec.doc}", "", f"  meta: {_fields_text(spec.meta)}"]
        if spec.optional:
            out.append(f"  optional meta: {_fields_text(spec.optional)}")
        for kind, fields in spec.kinds.items():
            out.append(f"  kind {kind}: {_fields_text(fields) or '-'}")
        out.append("")
        if not spec.arrays:
            continue
        rows = [("array", "dtype", "shape", "units", "required")] + [
            (
                a,
                "/".join(s.dtypes),
                " or ".join(map(_shape_text, s.shapes)),
                s.units,
                "yes" if s.required else "no",
            )
            for a, s in spec.arrays.items()
        ]
        widths = [max(len(r[i]) for r in rows) for i in range(5)]
        rule = "  " + "  ".join("=" * w for w in widths)
        lines = [
            "  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
            for r in rows
        ]
        out += [rule, lines[0], rule, *lines[1:], rule, ""]
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# Topics: which type each topic carries, who sends it and who reads it
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopicSpec:
    topic: str  # <node> = the sender's name in its graph; {a,b} = one of those
    type: str  # a REGISTRY type
    producers: tuple[str, ...]  # node kinds (configs/graphs: `kind:`), or who else sends it
    consumers: tuple[str, ...]
    kind: str = ""  # the meta "kind" of a type with kinds
    doc: str = ""


# The node kinds that handle each topic (their handlers and the graphs in configs/graphs/).
TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec("rgbd/<camera>", "rgbd", ("replay", "realsense", "oak"),
              ("associate", "tsdf", "splat", "recorder", "monitor"),
              doc="camera frames; posed from replay, unposed from a camera"),
    TopicSpec("rgbd/<camera>/posed", "rgbd", ("associate",),
              ("tsdf", "splat", "recorder", "monitor"), doc="camera frames with the SLAM pose"),
    TopicSpec("pose/<name>", "pose", ("SLAM front end",), ("associate",),
              doc="examples/slam_pose_publisher.py"),
    TopicSpec("camera_info/<camera>", "camera_info", ("programs outside the graph",), (),
              doc="registered for other programs; no node sends or reads it"),
    TopicSpec("keyframe/<splat>", "keyframe", ("splat",), ("trainer", "planner")),
    TopicSpec("fixer_sample/<splat>", "keyframe", ("splat",), ("trainer",),
              doc="frames drawn for GSFixer's training set"),
    TopicSpec("input_end/<splat>", "input_end", ("splat",), ("trainer",)),
    TopicSpec("render_request/<node>", "render_request",
              ("planner", "repair", "repair_writer"), ("tsdf", "splat"),
              doc="replies come back on render_reply/<node>/<server>"),
    TopicSpec("render_reply/<requester>/<server>", "render_reply", ("tsdf", "splat"),
              ("planner", "repair", "repair_writer")),
    TopicSpec("view_request/<map_server>", "render_request", ("map_server", "client programs"),
              ("planner",), doc="views to score and repair (the planner's listen input)"),
    TopicSpec("view/<planner>", "render_request", ("planner",), ("repair",),
              doc="views the planner accepted for repair"),
    TopicSpec("decision/<planner>/{gs,mesh}", "render_reply", ("planner",),
              ("repair", "repair_writer", "map_server"),
              doc="every view's decision, its reason and renders"),
    TopicSpec("repaired_view/<node>", "repaired_view", ("repair", "planner"),
              ("splat", "repair_writer", "map_server"),
              doc="GSFixer's repairs; the planner's fill of skipped views (meta fill_only)"),
    TopicSpec("repair_input/<repair>/{gs,mesh,fixer}", "render_reply", ("repair",),
              ("repair_writer",), doc="what GSFixer got, and its own output"),
    TopicSpec("checkpoint/<trainer>", "model_checkpoint", ("trainer",), ("repair",)),
    TopicSpec("trainer_plan/<trainer>", "trainer_plan", ("trainer",), ("repair",)),
    TopicSpec("distill/<splat>", "map_event", ("splat",), ("repair_writer", "map_server"),
              kind="distilled"),
    TopicSpec("export/<splat>", "map_event", ("splat",), ("repair_writer", "map_server"),
              kind="exported"),
    TopicSpec("mesh/<tsdf>", "map_event", ("tsdf",), ("trainer", "repair_writer", "map_server"),
              kind="mesh_written"),
    TopicSpec("tsdf/snapshot", "command", ("repair_writer",), ("tsdf",), kind="snapshot",
              doc="the TSDF node's snapshot_topic"),
    TopicSpec("splat/export", "command", ("repair_writer", "map_server"), ("splat",),
              kind="export", doc="the splat node's export_topic"),
    TopicSpec("heartbeat/<node>", "heartbeat", ("every node",), ()),
    TopicSpec("stats/<node>", "stats", ("every node",), (),
              doc="the splat node adds stats/<splat>/map"),
    TopicSpec("_ack", "ack", ("reliable receivers",), ("reliable senders",),
              doc="link level, never delivered to a node"),
)  # fmt: skip


def _field_cells(spec: MessageSpec, kind: str) -> list[str]:
    fields = [f"`{k}`: {v}" for k, v in spec.meta.items()]
    fields += [f"`{k}`: {v}" for k, v in spec.kinds.get(kind, {}).items()]
    fields += [f"`{k}`: {v} (optional)" for k, v in spec.optional.items()]
    for name, a in spec.arrays.items():
        shapes = " or ".join(map(_shape_text, a.shapes))
        fields.append(
            f"`{name}`: {'/'.join(a.dtypes)} {shapes}" + ("" if a.required else " (optional)")
        )
    return fields


def topics_markdown() -> str:
    """``docs/topics.md``: every topic with its type, fields, producers and consumers."""
    lines = [
        "# Topics and message types",
        "",
        "Generated from `gsfix_online/runtime/schema.py` (`TOPICS`, `REGISTRY`) by",
        "`topics_markdown()`; `tests/runtime/test_messages.py` keeps this file equal to it",
        "(`GSFIX_WRITE_DOCS=1` makes that test write it). `<node>` is the sending node's name in",
        "its graph; producers and consumers are node kinds. Every receiver checks a message",
        "against its type's fields and rejects it with a one-line error naming the topic, the",
        "type and the field.",
        "",
        "Field types: `int`, `float` (finite), `number` (a float that may be NaN), `str`, `bool`,",
        "`str_list`; arrays as dtype and shape. A `kind` row lists the fields common to the type,",
        "then those of that kind. The `wire` module's docstring has the arrays' units.",
        "",
        "| topic | type | fields | producers | consumers | note |",
        "|---|---|---|---|---|---|",
    ]
    for t in TOPICS:
        spec = REGISTRY[t.type]
        type_text = f"`{t.type}`" + (f" ({t.kind})" if t.kind else "")
        lines.append(
            f"| `{t.topic}` | {type_text} | {', '.join(_field_cells(spec, t.kind))} | "
            f"{', '.join(t.producers)} | {', '.join(t.consumers) or '-'} | {t.doc} |"
        )
    lines += ["", "## Message types", ""]
    lines += ["| type | meaning | kinds |", "|---|---|---|"]
    for name, spec in REGISTRY.items():
        lines.append(f"| `{name}` | {spec.doc} | {', '.join(spec.kinds) or '-'} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Validation shared by encode and decode
# --------------------------------------------------------------------------------------------


def is_int(x: object, lo: int = -(2**63), hi: int = INT64_MAX) -> bool:
    return type(x) is int and lo <= x <= hi  # msgpack gives plain ints; bool is not one


def _meta_ok(value: object, kind: str) -> bool:
    if kind == "int":
        return is_int(value)
    if kind == "float":
        return (isinstance(value, float) or is_int(value)) and math.isfinite(value)  # type: ignore[arg-type]
    if kind == "number":
        return isinstance(value, float) or is_int(value)
    if kind == "str":
        return isinstance(value, str)
    if kind == "bool":
        return isinstance(value, bool)
    return isinstance(value, list) and all(isinstance(v, str) for v in value)  # str_list


_SCALAR_TYPES = frozenset(_SCALARS)


def check_meta(type_name: str, spec: MessageSpec, meta: object, topic: str = "") -> None:
    """Meta against the type's fields (required, optional when present, and the kind's);
    ``topic``, where known, is named in the error."""
    if topic:
        type_name = f"{type_name} on {topic!r}"
    if not isinstance(meta, dict):
        raise WireError("meta", f"{type_name}: meta must be a map, got {type(meta).__name__}")
    for key, value in meta.items():
        if not isinstance(key, str):
            raise WireError("meta", f"{type_name}: meta keys must be str, got {key!r}")
        # A scalar of an exact type (what msgpack gives) passes at once; lists and subclasses
        # take the general test.
        if type(value) not in _SCALAR_TYPES and not (
            all(isinstance(v, _SCALARS) for v in value)
            if isinstance(value, list)
            else isinstance(value, _SCALARS)
        ):
            raise WireError("meta", f"{type_name}: meta[{key!r}] must be scalar or a flat list")
    _check_fields(type_name, spec.meta, meta)
    for key, kind in spec.optional.items():
        if key in meta and not _meta_ok(meta[key], kind):
            got = repr(meta[key])[:60]
            raise WireError("meta", f"{type_name}: meta[{key!r}] must be {kind}, got {got}")
    if spec.kinds:
        fields = spec.kinds.get(meta["kind"])
        if fields is None:
            known = ", ".join(spec.kinds)
            got = repr(meta["kind"])[:60]
            raise WireError("meta", f"{type_name}: meta['kind'] must be one of {known}, got {got}")
        _check_fields(f"{type_name} ({meta['kind']})", fields, meta)


def _check_fields(type_name: str, fields: Mapping[str, str], meta: dict[str, Any]) -> None:
    for key, kind in fields.items():
        if key not in meta or not _meta_ok(meta[key], kind):
            got = repr(meta.get(key, "<missing>"))[:60]
            raise WireError("meta", f"{type_name}: meta[{key!r}] must be {kind}, got {got}")


def check_arrays(
    type_name: str,
    spec: MessageSpec,
    descs: dict[str, tuple[str, tuple[int, ...]]],  # name -> (wire dtype, shape)
) -> None:
    """Array names, dtypes and shapes against the registry (no meta involved)."""
    for name, (dtype, shape) in descs.items():
        a = spec.arrays.get(name)
        if a is None:
            known = ", ".join(spec.arrays) or "none"
            raise WireError("schema", f"{type_name}: unknown array {name!r} (known: {known})")
        fits = any(
            len(p) == len(shape) and all(d is None or d == s for d, s in zip(p, shape, strict=True))
            for p in a.shapes
        )
        if dtype not in a.dtypes or not fits:
            want = " or ".join(f"{list(p)}".replace("None", "N") for p in a.shapes)
            raise WireError(
                "schema",
                f"{type_name}.{name} must be {'/'.join(a.dtypes)} {want}, got {dtype} {list(shape)}",
            )
    missing = [n for n, a in spec.arrays.items() if a.required and n not in descs]
    if missing:
        raise WireError("schema", f"{type_name}: missing arrays {missing}")
    hw = {n: descs[n][1][:2] for n in spec.same_hw if n in descs}
    if len(set(hw.values())) > 1:
        raise WireError("schema", f"{type_name}: image sizes differ: {hw}")


def check_rule(
    type_name: str, spec: MessageSpec, names: Collection[str], meta: dict[str, Any]
) -> None:
    """The type's own rule tying meta to the arrays present (after :func:`check_meta`)."""
    if spec.check is not None:
        err = spec.check(meta, names)
        if err:
            raise WireError("meta", f"{type_name}: {err}")


def all_finite(arr: np.ndarray) -> bool:
    if arr.size <= 64:  # poses and K: Python floats beat a numpy round trip
        return all(map(math.isfinite, arr.ravel().tolist()))
    return bool(np.isfinite(arr).all())


def finite_arrays(spec: MessageSpec, names: Iterable[str]) -> tuple[str, ...]:
    """Those of ``names`` that must hold no NaN/inf (poses, intrinsics)."""
    return tuple(n for n in names if n in spec.arrays and spec.arrays[n].finite)


def check_finite(type_name: str, names: Iterable[str], arrays: Mapping[str, np.ndarray]) -> None:
    """``names``: from :func:`finite_arrays` (a layout's, worked out once)."""
    for name in names:
        if not all_finite(arrays[name]):
            raise WireError("non_finite", f"{type_name}.{name} contains NaN or inf")
