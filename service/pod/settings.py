"""A pod's settings: who it is, where it listens, whom it reports to, and its limits.

The same environment variables describe a pod on a laptop (set by the local runner) and in
Kubernetes (set by the downward API); command-line flags override them (see ``main.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import Field

from vecsim.config import POD_NAME_PATTERN, Assignment
from vecsim.engine.base import DEFAULT_MAX_CHUNK
from vecsim.envsettings import from_environ

from ..settings import ServerSettings

DEFAULT_MAX_BODY_BYTES = 64 * 1024 * 1024
# The device node the NVIDIA driver creates: present exactly where a GPU is usable for EGL.
_NVIDIA_DEVICE = Path("/dev/nvidiactl")

# environment variable -> settings field
ENV_VARS: dict[str, str] = {
    "POD_NAME": "name",
    "POD_NAMESPACE": "namespace",
    "POD_IP": "pod_ip",
    "VECSIM_HOST": "host",
    "VECSIM_PORT": "port",
    "VECSIM_ADVERTISE_URL": "advertise_url",
    "CONTROLLER_URL": "controller_url",
    "VECSIM_TOKEN": "token",
    "VECSIM_MAX_ENVS": "max_envs",
    "VECSIM_GPU": "gpu",
    "VECSIM_HEARTBEAT_INTERVAL_S": "heartbeat_interval_s",
    "VECSIM_MAX_BODY_BYTES": "max_body_bytes",
    "VECSIM_STEP_TIMEOUT_S": "step_timeout_s",
    "VECSIM_BUILD_TIMEOUT_S": "build_timeout_s",
    "VECSIM_MAX_CHUNK": "max_chunk",
    "VECSIM_HEADER_TIMEOUT_S": "header_timeout_s",
    "VECSIM_KEEP_ALIVE_S": "keep_alive_s",
    "VECSIM_MAX_CONNECTIONS": "max_connections",
}


class PodSettings(ServerSettings):
    """Everything a pod needs to know before it starts serving (the token and uvicorn's limits:
    :class:`service.settings.ServerSettings`).

    ``assignment`` is set only in standalone mode, where the pod builds its envs at start-up
    without a controller.
    """

    name: str = Field("sim-0", min_length=1, max_length=63, pattern=POD_NAME_PATTERN)
    namespace: str = "default"
    pod_ip: str | None = None
    host: str | None = None
    port: int = Field(8100, ge=1, le=65535)
    advertise_url: str | None = None
    controller_url: str | None = None
    max_envs: int = Field(64, ge=0)
    gpu: bool | None = None
    # The longest wait between two tries at an unreachable controller: a restarted controller
    # hears every pod within it, and plans (heals the job) once it has.
    max_backoff_s: float = Field(2.0, gt=0)
    max_body_bytes: int = Field(DEFAULT_MAX_BODY_BYTES, ge=1)
    # A worker that answers no reset or step within this long counts as crashed (503, rebuild).
    step_timeout_s: float = Field(120.0, gt=0)
    # LIBERO scenes take minutes to build on a CPU.
    build_timeout_s: float = Field(900.0, gt=0)
    # The most actions per env one step call takes (stated in /v1/info).
    max_chunk: int = Field(DEFAULT_MAX_CHUNK, ge=1)
    assignment: Assignment | None = None

    @property
    def bind_host(self) -> str:
        """The address uvicorn listens on: ``host`` if given, else every interface when the pod
        has a routable ``POD_IP`` (others must reach it), else loopback only."""
        if self.host:
            return self.host
        return "0.0.0.0" if self.pod_ip else "127.0.0.1"

    @property
    def url(self) -> str:
        """The URL the controller and clients use to reach this pod."""
        if self.advertise_url:
            return self.advertise_url.rstrip("/")
        return f"http://{self.pod_ip or '127.0.0.1'}:{self.port}"

    @property
    def has_gpu(self) -> bool:
        """Whether to report a GPU to the controller: ``gpu`` if set, else whether the NVIDIA
        driver's device node exists."""
        return self.gpu if self.gpu is not None else _NVIDIA_DEVICE.exists()

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **overrides: Any) -> PodSettings:
        """Settings from environment variables (see ``ENV_VARS``), then ``overrides`` on top.

        Overrides whose value is None are ignored, so unset command-line flags fall through.

        Returns:
            The validated settings.

        Raises:
            vecsim.envsettings.SettingsError: a variable or override has a wrong value (named in
                the message with the value, the token's excepted).
        """
        return from_environ(cls, ENV_VARS, environ, overrides)
