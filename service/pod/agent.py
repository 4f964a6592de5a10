"""The pod's side of the control plane: register with the controller, then heartbeat.

The controller pushes assignments to the pod (``PUT /v1/assignment``); the agent only tells it
that the pod exists and what it holds, so that a restarted controller rebuilds its registry from
heartbeats. The agent never lets a controller problem take the pod down: it logs and retries
with a bounded backoff.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

import httpx

from service.contract import Heartbeat
from vecsim.auth import bearer_headers
from vecsim.config import PodCapacity, PodRegistration
from vecsim.transport import make_async_client, send_capped

from .settings import PodSettings

log = logging.getLogger(__name__)

# The controller answers a registration or heartbeat with a line of JSON; anything much larger
# is not its answer, and is not read past this.
_MAX_ANSWER_BYTES = 1 << 20


class ControllerRefusedError(Exception):
    """The controller answered a registration or heartbeat with an unexpected status."""


def backoff_delay(failures: int, base_s: float, cap_s: float) -> float:
    """Seconds to wait after ``failures`` failures in a row: ``base_s`` doubled per failure,
    never more than ``cap_s`` (and ``base_s`` when nothing failed)."""
    if failures <= 0:
        return base_s
    return min(cap_s, base_s * 2.0 ** min(failures, 32))


class ControllerAgent:
    """Registers one pod with the controller at ``settings.controller_url`` and heartbeats
    every ``settings.heartbeat_interval_s`` seconds with what ``report()`` says, sending the job's token
    (``settings.token``) with each."""

    def __init__(self, settings: PodSettings, report: Callable[[], Heartbeat]) -> None:
        if not settings.controller_url:
            raise ValueError("controller_url: the agent needs the controller's URL")
        self.settings = settings
        self.report = report
        self.base_url = settings.controller_url.rstrip("/")
        self.registered = False

    async def run(self) -> None:
        """Register and heartbeat until cancelled; never raises anything but cancellation."""
        failures = 0
        headers = bearer_headers(self.settings.token)
        # vecsim's transport: the controller's answers are read under its caps, as pods' are.
        async with make_async_client(base_url=self.base_url, timeout=5.0, headers=headers) as client:
            while True:
                try:
                    await self.beat(client)
                    failures = 0
                except Exception as exc:  # a controller problem must never end the agent
                    failures += 1
                    log.warning(
                        "pod %s: controller %s unreachable or refusing (%d in a row): %s: %s",
                        self.settings.name,
                        self.base_url,
                        failures,
                        type(exc).__name__,
                        exc,
                    )
                await asyncio.sleep(
                    backoff_delay(failures, self.settings.heartbeat_interval_s, self.settings.max_backoff_s)
                )

    async def beat(self, client: httpx.AsyncClient) -> None:
        """Register if not yet registered, then send one heartbeat; re-register when the
        controller no longer knows the pod (404).

        Raises:
            httpx.HTTPError: the controller could not be reached.
            ControllerRefusedError: the controller answered with an unexpected status.
        """
        if not self.registered:
            await self._register(client)
        heartbeat = self.report()
        path = f"/v1/pods/{self.settings.name}/heartbeat"
        response = await _post(client, path, heartbeat.model_dump(mode="json"))
        if response.status_code == 404:
            log.info("pod %s: controller forgot this pod; registering again", self.settings.name)
            self.registered = False
            await self._register(client)
            response = await _post(client, path, self.report().model_dump(mode="json"))
        _raise_for_status(response, "heartbeat")

    async def _register(self, client: httpx.AsyncClient) -> None:
        registration = PodRegistration(
            pod=self.settings.name,
            url=self.settings.url,
            capacity=PodCapacity(max_envs=self.settings.max_envs, gpu=self.settings.has_gpu),
        )
        response = await _post(client, "/v1/pods", registration.model_dump(mode="json"))
        _raise_for_status(response, "registration")
        self.registered = True
        log.info("pod %s: registered with controller %s as %s", self.settings.name, self.base_url, self.settings.url)


async def _post(client: httpx.AsyncClient, path: str, body: dict[str, Any]) -> httpx.Response:
    """POST ``body`` as JSON; the answer read whole under :data:`_MAX_ANSWER_BYTES`, within 10 s."""
    async with asyncio.timeout(10.0):
        return await send_capped(client, client.build_request("POST", path, json=body), _MAX_ANSWER_BYTES)


def _raise_for_status(response: httpx.Response, what: str) -> None:
    if response.status_code != 200:
        raise ControllerRefusedError(f"{what} answered {response.status_code}: {response.text[:200]}")
