"""The shared token that guards every request that changes state.

One secret per job (``VECSIM_TOKEN`` locally, the Kubernetes Secret ``vecsim-token`` in a
cluster) is sent as ``Authorization: Bearer <token>``. The pod and the controller require it on
every request whose method is not ``GET``/``HEAD``/``OPTIONS`` (assigning, resetting, stepping,
registering, heartbeating, setting the job); reading (health, readiness, metrics, info, routing)
stays open. With no token configured, checking is off (local development): the servers log a
warning at start-up.

Here: reading the token from the environment, the header a caller sends and the constant-time
check, shared by the client and both servers. The servers' ASGI middleware that applies it, and
the OpenAPI description of it, are in ``service.http``. Nothing here ever puts the token in a
message or a log line.
"""

from __future__ import annotations

import hmac
import os
import re
from collections.abc import Mapping

__all__ = [
    "OPEN_METHODS",
    "TOKEN_ENV",
    "authorization_problem",
    "bearer_headers",
    "check_token",
    "token_from_env",
    "tokens_match",
]

TOKEN_ENV = "VECSIM_TOKEN"
# Methods that only read: open to anyone who can reach the server.
OPEN_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
# What an HTTP header value may carry without quoting: visible ASCII, no spaces.
_TOKEN_CHARS = re.compile(r"^[\x21-\x7e]+$")


def check_token(token: str | None, source: str = TOKEN_ENV) -> str | None:
    """Check that ``token`` can travel in an ``Authorization`` header.

    Returns:
        ``token``, or None when it is None or empty (checking off).

    Raises:
        ValueError: the token holds spaces, control or non-ASCII characters (``source`` named,
            the token not shown).
    """
    if not token:
        return None
    # fullmatch: match's "$" also matches before a final newline, which a Secret made from a
    # file often ends in.
    if not _TOKEN_CHARS.fullmatch(token):
        raise ValueError(f"{source}: the token must be visible ASCII characters without spaces")
    return token


def token_from_env(environ: Mapping[str, str] | None = None) -> str | None:
    """Return the token in ``VECSIM_TOKEN`` (``environ`` defaults to ``os.environ``).

    Returns:
        The token, or None when the variable is unset or empty.

    Raises:
        ValueError: as :func:`check_token`.
    """
    environ = os.environ if environ is None else environ
    return check_token(environ.get(TOKEN_ENV))


def bearer_headers(token: str | None) -> dict[str, str]:
    """Return the headers that carry ``token`` (``{}`` when there is none)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


def tokens_match(given: str, expected: str) -> bool:
    """Compare two tokens in time that does not depend on where they differ."""
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), expected.encode("utf-8", "surrogateescape"))


def authorization_problem(header: str | None, token: str | None, server: str) -> str | None:
    """Say why a request with ``Authorization`` header ``header`` may not change ``server``.

    Returns:
        None when the request may go on (the token matches, or ``token`` is None: checking off);
        else a message naming what is missing or wrong, never the token.
    """
    if token is None:
        return None
    if header is None or not header.strip():
        return f"{server} needs an 'Authorization: Bearer <token>' header (the job's {TOKEN_ENV}); none was sent"
    scheme, _, given = header.strip().partition(" ")
    if scheme.lower() != "bearer" or not given.strip():
        return f"{server} needs the Authorization header in the form 'Bearer <token>'"
    if not tokens_match(given.strip(), token):
        return f"{server} refused the bearer token: it is not the job's {TOKEN_ENV}"
    return None
