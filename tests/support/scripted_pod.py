"""In-process scripted pods: the client's data plane with answers held until the test lets them go.

A :class:`ScriptedPod` is an ASGI app speaking the pod protocol as the client uses it:
``GET /v1/info`` (JSON), ``POST /v1/reset`` and ``POST /v1/step`` (with or without resets of
other envs in it; vecsim's wire both ways, the
job's bearer token, the routing generation, 409/422 refusals in the pod's ``{"detail": ...}``
form). Its envs are counters, so every answer is known in advance:

- env ``e`` of a pod of stage ``s``, reset to state id ``k``, observes ``state = [s, e, k, t]``
  (float32), ``t`` being the actions it has applied since the reset;
- an action ``a`` (``[2]``) earns reward ``a[0]``;
- an env reset to ``k > 0`` terminates, with success, at its ``k``-th action; ``k = 0`` never ends
  on its own. Stepping an env that has terminated is refused (422), as stepping a finished
  trajectory is a bug of the caller's.

Every reset or step is held at the pod, once it has arrived, until the test calls
:meth:`ScriptedPod.release` (or :meth:`ScriptedPod.open`, which stops holding): the test, not the
clock, decides when and in which order answers land. :class:`PodRouter` is one httpx transport
reaching several such apps by host name (``http://<pod name>/...``); no sockets are opened.

:class:`Timeline` is the shared record of what happened, from any thread, with a bounded wait for
a condition on it: tests synchronise on what the record shows, never on sleeps.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
from gymnasium import spaces
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from vecsim import wire
from vecsim.client.routing import routing_from_pod_infos
from vecsim.config import RoutingTable
from vecsim.spaces import space_to_json

TASK = "scripted/count"
TOKEN = "scripted-token"
# The longest any wait on a condition may take before the test fails naming the condition: far
# above what each condition needs, so only a broken schedule reaches it.
WAIT_S = 60.0

OBSERVATION_SPACE = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (4,), np.float32)})
ACTION_SPACE = spaces.Box(-1000.0, 1000.0, (2,), np.float32)


class Timeline:
    """Events in the order they happened (tuples, appended from any thread), and waits on them."""

    def __init__(self) -> None:
        self.lock = threading.Condition()
        self.events: list[tuple[Any, ...]] = []

    def add(self, *event: Any) -> None:
        with self.lock:
            self.events.append(event)
            self.lock.notify_all()

    def count(self, *event: Any) -> int:
        """How many recorded events equal ``event``."""
        with self.lock:
            return sum(1 for seen in self.events if seen == event)

    def of(self, *kinds: str) -> list[tuple[Any, ...]]:
        """The events whose first item is one of ``kinds``, in order."""
        with self.lock:
            return [event for event in self.events if event[0] in kinds]

    def wait_for(self, condition: Callable[[], bool], what: str, timeout: float = WAIT_S) -> None:
        """Return once ``condition()`` holds (checked whenever an event is added).

        Raises:
            AssertionError: it did not hold within ``timeout`` seconds; names ``what`` and lists
                the events so far.
        """
        with self.lock:
            if not self.lock.wait_for(condition, timeout):
                raise AssertionError(f"not seen within {timeout} s: {what}; events so far: {self.events}")

    def changed(self) -> None:
        """Wake the waiters: something a condition reads (not an event) has changed."""
        with self.lock:
            self.lock.notify_all()


@dataclass
class _HeldCall:
    op: str
    env_indices: tuple[int, ...]
    loop: asyncio.AbstractEventLoop
    gate: asyncio.Future[None]


def _open_gate(gate: asyncio.Future[None]) -> None:
    if not gate.done():  # a call the client gave up on (timeout, close) is cancelled already
        gate.set_result(None)


class ScriptedPod:
    """One pod of counter envs (see the module docstring), an ASGI app at ``self.app``.

    ``calls`` lists every reset and step that arrived, in order, as ``(op, env_indices)``, a step
    that also resets envs (a refill) as ``("reset+step", (reset env ids, stepped env ids))``;
    ``actions`` the actions array of every step, in order.
    """

    def __init__(self, name: str, stage_id: int, num_envs: int, timeline: Timeline, generation: int = 0) -> None:
        self.name, self.stage_id, self.num_envs, self.generation = name, stage_id, num_envs, generation
        self.url = f"http://{name}"
        self.timeline = timeline
        self.calls: list[tuple[str, tuple[int, ...]]] = []
        self.actions: list[np.ndarray] = []
        self.holding = True
        self._held: list[_HeldCall] = []
        self._state_ids = np.zeros(num_envs, np.int64)
        self._steps = np.zeros(num_envs, np.int64)
        self._ended = np.zeros(num_envs, bool)
        self.app = Starlette(
            routes=[
                Route("/v1/info", self._info, methods=["GET"]),
                Route("/v1/reset", self._reset, methods=["POST"]),
                Route("/v1/step", self._step, methods=["POST"]),
            ]
        )

    # -- what the test does ---------------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """The pod's ``GET /v1/info`` answer."""
        return {
            "pod": self.name,
            "stage_id": self.stage_id,
            "generation": self.generation,
            "ready": True,
            "num_envs": self.num_envs,
            "tasks": [{"task_id": TASK, "instruction": "count", "env_start": 0, "num_envs": self.num_envs}],
            "observation_space": space_to_json(OBSERVATION_SPACE),
            "action_space": space_to_json(ACTION_SPACE),
            "max_chunk": 16,
            "instance": f"{self.name}-build-1",
        }

    def held(self) -> list[tuple[str, tuple[int, ...]]]:
        """The calls that arrived and are held, oldest first, as ``(op, env_indices)``."""
        with self.timeline.lock:
            return [(call.op, call.env_indices) for call in self._held]

    def release(self) -> tuple[str, tuple[int, ...]]:
        """Let the oldest held call answer; return it as ``(op, env_indices)``.

        Raises:
            AssertionError: no call is held.
        """
        with self.timeline.lock:
            if not self._held:
                raise AssertionError(f"pod {self.name} holds no call to release")
            call = self._held.pop(0)
            self.timeline.lock.notify_all()
        call.loop.call_soon_threadsafe(_open_gate, call.gate)
        return call.op, call.env_indices

    def open(self) -> None:
        """Stop holding: every held call answers now, and later calls answer as they arrive."""
        with self.timeline.lock:
            self.holding = False
            held, self._held = self._held, []
            self.timeline.lock.notify_all()
        for call in held:
            call.loop.call_soon_threadsafe(_open_gate, call.gate)

    # -- the data plane -------------------------------------------------------------------------

    async def _hold(self, op: str, env_indices: np.ndarray | tuple[Any, ...]) -> None:
        """Note the call's arrival; wait until the test lets it answer."""
        ids = env_indices if isinstance(env_indices, tuple) else tuple(int(e) for e in env_indices)
        gate: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        with self.timeline.lock:
            self.calls.append((op, ids))
            if self.holding:
                self._held.append(_HeldCall(op, ids, asyncio.get_running_loop(), gate))
            else:
                gate.set_result(None)
            self.timeline.add("arrived", self.name, op)
        await gate

    async def _read(self, request: Request, fields: set[str]) -> dict[str, Any] | Response:
        """The request's wire body, or the pod's refusal of it."""
        if request.headers.get("authorization") != f"Bearer {TOKEN}":
            return _refuse(401, "missing or wrong bearer token")
        if request.headers.get("content-type", "").split(";")[0].strip() != wire.CONTENT_TYPE:
            return _refuse(415, f"send {wire.CONTENT_TYPE}")
        try:
            body = wire.decode(await request.body())
        except wire.WireError as exc:
            return _refuse(400, f"body is not valid wire: {exc}")
        optional = {"record_env_indices", "reset_env_indices", "reset_state_ids"} if "actions" in fields else set()
        if not fields <= set(body) or not set(body) <= fields | optional:
            return _refuse(422, f"body has fields {sorted(body)}, expected {sorted(fields)}")
        if int(body["generation"]) != self.generation:
            return _refuse(409, f"pod {self.name} holds generation {self.generation}, not {int(body['generation'])}")
        env_indices = np.asarray(body["env_indices"])
        if (
            env_indices.ndim != 1
            or len(set(env_indices.tolist())) != len(env_indices)
            or not all(0 <= e < self.num_envs for e in env_indices.tolist())
        ):
            return _refuse(
                422, f"env_indices {env_indices.tolist()}: not distinct env indices of 0..{self.num_envs - 1}"
            )
        return body

    async def _info(self, request: Request) -> Response:
        return JSONResponse(self.info())

    async def _reset(self, request: Request) -> Response:
        body = await self._read(request, {"generation", "env_indices", "state_ids"})
        if isinstance(body, Response):
            return body
        env_indices, state_ids = np.asarray(body["env_indices"]), np.asarray(body["state_ids"])
        if state_ids.shape != env_indices.shape:
            return _refuse(422, f"state_ids has shape {list(state_ids.shape)}, env_indices {list(env_indices.shape)}")
        await self._hold("reset", env_indices)
        return _answer(self._reset_envs(env_indices, state_ids))

    def _reset_envs(self, env_indices: np.ndarray, state_ids: np.ndarray) -> dict[str, Any]:
        """Reset the envs; return the reset answer."""
        self._state_ids[env_indices], self._steps[env_indices], self._ended[env_indices] = state_ids, 0, False
        n = len(env_indices)
        info = {"success": np.zeros(n, bool), "task_id": [TASK] * n}
        return {"env_indices": env_indices.astype(np.int32), "obs": self._obs(env_indices), "info": info}

    async def _step(self, request: Request) -> Response:
        body = await self._read(request, {"generation", "env_indices", "actions"})
        if isinstance(body, Response):
            return body
        env_indices, actions = np.asarray(body["env_indices"]), np.asarray(body["actions"])
        chunked = actions.ndim == 3
        if actions.dtype != np.float32 or actions.shape[:1] != env_indices.shape or actions.shape[-1:] != (2,):
            return _refuse(422, f"actions {actions.dtype} {list(actions.shape)}: expected float32 [n, (K,) 2]")
        if np.asarray(body.get("record_env_indices", ())).size:
            return _refuse(422, f"pod {self.name} renders no cameras; record_env_indices must be empty")
        ended = [int(e) for e in env_indices if self._ended[e]]
        if ended:
            return _refuse(422, f"env(s) {ended} of pod {self.name} terminated; reset before stepping them")
        resets = np.asarray(body.get("reset_env_indices", np.zeros(0, np.int64)))
        reset_states = np.asarray(body.get("reset_state_ids", np.zeros(0, np.int64)))
        if reset_states.shape != resets.shape or set(resets.tolist()) & set(env_indices.tolist()):
            return _refuse(422, f"reset_env_indices {resets.tolist()}: one state id each, none of env_indices")
        if resets.size:
            await self._hold("reset+step", (tuple(resets.tolist()), tuple(env_indices.tolist())))
            reset_answer = self._reset_envs(resets, reset_states)
        else:
            await self._hold("step", env_indices)
        self.actions.append(np.array(actions))
        chunks = actions if chunked else actions[:, None, :]
        n, k = chunks.shape[:2]
        reward, terminated = np.zeros((n, k), np.float32), np.zeros((n, k), bool)
        num_steps = np.zeros(n, np.int32)
        for row, env in enumerate(env_indices):
            for j in range(k):
                self._steps[env] += 1
                reward[row, j] = chunks[row, j, 0]
                num_steps[row] += 1
                if self._steps[env] == self._state_ids[env]:
                    terminated[row, j] = self._ended[env] = True
                    break
        answer: dict[str, Any] = {
            "env_indices": env_indices.astype(np.int32),
            "obs": self._obs(env_indices),
            "reward": reward if chunked else reward[:, 0],
            "terminated": terminated if chunked else terminated[:, 0],
            "truncated": np.zeros_like(terminated) if chunked else np.zeros(n, bool),
            "info": {"success": terminated.copy() if chunked else terminated[:, 0].copy()},
        }
        if chunked:
            answer["num_steps"] = num_steps
        if resets.size:
            answer["reset"] = reset_answer
        return _answer(answer)

    def _obs(self, env_indices: np.ndarray) -> dict[str, np.ndarray]:
        state = np.stack(
            [
                np.full(len(env_indices), self.stage_id),
                env_indices,
                self._state_ids[env_indices],
                self._steps[env_indices],
            ],
            axis=1,
        )
        return {"state": state.astype(np.float32)}


def _answer(body: dict[str, Any]) -> Response:
    return Response(wire.encode(body), media_type=wire.CONTENT_TYPE)


def _refuse(status: int, detail: str) -> Response:
    return JSONResponse({"detail": detail}, status_code=status)


class PodRouter(httpx.AsyncBaseTransport):
    """One transport to several in-process pods, chosen by the request's host (the pod's name)."""

    def __init__(self, pods: Sequence[ScriptedPod]) -> None:
        self._apps = {pod.name: httpx.ASGITransport(app=pod.app) for pod in pods}

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        app = self._apps.get(request.url.host)
        if app is None:
            raise httpx.ConnectError(f"no pod answers at {request.url.host}", request=request)
        return await app.handle_async_request(request)

    async def aclose(self) -> None:
        for app in self._apps.values():
            await app.aclose()


def scripted_job(num_stages: int, envs_per_pod: int, timeline: Timeline) -> tuple[list[ScriptedPod], RoutingTable]:
    """One pod per stage (``pod-<stage>``, ``envs_per_pod`` envs of :data:`TASK`) and their
    routing table, built from their ``/v1/info`` as for standalone pods."""
    pods = [ScriptedPod(f"pod-{stage}", stage, envs_per_pod, timeline) for stage in range(num_stages)]
    return pods, routing_from_pod_infos([(pod.url, pod.info()) for pod in pods], job_id="scripted")
