"""LiveMap: a live map's repairs followed through the graph, with no sockets.

The map server's graph side (``nodes.map_server.build_node``) runs on the in-memory transport
against the graph's own components: a real PlannerService numbers and decides the forwarded
view (its decision messages are the planner node's), a real SplatService distils the repaired
view into a tiny Gaussian map and exports it. Every message crosses the wire format.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gsfix_online.nodes.map_server import Params, build_node

from gsfix_online.mapping.splat.mapper import DensifyConfig, MapperConfig
from gsfix_online.mapping.splat.ply import save_model
from gsfix_online.repair.planner import ViewScore
from gsfix_online.repair.scheduler import Decision
from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig
from gsfix_online.runtime.requests import render_request
from gsfix_online.services.live_map import LiveConfig, model_folder, names
from gsfix_online.services.map_server import MapServer, RequestError, ServerConfig, wrap_map
from gsfix_online.services.planner import Params as PlannerParams
from gsfix_online.services.planner import PlannerService, decision_messages
from gsfix_online.services.splat import Params as SplatParams
from gsfix_online.services.splat import SplatService
from tests.apps.served_run import H, K, W, face_gaussians, pose

MAPPER = MapperConfig(distill_iters=3, densify=DensifyConfig(enabled=False))


def view_args(T=None, **kw):
    T = pose(0.05, 0.01) if T is None else T
    return {"T_world_cam": np.asarray(T).ravel().tolist(), "K": K.ravel().tolist(),
            "width": W, "height": H, **kw}  # fmt: skip


def wire(msg: Message) -> Message:
    """``msg`` as a receiver decodes it."""
    t = InMemoryTransport()
    t.publish(msg)
    return t.published[0]


class Graph:
    """The map server's graph side between a planner, a repair node and a splat node."""

    def __init__(self, tmp_path: Path, **live: object) -> None:
        self.now = 10.0
        self.service = MapServer(ServerConfig(), 0.0)
        self.root = tmp_path  # the splat node's write_root
        params = Params(live=LiveConfig(**live))  # type: ignore[arg-type]
        self.transport = InMemoryTransport()
        self.node, self.live = build_node(
            "map_server", params, self.transport, NodeRuntimeConfig(), self.service,
            clock=lambda: self.now,
        )  # fmt: skip
        self.planner = PlannerService("planner", PlannerParams())
        self.splat = SplatService("splat", SplatParams(mapper=MAPPER, write_root=str(tmp_path)))
        self.splat.mapper = wrap_map(face_gaussians(), MAPPER, 2.0)
        self.texts: list[str] = []

    def feed(self, *msgs: Message) -> None:
        for m in msgs:
            self.transport.feed(m)
        self.node.run_until_idle()

    def sent(self) -> list[Message]:
        out = self.transport.published
        self.transport.outbox.clear()
        return [m for m in out if not m.topic.startswith(("heartbeat/", "stats/"))]

    def updates(self) -> list:
        ups = self.live.take_updates()
        self.texts += [u.text for u in ups if u.kind == "progress"]
        return ups

    def request(self, args: dict) -> Message:
        """The client's repair: forwarded; the planner queues it and gives it an id."""
        for m in self.live.begin(args, self.now):
            self.node.publish(m, reliable=True)
        (fwd,) = self.sent()
        self.planner.on_view_request(fwd)
        return fwd

    def decide(self, repair: bool, reason: str, view=None) -> int:
        view = view or self.planner.planner.queue[-1]
        score = ViewScore(0.9, 0.4 if repair else 0.0, 0.1, 0.0, repair, reason)
        gs = np.full((view.height, view.width, 3), 77, np.uint8)
        zeros = np.zeros((view.height, view.width), np.float32)
        d = Decision(view, score, gs, zeros + 1, gs, zeros + 2, zeros > -1, 0.5)
        self.feed(*decision_messages("planner", d, 0, self.planner.views_total))
        return view.view_id

    def repaired(self, view_id: int, value: int = 200) -> np.ndarray:
        """The repair node's message (its topic and meta); distilled by the splat node."""
        color = np.full((H, W, 3), value, np.uint8)
        meta = {"view_id": view_id, "keyframe_id": -1, "model_step": 4, "model_version": 1,
                "render_s": 0.1, "fix_s": 0.2}  # fmt: skip
        msg = Message("repaired_view/repair", "repaired_view", view_id, 0, "world", meta,
                      {"color": color, "K": K, "T_world_cam": pose(0.05, 0.01)})  # fmt: skip
        self.feed(msg)
        self.feed(self.splat.on_repaired_view(wire(msg)))
        return color

    def export(self) -> None:
        """The splat node answers the map server's export request."""
        (req,) = self.sent()
        assert (req.topic, req.type, req.meta["kind"]) == ("splat/export", "command", "export")
        self.feed(self.splat.on_export(req))


@pytest.fixture
def graph(tmp_path):
    g = Graph(tmp_path)
    return g


def test_a_repaired_view_goes_through_each_stage_and_answers_with_the_new_map_version(graph):
    g = graph
    # 1. The graph's own export first: the live map at version 0
    first = save_model(g.root / "map", face_gaussians(), 1)
    g.feed(Message("export/splat", "map_event", meta={"kind": "exported", "path": str(first),
                                                      "version": 0, "step": 1}))  # fmt: skip
    assert [(m["name"], m["version"]) for m in g.service.list_maps()[0]["maps"]] == [("live", 0)]
    # 2. Two other requested views queue first: the planner numbers ours 2
    for x in (0.3, 0.4):
        g.planner.on_view_request(wire(render_request("other", -1, pose(x), K, W, H, ("color",))))
    fwd = g.request(view_args())
    assert (fwd.topic, fwd.type, fwd.meta["request_id"]) == ("view_request/map_server",
                                                             "render_request", -1)  # fmt: skip
    assert (fwd.meta["width"], fwd.meta["height"]) == (W, H)
    np.testing.assert_array_equal(fwd.arrays["K"], K)
    ours = g.planner.planner.queue[-1]
    assert ours.view_id == 2 and ours.origin == "request"
    # 3. Decisions of the other views pass by; ours is matched by its camera, then by its id
    g.decide(True, "other view", g.planner.planner.queue[0])
    g.repaired(0, 10)  # another view's repair and distillation: not ours
    assert g.sent() == [] and g.live.job.stage == "forwarded"
    g.now = 12.0
    assert g.decide(True, "holes 40 %") == 2 and g.live.job.view_id == 2
    g.now = 15.0
    image = g.repaired(2)
    g.now = 16.0
    g.export()
    ups = g.updates()
    # 4. The answer: the repair, the live map's new version (1), the stages in order
    done = ups[-1]
    assert done.kind == "done"
    np.testing.assert_array_equal(done.image, image)
    r = done.result
    assert (r["map_version"], r["view_id"], r["repair"], r["distilled"]) == (1, 2, True, 2)
    assert r["reason"].startswith("repaired: holes 40 %; GSFixer (step 4)")
    assert r["reason"].endswith("distilled into map version 1")
    assert list(r["stages_s"]) == ["forwarded", "decided", "repaired", "distilled", "exported"]
    assert r["stages_s"]["decided"] == 2.0 and r["seconds"] == 6.0
    assert [t.split(":")[0] for t in g.texts] == list(r["stages_s"])
    assert [u.fraction for u in ups[:-1]] == [0.05, 0.3, 0.6, 0.8, 1.0]
    assert g.texts[0] == ("forwarded: sent to planner as a view request; waiting for the "
                          "planner's decision")  # fmt: skip
    assert g.texts[-1] == "exported: map 'live' version 1"
    # the new version holds the splat node's distilled map, in its own export folder
    m = g.service.get("live")
    assert m.version == 1 and m.ply_path.parents[2] == g.root / "work/live_map/export-0001"
    assert len(m.gmap) == len(g.splat.mapper.gmap)
    np.testing.assert_array_equal(
        m.gmap.means.detach().numpy(), g.splat.mapper.gmap.means.detach().numpy()
    )
    assert not g.live.busy and g.live.stats()["live/repaired"] == 1


def test_a_skipped_view_answers_with_the_planners_reason_and_its_3dgs_render(graph):
    g = graph
    g.request(view_args())
    g.decide(False, "sees little mapped surface")
    done = g.updates()[-1]
    assert done.kind == "done" and done.result["map_version"] is None
    assert (
        done.result["reason"] == "skipped by planner: sees little mapped surface; the 3DGS render"
    )
    assert done.image.shape == (H, W, 3) and (done.image == 77).all()  # the decision's gs render
    assert [t.split(":")[0] for t in g.texts] == ["forwarded", "decided"]
    assert g.sent() == [] and not g.live.busy  # no export for a skipped view


def test_one_live_repair_at_a_time_and_bad_requests_are_refused_before_forwarding(graph):
    g = graph
    with pytest.raises(RequestError, match="bad pose") as err:
        g.live.begin(view_args(np.full((4, 4), np.nan)), g.now)
    assert err.value.kind == "bad_request"
    with pytest.raises(RequestError, match="size too large"):
        g.live.begin(view_args(width=100_000, height=100_000), g.now)
    assert g.sent() == [] and not g.live.busy
    g.request(view_args())
    g.now = 13.5
    with pytest.raises(RequestError, match=r"busy: .* \(3.5 s so far, waiting for the planner's"):
        g.live.begin(view_args(), g.now)


def test_a_view_the_graph_does_not_finish_fails_after_timeout_s_naming_the_stage(tmp_path):
    g = Graph(tmp_path, timeout_s=30.0)
    g.request(view_args())
    g.decide(True, "holes")
    g.live.poll(g.now + 30.0)
    assert g.live.busy  # not yet
    g.live.poll(g.now + 30.5)
    fail = g.updates()[-1]
    assert fail.kind == "failed" and not g.live.busy
    assert fail.text == ("live repair gave up after 30 s: no answer from the repair node's "
                         "GSFixer (stage decided)")  # fmt: skip
    # a late repair of that view changes nothing
    g.repaired(0)
    assert g.updates() == [] and g.sent() == []


def test_which_requests_are_for_the_live_map(graph, tmp_path):
    from tests.apps.served_run import make_served_run

    live = graph.live
    assert live.wants({}) and live.wants({"map": "live"}) and not live.wants({"map": "other"})
    graph.service.add_run(make_served_run(tmp_path / "r", checkpoint=False), name="run")
    assert not live.wants({}) and live.wants({"map": "live"})  # with a run: name the map


def test_export_paths_name_their_model_folder_relative_to_the_splat_nodes_root(tmp_path):
    ply = save_model(tmp_path / "work" / "m", face_gaussians(10), 7)
    folder = model_folder(ply)
    assert folder == (tmp_path / "work" / "m").resolve() == model_folder(tmp_path / "work/m")
    assert names(folder, Path("work/m")) and names(folder, Path("m"))
    assert not names(folder, Path("other/m")) and not names(folder, Path("work/m2"))
    assert names(folder, tmp_path / "work" / "m") and not names(folder, tmp_path / "m")
