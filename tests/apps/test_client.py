"""MapClient against `gsfix-online serve` as a real process over loopback: every call, every error
path, a busy server, timeouts, and a server killed in the middle of a repair."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from gsfix_online import MapClient
from gsfix_online.apps.client import (
    MapClientError,
    MapServerError,
    MapTimeoutError,
    Render,
    Repaired,
)
from gsfix_online.services.map_server import MapServer
from tests.apps.served_run import FACE_Z_M, H, K, W, make_served_run, pose
from tests.services.test_map_server import FAST

START_TIMEOUT_S = 60.0  # a cold start imports torch and Open3D on a loaded 2-core machine


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(run_dir, port: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "gsfix_online.apps.cli", "serve", str(run_dir),
           "server.mapper.distill_iters=2", "threads=1", "--port", str(port)]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.terminate()
    out, _ = proc.communicate(timeout=20)
    return out


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    run_dir = make_served_run(tmp_path_factory.mktemp("served"))
    port = free_port()
    proc = start_server(run_dir, port)
    client = MapClient(f"tcp://127.0.0.1:{port}", timeout_s=30.0, connect_timeout_s=START_TIMEOUT_S)
    try:
        client.maps(timeout_s=START_TIMEOUT_S)  # ready
        yield run_dir, proc, client
    finally:
        client.close()
        out = stop(proc)
        assert proc.returncode == 0, out  # SIGTERM ends it cleanly


def test_every_call_answers_what_the_run_folder_holds(served):
    run_dir, _, c = served
    maps = c.maps()
    assert [(m.name, m.gaussians, m.has_mesh, m.views) for m in maps] == [("run", 300, True, 5)]
    views = c.views()
    assert [v["kind"] for v in views] == ["keyframe"] * 3 + ["view"] * 2
    assert views[3]["images"]["gs"] == "views/000/gs.png" and views[3]["K"] == K.ravel().tolist()
    assert c.image("views/000/gs.png") == (run_dir / "views/000/gs.png").read_bytes()
    assert c.mesh() == (run_dir / "mesh.ply").read_bytes()
    assert c.mesh(fmt="glb")[:4] == b"glTF"
    if c.maps()[0].version == 0:  # before the repair test distils into it: the file, bit-exact
        ply = next((run_dir / "map").glob("point_cloud/*/point_cloud.ply"))
        assert c.splats() == ply.read_bytes()
    stats = c.stats()
    assert stats["uptime_s"] > 0 and stats["by_op"]["maps"] >= 2 and stats["busy"] is False


def test_render_over_the_wire_matches_the_component(served):
    run_dir, _, c = served
    r = c.render(pose(), K, W, H, source="both")
    assert isinstance(r, Render) and r.color.shape == (H, W, 3) and r.color.dtype == np.uint8
    assert r.mesh.shape == (H, W, 3) and r.alpha.dtype == np.float32
    np.testing.assert_allclose(r.depth_m[H // 2, W // 2], FACE_Z_M, atol=1e-5)
    ref = MapServer(FAST, 0.0)
    ref.add_run(run_dir)
    args = {"T_world_cam": pose().ravel().tolist(), "K": K.ravel().tolist(), "width": W,
            "height": H, "source": "both"}  # fmt: skip
    if c.maps()[0].version == 0:
        want = ref.handle("render", args, 0.0)[1]
        np.testing.assert_allclose(r.color, want["color"], atol=1)  # thread counts differ
        np.testing.assert_allclose(r.alpha, want["alpha"], atol=1e-5)
        np.testing.assert_array_equal(r.mesh, want["mesh"])
        np.testing.assert_allclose(r.provenance, want["provenance"], atol=1)
    assert r.provenance.dtype == np.uint8 and r.provenance.shape == (H, W)
    assert r.provenance.max() == 255 and r.provenance.min() == 0  # the face's repaired part
    only = c.render(pose().tolist(), K.ravel().tolist(), 16, 12, source="mesh")  # plain lists
    assert only.color is None and only.alpha is None and only.mesh.shape == (12, 16, 3)
    assert only.provenance is None


WIRE_ERRORS = [
    (lambda c: c.render(np.full((4, 4), np.nan), K, W, H), "bad_request",
     "bad pose: T_world_cam contains NaN or inf"),
    (lambda c: c.render(np.diag([1.0, 2.0, 1.0, 1.0]), K, W, H), "bad_request",
     "rotation is not orthonormal"),
    (lambda c: c.repair(pose(), K, 8000, 8000), "too_large", "size too large: 8000x8000"),
    (lambda c: c.render(pose(), K, W, H, map="tank"), "unknown_map", "unknown map 'tank'"),
    (lambda c: c.mesh(fmt="obj"), "bad_request", "fmt must be one of ply, glb"),
    (lambda c: c.image("../../etc/passwd.png"), "bad_request", "inside the run folder"),
    (lambda c: c.render(pose(), K[:2], W, H), "bad_request", "K must be 9 numbers, got 6"),
]  # fmt: skip


@pytest.mark.parametrize(("call", "kind", "text"), WIRE_ERRORS, ids=[e[2] for e in WIRE_ERRORS])
def test_errors_come_back_as_one_line_reasons(served, call, kind, text):
    _, _, c = served
    errors = c.stats()["errors"]
    with pytest.raises(MapServerError) as info:
        call(c)
    assert info.value.kind == kind and text in str(info.value) and "\n" not in str(info.value)
    assert c.stats()["errors"] == errors + 1  # and the server goes on serving


BAD_ADDRESSES = [
    ("127.0.0.1:5590", "address must look like tcp://HOST:PORT"),
    ("tcp://127.0.0.1", "address must look like tcp://HOST:PORT"),  # no port: a raw ZMQError
    ("http://127.0.0.1:5590", "address must look like tcp://HOST:PORT"),  # ditto
    ("tcp://:5590", "address must look like tcp://HOST:PORT"),
    ("tcp://127.0.0.1:99999", "address port must be in 1..65535"),
    (5590, "address must be a string"),
]


@pytest.mark.parametrize(("address", "text"), BAD_ADDRESSES, ids=[str(a) for a, _ in BAD_ADDRESSES])
def test_client_checks_its_address_in_one_line(address, text):
    with pytest.raises(ValueError, match=text) as info:
        MapClient(address)
    assert isinstance(info.value, MapClientError) and "\n" not in str(info.value)
    assert "tcp://127.0.0.1:5590" in str(info.value) or "1..65535" in str(info.value)


@pytest.mark.parametrize("timeout", [0, -1, float("inf"), float("nan"), "soon"])
def test_client_checks_its_timeout_in_one_line(timeout):
    with pytest.raises(ValueError, match="timeout_s must be positive and finite"):
        MapClient(timeout_s=timeout)
    c = MapClient(f"tcp://127.0.0.1:{free_port()}")
    with pytest.raises(ValueError, match="timeout_s must be positive and finite"):
        c.maps(timeout_s=timeout)  # before: inf ended in OverflowError
    c.close()


def test_nothing_listening_on_loopback_fails_fast():
    """A refused loopback connection is known at once: no waiting out the 10 s timeout."""
    c = MapClient(f"tcp://127.0.0.1:{free_port()}", timeout_s=10.0)
    t0 = time.monotonic()
    with pytest.raises(MapTimeoutError, match=r"nothing listens there \(connection refused"):
        c.maps()
    assert time.monotonic() - t0 < 3.0  # connect_timeout_s (1 s) and the probes
    c.close()
    c = MapClient(f"tcp://127.0.0.1:{free_port()}", timeout_s=0.5, connect_timeout_s=None)
    with pytest.raises(MapTimeoutError, match=r"did not answer maps within 0.5 s"):
        c.maps()  # a client that waits for its server to start waits out its timeout
    c.close()


def test_repair_reports_progress_answers_others_and_refuses_a_second(served):
    run_dir, _, c = served
    other = MapClient(c.address, timeout_s=10.0)
    seen: list[tuple[float, str]] = []
    during: dict[str, object] = {}

    def progress(fraction: float, text: str) -> None:
        if not seen:  # the repair runs: other calls are answered, another repair is refused
            during["maps"] = other.maps()
            with pytest.raises(MapServerError) as info:
                other.repair(pose(), K, W, H)
            during["busy"] = info.value
        seen.append((fraction, text))

    out = c.repair(pose(0.05), K, W, H, progress=progress, timeout_s=30.0)
    other.close()
    assert isinstance(out, Repaired) and out.image.shape == (H, W, 3)
    assert out.image.dtype == np.uint8 and out.map_version == 1
    assert "GSFixer (checkpoint step 3)" in out.reason and "distilled in 2 steps" in out.reason
    fractions = [f for f, _ in seen]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0 and fractions == sorted(fractions)
    assert during["maps"][0].version == 0
    assert during["busy"].kind == "busy" and "a repair of map 'run' is running" in str(
        during["busy"]
    )
    assert c.maps()[0].version == 1 and c.stats()["maps"] == {"run": 1}
    ply = next((run_dir / "map").glob("point_cloud/*/point_cloud.ply"))
    assert c.splats() != ply.read_bytes()  # the distilled map, not the run's file


def test_a_timed_out_client_goes_on_and_drops_the_late_answer(served):
    _, _, c = served
    with pytest.raises(MapTimeoutError, match=r"did not answer render within 0.001 s"):
        c.render(pose(), K, 400, 300, timeout_s=0.001)
    assert c.maps()[0].name == "run"  # the late render answer is dropped, not taken for this


def test_no_server_times_out_within_the_deadline():
    c = MapClient(f"tcp://127.0.0.1:{free_port()}", timeout_s=0.5)
    t0 = time.monotonic()
    with pytest.raises(
        MapTimeoutError, match=r"did not answer maps within 0.5 s \(is it running\?\)"
    ):
        c.maps()
    assert time.monotonic() - t0 < 1.0
    c.close()


def test_a_server_killed_mid_repair_is_reported_within_the_deadline(tmp_path):
    run_dir = make_served_run(tmp_path, checkpoint=False)
    port = free_port()
    proc = start_server(run_dir, port)
    c = MapClient(f"tcp://127.0.0.1:{port}", timeout_s=5.0, connect_timeout_s=START_TIMEOUT_S)
    killed = threading.Event()

    def kill(fraction: float, text: str) -> None:
        if not killed.is_set():
            proc.kill()  # SIGKILL: no goodbye on the socket beyond the kernel's
            killed.set()

    try:
        c.maps(timeout_s=START_TIMEOUT_S)
        t0 = time.monotonic()
        with pytest.raises(MapTimeoutError, match=r"went away during repair .*did it stop\?"):
            c.repair(pose(), K, W, H, progress=kill)
        assert killed.is_set() and time.monotonic() - t0 < 5.0
        t0 = time.monotonic()
        with pytest.raises(MapTimeoutError, match=r"did not answer stats within 1 s"):
            c.stats(timeout_s=1.0)
        assert time.monotonic() - t0 < 1.5
    finally:
        c.close()
        stop(proc)
