"""Exactly-once resets and steps: the answers a pod remembers by the request's ``Idempotency-Key``.

A state-changing request (``POST /v1/reset``, ``POST /v1/step``) may carry the header
``Idempotency-Key`` (the IETF httpapi draft's name): one id per logical call, the same on every
re-send of it. The pod answers a repeated key with the answer it gave, changing nothing; a
repeat while the first is still being applied waits for it; a repeat with another body (its
generation aside) is refused (422 naming the header). Only applied calls (200) are remembered:
a refusal changed nothing, so its repeat is judged again.

The memory is bounded per env: each env holds the answer of its last keyed call, so a pod keeps
at most one answer per env. A client sends an env's next call only after the last one answered,
so a re-send always finds its answer. Keys whose answers were superseded are kept (a bounded
number per env) so that a late repeat is refused, never applied again. A rebuild of the envs
starts an empty memory: their state is gone, and so are the answers about it.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections import Counter, OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np
from fastapi import Request
from pydantic import BaseModel

from vecsim.engine import InvalidRequestError
from vecsim.transport.httptools_impl import IDEMPOTENCY_KEY

from .bodies import Answer

__all__ = ["IDEMPOTENCY_KEY_PARAMETER", "AnswerMemory"]

# A key is an opaque token the client makes (vecsim's: 32 hex digits); bounded, printable ASCII.
_MAX_KEY_CHARS = 255
# Superseded keys remembered per env, so that a repeat arriving this late is still refused.
_SUPERSEDED_PER_ENV = 8
_MIN_SUPERSEDED = 256
_KEY_TEXT = (
    "one id per logical call, the same on every re-send: a repeat is answered what the first "
    "was answered, and changes nothing (another body under the same key: 422)"
)
# The header in a route's OpenAPI operation (``openapi_extra``). Not a FastAPI ``Header``
# parameter: :meth:`AnswerMemory.once` reads and checks it itself, and a declared parameter costs
# every step FastAPI's own extraction and validation (~20 us, a cheap scene's step ~1.5 ms).
IDEMPOTENCY_KEY_PARAMETER = {
    "name": IDEMPOTENCY_KEY,
    "in": "header",
    "required": False,
    "schema": {"type": "string", "title": IDEMPOTENCY_KEY, "description": _KEY_TEXT},
    "description": _KEY_TEXT,
}


@dataclass
class _Held:
    digest: bytes
    answer: Answer  # its parts are never written again: it is sent again as it was
    envs: int  # envs whose last keyed call this is; the answer is dropped at 0


class AnswerMemory:
    """The answers of one build of a pod's envs, by ``Idempotency-Key``; see the module's text."""

    def __init__(self, num_envs: int) -> None:
        self._answers: dict[str, _Held] = {}
        self._last_key: dict[int, str] = {}  # env index -> the key of its last keyed call
        self._superseded: OrderedDict[str, bytes] = OrderedDict()
        self._max_superseded = max(_MIN_SUPERSEDED, _SUPERSEDED_PER_ENV * num_envs)
        self._in_flight: dict[str, tuple[bytes, asyncio.Future[Answer]]] = {}

    def __len__(self) -> int:
        """The answers held now (at most one per env)."""
        return len(self._answers)

    async def once(
        self, request: Request, req: BaseModel, apply: Callable[[], Awaitable[tuple[Answer, np.ndarray]]]
    ) -> tuple[Answer, bool]:
        """Answer ``request`` (its body parsed: ``req``) exactly once per key: run ``apply`` (which
        returns the answer and the env ids it changed) the first time, the remembered answer after.

        A repeat is the same request but for its ``generation``: after a 409 the client sends the
        call again at the new generation, and when only the generation moved on (same envs), the
        answer of the first still stands.

        Returns:
            the answer, and whether it is a repeat's (nothing applied).

        Raises:
            InvalidRequestError: the key is malformed, or was used with another body, or its
                answer is no longer held (422, naming the header).
            Whatever ``apply`` raises (a repeat waiting on it raises the same).
        """
        key = request.headers.get(IDEMPOTENCY_KEY)
        if key is None:
            response, _ = await apply()
            return response, False
        if not 0 < len(key) <= _MAX_KEY_CHARS or not key.isascii() or not key.isprintable():
            raise InvalidRequestError(f"{IDEMPOTENCY_KEY}: must be 1 to {_MAX_KEY_CHARS} printable ASCII characters")
        digest = _digest(request, req)
        held = self._answers.get(key)
        if held is not None:
            self._check_same(key, held.digest, digest)
            return held.answer.again(), True
        if key in self._superseded:
            self._check_same(key, self._superseded[key], digest)
            raise InvalidRequestError(
                f"{IDEMPOTENCY_KEY}: {key!r} was applied, and its envs have had later calls since; its answer is no longer held"
            )
        running = self._in_flight.get(key)
        if running is not None:
            self._check_same(key, running[0], digest)
            response = await asyncio.shield(running[1])
            return response.again(), True
        future: asyncio.Future[Answer] = asyncio.get_running_loop().create_future()
        self._in_flight[key] = (digest, future)
        try:
            response, env_ids = await apply()
        except BaseException as exc:
            future.set_exception(exc)
            future.exception()  # retrieved: no "never retrieved" warning when no repeat waits
            raise
        finally:
            del self._in_flight[key]
        self._remember(key, digest, response, env_ids)
        future.set_result(response)
        return response, False

    @staticmethod
    def _check_same(key: str, held: bytes, digest: bytes) -> None:
        if held != digest:
            raise InvalidRequestError(
                f"{IDEMPOTENCY_KEY}: {key!r} was used for another request; a repeat must be the same request byte for byte"
            )

    def _remember(self, key: str, digest: bytes, response: Answer, env_ids: np.ndarray) -> None:
        envs = np.asarray(env_ids).ravel().tolist()
        if not envs:
            return  # a no-op changed nothing: its repeat may run again
        self._answers[key] = _Held(digest, response, len(envs))
        # The keys these envs had, counted, released once each (most often one: the envs' last call).
        left = Counter(map(self._last_key.get, envs))
        self._last_key.update(dict.fromkeys(envs, key))
        for before, count in left.items():
            if before is not None and before != key:
                self._release(before, count)

    def _release(self, key: str, envs: int) -> None:
        """``envs`` of the envs whose last keyed call was ``key`` had another since."""
        answer = self._answers[key]
        answer.envs -= envs
        if answer.envs:
            return
        del self._answers[key]
        self._superseded[key] = answer.digest
        while len(self._superseded) > self._max_superseded:
            self._superseded.popitem(last=False)


def _digest(request: Request, req: BaseModel) -> bytes:
    """What makes two requests the same: path, Accept (it picks the answer's encoding), and every
    field of the body but its generation."""
    # The scope's path, not request.url: building the URL costs more than the hash (every step).
    parts = [request.scope["path"].encode(), request.headers.get("accept", "").encode()]
    for name in type(req).model_fields:
        if name == "generation":
            continue
        value = getattr(req, name)
        if isinstance(value, np.ndarray):
            parts += [name.encode(), value.dtype.str.encode(), repr(value.shape).encode(), value.tobytes()]
        else:
            parts += [name.encode(), repr(value).encode()]
    # Each part behind its length, so that no two different lists of parts hash alike; one
    # update of the joined bytes (small: actions, ids) costs less than two per part.
    joined = b"".join(len(part).to_bytes(8, "little") + part for part in parts)
    return hashlib.blake2b(joined, digest_size=16).digest()
