"""Free TCP ports for a job on one machine: the one place the runner, the demo, the tests and the
benchmarks find them.

:func:`port_free` asks whether a port given in a config can be bound now the way uvicorn binds
it (``SO_REUSEADDR``), so the TIME_WAIT connections of a job that just stopped do not make it look
taken; a listener does. :func:`free_port` and :func:`free_port_block` hand out new ports and are
warier: a port with a connection still in TIME_WAIT is not handed out, since the process that
just left it may be a pod its runner is about to restart there. Nothing is held: another process
may take a port between this answer and its use.
"""

from __future__ import annotations

import socket
from collections.abc import Container

# Blocks end below this port: the kernel's ephemeral range often reaches past 65000.
_PORT_CEILING = 65000


def port_free(host: str, port: int) -> bool:
    """Return whether ``port`` on ``host`` can be bound now, as uvicorn binds it."""
    return _bindable(host, port, reuse_addr=True)


def _bindable(host: str, port: int, *, reuse_addr: bool) -> bool:
    """Whether ``port`` on ``host`` can be bound now; without ``reuse_addr`` a connection still in
    TIME_WAIT there makes it not."""
    with socket.socket() as sock:
        if reuse_addr:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = "127.0.0.1") -> int:
    """Return a TCP port on ``host`` that nothing listens on right now (the kernel's pick)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def free_port_block(n: int, host: str = "127.0.0.1", *, avoid: Container[int] = (), attempts: int = 50) -> int:
    """Return the first of ``n`` consecutive free ports on ``host``, none of them in ``avoid``
    (a job's pods listen on ``base_port + ordinal``).

    Raises:
        RuntimeError: no such block was found in ``attempts`` tries.
    """
    for _ in range(attempts):
        base = free_port(host)
        block = range(base, base + n)
        if base + n > _PORT_CEILING or any(port in avoid for port in block):
            continue
        if all(_bindable(host, port, reuse_addr=False) for port in block):
            return base
    raise RuntimeError(f"found no {n} consecutive free ports on {host}; free some ports and retry")
