"""A benchmark's own HTTP server in a child process, on a loopback port this process holds."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import psutil


@contextmanager
def server_process(script: str, method: str, probe_path: str, name: str) -> Iterator[tuple[str, psutil.Process]]:
    """Run ``script --serve-fd FD`` on a free loopback port; yield its URL and process once
    ``method probe_path`` answers 200 (within 30 s); stop it on exit."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    child = subprocess.Popen([sys.executable, script, "--serve-fd", str(sock.fileno())], pass_fds=[sock.fileno()])
    try:
        with httpx.Client(timeout=5) as probe:
            for _ in range(300):
                if child.poll() is not None:
                    raise SystemExit(f"{name} exited with {child.returncode}")
                try:
                    if probe.request(method, f"{url}{probe_path}").status_code == 200:
                        break
                except httpx.TransportError:
                    time.sleep(0.1)
            else:
                raise SystemExit(f"{name} did not answer within 30 s")
        yield url, psutil.Process(child.pid)
    finally:
        child.terminate()
        try:
            child.wait(10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        sock.close()
