from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import pytest
import yaml

from gsfix_online.core.config import (
    ConfigError,
    build,
    parse_override,
    read_yaml,
    rng,
    to_dict,
    write_config,
)


@dataclass(frozen=True)
class Inner:
    voxel_size: float = field(default=0.02, metadata=rng(1e-4, 1.0))
    levels: list[int] = field(default_factory=lambda: [1, 2])


@dataclass(frozen=True)
class Root:
    inner: Inner = field(default_factory=Inner)
    mode: Literal["a", "b"] = "a"
    count: int = field(default=3, metadata=rng(0, 10))
    flag: bool = False
    name: str = "x"


def test_defaults_yaml_and_overrides_in_priority_order(tmp_path):
    f1 = tmp_path / "one.yaml"
    f1.write_text("inner: {voxel_size: 0.05}\ncount: 4\n")
    f2 = tmp_path / "two.yaml"
    f2.write_text("count: 5\n")
    cfg = build(Root, [f1, f2], ["inner.levels=[3, 4]", "mode=b"])
    assert cfg == Root(inner=Inner(0.05, [3, 4]), mode="b", count=5)
    assert build(Root, [f1], ["count=7"]).count == 7


@pytest.mark.parametrize(
    ("text", "override", "msg"),
    [
        (
            "inner: {voxel_sise: 0.05}\n",
            None,
            "{f}: unknown key 'inner.voxel_sise'; did you mean 'inner.voxel_size'? "
            "(known keys: levels, voxel_size)",
        ),
        ("count: 2.5\n", None, "{f}: count: expected int, got 2.5 (float)"),
        ("count: 11\n", None, "{f}: count: value 11 is out of range [0, 10]"),
        ("flag: 1\n", None, "{f}: flag: expected bool, got 1 (int)"),
        ("mode: c\n", None, "{f}: mode: expected one of 'a', 'b', got 'c' (str)"),
        ("inner: 3\n", None, "{f}: inner: expected a mapping for section Inner"),
        ("inner: {levels: [1, x]}\n", None, "{f}: inner.levels[1]: expected int, got 'x'"),
        (
            "",
            "inner.voxel_size=-1",
            "command line 'inner.voxel_size=-1': inner.voxel_size: value -1.0 is out of range [0.0001, 1.0]",
        ),
        ("", "inner.voxel_size=.nan", "out of range"),
        ("", "nope=1", "command line 'nope=1': unknown key 'nope'"),
    ],
)
def test_errors_name_key_and_file(tmp_path, text, override, msg):
    f = tmp_path / "cfg.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        build(Root, [f], [override] if override else [])
    assert msg.format(f=f) in str(err.value) and "\n" not in str(err.value)


def test_bad_files_and_overrides(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        build(Root, [tmp_path / "missing.yaml"])
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        build(Root, [tmp_path / "list.yaml"])
    (tmp_path / "broken.yaml").write_text("a: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        build(Root, [tmp_path / "broken.yaml"])
    with pytest.raises(ConfigError, match="must look like key.sub=value"):
        parse_override("count")
    assert parse_override("inner.voxel_size=0.02") == (["inner", "voxel_size"], 0.02)


def test_write_load_round_trip(tmp_path):
    cfg = build(Root, overrides=["inner.voxel_size=0.5", "name=tank"])
    path = write_config(cfg, tmp_path / "out" / "config.yaml")
    assert build(Root, [path]) == cfg
    assert yaml.safe_load(path.read_text()) == to_dict(cfg)
    assert not list((tmp_path / "out").glob(".*"))  # no temporary files left behind


@dataclasses.dataclass(frozen=True)
class _Inner:
    lr: float = 1e-3
    steps: int = 10
    extra: dict[str, int] = dataclasses.field(default_factory=lambda: {"a": 1})


@dataclasses.dataclass(frozen=True)
class _Middle:
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    name: str = "m"


@dataclasses.dataclass(frozen=True)
class _Outer:
    # The parent's defaults for its sections differ from the section classes' own defaults
    middle: _Middle = dataclasses.field(
        default_factory=lambda: _Middle(_Inner(lr=5e-4, extra={"b": 2}), name="outer")
    )


def test_overriding_one_key_keeps_the_parents_defaults_of_the_section():
    cfg = build(_Outer, overrides=["middle.inner.steps=3"])
    assert cfg.middle == _Middle(_Inner(lr=5e-4, steps=3, extra={"b": 2}), name="outer")
    # a plain dict value replaces the default dict (it is a value, not a section)
    cfg = build(_Outer, overrides=["middle.inner.extra={c: 3}"])
    assert cfg.middle.inner.extra == {"c": 3} and cfg.middle.inner.lr == 5e-4
    assert build(_Outer).middle == _Outer().middle


@pytest.mark.parametrize(
    ("raw", "value"),
    [("3e-4", 3e-4), ("1E5", 1e5), ("-2.5e+1", -25.0), (".5", 0.5), ("12", 12), ("3e", "3e")],
)
def test_exponent_floats_are_numbers(raw, value, tmp_path):
    # YAML 1.1 (PyYAML's default) reads 3e-4 as a string; a learning rate written so is a number
    assert parse_override(f"a.b={raw}") == (["a", "b"], value)
    (tmp_path / "c.yaml").write_text(f"a: {{b: {raw}}}\n")
    assert read_yaml(tmp_path / "c.yaml") == {"a": {"b": value}}


# -- extends: a mapping starts from other files ------------------------------------------------


def test_extends_merges_bases_in_order_then_the_files_own_keys(tmp_path):
    (tmp_path / "a.yaml").write_text("inner: {voxel_size: 0.1, levels: [1]}\ncount: 1\nname: a\n")
    (tmp_path / "b.yaml").write_text("inner: {voxel_size: 0.2}\ncount: 2\n")
    (tmp_path / "top.yaml").write_text("extends: [a.yaml, b.yaml]\ncount: 3\n")
    assert read_yaml(tmp_path / "top.yaml") == {
        "inner": {"voxel_size": 0.2, "levels": [1]},  # b over a, key by key
        "count": 3,  # the file's own key over both
        "name": "a",
    }
    cfg = build(Root, [tmp_path / "top.yaml"], ["inner.levels=[5]"])
    assert cfg == Root(inner=Inner(0.2, [5]), count=3, name="a")


def test_extends_at_any_depth_is_relative_to_the_file_that_says_it(tmp_path):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "graphs").mkdir()
    (tmp_path / "profiles" / "inner.yaml").write_text("extends: base.yaml\nvoxel_size: 0.3\n")
    (tmp_path / "profiles" / "base.yaml").write_text("voxel_size: 0.5\nlevels: [7]\n")
    (tmp_path / "graphs" / "g.yaml").write_text(
        "inner: {extends: ../profiles/inner.yaml, levels: [8, 9]}\n"
    )
    assert read_yaml(tmp_path / "graphs" / "g.yaml") == {
        "inner": {"voxel_size": 0.3, "levels": [8, 9]}
    }


@pytest.mark.parametrize(
    ("texts", "msg"),
    [
        ({"top.yaml": "inner: {extends: gone.yaml}\n"}, "{d}/top.yaml: inner.extends: gone.yaml does not exist"),
        (
            {"top.yaml": "extends: a.yaml\n", "a.yaml": "extends: b.yaml\n", "b.yaml": "extends: a.yaml\n"},
            "{d}/b.yaml: extends: a.yaml extends itself (a.yaml -> b.yaml -> a.yaml)",
        ),
        ({"top.yaml": "extends: top.yaml\n"}, "extends itself (top.yaml -> top.yaml)"),
        ({"top.yaml": "extends: {a: 1}\n"}, "{d}/top.yaml: extends: expected a file name or a list"),
        ({"top.yaml": "extends: a.yaml\n", "a.yaml": "- 1\n"}, "{d}/a.yaml: top level must be a mapping"),
    ],
)  # fmt: skip
def test_a_bad_extends_is_one_line_naming_the_file(tmp_path, texts, msg):
    for name, text in texts.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError) as err:
        read_yaml(tmp_path / "top.yaml")
    assert msg.format(d=tmp_path) in str(err.value) and "\n" not in str(err.value)


def test_the_same_base_twice_is_no_cycle(tmp_path):
    (tmp_path / "base.yaml").write_text("count: 1\n")
    (tmp_path / "top.yaml").write_text("inner: {extends: base.yaml}\nother: {extends: base.yaml}\n")
    assert read_yaml(tmp_path / "top.yaml") == {"inner": {"count": 1}, "other": {"count": 1}}


# -- settings as the commands take them ---------------------------------------------------------


def test_an_unknown_key_names_the_nearest_valid_ones():
    with pytest.raises(
        ConfigError, match=r"unknown key 'inner\.voxel'; did you mean 'inner\.voxel_size'"
    ):
        build(Root, overrides=["inner.voxel=1"])
    # a key one level off: the key with the same last part
    with pytest.raises(ConfigError, match=r"unknown key 'levels'; did you mean 'inner\.levels'\?"):
        build(Root, overrides=["levels=[1]"])


def test_gather_then_to_overrides_round_trips(tmp_path):
    from gsfix_online.core.config import gather, to_overrides

    (tmp_path / "a.yaml").write_text("inner: {levels: [1, 2], voxel_size: 3.0e-4}\nname: 'x y'\n")
    settings, origins = gather([tmp_path / "a.yaml"], ["mode=b", "name=''"])
    assert settings == {"inner": {"levels": [1, 2], "voxel_size": 3e-4}, "name": "", "mode": "b"}
    assert origins["inner.levels"] == str(tmp_path / "a.yaml")
    assert origins["name"] == "command line 'name='''"
    again, _ = gather(None, to_overrides(settings))
    assert again == settings


def test_an_overlay_section_keeps_only_the_keys_given_and_checks_them():
    @dataclass(frozen=True)
    class WithOverlay:
        inner: dict = field(default_factory=dict, metadata={"overlay": Inner})

    assert build(WithOverlay).inner == {}
    assert build(WithOverlay, overrides=["inner.voxel_size=0.5"]).inner == {"voxel_size": 0.5}
    with pytest.raises(
        ConfigError, match=r"command line 'inner\.voxel_size=2': inner\.voxel_size: value 2"
    ):
        build(WithOverlay, overrides=["inner.voxel_size=2"])
    with pytest.raises(ConfigError, match="unknown key 'inner.nope'"):
        build(WithOverlay, overrides=["inner.nope=2"])


def test_a_bare_name_is_a_shipped_profile(tmp_path, monkeypatch):
    from pathlib import Path

    from gsfix_online.core.config import config_path, configs_dir

    monkeypatch.chdir(tmp_path)
    assert config_path("paper") == configs_dir() / "profiles" / "paper.yaml"
    assert config_path("mine.yaml") == Path("mine.yaml")  # a path stays a path
    (tmp_path / "paper").write_text("{}\n")
    assert config_path("paper") == Path("paper")  # a file of that name here wins
