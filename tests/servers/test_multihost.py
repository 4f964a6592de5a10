"""Several hosts on one machine: the controller and each pod in a network namespace of its own.

The test builds a private /24: a "switch" namespace holding a bridge, one namespace per host
(controller .1, pods .10 and up) and one veth into the test's own namespace (.254), each wired
to the bridge. Every namespace, link and address is the test's and is deleted at the end.
Processes see only their own namespace's loopback, so the controller can reach a pod only
through the address the pod advertises.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import secrets
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from support.service_procs import ip, unused_subnet, wait_until

from service.runner import Backoff, ManagedProcess

PYTHON = sys.executable
CONTROLLER_PORT = 8000  # fixed ports are safe here: every host is a fresh namespace of its own
POD_PORT = 8100
JOB = {
    "job_id": "multihost",
    "tasks": ["gym/Pendulum-v1"],
    "group_size": 1,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
    "max_episode_steps": 20,
}


@dataclass
class Network:
    subnet: ipaddress.IPv4Network
    namespaces: dict[str, str]  # host -> namespace name
    addresses: dict[str, str]  # host -> IPv4 address

    def exec_argv(self, host: str, *argv: str) -> list[str]:
        return ["ip", "netns", "exec", self.namespaces[host], *argv]


@pytest.fixture(scope="module")
def network() -> Iterator[Network]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2's `ip` to make network namespaces")
    tag = secrets.token_hex(3)
    subnet = unused_subnet()
    hosts = {"controller": 1, "sim-0": 10, "sim-1": 11}
    addr = {h: str(subnet.network_address + n) for h, n in hosts.items()}
    switch = f"vs{tag}-sw"
    namespaces = {h: f"vs{tag}-{h}" for h in hosts}
    host_link = f"vs{tag}h"
    made: list[str] = []
    try:
        try:
            ip("netns", "add", switch)
        except subprocess.CalledProcessError as exc:
            pytest.skip(f"`ip netns add` is not permitted here: {exc.stderr.strip()}")
        made.append(switch)
        try:
            _wire(tag, switch, namespaces, addr, made, host_link, subnet)
        except subprocess.CalledProcessError as exc:
            pytest.skip(f"cannot build the test network ({' '.join(exc.cmd)}): {exc.stderr.strip()}")
        yield Network(subnet=subnet, namespaces=namespaces, addresses=addr)
    finally:
        # Links still in this namespace after a failed setup go too (each veth takes its peer).
        for link in [host_link, *(f"vs{tag}a{i}" for i in range(len(namespaces)))]:
            subprocess.run(["ip", "link", "del", link], capture_output=True)
        for ns in reversed(made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _wire(
    tag: str,
    switch: str,
    namespaces: dict[str, str],
    addr: dict[str, str],
    made: list[str],
    host_link: str,
    subnet: ipaddress.IPv4Network,
) -> None:
    """A bridge in ``switch``; each host namespace and the test's own joined to it by a veth."""
    ip("-n", switch, "link", "add", "br0", "type", "bridge")
    ip("-n", switch, "link", "set", "br0", "up")
    for i, (host, ns) in enumerate(namespaces.items()):
        ip("netns", "add", ns)
        made.append(ns)
        ip("-n", ns, "link", "set", "lo", "up")
        ip("link", "add", f"vs{tag}a{i}", "type", "veth", "peer", "name", f"vs{tag}b{i}")
        ip("link", "set", f"vs{tag}a{i}", "netns", ns)
        ip("link", "set", f"vs{tag}b{i}", "netns", switch)
        ip("-n", ns, "link", "set", f"vs{tag}a{i}", "name", "eth0")
        ip("-n", ns, "addr", "add", f"{addr[host]}/24", "dev", "eth0")
        ip("-n", ns, "link", "set", "eth0", "up")
        ip("-n", switch, "link", "set", f"vs{tag}b{i}", "master", "br0", "up")
    # The test's own way in: one address of the subnet in its namespace.
    ip("link", "add", host_link, "type", "veth", "peer", "name", f"vs{tag}bh")
    ip("link", "set", f"vs{tag}bh", "netns", switch)
    ip("-n", switch, "link", "set", f"vs{tag}bh", "master", "br0", "up")
    ip("addr", "add", f"{subnet.network_address + 254}/24", "dev", host_link)
    ip("link", "set", host_link, "up")


@pytest.fixture(scope="module")
def hosts(network: Network, tmp_path_factory) -> Iterator[dict[str, ManagedProcess]]:
    logs: Path = tmp_path_factory.mktemp("multihost")
    controller_url = f"http://{network.addresses['controller']}:{CONTROLLER_PORT}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    processes = {
        "controller": ManagedProcess(
            "controller",
            network.exec_argv(
                "controller",
                PYTHON,
                "-m",
                "service.cli",
                "controller",
                "--host",
                network.addresses["controller"],
                "--port",
                str(CONTROLLER_PORT),
                "--heartbeat-interval",
                "0.5",
                "--heartbeat-ttl",
                "5",
                "--reconcile-interval",
                "0.2",
            ),
            env=env,
            log_path=logs / "controller.log",
            backoff=Backoff(initial_s=0.5),
            grace_s=5,
        )
    }
    for name in ("sim-0", "sim-1"):
        pod_ip = network.addresses[name]
        processes[name] = ManagedProcess(
            name,
            network.exec_argv(name, PYTHON, "-m", "service.cli", "pod"),
            env={
                **env,
                "POD_NAME": name,
                "POD_NAMESPACE": "multihost",
                "POD_IP": pod_ip,
                "VECSIM_PORT": str(POD_PORT),
                "VECSIM_ADVERTISE_URL": f"http://{pod_ip}:{POD_PORT}",
                "CONTROLLER_URL": controller_url,
                "VECSIM_HEARTBEAT_INTERVAL_S": "0.5",
                "VECSIM_MAX_ENVS": "4",
            },
            log_path=logs / f"{name}.log",
            backoff=Backoff(initial_s=0.5),
            grace_s=5,
        )
    try:
        for process in processes.values():
            process.start()
        yield processes
    finally:
        for process in processes.values():
            process.request_stop()
        deadline = time.monotonic() + 5
        for process in processes.values():
            process.finish_stop(deadline)


def until_ready(url: str, processes: dict[str, ManagedProcess], timeout: float) -> dict:
    detail = ["no answer"]

    def routing() -> dict | None:
        for name, process in processes.items():
            if process.restarts > 2:
                pytest.fail(f"{name} keeps exiting ({process.last_exit}):\n{process.log_tail()}")
        try:
            response = httpx.get(f"{url}/readyz", timeout=2)
            if response.status_code == 200:
                return httpx.get(f"{url}/v1/routing", timeout=2).json()
            detail[0] = response.text
        except httpx.HTTPError as exc:
            detail[0] = str(exc)
        return None

    try:
        return wait_until(routing, "the job to be ready", timeout_s=timeout, every=0.3)
    except AssertionError as e:
        pytest.fail(f"{e}: {detail[0]}")


@pytest.fixture(scope="module")
def table(network: Network, hosts: dict[str, ManagedProcess]) -> dict:
    controller_url = f"http://{network.addresses['controller']}:{CONTROLLER_PORT}"

    def put_job() -> httpx.Response | None:
        with contextlib.suppress(httpx.HTTPError):
            return httpx.put(f"{controller_url}/v1/job", json=JOB, timeout=5)
        return None

    response = wait_until(put_job, "the controller to answer in its namespace", timeout_s=60, every=0.3)
    assert response.status_code == 200, response.text
    return until_ready(controller_url, hosts, timeout=180)


@pytest.mark.slow
def test_pods_in_other_namespaces_register_under_their_advertised_addresses(network, table):
    controller_url = f"http://{network.addresses['controller']}:{CONTROLLER_PORT}"
    pods = httpx.get(f"{controller_url}/v1/pods", timeout=5).json()
    assert [(p["pod"], p["url"], p["ready"]) for p in pods] == [
        ("sim-0", f"http://{network.addresses['sim-0']}:{POD_PORT}", True),
        ("sim-1", f"http://{network.addresses['sim-1']}:{POD_PORT}", True),
    ]
    assert [[p["url"] for p in s["pods"]] for s in table["stages"]] == [[pods[0]["url"]], [pods[1]["url"]]]


@pytest.mark.slow
def test_a_pod_serves_the_data_plane_at_its_advertised_address(table):
    pod = table["stages"][1]["pods"][0]
    body = {"generation": table["generation"], "env_indices": [0], "state_ids": [3]}
    response = httpx.post(f"{pod['url']}/v1/reset", json=body, headers={"Accept": "application/json"}, timeout=30)
    assert response.status_code == 200, response.text
    assert response.json()["info"]["task_id"] == ["gym/Pendulum-v1"]


@pytest.mark.slow
def test_a_pod_is_not_on_the_controllers_loopback(network, table):
    probe = (
        "import httpx, sys\n"
        "try:\n"
        f"    httpx.get('http://127.0.0.1:{POD_PORT}/healthz', timeout=2)\n"
        "except httpx.ConnectError:\n"
        "    sys.exit(0)\n"
        "sys.exit(1)\n"
    )
    result = subprocess.run(network.exec_argv("controller", PYTHON, "-c", probe), capture_output=True, timeout=60)
    assert result.returncode == 0, result.stderr
