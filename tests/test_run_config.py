"""Settings given to a command reach the nodes that use them, and the resolved config written
beside a run is what each node receives: ``gsfix-online demo`` on a tiny tank, stopped before
any node starts."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from gsfix_online.apps.cli import main
from gsfix_online.core.config import read_yaml, to_dict

TINY = ["scene.width=64", "scene.height=48", "scene.n_frames=6", "scene.n_novel=2"]


class _Stop(Exception):
    """Raised instead of launching the graph: everything up to the launch has run."""


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> Path:
    """``gsfix-online demo`` with settings for the root, the shared fixer section and a node,
    up to the moment the graph would start."""
    import gsfix_online.jobs.repair_run as job

    out = tmp_path_factory.mktemp("demo")
    mp = pytest.MonkeyPatch()

    def stop(*args, **kwargs):
        raise _Stop

    mp.setattr(job, "run_graph", stop)
    try:
        with pytest.raises(_Stop):
            main(["demo", "--out", str(out), "--no-progress", *TINY,
                  "fixer.inference.steps=2", "splat.distill_passes=5"])  # fmt: skip
    finally:
        mp.undo()
    return out


def test_demo_fixer_settings_reach_the_trainer_and_the_repair_node(demo_run: Path):
    # the demo's own config says what was set, the resolved graph what every node runs with
    cfg = yaml.safe_load((demo_run / "config.yaml").read_text())
    assert cfg["fixer"] == {"inference": {"steps": 2}}
    assert "splat.distill_passes=5" in cfg["demo"]["extra_overrides"]
    assert set(cfg) == {"replay", "scene", "fixer", "demo"}  # the sections the demo reads
    nodes = read_yaml(demo_run / "repair" / "work" / "graph.yaml")["nodes"]
    for name in ("trainer", "repair"):
        assert nodes[name]["params"]["fixer"]["inference"] == {
            "steps": 2,
            "shifts": 4,  # the rest as the profile has it
            "batch_size": 4,
            "seed": 0,
        }
    assert nodes["splat"]["params"]["distill_passes"] == 5
    assert nodes["planner"]["params"]["proposals"]["max_proposals"] == 4  # the demo's own


def test_the_demo_config_runs_the_same_demo_again(demo_run: Path):
    from gsfix_online.jobs.config import load_config
    from gsfix_online.jobs.demo import READS, graph_settings

    cfg = load_config([demo_run / "config.yaml"], reads=READS)
    settings, _ = graph_settings(cfg)
    assert settings["fixer"] == {"inference": {"steps": 2}}
    assert settings["splat"] == {"distill_passes": 5}


def test_each_node_receives_what_the_resolved_graph_says(demo_run: Path, tmp_path: Path):
    from gsfix_online.runtime.graph import load_graph, read_node_file, write_node_file

    graph_file = demo_run / "repair" / "work" / "graph.yaml"
    written = read_yaml(graph_file)["nodes"]
    graph = load_graph(graph_file)  # as run_graph loads it
    for name in graph.nodes:
        path = write_node_file(graph, name, tmp_path / f"{name}.yaml")  # as the launcher does
        _, params = read_node_file(path, name)  # as the node's process parses it
        assert to_dict(params) == written[name]["params"], name


@pytest.mark.parametrize(
    ("argv", "msg"),
    [
        (["demo", "fixer.no_such_key=1"], "command line 'fixer.no_such_key=1': unknown key 'fixer.no_such_key'"),
        (["demo", "fixer.inference.stepz=2"], "did you mean 'fixer.inference.steps'?"),
        (["demo", "splat.mapper.kf_itrs=2"], "did you mean 'splat.mapper.kf_iters'"),
        (["demo", "source.stride=2"], "gsfix-online demo does not read 'source.stride'"),
        (["demo", "splatt.threads=2"], "unknown key 'splatt.threads'; did you mean 'splat'?"),
        (["scene", "ship-tank", "fixer.inference.steps=2", "--out", "x"], "gsfix-online scene does not read 'fixer.inference.steps'"),
        (["info", "x", "scene.width=64"], "gsfix-online info does not read 'scene.width'"),
        (["export", "ply", "x", "fixer.inference.steps=2"], "gsfix-online export reads no settings"),
        (["repair", "--input", "x", "--holdout", "2", "--out", "y", "scene.width=64"], "unknown key 'scene.width'"),
        (["bench", "fixer.inference.steps=0"], "fixer.inference.steps: value 0 is out of range"),
        (["launch", "x.yaml", "port_base=1"], "does not exist"),
        (["stress", "minutes=1", "aera=splat"], "unknown key 'aera'; did you mean 'area'?"),
        (["view", "RUN", "prot=8081"], "unknown key 'prot'; did you mean 'port'?"),
    ],
)  # fmt: skip
def test_a_setting_nothing_reads_is_a_one_line_error(argv, msg, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing is written anywhere else
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1, err
    assert not (tmp_path / "outputs").exists()


def test_config_prints_the_fixer_keys_given(capsys):
    assert main(["config", "-c", "paper", "fixer.inference.steps=3"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["fixer"]["inference"] == {"steps": 3, "shifts": 1}
    assert printed["fixer"]["train"]["lr"] == 3e-5
