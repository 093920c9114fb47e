"""kill -9 during a replay, with real processes: the launcher restarts the node, the splat node
resumes from its last snapshot, and the final map holds every keyframe: as many as the same
frames give mapped in one go (counted before and after, asserted equal).

The graph is replay -> splat and tsdf, each with ``restart: on-failure``. The replay node is
killed first (it restarts from the first frame; splat and tsdf skip the frames they have and
count them), then the splat node twice while it maps (it resumes from its snapshot; the replay
resends what it had not acknowledged).
"""

from __future__ import annotations

import io
import os
import signal
import time
from pathlib import Path

import torch
import yaml

from gsfix_online.mapping.splat.ply import load_model
from gsfix_online.mapping.splat.service import Params, SplatService
from gsfix_online.runtime import frame_to_message
from gsfix_online.runtime.graph import NodeEntry, load_graph, node_params
from gsfix_online.runtime.launcher import Launcher
from gsfix_online.sources.mcap_log import write_mcap
from tests.conftest import make_frames

N = 16
SPLAT = {
    "threads": 1,
    "snapshot_every": 1,  # every acknowledged frame is in the snapshot (acks follow the handler)
    "stop_after": N,
    "perturbed_renders": 0,
    "stats_every": 4,
    "mapper": {"kf_iters": 2, "non_kf_iters": 1, "train_downscale": 1, "densify": {"enabled": False},
               "keyframes": {"min_new_gaussians": 0, "min_overlap": 0.9}},
}  # fmt: skip


def _graph(run: Path, log: Path) -> Path:
    graph = {
        "name": "kill",
        "transport": "ipc",
        "run_dir": str(run),
        "reliable_send_timeout_s": 60,  # a killed reader comes back within this
        "nodes": {
            "replay": {
                "kind": "replay",
                "restart": "on-failure",
                "outputs": {"frames": "reliable"},
                "params": {"source": {"path": str(log)}, "replay": {"mode": "max"}},
            },
            "splat": {
                "kind": "splat",
                "restart": "on-failure",
                "max_restarts": 3,
                "inputs": ["replay/frames"],
                "outputs": {"keyframes": "reliable", "live": "latest"},
                "routes": {"keyframes": ["keyframe/"]},
                "params": {
                    **SPLAT,
                    "snapshot": str(run / "map.pt"),
                    "export_dir": str(run / "map"),
                },
            },
            "tsdf": {
                "kind": "tsdf",
                "restart": "on-failure",
                "inputs": ["replay/frames"],
                "outputs": {"out": "latest"},
                "params": {
                    "mesh_dir": str(run / "mesh"),
                    "formats": ["ply"],
                    "tsdf": {"voxel_size": 0.05, "depth_max": 6.0},
                },
            },  # fmt: skip
            "kf_reader": {
                "kind": "monitor",
                "restart": "on-failure",
                "inputs": ["splat/keyframes"],
            },
        },
    }
    path = run / "graph.yaml"
    path.write_text(yaml.safe_dump(graph))
    return path


def _reference_keyframes(frames) -> int:  # noqa: ANN001
    """The same frames mapped in one go, in this process."""
    params = node_params(NodeEntry(kind="splat", params=SPLAT))
    assert isinstance(params, Params)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        svc = SplatService("splat", params)
        for f in frames:
            svc.on_rgbd(frame_to_message(f, "rgbd/cam0"))
    finally:
        torch.set_num_threads(n)
    assert svc.mapper is not None and svc.frames == N
    return len(svc.mapper.store)


def _wait(cond, what: str, launcher: Launcher, out: io.StringIO, timeout_s: float = 60) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not cond():
        launcher.poll()
        if time.monotonic() > deadline:
            launcher.stop()
            raise AssertionError(f"timed out waiting for {what}:\n{out.getvalue()[-4000:]}")
        time.sleep(0.05)


def _mapped(run: Path) -> int:
    """Frames in the splat node's newest snapshot (0 before the first)."""
    from gsfix_online.mapping.splat.service import _read_snapshot

    try:
        return int(_read_snapshot(run / "map.pt")["counters"]["n_frames"])
    except Exception:  # not written yet, or replaced while read
        return 0


def test_kill_9_of_splat_and_replay_loses_no_keyframe(short_dir: Path) -> None:
    frames = make_frames(n=N, width=48, height=36, seed=3)
    log = short_dir / "log.mcap"
    write_mcap(log, frames)
    expected = _reference_keyframes(frames)

    out = io.StringIO()
    launcher = Launcher(load_graph(_graph(short_dir, log)), out=out, restart_delay_s=0.2)
    launcher.start()
    try:
        procs = launcher.procs
        # 1. replay, while splat maps (it restarts from the first frame; splat and tsdf skip
        #    the frames they have and count them)
        _wait(lambda: _mapped(short_dir) >= 2, "2 frames mapped", launcher, out)
        assert procs["replay"].popen.poll() is None, out.getvalue()[-3000:]
        os.kill(procs["replay"].popen.pid, signal.SIGKILL)
        _wait(lambda: procs["replay"].restarts == 1, "the replay restart", launcher, out)
        # 2. splat, twice, while it maps (each time after more snapshots)
        for k, after in enumerate((5, 9)):
            _wait(lambda a=after: _mapped(short_dir) >= a, f"{after} frames mapped", launcher, out)
            os.kill(procs["splat"].popen.pid, signal.SIGKILL)
            _wait(lambda k=k: procs["splat"].restarts == k + 1, "the splat restart", launcher, out)
        done = ("replay", "splat")  # then the launcher stops tsdf and the keyframe reader
        _wait(lambda: all(procs[n].done for n in done), "the graph to finish", launcher, out)
    finally:
        launcher.stop()
    logs = out.getvalue()
    codes = {n: p.returncode for n, p in procs.items()}
    assert codes == {"replay": 0, "splat": 0, "tsdf": 0, "kf_reader": 0}, logs[-4000:]
    assert procs["splat"].restarts == 2, logs[-4000:]
    assert logs.count("resumed from") == 2, logs[-4000:]

    # 3. The final map holds every keyframe: as many as mapping the frames in one go gives
    model = load_model(short_dir / "map")
    kf_names = sorted(c.img_name for c in model.cameras)
    assert len(kf_names) == len(set(kf_names)) == expected, (kf_names, expected)
    snap = torch.load(short_dir / "map.pt", weights_only=True)
    assert snap["counters"]["n_frames"] == N  # every frame mapped once, none twice
    # tsdf integrated each frame once and counted the restarted replay's repeats
    assert "'tsdf/frames': 16," in logs and "'tsdf/repeated': 0}" not in logs, logs[-3000:]
