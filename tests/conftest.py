"""Fixtures shared by the test modules; the helpers behind them live in ``support.service_procs``."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from pathlib import Path

import pytest
from support.service_procs import PodSpec, RunningPod, standalone_pods


@pytest.fixture
def refusing_port() -> Iterator[int]:
    """A loopback port that is bound but not listening: connections to it are refused."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    try:
        yield sock.getsockname()[1]
    finally:
        sock.close()


@pytest.fixture
def start_pods(tmp_path: Path) -> Iterator[Callable[[Sequence[PodSpec]], list[RunningPod]]]:
    """Starts standalone pods from specs and returns them once all are ready; every pod it
    started is stopped when the test ends."""
    with ExitStack() as stack:

        def start(specs: Sequence[PodSpec]) -> list[RunningPod]:
            return stack.enter_context(standalone_pods(specs, tmp_path / "pods"))

        yield start
