"""The map server in a live graph (configs/graphs/repair_served.yaml), as real processes: a
client repairs a view of the live map over loopback while the repair graph runs on a tiny tank
(tiny GSFixer models, as tests/jobs/test_repair_run.py)."""

from __future__ import annotations

import io
import json
import math
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.jobs.repair_run import prepare, run_graph
from gsfix_online.repair.views import read_views
from tests.jobs.test_repair_run import EAGER, FAST, far_away

GRAPHS = Path(__file__).resolve().parents[2] / "configs" / "graphs"
W, H = 80, 60
FX = W / 2 / math.tan(math.radians(75.0) / 2)  # the tank camera's 75 degrees across
K = np.array([[FX, 0, (W - 1) / 2], [0, FX, (H - 1) / 2], [0, 0, 1]])


def test_repair_served_is_the_repair_graph_with_a_map_server():
    from gsfix_online.core.config import read_yaml

    served = read_yaml(GRAPHS / "repair_served.yaml")  # extends repair.yaml
    plain = read_yaml(GRAPHS / "repair.yaml")
    nodes = served.pop("nodes")
    server = nodes.pop("map_server")
    assert nodes["planner"]["inputs"].pop() == "map_server/views"
    assert nodes["splat"]["inputs"].pop() == "map_server/to_splat"
    assert (served.pop("name"), plain.pop("name")) == ("repair_served", "repair")
    assert nodes == plain.pop("nodes") and served == plain  # node for node, key for key
    assert server["kind"] == "map_server" and server["params"]["host"] == "127.0.0.1"
    assert server["routes"] == {"views": ["view_request/"], "to_splat": ["splat/export"]}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def tank(tmp_path_factory) -> Path:
    from gsfix_online.core.config import build
    from gsfix_online.scene import generate_ship_tank
    from gsfix_online.scene.config import ShipTankConfig
    from gsfix_online.sources.mcap_log import write_mcap

    out = tmp_path_factory.mktemp("tank")
    cfg = build(ShipTankConfig, overrides=[f"width={W}", f"height={H}", "n_frames=10"])
    generate_ship_tank(cfg, out, write_mcap=write_mcap)
    lines = (out / "novel" / "views.txt").read_text().splitlines()
    # the list's one view is 100 m out of the tank, where no map has any surface: skipped
    (out / "view2.txt").write_text("\n".join([*lines[:1], far_away(lines[3])]) + "\n")
    return out


def test_a_client_repairs_a_view_of_the_live_map_while_the_graph_runs(tank: Path, tmp_path: Path):
    from gsfix_online import MapClient
    from gsfix_online.mapping.splat.ply import read_ply

    port = _free_port()
    out = tmp_path / "run"
    # the base GSFixer: the repair does not wait for the fine-tuning run (the wiring, not quality)
    over = [*FAST, *EAGER, f"map_server.port={port}", "splat.refine_at_input_end=0",
            "repair.checkpoint=base"]  # fmt: skip
    graph, _, n = prepare(tank / "log.mcap", tank / "view2.txt", out, tank / "novel" / "color",
                          graph_path=GRAPHS / "repair_served.yaml", overrides=over)  # fmt: skip
    assert n == 1
    # 1. A client asks for a view of the scene at its own size as soon as the server is up,
    #    while the launcher (it wants the main thread) runs the graph to its end
    T = read_views(tank / "novel" / "views.txt")[0].T_world_cam
    progress: list[tuple[float, str]] = []
    answers: dict = {}

    def client() -> None:
        try:
            with MapClient(f"tcp://127.0.0.1:{port}", 120.0, connect_timeout_s=120.0) as c:
                answers["got"] = c.repair(T, K, W, H, progress=lambda f, t: progress.append((f, t)))
                answers["maps"], answers["live"] = c.maps(), c.splats()
        except Exception as exc:  # reported below, with the graph's log
            answers["error"] = exc

    asking = threading.Thread(target=client)
    asking.start()
    log = io.StringIO()
    res = run_graph(graph, log, 300)  # generous: other jobs may load the 2 cores
    asking.join(60)
    assert res.returncode == 0, res.message + log.getvalue()[-4000:]
    assert "error" not in answers, f"{answers['error']!r}\n{log.getvalue()[-4000:]}"
    got, maps, live = answers["got"], answers["maps"], answers["live"]
    # 2. The answer: GSFixer's repair of that view, distilled into a new version of the map
    assert got.image.shape == (H, W, 3) and got.image.dtype == np.uint8 and got.image.std() > 1
    assert got.map_version == 0 and got.reason.startswith("repaired: ")
    assert "GSFixer (the packaged base)" in got.reason and got.reason.endswith("map version 0")
    assert [(m.name, m.version) for m in maps] == [("live", 0)]
    ply = out / "work" / "live_map" / "export-0001" / "point_cloud"
    (exported,) = ply.glob("iteration_*/point_cloud.ply")
    assert live == exported.read_bytes() and maps[0].gaussians == len(read_ply(exported))
    # 3. Progress: each stage of the graph once, in order, fractions rising
    stages = []
    for _, text in progress:
        stage = text.split(":")[0]
        if not stages or stages[-1] != stage:
            stages.append(stage)
    assert stages == ["forwarded", "decided", "repaired", "distilled", "exported"], progress
    assert [f for f, _ in progress] == sorted(f for f, _ in progress)
    # 4. The run holds the view too: decided as a request, repaired, distilled
    m = json.loads((out / "metrics.json").read_text())
    views = {v["view"]: v for v in m["views"]}
    assert len(views) == 2 and views["000"]["skipped"]
    req = views["001"]
    assert req["repair"] and req["origin"] == "request" and req["timings_s"]["distill_s"] > 0
    assert (out / "views" / "001" / "fixed.png").is_file()
    # the writer ended on its own export (DIR/map), not on the server's
    assert m["map"] == "map" and list((out / "map" / "point_cloud").glob("iteration_*/*.ply"))
