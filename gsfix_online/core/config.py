"""Typed configuration machinery: dataclass sections, YAML loading, overrides, validation.

Every component owns a frozen dataclass of parameters. Fields declare their allowed range with
``field(metadata={"range": (lo, hi)})`` (inclusive, ``None`` for open) and their help text with
``metadata={"help": ...}``. This module turns nested dicts (from YAML files and ``a.b=value``
command-line overrides) into those dataclasses, and rejects unknown keys, wrong types and
out-of-range values with one-line errors that name the key and the file it came from (an
unknown key also names the nearest valid ones).

A mapping in a YAML file, at any depth, may start from other files: ``extends: other.yaml`` (or a
list of files, merged in order), relative to the file that says it; the mapping's own keys then
override key by key (:func:`read_yaml`). The shipped profiles (``configs/profiles/``) hold each
policy once, and graphs and other configs extend them (:func:`profile` builds one in code).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

from gsfix_online.core.io import atomic_write_text

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


def rng(lo: float | None, hi: float | None, help: str = "") -> dict[str, Any]:
    """Field metadata: inclusive range [lo, hi] (None = unbounded) plus help text."""
    return {"range": (lo, hi), "help": help}


# --------------------------------------------------------------------------------------------
# Merging sources: defaults < YAML < command line
# --------------------------------------------------------------------------------------------


class _Loader(yaml.SafeLoader):
    """YAML with the 1.2 core schema's floats: ``3e-4`` and ``1e5`` are numbers, as a user who
    writes a learning rate expects (YAML 1.1, PyYAML's default, reads them as strings)."""


_Loader.yaml_implicit_resolvers = {
    k: [r for r in v if r[0] != "tag:yaml.org,2002:float"]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def load_yaml(text: str) -> Any:
    """``yaml.safe_load`` with YAML 1.2 floats (``3e-4``)."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass


def parse_override(text: str) -> tuple[list[str], Any]:
    """``tsdf.voxel_size=0.02`` -> (["tsdf", "voxel_size"], 0.02); the value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like key.sub=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override '{text}' has an empty key")
    try:
        value = load_yaml(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override '{text}': value is not valid YAML ({exc.problem})") from None
    return key.split("."), value


def _merge(
    dst: dict[str, Any], src: dict[str, Any], origin: str, origins: dict[str, str], prefix: str = ""
) -> None:
    for key, value in src.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and isinstance(dst.get(key), dict):
            _merge(dst[key], value, origin, origins, path + ".")
        else:
            dst[key] = value
            _record_origin(value, origin, origins, path)


def _record_origin(value: Any, origin: str, origins: dict[str, str], path: str) -> None:
    origins[path] = origin
    if isinstance(value, dict):
        for k, v in value.items():
            _record_origin(v, origin, origins, f"{path}.{k}")


EXTENDS = "extends"  # a mapping's key naming the file(s) it starts from


def config_path(name: str | os.PathLike[str]) -> Path:
    """A ``-c`` argument as a file: the path itself, or for a bare name such as ``paper`` that
    is not a file here, the shipped profile ``configs/profiles/paper.yaml``."""
    p = Path(name)
    shipped = configs_dir() / "profiles" / f"{p.name}.yaml"
    if not p.exists() and not p.suffix and len(p.parts) == 1 and shipped.is_file():
        return shipped
    return p


def deep_merge(dst: dict[str, Any], src: dict[str, Any]) -> dict[str, Any]:
    """``src`` over ``dst``, in place: mappings merge key by key, anything else is replaced."""
    for key, value in src.items():
        if isinstance(value, dict) and isinstance(dst.get(key), dict):
            deep_merge(dst[key], value)
        else:
            dst[key] = copy.deepcopy(value)
    return dst


def read_yaml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A YAML file of sections, with every ``extends:`` resolved: a mapping that says
    ``extends: FILE`` (or ``[FILE, ...]``, relative to the file it is in) is that file's mapping
    (those files' merged in order) with its own keys merged over it, key by key."""
    return _read_yaml(Path(path), ())


def _read_yaml(p: Path, chain: tuple[Path, ...]) -> dict[str, Any]:
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist")
    try:
        data = load_yaml(p.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({exc})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{p}: top level must be a mapping of sections, got {type(data).__name__}"
        )
    return _extend(data, p, (*chain, p.resolve()), "")


def _extend(node: Any, p: Path, chain: tuple[Path, ...], key: str) -> Any:
    """``node`` (from file ``p``, at ``key``) with the ``extends`` of its mappings resolved."""
    if isinstance(node, list):
        return [_extend(v, p, chain, key) for v in node]
    if not isinstance(node, dict):
        return node
    own = {k: _extend(v, p, chain, f"{key}{k}.") for k, v in node.items() if k != EXTENDS}
    if EXTENDS not in node:
        return own
    refs = node[EXTENDS]
    where = f"{p}: {key}{EXTENDS}"
    if isinstance(refs, str):
        refs = [refs]
    if not isinstance(refs, list) or not all(isinstance(r, str) and r for r in refs):
        raise ConfigError(f"{where}: expected a file name or a list of them, got {refs!r}")
    merged: dict[str, Any] = {}
    for ref in refs:
        target = p.parent / ref
        if target.resolve() in chain:
            loop = " -> ".join(c.name for c in (*chain[chain.index(target.resolve()) :], target))
            raise ConfigError(f"{where}: {ref} extends itself ({loop})")
        if not target.is_file():
            raise ConfigError(f"{where}: {ref} does not exist ({target})")
        deep_merge(merged, _read_yaml(target, chain))
    return deep_merge(merged, own)


def gather(
    files: list[str | os.PathLike[str]] | None = None, overrides: list[str] | None = None
) -> tuple[dict[str, Any], dict[str, str]]:
    """YAML ``files`` (in order, then ``overrides``) merged into one nested dict, and where each
    dotted key came from (``{"a.b": "command line 'a.b=1'"}``)."""
    merged: dict[str, Any] = {}
    origins: dict[str, str] = {}
    for f in files or []:
        path = config_path(f)
        _merge(merged, read_yaml(path), str(path), origins)
    for text in overrides or []:
        keys, value = parse_override(text)
        nested: dict[str, Any] = value
        for k in reversed(keys):
            nested = {k: nested}
        _merge(merged, nested, f"command line '{text}'", origins)
    return merged, origins


def to_overrides(data: dict[str, Any], prefix: str = "") -> list[str]:
    """A nested dict as ``a.b=VALUE`` overrides (VALUE in YAML flow style), leaf by leaf:
    ``parse_override`` reads each back to the same key and value."""
    out = []
    for key, value in data.items():
        if isinstance(value, dict) and value:
            out += to_overrides(value, f"{prefix}{key}.")
            continue
        text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30, sort_keys=False)
        out.append(f"{prefix}{key}={text.strip().removesuffix('...').strip()}")
    return out


def origin_of(origins: dict[str, str], key: str, default: str = "defaults") -> str:
    """Where ``key`` (dotted) or the first key under it came from."""
    if key in origins:
        return origins[key]
    return next((o for k, o in origins.items() if k.startswith(key + ".")), default)


def full_key(origins: dict[str, str], key: str) -> str:
    """The whole key the user gave under ``key`` (``fixer`` -> ``fixer.inference.steps``)."""
    origin = origin_of(origins, key)
    keys = [k for k, o in origins.items() if o == origin and (k == key or k.startswith(key + "."))]
    return max(keys, key=lambda k: k.count("."), default=key)


def under(origins: dict[str, str], prefix: str, new_prefix: str = "") -> dict[str, str]:
    """The origins of the keys under ``prefix``, renamed to start with ``new_prefix``."""
    head = prefix + "."
    join = new_prefix + "." if new_prefix else ""
    return {join + k[len(head) :]: o for k, o in origins.items() if k.startswith(head)}


def key_paths(cls: type, prefix: str = "") -> list[str]:
    """Every dotted key of dataclass ``cls`` (sections and their keys), e.g. for suggestions."""
    out = []
    for name, tp in get_type_hints(cls).items():
        if name.startswith("_") or name not in {f.name for f in dataclasses.fields(cls)}:
            continue
        key = f"{prefix}{name}"
        out.append(key)
        if dataclasses.is_dataclass(tp):
            out += key_paths(tp, key + ".")  # type: ignore[arg-type]
    return out


def nearest(key: str, candidates: list[str], n: int = 3) -> list[str]:
    """The valid keys nearest to ``key``: the closest spellings, and keys ending in its last
    part (``steps`` -> ``inference.steps``)."""
    common = os.path.commonprefix([key, *candidates])
    cut = common.rfind(".") + 1  # compared below the prefix they all share
    rel = {c[cut:]: c for c in candidates}
    close = [rel[c] for c in difflib.get_close_matches(key[cut:], list(rel), n=n, cutoff=0.6)]
    last = key.rsplit(".", 1)[-1]
    tail = [c for c in candidates if c.rsplit(".", 1)[-1] == last and c not in close]
    return (close + tail)[:n]


def unknown_key(
    where: str, key: str, known: list[str], candidates: list[str], near_to: str | None = None
) -> ConfigError:
    """The one-line error for ``key``: the valid keys nearest to it (or to ``near_to``, its part
    that is unknown), then the known keys at its level."""
    near = nearest(near_to or key, candidates)
    hint = f"; did you mean {', '.join(repr(c) for c in near)}?" if near else ""
    return ConfigError(f"{where}: unknown key '{key}'{hint} (known keys: {', '.join(known)})")


def profile(cls: type[T], name: str, section: str | None = None) -> T:
    """The shipped profile ``configs/profiles/NAME`` (or its ``section``) as ``cls``: the one
    definition of a policy, for code that builds a component without a graph."""
    path = configs_dir() / "profiles" / name
    data = read_yaml(path)
    if section is not None:
        data = data.get(section) or {}
    return _build(cls, data, "", str(path) if section is None else f"{path}: {section}")


# --------------------------------------------------------------------------------------------
# Building dataclasses with validation
# --------------------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin in (list, tuple):
        args = get_args(tp)
        inner = _type_name(args[0]) if args else "any"
        return f"list of {inner}"
    if origin is dict:
        return "a mapping"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str, where: str) -> Any:
    """Check ``value`` against annotation ``tp``; return it converted (lists to tuples etc.)."""

    def fail(expected: str | None = None) -> ConfigError:
        shown = repr(value) if not isinstance(value, dict) else "a mapping"
        return ConfigError(
            f"{where}: {key}: expected {expected or _type_name(tp)}, got {shown} ({type(value).__name__})"
        )

    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise fail(f"a mapping for section {tp.__name__}")
        return _build(tp, value, key, where)
    if origin is Literal:
        if value not in get_args(tp):
            raise fail()
        return value
    if origin in (typing.Union, types.UnionType):
        for arg in get_args(tp):
            try:
                return _convert(value, arg, key, where)
            except ConfigError:
                continue
        raise fail()
    if origin is dict:
        if not isinstance(value, dict):
            raise fail("a mapping")
        key_tp, val_tp = get_args(tp) or (Any, Any)
        return {
            _convert(k, key_tp, f"{key}.{k}", where): _convert(v, val_tp, f"{key}.{k}", where)
            for k, v in value.items()
        }
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise fail()
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise fail(f"{len(args)} values")
            return tuple(
                _convert(v, a, f"{key}[{i}]", where)
                for i, (v, a) in enumerate(zip(value, args, strict=True))
            )
        inner = args[0] if args else Any
        items = [_convert(v, inner, f"{key}[{i}]", where) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if tp is type(None):
        if value is not None:
            raise fail()
        return None
    if tp is bool:
        if not isinstance(value, bool):
            raise fail()
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail()
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise fail()
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise fail()
        return value
    raise ConfigError(f"{where}: {key}: unsupported annotation {tp!r}")


def _check_range(value: Any, meta: dict[str, Any], key: str, where: str) -> None:
    lo, hi = meta.get("range", (None, None))
    if value is None or isinstance(value, (str, bool)):
        return
    values = value if isinstance(value, (list, tuple)) else [value]
    for v in values:
        if not isinstance(v, (int, float)):
            continue
        if v != v or (lo is not None and v < lo) or (hi is not None and v > hi):
            span = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
            raise ConfigError(f"{where}: {key}: value {v!r} is out of range {span}")


def _field_default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _overlay(cls: type, base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """``top`` over ``base`` for dataclass ``cls``: sections (dataclass fields) merge key by key,
    every other value (dicts of plain fields included) is replaced."""
    hints = get_type_hints(cls)
    out = dict(base)
    for k, v in top.items():
        tp = hints.get(k)
        section = tp is not None and dataclasses.is_dataclass(tp)
        if section and isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _overlay(tp, out[k], v)
        else:
            out[k] = v
    return out


def _build(cls: type[T], data: dict[str, Any], prefix: str, origins: dict[str, str] | str) -> T:
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}

    def where_of(key: str) -> str:
        if isinstance(origins, str):
            return origins
        return origins.get(key, "defaults")

    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in fields:
            head = f"{prefix}." if prefix else ""
            raise unknown_key(where_of(key), key, sorted(fields), key_paths(cls, head))
        where = where_of(key)
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, dict):
                raise ConfigError(
                    f"{where}: {key}: expected a mapping for section {tp.__name__}, got {value!r}"
                )
            # Keys not given keep the parent's default for this section (a default_factory may
            # differ from the section class's own defaults), not the class defaults.
            default = _field_default(fields[name])
            if dataclasses.is_dataclass(default):
                value = _overlay(tp, to_dict(default), value)
            kwargs[name] = _build(tp, value, key, origins)
            continue
        schema = fields[name].metadata.get("overlay")
        if schema is not None:  # keys to set over another config: checked, kept as given
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: {key}: expected a mapping of {schema.__name__} keys")
            _build(schema, value, key, origins)
            kwargs[name] = copy.deepcopy(value)
            continue
        converted = _convert(value, tp, key, where)
        _check_range(converted, fields[name].metadata, key, where)
        kwargs[name] = converted
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where_of(prefix)}: {prefix or cls.__name__}: {exc}") from None
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ValueError as exc:
            raise ConfigError(f"{where_of(prefix)}: {prefix or cls.__name__}: {exc}") from None
    return obj


def build(
    cls: type[T],
    files: list[str | os.PathLike[str]] | None = None,
    overrides: list[str] | None = None,
    base: dict[str, Any] | None = None,
) -> T:
    """Build ``cls`` from defaults < ``base`` dict < YAML ``files`` (in order) < ``overrides``."""
    merged: dict[str, Any] = {}
    origins: dict[str, str] = {}
    if base:
        _merge(merged, base, "defaults", origins)
    given, given_origins = gather(files, overrides)
    _merge(merged, given, "", origins)
    origins.update(given_origins)
    return build_from(cls, merged, origins)


def build_from(cls: type[T], data: dict[str, Any], origins: dict[str, str], prefix: str = "") -> T:
    """Build ``cls`` from a nested dict (e.g. from :func:`gather`); errors name each key's origin
    and the key as ``prefix.key``."""
    return _build(cls, data, prefix, origins)


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain dict of YAML-safe values (tuples become lists)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


def configs_dir() -> Path:
    """The shipped configs (``graphs/``, ``profiles/``, ``sources/``): the repository's
    ``configs/`` folder, installed with the package as ``gsfix_online.configs`` (so a wheel finds
    them wherever it runs)."""
    from importlib.resources import files

    return Path(str(files("gsfix_online.configs")))


def write_config(obj: Any, path: str | os.PathLike[str]) -> Path:
    """Save the resolved config as YAML (atomically); returns the path written."""
    p = Path(path)
    atomic_write_text(p, yaml.safe_dump(to_dict(obj), sort_keys=False))
    return p
