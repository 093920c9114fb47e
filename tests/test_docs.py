"""The documentation stays true: its commands, options and config keys exist, and the site builds.

Every ``gsfix-online COMMAND ...`` the docs (``docs/**/*.md`` and ``README.md``) show in code is
checked against that command's ``--help``: the command must exist and every ``--option`` shown
with it must be one of its options. Every config key the docs show (``section.key`` or
``section.key=value`` in code, and the keys of YAML blocks whose sections are config sections)
must resolve in the config schema: the root config's sections, the params of the graphs' nodes
(``NODE.KEY``), ``nodes.NODE.KEY`` and the sections of the other jobs' configs. The results log
(``docs/results``, a link to ``benchmarks/results``) is history: its commands ran at the commits
it names and are not checked. Last, ``mkdocs build --strict`` builds the site into a temporary
folder, so a broken link or a page missing from the nav fails here.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import io
import json
import re
import subprocess
import sys
import types
import typing
from pathlib import Path
from typing import Any

import pytest
import yaml

from gsfix_online.apps.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def doc_files() -> list[Path]:
    pages = [p for p in sorted(DOCS.rglob("*.md")) if "results" not in p.relative_to(DOCS).parts]
    readme = ROOT / "README.md"
    return [*pages, readme] if readme.is_file() else pages


# --------------------------------------------------------------------------------------------
# Code in Markdown
# --------------------------------------------------------------------------------------------

FENCE = re.compile(r"^```([\w-]*)[^\n]*\n(.*?)^```", re.S | re.M)
SPAN = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")


def code_of(text: str) -> tuple[list[tuple[str, str]], list[str]]:
    """The fenced blocks as (language, body) and the inline code spans of a page."""
    blocks = [(m.group(1), m.group(2)) for m in FENCE.finditer(text)]
    prose = FENCE.sub("", text)
    return blocks, SPAN.findall(prose)


def commands_in(code: str) -> list[list[str]]:
    """Each ``gsfix-online ...`` in a piece of code, as its words up to the end of the shell
    command (a newline, ``;``, ``&&``, a pipe between spaces or a comment)."""
    code = code.replace("\\\n", " ")
    out = []
    for m in re.finditer(r"(?<![\w/-])gsfix-online\s+([^\n]*)", code):
        rest = re.split(r"\s\|\s|;|&&|\s#", m.group(1))[0]
        out.append(rest.split())
    return out


def test_commands_in_code_are_found() -> None:
    blocks, spans = code_of(
        "Run `gsfix-online repair --input X --out Y`, then:\n\n```bash\n"
        "gsfix-online view RUN --port 8081  # the viewer\nmake demo && gsfix-online \\\n"
        "  bench --quick\n```\n"
    )
    found = [c for _, body in blocks for c in commands_in(body)]
    found += [c for span in spans for c in commands_in(span)]
    assert found == [
        ["view", "RUN", "--port", "8081"],
        ["bench", "--quick"],
        ["repair", "--input", "X", "--out", "Y"],
    ]


# --------------------------------------------------------------------------------------------
# Commands and options
# --------------------------------------------------------------------------------------------

OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
NESTED = ("fixer",)  # commands whose jobs are subcommands with options of their own


def help_text(argv: list[str]) -> str:
    """``gsfix-online ARGV --help`` as the command prints it."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([*argv, "--help"])
    assert exit_info.value.code == 0, f"gsfix-online {' '.join(argv)} --help failed"
    return buf.getvalue()


def subcommands() -> set[str]:
    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return set(sub.choices)


def _command_key(words: list[str]) -> tuple[str, ...] | None:
    if not words or words[0].startswith("-") or not re.fullmatch(r"[a-z][a-z-]*", words[0]):
        return None  # `gsfix-online --help`, or a placeholder such as COMMAND
    if words[0] in NESTED and len(words) > 1 and not words[1].startswith("-"):
        return (words[0], words[1])
    return (words[0],)


def shown_commands() -> dict[tuple[str, ...], dict[str, set[str]]]:
    """Command -> option -> the pages that show it with that option ("" for no option)."""
    shown: dict[tuple[str, ...], dict[str, set[str]]] = {}
    for page in doc_files():
        blocks, spans = code_of(page.read_text())
        for code in [body for _, body in blocks] + spans:
            for words in commands_in(code):
                key = _command_key(words)
                if key is None:
                    continue
                options = shown.setdefault(key, {})
                for opt in ["", *OPTION.findall(" ".join(words[len(key) :]))]:
                    options.setdefault(opt, set()).add(str(page.relative_to(ROOT)))
    return shown


def test_the_docs_name_the_main_commands() -> None:
    shown = shown_commands()
    for command in ("demo", "repair", "bench", "view", "serve", "launch", "export", "info"):
        assert (command,) in shown, f"no page shows gsfix-online {command}"


def test_every_command_the_docs_show_exists_with_every_option_shown() -> None:
    known = subcommands()
    problems = []
    for key, options in sorted(shown_commands().items()):
        if key[0] not in known:
            pages = sorted(options[""])
            problems.append(f"gsfix-online {key[0]}: no such command ({', '.join(pages)})")
            continue
        accepted = set(OPTION.findall(help_text(list(key))))
        for opt, pages in sorted(options.items()):
            if opt and opt not in accepted:
                where = ", ".join(sorted(pages))
                problems.append(f"gsfix-online {' '.join(key)} has no {opt} ({where})")
    assert not problems, "\n".join(problems)


def test_the_option_check_fails_on_an_option_a_command_lacks() -> None:
    accepted = set(OPTION.findall(help_text(["repair"])))
    assert "--holdout" in accepted and "--views-gt" in accepted
    assert "--quick" not in accepted  # bench's, not repair's
    assert "--minutes" in set(OPTION.findall(help_text(["stress"])))
    assert "--resume" in set(OPTION.findall(help_text(["fixer", "pretrain"])))


def test_the_command_line_lists_the_commands_it_runs() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "gsfix_online.apps.cli", "--help"],
        capture_output=True, text=True, cwd=ROOT, check=True, timeout=120,
    ).stdout  # fmt: skip
    for command in ("demo", "repair", "bench", "view", "serve", "export"):
        assert re.search(rf"^\s+{command}\s", out, re.M), f"gsfix-online --help lacks {command}"


# --------------------------------------------------------------------------------------------
# Config keys
# --------------------------------------------------------------------------------------------


def _unwrap(tp: Any) -> Any:
    """``X | None`` -> X."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def resolves(cls: Any, parts: list[str]) -> bool:
    """Whether the dotted key ``parts`` names a field (or a section) of dataclass ``cls``; a
    last part ending in ``*`` must start the name of one."""
    if parts and parts[-1].endswith("*"):
        if not resolves(cls, parts[:-1]):
            return False
        for part in parts[:-1]:
            cls = _unwrap(typing.get_type_hints(cls)[part])
        stem = parts[-1][:-1]
        return dataclasses.is_dataclass(cls) and any(
            f.name.startswith(stem) for f in dataclasses.fields(cls)
        )
    for i, part in enumerate(parts):
        if not dataclasses.is_dataclass(cls):
            origin = typing.get_origin(cls)
            return cls is Any or origin is dict or cls is dict  # a free mapping takes any key
        fields = {f.name: f for f in dataclasses.fields(cls)}
        if part not in fields:
            return False
        overlay = fields[part].metadata.get("overlay")
        cls = overlay or _unwrap(typing.get_type_hints(cls)[part])
        if i == len(parts) - 1:
            return True
    return True


def schema() -> dict[str, list[Any]]:
    """Section name -> the dataclasses a key starting with it may belong to."""
    from gsfix_online.core.config import read_yaml
    from gsfix_online.jobs.config import SECTIONS, Config
    from gsfix_online.jobs.pretrain import PretrainConfig
    from gsfix_online.mapping.splat.config import MapperConfig
    from gsfix_online.mapping.tsdf import TsdfConfig
    from gsfix_online.runtime.graph import GraphConfig, node_module
    from gsfix_online.services.live_map import LiveConfig
    from gsfix_online.services.map_server import ServerConfig

    roots: dict[str, list[Any]] = {}
    for name in SECTIONS:  # the root config: source, replay, scene, fixer, demo
        f = {f.name: f for f in dataclasses.fields(Config)}[name]
        roots.setdefault(name, []).append(
            f.metadata.get("overlay") or typing.get_type_hints(Config)[name]
        )
    for path in sorted((ROOT / "configs" / "graphs").glob("*.yaml")):  # NODE.KEY of the graphs
        for node, entry in (read_yaml(path).get("nodes") or {}).items():
            roots.setdefault(node, []).append(node_module(entry["kind"]).Params)
    # the sections of the other commands' own configs (report, fixer pretrain, serve) and the
    # profiles' names for a component's config (`mapper.kf_iters` in mapper_cpu.yaml)
    extra = {
        "mapper": MapperConfig, "tsdf": TsdfConfig, "pretrain": PretrainConfig,
        "server": ServerConfig, "live": LiveConfig,
    }  # fmt: skip
    for name, cls in extra.items():
        roots.setdefault(name, []).append(cls)
    roots["graph"] = [GraphConfig]
    return roots


KEY = re.compile(
    r"(?<![\w./-])([a-z_][a-z0-9_]*(?:\.(?:[a-z_][a-z0-9_]*|\{[a-z0-9_,]+\}\w*))+\*?)"
)  # a trailing * stands for every key that starts so (`scene.room_*`)
FILE_SUFFIXES = {
    "yaml", "yml", "json", "py", "png", "ply", "glb", "mcap", "md", "csv", "txt", "html", "pt",
    "rrd", "db3", "bag", "npz", "sha256", "prev", "log", "jpg", "whl", "gz", "xz", "tar",
}  # fmt: skip


def _expand(key: str) -> list[str]:
    """``planner.skip.{hole,empty}_fraction`` -> both keys."""
    m = re.search(r"\{([a-z0-9_,]+)\}", key)
    if not m:
        return [key]
    return [
        k for alt in m.group(1).split(",") for k in _expand(key[: m.start()] + alt + key[m.end() :])
    ]


def _is_code_reference(key: str) -> bool:
    """``repair.fallback.for_view``: a module or attribute of the package, not a setting."""
    parts = key.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module("gsfix_online." + ".".join(parts[:cut]))
        except ImportError:
            continue
        for attr in parts[cut:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def keys_in(code: str, roots: dict[str, list[Any]]) -> list[str]:
    """The config keys shown in a piece of code: dotted names that start with a section."""
    out = []
    for m in KEY.finditer(code):
        key = m.group(1)
        if key.split(".")[0] not in roots or key.rsplit(".", 1)[-1] in FILE_SUFFIXES:
            continue
        out += _expand(key)
    return out


def _yaml_keys(data: Any, prefix: str = "") -> list[str]:
    if not isinstance(data, dict):
        return [prefix] if prefix else []
    out = []
    for k, v in data.items():
        if k == "extends":
            continue
        key = f"{prefix}.{k}" if prefix else str(k)
        out += _yaml_keys(v, key) if isinstance(v, dict) and v else [key]
    return out


def _shows_error(code: str) -> bool:
    """A wrong key on purpose, shown with the error it gives."""
    return "error:" in code or "unknown key" in code


def shown_keys(roots: dict[str, list[Any]]) -> dict[str, set[str]]:
    """Key -> the pages that show it."""
    shown: dict[str, set[str]] = {}
    for page in doc_files():
        blocks, spans = code_of(page.read_text())
        keys = [k for span in spans if not _shows_error(span) for k in keys_in(span, roots)]
        for lang, body in blocks:
            if _shows_error(body):
                continue
            if lang in ("yaml", "yml"):
                data = yaml.safe_load(body)
                if isinstance(data, dict) and data and set(data) <= set(roots):
                    keys += _yaml_keys(data)
            else:
                keys += keys_in(body, roots)
        for key in keys:
            shown.setdefault(key, set()).add(str(page.relative_to(ROOT)))
    return shown


def key_is_known(key: str, roots: dict[str, list[Any]]) -> bool:
    head, *rest = key.split(".")
    if head == "nodes" and len(rest) >= 2:  # nodes.NODE.KEY: a node's entry in the graph
        from gsfix_online.runtime.graph import NodeEntry

        return rest[0] in roots and resolves(NodeEntry, rest[1:])
    if any(resolves(cls, rest) for cls in roots.get(head, [])):
        return True
    return _is_code_reference(key)


@pytest.fixture(scope="module")
def roots() -> dict[str, list[Any]]:
    return schema()


def test_config_keys_shown_in_the_docs_exist(roots: dict[str, list[Any]]) -> None:
    shown = shown_keys(roots)
    assert len(shown) > 40, f"only {len(shown)} keys found: is the extraction broken?"
    bad = [
        f"{key} ({', '.join(sorted(pages))})"
        for key, pages in sorted(shown.items())
        if not key_is_known(key, roots)
    ]
    assert not bad, "unknown config keys in the docs:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("key", "known"),
    [
        ("fixer.inference.steps", True),
        ("fixer.inference.stepz", False),
        ("splat.mapper.kf_iters", True),
        ("splat.mapper.kf_iterz", False),
        ("planner.skip.hole_fraction", True),
        ("mapper.growth.init_opacity", True),
        ("source.max_assoc_s", True),
        ("source.max_assoc", False),
        ("nodes.splat.restart", True),
        ("nodes.splat.restarts", False),
        ("pretrain.maps.views", True),
        ("server.max_pixels", True),
        ("repair.fallback.for_view", True),  # a function's path, not a setting
        ("repair.fallback.for_views", False),
        ("scene.room_*", True),
        ("scene.rooms_*", False),
    ],
)
def test_the_key_check_tells_known_keys_from_unknown(
    roots: dict[str, list[Any]], key: str, known: bool
) -> None:
    assert key_is_known(key, roots) is known


def test_keys_in_code_and_yaml_blocks_are_found(roots: dict[str, list[Any]]) -> None:
    assert keys_in("gsfix-online demo fixer.inference.steps=2 -c paper", roots) == [
        "fixer.inference.steps"
    ]
    assert keys_in("planner.skip.{hole,empty}_fraction", roots) == [
        "planner.skip.hole_fraction",
        "planner.skip.empty_fraction",
    ]
    assert keys_in("configs/graphs/repair.yaml, mesh.ply, scene.json", roots) == []
    assert _yaml_keys({"fixer": {"inference": {"steps": 4}, "masks": {"p_mesh_only": 0}}}) == [
        "fixer.inference.steps",
        "fixer.masks.p_mesh_only",
    ]


# --------------------------------------------------------------------------------------------
# The site
# --------------------------------------------------------------------------------------------


def test_results_log_is_linked_into_the_docs() -> None:
    link = DOCS / "results"
    assert link.is_symlink() and not Path(link.readlink()).is_absolute()
    assert link.resolve() == (ROOT / "benchmarks" / "results").resolve()
    assert (link / "README.md").is_file()


def test_the_site_builds_strictly(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs", reason="the docs extra: pip install -e '.[docs]'")
    pytest.importorskip("mkdocstrings")
    res = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-4000:]
    site = tmp_path / "site"
    for page in ("index.html", "install/index.html", "api/client/index.html", "results/index.html"):
        assert (site / page).is_file(), f"the site lacks {page}"
    # the API reference is generated from the docstrings
    client = (site / "api/client/index.html").read_text()
    assert 'id="gsfix_online.apps.client.MapClient.repair"' in client
    # pictures and the results' data files reach the site
    assert (site / "results" / "bench_quick_pareto.png").is_file()
    assert (site / "results" / "bench_quick_cpu.json").is_file()


# --------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------

IMAGE = re.compile(r"!\[[^\]]*\]\(([^)]+\.png)\)")


def test_every_picture_exists_and_names_the_command_that_makes_it() -> None:
    pictures = 0
    for page in doc_files():
        text = page.read_text()
        for m in IMAGE.finditer(text):
            pictures += 1
            target = (page.parent / m.group(1)).resolve()
            assert target.is_file(), f"{page.name}: {m.group(1)} does not exist"
            after = text[m.end() : m.end() + 700]
            assert re.search(r"`(gsfix-online |make |\.venv/bin/python benchmarks/)", after), (
                f"{page.name}: {m.group(1)} does not say the command that regenerates it"
            )
    assert pictures >= 3


def test_the_stage_timing_bar_reads_a_demo_summary_and_a_run(tmp_path: Path) -> None:
    import runpy

    script = runpy.run_path(str(ROOT / "benchmarks" / "figure_stage_times.py"))
    demo = json.loads((ROOT / "benchmarks/results/one_house_demo_wheel_cpu.json").read_text())
    rows = script["stage_rows"](demo)
    assert rows[0] == ("scene", pytest.approx(16.349), False)
    assert ("GSFixer", pytest.approx(3.129), True) in rows
    run = {"timings_s": {"collect_s": 5.0}, "summary": {"stage_time_totals_s": {"fix_s": 1.5}}}
    assert script["stage_rows"](run) == [("collect (graph)", 5.0, False), ("GSFixer", 1.5, True)]
    out = tmp_path / "stages.png"
    assert script["main"]([str(ROOT / "benchmarks/results/one_house_demo_wheel_cpu.json"),
                           "--out", str(out)]) == 0  # fmt: skip
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
