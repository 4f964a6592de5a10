"""One supervised process, the way a kubelet runs a container.

The process runs in a process group of its own (so a terminal's Ctrl-C reaches only the runner,
and a stop reaches everything the process started, e.g. its env workers), and on Linux the kernel
kills it when the runner dies, even by SIGKILL (:mod:`vecsim.lifetime`). A thread watches it:
it runs the startup probe, then readiness and liveness probes (``service.probes``); when the
process exits or a startup/liveness probe fails, it restarts it after an exponential backoff.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import httpx

from service.probes import TERMINATION_GRACE_S, Probe, Probes
from vecsim.lifetime import exit_with_parent

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Backoff:
    """Restart delays: ``initial_s``, times ``factor`` after each restart, at most ``max_s``;
    back to ``initial_s`` after the process ran ``reset_after_s`` without a restart."""

    initial_s: float = 0.5
    factor: float = 2.0
    max_s: float = 30.0
    reset_after_s: float = 60.0


def probe_ok(url: str, probe: Probe) -> bool:
    """Returns whether ``GET url+probe.path`` answers 200..399 within the probe's timeout."""
    try:
        response = httpx.get(url + probe.path, timeout=probe.timeout_s)
    except httpx.HTTPError:
        return False
    return 200 <= response.status_code < 400


def group_alive(pgid: int) -> bool:
    """Returns whether any process of the process group ``pgid`` still exists."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def signal_group(pgid: int, sig: int) -> None:
    """Sends ``sig`` to every process of the group ``pgid``, if any is left."""
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


def _prepare_child(parent_pid: int, cpus: frozenset[int] | None) -> None:
    """Runs in the child between fork and exec: it dies with the runner, and the CPUs it is
    pinned to hold for every thread and process its program will start."""
    exit_with_parent(parent_pid)
    if cpus is not None:
        os.sched_setaffinity(0, cpus)


class ManagedProcess:
    """A command kept running: restarted on exit or failed probes, until :meth:`stop`.

    ``on_started`` runs (in the watcher thread) each time the startup probe first succeeds
    after a (re)start; an exception from it is logged, not raised. ``cpus`` pins the process
    (and so all it starts) to those CPUs from before its program runs; None leaves it unpinned.
    """

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str],
        log_path: Path,
        url: str | None = None,
        probes: Probes | None = None,
        backoff: Backoff = Backoff(),
        grace_s: float = TERMINATION_GRACE_S,
        on_started: Callable[[], None] | None = None,
        cpus: Collection[int] | None = None,
    ) -> None:
        self.name = name
        self.cpus = None if cpus is None else frozenset(cpus)
        self.argv = list(argv)
        self.env = dict(env)
        self.log_path = log_path
        self.url = url
        self.probes = probes
        self.backoff = backoff
        self.grace_s = grace_s
        self.on_started = on_started
        self.restarts = 0
        self.started = False  # the startup probe passed for the current process
        self.ready = False
        self.last_exit: str | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        """The current process's id (also its process group id), or ``None`` between runs."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    @property
    def state(self) -> str:
        if self._stopping.is_set():
            return "stopping"
        if self.pid is None:
            return "restarting" if self.restarts else "pending"
        if not self.started:
            return "starting"
        return "ready" if self.ready else "running"

    def log_tail(self, lines: int = 20) -> str:
        """Returns the last ``lines`` lines of the process's log ("" when there is none yet)."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])

    def start(self) -> None:
        """Starts the process and its watcher thread. Returns at once."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name}: already started")
        self._thread = threading.Thread(target=self._supervise, name=f"watch-{self.name}", daemon=True)
        self._thread.start()

    def request_stop(self) -> None:
        """Stops restarting and sends SIGTERM to the process (as Kubernetes does to a container's
        main process; it stops its own children). Returns at once."""
        with self._lock:
            self._stopping.set()
            if self._proc is not None and self._proc.poll() is None:
                self._proc.send_signal(signal.SIGTERM)

    def finish_stop(self, deadline: float) -> None:
        """Waits for the process until ``deadline`` (``time.monotonic()``), then SIGKILLs
        whatever is left of its group. Returns once nothing of it runs."""
        proc = self._proc
        if proc is not None:
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not exit within its grace period: killing it", self.name)
            self._kill_group(proc)
        if self._thread is not None:
            self._thread.join()

    def stop(self, grace_s: float | None = None) -> None:
        """SIGTERM, up to ``grace_s`` (default: its own) to exit, then SIGKILL of its whole group."""
        self.request_stop()
        self.finish_stop(time.monotonic() + (self.grace_s if grace_s is None else grace_s))

    def _kill_group(self, proc: subprocess.Popen[bytes]) -> None:
        # The group outlives its leader when children (env workers, forkserver) remain.
        if group_alive(proc.pid):
            signal_group(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 5.0
        while group_alive(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.02)

    def _spawn(self) -> subprocess.Popen[bytes] | None:
        with self._lock:
            if self._stopping.is_set():
                return None
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.log_path, "ab") as out:
                out.write(f"=== {time.strftime('%H:%M:%S')} start #{self.restarts}: {' '.join(self.argv)}\n".encode())
                out.flush()
                self._proc = subprocess.Popen(
                    self.argv,
                    env=self.env,
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                    # Forked by the watcher thread, which lives until the process is stopped.
                    preexec_fn=functools.partial(_prepare_child, os.getpid(), self.cpus),
                )
            self.started = self.ready = self.probes is None
            pinned = "" if self.cpus is None else f" on CPUs {sorted(self.cpus)}"
            log.info("%s started (pid %d)%s", self.name, self._proc.pid, pinned)
            return self._proc

    def _supervise(self) -> None:
        delay = self.backoff.initial_s
        while not self._stopping.is_set():
            proc = self._spawn()
            if proc is None:
                return
            began = time.monotonic()
            reason = self._watch(proc)
            if self._stopping.is_set():
                return
            self.started = self.ready = False
            self.last_exit = reason
            if reason.startswith("exited"):
                self._kill_group(proc)
            else:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=self.grace_s)
                except subprocess.TimeoutExpired:
                    pass
                self._kill_group(proc)
            if time.monotonic() - began >= self.backoff.reset_after_s:
                delay = self.backoff.initial_s
            self.restarts += 1
            log.warning(
                "%s %s; restart #%d in %.1f s (log: %s)", self.name, reason, self.restarts, delay, self.log_path
            )
            if self._stopping.wait(delay):
                return
            delay = min(self.backoff.max_s, delay * self.backoff.factor)

    def _watch(self, proc: subprocess.Popen[bytes]) -> str:
        """Returns why the process must be restarted, or "" when a stop was requested."""
        probes = self.probes
        now = time.monotonic()
        due = (
            {name: now + getattr(probes, name).initial_delay_s for name in ("startup", "readiness", "liveness")}
            if probes
            else {}
        )
        failures = {name: 0 for name in due}
        while not self._stopping.is_set():
            code = proc.poll()
            if code is not None:
                return f"exited with code {code}" if code >= 0 else f"exited by signal {-code}"
            if probes is not None and self.url is not None:
                phases = ("startup",) if not self.started else ("readiness", "liveness")
                for phase in phases:
                    probe: Probe = getattr(probes, phase)
                    if time.monotonic() < due[phase]:
                        continue
                    ok = probe_ok(self.url, probe)
                    due[phase] = time.monotonic() + probe.period_s
                    failures[phase] = 0 if ok else failures[phase] + 1
                    if phase == "readiness":
                        if ok:
                            self.ready = True
                        elif failures[phase] >= probe.failure_threshold:
                            self.ready = False
                    elif failures[phase] >= probe.failure_threshold:
                        return f"failed its {phase} probe {probe.path} {failures[phase]} times"
                    if phase == "startup" and ok:
                        self.started = self.ready = True
                        due["readiness"] = due["liveness"] = time.monotonic()
                        self._run_on_started()
            self._stopping.wait(0.1)
        return ""

    def _run_on_started(self) -> None:
        if self.on_started is None:
            return
        try:
            self.on_started()
        except Exception:
            log.exception("%s: start-up hook failed", self.name)
