"""Free TCP ports for a job on one machine: the one place the runner, the demo, the tests and the
benchmarks find them.

:func:`port_free` asks whether a port given in a config can be bound now the way uvicorn binds
it (``SO_REUSEADDR``), so the TIME_WAIT connections of a job that just stopped do not make it look
taken; a listener does. :func:`free_port` and :func:`free_port_block` hand out new ports and are
warier: a port with a connection still in TIME_WAIT is not handed out, since the process that
just left it may be a pod its runner is about to restart there.

They pick at random below the kernel's ephemeral range, not by binding port 0. The kernel hands
its ephemeral ports to every outgoing connection on the machine (a pod's heartbeat, a client's
request): a port it picked was free only when asked, and on a busy machine a connection could
take it before the pod that was given it binds it. Below that range only another such pick can
collide, and at random among thousands of ports it hardly does. Nothing is held: another process
may still take a port between this answer and its use.
"""

from __future__ import annotations

import random
import socket
from collections.abc import Container
from pathlib import Path

# New ports are picked from here up to the kernel's ephemeral range.
PICK_FROM = 10000
# Where the ephemeral range cannot be read (not Linux): its start on Linux by default.
_EPHEMERAL_DEFAULT = 32768
# The kernel's pick, where the range below the ephemeral one is too small: blocks end below this.
_PORT_CEILING = 65000
_RANDOM = random.SystemRandom()


def port_free(host: str, port: int) -> bool:
    """Return whether ``port`` on ``host`` can be bound now, as uvicorn binds it."""
    return _bindable(host, port, reuse_addr=True)


def _bindable(host: str, port: int, *, reuse_addr: bool) -> bool:
    """Whether ``port`` on ``host`` can be bound now; without ``reuse_addr`` a connection still in
    TIME_WAIT there makes it not."""
    with _socket_for(host) as sock:
        if reuse_addr:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def ephemeral_ports_from(path: str | Path = "/proc/sys/net/ipv4/ip_local_port_range") -> int:
    """The first port of the kernel's ephemeral range (32768 where ``path`` cannot be read)."""
    try:
        first = int(Path(path).read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return _EPHEMERAL_DEFAULT
    return first if 1024 < first <= 65535 else _EPHEMERAL_DEFAULT


def free_port(host: str = "127.0.0.1") -> int:
    """Return a TCP port on ``host`` that nothing listens on and no connection holds right now.

    Raises:
        RuntimeError: none was found (see :func:`free_port_block`).
    """
    return free_port_block(1, host)


def free_port_block(n: int, host: str = "127.0.0.1", *, avoid: Container[int] = (), attempts: int = 100) -> int:
    """Return the first of ``n`` consecutive free ports on ``host``, none of them in ``avoid``
    (a job's pods listen on ``base_port + ordinal``), picked at random below the kernel's
    ephemeral range; where that leaves fewer than 1,000 blocks, from the kernel's own picks.

    Raises:
        ValueError: ``n`` is not positive.
        RuntimeError: no such block was found in ``attempts`` tries.
    """
    if n < 1:
        raise ValueError(f"a block of ports needs n >= 1, got {n}")
    low, high = PICK_FROM, ephemeral_ports_from() - n
    for _ in range(attempts):
        base = _RANDOM.randrange(low, high + 1) if high - low >= 1000 else _kernels_pick(host)
        block = range(base, base + n)
        if base + n > _PORT_CEILING or any(port in avoid for port in block):
            continue
        if all(_bindable(host, port, reuse_addr=False) for port in block):
            return base
    raise RuntimeError(f"found no {n} consecutive free ports on {host}; free some ports and retry")


def _kernels_pick(host: str) -> int:
    with _socket_for(host) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _socket_for(host: str) -> socket.socket:
    """A TCP socket of ``host``'s address family (an IPv6 address has colons)."""
    return socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
