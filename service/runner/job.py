"""A whole job on one machine: the controller and N pods as processes, StatefulSet-style.

Pods are named ``sim-0 … sim-N-1``, listen on ``base_port + ordinal``, and get the environment
a pod gets in Kubernetes (POD_NAME, POD_NAMESPACE, POD_IP, VECSIM_ADVERTISE_URL, CONTROLLER_URL,
VECSIM_PORT, VECSIM_MAX_ENVS, VECSIM_TOKEN); ``pods.cpu_affinity`` shares the runner's CPUs
between them (by default each pod, its env workers too, runs on its own equal share).
Every process is probed and restarted like a container; each (re)start of the controller is
followed by ``PUT /v1/job``. Every process gets
the job's shared token (``VECSIM_TOKEN``): the one given, else a random one made per job, which
trainers read from :attr:`LocalJob.token`.

    with LocalJob(load_job_config("configs/tiny.yaml")) as job:
        table = job.wait_ready(timeout=300)
        ...  # job.controller_url serves GET /v1/routing
"""

from __future__ import annotations

import atexit
import logging
import os
import secrets
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import httpx

from service.controller.jobs import check_job
from service.probes import CONTROLLER, POD, TERMINATION_GRACE_S
from vecsim.auth import TOKEN_ENV, bearer_headers, check_token
from vecsim.config import JobConfig, PodCapacity, PodRecord, RoutingTable, parse_cpu_list

from .ports import port_free
from .process import Backoff, ManagedProcess
from .status import PodStatus, collect_status, format_status

log = logging.getLogger(__name__)

CONTROLLER_NAME = "controller"
# The mjwarp engine's CUDA device (vecsim.engine.mjwarp.settings.GPU_ENV; named here, as nothing
# above the engine imports one).
MJWARP_GPU_ENV = "VECSIM_MJWARP_GPU"


class CrashLoopError(RuntimeError):
    """A process of the job keeps exiting; the message names it and ends with its log."""


class JobRejectedError(RuntimeError):
    """The job cannot run: its config fails the checks, or the controller refused it (HTTP 422).
    The message lists what to change."""


def machine_cpus() -> set[int]:
    """The CPUs a pod may be pinned to: the container's cpuset where cgroup v2 names it, else every
    CPU of the machine. Not the runner's own affinity: a trainer that pins itself to one core
    still starts pods on the others."""
    cpuset = Path("/sys/fs/cgroup/cpuset.cpus.effective")
    try:
        return parse_cpu_list(cpuset.read_text().strip())
    except (OSError, ValueError):
        return set(range(os.cpu_count() or 1))


class LocalJob:
    """The controller and ``config.pods.replicas`` pods of one job, as supervised processes.

    Use as a context manager, or call :meth:`start` and :meth:`stop`. ``log_dir`` receives one
    log file per process (default: a new temporary directory); ``env`` adds environment variables
    to every process; ``grace_s`` is the SIGTERM-to-SIGKILL grace period. ``token`` is the job's
    shared token; left out, ``VECSIM_TOKEN`` from ``env`` or the environment is used, and
    without one a random token is made for this job.

    Raises:
        ValueError: the token given cannot travel in an HTTP header.
    """

    def __init__(
        self,
        config: JobConfig,
        *,
        log_dir: str | Path | None = None,
        namespace: str = "default",
        env: Mapping[str, str] | None = None,
        python: str = sys.executable,
        backoff: Backoff = Backoff(),
        grace_s: float = TERMINATION_GRACE_S,
        token: str | None = None,
    ) -> None:
        self.config = config
        self.log_dir = Path(log_dir) if log_dir is not None else Path(tempfile.mkdtemp(prefix="vecsim-up-"))
        self.namespace = namespace
        self.grace_s = grace_s
        self.job_error: str | None = None
        self._python = python
        self._backoff = backoff
        self._base_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self._base_env.setdefault("MUJOCO_GL", "egl")
        given = check_token(token, "token") or check_token(self._base_env.get(TOKEN_ENV))
        self.token: str = given or secrets.token_urlsafe(32)
        self._base_env[TOKEN_ENV] = self.token
        self.processes: dict[str, ManagedProcess] = {}
        self._started = False

    @property
    def controller_url(self) -> str:
        c = self.config.controller
        return f"http://{c.host}:{c.port}"

    @property
    def pod_names(self) -> list[str]:
        return [f"sim-{i}" for i in range(self.config.pods.replicas)]

    def pod_url(self, name: str) -> str:
        """Returns the advertised URL of pod ``name`` (``http://host:base_port+ordinal``).

        Raises:
            KeyError: ``name`` is not one of this job's pods.
        """
        if name not in self.pod_names:
            raise KeyError(f"no pod {name!r} in this job (pods: {self.pod_names})")
        pods = self.config.pods
        return f"http://{pods.host}:{pods.base_port + int(name.rsplit('-', 1)[1])}"

    def pod_env(self, name: str) -> dict[str, str]:
        """Returns the environment variables pod ``name`` gets (as from the downward API)."""
        pods = self.config.pods
        url = self.pod_url(name)
        gpu = pods.render_gpu_of(int(name.rsplit("-", 1)[1]))
        # MuJoCo's EGL context opens this device (the CPU engine's cameras), the mjwarp engine
        # runs on the CUDA device of this number; unset, each takes the first one that works.
        render = {} if gpu is None else {"MUJOCO_EGL_DEVICE_ID": str(gpu), MJWARP_GPU_ENV: str(gpu)}
        return {
            "POD_NAME": name,
            "POD_NAMESPACE": self.namespace,
            "POD_IP": pods.host,
            "VECSIM_ADVERTISE_URL": url,
            "CONTROLLER_URL": self.controller_url,
            "VECSIM_PORT": url.rsplit(":", 1)[1],
            "VECSIM_MAX_ENVS": str(pods.max_envs),
            "VECSIM_HEARTBEAT_INTERVAL_S": str(self.config.controller.heartbeat_interval_s),
            # Locally, listen on the advertised address only, not on every interface.
            "VECSIM_HOST": pods.host,
            **render,
        }

    def _controller_argv(self) -> list[str]:
        c = self.config.controller
        return [
            self._python,
            "-m",
            "service.cli",
            "controller",
            "--host",
            c.host,
            "--port",
            str(c.port),
            "--heartbeat-interval",
            str(c.heartbeat_interval_s),
            "--heartbeat-ttl",
            str(c.heartbeat_ttl_s),
            "--reconcile-interval",
            str(c.reconcile_interval_s),
        ]

    def check(self) -> list[str]:
        """Returns what to change in the config for the job to run (empty: nothing), the same
        checks the controller makes, plus enough replicas to fill every slot."""
        job, pods = self.config.job, self.config.pods
        # Every pod of a local job has the same capacity: checking one names the problem once.
        sample = [
            PodRecord(pod=n, url=self.pod_url(n), capacity=PodCapacity(max_envs=pods.max_envs))
            for n in self.pod_names[:1]
        ]
        _, problems = check_job(job, sample)
        ports = [("controller.port", self.config.controller.host, self.config.controller.port)]
        ports += [("pods.base_port", pods.host, pods.base_port + i) for i in range(pods.replicas)]
        for field, host, port in ports:
            if not port_free(host, port):
                problems.append(f"{field}: port {port} on {host} is in use by another process; choose another {field}")
        problems += self._affinity_problems()
        if pods.replicas < job.pods_needed:
            slots = (
                f"pods_per_stage {job.pods_per_stage} slots (stage_layout 'slices': each holds every stage)"
                if job.stage_layout == "slices"
                else f"{job.num_stages} stages x {job.pods_per_stage} pods_per_stage = {job.pods_needed} slots"
            )
            problems.append(
                f"pods.replicas: {pods.replicas} pods cannot fill {slots}; raise pods.replicas to at least {job.pods_needed}"
            )
        return problems

    def _affinity_problems(self) -> list[str]:
        lists = self.config.pods.cpu_affinity
        if isinstance(lists, str):
            return []
        usable = machine_cpus()
        problems = []
        for text in lists:
            missing = sorted(parse_cpu_list(text) - usable)
            if missing:
                problems.append(
                    f"pods.cpu_affinity: {text!r} names CPUs {missing}, but this machine's pods may run on "
                    f"CPUs {sorted(usable)}"
                )
        return problems

    def pod_cpus(self, name: str) -> list[int] | None:
        """Returns the CPUs pod ``name`` and its env workers run on (``pods.cpu_affinity``), or
        None when pods are not pinned."""
        return self.config.pods.cpus_of(int(name.rsplit("-", 1)[1]), machine_cpus())

    def start(self) -> LocalJob:
        """Starts the controller and every pod. Returns at once; see :meth:`wait_ready`.

        Raises:
            JobRejectedError: the config cannot run (nothing is started; the message says why).
            RuntimeError: already started.
        """
        if self._started:
            raise RuntimeError("this LocalJob was already started")
        problems = self.check()
        if problems:
            raise JobRejectedError(f"job {self.config.job.job_id!r} cannot run: " + "; ".join(problems))
        self._started = True
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log.info(
            "starting job %s: controller at %s, %d pods; logs in %s",
            self.config.job.job_id,
            self.controller_url,
            len(self.pod_names),
            self.log_dir,
        )
        atexit.register(self.stop)
        controller = ManagedProcess(
            CONTROLLER_NAME,
            self._controller_argv(),
            env=self._base_env,
            log_path=self.log_dir / f"{CONTROLLER_NAME}.log",
            url=self.controller_url,
            probes=CONTROLLER,
            backoff=self._backoff,
            grace_s=self.grace_s,
            on_started=self._put_job,
        )
        self.processes[CONTROLLER_NAME] = controller
        for name in self.pod_names:
            self.processes[name] = ManagedProcess(
                name,
                [self._python, "-m", "service.cli", "pod"],
                env={**self._base_env, **self.pod_env(name)},
                log_path=self.log_dir / f"{name}.log",
                url=self.pod_url(name),
                probes=POD,
                backoff=self._backoff,
                grace_s=self.grace_s,
                cpus=self.pod_cpus(name),
            )
        for process in self.processes.values():
            process.start()
        return self

    def _put_job(self) -> None:
        body = self.config.job.model_dump(mode="json")
        for attempt in range(5):
            try:
                response = httpx.put(
                    f"{self.controller_url}/v1/job", json=body, headers=bearer_headers(self.token), timeout=30
                )
            except httpx.HTTPError as exc:
                log.warning("PUT /v1/job failed (%s), attempt %d", exc, attempt + 1)
                time.sleep(0.5 * 2**attempt)
                continue
            if response.status_code == 200:
                self.job_error = None
                log.info("job %s sent to the controller", self.config.job.job_id)
                return
            self.job_error = (
                f"the controller refused job {self.config.job.job_id!r}: HTTP {response.status_code}: {response.text}"
            )
            log.error("%s", self.job_error)
            return
        self.job_error = f"could not reach the controller at {self.controller_url} to send the job"

    def wait_ready(self, timeout: float = 300.0, poll_s: float = 0.25, max_restarts: int = 3) -> RoutingTable:
        """Waits until the controller says the job is ready. Returns the routing table.

        Raises:
            JobRejectedError: the controller refused the job.
            CrashLoopError: a process restarted more than ``max_restarts`` times while waiting.
            TimeoutError: not ready within ``timeout`` s (the message says what is missing, and
                where the logs are).
            RuntimeError: the job was not started.
        """
        if not self._started:
            raise RuntimeError("start the LocalJob before waiting for it")
        deadline = time.monotonic() + timeout
        detail = "the controller did not answer"
        restarts = {name: p.restarts for name, p in self.processes.items()}
        with httpx.Client(base_url=self.controller_url, timeout=5.0) as client:
            while True:
                if self.job_error is not None:
                    raise JobRejectedError(self.job_error)
                for name, process in self.processes.items():
                    if process.restarts - restarts[name] > max_restarts:
                        raise CrashLoopError(
                            f"{name} restarted {process.restarts - restarts[name]} times while waiting "
                            f"({process.last_exit}); end of {process.log_path}:\n{process.log_tail()}"
                        )
                try:
                    response = client.get("/readyz")
                    if response.status_code == 200:
                        table = RoutingTable.model_validate(client.get("/v1/routing").json())
                        if table.ready:
                            return table
                    detail = response.json().get("detail", response.text)
                except (httpx.HTTPError, ValueError) as exc:
                    detail = f"the controller did not answer: {exc}"
                if time.monotonic() >= deadline:
                    raise TimeoutError(
                        f"job {self.config.job.job_id!r} not ready after {timeout:.0f} s: {detail}\n"
                        f"{format_status(self.status())}\nlogs: {self.log_dir}"
                    )
                time.sleep(poll_s)

    def is_ready(self) -> bool:
        """Returns whether the controller reports the job ready (``GET /readyz`` answers 200)."""
        try:
            return httpx.get(f"{self.controller_url}/readyz", timeout=2.0).status_code == 200
        except httpx.HTTPError:
            return False

    def status(self) -> list[PodStatus]:
        """Returns one row per process (controller first): stage, tasks, readiness, restarts."""
        return collect_status(self.controller_url, self.processes)

    def stop(self, grace_s: float | None = None) -> None:
        """Stops every process: SIGTERM, up to ``grace_s`` to exit, then SIGKILL of each whole
        process group. Returns when nothing this job started is running. Idempotent."""
        atexit.unregister(self.stop)
        if not self.processes:
            return
        grace = self.grace_s if grace_s is None else grace_s
        log.info("stopping job %s (grace %.0f s)", self.config.job.job_id, grace)
        for process in self.processes.values():
            process.request_stop()
        deadline = time.monotonic() + grace
        for process in self.processes.values():
            process.finish_stop(deadline)
        self.processes = {}

    def __enter__(self) -> LocalJob:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
