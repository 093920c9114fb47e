"""The wheel a user installs: one top-level package, with the nodes, the shipped profiles and
graphs, the base weights and the node registry, and graphs that load from it."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # no build isolation: builds offline with the environment's setuptools, in about 10 s
    cmd = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
           "-w", str(out), str(ROOT)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    (path,) = out.glob("gsfix_online-*.whl")
    return path


def test_the_wheel_installs_one_top_level_package(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"gsfix_online"}
    top_level = [n for n in names if n.endswith(".dist-info/top_level.txt")]
    if top_level:  # setuptools writes it: the packages site-packages gets
        text = zipfile.ZipFile(wheel).read(top_level[0]).decode().split()
        assert text == ["gsfix_online"]


def test_the_wheel_carries_nodes_configs_weights_and_every_package(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    for node in (ROOT / "nodes").glob("*.py"):
        assert f"gsfix_online/nodes/{node.name}" in names
    for cfg in (ROOT / "configs").rglob("*.yaml"):
        assert f"gsfix_online/configs/{cfg.relative_to(ROOT / 'configs').as_posix()}" in names
    for weight in (ROOT / "gsfix_online/fixer/weights/base").iterdir():
        assert f"gsfix_online/fixer/weights/base/{weight.name}" in names
    # every package folder is listed in pyproject.toml (an unlisted one would be left out)
    for init in (ROOT / "gsfix_online").rglob("__init__.py"):
        assert init.relative_to(ROOT).as_posix() in names
    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    found = {p.parent.relative_to(ROOT).as_posix().replace("/", ".")
             for p in (ROOT / "gsfix_online").rglob("__init__.py")}  # fmt: skip
    assert found | {"gsfix_online.nodes", "gsfix_online.configs"} == set(listed)


def test_graphs_and_node_kinds_load_from_the_unpacked_wheel(wheel: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    script = (
        "import gsfix_online, sys\n"
        "from gsfix_online.core.config import configs_dir\n"
        "from gsfix_online.runtime.graph import load_graph, node_module\n"
        f"assert gsfix_online.__file__.startswith({str(site)!r}), gsfix_online.__file__\n"
        f"assert str(configs_dir()).startswith({str(site)!r}), configs_dir()\n"
        "graphs = sorted((configs_dir() / 'graphs').glob('*.yaml'))\n"
        "for g in graphs:\n"
        "    graph = load_graph(g)\n"
        "    for entry in graph.nodes.values():\n"
        "        m = node_module(entry.kind)\n"
        f"        assert m.__file__.startswith({str(site)!r}), m.__file__\n"
        "print(len(graphs))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(site)}
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert int(done.stdout.split()[-1]) == len(list((ROOT / "configs/graphs").glob("*.yaml")))
