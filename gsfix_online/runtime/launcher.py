"""Starts the nodes of a graph as processes, prefixes their log lines, restarts crashed ones.

Each node runs as ``python -m gsfix_online.apps.cli node NAME --config RUN_DIR/NAME.yaml``: the same
command a user runs by hand on another machine. The launcher stops everything on Ctrl-C or
SIGTERM (SIGTERM to each node, SIGKILL after a grace period) and returns when every node has
exited for good: its exit code is 0 when all nodes ended with 0.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from gsfix_online.runtime import timeline
from gsfix_online.runtime.graph import PROFILE_ENV, GraphConfig, write_node_file

logger = logging.getLogger(__name__)


def node_import_env(environ: dict[str, str] | None = None) -> dict[str, str]:
    """Environment that makes a node process import the ``gsfix_online`` this process runs.
    ``python -m`` puts the working directory first on the node's ``sys.path``: a graph started
    inside another checkout ran that checkout's code in its nodes. PYTHONSAFEPATH (Python 3.11+)
    leaves it out; where this process imported the package from a folder outside the
    interpreter's site-packages (a source tree, or an editable install's), that folder goes
    first on PYTHONPATH, so the nodes find the same code whatever the working directory."""
    import site
    import sysconfig

    environ = os.environ if environ is None else environ
    root = Path(__file__).resolve().parents[2]  # the folder gsfix_online/runtime/ is in
    installed = {Path(p).resolve() for p in (*site.getsitepackages(), site.getusersitepackages(),
                                             *sysconfig.get_paths().values()) if p}  # fmt: skip
    env = {"PYTHONSAFEPATH": "1"}
    if root not in installed:
        env["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [environ.get("PYTHONPATH")])])
    return env


@dataclass
class _Proc:
    name: str
    popen: subprocess.Popen[str]
    restarts: int = 0
    done: bool = False
    returncode: int | None = None


class Launcher:
    def __init__(
        self,
        graph: GraphConfig,
        machine: str | None = None,
        out: TextIO | None = None,
        grace_s: float = 5.0,
        restart_delay_s: float = 0.5,
        timeline_dir: Path | None = None,  # the nodes' busy spans and CPU samples go here
        cpu_sample_s: float = 1.0,  # with a timeline: how often each node's CPU time is read
        profile_dir: Path | None = None,  # each node profiles itself into it (pyinstrument)
    ) -> None:
        if graph.transport == "ipc" and not graph.run_dir:
            graph = dataclasses.replace(
                graph, run_dir=tempfile.mkdtemp(prefix=f"gsfix-{graph.name}-")
            )
        self.graph = graph
        self.run_dir = Path(graph.run_dir or tempfile.mkdtemp(prefix=f"gsfix-{graph.name}-"))
        self.names = [n for n, e in graph.nodes.items() if machine is None or e.machine == machine]
        self.out = out or sys.stdout
        self.grace_s = grace_s
        self.restart_delay_s = restart_delay_s
        self.timeline_dir = timeline_dir
        self.profile_dir = profile_dir
        self.cpu_sample_s = cpu_sample_s
        self._next_cpu_sample = 0.0
        self._cpu_s: dict[str, float] = {}  # CPU seconds of the nodes' earlier lives (restarts)
        self._cpu_last: dict[str, float] = {}  # the last reading of each node's current life
        if timeline_dir is not None:
            timeline_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, _Proc] = {}
        self._lock = threading.Lock()
        self._stop = False

    def _spawn(self, name: str) -> subprocess.Popen[str]:
        cfg = write_node_file(self.graph, name, self.run_dir / f"{name}.yaml")
        cmd = [sys.executable, "-m", "gsfix_online.apps.cli", "node", name, "--config", str(cfg)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **node_import_env()}
        if self.timeline_dir is not None:
            env[timeline.ENV_DIR] = str(self.timeline_dir)
        if self.profile_dir is not None:
            env[PROFILE_ENV] = str(self.profile_dir)
        popen = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, bufsize=1
        )
        threading.Thread(target=self._pump, args=(name, popen), daemon=True).start()
        return popen

    def _pump(self, name: str, popen: subprocess.Popen[str]) -> None:
        assert popen.stdout is not None
        for line in popen.stdout:
            with self._lock:
                self.out.write(f"[{name}] {line}" if line.endswith("\n") else f"[{name}] {line}\n")
                self.out.flush()

    def start(self) -> None:
        for name in self.names:
            self.procs[name] = _Proc(name, self._spawn(name))
            logger.info("started %s (pid %d)", name, self.procs[name].popen.pid)

    def poll(self) -> bool:
        """Reap exited nodes and apply restart policies; True while any node is still running."""
        running = False
        for name, proc in self.procs.items():
            if proc.done:
                continue
            rc = proc.popen.poll()
            if rc is None:
                running = True
                continue
            entry = self.graph.nodes[name]
            again = not self._stop and (
                entry.restart == "always" or (entry.restart == "on-failure" and rc != 0)
            )
            if again and proc.restarts < entry.max_restarts:
                proc.restarts += 1
                logger.warning(
                    "%s exited with %d; restart %d of %d",
                    name,
                    rc,
                    proc.restarts,
                    entry.max_restarts,
                )
                time.sleep(self.restart_delay_s)
                self._cpu_s[name] = self._cpu_s.get(name, 0.0) + self._cpu_last.pop(name, 0.0)
                proc.popen = self._spawn(name)
                running = True
            else:
                proc.done, proc.returncode = True, rc
                level = logging.INFO if rc == 0 else logging.ERROR
                logger.log(
                    level, "%s exited with %d%s", name, rc, " (restarts exhausted)" if again else ""
                )
        return running

    def stop(self) -> None:
        """SIGTERM every running node, SIGKILL those still alive after the grace period."""
        self._stop = True
        for proc in self.procs.values():
            if proc.popen.poll() is None:
                proc.popen.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.grace_s
        for proc in self.procs.values():
            remaining = max(0.0, deadline - time.monotonic())
            try:
                proc.popen.wait(remaining)
            except subprocess.TimeoutExpired:
                logger.error("%s did not stop within %.1f s; killing it", proc.name, self.grace_s)
                proc.popen.kill()
                proc.popen.wait()
        self.poll()

    def run(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> int:
        """Start, supervise until every node is done (or ``until()``/timeout), stop; exit code."""
        previous = signal.signal(signal.SIGTERM, lambda *_: self._request_stop())
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        self.start()
        try:
            while not self._stop and self.poll():
                self._sample_cpu()
                if (until is not None and until()) or (
                    deadline is not None and time.monotonic() > deadline
                ):
                    break
                time.sleep(0.05)
        except KeyboardInterrupt:
            logger.info("Ctrl-C: stopping the graph")
        finally:
            self.stop()
            signal.signal(signal.SIGTERM, previous)
        codes = [p.returncode for p in self.procs.values()]
        return 0 if all(c == 0 for c in codes) else 1

    def _sample_cpu(self) -> None:
        """With a timeline: every ``cpu_sample_s`` append each running node's CPU seconds."""
        now = time.monotonic()
        if self.timeline_dir is None or now < self._next_cpu_sample:
            return
        self._next_cpu_sample = now + self.cpu_sample_s
        import psutil

        t_wall = time.time()  # before the reads, which take a while on a busy machine

        cpu: dict[str, float] = {}
        for name, proc in self.procs.items():
            try:
                t = psutil.Process(proc.popen.pid).cpu_times()
            except psutil.Error:  # exited between poll() and here
                continue
            self._cpu_last[name] = t.user + t.system
            cpu[name] = self._cpu_s.get(name, 0.0) + self._cpu_last[name]
        try:
            timeline.append_cpu_sample(self.timeline_dir, t_wall, cpu)
        except OSError as exc:  # a diagnostic: never stop the graph for it
            logger.warning("cannot write the CPU timeline: %s", exc)
            self.timeline_dir = None

    def _request_stop(self) -> None:
        self._stop = True
