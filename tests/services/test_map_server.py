"""MapServer (the component, no sockets) and RunFolder on a tiny run; the request loop's
server-side deadline and malformed frames over a real loopback ROUTER socket."""

from __future__ import annotations

import dataclasses
import json
import time

import cv2
import numpy as np
import pytest

from gsfix_online.mapping.splat.mapper import MapperConfig
from gsfix_online.mapping.splat.ply import read_ply
from gsfix_online.services.map_server import MapServer, RequestError, ServerConfig, wrap_map
from gsfix_online.services.run_folder import RunFolder, RunFolderError
from tests.apps.served_run import (
    FACE_Z_M,
    FALLBACK,
    REFERENCE_RGB,
    REPAIRED_X_M,
    H,
    K,
    W,
    make_served_run,
    pose,
    reference_frame,
)

FAST = ServerConfig(mapper=dataclasses.replace(ServerConfig().mapper, distill_iters=2))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return make_served_run(tmp_path_factory.mktemp("served"))


@pytest.fixture
def server(run_dir):
    s = MapServer(FAST, started=100.0)
    s.add_run(run_dir)
    return s


def view_args(T=None, K_=K, w=W, h=H, **kw):
    T = pose() if T is None else T
    return {"T_world_cam": np.asarray(T).ravel().tolist(), "K": np.asarray(K_).ravel().tolist(),
            "width": w, "height": h, **kw}  # fmt: skip


# -- RunFolder -----------------------------------------------------------------------------------


def test_run_folder_reads_cameras_keyframes_and_paths(run_dir):
    run = RunFolder(run_dir)
    assert [v.view_id for v in run.views] == [0, 1]
    v = run.views[1]
    np.testing.assert_array_equal(v.K, K)
    np.testing.assert_allclose(v.T_world_cam, pose(0.1, 0.02))
    assert (v.width, v.height, v.repair) == (W, H, False)
    assert v.images == {"gs": "views/001/gs.png", "output": "views/001/output.png"}
    assert [(k.id, k.repaired) for k in run.keyframes] == [(0, 0), (1, 0), (2, 0), (3, 1)]
    np.testing.assert_allclose(run.keyframes[2].T_world_cam, pose(0.1))
    np.testing.assert_allclose(run.keyframes[0].K, K)  # centre principal point, fx, fy
    assert run.mesh_path == run_dir / "mesh.ply" and run.checkpoint_dir is not None
    assert run.fallback["per_region"]["mesh_only"] == "mesh_inpaint"
    assert len(run.splat_model().gmap) == 300
    assert run.resolve("views/000/gs.png").is_file()
    for bad in ("../x.png", "/etc/passwd", ""):
        with pytest.raises(RunFolderError, match="inside the run folder"):
            run.resolve(bad)


def test_run_folder_errors_name_what_is_wrong(tmp_path, run_dir):
    with pytest.raises(RunFolderError, match="no such folder"):
        RunFolder(tmp_path / "nope")
    with pytest.raises(RunFolderError, match=r"not a run folder .* \(no metrics.json\)"):
        RunFolder(tmp_path)
    (tmp_path / "metrics.json").write_text("{not json")
    with pytest.raises(RunFolderError, match="not valid JSON"):
        RunFolder(tmp_path)
    data = json.loads((run_dir / "metrics.json").read_text())
    data["views"][1]["camera"]["T_world_cam"][3] = float("nan")
    (tmp_path / "metrics.json").write_text(json.dumps(data))
    with pytest.raises(RunFolderError, match=r"views\[1\]: T_world_cam contains NaN"):
        RunFolder(tmp_path)
    data["views"][1]["camera"]["T_world_cam"][3] = 0.0
    data["views"][1]["files"]["gs"] = "../../secret.png"
    (tmp_path / "metrics.json").write_text(json.dumps(data))
    with pytest.raises(RunFolderError, match="leaves the run folder"):
        RunFolder(tmp_path)


# -- quick requests ------------------------------------------------------------------------------


def test_maps_stats_views_and_files(server, run_dir):
    (maps, _), = [server.handle("maps", {}, 101.0)]  # fmt: skip
    assert maps["maps"] == [{"name": "run", "version": 0, "gaussians": 300, "has_mesh": True,
                             "views": 5}]  # fmt: skip
    views = server.handle("views", {"map": "run"}, 101.0)[0]["views"]
    # cameras.json's repaired camera 3 is one of the run's views: not listed again
    assert [(v["kind"], v["id"]) for v in views] == [
        ("keyframe", 0), ("keyframe", 1), ("keyframe", 2), ("view", 0), ("view", 1)
    ]  # fmt: skip
    assert views[4]["T_world_cam"] == pose(0.1, 0.02).ravel().tolist()
    ply = next((run_dir / "map").glob("point_cloud/*/point_cloud.ply"))
    assert server.handle("splats", {}, 101.0)[1]["data"] == ply.read_bytes()  # bit-exact
    assert server.handle("mesh", {}, 101.0)[1]["data"] == (run_dir / "mesh.ply").read_bytes()
    assert server.handle("mesh", {"fmt": "glb"}, 101.0)[1]["data"][:4] == b"glTF"
    png = server.handle("image", {"path": "views/001/output.png"}, 101.0)[1]["data"]
    assert png == (run_dir / "views/001/output.png").read_bytes()
    stats = server.handle("stats", {}, 103.5)[0]
    assert stats["uptime_s"] == 3.5 and stats["maps"] == {"run": 0} and stats["busy"] is False


def test_render_matches_the_renderers_and_the_analytic_depth(server):
    res, out = server.handle("render", view_args(source="both"), 101.0)
    assert res == {"version": 0, "source": "both"}
    assert out["color"].dtype == np.uint8 and out["color"].shape == (H, W, 3)
    assert out["mesh"].shape == (H, W, 3) and out["alpha"].shape == (H, W)
    # the camera at the origin looks at the box's front face, the plane z = 2 m
    np.testing.assert_allclose(out["depth_m"][H // 2, W // 2], FACE_Z_M, atol=1e-5)
    np.testing.assert_array_equal(out["mesh"][H // 2, W // 2], [200, 120, 40])
    # the 3DGS render is the Mapper's own
    ref, _, alpha = wrap_map(server.get("run").gmap, MapperConfig()).render_numpy(pose(), K, W, H)
    np.testing.assert_array_equal(out["color"], np.rint(np.clip(ref, 0, 1) * 255).astype(np.uint8))
    np.testing.assert_array_equal(out["alpha"], alpha)
    gs_only = server.handle("render", view_args(source="gs"), 101.0)[1]
    assert set(gs_only) == {"color", "alpha", "depth_m", "provenance"}
    assert set(server.handle("render", view_args(source="mesh"), 101.0)[1]) == {"mesh", "depth_m"}


def test_render_returns_the_share_of_repaired_gaussians_beside_the_colour(server):
    """The face's Gaussians right of x = REPAIRED_X_M grew from a repaired view: the render's
    provenance is 255 there, 0 on the observed left, and 0 where nothing is drawn."""
    out = server.handle("render", view_args(source="gs"), 101.0)[1]
    prov = out["provenance"]
    assert prov.dtype == np.uint8 and prov.shape == (H, W)
    fx, cx = K[0, 0], K[0, 2]
    col = lambda x_m: int(round(cx + fx * x_m / FACE_Z_M))  # noqa: E731  the face's column at x
    rows = slice(H // 2 - 3, H // 2 + 4)
    assert (prov[rows, col(-0.3) : col(0.1)] <= 3).all()  # observed
    assert (prov[rows, col(0.33) : col(0.45)] >= 250).all()  # grown from a repaired view
    assert 20 < prov[rows, col(REPAIRED_X_M)].mean() < 235  # the border blends both
    assert (prov[out["alpha"] < 1e-3] == 0).all()


BAD = [
    ("render", view_args(T=np.full((4, 4), np.nan)), "bad_request",
     "bad pose: T_world_cam contains NaN or inf"),
    ("render", view_args(T=np.diag([1.0, 1.0, 1.5, 1.0])), "bad_request",
     "bad pose: T_world_cam rotation is not orthonormal"),
    ("render", view_args(T=np.diag([1.0, 1.0, -1.0, 1.0])), "bad_request",
     "rotation is a reflection"),
    ("render", {**view_args(), "T_world_cam": [1.0] * 12}, "bad_request",
     "T_world_cam must be 16 numbers, got 12 values"),
    ("render", view_args(w=5000, h=4000), "too_large",
     "size too large: 5000x4000 = 20000000 pixels > max_pixels 16777216"),
    ("render", view_args(w=0), "bad_request", "width must be a positive int, got 0"),
    ("render", view_args(K_=np.diag([-1.0, 40.0, 1.0])), "bad_request", "bad intrinsics"),
    ("render", view_args(source="nerf"), "bad_request", "source must be one of gs, mesh, both"),
    ("render", view_args(map="tank"), "unknown_map", "unknown map 'tank' (serving: run)"),
    ("mesh", {"fmt": "obj"}, "bad_request", "fmt must be one of ply, glb, got 'obj'"),
    ("image", {"path": "../served0/x.png"}, "bad_request", "inside the run folder"),
    ("image", {"path": "views/009/gs.png"}, "not_found", "has no image views/009/gs.png"),
    ("image", {"path": "metrics.json"}, "bad_request", "must name a .png"),
    ("launch", {}, "unknown_op", "unknown request 'launch'"),
]  # fmt: skip


@pytest.mark.parametrize(("op", "args", "kind", "text"), BAD, ids=[b[3][:30] for b in BAD])
def test_bad_requests_raise_one_line_reasons(server, op, args, kind, text):
    with pytest.raises(RequestError) as info:
        server.handle(op, args, 101.0)
    assert info.value.kind == kind and text in str(info.value)
    assert "\n" not in str(info.value)


# -- repair --------------------------------------------------------------------------------------


def test_repair_is_serialised_distilled_into_a_copy_and_bumps_the_version(server, run_dir):
    T = pose(0.05, 0.0)
    job = server.begin_repair(view_args(T=T), 101.0)
    with pytest.raises(RequestError, match=r"busy: a repair of map 'run' is running \(2.0 s"):
        server.begin_repair(view_args(), 103.0)
    assert server.handle("stats", {}, 103.0)[0]["busy"] is True
    before = server.handle("splats", {}, 103.0)[1]["data"]
    seen: list[tuple[float, str]] = []
    job.run(lambda f, t: seen.append((f, t)))
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    # nothing visible changes before the swap: readers keep version 0
    assert server.handle("splats", {}, 104.0)[1]["data"] == before
    result = server.finish_repair(job, ok=True)
    assert result["map_version"] == 1 and server.get("run").version == 1
    assert (
        "GSFixer (checkpoint step 3)" in result["reason"]
        and "distilled in 2 steps" in result["reason"]
    )
    assert job.image is not None and job.image.shape == (H, W, 3) and job.image.dtype == np.uint8
    after = server.handle("splats", {}, 105.0)[1]["data"]
    assert after != before
    path = run_dir.parent / "after.ply"
    path.write_bytes(after)
    assert len(read_ply(path)) == len(server.get("run").gmap) >= 300
    assert server.handle("maps", {}, 105.0)[0]["maps"][0]["version"] == 1
    assert server.handle("stats", {}, 105.0)[0]["busy"] is False


def test_repair_checks_its_request_before_any_work(server, monkeypatch):
    calls: list[dict] = []
    real = server.render_gs

    def counted(*args, **kw):
        calls.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(server, "render_gs", counted)
    with pytest.raises(RequestError, match="bad pose"):
        server.begin_repair(view_args(T=np.full((4, 4), np.inf)), 101.0)
    with pytest.raises(RequestError, match="size too large"):
        server.begin_repair(view_args(w=8192, h=8192), 101.0)
    assert not server.busy and calls == []
    # accepted: the slot is taken, nothing is rendered on the caller's thread
    job = server.begin_repair(view_args(), 102.0)
    assert server.busy and calls == [] and job.gs is None and job.mesh is None
    with pytest.raises(RequestError, match="busy"):
        server.begin_repair(view_args(), 103.0)
    # the worker renders first, through a renderer of its own, and says so
    heard: list[tuple[float, str]] = []
    job.run(lambda f, t: heard.append((f, t)))
    assert heard[:2] == [(0.0, "rendering the view (3DGS and mesh)"),
                         (0.05, "the view is rendered; repairing it")]  # fmt: skip
    assert calls == [{"shared": False}] and server.get("run").renderer is None
    assert job.gs is not None and job.gs.shape == (H, W, 3) and job.valid is not None
    # the same pixels as a render request of that view
    _, out = server.render({"map": "run", **view_args()})
    np.testing.assert_array_equal(job.gs, out["color"])


def test_live_map_versions_follow_exports(tmp_path, run_dir):
    s = MapServer(FAST, 0.0)
    m = s.update_splats("live", run_dir / "map")
    assert (m.version, len(m.gmap), len(m.keyframes)) == (0, 300, 4) and not m.has_mesh
    s.update_mesh("live", run_dir / "mesh.ply")
    assert s.get(None).has_mesh
    assert s.update_splats("live", run_dir / "map").version == 1
    with pytest.raises(RequestError, match="is live: repairs go through its planner"):
        s.begin_repair(view_args(), 1.0)


# -- the request loop (nodes/map_server.py) on a real loopback socket ---------------------------


def test_request_loop_drops_expired_requests_and_answers_malformed_ones(server):
    import socket

    import zmq
    from gsfix_online.nodes.map_server import Params, RequestLoop

    from gsfix_online.apps.client import PROTOCOL, pack, unpack

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    times = [0.0, 5.0]  # the clock at receipt, then at handling; it stays at the last value
    loop = RequestLoop(
        server, Params(port=port), clock=lambda: times.pop(0) if times[1:] else times[0]
    )
    dealer = zmq.Context.instance().socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(loop.address)
    try:
        # received at t = 0 with a 1 s deadline, handled at t = 5: its client gave up, no answer
        dealer.send_multipart(pack({"id": 1, "op": "maps", "args": {}, "timeout_s": 1.0}))
        time.sleep(0.2)
        loop.step(timeout_ms=500)
        assert not dealer.poll(200) and server.counts["expired"] == 1
        # not our protocol: dropped; our protocol with a broken header: a one-line error
        dealer.send_multipart([b"hello"])
        dealer.send_multipart([PROTOCOL, b"\xc1"])
        time.sleep(0.2)
        loop.step(timeout_ms=500)
        assert dealer.poll(1000)
        header, _ = unpack(dealer.recv_multipart())
        assert header["status"] == "error" and header["kind"] == "bad_request"
        assert header["error"].startswith("malformed request: header is not msgpack")
        assert not dealer.poll(100)
    finally:
        dealer.close(linger=0)
        loop.close()


def test_a_render_slower_than_the_clients_deadline_is_followed_to_the_end(server, monkeypatch):
    """The worker renders a repair's view, so the request thread sends progress meanwhile: a
    client whose deadline (1 s) is shorter than the render (2.5 s) follows it to the end."""
    import socket
    import threading

    from gsfix_online.nodes.map_server import Params, RequestLoop

    from gsfix_online.apps.client import MapClient

    real = server.render_gs

    def slow(*args, **kw):
        time.sleep(2.5)
        return real(*args, **kw)

    monkeypatch.setattr(server, "render_gs", slow)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    loop = RequestLoop(server, Params(port=port, progress_every_s=0.1))
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            loop.step(timeout_ms=20)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    heard: list[tuple[float, str]] = []
    try:
        with MapClient(loop.address, timeout_s=1.0) as client:
            out = client.repair(pose(0.05), K, W, H,
                                progress=lambda f, t: heard.append((time.monotonic(), t)))  # fmt: skip
    finally:
        stop.set()
        thread.join(5.0)
        loop.close()
    assert out.image.shape == (H, W, 3) and out.map_version == 1
    texts = [t for _, t in heard]
    assert texts[0] == "accepted; rendering the view"
    assert "rendering the view (3DGS and mesh)" in texts
    # during the render the client heard the same stage again and again, never 1 s apart
    stamps = [s for s, _ in heard]
    assert texts.count("rendering the view (3DGS and mesh)") >= 10
    assert float(np.diff(stamps).max()) < 1.0


def test_run_folder_says_what_the_runs_repairs_chose_by(tmp_path):
    trainer = {**FALLBACK, "why": "the trainer's"}
    # a run written before the reach was recorded: its fallback, at every distance
    legacy = RunFolder(make_served_run(tmp_path / "a", False))
    assert legacy.choices() == (FALLBACK, None, None) and not legacy.records_choices
    held = {"holdout_reach_m": 0.3, "trainer_choice": trainer}
    assert RunFolder(make_served_run(tmp_path / "b", False, held)).choices() == (
        FALLBACK, 0.3, trainer
    )  # fmt: skip
    # no held-out frames: the recorded fallback was the trainer's own
    none = {"holdout_reach_m": None, "trainer_choice": trainer}
    assert RunFolder(make_served_run(tmp_path / "c", False, none)).choices() == (
        None, None, trainer
    )  # fmt: skip


@pytest.mark.parametrize("x_m, source", [(0.05, "held-out frames"), (0.9, "mesh first")])
def test_a_repair_on_demand_follows_what_the_runs_repairs_followed_at_its_distance(
    tmp_path, x_m, source
):
    # the held-out frames' choice holds 0.3 m from the input keyframes (x = 0, 0.05, 0.1 m);
    # at 0.9 m the view is 0.8 m from them, though 0.1 m from the repaired view at 1 m, which
    # is not a keyframe: it takes the mesh first, as the run's own far views did
    run = make_served_run(tmp_path, summary={"holdout_reach_m": 0.3, "trainer_choice": FALLBACK})
    s = MapServer(FAST, started=100.0)
    s.add_run(run)
    job = s.begin_repair(view_args(T=pose(x_m, 0.0)), 101.0)
    job.run(lambda f, t: None)
    want_m = 0.05 - x_m if x_m < 0.1 else x_m - 0.1
    assert f"from the {source} at {abs(want_m):.2f} m from the keyframes" in job.result["reason"]
    assert job.image is not None and job.image.shape == (H, W, 3)


def test_a_repair_on_demand_warps_the_runs_keyframes_where_its_choice_takes_them(tmp_path):
    # near the keyframes the run's repairs took the reference warp where both maps cover: the
    # served repair warps the run's input keyframes there too (their face is blue, the mesh's
    # orange); without keyframe images it can only give the mesh's colours, and says so
    near = {**FALLBACK, "per_region": {**FALLBACK["per_region"], "both": "ref_inpaint"}}
    summary = {"holdout_reach_m": 0.3, "trainer_choice": FALLBACK, "fallback": near}
    face = reference_frame(0.05)["depth"] > 0
    for refs in (True, False):
        run = make_served_run(tmp_path / str(refs), summary=summary, references=refs)
        s = MapServer(dataclasses.replace(FAST, feather_px=0.0), started=100.0)  # hard seams
        s.add_run(run)
        job = s.begin_repair(view_args(T=pose(0.05, 0.0)), 101.0)
        job.run(lambda f, t: None)
        assert "both=ref_inpaint, " in job.result["reason"]
        both = (job.alpha >= FAST.fixer.masks.alpha_threshold) & job.valid & face
        inner = cv2.erode(both.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # off the edges
        assert inner.sum() > 100
        got = np.median(job.image[inner].astype(int), axis=0)
        if refs:
            assert "3 reference frames warped over" in job.result["reason"]
            assert job.result["reference_coverage"] > 0.8 * face.mean()  # the face: 30 %
            assert np.abs(got - REFERENCE_RGB).max() <= 2, got
        else:
            assert "no reference frames (ref_inpaint is mesh_inpaint)" in job.result["reason"]
            assert job.result["reference_coverage"] == 0.0
            assert np.abs(got - (200, 120, 40)).max() <= 2, got  # the mesh's colour


def test_run_folder_reference_frames_are_checked(tmp_path):
    run = RunFolder(make_served_run(tmp_path, checkpoint=False, references=True))
    store = run.references(2)  # the most redundant of the three is evicted, as the planner's
    assert len(store) == 2 and store.n_evicted == 1
    assert [T[0, 3] for T in run.keyframe_poses()] == [0.0, 0.05, 0.1]
    np.savez(run.path / "work" / "keyframes" / "kf_00000009.npz", color=np.zeros((4, 4, 3)))
    with pytest.raises(RunFolderError, match=r"kf_00000009.npz: not a reference frame: .*depth"):
        run.references(10)
    with pytest.raises(RunFolderError, match=r"kf_00000009.npz: no keyframe pose"):
        run.keyframe_poses()


def test_a_repair_measures_its_distance_from_every_keyframe_the_run_had(tmp_path):
    # a keyframe 0.9 m along that the splat node's store evicted (not in cameras.json) is in
    # work/keyframes: the planner measured from it, and so does the server
    run = make_served_run(tmp_path, summary={"holdout_reach_m": 0.3, "trainer_choice": FALLBACK},
                          references=True)  # fmt: skip
    np.savez(run / "work" / "keyframes" / "kf_00000007.npz", **reference_frame(0.9))
    s = MapServer(FAST, started=100.0)
    s.add_run(run)
    job = s.begin_repair(view_args(T=pose(0.9, 0.0)), 101.0)
    job.run(lambda f, t: None)
    assert "from the held-out frames at 0.00 m from the keyframes" in job.result["reason"]


def test_a_repair_of_an_older_runs_map_says_it_follows_the_recorded_choice(server):
    # the fixture's run records no reach: its fallback choice, at any distance, and no distance
    job = server.begin_repair(view_args(T=pose(0.9, 0.0)), 101.0)
    job.run(lambda f, t: None)
    assert "from the run's recorded choice (at any distance: an older run)" in job.result["reason"]
    assert "from the keyframes" not in job.result["reason"]


def test_served_repairs_sets_the_servers_choice_beside_the_runs(tmp_path, capsys):
    # benchmarks/served_repairs.py on a run whose view 0 the repair node took the mesh first for
    import runpy
    from pathlib import Path

    run = make_served_run(tmp_path, summary={"holdout_reach_m": 0.01, "trainer_choice": FALLBACK})
    m = json.loads((run / "metrics.json").read_text())
    m["views"][0]["model"] = {"choice_from": "mesh first", "keyframe_distance_m": 0.02}
    (run / "metrics.json").write_text(json.dumps(m))
    script = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "served_repairs.py"))
    assert script["main"]([str(run), "--out", str(tmp_path / "s.json")]) == 0
    rows = json.loads((tmp_path / "s.json").read_text())["views"]
    # view 0 sits at x = 0, y = 0.02: 0.02 m from the keyframe at the origin, beyond the reach
    assert [(r["view"], r["server_from"], r["server_distance_m"]) for r in rows] == [
        ("000", "mesh first", 0.02)
    ]
    assert rows[0]["node_from"] == "mesh first" and rows[0]["mean_abs_diff"] >= 0
    assert "1 of 1 views: the same source of the choice" in capsys.readouterr().out
