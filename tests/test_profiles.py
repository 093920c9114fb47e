"""The shipped profiles (configs/profiles/): each policy defined once, and read from there by the
graphs, the reports, the corpus and the map server."""

from __future__ import annotations

from gsfix_online.core.config import build, configs_dir, profile, to_dict
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.mapping.splat.mapper import MapperConfig
from gsfix_online.runtime.graph import load_graph, node_params

GRAPH = configs_dir() / "graphs" / "repair.yaml"


def _params(graph, name: str) -> dict:
    return to_dict(node_params(graph.nodes[name]))


def test_every_profile_builds_its_config():
    import gsfix_online.nodes.trainer as trainer

    from gsfix_online.jobs.config import Config

    assert profile(MapperConfig, "mapper_cpu.yaml").kf_iters == 2
    assert profile(FixerConfig, "repair_cpu.yaml").inference.shifts == 4
    assert profile(trainer.Params, "trainer_cpu.yaml").policy.max_steps_per_run == 600
    assert build(Config, [configs_dir() / "profiles" / "paper.yaml"]).fixer["inference"] == {
        "steps": 4,
        "shifts": 1,
    }


def test_the_repair_graph_runs_the_profiles():
    import gsfix_online.nodes.trainer as trainer

    graph = load_graph(GRAPH)
    assert _params(graph, "splat")["mapper"] == to_dict(profile(MapperConfig, "mapper_cpu.yaml"))
    repair = profile(FixerConfig, "repair_cpu.yaml")
    assert _params(graph, "repair")["fixer"] == to_dict(repair)
    tp = profile(trainer.Params, "trainer_cpu.yaml")
    assert _params(graph, "trainer")["fixer"] == to_dict(tp.fixer)
    assert _params(graph, "trainer")["policy"] == to_dict(tp.policy)
    # the trainer scores the repairs the repair node will make
    assert tp.fixer.inference == repair.inference and tp.fixer.model == repair.model


def test_the_reports_the_corpus_and_the_map_server_read_the_profiles():
    import dataclasses

    import gsfix_online.nodes.trainer as trainer

    from gsfix_online.jobs.fixer_report import FixerReportConfig
    from gsfix_online.jobs.map_corpus import MapCorpusConfig
    from gsfix_online.jobs.splat_report import ReportConfig
    from gsfix_online.services.map_server import ServerConfig

    mapper = profile(MapperConfig, "mapper_cpu.yaml")
    assert MapCorpusConfig().mapper == mapper
    report = FixerReportConfig()
    assert report.mapper == dataclasses.replace(mapper, refine_views=1)
    assert report.fixer == profile(trainer.Params, "trainer_cpu.yaml").fixer
    assert ServerConfig().fixer == profile(FixerConfig, "repair_cpu.yaml")
    splat = build(ReportConfig, [configs_dir() / "report_splat_fast.yaml"])
    assert splat.mapper == dataclasses.replace(mapper, refine_views=1)


def test_repair_served_is_the_repair_graph_plus_its_map_server():
    plain = load_graph(GRAPH)
    served = load_graph(configs_dir() / "graphs" / "repair_served.yaml")
    assert set(served.nodes) == {*plain.nodes, "map_server"}
    for name in plain.nodes:
        assert _params(served, name) == _params(plain, name), name


def test_paper_selects_the_papers_protocol_on_every_node_that_runs_gsfixer():
    graph = load_graph(GRAPH, files=["paper"])  # -c paper
    for name in ("trainer", "repair"):
        fx = _params(graph, name)["fixer"]
        assert (fx["inference"]["steps"], fx["inference"]["shifts"]) == (4, 1), name
    train = _params(graph, "trainer")["fixer"]["train"]
    assert (train["lr"], train["grad_accum"], train["ema_decay"], train["wise_alpha"]) == (
        3e-5,
        16,
        0.0,
        1.0,
    )
    assert _params(graph, "splat") == _params(load_graph(GRAPH), "splat")  # GSFixer only
