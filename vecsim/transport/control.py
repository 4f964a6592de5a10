"""The control plane's blocking GET through the transport: the controller's routing table and a
pod's ``/v1/info``, read before a client's event loop runs (``fetch_routing``,
``StageClient.from_pods``). The request takes the path of every call to a pod,
:meth:`Transport.fetch` on the default transport, with its caps, on an event loop of its own.

    response = get_answer("http://127.0.0.1:8000/v1/routing", timeout_s=10)
"""

from __future__ import annotations

import asyncio
import concurrent.futures

import httpx

from .answers import MAX_CONTROL_ANSWER_BYTES
from .auto import make_transport
from .errors import ReadTimedOut, mapped

__all__ = ["get_answer"]


async def _get(url: str, timeout_s: float, max_bytes: int, headers: tuple[tuple[str, str], ...]) -> tuple[int, bytes]:
    transport = make_transport()
    try:
        async with asyncio.timeout(timeout_s):
            return await transport.fetch("GET", url, headers, b"", max_bytes)
    except TimeoutError:
        raise ReadTimedOut(f"no whole answer within {timeout_s} s") from None
    finally:
        await transport.aclose()


def get_answer(
    url: str, *, timeout_s: float, max_bytes: int = MAX_CONTROL_ANSWER_BYTES, headers: dict[str, str] | None = None
) -> httpx.Response:
    """``GET url`` from a blocking caller, through the default transport, read whole under the cap
    ``max_bytes`` within ``timeout_s`` in all. From inside a running event loop it runs on a
    thread of its own, so a notebook's loop can call it too.

    Returns:
        the response: its status and decoded body (no headers: the control plane reads none).

    Raises:
        httpx.ReadTimeout: no whole answer within ``timeout_s``.
        httpx.HTTPError: what the transport met (mapped by ``vecsim.transport.errors``), the URL named.
    """
    request = httpx.Request("GET", url)
    fetch = _get(url, timeout_s, max_bytes, tuple((headers or {}).items()))
    with mapped(f"GET {url}", request):
        try:
            asyncio.get_running_loop()
        except RuntimeError:
            status, body = asyncio.run(fetch)
        else:
            with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="vecsim-get") as pool:
                status, body = pool.submit(asyncio.run, fetch).result()
    return httpx.Response(status, content=body, request=request)
