"""Talking to a running pod the way the tests check it by hand: a wire request answered 200 and
decoded (:func:`wire_answer`, over :func:`support.service_procs.post_wire`), and one figure of a
server's ``/metrics`` (:func:`metric`)."""

from __future__ import annotations

import re
from typing import Any

import httpx
from support.service_procs import post_wire

from vecsim import wire


def wire_answer(
    url: str, op: str, body: dict[str, Any], token: str | None = None, timeout: float = 60
) -> dict[str, Any]:
    """``POST url/v1/<op>`` with ``body`` as wire; assert it was answered 200 and return the decoded answer."""
    response = post_wire(url, op, body, token, timeout=timeout)
    assert response.status_code == 200, response.text
    return wire.decode(response.content)


def metric(url: str, name: str) -> float:
    """The value of the unlabelled metric ``name`` (a counter's ``_total`` sample too) on ``url/metrics``."""
    text = httpx.get(f"{url}/metrics", timeout=10).text
    match = re.search(rf"^{name}(?:_total)? (\S+)$", text, re.MULTILINE)
    assert match, f"no metric {name} on {url}/metrics"
    return float(match.group(1))
