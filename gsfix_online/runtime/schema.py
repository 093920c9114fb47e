"""The message registry: which arrays (dtype, shape, units) and meta each message type carries.

Pure data and checks, shared by ``wire.encode`` and ``wire.decode``; the tables in the ``wire``
module docstring are :func:`describe_registry` of this registry.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass
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
    meta: Mapping[str, str]  # key -> "int" | "float" | "str" | "bool" | "str_list"
    same_hw: tuple[str, ...] = ()  # images whose [H, W] must agree
    check: Callable[[dict[str, Any], Collection[str]], str | None] | None = None  # -> error or None


_COLOR = ArraySpec(("uint8",), ((None, None, 3), (None, None)), "rgb8/mono8")
_RGB = ArraySpec(("uint8",), ((None, None, 3),), "rgb8")
_DEPTH = ArraySpec(("float32",), ((None, None),), "m")
_ALPHA = ArraySpec(("float32",), ((None, None),), "0..1")
_K = ArraySpec(("float64",), ((3, 3),), "px", finite=True)
_POSE = ArraySpec(("float64",), ((4, 4),), "m", finite=True)
_IMAGES = ("color", "depth", "gs_render", "gs_alpha", "alpha", "mask")


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
    if not what or not set(what) <= {"color", "depth", "alpha"}:
        return f"what must be a non-empty subset of color/depth/alpha, got {what}"
    return _check_size(meta, names)


def _check_reply(meta: dict[str, Any], names: Collection[str]) -> str | None:
    return None if names else "render_reply carries no color, depth or alpha"


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
        "render the map at a pose; what: non-empty subset of color, depth, alpha",
        {"K": _K, "T_world_cam": _POSE},
        {"width": "int", "height": "int", "request_id": "int", "what": "str_list"},
        check=_check_request,
    ),
    "render_reply": MessageSpec(
        "the images asked for by render_request request_id (at least one)",
        {"color": _opt(_RGB), "depth": _opt(_DEPTH), "alpha": _opt(_ALPHA)},
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
            # The mesh render's depth (0 = no surface): where the map has holes, distillation
            # seeds Gaussians at this depth with the repaired colour.
            "depth": _opt(_DEPTH),
        },
        {"keyframe_id": "int", "model_step": "int"},
        same_hw=_IMAGES,
    ),
    "checkpoint": MessageSpec(
        "a model checkpoint was written to path",
        {},
        {"path": "str", "version": "int", "step": "int"},
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
        meta = ", ".join(f"{k} ({v})" for k, v in spec.meta.items())
        out += [f"``{name}``: {spec.doc}", "", f"  meta: {meta}", ""]
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
# Validation shared by encode and decode
# --------------------------------------------------------------------------------------------


def is_int(x: object, lo: int = -(2**63), hi: int = INT64_MAX) -> bool:
    return type(x) is int and lo <= x <= hi  # msgpack gives plain ints; bool is not one


def _meta_ok(value: object, kind: str) -> bool:
    if kind == "int":
        return is_int(value)
    if kind == "float":
        return (isinstance(value, float) or is_int(value)) and math.isfinite(value)  # type: ignore[arg-type]
    if kind == "str":
        return isinstance(value, str)
    if kind == "bool":
        return isinstance(value, bool)
    return isinstance(value, list) and all(isinstance(v, str) for v in value)  # str_list


_SCALAR_TYPES = frozenset(_SCALARS)


def check_meta(type_name: str, spec: MessageSpec, meta: object) -> None:
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
    for key, kind in spec.meta.items():
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
